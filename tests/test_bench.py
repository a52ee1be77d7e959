"""The bench scores against truth: a correct solve counts as correct, a wrong match as incorrect."""

import numpy as np

from skyview.bench import format_markdown, run_bench, score_trial
from skyview.truth import centroid_truth, wrong_matches
from skyview.scenarios import SCENARIOS


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
