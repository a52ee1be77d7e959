"""`skyview solve IMG --fov-deg F` in-process: the default pipeline with the FOV given, one camera per run.

    python benchmarks/fov_given.py SCENARIO N U

Renders N frames of the skyview scenario SCENARIO (attitudes uniform on SO(3), seed 11) with a camera whose
true FOV is F / (1 + U), F the scenario's FOV, and solves each with `solve_image(image, fov_deg=F)` (the
default tolerance, +-10 %), timing the whole call (centroids, identification, attitude; the image already
decoded, both paths warmed up on the first frame). Scored as `skyview bench --blind` scores: correct =
solved, no wrong match and the boresight within 5 px. Prints one JSON line: the counts, the median and p95
milliseconds, the median boresight error in pixels and which method answered how often.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace

import numpy as np

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.catalog import load_guide_catalog
from skyview.simulate.render import SensorModel, simulate_image
from skyview.simulate.scenarios import SCENARIOS
from skyview.simulate.truth import wrong_matches
from skyview.solver.pipeline import solve_image


def main(scenario: str, n: int, u: float) -> dict:
    given = SCENARIOS[scenario].fov_deg
    sc = replace(SCENARIOS[scenario], fov_deg=given / (1 + u))  # the lens; the user types `given`
    cat = load_guide_catalog()
    rng = np.random.default_rng(11)
    Rs = random_attitudes(n, rng)
    seeds = rng.integers(0, 2**31 - 1, n)
    cam = sc.camera()
    frames = [simulate_image(cat, cam, Rs[k], SensorModel(), seed=int(seeds[k]), **sc.render_kwargs())
              for k in range(n)]
    solve_image(frames[0].image, fov_deg=given)
    solve_image(frames[0].image)  # both paths loaded before the clock runs
    rows = []
    px_arcsec = np.degrees(cam.pixel_scale_rad) * 3600
    for k, fr in enumerate(frames):
        t0 = time.perf_counter()
        res = solve_image(fr.image, fov_deg=given)
        ms = (time.perf_counter() - t0) * 1e3
        px, outcome = None, "inconclusive"
        if res.solved:
            px = attitude_error_arcsec(res.R, Rs[k])["boresight"] / px_arcsec
            wrong = wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in res.matches], fr.truth)
            outcome = "incorrect" if (wrong or px > 5) else "correct"
        rows.append({"outcome": outcome, "px": px, "ms": ms, "method": res.method})
    ms = np.array([r["ms"] for r in rows])
    px = np.array([r["px"] for r in rows if r["px"] is not None])
    return {"scenario": scenario, "n": n, "u": u,
            **{o: sum(r["outcome"] == o for r in rows) for o in ("correct", "inconclusive", "incorrect")},
            "median_ms": round(float(np.median(ms)), 2), "p95_ms": round(float(np.percentile(ms, 95)), 1),
            "median_px": round(float(np.median(px)), 4) if len(px) else None,
            "methods": {m: sum(r["method"] == m for r in rows) for m in sorted({r["method"] for r in rows})}}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], int(sys.argv[2]), float(sys.argv[3]))))
