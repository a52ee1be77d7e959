"""The spherical-triangle method with pivoting (Cole & Crassidis 2006, section III).

Databases: which variant reads what, and why.

- database="triangles" (the paper's, default): every catalog star triangle that can appear in one
  image. The paper keeps the triangles that fit its circular 8 deg FOV; our sensor is a rectangle, and
  a triangle that appears on it lies inside the rectangle's circumscribed circle. So the database
  holds the triangles whose smallest enclosing cap has a radius <= R, R = camera.half_diagonal_rad
  rounded UP on the 5 % grid of `database.angular_range`: the database belongs to the sky (catalog,
  depth, R), not to one camera, and one file serves every camera whose half-diagonal is below R
  (as the angle database); each triangle's cap radius is stored (float32) and a look-up keeps the
  candidates whose cap fits the camera's own circle, so every camera gets the candidates a database
  of its own would give. At 8 deg / Hp <= 6.0 (4,559 stars, R = 5.74 deg): 1,450,092 triangles
  (1,506,879 with all sides <= 2R; `report` gives the counts for the paper's circle). Built
  vectorised and in chunks (`_triangle_chunks`, CHUNK_CANDIDATES candidate third stars at a time):
  catalog pairs up to 2R (cKDTree), triangles from the pair adjacency (i < j < k with (i, j), (i, k),
  (j, k) all pairs), the cap test, then for each kept triangle the area (L'Huilier, eqs. 15-16) and
  the polar moment about the centroid (recursive subdivision to depth 3 = 64 pieces, eq. 25), from
  `skyview.identify.spherical`; only the kept rows are collected. Stored sorted by area: star rows
  as int16 (int32 beyond 32,767 stars), area and polar moment as float32 (their rounding, 6e-8
  relative, is 10^4 times below the smallest 3-sigma bound), a k-vector on the area (parabola fit,
  as the paper) and one on the polar moment through a sort permutation (the paper's "two linked
  lists"), each triangle's rank in polar-moment order and those ranks sorted within blocks (the
  counter below): 38 bytes a triangle, 55 MB at 8 deg, memory-mapped on load (~5 ms). The build
  holds about BUILD_FIXED_BYTES + BYTES_PER_TRIANGLE bytes a triangle at its peak (400 MB + 52 B),
  the estimate checked against the memory budget (`database.check_memory`, 4 GB by default) before
  it starts. Measured peak RSS (/usr/bin/time -v, the whole process): 447 MB for 8 deg / Hp 6
  (1.45 M triangles, built in 11 s at load 1.6 on the shared 2-core machine, 21 s at load 5) and
  616 MB for 11 deg / Hp 6 (5.3 M triangles, 142 s at load 5), i.e. ~380 MB + 45 bytes a triangle.
  At 20 deg / Hp 6 the
  database would hold ~54 M triangles: ~3 GB at the peak (within the 4 GB budget, where the
  former one-piece build needed an estimated 12.9 GB), 2 GB on disk and ~10 minutes of polar
  moments. The paper variant still builds it when asked; the improved variant does not need it.
- database="pairs" (the improved variant): no triangle database at all. The candidates of an
  observed triangle are joined from the angle method's pair database (`angle.load_pair_database`,
  the same cached file the angle method reads: ~683,000 pairs, 11 MB at 20 deg / Hp 6) and then
  filtered by handedness, area and polar moment (`join_pairs`): with vertex_order="sides" the stored
  path keeps exactly the oriented triangles whose three sides match within beta sigma_p, so joining
  the sides first gives the same candidates (tests/test_triangle.py checks this triangle by
  triangle) without storing 54 M triangles at 20 deg. The polar-moment sigma line (below) comes from
  the same simulation on ~20,000 random catalog triangles (`build_moment_sigma`, a small cached
  database of its own). The join costs about what the stored look-up costs at 8 deg and is what
  makes the method usable at 20 deg.

Bounds (beta = 3). Area: beta sigma_A with sigma_A from eqs. 20-24 (area_sigma="paper": H H^T with
the three sides independent, each with the variance of an angle between two stars, sigma_p^2 = 2 sigma^2
(eq. 13): then 0.24 % of true triangles fall outside the 3 sigma bound, the paper's "0.3 %";
"star-sigma": the star's sigma^2, 1.8 % outside; docs/methods.md), or with the covariance of the
sides of noisy stars (area_sigma="stars"; see `spherical`: eq. 24 under-states sigma_A by a median
factor 1.2 and up to 2, and over-states it for slivers). Polar moment: as the paper, a bound from
simulation, cached beside the database (a small file per camera circle: drawn from the stored
triangles that fit the camera, in their stored order, it is the line a database built for that camera
alone would hold; with database="pairs" from ~20,000 random catalog triangles, `build_moment_sigma`):
MOMENT_SIGMA_TRIANGLES = 1000 random catalog triangles x
MOMENT_SIGMA_TRIALS = 100 noisy measurements (tangent-plane error sigma_ref per axis), the standard
deviation of each one's polar moment over sigma_ref, and the lowest line sigma_I / sigma = c0 + c1 I
lying MOMENT_SIGMA_MARGIN = 10 % above all of them (a linear program): "a line slightly above the
maximum standard deviations". The bound is beta sigma (c0 + c1 I).

Look-up. The candidates of an observed triangle are the catalog triangles whose area lies in
[A - beta sigma_A, A + beta sigma_A] and whose polar moment lies in [I - beta sigma_I, I + beta sigma_I]:
two k-vector ranges and their intersection (the shorter range filtered by the other). Counting the
intersection for many observed triangles at once uses the area order cut into blocks of BLOCK
triangles with their polar-moment ranks sorted inside each block (`_count`).

Vertex order. Area and polar moment do not depend on the order of the vertices, so a candidate may
map onto the observed triangle in 6 orders. vertex_order="paper" (default): as the paper, a candidate
is a set of three catalog stars; the hypotheses keep all 6 orders, pivoting prunes (or joins) on the
shared observed stars (the paper's "two stars in common"), and the chain ends when ONE SET of
catalog stars is left; then its vertex order is taken from the sides and the handedness (below), and
a set that fits in no order is rejected (the paper would have reported it: see first_chain).
vertex_order="sides": every candidate is oriented at once, keeping the orders in which each observed
side matches its catalog side within beta sigma_p (sigma_p = sqrt(2) sigma, eq. 14) and the handedness
agrees: the sign of the triple product p.(q x r) is that of the catalog triangle in that order (a
rotation keeps it, a mirror flips it), tested where the observed sign is certain (beyond beta of its
sigma); after each pivot every pair of stars of a hypothesis must match its observed angle.

Pivoting as printed (pivoting="shared-star", the default; section III-E): each triangle's candidates
form a list; the next triangle shares two observed stars with the current one, and a candidate of
either list survives when two of its catalog stars sit, on those two observed stars, in some
candidate of the other list ("any solution in each list that does not have two stars in common with
at least one solution in the other lists is discarded"); the following triangle meets the pruned list
of the one before it only. The chain ends when a list holds one star set, when no triangle shares two
stars with the current one, or at the pivot limit; the answer is that triangle's three stars, every
other star is left to verify with. pivoting="lists": two common stars anywhere (the print taken
literally). pivoting="join" (beyond the paper, in IMPROVED_PARAMS; the former paper variant) is the
chain below.

Pivoting by joins. The first triangle is the one with the largest area (order="largest", default: the paper
starts the angle method with the largest angle, "which typically offers the fewest solutions"), or the
fewest candidates (order="fewest", the paper's "ideal" order: needs every triangle's candidates
counted). Each pivot takes the next triangle in that order that shares two stars with the previous
one (when none is left, two stars with any used star) and joins its candidates with the hypotheses on
the shared observed stars (a vectorised sort + searchsorted join, `join`): a hypothesis survives with
every candidate that puts the same catalog stars on the shared observed stars and gains the third
star (never a catalog star it already uses); a triangle of three used stars must match as it is.
The chain stops when one star set is left (or a few that differ only by unresolved close pairs),
when no triangle is left, or at the pivot limit (max_pivots = 3, the paper's); a triangle with more
than max_candidates = 10,000 candidates is skipped. The one hypothesis left then goes to the shared
verification (`skyview.identify.verify`); only a verified one is reported.

Options beyond the paper (`IMPROVED_PARAMS` = pivoting="join", vertex_order="sides", area_sigma="stars",
close_triangles, backtrack, max_stars=12; the paper's method is the default):
- close_triangles: a pivot first takes a triangle made only of stars already in the hypotheses (no
  new star, strong pruning), so the chain ends with few stars and leaves the others to verify with;
- backtrack: when the hypotheses go to zero (a false star, a bound missed) or the one left fails
  verification, restart without a suspect star: the one the failed triangles point at most (each
  triangle that emptied the set blames its three stars, a failed verification its stars by half),
  ties broken by the chain's own order (the star just added first, then the others, newest first);
  at most max_restarts restarts, max_dropped stars at once. Every verification counts in the
  Bonferroni factor of the verification statistic, so no wrong attitude gets an easier pass.

Not in the paper, in IMPROVED_PARAMS: max_stars = 12 caps the stars that form triangles (the brightest;
every star still takes part in verification): the paper's CPU time grew to 400 s with more than 20
stars in the FOV. The paper variant forms triangles from every star (max_stars=None). database="pairs"
(above) is in IMPROVED_PARAMS too; it needs vertex_order="sides" and pivoting="join".
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.optimize import linprog

from skyview.attitude import svd_attitude
from skyview.camera import Camera
from skyview.catalog import GuideCatalog
from skyview.errors import BadInput
from skyview.identify import database as database_module
from skyview.identify import spherical as sph
from skyview.identify.base import (FAILED, IDENTIFIED, INCONCLUSIVE, Identification, Identifier, Observation,
                                   Step)
from skyview.identify.angle import _by_star, _pair_indices, load_pair_database
from skyview.identify.kvector import KVector
from skyview.identify.layers import Hypotheses
from skyview.identify.synthetic import add_noise
from skyview.identify.verify import (CALIBRATED, RADIUS_SIGMAS, STATISTICS, angular_distance, match_radius,
                                     verification_step, verify)

ORDERS = ("largest", "fewest")
# eq. 24 with the pair sigma sqrt(2) sigma ("paper": its 3 sigma bound then holds), with the star sigma
# ("star-sigma", the print's other reading), or the full covariance of the sides ("stars")
AREA_SIGMAS = ("paper", "star-sigma", "stars")
VERTEX_ORDERS = ("paper", "sides")
# where the candidates of an observed triangle come from: the stored triangle database ("triangles", the
# paper's), or joined from the angle database's pairs and then filtered by area and polar moment ("pairs")
DATABASES = ("triangles", "pairs")
IMPROVED_PARAMS = {"vertex_order": "sides", "close_triangles": True, "backtrack": True, "area_sigma": "stars",
                   "pivoting": "join", "max_stars": 12, "database": "pairs"}
# the paper's pairwise list pruning: two common stars anywhere ("lists") or on the two shared observed
# stars ("shared-star"); beyond the paper: full assignments joined on the shared stars ("join")
PIVOTINGS = ("shared-star", "lists", "join")
CAP = 200  # catalog rows / groups kept in one step
MAX_EQUIVALENT = 16  # at most this many hypotheses are compared for unresolved close pairs
DATABASE_VERSION = 5
MOMENT_SIGMA_VERSION = 1
BYTES_PER_TRIANGLE = 52  # peak memory of the chunked build per kept triangle (arrays, the sort, the k-vectors)
BUILD_FIXED_BYTES = 400 * 2 ** 20  # and what it holds whatever the size (Python, one chunk, the moment fit)
CHUNK_CANDIDATES = 1_000_000  # candidate third stars made and tested at once while building (~100 MB)
BLOCK = 256  # triangles per block of the candidate counter
MEASURE_BATCH = 16  # observed triangles measured at once when the search reaches an unmeasured one
SCAN_LIMIT = 65536  # a triangle looked up alone is counted by listing its candidates up to this range
MOMENT_SIGMA_TRIANGLES = 1000
MOMENT_SIGMA_TRIALS = 100
MOMENT_SIGMA_MARGIN = 1.1
MOMENT_SIGMA_REF_RAD = 87e-6  # the paper's noise; the bound is stored per unit sigma
MOMENT_SIGMA_SEED = 20060101
SQ2 = float(np.sqrt(2.0))
DEG2_PER_SR = float(np.degrees(1.0) ** 2)
_PERMS = np.array([[0, 1, 2], [1, 2, 0], [2, 0, 1], [0, 2, 1], [2, 1, 0], [1, 0, 2]])
_PARITY = np.array([1, 1, 1, -1, -1, -1])
_SIDE = np.array([[-1, 0, 2], [0, -1, 1], [2, 1, -1]])  # side index of vertex pair (x, y): ij=0, jk=1, ki=2


# ---------------------------------------------------------------------- database

def catalog_triangles(xyz: np.ndarray, max_side_rad: float, pairs: np.ndarray | None = None,
                      first: np.ndarray | None = None) -> np.ndarray:
    """All (i < j < k) whose three sides are <= max_side_rad, shape (T, 3) int64, vectorised.

    pairs: the unordered catalog pairs within max_side_rad (i < j), e.g. GuideCatalog.pairs_within.
    From the pair adjacency: for each pair (i, j), every k > j that is a neighbour of i, kept when
    (j, k) is a pair too. first: a mask of the stars allowed as the first (lowest) vertex i, or None.
    """
    for lo, hi, tri in _triangle_chunks(xyz, max_side_rad, pairs, first, chunk=None):
        return tri
    return np.zeros((0, 3), dtype=np.int64)


def _triangle_chunks(xyz: np.ndarray, max_side_rad: float, pairs: np.ndarray | None, first: np.ndarray | None,
                     chunk: int | None):
    """catalog_triangles in pieces: (first pair, last pair, triangles) for consecutive sorted pairs
    (i, j) with about `chunk` candidate third stars at a time (None: all at once), so that a large sky
    is never held as one list of candidate third stars."""
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    if pairs is None:
        from scipy.spatial import cKDTree
        pairs = cKDTree(xyz).query_pairs(float(2.0 * np.sin(max_side_rad / 2.0)), output_type="ndarray")
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    i, j = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    ok = angular_distance(xyz[i], xyz[j]) <= max_side_rad
    i, j = i[ok], j[ok]
    o = np.lexsort((j, i))
    i, j = i[o], j[o]
    if len(i) == 0:
        yield 0, 0, np.zeros((0, 3), dtype=np.int64)
        return
    row_start = np.searchsorted(i, np.arange(n + 1))
    after = row_start[i + 1] - np.arange(len(i)) - 1  # neighbours of i beyond j (sorted rows)
    if first is not None:
        after = np.where(np.asarray(first, dtype=bool)[i], after, 0)
    keys = i * n + j  # sorted (lexsort above)
    if chunk is None:
        bounds = [0, len(i)]
    else:  # cut where the running count of candidates crosses a multiple of chunk
        cum = np.cumsum(after)
        cuts = np.searchsorted(cum, np.arange(1, int(cum[-1]) // max(1, int(chunk)) + 1) * int(chunk), side="right")
        bounds = np.unique(np.concatenate([[0], cuts, [len(i)]])).tolist()
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        aft = after[lo:hi]
        total = int(aft.sum())
        src = lo + np.repeat(np.arange(hi - lo), aft)
        offs = np.arange(total) - np.repeat(np.cumsum(aft) - aft, aft)
        k = j[src + 1 + offs]
        a, b = i[src], j[src]
        q = b * n + k
        pos = np.minimum(np.searchsorted(keys, q), len(keys) - 1)
        keep = keys[pos] == q
        yield lo, hi, np.stack([a[keep], b[keep], k[keep]], axis=1)


def fit_moment_sigma(xyz: np.ndarray, tri: np.ndarray, depth: int, rng: np.random.Generator,
                     n_triangles: int = MOMENT_SIGMA_TRIANGLES, n_trials: int = MOMENT_SIGMA_TRIALS,
                     sigma_ref: float = MOMENT_SIGMA_REF_RAD, margin: float = MOMENT_SIGMA_MARGIN
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The paper's polar-moment sigma bound by simulation (section III-D).

    n_triangles random catalog triangles, n_trials noisy measurements of each (sigma_ref per
    tangent-plane axis); returns the line coefficients (c0, c1) of sigma_I / sigma <= c0 + c1 I and the
    samples (I, std(I_measured) / sigma_ref) it was fitted to.
    """
    if len(tri) == 0:
        return np.zeros(2), np.zeros((0, 2))
    pick = rng.choice(len(tri), size=min(n_triangles, len(tri)), replace=False)
    V = np.asarray(xyz, dtype=np.float64)[tri[pick]]  # (m, 3, 3)
    I0 = sph.polar_moment(V[:, 0], V[:, 1], V[:, 2], depth)
    noisy = [add_noise(np.repeat(V[:, s], n_trials, axis=0), sigma_ref, rng) for s in range(3)]
    I = sph.polar_moment(*noisy, depth).reshape(len(pick), n_trials)
    s = I.std(axis=1, ddof=1) / sigma_ref
    return upper_line(I0, margin * s), np.stack([I0, s], axis=1)


def upper_line(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(c0, c1) >= 0 of the line c0 + c1 x that lies above every (x, y) with the least mean height."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    sx = max(float(np.max(x)), 1e-300)
    sy = max(float(np.max(y)), 1e-300)
    xs, ys = x / sx, y / sy
    res = linprog(c=[1.0, float(np.mean(xs))], A_ub=-np.stack([np.ones_like(xs), xs], axis=1), b_ub=-ys,
                  bounds=[(0, None), (0, None)], method="highs")
    if not res.success:  # pragma: no cover - the problem is always feasible (c0 = max y)
        return np.array([float(np.max(y)), 0.0])
    c0, c1 = res.x
    return np.array([c0 * sy * (1.0 + 1e-9), c1 * sy / sx * (1.0 + 1e-9)])


COUNT_NAMES = ("sides_within_diameter", "cap_within_radius")


def build_triangle_database(catalog: GuideCatalog, max_radius_rad: float, depth: int = sph.MOMENT_DEPTH,
                            fit: str = "parabola") -> dict[str, np.ndarray]:
    """Catalog triangles whose enclosing cap radius is <= max_radius_rad, with area, polar moment,
    their k-vectors and the polar-moment sigma line.

    Built in chunks of CHUNK_PAIRS catalog pairs: each chunk's triangles are made, cap-tested and
    measured (area, polar moment) in float64, and only the kept rows (star indices, float32 area and
    moment) are collected, so the peak memory is about BYTES_PER_TRIANGLE bytes a kept triangle.
    `counts` records how many triangles have all sides <= the diameter 2 max_radius_rad and how many
    pass the cap rule itself (COUNT_NAMES).
    """
    xyz = catalog.xyz
    pairs = catalog.pairs_within(2.0 * max_radius_rad)
    idx_dtype = np.int16 if len(catalog) <= np.iinfo(np.int16).max else np.int32
    parts_tri, parts_area, parts_moment, parts_cap = [], [], [], []
    n_sides = 0
    for _, _, tri in _triangle_chunks(xyz, 2.0 * max_radius_rad, pairs, None, CHUNK_CANDIDATES):
        n_sides += len(tri)
        A, B, C = xyz[tri[:, 0]], xyz[tri[:, 1]], xyz[tri[:, 2]]
        cap = sph.enclosing_cap_radius(A, B, C)
        keep = cap <= max_radius_rad
        tri, A, B, C = tri[keep], A[keep], B[keep], C[keep]
        parts_cap.append(cap[keep].astype(np.float32))
        parts_tri.append(tri.astype(idx_dtype))
        parts_area.append(sph.area(A, B, C).astype(np.float32))
        parts_moment.append(sph.polar_moment(A, B, C, depth).astype(np.float32))
    tri = np.concatenate(parts_tri) if parts_tri else np.zeros((0, 3), dtype=idx_dtype)
    area = np.concatenate(parts_area) if parts_area else np.zeros(0, dtype=np.float32)
    moment = np.concatenate(parts_moment) if parts_moment else np.zeros(0, dtype=np.float32)
    cap = np.concatenate(parts_cap) if parts_cap else np.zeros(0, dtype=np.float32)
    del parts_tri, parts_area, parts_moment, parts_cap, pairs
    counts = np.array([n_sides, len(tri)], dtype=np.int64)
    order = np.lexsort((tri[:, 2], tri[:, 1], tri[:, 0], area))
    tri, area, moment, cap = tri[order], area[order], moment[order], cap[order]
    del order
    m_order = np.argsort(moment, kind="stable").astype(np.int32)
    rank = np.empty(len(m_order), dtype=np.int32)
    rank[m_order] = np.arange(len(m_order), dtype=np.int32)
    kv_a = KVector(area.astype(np.float64), fit=fit, presorted=True)
    area_k, area_coef = kv_a.k.astype(np.int32), kv_a.coef
    del kv_a
    moment_sorted = moment[m_order]
    kv_m = KVector(moment_sorted.astype(np.float64), fit=fit, presorted=True)
    block_rank = _block_sorted(rank, BLOCK)
    return {
        "tri": tri, "cap": cap,
        "area": area, "area_k": area_k, "area_coef": area_coef,
        "moment_sorted": moment_sorted, "moment_order": m_order, "moment_rank": rank,
        "moment_k": kv_m.k.astype(np.int32), "moment_coef": kv_m.coef, "block_rank": block_rank,
        "fit": np.array(fit), "counts": counts,
    }


def _camera_moment_sigma(xyz: np.ndarray, tri: np.ndarray, cap: np.ndarray, cap_limit: float, depth: int
                         ) -> dict[str, np.ndarray]:
    """fit_moment_sigma on the stored triangles that fit a camera (cap <= cap_limit), in their stored
    order: the draw a database built for that camera alone makes (the same seed, the same rows)."""
    rows = np.flatnonzero(np.asarray(cap) <= cap_limit)
    coef, samples = fit_moment_sigma(xyz, np.asarray(tri[rows], dtype=np.int64), depth,
                                     np.random.default_rng(MOMENT_SIGMA_SEED))
    return {"moment_sigma_coef": coef, "moment_sigma_samples": samples}


def triangles_estimate(n_stars: int, max_radius_rad: float) -> float:
    """Expected number of catalog triangles with all sides <= 2 max_radius_rad: about N k^2 / 6 for k
    neighbours within 2 max_radius_rad (the cap rule keeps ~85-95 % of them)."""
    k = 2.0 * database_module.pairs_estimate(n_stars, 2.0 * max_radius_rad) / max(n_stars, 1)
    return n_stars * k * k / 6.0


MOMENT_SAMPLE_TRIANGLES = 20_000  # triangles the moment sigma line of the pair lookup draws its 1000 from


def build_moment_sigma(catalog: GuideCatalog, max_radius_rad: float, depth: int = sph.MOMENT_DEPTH
                       ) -> dict[str, np.ndarray]:
    """The polar-moment sigma line without a triangle database: the same simulation (fit_moment_sigma)
    on catalog triangles whose lowest vertex is a random subset of the stars (every triangle equally
    likely), about MOMENT_SAMPLE_TRIANGLES of them, cap <= max_radius_rad."""
    rng = np.random.default_rng(MOMENT_SIGMA_SEED)
    frac = min(1.0, 2.0 * MOMENT_SAMPLE_TRIANGLES / max(triangles_estimate(len(catalog), max_radius_rad), 1.0))
    first = rng.random(len(catalog)) < frac
    tri = catalog_triangles(catalog.xyz, 2.0 * max_radius_rad, catalog.pairs_within(2.0 * max_radius_rad), first)
    xyz = catalog.xyz
    tri = tri[sph.enclosing_cap_radius(xyz[tri[:, 0]], xyz[tri[:, 1]], xyz[tri[:, 2]]) <= max_radius_rad]
    coef, samples = fit_moment_sigma(xyz, tri, depth, rng)
    return {"moment_sigma_coef": coef, "moment_sigma_samples": samples}


def triangle_counts(catalog: GuideCatalog, max_radius_rad: float, fov_rad: float) -> dict[str, int]:
    """How many catalog triangles each rule keeps (for the report): all sides <= 2 max_radius_rad, an
    enclosing cap <= max_radius_rad, and for a circular FOV all sides <= fov_rad and a cap <= fov_rad / 2."""
    out = dict.fromkeys(("sides_within_diagonal", "cap_within_half_diagonal", "sides_within_fov",
                         "cap_within_half_fov"), 0)
    xyz = catalog.xyz
    reach = max(2.0 * max_radius_rad, fov_rad)
    for _, _, tri in _triangle_chunks(xyz, reach, catalog.pairs_within(reach), None, CHUNK_CANDIDATES):
        A, B, C = xyz[tri[:, 0]], xyz[tri[:, 1]], xyz[tri[:, 2]]
        cap = sph.enclosing_cap_radius(A, B, C)
        longest = np.max(np.stack(sph.sides(A, B, C)), axis=0)
        out["sides_within_diagonal"] += int(np.sum(longest <= 2.0 * max_radius_rad))
        out["cap_within_half_diagonal"] += int(np.sum(cap <= max_radius_rad))
        out["sides_within_fov"] += int(np.sum(longest <= fov_rad))
        out["cap_within_half_fov"] += int(np.sum(cap <= fov_rad / 2.0))
    return out


def _block_sorted(rank: np.ndarray, block: int) -> np.ndarray:
    """The ranks sorted within each block of `block` consecutive triangles (area order)."""
    n = len(rank)
    nb = -(-n // block)
    pad = np.full(nb * block, np.iinfo(np.int32).max, dtype=np.int32)
    pad[:n] = rank
    return np.sort(pad.reshape(nb, block), axis=1).ravel()  # the padding sorts to the end of the last block


def _block_search(sorted_blocks: np.ndarray, blk: np.ndarray, value: np.ndarray, block: int) -> np.ndarray:
    """Per (block, value): how many ranks in that block are < value (a bisection inside the block)."""
    lo = blk.astype(np.int64) * block
    base = lo.copy()
    hi = lo + block
    for _ in range(int(np.ceil(np.log2(block))) + 1):
        mid = (lo + hi) >> 1
        right = (sorted_blocks[np.minimum(mid, len(sorted_blocks) - 1)] < value) & (lo < hi)
        lo = np.where(right, mid + 1, lo)
        hi = np.where(right, hi, mid)
    return lo - base


def _kvector(sorted_values: np.ndarray, k: np.ndarray, coef: np.ndarray, fit: str) -> KVector:
    """A KVector over stored arrays, kept in their compact dtypes (float32 values, int32 k)."""
    kv = KVector.__new__(KVector)
    kv.sorted_values = sorted_values
    kv.k = k
    kv.coef = np.asarray(coef, dtype=np.float64)
    kv.fit = fit
    kv.order = None
    return kv


def moment_convergence(xyz: np.ndarray, tri: np.ndarray, depths=range(0, 7)) -> dict[int, np.ndarray]:
    """Polar moment of the given catalog triangles at each recursion depth (the paper's Fig. 7)."""
    V = np.asarray(xyz, dtype=np.float64)[np.asarray(tri)]
    return {int(d): sph.polar_moment(V[:, 0], V[:, 1], V[:, 2], int(d)) for d in depths}


# ---------------------------------------------------------------------- the method

@dataclass
class _Chain:
    outcome: str  # "unique", "empty" or "ambiguous"
    reason: str
    used: list[int]
    H: np.ndarray  # (n_hypotheses, len(used)) catalog rows
    suspects: list[int] = field(default_factory=list)
    culprit: list[int] = field(default_factory=list)  # the observed stars of the triangle that emptied the set
    pivots: int = 0
    candidates: list[int] = field(default_factory=list)
    hypotheses: list[int] = field(default_factory=list)
    best: np.ndarray | None = None  # the hypothesis sent to verification
    answer: np.ndarray | None = None  # what the paper's method reports: the one star set left, best vertex order


class TriangleMethod(Identifier):
    """Cole & Crassidis' spherical-triangle method with pivoting, ending in the shared verification."""

    name = "triangle"
    improved_params = IMPROVED_PARAMS

    def __init__(self, catalog: GuideCatalog, camera: Camera, sigma_rad: float, *, beta: float = 3.0,
                 max_pivots: int | None = 3, max_candidates: int = 10_000, order: str = "largest",
                 area_sigma: str = "paper", vertex_order: str = "paper", depth: int = sph.MOMENT_DEPTH,
                 max_stars: int | None = None, pivoting: str = "shared-star",
                 close_triangles: bool = False, backtrack: bool = False, max_restarts: int = 10,
                 max_dropped: int = 1, statistic: str = CALIBRATED, threshold: float | None = None,
                 radius_sigmas: float = RADIUS_SIGMAS, kvector_fit: str = "parabola",
                 database: str = "triangles"):
        if not (np.isfinite(sigma_rad) and sigma_rad > 0):
            raise BadInput(f"the measurement sigma must be a positive number, not {sigma_rad!r}")
        if not (np.isfinite(beta) and beta > 0):
            raise BadInput(f"beta must be positive, not {beta!r}")
        if max_pivots is not None and int(max_pivots) < 0:
            raise BadInput("max_pivots must be >= 0 or None (unlimited)")
        if int(max_candidates) < 1:
            raise BadInput("max_candidates must be at least 1")
        if order not in ORDERS:
            raise BadInput(f"unknown order {order!r}: choose from {', '.join(ORDERS)}")
        if area_sigma not in AREA_SIGMAS:
            raise BadInput(f"unknown area_sigma {area_sigma!r}: choose from {', '.join(AREA_SIGMAS)}")
        if pivoting not in PIVOTINGS:
            raise BadInput(f"unknown pivoting {pivoting!r}: choose from {', '.join(PIVOTINGS)}")
        if vertex_order not in VERTEX_ORDERS:
            raise BadInput(f"unknown vertex_order {vertex_order!r}: choose from {', '.join(VERTEX_ORDERS)}")
        if not (0 <= int(depth) <= 8):
            raise BadInput("depth must be between 0 and 8")
        if max_stars is not None and int(max_stars) < 3:
            raise BadInput("max_stars must be at least 3 or None (all)")
        if statistic not in STATISTICS:
            raise BadInput(f"unknown verification statistic {statistic!r}: choose from {', '.join(STATISTICS)}")
        if threshold is not None and not (0 < float(threshold) <= 1):
            raise BadInput("threshold must be in (0, 1]")
        if kvector_fit not in ("line", "parabola"):
            raise BadInput("kvector_fit must be 'line' or 'parabola'")
        if int(max_restarts) < 0 or int(max_dropped) < 0:
            raise BadInput("max_restarts and max_dropped must be >= 0")
        if not (np.isfinite(radius_sigmas) and radius_sigmas > 0):
            raise BadInput("radius_sigmas must be positive")
        if database not in DATABASES:
            raise BadInput(f"unknown database {database!r}: choose from {', '.join(DATABASES)}")
        if database == "pairs" and (vertex_order != "sides" or pivoting != "join"):
            raise BadInput("database='pairs' joins oriented triangles: it needs vertex_order='sides' and "
                           "pivoting='join'")
        self.catalog = catalog
        self.camera = camera
        self.sigma_rad = float(sigma_rad)
        self.beta = float(beta)
        self.max_pivots = None if max_pivots is None else int(max_pivots)
        self.max_candidates = int(max_candidates)
        self.order = order
        self.area_sigma = area_sigma
        self.vertex_order = vertex_order
        self.pivoting = pivoting
        self.depth = int(depth)
        self.max_stars = None if max_stars is None else int(max_stars)
        self.close_triangles = bool(close_triangles)
        self.backtrack = bool(backtrack)
        self.max_restarts = int(max_restarts)
        self.max_dropped = int(max_dropped)
        self.statistic = statistic
        self.threshold = threshold
        self.radius_sigmas = float(radius_sigmas)

        self.database = database
        # the database belongs to the sky: caps up to the half-diagonal rounded up on the 5 % grid of
        # database.angular_range, so one database serves every camera whose half-diagonal is below it
        self.max_radius_rad = database_module.angular_range(camera.half_diagonal_rad)
        moment_params = [MOMENT_SIGMA_TRIANGLES, MOMENT_SIGMA_TRIALS, MOMENT_SIGMA_MARGIN, MOMENT_SIGMA_REF_RAD,
                         MOMENT_SIGMA_SEED]
        n_tri = triangles_estimate(len(catalog), self.max_radius_rad)
        if database == "pairs":
            self._init_pairs(catalog, camera, moment_params)
            return
        params = {"max_radius_rad": self.max_radius_rad, "depth": self.depth, "kvector_fit": kvector_fit,
                  "moment_sigma": moment_params, "version": DATABASE_VERSION}
        self.database_key = database_module.make_key(self.name, params, catalog, None)
        # built in chunks: ~BYTES_PER_TRIANGLE bytes a triangle at the peak, ~10 us each (the polar moment)
        what = (f"the triangle database ({len(catalog):,} stars, caps up to "
                f"{np.degrees(self.max_radius_rad):.1f} deg, ~{n_tri / 1e6:.1f} M triangles)")
        arrays, info = database_module.load_or_build(
            self.database_key,
            lambda: build_triangle_database(catalog, self.max_radius_rad, self.depth, kvector_fit),
            mmap=True, what=what, estimate_s=10e-6 * n_tri, estimate_bytes=BUILD_FIXED_BYTES + BYTES_PER_TRIANGLE * n_tri)
        t0 = time.perf_counter()
        self.tri = arrays["tri"]
        self.area = arrays["area"]
        self.moment_order = arrays["moment_order"]
        self.moment_rank = arrays["moment_rank"]
        fit = str(arrays["fit"][()])
        self.kv_area = _kvector(self.area, arrays["area_k"], arrays["area_coef"], fit)
        self.kv_moment = _kvector(arrays["moment_sorted"], arrays["moment_k"], arrays["moment_coef"], fit)
        self.block_rank = arrays["block_rank"]
        # the database serves every camera whose half-diagonal is below its range; a look-up keeps the
        # triangles that fit THIS camera's circumscribed circle, as a database of its own would
        self.cap = arrays["cap"]
        self.cap_limit = float(camera.half_diagonal_rad)
        # the polar-moment sigma line of the triangles that fit this camera (the paper's simulation on
        # 1000 of them): what a database of its own would hold, a small cached file of its own
        mkey = database_module.make_key("triangle-moment", {
            "triangles": database_module.key_string(self.database_key), "cap_limit": self.cap_limit,
            "version": MOMENT_SIGMA_VERSION}, catalog, None)
        line, minfo = database_module.load_or_build(
            mkey, lambda: _camera_moment_sigma(catalog.xyz, self.tri, self.cap, self.cap_limit, self.depth),
            what="the polar-moment sigma line of the triangle method", estimate_s=2.0)
        self.moment_sigma_coef = np.asarray(line["moment_sigma_coef"], dtype=np.float64)
        self.moment_sigma_samples = np.asarray(line["moment_sigma_samples"])
        counts = dict(zip(COUNT_NAMES, (int(c) for c in arrays["counts"])))
        info.update(triangles=len(self.tri), triangle_counts=counts, fov_deg=float(camera.fov_deg),
                    max_radius_deg=float(np.degrees(self.max_radius_rad)), catalog_stars=len(catalog),
                    moment_sigma_coef=self.moment_sigma_coef.tolist(), database="triangles",
                    index_s=time.perf_counter() - t0)
        self._n_patterns = len(self.tri)
        self.database_info = info
        self._key_string = database_module.key_string(self.database_key)

    def _init_pairs(self, catalog: GuideCatalog, camera: Camera, moment_params: list) -> None:
        """No triangle database: the angle database's pairs (shared with the angle method) and the
        polar-moment sigma line (a small database of its own)."""

        self.pair_i, self.pair_j, self.kv_pairs, info = load_pair_database(catalog, camera)
        self.pair_max_sep_rad = float(info["max_sep_rad"])
        params = {"max_radius_rad": self.max_radius_rad, "depth": self.depth, "moment_sigma": moment_params,
                  "sample": MOMENT_SAMPLE_TRIANGLES, "version": MOMENT_SIGMA_VERSION}
        mkey = database_module.make_key("triangle-moment", params, catalog, None)
        arrays, minfo = database_module.load_or_build(
            mkey, lambda: build_moment_sigma(catalog, self.max_radius_rad, self.depth),
            what="the polar-moment sigma line of the triangle method", estimate_s=2.0)
        self.moment_sigma_coef = np.asarray(arrays["moment_sigma_coef"], dtype=np.float64)
        self.moment_sigma_samples = np.asarray(arrays["moment_sigma_samples"])
        # the key recorded in results names both databases the method reads
        self.database_key = database_module.make_key(self.name, {"database": "pairs", "pairs": info["key"],
                                                                 "moment_sigma": mkey}, catalog, None)
        self._key_string = database_module.key_string(self.database_key)
        info.update(database="pairs", pairs=len(self.pair_i), max_sep_deg=float(np.degrees(self.pair_max_sep_rad)),
                    max_radius_deg=float(np.degrees(self.max_radius_rad)), fov_deg=float(camera.fov_deg),
                    catalog_stars=len(catalog), moment_sigma_coef=self.moment_sigma_coef.tolist(),
                    moment_sigma_key=minfo["key_string"], moment_sigma_source=minfo["source"])
        self._n_patterns = len(self.pair_i)
        self.database_info = info

    @property
    def database_key_string(self) -> str:
        return self._key_string

    @property
    def n_patterns(self) -> int:
        """Patterns in the database (the tetra3 statistic divides its threshold by this): the stored
        triangles, or with database="pairs" the pairs."""
        return self._n_patterns

    # ------------------------------------------------------------------ bounds and look-up
    def moment_sigma(self, moment: np.ndarray, sigma: float) -> np.ndarray:
        """The simulated polar-moment sigma bound for a measured polar moment (section III-D)."""
        c0, c1 = self.moment_sigma_coef
        return float(sigma) * (c0 + c1 * np.asarray(moment, dtype=np.float64))

    def triangle_bounds(self, V: np.ndarray, sigma: float, lookup: bool = True) -> dict[str, np.ndarray]:
        """Every observed triangle of the stars V: stars, area, polar moment, bounds, and the k-vector
        ranges (s1, e1: area order; s2, e2: polar-moment order) and candidate counts.

        lookup=False leaves the ranges and counts at -1, to be filled for the triangles actually visited
        (`count_of`): the largest-area order needs only those.
        """
        ti, tj, tk = _combinations(len(V))
        A, B, C = V[ti], V[tj], V[tk]
        a, b, c = sph.sides(A, B, C)
        area = sph.lhuilier(a, b, c)
        n = len(area)
        out = dict(ti=ti, tj=tj, tk=tk, sides=np.stack([a, b, c], axis=1), area=area, triple=sph.triple(A, B, C),
                   sigma=sigma, V=V, area_bound=np.full(n, np.nan), moment=np.full(n, np.nan),
                   moment_bound=np.full(n, np.nan), triple_sigma=np.full(n, np.nan))
        if lookup or self.order == "fewest":
            self._measure(out, np.arange(n))
        if self.database == "pairs":  # no ranges: each triangle's candidates are joined when it is visited
            for key in ("s1", "e1", "s2", "e2", "counts"):
                out[key] = np.full(len(area), -1, dtype=np.int64)
            if lookup:
                for k in range(len(area)):
                    self.count_of(out, k)
        elif lookup:
            with np.errstate(invalid="ignore"):
                da, moment, dm = out["area_bound"], out["moment"], out["moment_bound"]
                out["s1"], out["e1"] = self.kv_area.ranges(area - da, area + da)
                out["s2"], out["e2"] = self.kv_moment.ranges(moment - dm, moment + dm)
            out["counts"] = self._count(out)
            # the counter sees the whole database; list the candidates to keep those that fit this camera
            for k in np.flatnonzero(out["counts"] > 0).tolist():
                if min(out["e1"][k] - out["s1"][k], out["e2"][k] - out["s2"][k]) <= SCAN_LIMIT:
                    out.setdefault("rows", {})[k] = rows = self._scan(out, k)
                    out["counts"][k] = len(rows)
        else:
            for key in ("s1", "e1", "s2", "e2", "counts"):
                out[key] = np.full(len(area), -1, dtype=np.int64)
        return out

    def _measure(self, t: dict, idx: np.ndarray) -> None:
        """Fill the area bound, polar moment, its bound and the triple product's sigma of the observed
        triangles idx (the largest-area order measures only the triangles it visits, MEASURE_BATCH at a
        time: the polar moments of all 220 triangles of 12 stars would cost more than the search)."""
        V, sigma = t["V"], t["sigma"]
        A, B, C = V[t["ti"][idx]], V[t["tj"][idx]], V[t["tk"][idx]]
        if self.area_sigma == "paper":  # eq. 24 with each side's own sigma, sqrt(2) sigma (eq. 13)
            a, b, c = t["sides"][idx].T
            s_area = sph.area_sigma_paper(a, b, c, SQ2 * sigma)
        elif self.area_sigma == "star-sigma":
            a, b, c = t["sides"][idx].T
            s_area = sph.area_sigma_paper(a, b, c, sigma)
        else:
            s_area = sph.area_sigma_stars(A, B, C, sigma)
        moment = sph.polar_moment(A, B, C, self.depth)
        t["area_bound"][idx] = self.beta * s_area
        t["moment"][idx] = moment
        t["moment_bound"][idx] = self.beta * self.moment_sigma(moment, sigma)
        t["triple_sigma"][idx] = sph.triple_sigma(A, B, C, sigma)

    def _ensure(self, t: dict, k: int) -> None:
        """Observed triangle k measured (`_measure`), with the next unmeasured ones in the search order."""
        if not np.isnan(t["moment"][k]):
            return
        todo = np.flatnonzero(np.isnan(t["moment"]))
        pr = t.get("priority")
        if pr is not None and len(todo) > MEASURE_BATCH:
            todo = todo[np.argsort(pr[todo], kind="stable")[:MEASURE_BATCH]]
            if k not in todo:
                todo = np.append(todo[:-1], k)
        elif pr is None:
            todo = np.array([k])
        self._measure(t, np.sort(todo))

    def _count(self, t: dict) -> np.ndarray:
        """|area range ∩ polar-moment range| of each observed triangle, exact and vectorised.

        A catalog triangle is a candidate when its position in area order is in [s1, e1) and its
        position in polar-moment order (its rank) in [s2, e2) (and it fits the camera: `_scan` applies
        that, this counter counts the whole database's range). The area order is cut into blocks of
        BLOCK triangles whose ranks are stored sorted (`block_rank`): a block wholly
        inside [s1, e1) is counted with two binary searches, the at most 2 BLOCK triangles of the two
        partial blocks at the ends one by one.
        """
        s1, e1, s2, e2 = t["s1"], t["e1"], t["s2"], t["e2"]
        b = BLOCK
        q = np.arange(len(s1))
        live = (e1 > s1) & (e2 > s2)
        first = -(-s1 // b)  # first block starting at or after s1
        last = e1 // b  # blocks [first, last) lie inside [s1, e1)
        full = live & (last > first)
        counts = np.zeros(len(s1), dtype=np.int64)
        # whole blocks: two bisections inside each (triangle, block)'s sorted ranks
        nb = np.where(full, last - first, 0)
        if nb.sum():
            owner = np.repeat(q, nb)
            blk = np.repeat(first, nb) + (np.arange(int(nb.sum())) - np.repeat(np.cumsum(nb) - nb, nb))
            c = (_block_search(self.block_rank, blk, e2[owner], b) - _block_search(self.block_rank, blk, s2[owner], b))
            counts += np.bincount(owner, weights=c, minlength=len(s1)).astype(np.int64)
        # the ends: [s1, first * b) and [last * b, e1) (or all of [s1, e1) when no block fits inside)
        ends = ((s1, np.where(full, first * b, e1)), (np.where(full, last * b, e1), e1))
        for lo, hi in ends:
            ln = np.where(live, np.maximum(hi - lo, 0), 0)
            total = int(ln.sum())
            if total == 0:
                continue
            owner = np.repeat(q, ln)
            pos = np.repeat(lo - np.cumsum(ln) + ln, ln) + np.arange(total)
            r = self.moment_rank[pos]
            ok = (r >= s2[owner]) & (r < e2[owner])
            counts += np.bincount(owner, weights=ok, minlength=len(s1)).astype(np.int64)
        return counts

    def count_of(self, t: dict, k: int) -> int:
        """The candidate count of observed triangle k, looked up and counted now if it was left out
        (database="pairs": the catalog star sets that the pair join leaves)."""
        self._ensure(t, k)
        if t["counts"][k] < 0 and self.database == "pairs":
            t.setdefault("oriented", {})[k] = H = self.join_pairs(t, k)
            t["counts"][k] = _n_sets(H)
        elif t["counts"][k] < 0:
            a, da, i, di = t["area"][k], t["area_bound"][k], t["moment"][k], t["moment_bound"][k]
            t["s1"][k], t["e1"][k] = self.kv_area.range(a - da, a + da)
            t["s2"][k], t["e2"][k] = self.kv_moment.range(i - di, i + di)
            if min(t["e1"][k] - t["s1"][k], t["e2"][k] - t["s2"][k]) <= SCAN_LIMIT:  # list them at once
                t.setdefault("rows", {})[k] = rows = self._scan(t, k)
                t["counts"][k] = len(rows)
            else:
                one = {key: t[key][k:k + 1] for key in ("s1", "e1", "s2", "e2")}
                t["counts"][k] = self._count(one)[0]
        return int(t["counts"][k])

    def join_pairs(self, t: dict, k: int) -> np.ndarray:
        """database="pairs": the oriented candidates of observed triangle k ((p, q, r) = (ti, tj, tk)[k]),
        without a triangle database.

        The catalog pairs whose angle matches side pq within beta sigma_p (sigma_p = sqrt(2) sigma, the
        tolerance `orient` gives each side) are joined on the shared star q with the pairs matching
        side qr, in both orientations; a third side rp within the same tolerance closes the triangle
        (its angle computed from the two stars, as the database computes its pairs'). Then, as the
        triangle database's candidates: the handedness where the observed sign is certain, the area
        within its bound and the polar moment within its bound. Returns (h, 3) catalog rows in the
        order (p, q, r): what `orient` returns from the stored candidates, up to the stored database's
        cap rule (a triangle that matches a sensor's triangle within the noise fits the sensor).
        """
        self._ensure(t, k)
        sig = float(t["sigma"])
        tol = self.beta * SQ2 * sig
        sides = t["sides"][k]
        lo, hi = sides - tol, sides + tol
        st, sp = self.kv_pairs.ranges(lo[:2], hi[:2])
        pi, pj, xyz = self.pair_i, self.pair_j, self.catalog.xyz
        a1, b1 = pi[st[0]:sp[0]], pj[st[0]:sp[0]]
        a2, b2 = pi[st[1]:sp[1]], pj[st[1]:sp[1]]
        cp, cq = np.concatenate([a1, b1]), np.concatenate([b1, a1])  # (catalog p, catalog q), both orientations
        q2, r2 = np.concatenate([a2, b2]), np.concatenate([b2, a2])
        r2s, start, size = _by_star(q2, r2, len(xyz))  # side qr's pairs in blocks by their star on q
        cnt = size[cq]
        rows = np.repeat(np.arange(len(cp)), cnt)
        c = r2s[np.repeat(start[cq] - np.cumsum(cnt) + cnt, cnt) + np.arange(int(cnt.sum()))]
        a, b = cp[rows], cq[rows]
        ok = c != a
        a, b, c = a[ok], b[ok], c[ok]
        # side rp: a cheap test on the dot product, a little wider than the bounds, then the angle exactly
        # as the database computes its pairs' (the same triangles as computing every angle)
        hi_rp = min(float(hi[2]), self.pair_max_sep_rad)
        near = np.einsum("ij,ij->i", xyz[c], xyz[a]) >= np.cos(min(hi_rp + 1e-6, np.pi))
        a, b, c = a[near], b[near], c[near]
        d = angular_distance(xyz[c], xyz[a])
        ok = (d >= lo[2]) & (d <= hi[2]) & (d <= self.pair_max_sep_rad)
        a, b, c = a[ok], b[ok], c[ok]
        A, B, C = xyz[a], xyz[b], xyz[c]
        tr, trs = float(t["triple"][k]), float(t["triple_sigma"][k])
        if len(a) and abs(tr) > self.beta * trs:
            ok = np.sign(sph.triple(A, B, C)) == np.sign(tr)
            a, b, c, A, B, C = a[ok], b[ok], c[ok], A[ok], B[ok], C[ok]
        if len(a):
            ar, da = float(t["area"][k]), float(t["area_bound"][k])
            area = sph.area(A, B, C)
            ok = (area >= ar - da) & (area <= ar + da)
            a, b, c, A, B, C = a[ok], b[ok], c[ok], A[ok], B[ok], C[ok]
        if len(a):
            mo, dm = float(t["moment"][k]), float(t["moment_bound"][k])
            moment = sph.polar_moment(A, B, C, self.depth)
            ok = (moment >= mo - dm) & (moment <= mo + dm)
            a, b, c = a[ok], b[ok], c[ok]
        t.setdefault("side_counts", {})[k] = (int(sp[0] - st[0]), int(sp[1] - st[1]))
        return np.stack([a, b, c], axis=1)

    def hypotheses(self, t: dict, k: int, sigma: float) -> tuple[np.ndarray, list[tuple[int, ...]]]:
        """The oriented candidates of observed triangle k (rows over (ti, tj, tk)[k]) and the catalog
        triangles a step draws for them (capped)."""
        if self.database == "pairs":
            self.count_of(t, k)
            H = t["oriented"][k]
            shown = np.unique(np.sort(H[:64 * CAP], axis=1), axis=0)[:CAP] if len(H) else H
            return H, list(map(tuple, shown.astype(int).tolist()))
        rows = self.candidates(t, k)
        H, src = self.orient(t, k, rows, sigma)
        return H, _groups(self.tri, rows, src)

    def candidates(self, t: dict, m: int) -> np.ndarray:
        """Rows (into self.tri, area order) of the catalog triangles matching observed triangle m:
        the shorter of its two ranges, filtered by the other."""
        self.count_of(t, m)
        rows = t.get("rows", {}).get(m)
        return rows if rows is not None else self._scan(t, m)

    def _scan(self, t: dict, m: int) -> np.ndarray:
        """The candidate rows of observed triangle m: its two ranges intersected, then the triangles
        that fit this camera (enclosing cap <= its half-diagonal)."""
        s1, e1, s2, e2 = int(t["s1"][m]), int(t["e1"][m]), int(t["s2"][m]), int(t["e2"][m])
        if e1 - s1 <= e2 - s2:
            r = self.moment_rank[s1:e1]
            rows = s1 + np.flatnonzero((r >= s2) & (r < e2))
        else:
            p = self.moment_order[s2:e2].astype(np.int64)
            rows = np.sort(p[(p >= s1) & (p < e1)])
        return rows[self.cap[rows] <= self.cap_limit]

    def orient(self, t: dict, m: int, rows: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
        """Hypotheses of observed triangle m from candidate rows: (h, 3) catalog stars for the observed
        stars (ti, tj, tk)[m], and the candidate row each came from.

        vertex_order="sides": the vertex orders whose sides match the observed sides within
        beta sigma_p and whose handedness (sign of the triple product) is the observed one when that
        sign is certain. vertex_order="paper": every one of the 6 orders (the paper matches triangles
        by area and polar moment only; the join and the final resolution sort the orders out).
        """
        self._ensure(t, m)
        if len(rows) == 0:
            return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
        cat = self.tri[rows].astype(np.int64)  # (r, 3)
        if self.vertex_order == "paper":
            H = cat[:, _PERMS].reshape(-1, 3)
            return H, np.repeat(rows, len(_PERMS))
        P = self.catalog.xyz[cat]  # (r, 3, 3)
        S = np.stack(sph.sides(P[:, 0], P[:, 1], P[:, 2]), axis=1)  # ij, jk, ki
        sgn = np.sign(sph.triple(P[:, 0], P[:, 1], P[:, 2]))
        obs_sides = t["sides"][m]  # pq, qr, rp
        tol = self.beta * SQ2 * sigma
        tr, trs = float(t["triple"][m]), float(t["triple_sigma"][m])
        check_hand = abs(tr) > self.beta * trs
        keep_rows, keep_perm = [], []
        for k, perm in enumerate(_PERMS):
            sp_ = S[:, [_SIDE[perm[0], perm[1]], _SIDE[perm[1], perm[2]], _SIDE[perm[2], perm[0]]]]
            ok = np.all(np.abs(sp_ - obs_sides[None, :]) <= tol, axis=1)
            if check_hand:
                ok &= sgn * _PARITY[k] == np.sign(tr)
            idx = np.flatnonzero(ok)
            keep_rows.append(idx)
            keep_perm.append(np.full(len(idx), k))
        idx = np.concatenate(keep_rows)
        perm = _PERMS[np.concatenate(keep_perm)]
        H = np.take_along_axis(cat[idx], perm, axis=1)
        return H, rows[idx]

    def consistent(self, V: np.ndarray, used: list[int], triangles: list[list[int]], H: np.ndarray,
                   sigma: float) -> np.ndarray:
        """The hypotheses whose every pair of stars matches the observed angle within beta sigma_p and
        whose every triangle of the chain has the observed handedness where that is certain."""
        if len(H) == 0:
            return H
        xyz = self.catalog.xyz
        col = {s: c for c, s in enumerate(used)}
        tol = self.beta * SQ2 * sigma
        x, y = _pair_indices(len(used))  # every pair of stars at once
        u = np.asarray(used)
        obs_angle = angular_distance(V[u[x]], V[u[y]])
        P = xyz[H]
        ok = np.all(np.abs(angular_distance(P[:, x], P[:, y]) - obs_angle) <= tol, axis=1)
        T = np.asarray(triangles)  # every triangle of the chain at once
        A, B, C = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
        tr = sph.triple(A, B, C)
        certain = np.abs(tr) > self.beta * sph.triple_sigma(A, B, C, sigma)
        if np.any(certain):
            c = np.array([[col[s] for s in tri] for tri in T[certain].tolist()])  # (t, 3) columns of H
            Pc = P[:, c]  # (h, t, 3 vertices, 3)
            hand = np.sign(sph.triple(Pc[:, :, 0], Pc[:, :, 1], Pc[:, :, 2])) == np.sign(tr[certain])
            ok &= np.all(hand, axis=1)
        return H[ok]

    # ------------------------------------------------------------------ identify
    def identify(self, obs: Observation) -> Identification:
        t0 = time.perf_counter()
        steps: list[Step] = []
        n = len(obs)
        sigma = float(obs.sigma_rad) if (obs.sigma_rad is not None and np.isfinite(obs.sigma_rad)
                                         and obs.sigma_rad > 0) else self.sigma_rad
        result = Identification(method=self.name, status=FAILED, matches={}, steps=steps,
                                database_key=self.database_key_string)
        if n < 3:
            result.reason = f"the spherical-triangle method needs at least 3 stars, the frame has {n}"
            result.stats = {"stars": n, "time_s": time.perf_counter() - t0}
            return result
        V = np.asarray(obs.vectors, dtype=np.float64)
        if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
            raise BadInput(f"observed vectors must be a finite (N, 3) array, not shape {V.shape}")
        m = n if self.max_stars is None else min(n, self.max_stars)
        t = self.triangle_bounds(V[:m], sigma, lookup=self.order == "fewest")
        if self.order == "fewest":
            rank = np.lexsort((-t["area"], t["counts"]))
        else:
            rank = np.argsort(-t["area"], kind="stable")
        priority = np.empty(len(rank), dtype=np.int64)
        priority[rank] = np.arange(len(rank))
        t["priority"] = priority
        t["tol"] = 2.0 * match_radius(sigma, self.radius_sigmas)
        t["sigma"] = sigma
        t["stars"] = m

        queue: list[frozenset] = [frozenset()]
        seen = {frozenset()}
        blame = np.zeros(m)
        chains: list[_Chain] = []
        n_verified = 0
        reasons = []
        budget = 1 + (self.max_restarts if self.backtrack else 0)
        while queue and len(chains) < budget:
            # the restart whose dropped star the failed triangles point at most (ties: first queued)
            pick = int(np.argmax([blame[list(e)].sum() if e else 0.0 for e in queue]))
            excluded = queue.pop(pick)
            if excluded:
                steps.append(Step("backtrack", f"restart without observed star(s) {sorted(excluded)}",
                                  observed=sorted(excluded), numbers={"restart": len(chains)}))
            chain = (self._chain if self.pivoting == "join" else self._chain_lists)(V, excluded, t, steps)
            chains.append(chain)
            suspects: list[int] = []
            if chain.outcome == "unique":
                chain.best = chain.answer = self._best(V, chain.used, chain.H, sigma)
                hyp = dict(zip(chain.used, chain.best.tolist()))
                n_verified += 1
                ver = verify(V, hyp, self.catalog, self.camera, sigma, n_hypotheses=n_verified,
                             n_patterns=self.n_patterns, statistic=self.statistic, threshold=self.threshold,
                             radius_rad=match_radius(sigma, self.radius_sigmas))
                vd = ver.to_dict()
                steps.append(verification_step(ver, hyp, cap=CAP))
                result.verification = vd
                if ver.passed:
                    result.accept(ver)
                    break
                reasons.append(f"verification failed: {ver.reason}")
                suspects = chain.used[::-1]
                blame[chain.used] += 0.5
            else:
                reasons.append(chain.reason)
                if chain.outcome == "empty":
                    suspects = chain.suspects
                    blame[chain.culprit] += 1.0
            if self.backtrack and len(excluded) < self.max_dropped:
                for s in suspects:
                    e2 = excluded | {int(s)}
                    if e2 not in seen and m - len(e2) >= 3:
                        seen.add(e2)
                        queue.append(e2)
        if result.status != IDENTIFIED:
            result.status = INCONCLUSIVE
            result.reason = reasons[0] if len(reasons) == 1 else "; ".join(
                f"chain {k + 1}: {r}" for k, r in enumerate(reasons))
        last, first = chains[-1], chains[0]
        result.stats = {
            "stars": n,
            "triangle_stars": m,
            "triangles": len(t["area"]),
            "pivots": last.pivots,
            "pivots_total": int(sum(c.pivots for c in chains)),
            "stars_used": len(last.used),
            "candidates": last.candidates,
            "hypotheses": last.hypotheses,
            "chains": len(chains),
            "verifications": n_verified,
            # the paper's own criterion: the answer of the first chain, before our vertex-order check and
            # the verification ("unique" also when that one star set fits in no vertex order)
            "first_chain": {"outcome": "unique" if first.answer is not None else first.outcome,
                            "matches": ({int(o): int(c) for o, c in zip(first.used, first.answer)}
                                        if first.answer is not None else {}),
                            "vertex_order_ok": first.best is not None},
            "time_s": time.perf_counter() - t0,
        }
        return result

    # ------------------------------------------------------------------ one pivoting chain
    def _numbers(self, t: dict, k: int) -> dict[str, float]:
        if self.database == "pairs":
            n_pq, n_qr = t.get("side_counts", {}).get(k, (-1, -1))
            return {"area_sr": float(t["area"][k]), "area_bound_sr": float(t["area_bound"][k]),
                    "moment": float(t["moment"][k]), "moment_bound": float(t["moment_bound"][k]),
                    "pairs_side1": n_pq, "pairs_side2": n_qr, "candidates": int(t["counts"][k])}
        return {"area_sr": float(t["area"][k]), "area_bound_sr": float(t["area_bound"][k]),
                "moment": float(t["moment"][k]), "moment_bound": float(t["moment_bound"][k]),
                "candidates_area": int(t["e1"][k] - t["s1"][k]),
                "candidates_moment": int(t["e2"][k] - t["s2"][k]), "candidates": int(t["counts"][k])}

    def _label(self, t: dict, k: int) -> str:
        return (f"triangle {t['ti'][k]}-{t['tj'][k]}-{t['tk'][k]} (area {t['area'][k] * DEG2_PER_SR:.4f} "
                f"+- {t['area_bound'][k] * DEG2_PER_SR:.4f} deg2, polar moment {t['moment'][k]:.3e} "
                f"+- {t['moment_bound'][k]:.1e})")

    def _chain(self, V: np.ndarray, excluded: frozenset, t: dict, steps: list[Step]) -> _Chain:
        ti, tj, tk, counts, priority = t["ti"], t["tj"], t["tk"], t["counts"], t["priority"]
        sigma, m = t["sigma"], t["stars"]
        done = np.zeros(len(ti), dtype=bool)
        if excluded:
            ex = np.zeros(m, dtype=bool)
            ex[list(excluded)] = True
            done |= ex[ti] | ex[tj] | ex[tk]
        candidates: list[int] = []
        hyps: list[int] = []

        def pick_next(mask):
            idx = np.flatnonzero(mask)
            return int(idx[np.argmin(priority[idx])]) if len(idx) else -1

        def skip(k):
            steps.append(Step("skip", f"skipped {self._label(t, k)}: {counts[k]} candidates > {self.max_candidates}",
                              observed=[int(ti[k]), int(tj[k]), int(tk[k])],
                              numbers=self._numbers(t, k) | {"max_candidates": self.max_candidates}))

        # first triangle
        while True:
            k = pick_next(~done)
            if k < 0:
                return _Chain("ambiguous", "no triangle with at most max_candidates candidates to start from", [],
                              np.zeros((0, 0), dtype=np.int64))
            done[k] = True
            if self.count_of(t, k) > self.max_candidates:
                skip(k)
                continue
            break
        H, groups = self.hypotheses(t, k, sigma)
        used = [int(ti[k]), int(tj[k]), int(tk[k])]
        triangles = [used.copy()]
        n_sets = _n_sets(H)
        candidates.append(int(counts[k]))
        hyps.append(n_sets)
        steps.append(Step("pick", f"picked {self._label(t, k)}: {counts[k]} candidates"
                                  + (f", {len(H)} in a vertex order that fits the sides and handedness"
                                     if self.vertex_order == "sides" else ""),
                          observed=used.copy(), catalog=_distinct(H), groups=groups,
                          numbers=self._numbers(t, k) | {"hypotheses": len(H), "sets": n_sets},
                          layers=(Hypotheses.sample(used, H),)))
        if len(H) == 0:
            return _Chain("empty", f"no catalog triangle matches the first triangle {used[0]}-{used[1]}-{used[2]}",
                          used, H, suspects=used[::-1], culprit=used.copy(), candidates=candidates, hypotheses=hyps)
        prev = tuple(used)
        pivots = 0
        while not self._settled(V, used, triangles, H, n_sets, sigma, t["tol"]):
            if self.max_pivots is not None and pivots >= self.max_pivots:
                steps.append(Step("stop", f"pivot limit {self.max_pivots} reached with {n_sets} candidate "
                                          f"star sets", observed=used.copy(), catalog=_distinct(H),
                                  numbers={"hypotheses": len(H), "sets": n_sets}))
                return _Chain("ambiguous", f"{n_sets} star sets left after {pivots} pivots (the limit)", used, H,
                              pivots=pivots, candidates=candidates, hypotheses=hyps)
            in_used = np.zeros(m, dtype=bool)
            in_used[used] = True
            in_prev = np.zeros(m, dtype=bool)
            in_prev[list(prev)] = True
            n_prev = in_prev[ti].astype(int) + in_prev[tj] + in_prev[tk]
            n_used = in_used[ti].astype(int) + in_used[tj] + in_used[tk]
            k = pick_next(~done & (n_used == 3)) if self.close_triangles else -1
            if k < 0:
                k = pick_next(~done & (n_prev == 2))
            if k < 0:  # nothing shares two stars with the previous triangle: two with any used star
                k = pick_next(~done & (n_used >= 2))
            if k < 0:
                steps.append(Step("stop", f"no triangle left to pivot to; {n_sets} candidate star sets",
                                  observed=used.copy(), catalog=_distinct(H),
                                  numbers={"hypotheses": len(H), "sets": n_sets}))
                return _Chain("ambiguous", f"{n_sets} star sets left and no triangle to pivot to", used, H,
                              pivots=pivots, candidates=candidates, hypotheses=hyps)
            done[k] = True
            if self.count_of(t, k) > self.max_candidates:
                skip(k)
                continue
            obs3 = [int(ti[k]), int(tj[k]), int(tk[k])]
            O, groups = self.hypotheses(t, k, sigma)
            before, sets_before = len(H), n_sets
            shared = [s for s in obs3 if s in used]
            H, used, new = join(H, used, obs3, O)
            triangles.append(obs3)
            if self.vertex_order == "sides":  # every pair of stars, also across triangles
                H = self.consistent(V, used, triangles, H, sigma)
            pivots += 1
            n_sets = _n_sets(H)
            candidates.append(int(counts[k]))
            hyps.append(n_sets)
            steps.append(Step("pivot", f"pivoted to {self._label(t, k)} sharing stars "
                                       f"{'-'.join(map(str, shared))}: {counts[k]} candidates, "
                                       f"{sets_before} -> {n_sets} candidate star sets",
                              observed=obs3, catalog=_distinct(H), groups=groups,
                              numbers=self._numbers(t, k) | {"oriented": len(O), "hypotheses_before": before,
                                                             "hypotheses_after": len(H), "sets_before": sets_before,
                                                             "sets_after": n_sets, "pivot": pivots,
                                                             "shared": len(shared),
                                                             "new_star": -1 if new is None else new},
                              layers=(Hypotheses.sample(used, H, shared=shared),)))
            if len(H) == 0:
                if new is not None:
                    first_suspect = new
                else:  # a closed triangle: the newest of its stars first
                    first_suspect = max(obs3, key=used.index)
                rest = [s for s in used[::-1] if s != first_suspect]
                return _Chain("empty", f"no hypothesis survives triangle {'-'.join(map(str, obs3))}", used, H,
                              suspects=[first_suspect] + rest, culprit=obs3, pivots=pivots, candidates=candidates,
                              hypotheses=hyps)
            prev = tuple(obs3)
        # one set of catalog stars (or a few that differ by unresolved close pairs): its vertex order
        Hc = self.consistent(V, used, triangles, H, sigma)
        if len(Hc) == 0:  # the paper would report this set; it fits in no vertex order, so it is wrong
            steps.append(Step("stop", "the one star set left fits the observed stars in no vertex order (sides or "
                                      "handedness)", observed=used.copy(), catalog=_distinct(H),
                              numbers={"hypotheses": len(H), "sets": n_sets}))
            return _Chain("empty", "the remaining catalog stars fit the observed stars in no vertex order "
                                   "(sides or handedness)", used, Hc, suspects=used[::-1], culprit=used.copy(),
                          pivots=pivots, candidates=candidates, hypotheses=hyps,
                          answer=self._best(V, used, H, sigma) if n_sets == 1 else None)
        n_final = _n_sets(Hc)
        return _Chain("unique", "one star set left" if n_final == 1 else
                      f"{n_final} star sets left that differ only by unresolved close pairs",
                      used, Hc, pivots=pivots, candidates=candidates, hypotheses=hyps)

    def _chain_lists(self, V: np.ndarray, excluded: frozenset, t: dict, steps: list[Step]) -> _Chain:
        """The paper's pivoting: candidate lists of consecutive triangles pruned against each other.

        "Any solution in each list that does not have two stars in common with at least one solution in
        the other lists is discarded"; the next triangle shares two observed stars with the current one
        and meets its pruned list only. Ends when a list holds one star set; its vertex order is then
        taken from the sides and the handedness, as in the join.
        """
        ti, tj, tk, counts, priority = t["ti"], t["tj"], t["tk"], t["counts"], t["priority"]
        sigma, m = t["sigma"], t["stars"]
        oriented = self.pivoting == "shared-star"
        done = np.zeros(len(ti), dtype=bool)
        if excluded:
            ex = np.zeros(m, dtype=bool)
            ex[list(excluded)] = True
            done |= ex[ti] | ex[tj] | ex[tk]
        candidates: list[int] = []
        hyps: list[int] = []

        def next_triangle(mask):
            while True:
                idx = np.flatnonzero(mask & ~done)
                if not len(idx):
                    return -1
                k = int(idx[np.argmin(priority[idx])])
                done[k] = True
                if self.count_of(t, k) <= self.max_candidates:
                    return k
                steps.append(Step("skip", f"skipped {self._label(t, k)}: {counts[k]} candidates > "
                                          f"{self.max_candidates}", observed=[int(ti[k]), int(tj[k]), int(tk[k])],
                                  numbers=self._numbers(t, k) | {"max_candidates": self.max_candidates}))

        def listed(k):
            rows = self.candidates(t, k)
            if oriented:  # rows over the observed stars (ti, tj, tk)[k], every vertex order that may fit
                return rows, self.orient(t, k, rows, sigma)[0]
            return rows, self.tri[rows].astype(np.int64)

        k = next_triangle(np.ones(len(ti), dtype=bool))
        if k < 0:
            return _Chain("ambiguous", "no triangle with at most max_candidates candidates to start from", [],
                          np.zeros((0, 0), dtype=np.int64))
        cur_obs = [int(ti[k]), int(tj[k]), int(tk[k])]
        rows, cur = listed(k)
        used = cur_obs.copy()
        candidates.append(int(counts[k]))
        hyps.append(_n_sets(cur))
        steps.append(Step("pick", f"picked {self._label(t, k)}: {counts[k]} candidates", observed=cur_obs.copy(),
                          catalog=_distinct(cur), groups=_groups(self.tri, rows, rows),
                          numbers=self._numbers(t, k) | {"sets": _n_sets(cur)},
                          layers=(Hypotheses.sample(cur_obs, cur),)))
        if len(cur) == 0:
            return _Chain("empty", f"no catalog triangle matches the first triangle {'-'.join(map(str, cur_obs))}",
                          used, cur, suspects=used[::-1], culprit=used.copy(), candidates=candidates, hypotheses=hyps)
        prev, prev_obs = None, None
        pivots = 0
        while _n_sets(cur) != 1 and (prev is None or _n_sets(prev) != 1):
            if self.max_pivots is not None and pivots >= self.max_pivots:
                steps.append(Step("stop", f"pivot limit {self.max_pivots} reached with {_n_sets(cur)} candidate "
                                          "star sets", observed=cur_obs.copy(), numbers={"sets": _n_sets(cur)}))
                return _Chain("ambiguous", f"{_n_sets(cur)} star sets left after {pivots} pivots (the limit)", used,
                              cur, pivots=pivots, candidates=candidates, hypotheses=hyps)
            in_cur = np.zeros(m, dtype=bool)
            in_cur[cur_obs] = True
            k = next_triangle(in_cur[ti].astype(int) + in_cur[tj] + in_cur[tk] == 2)
            if k < 0:
                steps.append(Step("stop", f"no triangle sharing two stars with triangle {'-'.join(map(str, cur_obs))} "
                                          f"is left; {_n_sets(cur)} candidate star sets", observed=cur_obs.copy(),
                                  numbers={"sets": _n_sets(cur)}))
                return _Chain("ambiguous", f"{_n_sets(cur)} star sets left and no triangle to pivot to", used, cur,
                              pivots=pivots, candidates=candidates, hypotheses=hyps)
            new_obs = [int(ti[k]), int(tj[k]), int(tk[k])]
            rows, new = listed(k)
            before = _n_sets(cur)
            M = int(max(cur.max(initial=0), new.max(initial=0))) + 1
            if oriented:  # the two common catalog stars sit on the two observed stars the triangles share
                s1, s2 = [s for s in new_obs if s in cur_obs]
                kc = cur[:, cur_obs.index(s1)] * M + cur[:, cur_obs.index(s2)]
                kn = new[:, new_obs.index(s1)] * M + new[:, new_obs.index(s2)]
                keep_cur, keep_new = np.isin(kc, kn), np.isin(kn, kc)
            else:
                pc, pn = _pair_keys(cur, M), _pair_keys(new, M)
                keep_cur = np.isin(pc, pn).any(axis=1)
                keep_new = np.isin(pn, pc).any(axis=1)
            prev, prev_obs = cur[keep_cur], cur_obs
            cur, cur_obs = new[keep_new], new_obs
            added = [s for s in new_obs if s not in used]
            used += added
            pivots += 1
            candidates.append(int(counts[k]))
            hyps.append(_n_sets(cur))
            steps.append(Step("pivot", f"pivoted to {self._label(t, k)}: {counts[k]} candidates, {_n_sets(cur)} share "
                                       f"two stars with the previous list ({before} -> {_n_sets(prev)})",
                              observed=new_obs.copy(), catalog=_distinct(cur), groups=_groups(self.tri, rows, rows),
                              numbers=self._numbers(t, k) | {"sets": _n_sets(cur), "previous_before": before,
                                                             "previous_after": _n_sets(prev), "pivot": pivots},
                              layers=(Hypotheses.sample(new_obs, cur, shared=[s for s in new_obs if s in prev_obs]),)))
            if len(cur) == 0:
                rest = [s for s in used[::-1] if s not in added]
                return _Chain("empty", f"no candidate of triangle {'-'.join(map(str, new_obs))} shares two stars "
                                       "with the previous list", used, cur, suspects=added + rest,
                              culprit=new_obs.copy(), pivots=pivots, candidates=candidates, hypotheses=hyps)
        one, one_obs = (cur, cur_obs) if _n_sets(cur) == 1 else (prev, prev_obs)
        H = one if oriented else one[:1][:, _PERMS].reshape(-1, 3)
        Hc = self.consistent(V, one_obs, [one_obs], H, sigma)
        if len(Hc) == 0:  # the paper would report this set; it fits in no vertex order, so it is wrong
            steps.append(Step("stop", "the one star set left fits the observed stars in no vertex order (sides or "
                                      "handedness)", observed=one_obs.copy(), catalog=_distinct(H)))
            return _Chain("empty", "the remaining catalog stars fit the observed stars in no vertex order "
                                   "(sides or handedness)", one_obs, Hc, suspects=used[::-1], culprit=one_obs.copy(),
                          pivots=pivots, candidates=candidates, hypotheses=hyps,
                          answer=self._best(V, one_obs, H, sigma))
        return _Chain("unique", f"one star set left for triangle {'-'.join(map(str, one_obs))}", one_obs, Hc,
                      pivots=pivots, candidates=candidates, hypotheses=hyps)

    def _settled(self, V: np.ndarray, used: list[int], triangles: list[list[int]], H: np.ndarray, n_sets: int,
                 sigma: float, tol: float) -> bool:
        """One set of catalog stars left, or a few that differ only by unresolved close pairs."""
        if n_sets <= 1:
            return True
        if n_sets > MAX_EQUIVALENT:
            return False
        stars = np.unique(H)
        if self.vertex_order == "paper" and not _has_close_pair(self.catalog.xyz[stars], tol):
            return False  # different sets can only be one pattern through catalog stars closer than tol
        Hc = self.consistent(V, used, triangles, H, sigma)
        if self.vertex_order == "paper" and _n_sets(Hc) < n_sets:
            return False  # the paper tells sets apart by pivoting only, never by their sides
        return len(Hc) > 0 and (_n_sets(Hc) == 1 or self._equivalent(Hc, tol))

    def _equivalent(self, H: np.ndarray, tol: float) -> bool:
        """A few hypotheses that put every observed star on catalog stars closer than tol to each other
        (unresolved close pairs: one pattern at this noise)."""
        if len(H) < 2 or len(H) > MAX_EQUIVALENT:
            return False
        xyz = self.catalog.xyz
        return bool(np.all(angular_distance(xyz[H], xyz[H[:1]]) <= tol))

    def _best(self, V: np.ndarray, used: list[int], H: np.ndarray, sigma: float) -> np.ndarray:
        """Among equivalent hypotheses, the one that fits the observed stars best."""
        if len(H) == 1:
            return H[0]
        b = V[used]
        losses = [svd_attitude(b, self.catalog.xyz[h], sigma).loss for h in H]
        return H[int(np.argmin(losses))]


# ---------------------------------------------------------------------- helpers

def join(H: np.ndarray, used: list[int], obs3: list[int], O: np.ndarray) -> tuple[np.ndarray, list[int], int | None]:
    """Join hypotheses H (columns: observed stars `used`) with the oriented candidates O of the observed
    triangle obs3 (columns in obs3's order) on the shared observed stars.

    Two shared stars: a hypothesis survives with every candidate that has its catalog stars on the
    two shared observed stars, and the candidate's third star is appended (never a catalog star the
    hypothesis already uses). Three shared stars (a closed triangle): the hypothesis' three stars must
    be a candidate as they are. Returns (H', used', new): new is the observed star added, or None.
    """
    pos = [used.index(s) if s in used else -1 for s in obs3]
    shared = [c for c in range(3) if pos[c] >= 0]
    if len(shared) < 2:
        raise ValueError("a pivot triangle must share at least two stars with the hypotheses")
    if len(H) == 0 or len(O) == 0:
        new = None if len(shared) == 3 else obs3[[c for c in range(3) if pos[c] < 0][0]]
        width = len(used) + (0 if new is None else 1)
        return np.zeros((0, width), dtype=np.int64), used + ([] if new is None else [new]), new
    M = int(max(H.max(), O.max())) + 1
    if len(shared) == 3:
        hk = (H[:, pos[0]] * M + H[:, pos[1]]) * M + H[:, pos[2]]
        ok_ = (O[:, 0] * M + O[:, 1]) * M + O[:, 2]
        return H[np.isin(hk, ok_)], used, None
    c1, c2 = shared
    c3 = 3 - c1 - c2
    okey = O[:, c1] * M + O[:, c2]
    o = np.argsort(okey, kind="stable")
    okey_s, third = okey[o], O[o, c3]
    hkey = H[:, pos[c1]] * M + H[:, pos[c2]]
    lo = np.searchsorted(okey_s, hkey, side="left")
    hi = np.searchsorted(okey_s, hkey, side="right")
    cnt = hi - lo
    total = int(cnt.sum())
    rows = np.repeat(np.arange(len(H)), cnt)
    offs = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    newc = third[np.repeat(lo, cnt) + offs]
    Hn = H[rows]
    ok = ~np.any(Hn == newc[:, None], axis=1)
    new = obs3[c3]
    return np.concatenate([Hn[ok], newc[ok, None]], axis=1), used + [new], new


def _pair_keys(S: np.ndarray, M: int) -> np.ndarray:
    """(n, 3) keys of the three unordered star pairs of each star set."""
    a = np.sort(S, axis=1)
    return np.stack([a[:, 0] * M + a[:, 1], a[:, 0] * M + a[:, 2], a[:, 1] * M + a[:, 2]], axis=1)


@lru_cache(maxsize=64)
def _combinations(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (i < j < k) of n stars, as three index arrays (read-only, cached)."""
    c = np.fromiter(itertools.chain.from_iterable(itertools.combinations(range(n), 3)), dtype=np.int64)
    c = c.reshape(-1, 3)
    out = tuple(np.ascontiguousarray(c[:, s]) for s in range(3))
    for a in out:
        a.flags.writeable = False
    return out


def _has_close_pair(xyz: np.ndarray, tol: float) -> bool:
    """Whether two of these (distinct) catalog stars lie within tol of each other."""
    if len(xyz) < 2:
        return False
    d = angular_distance(xyz[:, None, :], xyz[None, :, :])
    return bool(np.any(d[np.triu_indices(len(xyz), 1)] <= tol))


def _n_sets(H: np.ndarray) -> int:
    """How many distinct sets of catalog stars the hypotheses hold (vertex orders of one set count once).

    A set is keyed by the wrapping sum of a fixed random 64-bit word per catalog star: independent
    of the order, and two different sets collide with probability 2^-64.
    """
    if len(H) <= 1:
        return len(H)
    words = _star_words(int(H.max()) + 1)
    return int(len(np.unique(words[H].sum(axis=1, dtype=np.uint64))))


_WORDS = np.zeros(0, dtype=np.uint64)


def _star_words(n: int) -> np.ndarray:
    """The first n of a fixed sequence of random 64-bit words (grown on demand, same for every run)."""
    global _WORDS
    if len(_WORDS) < n:
        size = max(n, 2 * len(_WORDS), 8192)
        _WORDS = np.random.default_rng(0x5E75).integers(0, np.iinfo(np.uint64).max, size=size, dtype=np.uint64,
                                                        endpoint=True)
    return _WORDS


def _distinct(H: np.ndarray) -> list[int]:
    """Distinct catalog rows of the first hypotheses, capped."""
    return np.unique(H[:4 * CAP]).astype(int)[:CAP].tolist() if H.size else []


def _groups(tri: np.ndarray, rows: np.ndarray, oriented_rows: np.ndarray) -> list[tuple[int, ...]]:
    """Candidate catalog triangles to draw, those that fit in some vertex order first, capped."""
    if len(oriented_rows) == len(_PERMS) * len(rows):  # vertex_order="paper": every candidate
        return list(map(tuple, tri[rows[:CAP]].astype(int).tolist()))
    first = np.unique(oriented_rows[:64 * CAP])[:CAP]
    if len(first) < CAP and len(rows) > len(first):
        rest = rows[~np.isin(rows, first)][:CAP - len(first)]
        first = np.concatenate([first, rest])
    return list(map(tuple, tri[first].astype(int).tolist()))


# ---------------------------------------------------------------------- figures for the report

def report(fov_deg: float = 8.0, width: int = 1024, mag: float = 6.0, sigma: float = MOMENT_SIGMA_REF_RAD,
           n_triangles: int = 1000, seed: int = 1) -> dict:
    """Database figures (built in a throw-away cache, then loaded), the polar moment's convergence with
    the recursion depth (Fig. 7), its simulated sigma bound (Fig. 8) and the area sigma of eqs. 20-24
    against a Monte Carlo."""
    import os
    import tempfile

    from skyview.catalog import load_guide_catalog

    cat = load_guide_catalog().brighter_than(mag)
    cam = Camera.from_fov(fov_deg, width)
    old = os.environ.get("SKYVIEW_CACHE")
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["SKYVIEW_CACHE"] = tmp
        try:
            built = TriangleMethod(cat, cam, sigma)
            t0 = time.perf_counter()
            loaded = TriangleMethod(cat, cam, sigma)
            init_s = time.perf_counter() - t0
        finally:
            if old is None:
                os.environ.pop("SKYVIEW_CACHE", None)
            else:
                os.environ["SKYVIEW_CACHE"] = old
    info = built.database_info
    counts = triangle_counts(cat, built.max_radius_rad, np.radians(fov_deg))
    out = {"database": {"catalog_stars": len(cat), "triangles": info["triangles"], **counts,
                        "nbytes": info["nbytes"], "file_bytes": info["file_bytes"], "build_s": info["build_s"],
                        "load_s": loaded.database_info["load_s"], "index_s": loaded.database_info["index_s"],
                        "init_s": init_s, "moment_sigma_coef": info["moment_sigma_coef"]}}
    rng = np.random.default_rng(seed)
    tri = built.tri[rng.choice(len(built.tri), size=n_triangles, replace=False)].astype(np.int64)
    conv = moment_convergence(cat.xyz, tri, range(0, 8))
    out["convergence"] = {
        f"{d}->{d + 1}": {"median": float(np.median(np.abs(conv[d + 1] - conv[d]) / conv[d + 1])),
                          "max": float(np.max(np.abs(conv[d + 1] - conv[d]) / conv[d + 1]))} for d in range(1, 7)}
    out["depth_3_vs_7"] = float(np.median(np.abs(conv[3] - conv[7]) / conv[7]))
    I, s = built.moment_sigma_samples.T
    line = built.moment_sigma_coef[0] + built.moment_sigma_coef[1] * I
    out["moment_sigma"] = {"samples": len(I), "line_over_sd_median": float(np.median(line / s)),
                           "line_over_sd_min": float(np.min(line / s))}
    V = cat.xyz[tri[:300]]
    mc = np.array([np.std(sph.area(*(add_noise(np.repeat(V[k, c][None], 300, 0), sigma, rng) for c in range(3))))
                   for k in range(len(V))])
    a, b, c = sph.sides(V[:, 0], V[:, 1], V[:, 2])
    paper = sph.area_sigma_paper(a, b, c, sigma)
    stars = sph.area_sigma_stars(V[:, 0], V[:, 1], V[:, 2], sigma)
    q = [0.05, 0.5, 0.95]
    out["area_sigma_mc"] = {"mc_over_eq24": np.quantile(mc / paper, q).tolist(),
                            "mc_over_stars": np.quantile(mc / stars, q).tolist(), "quantiles": q}
    return out
