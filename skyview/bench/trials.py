"""One Monte Carlo trial, wherever it runs (in this process, a forked worker or a Dask worker): render the
frame of trial k from the context's attitudes and seeds, solve it with the context's `MethodSolver`, score it
against the truth. Trial k gets the same attitude and noise seed wherever it runs."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from skyview.core.attitude import attitude_error_arcsec
from skyview.simulate.render import SensorModel, simulate_image
from skyview.simulate.scenarios import Scenario
from skyview.simulate.scoring import score_trial
from skyview.simulate.truth import wrong_matches
from skyview.solver.pipeline import MethodSolver


@dataclass
class TrialContext:
    solver: MethodSolver
    catalog: object
    camera: object
    scenario: Scenario
    sensor: SensorModel
    attitudes: np.ndarray
    seeds: np.ndarray


def score_unverified(result, truth: dict, catalog_hip: np.ndarray) -> str | None:
    """The paper's own criterion: the method's first answer before verification (when it reports one)."""
    ident = result.identification
    first = ident.stats.get("first_chain") if ident else None
    if first is None:
        return None
    matches = first.get("matches") or {}
    if not matches:
        return "inconclusive"
    cents = result.centroids.uv
    wrong = wrong_matches([(int(o), cents[int(o), 0], cents[int(o), 1], int(catalog_hip[int(c)]))
                           for o, c in matches.items()], truth)
    return "incorrect" if wrong else "correct"


def n_catalog_stars(truth: dict) -> int:
    """Rendered stars within the scenario's catalog limit (faint field stars not counted)."""
    return sum(1 for st in truth["stars"] if not st.get("faint"))


def run_trial(ctx: TrialContext, k: int):
    """Simulate, solve and score trial k: (trial record, frame, result)."""
    scenario, solver = ctx.scenario, ctx.solver
    ts = time.perf_counter()
    frame = simulate_image(ctx.catalog, ctx.camera, ctx.attitudes[k], ctx.sensor, seed=int(ctx.seeds[k]),
                           **scenario.render_kwargs())
    sim_ms = (time.perf_counter() - ts) * 1e3
    result = solver.solve_array(frame.image)
    outcome, wrong = score_trial(result, frame.truth)
    unverified = score_unverified(result, frame.truth, solver.catalog.hip)
    ident = result.identification
    err = attitude_error_arcsec(result.R, ctx.attitudes[k]) if result.solved else None
    trial = {
        "trial": k, "seed": int(ctx.seeds[k]), "outcome": outcome,
        "status": ident.status if ident else "failed", "reason": result.reason,
        "unverified_outcome": unverified,
        "cause": (ident.stats.get("cause") if ident and outcome != "correct" else None),
        "stars_in_fov": n_catalog_stars(frame.truth), "centroids": result.centroids.n_detected,
        "matches": len(result.matches), "wrong_matches": wrong,
        "pivots": (ident.stats.get("pivots") if ident else None),
        "p_false": (ident.verification.get("p_false") if ident else None),
        "err_boresight_arcsec": err["boresight"] if err else None,
        "err_cross_arcsec": [err["cross_x"], err["cross_y"]] if err else None,
        "err_roll_arcsec": err["roll"] if err else None,
        "sigma_boresight_arcsec": result.sigma_boresight_arcsec,
        "sigma_roll_arcsec": result.sigma_roll_arcsec,
        "time_ms": {"simulate": sim_ms, **result.time_ms},
        "quaternion_true": [float(x) for x in np.asarray(frame.truth["quaternion"])],
    }
    return trial, frame, result
