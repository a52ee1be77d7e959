"""The matching and the verification of a tracked frame, in small numpy steps.

A tracked frame has a few tens of stars: the generic tools (scipy's KD-tree and Rotation, numpy's
`cross`, `eigvalsh`, `pinv`) spend more on their call overhead than on the numbers. These are the same
computations in closed form:

- `predicted_sigma`: the largest standard deviation of a direction b moved by an attitude error of
  covariance P, sqrt of the largest eigenvalue of [b]x P [b]x^T (the value of
  `skyview.identify.verify.predicted_sigma`): that matrix is singular (b is its null vector), so its
  nonzero eigenvalues are (t +- sqrt(t^2 - 4 m)) / 2, t its trace and m the sum of its principal 2x2
  minors;
- `match_radii`: `verify.star_radii` with that sigma;
- `wahba`: Markley's SVD solution and the QUEST covariance (`attitude.svd_attitude`'s numbers);
- `nearest_one_to_one`: nearest catalog direction within a radius by brute force (tens by tens);
- `rotvec`, `rotation_matrix`: the log and exp maps of rotations;
- `verify_windowed`: the tracked hypothesis test of `verify.verify` (three well-spread tracked
  matches make the hypothesis, every other detected star tests it, P(false) = `p_false_calibrated`
  of the agreeing count times the hypotheses tried), with the chance of one star taken within the
  window it was found in, p_i = pi r_i^2 / window solid angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from skyview.identify.verify import CALIBRATED, DEFAULT_THRESHOLD, MAX_RADIUS_RAD, p_false_calibrated

HYPOTHESIS_STARS = 3  # tracked matches that make the verified hypothesis (the rest test it)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (np.cross without its axis handling)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def predicted_sigma(b: np.ndarray, P: np.ndarray) -> np.ndarray:
    """sqrt of the largest eigenvalue of [b_i]x P [b_i]x^T for each row of b (closed form)."""
    b = np.asarray(b, dtype=np.float64).reshape(-1, 3)
    x, y, z = b[:, 0], b[:, 1], b[:, 2]
    # K = [b]x = [[0, -z, y], [z, 0, -x], [-y, x, 0]]; C = K P K^T
    K = np.zeros((len(b), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -z, y, -x
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = z, -y, x
    C = K @ P @ K.transpose(0, 2, 1)
    t = C[:, 0, 0] + C[:, 1, 1] + C[:, 2, 2]
    m = (C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] ** 2 + C[:, 0, 0] * C[:, 2, 2] - C[:, 0, 2] ** 2
         + C[:, 1, 1] * C[:, 2, 2] - C[:, 1, 2] ** 2)
    lam = 0.5 * (t + np.sqrt(np.maximum(t * t - 4.0 * m, 0.0)))
    return np.sqrt(np.maximum(lam, 0.0))


def match_radii(b: np.ndarray, P: np.ndarray, sigma_rad: float, radius_rad: float) -> np.ndarray:
    """Per-star match radius r sqrt(1 + s_i^2 / sigma^2), s_i = predicted_sigma, capped (`verify.star_radii`)."""
    s = predicted_sigma(b, P)
    return np.minimum(radius_rad * np.sqrt(1.0 + (s / sigma_rad) ** 2), max(MAX_RADIUS_RAD, radius_rad))


def wahba(b: np.ndarray, r: np.ndarray, sigma_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """The attitude R (b_i ~ R r_i, Markley's SVD solution, equal weights) and its QUEST covariance
    (camera axes, rad^2): the numbers of `attitude.svd_attitude`."""
    w = 1.0 / (sigma_rad * sigma_rad)
    U, _, Vt = np.linalg.svd(b.T @ r)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        U = U.copy()
        U[:, 2] = -U[:, 2]
    F = w * (len(b) * np.eye(3) - b.T @ b)
    try:
        P = np.linalg.inv(F)
    except np.linalg.LinAlgError:  # two stars along one line: the roll about it is not measured
        P = np.linalg.pinv(F)
    return U @ Vt, P


def rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix: the log map (scipy's near a half turn)."""
    R = np.asarray(R, dtype=np.float64)
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if c < -0.99:
        return Rotation.from_matrix(R).as_rotvec()
    s = float(np.linalg.norm(w))  # sin(angle)
    angle = math.atan2(s, min(1.0, c))
    return w * (angle / s if s > 1e-12 else 1.0)


def rotation_matrix(rotvec_rad: np.ndarray) -> np.ndarray:
    """The rotation matrix of a rotation vector (Rodrigues' formula)."""
    w = np.asarray(rotvec_rad, dtype=np.float64)
    a = float(np.linalg.norm(w))
    if a < 1e-12:
        return np.eye(3)
    k = w / a
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * K + (1.0 - math.cos(a)) * (K @ K)


def nearest_one_to_one(query: np.ndarray, ref: np.ndarray, radius_rad: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, int]:
    """(query index, ref index) pairs: each query's nearest ref unit vector within its radius; a query
    with a second ref within its radius (an unresolved pair) is left out, and a ref wanted by two
    queries goes to the closer. Also returns how many queries with a ref within their radius were
    left out."""
    d = query @ ref.T  # cosines (n, M)
    cos_r = np.cos(np.broadcast_to(radius_rad, (len(query),)))
    best = np.argmax(d, axis=1)
    n = np.arange(len(query))
    top = d[n, best]
    within = top >= cos_r
    if ref.shape[0] > 1:
        d[n, best] = -2.0
        within_two = within & (d.max(axis=1) >= cos_r)
    else:
        within_two = np.zeros(len(query), dtype=bool)
    q = np.flatnonzero(within & ~within_two)
    q = q[np.argsort(-top[q], kind="stable")]  # the closest first keeps its ref
    _, first = np.unique(best[q], return_index=True)
    q = np.sort(q[first])
    return q, best[q], int(within.sum()) - len(q)


def spread_subset(vectors: np.ndarray, order: np.ndarray, k: int) -> list[int]:
    """k indices of `order` (brightest first) that spread far: the brightest, the farthest from it,
    then the one farthest from the line through the two (largest triangle)."""
    order = np.asarray(order, dtype=np.int64)
    if len(order) <= k:
        return order.tolist()
    v = vectors[order]
    d = v - v[0]
    second = int(np.argmax(np.einsum("ij,ij->i", d, d)))
    chosen = [0, second]
    if k >= 3:
        c = cross(np.broadcast_to(d[second], d.shape), d)
        area = np.einsum("ij,ij->i", c, c)
        area[chosen] = -1.0
        chosen.append(int(np.argmax(area)))
    return order[chosen].tolist()


@dataclass
class TrackedSolution:
    R: np.ndarray
    covariance: np.ndarray
    p_false: float
    matches: dict[int, int]  # observed index -> catalog row, every star that fits


def verify_windowed(b: np.ndarray, matches: dict[int, int], order: np.ndarray, window_sr: np.ndarray,
                    catalog_xyz: np.ndarray, sigma_rad: float, radius_rad: float, min_matches: int,
                    tries: int) -> tuple[TrackedSolution | None, str]:
    """The verification of a windowed frame (see the module docstring): up to `tries` hypotheses (three
    well-spread tracked matches of `order`, brightest first; the next try three of the rest), each
    tested by every other detected star. A passed hypothesis is extended to every agreeing star and the
    attitude re-estimated from all; a star that then misfits its radius is left out. Returns the
    solution, or None and the reason."""
    reason = "no hypothesis"
    n = len(b)
    for t in range(tries):
        pool = order[t * HYPOTHESIS_STARS:]
        k = min(HYPOTHESIS_STARS, n - 1, len(pool))
        if k < 2:
            break
        hyp = spread_subset(b, pool, k)
        h_cat = [matches[i] for i in hyp]
        R, P = wahba(b[hyp], catalog_xyz[h_cat], sigma_rad)
        if np.any(np.linalg.norm(b[hyp] - catalog_xyz[h_cat] @ R.T, axis=1) > radius_rad):
            reason = "the hypothesis does not fit itself"
            continue
        mask = np.ones(n, dtype=bool)
        mask[hyp] = False
        others = np.flatnonzero(mask)
        if len(others) == 0:
            reason = "no detected star is left outside the hypothesis to test it"
            break
        radii = match_radii(b[others], P, sigma_rad, radius_rad)
        taken = set(h_cat)
        cand = np.array([o in matches and matches[o] not in taken for o in others.tolist()], dtype=bool)
        agree: dict[int, int] = {}
        if np.any(cand):
            o_c = others[cand]
            c_c = np.array([matches[o] for o in o_c.tolist()])
            ok = np.linalg.norm(b[o_c] - catalog_xyz[c_c] @ R.T, axis=1) <= radii[cand]
            agree = dict(zip(o_c[ok].tolist(), c_c[ok].tolist()))
        p = np.minimum(1.0, np.pi * radii ** 2 / window_sr[others])
        p_false = p_false_calibrated(len(agree), len(others), p, t + 1)
        if not p_false < DEFAULT_THRESHOLD[CALIBRATED]:
            reason = f"{len(agree)} of {len(others)} other detected stars agree, P(false) = {p_false:.2e}"
            continue
        final = {**dict(zip(hyp, h_cat)), **agree}
        f_obs = np.array(sorted(final))
        f_cat = np.array([final[o] for o in f_obs.tolist()])
        R, P = wahba(b[f_obs], catalog_xyz[f_cat], sigma_rad)
        fit = (np.linalg.norm(b[f_obs] - catalog_xyz[f_cat] @ R.T, axis=1)
               <= match_radii(b[f_obs], P, sigma_rad, radius_rad))
        if np.sum(fit) < min_matches:
            reason = "fewer stars than tracking needs fit the extended attitude"
            continue
        if not np.all(fit):
            f_obs, f_cat = f_obs[fit], f_cat[fit]
            R, P = wahba(b[f_obs], catalog_xyz[f_cat], sigma_rad)
        return TrackedSolution(R, P, float(p_false), dict(zip(f_obs.tolist(), f_cat.tolist()))), ""
    return None, reason


def verify_by_prediction(b: np.ndarray, matches: dict[int, int], p_each: np.ndarray, catalog_xyz: np.ndarray,
                         sigma_rad: float, radii: np.ndarray, min_stars: int,
                         threshold: float = DEFAULT_THRESHOLD[CALIBRATED]) -> tuple[TrackedSolution | None, str]:
    """Tracking on the last stars: the prediction itself is the hypothesis (it came from earlier frames and
    the motion, not from this frame), so every detected star tests it. `p_each[j]`: the chance that
    detected star j lands within its match bound of a predicted catalog star by accident (the catalog's
    density around the field times the bound's area, or the bound's share of its window). P(false) is
    the shared verification's (`verify.p_false_calibrated`, one hypothesis): at least len(matches) of
    the len(b) stars so placed by chance. Accepted below `threshold` with at least `min_stars` matches
    (2 with a known turn or rate, 3 when the motion is unknown); the attitude is then estimated from the
    matches alone, and every match must fit it within its bound. Returns the solution, or None and why."""
    k, n = len(matches), len(b)
    if k < min_stars:
        return None, f"{k} of {n} stars matched the prediction; the prediction alone needs {min_stars}"
    p_false = p_false_calibrated(k, n, np.minimum(1.0, np.asarray(p_each, dtype=np.float64)), 1)
    if not p_false < threshold:
        return None, f"{k} of {n} stars on their predicted places, P(false) = {p_false:.2e}"
    obs = np.array(sorted(matches))
    cat = np.array([matches[o] for o in obs.tolist()])
    R, P = wahba(b[obs], catalog_xyz[cat], sigma_rad)
    if np.any(np.linalg.norm(b[obs] - catalog_xyz[cat] @ R.T, axis=1) > radii[obs]):
        return None, "the matched stars do not fit one attitude"
    return TrackedSolution(R, P, float(p_false), dict(zip(obs.tolist(), cat.tolist()))), ""
