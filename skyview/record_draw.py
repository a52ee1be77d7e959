"""Rerun rendering of skyview's drawables: what every recording shares.

The recorder is a thin sink: `skyview.present` decides what a step shows (`StepView`, one palette, one
image stretch) and `log_step` logs it, one entity per role, the same roles the viewer draws as nodes.
Also here: entity paths, the output-path check, the atomic writer (`open_recording`), the pinhole and
pose archetypes, the static sky, and labels placed beside stars without collisions. Used by
`skyview.record` (one solve) and `skyview.record_sequence` (a frame sequence).

Pixel coordinates: skyview puts pixel centres at integers, Rerun at half-integers (its pixel (0, 0)
spans [0, 1]), so every 2-D position and the principal point are shifted by +0.5 here.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from skyview import sky_geometry as sg
from skyview.errors import BadInput
from skyview.present import (IMAGE_ROLES, PALETTE, SKY_ROLES, TEXTURE_FLOOR_SIGMAS, ImageEdges, ImageMarks, SkyLines,
                             SkyPoints, StepView, place_labels, stretch, stretch_note, unit_of)

APP_ID = "skyview"
TIMELINE = "step"
JPEG_QUALITY = 85
PIXEL_OFFSET = 0.5  # skyview pixel centre (integer) -> Rerun pixel centre (half-integer)
IMAGE_PLANE_DISTANCE = 1.03  # where the sensor image sits in 3D: just behind the stars on the unit sphere
LABEL_OFFSET_PX = 14.0  # labels sit this far right of their star in the image
LABEL_CHAR_PX = 17.0  # one label character in image pixels, as a 1024-pixel image shows in its panel
LABEL_HEIGHT_PX = 40.0

# Entity paths (kept in one place: the tests and the docs read them from here).
CATALOG = "sky/catalog"
GRID = "sky/grid"
FOV_ESTIMATED = "sky/fov/estimated"
FOV_TRUE = "sky/fov/true"
OBSERVED = "sky/observed"
MATCHES = "sky/matches"
MATCH_LABELS = "sky/matches/labels"
STEP_SKY = "sky/step"  # sky/step/<role> for the sky roles of skyview.present
CAMERA = "camera"
IMAGE = "camera/image"
CENTROIDS = "camera/image/centroids"
IMAGE_MATCHES = "camera/image/matches"
IMAGE_LABELS = "camera/image/labels"
IMAGE_STEP = "camera/image/step"  # camera/image/step/<role> for the image roles
TRUTH_STARS = "camera/image/truth/stars"
TRUTH_FALSE_STARS = "camera/image/truth/false_stars"
TRUE_CAMERA = "truth/camera"
STEP_LOG = "steps/log"
STEP_NUMBERS = "steps/numbers"  # steps/numbers/<unit>/<name>: one plot per unit
RESULT = "result"

C_GRID = PALETTE["grid"]
C_FOV_EST = PALETTE["estimated"]
C_FOV_TRUE = PALETTE["true"]
C_MATCH = PALETTE["identified"]
C_CENTROID = PALETTE["centroid"]
C_OBSERVED = PALETTE["unidentified"]
C_TRUTH = PALETTE["true"]
C_FALSE = PALETTE["false star"]
NO_AXES = rrb.SpatialInformation(target_frame="tf#/", show_axes=False, show_bounding_box=False)  # no origin arrows


def step_path(role: str) -> str:
    """The entity of a step role: sky roles under sky/step, image roles under camera/image/step."""
    return f"{IMAGE_STEP}/{role}" if role in IMAGE_ROLES else f"{STEP_SKY}/{role}"


@dataclass
class RecordInfo:
    """What a recording writer wrote."""

    path: Path
    bytes: int
    write_ms: float  # building and writing the recording (the solve not included)
    steps: int  # entries on the `step` timeline
    status: str

    def to_dict(self) -> dict:
        d = asdict(self)
        d["path"] = str(self.path)
        return d


def check_output_path(path: str | os.PathLike, force: bool = False) -> Path:
    """Validate where a recording will go, before any work is done: a one-line BadInput otherwise.

    The folder must exist and be writable; an existing file is kept unless `force`.
    """
    p = Path(path)
    if p.suffix != ".rrd":
        raise BadInput(f"{p}: a recording is written as a .rrd file (the Rerun viewer opens .rrd)")
    if p.is_dir():
        raise BadInput(f"{p} is a folder, not a .rrd file")
    parent = p.parent
    if not parent.exists():
        raise BadInput(f"folder {parent} does not exist")
    if not parent.is_dir():
        raise BadInput(f"{parent} is not a folder")
    if p.exists() and not force:
        raise BadInput(f"{p} exists; use --force to overwrite it")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise BadInput(f"cannot write into {parent}: permission denied")
    return p


@contextmanager
def open_recording(p: Path, rec_id: str, title: str, bp: rrb.Blueprint) -> Iterator[rr.RecordingStream]:
    """A recording stream that writes `p` (already checked with `check_output_path`): into a file beside
    it, moved into place only when the block completes; a failure leaves nothing behind. No wall-clock
    column: the same inputs give the same contents. OSError becomes a one-line BadInput."""
    tmp = p.with_name(f".{p.name}.tmp{os.getpid()}.rrd")
    try:
        with open(tmp, "xb"):  # a permission or path problem surfaces here as an OSError
            pass
    except OSError as exc:
        raise BadInput(f"cannot write {p}: {exc.strerror or exc}") from None
    rec = rr.RecordingStream(APP_ID, recording_id=rec_id, send_properties=False)
    rec.set_log_time_enabled(False)
    ok = False
    try:
        rec.save(str(tmp), default_blueprint=bp)
        rec.send_recording_name(title)
        yield rec
        rec.flush()
        rec.disconnect()
        if not tmp.exists() or tmp.stat().st_size == 0:
            raise BadInput(f"cannot write {p}: the recording came out empty")
        os.replace(tmp, p)
        ok = True
    except OSError as exc:
        raise BadInput(f"cannot write {p}: {exc.strerror or exc}") from None
    finally:
        if not ok:
            rec.disconnect()
            tmp.unlink(missing_ok=True)


# ============================================================================ archetypes

def display_image(image: np.ndarray) -> tuple[np.ndarray, str]:
    """8-bit view of a sensor image and how it was made: `present.stretch` with the background at black,
    as the viewer's sensor texture (`viewer.picture.texture`)."""
    a = np.asarray(image)
    if a.ndim != 2:
        raise BadInput(f"expected a single-channel image, got shape {a.shape}")
    from scipy.ndimage import grey_dilation

    # a star is a few pixels wide: widened by one pixel (as the viewer's texture) so that it survives the
    # shrink of a 1024-pixel frame into a panel a third as wide
    shown = grey_dilation(stretch(a, floor_sigmas=TEXTURE_FLOOR_SIGMAS), size=(3, 3))
    return shown, f"{stretch_note(a, TEXTURE_FLOOR_SIGMAS)}, widened 3 x 3; JPEG quality {JPEG_QUALITY}"


def rerun_uv(uv: np.ndarray) -> np.ndarray:
    return (np.asarray(uv, dtype=np.float64).reshape(-1, 2) + PIXEL_OFFSET).astype(np.float32)


def pinhole(camera, color=None) -> list:
    """Intrinsics (principal point moved to Rerun's pixel convention), RDF = OpenCV camera axes; the
    camera-axis arrows the viewer would draw at the pinhole are switched off (they would cross the sky)."""
    K = camera.K.copy()
    K[0, 2] += PIXEL_OFFSET
    K[1, 2] += PIXEL_OFFSET
    return [rr.Pinhole(image_from_camera=K, resolution=[camera.width, camera.height],
                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=IMAGE_PLANE_DISTANCE,
                       color=color, line_width=0.0002),
            rr.TransformAxes3D(axis_length=0.0)]


def pose(R: np.ndarray) -> rr.Transform3D:
    """v_cam = R @ v_icrs: R maps the parent (ICRS) into the child (camera)."""
    return rr.Transform3D(mat3x3=np.asarray(R, dtype=np.float32), relation=rr.TransformRelation.ChildFromParent)


def entity_name(name: str) -> str:
    keep = "".join(ch if ch.isalnum() or ch in "_-." else "_" for ch in str(name))
    return keep or "_"


def fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def log_sky(rec, catalog) -> None:
    """The celestial sphere (static): the guide catalog by magnitude and colour, the RA/Dec grid."""
    radii = sg.star_radius(catalog.mag, r_bright=0.007, r_faint=0.0018).astype(np.float32)
    rec.log(CATALOG, rr.Points3D(catalog.xyz.astype(np.float32), radii=radii,
                                 colors=sg.star_color(catalog.mag, catalog.bv)), static=True)
    rec.log(GRID, rr.LineStrips3D([g.astype(np.float32) for g in sg.radec_grid()], colors=C_GRID,
                                  radii=rr.Radius.ui_points(0.5)), static=True)


def image_labels(uv: np.ndarray, texts: list[str], priority: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Label anchors beside their stars in the image (LABEL_OFFSET_PX to the right), only those that do
    not overlap a more important one (`present.place_labels`): (K, 2) Rerun pixels and their texts."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros((0, 2), np.float32), []
    sizes = np.array([[LABEL_CHAR_PX * len(t), LABEL_HEIGHT_PX] for t in texts])
    keep = place_labels(uv, priority, sizes, gap=LABEL_OFFSET_PX)
    at = uv[keep] + np.stack([LABEL_OFFSET_PX + 0.5 * sizes[keep, 0], np.zeros(int(keep.sum()))], axis=1)
    return rerun_uv(at), [t for t, k in zip(texts, keep) if k]


def step_archetypes(view: StepView, uv: np.ndarray) -> dict[str, Any]:
    """The Rerun archetype of every role a step draws (entity path -> archetype); uv: the centroids."""
    out: dict[str, Any] = {}
    for role, d in view.drawables.items():
        if isinstance(d, SkyLines):
            out[step_path(role)] = rr.LineStrips3D(d.segments.astype(np.float32), colors=d.color,
                                                   radii=rr.Radius.ui_points(d.width * 0.75))
        elif isinstance(d, SkyPoints):
            out[step_path(role)] = rr.Points3D(d.xyz.astype(np.float32), colors=d.colors, radii=d.size * 0.6)
        elif isinstance(d, ImageMarks):
            sel = d.observed[d.observed < len(uv)]
            out[step_path(role)] = rr.Points2D(rerun_uv(uv[sel]), colors=d.color + (200,),
                                               radii=rr.Radius.ui_points(9.0 if role == "observed" else 7.0),
                                               labels=[f"#{i}" for i in sel], show_labels=False, draw_order=15)
        elif isinstance(d, ImageEdges):
            e = d.edges[(d.edges < len(uv)).all(axis=1)] if len(d.edges) else d.edges
            out[step_path(role)] = rr.LineStrips2D(np.stack([rerun_uv(uv[e[:, 0]]), rerun_uv(uv[e[:, 1]])], axis=1)
                                                   if len(e) else np.zeros((0, 2, 2), np.float32),
                                                   colors=d.color, radii=rr.Radius.ui_points(1.5), draw_order=16)
    return out


def number_path(name: str) -> str:
    return f"{STEP_NUMBERS}/{unit_of(name)}/{entity_name(name)}"


def log_step(rec, view: StepView, uv: np.ndarray, drawn: set[str]) -> set[str]:
    """Log one step (time set by the caller): its log line, its numbers (one plot per unit) and its
    drawables; roles drawn at the step before and absent now are cleared. Returns the paths drawn."""
    text = f"[{view.kind}] {view.note}" + "".join(f"\n  {t}" for t in view.text)
    rec.log(STEP_LOG, rr.TextLog(text, level=view.kind))
    for name, value in view.numbers.items():
        if value is not None and math.isfinite(value):
            rec.log(number_path(name), rr.Scalars(float(value)))
    now = step_archetypes(view, np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    for path, arch in now.items():
        rec.log(path, arch)
    for path in drawn - set(now):
        rec.log(path, rr.Clear(recursive=False))
    return set(now)


def step_role_paths() -> list[str]:
    return [step_path(r) for r in SKY_ROLES + IMAGE_ROLES]


def unit_plots(views: list[StepView]) -> list[rrb.TimeSeriesView]:
    """One time-series view per unit the steps' numbers are in (never two units in one plot)."""
    units: list[str] = []
    for v in views:
        for name in v.numbers:
            u = unit_of(name)
            if u not in units:
                units.append(u)
    return [rrb.TimeSeriesView(name=f"step numbers ({u})", origin=f"/{STEP_NUMBERS}/{u}",
                               plot_legend=rrb.Corner2D.RightTop) for u in units]
