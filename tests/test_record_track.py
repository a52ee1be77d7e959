"""`skyview solve-sequence ... --record PATH.rrd` for tracking (skyview.record.track): the recording
has a `frame` timeline with each frame's entities, and its values are the tracker's, against the truth."""

import json
import math
from collections import defaultdict

import numpy as np
import pytest
from rerun.chunk import RrdReader

from skyview.cli import main
from skyview.core.attitude import R_from_radec_roll
from skyview.core.camera import Camera
from skyview.core.catalog import load_guide_catalog
from skyview.simulate.render import SensorModel, save_sequence, simulate_sequence, turn_about_camera_axis

CAM = Camera.from_fov(12.0, 1024)
PER_FRAME = ("/camera", "/camera/image", "/camera/image/centroids", "/camera/image/matches", "/sky/footprint",
             "/sky/boresight", "/log", "/plots/mode", "/plots/matches", "/plots/time_ms", "/plots/error_arcsec")


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory):
    cat = load_guide_catalog()
    R0 = R_from_radec_roll(math.radians(83.8), math.radians(-5.4), math.radians(20.0))
    sim = simulate_sequence(cat, CAM, R0, 5, turn_about_camera_axis("y", math.radians(2.0)), SensorModel(), seed=3,
                            mag_limit=6.0)
    d = tmp_path_factory.mktemp("track-seq")
    save_sequence(sim, d)
    return d


def read(path) -> dict:
    """Per entity: static flag, timelines, and the (frame, value) rows of each column."""
    out: dict = defaultdict(lambda: {"static": False, "timelines": set(), "columns": defaultdict(list)})
    for ch in RrdReader(path).stream():
        e = out[ch.entity_path]
        e["static"] |= ch.is_static
        e["timelines"] |= set(ch.timeline_names)
        b = ch.to_record_batch()
        frames = b.column("frame").to_pylist() if "frame" in b.schema.names else [None] * b.num_rows
        for name in b.schema.names:
            if name not in ("frame", "rerun.controls.RowId"):
                e["columns"][name] += list(zip(frames, b.column(name).to_pylist()))
    for e in out.values():
        for rows in e["columns"].values():
            rows.sort(key=lambda r: -1 if r[0] is None else r[0])
    return dict(out)


def test_the_recording_has_a_frame_timeline_with_every_frame(sequence_dir, capsys):
    rrd = sequence_dir / "track.rrd"
    rc = main(["solve-sequence", str(sequence_dir), "--method", "angle", "--variant", "improved", "--no-turns",
               "--json", "--record", str(rrd)])
    rows = [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]
    assert rc == 0 and len(rows) == 5
    # without turns: frame 1 loses lock (lost-in-space solves it), then the rate predicts
    assert [r["mode"] for r in rows] == ["lost_in_space", "lost_in_space", "tracking", "tracking", "tracking"]
    ent = read(rrd)
    for name in ("/sky/stars", "/sky/true_path", "/sky/path", "/result"):
        assert ent[name]["static"] and not ent[name]["timelines"]
    for name in PER_FRAME:
        e = ent[name]
        assert e["timelines"] == {"frame"}, name
        temporal = [rows for rows in e["columns"].values() if rows and rows[0][0] is not None]
        assert temporal and all([f for f, _ in rows] == [0, 1, 2, 3, 4] for rows in temporal), name  # one row a frame
    mode = [v[0] for _, v in ent["/plots/mode"]["columns"]["Scalars:scalars"]]
    assert mode == [0.0, 0.0, 1.0, 1.0, 1.0]
    n_matches = [v[0] for _, v in ent["/plots/matches"]["columns"]["Scalars:scalars"]]
    assert n_matches == [float(r["n_matches"]) for r in rows]
    err = [v[0] for _, v in ent["/plots/error_arcsec"]["columns"]["Scalars:scalars"]]
    assert np.allclose(err, [r["error_arcsec"]["total"] for r in rows]) and max(err) < 15.0
    rel = [v[0] for _, v in ent["/plots/relative_error_arcsec"]["columns"]["Scalars:scalars"]]
    assert len(rel) == 4 and max(rel) < 15.0
    logs = [v[0] for _, v in ent["/log"]["columns"]["TextLog:text"]]
    assert "lock lost" in logs[1] and logs[2] == "frame 2: tracking"
    labels = [v for _, v in ent["/camera/image/matches"]["columns"]["Points2D:labels"]]
    assert [len(x) for x in labels] == n_matches and labels[2][0].startswith("HIP ")
    table = ent["/result"]["columns"]["TextDocument:text"][0][1][0]
    assert "| 2 | tracking | solved |" in table


def test_bad_record_paths_are_one_line(sequence_dir, capsys):
    (sequence_dir / "exists.rrd").write_bytes(b"x")
    for path in ("exists.rrd", "track.txt", "missing/track.rrd"):
        rc = main(["solve-sequence", str(sequence_dir), "--method", "angle", "--record", str(sequence_dir / path)])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1, (path, err)


def test_the_recording_is_written_as_the_run_goes_and_a_killed_run_keeps_its_frames(sequence_dir, tmp_path):
    # issue 28, item 1: 60 frames (the sequence's five, again and again); the process killed outright once
    # 20 frames have answered: the .rrd holds them, frame by frame
    import os
    import signal
    import subprocess
    import sys
    import time

    frames = sorted(p for p in sequence_dir.glob("*.png"))
    paths = [str(frames[k % len(frames)]) for k in range(60)]
    rrd = tmp_path / "long.rrd"
    cmd = [sys.executable, "-c", "import sys; from skyview.cli import main; sys.exit(main(sys.argv[1:]))",
           "solve-sequence", *paths, "--fov-deg", "12", "--method", "angle", "--json", "--record", str(rrd)]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    seen, deadline = 0, time.monotonic() + 120
    while seen < 20 and time.monotonic() < deadline:
        if p.stdout.readline():
            seen += 1
    assert seen == 20
    time.sleep(0.2)  # (the recorder logs a frame before its line is printed)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=30)
    assert rrd.exists()
    # the kill may cut the last message short: Rerun's viewer and its `rerun rrd` tools read what came before it,
    # the Python reader refuses the whole file, so it reads the messages that are whole (`_whole_messages`)
    done = set()
    for ch in RrdReader(_whole_messages(rrd, tmp_path / "whole.rrd")).stream():
        if ch.entity_path == "/plots/mode":
            done |= set(ch.to_record_batch().column("frame").to_pylist())
    assert set(range(16)) <= done, sorted(done)  # flushed every 8 frames: at most the last 8 not yet on disk


def _whole_messages(rrd, out):
    """A copy of the recording `rrd` up to its last whole message: the RRD stream is a 12-byte header ("RRF2",
    version, options) and messages, each a little-endian (kind, length) u64 pair and `length` bytes."""
    import struct

    data = rrd.read_bytes()
    assert data[:4] == b"RRF2"
    pos = 12
    while pos + 16 <= len(data):
        _, length = struct.unpack_from("<QQ", data, pos)
        if pos + 16 + length > len(data):
            break
        pos += 16 + length
    out.write_bytes(data[:pos])
    return out
