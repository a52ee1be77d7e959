"""The ellipticity pivot-star method (Sun, Qi, Jin & Wang 2017): maths, database, identification."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import skyview.identify.verify as verify_module
from skyview.bench.runner import score_trial
from skyview.core.attitude import R_from_radec_roll, attitude_error_arcsec, random_attitudes
from skyview.core.camera import Camera
from skyview.core.catalog import (
    FLAG_DOUBLE,
    FLAG_MULTIPLE,
    FLAG_VARIABLE,
    GuideCatalog,
    load_guide_catalog,
    radec_to_vec,
)
from skyview.core.errors import BadInput
from skyview.experiments.ellipticity_sweep import grid, run_sweep
from skyview.identify import IDENTIFIED, METHODS, make_identifier
from skyview.identify.base import Observation
from skyview.identify.ellipticity import (
    EllipticityMethod,
    build_ellipticity_database,
    ellipticity,
    eps_sigma,
    guide_rows,
    nearest_adjacent,
    pattern_features,
    singular_vector_attitude,
)
from skyview.identify.ellipticity_batch import NoHypothesis, first_hypotheses
from skyview.identify.synthetic import add_noise, synthetic_frame, synthetic_frames
from skyview.identify.verify import angular_distance
from skyview.simulate.render import SensorModel, simulate_image
from skyview.solver.pipeline import MethodSolver

SIGMA = 10e-6


@pytest.fixture(scope="module")
def cam():
    return Camera.from_fov(20.0, 1024)


@pytest.fixture(scope="module")
def paper(cat, cam):
    return make_identifier("ellipticity", cat, cam, SIGMA)


@pytest.fixture(scope="module")
def improved(cat, cam):
    return make_identifier("ellipticity", cat, cam, SIGMA, variant="improved")


def correct(result, truth) -> bool:
    return all(truth[o] == c for o, c in result.matches.items())


# ---------------------------------------------------------------------- maths

def test_eps_and_angles_invariant_under_rotations():
    rng = np.random.default_rng(11)
    for _ in range(20):
        centre = Rotation.random(random_state=rng).apply([0.0, 0.0, 1.0])
        v = add_noise(np.repeat(centre[None], 4, axis=0), np.radians(3.0), rng)  # a 3-deg scatter
        eps, theta, s = pattern_features(v)
        R = Rotation.random(5, random_state=rng).as_matrix()
        eps_r, theta_r, s_r = pattern_features(np.einsum("kij,nj->kni", R, v))
        np.testing.assert_allclose(eps_r, eps, rtol=0, atol=1e-12)
        np.testing.assert_allclose(theta_r, np.broadcast_to(theta, theta_r.shape), rtol=0, atol=1e-12)
        np.testing.assert_allclose(s_r, np.broadcast_to(s, s_r.shape), rtol=0, atol=1e-12)
        assert s[0] > 1.9 and 0 < eps <= 1  # the largest singular value is close to 2


def test_eps_hand_computed():
    # four vectors (+-a, 0, c), (0, +-b, d): A A^T = diag(2a^2, 2b^2, 2(c^2 + d^2)), so the singular
    # values are sqrt(2) (c^2 + d^2)^(1/2), sqrt(2) b, sqrt(2) a and eps = a / b
    a, b = np.sin(np.radians(2.0)), np.sin(np.radians(3.0))
    c, d = np.cos(np.radians(2.0)), np.cos(np.radians(3.0))
    v = np.array([[a, 0, c], [-a, 0, c], [0, b, d], [0, -b, d]])
    eps, theta, s = pattern_features(v)
    assert eps == pytest.approx(a / b, abs=1e-14)
    assert ellipticity(v) == pytest.approx(0.6668359, abs=1e-7)
    np.testing.assert_allclose(s, np.sqrt(2.0) * np.array([np.sqrt(c * c + d * d), b, a]), atol=1e-14)
    # angles from the pivot (the first vector): 4 deg across, arccos(c d) to the other two
    np.testing.assert_allclose(np.degrees(theta), [4.0, np.degrees(np.arccos(c * d)), np.degrees(np.arccos(c * d))],
                               atol=1e-10)


@pytest.mark.parametrize("deg", [20.0, 4.0, 1.0])
def test_the_batched_look_ups_svd_is_numpys(deg):
    """The look-up's SVD of (m, 3, 4) pattern matrices from the eigen-decomposition of A A^T: numpy's singular
    values, eps and eps thresholds (relative 1e-8 even for 1 deg patterns), singular vectors up to sign."""
    from skyview.identify.ellipticity_batch import _svd_3x4, eps_sigma_stacked

    rng = np.random.default_rng(int(deg))
    W = np.array([0.0, 0.0, 1.0]) + np.radians(deg) / 2 * rng.normal(size=(300, 4, 3))
    W /= np.linalg.norm(W, axis=2, keepdims=True)
    A = np.swapaxes(W, 1, 2)
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    U2, s2, Vt2 = _svd_3x4(A)
    np.testing.assert_allclose(s2, s, rtol=1e-8, atol=0)
    np.testing.assert_allclose(s2[:, 2] / s2[:, 1], s[:, 2] / s[:, 1], rtol=1e-8, atol=0)
    sign = np.sign(np.sum(U * U2, axis=1))  # (m, 3): each singular pair's sign
    np.testing.assert_allclose(U2 * sign[:, None, :], U, atol=1e-7)
    np.testing.assert_allclose(Vt2 * sign[:, :, None], Vt, atol=1e-6)
    np.testing.assert_allclose(eps_sigma_stacked(A, U2, s2, Vt2, 1e-5), eps_sigma_stacked(A, U, s, Vt, 1e-5),
                               rtol=1e-8, atol=0)


def test_an_ellipticity_identifier_from_the_cache_imports_no_scipy_spatial():
    """A coverage worker's or a solve's ellipticity identifier, its database in the cache, loads without
    scipy.spatial (~0.35 s of a worker's start): the guide catalog's close pairs come from a sweep along z."""
    import subprocess
    import sys

    code = ("import sys; from skyview.core.catalog import load_guide_catalog; from skyview.core.camera import Camera; "
            "from skyview.identify import make_identifier; "
            "make_identifier('ellipticity', load_guide_catalog().brighter_than(6.0), Camera.from_fov(20.0, 1024), "
            "1e-5, variant='improved'); print(sorted(m for m in sys.modules if m.startswith('scipy.spatial')))")
    for run in ("builds the database (a k-d tree may build it)", "loads it"):
        p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stderr[-500:]
    assert p.stdout.strip() == "[]"


def test_eps_sigma_matches_monte_carlo(cat):
    rng = np.random.default_rng(5)
    rows = guide_rows(cat)
    nb, _ = nearest_adjacent(cat.xyz[rows], np.radians(1.0))
    v = cat.xyz[rows][np.r_[0, nb[0]]]
    sigma = 35e-6
    draws = np.array([ellipticity(add_noise(v, sigma, rng)) for _ in range(3000)])
    assert np.std(draws) == pytest.approx(eps_sigma(v, sigma), rel=0.1)


def test_singular_vector_attitude_equals_truth_noise_free(paper):
    rng = np.random.default_rng(3)
    for k in rng.choice(len(paper.eps), size=10, replace=False):
        ref = paper.catalog.xyz[paper.stars[k]]
        R = random_attitudes(1, rng)[0]
        R_sv = singular_vector_attitude(ref @ R.T, ref)
        np.testing.assert_allclose(R_sv, R, atol=1e-9)
        assert np.linalg.det(R_sv) == pytest.approx(1.0)


# ---------------------------------------------------------------------- guide catalog and database

def test_guide_catalog_is_the_papers_filters(cat, paper):
    chained = cat.brighter_than(6.0).without_flags(FLAG_MULTIPLE).without_close_pairs(np.radians(0.2))
    rows = guide_rows(cat)
    np.testing.assert_array_equal(cat.hip[rows], chained.hip)
    assert len(rows) == 3865  # the paper: N = 3,974 from SAO (within 3 %)
    assert abs(len(rows) / 3974 - 1) < 0.03
    np.testing.assert_array_equal(paper.guide_rows, rows)
    info = paper.database_info
    assert info["guide_stars"] == 3865 and info["patterns"] == 3865 and info["catalog_stars"] == len(cat)
    # the patterns refer to rows of the catalog the identifier was given
    np.testing.assert_array_equal(paper.stars, rows[paper.stars_guide])
    assert np.all(cat.flags[paper.stars] & FLAG_MULTIPLE == 0)
    # the Hipparcos duplicity and variability flags as well would leave a quarter fewer than the paper's
    assert len(guide_rows(cat, drop_flags=FLAG_DOUBLE | FLAG_VARIABLE)) == 2994


def tiny_catalog(n=40, seed=1):
    rng = np.random.default_rng(seed)
    ra = rng.uniform(0.0, np.radians(12.0), n)
    dec = rng.uniform(-np.radians(6.0), np.radians(6.0), n)
    ra[1], dec[1] = ra[0] + np.radians(0.5), dec[0]  # a neighbour closer than theta_min
    xyz = radec_to_vec(ra, dec)
    z = np.zeros(n, dtype=np.float32)
    return GuideCatalog(hip=np.arange(1, n + 1, dtype=np.int32), xyz=xyz, mag=z + 3.0, pm=np.zeros((n, 2), np.float32),
                        bv=z, flags=np.zeros(n, dtype=np.uint8))


def test_database_on_tiny_catalog_brute_force():
    g = tiny_catalog()
    theta_min = np.radians(1.0)
    db = build_ellipticity_database(g, theta_min)
    assert len(db["eps"]) == len(g) and np.all(np.diff(db["eps"]) >= 0)
    d = angular_distance(g.xyz[:, None], g.xyz[None, :])
    for k in range(len(db["eps"])):
        p = int(db["stars"][k, 0])
        others = [j for j in np.argsort(d[p]) if j != p and d[p, j] >= theta_min][:3]
        assert db["stars"][k, 1:].tolist() == others
        np.testing.assert_allclose(db["theta"][k], d[p, others], atol=1e-12)
        A = g.xyz[[p, *others]].T
        s = np.linalg.svd(A, compute_uv=False)
        assert db["eps"][k] == pytest.approx(s[2] / s[1], abs=1e-12)
    # star 1 is 0.5 deg from star 0: never its adjacent star
    k0 = int(np.flatnonzero(db["stars"][:, 0] == 0)[0])
    assert 1 not in db["stars"][k0, 1:].tolist()


def test_nearest_adjacent_reports_missing():
    g = tiny_catalog(n=3)
    nb, ang = nearest_adjacent(g.xyz, np.radians(1.0))
    assert np.all(nb[:, 2] == -1) and np.all(np.isinf(ang[:, 2]))
    assert len(build_ellipticity_database(g, np.radians(1.0))["eps"]) == 0


def test_database_cached_and_keyed(tmp_path, monkeypatch, cat, cam):
    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    a = EllipticityMethod(cat, cam, SIGMA)
    assert a.database_info["source"] == "built" and a.database_info["build_s"] < 5.0
    b = EllipticityMethod(cat, Camera.from_fov(8.0, 512), 87e-6, eps_threshold=0.002)  # no camera dependence
    assert b.database_info["source"] == "cache" and b.database_key == a.database_key
    c = EllipticityMethod(cat, cam, SIGMA, theta_min_deg=1.5)
    d = EllipticityMethod(cat, cam, SIGMA, drop_flags=0)
    assert len({x.database_key_string for x in (a, c, d)}) == 3
    assert len(d.guide) > len(a.guide)


def test_bad_parameters(cat, cam):
    for kw in ({"n_adjacent": 2}, {"eps_threshold": 0}, {"angle_threshold_deg": -1}, {"theta_min_deg": float("nan")},
               {"max_pivots": 0}, {"statistic": "nope"}, {"threshold": 2.0}, {"drop_flags": -1}):
        with pytest.raises(BadInput):
            EllipticityMethod(cat, cam, SIGMA, **kw)
    with pytest.raises(BadInput):
        EllipticityMethod(cat, cam, 0.0)
    with pytest.raises(BadInput):
        make_identifier("ellipticity", cat, cam, SIGMA, nonsense=1)


# ---------------------------------------------------------------------- identification (vector level)

def guide_frames(cat, cam, n, seed, false_stars=0):
    """Frames whose sky is the guide catalog (the paper's conditions), boresight near a guide star."""
    gcat = cat.select(guide_rows(cat), "guide")
    rng = np.random.default_rng(seed)
    return gcat, [synthetic_frame(gcat, cam, R, SIGMA, rng, false_stars=false_stars)
                  for R in random_attitudes(n, rng)]


def test_paper_variant_identifies_guide_sky(cat, cam):
    gcat, frames = guide_frames(cat, cam, 12, seed=21)
    ident = make_identifier("ellipticity", gcat, cam, SIGMA)
    n_ok = 0
    for f in frames:
        r = ident.identify(f.obs)
        if not r.identified:
            continue
        n_ok += 1
        assert correct(r, f.truth)
        assert attitude_error_arcsec(r.R, f.R)["boresight"] < 10.0
        # the paper's attitude from the left singular vectors is right too (it is not the optimal one)
        assert attitude_error_arcsec(r.stats["R_singular_vectors"], f.R)["total"] < 600.0
        kinds = [s.kind for s in r.steps]
        assert kinds[:4] == ["pivot", "adjacent", "pattern", "lookup"] and kinds[-1] == "verify"
        assert r.stats["pivots"] == 1 and r.stats["first_chain"]["outcome"] == "unique"
        pivot_step = r.steps[0]
        assert pivot_step.numbers["offset_deg"] <= 4.0
        lookup = r.steps[3]
        assert 1 <= len(lookup.groups) <= 200 and all(len(g) == 4 for g in lookup.groups)
        assert tuple(r.steps[-1].groups[0]) in {tuple(g) for g in lookup.groups}
    assert n_ok >= 10


def test_identified_matches_are_rows_of_the_given_catalog(cat, cam, improved):
    rng = np.random.default_rng(8)
    for R in random_attitudes(5, rng):
        f = synthetic_frame(cat, cam, R, SIGMA, rng)  # every Hp <= 6 star: a third are not guide stars
        r = improved.identify(f.obs)
        assert r.status == IDENTIFIED, r.reason
        assert correct(r, f.truth)
        # verification reprojects the whole catalog: stars the guide catalog dropped are matched too
        assert len(r.matches) >= 0.9 * len(f.obs)
        assert any(int(c) not in set(improved.guide_rows.tolist()) for c in r.matches.values())


def test_false_star_paper_option_and_improved(cat, cam, improved):
    rng = np.random.default_rng(4)
    n_ok = 0
    for R in random_attitudes(8, rng):
        f = synthetic_frame(cat, cam, R, SIGMA, rng, false_stars=1)
        r = improved.identify(f.obs)
        if r.identified:
            n_ok += 1
            assert correct(r, f.truth)
            assert int(np.flatnonzero(f.truth < 0)[0]) not in r.matches
    assert n_ok >= 7


def test_no_pivot_within_critical_value(paper, cam):
    # four stars, all 6-8 deg from the boresight: the paper's pivot must be within 4 deg
    v = np.array([R_from_radec_roll(0, 0, 0) @ radec_to_vec(np.radians(a), np.radians(d))
                  for a, d in ((6, 0), (0, 7), (-7, 0), (0, -8))])
    uv, _ = cam.project(v)
    r = paper.identify(Observation(vectors=v, uv=uv, brightness=np.ones(4), sigma_rad=SIGMA))
    assert not r.identified and "within 4 deg" in r.reason
    r3 = paper.identify(Observation(vectors=v[:3], uv=uv[:3], brightness=np.ones(3), sigma_rad=SIGMA))
    assert r3.status == "failed"


# ---------------------------------------------------------------------- end to end on images

def test_end_to_end_images_with_a_false_star(cat):
    cam = Camera.from_fov(20.0, 1024)
    # a 20 deg field at Hp 6 holds 30-80 stars: keep them all (the default max_stars=40 drops the faint
    # ones, and with them the adjacent stars of the patterns)
    solver = MethodSolver(cam, "ellipticity", mag_limit=6.0, sigma_rad=36e-6, catalog=load_guide_catalog(),
                          variant="improved", max_stars=200)
    assert "ellipticity" in METHODS
    rng = np.random.default_rng(2017)
    Rs = random_attitudes(4, rng)
    for k, R in enumerate(Rs):
        frame = simulate_image(load_guide_catalog(), cam, R, SensorModel(), seed=100 + k, mag_limit=6.0,
                               n_false_stars=1 if k % 2 else 0, false_star_placement="disk",
                               position_noise_rad=10e-6)
        res = solver.solve_array(frame.image)
        outcome, wrong = score_trial(res, frame.truth)
        assert outcome == "correct", (outcome, wrong, res.reason)
        assert attitude_error_arcsec(res.R, R)["boresight"] < 10.0
        assert len(res.matches) >= 10


# ---------------------------------------------------------------------- the sweep

def test_sweep_grid_and_a_small_sweep():
    ra, dec = grid(1.0, 0.5, 89.0)
    assert len(ra) * len(dec) == 128_877  # the paper's count (RA 0 and 360 both included)
    ra2, dec2 = grid(0.5, 0.1, 89.0)
    assert len(ra2) * len(dec2) == 1_284_101
    s = run_sweep(variant="improved", frames="sky", stride=60, workers=1, progress=False)
    assert s["boresights"] == 7 * 6
    assert s["counts"]["incorrect"] == 0
    assert s["counts"]["correct"] + s["counts"]["not identified"] == s["boresights"]


# ---------------------------------------------------------------------- many frames at once (a sweep's)

@pytest.mark.parametrize("variant, noise, sigma, max_stars", [
    ("improved", 10e-6, 10e-6, 1000),  # Sun et al.'s sweep: the first hypothesis decides almost every frame
    ("paper", 10e-6, 10e-6, 1000),  # one pivot: many frames end with no hypothesis
    ("improved", 40e-6, 12e-6, 40),  # noisier than told: first hypotheses fail, the walk goes on
])
def test_a_batch_identifies_every_frame_as_identify_does(cat, cam, variant, noise, sigma, max_stars, monkeypatch):
    ident = make_identifier("ellipticity", cat, cam, sigma, variant=variant)
    n = 160
    Rs = random_attitudes(n, np.random.default_rng(26))
    frames = synthetic_frames(cat, cam, Rs, noise, [np.random.default_rng([26, i]) for i in range(n)])
    obs = [Observation(f.obs.vectors[:max_stars], f.obs.uv[:max_stars], f.obs.brightness[:max_stars], sigma)
           for f in frames]
    # each frame's first hypothesis is the one the method's walk yields first
    firsts = first_hypotheses(ident, [o.vectors for o in obs], np.full(n, sigma))
    for o, first in zip(obs, firsts):
        search = ident.begin(o)
        walk = None if ident.too_few(search) else next(ident.hypotheses(search), None)
        if isinstance(first, NoHypothesis):  # the walk yields nothing, and fails for the reason given
            assert walk is None and first.reason == ident.identify(o).reason
        elif first is not None:
            assert walk is not None and first == walk.matches
        else:
            assert len(o) < ident.min_stars
    decided = sum(isinstance(f, dict) for f in firsts)
    none_at_all = sum(isinstance(f, NoHypothesis) for f in firsts)
    # and every identification is identify's: status, matches, attitude, verification
    made = []
    real_verify = verify_module.verify
    monkeypatch.setattr(verify_module, "verify", lambda *a, **k: made.append(1) or real_verify(*a, **k))
    monkeypatch.setattr("skyview.identify.ellipticity.BATCH_FRAMES", 64)  # three batches: 64, 64, 32
    batch = list(ident.identify_batch(obs))
    assert len(batch) == n
    # each hypothesis verified once: a walk after a failed first hypothesis takes the batch's verification
    assert len(made) == sum(b.stats["verifications"] for b in batch)
    monkeypatch.undo()
    one = [ident.identify(o) for o in obs]
    for a, b in zip(one, batch):
        assert (a.status, a.matches, a.reason) == (b.status, b.matches, b.reason)
        assert (a.R is None and b.R is None) or np.array_equal(a.R, b.R)
        assert a.verification.get("p_false") == b.verification.get("p_false")
        if not b.stats.get("batched"):  # walked: the same steps too
            assert [s.to_dict() for s in a.steps] == [s.to_dict() for s in b.steps]
        assert b.stats["time_s"] > 0
    batched = sum(bool(b.stats.get("batched")) and b.identified for b in batch)
    walked_after_a_failed_first = sum(not b.stats.get("batched") and b.stats.get("verifications", 0) >= 2
                                      for b in batch)
    if variant == "improved" and noise == sigma:
        assert decided == batched >= 0.95 * n and sum(a.identified for a in one) >= 0.95 * n
    elif variant == "paper":  # one pivot: a frame without a candidate there is inconclusive
        assert 0.3 * n <= decided < n and sum(a.identified for a in one) == batched and none_at_all >= 0.1 * n
    else:
        # the walk goes on after the batch's verification of its first hypothesis (reused, not made again)
        assert walked_after_a_failed_first >= 10 and batched >= 0.3 * n


def test_a_method_without_its_own_batch_identifies_frame_by_frame(cat):
    cam8 = Camera.from_fov(8.0, 1024)
    ident = make_identifier("angle", cat, cam8, SIGMA, variant="improved")
    Rs = random_attitudes(20, np.random.default_rng(3))
    frames = [synthetic_frame(cat, cam8, R, SIGMA, np.random.default_rng(i)) for i, R in enumerate(Rs)]
    batch = list(ident.identify_batch([f.obs for f in frames]))
    for f, b in zip(frames, batch):
        a = ident.identify(f.obs)
        assert (a.status, a.matches) == (b.status, b.matches) and b.stats["time_s"] > 0
    assert sum(b.identified and correct(b, f.truth) for f, b in zip(frames, batch)) >= 15


def test_a_subclass_with_its_own_walk_is_identified_frame_by_frame(cat, cam):
    class NearestFirst(EllipticityMethod):  # a walk of its own: the batch must not stand in for it
        def hypotheses(self, search):
            yield from super().hypotheses(search)

    ident = NearestFirst(cat, cam, SIGMA)
    Rs = random_attitudes(12, np.random.default_rng(5))
    frames = [synthetic_frame(cat, cam, R, SIGMA, np.random.default_rng(i)) for i, R in enumerate(Rs)]
    batch = list(ident.identify_batch([f.obs for f in frames]))
    assert not any(b.stats.get("batched") for b in batch) and all(b.steps for b in batch)
    assert [b.matches for b in batch] == [ident.identify(f.obs).matches for f in frames]
