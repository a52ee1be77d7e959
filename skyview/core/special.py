"""Two special functions the pipeline needs on every solve, without scipy.special.

numpy has neither the error function (the centroider's pixel-integrated Gaussian PSF) nor a binomial
tail (the verification's chance agreement); scipy.special has both, and costs about 0.15 s to import in
every process (`import scipy.special` pulls in its array-API layer), half of what a whole `skyview
solve` may take. Both here agree with scipy's to a few ulp (tests/test_special.py).
"""

from __future__ import annotations

import math

import numpy as np

_NORMAL = 2.2250738585072014e-308  # the smallest normal float

_ERX = 8.45062911510467529297e-01
_EFX = 1.28379167095512586316e-01
_PP = (1.28379167095512558561e-01, -3.25042107247001499370e-01, -2.84817495755985104766e-02,
       -5.77027029648944159157e-03, -2.37630166566501626084e-05)
_QQ = (3.97917223959155352819e-01, 6.50222499887672944485e-02, 5.08130628187576562776e-03,
       1.32494738004321644526e-04, -3.96022827877536812320e-06)
_PA = (-2.36211856075265944077e-03, 4.14856118683748331666e-01, -3.72207876035701323847e-01,
       3.18346619901161753674e-01, -1.10894694282396677476e-01, 3.54783043256182359371e-02,
       -2.16637559486879084300e-03)
_QA = (1.06420880400844228286e-01, 5.40397917702171048937e-01, 7.18286544141962662868e-02,
       1.26171219808761642112e-01, 1.36370839120290507362e-02, 1.19844998467991074170e-02)
_RA = (-9.86494403484714822705e-03, -6.93858572707181764372e-01, -1.05586262253232909814e+01,
       -6.23753324503260060396e+01, -1.62396669462573470355e+02, -1.84605092906711035994e+02,
       -8.12874355063065934246e+01, -9.81432934416914548592e+00)
_SA = (1.96512716674392571292e+01, 1.37657754143519042600e+02, 4.34565877475229228821e+02,
       6.45387271733267880336e+02, 4.29008140027567833386e+02, 1.08635005541779435134e+02,
       6.57024977031928170135e+00, -6.04244152148580987438e-02)
_RB = (-9.86494292470009928597e-03, -7.99283237680523006574e-01, -1.77579549177547519889e+01,
       -1.60636384855821916062e+02, -6.37566443368389627722e+02, -1.02509513161107724954e+03,
       -4.83519191608651397019e+02)
_SB = (3.03380607434824582924e+01, 3.25792512996573918826e+02, 1.53672958608443695994e+03,
       3.19985821950859553908e+03, 2.55305040643316442583e+03, 4.74528541206955367215e+02,
       -2.24409524465858183362e+01)


def erf(x, out=None) -> np.ndarray:
    """The error function of an array, to within 1 ulp of the C library's (the same algorithm: Sun's
    fdlibm s_erf.c, its rational approximations on |x| < 0.84375, < 1.25, < 1/0.35, < 6 and 1 beyond);
    `out`: an array of x's shape to write into, as a ufunc's."""
    x = np.asarray(x, dtype=np.float64)
    ax = np.abs(x)
    res = np.empty_like(x)
    # |x| < 0.84375
    m = ax < 0.84375
    if m.any():
        xs = x[m]
        z = xs * xs
        r = _PP[0] + z * (_PP[1] + z * (_PP[2] + z * (_PP[3] + z * _PP[4])))
        s = 1.0 + z * (_QQ[0] + z * (_QQ[1] + z * (_QQ[2] + z * (_QQ[3] + z * _QQ[4]))))
        y = r / s
        small = np.abs(xs) < 2.0 ** -28
        res[m] = np.where(small, xs + _EFX * xs, xs + xs * y)
    # 0.84375 <= |x| < 1.25
    m = (ax >= 0.84375) & (ax < 1.25)
    if m.any():
        s = ax[m] - 1.0
        P = _PA[0] + s * (_PA[1] + s * (_PA[2] + s * (_PA[3] + s * (_PA[4] + s * (_PA[5] + s * _PA[6])))))
        Q = 1.0 + s * (_QA[0] + s * (_QA[1] + s * (_QA[2] + s * (_QA[3] + s * (_QA[4] + s * _QA[5])))))
        v = _ERX + P / Q
        res[m] = np.where(x[m] >= 0, v, -v)
    # 1.25 <= |x| < 6
    m = (ax >= 1.25) & (ax < 6.0)
    if m.any():
        a = ax[m]
        s = 1.0 / (a * a)
        low = a < 1.0 / 0.35
        R = np.where(low, _RA[0] + s * (_RA[1] + s * (_RA[2] + s * (_RA[3] + s * (_RA[4] + s * (_RA[5] + s * (_RA[6] + s * _RA[7])))))),
                     _RB[0] + s * (_RB[1] + s * (_RB[2] + s * (_RB[3] + s * (_RB[4] + s * (_RB[5] + s * _RB[6]))))))
        S = np.where(low, 1.0 + s * (_SA[0] + s * (_SA[1] + s * (_SA[2] + s * (_SA[3] + s * (_SA[4] + s * (_SA[5] + s * (_SA[6] + s * _SA[7]))))))),
                     1.0 + s * (_SB[0] + s * (_SB[1] + s * (_SB[2] + s * (_SB[3] + s * (_SB[4] + s * (_SB[5] + s * _SB[6])))))))
        z = (a.view(np.uint64) & np.uint64(0xFFFFFFFF00000000)).view(np.float64)
        r = np.exp(-z * z - 0.5625) * np.exp((z - a) * (z + a) + R / S)
        v = 1.0 - r / a
        res[m] = np.where(x[m] >= 0, v, -v)
    m = ax >= 6.0
    if m.any():
        res[m] = np.where(x[m] >= 0, 1.0, -1.0)
    nan = np.isnan(x)
    if nan.any():
        res[nan] = np.nan
    if out is not None:
        out[...] = res
        return out
    return res


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
