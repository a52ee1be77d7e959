"""A tracked sequence of any method in the viewer (skyview.viewer.sequence_run.track_sequence_run):
modes per frame against the truth, lock lost and regained, and the footprints drawn on a real viser
server."""

from __future__ import annotations

import numpy as np
import pytest

from skyview.core.errors import BadInput
from skyview.viewer.player import Player
from skyview.viewer.run import SceneConfig, Solvers
from skyview.viewer.sequence_run import SequenceConfig, track_sequence_run

SCENE = SceneConfig(ra_deg=83.8, dec_deg=-5.4, roll_deg=20.0, fov_deg=12.0, mag_limit=6.0, seed=3)
PAN = SequenceConfig(n_frames=6, turn="pan about camera y", step_deg=2.0)


@pytest.fixture(scope="module")
def solvers():
    return Solvers()


@pytest.fixture(scope="module")
def with_gyros(solvers):
    return track_sequence_run(SCENE, PAN, "angle", "improved", solvers)


def test_a_tracked_sequence_with_the_turns_given(with_gyros):
    seq = with_gyros
    assert seq.modes == ["lost_in_space"] + ["tracking"] * 5 and seq.lock_events() == []
    for k, run in enumerate(seq.frames):
        assert run.result.solved and run.wrong_matches == 0 and len(run.matches) >= 8
        assert run.error_arcsec["boresight"] < 3.0 and run.error_arcsec["total"] < 15.0
        if k:
            assert seq.tracked[k].relative_to == k - 1
            assert abs(np.degrees(np.linalg.norm(seq.tracked[k].relative_rotvec_rad)) - 2.0) < 0.005
    assert "| 5 | tracking |" in seq.markdown()


def test_without_gyros_lock_is_lost_at_frame_1_and_regained(solvers):
    """No turns: the still prediction misses the 2 deg turn (lock lost), lost-in-space solves frame 1
    (regained), and from frame 2 the rate of the last two attitudes predicts."""
    seq = track_sequence_run(SCENE, PAN, "svd", "improved", solvers, gyros=False)
    assert seq.modes == ["lost_in_space", "lost_in_space"] + ["tracking"] * 4
    ev = seq.lock_events()
    assert [(k, what) for k, what, _ in ev] == [(1, "lost"), (1, "regained")]
    assert "matched the prediction" in ev[0][2] and ev[1][2] == "by lost-in-space"
    assert all(r.wrong_matches == 0 for r in seq.frames)
    assert "lock lost" in seq.frame_markdown(1)


def test_the_footprints_and_the_played_frame_on_a_viser_scene(with_gyros):
    import viser

    seq = with_gyros
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        seq.show(server.scene)
        # one line set per mode present (lost-in-space, tracking) + one label per frame, and the outline
        assert len(seq.handles) == 2 + len(seq) and seq.current is not None and seq.shown == len(seq) - 1
        labels = [h for h in seq.handles if hasattr(h, "text")]
        assert [h.text for h in labels][:2] == ["0 · lost-in-space", "1 · tracking"]
        # the viewer's one player plays the frames (the session's moves the slider, which calls set_frame)
        shown = []

        def show(k):
            seq.set_frame(server.scene, k)
            shown.append(seq.shown)

        player = Player(None, show, interval_s=0.0, label="Play the frames", min_length=2)
        player.toggle(len(seq), None)
        assert player.wait(10) and shown == list(range(len(seq))) and seq.shown == len(seq) - 1
        seq.set_frame(server.scene, 2)
        assert seq.shown == 2
        with pytest.raises(BadInput):
            seq.set_frame(server.scene, 6)
        seq.hide()
        assert seq.handles == [] and seq.current is None
    finally:
        server.stop()


def test_the_stochastic_method_is_not_tracked(solvers):
    with pytest.raises(BadInput):
        track_sequence_run(SCENE, PAN, "stochastic", "paper", solvers)
