"""Sky coverage (skyview.bench.coverage): a small sweep on a 2-worker Dask LocalCluster equals the single-process
answer; an interrupted sweep resumes; the outputs (map, sphere, table); bad input; the viewer's layer."""

import json
import math

import cv2
import numpy as np
import pytest

from skyview.bench.coverage import SOLVED, WRONG, CoverageConfig, load_results, orientations
from skyview.bench.coverage_map import mollweide_lonlat, sphere_mesh
from skyview.bench.coverage_sweep import run_coverage
from skyview.cli import main
from skyview.core.errors import BadInput

# 12 directions x 2 rolls of the angle method at 20 deg (a fast method; sub-second per task)
CFG = CoverageConfig("angle", "improved", fov_deg=20.0, mag_limit=5.0, nside=1, rolls=2, chunk=5)


@pytest.fixture(scope="module")
def inline(tmp_path_factory):
    out = tmp_path_factory.mktemp("cov-inline")
    return out, run_coverage(CFG, out, scheduler="inline", progress=False)


def test_orientations_cover_the_sphere_evenly():
    ori = orientations(CFG)
    assert ori.shape == (24, 3)
    # each direction twice, its two rolls 180 deg apart
    assert np.allclose(ori[0::2, :2], ori[1::2, :2])
    d = (ori[1::2, 2] - ori[0::2, 2]) % 360.0
    assert np.allclose(d, 180.0)
    v = np.stack([np.cos(np.radians(ori[:, 1])) * np.cos(np.radians(ori[:, 0])),
                  np.cos(np.radians(ori[:, 1])) * np.sin(np.radians(ori[:, 0])), np.sin(np.radians(ori[:, 1]))], 1)
    assert np.linalg.norm(v.mean(axis=0)) < 1e-9  # HEALPix centres balance out
    sun = orientations(CoverageConfig("ellipticity", grid="sun"))
    assert len(sun) == 128_877 and sun[:, 2].max() == 0.0


def test_the_single_process_sweep_is_right_against_the_truth(inline):
    out, s = inline
    res = load_results(out)
    assert np.array_equal(res["index"], np.arange(24))
    assert s["complete"] and s["orientations"] == 24
    assert s["counts"]["wrong"] == 0 and not np.any(res["outcome"] == WRONG)
    assert s["counts"]["solved"] >= 20  # 20 deg at Hp 5: every field holds enough stars
    assert s["enough_stars_pct"] == 100.0 and res["stars"].min() >= 4
    assert s["coverage_pct"] == pytest.approx(100.0 * np.mean(res["outcome"] == SOLVED))
    for f in ("json", "md", "png", "rrd"):
        assert (out / f"coverage.{f}").stat().st_size > 0


def test_a_local_cluster_of_two_workers_gives_the_single_process_answer(inline, tmp_path):
    # thread workers (processes=False): the same engine and tasks, without the processes' start-up in CI
    s = run_coverage(CFG, tmp_path, scheduler=None, n_workers=2, processes=False, progress=False)
    a, b = load_results(inline[0]), load_results(tmp_path)
    for k in ("index", "ra_deg", "dec_deg", "roll_deg", "stars", "outcome"):
        assert np.array_equal(a[k], b[k]), k
    assert s["counts"] == inline[1]["counts"]


def test_an_interrupted_sweep_resumes_where_it_stopped(inline, tmp_path):
    part = run_coverage(CFG, tmp_path, scheduler="inline", progress=False, max_tasks=2)
    assert part == {"complete": False, "tasks_done": 2, "tasks": 5}
    first = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "chunks").glob("*.npz")}
    s = run_coverage(CFG, tmp_path, scheduler="inline", progress=False)
    assert s["run"]["tasks_run"] == 3  # only the missing tasks ran
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "chunks").glob("*.npz") if p.name in first} == first
    assert np.array_equal(load_results(tmp_path)["outcome"], load_results(inline[0])["outcome"])


def test_another_configuration_in_the_same_folder_is_refused(inline, capsys):
    rc = main(["coverage", "--method", "angle", "--variant", "improved", "--fov-deg", "8", "--mag-limit", "5",
               "--nside", "1", "--out", str(inline[0]), "--quiet"])
    assert rc == 2
    assert "another configuration" in capsys.readouterr().err


@pytest.mark.parametrize("args, msg", [
    (["--method", "nope", "--fov-deg", "8", "--mag-limit", "6"], "invalid choice"),
    (["--method", "angle", "--fov-deg", "0", "--mag-limit", "6"], "--fov-deg"),
    (["--method", "angle", "--fov-deg", "8", "--mag-limit", "6", "--nside", "3"], "power of 2"),
    (["--method", "angle", "--fov-deg", "8", "--mag-limit", "6", "--rolls", "0"], "--rolls"),
])
def test_bad_input_is_one_line_and_exit_2(args, msg, capsys, tmp_path):
    rc = main(["coverage", *args, "--out", str(tmp_path / "x")])
    assert rc == 2
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_the_cli_writes_the_summary_as_json(tmp_path, capsys):
    rc = main(["coverage", "--method", "angle", "--variant", "improved", "--fov-deg", "20", "--mag-limit", "5",
               "--nside", "1", "--rolls", "1", "--scheduler", "inline", "--out", str(tmp_path), "--json", "--quiet"])
    assert rc == 0
    s = json.loads(capsys.readouterr().out)
    assert s["orientations"] == 12 and s["counts"]["wrong"] == 0
    assert s["run"]["orientations_per_s_per_core"] > 0


def test_the_mollweide_map_is_equal_area_and_oriented():
    ra, dec, inside = mollweide_lonlat(400, 200)
    assert inside.mean() == pytest.approx(math.pi / 4, abs=0.01)  # an ellipse fills pi/4 of its box
    # equal area: the share of the ellipse north of Dec 30 deg is the sphere's, (1 - sin 30) / 2
    assert np.mean(dec[inside] > 30.0) == pytest.approx(0.25, abs=0.01)
    assert abs(ra[100, 200] % 360.0) < 1.0 or abs(ra[100, 200] - 360.0) < 1.0  # RA 0 at the centre
    assert 40 < ra[100, 150] < 50  # a quarter of the half-width left of the centre: RA 45 (east left)


def test_the_map_png_shows_the_solved_share(inline):
    img = cv2.imread(str(inline[0] / "coverage.png"))
    assert img.shape[1] == 900 and img.shape[0] > 450


def test_the_sphere_mesh_covers_the_sphere():
    v, t, rgb = sphere_mesh(2, np.linspace(0, 1, 48))
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-6)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    assert area == pytest.approx(4 * math.pi, rel=0.03)  # flat triangles: a little under the sphere's area
    assert rgb.shape == v.shape and rgb.dtype == np.uint8


def test_the_recording_holds_the_sphere_and_the_table(inline):
    import rerun as rr

    summary = str(rr.chunk.RrdReader(str(inline[0] / "coverage.rrd")).stream().collect().summary()) \
        if hasattr(rr, "chunk") else ""
    assert "sky/coverage" in summary and "summary" in summary


def test_the_viewer_layer_adds_and_removes_the_coloured_sphere(inline):
    import viser

    from skyview.viewer.coverage_layer import CoverageLayer

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        layer = CoverageLayer.from_folder(inline[0])
        layer.show(server.scene, fov_deg=20.0)
        assert layer.visible and len(layer.handles) >= 2
        assert "20 deg" in layer.caption and "angle" in layer.caption
        layer.hide()
        assert not layer.visible and layer.handles == []
    finally:
        server.stop()


def test_a_sample_of_suns_grid_is_a_seeded_subset_in_grid_order():
    full = orientations(CoverageConfig("ellipticity", grid="sun"))
    cfg = CoverageConfig("ellipticity", grid="sun", sample=500).checked()
    a, b = orientations(cfg), orientations(CoverageConfig("ellipticity", grid="sun", sample=500))
    assert a.shape == (500, 3) and np.array_equal(a, b)
    key = lambda o: set(map(tuple, np.round(o, 6)))  # noqa: E731
    assert key(a) <= key(full)
    order = np.lexsort((a[:, 0], a[:, 1]))  # the grid's order: Dec rows, RA within a row
    assert np.array_equal(order, np.arange(500))
    other = orientations(CoverageConfig("ellipticity", grid="sun", sample=500, seed=1))
    assert not np.array_equal(a, other)
    assert "a random 500 of them" in cfg.describe()


@pytest.mark.slow
def test_the_stochastic_method_is_swept_with_its_own_sequences(tmp_path):
    """A single frame never solves for the stochastic method; each orientation is a 5-frame sequence
    (FOV/3 per frame about the camera y axis, the turn given), identified together against the truth."""
    cfg = CoverageConfig("stochastic", "improved", fov_deg=8.0, mag_limit=6.0, nside=1, rolls=1, sample=6, chunk=3)
    assert cfg.checked().frames == 5 and CoverageConfig("angle", frames=None).checked().frames == 1
    s = run_coverage(cfg, tmp_path, scheduler="inline", progress=False)
    res = load_results(tmp_path)
    assert s["orientations"] == 6 and s["counts"]["wrong"] == 0
    assert s["counts"]["solved"] >= 2 and np.all(res["stars"][res["outcome"] == SOLVED] >= 4)
    assert json.loads((tmp_path / "config.json").read_text())["frames"] == 5
    with pytest.raises(BadInput, match="single frames"):
        CoverageConfig("angle", frames=3).checked()


@pytest.mark.slow
def test_a_sweep_killed_with_sigkill_resumes_to_the_table_of_an_uninterrupted_run(tmp_path):
    # issue 28, item 5: the process killed outright (no handler runs) mid-sweep, then the same command again
    import os
    import signal
    import subprocess
    import sys
    import time

    args = ["coverage", "--method", "angle", "--variant", "improved", "--fov-deg", "20", "--mag-limit", "5",
            "--nside", "2", "--rolls", "2", "--chunk", "4", "--scheduler", "inline", "--quiet", "--json"]
    killed, whole = tmp_path / "killed", tmp_path / "whole"
    cmd = [sys.executable, "-c", "import sys; from skyview.cli import main; sys.exit(main(sys.argv[1:]))"]
    p = subprocess.Popen(cmd + args + ["--out", str(killed)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while len(list((killed / "chunks").glob("task-*.npz"))) < 3 and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert p.poll() is None, "the sweep ended before it could be killed"
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=30)
    n_before = len([q for q in (killed / "chunks").glob("task-*.npz") if not q.stem.endswith(".tmp")])
    assert 3 <= n_before < 24  # 96 orientations in 24 tasks: stopped part way
    again = subprocess.run(cmd + args + ["--out", str(killed)], capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-400:]
    resumed = json.loads(again.stdout)
    assert resumed["run"]["tasks_run"] == 24 - n_before  # only what the killed run had not saved
    ref = subprocess.run(cmd + args + ["--out", str(whole)], capture_output=True, text=True, timeout=600)
    assert ref.returncode == 0, ref.stderr[-400:]
    uninterrupted = json.loads(ref.stdout)
    a, b = load_results(killed), load_results(whole)
    assert set(a) == set(b)
    for k in set(a) - {"time_ms", "worker_s"}:  # every record but its timings
        assert np.array_equal(a[k], b[k]), k
    for k in ("counts", "coverage_pct", "orientations", "enough_stars_pct"):
        assert resumed[k] == uninterrupted[k], k


@pytest.mark.slow
def test_a_dask_worker_lost_mid_sweep_is_replaced_and_the_sweep_gives_the_same_table(tmp_path):
    # issue 28, item 5: a worker process killed outright while it holds tasks; Dask's nanny starts another and
    # the scheduler gives the lost tasks again: the sweep completes with every record of the single-process one
    import os
    import signal
    import threading
    import time

    from dask.distributed import LocalCluster

    cfg = CoverageConfig("angle", "improved", fov_deg=20.0, mag_limit=5.0, nside=2, rolls=2, chunk=4)  # 24 tasks
    ref = run_coverage(cfg, tmp_path / "ref", scheduler="inline", progress=False)
    out = tmp_path / "lost"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        pids = [w.process.pid for w in cluster.workers.values()]
        killed = []

        def kill_one():
            deadline = time.monotonic() + 120
            while len(list((out / "chunks").glob("task-*.npz"))) < 3 and time.monotonic() < deadline:
                time.sleep(0.02)
            os.kill(pids[0], signal.SIGKILL)
            killed.append(pids[0])

        t = threading.Thread(target=kill_one)
        t.start()
        s = run_coverage(cfg, out, scheduler=cluster.scheduler_address, progress=False)
        t.join(30)
    assert killed and s["complete"] and len(list((out / "chunks").glob("task-*.npz"))) == 24
    a, b = load_results(tmp_path / "ref"), load_results(out)
    for k in ("index", "ra_deg", "dec_deg", "roll_deg", "stars", "outcome"):
        assert np.array_equal(a[k], b[k]), k
    assert s["counts"] == ref["counts"]


def test_a_task_in_batches_of_frames_gives_the_answer_of_one_batch(monkeypatch):
    from skyview.bench import coverage

    cfg = CoverageConfig("ellipticity", "improved", fov_deg=20.0, mag_limit=6.0, grid="sun", sample=40,
                         noise_urad=10, max_stars=1000, chunk=40).checked()
    whole = coverage.run_task(cfg.to_dict(), 0)
    monkeypatch.setattr(coverage, "BATCH_FRAMES", 7)  # six batches of 7 frames, one of 5
    parts = coverage.run_task(cfg.to_dict(), 0)
    for k in ("index", "stars", "outcome"):
        assert np.array_equal(whole[k], parts[k]), k
    assert np.all(whole["outcome"] == SOLVED) and whole["stars"].min() >= 4  # Sun's grid: every one solved


def test_an_out_that_is_a_file_is_refused_in_one_line_and_the_file_is_kept(tmp_path, capsys):
    f = tmp_path / "results.txt"
    f.write_text("the user's notes")
    rc = main(["coverage", "--method", "angle", "--fov-deg", "8", "--mag-limit", "6", "--nside", "1", "--rolls", "1",
               "--out", str(f)])
    err = capsys.readouterr().err
    assert rc == 2 and "--out" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert f.read_text() == "the user's notes"
