"""Simulated cases and bench failures, recorded: `skyview record` and `skyview bench --record-failures`.

`CaseRunner` simulates a scenario case (attitude from the seed), solves it and scores it against the
truth (`skyview.simulate.scoring`); `record_case` records one; `FailureRecorder` records every trial of a bench
run that is not correct. The recording itself is `skyview.record.recording.record_solve`.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from skyview.core.attitude import random_attitudes
from skyview.core.errors import BadInput
from skyview.record.draw import RecordInfo, check_output_path
from skyview.record.recording import record_solve
from skyview.simulate.scoring import score_trial

# ============================================================================ simulated cases

def case_attitude(seed: int) -> np.ndarray:
    """The attitude of case `seed`: uniform on SO(3), drawn from numpy's Generator(seed)."""
    return random_attitudes(1, np.random.default_rng(int(seed)))[0]


@dataclass
class Case:
    """One simulated, solved case."""

    method: str
    variant: str
    scenario: str
    seed: int
    frame: Any  # simulate.SimulatedFrame
    result: Any  # pipeline.SolveResult
    solver: Any  # pipeline.MethodSolver
    outcome: str  # correct | inconclusive | incorrect (bench.score_trial)
    meta: dict = field(default_factory=dict)


class CaseRunner:
    """Simulates and solves cases of one method / variant / scenario, keeping the solver loaded."""

    def __init__(self, method: str, scenario: str, variant: str = "paper", catalog=None):
        from skyview.core.catalog import load_guide_catalog
        from skyview.identify import METHODS
        from skyview.simulate.scenarios import get_scenario
        from skyview.solver.pipeline import MethodSolver

        if method not in METHODS:
            raise BadInput(f"unknown method {method!r}: choose from {', '.join(METHODS)}")
        self.scenario = get_scenario(scenario)
        self.method, self.variant = method, variant
        self.catalog = catalog if catalog is not None else load_guide_catalog()
        self.camera = self.scenario.camera()
        self.solver = MethodSolver(self.camera, method, mag_limit=self.scenario.mag_limit,
                                   sigma_rad=self.scenario.sigma_rad, catalog=self.catalog, variant=variant,
                                   max_stars=self.scenario.max_stars)

    def run(self, seed: int) -> Case:
        from skyview.simulate.render import SensorModel, simulate_image

        sc = self.scenario
        t0 = time.perf_counter()
        frame = simulate_image(self.catalog, self.camera, case_attitude(seed), SensorModel(), seed=int(seed),
                               mag_limit=sc.mag_limit, n_false_stars=sc.n_false_stars,
                               false_star_placement=sc.false_star_placement, position_noise_rad=sc.noise_rad)
        sim_ms = (time.perf_counter() - t0) * 1e3
        result = self.solver.solve_array(frame.image, measure_all=True)  # every detected star recorded
        outcome, _ = score_trial(result, frame.truth)
        meta = {"method": self.method, "variant": self.variant, "scenario": f"{sc.name}: {sc.description}",
                "seed": int(seed), "outcome against truth": outcome,
                "stars drawn": len(frame.truth["stars"]), "simulate ms": round(sim_ms, 2),
                "remake": f"skyview record --method {self.method} --variant {self.variant} "
                          f"--scenario {sc.name} --seed {int(seed)}"}
        return Case(self.method, self.variant, sc.name, int(seed), frame, result, self.solver, outcome, meta)

    def record(self, case: Case, path: str | os.PathLike, force: bool = False) -> RecordInfo:
        return record_solve(path, case.result, case.frame.image, catalog=self.solver.catalog,
                            truth=case.frame.truth, force=force, meta=case.meta)


def record_case(path: str | os.PathLike, method: str, scenario: str, seed: int, *, variant: str = "paper",
                force: bool = False, catalog=None) -> tuple[RecordInfo, Case]:
    """Simulate case `seed` of `scenario`, solve it with `method` and record it at `path`."""
    check_output_path(path, force)  # fail before the slow part
    runner = CaseRunner(method, scenario, variant, catalog)
    case = runner.run(seed)
    return runner.record(case, path, force), case


# ============================================================================ bench failures

class FailureRecorder:
    """`run_bench(on_trial=...)` callback: one recording per trial that is not correct.

    Files are `<folder>/<method>-<variant>-<scenario>-seed<bench seed>-trial<k>-<outcome>.rrd`; an existing
    name gets a -2, -3, ... suffix (nothing is overwritten). The trial dict gains a "recording" entry.
    """

    def __init__(self, folder: str | os.PathLike, *, method: str, variant: str, scenario: str, seed: int):
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise BadInput(f"{self.folder} is not a folder")
        if not self.folder.parent.is_dir():
            raise BadInput(f"folder {self.folder.parent} does not exist")
        try:
            self.folder.mkdir(exist_ok=True)
        except OSError as exc:
            raise BadInput(f"cannot create the folder {self.folder}: {exc.strerror}") from None
        if not os.access(self.folder, os.W_OK | os.X_OK):
            raise BadInput(f"cannot write into {self.folder}: permission denied")
        self.stem = f"{method}-{variant}-{scenario}-seed{seed}"
        self.scenario = scenario
        self.bench_seed = seed
        self.written: list[RecordInfo] = []

    def __call__(self, trial: dict, frame, result, solver) -> None:
        if trial["outcome"] == "correct":
            return
        base = f"{self.stem}-trial{trial['trial']:04d}-{trial['outcome']}"
        p, k = self.folder / f"{base}.rrd", 1
        while p.exists():
            k += 1
            p = self.folder / f"{base}-{k}.rrd"
        meta = {"method": result.method, "variant": result.variant, "scenario": self.scenario,
                "bench seed": self.bench_seed, "trial": trial["trial"], "image seed": trial["seed"],
                "outcome against truth": trial["outcome"]}
        info = record_solve(p, result, frame.image, catalog=solver.catalog, truth=frame.truth, meta=meta)
        trial["recording"] = str(p)
        self.written.append(info)
