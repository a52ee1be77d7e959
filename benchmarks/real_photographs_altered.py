"""The eight real photographs altered as other cameras and exports alter images, solved blind.

Each photograph in tests/data/real-images/ is turned into seven others: 4x upscaled and saved as a
colour JPEG with the stars saturated into disks (a phone or a raw converter's export), its centre half
cropped (a longer lens), rotated 90 deg, blurred by a 3 px Gaussian (a defocused lens), sprinkled with
300 hot pixels, halved in resolution, and saved as an 8-bit JPEG of quality 40. Every one is solved
blind (no FOV) by `skyview.solve`, and its boresight compared with the reference attitude: a solve is
correct within 0.1 deg, wrong beyond. Prints one line per image and a summary (docs/blind.md keeps it).

Run: SKYVIEW_CACHE=/tmp/svcache .venv/bin/python benchmarks/real_photographs_altered.py [VARIANT ...]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

import skyview
from skyview.detect.centroids import load_image

REAL = Path(__file__).resolve().parent.parent / "tests" / "data" / "real-images"
MAX_ERROR_ARCSEC = 0.1 * 3600.0


def to_8bit(img: np.ndarray) -> np.ndarray:
    """Stretched to 8 bits with the brightest 0.1 % of pixels clipped (stars saturate, as in a JPEG)."""
    return cv2.convertScaleAbs(img, alpha=255.0 / max(1.0, float(np.percentile(img, 99.9))))


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    return cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])[1], cv2.IMREAD_UNCHANGED)


def variants(img: np.ndarray):
    h, w = img.shape
    g8 = to_8bit(img)
    big = cv2.resize(g8, None, fx=4, fy=4, interpolation=cv2.INTER_CUBIC)
    yield "jpeg-colour-x4", jpeg(cv2.cvtColor(big, cv2.COLOR_GRAY2BGR), 85)
    yield "crop-centre-half", img[h // 4: 3 * h // 4, w // 4: 3 * w // 4]
    yield "rot90", np.ascontiguousarray(np.rot90(img))
    yield "defocus-blur3", cv2.GaussianBlur(img, (0, 0), 3.0)
    hot = img.copy()
    rng = np.random.default_rng(1)
    hot[rng.integers(0, h, 300), rng.integers(0, w, 300)] = img.max()
    yield "hot-pixels-300", hot
    yield "half-res", cv2.resize(img, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    yield "jpeg-q40", jpeg(g8, 40)


def main(which: list[str]) -> int:
    ref = json.loads((REAL / "reference.json").read_text())
    counts = {"correct": 0, "wrong": 0, "not solved": 0}
    times = []
    for name in sorted(ref):
        img = load_image(REAL / name)
        boresight = np.asarray(ref[name]["R"])[2]
        for vname, v in variants(img):
            if which and vname not in which:
                continue
            t = time.perf_counter()
            s = skyview.solve(v)
            times.append(time.perf_counter() - t)
            if s.solved:
                err = float(np.degrees(np.arccos(np.clip(np.asarray(s.R)[2] @ boresight, -1, 1)))) * 3600
                outcome = "correct" if err <= MAX_ERROR_ARCSEC else "wrong"
                print(f"{name[:36]:36s} {vname:17s} solved, FOV {s.fov_deg:6.2f} deg, boresight {err:5.0f}\" "
                      f"from the reference, {times[-1] * 1e3:5.0f} ms", flush=True)
            else:
                outcome = "not solved"
                print(f"{name[:36]:36s} {vname:17s} not solved: {s.reason[:90]}", flush=True)
            counts[outcome] += 1
    total = sum(counts.values())
    print(f"\n{counts['correct']} of {total} correct, {counts['wrong']} wrong, {counts['not solved']} not solved; "
          f"median {np.median(times) * 1e3:.0f} ms per image (decoded, solve only)")
    return 0 if counts["wrong"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
