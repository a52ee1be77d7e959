"""`skyview bench --scheduler`: the Monte Carlo bench's trials on Dask (skyview.bench.dask_engine) give the
same trials and summary as the local run."""

import json

import pytest

from skyview.bench.runner import run_bench
from skyview.cli import main
from skyview.simulate.scenarios import get_scenario

SAME = ("trial", "seed", "outcome", "status", "stars_in_fov", "centroids", "matches", "wrong_matches",
        "err_boresight_arcsec", "quaternion_true")


@pytest.mark.slow
def test_a_two_worker_local_cluster_gives_the_local_summary():
    pytest.importorskip("dask.distributed")
    sc = get_scenario("cole8")
    local = run_bench("angle", sc, 6, seed=4, variant="improved", progress=False)
    dask = run_bench("angle", sc, 6, seed=4, variant="improved", progress=False, scheduler="local", workers=2)
    assert dask["scheduler"] == "local"
    assert dask["counts"] == local["counts"] and dask["rates"] == local["rates"]
    assert dask["by_stars_in_fov"] == local["by_stars_in_fov"]
    assert dask["attitude_accuracy"] == local["attitude_accuracy"]
    assert [{k: t[k] for k in SAME} for t in dask["trials"]] == [{k: t[k] for k in SAME} for t in local["trials"]]
    assert sum(local["counts"].values()) == 6 and local["counts"]["correct"] >= 4


@pytest.mark.slow
def test_cli_scheduler_inline_and_bad_combinations(tmp_path, capsys):
    rc = main(["bench", "--method", "angle", "-n", "2", "--scheduler", "inline", "--quiet", "--out", str(tmp_path)])
    assert rc == 0
    saved = json.loads(next(tmp_path.glob("*.json")).read_text())
    assert saved["scheduler"] == "inline" and saved["n"] == 2
    capsys.readouterr()
    for argv in (["bench", "-n", "2", "--scheduler", "local", "--jobs", "2", "--out", str(tmp_path)],
                 ["bench", "-n", "2", "--scheduler", "local", "--blind", "--out", str(tmp_path)],
                 ["bench", "-n", "2", "--scenario", "slew", "--scheduler", "local", "--out", str(tmp_path)],
                 ["bench", "-n", "2", "--scheduler", "tcp://127.0.0.1:1", "--quiet", "--out", str(tmp_path)]):
        rc = main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert rc != 0 and len(err) == 1, (argv, err)
