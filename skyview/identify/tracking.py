"""A tracked frame's identification: the hypotheses a prediction gives, verified by the one verification.

A tracker (`skyview.solver.track`) predicts the next frame's attitude from the last solved frames and the
motion (`Prediction`). `TrackedIdentifier` is an `Identifier` like the six methods: its hypotheses go
through the template and the shared `skyview.identify.verify` and come out as one `Identification`:

1. each observed star is matched to the nearest predicted catalog star of the field within its bound from
   the prediction's covariance (one-to-one; a star with two catalog stars within its bound is left out:
   `nearest_one_to_one`); when some were left out, the attitude is estimated from the matches and they
   are matched once more with the bound of that estimate;
2. with at least `min_matches` matches, the hypotheses are three well-spread tracked matches (brightest
   first; the next try three of the rest), each tested by every other observed star in `verify.verify`
   (a frame measured in windows: the chance of a star taken within its window, `Observation.window_sr`);
3. when they are refused, or too few stars matched, the prediction itself is the hypothesis
   (`verify.verify_prediction`): every observed star tests it, two or three on their predicted places
   suffice. The hypotheses verified for the frame are counted together (Bonferroni).

A tracked frame has a few tens of stars: the generic tools (scipy's KD-tree and Rotation, numpy's
`cross`, `eigvalsh`, `pinv`) spend more on their call overhead than on the numbers, so the geometry here
is in closed form:

- `predicted_sigma`: the largest standard deviation of a direction b moved by an attitude error of
  covariance P, sqrt of the largest eigenvalue of [b]x P [b]x^T (the value of
  `skyview.identify.verify.predicted_sigma`): that matrix is singular (b is its null vector), so its
  nonzero eigenvalues are (t +- sqrt(t^2 - 4 m)) / 2, t its trace and m the sum of its principal 2x2
  minors;
- `match_radii`: `verify.star_radii` with that sigma;
- `wahba`: Markley's SVD solution and the QUEST covariance (`attitude.svd_attitude`'s numbers);
- `nearest_one_to_one`: nearest catalog direction within a radius by brute force (tens by tens);
- `rotvec`, `rotation_matrix`: the log and exp maps of rotations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import numpy as np
from scipy.spatial.transform import Rotation

from skyview.identify.base import Hypothesis, Identification, Identifier, Observation, Search
from skyview.identify.steps import LazyStep
from skyview.identify.verify import CALIBRATED, MAX_RADIUS_RAD, RADIUS_SIGMAS

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


@dataclass(frozen=True)
class Prediction:
    """Where a tracker expects the frame: the attitude R and its covariance P (rad^2, camera axes), how it
    was predicted ("turn": a turn given, "rate": the rate of the last solved attitudes, "still": neither),
    the catalog rows around the predicted field, the stars per steradian an accidental match is drawn
    from, and how many matched stars the prediction alone needs (two when the motion is known, three
    when it is not)."""

    R: np.ndarray
    P: np.ndarray
    how: str
    rows: np.ndarray
    density_sr: float
    min_stars: int


class TrackedIdentifier(Identifier):
    """The identification of a tracked frame (the module docstring) against the tracking catalog, through
    the camera the tracker holds. `identify_predicted(obs, prediction)`; when identified, its
    stats say `verified_by`: "hypothesis" (three tracked matches tested by the rest) or "prediction"."""

    name = "track"
    title = "tracking"
    min_stars = 0  # a frame with no star is refused by its prediction: "0 of 0 stars matched"
    statistic = CALIBRATED
    threshold = None
    radius_sigmas = RADIUS_SIGMAS

    def __init__(self, catalog, camera, sigma_rad: float, *, min_matches: int = 3, tries: int = 2):
        self.catalog, self.camera, self.sigma_rad = catalog, camera, float(sigma_rad)
        self.min_matches, self.tries = int(min_matches), int(tries)
        self.database_key, self.database_info = {}, {}

    def identify_predicted(self, obs: Observation, prediction: Prediction) -> Identification:
        """Identify a frame's observed stars (brightest first; measured in windows: `obs.window_sr`) where
        `prediction` expects them."""
        search = self.begin(obs)
        search.data["prediction"] = prediction
        return self.run(search)

    def match(self, b: np.ndarray, rows: np.ndarray, R: np.ndarray, P: np.ndarray,
              sigma_rad: float) -> tuple[dict[int, int], int]:
        """Observed index -> catalog row (of the field rows): nearest neighbours within the bound of
        prediction (R, P), one-to-one; an observed star with two catalog stars within its bound is left
        out. Also returns how many were left out so (ambiguous, or their catalog star taken by a closer one)."""
        if len(rows) == 0 or len(b) == 0:
            return {}, 0
        radii = match_radii(b, P, sigma_rad, RADIUS_SIGMAS * sigma_rad)
        qi, rj, n_left = nearest_one_to_one(b, self.catalog.xyz[rows] @ R.T, radii)
        return dict(zip(qi.tolist(), rows[rj].tolist())), n_left

    def hypotheses(self, search: Search):
        pred: Prediction = search.data["prediction"]
        b, sigma = search.V, search.sigma
        matches, n_left = self.match(b, pred.rows, pred.R, pred.P, sigma)
        on_prediction = dict(matches)  # within the prediction's own bound: what the prediction test counts
        if len(matches) >= 2 and (n_left or len(matches) < len(b)):
            # some stars were left out at the prediction's bound: refine the attitude with the matches,
            # then match again with the tighter bound of that estimate
            idx = np.array(sorted(matches))
            r = self.catalog.xyz[[matches[i] for i in idx]]
            R_est, P_est = wahba(b[idx], r, sigma)
            resid = np.linalg.norm(cross(b[idx], r @ R_est.T), axis=1)
            if np.all(resid < RADIUS_SIGMAS * sigma * 3):
                matches, _ = self.match(b, pred.rows, R_est, P_est, sigma)
        search.steps.append(LazyStep("match", f"{len(matches)} of {len(b)} stars on their predicted places "
                                              f"({pred.how})", observed=sorted(matches),
                                     catalog_of=partial(_rows_in_order, dict(matches)),
                                     numbers={"matched": len(matches), "left_out": n_left}))
        search.stats["matched"] = len(matches)
        lost = f"{len(matches)} of {len(b)} stars matched the prediction ({pred.how}); tracking needs {self.min_matches}"
        if len(b) == 0:
            search.reasons.append(lost)
            return
        if len(matches) >= self.min_matches:
            idx = np.array(sorted(matches))
            order = idx[np.argsort(-np.asarray(search.obs.brightness)[idx], kind="stable")]
            ver = None
            for t in range(self.tries):
                # three well-spread tracked matches (the next try: three of the rest); every other star tests them
                pool = order[t * HYPOTHESIS_STARS:]
                k = min(HYPOTHESIS_STARS, len(b) - 1, len(pool))
                if k < 2:
                    break
                hyp = spread_subset(b, pool, k)
                ver = yield Hypothesis({int(i): matches[int(i)] for i in hyp}, numbers={"try": t + 1},
                                       on_accept=partial(_verified_by, search, "hypothesis"))
            lost = "verification refused the tracked matches: " + (ver.reason if ver else "no hypothesis")
        # the prediction itself: every detected star tests it
        ver = yield Hypothesis(on_prediction, prediction=pred, on_accept=partial(_verified_by, search, "prediction"))
        search.reasons.append(f"{lost}; {ver.reason}")


def _verified_by(search: Search, how: str, _ver) -> None:
    search.stats["verified_by"] = how


def _rows_in_order(matches: dict[int, int]) -> list[int]:
    return [int(r) for _, r in sorted(matches.items())]
