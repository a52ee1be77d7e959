"""`skyview bench --scheduler ADDRESS`: the Monte Carlo bench's trials on Dask.

The same engine as the coverage sweep (`skyview.bench.executor.run_tasks`): the trials are cut into tasks
of `chunk` trial numbers; a worker (`bench_task`) builds the bench's context once per configuration
(catalog, camera, solver: its database from the worker's cache; the attitudes and noise seeds drawn
from the seed exactly as `run_bench` draws them) and runs `skyview.bench.trials.run_trial` for each of its trials.
Trial k gets the same attitude and noise seed wherever it runs, so the outcomes are those of the
local run; only the timings differ. `scheduler="local"` starts a LocalCluster of n_workers processes
on this machine; an address ("tcp://host:8786") uses that cluster (the workers need skyview
installed and the same catalog); "inline" runs the tasks in this process.
"""

from __future__ import annotations

from collections import Counter
from typing import Callable

import numpy as np

from skyview.simulate.render import SensorModel
from skyview.simulate.scenarios import Scenario

LOCAL = "local"
DEFAULT_CHUNK = 8
_STATE: dict = {}  # per worker process: the context of the last configuration


def _context(method: str, scenario: Scenario, n: int, seed: int, method_params: dict | None, variant: str,
             sensor: SensorModel):
    from skyview.bench.trials import TrialContext
    from skyview.core.attitude import random_attitudes
    from skyview.core.catalog import load_guide_catalog
    from skyview.solver.pipeline import MethodSolver

    key = (method, repr(scenario), n, seed, repr(sorted((method_params or {}).items())), variant, repr(sensor))
    if _STATE.get("key") != key:
        rng = np.random.default_rng(seed)  # the draws of run_bench, in its order
        catalog = load_guide_catalog()
        camera = scenario.camera()
        solver = MethodSolver(camera, method, mag_limit=scenario.mag_limit, sigma_rad=scenario.sigma_rad,
                              catalog=catalog, method_params=method_params, variant=variant,
                              max_stars=scenario.max_stars)
        ctx = TrialContext(solver=solver, catalog=catalog, camera=camera, scenario=scenario, sensor=sensor,
                            attitudes=random_attitudes(n, rng), seeds=rng.integers(0, 2**31 - 1, size=n))
        _STATE.clear()
        _STATE.update(key=key, ctx=ctx)
    return _STATE["ctx"]


def bench_task(method: str, scenario: Scenario, n: int, seed: int, method_params: dict | None, variant: str,
               sensor: SensorModel, trials: list[int]) -> list[dict]:
    """Run the bench's trials `trials` (numbers < n) of this configuration: their records."""
    from skyview.bench.trials import run_trial

    ctx = _context(method, scenario, n, seed, method_params, variant, sensor)
    out = []
    for k in trials:
        try:
            out.append(run_trial(ctx, int(k))[0])
        except Exception as exc:  # noqa: BLE001 - one failed trial is reported, the others go on
            out.append({"trial": int(k), "outcome": "error", "reason": f"{type(exc).__name__}: {exc}"})
    return out


def trials_on_dask(method: str, scenario: Scenario, n: int, *, seed: int, method_params: dict | None, variant: str,
                   sensor: SensorModel, scheduler: str, n_workers: int = 2, chunk: int = DEFAULT_CHUNK,
                   on_trial: Callable[[dict, Counter], None] | None = None) -> list[dict]:
    """Every trial k < n, run by `bench_task` on Dask; the records in trial order. on_trial(record,
    counts) in this process as each arrives."""
    from skyview.bench.executor import run_tasks

    chunk = max(1, int(chunk))
    tasks = [list(range(s, min(s + chunk, n))) for s in range(0, n, chunk)]
    args = [(method, scenario, n, seed, method_params, variant, sensor, t) for t in tasks]
    records: list[dict] = []
    counts: Counter = Counter()

    def collect(_a, recs):
        for r in recs:
            records.append(r)
            counts[r["outcome"]] += 1
            if on_trial is not None:
                on_trial(r, counts)

    run_tasks(bench_task, args, scheduler=None if scheduler == LOCAL else scheduler, n_workers=n_workers,
              on_result=collect)
    return sorted(records, key=lambda r: r["trial"])
