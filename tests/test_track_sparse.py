"""Tracking to the last star (issue 28, item 2): with a prediction, two stars on their predicted places
are a verified frame (three when the motion is unknown), judged by the shared verification's statistic;
a frame with fewer is coasted on the motion model and says so. Truth: simulated 8 deg slews at Hp 6."""

import math

import numpy as np
import pytest

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.special import binomial_sf
from skyview.simulate.render import SensorModel, simulate_sequence, turn_about_camera_axis
from skyview.simulate.scenarios import get_scenario
from skyview.simulate.truth import wrong_matches
from skyview.solver.track import COASTING, TRACKING, Tracker
from skyview.solver.track_verify import verify_by_prediction


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
    xyz = b.copy()  # the catalog stars exactly where the stars are seen (the identity attitude)
    radii = np.full(3, 1e-4)
    matches = {0: 0, 1: 1}
    p = np.full(3, 1e-3)
    sol, _ = verify_by_prediction(b, matches, p, xyz, 1e-5, radii, min_stars=2)
    assert sol is not None and sol.p_false == pytest.approx(binomial_sf(2, 3, 1e-3))
    np.testing.assert_allclose(sol.R, np.eye(3), atol=1e-9)
    assert verify_by_prediction(b, matches, p, xyz, 1e-5, radii, min_stars=3)[0] is None  # motion unknown: 3
    sol, why = verify_by_prediction(b, matches, np.full(3, 0.05), xyz, 1e-5, radii, min_stars=2)
    assert sol is None and "P(false)" in why  # two of three on places a fifth of the sky's: chance
