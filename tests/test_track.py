"""Tracking mode (skyview.solver.track): lost-in-space once, then tracked frames; loss of lock; the CLI; the bench."""

import json
import math

import numpy as np
import pytest

from skyview.cli import main
from skyview.core.attitude import R_from_radec_roll, attitude_error_arcsec
from skyview.core.camera import Camera
from skyview.core.errors import BadInput
from skyview.simulate.render import (
    SensorModel,
    save_sequence,
    simulate_image,
    simulate_sequence,
    turn_about_camera_axis,
)
from skyview.simulate.truth import wrong_matches
from skyview.solver.track import LOST_IN_SPACE, TRACKING, Tracker, body_turn_rotvec

CAM = Camera.from_fov(12.0, 1024)
STEP = math.radians(2.0)


@pytest.fixture(scope="module")
def slew(catalog):
    R0 = R_from_radec_roll(math.radians(83.8), math.radians(-5.4), math.radians(20.0))
    return simulate_sequence(catalog, CAM, R0, 10, turn_about_camera_axis("y", STEP), SensorModel(), seed=3,
                             mag_limit=6.0)


@pytest.fixture(scope="module")
def tracker(catalog):
    return Tracker(CAM, "angle", variant="improved", catalog=catalog)


def _wrong(fr, frame) -> list[int]:
    return wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in fr.matches], frame.truth)


def _check_slew(frames, sim):
    assert [f.mode for f in frames] == [LOST_IN_SPACE] + [TRACKING] * 9
    for fr, sf in zip(frames, sim.frames):
        assert fr.solved, fr.reason
        err = attitude_error_arcsec(fr.R, sf.R)
        assert err["boresight"] < 3.0 and err["total"] < 15.0, err  # roll is the weak axis of a 12 deg field
        assert _wrong(fr, sf) == [] and len(fr.matches) >= 10
    for fr in frames[1:]:
        assert fr.relative_to == fr.frame - 1
        true = body_turn_rotvec(sim.frames[fr.frame - 1].R, sim.frames[fr.frame].R)
        assert np.degrees(np.linalg.norm(true)) == pytest.approx(2.0, abs=1e-9)
        assert np.linalg.norm(fr.relative_rotvec_rad - true) * 206265 < 15.0


def test_a_slew_is_tracked_after_one_lost_in_space_frame(tracker, slew):
    tracker.reset()
    turns = [slew.dR_cam(k) for k in range(9)]
    frames = tracker.run([f.image for f in slew.frames], turns)
    _check_slew(frames, slew)
    assert all(f.predicted_by == "turn" for f in frames[1:])
    assert all("track" in f.time_ms and "lost_in_space" not in f.time_ms for f in frames[1:])
    # each tracked frame is an identification like any method's: its hypotheses through the template and the
    # shared verification (a windowed frame's chances within its windows), one Identification
    for f in frames[1:]:
        ident = f.identification
        assert ident.identified and ident.method == "track" and ident.stats["verified_by"] == f.verified_by
        kinds = [st.kind for st in ident.steps]
        assert kinds[0] == "match" and kinds[-1] == "verify" and kinds.count("verify") == ident.verification["n_hypotheses"]
        assert ident.verification["p_false"] == f.p_false < 1e-3
        np.testing.assert_array_equal(ident.R, f.R)
        assert sorted(ident.matches) == sorted(m["index"] for m in f.matches)
        # the chance of each tested star is its bound's share of its window, not the sky's density
        assert min(ident.verification["p_tested"]) > 10 * ident.verification["p_single"]


@pytest.mark.parametrize("method", ["svd", "ellipticity"])
def test_other_methods_track_the_slew_too(method, catalog, slew):
    """The same acceptance for two more methods (their databases build in seconds): one lost-in-space
    frame, nine tracked, accurate against the truth, no wrong match."""
    tr = Tracker(CAM, method, variant="improved", catalog=catalog)
    frames = tr.run([f.image for f in slew.frames], [slew.dR_cam(k) for k in range(9)])
    _check_slew(frames, slew)


def test_the_rate_predicts_once_two_attitudes_are_known(tracker, slew):
    """Without the turns: frame 1 has no rate (the camera moved 2 deg: lock is lost, LIS solves it),
    from frame 2 on the rate of the last two attitudes predicts."""
    tracker.reset()
    frames = tracker.run([f.image for f in slew.frames])
    assert frames[1].mode == LOST_IN_SPACE and frames[1].lost_lock and frames[1].solved
    assert [f.mode for f in frames[2:]] == [TRACKING] * 8
    assert all(f.predicted_by == "rate" for f in frames[2:])
    for fr, sf in zip(frames, slew.frames):
        assert fr.solved and _wrong(fr, sf) == []


def test_a_sudden_jump_loses_lock_and_lost_in_space_recovers(tracker, catalog):
    """The gyros report 2 deg per frame, but before frame 5 the camera jumped 10 deg more."""
    turn = turn_about_camera_axis("y", STEP)
    jump = turn_about_camera_axis("x", math.radians(10.0))
    Rs = [R_from_radec_roll(math.radians(150.0), math.radians(30.0), 0.4)]
    for k in range(1, 8):
        Rs.append(turn.apply(Rs[-1]) if k != 5 else jump.apply(turn.apply(Rs[-1])))
    images = [simulate_image(catalog, CAM, R, SensorModel(), seed=10 + k, mag_limit=6.0) for k, R in enumerate(Rs)]
    tracker.reset()
    frames = tracker.run([f.image for f in images], [turn.matrix] * 7)
    assert [f.mode for f in frames] == [LOST_IN_SPACE] + [TRACKING] * 4 + [LOST_IN_SPACE] + [TRACKING] * 2
    assert frames[5].lost_lock and frames[5].solved
    for fr, sf in zip(frames, images):
        assert fr.solved and _wrong(fr, sf) == []
        assert attitude_error_arcsec(fr.R, sf.R)["boresight"] < 3.0
    true = body_turn_rotvec(Rs[4], Rs[5])
    assert np.linalg.norm(frames[5].relative_rotvec_rad - true) * 206265 < 15.0  # the jump, measured


def test_a_blank_frame_is_not_solved_and_tracking_resumes(tracker, slew):
    images = [f.image for f in slew.frames]
    images[4] = np.full_like(images[4], 10)
    tracker.reset()
    frames = tracker.run(images, [slew.dR_cam(k) for k in range(9)])
    assert not frames[4].solved and "no stars" in frames[4].reason and frames[4].R is None
    assert [f.mode for k, f in enumerate(frames) if k != 4] == [LOST_IN_SPACE] + [TRACKING] * 8
    assert frames[5].relative_to == 3  # predicted over the gap, from the last solved frame
    true = body_turn_rotvec(slew.frames[3].R, slew.frames[5].R)
    assert np.linalg.norm(frames[5].relative_rotvec_rad - true) * 206265 < 15.0
    for k, (fr, sf) in enumerate(zip(frames, slew.frames)):
        if k != 4:
            assert fr.solved and _wrong(fr, sf) == []


def test_cli_json_lines(slew, tmp_path, capsys, cache):
    save_sequence(slew, tmp_path)
    out = tmp_path / "track.jsonl"
    rc = main(["solve-sequence", str(tmp_path), "--method", "angle", "--variant", "improved", "--json",
               "--output", str(out)])
    lines = capsys.readouterr().out.strip().splitlines()
    assert rc == 0 and len(lines) == 10 and out.read_text().strip().splitlines() == lines
    rows = [json.loads(x) for x in lines]
    assert [r["mode"] for r in rows] == ["lost_in_space"] + ["tracking"] * 9
    for r in rows:
        assert {"ra_deg", "dec_deg", "roll_deg", "quaternion", "n_matches", "time_ms"} <= set(r)
        assert r["wrong_matches"] == 0 and r["error_arcsec"]["boresight"] < 3.0
    assert all(abs(r["relative_angle_deg"] - 2.0) < 0.005 for r in rows[1:])
    # image paths in time order (no turns: the rate predicts), a readable line per frame
    paths = [str(tmp_path / f"frame_{k:03d}.png") for k in range(10)]
    rc = main(["solve-sequence", *paths, "--method", "angle", "--variant", "improved", "--fov-deg", "12"])
    text = capsys.readouterr().out.strip().splitlines()
    assert rc == 0 and len(text) == 10 and "tracking" in text[-1]


def test_cli_bad_inputs_are_one_line(tmp_path, capsys, slew, cache):
    save_sequence(slew, tmp_path)
    png = str(tmp_path / "frame_000.png")
    for argv in (["solve-sequence", png, "--method", "angle"],  # a method needs the FOV
                 ["solve-sequence", str(tmp_path / "missing.png"), "--fov-deg", "12", "--method", "angle"],
                 ["solve-sequence", str(tmp_path), "--method", "angle", "--p-identify", "0.9"],
                 ["solve-sequence", png, "--method", "stochastic"],
                 ["solve-sequence", str(tmp_path), png, "--method", "angle"]):
        rc = main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1, (argv, err)


def test_a_sequence_goes_on_past_frames_it_cannot_read(slew, tmp_path, capsys, cache):
    """A corrupt frame, a dropped one and one of another camera are each that frame's error (its JSON line,
    exit code 1); every good frame around them is solved, the tracker predicting across the gaps."""
    import cv2

    save_sequence(slew, tmp_path)
    paths = [str(tmp_path / f"frame_{k:03d}.png") for k in range(10)]
    (tmp_path / "frame_004.png").write_bytes(b"\x89PNG but not really")
    paths.insert(7, str(tmp_path / "dropped.png"))
    cv2.imwrite(str(tmp_path / "other.png"), np.zeros((64, 80), np.uint16))
    paths.append(str(tmp_path / "other.png"))
    rc = main(["solve-sequence", *paths, "--method", "angle", "--variant", "improved", "--fov-deg", "12", "--json"])
    out, err = capsys.readouterr()
    rows = [json.loads(x) for x in out.strip().splitlines()]
    assert rc == 1 and [r["frame"] for r in rows] == list(range(len(paths)))
    assert [r["frame"] for r in rows if r["status"] == "error"] == [4, 7, 11]
    assert all(r["error"] and "\n" not in r["error"] for r in rows if r["status"] == "error")
    good = [r for r in rows if r["status"] != "error"]
    assert len(good) == 9 and all(r["status"] == "solved" for r in good)
    for r in good:  # one JSON shape: the rotation matrix beside the quaternion, as `skyview solve --json`
        assert len(r["R"]) == 3 and {"quaternion", "ra_deg", "dec_deg", "roll_deg"} <= set(r)
    truth = {k: f for k, f in zip([0, 1, 2, 3, 5, 6, 8, 9, 10], [0, 1, 2, 3, 5, 6, 7, 8, 9])}
    for r in good:
        R_true = slew.frames[truth[r["frame"]]].R
        assert np.degrees(np.arccos(np.clip(np.asarray(r["R"])[2] @ R_true[2], -1, 1))) * 3600 < 10
    assert "3 of 12 frames could not be solved at all" in err and "Traceback" not in err
    none = main(["solve-sequence", str(tmp_path / "frame_004.png"), str(tmp_path / "dropped.png"), "--fov-deg", "12"])
    assert none == 2 and "none of the 2 frames could be read" in capsys.readouterr().err


def test_a_sequence_folder_goes_on_past_frames_it_cannot_read(slew, tmp_path, capsys, cache, monkeypatch):
    """A sequence.json whose frames include a corrupt one and one of another size: tracking and the stochastic
    method both go on past them (each that frame's error, exit code 1), and the frames are read one at a time as
    they are solved, not all before the first (memory flat over a long sequence)."""
    import cv2

    import skyview.solver.sequence as sq

    save_sequence(slew, tmp_path)
    (tmp_path / "frame_004.png").write_bytes(b"\x89PNG but not really")
    cv2.imwrite(str(tmp_path / "frame_007.png"), np.zeros((64, 80), np.uint16))
    reads = []
    load = sq.load_image
    monkeypatch.setattr(sq, "load_image", lambda p: reads.append(p) or load(p))
    seq = sq.load_sequence(tmp_path)
    assert len(reads) == 1 and len(seq.images) == 10  # the first frame only: the size
    assert isinstance(seq.images.read(4), BadInput) and "frame_007.png is 80x64" in str(seq.images.read(7))
    with pytest.raises(BadInput):
        seq.images[4]
    rc = main(["solve-sequence", str(tmp_path), "--method", "angle", "--variant", "improved", "--json"])
    out, err = capsys.readouterr()
    rows = [json.loads(x) for x in out.strip().splitlines()]
    assert rc == 1 and [r["status"] for r in rows] == ["solved"] * 4 + ["error"] + ["solved"] * 2 + ["error"] + \
        ["solved"] * 2
    assert all(r["wrong_matches"] == 0 and r["error_arcsec"]["boresight"] < 3.0 for r in rows if r["solved"])
    assert "2 of 10 frames could not be solved at all" in err and "Traceback" not in err
    # the stochastic method: the unreadable frames are frames without stars, carried across with the turns
    rc = main(["solve-sequence", str(tmp_path), "--json"])
    out, err = capsys.readouterr()
    d = json.loads(out)
    assert rc == 1 and d["frames_unusable"] == [4, 7] and len(d["frames"]) == 10
    assert [f["status"] for f in d["frames"] if f["frame"] in (4, 7)] == ["error", "error"]
    assert all(f.get("wrong_matches", 0) == 0 for f in d["frames"])
    assert "2 of 10 frames could not be used: frames 4, 7" in err and "Traceback" not in err
    for k in range(10):  # none readable: one line, exit code 2
        (tmp_path / f"frame_{k:03d}.png").write_bytes(b"")
    assert main(["solve-sequence", str(tmp_path)]) == 2 and "none of the 10 images" in capsys.readouterr().err


def test_slew_bench(cache):
    from skyview.bench.runner import format_markdown, run_bench
    from skyview.simulate.scenarios import get_scenario

    s = run_bench("angle", get_scenario("slew"), 1, variant="improved", progress=False)
    t = s["tracking_with_turns"]
    assert t["frames"] == 10 and t["solved"] == 10 and t["tracked"] == 9 and t["frames_with_wrong_match"] == 0
    assert s["tracking_with_rate"]["frames_with_wrong_match"] == 0
    assert t["relative_rotation_error_arcsec"]["max"] < 30.0
    md = format_markdown(s)
    assert "Tracking with angle" in md and "Time per frame" in md


def test_tracked_frames_centroid_only_windows_around_the_predicted_stars(tracker, slew):
    """A tracked frame measures windows around the brightest TRACK_STARS predicted stars (track_window):
    the positions are those of the whole-image centroider, and far fewer pixels are read."""
    from skyview.detect.centroids import detect_centroids
    from skyview.detect.windows import centroid_windows
    from skyview.solver.track import TRACK_STARS

    tracker.reset()
    frames = tracker.run([f.image for f in slew.frames[:4]], [slew.dR_cam(k) for k in range(3)])
    assert "centroid" in frames[0].time_ms and "centroid_windows" not in frames[0].time_ms
    for fr in frames[1:]:
        assert "centroid_windows" in fr.time_ms and "centroid" not in fr.time_ms and "lost_in_space" not in fr.time_ms
        assert fr.solved and fr.n_centroids <= 16
    img = slew.frames[3].image
    full = detect_centroids(img)
    R = slew.frames[3].R
    centers, half = tracker._windows(tracker._field(R), R, np.eye(3) * 1e-12, CAM.width, CAM.height)
    win = centroid_windows(img, centers, half, CAM.pixel_scale_rad, psf_sigma_px=full.psf_sigma_px)
    assert len(centers) <= TRACK_STARS and win.n_pixels < 0.02 * CAM.width * CAM.height
    inner = ~win.centroids.edge
    d = np.min(np.linalg.norm(win.centroids.uv[inner, None] - full.uv[None], axis=2), axis=1)
    # the same centroids as the whole image gives (the brightest, saturated star differs most: 0.03 px)
    assert inner.sum() >= 10 and d.max() < 0.05 and np.median(d) < 0.002


def test_the_rate_filter_predicts_a_constant_turn(tracker, slew):
    """After three solved frames without turns the filtered rate is the slew's 2 deg per frame."""
    tracker.reset()
    tracker.run([f.image for f in slew.frames[:5]])
    true = body_turn_rotvec(slew.frames[0].R, slew.frames[1].R)
    # the filter's rate is the turn of the attitude (R_j R_i^T), the inverse of the body's turn
    assert np.linalg.norm(-tracker.rate - true) * 206265 < 10.0
    sd = np.sqrt(np.diag(tracker.rate_covariance)) * 206265  # its 1-sigma per camera axis: roll is the weak one
    assert sd[0] < 10.0 and sd[1] < 10.0 and sd[2] < 120.0
