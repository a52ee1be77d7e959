"""The viewer tracks a sequence with any single-frame method: frame 0 lost-in-space, then tracking."""

import contextlib
import io

import pytest

from skyview.viewer.run import Solvers

viser = pytest.importorskip("viser")


def test_a_tab_tracks_a_sequence_and_steps_through_its_frames():
    from skyview.viewer.session import Session

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    s = Session(server, Solvers(), method="angle", variant="improved")
    try:
        assert s.wait_idle(120)
        p = s.panel
        with s.quietly():  # no solve for this control alone
            p.n_frames.value = 4
        p.track.value = True  # fires: the sequence controls show, and the tab re-solves as a tracked sequence
        assert s.wait_idle(180), s.error
        assert p.seq_controls.visible and p.seq_box.visible
        seq = s.tracked
        assert seq is not None and len(seq) == 4 and s.seq is None
        assert seq.modes[0] == "lost_in_space" and seq.modes[1:] == ["tracking"] * 3
        assert s.frame_index == 3 and "tracking" in p.frame_text.content.lower()
        p.frame.value = 1  # the slider shows frame 1: its own run and text
        assert s.frame_index == 1 and s.run is seq.frames[1]
        assert seq.shown == 1
        # back to one image: the tracked sequence leaves the scene
        p.track.value = False
        assert s.wait_idle(120)
        assert s.tracked is None and s.seq is None and not p.seq_box.visible
    finally:
        s.close()
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
