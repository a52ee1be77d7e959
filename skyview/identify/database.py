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
import os
import tempfile
import time
import warnings
from pathlib import Path
from typing import Callable

import numpy as np

from skyview.camera import Camera
from skyview.catalog import GuideCatalog, cache_dir

FORMAT_VERSION = 1
_KEY_FIELD = "__key__"


def make_key(method: str, params: dict, catalog: GuideCatalog, camera: Camera | None) -> dict:
    """Everything a database depends on, as a JSON-able dict."""
    key = {
        "method": str(method),
        "format": FORMAT_VERSION,
        "params": _jsonable(params),
        "catalog": {"fingerprint": catalog.fingerprint, "stars": len(catalog), "epoch": float(catalog.epoch),
                    "filters": list(catalog.history)},
    }
    if camera is not None:
        key["camera"] = {k: (float(v) if isinstance(v, float) else int(v))
                         for k, v in (("width", camera.width), ("height", camera.height), ("fx", camera.fx),
                                      ("fy", camera.fy), ("cx", camera.cx), ("cy", camera.cy),
                                      ("k1", camera.k1), ("k2", camera.k2))}
    return key


def key_hash(key: dict) -> str:
    blob = json.dumps(key, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def key_string(key: dict) -> str:
    """`<method>-<hash16>`: the short form recorded in results."""
    return f"{key['method']}-{key_hash(key)}"


def database_path(key: dict) -> Path:
    return cache_dir() / "databases" / f"{key_string(key)}.npz"


def load_or_build(key: dict, build: Callable[[], dict[str, np.ndarray]]) -> tuple[dict[str, np.ndarray], dict]:
    """The arrays of the database for `key`: loaded from the cache, or built once and saved.

    Returns (arrays, info); info holds the key, its string form, the path, whether it was built or
    loaded, the build or load time, the file size and the in-memory size in bytes.
    """
    path = database_path(key)
    info = {"key": key, "key_string": key_string(key), "path": str(path)}
    if path.exists():
        t0 = time.perf_counter()
        arrays = _read(path, key)
        if arrays is not None:
            info.update(source="cache", load_s=time.perf_counter() - t0, build_s=None,
                        file_bytes=path.stat().st_size, nbytes=_nbytes(arrays))
            return arrays, info
    t0 = time.perf_counter()
    arrays = build()
    info.update(source="built", build_s=time.perf_counter() - t0, load_s=None, nbytes=_nbytes(arrays))
    try:
        _write(path, key, arrays)
        info["file_bytes"] = path.stat().st_size
    except OSError as exc:  # a read-only cache still works, it just rebuilds next time
        warnings.warn(f"could not cache the database at {path}: {exc}", RuntimeWarning, stacklevel=2)
        info["file_bytes"] = None
    return arrays, info


def _read(path: Path, key: dict) -> dict[str, np.ndarray] | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            stored = json.loads(str(z[_KEY_FIELD]))
            if stored != json.loads(json.dumps(key)):
                return None
            return {k: z[k] for k in z.files if k != _KEY_FIELD}
    except (OSError, ValueError, KeyError, EOFError):
        return None


def _write(path: Path, key: dict, arrays: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}-", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **{_KEY_FIELD: np.array(json.dumps(key, sort_keys=True))}, **arrays)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _nbytes(arrays: dict[str, np.ndarray]) -> int:
    return int(sum(np.asarray(a).nbytes for a in arrays.values()))


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if x is None or isinstance(x, (bool, int, float, str)):
        return x
    return str(x)
