"""Each method of the papers, both variants, on the eight real photographs in tests/data/real-images/,
told each photograph's FOV exactly (the papers' calibrated mode: --fov-error 0, no distortion model),
as Juang, Kim & Junkins tried their method on night-sky images. Correct: boresight within 0.1 deg of
the reference; wrong: solved farther off. Run: SKYVIEW_CACHE=... .venv/bin/python
benchmarks/real_photographs_calibrated.py (the triangle method builds a database per FOV: minutes).
"""
import json, time, numpy as np, sys
from pathlib import Path
from skyview.pipeline import solve_image
from skyview.centroid import load_image
from skyview.attitude import attitude_error_arcsec
real = Path(__file__).resolve().parent.parent / 'tests' / 'data' / 'real-images'; ref = json.loads((real/'reference.json').read_text())
rows = []
for method in ("angle", "triangle", "svd", "ellipticity", "genetic"):
    for variant in ("paper", "improved"):
        ok = wrong = 0; ts = []
        for name in sorted(ref):
            img = load_image(real/name)
            t = time.perf_counter()
            try:
                r = solve_image(img, ref[name]['fov_deg'], method, fov_error=0.0, variant=variant)
            except Exception as e:
                print(method, variant, name, "ERROR", e); continue
            ts.append(time.perf_counter() - t)
            if r.solved:
                e = attitude_error_arcsec(r.R, np.array(ref[name]['R']))['boresight']
                if e < 0.1 * 3600: ok += 1
                else: wrong += 1
        print(f"| {method} | {variant} | {ok} / 8 | {wrong} | {np.median(ts)*1e3:.0f} ms |", flush=True)
