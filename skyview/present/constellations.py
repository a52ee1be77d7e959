"""The 88 constellations: their stick figures and names, on the sphere and over a solved image.

The data are d3-celestial 0.7.35's (`assets/constellations/`, BSD 3-Clause; the IAU / Sky & Telescope
figures, J2000 vertices; its README says where they come from and how to fetch them again). Serpens'
two parts (Caput, Cauda) are one constellation here, as the IAU counts them.

`figure_polylines()`: every figure as unit-vector polylines (for the 3-D sphere, where a chord seen from
the centre is the great-circle arc). `image_figures(camera, R)`: the figures that cross a solved image,
through the camera its solve fitted (any lens), as pixel runs inside the sensor with the constellation's
name and where to write it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import REPO_ROOT, radec_to_vec

ASSET_DIR = REPO_ROOT / "assets" / "constellations"
STEP_DEG = 0.25  # a figure's edges are sampled this finely along their great circles for an image


@dataclass(frozen=True)
class Constellation:
    abbr: str  # IAU abbreviation, e.g. "Ori"
    name: str  # e.g. "Orion"
    label_xyz: np.ndarray  # (3,) where its name goes on the sphere (d3-celestial's label position)
    lines: tuple[np.ndarray, ...]  # the figure: (K, 3) unit-vector polylines, vertex to vertex


@dataclass(frozen=True)
class ImageFigure:
    abbr: str
    name: str
    runs: tuple[np.ndarray, ...]  # (K, 2) pixel polylines inside the sensor
    anchor: tuple[float, float]  # where its name goes in the image (pixels)


def _unit(ra_deg, dec_deg) -> np.ndarray:
    return radec_to_vec(np.radians(np.asarray(ra_deg, dtype=np.float64) % 360.0),
                        np.radians(np.asarray(dec_deg, dtype=np.float64)))


@lru_cache(maxsize=1)
def constellations() -> dict[str, Constellation]:
    """The 88 constellations by abbreviation (read once: 78 KB of JSON, ~10 ms)."""
    lines = json.loads((ASSET_DIR / "constellations.lines.json").read_text(encoding="utf-8"))
    names = json.loads((ASSET_DIR / "constellations.json").read_text(encoding="utf-8"))
    polylines: dict[str, list[np.ndarray]] = {}
    for f in lines["features"]:
        for poly in f["geometry"]["coordinates"]:
            lon, lat = np.asarray(poly, dtype=np.float64).T
            polylines.setdefault(f["id"], []).append(_unit(lon, lat))
    out: dict[str, Constellation] = {}
    for f in names["features"]:
        abbr = f["id"]
        if abbr in out:  # Serpens: Caput and Cauda under one abbreviation
            continue
        lon, lat = f["geometry"]["coordinates"]
        name = "Serpens" if abbr == "Ser" else f["properties"]["name"]  # not "Serpens Caput": both parts
        out[abbr] = Constellation(abbr, name, _unit(lon, lat), tuple(polylines.get(abbr, ())))
    return out


def figure_polylines() -> list[np.ndarray]:
    """Every figure's polylines, unit vectors (the sphere's lines)."""
    return [line for c in constellations().values() for line in c.lines]


def _sampled(line: np.ndarray, step_rad: float) -> np.ndarray:
    """A polyline of unit vectors with points every step_rad along each edge's great circle."""
    out = [line[:1]]
    for a, b in zip(line[:-1], line[1:]):
        ang = math.acos(float(np.clip(a @ b, -1.0, 1.0)))
        n = max(1, math.ceil(ang / step_rad))
        t = np.arange(1, n + 1)[:, None] / n
        if ang < 1e-12:
            out.append(b[None])
            continue
        out.append((np.sin((1 - t) * ang) * a + np.sin(t * ang) * b) / math.sin(ang))
    return np.concatenate(out)


def image_figures(camera: Camera, R: np.ndarray) -> list[ImageFigure]:
    """The figures that cross the image of `camera` at attitude R (v_cam = R v_icrs): each figure's pixel
    runs inside the sensor and its name's anchor (its label position when that is in the image, else the
    middle of its longest run). Figures wholly outside the field are skipped before they are sampled."""
    R = np.asarray(R, dtype=np.float64)
    boresight = R[2]
    reach = min(math.pi, camera.half_diagonal_rad * 1.05)
    out = []
    for c in constellations().values():
        runs = []
        for line in c.lines:
            # an edge can cross the field only if it comes within reach of the boresight: its ends
            # no farther than reach + the edge's own length
            ang_end = np.arccos(np.clip(line @ boresight, -1.0, 1.0))
            edge = np.arccos(np.clip(np.einsum("ij,ij->i", line[:-1], line[1:]), -1.0, 1.0))
            if not np.any(np.minimum(ang_end[:-1], ang_end[1:]) <= reach + edge):
                continue
            pts = _sampled(line, math.radians(STEP_DEG))
            uv, front = camera.project(pts @ R.T)
            inside = front & camera.in_image(uv)
            idx = np.flatnonzero(inside)
            if len(idx) < 2:
                continue
            for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
                if len(run) >= 2:
                    runs.append(uv[run])
        if not runs:
            continue
        uv_label, front = camera.project((c.label_xyz @ R.T)[None])
        if bool(front[0]) and bool(camera.in_image(uv_label)[0]):
            anchor = (float(uv_label[0, 0]), float(uv_label[0, 1]))
        else:
            longest = max(runs, key=len)
            anchor = (float(longest[len(longest) // 2, 0]), float(longest[len(longest) // 2, 1]))
        out.append(ImageFigure(c.abbr, c.name, tuple(runs), anchor))
    return out
