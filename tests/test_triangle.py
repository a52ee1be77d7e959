"""The spherical-triangle method (Cole & Crassidis): geometry, database, search, and end to end."""

import itertools

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from skyview.core.attitude import random_attitudes
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, radec_to_vec
from skyview.core.errors import BadInput
from skyview.identify import FAILED, IDENTIFIED, METHODS, database, make_identifier
from skyview.identify import spherical as sph
from skyview.identify.angle import AngleMethod
from skyview.identify.base import Observation
from skyview.identify.layers import Hypotheses
from skyview.identify.synthetic import add_noise, synthetic_frame
from skyview.identify.triangle import IMPROVED_PARAMS, TriangleMethod, join
from skyview.identify.triangle_database import _triangle_chunks, catalog_triangles, moment_convergence, upper_line
from skyview.identify.verify import angular_distance
from skyview.simulate.render import simulate_image
from skyview.simulate.truth import wrong_matches
from skyview.solver.pipeline import MethodSolver

SIGMA = 87e-6
RNG_SEED = 31


def random_triangles(rng, n, size_rad=0.05):
    """n random small triangles (vertices within size_rad of a random centre)."""
    c = rng.normal(size=(n, 3))
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    out = []
    for _ in range(3):
        e = rng.normal(size=(n, 3)) * size_rad
        e -= np.sum(e * c, axis=1, keepdims=True) * c
        v = c + e
        out.append(v / np.linalg.norm(v, axis=1, keepdims=True))
    return out


# ---------------------------------------------------------------------- geometry

def test_area_hand_computed_and_planar_limit():
    x, y, z = np.eye(3)
    assert sph.area(x, y, z) == pytest.approx(np.pi / 2, rel=1e-14)  # the octant
    assert sph.lhuilier(np.pi / 2, np.pi / 2, np.pi / 2) == pytest.approx(np.pi / 2, rel=1e-14)
    rng = np.random.default_rng(RNG_SEED)
    # small triangles: the spherical excess tends to the plane (Heron) area, relative error ~ size^2
    A, B, C = random_triangles(rng, 200, size_rad=1e-3)
    a, b, c = sph.sides(A, B, C)
    s = (a + b + c) / 2
    heron = np.sqrt(s * (s - a) * (s - b) * (s - c))
    ok = heron > 1e-9  # leave out slivers, whose Heron area is itself ill-conditioned
    np.testing.assert_allclose(sph.lhuilier(a, b, c)[ok], heron[ok], rtol=1e-5)
    # L'Huilier agrees with the solid-angle formula of Van Oosterom & Strackee for any size
    A, B, C = random_triangles(rng, 500, size_rad=0.3)
    vs = 2 * np.arctan2(np.abs(sph.triple(A, B, C)),
                        1 + np.sum(A * B, 1) + np.sum(B * C, 1) + np.sum(C * A, 1))
    np.testing.assert_allclose(sph.area(A, B, C), vs, rtol=1e-8, atol=1e-15)


def test_rotation_invariance_of_area_and_polar_moment():
    rng = np.random.default_rng(RNG_SEED)
    A, B, C = random_triangles(rng, 100, size_rad=0.04)
    area, moment = sph.area(A, B, C), sph.polar_moment(A, B, C)
    cap = sph.enclosing_cap_radius(A, B, C)
    for Q in random_attitudes(5, rng):
        rA, rB, rC = A @ Q.T, B @ Q.T, C @ Q.T
        np.testing.assert_allclose(sph.area(rA, rB, rC), area, rtol=1e-9)
        np.testing.assert_allclose(sph.polar_moment(rA, rB, rC), moment, rtol=1e-8)
        np.testing.assert_allclose(sph.enclosing_cap_radius(rA, rB, rC), cap, rtol=1e-9)
        assert np.all(np.sign(sph.triple(rA, rB, rC)) == np.sign(sph.triple(A, B, C)))  # rotations keep handedness
    # the vertex order changes neither area nor polar moment; a mirror keeps them but flips the handedness
    np.testing.assert_allclose(sph.area(B, A, C), area, rtol=1e-12)
    np.testing.assert_allclose(sph.polar_moment(C, A, B), moment, rtol=1e-9)
    M = np.diag([1.0, 1.0, -1.0])
    np.testing.assert_allclose(sph.polar_moment(A @ M, B @ M, C @ M), moment, rtol=1e-9)
    assert np.all(np.sign(sph.triple(A @ M, B @ M, C @ M)) == -np.sign(sph.triple(A, B, C)))


def test_polar_moment_closed_form_and_subdivision():
    rng = np.random.default_rng(RNG_SEED)
    A, B, C = random_triangles(rng, 50, size_rad=2e-3)
    a, b, c = sph.sides(A, B, C)
    J = sph.planar_polar_moment(a, b, c)  # A (a^2 + b^2 + c^2) / 36
    ok = J > 1e-6 * np.max(J)
    for depth in range(0, 6):
        # the depth-d sum of the pieces' centroid moments is J (1 - 4^-d) for a plane triangle
        np.testing.assert_allclose(sph.polar_moment(A, B, C, depth)[ok], J[ok] * (1 - 4.0 ** -depth), rtol=1e-4,
                                   atol=1e-30)
    # the shared-grid evaluation is the recursive subdivision of the paper (Fig. 6)
    A, B, C = random_triangles(rng, 20, size_rad=0.05)
    for depth in range(0, 5):
        P, Q, R = sph.subdivide(A, B, C, depth)
        assert P.shape == (20, 4 ** depth, 3)
        np.testing.assert_allclose(sph.area(P, Q, R).sum(axis=1), sph.area(A, B, C), rtol=1e-9)
        G = sph.centroid(A, B, C)[:, None, :]
        ref = np.sum(sph.arc(sph.normalize(P + Q + R), G) ** 2 * sph.area(P, Q, R), axis=1)
        np.testing.assert_allclose(sph.polar_moment(A, B, C, depth), ref, rtol=1e-9)


def test_polar_moment_converges_with_depth(cat):
    tri = catalog_triangles(cat.xyz, np.radians(8.0))[::1999][:100]  # catalog triangles, spread out
    conv = moment_convergence(cat.xyz, tri, range(1, 6))
    change = [np.median(np.abs(conv[d + 1] - conv[d]) / conv[d + 1]) for d in range(1, 5)]
    # each level changes the value about 4 times less than the one before (Fig. 7); depth 3 -> 4: ~1 %
    assert all(change[k + 1] < change[k] / 3 for k in range(len(change) - 1))
    assert 0.005 < change[2] < 0.02


def test_enclosing_cap_against_brute_force():
    rng = np.random.default_rng(RNG_SEED)
    A, B, C = random_triangles(rng, 16, size_rad=0.05)
    r = sph.enclosing_cap_radius(A, B, C)
    obtuse = 0
    for k in range(16):
        pts = np.stack([A[k], B[k], C[k]])
        c0 = sph.centroid(A[k], B[k], C[k])
        e1 = np.cross(c0, [0.0, 0.0, 1.0] if abs(c0[2]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(c0, e1)

        def worst(xy):
            c = c0 + xy[0] * e1 + xy[1] * e2
            return np.max(angular_distance(pts, c / np.linalg.norm(c)))

        best = min(minimize(worst, x0, method="Nelder-Mead", options={"xatol": 1e-12, "fatol": 1e-14}).fun
                   for x0 in ([0.0, 0.0], [0.01, 0.0], [0.0, 0.01]))
        assert r[k] == pytest.approx(best, rel=1e-5)
        obtuse += r[k] == pytest.approx(max(sph.sides(A[k], B[k], C[k])) / 2, rel=1e-9)
    assert 0 < obtuse < 16  # both cases: the longest side as diameter, and the circumscribed cap


def test_area_jacobian_and_sigma_against_monte_carlo():
    rng = np.random.default_rng(RNG_SEED)
    A, B, C = random_triangles(rng, 30, size_rad=0.04)
    a, b, c = sph.sides(A, B, C)
    H = sph.area_jacobian(a, b, c)
    h = 1e-7  # eqs. 20-23 are the derivatives of L'Huilier's formula
    num = np.stack([(sph.lhuilier(a + h, b, c) - sph.lhuilier(a - h, b, c)) / (2 * h),
                    (sph.lhuilier(a, b + h, c) - sph.lhuilier(a, b - h, c)) / (2 * h),
                    (sph.lhuilier(a, b, c + h) - sph.lhuilier(a, b, c - h)) / (2 * h)], axis=1)
    np.testing.assert_allclose(H, num, rtol=1e-3)  # near-slivers curve hard: a loose finite difference
    # Monte Carlo: 2000 noisy measurements of each triangle
    mc = np.array([np.std(sph.area(*(add_noise(np.repeat(P[k:k + 1], 2000, 0), SIGMA, rng) for P in (A, B, C))))
                   for k in range(len(A))])
    stars = sph.area_sigma_stars(A, B, C, SIGMA)
    paper = sph.area_sigma_paper(a, b, c, SIGMA)
    # with the covariance of the sides of noisy stars the linearisation matches (sd of the sd: 1.6 %)
    np.testing.assert_allclose(mc / stars, 1.0, atol=0.07)
    # eq. 24 as printed (independent sides, variance sigma^2) under-states sigma_A for these triangles
    assert np.median(mc / paper) > 1.1
    # an equilateral triangle: sqrt(3) too small in the plane limit
    phi = np.pi / 2 + np.array([0.0, 2.0, 4.0]) * np.pi / 3
    P = sph.normalize(np.stack([np.ones(3), 0.005 * np.cos(phi), 0.005 * np.sin(phi)], axis=1))
    ratio = sph.area_sigma_stars(P[0], P[1], P[2], SIGMA) / sph.area_sigma_paper(*sph.sides(P[0], P[1], P[2]), SIGMA)
    assert ratio == pytest.approx(np.sqrt(3), rel=1e-4)


def test_fast_forms_give_the_same_numbers():
    """The plain-float and fewer-call forms the search uses for a few triangles give the numbers of the
    vectorised functions to the last bit (from slivers to wide triangles, one to many at once)."""
    rng = np.random.default_rng(RNG_SEED)
    for size in (1e-4, 3e-3, 0.05, 0.3):
        for n in (1, 2, 5, 40):
            A, B, C = random_triangles(rng, n, size_rad=size)
            a, b, c = sph.sides(A, B, C)
            s_area, s_triple = sph.triangle_sigmas(A, B, C, a, b, c, SIGMA)
            assert np.array_equal(s_area, sph.area_sigma_stars(A, B, C, SIGMA))
            assert np.array_equal(s_triple, sph.triple_sigma(A, B, C, SIGMA))
            assert np.array_equal(sph.lhuilier_few(sph.sides_few(A.tolist(), B.tolist(), C.tolist())), sph.area(A, B, C))
            assert np.array_equal(sph.lhuilier_zero_first(np.stack([np.zeros(n), a, b, c])), sph.lhuilier(a, b, c))
            tr = [sph.dot3(p, sph.cross3(q, r)) for p, q, r in zip(A.tolist(), B.tolist(), C.tolist())]
            assert np.array_equal(tr, sph.triple(A, B, C))
            for depth in (0, 1, 3):
                assert np.array_equal(sph.polar_moment_few(A, B, C, depth), sph.polar_moment(A, B, C, depth))
    # a degenerate triangle (a repeated vertex): left to the vectorised forms, which bound it by inf
    A, B, C = random_triangles(rng, 1)
    assert sph.triangle_sigmas(A, A, C, *sph.sides(A, A, C), SIGMA) is None
    assert sph.sign(-2.0) == -1 and sph.sign(0.0) == 0 and sph.sign(3.0) == 1


def test_upper_line_lies_above_every_point():
    rng = np.random.default_rng(RNG_SEED)
    x = rng.uniform(0, 1, 300)
    y = 0.2 + 0.5 * x + rng.uniform(0, 0.1, 300)
    c0, c1 = upper_line(x, y)
    assert np.all(c0 + c1 * x >= y)
    assert c0 + c1 * np.mean(x) < np.mean(y) + 0.1  # and hugs the points (least mean height)


# ---------------------------------------------------------------------- fixtures

CENTRE = radec_to_vec(np.radians(84.0), np.radians(-1.0))  # Orion: a cap of the real sky, 20 deg wide
CAP_DEG = 20.0


@pytest.fixture(scope="module")
def region(cat):
    """The mag-6 catalog within 20 deg of Orion: real density, a database that builds in ~2 s."""
    return cat.select(cat.xyz @ CENTRE >= np.cos(np.radians(CAP_DEG)), "test-cap-orion-20deg")


@pytest.fixture(scope="module")
def paper(cache, region, cam):
    return make_identifier("triangle", region, cam, SIGMA)


@pytest.fixture(scope="module")
def improved(cache, region, cam, paper):
    return make_identifier("triangle", region, cam, SIGMA, variant="improved")


@pytest.fixture(scope="module")
def stored_sides(cache, region, cam, paper):
    """The improved variant's search on the stored triangle database (database="triangles")."""
    return make_identifier("triangle", region, cam, SIGMA, variant="improved", database="triangles")


def region_attitudes(rng, n, cam, region, n_min):
    """Attitudes whose whole sensor lies inside the region, with at least n_min stars on it."""
    out = []
    limit = np.radians(CAP_DEG) - cam.half_diagonal_rad - 1e-3
    while len(out) < n:
        R = random_attitudes(1, rng)[0]
        axis = np.cross(R[2], CENTRE)
        ang = angular_distance(R[2], CENTRE)
        if ang > limit:  # rotate the boresight towards the centre, into the region
            shrink = ang - rng.uniform(0, limit)
            Q = Rotation.from_rotvec(axis / np.linalg.norm(axis) * shrink).as_matrix()
            R = R @ Q.T
        if angular_distance(R[2], CENTRE) <= limit and len(cam.visible(R, region.xyz)[0]) >= n_min:
            out.append(R)
    return out


def frames(region, cam, n, seed, n_min=5, false_stars=0):
    rng = np.random.default_rng(seed)
    return [synthetic_frame(region, cam, R, SIGMA, rng, false_stars=false_stars)
            for R in region_attitudes(rng, n, cam, region, n_min)]


# ---------------------------------------------------------------------- database

def tiny_catalog(n=40, seed=3, radius_deg=9.0):
    rng = np.random.default_rng(seed)
    c = np.array([0.3, -0.5, 0.8])
    c /= np.linalg.norm(c)
    e = rng.normal(size=(n, 3))
    e -= (e @ c)[:, None] * c
    e *= np.radians(radius_deg) * np.sqrt(rng.uniform(0, 1, (n, 1))) / np.linalg.norm(e, axis=1, keepdims=True)
    xyz = c + e
    xyz /= np.linalg.norm(xyz, axis=1, keepdims=True)
    return GuideCatalog(hip=np.arange(1, n + 1, dtype=np.int32), xyz=xyz, mag=rng.uniform(1, 6, n).astype(np.float32),
                        pm=np.zeros((n, 2), np.float32), bv=np.zeros(n, np.float32), flags=np.zeros(n, np.uint8),
                        history=("tiny-test-catalog",))


@pytest.mark.slow
def test_database_on_a_tiny_catalog(tmp_path, monkeypatch, cam):
    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    cat = tiny_catalog()
    m = TriangleMethod(cat, cam, SIGMA)
    info = m.database_info
    assert info["source"] == "built" and info["file_bytes"] > 0
    r_max = database.angular_range(cam.half_diagonal_rad)  # the half-diagonal rounded up on the 5 % grid
    assert cam.half_diagonal_rad <= r_max < 1.05 * cam.half_diagonal_rad and m.max_radius_rad == r_max
    # brute force over every triple of stars
    T = np.array(list(itertools.combinations(range(len(cat)), 3)))
    A, B, C = (cat.xyz[T[:, s]] for s in range(3))
    sides_ok = int(np.sum(np.max(np.stack(sph.sides(A, B, C)), axis=0) <= 2 * r_max))
    expected = set(map(tuple, T[sph.enclosing_cap_radius(A, B, C) <= r_max].tolist()))
    got = {tuple(int(x) for x in t) for t in m.tri}
    assert got == expected and len(m.tri) == len(expected) > 100
    assert info["triangle_counts"]["sides_within_diameter"] == sides_ok
    assert info["triangle_counts"]["cap_within_radius"] == len(expected)
    assert m.tri.dtype == np.int16 and m.area.dtype == np.float32
    # stored area and polar moment are those of the stars, sorted by area; the moment order is a permutation
    T = m.tri.astype(np.int64)
    P = [cat.xyz[T[:, s]] for s in range(3)]
    np.testing.assert_allclose(m.area, sph.area(*P), rtol=1e-6)
    np.testing.assert_allclose(m.cap, sph.enclosing_cap_radius(*P), rtol=1e-6)  # each triangle's cap, stored
    assert np.any(m.cap > cam.half_diagonal_rad)  # the rounded-up range holds triangles beyond this camera
    assert np.all(np.diff(m.area) >= 0)
    moment = m.kv_moment.sorted_values[m.moment_rank]
    np.testing.assert_allclose(moment, sph.polar_moment(*P), rtol=1e-6)
    np.testing.assert_array_equal(np.sort(m.moment_order), np.arange(len(T)))
    np.testing.assert_array_equal(m.moment_rank[m.moment_order], np.arange(len(T)))
    # the polar-moment sigma line lies above every simulated standard deviation
    I, s = m.moment_sigma_samples.T
    c0, c1 = m.moment_sigma_coef
    assert np.all(c0 + c1 * I >= s) and len(I) == min(1000, len(T))
    # the ranks sorted within each block, stored with the database
    blocks = np.sort(np.pad(m.moment_rank, (0, -len(T) % 256), constant_values=np.iinfo(np.int32).max)
                     .reshape(-1, 256), axis=1).ravel()
    np.testing.assert_array_equal(m.block_rank, blocks)
    # loaded again from the cache (memory-mapped), the same arrays
    again = TriangleMethod(cat, cam, SIGMA, beta=2.0)
    assert again.database_info["source"] == "cache"
    np.testing.assert_array_equal(again.tri, m.tri)
    assert isinstance(again.tri, np.memmap)
    # the database belongs to the sky: a camera of nearly the same field (another size, a fitted FOV)
    # whose half-diagonal rounds up to the same range reads the same file
    other = Camera.from_fov(7.9, 800, 800)
    assert database.angular_range(other.half_diagonal_rad) == r_max
    shared = TriangleMethod(cat, other, SIGMA)
    assert shared.database_info["source"] == "cache" and shared.database_key_string == m.database_key_string
    # the pieces of a chunked build are the triangles of one piece
    tri = catalog_triangles(cat.xyz, 2 * r_max)
    pieces = [t for _, _, t in _triangle_chunks(cat.xyz, 2 * r_max, None, None, 50)]
    assert len(pieces) > 3
    np.testing.assert_array_equal(np.concatenate(pieces), tri)


def test_kvector_built_in_chunks_is_the_kvector(monkeypatch):
    """The build's k-vectors, made a chunk at a time to keep its memory low: KVector's k and curve."""
    from skyview.identify import triangle_database as tdb
    from skyview.identify.kvector import KVector

    monkeypatch.setattr(tdb, "KVECTOR_CHUNK", 1000)
    rng = np.random.default_rng(RNG_SEED)
    for n in (1, 2, 3, 1000, 1001, 54321):
        v = np.sort(rng.gamma(2.0, size=n).astype(np.float32))
        for fit in ("line", "parabola"):
            kv = KVector(v.astype(np.float64), fit=fit, presorted=True)
            k, coef = tdb._kvector_arrays(v, fit)
            assert k.dtype == np.int32 and np.array_equal(k, kv.k)
            np.testing.assert_allclose(coef, kv.coef, rtol=1e-12)
    with pytest.raises(ValueError):
        tdb._kvector_arrays(np.array([1.0, 3.0, 2.0, 4.0], dtype=np.float32), "line")


def test_candidates_are_the_intersection(paper, region, cam):
    f = frames(region, cam, 1, seed=4, n_min=7)[0]
    V = f.obs.vectors[:7]
    t = paper.triangle_bounds(V, SIGMA)
    area = paper.area.astype(np.float64)
    moment = paper.kv_moment.sorted_values[paper.moment_rank].astype(np.float64)
    for k in range(len(t["area"])):
        inside = ((area >= t["area"][k] - t["area_bound"][k]) & (area <= t["area"][k] + t["area_bound"][k])
                  & (moment >= t["moment"][k] - t["moment_bound"][k])
                  & (moment <= t["moment"][k] + t["moment_bound"][k])
                  & (paper.cap <= cam.half_diagonal_rad))  # the database's range is larger: this camera's circle
        rows = paper.candidates(t, k)
        np.testing.assert_array_equal(rows, np.flatnonzero(inside))
        assert t["counts"][k] == len(rows)
    # looked up one by one (the largest-area order), the same ranges and counts
    lazy = paper.triangle_bounds(V, SIGMA, lookup=False)
    assert np.all(lazy["counts"] == -1)
    for k in range(len(t["area"])):
        assert paper.count_of(lazy, k) == t["counts"][k]
    for key in ("s1", "e1", "s2", "e2"):
        np.testing.assert_array_equal(lazy[key], t[key])
    # the true triangle of observed stars 0-1-2 is among its candidates (3-sigma bounds)
    true = tuple(sorted(int(x) for x in f.truth[:3]))
    k0 = int(np.flatnonzero((t["ti"] == 0) & (t["tj"] == 1) & (t["tk"] == 2))[0])
    assert true in {tuple(int(x) for x in paper.tri[r]) for r in paper.candidates(t, k0)}


def test_orientation_by_sides_and_handedness(stored_sides, region, cam):
    improved = stored_sides
    f = frames(region, cam, 1, seed=6, n_min=6)[0]
    t = improved.triangle_bounds(f.obs.vectors[:6], SIGMA)
    k0 = int(np.flatnonzero((t["ti"] == 0) & (t["tj"] == 1) & (t["tk"] == 2))[0])
    rows = improved.candidates(t, k0)
    H, src = improved.orient(t, k0, rows, SIGMA)
    assert [int(x) for x in f.truth[:3]] in H.tolist()  # the true vertex order
    assert len(H) < len(rows)  # most candidates fit no vertex order
    # a mirror image of the observed triangle has the same area and polar moment but no valid order
    M = np.diag([1.0, 1.0, -1.0])
    tm = improved.triangle_bounds(f.obs.vectors[:6] @ M, SIGMA)
    np.testing.assert_allclose(tm["area"], t["area"], rtol=1e-12)
    Hm, _ = improved.orient(tm, k0, rows, SIGMA)
    assert [int(x) for x in f.truth[:3]] not in Hm.tolist()


def test_pair_join_gives_the_stored_candidates(improved, stored_sides, region, cam):
    """database="pairs" (the improved variant) joins each observed triangle's candidates from the angle
    database: with the same polar-moment bound, exactly the oriented candidates of the stored database."""
    assert improved.database == "pairs" and not hasattr(improved, "tri")
    # it reads the angle method's own pair database (one file for both)
    assert improved.database_info["key_string"] == AngleMethod(region, cam, SIGMA).database_key_string
    I, s = improved.moment_sigma_samples.T
    c0, c1 = improved.moment_sigma_coef
    assert np.all(c0 + c1 * I >= s) and len(I) == 1000
    # the two simulated lines agree closely (different random triangles, the same rule)
    Ic = np.quantile(I, 0.9)
    assert improved.moment_sigma(Ic, SIGMA) == pytest.approx(stored_sides.moment_sigma(Ic, SIGMA), rel=0.2)
    improved.moment_sigma_coef, saved = stored_sides.moment_sigma_coef, improved.moment_sigma_coef
    try:
        n_true = 0
        for f in frames(region, cam, 3, seed=21, n_min=6):
            V = f.obs.vectors[:6]
            tp = improved.triangle_bounds(V, SIGMA)
            ts = stored_sides.triangle_bounds(V, SIGMA)
            for k in range(len(tp["area"])):
                Hp = improved.oriented_candidates(tp, k, SIGMA)[0]
                Hs = stored_sides.orient(ts, k, stored_sides.candidates(ts, k), SIGMA)[0]
                assert set(map(tuple, Hp.tolist())) == set(map(tuple, Hs.tolist()))
                assert tp["counts"][k] == len({frozenset(h) for h in Hp.tolist()})
                truth = [int(f.truth[i]) for i in (tp["ti"][k], tp["tj"][k], tp["tk"][k])]
                n_true += truth in Hp.tolist()
        assert n_true >= 50  # the true vertex order is nearly always among them (3 sigma bounds)
    finally:
        improved.moment_sigma_coef = saved


def test_pair_join_prunes_and_joins_in_the_same_order(improved, region, cam, monkeypatch):
    """join_pairs first drops the pairs with a star that ends no pair of its other side, then joins the
    few left all at once (up to JOIN_DENSE): the same candidates, in the same order, as joining every
    pair in blocks by their star (`by_star`)."""
    import skyview.identify.triangle_lookup as lookup

    ends, n = lookup._ends, 0
    for f in frames(region, cam, 3, seed=29, n_min=6):
        out = []
        for dense, prune in ((True, True), (False, True), (False, False)):
            monkeypatch.setattr(lookup, "JOIN_DENSE", lookup.JOIN_DENSE if dense else -1)  # -1: always by_star
            monkeypatch.setattr(lookup, "_ends", ends if prune else lambda *args: np.ones((3, args[3]), dtype=bool))
            t = improved.triangle_bounds(f.obs.vectors[:6], 10 * SIGMA, lookup=False)  # many candidates
            out.append([improved.join_pairs(t, k).tolist() for k in range(len(t["area"]))])
        assert out[0] == out[1] == out[2]
        n += sum(map(len, out[0]))
    assert n >= 300  # (3 frames of 20 triangles)
    pi, pj = improved.pair_i, improved.pair_j
    on = ends(improved.pair_ends, [0, 5, 7], [4, 7, 9], len(region.xyz), 2)  # side rp left out: every star may be r or p
    assert on[2].all() and set(np.flatnonzero(on[0])) == set(pi[:4]) | set(pj[:4])
    assert set(np.flatnonzero(on[1])) == set(pi[5:7]) | set(pj[5:7])


def test_join_records_what_consistent_keeps_of_one_triangle(improved, region, cam):
    """The pair join records which of its rows `consistent` keeps as a chain of that one triangle (the
    chain then takes them from there): the same rows as `consistent`, also where some fail (side pq
    looked up half a bound off its measured angle)."""
    n_rows = n_out = 0
    sigma = 3 * SIGMA
    for f in frames(region, cam, 3, seed=31, n_min=6):
        V = f.obs.vectors[:6]
        for shift in (0.0, 0.5):
            t = improved.triangle_bounds(V, sigma, lookup=False)
            t["sides"][:, 0] += shift * improved.beta * np.sqrt(2.0) * sigma
            for k in range(len(t["area"])):
                H = improved.join_pairs(t, k)
                kept = t.get("consistent_rows", {}).get(k)
                if kept is None:  # many rows: not recorded (the chain runs `consistent`)
                    continue
                tri = [int(t["ti"][k]), int(t["tj"][k]), int(t["tk"][k])]
                want = improved.consistent(V, tri, [tri], H, sigma, t)
                assert len(kept) == len(H) and np.array_equal(H[np.array(kept, dtype=bool)], want)
                n_rows, n_out = n_rows + len(H), n_out + len(H) - len(want)
    assert n_rows >= 60 and n_out > 0


def test_measured_as_visited_gives_the_figures_of_measuring_all(improved, region, cam):
    """The largest-area order measures only the triangles it visits (with database="pairs", one at a time
    in plain floats, each polar moment with its candidates'): the same figures, to the last bit, as
    measuring every triangle at once."""
    for f in frames(region, cam, 2, seed=23, n_min=7):
        V = f.obs.vectors[:7]
        lazy = improved.triangle_bounds(V, SIGMA, lookup=False)
        lazy["priority"] = np.argsort(np.argsort(-lazy["area"], kind="stable"))
        full = improved.triangle_bounds(V, SIGMA, lookup=False)
        improved._measure(full, np.arange(len(full["area"])))
        for k in (0, 5, 34, 1):  # out of the batch order too
            improved.count_of(lazy, k)
            for key in ("area_bound", "moment", "moment_bound", "triple_sigma"):
                assert lazy[key][k] == full[key][k]
        measured = ~np.isnan(lazy["area_bound"])
        assert measured.sum() == 4  # the four visited, not all
        done = np.flatnonzero(lazy["counts"] >= 0)
        assert np.array_equal(lazy["moment"][done], full["moment"][done])


def test_consistent_in_plain_floats_matches_the_vectorised_test(improved, region, cam):
    """A few hypotheses are checked in plain floats (`_consistent_few`): the same survivors as the
    vectorised test, for true hypotheses, mirrored ones and ones with a side just outside the bound."""
    from skyview.identify.triangle import _triangle_index

    for f in frames(region, cam, 3, seed=41, n_min=6):
        V = f.obs.vectors[:6]
        t = improved.triangle_bounds(V, SIGMA, lookup=False)
        used, triangles = [0, 1, 2, 4], [[0, 1, 2], [0, 2, 4], [1, 2, 4]]
        for tri in triangles:
            improved.count_of(t, _triangle_index(*tri, 6))  # measured, as the chain's triangles are
        truth = np.array([f.truth[u] for u in used])
        rng = np.random.default_rng(2)
        H = np.stack([truth, truth[[1, 0, 2, 3]], rng.permutation(truth),
                      rng.integers(0, len(region), size=4), truth[[0, 1, 3, 2]]])
        expect = improved.consistent(V, used, triangles, H, SIGMA)
        got = improved.consistent(V, used, triangles, H, SIGMA, t)
        assert np.array_equal(got, expect) and len(expect) >= 1 and expect[0].tolist() == truth.tolist()
    # the triangle index is the position in itertools.combinations' order (triangle_bounds')
    for m in (3, 5, 12):
        expect = list(range(m * (m - 1) * (m - 2) // 6))
        assert [_triangle_index(*c, m) for c in itertools.combinations(range(m), 3)] == expect


def test_distinct_star_sets_and_lazy_hypotheses_layer():
    from skyview.identify.triangle import _distinct
    from skyview.identify.triangle_lookup import _distinct_sets

    rng = np.random.default_rng(5)
    H = rng.integers(0, 40, size=(300, 3))
    expect = np.unique(np.sort(H, axis=1), axis=0)[:200]
    assert _distinct_sets(H) == list(map(tuple, expect.tolist())) and _distinct_sets(H[:0]) == []
    for n in (1, 3, 21, 22):  # a few rows are taken in plain Python: the same sets and stars
        assert _distinct_sets(H[:n]) == list(map(tuple, np.unique(np.sort(H[:n], axis=1), axis=0).tolist()))
        assert _distinct(H[:n]) == np.unique(H[:n]).tolist()
    # a step's layer samples its hypotheses when a sink reads them: the same rows as sampling at once
    layer = Hypotheses.sample([4, 1, 7], H.astype(np.int32), cap=50, shared=[1])
    assert (layer.used, layer.total, layer.shared) == ((4, 1, 7), 300, (1,))
    keep = np.linspace(0, 299, 50).round().astype(int)
    assert layer.rows.dtype == np.int64 and np.array_equal(layer.rows, H[keep])
    import pickle

    back = pickle.loads(pickle.dumps(layer))  # pickles (and copies) as a plain layer
    assert type(back) is Hypotheses and np.array_equal(back.rows, layer.rows) and back.total == 300


def test_join_on_shared_observed_stars():
    H = np.array([[10, 20, 30], [11, 21, 31], [12, 22, 32]])  # observed stars [0, 1, 2]
    # triangle (1, 2, 5): candidates in observed order
    O = np.array([[20, 30, 40], [21, 31, 41], [21, 31, 42], [99, 98, 97], [20, 30, 10]])
    H2, used, new = join(H, [0, 1, 2], [1, 2, 5], O)
    assert used == [0, 1, 2, 5] and new == 5
    assert sorted(map(tuple, H2.tolist())) == [(10, 20, 30, 40), (11, 21, 31, 41), (11, 21, 31, 42)]
    # a closed triangle (0, 1, 5): the three stars must be a candidate as they are
    H3, used3, new3 = join(H2, used, [5, 0, 1], np.array([[41, 11, 21], [40, 11, 21]]))
    assert new3 is None and used3 == used and H3.tolist() == [[11, 21, 31, 41]]
    with pytest.raises(ValueError):
        join(H, [0, 1, 2], [0, 5, 6], O)


# ---------------------------------------------------------------------- identification

def assert_correct(result, frame):
    assert result.status == IDENTIFIED, result.reason
    assert len(result.matches) >= 3
    for o, c in result.matches.items():
        assert frame.truth[o] == c


def test_identifies_fields_with_known_truth(paper, improved, region, cam):
    n_paper = n_improved = 0
    for f in frames(region, cam, 8, seed=2024, n_min=6):
        r = paper.identify(f.obs)
        kinds = [s.kind for s in r.steps]
        assert kinds[0] in ("pick", "skip") and set(kinds) <= {"pick", "pivot", "skip", "stop", "verify"}
        assert r.stats["pivots"] == kinds.count("pivot") <= 3  # the paper's pivot limit
        if r.status == IDENTIFIED:
            n_paper += 1
            assert_correct(r, f)
            assert kinds[-1] == "verify" and r.verification["passed"]
            assert r.database_key == paper.database_key_string
        first = r.stats["first_chain"]
        if first["outcome"] == "unique" and first["vertex_order_ok"]:  # before verification
            for o, c in first["matches"].items():  # the true star, or its unresolved companion
                assert angular_distance(region.xyz[c], region.xyz[f.truth[o]]) <= 2 * 3 * np.sqrt(2) * SIGMA
        r = improved.identify(f.obs)
        if r.status == IDENTIFIED:
            n_improved += 1
            assert_correct(r, f)
    assert n_paper >= 4 and n_improved >= 7


def test_false_star_never_gives_a_wrong_identification(paper, improved, region, cam):
    n_ok = {"paper": 0, "improved": 0}
    backtracked = False
    for f in frames(region, cam, 15, seed=99, n_min=4, false_stars=1):
        assert f.n_true == len(f.obs) - 1
        for name, m in (("paper", paper), ("improved", improved)):
            r = m.identify(f.obs)
            if r.status == IDENTIFIED:
                assert all(f.truth[o] == c for o, c in r.matches.items()), (name, f.truth, r.matches)
                assert int(np.flatnonzero(f.truth < 0)[0]) not in r.matches
                n_ok[name] += 1
                backtracked |= any(s.kind == "backtrack" for s in r.steps)
    assert n_ok["paper"] >= 4 and n_ok["improved"] > n_ok["paper"] and backtracked


def test_paper_pivoting_prunes_consecutive_lists(paper, region, cam):
    """The paper's pivoting: each list keeps the candidates with two stars in common with the other list."""
    assert paper.pivoting == "shared-star" and IMPROVED_PARAMS["pivoting"] == "join"
    seen = 0
    for f in frames(region, cam, 12, seed=5, n_min=7):
        r = paper.identify(f.obs)
        for s in (s for s in r.steps if s.kind == "pivot"):
            seen += 1
            assert s.numbers["sets"] <= s.numbers["candidates"]
            assert s.numbers["previous_after"] <= s.numbers["previous_before"]
        if r.status == IDENTIFIED:
            assert all(f.truth[o] == c for o, c in r.matches.items())
    assert seen >= 3


def test_steps_shrink_as_it_pivots(cache, region, cam):
    paper = TriangleMethod(region, cam, SIGMA, pivoting="join")  # the join's steps (improved); lists: below
    seen = shrinking = 0
    for f in frames(region, cam, 12, seed=5, n_min=7):
        r = paper.identify(f.obs)
        pivots = [s for s in r.steps if s.kind == "pivot"]
        if not pivots:
            continue
        seen += 1
        pick = r.steps[0]
        assert pick.kind == "pick" and len(pick.observed) == 3
        n = pick.numbers
        assert n["candidates"] <= min(n["candidates_area"], n["candidates_moment"])
        assert n["hypotheses"] == 6 * n["candidates"]  # the paper's vertex order: all 6 kept
        assert 0 < len(pick.groups) <= 200 and all(len(g) == 3 for g in pick.groups)
        sets = [n["sets"]] + [s.numbers["sets_after"] for s in pivots]
        for s in pivots:
            assert s.numbers["shared"] >= 2 and len(s.layer(Hypotheses).shared) >= 2
            # a join keeps at most every (hypothesis, candidate) pair that agrees on the shared stars
            assert s.numbers["sets_after"] <= s.numbers["sets_before"] * max(1, s.numbers["candidates"])
            assert len(s.catalog) <= 200 and len(s.groups) <= 200
            d = s.to_dict()
            assert d["kind"] == "pivot" and isinstance(d["numbers"]["candidates"], float)
        if r.status == IDENTIFIED:
            assert r.steps[-1].kind == "verify" and (sets[-1] == 1 or sets[-1] < sets[0])  # 1, or unresolved doubles
            shrinking += all(b < a for a, b in zip(sets, sets[1:]))
    assert seen >= 5 and shrinking >= 4


def test_rotation_invariance_of_the_identification(improved, region, cam):
    f = frames(region, cam, 1, seed=77, n_min=7)[0]
    base = improved.identify(f.obs)
    assert_correct(base, f)
    first = base.stats["first_chain"]
    for Q in random_attitudes(4, np.random.default_rng(1)):  # any rotation of the camera-frame vectors
        obs = Observation(vectors=f.obs.vectors @ Q.T, uv=np.zeros((len(f.obs), 2)),
                          brightness=f.obs.brightness, sigma_rad=SIGMA)
        assert improved.identify(obs).stats["first_chain"] == first


@pytest.mark.slow
def test_end_to_end_on_simulated_images(cache, region, cam):
    rng = np.random.default_rng(11)
    sigma = float(np.hypot(SIGMA, 0.1 * cam.pixel_scale_rad))  # the cole8 scenario's identifier sigma
    solvers = {v: MethodSolver(cam, "triangle", mag_limit=6.0, sigma_rad=sigma, catalog=region, variant=v)
               for v in ("paper", "improved")}
    solved = {v: 0 for v in solvers}
    for k, R in enumerate(region_attitudes(rng, 4, cam, region, n_min=7)):
        for n_false in (0, 1):
            frame = simulate_image(region, cam, R, seed=100 + k, mag_limit=6.0, n_false_stars=n_false,
                                   false_star_placement="disk", position_noise_rad=SIGMA)
            for v, solver in solvers.items():
                res = solver.solve_array(frame.image)
                if res.solved:
                    solved[v] += 1
                    assert not wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in res.matches],
                                             frame.truth)
                    assert res.identification.method == "triangle"
    assert solved["paper"] >= 1 and solved["improved"] >= 7  # the paper's method rarely survives a false star


def test_limits_and_small_inputs(paper, region, cam):
    f = frames(region, cam, 1, seed=8, n_min=8)[0]
    r = TriangleMethod(region, cam, SIGMA, max_pivots=0).identify(f.obs)
    assert "pivot" not in [s.kind for s in r.steps]
    r = TriangleMethod(region, cam, SIGMA, max_candidates=1).identify(f.obs)  # every triangle has more
    assert r.status != IDENTIFIED and set(s.kind for s in r.steps) == {"skip"}
    m = min(len(f.obs), 12)  # max_stars = 12 brightest stars form the triangles
    assert len(r.steps) == m * (m - 1) * (m - 2) // 6  # each of their triangles skipped
    # order="fewest" (the paper's "ideal" order) starts with the triangle that has the fewest candidates
    fewest = TriangleMethod(region, cam, SIGMA, order="fewest")
    r = fewest.identify(f.obs)
    counts = fewest.triangle_bounds(f.obs.vectors[:12], SIGMA)["counts"]
    assert r.steps[0].kind == "pick" and r.steps[0].numbers["candidates"] == counts.min()
    # the default starts with the largest area
    r = paper.identify(f.obs)
    largest = paper.triangle_bounds(f.obs.vectors[:12], SIGMA)["area"].max()
    assert r.steps[0].numbers["area_sr"] == pytest.approx(largest)
    r = TriangleMethod(region, cam, SIGMA, max_stars=4).identify(f.obs)
    assert r.stats["triangles"] == 4 and r.stats["triangle_stars"] == 4
    few = Observation(vectors=f.obs.vectors[:2], uv=f.obs.uv[:2], brightness=f.obs.brightness[:2], sigma_rad=SIGMA)
    r = paper.identify(few)
    assert r.status == FAILED and "at least 3" in r.reason
    none = Observation(vectors=np.zeros((0, 3)), uv=np.zeros((0, 2)), brightness=np.zeros(0), sigma_rad=SIGMA)
    assert paper.identify(none).status == FAILED


def test_registry_and_bad_input(cache, region, cam):
    assert METHODS["triangle"] is TriangleMethod and TriangleMethod.improved_params == IMPROVED_PARAMS
    for bad in ({"order": "random"}, {"area_sigma": "x"}, {"vertex_order": "x"}, {"beta": 0}, {"max_pivots": -1},
                {"max_stars": 2}, {"max_candidates": 0}, {"depth": -1}, {"database": "x"},
                {"database": "pairs"}):
        with pytest.raises(BadInput):
            make_identifier("triangle", region, cam, SIGMA, **bad)
    with pytest.raises(BadInput, match="no parameter"):
        make_identifier("triangle", region, cam, SIGMA, bogus=1)
    with pytest.raises(BadInput):
        make_identifier("triangle", region, cam, -1.0)
