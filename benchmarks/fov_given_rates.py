"""How right the default pipeline is when the FOV is given, typed a little off: `solve_image(image, fov_deg=F)`.

    python benchmarks/fov_given_rates.py SCENARIO N E [SEED]
    python benchmarks/fov_given_rates.py photos

Renders N frames of the skyview scenario SCENARIO (attitudes `random_attitudes(N, default_rng(SEED))`, frame k
rendered with seed k; SEED 7 by default) and solves frame k with the FOV typed as its true FOV x (1 + u_k),
u_k uniform in +-E (`default_rng(SEED + 1000)`), the default tolerance (+-10 %) behind it. `photos`: the eight
photographs of tests/data/real-images at their reference FOV. Prints one line: frames solved, the boresight
errors in pixels (how many over 5 px, which scores wrong, and over 1 px; the largest), which method answered
(the first try at the FOV given is "angle", the blind search "blind"), how many answers ended with the camera
fitted, and the median time of a solve (identification included, the first solve of each new camera
too). docs/benchmarks.md keeps the table of the 2026-12-07 fifth stop.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.catalog import load_guide_catalog
from skyview.detect.centroids import load_image
from skyview.simulate.render import simulate_image
from skyview.simulate.scenarios import get_scenario
from skyview.solver.pipeline import solve_image

REAL = Path(__file__).resolve().parent.parent / "tests" / "data" / "real-images"


def frames(name: str, n: int, seed: int):
    """(image, true attitude, true FOV) of each frame."""
    if name == "photos":
        ref = json.loads((REAL / "reference.json").read_text())
        return [(load_image(REAL / k), np.array(v["R"]), float(v["fov_deg"])) for k, v in sorted(ref.items())]
    sc = get_scenario(name)
    cat = load_guide_catalog()
    return [(simulate_image(cat, sc.camera(), R, sc.sensor(), seed=k, **sc.render_kwargs()).image, R, sc.fov_deg)
            for k, R in enumerate(random_attitudes(n, np.random.default_rng(seed)))]


def main(name: str, n: int = 100, error: float = 0.0, seed: int = 7) -> str:
    shots = frames(name, n, seed)
    us = np.random.default_rng(seed + 1000).uniform(-error, error, len(shots))
    px, methods, fitted, ms = [], {}, 0, []
    for (image, R, fov), u in zip(shots, us):
        t0 = time.perf_counter()
        res = solve_image(image, fov_deg=fov * (1 + u))
        ms.append((time.perf_counter() - t0) * 1e3)
        if res.solved:
            px.append(attitude_error_arcsec(res.R, R)["boresight"] / (3600.0 * fov / image.shape[1]))
            methods[res.method] = methods.get(res.method, 0) + 1
            fitted += bool(res.camera_fitted)
    px = np.array(px)
    return (f"{name} +-{error:g}: solved {len(px)}/{len(shots)}, over 5 px {int(np.sum(px > 5))}, over 1 px "
            f"{int(np.sum(px > 1))}, largest {px.max() if len(px) else float('nan'):.2f} px; answered by {methods}, "
            f"camera fitted {fitted}; median {np.median(ms):.2f} ms")


if __name__ == "__main__":
    args = sys.argv[1:]
    if not args or args[0] in ("-h", "--help"):
        print(__doc__)
        sys.exit(0)
    print(main(args[0], *(int(args[1]),) if len(args) > 1 else (),
               *(float(args[2]),) if len(args) > 2 else (), *(int(args[3]),) if len(args) > 3 else ()))
