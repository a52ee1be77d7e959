"""The triangle method's databases (Cole & Crassidis 2006, section III; the method is
`skyview.identify.triangle`): the stored triangle database (built, cached, counted), the
polar-moment sigma line of the paper's simulation, and the figures of the report.

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
  counter below): 38 bytes a triangle, 55 MB at 8 deg, memory-mapped on load (~2 ms). The build
  holds about BUILD_FIXED_BYTES + BYTES_PER_TRIANGLE bytes a triangle at its peak (400 MB + 52 B a
  triangle of `triangles_estimate`, which counts ~1.3 times the triangles kept), the estimate checked
  against the memory budget (`database.check_memory`, 4 GB by default) before it starts: ~300 MB of
  chunk work, then ~60 bytes a kept triangle while the arrays are sorted and indexed (one array
  replaced at a time, the k-vectors a chunk at a time: `_kvector_arrays`). Measured peak RSS
  (/usr/bin/time, the whole process): 434 MB for 8 deg / Hp 6 (1.45 M triangles, built in 11 s at
  load 0.5 on the shared 2-core machine) and 2.8 GB for 20 deg / Hp 6 (48.4 M triangles, 1.8 GB on
  disk, built in 7 minutes at low priority and load 2.5, most of it the polar moments; 5.3 GB,
  over the budget, before the k-vectors were built in chunks). The paper variant still builds it
  when asked; the improved variant does not need it.
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
"""

from __future__ import annotations

import time

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog
from skyview.identify import database as database_module
from skyview.identify import spherical as sph
from skyview.identify.kvector import KVector
from skyview.identify.synthetic import add_noise
from skyview.identify.verify import angular_distance

DATABASE_VERSION = 5
MOMENT_SIGMA_VERSION = 1
BYTES_PER_TRIANGLE = 52  # peak memory of the build per estimated triangle (~60 B a kept one: the sort, the index)
BUILD_FIXED_BYTES = 400 * 2 ** 20  # and what it holds whatever the size (Python, one chunk, the moment fit)
CHUNK_CANDIDATES = 1_000_000  # candidate third stars made and tested at once while building (~100 MB)
BLOCK = 256  # triangles per block of the candidate counter
MOMENT_SIGMA_TRIANGLES = 1000
MOMENT_SIGMA_TRIALS = 100
MOMENT_SIGMA_MARGIN = 1.1
MOMENT_SIGMA_REF_RAD = 87e-6  # the paper's noise; the bound is stored per unit sigma
MOMENT_SIGMA_SEED = 20060101
MOMENT_PARAMS = [MOMENT_SIGMA_TRIANGLES, MOMENT_SIGMA_TRIALS, MOMENT_SIGMA_MARGIN, MOMENT_SIGMA_REF_RAD,
                 MOMENT_SIGMA_SEED]


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
    from scipy.optimize import linprog  # here: scipy.optimize costs ~0.2 s to import, only a build needs it

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
    del pairs
    # one array at a time, each freed as soon as it is replaced: the peak stays near the arrays kept
    # (the build's peak is BYTES_PER_TRIANGLE a triangle; 48 M triangles at 20 deg)
    tri = np.concatenate(parts_tri) if parts_tri else np.zeros((0, 3), dtype=idx_dtype)
    del parts_tri
    area = np.concatenate(parts_area) if parts_area else np.zeros(0, dtype=np.float32)
    del parts_area
    moment = np.concatenate(parts_moment) if parts_moment else np.zeros(0, dtype=np.float32)
    del parts_moment
    cap = np.concatenate(parts_cap) if parts_cap else np.zeros(0, dtype=np.float32)
    del parts_cap
    counts = np.array([n_sides, len(tri)], dtype=np.int64)
    order = np.lexsort((tri[:, 2], tri[:, 1], tri[:, 0], area))
    tri = tri[order]
    area = area[order]
    moment = moment[order]
    cap = cap[order]
    del order
    m_order = np.argsort(moment, kind="stable").astype(np.int32)
    rank = np.empty(len(m_order), dtype=np.int32)
    rank[m_order] = np.arange(len(m_order), dtype=np.int32)
    area_k, area_coef = _kvector_arrays(area, fit)
    moment_sorted = moment[m_order]
    del moment
    moment_k, moment_coef = _kvector_arrays(moment_sorted, fit)
    block_rank = _block_sorted(rank, BLOCK)
    return {
        "tri": tri, "cap": cap,
        "area": area, "area_k": area_k, "area_coef": area_coef,
        "moment_sorted": moment_sorted, "moment_order": m_order, "moment_rank": rank,
        "moment_k": moment_k, "moment_coef": moment_coef, "block_rank": block_rank,
        "fit": np.array(fit), "counts": counts,
    }


KVECTOR_CHUNK = 1 << 20  # values per step of `_kvector_arrays`


def _kvector_arrays(sorted_values: np.ndarray, fit: str) -> tuple[np.ndarray, np.ndarray]:
    """(k as int32, coef) of KVector(sorted_values as float64, fit, presorted=True), KVECTOR_CHUNK values
    at a time: KVector holds ~60 bytes a value of float64 temporaries (the fit's x, g and r, the curve z),
    3 GB for the 48 M triangles at 20 deg, where this holds one float64 copy of the values and the k.
    The same curve and k but for the fit's two sums, added chunk by chunk (their rounding differs from
    one dot product's in the last bits): every look-up is exact whatever the curve (`KVector.range`
    trims its superset by bisection)."""
    s = np.asarray(sorted_values, dtype=np.float64)  # float32 values: exact in float64
    n = s.size
    if n <= 2:
        kv = KVector(s, fit=fit, presorted=True)
        return kv.k.astype(np.int32), kv.coef
    for i in range(0, n, KVECTOR_CHUNK):
        c = s[i:i + KVECTOR_CHUNK + 1]
        if not (np.all(np.isfinite(c)) and np.all(c[1:] >= c[:-1])):
            raise ValueError("k-vector values must be finite and sorted")
    L = float(n - 1)
    # KVector's end points z0 = s_min - eps and z0 + delta = s_max + eps: those of the two end values'
    z0, delta = (float(c) for c in KVector(s[[0, -1]], presorted=True).coef[:2])
    a = 0.0
    if fit == "parabola":  # KVector's least-squares curvature, its sums a chunk at a time
        gg = gr = 0.0
        for i in range(0, n, KVECTOR_CHUNK):
            x = np.arange(i, min(i + KVECTOR_CHUNK, n), dtype=np.float64)
            g = x * x - L * x
            gg += float(g @ g)
            gr += float(g @ (s[i:i + len(x)] - (z0 + delta / L * x)))
        if gg > 0:
            a = gr / gg
        lim = 0.999 * delta / (L * L)
        a = float(np.clip(a, -lim, lim))
    b = delta / L - a * L
    k = np.empty(n, dtype=np.int32)
    for i in range(0, n, KVECTOR_CHUNK):
        j = np.arange(i, min(i + KVECTOR_CHUNK, n), dtype=np.float64)
        z = z0 + b * j + a * j * j
        if i == 0:
            z[0] = z0
        if i + len(j) == n:
            z[-1] = z0 + delta  # above s_max: k = n, as KVector's
        k[i:i + len(j)] = np.searchsorted(s, z, side="right")
    return k, np.array([z0, b, a])


def _camera_moment_sigma(xyz: np.ndarray, tri: np.ndarray, cap: np.ndarray, cap_limit: float, depth: int
                         ) -> dict[str, np.ndarray]:
    """fit_moment_sigma on the stored triangles that fit a camera (cap <= cap_limit), in their stored
    order: the draw a database built for that camera alone makes (the same seed, the same rows)."""
    # the rows in their stored dtype (int16): an int64 copy of 48 M triangles would take 1.2 GB
    coef, samples = fit_moment_sigma(xyz, tri[np.asarray(cap) <= cap_limit], depth,
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



def load_triangle_database(catalog: GuideCatalog, camera: Camera, max_radius_rad: float, depth: int,
                           kvector_fit: str, name: str = "triangle") -> tuple[dict, dict]:
    """The stored triangle database (caps up to max_radius_rad), memory-mapped from the cache or built
    once, read for `camera`, and the polar-moment sigma line of the triangles that fit the camera (a
    small cached file of its own). Returns (fields, info): fields are what the method reads (tri, area,
    moment_order, moment_rank, kv_area, kv_moment, block_rank, cap, cap_limit, moment_sigma_coef,
    moment_sigma_samples, database_key); info the cache's figures and the counts."""
    params = {"max_radius_rad": max_radius_rad, "depth": depth, "kvector_fit": kvector_fit,
              "moment_sigma": MOMENT_PARAMS, "version": DATABASE_VERSION}
    key = database_module.make_key(name, params, catalog, None)
    n_tri = triangles_estimate(len(catalog), max_radius_rad)
    # built in chunks: ~BYTES_PER_TRIANGLE bytes a triangle at the peak, ~10 us each (the polar moment)
    what = (f"the triangle database ({len(catalog):,} stars, caps up to "
            f"{np.degrees(max_radius_rad):.1f} deg, ~{n_tri / 1e6:.1f} M triangles)")
    arrays, info = database_module.load_or_build(
        key, lambda: build_triangle_database(catalog, max_radius_rad, depth, kvector_fit),
        mmap=True, what=what, estimate_s=10e-6 * n_tri, estimate_bytes=BUILD_FIXED_BYTES + BYTES_PER_TRIANGLE * n_tri)
    t0 = time.perf_counter()
    fit = str(arrays["fit"][()])
    # the database serves every camera whose half-diagonal is below its range; a look-up keeps the
    # triangles that fit THIS camera's circumscribed circle, as a database of its own would
    f = {"tri": arrays["tri"], "area": arrays["area"], "moment_order": arrays["moment_order"],
         "moment_rank": arrays["moment_rank"], "block_rank": arrays["block_rank"],
         "kv_area": _kvector(arrays["area"], arrays["area_k"], arrays["area_coef"], fit),
         "kv_moment": _kvector(arrays["moment_sorted"], arrays["moment_k"], arrays["moment_coef"], fit),
         "cap": arrays["cap"], "cap_limit": float(camera.half_diagonal_rad), "database_key": key}
    # the polar-moment sigma line of the triangles that fit this camera (the paper's simulation on
    # 1000 of them): what a database of its own would hold, a small cached file of its own
    mkey = database_module.make_key("triangle-moment", {
        "triangles": database_module.key_string(key), "cap_limit": f["cap_limit"],
        "version": MOMENT_SIGMA_VERSION}, catalog, None)
    line, _ = database_module.load_or_build(
        mkey, lambda: _camera_moment_sigma(catalog.xyz, f["tri"], f["cap"], f["cap_limit"], depth),
        what="the polar-moment sigma line of the triangle method", estimate_s=2.0)
    f["moment_sigma_coef"] = np.asarray(line["moment_sigma_coef"], dtype=np.float64)
    f["moment_sigma_samples"] = np.asarray(line["moment_sigma_samples"])
    counts = dict(zip(COUNT_NAMES, (int(c) for c in arrays["counts"])))
    info.update(triangles=len(f["tri"]), triangle_counts=counts, fov_deg=float(camera.fov_deg),
                max_radius_deg=float(np.degrees(max_radius_rad)), catalog_stars=len(catalog),
                moment_sigma_coef=f["moment_sigma_coef"].tolist(), database="triangles",
                index_s=time.perf_counter() - t0)
    return f, info


# ---------------------------------------------------------------------- figures for the report
