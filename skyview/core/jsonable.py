"""numpy values inside dicts and lists -> plain Python for JSON (one converter for every writer)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np


def plain(x: Any, *, nan_as_none: bool = False, other: Callable[[Any], Any] | None = None) -> Any:
    """`x` with dicts (keys as str), lists, tuples, arrays and numpy scalars turned into plain Python.

    nan_as_none: NaN and infinities become None (JSON has neither). other: applied to any value that
    is not a number, string, bool, None or container (e.g. `str` for a database key); by default such
    values are returned as they are.
    """
    if isinstance(x, dict):
        return {str(k): plain(v, nan_as_none=nan_as_none, other=other) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v, nan_as_none=nan_as_none, other=other) for v in x]
    if isinstance(x, np.ndarray):
        return plain(x.tolist(), nan_as_none=nan_as_none, other=other) if (nan_as_none or other) else x.tolist()
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return None if nan_as_none and not np.isfinite(x) else float(x)
    if x is None or isinstance(x, (int, str)) or other is None:
        return x
    return other(x)
