"""Tracking to the last star (issue 28, item 2): with a prediction, two stars on their predicted places
are a verified frame (three when the motion is unknown), judged by the shared verification's statistic;
a frame with fewer is coasted on the motion model and says so. Truth: simulated 8 deg slews at Hp 6."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.special import binomial_sf
from skyview.identify.verify import RADIUS_SIGMAS, verify_prediction
from skyview.simulate.render import SensorModel, simulate_sequence, turn_about_camera_axis
from skyview.simulate.scenarios import get_scenario
from skyview.simulate.truth import wrong_matches
from skyview.solver.track import COASTING, TRACKING, Tracker


@pytest.fixture(scope="module")
def slews(catalog):
    """The first nine slews of `skyview bench --scenario slew8 -n 20` (seed 0): 20 frames of 2 deg."""
    sc = get_scenario("slew8")
    rng = np.random.default_rng(0)
    atts = random_attitudes(20, rng)
    seeds = rng.integers(0, 2**31 - 1, size=20)
    turn = turn_about_camera_axis("y", math.radians(sc.step_deg))
    return sc, [simulate_sequence(catalog, sc.camera(), atts[i], sc.frames, turn, SensorModel(), seed=int(seeds[i]),
                                  **sc.render_kwargs()) for i in range(9)]


def _run(catalog, sc, sim, with_turns: bool):
    tr = Tracker(sc.camera(), "angle", mag_limit=sc.mag_limit, sigma_rad=sc.sigma_rad, catalog=catalog)
    return [tr.process(f.image, sim.dR_cam(k - 1) if (k and with_turns) else None) for k, f in enumerate(sim.frames)]


@pytest.mark.parametrize("with_turns", [True, False])
def test_frames_of_two_or_three_stars_keep_lock_with_no_wrong_match(catalog, slews, with_turns):
    sc, sims = slews
    by_prediction = []
    for sim in sims[:3]:
        frames = _run(catalog, sc, sim, with_turns)
        locked = False
        for k, fr in enumerate(frames):
            truth = sim.frames[k].truth
            n_stars = len(truth["stars"])
            if fr.solved:
                locked = True
                assert not wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in fr.matches], truth)
                assert attitude_error_arcsec(fr.R, sim.frames[k].R)["boresight"] < 60.0
                if fr.verified_by == "prediction":
                    by_prediction.append(len(fr.matches))
                    assert fr.mode == TRACKING and fr.p_false < 1e-3
            elif locked and n_stars >= 2 and fr.mode != "lost_in_space":
                pytest.fail(f"frame {k} shows {n_stars} stars but was not solved: {fr.reason}")
    assert min(by_prediction) == 2 and len(by_prediction) >= 5  # frames of two stars among them


def test_a_frame_with_one_star_is_coasted_on_the_motion_and_the_next_reacquires(catalog, slews):
    sc, sims = slews
    sim = sims[8]  # its frames 8-10 show one star or none at Hp 6 (the bench's ninth slew)
    frames = _run(catalog, sc, sim, with_turns=True)
    coasted = [fr for fr in frames if fr.mode == COASTING]
    assert len(coasted) >= 2, [(fr.frame, fr.mode, len(sim.frames[fr.frame].truth["stars"])) for fr in frames]
    assert all(len(sim.frames[fr.frame].truth["stars"]) <= 1 for fr in coasted)
    for fr in coasted:
        d = fr.to_dict()
        assert d["status"] == "failed" and not d["solved"] and d["R"] is None and "coasting" in d["reason"]
        err = attitude_error_arcsec(np.asarray(d["coasted"]["R"]), sim.frames[fr.frame].R)["boresight"]
        assert err < 5.0 * d["coasted"]["sigma_arcsec"]["boresight"] + 5.0  # the prediction, and its sigma
    last = coasted[-1].frame
    assert any(fr.solved for fr in frames[last + 1:])  # lock comes back after the gap


def test_the_prediction_alone_needs_its_chance_below_the_threshold_and_enough_stars():
    rng = np.random.default_rng(1)
    b = rng.normal(size=(3, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    catalog = SimpleNamespace(xyz=b.copy())  # the catalog stars exactly where the stars are seen (identity)
    sigma = 1e-5
    r = RADIUS_SIGMAS * sigma  # a certain prediction (P = 0): every bound is the base radius
    per_star = 1e-3 / (math.pi * r ** 2)  # stars per sr that give each detected star a chance of 1e-3
    matches = {0: 0, 1: 1}
    ver = verify_prediction(b, matches, catalog, sigma, np.zeros((3, 3)), per_star, 2)
    assert ver.passed and ver.p_false == pytest.approx(binomial_sf(2, 3, 1e-3))
    assert ver.matches == matches and ver.n_tested == 3 and ver.n_agree == 2
    np.testing.assert_allclose(ver.R, np.eye(3), atol=1e-9)
    # the hypotheses verified before it on the frame are counted with it (Bonferroni)
    later = verify_prediction(b, matches, catalog, sigma, np.zeros((3, 3)), per_star, 2, n_hypotheses=3)
    assert later.p_false == pytest.approx(3 * ver.p_false)
    assert not verify_prediction(b, matches, catalog, sigma, np.zeros((3, 3)), per_star, 3).passed  # motion unknown
    ver = verify_prediction(b, matches, catalog, sigma, np.zeros((3, 3)), 50 * per_star, 2)
    assert not ver.passed and "P(false)" in ver.reason  # two of three on places a twentieth of the sky's: chance
    # a match off its predicted place by more than its bound does not fit the attitude of the others
    moved = b.copy()
    moved[1] = np.cos(3 * r) * b[1] + np.sin(3 * r) * np.cross(b[1], b[0]) / np.linalg.norm(np.cross(b[1], b[0]))
    ver = verify_prediction(moved, {0: 0, 1: 1, 2: 2}, catalog, sigma, np.zeros((3, 3)), per_star, 2)
    assert not ver.passed and "do not fit" in ver.reason
