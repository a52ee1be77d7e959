"""Two special functions the pipeline needs on every solve, without scipy.special.

numpy has neither the error function (the centroider's pixel-integrated Gaussian PSF) nor a binomial
tail (the verification's chance agreement); scipy.special has both, and costs about 0.15 s to import in
every process (`import scipy.special` pulls in its array-API layer), half of what a whole `skyview
solve` may take. The error function here is the C library's, the tails agree with scipy's to 1e-11
(tests/test_special.py).
"""

from __future__ import annotations

import math

import numpy as np

_NORMAL = 2.2250738585072014e-308  # the smallest normal float


def erf(x, out=None) -> np.ndarray:
    """The error function of an array: the C library's (Python's math.erf), element by element, so that
    a value never depends on the array it came in (a star fitted alone or in a batch gets the same bits).
    `out`: an array of x's shape to write into, as a ufunc's. About 50 ns an element: a frame's PSF fits
    ask for a few thousand (0.1 ms), what scipy.special.erf would do in 0.02 ms after its 0.15 s import."""
    x = np.asarray(x, dtype=np.float64)
    values = np.fromiter(map(math.erf, x.ravel().tolist()), dtype=np.float64, count=x.size).reshape(x.shape)
    if out is None:
        return values
    out[...] = values
    return out


def binomial_sf(k: int, n: int, p: float) -> float:
    """P[X >= k] for X ~ Binomial(n, p) (scipy.special.bdtrc(k - 1, n, p), to ~1e-14 relative): the
    terms C(n, j) p^j (1 - p)^(n - j) for j = k .. n summed from the first, each from the one before (no
    cancellation: a tail of 1e-300 is as exact as one of 0.5)."""
    if k <= 0:
        return 1.0
    if k > n or p <= 0.0:
        return 0.0
    if p >= 1.0:
        return 1.0
    q = 1.0 - p
    if k <= n * p:  # the tail holds the mean: one minus the other tail (of the misses), which lies past it
        return float(max(0.0, 1.0 - binomial_sf(n - k + 1, n, q)))
    first = _binomial_term(k, n, p, q)
    ratio = p / q
    term, total = 1.0, 1.0
    for j in range(k, n):
        term *= (n - j) / (j + 1) * ratio
        total += term
        if term < total * 1e-17:
            break
    return float(min(1.0, first * total))


def _binomial_term(k: int, n: int, p: float, q: float) -> float:
    """C(n, k) p^k q^(n - k): from the exact binomial coefficient and correctly rounded powers (a few ulp),
    through logarithms only where a factor would overflow or underflow."""
    try:
        pk, qk = p ** k, q ** (n - k)
        t = float(math.comb(n, k)) * pk * qk
        if all(_NORMAL <= x < math.inf for x in (pk, qk, t)):  # no factor left the normal floats
            return t
    except OverflowError:
        pass
    return math.exp(math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)
                    + k * math.log(p) + (n - k) * math.log1p(-p))


def binomial_cdf(k: int, n: int, p: float) -> float:
    """P[X <= k] for X ~ Binomial(n, p) (scipy.special.bdtr(k, n, p)), as the upper tail of the misses
    (n - X ~ Binomial(n, 1 - p)): small values without cancellation."""
    if k < 0:
        return 0.0
    if k >= n:
        return 1.0
    return binomial_sf(n - k, n, 1.0 - p)
