"""The shared verification: correct hypotheses pass, wrong ones fail, P(false) is what it says."""

from itertools import combinations, permutations, product
from math import comb

import numpy as np
import pytest
from scipy.stats import binom

from skyview.core.attitude import (
    R_from_radec_roll,
    attitude_error_arcsec,
    attitudes_from_radec_roll,
    radec_roll_from_R,
    random_attitudes,
    svd_attitude,
)
from skyview.core.camera import Camera
from skyview.core.catalog import load_guide_catalog, vec_to_radec
from skyview.identify.synthetic import synthetic_frame, synthetic_frames
from skyview.identify.verify import (
    CALIBRATED,
    DEFAULT_THRESHOLD,
    TETRA3,
    angular_distance,
    match_one_to_one,
    match_radius,
    p_false_calibrated,
    p_false_tetra3,
    poisson_binomial_sf,
    verify,
)

SIGMA = 87e-6


def frame_with(cat, cam, n_min, seed, n_max=99):
    rng = np.random.default_rng(seed)
    while True:
        R = random_attitudes(1, rng)[0]
        f = synthetic_frame(cat, cam, R, SIGMA, rng)
        if n_min <= len(f.obs) <= n_max:
            return f


def test_correct_hypothesis_passes_and_extends(cat, cam):
    f = frame_with(cat, cam, 7, seed=1)
    hyp = {i: int(f.truth[i]) for i in range(3)}
    v = verify(f.obs.vectors, hyp, cat, cam, SIGMA)
    assert v.passed, v.reason
    assert v.n_tested == len(f.obs) - 3
    assert v.n_agree == v.n_tested
    assert v.p_false < DEFAULT_THRESHOLD[CALIBRATED]
    # extended to every observed star, all correct
    assert v.matches == {i: int(f.truth[i]) for i in range(len(f.obs))}
    assert attitude_error_arcsec(v.R, f.R)["boresight"] < 60.0
    d = v.to_dict()
    assert d["passed"] and d["n_matches"] == len(f.obs) and d["statistic"] == CALIBRATED


def test_reported_attitude_is_the_estimate_from_the_reported_matches(cat, cam):
    """verify reuses an estimate when a round leaves the matches unchanged: what it reports must still be
    exactly the SVD estimate from the final matches, on frames where rounds change them and where not."""
    for seed in range(6):
        f = frame_with(cat, cam, 5, seed=seed)
        for k in (2, 3, len(f.obs)):
            hyp = {i: int(f.truth[i]) for i in range(k)}
            v = verify(f.obs.vectors, hyp, cat, cam, SIGMA)
            if not v.passed:
                continue
            obs = np.array(sorted(v.matches))
            est = svd_attitude(f.obs.vectors[obs], cat.xyz[[v.matches[o] for o in obs]], SIGMA)
            assert np.array_equal(v.R, est.R) and np.array_equal(v.covariance, est.covariance)
            assert v.matches == {int(i): int(f.truth[i]) for i in obs}


def test_shuffled_hypothesis_fails(cat, cam):
    f = frame_with(cat, cam, 7, seed=2)
    rows = [int(f.truth[i]) for i in range(4)]
    for perm in ([1, 0, 2, 3], [1, 2, 3, 0], [3, 2, 1, 0]):
        hyp = {i: rows[p] for i, p in enumerate(perm)}
        v = verify(f.obs.vectors, hyp, cat, cam, SIGMA)
        assert not v.passed
        assert "does not fit" in v.reason


def test_pattern_from_elsewhere_fails(cat, cam):
    """Three stars of frame B (a self-consistent pattern) among the other stars of frame A."""
    a = frame_with(cat, cam, 7, seed=3)
    b = frame_with(cat, cam, 4, seed=4)
    assert a.R[2] @ b.R[2] < np.cos(np.radians(20))  # far apart on the sky
    vectors = np.concatenate([b.obs.vectors[:3], a.obs.vectors[3:]])
    hyp = {i: int(b.truth[i]) for i in range(3)}
    v = verify(vectors, hyp, cat, cam, SIGMA)
    assert not v.passed
    assert v.max_residual_rad < match_radius(SIGMA)  # the pattern itself fits ...
    assert v.n_tested == len(a.obs) - 3 and v.n_agree == 0  # ... but nothing else does
    # random catalog stars for a true frame's stars do not even fit
    rng = np.random.default_rng(5)
    hyp = {i: int(r) for i, r in enumerate(rng.choice(len(cat), 3, replace=False))}
    assert not verify(a.obs.vectors, hyp, cat, cam, SIGMA).passed


def test_no_other_star_cannot_be_verified(cat, cam):
    f = frame_with(cat, cam, 4, seed=6, n_max=4)
    hyp = {i: int(f.truth[i]) for i in range(4)}
    v = verify(f.obs.vectors, hyp, cat, cam, SIGMA)
    assert not v.passed and v.n_tested == 0
    assert "no observed star" in v.reason
    v = verify(f.obs.vectors, {0: int(f.truth[0])}, cat, cam, SIGMA)
    assert not v.passed  # one star gives no attitude


def test_poisson_binomial_tail_against_enumeration():
    """Every k, tiny and near-1 probabilities, by both of its paths (the hits or the misses counted,
    Python floats or numpy): the enumerated tail within 1e-12, with no cancellation in tiny tails."""
    rng = np.random.default_rng(3)
    for n in range(1, 11):
        ps = np.concatenate([rng.uniform(0, 1, n - n // 3) ** 4, 1 - rng.uniform(0, 1e-9, n // 3)])
        rows = np.array(list(product([0, 1], repeat=n)))
        weight = np.prod(np.where(rows == 1, ps, 1 - ps), axis=1)
        for k in range(n + 2):
            tail = float(weight[rows.sum(axis=1) >= k].sum())
            assert poisson_binomial_sf(k, ps) == pytest.approx(tail, rel=1e-12, abs=0 if tail else 1e-300)
    ps = rng.uniform(1e-6, 0.6, 80)  # states beyond 32: numpy; against the plain full distribution
    dist = np.zeros(81)
    dist[0] = 1.0
    for p in ps:
        dist[1:] = dist[1:] * (1 - p) + dist[:-1] * p
        dist[0] *= 1 - p
    for k in (1, 20, 40, 41, 60, 79, 80):
        assert poisson_binomial_sf(k, ps) == pytest.approx(dist[k:].sum(), rel=1e-12)


def test_p_false_by_hand(cat, cam):
    # the formula
    p, n, k, T = 0.01, 5, 2, 3
    tail = sum(comb(n, j) * p ** j * (1 - p) ** (n - j) for j in range(k, n + 1))
    assert p_false_calibrated(k, n, p, T) == pytest.approx(T * tail, rel=1e-12)
    assert p_false_calibrated(0, 5, p) == 1.0 and p_false_calibrated(1, 0, p) == 1.0
    assert p_false_calibrated(3, 3, 0.5, 100) == 1.0  # capped
    # the tetra3 form: BinomCDF(n_obs - (m - 2), n_obs, 1 - N r^2)
    p1 = 8 * 0.01 ** 2
    expected = sum(comb(6, j) * (1 - p1) ** j * p1 ** (6 - j) for j in range(0, 6 - (5 - 2) + 1))
    assert p_false_tetra3(5, 6, 8, 0.01) == pytest.approx(expected, rel=1e-12)

    # the Poisson-binomial tail (unequal p) by enumeration
    ps = [0.01, 0.2, 0.05, 0.3]
    tail = 0.0
    for mask in range(16):
        bits = [(mask >> i) & 1 for i in range(4)]
        if sum(bits) >= 2:
            tail += np.prod([p if bit else 1 - p for p, bit in zip(ps, bits)])
    assert p_false_calibrated(2, 4, ps, 5) == pytest.approx(5 * tail, rel=1e-12)
    assert poisson_binomial_sf(2, [0.1] * 6) == pytest.approx(binom.sf(1, 6, 0.1), rel=1e-12)

    # what verify reports, recomputed by hand from its counts
    f = frame_with(cat, cam, 5, seed=7, n_max=6)
    hyp = {i: int(f.truth[i]) for i in range(3)}
    v = verify(f.obs.vectors, hyp, cat, cam, SIGMA, n_hypotheses=2)
    r = 3 * np.sqrt(2) * SIGMA
    assert v.radius_rad == pytest.approx(r)
    dens = v.n_frame / cam.solid_angle_sr
    assert v.p_single == pytest.approx(dens * np.pi * r ** 2, rel=1e-12)
    n, k = v.n_tested, v.n_agree
    assert n == len(f.obs) - 3 and k == n and len(v.p_tested) == n
    # each tested star's radius grows with the attitude uncertainty of the 3-star hypothesis
    est = svd_attitude(f.obs.vectors[:3], cat.xyz[[hyp[0], hyp[1], hyp[2]]], SIGMA)
    for t, o in enumerate(range(3, len(f.obs))):
        b = f.obs.vectors[o]
        B = np.stack([np.cross(e, b) for e in np.eye(3)], axis=1)  # dphi -> dphi x b
        lam = np.linalg.eigvalsh(B @ est.covariance @ B.T)[-1]
        r_i = r * np.sqrt(1 + lam / SIGMA ** 2)
        assert r_i > r
        # density: the frame's (sparse field: no denser neighbourhood), times pi r_i^2
        assert v.p_tested[t] == pytest.approx(dens * np.pi * r_i ** 2, rel=1e-9)
    tail = 1.0
    for p in v.p_tested:  # k == n: every tested star agreed
        tail *= p
    assert v.p_false == pytest.approx(2 * tail, rel=1e-9)
    # n_frame: the catalog stars on the sensor (grown by r) at the attitude of the hypothesis
    idx, _ = cam.visible(est.R, cat.xyz, margin=-r * cam.fx)
    assert len(cam.visible(est.R, cat.xyz)[0]) <= v.n_frame == len(idx)

    # a frame measured in windows (a tracker's): each tested star's chance is its radius' share of the window
    # it was found in, whatever the sky's density; the same agreements, the same matches
    window = np.linspace(2e-5, 4e-5, len(f.obs))
    vw = verify(f.obs.vectors, hyp, cat, cam, SIGMA, n_hypotheses=2, window_sr=window)
    radii = np.sqrt(np.asarray(v.p_tested) / (dens * np.pi))
    np.testing.assert_allclose(vw.p_tested, np.minimum(1.0, np.pi * radii ** 2 / window[3:]), rtol=1e-9)
    assert vw.n_agree == v.n_agree and vw.matches == v.matches
    assert vw.p_false == pytest.approx(p_false_calibrated(k, n, vw.p_tested, 2), rel=1e-12) and vw.p_false > v.p_false

    vt = verify(f.obs.vectors, hyp, cat, cam, SIGMA, statistic=TETRA3, n_patterns=1000)
    m, n_obs = len(vt.matches), len(f.obs)
    expected = p_false_tetra3(m, n_obs, vt.n_frame, r / np.radians(cam.fov_deg))
    assert vt.p_false == pytest.approx(expected) and vt.threshold_effective == pytest.approx(1e-3 / 1000)


def test_cluster_wrong_hypotheses_fail(cat, cam):
    """In the Pleiades every 3-star hypothesis whose sides match within the angle bound is tried:
    the true ones pass, the wrong ones (mirror images, cluster stars mapped onto cluster stars at
    ~20x the average density) all fail."""
    alcyone = cat.index_of(17702)
    ra, dec = cat.ra_dec
    R = R_from_radec_roll(ra[alcyone], dec[alcyone], 0.0)
    idx, _ = cam.visible(R, cat.xyz)
    v = cat.xyz[idx] @ R.T  # noise-free
    cl = np.flatnonzero(angular_distance(cat.xyz[idx], cat.xyz[alcyone]) < np.radians(1.0))
    D = angular_distance(v[:, None], v[None, :])
    T = np.array(list(combinations(cl, 3)))
    P = np.array(list(permutations(cl, 3)))
    bound = 3 * np.sqrt(2) * SIGMA
    ok = np.ones((len(T), len(P)), dtype=bool)
    for x, y in ((0, 1), (1, 2), (0, 2)):
        ok &= np.abs(D[T[:, x], T[:, y]][:, None] - D[P[:, x], P[:, y]][None, :]) < bound
    n_right = n_wrong = 0
    for t, p in zip(*np.nonzero(ok)):
        obs, rows = T[t], P[p]
        right = bool(np.all(obs == rows))
        res = verify(v, {int(o): int(idx[c]) for o, c in zip(obs, rows)}, cat, cam, SIGMA)
        assert res.passed == right, (obs, rows, res.reason)
        n_right += right
        n_wrong += not right
    assert n_right > 50 and n_wrong > 20


def test_threshold_decides(cat, cam):
    f = frame_with(cat, cam, 4, seed=8, n_max=4)  # one star to test: P(false) ~ 1e-4
    hyp = {i: int(f.truth[i]) for i in range(3)}
    v = verify(f.obs.vectors, hyp, cat, cam, SIGMA)
    assert v.passed and v.n_agree == 1 and 1e-5 < v.p_false < 1e-3
    v = verify(f.obs.vectors, hyp, cat, cam, SIGMA, threshold=v.p_false / 2)
    assert not v.passed and "not below" in v.reason
    v = verify(f.obs.vectors, hyp, cat, cam, SIGMA, n_hypotheses=100)  # Bonferroni
    assert not v.passed


def test_match_one_to_one_and_ambiguity():
    ref = np.array([[0, 0, 1.0], [1e-3, 0, 1.0], [1e-3 + 2e-5, 0, 1.0]])
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    q = np.array([[1e-5, 0, 1.0], [2e-5, 0, 1.0], [5e-3, 0, 1.0], [1.005e-3, 0, 1.0]])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    qi, rj, d, amb = match_one_to_one(q, ref, 1e-4)
    assert dict(zip(qi.tolist(), rj.tolist())) == {0: 0, 3: 1}  # query 1 loses ref 0 to the closer query 0
    assert np.all(d < 1e-4)
    assert amb.tolist() == [3]  # two ref stars within the radius


def test_unresolved_close_pair_is_not_reported(cat, cam):
    """HIP 88817 / 88818 are 14" apart: below the noise, their identity is never reported."""
    i, j = cat.index_of(88817), cat.index_of(88818)
    ra, dec = cat.ra_dec
    R = R_from_radec_roll(ra[i] + np.radians(1.0), dec[i] + np.radians(0.5), 0.3)
    rng = np.random.default_rng(9)
    f = synthetic_frame(cat, cam, R, SIGMA, rng)
    assert {i, j} <= set(f.truth.tolist())
    others = [k for k in range(len(f.obs)) if f.truth[k] not in (i, j)]
    hyp = {k: int(f.truth[k]) for k in others[:3]}
    v = verify(f.obs.vectors, hyp, cat, cam, SIGMA)
    assert v.passed, v.reason
    pair_obs = {k for k in range(len(f.obs)) if f.truth[k] in (i, j)}
    assert pair_obs <= set(v.ambiguous)
    assert not (pair_obs & set(v.matches))
    assert all(f.truth[o] == c for o, c in v.matches.items())
    assert len(v.matches) == len(f.obs) - 2


def test_unknown_statistic(cat, cam):
    f = frame_with(cat, cam, 5, seed=10)
    with pytest.raises(ValueError):
        verify(f.obs.vectors, {0: int(f.truth[0]), 1: int(f.truth[1])}, cat, cam, SIGMA, statistic="magic")


def test_a_blended_close_pair_is_never_reported():
    """nu Draconis (HIP 85819 / 85829, 62" apart, Hp 4.96 / 4.94) seen through a 20 deg, 1024 px camera
    is one centroid between the two: the verification must report neither identity, whichever
    component the centroid happens to lie nearer to."""
    cat = load_guide_catalog().brighter_than(6.0)
    cam20 = Camera.from_fov(20.0, 1024)
    a, b = cat.index_of(85819), cat.index_of(85829)
    mid = cat.xyz[a] + cat.xyz[b]
    mid /= np.linalg.norm(mid)
    ra, dec = vec_to_radec(mid)
    R = R_from_radec_roll(float(ra) + 0.02, float(dec) + 0.01, 0.3)
    rows, _ = cam20.visible(R, cat.xyz)
    rows = [int(r) for r in rows if r not in (a, b)]
    for lean in (0.0, 0.45, -0.45):  # the blend's centroid at the midpoint or next to one component
        blend = mid + lean * (cat.xyz[a] - cat.xyz[b])
        vectors = np.vstack([cat.xyz[rows] @ R.T, (blend / np.linalg.norm(blend)) @ R.T])
        k = len(vectors) - 1
        hyp = {i: rows[i] for i in range(4)}
        ver = verify(vectors, hyp, cat, cam20, 10e-6)
        assert ver.passed
        assert k not in ver.matches
        if lean:  # within the match radius of one component: without the blend rule it would be reported
            assert k in ver.ambiguous
        assert all(ver.matches[i] == rows[i] for i in ver.matches)


def test_predicted_sigma_closed_form_is_the_largest_eigenvalue():
    """sqrt of the largest eigenvalue of [b]x P [b]x^T (the batched eigensolver's answer) for unit and
    non-unit vectors, full-rank and rank-deficient covariances."""
    from skyview.identify.verify import predicted_sigma
    rng = np.random.default_rng(4)
    for k in range(200):
        A = rng.normal(size=(3, 3))
        P = A @ A.T * 10.0 ** rng.uniform(-12, -6)
        if k % 4 == 0:
            P[2], P[:, 2] = 0.0, 0.0
        b = rng.normal(size=(15, 3))
        if k % 2:
            b /= np.linalg.norm(b, axis=1, keepdims=True)
        K = np.zeros((len(b), 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -b[:, 2], b[:, 1], -b[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = b[:, 2], -b[:, 1], b[:, 0]
        ref = np.sqrt(np.maximum(np.linalg.eigvalsh(K @ P @ K.transpose(0, 2, 1))[:, -1], 0.0))
        np.testing.assert_allclose(predicted_sigma(b, P), ref, rtol=1e-9, atol=1e-12 * ref.max())
    assert predicted_sigma(np.zeros((0, 3)), np.eye(3)).shape == (0,)


def test_radii_of_a_subset_from_every_rows_unit_vectors():
    """verify normalises every observed vector once and takes the rows of a subset: the radii are those
    of the subset's own vectors, to the bit."""
    from skyview.identify.verify import _unit_rows, star_radii
    rng = np.random.default_rng(10)
    for k in range(300):
        b = rng.normal(size=(int(rng.integers(2, 60)), 3))
        b /= np.linalg.norm(b, axis=1, keepdims=True) * (1.0 if k % 2 else rng.uniform(0.5, 2.0))
        A = rng.normal(size=(3, 3))
        P = A @ A.T * 10.0 ** rng.uniform(-12, -7)
        idx = np.sort(rng.choice(len(b), int(rng.integers(0, len(b) + 1)), replace=False))
        n, s2 = _unit_rows(b)
        assert np.array_equal(star_radii(None, P, 1e-4, 4e-4, (n[idx], s2[idx])), star_radii(b[idx], P, 1e-4, 4e-4))


# ------------------------------------------------------------------ the fast paths give the same answers

def _verification_record(v):
    return (v.passed, v.reason, v.matches, v.p_false, v.n_agree, v.n_tested, v.n_frame, v.p_tested, v.ambiguous,
            v.agreeing, v.max_residual_rad, v.radius_max_rad, None if v.R is None else v.R.tolist())


def _hypotheses(f, rng):
    """A correct hypothesis of 2-4 stars of frame f, and the same stars shuffled."""
    n = len(f.obs)
    k = int(rng.integers(2, min(4, n) + 1))
    obs = [int(i) for i in rng.choice(n, k, replace=False)]
    right = {i: int(f.truth[i]) for i in obs}
    shuffled = dict(zip(obs, np.roll([right[i] for i in obs], 1).tolist()))
    return right, shuffled


def test_fast_paths_agree_with_the_general_ones(cat, cam, monkeypatch):
    """The pairs within a radius (from one distance array, or the few a dot product puts near), paired in
    Python lists, and the remembered nearest-neighbour chords answer exactly as the k-d tree paths and
    the numpy pairing: every figure of the verification equal, to the last bit."""
    import skyview.identify.verify as V

    rng = np.random.default_rng(5)
    cases = []
    for seed in range(40):
        f = frame_with(cat, cam, 3, seed=100 + seed)
        cases += [(f, h) for h in _hypotheses(f, rng)]
    # the base radius as it is, and 40 times wider (several catalog stars within each: the pairing and
    # the ambiguity decide)
    radii = (match_radius(SIGMA), 40 * match_radius(SIGMA))

    def run():
        return [_verification_record(verify(f.obs.vectors, h, cat, cam, SIGMA, radius_rad=r))
                for f, h in cases for r in radii]

    fast = run()
    assert sum(r[0] for r in fast) >= 20  # correct hypotheses pass: the accepted branch is exercised
    monkeypatch.setattr(V, "ONE_EACH_FAST", False)  # one-to-one frames paired as any other
    assert run() == fast
    monkeypatch.setattr(V, "PREFILTER_PAIRS", 0)  # every frame's pairs through the dot-product prefilter
    assert run() == fast
    monkeypatch.setattr(V, "_apart", lambda x, radius_rad: False)  # every ambiguity and crowd counted
    monkeypatch.setattr(V, "_stars_apart", lambda catalog, rows, v, radius_rad: False)
    assert run() == fast
    monkeypatch.setattr(V, "BRUTE_PAIRS", 0)  # every distance from a k-d tree
    monkeypatch.setattr(V, "ONE_TO_ONE_PY", -1)  # the numpy pairing
    monkeypatch.setattr(V, "_NEAREST", {})
    monkeypatch.setattr(V, "_has_neighbour", lambda catalog, rows, chords: np.asarray(
        catalog.tree.query_ball_point(catalog.xyz[rows], chords, return_length=True)) >= 2)
    assert run() == fast


def test_p_false_decides_and_sums_as_numpy_did():
    """p_false_calibrated (on Python floats) takes the binomial exactly when np.all(ps == ps[0]) holds
    (a NaN included) and the Poisson-binomial tail otherwise; the misses' probabilities 1 - p are the
    numbers numpy's 1.0 - ps gives. (skyview.core.special.binomial_sf is scipy's bdtrc to 1e-11:
    tests/test_special.py.)"""
    from skyview.core.special import binomial_sf
    from skyview.identify.verify import p_false_calibrated, poisson_binomial_sf

    rng = np.random.default_rng(8)
    for k in range(300):
        n = int(rng.integers(1, 45))
        ps = rng.uniform(0, 10.0 ** rng.uniform(-5, 0), n)
        if k % 3 == 0:
            ps[:] = ps[0]
        if k % 50 == 7:
            ps[int(rng.integers(0, n))] = np.nan
        assert np.array_equal([1.0 - p for p in ps.tolist()], 1.0 - ps, equal_nan=True)
        for n_agree in {1, 2, n // 2 + 1, n - 1, n} - {0}:
            want = (binomial_sf(n_agree, n, float(ps[0])) if np.all(ps == ps[0])
                    else poisson_binomial_sf(n_agree, ps))
            got = p_false_calibrated(n_agree, n, ps, 3)
            assert got == min(1.0, 3 * want) or (np.isnan(got) and np.isnan(want))
            assert p_false_calibrated(n_agree, n, ps.tolist(), 3) == got or np.isnan(got)


def test_verify_step_shows_the_verification(cat, cam):
    """The 'verify' step's figures are the verification record's, its rows the matches' (or the rejected
    hypothesis'), in observed order."""
    from skyview.identify.verify import VERIFY_NUMBERS, verification_step

    f = frame_with(cat, cam, 3, seed=3)
    right, shuffled = _hypotheses(f, np.random.default_rng(2))
    for h in (right, shuffled):
        ver = verify(f.obs.vectors, h, cat, cam, SIGMA)
        step = verification_step(ver, h, numbers={"extra": 2.0})
        vd = ver.to_dict()
        assert step.numbers == {**{k: vd[k] for k in VERIFY_NUMBERS}, "passed": float(ver.passed), "extra": 2.0}
        assert [type(step.numbers[k]) for k in VERIFY_NUMBERS] == [type(vd[k]) for k in VERIFY_NUMBERS]
        shown = ver.matches or h
        assert step.observed == sorted(shown) and step.catalog == [shown[o] for o in sorted(shown)]
        assert step.to_dict()["catalog"] == step.catalog


def test_has_neighbour_is_the_kd_tree_count(cat):
    """Remembered nearest-neighbour chords, with chords exactly at (and a hair around) a neighbour's
    distance, answer as the k-d tree's own count."""
    from skyview.core.catalog import chord
    from skyview.identify.verify import _has_neighbour

    rng = np.random.default_rng(3)
    rows = rng.choice(len(cat.xyz), 400, replace=False)
    nn = cat.tree.query(cat.xyz[rows], k=2)[0][:, 1]
    for chords in (chord(rng.uniform(1e-4, 0.02, len(rows))), nn, nn * (1 + 1e-15), nn * (1 - 1e-15)):
        want = np.asarray(cat.tree.query_ball_point(cat.xyz[rows], chords, return_length=True)) >= 2
        assert np.array_equal(_has_neighbour(cat, rows, chords), want)
        assert np.array_equal(_has_neighbour(cat, rows, chords), want)  # remembered the second time


@pytest.mark.slow
def test_nearest_table_is_each_stars_nearest_chord_and_cached(cat, tmp_path, monkeypatch):
    """The verification's table of nearest-neighbour chords is every star's chord to its nearest other
    star (measured here star by star; inf beyond the reach, 0 for a star that shares its place), built
    once and read back from the cache with the same numbers; a catalog of one star has no neighbour."""
    from skyview.identify import database
    from skyview.identify.verify import NEAREST_REACH_RAD, nearest_table

    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    built = nearest_table(cat)
    reach = 2.0 * np.sin(NEAREST_REACH_RAD / 2.0)
    want = np.empty(len(cat.xyz))
    for k in range(0, len(cat.xyz), 500):  # every pair's chord, a block of stars at a time
        d = np.linalg.norm(cat.xyz[k:k + 500, None] - cat.xyz[None], axis=2)
        d[np.arange(len(d)), np.arange(k, k + len(d))] = np.inf  # not a star with itself
        want[k:k + len(d)] = d.min(axis=1)
    far = want > reach * (1 + 1e-12)
    assert np.isinf(built[far]).all() and np.isfinite(built[~far]).all()
    np.testing.assert_allclose(built[~far], want[~far], rtol=1e-12, atol=1e-15)
    assert np.isinf(built).any() and np.isfinite(built).any()
    files = list((tmp_path / "databases").glob("nearest-*.npz"))
    assert len(files) == 1
    assert np.array_equal(nearest_table(cat), built)  # from the file
    twin = cat.select(np.r_[np.arange(len(cat.xyz)), 0], "star 0 twice")  # star 0 twice: each one's nearest is the other
    assert nearest_table(twin)[0] == 0.0 and nearest_table(twin)[-1] == 0.0
    assert np.isinf(nearest_table(cat.select(np.array([5]), "one star")))[0]
    assert database.clear_cache("nearest")[0] == 3 and not list((tmp_path / "databases").glob("nearest-*"))


def test_stars_apart_only_where_no_ball_holds_two(cat):
    """_stars_apart (from the remembered nearest neighbours) says True only where no two of the stars lie
    within twice the ball's chord, turned by any attitude; it says False next to a close pair, and
    beyond the neighbours' reach it is _apart itself."""
    from skyview.core.catalog import chord
    from skyview.identify.verify import NEAREST_REACH_RAD, _apart, _stars_apart

    rng = np.random.default_rng(4)
    said = []
    for k in range(300):
        R = random_attitudes(1, rng)[0]
        rows = np.sort(rng.choice(len(cat.xyz), int(rng.integers(0, 80)), replace=False))
        v = cat.xyz[rows] @ R.T
        radius = float(rng.choice([1e-4, 1e-3, 5e-3, 0.02]))
        got = _stars_apart(cat, rows, v, radius)
        d = np.linalg.norm(v[:, None] - v[None], axis=2) + np.diag(np.full(len(rows), np.inf))
        if got:
            assert len(rows) < 2 or d.min() > 2 * chord(radius)
        said.append(got)
    assert any(said) and not all(said)
    i, j = cat.pairs_within(np.radians(0.05))[0]
    pair = np.array([i, j])
    assert not _stars_apart(cat, pair, cat.xyz[pair], np.radians(0.05))
    wide = 0.6 * NEAREST_REACH_RAD  # twice its chord beyond the reach
    assert _stars_apart(cat, pair, cat.xyz[pair], wide) == _apart(cat.xyz[pair], wide)


def test_svd_attitude_one_sigma_is_the_per_pair_path_to_the_bit():
    from skyview.core.attitude import q_method_attitude

    rng = np.random.default_rng(11)
    for _ in range(200):
        n = int(rng.integers(2, 30))
        r = rng.normal(size=(n, 3))
        r /= np.linalg.norm(r, axis=1)[:, None]
        R = random_attitudes(1, rng)[0]
        b = r @ R.T + rng.normal(size=(n, 3)) * 1e-4
        b /= np.linalg.norm(b, axis=1)[:, None]
        s = float(rng.uniform(1e-5, 1e-3))
        one, per_pair = svd_attitude(b, r, s), svd_attitude(b, r, np.full(n, s))
        assert np.array_equal(one.R, per_pair.R) and np.array_equal(one.covariance, per_pair.covariance)
        assert one.loss == per_pair.loss
        resid = b - r @ one.R.T
        assert one.loss == pytest.approx(0.5 * np.sum(resid * resid) / s ** 2, rel=1e-12)
        assert abs(np.linalg.det(one.R) - 1.0) < 1e-12
        assert attitude_error_arcsec(one.R, q_method_attitude(b, r, s).R)["total"] < 1e-6


def test_svd3_is_numpys_svd_to_the_bit():
    """The LAPACK routine called directly gives np.linalg.svd's U and V^T, rank-deficient matrices too."""
    from skyview.core.attitude import _svd3

    rng = np.random.default_rng(6)
    for k in range(200):
        B = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-3, 12)
        if k % 5 == 0:
            B[2] = B[0] * 2.0
        U, _, Vt = np.linalg.svd(B)
        got = _svd3(B)
        assert np.array_equal(got[0], U) and np.array_equal(got[1], Vt)


def test_svd_attitude_bad_input():
    b = np.eye(3)
    with pytest.raises(ValueError):
        svd_attitude(b, b, 0.0)
    with pytest.raises(ValueError):
        svd_attitude(b[:1], b[:1], 1e-4)
    with pytest.raises(np.linalg.LinAlgError):
        svd_attitude(np.full((3, 3), np.nan), b, 1e-4)


def test_remembered_estimate_is_the_estimate(cat, cam):
    """The solver's attitude stage reuses the estimate the verification ended in: the same numbers as a
    new svd_attitude, in arrays of its own; anything else is estimated anew."""
    from skyview.core.attitude import svd_attitude_remembered

    f = frame_with(cat, cam, 6, seed=4)
    v = verify(f.obs.vectors, {i: int(f.truth[i]) for i in range(3)}, cat, cam, SIGMA)
    assert v.passed
    obs = np.array(sorted(v.matches))
    b, r = f.obs.vectors[obs], cat.xyz[[v.matches[o] for o in obs]]
    again = svd_attitude_remembered(b, r, SIGMA)
    new = svd_attitude(b, r, SIGMA)
    assert np.array_equal(again.R, new.R) and np.array_equal(again.covariance, new.covariance)
    assert again.loss == new.loss
    assert again.R is not v.R and np.array_equal(again.R, v.R)
    other = svd_attitude_remembered(b[:-1], r[:-1], SIGMA)  # not remembered: estimated
    assert np.array_equal(other.R, svd_attitude(b[:-1], r[:-1], SIGMA).R)


def test_result_cross_and_matched_stars(cat):
    from skyview.solver.result import _cross, matched_stars

    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
    assert np.array_equal(_cross(a, b), np.cross(a, b))
    uv = rng.uniform(0, 1000, (5, 2))
    matches = {3: 10, 0: 42, 4: 7}
    ms = matched_stars(cat, uv, matches, np.array([1e-5, 2e-5, 3e-5]))
    assert [m["index"] for m in ms] == [0, 3, 4]
    ra, dec = np.degrees(vec_to_radec(cat.xyz[[42, 10, 7]]))
    for m, row, k in zip(ms, (42, 10, 7), range(3)):
        assert m["hip"] == int(cat.hip[row]) and m["mag"] == float(cat.mag[row])
        assert (m["u"], m["v"]) == (float(uv[m["index"], 0]), float(uv[m["index"], 1]))
        assert m["ra_deg"] == float(ra[k]) and m["dec_deg"] == float(dec[k])
        assert m["residual_arcsec"] == pytest.approx((k + 1) * 1e-5 * 206264.806, rel=1e-6)
    assert matched_stars(cat, uv, {}) == []


def test_local_density_from_the_stars_around_a_frame_is_the_kd_tree_count(cat, cam):
    """The local density from the stars fetched around a frame (dot products, the few near the limit
    measured) counts as the k-d tree does; so does the sky index without them."""
    from skyview.core.catalog import chord
    from skyview.identify.verify import LOCAL_RADIUS_RAD, NearStars, local_density

    rng = np.random.default_rng(8)
    area = 2.0 * np.pi * (1.0 - np.cos(LOCAL_RADIUS_RAD))
    for seed in range(30):
        f = frame_with(cat, cam, 3, seed=300 + seed)
        d = f.obs.vectors @ f.R
        near = NearStars(cat, cam.half_diagonal_rad + LOCAL_RADIUS_RAD + 0.01)
        near.rows(f.R[2], cam.half_diagonal_rad)
        assert near.covers(d, LOCAL_RADIUS_RAD)
        n = cat.tree.query_ball_point(d, float(chord(LOCAL_RADIUS_RAD)), return_length=True)
        leave = rng.integers(0, 2, len(d)).astype(float)
        want = np.maximum(n - leave, 0.0)
        want[want < 3] = 0.0
        want /= area
        np.testing.assert_array_equal(local_density(cat, d, leave, among=near.wide), want)
        assert np.array_equal(near.wide_xyz, cat.xyz[near.wide]) and np.array_equal(near.xyz, cat.xyz[near.idx])
        np.testing.assert_array_equal(local_density(cat, d, leave, among=near.wide, among_xyz=near.wide_xyz), want)
        np.testing.assert_array_equal(local_density(cat, d, leave), want)
    assert not near.covers(-d, LOCAL_RADIUS_RAD)  # the far side of the sky is not among its stars


def test_quaternion_and_rotation_vector_are_scipys_to_the_bit():
    from scipy.spatial.transform import Rotation

    from skyview.core.attitude import quat_from_R, rotvec_from_R

    rng = np.random.default_rng(4)
    Rs = list(random_attitudes(3000, rng)) + [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]),
                                              np.diag([-1.0, -1, 1])]
    for scale in (1e-7, 1e-4, 1e-1, 2.0):  # small rotations: the series branch of the angle
        Rs += [Rotation.from_rotvec(rng.normal(0, scale, 3)).as_matrix() for _ in range(300)]
    Rs += [R + rng.normal(0, 1e-6, (3, 3)) for R in Rs[:50]]  # not orthogonal: scipy's own path
    for R in Rs:
        q = Rotation.from_matrix(R).as_quat(scalar_first=True)
        assert np.array_equal(quat_from_R(R), -q if q[0] < 0 else q)
        assert np.array_equal(rotvec_from_R(R), Rotation.from_matrix(R).as_rotvec())


def test_calibrated_verification_imports_no_kd_tree():
    """Verifying, estimating and reporting an attitude (the calibrated solve path) never imports
    scipy.spatial (~0.1 s): the sky index answers the neighbour queries."""
    import subprocess
    import sys

    code = """
import sys
import numpy as np
from skyview.core.attitude import R_from_radec_roll, attitude_error_arcsec, quat_from_R
from skyview.core.camera import Camera
from skyview.core.catalog import load_guide_catalog
from skyview.identify.synthetic import synthetic_frame
from skyview.identify.verify import verify
cat = load_guide_catalog().brighter_than(6.0)
cam = Camera.from_fov(20.0, 1024)
R = R_from_radec_roll(1.4, -0.1, 0.2)
f = synthetic_frame(cat, cam, R, 87e-6, np.random.default_rng(0))
v = verify(f.obs.vectors, {i: int(f.truth[i]) for i in range(3)}, cat, cam, 87e-6)
assert v.passed, v.reason
quat_from_R(v.R), attitude_error_arcsec(v.R, R)
print(sorted(m for m in sys.modules if m.startswith("scipy.spatial")))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_frame_stars_with_shared_near_stars_are_a_fresh_fetchs(catalog):
    """`frame_stars(..., near=)` with the stars fetched around an earlier attitude and camera of the same
    frame (a blind hypothesis' quick check, then its fits) gives the rows a fresh fetch gives: undistorted
    and distorted pinholes (the verification frame's in-place projection), the fit moving the boresight and
    the FOV; and for a distortion that folds back before the corner (a fit pushed to its bounds), the rows
    stay the field's however wide the earlier fetch was."""
    from skyview.core.camera_fit import MAX_STRETCH
    from skyview.identify.verify import NearStars, frame_stars

    rng = np.random.default_rng(21)
    for R in random_attitudes(40, rng):
        fov = float(rng.uniform(5.0, 40.0))
        k1 = float(rng.choice([0.0, 1.0]) * rng.uniform(-0.15, 0.15))
        near = NearStars(catalog)
        first = Camera.from_fov(fov * 1.05, 1024, 768, k1=k1)
        frame_stars(catalog, first, R, near=near)  # the quick check's camera, a little wide
        nudge = R_from_radec_roll(0.0, 0.0, 0.0)  # then the fits: the boresight moved by ~20"
        turn = np.array([[1.0, 0.0, 1e-4], [0.0, 1.0, 0.0], [-1e-4, 0.0, 1.0]])
        for cam, Rk in ((Camera.from_fov(fov, 1024, 768, k1=k1), turn @ R), (Camera.from_fov(fov, 1024, 768, k1=k1,
                                                                                              k2=0.01), nudge @ R)):
            shared = frame_stars(catalog, cam, Rk, near=near)
            fresh = frame_stars(catalog, cam, Rk)
            assert np.array_equal(shared, fresh)
            uv, front = cam.project(catalog.xyz[fresh] @ Rk.T)
            assert front.all() and cam.in_image(uv).all()
    # a barrel term at the fit's bound: the model turns back inside the image
    R = random_attitudes(1, rng)[0]
    folding = Camera.from_fov(30.0, 1024, 768)
    rc2 = (np.hypot(1024, 768) / 2.0 / folding.fx) ** 2
    folding = Camera.from_fov(30.0, 1024, 768, k1=-MAX_STRETCH / rc2)
    near = NearStars(catalog)
    frame_stars(catalog, Camera.from_fov(39.0, 1024, 768), R, near=near)
    assert np.array_equal(frame_stars(catalog, folding, R, near=near), frame_stars(catalog, folding, R))


@pytest.mark.parametrize("camera, mag", [
    (Camera.from_fov(20.0, 1024), 6.0),
    (Camera.from_fov(30.0, 800, 600, k1=-0.2, k2=0.05), 6.0),  # barrel: frame_stars keeps the corner's cone
    (Camera.from_fov(150.0, 640, 480, model="equisolid", k1=-0.05), 4.0),  # a fisheye beyond its half-diagonal
])
def test_many_synthetic_frames_at_once_are_those_made_one_by_one(catalog, camera, mag):
    cat = catalog.brighter_than(mag)
    rng = np.random.default_rng(11)
    n = 300
    ra, dec, roll = rng.uniform(0, 2 * np.pi, n), np.arcsin(rng.uniform(-1, 1, n)), rng.uniform(-np.pi, np.pi, n)
    Rs = attitudes_from_radec_roll(ra, dec, roll)
    # proper rotations whose boresight, RA, Dec and roll are the ones asked for (R_from_radec_roll is one of them)
    assert np.allclose(Rs @ Rs.transpose(0, 2, 1), np.eye(3), rtol=0, atol=1e-14) and np.all(np.linalg.det(Rs) > 0)
    back = np.array([radec_roll_from_R(R) for R in Rs])
    assert np.allclose(back[:, 0], ra, rtol=0, atol=1e-12) and np.allclose(back[:, 1], dec, rtol=0, atol=1e-12)
    assert np.allclose(np.angle(np.exp(1j * (back[:, 2] - roll))), 0.0, rtol=0, atol=1e-12)
    assert np.array_equal(R_from_radec_roll(ra[0], dec[0], roll[0]), Rs[0])
    many = synthetic_frames(cat, camera, Rs, 20e-6, [np.random.default_rng([4, i]) for i in range(n)])
    stars = 0
    for i, (R, b) in enumerate(zip(Rs, many)):
        a = synthetic_frame(cat, camera, R, 20e-6, np.random.default_rng([4, i]))
        assert np.array_equal(a.truth, b.truth)  # the same stars, brightest first
        assert np.allclose(a.obs.vectors, b.obs.vectors, rtol=0, atol=1e-15)  # the same noise draws
        assert np.allclose(a.obs.uv, b.obs.uv, rtol=0, atol=1e-9) and np.array_equal(a.obs.brightness, b.obs.brightness)
        assert b.obs.sigma_rad == 20e-6 and np.array_equal(b.R, R)
        stars += len(a.truth)
    assert stars > 20 * n
