"""Rerun rendering of skyview's drawables: what every recording shares.

The recorder is a thin sink: `skyview.present.drawables` decides what a step shows (`StepView`, one palette, one
image stretch) and `log_step` logs it, one entity per role, the same roles the viewer draws as nodes.
Also here: entity paths, the output-path check, the atomic writer (`open_recording`), the pinhole and
pose archetypes, the static sky, and labels placed beside stars without collisions. Used by
`skyview.record.recording` (one solve) and `skyview.record.sequence` (a frame sequence).

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

from skyview.core import sky_geometry as sg
from skyview.core.errors import BadInput
from skyview.present.drawables import (
    IMAGE_ROLES,
    PALETTE,
    SKY_ROLES,
    TEXTURE_FLOOR_SIGMAS,
    ImageEdges,
    ImageMarks,
    SkyLines,
    SkyPoints,
    StepView,
    layout_labels,
    stretch,
    stretch_note,
    unit_of,
)

APP_ID = "skyview"
TIMELINE = "step"
JPEG_QUALITY = 85
PIXEL_OFFSET = 0.5  # skyview pixel centre (integer) -> Rerun pixel centre (half-integer)
IMAGE_PLANE_DISTANCE = 1.03  # where the sensor image sits in 3D: just behind the stars on the unit sphere
FISHEYE_IMAGE_PLANE = 0.02  # a fisheye's Pinhole plane: out of the way (its image is drawn on PHOTO)
PHOTO_MAX_SIDE = 768  # px: a fisheye's texture on PHOTO at most this many a side (RGB, uncompressed in the .rrd)
SKY_MATCH_RADIUS = 0.006  # an identified star on the sky (world units: the sphere's radius is 1)
SKY_OBSERVED_RADIUS = 0.004  # an observed star's direction on the sky

# Labels are laid out in screen pixels of the window the recording opens in: the browser test's 1400 x 860
# (a larger window only spreads them apart), cut by the blueprint's shares (skyview.record.recording.blueprint).
WINDOW_PX = (1400.0, 860.0)
WINDOW_CHROME_PX = 66.0  # Rerun's top bar and the collapsed time panel
VIEW_TITLE_PX = 28.0  # a view's title bar
SKY_COLUMN_SHARES = (3, 2)  # the sky | the image over the tabs
IMAGE_ROW_SHARES = (5, 4)  # the image over the tabs
SKY_VIEW_PX = (WINDOW_PX[0] * SKY_COLUMN_SHARES[0] / sum(SKY_COLUMN_SHARES),
               WINDOW_PX[1] - WINDOW_CHROME_PX - VIEW_TITLE_PX)
IMAGE_VIEW_PX = (WINDOW_PX[0] * SKY_COLUMN_SHARES[1] / sum(SKY_COLUMN_SHARES),
                 (WINDOW_PX[1] - WINDOW_CHROME_PX) * IMAGE_ROW_SHARES[0] / sum(IMAGE_ROW_SHARES) - VIEW_TITLE_PX)
EYE_BACK = 0.45  # the sky view's eye sits this far out along the boresight (the sphere's radius is 1) ...
EYE_DROP = 0.03  # ... and this far below it (image-down), looking at the boresight on the sphere
EYE_FOV_Y = math.radians(55.0)  # Rerun's 3-D eye: vertical field of view
# A Rerun label on screen (egui's body font): a box as wide as its text (~6.6 px a character) plus 13 px and
# 23 px tall, centred under its point with its top LABEL_DROP_PX below it.
LABEL_CHAR_PX, LABEL_PAD_PX, LABEL_HEIGHT_PX, LABEL_DROP_PX = 6.6, 13.0, 23.0, 1.0
LABEL_GAP_PX = 3.0  # between a label and its star's mark
LABEL_APART_PX = 8.0  # every other labelled star's mark is this much farther from a label than its own star's
SKY_MARK_GROW = 1.2  # a star on the sky covers its projected radius and the image plane's marks beside it
IMAGE_RING_PX = 10.0  # the widest mark drawn on a star in the image (the truth rings, 10 ui points)

# Entity paths (kept in one place: the tests and the docs read them from here).
CATALOG = "sky/catalog"
GRID = "sky/grid"
FOV_ESTIMATED = "sky/fov/estimated"
FOV_TRUE = "sky/fov/true"
OBSERVED = "sky/observed"
MATCHES = "sky/matches"
MATCH_LABELS = "sky/matches/labels"
STEP_SKY = "sky/step"  # sky/step/<role> for the sky roles of skyview.present.drawables
CAMERA = "camera"
IMAGE = "camera/image"
# a fisheye's image in 3-D: the sensor's mesh textured with it (Rerun's Pinhole has no fisheye model; the
# Pinhole's own plane is kept small, FISHEYE_IMAGE_PLANE, and the 2-D view reads the image from it as before)
PHOTO = "camera/photo"
CENTROIDS = "camera/image/centroids"
IMAGE_MATCHES = "camera/image/matches"
IMAGE_LABELS = "camera/image/labels"
IMAGE_STEP = "camera/image/step"  # camera/image/step/<role> for the image roles
TRUTH_STARS = "camera/image/truth/stars"
TRUTH_FALSE_STARS = "camera/image/truth/false_stars"
TRUTH_FALSE_LABELS = "camera/image/truth/false_stars/labels"
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
    plane = FISHEYE_IMAGE_PLANE if camera.fisheye else IMAGE_PLANE_DISTANCE
    return [rr.Pinhole(image_from_camera=K, resolution=[camera.width, camera.height],
                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=plane,
                       color=color, line_width=0.0002),
            rr.TransformAxes3D(axis_length=0.0)]


def fisheye_photo(camera, shown: np.ndarray) -> rr.Mesh3D:
    """A fisheye's image in 3-D, where the lens saw each pixel: the sensor's mesh (`sky_geometry.sensor_mesh`) at
    IMAGE_PLANE_DISTANCE in the camera frame, textured with the image shown (grey, at most PHOTO_MAX_SIDE a side;
    Rerun's texture coordinates: 0, 0 the image's top-left corner), seen from both sides."""
    import cv2

    directions, faces, pixels = sg.sensor_mesh(camera)
    g = np.asarray(shown)
    scale = PHOTO_MAX_SIDE / max(g.shape[:2])
    if scale < 1.0:
        g = cv2.resize(g, (max(1, round(g.shape[1] * scale)), max(1, round(g.shape[0] * scale))),
                       interpolation=cv2.INTER_AREA)
    rgb = np.repeat(g[:, :, None], 3, axis=2) if g.ndim == 2 else g[:, :, :3]
    uv = (pixels + 0.5) / np.array([camera.width, camera.height])
    return rr.Mesh3D(vertex_positions=(directions * IMAGE_PLANE_DISTANCE).astype(np.float32),
                     triangle_indices=faces.astype(np.uint32), vertex_texcoords=uv.astype(np.float32),
                     albedo_texture=np.ascontiguousarray(rgb.astype(np.uint8)), face_rendering="DoubleSided")


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
    rec.log(CATALOG, rr.Points3D(catalog.xyz.astype(np.float32), radii=catalog_radii(catalog),
                                 colors=sg.star_color(catalog.mag, catalog.bv)), static=True)
    rec.log(GRID, rr.LineStrips3D([g.astype(np.float32) for g in sg.radec_grid()], colors=C_GRID,
                                  radii=rr.Radius.ui_points(0.5)), static=True)


def catalog_radii(catalog) -> np.ndarray:
    """The radius of each catalog star on the sky (by magnitude), as `log_sky` draws it."""
    return sg.star_radius(catalog.mag, r_bright=0.007, r_faint=0.0018).astype(np.float32)


def label_sizes(texts: list[str]) -> np.ndarray:
    """(N, 2) screen width and height of Rerun labels."""
    return np.array([[LABEL_CHAR_PX * len(t) + LABEL_PAD_PX, LABEL_HEIGHT_PX] for t in texts]).reshape(-1, 2)


def rerun_label_anchor(centre: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Where to put a label's point so that Rerun (which centres a label under its point) draws its box
    centred at `centre` (screen pixels)."""
    return np.asarray(centre, dtype=np.float64) - np.stack([np.zeros(len(size)), size[:, 1] / 2 + LABEL_DROP_PX], 1)


def image_scale(camera) -> float:
    """Screen pixels per image pixel in the image view (the image fitted to IMAGE_VIEW_PX)."""
    return min(IMAGE_VIEW_PX[0] / camera.width, IMAGE_VIEW_PX[1] / camera.height)


def image_view_bounds(camera) -> np.ndarray:
    """Where the image view's labels may go, in its screen pixels (the image's corner at the origin): on
    the image, else in the margins Rerun leaves beside the fitted image (light: less readable), not over
    the view's edge. (2, 4) areas as (x0, y0, x1, y1), tried in turn."""
    s = image_scale(camera)
    w, h = camera.width * s, camera.height * s
    mx, my = (IMAGE_VIEW_PX[0] - w) / 2 - LABEL_GAP_PX, (IMAGE_VIEW_PX[1] - h) / 2 - LABEL_GAP_PX
    return np.array([[0.0, 0.0, w, h], [-mx, -my, w + mx, h + my]])


def image_labels(uv: np.ndarray, texts: list[str], priority: np.ndarray, camera, stars: np.ndarray | None = None,
                 taken: np.ndarray | None = None) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Labels beside their stars in the image view, on no other label and no star (`present.layout_labels`
    in the view's screen pixels, the brightest first; a label with no room is hidden): (K, 2) Rerun pixels
    of the points to log them on (radius 0), their texts and their (K, 4) screen boxes. stars: (M, 2) the
    other stars marked (uv); taken: screen boxes of labels placed before (an earlier call's)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros((0, 2), np.float32), [], np.zeros((0, 4))
    s = image_scale(camera)
    lay = layout_labels(rerun_uv(uv) * s, label_sizes(texts), priority, anchor_radius=IMAGE_RING_PX,
                        stars=rerun_uv(np.zeros((0, 2)) if stars is None else stars) * s, star_radius=IMAGE_RING_PX,
                        gap=LABEL_GAP_PX, apart=LABEL_APART_PX, bounds=image_view_bounds(camera), taken=taken)
    at = rerun_label_anchor(lay.centre[lay.shown], lay.size[lay.shown]) / s
    return at.astype(np.float32), [t for t, k in zip(texts, lay.shown) if k], lay.boxes()


@dataclass(frozen=True)
class SkyEye:
    """A 3-D view's opening eye (the blueprint's): at `position`, looking at `target`, `up` up; it projects
    the sky to the view's screen pixels (`view_px` wide and high, Rerun's EYE_FOV_Y) and back."""

    position: np.ndarray
    target: np.ndarray
    up: np.ndarray
    view_px: tuple[float, float] = SKY_VIEW_PX

    @classmethod
    def behind(cls, R: np.ndarray) -> SkyEye:
        """Looking out along the boresight R[2] from behind the camera, image-up (-R[1]) up."""
        R = np.asarray(R, dtype=np.float64)
        b, up = R[2], -R[1]
        return cls(EYE_BACK * b - EYE_DROP * up, b, up)

    def _axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        f = self.target - self.position
        f = f / np.linalg.norm(f)
        r = np.cross(f, self.up)
        r = r / np.linalg.norm(r)
        return f, r, np.cross(r, f), self.view_px[1] / 2.0 / math.tan(EYE_FOV_Y / 2.0)

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(N, 2) screen pixels, (N,) depths along the view and the focal length in pixels."""
        f, r, u, F = self._axes()
        W, H = self.view_px
        d = np.asarray(xyz, dtype=np.float64).reshape(-1, 3) - self.position
        z = d @ f
        with np.errstate(divide="ignore", invalid="ignore"):
            px = np.stack([W / 2 + F * (d @ r) / z, H / 2 - F * (d @ u) / z], axis=1)
        return px, z, F

    def on_sphere(self, px: np.ndarray) -> np.ndarray:
        """The points of the unit sphere seen at screen pixels `px` (the eye is inside the sphere)."""
        f, r, u, F = self._axes()
        W, H = self.view_px
        px = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        ray = f + np.outer((px[:, 0] - W / 2) / F, r) - np.outer((px[:, 1] - H / 2) / F, u)
        ray /= np.linalg.norm(ray, axis=1)[:, None]
        pe = ray @ self.position
        t = -pe + np.sqrt(pe ** 2 - (self.position @ self.position - 1.0))
        return self.position + t[:, None] * ray


def sky_labels(xyz: np.ndarray, texts: list[str], priority: np.ndarray, eye: SkyEye, stars: np.ndarray,
               star_radius: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """The sky view's labels of stars `xyz` (drawn SKY_MATCH_RADIUS wide) that fit beside them at the
    view's opening `eye` (the blueprint's), on no other label and no star `stars` (radii `star_radius`,
    world units): `present.layout_labels` in the view's screen pixels, the brightest first. Returns (K, 3)
    points of the unit sphere to log them on (radius 0) and their texts."""
    view = np.asarray(eye.view_px, dtype=np.float64)
    px, z, F = eye.project(xyz)
    inside = (z > 0.05) & np.all((px >= 0) & (px <= view), axis=1)
    sp, sz, _ = eye.project(stars)
    seen = (sz > 0.05) & np.all((sp >= -20) & (sp <= view + 20), axis=1)
    rows = np.flatnonzero(inside)
    if len(rows) == 0:
        return np.zeros((0, 3), np.float32), []
    sizes = label_sizes([texts[i] for i in rows])
    grow = SKY_MARK_GROW * F  # a sphere's mark on screen: its projected radius, widened
    lay = layout_labels(px[rows], sizes, np.asarray(priority)[rows],
                        anchor_radius=SKY_MATCH_RADIUS * grow / z[rows] + 2,
                        stars=sp[seen], star_radius=np.asarray(star_radius)[seen] * grow / sz[seen] + 2,
                        gap=LABEL_GAP_PX, apart=LABEL_APART_PX, bounds=(0.0, 0.0, view[0], view[1]))
    at = eye.on_sphere(rerun_label_anchor(lay.centre[lay.shown], lay.size[lay.shown]))
    return at.astype(np.float32), [texts[i] for i, k in zip(rows, lay.shown) if k]


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
