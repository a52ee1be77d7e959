"""The verification every identification method ends in.

Long (~1,000 lines) because it is one procedure with its statistics (the calibrated Poisson-binomial and
the tetra3 binomial), the per-star radii, the blend and crowding checks, and the exact fast paths it
takes on small frames (each tested against its plain form in tests/test_verify.py).

Given a hypothesis (observed index -> catalog row):

1. estimate the attitude R from the hypothesis alone (Markley's SVD method), with its covariance P;
2. reject it if any hypothesis star lies farther than the match radius r from its catalog star
   (a hypothesis that does not even fit itself);
3. reproject the catalog with R and count the observed stars that are NOT in the hypothesis and land
   within their match radius r_i of a catalog star (one-to-one, nearest first, catalog stars of the
   hypothesis excluded);
4. compute P(false), the probability that at least that many agreements happen by chance, and accept
   when P(false) < threshold;
5. on success, extend the matches to every observed star that agrees, re-estimate R with all of them
   (twice, re-matching with the better attitude) and return the attitude, its covariance and the
   matches. A star with two catalog stars within its radius (an unresolved close pair such as
   HIP 88817 / 88818, 14" apart), or a catalog star with two observed stars within it (a false star
   next to a real one) is never reported: its identity cannot be told.

Match radius. r = RADIUS_SIGMAS * sigma with RADIUS_SIGMAS = 3 sqrt(2) (the same beta sigma_p,
beta = 3, as the angle bound of Cole & Crassidis). The distance between an observed star and its
reprojected catalog star has two tangent-plane components of standard deviation sigma, so its square
over sigma^2 is chi-square with 2 degrees of freedom and P(d > r) = exp(-r^2 / (2 sigma^2)) = exp(-9)
= 1.2e-4: a true star is missed about once in 8,000. At 87 microradians r = 369 microradians = 76"
(2.7 pixels for 8 deg over 1024 pixels). The attitude of a hypothesis is itself uncertain, most of
all in roll when its stars are close together, and the error of a predicted position grows with the
distance from the hypothesis stars. So each tested star gets its own radius
r_i = r sqrt(1 + lambda_i / sigma^2), lambda_i the largest eigenvalue of [b_i]x P [b_i]x^T (the
predicted position's covariance), capped at MAX_RADIUS_RAD. Without this a hypothesis made of three
stars 2' apart in the Pleiades "verified" with two cluster stars that happened to land near others.

Statistic "calibrated" (default; docs/methods.md "Shared verification"). A random (unrelated)
observed direction lands within r_i of a catalog star with probability p_i = rho_i pi r_i^2: the
catalog density times the match area. rho_i is the frame's density n_frame / Omega_frame (n_frame
counts the stars on the sensor grown by r, Omega_frame is the sensor's solid angle: slightly
conservative), or the local density within LOCAL_RADIUS_RAD = 1 deg of the tested star where that
is higher and rests on at least LOCAL_MIN_COUNT = 3 stars (the star it landed on left out): in the
Pleiades a wrong hypothesis maps cluster stars onto cluster stars, at 10-30 times the frame's
average density. The
hypothesis stars were used to make R, so they are no evidence; only the
n_tested other observed stars are tested, and under the null hypothesis (R is wrong) the number
that agree is a sum of independent Bernoulli(p_i) (Poisson-binomial; Binomial(n_tested, p) when the
radii are equal). P(false) = T * P[agreements >= n_agree], where T is the number of hypotheses the
method has verified for this frame so far (Bonferroni). A hypothesis with no other star to test
cannot be verified and is not identified.

Threshold. DEFAULT_THRESHOLD = 1e-3. At mag 6 and 8 deg an image holds about 4-10 catalog stars,
p_i = 1e-4 ... 3e-4 per tested star at sigma = 87 microradians, so ONE agreeing star gives P(false)
of order 1e-4 to 3e-4, two give 1e-8. A threshold of 1e-4 would reject most single-agreement frames,
exactly the sparse (4-6 star) fields that must stay solvable (`skyview experiment measure`: 15-50 %
of all identifications have 1e-4 <= P(false) < 1e-3); 1e-3 accepts them. It bounds the rate of wrong
answers by P(a wrong hypothesis reaches verification) x 1e-3: that first factor is below 0.2 even
with a false star (Cole & Crassidis: 17 % incorrect without verification), so wrong attitudes stay
near 2e-4 at worst, inside the project's 0.1 %.

Speed (the same answers). A frame holds tens of stars on each side, so the nearest catalog stars of
the tested stars (nearest, second nearest, the crowding count) come from one array of distances
(`_nearest_two`, `_count_within`; a k-d tree only beyond BRUTE_PAIRS pairs) instead of building a
k-d tree per round; the catalog stars around the frame are fetched once per verification from the
catalog's sky index (`GuideCatalog.sky`: numpy, no scipy.spatial), a little wider (NEAR_SLACK_RAD)
and as far as the local density of the observed stars reaches, and every refined attitude reuses
them (`NearStars`); the local density counts among those stars (`local_density`, `among`); the radii of
all stars are computed once per estimate. Only the (observed, catalog) pairs within a radius are
measured (all of a small frame's, or those a dot-product prefilter keeps on a larger one:
`_Frame._within`); a frame whose pairs are one-to-one agrees pair for pair, any other is paired in
Python lists (`_Frame.agreeing`); whether a matched catalog star has a neighbour within the blend
radius comes from each star's nearest-neighbour chord, looked up once per catalog (`_has_neighbour`);
the estimate from every match is remembered for the solver's attitude stage (`attitude.remember_svd`).
The hypothesis stars' ambiguity and the crowding count are only counted when two pool stars (two
observed stars) lie close enough for one radius to hold both (`_stars_apart`: the pool stars' remembered
nearest-neighbour chords; `_apart`: one product of the observed rows; the triangle inequality says
nothing else can be ambiguous or crowded); the Poisson-binomial tail runs on
the Python floats of p_tested (the same IEEE operations as numpy's).
Each of these gives the general path's (and the k-d tree's) numbers to the last bit
(tests/test_verify.py and tests/test_catalog.py compare them).

Windowed frames. A tracker measures only windows around the stars it predicts: a star found in a window
of solid angle W_i lands within r_i of the predicted star by accident with p_i = pi r_i^2 / W_i (the
window holds a detection by construction), not the sky's density times the area: `verify(...,
window_sr=...)`.

A predicted attitude as the hypothesis (`verify_prediction`). A tracker's prediction comes from earlier
frames and the motion, not from this frame, so every detected star tests it: P(false) is the same
calibrated statistic of the stars on their predicted places (p_i: the density around the field times
the bound's area), at least `min_stars` of them; the attitude is then estimated from those stars, and
each must fit it within its bound. What keeps lock on frames of two or three stars, where no star is
left to test a hypothesis made of three.

Statistic "tetra3": the classic tetra3 form for comparison: per star p1 = N_nearby (r / FOV)^2
(r as a fraction of the horizontal FOV, no pi), P = BinomCDF(n_obs - (n_matched - 2), n_obs, 1 - p1)
over ALL observed stars and ALL matches (hypothesis included, minus two degrees of freedom), and the
threshold (tetra3's 1e-3) divided by the number of patterns in the method's database.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from skyview.core.attitude import RAD_TO_ARCSEC, remember_svd, svd_attitude
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, chord
from skyview.core.catalog import einsum_c as _einsum
from skyview.core.special import binomial_cdf, binomial_sf
from skyview.identify.steps import LazyStep

_min, _max = np.minimum.reduce, np.maximum.reduce  # what ndarray.min() / .max() call, without their Python wrappers

CALIBRATED = "calibrated"
TETRA3 = "tetra3"
STATISTICS = (CALIBRATED, TETRA3)
RADIUS_SIGMAS = 3.0 * np.sqrt(2.0)
DEFAULT_THRESHOLD = {CALIBRATED: 1e-3, TETRA3: 1e-3}
MAX_RADIUS_RAD = float(np.radians(1.0))  # a prediction worse than this is no evidence at all
LOCAL_RADIUS_RAD = float(np.radians(1.0))  # neighbourhood for the local catalog density
LOCAL_MIN_COUNT = 3  # fewer stars than this in the neighbourhood: too few to estimate a density
# Two catalog stars closer than this on the sensor may be seen as one blended centroid (PSF sigma ~1.1 px;
# the centroider separates bright pairs from ~3.5 px, faint equal pairs not always: HIP 38031/38037, 4.6 px
# apart at 8 deg): the blend's identity is either, so neither is reported.
BLEND_RADIUS_PX = 5.0


BLEND_DELTA_MAG = 2.5  # a companion this much fainter moves a blended centroid by < 10 % of the separation


def resolved_matches(matches: dict[int, int], catalog: GuideCatalog, pixel_scale_rad: float) -> dict[int, int]:
    """The matches (observed index -> row of `catalog`, the FULL guide catalog) without the stars that
    have a companion close enough to blend with them (within BLEND_RADIUS_PX pixels) and bright enough
    to move the centroid (at most BLEND_DELTA_MAG fainter): such a centroid is the pair's, and naming
    one star of it is a guess. A verification at a catalog depth leaves the fainter companions out, so
    every answer reported to a user goes through this. Fewer than two left: the matches unchanged."""
    if not matches:
        return matches
    obs = np.array(sorted(matches))
    rows = np.array([matches[o] for o in obs], dtype=np.int64)
    radius = BLEND_RADIUS_PX * pixel_scale_rad
    lim = float(chord(radius))
    if radius <= BLEND_REACH_RAD:  # the table holds every companion that near
        table = _BLEND.get(catalog)
        if table is None:
            table = _BLEND[catalog] = blend_table(catalog)
        blended = table[rows] <= lim
    else:  # a camera of over 0.4 deg a pixel: the stars near each match, from the k-d tree
        near = catalog.tree.query_ball_point(catalog.xyz[rows], lim)
        blended = np.array([any(k != c and catalog.mag[k] <= catalog.mag[c] + BLEND_DELTA_MAG for k in nb)
                            for c, nb in zip(rows.tolist(), near)], dtype=bool)
    keep = {int(o): int(c) for o, c, b in zip(obs.tolist(), rows.tolist(), blended.tolist()) if not b}
    return keep if len(keep) >= 2 else matches


BLEND_REACH_RAD = math.radians(2.0)
_BLEND: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def blend_table(catalog: GuideCatalog) -> np.ndarray:
    """The chord from every catalog star to its nearest companion that could blend with it (any star
    at most BLEND_DELTA_MAG fainter than it, or brighter), inf where none lies within BLEND_REACH_RAD:
    built once per catalog from the k-d tree's pairs and cached on disk as a database (8 bytes a star:
    0.6 MB for the full catalog), so that `resolved_matches` is one look-up per match."""
    from skyview.identify import database

    def build() -> dict:
        pairs = catalog.tree.query_pairs(float(chord(BLEND_REACH_RAD)), output_type="ndarray")
        i, j = pairs[:, 0], pairs[:, 1]
        d = np.sqrt(squared_chords_rows(catalog.xyz[i], catalog.xyz[j]))
        out = np.full(len(catalog.xyz), np.inf)
        mag = catalog.mag
        for a, b in ((i, j), (j, i)):  # b can blend with a when it is at most BLEND_DELTA_MAG fainter
            ok = mag[b] <= mag[a] + BLEND_DELTA_MAG
            np.minimum.at(out, a[ok], d[ok])
        return {"chord": out}

    key = database.make_key("blend", {"reach_rad": BLEND_REACH_RAD, "delta_mag": BLEND_DELTA_MAG}, catalog, None)
    arrays, _ = database.load_or_build(key, build)
    return np.asarray(arrays["chord"], dtype=np.float64)


def squared_chords_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a_k - b_k|^2 row by row."""
    diff = a - b
    return np.einsum("ij,ij->i", diff, diff)


def local_density(catalog: GuideCatalog, directions_icrs: np.ndarray, leave_out: np.ndarray | None = None,
                  radius_rad: float = LOCAL_RADIUS_RAD, min_count: int = LOCAL_MIN_COUNT,
                  among: np.ndarray | None = None, among_xyz: np.ndarray | None = None) -> np.ndarray:
    """Catalog stars per steradian within radius_rad of each direction, 0 where fewer than min_count.

    leave_out: how many stars to discount per direction (the star it landed on). With fewer than
    min_count stars the count is Poisson noise (0.35 expected within 1 deg at mag 6), not a density.
    among: catalog rows known to hold every star within radius_rad of the directions (the stars
    around a frame: fewer to measure; among_xyz: their directions, where the caller has them). The
    counts are the k-d tree's (`GuideCatalog.ball_counts`).
    """
    d = np.asarray(directions_icrs, dtype=np.float64)
    d = d[None] if d.ndim == 1 else d  # = np.atleast_2d
    if len(d) == 0:
        return np.zeros(0)
    ch, area = _chord_area(float(radius_rad))
    n = catalog.ball_counts(d, ch, among, among_xyz)
    # (float64 counts; a count below min_count is 0, so one below 0 needs no np.maximum first when
    # min_count > 0: the same numbers, +0.0 included)
    n = n.astype(np.float64) if leave_out is None else n - leave_out  # (int64 - float64: float64, exact)
    if leave_out is not None and min_count <= 0:
        n = np.maximum(n, 0.0)
    n[n < min_count] = 0.0
    return n / area


@lru_cache(maxsize=64)
def _chord_area(radius_rad: float) -> tuple[float, float]:
    """The chord of an angle and the solid angle of the cap it spans (numpy's numbers, made once)."""
    return float(chord(radius_rad)), float(2.0 * np.pi * (1.0 - np.cos(radius_rad)))


def match_radius(sigma_rad: float, k: float = RADIUS_SIGMAS) -> float:
    """The match radius r = k sigma (radians)."""
    return float(k * sigma_rad)


def p_single(n_frame: int, frame_solid_angle_sr: float, radius_rad) -> float | np.ndarray:
    """Chance that an unrelated direction lands within r of one of n_frame catalog stars."""
    if isinstance(radius_rad, float):  # one radius: Python floats (verify calls this once a hypothesis)
        return min(1.0, n_frame / frame_solid_angle_sr * math.pi * radius_rad ** 2)
    p = np.minimum(1.0, n_frame / frame_solid_angle_sr * np.pi * np.asarray(radius_rad, dtype=np.float64) ** 2)
    return float(p) if np.ndim(p) == 0 else p


def _per_item(x, n: int) -> np.ndarray:
    """x (one number or n of them) as n float64 values (np.broadcast_to's result, without its overhead)."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        return np.full(n, float(a))
    if a.shape != (n,):
        return np.broadcast_to(a, (n,))
    return a


def poisson_binomial_sf(k: int, ps) -> float:
    """P[sum of independent Bernoulli(p_i) >= k] (exact; no cancellation for tiny tails).

    The distribution is carried only as far as the answer needs: the counts 0 .. k-1 and one state
    for ">= k" (every term a sum of products of probabilities, nothing subtracted), or, when k is
    near n, the same over the misses (P[X >= k] = P[n - X <= n - k]). Small states run in Python
    floats (a frame's tens of stars: no numpy call per star), larger ones in numpy.
    """
    return _sf(k, np.asarray(ps, dtype=np.float64).ravel().tolist())


def _sf(k: int, ps: list[float]) -> float:
    """poisson_binomial_sf of Python floats (1.0 - p is the number numpy's 1.0 - ps gives)."""
    n = len(ps)
    if k <= 0:
        return 1.0
    if k > n:
        return 0.0
    qs = [1.0 - p for p in ps]
    if n - k + 1 < k:  # P[X >= k] = P[misses <= n - k]: the states 0 .. n - k of the misses, summed
        return float(min(1.0, sum(_states(n - k + 1, qs, ps))))
    return float(min(1.0, _states(k, ps, qs, absorb=True)[k]))


def _states(k: int, ps: list[float], qs: list[float], absorb: bool = False):
    """The distribution of a sum of Bernoulli(p_i) (q_i = 1 - p_i given, not recomputed: no
    cancellation when p_i is near 1) over the counts 0 .. k-1, plus with absorb=True a last state
    "k or more" that the mass moving past k-1 joins."""
    if k == 1 and not absorb:  # one state: the product of the q_i, in order (the loop below, unrolled)
        return [math.prod(qs)]
    if k <= 32:
        dist = [1.0] + [0.0] * (k - 1 + absorb)
        for p, q in zip(ps, qs):
            if absorb:
                dist[k] += dist[k - 1] * p
            for j in range(k - 1, 0, -1):
                dist[j] = dist[j] * q + dist[j - 1] * p
            dist[0] *= q
        return dist
    dist = np.zeros(k + absorb)
    dist[0] = 1.0
    for p, q in zip(ps, qs):
        if absorb:
            dist[k] += dist[k - 1] * p
        dist[1:k] = dist[1:k] * q + dist[:k - 1] * p
        dist[0] *= q
    return dist.tolist()


def p_false_calibrated(n_agree: int, n_tested: int, p, n_hypotheses: int = 1) -> float:
    """T * P[at least n_agree of the n_tested stars land on a catalog star by chance], capped at 1.

    p: one probability for every tested star (binomial) or one per star (Poisson-binomial).
    1 when nothing was tested or nothing agreed.
    """
    if n_tested <= 0 or n_agree <= 0:
        return 1.0
    # (a list of one float per star, as verify has p_tested, is used as it is: the same floats)
    ps = p if type(p) is list and len(p) == n_tested else _per_item(p, n_tested).tolist()
    return _p_false_floats(n_agree, ps, n_hypotheses)


def _p_false_floats(n_agree: int, ps: list[float], n_hypotheses: int) -> float:
    """p_false_calibrated of one probability per tested star as Python floats (at least one star
    tested, one agreeing): the comparisons and numbers numpy's arrays give."""
    p0 = ps[0]
    if p0 == p0 and ps.count(p0) == len(ps):  # = np.all(ps == ps[0]) (count: `is` or ==; NaN: never)
        tail = binomial_sf(n_agree, len(ps), p0)  # P[X >= n_agree]
    else:
        tail = _sf(n_agree, ps)
    return float(min(1.0, max(1, n_hypotheses) * tail))


def p_false_tetra3(n_matched: int, n_observed: int, n_nearby: int, radius_fraction: float) -> float:
    """tetra3's mismatch probability: BinomCDF(n_obs - (n_matched - 2), n_obs, 1 - N_nearby r^2)."""
    p1 = min(1.0, n_nearby * radius_fraction ** 2)
    return binomial_cdf(n_observed - (n_matched - 2), n_observed, 1.0 - p1)  # P[X <= k]


def predicted_sigma(vectors: np.ndarray, covariance: np.ndarray, unit: tuple | None = None) -> np.ndarray:
    """Largest standard deviation of the predicted position R r_i caused by the attitude error.

    A small attitude error dphi (camera frame, covariance P) moves a direction b by dphi x b, whose
    covariance is [b]x P [b]x^T; this returns the square root of its largest eigenvalue per star.
    unit: `_unit_rows(vectors)` where the caller has it (a row's numbers do not depend on the others).
    """
    if unit is None:
        b = np.asarray(vectors, dtype=np.float64)
        b = b[None] if b.ndim == 1 else b  # = np.atleast_2d
        if len(b) == 0:
            return np.zeros(0)
        unit = _unit_rows(b)
    n, s2 = unit
    if len(n) == 0:
        return np.zeros(0)
    # In closed form (no batched eigensolver): [b]x P [b]x^T is |b|^2 times P restricted to the plane
    # normal to the unit vector n = b / |b| (turned by 90 degrees in it; its third eigenvalue, along n,
    # is 0). That 2x2 restriction has trace tr P - n^T P n and determinant n^T adj(P) n; its larger
    # eigenvalue is t/2 + sqrt(t^2/4 - det).
    P = np.asarray(covariance, dtype=np.float64)
    rows = P.tolist()
    if not (rows[0][1] == rows[1][0] and rows[0][2] == rows[2][0] and rows[1][2] == rows[2][1]):
        P = 0.5 * (P + P.T)  # (for a symmetric P, the estimators' covariance, this gives P itself)
        rows = P.tolist()
    (a, q, c), (_, d, e), (_, _, f) = rows  # symmetric: six numbers, as Python floats
    a01, a02, a12 = c * e - q * f, q * e - c * d, q * c - a * e
    adj = np.array([[d * f - e * e, a01, a02], [a01, a * f - c * c, a12], [a02, a12, a * d - q * q]])
    t = (a + d + f) - _einsum("ij,ij->i", n @ P, n)
    det = _einsum("ij,ij->i", n @ adj, n)
    lam = 0.5 * t + np.sqrt(np.maximum(0.25 * t * t - det, 0.0))
    return np.sqrt(np.maximum(lam * s2, 0.0))


def _unit_rows(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(b / |b|, |b|^2) of (n, 3) rows, as predicted_sigma uses them (a zero row stays zero)."""
    s2 = _einsum("ij,ij->i", b, b)
    return b / np.sqrt(np.where(s2 > 0, s2, 1.0))[:, None], s2


def star_radii(vectors: np.ndarray, covariance: np.ndarray, sigma_rad: float, radius_rad: float,
               unit: tuple | None = None) -> np.ndarray:
    """Per-star match radius r_i = r sqrt(1 + s_i^2 / sigma^2), s_i = predicted_sigma, capped."""
    s = predicted_sigma(vectors, covariance, unit)
    return np.minimum(radius_rad * np.sqrt(1.0 + (s / sigma_rad) ** 2), max(MAX_RADIUS_RAD, radius_rad))


@dataclass
class Verification:
    passed: bool
    reason: str
    statistic: str
    threshold: float  # as given
    threshold_effective: float  # the value P(false) is compared with (tetra3: / n_patterns)
    radius_rad: float  # the base match radius r
    n_hypothesis: int = 0
    n_agree: int = 0
    n_tested: int = 0
    n_frame: int = 0
    n_hypotheses: int = 1
    p_single: float = float("nan")  # density x pi r^2 for the base radius
    p_tested: list[float] = field(default_factory=list)  # p_i of each tested star
    radius_max_rad: float = float("nan")  # the largest r_i of the tested stars
    p_false: float = 1.0
    max_residual_rad: float = float("nan")
    R: np.ndarray | None = None
    covariance: np.ndarray | None = None
    matches: dict[int, int] = field(default_factory=dict)
    agreeing: dict[int, int] = field(default_factory=dict)  # the other stars that agreed with R(hypothesis)
    ambiguous: list[int] = field(default_factory=list)  # observed stars left out: two catalog stars within r

    def in_rows(self, rows: np.ndarray) -> "Verification":
        """A copy whose matches and agreeing stars name catalog rows `rows[k]` instead of k (the rows of a
        catalog of which the verified one is a subset)."""
        rows = np.asarray(rows)
        return replace(self, matches={o: int(rows[c]) for o, c in self.matches.items()},
                                   agreeing={o: int(rows[c]) for o, c in self.agreeing.items()})

    def to_dict(self) -> dict:
        return {
            "passed": bool(self.passed), "reason": self.reason, "statistic": self.statistic,
            "threshold": float(self.threshold), "threshold_effective": float(self.threshold_effective),
            "radius_rad": float(self.radius_rad), "radius_arcsec": float(self.radius_rad * RAD_TO_ARCSEC),
            "radius_max_arcsec": float(self.radius_max_rad * RAD_TO_ARCSEC),
            "n_hypothesis": int(self.n_hypothesis), "n_agree": int(self.n_agree), "n_tested": int(self.n_tested),
            "n_frame": int(self.n_frame), "n_hypotheses": int(self.n_hypotheses),
            "p_single": float(self.p_single), "p_tested": list(map(float, self.p_tested)),
            "p_false": float(self.p_false),
            "max_residual_arcsec": float(self.max_residual_rad * RAD_TO_ARCSEC),
            "n_matches": len(self.matches), "ambiguous": list(map(int, self.ambiguous)),
        }


def angular_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors (rows), accurate for small angles."""
    # = 2 arcsin(clip(np.linalg.norm(a - b, axis=-1) / 2, 0, 1)): the norm is sqrt(add.reduce(d * d)) as
    # numpy computes it, and a norm is >= 0 (NaN stays NaN either way): the same numbers, fewer calls
    d = np.asarray(a) - np.asarray(b)
    return 2.0 * np.arcsin(np.minimum(np.sqrt(np.add.reduce(d * d, axis=-1)) / 2.0, 1.0))


def match_one_to_one(query: np.ndarray, ref: np.ndarray, radius_rad
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (query index, ref index, distance) within the radius, each ref used once (nearest wins).

    radius_rad: one radius, or one per query. Every query takes its nearest ref star; when two
    queries want the same ref star the closer one keeps it and the other is left unmatched. Also
    returns the queries that are AMBIGUOUS: two or more ref stars lie within their radius (an
    unresolved close pair), whose identity cannot be told.
    """
    e = np.zeros(0, dtype=np.int64)
    if len(query) == 0 or len(ref) == 0:
        return e, e, np.zeros(0), e
    cq = chord(_per_item(radius_rad, len(query)))
    d0, j0, d1 = _nearest_two(np.asarray(query, dtype=np.float64), np.asarray(ref, dtype=np.float64),
                              float(cq.max()))
    ambiguous = np.flatnonzero(d1 <= cq)
    qi, rj, dist = _one_to_one(d0, j0, cq)
    return qi, rj, dist, ambiguous


BRUTE_PAIRS = 65536  # up to this many (query, ref) pairs the distances are one numpy array, not a k-d tree
SPLIT_PAIRS = 256  # from this many pairs the differences are written one coordinate at a time
PREFILTER_PAIRS = 400  # from this many pairs only those a dot product puts near are measured (_Frame._within)
PREFILTER_MARGIN = 1e-12  # on the squared chord: its rounding through the dot product is ~1e-15


def _chords(query: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(n, m) chords |query_i - ref_j|. The (n, m, 3) differences are the same numbers either way; a
    broadcast over the last axis of length 3 is slow for larger arrays, three (n, m) subtractions
    into it are not."""
    n, m = len(query), len(ref)
    if n * m < SPLIT_PAIRS:
        diff = query[:, None, :] - ref[None, :, :]
    else:
        diff = np.empty((n, m, 3))
        for k in range(3):
            np.subtract(query[:, k, None], ref[None, :, k], out=diff[..., k])
    return np.sqrt(_einsum("ijk,ijk->ij", diff, diff))


def _nearest_two(query: np.ndarray, ref: np.ndarray, bound: float, keep: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per query row: the chord to its nearest ref row among ref[keep] (all by default), that row's
    index in ref[keep], and the chord to the second nearest of ALL ref rows; beyond `bound` a chord is
    inf and a row len(ref[keep]), as cKDTree.query(k=2, distance_upper_bound=bound) gives them.
    Small problems (the frames of a star tracker: tens of stars on each side) are one (n, m) array
    of distances, larger ones a k-d tree."""
    n, m = len(query), len(ref)
    if n * m <= BRUTE_PAIRS:
        D = _chords(query, ref)
        d1 = np.partition(D, 1, axis=1)[:, 1] if m > 1 else np.full(n, np.inf)
        Dk = D if keep is None else D[:, keep]
        mk = Dk.shape[1]
        if mk:
            j0 = np.argmin(Dk, axis=1)
            d0 = Dk[np.arange(n), j0]
        else:
            j0, d0 = np.zeros(n, dtype=np.int64), np.full(n, np.inf)
        out = d0 > bound
        d0[out] = np.inf
        j0[out] = mk
        d1[d1 > bound] = np.inf
        return d0, j0, d1
    from scipy.spatial import cKDTree  # (only for frames of hundreds of stars: not imported on the usual path)

    k = 2 if m > 1 else 1
    d, j = cKDTree(ref).query(query, k=k, distance_upper_bound=bound)
    d1 = d.reshape(n, k)[:, 1] if k == 2 else np.full(n, np.inf)
    if keep is not None:
        sub = ref[keep]
        if len(sub) == 0:
            return np.full(n, np.inf), np.zeros(n, dtype=np.int64), d1
        d, j = cKDTree(sub).query(query, k=1, distance_upper_bound=bound)
        return d, j, d1
    d, j = d.reshape(n, k), j.reshape(n, k)
    return d[:, 0], j[:, 0], d1


def _plus_one(q: np.ndarray) -> np.ndarray:
    """|q_i|^2 + 1 per row (the squared lengths _Frame._within's dot-product prefilter adds to |v|^2 = 1)."""
    return _einsum("ij,ij->i", q, q) + 1.0


def _count_within(query: np.ndarray, ref: np.ndarray, chords: np.ndarray) -> np.ndarray:
    """How many ref rows lie within each query's chord (= cKDTree(ref).query_ball_point(query, chords,
    return_length=True)). The chords are _chords's; from PREFILTER_PAIRS pairs only those a dot product
    puts within reach (as _Frame._within, with both lengths) are measured."""
    n, m = len(query), len(ref)
    if n * m < PREFILTER_PAIRS:
        return np.count_nonzero(_chords(query, ref) <= chords[:, None], axis=1)
    if n * m <= BRUTE_PAIRS:
        qq = _einsum("ij,ij->i", query, query)
        rr = _einsum("ij,ij->i", ref, ref)
        ks, js = np.nonzero((qq[:, None] + rr[None, :]) - 2.0 * (query @ ref.T)
                            <= (chords * chords + PREFILTER_MARGIN)[:, None])
        diff = query[ks] - ref[js]
        ok = np.sqrt(_einsum("ij,ij->i", diff, diff)) <= chords[ks]
        return np.bincount(ks[ok], minlength=n)
    from scipy.spatial import cKDTree

    return np.asarray(cKDTree(ref).query_ball_point(query, chords, return_length=True))


APART_MARGIN = 1e-12  # on a squared chord: a thousand times the rounding of |a|^2 + |b|^2 - 2 a.b


def _apart(x: np.ndarray, radius_rad: float) -> bool:
    """Whether no two rows of x (directions) lie within twice the chord of radius_rad of each other,
    so that no ball of that radius, wherever it is, holds two of them (the triangle inequality, with
    APART_MARGIN to spare). From the products of the rows: |a - b|^2 = |a|^2 + |b|^2 - 2 a.b is at
    least 2 min |x_i|^2 - 2 max a.b (a, b two rows)."""
    n = len(x)
    if n < 2:
        return True
    g = x @ x.T
    s_min = float(_min(g.diagonal()))
    g.flat[::n + 1] = -np.inf  # a row with itself
    c = 2.0 * math.sin(0.5 * min(radius_rad, math.pi))
    return 2.0 * s_min - 2.0 * float(_max(g, axis=None)) > 4.0 * c * c + APART_MARGIN


def _one_to_one(d0: np.ndarray, j0: np.ndarray, cq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From each query's nearest ref (chord d0, row j0) and its chord radius cq: the pairs within the
    radius, each ref kept by its nearest query; (query index, ref index, angle), nearest first."""
    ok = d0 <= cq
    qi = np.flatnonzero(ok)
    rj = j0[ok].astype(np.int64)
    dist = 2.0 * np.arcsin(np.minimum(d0[ok] / 2.0, 1.0))  # = np.clip(.., 0, 1): a chord is >= 0
    if len(qi) <= ONE_TO_ONE_PY:  # a frame's few matches: Python lists, not eight numpy calls
        # nearest first (a stable sort: ties keep the query order), each ref by its first (nearest) query
        dl, rl = dist.tolist(), rj.tolist()
        order = sorted(range(len(qi)), key=dl.__getitem__)
        if len(set(rl)) < len(rl):  # two queries want one ref star: the nearer keeps it
            seen, first = set(), []
            for k in order:
                if rl[k] not in seen:
                    seen.add(rl[k])
                    first.append(k)
            order = first
        return qi[order], rj[order], dist[order]
    order = np.argsort(dist, kind="stable")
    qi, rj, dist = qi[order], rj[order], dist[order]
    by_ref = np.argsort(rj, kind="stable")  # the first (nearest) query of each ref star: = np.unique(rj,
    rs = rj[by_ref]                          # return_index=True)[1], without its per-call overhead
    head = np.ones(len(rs), dtype=bool)
    np.not_equal(rs[1:], rs[:-1], out=head[1:])
    first = np.sort(by_ref[head])
    return qi[first], rj[first], dist[first]


ONE_TO_ONE_PY = 64  # up to this many pairs within the radius _one_to_one runs in Python lists
ONE_EACH_FAST = True  # _Frame.agreeing answers a frame of one-to-one pairs without pairing them, and pairs
# surely within their radius are not measured (_Frame._within(chords=False))


_NEAREST: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # catalog -> chord to each star's nearest
NEAREST_UNSURE = 1e-9  # relative: a chord this close to the limit is decided by the exact count
NEAREST_REACH_RAD = float(np.radians(1.0))  # nearest neighbours are looked for this far (inf beyond)


def _has_neighbour(catalog: GuideCatalog, rows: np.ndarray, chords: np.ndarray) -> np.ndarray:
    """catalog.tree.query_ball_point(catalog.xyz[rows], chords, return_length=True) >= 2: whether
    another catalog star lies within each chord. From the chord to each star's nearest neighbour
    (`nearest_table`: the tree's k=2 distance; inf beyond NEAREST_REACH_RAD, one table per catalog,
    cached); a neighbour within NEAREST_UNSURE of
    the limit, or a chord beyond half the reach, is counted exactly (`GuideCatalog.ball_counts`), so
    the answer is the tree's answer."""
    d = _nearest(catalog, rows)
    out = d <= chords
    unsure = (np.abs(d - chords) <= NEAREST_UNSURE * chords) | (chords > 0.5 * _NEAREST_REACH_CHORD)
    if unsure.any():
        out[unsure] = catalog.ball_counts(catalog.xyz[rows[unsure]], chords[unsure]) >= 2
    return out


_NEAREST_REACH_CHORD = float(chord(NEAREST_REACH_RAD))


def _nearest(catalog: GuideCatalog, rows: np.ndarray) -> np.ndarray:
    """The chord from each catalog star (rows) to its nearest other star (inf beyond NEAREST_REACH_RAD),
    from the catalog's table of them (`nearest_table`), read once per catalog and process."""
    nn = _NEAREST.get(catalog)
    if nn is None:
        nn = _NEAREST[catalog] = nearest_table(catalog)
    return nn[rows]


def nearest_table(catalog: GuideCatalog) -> np.ndarray:
    """The chord from every catalog star to its nearest other star, inf where none lies within
    NEAREST_REACH_RAD: the k-d tree's k=2 query, built once per catalog and cached on disk as a database (8 bytes a star: 36 kB at
    mag 6, 0.6 MB for the full 78,000-star catalog; it loads in about a millisecond). Whole, not star by
    star as frames ask: a first frame in a new part of the sky costs no more than the next one."""
    from skyview.identify import database

    key = database.make_key("nearest", {"reach_rad": NEAREST_REACH_RAD}, catalog, None)
    arrays, _ = database.load_or_build(key, lambda: {"chord": _nearest_chords_all(catalog)})
    return np.asarray(arrays["chord"], dtype=np.float64)


def _nearest_chords_all(catalog: GuideCatalog) -> np.ndarray:
    """nearest_table's build: one k=2 query of the catalog's k-d tree (a star's first answer is itself,
    or a star at the same place: the chord 0 either way)."""
    if len(catalog.xyz) < 2:
        return np.full(len(catalog.xyz), np.inf)
    d, _ = catalog.tree.query(catalog.xyz, k=2, distance_upper_bound=_NEAREST_REACH_CHORD)
    return np.ascontiguousarray(d[:, 1], dtype=np.float64)


APART_CHORD_MARGIN = 1e-9  # on a chord: a million times the rounding of a turned direction's chords


def _stars_apart(catalog: GuideCatalog, rows: np.ndarray, v: np.ndarray, radius_rad: float) -> bool:
    """Whether no ball of radius_rad holds two of the catalog stars `rows` (their directions v, turned by
    an attitude): as `_apart(v, radius_rad)`, but from each star's nearest other catalog star
    (`_nearest`, remembered per catalog): all of them farther than twice the ball's chord (and
    APART_CHORD_MARGIN, far more than a turn's rounding of a chord) say so for any attitude. A False
    where _apart would say True only costs the exact count (`_Frame.ambiguous`: the same answer)."""
    if len(rows) < 2:
        return True
    c2 = 4.0 * math.sin(0.5 * min(radius_rad, math.pi)) + APART_CHORD_MARGIN
    if c2 >= _NEAREST_REACH_CHORD:  # beyond the reach of the remembered neighbours: the products
        return _apart(v, radius_rad)
    return float(_min(_nearest(catalog, rows))) > c2


def frame_stars(catalog: GuideCatalog, camera: Camera, R: np.ndarray, margin_rad: float = 0.0,
                near: NearStars | None = None) -> np.ndarray:
    """Catalog rows that land on the sensor for attitude R (the sensor grown by margin_rad), ascending.
    near: the catalog stars fetched around an earlier attitude of the same frame (`NearStars`), reused
    while they still cover this one (a camera fit moves the boresight by arcseconds) and fetched again
    when they do not: the same rows."""
    frame = _Frame(catalog, camera, R, margin_rad, margin_rad, near, count=False)
    if camera.distorted and not camera.fisheye and len(frame.rows):
        # a distortion that turns back before the corner (the model pushed to its bounds by a bad fit)
        # folds stars from beyond the field onto the sensor: kept to the field's cone, so that the rows do
        # not depend on how wide the stars fetched were (a lens that does not fold has none there)
        return frame.rows[frame.v[:, 2] >= math.cos(camera.half_diagonal_rad + max(margin_rad, 0.0)) - 1e-12]
    return frame.rows


@lru_cache(maxsize=64)
def _focal_centre(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """[fx, fy] and [cx, cy] as arrays, made once per camera."""
    return np.array([camera.fx, camera.fy]), np.array([camera.cx, camera.cy])


NEAR_SLACK_RAD = float(np.radians(0.25))  # the catalog stars near a frame are fetched this much wider


@lru_cache(maxsize=64)
def _solid_angle_sr(camera: Camera) -> float:
    """camera.solid_angle_sr, computed once per camera (a dozen scalar numpy calls: ~20 us a call)."""
    return camera.solid_angle_sr


_NO_ROWS = np.zeros(0, dtype=np.int64)
_NO_XYZ = np.zeros((0, 3))


class NearStars:
    """The catalog stars within some radius of a direction, fetched once (per verification, or per blind
    hypothesis for its quick check, camera fits and depth: `frame_stars(..., near=)`) and reused by every
    later attitude whose frame they still cover (a refit moves the boresight by arcseconds):
    `rows(b, radius)` is catalog.within(b, radius) or a superset of it, ascending; and
    `wide`, the stars within `wide_rad` (the local density's reach) or a superset (`wide_xyz`: their
    directions)."""

    def __init__(self, catalog: GuideCatalog, wide_rad: float = 0.0):
        self.catalog = catalog
        self.center = self.unit = None  # the direction fetched around (and it normalised)
        self.radius = -1.0
        self.wide_rad = wide_rad
        self.idx = self.wide = _NO_ROWS  # (shared empty arrays, replaced, never written to)
        self.xyz = self.wide_xyz = _NO_XYZ

    def rows(self, b: np.ndarray, radius: float) -> np.ndarray:
        """The rows (and `self.xyz`, their directions), ascending."""
        if self.center is not None:
            d = self.center - b
            moved = 2.0 * math.asin(min(1.0, math.sqrt(float(d @ d)) / 2.0))
            if moved + radius <= self.radius:
                return self.idx
        self.center, self.radius = np.array(b, dtype=np.float64), radius + NEAR_SLACK_RAD
        self.unit = self.center / math.sqrt(float(self.center @ self.center))
        self.wide_rad = max(self.wide_rad, self.radius)
        # the stars the sky index puts within each radius (ascending, as catalog.within gives them; a
        # 1e-9 margin on the cosine: a superset)
        self.wide, cos_b, self.wide_xyz = self.catalog.sky.cap_cosines(self.center, self.wide_rad, True)
        inner = cos_b >= math.cos(min(self.radius, math.pi)) - 1e-9
        self.idx, self.xyz = self.wide[inner], self.wide_xyz[inner]  # (= catalog.xyz[idx])
        return self.idx

    def covers(self, directions: np.ndarray, radius_rad: float) -> bool:
        """Whether every star within radius_rad of the directions (unit vectors) is in `wide`."""
        if self.center is None:
            return False
        if len(directions) == 0:
            return True
        cos_far = float(_min(directions @ self.unit))
        return math.acos(max(-1.0, min(1.0, cos_far))) + radius_rad + 1e-7 <= self.wide_rad


class _Frame:
    """The catalog reprojected with one attitude: the stars on the sensor grown by r (n_frame, the
    density), and the pool of stars an observed star may match (grown by the largest radius)."""

    def __init__(self, catalog: GuideCatalog, camera: Camera, R: np.ndarray, r: float, r_pool: float,
                 near: NearStars | None = None, count: bool = True):
        R = np.asarray(R, dtype=np.float64)
        grow = max(float(r), float(r_pool), 0.0)
        radius = camera.half_diagonal_rad + grow + 1e-9
        near = near or NearStars(catalog)
        rows = near.rows(R[2], radius)
        v = near.xyz @ R.T
        f = max(camera.fx, camera.fy)
        if len(rows):
            if camera.fisheye:
                uv, front = camera.project(v)  # NaN pixels behind the camera compare False below
                every = False
            else:  # = camera.project without its per-call overhead: the same numbers
                z = v[:, 2]
                # (the usual case: every star in front, nothing to replace; = (z > 1e-12).all(): a NaN
                # minimum compares False, as every NaN z would)
                every = float(_min(z)) > 1e-12
                if not every:
                    front = z > 1e-12
                    z = np.where(front, z, 1.0)
                # x = fx (v_x / z) + cx and y likewise, both columns at once (the same operations), through
                # the radial distortion as Camera._distort applies it
                fxy, cxy = _focal_centre(camera)
                xy = v[:, :2] / z[:, None]
                if camera.distorted:
                    r2 = np.add.reduce(xy * xy, axis=1, keepdims=True)  # (= np.sum of two: x^2 + y^2)
                    xy = xy * (1.0 + camera.k1 * r2 + camera.k2 * r2 * r2)
                uv = xy * fxy + cxy

            def inside(margin):  # = camera.in_image(uv, margin) without its per-call overhead
                hi = np.array([camera.width - 0.5 - margin, camera.height - 0.5 - margin])
                ok = (uv >= -0.5 + margin) & (uv <= hi)
                return ok[:, 0] & ok[:, 1]

            pool = inside(-grow * f) if every else front & inside(-grow * f)
            # (n_frame only where it is asked for: a refit needs the pool alone)
            if count:
                seen = inside(-max(float(r), 0.0) * f)
                self.n_frame = int(np.count_nonzero(seen if every else front & seen))
            else:
                self.n_frame = -1
        else:
            pool = np.zeros(0, dtype=bool)
            self.n_frame = 0
        self.rows = rows[pool]
        self.v = v[pool]

    def _within(self, q: np.ndarray, cq: np.ndarray, chords: bool = True, qq1: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The pairs (row k of q, pool star j, chord) with chord <= cq[k], k ascending and j ascending
        within a row. The chords are _chords's numbers (the same differences and sums, pair by pair);
        on larger frames only the pairs a dot product puts within reach (a 1e-12 margin on the squared
        chord, a thousand times its rounding) are measured. chords=False: the chords may be left out
        (None) where every pair the dot product keeps lies within reach by more than that margin (they
        are then surely within: only the pairs are asked for). qq1: |q|^2 + 1 per row, where the caller
        has it (`_plus_one`: verify's every round asks with the same q)."""
        n, m = len(q), len(self.v)
        if n * m < PREFILTER_PAIRS:
            D = _chords(q, self.v)
            ks, js = (D <= cq[:, None]).nonzero()
            return ks, js, D[ks, js]
        # |q - v|^2 = |q|^2 + |v|^2 - 2 q.v <= cq^2, with |v|^2 = 1 to ~1e-15 (catalog unit vectors
        # turned by an attitude): q.v >= (|q|^2 + 1 - cq^2) / 2, less the margin
        # (e = q.v - reach: within ~1e-15 of (cq^2 - |q - v|^2) / 2, a margin's 1/500)
        e = q @ self.v.T - (0.5 * ((_plus_one(q) if qq1 is None else qq1) - cq * cq))[:, None]
        ks, js = (e >= -0.5 * PREFILTER_MARGIN).nonzero()
        # every kept pair is surely within when each clears the upper limit
        if not chords and (len(ks) == 0 or float(_min(e[ks, js])) >= 0.5 * PREFILTER_MARGIN):
            return ks, js, None
        diff = q[ks] - self.v[js]
        d = np.sqrt(_einsum("ij,ij->i", diff, diff))
        ok = d <= cq[ks]
        return ks[ok], js[ok], d[ok]

    def ambiguous(self, q: np.ndarray, radii) -> np.ndarray:
        """Mask of observed vectors q with two or more catalog stars within their radius."""
        if len(self.rows) < 2 or len(q) == 0:
            return np.zeros(len(q), dtype=bool)
        cq = chord(_per_item(radii, len(q)))
        if len(q) * len(self.v) > BRUTE_PAIRS:
            return _nearest_two(q, self.v, float(cq.max()))[2] <= cq
        pairs = self._within(q, cq, chords=not ONE_EACH_FAST)[0]
        return np.bincount(pairs, minlength=len(q)) >= 2  # = second nearest within

    def agreeing(self, vectors: np.ndarray, others: np.ndarray, exclude_rows: np.ndarray, radii,
                 q: np.ndarray | None = None, qq1: np.ndarray | None = None, exclude_list: list | None = None
                 ) -> tuple[dict[int, int], set[int]]:
        """Observed stars among `others` within their radius of a catalog star not in exclude_rows
        (one-to-one), and those with two or more catalog stars within it (ambiguous: not in the dict).
        q: vectors[others], qq1: `_plus_one(q)`, exclude_list: exclude_rows as a list of Python ints,
        where the caller has them."""
        if len(others) == 0 or len(self.rows) == 0:
            return {}, set()
        q = vectors[others] if q is None else q
        # = chord(radii) (verify passes one radius per star: no _per_item)
        cq = 2.0 * np.sin((radii if type(radii) is np.ndarray and radii.shape == others.shape
                           else _per_item(radii, len(others))) / 2.0)
        if len(others) * len(self.v) <= BRUTE_PAIRS:
            qs, cs, ds = self._within(q, cq, not ONE_EACH_FAST, qq1)
            q_l, c_l = qs.tolist(), cs.tolist()
            if ONE_EACH_FAST and len(set(q_l)) == len(q_l) and len(set(c_l)) == len(c_l):
                rows_c = self.rows[cs].tolist()
                if set(rows_c).isdisjoint(np.asarray(exclude_rows).ravel().tolist() if exclude_list is None
                                          else exclude_list):
                    # the usual frame: every star has at most one catalog star within its radius, none
                    # of the hypothesis, and no catalog star is wanted twice: no ambiguity, all agree
                    return dict(zip(others[qs].tolist(), rows_c)), set()
        ex = np.asarray(exclude_rows).ravel()
        keep = (self.rows[:, None] != ex[None, :]).all(axis=1) if ex.size <= 16 else ~np.isin(self.rows, ex)
        # the nearest catalog star not in the hypothesis; ambiguity is judged against every catalog
        # star, those of the hypothesis included
        if len(others) * len(self.v) > BRUTE_PAIRS:
            d0, j0, d1 = _nearest_two(q, self.v, float(cq.max()), keep)
            amb_mask = d1 <= cq
            qi, rj, _ = _one_to_one(d0, j0, cq)
            pool = self.rows[keep]
            amb = amb_mask.tolist()
            agree = {o: c for o, c, a in zip(others[qi].tolist(), pool[rj].tolist(), qi.tolist()) if not amb[a]}
            return agree, set(others[amb_mask].tolist())
        # the same answer from the few (query, catalog star) pairs within the radius: a query is
        # ambiguous with two or more of them (= its second nearest within), and its nearest catalog
        # star not in the hypothesis (= argmin over those: the first column on a tie) is within the
        # radius exactly when one of its pairs is such a star
        if ds is None:
            qs, cs, ds = self._within(q, cq, True, qq1)
            q_l, c_l = qs.tolist(), cs.tolist()
        ds = ds.tolist()
        keep_l = keep.tolist()
        count = [0] * len(others)
        best: dict[int, tuple[float, int]] = {}
        for qk, ck, dk in zip(q_l, c_l, ds):
            count[qk] += 1
            if keep_l[ck]:
                b = best.get(qk)
                if b is None or dk < b[0]:  # columns ascend within a query: the first on a tie stays
                    best[qk] = (dk, ck)
        amb = [c >= 2 for c in count]
        agree: dict[int, int] = {}
        if best:
            ok = sorted(best)  # = np.flatnonzero(d0 <= cq)
            d_ok = np.array([best[k][0] for k in ok])
            dist = (2.0 * np.arcsin(np.minimum(d_ok / 2.0, 1.0))).tolist()  # _one_to_one's angles, same array
            rows = self.rows.tolist()
            taken = set()
            for k in sorted(range(len(ok)), key=dist.__getitem__):  # nearest first; a catalog star once
                qk = ok[k]
                ck = best[qk][1]
                if ck not in taken:
                    taken.add(ck)
                    if not amb[qk]:
                        agree[int(others[qk])] = rows[ck]
        amb_mask = np.array(amb, dtype=bool)
        return agree, set(others[amb_mask].tolist())


def verify(vectors: np.ndarray, hypothesis: dict[int, int], catalog: GuideCatalog, camera: Camera,
           sigma_rad: float, *, n_hypotheses: int = 1, n_patterns: int = 1, statistic: str = CALIBRATED,
           threshold: float | None = None, radius_rad: float | None = None,
           window_sr: np.ndarray | None = None) -> Verification:
    """Verify a hypothesis (observed index -> catalog row) against the whole frame.

    vectors: (N, 3) camera-frame unit vectors of ALL observed stars. n_hypotheses: how many
    hypotheses have been verified for this frame, this one included (Bonferroni factor of the
    calibrated statistic). n_patterns: the size of the method's pattern database (the tetra3
    statistic divides its threshold by it). radius_rad: the base match radius (default 3 sqrt(2) sigma).
    window_sr: (N,) the solid angle of the window each observed star was found in, for a frame
    measured in windows only (a tracker's): a tested star's chance is then its radius' share of its window.
    """
    if statistic not in STATISTICS:
        raise ValueError(f"unknown verification statistic {statistic!r}: choose from {', '.join(STATISTICS)}")
    thr = DEFAULT_THRESHOLD[statistic] if threshold is None else float(threshold)
    thr_eff = thr / max(1, int(n_patterns)) if statistic == TETRA3 else thr
    r = match_radius(sigma_rad) if radius_rad is None else float(radius_rad)
    vectors = np.asarray(vectors, dtype=np.float64)
    n_obs = len(vectors)
    out = Verification(passed=False, reason="", statistic=statistic, threshold=thr, threshold_effective=thr_eff,
                       radius_rad=r, n_hypothesis=len(hypothesis), n_hypotheses=int(n_hypotheses))
    if len(hypothesis) < 2:
        out.reason = "a hypothesis needs at least two stars to give an attitude"
        return out
    h_keys = sorted(hypothesis)
    h_obs = np.array(h_keys, dtype=np.int64)
    h_cat = np.array([hypothesis[i] for i in h_keys], dtype=np.int64)
    if h_obs[0] < 0 or h_obs[-1] >= n_obs:  # sorted
        raise ValueError("hypothesis refers to an observed star that does not exist")
    h_cat_l = h_cat.tolist()  # (Python ints)
    if len(set(h_cat_l)) != len(h_cat_l):
        out.reason = "the hypothesis assigns one catalog star to two observed stars"
        return out

    b_h, r_h = vectors[h_obs], catalog.xyz[h_cat]
    est = svd_attitude(b_h, r_h, sigma_rad)
    R = est.R
    resid = angular_distance(b_h, r_h @ R.T)
    out.max_residual_rad = float(_max(resid))
    if out.max_residual_rad > r:
        out.reason = (f"the hypothesis does not fit itself: a residual of {out.max_residual_rad * RAD_TO_ARCSEC:.1f}\" "
                      f"exceeds the match radius {r * RAD_TO_ARCSEC:.1f}\"")
        return out

    rest = np.ones(n_obs, dtype=bool)
    rest[h_obs] = False
    others = rest.nonzero()[0]  # = np.setdiff1d(np.arange(n_obs), h_obs) (= np.flatnonzero of a 1-d mask)
    out.n_tested = int(len(others))
    # every star's unit vector and squared length, for the radii of each estimate (row by row: a subset's
    # rows are the same numbers)
    unit_all = _unit_rows(vectors)
    radii = star_radii(None, est.covariance, sigma_rad, r, (unit_all[0][others], unit_all[1][others]))
    out.radius_max_rad = float(_max(radii)) if len(radii) else r
    # the catalog stars around the frame, fetched once for every round below, as far as the local
    # density of the observed stars reaches (an observed star lies acos(z) from the boresight)
    z_min = float(_min(vectors[:, 2]))
    # (a windowed frame's chances need no local density: the frame's stars only)
    reach = 0.0 if window_sr is not None else LOCAL_RADIUS_RAD
    near = NearStars(catalog, math.acos(max(-1.0, min(1.0, z_min))) + reach + NEAR_SLACK_RAD)
    frame = _Frame(catalog, camera, R, r, out.radius_max_rad, near)
    out.n_frame = frame.n_frame
    solid_angle = _solid_angle_sr(camera)
    out.p_single = p_single(out.n_frame, solid_angle, r)
    q = vectors[others]
    qq1 = _plus_one(q)  # (every round's q)
    agree, amb = frame.agreeing(vectors, others, h_cat, radii, q, qq1, h_cat_l)
    out.n_agree = len(agree) + len(amb)  # an unresolved close pair still is a catalog star
    out.agreeing = agree
    if window_sr is not None:  # a star found in a window: the chance of one placed within r_i of its centre
        out.p_tested = np.minimum(1.0, np.pi * radii ** 2 / np.asarray(window_sr, dtype=np.float64)[others]).tolist()
    else:
        # density: the frame's, or the local one around each tested star where that is higher (a
        # cluster); the star a tested star landed on is left out of its own neighbourhood
        landed = np.array([o in agree or o in amb for o in others.tolist()], dtype=np.float64)
        tested = q @ R
        cover = near.covers(tested, LOCAL_RADIUS_RAD)
        dens = np.maximum(out.n_frame / solid_angle, local_density(catalog, tested, leave_out=landed,
                                                                  among=near.wide if cover else None,
                                                                  among_xyz=near.wide_xyz if cover else None))
        out.p_tested = np.minimum(1.0, dens * np.pi * radii ** 2).tolist()
    if statistic == CALIBRATED:
        out.p_false = p_false_calibrated(out.n_agree, out.n_tested, out.p_tested, n_hypotheses)
    else:
        fov_rad = np.radians(camera.fov_deg)
        out.p_false = p_false_tetra3(len(hypothesis) + out.n_agree, n_obs, out.n_frame, r / fov_rad)
    if out.n_tested == 0:
        out.reason = "no observed star is left outside the hypothesis to test it"
        return out
    if out.n_agree == 0:
        out.reason = f"none of the {out.n_tested} other observed stars lands on a catalog star"
        return out
    if not out.p_false < thr_eff:
        out.reason = (f"{out.n_agree} of {out.n_tested} other stars agree, P(false) = {out.p_false:.2e} "
                      f"is not below {thr_eff:.2e}")
        return out

    # accepted: extend to every observed star that agrees and re-estimate with all of them (twice,
    # re-matching with the better attitude), leaving out of the reported matches every star whose
    # identity is ambiguous
    # (every step below is a deterministic function of the matches it starts from: when a round
    # leaves the matches as they were, its estimate, frame and agreements are reused, not recomputed)
    h_obs_l = h_obs.tolist()
    hyp = dict(zip(h_obs_l, h_cat_l))
    current = {**hyp, **agree}
    done = None  # (matches, their estimate, its observed indices and catalog rows) of the last round
    for _ in range(2):
        if done is not None and done[0] == current:
            break
        est, e_obs, e_cat = _estimate(vectors, current, catalog, sigma_rad)
        radii_all = star_radii(vectors, est.covariance, sigma_rad, r, unit_all)  # every star's, for this estimate
        radii = radii_all[others]
        frame = _Frame(catalog, camera, est.R, r, float(_max(radii)) if len(radii) else r, near, count=False)
        agree_i, amb_i = frame.agreeing(vectors, others, h_cat, radii, q, qq1, h_cat_l)
        done = (current, est, e_obs, e_cat)
        current = {**hyp, **agree_i}
    h_rad = radii_all[h_obs]
    if _stars_apart(catalog, frame.rows, frame.v, float(_max(h_rad))):
        # (no two pool stars close enough for one radius to hold both: nobody is ambiguous)
        final = dict(hyp)  # Python ints, in h_obs order (as the comprehension below)
        ambiguous = set(amb_i)
    else:
        h_amb = frame.ambiguous(b_h, h_rad)
        final = {o: c for o, c, a in zip(h_obs_l, h_cat_l, h_amb.tolist()) if not a}
        ambiguous = set(h_obs[h_amb].tolist()) | amb_i
    final.update(agree_i)
    dropped: list[int] = []
    if len(final) >= 2:
        same = final == done[0]
        # (the same matches: the same sorted indices and rows the estimate was made of)
        est, f_obs, f_cat = done[1:] if same else _estimate(vectors, final, catalog, sigma_rad)
        rad = radii_all[f_obs] if same else star_radii(None, est.covariance, sigma_rad, r,
                                                       (unit_all[0][f_obs], unit_all[1][f_obs]))
        pred = catalog.xyz[f_cat] @ est.R.T
        # every reported star must fit the final attitude (a hypothesis star that only just fitted
        # its own attitude may not) ...
        misfit = angular_distance(vectors[f_obs], pred) > rad
        # ... and a catalog star with another catalog star closer than the sensor resolves may be
        # half of a blend whose centroid sits between the two: its identity is either
        blend = np.maximum(rad, BLEND_RADIUS_PX * camera.pixel_scale_rad)
        unclear = _has_neighbour(catalog, f_cat, 2.0 * np.sin(blend / 2.0))  # (= chord(blend))
        # ... and a catalog star with two observed stars within the radius (a false star or a hot
        # pixel next to a star) may belong to either, so neither is reported (none is where no
        # radius can hold two observed stars)
        if not _apart(vectors, float(_max(rad))):
            unclear |= _count_within(pred, vectors, chord(rad)) >= 2
        dropped = f_obs[misfit | unclear].tolist()  # (Python ints)
        for o in dropped:
            final.pop(o)
        if dropped:
            ambiguous |= set(f_obs[unclear].tolist())
    out.ambiguous = sorted(ambiguous)
    if len(final) < 2:
        out.reason = "fewer than two observed stars have an unambiguous identity"
        return out
    if dropped:  # (else the estimate above is of these very matches)
        est = _estimate(vectors, final, catalog, sigma_rad)[0]
    out.passed = True
    out.reason = f"{out.n_agree} of {out.n_tested} other stars agree, P(false) = {out.p_false:.2e}"
    out.R = est.R
    out.covariance = est.covariance
    out.matches = {o: final[o] for o in sorted(final)}  # Python ints: from tolist() and int()
    return out


def verify_prediction(vectors: np.ndarray, matches: dict[int, int], catalog: GuideCatalog, sigma_rad: float,
                      covariance: np.ndarray, density_sr: float, min_stars: int, *, n_hypotheses: int = 1,
                      threshold: float | None = None, radius_rad: float | None = None) -> Verification:
    """Verify a predicted attitude (the module docstring): `matches` (observed index -> catalog row) are the
    observed stars found on their predicted places, each within its bound from the prediction's
    `covariance` (`star_radii`); `density_sr` the stars per steradian an accidental one is drawn from.
    Passed when at least `min_stars` are matched, P(false) (calibrated, every observed star tested, times
    n_hypotheses) is below the threshold, and every match fits the attitude estimated from the matches."""
    vectors = np.asarray(vectors, dtype=np.float64)
    thr = DEFAULT_THRESHOLD[CALIBRATED] if threshold is None else float(threshold)
    r = match_radius(sigma_rad) if radius_rad is None else float(radius_rad)
    k, n = len(matches), len(vectors)
    out = Verification(passed=False, reason="", statistic=CALIBRATED, threshold=thr, threshold_effective=thr,
                       radius_rad=r, n_agree=k, n_tested=n, n_hypotheses=int(n_hypotheses))
    if k < min_stars:
        out.reason = f"{k} of {n} stars matched the prediction; the prediction alone needs {min_stars}"
        return out
    radii = star_radii(vectors, covariance, sigma_rad, r)
    out.radius_max_rad = float(_max(radii)) if n else r
    out.p_tested = np.minimum(1.0, density_sr * np.pi * radii ** 2).tolist()
    out.p_false = p_false_calibrated(k, n, out.p_tested, n_hypotheses)
    if not out.p_false < thr:
        out.reason = f"{k} of {n} stars on their predicted places, P(false) = {out.p_false:.2e}"
        return out
    est, obs, cat = _estimate(vectors, matches, catalog, sigma_rad)
    if np.any(angular_distance(vectors[obs], catalog.xyz[cat] @ est.R.T) > radii[obs]):
        out.reason = "the matched stars do not fit one attitude"
        return out
    out.passed = True
    out.reason = f"{k} of {n} stars on their predicted places, P(false) = {out.p_false:.2e}"
    out.R, out.covariance = est.R, est.covariance
    out.matches = out.agreeing = {int(o): int(c) for o, c in zip(obs.tolist(), cat.tolist())}
    return out


def _estimate(vectors, matches, catalog, sigma_rad):
    """svd_attitude from the matches (observed index -> catalog row), in observed order; remembered
    (`attitude.remember_svd`) for the solver's attitude stage, which asks for the same estimate. With
    the observed indices (ascending) and their catalog rows, as arrays."""
    keys = sorted(matches)
    obs = np.array(keys, dtype=np.int64)
    rows = np.array([matches[i] for i in keys], dtype=np.int64)
    b, r = vectors[obs], catalog.xyz[rows]
    est = svd_attitude(b, r, sigma_rad)
    remember_svd(b, r, sigma_rad, est)
    return est, obs, rows


VERIFY_NUMBERS = ("n_agree", "n_tested", "p_false", "threshold_effective", "radius_arcsec", "n_hypotheses",
                  "p_single")


def verification_step(ver: Verification, hypothesis: dict[int, int], *, cap: int = 200,
                      numbers: dict | None = None, vd: dict | None = None, **fields):
    """The 'verify' step every method records: the matches (or the rejected hypothesis), the figures
    of the verification (VERIFY_NUMBERS of `Verification.to_dict`: `vd`, where the caller has made it),
    plus the method's own `numbers` and Step fields (groups, layers). The catalog rows are listed when
    first read (from a copy of the matches taken now: `LazyStep`)."""
    vd = ver.to_dict() if vd is None else vd
    shown = dict(ver.matches or hypothesis)
    nums = {k: vd[k] for k in VERIFY_NUMBERS} | {"passed": float(ver.passed)} | (numbers or {})
    return LazyStep("verify", ("verified: " if ver.passed else "rejected: ") + ver.reason, observed=sorted(shown),
                    catalog_of=lambda: [int(r) for _, r in sorted(shown.items())][:cap], numbers=nums, **fields)
