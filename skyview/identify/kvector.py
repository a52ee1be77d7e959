"""Mortari's k-vector: range look-up on a sorted array in (nearly) constant time.

Mortari (1997), "Search-less algorithm for star pattern recognition": sort the values s_0 <= ... <=
s_{n-1}, draw the straight line z(x) = q + m x through (0, s_min - eps) and (n-1, s_max + eps) and
store k[j] = #{ i : s_i <= z(j) }. For a query [lo, hi] the line is inverted, j_lo = floor(z^-1(lo))
and j_hi = ceil(z^-1(hi)), and the values in s[k[j_lo] : k[j_hi]] are a superset of the answer with
only a few extra elements at either end. The small widening eps keeps the first and last values
strictly inside the line, so k[0] = 0 and k[n-1] = n.

Here the ends are trimmed exactly (a short bisection inside the superset), so `query` returns
exactly the set `(values >= lo) & (values <= hi)`. The inverse is also widened by one index on each
side so that floating-point rounding in z^-1 can never lose an element; a final check falls back to
a binary search on the whole array should that ever happen anyway.

`fit="parabola"` replaces the line by a monotone parabola through the same two end points whose
curvature is fitted to the data by least squares (Cole & Crassidis use one for the spherical-triangle
areas, whose sorted values are far from linear): the superset is then tighter where the values
bunch up.
"""

from __future__ import annotations

import numpy as np

FITS = ("line", "parabola")


class KVector:
    """Range queries on a fixed array of values.

    values: any 1-D array. `order` maps sorted position -> original index; `sorted_values` is
    values[order]. `query(lo, hi)` returns original indices (in sorted-value order), `range(lo, hi)`
    the slice [start, stop) of `sorted_values`, `ranges(lo, hi)` the same for arrays of bounds.
    """

    def __init__(self, values: np.ndarray, fit: str = "line", presorted: bool = False):
        if fit not in FITS:
            raise ValueError(f"k-vector fit must be one of {FITS}, not {fit!r}")
        v = np.asarray(values, dtype=np.float64).ravel()
        if v.size and not np.all(np.isfinite(v)):
            raise ValueError("k-vector values must be finite")
        if presorted:
            if v.size > 1 and np.any(np.diff(v) < 0):
                raise ValueError("presorted=True but the values are not sorted")
            self.order = None
            self.sorted_values = v
        else:
            self.order = np.argsort(v, kind="stable")
            self.sorted_values = v[self.order]
        self.fit = fit
        s = self.sorted_values
        n = s.size
        if n < 2:
            self.coef = np.zeros(3)
            self.k = np.arange(n + 1, dtype=np.int64)[:n]
            return
        L = float(n - 1)
        scale = max(abs(s[0]), abs(s[-1]))
        eps = 8.0 * np.finfo(np.float64).eps * (scale if scale > 0 else 1.0)
        z0, zL = s[0] - eps, s[-1] + eps
        delta = zL - z0
        a = 0.0
        if fit == "parabola" and n > 2:
            x = np.arange(n, dtype=np.float64)
            g = x * x - L * x  # the parabola's shape with both end points fixed
            r = s - (z0 + delta / L * x)
            gg = float(g @ g)
            if gg > 0:
                a = float(g @ r) / gg
            lim = 0.999 * delta / (L * L)  # keep z(x) strictly increasing on [0, L]
            a = float(np.clip(a, -lim, lim))
        b = delta / L - a * L
        self.coef = np.array([z0, b, a])  # z(x) = z0 + b x + a x^2
        j = np.arange(n, dtype=np.float64)
        z = z0 + b * j + a * j * j
        z[0], z[-1] = z0, zL
        self.k = np.searchsorted(s, z, side="right").astype(np.int64)

    # ---------------------------------------------------------------- persistence
    def to_arrays(self, prefix: str = "kv_") -> dict[str, np.ndarray]:
        d = {f"{prefix}sorted": self.sorted_values, f"{prefix}k": self.k, f"{prefix}coef": self.coef,
             f"{prefix}fit": np.array(self.fit)}
        if self.order is not None:
            d[f"{prefix}order"] = self.order
        return d

    @classmethod
    def from_arrays(cls, arrays: dict, prefix: str = "kv_") -> "KVector":
        kv = cls.__new__(cls)
        kv.sorted_values = np.asarray(arrays[f"{prefix}sorted"], dtype=np.float64)
        kv.k = np.asarray(arrays[f"{prefix}k"], dtype=np.int64)
        kv.coef = np.asarray(arrays[f"{prefix}coef"], dtype=np.float64)
        kv.fit = str(arrays[f"{prefix}fit"])
        kv.order = np.asarray(arrays[f"{prefix}order"]) if f"{prefix}order" in arrays else None
        return kv

    @property
    def nbytes(self) -> int:
        n = self.sorted_values.nbytes + self.k.nbytes + self.coef.nbytes
        return int(n + (self.order.nbytes if self.order is not None else 0))

    def __len__(self) -> int:
        return int(self.sorted_values.size)

    # ---------------------------------------------------------------- queries
    def _inverse(self, y: np.ndarray) -> np.ndarray:
        """x with z(x) = y (y clipped to the line's range); stable for a -> 0."""
        z0, b, a = self.coef
        L = len(self) - 1
        zL = z0 + b * L + a * L * L
        d = np.clip(y, z0, zL) - z0
        disc = np.maximum(b * b + 4.0 * a * d, 0.0)
        den = b + np.sqrt(disc)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(den > 0, 2.0 * d / den, 0.0)
        return x

    def ranges(self, lo, hi) -> tuple[np.ndarray, np.ndarray]:
        """Slices [start, stop) of `sorted_values` holding exactly the values in [lo, hi] (arrays).

        A batch of bounds is answered by two binary searches in C over the whole array (O(log n)
        each; ~20 us for 600 queries on 118,000 pair angles), which in numpy beats walking the
        k-vector's supersets (a vectorised bisection of a few dozen numpy calls, ~0.3-0.8 ms): the
        answers are the same slices."""
        lo = np.atleast_1d(np.asarray(lo, dtype=np.float64))
        hi = np.atleast_1d(np.asarray(hi, dtype=np.float64))
        if lo.shape != hi.shape:
            lo, hi = np.broadcast_arrays(lo, hi)
        s = self.sorted_values
        if lo.size > 32:
            # queries in increasing order: numpy's binary search starts each from the previous answer,
            # so on a large table (700,000 angles at 20 deg) it misses the cache about half as often
            # (the same answers; ~0.8 -> 0.4 ms for 1,800 queries)
            order = np.argsort(lo, kind="stable")
            start = np.empty(lo.size, dtype=np.int64)
            stop = np.empty(lo.size, dtype=np.int64)
            start[order] = np.searchsorted(s, lo[order], side="left")
            stop[order] = np.searchsorted(s, hi[order], side="right")
        else:
            start = np.searchsorted(s, lo, side="left").astype(np.int64, copy=False)
            stop = np.searchsorted(s, hi, side="right").astype(np.int64, copy=False)
        bad = ~(lo <= hi)  # NaN or an inverted range: empty, (0, 0) as from `range`
        if bad.any():
            stop = np.maximum(stop, start)
            start[bad] = 0
            stop[bad] = 0
        return start, stop

    def ranges_kvector(self, lo, hi) -> tuple[np.ndarray, np.ndarray]:
        """`ranges` through the k-vector (Mortari's superset, then a vectorised bisection inside it):
        the same slices, kept as the method the papers describe and checked against `ranges`."""
        lo = np.atleast_1d(np.asarray(lo, dtype=np.float64))
        hi = np.atleast_1d(np.asarray(hi, dtype=np.float64))
        lo, hi = np.broadcast_arrays(lo, hi)
        s = self.sorted_values
        n = s.size
        if n < 2:
            start = np.searchsorted(s, lo, side="left")
            stop = np.searchsorted(s, hi, side="right")
        else:
            L = n - 1
            with np.errstate(invalid="ignore"):
                jl = np.clip(np.floor(self._inverse(lo)).astype(np.int64) - 1, 0, L)
                jh = np.clip(np.ceil(self._inverse(hi)).astype(np.int64) + 1, 0, L)
            a = self.k[jl]
            b = self.k[jh]
            start = _bisect(s, a, np.maximum(a, b), lo, strict=False)
            stop = _bisect(s, start, np.maximum(start, b), hi, strict=True)
            # the superset [a, b) must hold every answer; it always does, but never trust rounding
            bad = ((a > 0) & (s[np.maximum(a - 1, 0)] >= lo)) | ((b < n) & (s[np.minimum(b, n - 1)] <= hi))
            if np.any(bad):  # pragma: no cover - defensive
                start[bad] = np.searchsorted(s, lo[bad], side="left")
                stop[bad] = np.searchsorted(s, hi[bad], side="right")
        bad = ~(lo <= hi)
        stop = np.maximum(stop, start)
        start[bad] = 0
        stop[bad] = 0
        return start.astype(np.int64), stop.astype(np.int64)

    def range(self, lo: float, hi: float) -> tuple[int, int]:
        """Slice [start, stop) of `sorted_values` holding exactly the values in [lo, hi]."""
        lo, hi = float(lo), float(hi)
        s = self.sorted_values
        n = s.size
        if not (lo <= hi) or n == 0:
            return 0, 0
        if n < 2:
            st, sp = self.ranges(lo, hi)
            return int(st[0]), int(sp[0])
        L = n - 1
        z0, b, a = (float(c) for c in self.coef)
        zL = z0 + b * L + a * L * L

        def inv(y: float) -> float:
            d = min(max(y, z0), zL) - z0
            den = b + np.sqrt(max(b * b + 4.0 * a * d, 0.0))
            return 2.0 * d / den if den > 0 else 0.0

        jl = min(max(int(np.floor(inv(lo))) - 1, 0), L)
        jh = min(max(int(np.ceil(inv(hi))) + 1, 0), L)
        ka, kb = int(self.k[jl]), int(self.k[jh])
        if (ka > 0 and s[ka - 1] >= lo) or (kb < n and s[kb] <= hi):  # pragma: no cover - defensive
            return int(np.searchsorted(s, lo, "left")), int(np.searchsorted(s, hi, "right"))
        window = s[ka:kb]
        start = ka + int(np.searchsorted(window, lo, "left"))
        stop = ka + int(np.searchsorted(window, hi, "right"))
        return start, max(start, stop)

    def count(self, lo, hi) -> np.ndarray:
        start, stop = self.ranges(lo, hi)
        return stop - start

    def query(self, lo: float, hi: float) -> np.ndarray:
        """Original indices of the values in [lo, hi], in sorted-value order."""
        start, stop = self.range(lo, hi)
        if self.order is None:
            return np.arange(start, stop, dtype=np.int64)
        return self.order[start:stop]


def _bisect(s: np.ndarray, lo_idx: np.ndarray, hi_idx: np.ndarray, v: np.ndarray, strict: bool) -> np.ndarray:
    """Per query, the first index i in [lo_idx, hi_idx) with s[i] >= v (s[i] > v if strict), else hi_idx."""
    lo = lo_idx.astype(np.int64).copy()
    hi = hi_idx.astype(np.int64).copy()
    n = s.size
    active = lo < hi
    while np.any(active):
        mid = (lo + hi) // 2
        sm = s[np.minimum(mid, n - 1)]
        right = (sm <= v) if strict else (sm < v)
        go_right = active & right
        go_left = active & ~right
        lo = np.where(go_right, mid + 1, lo)
        hi = np.where(go_left, mid, hi)
        active = lo < hi
    return lo
