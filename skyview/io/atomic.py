"""Writing files so that a user's data is never half-written or overwritten by accident."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from skyview.core.errors import BadInput


def write_atomic(items: list[tuple[Path, bytes]], force: bool) -> None:
    """Write all files or none: temp files in the target folders, then os.replace each one.

    Without force, nothing is written if any target exists (checked before writing), and each file
    is moved into place with a no-clobber link where the filesystem supports it.
    """
    if not force:
        for p, _ in items:
            if p.exists() or p.is_symlink():
                raise BadInput(f"{p} already exists (use force to overwrite)")
    temps: list[tuple[Path, Path]] = []
    done: list[Path] = []
    try:
        for p, data in items:
            fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
            temps.append((Path(tmp), p))
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.chmod(tmp, 0o644)
        for tmp, p in temps:
            if force:
                os.replace(tmp, p)
            else:
                try:
                    os.link(tmp, p)  # fails if p appeared meanwhile: never clobber
                    os.unlink(tmp)
                except FileExistsError:
                    raise BadInput(f"{p} already exists (use force to overwrite)") from None
                except OSError:
                    if p.exists():
                        raise BadInput(f"{p} already exists (use force to overwrite)") from None
                    os.replace(tmp, p)
            done.append(p)
    except OSError as exc:
        for p in done:
            _unlink_quiet(p)
        raise BadInput(f"could not write {exc.filename or items[0][0]}: {exc.strerror or exc}") from None
    except BaseException:
        for p in done:
            _unlink_quiet(p)
        raise
    finally:
        for tmp, _ in temps:
            _unlink_quiet(tmp)


def _unlink_quiet(p: Path) -> None:
    try:
        os.unlink(p)
    except OSError:
        pass
