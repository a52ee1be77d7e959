"""Faults and fuzz: every kind of file skyview reads, damaged; odd arrays; killed and interrupted benches.

Each case asserts the exit code, one line on stderr (one JSON object on stdout with --json), and
that nothing on disk was lost or overwritten.
"""

import json
import os
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from skyview.cli import main

REAL = Path(__file__).parent / "data" / "real-images"


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line(err: str) -> bool:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    return len(lines) == 1 and lines[0].startswith("skyview:") and "Traceback" not in err


@pytest.fixture(scope="module")
def sky(tmp_path_factory):
    """A simulated field and its truth sidecar."""
    d = tmp_path_factory.mktemp("sky")
    png = d / "sky.png"
    assert main(["simulate", "--ra", "83.8", "--dec", "-5.4", "--roll", "30", "--fov-deg", "12", "--mag-limit",
                 "7", "--seed", "2", "--out", str(png)]) == 0
    return png


def _png_bomb(w: int, h: int) -> bytes:
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)

    comp = zlib.compressobj(9)
    row = b"\x00" * (w + 1)
    data = b"".join(comp.compress(row) for _ in range(h)) + comp.flush()
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", data) + chunk(b"IEND", b""))


# ------------------------------------------------------------------------------------------ images

@pytest.mark.slow
def test_damaged_images_are_one_line_errors_with_json(capsys, tmp_path, sky):
    rng = np.random.default_rng(0)
    good_png = sky.read_bytes()
    ok, jpg = cv2.imencode(".jpg", cv2.imread(str(sky), cv2.IMREAD_UNCHANGED).astype(np.uint8))
    tiff = cv2.imencode(".tiff", np.zeros((40, 40), np.uint16))[1].tobytes()
    cases = {
        "truncated.png": good_png[:200],
        "random.png": rng.integers(0, 256, 5000, dtype=np.uint8).tobytes(),
        "truncated.jpg": jpg.tobytes()[:100],
        "truncated.tiff": tiff[:60],
        "empty.png": b"",
        "bomb.png": _png_bomb(20000, 20000),  # 400 MP announced in a ~400 kB file
    }
    for name, data in cases.items():
        f = tmp_path / name
        f.write_bytes(data)
        code, out, err = run(capsys, "solve", f, "--json")
        assert code == 2 and one_line(err), (name, err)
        obj = json.loads(out)
        assert obj["status"] == "error" and obj["exit_code"] == 2
        assert obj["error"] and not obj["error"].startswith("error") and obj["error"] in err  # the same sentence
        assert f.read_bytes() == data  # never touched
        if name.startswith("truncated.") and name != "truncated.tiff":  # said so, with what is missing
            assert "truncated" in obj["error"], obj["error"]


def test_a_link_to_nothing_says_so(capsys, tmp_path):
    """A symbolic link whose target is missing, or two that point at each other: one line that says it is a link
    leading to no file (not that the path does not exist: `ls` shows it), exit 2."""
    (tmp_path / "gone.png").symlink_to(tmp_path / "deleted.png")
    (tmp_path / "a.png").symlink_to(tmp_path / "b.png")
    (tmp_path / "b.png").symlink_to(tmp_path / "a.png")
    for name in ("gone.png", "a.png"):
        code, out, err = run(capsys, "solve", tmp_path / name)
        assert code == 2 and one_line(err) and "symbolic link that leads to no file" in err, err
    code, out, err = run(capsys, "solve", tmp_path / "nothing.png")
    assert code == 2 and "does not exist" in err


def test_a_camera_raw_file_says_what_to_do(capsys, tmp_path):
    """A camera's raw file (OpenCV reads none): one line naming the format and what to export instead."""
    f = tmp_path / "IMG_0001.CR2"
    data = b"II*\x00\x10\x00\x00\x00CR\x02\x00" + bytes(range(256)) * 40
    f.write_bytes(data)
    code, out, err = run(capsys, "solve", f, "--json")
    assert code == 2 and one_line(err)
    msg = json.loads(out)["error"]
    assert "camera raw file (.CR2)" in msg and "TIFF" in msg and f.read_bytes() == data


def test_float_tiff_with_nan_and_inf(capsys, tmp_path):
    a = np.random.default_rng(1).normal(100, 5, (64, 64)).astype(np.float32)
    a[5, 5], a[10, 10] = np.nan, np.inf
    some = tmp_path / "some.tiff"
    cv2.imwrite(str(some), a)
    code, out, err = run(capsys, "solve", some)
    assert code == 1 and "no stars" in err  # a noise frame: read, searched, not solved
    allnan = tmp_path / "allnan.tiff"
    cv2.imwrite(str(allnan), np.full((64, 64), np.nan, np.float32))
    code, out, err = run(capsys, "solve", allnan)
    assert code == 2 and one_line(err) and "finite" in err


def test_odd_arrays_to_the_api():
    import skyview
    from skyview.core.errors import BadInput

    img = cv2.imread(str(REAL / sorted(os.listdir(REAL))[0]), cv2.IMREAD_UNCHANGED)
    assert skyview.solve_image(np.asfortranarray(img)).solved
    assert skyview.solve_image(np.ascontiguousarray(img.T).T).solved  # a transposed view
    assert skyview.solve_image(img.astype(np.float64)).solved
    for bad in (img.tolist(), None, b"\x89PNG", (1, 2), np.zeros((5, 5)), np.zeros((20, 20, 7))):
        with pytest.raises(BadInput):
            skyview.solve_image(bad)


# ------------------------------------------------------------------------------------------ sidecars

def test_a_json_beside_the_image_that_is_not_a_sidecar_is_left_alone(capsys, tmp_path, sky):
    img = tmp_path / "photo.png"
    img.write_bytes(sky.read_bytes())
    for content in ('{"exposure": 30, "iso": 1600}', "{not json", '{"R": "x"}', "[]"):
        (tmp_path / "photo.json").write_text(content)
        code, out, err = run(capsys, "solve", img, "--json")
        assert code == 0, err
        assert "truth" not in json.loads(out)
        assert (tmp_path / "photo.json").read_text() == content
    code, out, err = run(capsys, "solve", img, "--truth", tmp_path / "photo.json")
    assert code == 2 and one_line(err)  # asked for explicitly: an error


def test_a_sequence_may_not_name_files_outside_its_folder(capsys, tmp_path, sky):
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "a.png").write_bytes(sky.read_bytes())
    eye = np.eye(3).tolist()
    for names in (["a.png", "../outside.png"], ["a.png", "/etc/passwd"]):
        (seq / "sequence.json").write_text(json.dumps({"images": names, "relative": [{"dR_cam": eye}],
                                                       "camera": {}}))
        code, out, err = run(capsys, "solve-sequence", seq, "--fov-deg", "12")
        assert code == 2 and one_line(err) and "not a file in the sequence's folder" in err


# ------------------------------------------------------------------------------------------ outputs

def test_outputs_are_checked_before_the_work_and_never_overwritten(capsys, tmp_path, sky):
    keep = tmp_path / "keep.json"
    keep.write_text("user data")
    for args in (["--output", keep], ["--wcs", keep], ["--output", tmp_path / "no" / "x.json"]):
        code, out, err = run(capsys, "solve", sky, *args)
        assert code == 2 and one_line(err)
    assert keep.read_text() == "user data"
    cat = tmp_path / "cat.npz"
    cat.write_bytes(b"precious")
    code, out, err = run(capsys, "catalog", "build", "--out", cat)
    assert code == 2 and one_line(err) and cat.read_bytes() == b"precious"
    t0 = time.perf_counter()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, out, err = run(capsys, "bench", "-n", "50", "--out", blocker / "sub")
    assert code == 2 and one_line(err) and time.perf_counter() - t0 < 10  # refused before the Monte Carlo


@pytest.mark.parametrize("argv", [["simulate", "--ra", "1", "--dec", "1", "--seed", "-1"],
                                  ["simulate", "--ra", "1", "--dec", "1", "--width", "100000"],
                                  ["simulate", "--ra", "1", "--dec", "1", "--frames", "0"],
                                  ["solve", "{sky}", "--method", "angle", "--fov-deg", "12", "--param", "sigma_rad=1"],
                                  ["solve", "{sky}", "--method", "angle", "--fov-deg", "12", "--param", "variant=x"],
                                  ["solve", "{sky}", "--method", "astrology"],
                                  ["solve", "{sky}", "--fov-error", "1.5"]])
def test_bad_options_are_exit_2(capsys, tmp_path, sky, argv):
    argv = [str(sky) if a == "{sky}" else a for a in argv]
    if argv[0] == "simulate":
        argv += ["--out", str(tmp_path / "x.png")]
    code, out, err = run(capsys, *argv, "--json")
    assert code == 2 and one_line(err)
    assert json.loads(out)["status"] == "error"
    assert not (tmp_path / "x.png").exists()


def test_broken_pipe_is_not_an_error(sky):
    p = subprocess.run(f"{sys.executable} -m skyview solve {sky} --json | head -c 10 > /dev/null",
                       shell=True, capture_output=True, text=True, timeout=120)
    assert "Traceback" not in p.stderr and "internal error" not in p.stderr


# ------------------------------------------------------------------------------------------ recordings

def test_ctrl_c_during_a_solve_is_one_line_and_with_json_one_object(capsys, monkeypatch, sky):
    """Ctrl-C in the middle of a solve: "skyview: interrupted" on stderr, exit 130, no traceback; with --json a
    script reading stdout still gets its one JSON object, which says so."""
    import skyview.solver.pipeline as pipeline

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "solve_image", interrupted)
    for extra in ([], ["--json"]):
        assert main(["solve", str(sky), *extra]) == 130
        out, err = capsys.readouterr()
        assert err.strip() == "skyview: interrupted" and "Traceback" not in err
        if extra:
            assert json.loads(out) == {"status": "interrupted", "exit_code": 130}
        else:
            assert out == ""


def test_damaged_recordings_are_refused(capsys, tmp_path):
    src = Path(__file__).parent.parent / "recordings" / "angle-cole8.rrd"
    data = src.read_bytes()
    for name, content in (("half.rrd", data[: len(data) // 2]), ("junk.rrd", b"RRF2" + b"\x00" * 100),
                          ("text.rrd", b"hello")):
        f = tmp_path / name
        f.write_bytes(content)
        code, out, err = run(capsys, "replay", f, "--web", "--port", "0")
        assert code == 2 and one_line(err), (name, err)
        assert f.read_bytes() == content


# ------------------------------------------------------------------------------------------ cache

@pytest.mark.slow
def test_a_truncated_cached_database_heals_itself(capsys, tmp_path, monkeypatch, sky):
    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    args = ["solve", sky, "--method", "angle", "--variant", "improved", "--fov-deg", "12", "--fov-error", "0", "--json"]
    code, out, err = run(capsys, *args)
    assert code == 0, err
    dbs = list((tmp_path / "databases").glob("angle-*.npz"))
    assert len(dbs) == 1
    dbs[0].write_bytes(dbs[0].read_bytes()[:1000])
    import skyview.solver.pipeline

    messages = ""
    for _ in range(2):  # healed once, then fine (each run as a new process would: no solver kept)
        skyview.solver.pipeline._SOLVERS.clear()
        code, out, err = run(capsys, *args)
        assert code == 0 and json.loads(out)["status"] == "solved"
        messages += err
    assert messages.count("damaged") == 1 and dbs[0].stat().st_size > 1000


def test_a_cache_that_cannot_be_written_still_solves_and_says_so_once(capsys, tmp_path, monkeypatch, sky):
    """SKYVIEW_CACHE naming a file (or any folder that cannot be made): the databases are built in memory, the
    solve answers, and stderr holds one line saying why (not a Python warning per database)."""
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the cache should be")
    monkeypatch.setenv("SKYVIEW_CACHE", str(blocker))
    import skyview.identify.database
    import skyview.solver.pipeline

    skyview.solver.pipeline._SOLVERS.clear()
    monkeypatch.setattr(skyview.identify.database, "_UNWRITABLE", set())
    args = ["solve", sky, "--method", "angle", "--variant", "improved", "--fov-deg", "12", "--fov-error", "0", "--json"]
    code, out, err = run(capsys, *args)
    skyview.solver.pipeline._SOLVERS.clear()
    assert code == 0 and json.loads(out)["status"] == "solved"
    said = [ln for ln in err.splitlines() if "could not write the cache" in ln]
    assert len(said) == 1 and said[0].startswith("skyview:") and "SKYVIEW_CACHE" in said[0]
    assert "Warning" not in err and "Traceback" not in err
    assert blocker.read_text() == "a file where the cache should be"


# ------------------------------------------------------------------------------------------ benches

def _mark(path: str) -> str:
    """The context of the trials below: the path of a file that says whether a worker died already."""
    return path


def _dies_once(ctx, k):
    """A trial function whose worker is killed the first time it reaches trial 7, and always at 13."""
    if k == 13 or (k == 7 and not os.path.exists(ctx)):
        if k == 7:
            Path(ctx).write_text("died once")
        os.kill(os.getpid(), signal.SIGKILL)
    return ({"trial": k, "outcome": "correct"}, None, None)


def test_a_killed_worker_loses_no_trial(tmp_path):
    """The benches' workers (`--jobs 2`: a LocalCluster of two processes) killed in the middle of a task:
    the task is run again on a new worker, and a task that kills its worker twice has its trials reported
    as lost, not dropped; every other trial is kept."""
    from skyview.bench.dask_engine import trials_on_dask

    trials = trials_on_dask(_mark, (str(tmp_path / "mark"),), _dies_once, 20, n_workers=2, chunk=5)
    assert [t["trial"] for t in trials] == list(range(20))
    lost = [t for t in trials if t["outcome"] == "error"]
    # trial 13's task (10-14) died twice: reported, not dropped; trial 7's was run again and finished
    assert {t["trial"] for t in lost} == set(range(10, 15)) and all("died" in t["reason"] for t in lost)
    assert trials[7]["outcome"] == "correct"


def _running(pid: int) -> bool:
    """Whether the process is alive (not gone, not a zombie waiting to be reaped)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _descendants(pid: int) -> set[int]:
    """The processes started by `pid`, and theirs (from /proc)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            if c not in out:
                out.add(c)
                todo.append(c)
    return out


@pytest.mark.slow
def test_ctrl_c_stops_a_bench_at_once_and_saves_what_finished(tmp_path):
    out = tmp_path / "res"
    p = subprocess.Popen([sys.executable, "-m", "skyview", "bench", "-n", "2000", "--jobs", "2", "--quiet",
                          "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))  # as a background job
    time.sleep(12)
    workers = _descendants(p.pid)
    assert len(workers) >= 2  # the LocalCluster's two worker processes (and their nannies)
    t0 = time.perf_counter()
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=30)
    assert p.returncode == 130, stderr
    assert time.perf_counter() - t0 < 5.0
    saved = json.loads(next(out.glob("*.json")).read_text())
    assert saved["interrupted"] and 0 < saved["trials_finished"] < 2000
    time.sleep(0.5)
    assert not [w for w in workers if _running(w)]  # no orphaned workers


def test_a_frame_of_hot_pixels_alone_says_so(capsys, tmp_path):
    """A dark frame whose only bright points are single pixels: not solved (exit 1), in one line that says they
    were taken for hot pixels, not only that the sky is blank."""
    import cv2

    from skyview.cli import main

    img = np.full((600, 800), 10, np.uint8)
    rng = np.random.default_rng(0)
    img[rng.integers(0, 600, 300), rng.integers(0, 800, 300)] = 255
    path = tmp_path / "hot.png"
    cv2.imwrite(str(path), img)
    assert main(["solve", str(path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "taken for a sensor's hot pixels" in err[0] and "Traceback" not in err[0]
