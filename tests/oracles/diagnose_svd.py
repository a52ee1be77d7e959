"""The svd method's failure causes with the truth of a simulated frame (Juang, Kim & Junkins' words).

Truth never enters an identifier: the method reports its own cause (stats["cause"], "attempts"); here,
after the fact, the truth of the frame tells a ranking error from a missing boresight set.

    diagnose            per attempt and per frame: too_few_stars / missing_set / ranking / noise
    cat_rows_on_sensor  the catalog rows that project onto the sensor at an attitude
    bench_trial_hook    `skyview.bench.runner.run_bench(on_trial=...)`: the cause of an unsolved svd trial
"""

from __future__ import annotations

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog
from skyview.identify.base import Identification
from skyview.identify.svd import SVDMethod
from skyview.simulate.scoring import truth_rows


def diagnose(method: SVDMethod, result: Identification, truth_rows: np.ndarray, R_true: np.ndarray) -> dict:
    """The failure causes the paper names, for one frame whose truth is known (a simulation).

    truth_rows: the catalog row of each observed star (-1: a false star, a hot pixel, or a star not in
    the catalog). R_true: the true attitude. Each attempt of `result.stats["attempts"]` gets a cause:

    - "too_few_stars": fewer than N stars in the boresight's circle (after the delta_m rule), or
      no star left to verify with (lack of measurements);
    - "missing_set" (the paper's lack of boresight direction, Fig. 5): the boresight is not a
      reference star (a false star, a removed close pair), or its catalog set has a star off the
      sensor, so the set seen is in no catalog row;
    - "ranking": the catalog set is on the sensor but the measured set differs from it: an order
      swap, a rank swap at the N/N+1 boundary, a star deleted by the delta_m rule, a false star in
      the set, a catalog star not detected;
    - "noise": the measured set is the catalog set in the right order, and still failed (a bound or
      the sign rule rejected it, or the verification did).

    Returns {"outcome", "first": cause of the first attempt, "frame": the frame's cause (noise >
    ranking > missing_set > too_few_stars: the cause nearest to success), "counts": per cause}.
    """
    truth_rows = np.asarray(truth_rows, dtype=np.int64)
    if result.identified:
        return {"outcome": "identified", "first": "", "frame": "", "counts": {}}
    attempts = result.stats.get("attempts", [])
    if not attempts:
        return {"outcome": result.status, "first": "too_few_stars", "frame": "too_few_stars",
                "counts": {"too_few_stars": 1}}
    causes = []
    cat = method.catalog
    for a in attempts:
        stars = list(a["stars"])
        if a.get("within", len(stars)) < method.N:
            causes.append("too_few_stars")
            continue
        b = int(truth_rows[a["boresight"]])
        expected = method.catalog_sets_of(b) if b >= 0 else []
        if not expected:
            causes.append("missing_set")
            continue
        on_sensor = set(cat_rows_on_sensor(method.camera, cat, R_true, {r for e in expected for r in e}))
        if all(any(r not in on_sensor for r in e) for e in expected):
            causes.append("missing_set")
            continue
        seen = tuple(int(truth_rows[i]) for i in stars)
        if seen in expected:
            causes.append("too_few_stars" if a["cause"] == "too_few_stars" else "noise")
        else:
            causes.append("ranking")
    counts = {c: causes.count(c) for c in sorted(set(causes))}
    frame = next(c for c in ("noise", "ranking", "missing_set", "too_few_stars") if c in causes)
    return {"outcome": result.status, "first": causes[0], "frame": frame, "counts": counts}


def cat_rows_on_sensor(camera: Camera, catalog: GuideCatalog, R: np.ndarray, rows) -> list[int]:
    """The catalog rows among `rows` that project onto the sensor at attitude R."""
    rows = np.array(sorted(rows), dtype=np.int64)
    if len(rows) == 0:
        return []
    uv, front = camera.project(catalog.xyz[rows] @ np.asarray(R).T)
    return rows[front & camera.in_image(uv)].tolist()


def bench_trial_hook(trial: dict, frame, result, solver) -> None:
    """For `skyview.bench.runner.run_bench(on_trial=...)`: adds the paper's failure cause of an unsolved
    SVD trial to the trial record, "svd_cause" (with the truth, `diagnose`'s frame cause) and
    "svd_cause_untruthed" (the method's own stats["cause"]); other methods are left alone."""
    ident = result.identification
    if ident is None:
        if not result.solved:
            trial["svd_cause"] = trial["svd_cause_untruthed"] = "too_few_stars"
        return
    if ident.method != SVDMethod.name or ident.identified:
        return
    rows = truth_rows(result.centroids.uv, frame.truth, solver.catalog)
    trial["svd_cause"] = diagnose(solver.identifier, ident, rows, np.asarray(frame.truth["R"]))["frame"]
    trial["svd_cause_untruthed"] = ident.stats.get("cause", "")
