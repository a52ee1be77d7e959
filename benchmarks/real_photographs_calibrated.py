"""Each method of the papers, both variants, on the eight real photographs in tests/data/real-images/.

Every method is told each photograph's FOV exactly: the papers' calibrated mode, `--fov-error 0`, with
no distortion model. This is the test Juang, Kim & Junkins made with their method on night-sky images.
A solve is correct when its boresight is within 0.1 deg of the reference, wrong when it is solved but
farther off. Prints one markdown row per method and variant (docs/benchmarks.md keeps the table).

Run: SKYVIEW_CACHE=/tmp/svcache .venv/bin/python benchmarks/real_photographs_calibrated.py
(the triangle method builds a database for every photograph's exact FOV: minutes the first time).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from skyview.attitude import attitude_error_arcsec
from skyview.centroid import load_image
from skyview.pipeline import solve_image

REAL = Path(__file__).resolve().parent.parent / "tests" / "data" / "real-images"
METHODS = ("angle", "triangle", "svd", "ellipticity", "genetic")  # stochastic needs a frame sequence
MAX_ERROR_ARCSEC = 0.1 * 3600.0


def main() -> None:
    ref = json.loads((REAL / "reference.json").read_text())
    images = {name: load_image(REAL / name) for name in sorted(ref)}
    print("| method | variant | correct | wrong | time per image (median) |")
    print("|---|---|---|---|---|")
    for method in METHODS:
        for variant in ("paper", "improved"):
            correct = wrong = 0
            times = []
            for name, image in images.items():
                t0 = time.perf_counter()
                result = solve_image(image, ref[name]["fov_deg"], method, fov_error=0.0, variant=variant)
                times.append(time.perf_counter() - t0)
                if result.solved:
                    err = attitude_error_arcsec(result.R, np.array(ref[name]["R"]))["boresight"]
                    correct += err < MAX_ERROR_ARCSEC
                    wrong += err >= MAX_ERROR_ARCSEC
            print(f"| {method} | {variant} | {correct} / {len(images)} | {wrong} | "
                  f"{np.median(times) * 1e3:.0f} ms |", flush=True)


if __name__ == "__main__":
    main()
