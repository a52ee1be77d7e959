"""The RA/Dec grid over a solved image: where the lines of constant right ascension and declination fall on
the sensor, through the camera the solve fitted (any lens: `skyview.core.camera`), for drawing over the
photograph (the viewer's panel image).

The spacing follows the field: about four lines of declination across the diagonal, on a "nice" step
(1, 2, 5 x 10^k degrees, or 15 and 30 for the widest skies, in arcminutes below a degree), and the
meridians on the step in hours and minutes of right ascension that spaces them alike at the field's
declination. Each line is a list of pixel runs (polylines inside the sensor), with the label it
carries ("+42°", "-5°30'", "12h", "5h40m") and the pixel where it enters the image (for its label).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import radec_to_vec, vec_to_radec

DEC_STEPS_DEG = (1 / 60, 2 / 60, 5 / 60, 10 / 60, 15 / 60, 20 / 60, 30 / 60, 1.0, 2.0, 5.0, 10.0, 15.0, 30.0)
RA_STEPS_DEG = tuple(m / 4.0 for m in (1, 2, 5, 10, 15, 20, 30)) + tuple(15.0 * h for h in (1, 2, 3, 6))
LINES_ACROSS = 4.0  # about this many declination lines across the image's diagonal
SAMPLES = 400  # points along each line across the field


@dataclass(frozen=True)
class GridLine:
    kind: str  # "ra" (a meridian) or "dec" (a parallel)
    value_deg: float
    label: str
    runs: tuple[np.ndarray, ...]  # (K, 2) pixel polylines inside the sensor
    anchor: tuple[float, float]  # the first pixel of the line inside the image (its label's place)


def _nice(step: float, steps: tuple[float, ...]) -> float:
    return next((s for s in steps if s >= step * 0.999), steps[-1])


def dec_label(dec_deg: float) -> str:
    sign = "+" if dec_deg >= 0 else "-"
    d = abs(dec_deg)
    deg, minutes = int(d + 1e-9), round((d - int(d + 1e-9)) * 60)
    return f"{sign}{deg}°" + (f"{minutes:02d}'" if minutes else "")


def ra_label(ra_deg: float) -> str:
    total_min = round((ra_deg % 360.0) / 15.0 * 60.0)
    h, m = divmod(total_min, 60)
    return f"{h % 24}h" + (f"{m:02d}m" if m else "")


def image_grid(camera: Camera, R: np.ndarray) -> list[GridLine]:
    """The RA/Dec lines over the image of `camera` at attitude R (v_cam = R v_icrs) (see the module
    docstring). Lines that do not cross the sensor are left out."""
    R = np.asarray(R, dtype=np.float64)
    half = camera.half_diagonal_rad
    ra0, dec0 = (math.degrees(x) for x in vec_to_radec(R[2]))
    dec_step = _nice(2.0 * math.degrees(half) / LINES_ACROSS, DEC_STEPS_DEG)
    ra_step = _nice(dec_step / max(math.cos(math.radians(dec0)), 0.05), RA_STEPS_DEG)
    reach = min(math.degrees(half) * 1.05, 180.0)
    lines: list[GridLine] = []
    # parallels within the reach of the boresight's declination
    lo, hi = max(-90.0, dec0 - reach), min(90.0, dec0 + reach)
    for d in np.arange(math.ceil(lo / dec_step) * dec_step, hi + 1e-9, dec_step):
        if abs(d) >= 90.0 - 1e-9:
            continue
        ra_span = 180.0 if (abs(d) + reach >= 90.0 or reach >= 90.0) else min(
            180.0, math.degrees(math.asin(min(1.0, math.sin(math.radians(reach)) / math.cos(math.radians(d))))) + 1)
        ras = np.linspace(ra0 - ra_span, ra0 + ra_span, SAMPLES)
        lines.append(_line(camera, R, "dec", float(d), dec_label(float(d)), np.radians(ras),
                           np.full(SAMPLES, math.radians(d))))
    # meridians: every ra_step (all around when the field holds a pole or is wide)
    span = 180.0 if (abs(dec0) + reach >= 90.0 or reach >= 60.0) else min(
        180.0, math.degrees(math.asin(min(1.0, math.sin(math.radians(reach)) / math.cos(math.radians(dec0))))) + 1)
    first = math.ceil((ra0 - span) / ra_step) * ra_step
    for a in np.arange(first, ra0 + span + 1e-9, ra_step):
        if span >= 180.0 and a >= first + 360.0 - 1e-9:
            break
        decs = np.linspace(max(-90.0, lo - 1.0), min(90.0, hi + 1.0), SAMPLES)
        lines.append(_line(camera, R, "ra", float(a % 360.0), ra_label(float(a)), np.full(SAMPLES, math.radians(a)),
                           np.radians(decs)))
    return [g for g in lines if g.runs]


def _line(camera: Camera, R: np.ndarray, kind: str, value: float, label: str, ra: np.ndarray,
          dec: np.ndarray) -> GridLine:
    uv, front = camera.project(radec_to_vec(ra, dec) @ R.T)
    inside = front & camera.in_image(uv)
    runs, anchor = [], (math.nan, math.nan)
    idx = np.flatnonzero(inside)
    if len(idx):
        breaks = np.flatnonzero(np.diff(idx) > 1) + 1
        for run in np.split(idx, breaks):
            if len(run) >= 2:
                runs.append(uv[run])
        anchor = (float(uv[idx[0], 0]), float(uv[idx[0], 1]))
    return GridLine(kind, value, label, tuple(runs), anchor)
