"""The stochastic method (Udomkesmalee et al. 1994): statistics, the Bayesian recursion, sequences end to end."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from skyview.bench.sequence import bench_sequence, format_sequence_markdown
from skyview.cli import main
from skyview.core.attitude import attitude_error_arcsec
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, load_guide_catalog, radec_to_vec
from skyview.core.errors import BadInput
from skyview.identify import IDENTIFIED, METHODS, make_identifier
from skyview.identify.base import Observation
from skyview.identify.layers import Posterior
from skyview.identify.stochastic import (
    PAPER_Q,
    StochasticMethod,
    field_statistics,
    neighbour_angles,
    observed_basis,
    position_angles,
)
from skyview.simulate.render import betelgeuse_ra_sequence, save_sequence, turn_about_camera_axis
from skyview.simulate.scenarios import get_scenario
from skyview.simulate.scoring import sequence_truth
from skyview.solver.sequence import PAPER_SENSOR, perturb_magnitudes, vector_frame, zero_point

DEG = np.pi / 180


@pytest.fixture(scope="module")
def full_catalog(catalog):
    return catalog  # conftest's session catalog


@pytest.fixture(scope="module")
def cat(full_catalog):
    return full_catalog.brighter_than(4.5)


@pytest.fixture(scope="module")
def cam():
    return Camera.from_fov(30.0, 1024)


@pytest.fixture(scope="module")
def ident(cache, cat, cam):
    # the simulator's photometric zero point, realistic noise (centroids of a 105"/px camera)
    return make_identifier("stochastic", cat, cam, 20.0 / 206265.0, mag_zero_point=zero_point(PAPER_SENSOR))


# ------------------------------------------------------------------------------ statistics


def test_statistics_of_a_hand_made_field():
    # designated star mag 2; neighbours at 1, 2, 3 deg, position angles 0, 90, 180 deg, mags 3, 4, 5
    x = field_statistics(2.0, np.array([3.0, 4.0, 5.0]), np.array([1.0, 2.0, 3.0]) * DEG,
                         np.array([0.0, 90.0, 180.0]) * DEG)
    gaps = np.array([90.0, 90.0, 180.0]) * DEG  # the neighbouring angles of Fig. 1
    assert x[0] == 4
    assert x[1] == pytest.approx(3.5)
    assert x[2] == pytest.approx(np.sqrt(1.25))  # std of 2, 3, 4, 5 (ddof 0)
    assert x[3] == pytest.approx(2.0 * DEG)
    assert x[4] == pytest.approx(np.sqrt(2.0 / 3.0) * DEG)
    assert x[5] == pytest.approx(np.std(gaps))
    assert np.sort(neighbour_angles(np.array([0.0, 90.0, 180.0]) * DEG)) == pytest.approx(np.sort(gaps))


def test_statistics_edge_cases_and_angles_sum_to_a_turn():
    assert field_statistics(3.0, [], [], []).tolist() == [1, 3.0, 0, 0, 0, 0]
    one = field_statistics(3.0, [4.0], [0.1], [1.0])
    assert one[5] == 0.0 and one[4] == 0.0 and one[3] == pytest.approx(0.1)
    rng = np.random.default_rng(1)
    phi = rng.uniform(-np.pi, np.pi, 17)
    assert neighbour_angles(phi).sum() == pytest.approx(2 * np.pi)
    assert np.all(neighbour_angles(phi) >= 0)


def test_statistics_from_vectors_are_rotation_invariant():
    rng = np.random.default_rng(7)
    v = rng.normal(size=(12, 3)) * [0.2, 0.2, 1.0]
    v[:, 2] = np.abs(v[:, 2]) + 1.0
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    mags = rng.uniform(0, 4.5, 12)

    def stats(vec):
        a1, a2 = observed_basis(vec[0])
        d, phi = position_angles(vec[0], vec[1:], a1, a2)
        return field_statistics(mags[0], mags[1:], d, phi)

    x0 = stats(v)
    for R in Rotation.random(5, random_state=3).as_matrix():
        assert stats(v @ R.T) == pytest.approx(x0, abs=1e-9)
    # the hand-computable parts agree with a direct computation
    d = np.arccos(np.clip(v[1:] @ v[0], -1, 1))
    assert x0[3] == pytest.approx(d.mean()) and x0[4] == pytest.approx(d.std())


# ------------------------------------------------------------------------------ the Bayesian update


def _isolated_catalog(mags):
    """Stars so far apart that each 10 deg field holds only itself: xi_s = [1, m_s, 0, 0, 0, 0]."""
    n = len(mags)
    ra = np.arange(n) * 2 * np.pi / n
    xyz = radec_to_vec(ra, np.zeros(n))
    return GuideCatalog(hip=np.arange(1, n + 1, dtype=np.int32), xyz=xyz, mag=np.asarray(mags, np.float32),
                        pm=np.zeros((n, 2), np.float32), bv=np.zeros(n, np.float32), flags=np.zeros(n, np.uint8))


def _single_star(m):
    return Observation(vectors=np.array([[0.0, 0.0, 1.0]]), uv=np.array([[127.5, 127.5]]),
                       brightness=np.array([10 ** (-0.4 * m)]), sigma_rad=1e-4)


def test_bayesian_update_by_hand(cache):
    mags = [1.0, 2.0, 3.0, 2.5]
    small = _isolated_catalog(mags)
    m = StochasticMethod(small, Camera.from_fov(10.0, 256), 1e-4, mag_zero_point=0.0, p_identify=1.0)
    assert m.xi[:, 0] == pytest.approx(1.0) and m.xi[:, 1] == pytest.approx(mags)
    assert np.all(m.xi[:, 2:] == 0)
    q = PAPER_Q[1]  # 0.36 mag^2: the only component that differs between the hypotheses
    state = m.start()
    assert state.posterior == pytest.approx(np.full(4, 0.25))  # equal priors 1/N
    r0 = m.update(state, _single_star(2.0), None)
    like0 = np.exp(-0.5 * (2.0 - np.array(mags)) ** 2 / q)
    assert state.posterior == pytest.approx(like0 / like0.sum())
    assert r0.stats["above_prior"] == int(np.sum(like0 / like0.sum() > 0.25))
    # a turn about the boresight keeps every row on its star; the posterior is carried over (eq. 3)
    turn = Rotation.from_rotvec([0, 0, 0.3]).as_matrix()
    r1 = m.update(state, _single_star(2.4), turn)
    like1 = np.exp(-0.5 * (2.4 - np.array(mags)) ** 2 / q)
    post = like0 * like1 / np.sum(like0 * like1)
    assert state.rows.tolist() == [0, 1, 2, 3]
    assert state.posterior == pytest.approx(post)
    assert r1.stats["top_rows"][0] == int(np.argmax(post)) == 1
    assert r1.stats["top_posterior"] == pytest.approx(post.max())
    assert r1.status != IDENTIFIED  # nothing to verify with in a one-star field


def test_relative_magnitudes_without_a_zero_point(cache):
    mags = [1.0, 2.0, 3.0]
    m = StochasticMethod(_isolated_catalog(mags), Camera.from_fov(10.0, 256), 1e-4)
    state = m.start()
    # with one star, mean(m) - m_designated = 0 for every hypothesis: no magnitude information at all
    m.update(state, _single_star(-12.0), None)
    assert state.posterior == pytest.approx(np.full(3, 1 / 3))


# ------------------------------------------------------------------------------ sequences end to end


def _check_identifications(results, truths, true_R):
    n_id = 0
    for r, tr, R in zip(results, truths, true_R):
        if r.identified:
            n_id += 1
            assert len(r.matches) >= 3
            assert all(int(tr[o]) == c for o, c in r.matches.items()), "a wrong match"
            assert attitude_error_arcsec(r.R, R)["total"] < 300
    return n_id


def test_sequence_end_to_end_images(ident, cat, cam, full_catalog):
    seq = betelgeuse_ra_sequence(full_catalog, cam, n_frames=5, sensor=PAPER_SENSOR, seed=5, mag_limit=4.5,
                                 position_noise_rad=10.0 / 206265.0)
    from skyview.detect.centroids import detect_centroids
    from skyview.solver.sequence import observation, truth_rows

    rng = np.random.default_rng(0)
    obs = [perturb_magnitudes(observation(detect_centroids(f.image), cam, ident.sigma_rad), 0.6, rng)
           for f in seq.frames]
    truths = [truth_rows(o.uv, f.truth, cat) for o, f in zip(obs, seq.frames)]
    res = ident.identify_sequence(obs, [seq.dR_cam(k) for k in range(4)])
    assert _check_identifications(res, truths, [f.R for f in seq.frames]) >= 1
    # the truth is scored after the fact, from the posterior layers (the method never sees it)
    scored = sequence_truth(res, truths)
    assert scored[-1]["true_posterior"] > 0.9 and scored[-1]["true_rank"] == 0
    assert scored[-1]["true_row"] == truths[-1][res[-1].stats["designated"]]
    assert scored[0]["true_sequence_posterior"] < scored[-1]["true_sequence_posterior"]
    # the step record: per frame the hypotheses above the prior, the leading ones; no truth in it
    upd = [s for s in res[-1].steps if s.kind == "update"][0]
    assert {"above_prior", "top_posterior"} <= set(upd.numbers)
    assert not any(key.startswith("true") for s in res[-1].steps for key in s.numbers)
    assert not any(key.startswith("true") for r in res for key in r.stats)
    post = upd.layer(Posterior)
    assert len(post.top_mass) == len(upd.catalog) == 10
    assert np.all(np.diff(post.top_mass) <= 0)
    assert [s.kind for s in res[1].steps][:3] == ["statistics", "predict", "update"]
    json.dumps(res[-1].to_dict())


def test_random_sequences_never_wrong(ident, cat, cam):
    rng = np.random.default_rng(11)
    trn = turn_about_camera_axis("y", 10 * DEG)
    n_id = 0
    for R0 in Rotation.random(4, random_state=5).as_matrix():
        Rs = [R0]
        for _ in range(3):
            Rs.append(trn.apply(Rs[-1]))
        frames = [vector_frame(cat, cam, R, ident.sigma_rad, rng) for R in Rs]
        obs = [perturb_magnitudes(o, 0.6, rng) for o, _ in frames]
        # vector frames have brightness 10^(-0.4 Hp): zero point 0
        m = make_identifier("stochastic", cat, cam, ident.sigma_rad, mag_zero_point=0.0, variant="improved")
        res = m.identify_sequence(obs, [Rs[k + 1] @ Rs[k].T for k in range(3)])
        n_id += _check_identifications(res, [t for _, t in frames], Rs)
    assert n_id >= 4


def test_single_frame_through_the_solver(cache, full_catalog):
    from skyview.simulate.render import R_pointing_at, simulate_image
    from skyview.solver.pipeline import MethodSolver

    camera = Camera.from_fov(30.0, 1024)
    solver = MethodSolver(camera, "stochastic", mag_limit=4.5, catalog=full_catalog,
                          method_params={"mag_zero_point": zero_point(PAPER_SENSOR), "verify_top": 3})
    frame = simulate_image(full_catalog, camera, R_pointing_at(full_catalog, 27989), PAPER_SENSOR, seed=2,
                           mag_limit=4.5)
    res = solver.solve_array(frame.image)
    steps = res.identification.steps
    assert [s.kind for s in steps][:2] == ["statistics", "update"]  # one frame: the prior update only
    if res.solved:
        assert attitude_error_arcsec(res.R, frame.R)["total"] < 300
        truth = {s["hip"] for s in frame.truth["stars"]}
        assert all(m["hip"] in truth for m in res.matches)


def test_cli_solve_sequence(tmp_path, capsys, full_catalog, cache):
    cam = Camera.from_fov(30.0, 512)
    seq = betelgeuse_ra_sequence(full_catalog, cam, n_frames=4, sensor=PAPER_SENSOR, seed=1, mag_limit=4.5)
    save_sequence(seq, tmp_path)
    out = tmp_path / "result.json"
    rc = main(["solve-sequence", str(tmp_path), "--variant", "improved", "--json", "--output", str(out)])
    d = json.loads(capsys.readouterr().out)
    assert rc in (0, 1) and d == json.loads(out.read_text())
    assert len(d["frames"]) == 4 and d["mag_zero_point"] == pytest.approx(zero_point(PAPER_SENSOR))
    for f in d["frames"]:
        assert f.get("wrong_matches", 0) == 0
    if rc == 0:
        assert d["status"] == "solved" and d["frames"][d["frame"]]["error_arcsec"]["total"] < 300
    assert main(["solve-sequence", str(tmp_path), "--output", str(out)]) == 2  # exists: not overwritten
    assert main(["solve-sequence", str(tmp_path / "missing.json")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_bench_sequence_vector(cache):
    s = bench_sequence(get_scenario("udomkesmalee30"), 2, n_frames=3, level="vector",
                       position_noise_rad=20.0 / 206265.0, progress=False)
    assert len(s["per_frame"]) == 3 and s["outcomes_last_frame"]["incorrect"] == 0
    assert s["catalog_stars"] == len(load_guide_catalog().brighter_than(4.5))
    assert "Table 2" in format_sequence_markdown(s)
    json.dumps(s)


def test_bad_input(ident, cam, cat):
    o, _ = vector_frame(cat, cam, np.eye(3), ident.sigma_rad, np.random.default_rng(0))
    with pytest.raises(BadInput):
        ident.identify_sequence([o, o], [])  # two frames need one turn
    with pytest.raises(BadInput):
        ident.identify_sequence([o, o], [np.eye(3) * 2])  # not a rotation
    with pytest.raises(BadInput):
        make_identifier("stochastic", cat, cam, 1e-4, mag_cut=4.5)  # a cut needs a zero point
    with pytest.raises(BadInput):
        make_identifier("stochastic", cat, cam, 1e-4, Q=(1, 2, 3))
    assert "stochastic" in METHODS
    empty = Observation(np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0), 1e-4)
    assert ident.identify(empty).status == "failed"


def test_an_empty_first_frame_leaves_the_prior(cache):
    m = StochasticMethod(_isolated_catalog([1.0, 2.0, 3.0]), Camera.from_fov(10.0, 256), 1e-4, mag_zero_point=0.0)
    state = m.start()
    empty = Observation(np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0), 1e-4)
    r = m.update(state, empty, None)
    assert r.status == "failed" and state.frames == 0 and state.posterior == pytest.approx(np.full(3, 1 / 3))
    r = m.update(state, _single_star(1.0), np.eye(3))  # the first star seen is the prior update
    assert r.stats["frame"] == 1 and state.frames == 1
    assert r.stats["top_rows"][0] == 0


def test_boresight_hypothesis_registers_the_true_sequence_exactly(cache, cat, cam):
    """The paper taken literally: row r is "the boresight is on star r", carried by the inertial turn
    (10 deg along RA). Starting on Betelgeuse, the Betelgeuse row's boresight IS the true boresight, so
    its designated star is f(true boresight) at every frame, whatever the noise."""
    from skyview.simulate.render import HIP_BETELGEUSE, R_pointing_at, turn_along_ra

    m = make_identifier("stochastic", cat, cam, 1.0 * DEG, mag_zero_point=0.0, hypothesis="boresight")
    rng = np.random.default_rng(5)
    R = R_pointing_at(cat, HIP_BETELGEUSE)
    trn = turn_along_ra(10 * DEG)
    row0 = int(np.flatnonzero(cat.hip == HIP_BETELGEUSE)[0])
    state = m.start()
    T = None
    for k in range(4):
        obs, truth = vector_frame(cat, cam, R, 1.0 * DEG, rng)
        f_true = m.designated_star(R)
        des = int(np.flatnonzero(truth == f_true)[0])
        m.update(state, perturb_magnitudes(obs, 0.6, rng), T, designated=des)
        assert state.rows[row0] == f_true  # the true sequence registers exactly
        assert np.allclose(state.R[row0][2], R[2], atol=1e-9)  # its boresight is the true one
        R_next = trn.apply(R)
        T = R_next.T @ R  # the inertial turn: R_{k+1} = R_k T^T
        R = R_next
    with pytest.raises(BadInput):
        make_identifier("stochastic", cat, cam, 1e-4, hypothesis="boresight", registration="designated")
    with pytest.raises(BadInput):
        make_identifier("stochastic", cat, cam, 1e-4, hypothesis="roll")
