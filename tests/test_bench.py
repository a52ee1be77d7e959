"""The bench scores against truth: a correct solve counts as correct, a wrong match as incorrect."""

import json

import numpy as np
import pytest

from skyview.bench.runner import format_markdown, run_bench, score_trial
from skyview.simulate.scenarios import SCENARIOS
from skyview.simulate.truth import centroid_truth, wrong_matches


def test_bench_runs_and_scores_against_truth(tmp_path, monkeypatch):
    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    s = run_bench("angle", SCENARIOS["cole8"], 6, seed=3, variant="improved", progress=False)
    assert sum(s["counts"].values()) == 6 == len(s["trials"])
    assert s["counts"]["incorrect"] == 0
    for t in s["trials"]:
        if t["outcome"] == "correct":
            assert t["matches"] >= 3 and t["err_boresight_arcsec"] < 120
        if t["stars_in_fov"] <= 2:
            assert t["outcome"] == "inconclusive"
    md = format_markdown(s)
    assert "| correct | inconclusive | incorrect |" in md and "cole8" in md


def test_scoring_catches_a_wrong_match():
    truth = {"stars": [{"hip": 10, "u_noisy": 100.0, "v_noisy": 200.0}, {"hip": 11, "u_noisy": 400.0, "v_noisy": 50.0}],
             "false_stars": [{"u": 700.0, "v": 700.0}]}
    assert wrong_matches([(0, 100.5, 199.5, 10), (1, 400.0, 50.0, 11)], truth) == []
    assert wrong_matches([(0, 100.5, 199.5, 11)], truth) == [0]  # swapped identity
    assert wrong_matches([(2, 700.0, 700.0, 12)], truth) == [2]  # a false star called a star
    assert wrong_matches([(3, 10.0, 10.0, 10)], truth) == [3]  # nothing rendered there

    class R:
        solved = True
        matches = [{"index": 0, "u": 100.2, "v": 200.1, "hip": 11}]

    assert score_trial(R, truth) == ("incorrect", [0])
    R.solved = False
    assert score_trial(R, truth) == ("inconclusive", [])


def test_centroid_truth_labels_stars_false_stars_and_nothing():
    truth = {"stars": [{"hip": 10, "u": 100.0, "v": 200.0}], "false_stars": [{"u": 700.0, "v": 700.0}]}
    assert centroid_truth(np.array([[100.4, 200.2], [700.0, 701.0], [5.0, 5.0]]), truth) == [10, -1, None]


def test_two_jobs_give_the_same_outcomes_as_one():
    """Trial k gets the same attitude and noise whatever the number of processes."""
    one = run_bench("angle", SCENARIOS["cole8"], 6, seed=5, progress=False)
    two = run_bench("angle", SCENARIOS["cole8"], 6, seed=5, progress=False, jobs=2)
    assert two["jobs"] == 2 and [t["trial"] for t in two["trials"]] == list(range(6))
    for a, b in zip(one["trials"], two["trials"]):
        assert (a["seed"], a["outcome"], a["matches"], a["quaternion_true"]) == \
            (b["seed"], b["outcome"], b["matches"], b["quaternion_true"])
    assert one["counts"] == two["counts"]


def test_cli_jobs_refuses_recording_failures(tmp_path, capsys):
    from skyview.cli import main

    rec = tmp_path / "failures"
    assert main(["bench", "-n", "2", "--jobs", "2", "--record-failures", str(rec), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--jobs" in err[0] and not rec.exists()


# ---------------------------------------------------------------------------------- blind bench

def _small_blind_solver(monkeypatch, tmp_path):
    """A blind database for 18-36 deg fields only: builds in about a second (the full one takes ~10 s)."""
    import functools

    from skyview.bench import runner as bench
    from skyview.identify.patterns import PatternParams

    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(bench, "BlindSolver",
                        functools.partial(bench.BlindSolver, pattern_params=PatternParams(min_edge_deg=8.0)))


@pytest.mark.slow
def test_blind_bench_cli_end_to_end(tmp_path, monkeypatch, capsys):
    from skyview.cli import main

    _small_blind_solver(monkeypatch, tmp_path)
    out = tmp_path / "results"
    code = main(["bench", "--blind", "--scenario", "blind20", "-n", "3", "--fov-error", "0.1", "--quiet",
                 "--out", str(out)])
    text = capsys.readouterr().out
    assert code == 0
    assert "| FOV given | correct | inconclusive | incorrect |" in text and "+-10 %" in text
    saved = list(out.glob("blind-blind20-fov0.1-n3-seed0.json"))
    assert len(saved) == 1
    s = json.loads(saved[0].read_text())
    assert sum(s["counts"].values()) == 3 and s["counts"]["incorrect"] == 0
    for t in s["trials"]:
        assert abs(t["fov_given_deg"] / t["fov_true_deg"] - 1) <= 0.1
        if t["outcome"] == "correct":
            assert abs(t["fov_error_pct"]) < 1.0 and t["err_boresight_arcsec"] < 5 * 70.3
    assert s["counts"]["correct"] >= 2


@pytest.mark.slow
def test_blind_bench_with_jpeg_and_distortion(tmp_path, monkeypatch):
    from skyview.bench.runner import format_blind_markdown, run_blind_bench

    _small_blind_solver(monkeypatch, tmp_path)
    sc = SCENARIOS["blind20"].with_changes(jpeg_quality=80, k1=0.05)
    assert sc.name == "blind20[jpeg_quality=80,k1=0.05]" and sc.camera().k1 == 0.05
    s = run_blind_bench(sc, 2, seed=1, progress=False)
    assert s["fov_error"] is None and s["counts"]["incorrect"] == 0 and len(s["trials"]) == 2
    assert all(t["fov_given_deg"] is None and t["faint_in_fov"] > 0 for t in s["trials"])
    md = format_blind_markdown(s)
    assert "none (blind)" in md and "JPEG quality 80" in md and "k1 0.05" in md


def test_bench_flags_are_checked(tmp_path, capsys):
    from skyview.cli import main

    for flags in (["--blind", "--jpeg-quality", "0"], ["--blind", "--jpeg-quality", "101"],
                  ["--blind", "--fov-error", "1.5"], ["--fov-error", "0.1"], ["--blind", "--method", "angle"],
                  ["--blind", "--vignetting", "1.2"], ["--blind", "--scenario", "nope"]):
        assert main(["bench", "-n", "1", "--quiet", "--out", str(tmp_path), *flags]) == 2, flags
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "skyview: error:" in err
