"""`skyview bench --speed` (skyview.bench.speed): what it scores and reports; the times themselves are
benchmark figures, not tested."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from skyview.bench.speed import (
    PEER_ONE_THREAD,
    STAGES,
    _peer_trials,
    _ratios,
    _summarize,
    boresight_error_px,
    format_markdown,
    run_speed_bench,
)
from skyview.cli import main
from skyview.core.attitude import R_from_radec_roll
from skyview.core.errors import BadInput
from skyview.detect.centroids import load_image
from skyview.simulate.scenarios import get_scenario


def test_speed_bench_scores_and_times_every_stage(tmp_path):
    s = run_speed_bench(get_scenario("cole8"), 3, seed=0, blind=False, peers=False, work_dir=tmp_path,
                        rounds=2, progress=False)
    r = s["results"]["angle (improved)"]
    assert r["n"] == 3 and sum(r["outcomes"].values()) == 3
    assert r["outcomes"]["incorrect"] == 0 and r["outcomes"]["correct"] >= 1  # seed 0: trials 0 and 2 solve
    assert set(STAGES) <= set(r["stages_ms"])
    st = r["stages_ms"]
    assert st["total"]["median"] >= st["centroid"]["median"] > 0
    assert st["total+decode"]["median"] > st["total"]["median"]
    assert "tetra3rs" not in s["results"] and s["ratio_to_tetra3rs"] == {}
    assert s["ratio_to_tetra3rs_one_thread"] == {}
    assert r["cpu_ms"]["n"] == 3 and r["cpu_ms"]["median"] > 0 and r["cores"]["median"] > 0  # CPU over wall
    pngs = sorted(tmp_path.glob("trial*.png"))
    assert len(pngs) == 3  # the images the peers would read
    assert s["bit_depth"] == 16 and load_image(pngs[0]).dtype == np.uint16  # the frames tetra3rs is made for
    md = format_markdown(s)
    assert "| angle (improved) |" in md and "load average" in md and "3 16-bit images" in md
    t = s["results"]["triangle (improved)"]  # the default pair of issue 11: angle and triangle, improved
    assert t["n"] == 3 and t["outcomes"]["incorrect"] == 0 and t["outcomes"]["correct"] >= 1
    d = s["results"]["default, FOV given"]  # what `skyview solve IMG --fov-deg F` runs, timed beside them
    assert d["n"] == 3 and d["outcomes"]["incorrect"] == 0 and d["outcomes"]["correct"] >= 1
    assert "| default, FOV given |" in md


def test_speed_bench_renders_8_bit_frames_when_asked(tmp_path):
    s = run_speed_bench(get_scenario("cole8"), 1, seed=0, blind=False, peers=False, work_dir=tmp_path,
                        rounds=1, progress=False, methods=(("angle", "improved"),), bit_depth=8, default_path=False)
    assert s["bit_depth"] == 8 and load_image(next(tmp_path.glob("trial*.png"))).dtype == np.uint8
    assert "1 8-bit images" in format_markdown(s)
    with pytest.raises(BadInput, match="bit depth 12"):
        run_speed_bench(get_scenario("cole8"), 1, peers=False, work_dir=tmp_path, bit_depth=12)


def test_tetra3rs_answers_are_scored_by_the_boresight():
    ra, dec, roll = math.radians(83.0), math.radians(-5.0), math.radians(30.0)
    R = R_from_radec_roll(ra, dec, roll)
    scale = math.radians(8.0) / 1024
    off = R_from_radec_roll(ra, dec + 10 * scale, roll)  # the boresight 10 px north
    images = [{"name": f"t{k}", "R": R} for k in range(3)]
    answer = {"results": {"tetra3rs-fov": [
        {"name": "t0", "solved": True, "R": R.tolist(), "time_ms": 2.0},
        {"name": "t1", "solved": True, "R": off.tolist(), "time_ms": 4.0},
        {"name": "t2", "solved": False, "time_ms": 3.0}]}}
    assert boresight_error_px(off, R, scale) == pytest.approx(10.0, rel=1e-3)
    trials = _peer_trials(answer, images, scale, max_error_px=5.0)["trials"]
    assert [t["outcome"] for t in trials] == ["correct", "incorrect", "inconclusive"]
    assert np.median([t["total"] for t in trials]) == 3.0


def _entry(label, totals, cpus, walls=None):
    trials = [{"name": f"t{k}", "outcome": "correct", "total": t, "cpu": c, **({"wall": walls[k]} if walls else {})}
              for k, (t, c) in enumerate(zip(totals, cpus))]
    return _summarize({"label": label, "trials": trials})


def test_speed_summary_reports_the_cores_each_solver_kept_busy_and_both_peer_ratios():
    # tetra3rs's extractor runs on a thread pool: CPU time above the wall time; its one-thread run is the
    # comparison on one core, skyview's way
    results = {"default, FOV given": _entry("skyview", [3.0, 3.0, 3.0], [3.1, 3.0, 3.2], [3.1, 3.0, 3.2]),
               "tetra3rs": _entry("tetra3rs", [2.0, 2.5, 2.4], [3.6, 4.5, 4.3]),
               PEER_ONE_THREAD: _entry("tetra3rs, 1 thread", [4.0, 4.0, 4.1], [4.0, 4.0, 4.1])}
    assert results["tetra3rs"]["cores"]["median"] == pytest.approx(1.8)
    assert results["default, FOV given"]["cores"]["median"] == pytest.approx(1.0)
    assert _ratios(results, "tetra3rs") == {"default, FOV given": pytest.approx(3.0 / 2.4)}
    assert _ratios(results, PEER_ONE_THREAD) == {"default, FOV given": pytest.approx(0.75)}
    assert _ratios(results, "cedar") == {}  # no such peer in the run
    s = {"scenario": get_scenario("sun20").to_dict(), "n": 3, "seed": 0, "rounds": 1, "bit_depth": 16,
         "results": results, "ratio_to_tetra3rs": _ratios(results, "tetra3rs"),
         "ratio_to_tetra3rs_one_thread": _ratios(results, PEER_ONE_THREAD), "peer_note": None,
         "machine": {"python": "3.11", "cpu": "x86_64", "cores": 2, "load_average": [1.0, 1.0, 1.0]}}
    md = format_markdown(s)
    assert "| tetra3rs | 3 | 0 | 0 |" in md and md.count(" | 1.8 |") == 1  # its cores column
    assert "default, FOV given 1.25x" in md and f"Over {PEER_ONE_THREAD}'s (both on one core): default, FOV given 0.75x" in md


def test_peer_trials_keep_the_cpu_time_and_say_how_many_threads():
    images = [{"name": "t0", "R": np.eye(3)}]
    answer = {"results": {"tetra3rs-fov": [{"name": "t0", "solved": True, "R": np.eye(3).tolist(), "time_ms": 2.0,
                                            "cpu_ms": 3.5}]}}
    one = _peer_trials(answer, images, 1e-4, max_error_px=5.0, threads=1)
    assert one["trials"][0]["cpu"] == 3.5 and "1 thread)" in one["label"]
    assert "every core" in _peer_trials(answer, images, 1e-4, max_error_px=5.0)["label"]


def test_cli_speed_bench(tmp_path, capsys):
    assert main(["bench", "--speed", "--no-peers", "-n", "1", "--rounds", "1", "--quiet", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| angle (improved) |" in out and "| blind |" in out
    saved = json.loads(next(tmp_path.glob("speed-cole8-n1-seed0*.json")).read_text())
    assert saved["kind"] == "speed" and saved["results"]["blind"]["n"] == 1


def test_a_peers_python_that_does_not_exist_is_an_error_not_another_one(tmp_path, capsys):
    """--peers-python names the peers' interpreter: a path that is not there is a one-line error and exit 2,
    before any image is rendered, never the default virtualenv used in its place."""
    from skyview.bench.speed import peers_python

    with pytest.raises(BadInput, match="does not exist"):
        peers_python(str(tmp_path / "nowhere" / "python"))
    out = tmp_path / "out"
    assert main(["bench", "--speed", "--peers-python", str(tmp_path / "nowhere"), "-n", "1", "--quiet",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_cli_speed_bench_refuses_other_modes(capsys):
    assert main(["bench", "--speed", "--blind", "-n", "1"]) == 2
    err = capsys.readouterr().err
    assert "--speed" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert main(["bench", "--bit-depth", "8", "-n", "1"]) == 2  # the other benches render as their scenario says
    err = capsys.readouterr().err
    assert "--bit-depth goes with --speed" in err and len(err.strip().splitlines()) == 1
    assert main(["bench", "--speed", "--bit-depth", "12", "-n", "1"]) == 2  # argparse's choices
    assert "Traceback" not in capsys.readouterr().err


def _two_photographs(tmp_path):
    """Two of the real photographs and their reference attitudes, in a folder as `--real` reads it."""
    import shutil

    src = Path(__file__).parent / "data" / "real-images"
    ref = json.loads((src / "reference.json").read_text())
    names = sorted(ref)[:2]
    folder = tmp_path / "photos"
    folder.mkdir()
    for n in names:
        shutil.copy(src / n, folder / n)
    (folder / "reference.json").write_text(json.dumps({n: ref[n] for n in names}))
    return folder, names


def test_photo_speed_scores_blind_solves_and_times_whole_processes(tmp_path):
    from skyview.bench.photo_speed import format_photo_markdown, run_photo_speed

    folder, names = _two_photographs(tmp_path)
    s = run_photo_speed(folder, rounds=1, process_rounds=1, peers=False, progress=False)
    sk = s["results"]["skyview"]
    assert sk["outcomes"] == {"correct": 2, "inconclusive": 0, "incorrect": 0}
    assert [t["name"] for t in sk["trials"]] == names
    assert all(t["err_arcsec"] < 120 and t["total"] > 0 for t in sk["trials"])
    assert all(t["cpu"] > 0 and t["wall"] >= t["total"] for t in sk["trials"]) and sk["cores"]["median"] > 0
    procs = s["processes"]["skyview solve PHOTO --json (wall s)"]
    assert 0 < procs["min"] <= procs["median"] <= procs["max"]
    assert "tetra3rs" not in s["results"] and s["ratio_to_tetra3rs"] is None  # peers=False: skyview alone
    assert s["ratio_to_tetra3rs_one_thread"] is None
    md = format_photo_markdown(s)
    assert "| skyview blind" in md and "skyview solve PHOTO --json" in md


def test_cli_photo_speed_refuses_a_folder_without_reference(tmp_path, capsys):
    (tmp_path / "x.png").write_bytes(b"")
    assert main(["bench", "--speed", "--real", str(tmp_path), "--no-peers", "--quiet", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "reference.json" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert main(["bench", "--speed", "--real", str(tmp_path / "none"), "--quiet"]) == 2
    assert "no such folder" in capsys.readouterr().err
    for bad in ('[1, 2]', '{"x.png": {"fov_deg": 11}}', '{"x.png": {"R": [1, 2], "fov_deg": 1, "width": 2, "height": 2}}'):
        (tmp_path / "reference.json").write_text(bad)
        assert main(["bench", "--speed", "--real", str(tmp_path), "--no-peers", "--quiet", "--out",
                     str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert "reference.json" in err and "internal error" not in err and len(err.strip().splitlines()) == 1
