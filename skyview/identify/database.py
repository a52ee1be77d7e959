"""On-disk cache for method databases.

A database depends on the method, its parameters, the catalog (its content fingerprint, epoch and
filters), the camera geometry and the file format. All of that goes into a key dict; its SHA-256
names the file `cache_dir()/databases/<method>-<hash16>.npz`. The file is a plain, uncompressed
`np.savez` (loads in milliseconds), written to a temporary file in the same folder and renamed into
place, so a reader never sees half a file. The key is stored inside the file as JSON and checked on
load: a file whose key differs (or that cannot be read) is rebuilt.
"""

from __future__ import annotations

import hashlib
import json
import mmap as mmap_module
import os
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, cache_dir
from skyview.core.errors import BadInput
from skyview.core.jsonable import plain

FORMAT_VERSION = 1
_KEY_FIELD = "__key__"
_NAMES_FIELD = "__names__"
DEFAULT_CACHE_MB = 4096  # SKYVIEW_CACHE_MB overrides; the least recently used databases go first

_UNWRITABLE: set[str] = set()  # cache folders this process could not write (said once each)


def make_key(method: str, params: dict, catalog: GuideCatalog, camera: Camera | None) -> dict:
    """Everything a database depends on, as a JSON-able dict."""
    key = {
        "method": str(method),
        "format": FORMAT_VERSION,
        "params": plain(params, other=str),
        "catalog": {"fingerprint": catalog.fingerprint, "stars": len(catalog), "epoch": float(catalog.epoch),
                    "filters": list(catalog.history)},
    }
    if camera is not None:
        key["camera"] = {k: (float(v) if isinstance(v, float) else int(v))
                         for k, v in (("width", camera.width), ("height", camera.height), ("fx", camera.fx),
                                      ("fy", camera.fy), ("cx", camera.cx), ("cy", camera.cy),
                                      ("k1", camera.k1), ("k2", camera.k2))}
    return key


RANGE_STEP = 1.05  # angular ranges of databases are rounded up to this geometric grid


def angular_range(rad: float) -> float:
    """An angular range rounded UP to the next step of a 5 % geometric grid (from 0.1 deg).

    A database that covers the rounded range serves every camera whose own range falls below it,
    so cameras that differ a little (a fitted FOV, another image size) share one database instead
    of building their own."""
    base = np.radians(0.1)
    k = max(0, int(np.ceil(np.log(max(rad, base) / base) / np.log(RANGE_STEP) - 1e-9)))
    return float(base * RANGE_STEP ** k)


DEFAULT_MEMORY_MB = 4096  # budget of one database build; SKYVIEW_MEMORY_MB overrides


def memory_budget_mb() -> float:
    env = os.environ.get("SKYVIEW_MEMORY_MB")
    try:
        return float(env) if env else float(DEFAULT_MEMORY_MB)
    except ValueError:
        raise BadInput(f"SKYVIEW_MEMORY_MB={env!r} is not a number") from None


def check_memory(estimated_bytes: float, what: str, budget_mb: float | None = None) -> None:
    """Refuse, before any work, a build whose estimated peak memory exceeds the budget."""
    budget = memory_budget_mb() if budget_mb is None else float(budget_mb)
    mb = estimated_bytes / 2 ** 20
    if mb > budget:
        raise BadInput(f"{what} would need about {mb:,.0f} MB of memory, over the budget of {budget:,.0f} MB: "
                       f"use a brighter --mag-limit or a narrower field, or raise SKYVIEW_MEMORY_MB")


def pairs_estimate(n_stars: int, max_sep_rad: float) -> float:
    """Expected number of star pairs closer than max_sep_rad among n_stars spread over the sky."""
    return 0.5 * n_stars * max(n_stars - 1, 0) * (1.0 - np.cos(min(max_sep_rad, np.pi))) / 2.0


def key_hash(key: dict) -> str:
    blob = json.dumps(key, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def key_string(key: dict) -> str:
    """`<method>-<hash16>`: the short form recorded in results."""
    return f"{key['method']}-{key_hash(key)}"


def database_path(key: dict) -> Path:
    return cache_dir() / "databases" / f"{key_string(key)}.npz"


ANNOUNCE_AFTER_S = 2.0  # a build expected to take longer says what it builds and for how long


def load_or_build(key: dict, build: Callable[[], dict[str, np.ndarray]], *, mmap: bool = False,
                  what: str | None = None, estimate_s: float = 0.0, estimate_bytes: float = 0.0
                  ) -> tuple[dict[str, np.ndarray], dict]:
    """The arrays of the database for `key`: loaded from the cache, or built once and saved.

    Returns (arrays, info); info holds the key, its string form, the path, whether it was built or
    loaded, the build or load time, the file size and the in-memory size in bytes. mmap=True maps
    the arrays of the (uncompressed) file read-only instead of reading them: a large database then
    loads in milliseconds and its pages are shared between processes. what / estimate_s: a build
    expected to take more than ANNOUNCE_AFTER_S seconds prints one line on stderr before it starts
    (what it builds, about how long) and one when it is done. estimate_bytes: the build's peak memory,
    checked against the budget (`check_memory`) before a build starts, never for a cached database.
    """
    path = database_path(key)
    info = {"key": key, "key_string": key_string(key), "path": str(path)}
    if path.exists():
        t0 = time.perf_counter()
        arrays = _read_mmap(path, key) if mmap else _read(path, key)
        if arrays is not None:
            info.update(source="cache", load_s=time.perf_counter() - t0, build_s=None,
                        file_bytes=path.stat().st_size, nbytes=_nbytes(arrays))
            touch(path)
            return arrays, info
        print(f"skyview: the cached database {path.name} is damaged or from another version; rebuilding it",
              file=sys.stderr, flush=True)
    if estimate_bytes:
        check_memory(estimate_bytes, what or f"the {key.get('method', '')} database")
    announce = what is not None and estimate_s > ANNOUNCE_AFTER_S
    if announce:
        print(f"skyview: building {what} once (about {estimate_s:.0f} s; cached for later runs)",
              file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    arrays = build()
    info.update(source="built", build_s=time.perf_counter() - t0, load_s=None, nbytes=_nbytes(arrays))
    if announce:
        print(f"skyview: built {what} in {info['build_s']:.1f} s", file=sys.stderr, flush=True)
    try:
        _write(path, key, arrays)
        info["file_bytes"] = path.stat().st_size
        evict_to_budget(keep=path)
    except OSError as exc:  # a read-only cache still works, it just rebuilds next time
        # (one line on stderr for the user, as the build's own lines; once per cache folder and process)
        if str(path.parent) not in _UNWRITABLE:
            _UNWRITABLE.add(str(path.parent))
            reason = exc.strerror or str(exc)
            print(f"skyview: could not write the cache in {path.parent} ({reason}): the databases are built again in "
                  "each process; set SKYVIEW_CACHE to a writable folder", file=sys.stderr, flush=True)
        info["file_bytes"] = None
    return arrays, info


def random_access(arrays: dict[str, np.ndarray]) -> None:
    """Tell the kernel that these memory-mapped arrays (`load_or_build(..., mmap=True)`) are read at random
    places: a page faulted in from the disk is read alone, not with the 128 KB read-ahead around it."""
    for a in arrays.values():
        m = getattr(a, "_mmap", None)  # (np.memmap's map)
        if m is not None and hasattr(mmap_module, "MADV_RANDOM"):
            m.madvise(mmap_module.MADV_RANDOM)


def prefetch(mapped: np.ndarray, rows: np.ndarray) -> None:
    """Ask the kernel for the pages that hold mapped[rows] (a memory-mapped array's rows) all at once
    (MADV_WILLNEED, one call per run of pages): on a cold page cache the disk then reads them together
    instead of one page fault at a time. Costs ~1 us a run when they are already there; nothing for an
    array that is not a map."""
    m = getattr(mapped, "_mmap", None)
    if m is None or len(rows) == 0 or not hasattr(mmap_module, "MADV_WILLNEED"):
        return
    page = mmap_module.PAGESIZE
    lead = mapped.offset % mmap_module.ALLOCATIONGRANULARITY  # where the array starts in its map
    first = lead + np.asarray(rows, dtype=np.int64) * mapped.strides[0]
    # (sorted, repeats kept: np.unique would import numpy.ma, which a solve does not need)
    pages = np.sort(np.concatenate([first // page, (first + mapped.strides[0] - 1) // page]))
    cut = np.flatnonzero(np.diff(pages) > 1) + 1
    size = len(m)
    for s, e in zip(pages[np.r_[0, cut]].tolist(), (pages[np.r_[cut - 1, len(pages) - 1]] + 1).tolist()):
        m.madvise(mmap_module.MADV_WILLNEED, s * page, min(e * page, size) - s * page)


SKY_INDEX_MIN_STARS = 20_000  # a catalog this large keeps its sky index in the cache
SKY_INDEX_FORMAT = 1  # bump with any change to how SkyIndex or its cells are made: the files are keyed by it


def with_cached_sky_index(catalog: GuideCatalog) -> GuideCatalog:
    """The catalog with its sky index (`GuideCatalog.sky`: the z order and the cube-face cells) read from
    the cache instead of sorted in every process: built once per catalog (its fingerprint: a catalog at
    another epoch has its own): ~20 ms to build for the 78,352 stars of the guide catalog, ~6 ms to load
    (the fingerprint included; copied into memory, since the cap queries' gathers run ~2.5x slower on a
    file-backed map), 48 bytes a star on disk (3.8 MB), counted in the cache's budget. A small catalog (fewer than
    SKY_INDEX_MIN_STARS stars: a millisecond's sort) or one whose index is already made is left as it is."""
    from skyview.core.catalog import SKY_CELLS, SkyIndex

    if "sky" in catalog.__dict__ or len(catalog.hip) < SKY_INDEX_MIN_STARS:
        return catalog
    key = {"method": "sky_index", "catalog": catalog.fingerprint, "stars": int(len(catalog.hip)),
           "cells": SKY_CELLS, "format": SKY_INDEX_FORMAT}
    arrays, _ = load_or_build(key, lambda: SkyIndex(catalog.xyz).to_arrays(), mmap=True)
    try:
        catalog.__dict__["sky"] = SkyIndex.from_arrays(catalog.xyz, arrays)
    except (KeyError, ValueError):  # not this catalog's after all: sorted here, as without a cache
        pass
    return catalog


def _read(path: Path, key: dict) -> dict[str, np.ndarray] | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            stored = json.loads(str(z[_KEY_FIELD]))
            if stored != json.loads(json.dumps(key)):
                return None
            names = json.loads(str(z[_NAMES_FIELD]))
            if set(names) - set(z.files):
                return None  # an array is missing
            return {k: z[k] for k in names}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


def _read_mmap(path: Path, key: dict) -> dict[str, np.ndarray] | None:
    """Memory-map every array of an uncompressed .npz (zip members are stored contiguously)."""

    try:
        out = {}
        names = None
        with zipfile.ZipFile(path) as zf, open(path, "rb") as fh:
            for zi in zf.infolist():
                if zi.compress_type != zipfile.ZIP_STORED or not zi.filename.endswith(".npy"):
                    return None
                fh.seek(zi.header_offset)
                local = fh.read(30)
                if local[:4] != b"PK\x03\x04":
                    return None
                start = zi.header_offset + 30 + int.from_bytes(local[26:28], "little") \
                    + int.from_bytes(local[28:30], "little")
                fh.seek(start)
                version = np.lib.format.read_magic(fh)
                reader = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                          else np.lib.format.read_array_header_2_0)
                shape, fortran, dtype = reader(fh)
                name = zi.filename[:-4]
                if dtype.hasobject:
                    return None
                if name == _KEY_FIELD:
                    fh.seek(start)
                    stored = json.loads(str(np.lib.format.read_array(fh, allow_pickle=False)))
                    if stored != json.loads(json.dumps(key)):
                        return None
                    continue
                if name == _NAMES_FIELD:
                    fh.seek(start)
                    names = json.loads(str(np.lib.format.read_array(fh, allow_pickle=False)))
                    continue
                n = int(np.prod(shape)) if shape else 1
                if fh.tell() + n * dtype.itemsize > path.stat().st_size:
                    return None  # truncated
                out[name] = np.memmap(path, dtype=dtype, mode="r", offset=fh.tell(), shape=shape,
                                      order="F" if fortran else "C")
        if names is None or set(names) - set(out):
            return None  # no list of arrays, or an array is missing
        return {k: out[k] for k in names}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


def _write(path: Path, key: dict, arrays: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}-", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **{_KEY_FIELD: np.array(json.dumps(key, sort_keys=True)),
                            _NAMES_FIELD: np.array(json.dumps(sorted(arrays)))}, **arrays)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _nbytes(arrays: dict[str, np.ndarray]) -> int:
    return int(sum(np.asarray(a).nbytes for a in arrays.values()))


def cache_budget_bytes() -> int:
    env = os.environ.get("SKYVIEW_CACHE_MB")
    try:
        return int(float(env) * 2 ** 20) if env else DEFAULT_CACHE_MB * 2 ** 20
    except ValueError:
        return DEFAULT_CACHE_MB * 2 ** 20


def touch(path: Path) -> None:
    """Mark a database as just used (its modification time), for the least-recently-used eviction."""
    try:
        os.utime(path)
    except OSError:
        pass


def evict_to_budget(keep: Path | None = None, budget_bytes: int | None = None) -> list[Path]:
    """Delete the least recently used databases until the cache fits its budget (never `keep`)."""
    budget = cache_budget_bytes() if budget_bytes is None else int(budget_bytes)
    rows = cached_databases()
    total = sum(r["bytes"] for r in rows)
    removed = []
    for r in sorted(rows, key=lambda d: d["used"]):
        if total <= budget:
            break
        p = Path(r["path"])
        if keep is not None and p == Path(keep):
            continue
        try:
            p.unlink()
        except OSError:
            continue
        total -= r["bytes"]
        removed.append(p)
    return removed


def cached_databases() -> list[dict]:
    """The databases in the cache: path, method, bytes, last use (POSIX time), newest use first."""
    folder = cache_dir() / "databases"
    out = []
    for p in sorted(folder.glob("*.npz")) if folder.is_dir() else []:
        try:
            st = p.stat()
        except OSError:
            continue
        out.append({"path": str(p), "method": p.stem.rsplit("-", 1)[0], "bytes": int(st.st_size),
                    "used": st.st_mtime})
    return sorted(out, key=lambda d: -d["used"])


def clear_cache(method: str | None = None) -> tuple[int, int]:
    """Delete cached databases (of one method, or all) and stray temporary files: (files, bytes)."""
    folder = cache_dir() / "databases"
    n = b = 0
    if not folder.is_dir():
        return 0, 0
    for p in list(folder.glob("*.npz")) + list(folder.glob(".*.tmp")):
        if method is not None and p.stem.rsplit("-", 1)[0] != method:
            continue
        try:
            size = p.stat().st_size
            p.unlink()
        except OSError:
            continue
        n, b = n + 1, b + size
    return n, b
