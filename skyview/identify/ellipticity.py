"""The ellipticity pivot-star method (Sun, Qi, Jin & Wang 2017, Optik).

Guide catalog (section 3.1). Stars brighter than 6.0 (the paper: Mv from SAO; here Hipparcos Hp),
without double stars, then without every star that has another remaining star closer than 0.2 deg
(both stars of the pair go). The paper's catalog has N = 3,974 stars. "Double stars" are read as
Hipparcos entries with more than one resolved component (FLAG_MULTIPLE): N = 3,865 (-2.7 %). The
Hipparcos duplicity and variability-annex flags as well (drop_flags = FLAG_DOUBLE | FLAG_VARIABLE)
would leave 2,994 (-25 %): the variability annex lists 0.01-mag micro-variables that no SAO-based
"changing stars" list holds, so the paper's catalog cannot have dropped them. The identifier is handed the
scenario's catalog (every star the camera sees); the guide catalog is a subset of its rows, and
everything the method reports (matches, steps, groups) is mapped back to rows of the catalog it was
given. Verification reprojects that given catalog: the image holds all of its stars, not only the
guide stars, so a star the guide catalog dropped (a double, a variable) still counts as agreement.

Pattern (section 3.1, Table 1). Every guide star is a pivot. Its adjacent stars are the 3 nearest
guide stars no closer than theta_min = 1 deg, ranked by their angle from the pivot. The 3 x 4 matrix
A = [v_pivot v_1 v_2 v_3] of their unit vectors has three singular values sigma1 >= sigma2 >= sigma3
(sigma1 is always close to 2 and carries no information); the ellipticity is eps = sigma3 / sigma2
(eq. 1). The pattern of the pivot is (eps, theta_p1, theta_p2, theta_p3), the ellipticity and the
three pivot-adjacent angles, stored N x 4 with the 4 stars of each pattern, sorted by eps. The
database does not depend on the camera or the noise; it is built vectorised (one cKDTree k-nearest
query for all pivots, one stacked SVD) and cached (`skyview.identify.database`).

Recognition (section 3.2, Fig. 4). The pivot is the observed star nearest the boresight, no farther
than 4 deg from it (the paper's "critical value, for example 4 deg"); its 3 nearest observed stars
no closer than theta_min are its adjacent stars. eps and the three angles of the observed pattern
are matched with the database: |eps - eps_k| <= 0.001 (an eps window found by binary search, the
paper's "matching range is narrowed down by the ellipticity") and |theta_pi - theta_pki| <= 0.02 deg
for i = 1, 2, 3. The attitude follows from the left singular vectors (Juang, Kim & Junkins 2004):
with W = R V (W observed, V catalog), W = P_w S Q_w^T and V = P_v S Q_v^T give P_w = R P_v D and
Q_w = Q_v D for a diagonal sign matrix D, so R = P_w D P_v^T with D_ii = sign(q_w,i . q_v,i). The
paper writes observed vectors as [-x, -y, f] in its focal-plane frame; skyview's observed vectors are
already camera-frame unit vectors in the OpenCV convention, so this R is skyview's attitude
(v_cam = R v_icrs) as it stands. Every candidate within the thresholds then goes to the shared
verification (`skyview.identify.verify`), and only a verified candidate is an identification.

The paper's camera sees its guide catalog. A real one (and skyview's simulator) sees every star
brighter than 6.0: with Hipparcos, 4,559 stars, of which the guide catalog keeps 3,865. The others
are unknown to the database, and in many frames the pivot or one of its 3 nearest observed stars is
such a star. Vector level, 300 random attitudes of sun20's camera (seed 1, 10 urad,
`skyview experiment measure`-style run, docs/methods.md): 58.7 % identified with this
catalog, 25.3 % with the 2,994-star catalog (duplicity and variability flags too), 93.3 % with
drop_flags=0 (every star; not the paper's). The options below bring it to ~100 %, never wrongly.

What the paper does not say, and what we do. (a) When the pivot has fewer than 3 adjacent stars in
the image, the paper's Table 3 counts such "first selected pivot stars" among its successes, so it
took another pivot: we take the next observed star nearest the boresight (within 4 deg). (b) When
the first pattern finds no candidate, or no candidate passes verification, the paper stops: the
frame is not identified (the option next_pivot tries the next pivot instead). (c) "More than 3
adjacent stars can be chosen (e.g., 4-5 adjacent stars)" for robustness to fake stars: with
n_adjacent = k > 3 the k nearest observed adjacent stars are taken and their 3-subsets are matched
in order ((1,2,3), (1,2,4), ...), so up to k - 3 stars that are not the database's neighbours (a
fake star, a star the guide catalog dropped) are tolerated. The database stays N x 4. With one
false star within half the FOV of the boresight (guide-star sky, 10 urad) the paper's method
identifies 59 % of random attitudes, 82 % with 4 or 5 adjacent stars.

Improvements (options, off by default; `IMPROVED_PARAMS` turns them on, with n_adjacent = 8):
- next_pivot: on failure take the next pivot nearest the boresight (up to max_pivots = 30), and
  pivot_radius_deg = 8 instead of 4: with the paper's 4 deg some boresights of a full-sky grid have no
  guide star near enough (3.1 % with the former 2,994-star guide catalog), and the paper still
  reports 100 %, so its 4 deg cannot have been a hard limit;
- adaptive_thresholds: the thresholds follow the measurement noise sigma instead of the paper's fixed
  0.001 and 0.02 deg: the angle threshold is beta sqrt(2) sigma, and the eps threshold is beta times
  the first-order standard deviation of the observed eps (d sigma_k = u_k^T dA v_k for each
  singular triplet, so d eps = (d sigma3 - eps d sigma2) / sigma2). The paper's 0.001 holds the true
  pattern only for sigma of ~10 microradians (measured: 99.97 % of the guide stars at 10 urad, 88 %
  at 35 urad, 54 % at 82 urad); the angle threshold of 0.02 deg holds up to ~80 urad;
- theta_min_slack: observed stars down to theta_min minus the angle threshold count as adjacent
  (a neighbour at 1.005 deg in the catalog may be measured at 0.995 deg); with n_adjacent > 3 an
  extra star is then harmless;
- resolve_ties: two adjacent stars whose angles from the pivot differ by less than the threshold can
  swap ranks between the image and the catalog; the assignment of such stars is the permutation
  (within the thresholds) with the smallest attitude residual, instead of the rank order.

Many frames (a coverage sweep's task): `identify_batch` finds every frame's first hypothesis as arrays
(`skyview.identify.ellipticity_batch`: the same hypothesis the walk below yields first) and verifies
it; a frame it verifies is identified as `identify` would (without the steps), any other is walked by
`identify`'s template, its first verification the one already made.

Images. A 20 deg field at Hp 6 holds a median of ~39 stars, over 100 in the Milky Way. The MethodSolver
hands the identifier only its max_stars = 40 brightest centroids (its default); the faint stars it
drops are adjacent stars of the patterns. On sun20 (300 attitudes) the improved variant identifies
95 % with max_stars = 40 and 100 % with max_stars = 200; the paper's variant 17 % and 25 %.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from functools import partial
from itertools import combinations, permutations

import numpy as np

from skyview.core.attitude import attitude_error_arcsec, svd_attitude
from skyview.core.camera import Camera
from skyview.core.catalog import FLAG_MULTIPLE, GuideCatalog, chord, close_pairs
from skyview.core.errors import BadInput
from skyview.identify import database
from skyview.identify.base import INCONCLUSIVE, Hypothesis, Identifier, Search, Step
from skyview.identify.ellipticity_batch import NoHypothesis, first_hypotheses, pattern_lookup
from skyview.identify.layers import Attitudes, Hypotheses
from skyview.identify.params import MethodParams, positive
from skyview.identify.steps import LazyStep
from skyview.identify.verify import angular_distance

# the paper's parameters (section 3)
MAG_LIMIT = 6.0  # guide stars brighter than 6.0
CLOSE_PAIR_DEG = 0.2  # "too close stars less 0.2 deg are discarded"
THETA_MIN_DEG = 1.0  # minimum pivot-adjacent angle theta_min
EPS_THRESHOLD = 0.001  # ellipticity threshold
ANGLE_THRESHOLD_DEG = 0.02  # angular-separation threshold
PIVOT_RADIUS_DEG = 4.0  # the pivot is no farther than this from the boresight
N_ADJACENT = 3  # adjacent stars per pattern (the paper's option for fake stars: 4-5 in the image)
# "double stars, changing stars ... are discarded": Hipparcos entries with resolved components (3,865 stars
# at Hp <= 6.0 against the paper's 3,974; with the duplicity and variability flags too: 2,994)
DROP_FLAGS = FLAG_MULTIPLE

CAP = 200  # catalog rows / groups kept in one step
BATCH_FRAMES = 256  # frames whose first hypotheses `identify_batch` finds together
DATABASE_VERSION = 2


# ---------------------------------------------------------------------- guide catalog

def guide_rows(catalog: GuideCatalog, mag_limit: float = MAG_LIMIT, close_pair_deg: float = CLOSE_PAIR_DEG,
               drop_flags: int = DROP_FLAGS) -> np.ndarray:
    """Rows of `catalog` in the paper's guide catalog: brighter than mag_limit, no star carrying a bit of
    drop_flags (doubles and variables), and no star with another remaining star closer than
    close_pair_deg (both are dropped).

    The same stars as catalog.brighter_than(m).without_flags(drop_flags).without_close_pairs(radians(d)),
    as row indices of the catalog given.
    """
    keep = (catalog.mag <= mag_limit) & ((catalog.flags & int(drop_flags)) == 0)
    rows = np.flatnonzero(keep)
    if len(rows) > 1 and close_pair_deg > 0:
        pairs = close_pairs(catalog.xyz[rows], float(chord(np.radians(close_pair_deg))))  # (no scipy import)
        drop = np.zeros(len(rows), dtype=bool)
        drop[pairs.ravel()] = True
        rows = rows[~drop]
    return rows.astype(np.int64)


# ---------------------------------------------------------------------- pattern maths

def pattern_features(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ellipticity, pivot-adjacent angles and singular values of patterns.

    vectors: (..., 4, 3) unit vectors, the pivot first. Returns eps (...,), theta (..., 3) radians
    (angle of each adjacent star from the pivot, in the order given) and the singular values
    (..., 3) of the 3 x 4 matrix A = [v_p v_1 v_2 v_3], largest first.
    """
    v = np.asarray(vectors, dtype=np.float64)
    s = np.linalg.svd(np.swapaxes(v, -1, -2), compute_uv=False)
    eps = s[..., 2] / s[..., 1]
    theta = angular_distance(v[..., 1:, :], v[..., :1, :])
    return eps, theta, s


def ellipticity(vectors: np.ndarray) -> float | np.ndarray:
    """eps = sigma3 / sigma2 of the 3 x 4 matrix of (..., 4, 3) unit vectors (eq. 1)."""
    return pattern_features(vectors)[0]


def eps_sigma(vectors: np.ndarray, sigma_rad: float) -> float:
    """First-order standard deviation of eps for a pattern whose 4 directions each carry an isotropic
    tangent-plane error of sigma_rad per axis.

    d sigma_k = u_k^T dA v_k (u_k, v_k the left and right singular vectors), so
    d eps = sum_j g_j . dw_j / sigma2 with g_j = v3[j] u3 - eps v2[j] u2.
    """
    W = np.asarray(vectors, dtype=np.float64).T  # 3 x 4
    U, s, Vt = np.linalg.svd(W, full_matrices=False)
    eps = s[2] / s[1]
    g = np.outer(U[:, 2], Vt[2]) - eps * np.outer(U[:, 1], Vt[1])  # 3 x 4, column j = g_j
    gt = g - W * np.sum(g * W, axis=0)  # tangent-plane part of each g_j
    return float(sigma_rad * np.sqrt(np.sum(gt * gt)) / s[1])


def singular_vector_attitude(observed: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Attitude from the left singular vectors (Juang, Kim & Junkins 2004), as the paper does.

    observed: (4, 3) camera-frame unit vectors, reference: (4, 3) ICRS unit vectors of the same stars
    in the same order. W = R V with W = P_w S Q_w^T, V = P_v S Q_v^T gives R = P_w D P_v^T, D the
    signs of the dot products of corresponding right singular vectors. Returns R (v_cam = R v_icrs).
    """
    Pw, _, Qwt = np.linalg.svd(np.asarray(observed, dtype=np.float64).T, full_matrices=False)
    Pv, _, Qvt = np.linalg.svd(np.asarray(reference, dtype=np.float64).T, full_matrices=False)
    d = np.where(np.sum(Qwt * Qvt, axis=1) < 0.0, -1.0, 1.0)
    return (Pw * d) @ Pv.T


def nearest_adjacent(xyz: np.ndarray, theta_min_rad: float, k: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """For every star, its k nearest stars no closer than theta_min_rad (bulk cKDTree query).

    Returns (neighbours (N, k) int64, angles (N, k) radians), nearest first; -1 / inf where the
    catalog has fewer than k such stars.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    nb = -np.ones((n, k), dtype=np.int64)
    ang = np.full((n, k), np.inf)
    if n == 0:
        return nb, ang
    from scipy.spatial import cKDTree  # (the database's build only: a solve or a sweep loads it from the cache)

    tree = cKDTree(xyz)
    todo = np.arange(n)
    kq = min(n, k + 16)
    while len(todo):
        d, j = tree.query(xyz[todo], k=kq)
        d, j = d.reshape(len(todo), kq), j.reshape(len(todo), kq)
        a = 2.0 * np.arcsin(np.clip(d / 2.0, 0.0, 1.0))
        ok = (a >= theta_min_rad) & (j != todo[:, None]) & (j < n)
        done = (ok.sum(axis=1) >= k) | (kq >= n)
        pos = np.argsort(~ok, axis=1, kind="stable")[:, :k]
        got_ok = np.take_along_axis(ok, pos, axis=1)
        rows = todo[done]
        nb[rows] = np.where(got_ok[done], np.take_along_axis(j, pos, axis=1)[done], -1)
        ang[rows] = np.where(got_ok[done], np.take_along_axis(a, pos, axis=1)[done], np.inf)
        todo = todo[~done]
        kq = min(n, 2 * kq)
    return nb, ang


def build_ellipticity_database(guide: GuideCatalog, theta_min_rad: float) -> dict[str, np.ndarray]:
    """The N x 4 pattern table: (eps, theta_p1, theta_p2, theta_p3) of every guide star with 3 adjacent
    stars, with its stars (pivot, adjacent 1, 2, 3) as guide rows, sorted by eps."""
    nb, ang = nearest_adjacent(guide.xyz, theta_min_rad, 3)
    pivots = np.flatnonzero(np.all(nb >= 0, axis=1))
    stars = np.concatenate([pivots[:, None], nb[pivots]], axis=1)
    eps, theta, _ = pattern_features(guide.xyz[stars])
    order = np.lexsort((pivots, eps))
    return {"eps": eps[order], "theta": theta[order], "stars": stars[order].astype(np.int32)}


# ---------------------------------------------------------------------- the method

@dataclass(frozen=True)
class EllipticityParams(MethodParams):
    """The ellipticity method's parameters (the paper's section 3; the module docstring explains each)."""

    mag_limit: float = MAG_LIMIT
    close_pair_deg: float = CLOSE_PAIR_DEG
    drop_flags: int = DROP_FLAGS
    theta_min_deg: float = THETA_MIN_DEG
    eps_threshold: float = EPS_THRESHOLD
    angle_threshold_deg: float = ANGLE_THRESHOLD_DEG
    pivot_radius_deg: float = PIVOT_RADIUS_DEG
    n_adjacent: int = N_ADJACENT
    next_pivot: bool = False
    max_pivots: int = 30
    adaptive_thresholds: bool = False
    beta: float = 3.0
    theta_min_slack: bool = False
    resolve_ties: bool = False
    max_candidates: int = 32

    def __post_init__(self):
        for nm in ("theta_min_deg", "eps_threshold", "angle_threshold_deg", "pivot_radius_deg", "beta",
                   "radius_sigmas"):
            positive(nm, getattr(self, nm))
        positive("close_pair_deg", self.close_pair_deg, allow_zero=True)
        if int(self.drop_flags) < 0:
            raise BadInput(f"drop_flags must be a combination of FLAG_* bits, not {self.drop_flags!r}")
        if not np.isfinite(self.mag_limit):
            raise BadInput(f"mag_limit must be a number, not {self.mag_limit!r}")
        if int(self.n_adjacent) < 3:
            raise BadInput("n_adjacent must be at least 3 (a pattern is the pivot and 3 adjacent stars)")
        if int(self.max_pivots) < 1 or int(self.max_candidates) < 1:
            raise BadInput("max_pivots and max_candidates must be at least 1")
        super().__post_init__()


PAPER = EllipticityParams()
IMPROVED = replace(PAPER, n_adjacent=8, next_pivot=True, pivot_radius_deg=8.0, adaptive_thresholds=True,
                   theta_min_slack=True, resolve_ties=True)
IMPROVED_PARAMS = IMPROVED.changed()


class EllipticityMethod(Identifier):
    """Sun, Qi, Jin & Wang's ellipticity pivot-star method, ending in the shared verification."""

    name = "ellipticity"
    paper_scenario = "sun20"
    title = "the ellipticity method"
    Params = EllipticityParams
    min_stars = 4
    improved_params = IMPROVED_PARAMS

    def __init__(self, catalog: GuideCatalog, camera: Camera, sigma_rad: float, **params):
        p = self.configure(catalog, camera, sigma_rad, params)
        mag_limit, close_pair_deg, drop_flags, theta_min_deg = p.mag_limit, p.close_pair_deg, p.drop_flags, \
            p.theta_min_deg
        self.theta_min = float(np.radians(p.theta_min_deg))
        self.eps_threshold = float(p.eps_threshold)
        self.angle_threshold = float(np.radians(p.angle_threshold_deg))
        self.pivot_radius = float(np.radians(p.pivot_radius_deg))
        self.n_adjacent = int(p.n_adjacent)
        self.max_pivots = int(p.max_pivots)
        self.beta = float(p.beta)
        self.max_candidates = int(p.max_candidates)
        self.radius_sigmas = float(p.radius_sigmas)

        t0 = time.perf_counter()
        self.guide_rows = guide_rows(catalog, mag_limit, close_pair_deg, drop_flags)
        note = (f"ellipticity guide: mag<={mag_limit:g}, without_flags={int(drop_flags)}, "
                f"close_pairs<{close_pair_deg:g}deg:none")
        self.guide = catalog.select(self.guide_rows, note)
        guide_s = time.perf_counter() - t0
        if len(self.guide) < 4:
            raise BadInput(f"the guide catalog has {len(self.guide)} stars: a pattern needs 4")
        params = {"theta_min_deg": float(theta_min_deg), "version": DATABASE_VERSION}
        # the patterns depend on the guide stars only, not on the camera or the noise
        self.database_key = database.make_key(self.name, params, self.guide, None)
        arrays, info = database.load_or_build(
            self.database_key, lambda: build_ellipticity_database(self.guide, self.theta_min))
        self.eps = arrays["eps"]
        self.theta = arrays["theta"]
        self.stars_guide = arrays["stars"].astype(np.int64)
        self.stars = self.guide_rows[self.stars_guide]  # the same patterns as rows of the given catalog
        info.update(patterns=len(self.eps), guide_stars=len(self.guide), catalog_stars=len(catalog),
                    guide_s=guide_s, theta_min_deg=float(theta_min_deg),
                    theta_p3_max_deg=float(np.degrees(self.theta[:, 2].max())) if len(self.eps) else None,
                    feature_bytes=int(self.eps.nbytes + self.theta.nbytes),
                    star_bytes=int(arrays["stars"].nbytes))
        self.database_info = info

    @property
    def n_patterns(self) -> int:
        return len(self.eps)

    # ------------------------------------------------------------------ identify (the template's parts)
    def too_few(self, search: Search) -> str:
        search.stats = {"pivots": 0, "patterns": 0, "candidates": [], "verifications": 0,
                        "first_pivot_adjacent": None, "first_chain": {"outcome": "none", "matches": {}}}
        if search.n < self.min_stars:
            return f"the ellipticity method needs a pivot and 3 adjacent stars, the frame has {search.n}"
        return ""

    def failure_reason(self, search: Search) -> str:
        reasons = search.reasons or ["no hypothesis to verify"]
        return reasons[-1] if len(reasons) == 1 else f"{len(reasons)} failures, the last: {reasons[-1]}"

    def hypotheses(self, search: Search):
        """Pivots nearest the boresight first; each pivot's patterns (`_pivot`)."""
        V, sigma, steps, stats, reasons = search.V, search.sigma, search.steps, search.stats, search.reasons
        # pivots: observed stars by angle from the boresight [0 0 1], within the critical value
        offset = angular_distance(V, np.array([0.0, 0.0, 1.0]))
        order = np.argsort(offset, kind="stable")
        pivots = order[offset[order] <= self.pivot_radius]
        if len(pivots) == 0:
            steps.append(Step("pivot", f"no observed star within {np.degrees(self.pivot_radius):g} deg of the "
                                       f"boresight (nearest: {order[0]}, {np.degrees(offset[order[0]]):.3f} deg)",
                              observed=[int(order[0])],
                              numbers={"offset_deg": float(np.degrees(offset[order[0]])),
                                       "pivot_radius_deg": float(np.degrees(self.pivot_radius))}))
            reasons.append(f"no observed star within {np.degrees(self.pivot_radius):g} deg of the boresight")
            return

        tol_theta = self.beta * np.sqrt(2.0) * sigma if self.adaptive_thresholds else self.angle_threshold
        theta_lo = self.theta_min - (tol_theta if self.theta_min_slack else 0.0)
        tried = 0
        for rank, p in enumerate(pivots.tolist()):
            if tried >= self.max_pivots:
                break
            ang = angular_distance(V, V[p])
            near = np.flatnonzero(ang >= theta_lo)
            adj = near[np.argsort(ang[near], kind="stable")][:self.n_adjacent]
            steps.append(Step("pivot", f"pivot: observed star {p}, {np.degrees(offset[p]):.3f} deg from the boresight"
                                       + ("" if rank == 0 else f" (star {rank + 1} by distance)"),
                              observed=[p], numbers={"offset_deg": float(np.degrees(offset[p])), "rank": rank,
                                                     "pivot_radius_deg": float(np.degrees(self.pivot_radius))}))
            if stats["first_pivot_adjacent"] is None:
                stats["first_pivot_adjacent"] = int(len(adj))
            steps.append(Step("adjacent", f"{len(adj)} adjacent star(s) no closer than {np.degrees(theta_lo):.3f} deg: "
                              + ", ".join(f"{int(a)} ({np.degrees(ang[a]):.3f} deg)" for a in adj),
                              observed=[p] + adj.tolist(),
                              numbers={f"theta_{k + 1}_deg": float(np.degrees(ang[a])) for k, a in enumerate(adj)}
                              | {"adjacent": len(adj), "theta_min_deg": float(np.degrees(self.theta_min))}))
            if len(adj) < 3:
                reasons.append(f"pivot {p} has {len(adj)} adjacent star(s) in the image")
                continue  # the paper counts such first pivots among its successes: it took another
            tried += 1
            stats["pivots"] = tried
            yield from self._pivot(search, p, adj, tol_theta)
            if not self.next_pivot:
                break
        if tried == 0:
            reasons.append(f"no pivot within {np.degrees(self.pivot_radius):g} deg of the boresight has 3 adjacent "
                           "stars in the image")

    def _pivot(self, search: Search, p: int, adj: np.ndarray, tol_theta: float):
        """All patterns of one pivot (the 3-subsets of its adjacent stars, in order): yields the
        hypotheses of the candidates, best first."""
        V, sigma, steps, stats, reasons = search.V, search.sigma, search.steps, search.stats, search.reasons
        subsets = np.array(list(combinations(range(len(adj)), 3)), dtype=np.int64)
        idx = np.concatenate([np.full((len(subsets), 1), p), adj[subsets]], axis=1)  # (m, 4) observed
        W = V[idx]  # (m, 4, 3)
        # the features, eps windows and angle test of every pattern at once
        eps, theta, s, tol_eps, lo, hi, hit_pos, hit_seg = pattern_lookup(self, W, sigma,
                                                                            np.full(len(idx), tol_theta))
        bounds = np.searchsorted(hit_seg, np.arange(len(idx) + 1))
        for m in range(len(idx)):
            o = idx[m].tolist()
            th = theta[m]
            window = self.stars[lo[m]:hi[m]]
            within = hit_pos[bounds[m]:bounds[m + 1]]
            stats["patterns"] += 1
            stats["candidates"].append(int(len(within)))
            # the steps are read by the viewer and the recordings, not by a sweep: made when first read
            steps.append(LazyStep("pattern", observed=o, note_of=partial(_pattern_note, p, o, float(eps[m]), th),
                                  numbers_of=partial(_pattern_numbers, float(eps[m]), s[m], th)))
            steps.append(LazyStep("lookup", observed=o,
                                  note_of=partial(_lookup_note, len(window), float(tol_eps[m]), len(within), tol_theta),
                                  catalog_of=partial(_distinct_at, self.stars, within),
                                  groups_of=partial(_groups, window),
                                  numbers_of=partial(_lookup_numbers, float(eps[m]), float(tol_eps[m]), tol_theta,
                                                     len(window), len(within)),
                                  layers_of=partial(_lookup_layers, o, self.stars, within)))
            if stats["first_chain"]["outcome"] == "none":
                stats["first_chain"] = (
                    {"outcome": "unique", "matches": dict(zip(o, self.stars[within[0]].tolist()))} if len(within) == 1
                    else {"outcome": "empty" if len(within) == 0 else "ambiguous", "matches": {}})
            if len(within) == 0:
                reasons.append(f"no pattern matches pivot {p} with adjacent {o[1:]}")
                continue
            # best candidates first (normalised distance in the four features)
            cost = ((self.eps[within] - eps[m]) / tol_eps[m]) ** 2 + np.sum(
                ((self.theta[within] - th) / tol_theta) ** 2, axis=1)
            for k in within[np.argsort(cost, kind="stable")][:self.max_candidates].tolist():
                rows = self._assign(W[m], k, th, tol_theta, sigma)
                R_sv = singular_vector_attitude(W[m], self.catalog.xyz[rows])

                def compare(ver, R_sv=R_sv):  # the paper's attitude beside the verified one
                    if ver.R is None:
                        return {}, {}
                    return {"singular_vector_vs_verified_arcsec": attitude_error_arcsec(R_sv, ver.R)["total"]}, {}

                def record(ver, o=o, rows=rows, e=float(eps[m]), R_sv=R_sv):
                    stats["pattern"] = {"pivot": p, "adjacent": o[1:], "catalog": rows.tolist(), "eps": e}
                    stats["R_singular_vectors"] = R_sv

                stats["verifications"] += 1  # every verification counts in the Bonferroni factor
                ver = yield Hypothesis(dict(zip(o, rows.tolist())), groups=[tuple(rows.tolist())], judge=compare,
                                       layers=(Attitudes.of(R_sv, name="singular-vector attitude"),), on_accept=record)
                reasons.append(f"candidate {rows.tolist()} failed verification: {ver.reason}")

    def identify_batch(self, observations):
        """Identify many frames, yielding each frame's identification in turn: each frame's first
        hypothesis found for BATCH_FRAMES frames at a time as arrays (`skyview.identify.ellipticity_batch`)
        and verified. A frame whose first hypothesis is verified is identified as `identify` identifies it
        (the same status, matches, attitude and verification) without the steps, and its stats hold only
        stars, verifications (1), batched (True) and time_s (not the walk's pivots, patterns, candidates,
        first_pivot_adjacent, first_chain); so is a frame whose walk would find no candidate at all
        (inconclusive, the walk's reason, verifications 0). Every other frame is identified by the walk
        (`run`: its steps and stats recorded, the first hypothesis' verification the one made here).
        stats["time_s"]: the frame's own time plus its share of the batch. A subclass with its own walk
        identifies frame by frame."""
        cls = type(self)
        if cls.hypotheses is not EllipticityMethod.hypotheses or cls._pivot is not EllipticityMethod._pivot:
            yield from super().identify_batch(observations)
            return
        batch = []
        for obs in observations:
            batch.append(obs)
            if len(batch) == BATCH_FRAMES:  # (the batch's arrays bounded: frames x stars)
                yield from self._identify_together(batch)
                batch = []
        if batch:
            yield from self._identify_together(batch)

    def _identify_together(self, observations: list):
        t0 = time.perf_counter()
        searches = [self.begin(obs) for obs in observations]
        firsts = first_hypotheses(self, [s.V for s in searches], np.array([s.sigma for s in searches]))
        shared = (time.perf_counter() - t0) / max(len(searches), 1)
        for search, first in zip(searches, firsts):
            t1 = time.perf_counter()
            result = search.result
            if isinstance(first, NoHypothesis):  # the walk would find no candidate: its reason, no steps
                result.status, result.reason = INCONCLUSIVE, first.reason
                result.stats = {"stars": search.n, "verifications": 0, "batched": True,
                                "time_s": shared + time.perf_counter() - t1}
                yield result
                continue
            if first is not None:
                hyp = Hypothesis(first)
                ver = self.verification(search, hyp)
                if ver.passed:
                    result.accept(ver)
                    result.verification = ver.to_dict()
                    result.stats = {"stars": search.n, "verifications": 1, "batched": True,
                                    "time_s": shared + time.perf_counter() - t1}
                    yield result
                    continue
                # the walk from the start, its first hypothesis' verification this one (not made twice)
                search = self.begin(search.obs)
                search.first_verified = (hyp.matches, ver)
            result = self.run(search)
            result.stats["time_s"] = shared + time.perf_counter() - t1
            yield result

    def _assign(self, W: np.ndarray, k: int, theta: np.ndarray, tol_theta: float, sigma: float) -> np.ndarray:
        """Catalog rows (pivot, adjacent 1..3) for the observed pattern W and database pattern k.

        The paper assigns by rank. With resolve_ties, adjacent stars whose angles are too close to
        rank reliably are assigned by the permutation (within the threshold) that fits best."""
        rows = self.stars[k]
        if not self.resolve_ties:
            return rows
        cat_theta = self.theta[k]
        best, best_loss = rows, None
        for perm in permutations(range(3)):
            if not np.all(np.abs(theta - cat_theta[list(perm)]) <= tol_theta):
                continue
            r = np.concatenate([rows[:1], rows[1:][list(perm)]])
            loss = svd_attitude(W, self.catalog.xyz[r], sigma).loss
            if best_loss is None or loss < best_loss:
                best, best_loss = r, loss
        return best


def _pattern_note(p: int, o: list[int], eps: float, theta: np.ndarray) -> str:
    return (f"pattern of pivot {p} with adjacent {o[1:]}: eps = {eps:.5f}, theta = "
            + ", ".join(f"{np.degrees(t):.3f}" for t in theta) + " deg")


def _pattern_numbers(eps: float, s: np.ndarray, theta: np.ndarray) -> dict[str, float]:
    return {"eps": eps, "sigma1": float(s[0]), "sigma2": float(s[1]), "sigma3": float(s[2]),
            "theta_p1_deg": float(np.degrees(theta[0])), "theta_p2_deg": float(np.degrees(theta[1])),
            "theta_p3_deg": float(np.degrees(theta[2]))}


def _lookup_note(n_window: int, tol_eps: float, n_within: int, tol_theta: float) -> str:
    return (f"{n_window} pattern(s) with eps within +-{tol_eps:.5f}, "
            f"{n_within} of them with all angles within +-{np.degrees(tol_theta):.4f} deg")


def _lookup_numbers(eps: float, tol_eps: float, tol_theta: float, n_window: int, n_within: int) -> dict[str, float]:
    return {"eps": eps, "eps_threshold": tol_eps, "angle_threshold_deg": float(np.degrees(tol_theta)),
            "eps_window": n_window, "candidates": n_within}


def _distinct_at(stars: np.ndarray, within: np.ndarray) -> list[int]:
    return _distinct(stars[within])


def _lookup_layers(o: list[int], stars: np.ndarray, within: np.ndarray) -> tuple:
    return (Hypotheses.sample(o, stars[within]),)


def _distinct(stars: np.ndarray) -> list[int]:
    return sorted(set(np.asarray(stars).ravel().tolist()))[:CAP] if np.size(stars) else []


def _groups(stars: np.ndarray) -> list[tuple[int, ...]]:
    return [tuple(g) for g in np.asarray(stars)[:CAP].tolist()]
