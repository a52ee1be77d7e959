"""The Monte Carlo benches' trials on more than one process: `skyview bench --jobs N` (a LocalCluster of N
worker processes on this machine) and `--scheduler ADDRESS` (a Dask cluster).

The same engine as the coverage sweep (`skyview.bench.executor.run_tasks`): the trials are cut into tasks
of `chunk` trial numbers; a worker (`trials_task`) builds the bench's context once per configuration, by
the bench's own module-level function (`method_context`, `runner.blind_context`: catalog, camera, solver,
its database from the worker's cache, and the attitudes and noise seeds drawn from the seed exactly as
the bench in one process draws them), then runs the bench's trial function for each of its trials.
Trial k gets the same attitude and noise seed wherever it runs, so the outcomes are those of the run in
one process; only the timings differ.

Faults: a trial that raises is a trial with outcome "error" and its reason; a task whose worker dies is
run once more on another worker (Dask's `allowed-failures`, set to MAX_TASK_RETRIES), then its trials are
reported with outcome "error" — every finished trial is kept. Ctrl-C stops the cluster's workers and
raises `Interrupted` with the trials finished so far. `scheduler="local"` starts the LocalCluster; an
address ("tcp://host:8786") uses that cluster (the workers need skyview installed and the same catalog).
"""

from __future__ import annotations

from collections import Counter
from typing import Callable

import numpy as np

from skyview.simulate.render import SensorModel
from skyview.simulate.scenarios import Scenario

LOCAL = "local"
DEFAULT_CHUNK = 5
MAX_TASK_RETRIES = 1  # a task whose worker died is run once more, then its trials are reported as lost
_STATE: dict = {}  # per worker process: the context of the last configuration


class Interrupted(Exception):
    """Ctrl-C during a bench: the trials finished so far travel with it."""

    def __init__(self, trials: list[dict]):
        super().__init__(f"interrupted after {len(trials)} trials")
        self.trials = trials


def method_context(method: str, scenario: Scenario, n: int, seed: int, method_params: dict | None, variant: str,
                   sensor: SensorModel):
    """The method bench's context (`skyview.bench.trials.TrialContext`), drawn from the seed as `run_bench`
    draws it."""
    from skyview.bench.trials import TrialContext
    from skyview.core.attitude import random_attitudes
    from skyview.core.catalog import load_guide_catalog
    from skyview.solver.pipeline import MethodSolver

    rng = np.random.default_rng(seed)  # the draws of run_bench, in its order
    catalog = load_guide_catalog()
    camera = scenario.camera()
    solver = MethodSolver(camera, method, mag_limit=scenario.mag_limit, sigma_rad=scenario.sigma_rad,
                          catalog=catalog, method_params=method_params, variant=variant,
                          max_stars=scenario.max_stars)
    return TrialContext(solver=solver, catalog=catalog, camera=camera, scenario=scenario, sensor=sensor,
                        attitudes=random_attitudes(n, rng), seeds=rng.integers(0, 2**31 - 1, size=n))


def _context(make: Callable, args: tuple):
    key = (make.__module__, make.__qualname__, repr(args))
    if _STATE.get("key") != key:
        ctx = make(*args)
        _STATE.clear()
        _STATE.update(key=key, ctx=ctx)
    return _STATE["ctx"]


def trials_task(make: Callable, args: tuple, run_one: Callable, trials: list[int]) -> list[dict]:
    """Run the trials `trials` of the configuration make(*args) (built once per worker) with run_one(ctx, k):
    their records."""
    ctx = _context(make, args)
    out = []
    for k in trials:
        try:
            out.append(run_one(ctx, int(k))[0])
        except Exception as exc:  # noqa: BLE001 - one failed trial is reported, the others go on
            out.append({"trial": int(k), "outcome": "error", "reason": f"{type(exc).__name__}: {exc}"})
    return out


def trials_on_dask(make: Callable, args: tuple, run_one: Callable, n: int, *, scheduler: str = LOCAL,
                   n_workers: int = 2, chunk: int = DEFAULT_CHUNK,
                   on_trial: Callable[[dict, Counter], None] | None = None) -> list[dict]:
    """Every trial k < n, run_one(make(*args), k) on Dask (`trials_task`); the records in trial order.
    on_trial(record, counts) in this process as each arrives. Raises Interrupted on Ctrl-C."""
    import dask
    import distributed  # noqa: F401 - its defaults in dask's config before the settings below change two

    from skyview.bench.executor import run_tasks

    chunk = max(1, int(chunk))
    tasks = [list(range(s, min(s + chunk, n))) for s in range(0, n, chunk)]
    records: list[dict] = []
    counts: Counter = Counter()

    def collect(recs):
        for r in recs:
            records.append(r)
            counts[r["outcome"]] += 1
            if on_trial is not None:
                on_trial(r, counts)

    def lost(a, exc):
        why = "its worker died twice" if type(exc).__name__ == "KilledWorker" else f"{type(exc).__name__}: {exc}"
        collect([{"trial": int(k), "outcome": "error", "reason": why} for k in a[-1]])

    try:
        # one task at a time on each worker (none queued there), so that a worker's death counts against
        # the task it was running only
        with dask.config.set({"distributed.scheduler.allowed-failures": MAX_TASK_RETRIES,
                              "distributed.scheduler.worker-saturation": 1.0}):
            run_tasks(trials_task, [(make, args, run_one, t) for t in tasks],
                      scheduler=None if scheduler == LOCAL else scheduler, n_workers=n_workers,
                      on_result=lambda _a, recs: collect(recs), on_error=lost)
    except KeyboardInterrupt:
        raise Interrupted(sorted(records, key=lambda r: r["trial"])) from None
    return sorted(records, key=lambda r: r["trial"])
