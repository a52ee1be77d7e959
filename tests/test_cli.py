"""The command line as a user meets it: end to end on a simulated sky, and every bad input."""

import argparse
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from skyview.cli import main
from skyview.core.errors import BadInput


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(err: str) -> bool:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    return len(lines) == 1 and lines[0].startswith("skyview:") and "Traceback" not in err


@pytest.fixture(scope="module")
def orion(tmp_path_factory):
    d = tmp_path_factory.mktemp("orion")
    png = d / "orion.png"
    code = main(["simulate", "--ra", "83.8", "--dec", "-5.4", "--roll", "30", "--fov-deg", "8", "--seed", "1",
                 "--out", str(png)])
    assert code == 0
    return png


def test_simulate_then_solve_end_to_end(orion, capsys):
    truth = json.loads(orion.with_suffix(".json").read_text())
    assert truth["ra_deg"] == pytest.approx(83.8) and truth["roll_deg"] == pytest.approx(30.0)
    code, out, err = run(capsys, "solve", str(orion), "--fov-deg", "8", "--json", "--method", "angle",
                         "--fov-error", "0")
    assert code == 0, err
    res = json.loads(out)
    assert res["status"] == "solved" and res["method"] == "angle" and not res["camera_fitted"]
    for key in ("R", "quaternion", "ra_deg", "dec_deg", "roll_deg", "sigma_arcsec", "matches", "n_centroids",
                "time_ms", "database_key"):
        assert key in res
    assert res["truth"]["error_arcsec"]["boresight"] < 60.0
    assert abs(res["truth"]["error_arcsec"]["roll"]) < 60.0
    assert res["truth"]["wrong_matches"] == 0
    assert res["ra_deg"] == pytest.approx(83.8, abs=0.01) and res["dec_deg"] == pytest.approx(-5.4, abs=0.01)
    assert res["roll_deg"] == pytest.approx(30.0, abs=0.05)
    q = np.array(res["quaternion"])
    assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
    truth_hips = {s["hip"] for s in json.loads(orion.with_suffix(".json").read_text())["stars"]}
    assert len(res["matches"]) >= 4 and {m["hip"] for m in res["matches"]} <= truth_hips


def test_solve_in_a_subprocess_prints_json(orion):
    p = subprocess.run([sys.executable, "-m", "skyview", "solve", str(orion), "--fov-deg", "8", "--json"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["status"] == "solved"


def test_missing_file(capsys, tmp_path):
    code, out, err = run(capsys, "solve", str(tmp_path / "nothing.png"), "--fov-deg", "8")
    assert code == 2 and one_line_error(err) and "nothing.png" in err


def test_not_an_image(capsys, tmp_path):
    bad = tmp_path / "notes.png"
    bad.write_text("this is not a picture\n")
    code, out, err = run(capsys, "solve", str(bad), "--fov-deg", "8")
    assert code == 2 and one_line_error(err)


def test_a_directory(capsys, tmp_path):
    code, out, err = run(capsys, "solve", str(tmp_path), "--fov-deg", "8")
    assert code == 2 and one_line_error(err)


def test_blank_image(capsys, tmp_path):
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((256, 256), 17, np.uint8))
    code, out, err = run(capsys, "solve", str(blank), "--fov-deg", "8")
    assert code == 2 and one_line_error(err) and "blank" in err


def test_a_float_image_of_values_under_one_is_not_blank_and_a_constant_one_says_its_value(capsys, tmp_path):
    """Blank means every pixel equal: a float image of values in 0..1 (their integer parts all 0) is searched for
    stars; a constant one says the value it holds."""
    noise = tmp_path / "unit.tiff"
    cv2.imwrite(str(noise), (np.random.default_rng(3).random((120, 160)) * 0.9).astype(np.float32))
    code, out, err = run(capsys, "solve", str(noise))
    assert code == 1 and "every pixel" not in err
    flat = tmp_path / "flat.tiff"
    cv2.imwrite(str(flat), np.full((64, 64), 0.5, np.float32))
    code, out, err = run(capsys, "solve", str(flat))
    assert code == 2 and one_line_error(err) and "every pixel is 0.5" in err


def _chunk(kind: bytes, data: bytes) -> bytes:
    import struct
    import zlib

    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def test_a_damaged_png_is_one_line_on_stderr(tmp_path):
    """A PNG cut short, and one whose image data is shorter than its header says: one line on stderr and exit 2,
    as a whole process (libpng wrote its own line to the process's stderr first, past OpenCV's logging)."""
    import struct
    import zlib

    ok, buf = cv2.imencode(".png", np.random.default_rng(1).integers(0, 255, (64, 64), dtype=np.uint8))
    cut = tmp_path / "cut.png"
    cut.write_bytes(buf.tobytes()[: len(buf) // 3])
    short = tmp_path / "short.png"
    short.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", 900, 900, 8, 0, 0, 0, 0))
                      + _chunk(b"IDAT", zlib.compress(b"\x00" * 100)) + _chunk(b"IEND", b""))
    for path in (cut, short):
        for extra in ([], ["--json"]):
            p = subprocess.run([sys.executable, "-m", "skyview", "solve", str(path), *extra], capture_output=True,
                               text=True, timeout=120)
            assert p.returncode == 2, p.stderr
            assert len(p.stderr.strip().splitlines()) == 1 and "libpng" not in p.stderr, (p.stdout, p.stderr)
            if extra:
                lines = p.stdout.strip().splitlines()
                assert len(lines) == 1 and json.loads(lines[0])["status"] == "error"
    assert "truncated" in subprocess.run([sys.executable, "-m", "skyview", "solve", str(cut)], capture_output=True,
                                         text=True, timeout=120).stderr


def test_empty_sky_is_not_solved(capsys, tmp_path):
    png = tmp_path / "empty.png"
    assert main(["simulate", "--ra", "10", "--dec", "10", "--mag-limit", "-3", "--out", str(png)]) == 0
    capsys.readouterr()
    code, out, err = run(capsys, "solve", str(png), "--fov-deg", "8", "--json")
    assert code == 1 and one_line_error(err)
    assert json.loads(out)["status"] == "failed"


@pytest.mark.parametrize("fov", ["0", "-3", "360", "400", "nan", "abc"])
def test_impossible_fov(capsys, orion, fov):
    code, out, err = run(capsys, "solve", str(orion), "--fov-deg", fov)
    assert code == 2 and one_line_error(err)


def test_unknown_method(capsys, orion):
    code, out, err = run(capsys, "solve", str(orion), "--fov-deg", "8", "--method", "astrology")
    assert code == 2 and one_line_error(err) and "astrology" in err


def test_simulate_refuses_to_overwrite_and_to_write_into_a_missing_folder(capsys, tmp_path):
    png = tmp_path / "sky.png"
    png.write_bytes(b"user data")
    code, out, err = run(capsys, "simulate", "--ra", "1", "--dec", "2", "--out", str(png))
    assert code == 2 and one_line_error(err)
    assert png.read_bytes() == b"user data"
    code, out, err = run(capsys, "simulate", "--ra", "1", "--dec", "2", "--out", str(tmp_path / "no" / "sky.png"))
    assert code == 2 and one_line_error(err)
    code, out, err = run(capsys, "simulate", "--ra", "1", "--dec", "95", "--out", str(tmp_path / "x.png"))
    assert code == 2 and one_line_error(err)


def test_simulate_frames_into_a_folder_it_makes_as_the_docs_say(capsys, tmp_path, monkeypatch):
    """`skyview simulate --frames N --out seq/` (docs/tracking.md, docs/stochastic.md) writes the folder seq with
    frame_000.png ... and sequence.json, making it when it is not there, and `skyview solve-sequence seq/` reads
    it; a name ending in .json keeps the stem form beside each other; a folder made by a run whose write failed
    is not left behind, nor is anything written into a folder whose parent is missing."""
    monkeypatch.chdir(tmp_path)
    sky = ["simulate", "--ra", "83.8", "--dec", "-5.4", "--roll", "20", "--fov-deg", "12", "--turn-deg", "2"]
    code, out, err = run(capsys, *sky, "--frames", "3", "--out", "seq/")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "seq").iterdir()) == [
        "frame_000.json", "frame_000.png", "frame_001.json", "frame_001.png", "frame_002.json", "frame_002.png",
        "sequence.json"]
    code, out, err = run(capsys, "solve-sequence", "seq/", "--method", "angle", "--variant", "improved", "--json")
    frames = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert code == 0 and len(frames) == 3 and all(f["solved"] for f in frames)
    code, out, err = run(capsys, *sky, "--frames", "2", "--out", "run.json")
    assert code == 0 and (tmp_path / "run_001.png").is_file() and (tmp_path / "run.json").is_file()
    code, out, err = run(capsys, *sky, "--frames", "2", "--out", "seq")  # its frames are there already
    assert code == 2 and one_line_error(err) and "already exists" in err
    code, out, err = run(capsys, *sky, "--frames", "2", "--out", "nowhere/seq")
    assert code == 2 and one_line_error(err) and not (tmp_path / "nowhere").exists()

    def full_disk(*args, **kwargs):
        raise BadInput("cannot write seq2/frame_000.png: no space left on the device")

    monkeypatch.setattr("skyview.simulate.render.save_sequence", full_disk)
    code, out, err = run(capsys, *sky, "--frames", "2", "--out", "seq2")
    assert code == 2 and one_line_error(err) and not (tmp_path / "seq2").exists()


def test_solve_output_is_never_overwritten(capsys, orion, tmp_path):
    keep = tmp_path / "result.json"
    keep.write_text("precious")
    code, out, err = run(capsys, "solve", str(orion), "--fov-deg", "8", "--output", str(keep))
    assert code == 2 and one_line_error(err) and keep.read_text() == "precious"
    code, out, err = run(capsys, "solve", str(orion), "--fov-deg", "8", "--output", str(tmp_path / "no" / "r.json"))
    assert code == 2 and one_line_error(err)


def test_unknown_scenario_and_bad_options(capsys):
    code, out, err = run(capsys, "bench", "--scenario", "hubble")
    assert code == 2 and one_line_error(err)
    code, out, err = run(capsys, "solve")
    assert code == 2 and one_line_error(err)


def test_method_parameters_by_name(orion, capsys):
    # a parameter reaches the method: this field solves, but not when the angle method may not pivot
    code, out, err = run(capsys, "solve", str(orion), "--fov-deg", "8", "--method", "angle", "--json", "--param",
                         "max_pivots=0")
    assert code == 1, err
    assert "after 0 pivots (the limit)" in json.loads(out)["reason"]
    for bad, words in ((["--param", "max_pivotz=1"], "no parameter 'max_pivotz'"),
                       (["--param", "max_pivots=abc"], "cannot take max_pivots='abc'"),
                       (["--param", "max_pivots"], "not KEY=VALUE")):
        code, out, err = run(capsys, "solve", str(orion), "--fov-deg", "8", "--method", "angle", *bad)
        assert code == 2 and one_line_error(err) and words in err, err


def test_solve_blind_with_no_options(orion, capsys):
    """The default pipeline: no FOV, no method; the fitted camera is reported."""
    code, out, err = run(capsys, "solve", str(orion), "--json")
    assert code == 0, err
    res = json.loads(out)
    assert res["status"] == "solved" and res["method"] == "blind" and res["camera_fitted"]
    assert res["fov_deg"] == pytest.approx(8.0, rel=0.005)
    assert res["plate_scale_arcsec_per_px"] == pytest.approx(8.0 * 3600 / 1024, rel=0.01)
    assert res["truth"]["wrong_matches"] == 0 and res["truth"]["error_arcsec"]["boresight"] < 30.0
    # a wrong FOV estimate within its tolerance still solves; outside it, not (and never wrongly)
    code, out, err = run(capsys, "solve", str(orion), "--fov-deg", "8.6", "--json")
    assert code == 0 and json.loads(out)["fov_deg"] == pytest.approx(8.0, rel=0.005)
    code, out, err = run(capsys, "solve", str(orion), "--fov-deg", "8.6", "--fov-error", "0", "--method", "angle")
    assert code == 1 and one_line_error(err)


def test_solve_writes_a_wcs_and_refuses_to_overwrite(orion, capsys, tmp_path):
    pytest.importorskip("astropy")
    from astropy.io import fits

    wcs = tmp_path / "orion.wcs"
    code, out, err = run(capsys, "solve", str(orion), "--wcs", str(wcs))
    assert code == 0, err
    hdr = fits.getheader(wcs)
    truth = json.loads(orion.with_suffix(".json").read_text())
    assert hdr["CTYPE1"].startswith("RA---TAN") and hdr["CRVAL1"] == pytest.approx(truth["ra_deg"], abs=0.01)
    before = wcs.read_bytes()
    code, out, err = run(capsys, "solve", str(orion), "--wcs", str(wcs))
    assert code == 2 and one_line_error(err) and wcs.read_bytes() == before
    code, out, err = run(capsys, "solve", str(orion), "--wcs", str(tmp_path / "no" / "x.wcs"))
    assert code == 2 and one_line_error(err)


@pytest.mark.parametrize("bad", [["--fov-error", "2"], ["--fov-error", "-0.1"], ["--param", "x=1"],
                                 ["--method", "angle", "--fov-deg", "500"]])
def test_solve_bad_options_are_one_line(orion, capsys, bad):
    code, out, err = run(capsys, "solve", str(orion), *bad)
    assert code == 2 and one_line_error(err)


def test_cache_list_and_clear(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    (tmp_path / "databases").mkdir()
    (tmp_path / "databases" / "angle-0123456789abcdef.npz").write_bytes(b"x" * 2048)
    code, out, err = run(capsys, "cache", "list")
    assert code == 0 and "1 database(s)" in out and "angle-0123456789abcdef.npz" in out
    code, out, err = run(capsys, "cache", "clear")
    assert code == 0 and "removed 1" in out
    assert not any((tmp_path / "databases").iterdir())


def _subcommands(parser, prefix=()):
    """(argv prefix, parser) for every subcommand, nested ones (cache clear, catalog build) included."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*prefix, name), sub
                yield from _subcommands(sub, (*prefix, name))


def test_every_subcommand_help_lists_the_choices(capsys):
    from skyview.cli import build_parser
    from skyview.identify import METHODS
    from skyview.simulate.scenarios import SCENARIOS

    subs = list(_subcommands(build_parser()))
    assert {" ".join(argv) for argv, _ in subs} >= {"demo", "simulate", "solve", "bench", "solve-sequence",
                                                    "bench-sequence", "record", "replay", "cache", "cache clear",
                                                    "catalog", "catalog build", "view"}
    for argv, sub in subs:
        with pytest.raises(SystemExit) as exc:
            main([*argv, "--help"])
        assert exc.value.code == 0, argv
        out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
        options = {s for a in sub._actions for s in a.option_strings}
        if "--method" in options:
            assert all(m in out for m in METHODS), (argv, out)
        if "--scenario" in options:
            assert all(s in out for s in SCENARIOS), (argv, out)
        for action in sub._actions:  # every argument says what it is (and its unit, in the text)
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            assert action.help, (argv, action.dest)


def test_replay_finds_the_example_recordings_from_any_folder(tmp_path, monkeypatch, capsys):
    from skyview.cli import resolve_recording

    monkeypatch.chdir(tmp_path)
    p = resolve_recording("recordings/angle-cole8.rrd", None)
    assert p.is_absolute() and p.exists() and p.name == "angle-cole8.rrd"
    assert resolve_recording(None, "angle").name.startswith("angle-")
    code, out, err = run(capsys, "replay", "--example", "astrology")
    assert code == 2 and one_line_error(err) and "angle" in err and "triangle" in err


def test_a_calibrated_failure_says_what_to_try(orion, capsys):
    code, out, err = run(capsys, "solve", str(orion), "--fov-deg", "9.5", "--fov-error", "0", "--method", "angle")
    assert code == 1 and one_line_error(err)
    assert "leave out --fov-error 0" in err and "--variant improved" in err


# ---------------------------------------------------------------------- experiments

def test_every_experiment_is_registered_and_listed(capsys):
    import importlib
    import pkgutil

    import skyview.experiments as experiments
    from skyview.experiments import EXPERIMENTS

    modules = {m.name for m in pkgutil.iter_modules(experiments.__path__)}
    assert modules == set(EXPERIMENTS)  # a module without its registry line would be unreachable
    with pytest.raises(SystemExit) as exc:
        main(["experiment", "--help"])
    assert exc.value.code == 0
    listing = capsys.readouterr().out
    for name, line in EXPERIMENTS.items():
        assert f"{name}  " in listing and line in listing
        module = importlib.import_module(f"skyview.experiments.{name}")
        parser = argparse.ArgumentParser()
        module.add_arguments(parser)
        assert all(a.help for a in parser._actions), name  # every option says what it is
        assert callable(module.command)
        assert f'main(["experiment", "{name}"' in Path(module.__file__).read_text()  # python -m ... NAME


@pytest.mark.parametrize("argv", [["nope"], ["measure", "--bogus"], ["measure", "--n", "many"],
                                  ["measure", "--method", "svd", "--configs", "paper"],
                                  ["genetic_map", "--runs", "0"], ["ellipticity_sweep", "--param", "x=not json"]])
def test_an_experiment_with_bad_arguments_says_so_in_one_line(capsys, argv):
    code, out, err = run(capsys, "experiment", *argv)
    assert code == 2 and one_line_error(err) and out == ""


def test_an_experiment_runs_from_the_cli_and_as_a_module(tmp_path, capsys):
    out = tmp_path / "measure.json"
    code, text, err = run(capsys, "experiment", "measure", "--n", "12", "--false-stars", "0", "--configs", "paper",
                          "--json", str(out))
    assert code == 0, err
    report = json.loads(out.read_text())
    counts = report["runs"][0]["configs"]["paper"]["counts"]
    assert sum(counts.values()) == 12 and counts["incorrect"] == 0  # every attitude accounted for, none wrong
    assert "database angle-" in text and "paper" in text
    p = subprocess.run([sys.executable, "-m", "skyview.experiments.measure", "--n", "0x"], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 2 and "skyview experiment measure" in p.stderr and "Traceback" not in p.stderr


def test_the_choices_come_from_the_registries():
    from skyview.cli import build_parser
    from skyview.identify import METHODS, VARIANTS
    from skyview.identify.verify import STATISTICS

    seen = set()
    for argv, sub in _subcommands(build_parser()):
        for action in sub._actions:
            if "--variant" in action.option_strings:
                assert tuple(action.choices) == tuple(VARIANTS) and action.default == VARIANTS[0], argv
                seen.add("variant")
            if "--statistic" in action.option_strings:
                assert tuple(action.choices) == tuple(STATISTICS), argv
                seen.add("statistic")
            if "--method" in action.option_strings and action.choices is not None:
                assert set(METHODS) <= set(action.choices) <= set(METHODS) | {"blind"}, argv
                seen.add("method")
    assert seen == {"variant", "statistic", "method"}


@pytest.mark.slow
def test_demo_ends_in_the_viewer_on_a_real_photograph(tmp_path, monkeypatch, capsys):
    """In a terminal `skyview demo` opens the viewer on one of the bundled photographs, solved blind (the
    server itself is stubbed: the test records what it was asked to serve)."""
    import skyview.viewer.app as app

    asked = {}
    monkeypatch.setattr(app, "serve", lambda **kw: asked.update(kw) or 0)
    monkeypatch.setattr(sys.stdin, "isatty", lambda: True, raising=False)
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True, raising=False)
    monkeypatch.chdir(tmp_path)
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    assert asked["image"].endswith(".png") and "real-images" in asked["image"] and asked["method"] is None
    assert "5. the viewer on the photograph" in out


def test_an_fov_given_far_off_is_solved_at_any_fov_with_a_note_unless_its_tolerance_is_given(capsys):
    """--fov-deg given as the diagonal (14.25 deg for the photographs' 11.43 deg horizontal) or the vertical FOV
    (8.6 deg), or just wrong (17 deg): nothing verifies within +-10 %, so the blind search takes any FOV and a
    note says how far the one given was off, and what it looks like; with --fov-error given, it is kept to."""
    photo = Path(__file__).parent / "data" / "real-images" / "2019-07-29T204726_Alt40_Azi-135_Try1.png"
    for given, hint in ((14.25, "diagonal"), (8.6, "vertical"), (17.0, None)):
        code, out, err = run(capsys, "solve", str(photo), "--fov-deg", str(given), "--json")
        d = json.loads(out)
        assert code == 0 and d["fov_deg"] == pytest.approx(11.433, abs=0.01)
        note = [n for n in d["notes"] if "is off by more than" in n]
        assert len(note) == 1 and (hint is None or f"the {hint} FOV" in note[0]), d["notes"]
        assert (hint is not None) == ("FOV is" in note[0])
    code, out, err = run(capsys, "solve", str(photo), "--fov-deg", "14.25", "--fov-error", "0.1", "--json")
    assert code == 1 and json.loads(out)["status"] == "failed"
