"""Rerun recordings (.rrd) of a solve that replay step by step.

`record_solve(path, result, image, catalog=..., truth=...)` writes one solve: the celestial sphere, the
camera at the estimated (and true) attitude, the sensor image with its centroids, every identification
step on a `step` timeline, the matches and the result. `record_case` simulates a scenario case, solves it
and records it (`skyview record`); `FailureRecorder` records the failed trials of a bench run
(`skyview bench --record-failures`); `record_examples` regenerates the example recordings
(`skyview record --examples`). Open a recording with `skyview replay FILE.rrd` (or `rerun FILE.rrd`).
Frame sequences (the stochastic method) are recorded by `skyview.record_sequence` with these helpers.

What is drawn comes from the `SolveResult` and its `Step` objects only (kind, note, observed, catalog,
groups, numbers, extra): nothing here knows a method. Entity paths (see docs/recordings.md):

    sky/catalog                 guide catalog stars (static; radius and colour from magnitude)
    sky/grid                    RA/Dec grid, 30 deg in RA, 15 deg in Dec (static)
    sky/fov/estimated           sensor footprint at the estimated attitude (static, when solved)
    sky/fov/true                sensor footprint at the true attitude (static, when known)
    sky/observed                every centroid's direction, under the shown attitude (static)
    sky/matches                 matched catalog stars, labelled "HIP n (#rank)" (static)
    sky/candidates              the step's candidate groups (pairs, triangles, ...) as great-circle arcs
    sky/step/observed           the step's observed stars (3D, under the shown attitude)
    sky/step/catalog            the step's catalog stars
    sky/step/extra/<name>       a step extra that is an (N, 3) array of unit vectors (points), or a dict
                                that outlines a region of the sky (a LineStrips3D: see below)
    camera                      camera pose: Transform3D(mat3x3=R, relation=ChildFromParent)
    camera/image                Pinhole + the sensor image (JPEG, stretched to 8 bit for display)
    camera/image/centroids      centroids, labelled with their brightness rank (#0 brightest)
    camera/image/matches        matched catalog stars reprojected with the estimated attitude
    camera/image/step           the step's observed stars in the image
    camera/image/truth/stars    where the simulator drew the catalog stars (when truth is known)
    camera/image/truth/false_stars  where it drew false stars (debris), labelled
    truth/camera                camera pose and frustum at the true attitude (when known)
    steps/log                   one TextLog entry per step: "[kind] note" (level = the step kind)
    steps/numbers/<name>        one Scalars series per `Step.numbers` entry
    steps/series/<name>         a step extra that is a 1-D float array, as a bar chart
    result                      the result as a Markdown document (static)

Step extras follow the viewer's conventions (skyview/viewer/steps.py): an (N, 3) float array of unit
vectors is points on the sphere; a 1-D float array a bar chart; a dict with "corners" ((K, 3) unit
vectors, K >= 3) a closed polygon of great-circle arcs, or else with "center" (a unit 3-vector) and
"radius_rad" the small circle at that angular radius (`sky_geometry.outline_polyline`; a GA's search
box), logged as one closed line strip when it changes and cleared at a step without it; anything else
is left out.

"The shown attitude" is the estimated attitude when the image was solved, else the true one when it is
known; without either, the 3D view has no observed stars (the image still has them).

Pixel coordinates: skyview puts pixel centres at integers, Rerun at half-integers (its pixel (0, 0)
spans [0, 1]), so every 2-D position and the principal point are shifted by +0.5 here.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from skyview import sky_geometry as sg
from skyview.attitude import attitude_error_arcsec, radec_roll_from_R, random_attitudes
from skyview.errors import BadInput

APP_ID = "skyview"
TIMELINE = "step"
JPEG_QUALITY = 85
ARC_POINTS = 8  # points per great-circle arc of a candidate group
PIXEL_OFFSET = 0.5  # skyview pixel centre (integer) -> Rerun pixel centre (half-integer)
MAX_SHOWN_LABELS = 12  # more match labels than this in the 3D view overlap: they show on hover instead
IMAGE_PLANE_DISTANCE = 1.03  # where the sensor image sits in 3D: just behind the stars on the unit sphere

# Entity paths (kept in one place: the tests and the docs read them from here).
CATALOG = "sky/catalog"
GRID = "sky/grid"
FOV_ESTIMATED = "sky/fov/estimated"
FOV_TRUE = "sky/fov/true"
OBSERVED = "sky/observed"
MATCHES = "sky/matches"
CANDIDATES = "sky/candidates"
STEP_OBSERVED = "sky/step/observed"
STEP_CATALOG = "sky/step/catalog"
STEP_EXTRA = "sky/step/extra"
CAMERA = "camera"
IMAGE = "camera/image"
CENTROIDS = "camera/image/centroids"
IMAGE_MATCHES = "camera/image/matches"
IMAGE_STEP = "camera/image/step"
TRUTH_STARS = "camera/image/truth/stars"
TRUTH_FALSE_STARS = "camera/image/truth/false_stars"
TRUE_CAMERA = "truth/camera"
STEP_LOG = "steps/log"
STEP_NUMBERS = "steps/numbers"
STEP_SERIES = "steps/series"
RESULT = "result"

# Colours (RGB)
C_GRID = (60, 70, 90)
C_FOV_EST = (255, 200, 0)
C_FOV_TRUE = (80, 220, 120)
C_OBSERVED = (0, 200, 255)
C_MATCH = (255, 120, 255)
C_CANDIDATE = (60, 255, 140)
C_STEP_OBS = (255, 230, 0)
C_STEP_CAT = (255, 80, 80)
C_EXTRA = (255, 150, 40)
C_OUTLINE = (190, 140, 255)  # a step's outlined region of the sky (a GA's search box), lavender
C_CENTROID = (255, 60, 60)
C_TRUTH = (80, 220, 120)
C_FALSE = (255, 150, 0)

# The default scenario of each method: its paper's conditions (used by --examples).
EXAMPLE_SCENARIOS = {"angle": "cole8", "triangle": "cole8", "svd": "juang8", "ellipticity": "sun20", "genetic": "sun20"}
# Sequence methods: their example is the paper's frame sequence (skyview.record_sequence), on this scenario.
SEQUENCE_EXAMPLES = {"stochastic": "udomkesmalee30"}
# The failure example: the paper variant of this method on this scenario, first seed that ends inconclusive.
FAILURE_EXAMPLE = ("angle", "cole8-false")
EXAMPLE_SEED_START = 1
EXAMPLE_SEED_TRIES = 40
MANIFEST = "index.json"


@dataclass
class RecordInfo:
    """What `record_solve` wrote."""

    path: Path
    bytes: int
    write_ms: float  # building and writing the recording (the solve not included)
    steps: int  # entries on the `step` timeline
    status: str

    def to_dict(self) -> dict:
        d = asdict(self)
        d["path"] = str(self.path)
        return d


# ============================================================================ paths

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


def _temp_path(p: Path) -> Path:
    return p.with_name(f".{p.name}.tmp{os.getpid()}.rrd")


# ============================================================================ drawing helpers

def display_image(image: np.ndarray) -> tuple[np.ndarray, str]:
    """8-bit view of a sensor image for display, and a sentence saying how it was made.

    An asinh stretch from just above the background (median + 2 sigma, sigma from the MAD) to the
    brightest pixel, with a softening of 3 sigma: faint stars stay visible, bright ones do not
    saturate, and the flat background maps to black (so the JPEG stays small). Used for 8- and 16-bit
    images alike; the solve itself always uses the raw image.
    """
    a = np.asarray(image)
    if a.ndim != 2:
        raise BadInput(f"expected a single-channel image, got shape {a.shape}")
    sample = a[::4, ::4].astype(np.float64)
    med = float(np.median(sample))
    sigma = 1.4826 * float(np.median(np.abs(sample - med)))
    sigma = max(sigma, 1.0 if np.issubdtype(a.dtype, np.integer) else 1e-6)
    lo = med + 2.0 * sigma
    hi = float(a.max())
    soft = 3.0 * sigma
    if hi <= lo:
        out = np.zeros(a.shape, dtype=np.uint8)
    else:
        x = np.clip(a.astype(np.float32) - np.float32(lo), 0, None) / np.float32(soft)
        out = (np.arcsinh(x) * np.float32(255.0 / math.asinh((hi - lo) / soft)) + 0.5).astype(np.uint8)
    bits = f"{a.dtype.itemsize * 8}-bit" if np.issubdtype(a.dtype, np.integer) else str(a.dtype)
    how = (f"{bits} image shown with an asinh stretch to 8 bit (black at median + 2 sigma = {lo:.1f}, "
           f"softening 3 sigma = {soft:.1f}, white at the maximum {hi:.0f}); JPEG quality {JPEG_QUALITY}")
    return out, how


def _arc_strips(xyz: np.ndarray, groups) -> np.ndarray:
    """(E, ARC_POINTS, 3): one great-circle polyline per edge of every group (catalog rows into xyz).

    One 3-D array rather than a list of strips: rerun-sdk converts it in one go (a list is ~20x slower)."""
    segs = sg.group_segments(xyz, groups, ARC_POINTS)
    if len(segs) == 0:
        return np.zeros((0, ARC_POINTS, 3), dtype=np.float32)
    segs = segs.reshape(-1, ARC_POINTS - 1, 2, 3)
    return np.concatenate([segs[:, :, 0], segs[:, -1:, 1]], axis=1).astype(np.float32)


def _rerun_uv(uv: np.ndarray) -> np.ndarray:
    return (np.asarray(uv, dtype=np.float64).reshape(-1, 2) + PIXEL_OFFSET).astype(np.float32)


def _pinhole(camera, color=None) -> list:
    """Intrinsics (principal point moved to Rerun's pixel convention), RDF = OpenCV camera axes; the
    camera-axis arrows the viewer would draw at the pinhole are switched off (they would cross the sky)."""
    K = camera.K.copy()
    K[0, 2] += PIXEL_OFFSET
    K[1, 2] += PIXEL_OFFSET
    return [rr.Pinhole(image_from_camera=K, resolution=[camera.width, camera.height],
                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=IMAGE_PLANE_DISTANCE,
                       color=color, line_width=0.0002),
            rr.TransformAxes3D(axis_length=0.0)]


def _pose(R: np.ndarray) -> rr.Transform3D:
    """v_cam = R @ v_icrs: R maps the parent (ICRS) into the child (camera)."""
    return rr.Transform3D(mat3x3=np.asarray(R, dtype=np.float32), relation=rr.TransformRelation.ChildFromParent)


def _unit_rows(a: Any) -> np.ndarray | None:
    """`a` as an (N, 3) float array of unit vectors, or None when it is not one."""
    if not isinstance(a, np.ndarray) or a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
        return None
    if not np.issubdtype(a.dtype, np.floating) or not np.all(np.isfinite(a)):
        return None
    if np.abs(np.linalg.norm(a, axis=1) - 1.0).max() > 1e-3:
        return None
    if a.shape == (3, 3) and np.allclose(a @ a.T, np.eye(3), atol=1e-3):
        return None  # a rotation (attitude) matrix, not a set of directions
    return a.astype(np.float32)


def _series(a: Any) -> np.ndarray | None:
    """`a` as a 1-D float series (a posterior, costs, ...), or None."""
    if isinstance(a, (list, tuple)):
        a = np.asarray(a)
    if not isinstance(a, np.ndarray) or a.ndim != 1 or len(a) == 0 or not np.issubdtype(a.dtype, np.floating):
        return None
    return np.nan_to_num(a.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)


def _has_hip(catalog, hip: int) -> bool:
    try:
        catalog.index_of(hip)
    except KeyError:
        return False
    return True


def _entity_name(name: str) -> str:
    keep = "".join(ch if ch.isalnum() or ch in "_-." else "_" for ch in str(name))
    return keep or "_"


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


# ============================================================================ the result document

def result_markdown(result, *, truth: dict | None = None, meta: dict | None = None,
                    image_note: str = "", wrong: list[int] | None = None) -> str:
    """The result as Markdown: status, attitude, sigma, error against truth, time per stage."""
    d = result.to_dict()
    lines = [f"# {result.method} ({result.variant}): {result.status}", ""]
    if result.reason:
        lines += [f"**Reason:** {result.reason}", ""]
    if meta:
        lines += ["| | |", "|---|---|"] + [f"| {k} | {_fmt(v)} |" for k, v in meta.items()] + [""]
    if result.R is not None:
        s = d["sigma_arcsec"]
        q = d["quaternion"]
        lines += [
            "## Attitude (estimated)", "",
            f"- RA **{d['ra_deg']:.5f}°**, Dec **{d['dec_deg']:+.5f}°**, roll **{d['roll_deg']:+.4f}°**",
            f"- quaternion [w x y z]: {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}",
            f"- 1-sigma: boresight {s['boresight']:.2f}\", roll {s['roll']:.1f}\"",
            "",
        ]
    ident = result.identification
    lines += ["## Identification", "",
              f"- {len(result.centroids)} centroids, {len(result.matches)} matched"
              + (f", {len(ident.steps)} steps, status {ident.status}" if ident else "")]
    if ident and ident.verification:
        v = ident.verification
        keys = [k for k in ("n_agree", "n_tested", "p_false", "threshold_effective") if k in v]
        if keys:
            lines.append("- verification: " + ", ".join(f"{k} {_fmt(v[k])}" for k in keys))
    if result.matches:
        lines += ["", "| # | u | v | HIP | Hp | residual (\") |", "|---|---|---|---|---|---|"]
        lines += [f"| {m['index']} | {m['u']:.2f} | {m['v']:.2f} | {m['hip']} | {m['mag']:.2f} | "
                  f"{m.get('residual_arcsec', float('nan')):.2f} |" for m in result.matches]
    if truth is not None:
        ra, dec, roll = radec_roll_from_R(np.asarray(truth["R"], dtype=float))
        lines += ["", "## Truth", "",
                  f"- RA {math.degrees(ra):.5f}°, Dec {math.degrees(dec):+.5f}°, roll {math.degrees(roll):+.4f}°",
                  f"- {len(truth.get('stars', []))} catalog stars and {len(truth.get('false_stars', []))} "
                  f"false stars drawn"]
        if result.R is not None:
            e = attitude_error_arcsec(result.R, np.asarray(truth["R"], dtype=float))
            lines.append(f"- error: boresight **{e['boresight']:.2f}\"** (cross x {e['cross_x']:.2f}\", "
                         f"y {e['cross_y']:.2f}\"), roll **{e['roll']:.1f}\"**")
        if wrong is not None:
            lines.append(f"- wrong matches: **{len(wrong)}**" + (f" (#{', #'.join(map(str, wrong))})" if wrong else ""))
    lines += ["", "## Time per stage (ms)", "", "| stage | ms |", "|---|---|"]
    lines += [f"| {k} | {v:.2f} |" for k, v in result.time_ms.items()]
    if image_note:
        lines += ["", f"*Image:* {image_note}."]
    if result.database_key:
        lines += ["", "*Database key:* `" + json.dumps(result.database_key, sort_keys=True) + "`"]
    return "\n".join(lines) + "\n"


# ============================================================================ the blueprint

NO_AXES = rrb.SpatialInformation(target_frame="tf#/", show_axes=False, show_bounding_box=False)  # no origin arrows


def blueprint(R_view: np.ndarray | None, series: list[str]) -> rrb.Blueprint:
    """3D sky (looking out along the boresight from behind the camera), the image with its centroids,
    the step numbers plotted over the step timeline, the step log and the result."""
    eye = None
    if R_view is not None:
        b, up = R_view[2], -R_view[1]
        eye = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=(0.45 * b - 0.03 * up).tolist(),
                                look_target=b.tolist(), eye_up=up.tolist())
    sky = rrb.Spatial3DView(name="sky", origin="/", contents=["/sky/**", "/camera/**", "/truth/**"],
                            background=[5, 8, 16], line_grid=rrb.LineGrid3D(visible=False), eye_controls=eye,
                            spatial_information=NO_AXES)
    tabs = [rrb.TextLogView(name="step log", origin=f"/{STEP_LOG}"),
            rrb.TextDocumentView(name="result", origin=f"/{RESULT}")]
    tabs += [rrb.BarChartView(name=name, origin=f"/{STEP_SERIES}/{name}") for name in series]
    right = rrb.Vertical(
        rrb.Spatial2DView(name="image", origin=f"/{IMAGE}"),
        rrb.TimeSeriesView(name="step numbers", origin=f"/{STEP_NUMBERS}", plot_legend=rrb.Corner2D.RightTop),
        rrb.Tabs(*tabs, active_tab=0),
        row_shares=[5, 3, 3])
    return rrb.Blueprint(rrb.Horizontal(sky, right, column_shares=[3, 2]),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed", timeline=TIMELINE))


# ============================================================================ writing

def record_solve(path: str | os.PathLike, result, image: np.ndarray, *, catalog, truth: dict | None = None,
                 force: bool = False, meta: dict | None = None, name: str | None = None) -> RecordInfo:
    """Write `result` (a pipeline.SolveResult of `image`) as a Rerun recording at `path`.

    catalog: the guide catalog the solver used (`Solver.catalog`: step groups and matches are rows of
    it). truth: the simulator's truth dict when known (true attitude, drawn stars, false stars).
    meta: extra key/values for the result document (scenario, seed, image file, ...). The file is
    written next to `path` and moved into place only when complete: nothing is overwritten unless
    `force`, and a failed write leaves nothing behind. Raises BadInput for a bad path.
    """
    t0 = time.perf_counter()
    p = check_output_path(path, force)
    image = np.asarray(image)
    camera = result.camera
    if image.shape != (camera.height, camera.width):
        raise BadInput(f"image is {image.shape[1]}x{image.shape[0]} but the result's camera is "
                       f"{camera.width}x{camera.height}")
    missing = [m["hip"] for m in result.matches if not _has_hip(catalog, m["hip"])]
    if missing:
        raise BadInput(f"the catalog given ({len(catalog)} stars) lacks matched star(s) HIP "
                       f"{', '.join(map(str, missing[:5]))}: it is not the one the solver used (pass Solver.catalog)")
    R_est = None if result.R is None else np.asarray(result.R, dtype=np.float64)
    R_true = None if truth is None else np.asarray(truth["R"], dtype=np.float64)
    R_view = R_est if R_est is not None else R_true
    ident = result.identification
    steps = list(ident.steps) if ident else []
    series = sorted({_entity_name(k) for s in steps for k, v in s.extra.items() if _series(v) is not None})
    wrong = None
    if truth is not None:
        from skyview.bench import score_trial  # scoring against truth lives with the bench

        wrong = score_trial(result, truth)[1]

    title = name or p.stem
    # the same solve of the same image gets the same id (reproducible); different ones never merge in a viewer
    digest = hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()
    rec_id = str(uuid.uuid5(uuid.NAMESPACE_URL, f"skyview:{title}:{result.method}:{result.variant}:{digest}"))
    with open_recording(p, rec_id, title, blueprint(R_view, series)) as rec:
        image_note = _write_static(rec, result, image, catalog, truth, R_est, R_true, R_view)
        _write_steps(rec, steps, result, catalog, R_view)
        rec.log(RESULT, rr.TextDocument(result_markdown(result, truth=truth, meta=meta, image_note=image_note,
                                                        wrong=wrong), media_type=rr.MediaType.MARKDOWN),
                static=True)
    return RecordInfo(path=p, bytes=p.stat().st_size, write_ms=(time.perf_counter() - t0) * 1e3,
                      steps=len(steps), status=result.status)


@contextmanager
def open_recording(p: Path, rec_id: str, title: str, bp: rrb.Blueprint) -> Iterator[rr.RecordingStream]:
    """A recording stream that writes `p` (already checked with `check_output_path`): into a file beside
    it, moved into place only when the block completes; a failure leaves nothing behind. No wall-clock
    column: the same inputs give the same contents. OSError becomes a one-line BadInput."""
    tmp = _temp_path(p)
    try:
        # create the file ourselves first: a permission or path problem surfaces here as an OSError
        with open(tmp, "xb"):
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


def _write_static(rec, result, image, catalog, truth, R_est, R_true, R_view) -> str:
    camera = result.camera
    # --- the celestial sphere
    radii = sg.star_radius(catalog.mag, r_bright=0.007, r_faint=0.0018).astype(np.float32)
    rec.log(CATALOG, rr.Points3D(catalog.xyz.astype(np.float32), radii=radii,
                                 colors=sg.star_color(catalog.mag, catalog.bv)), static=True)
    rec.log(GRID, rr.LineStrips3D([g.astype(np.float32) for g in sg.radec_grid()], colors=C_GRID,
                                  radii=rr.Radius.ui_points(0.5)), static=True)
    if R_est is not None:
        rec.log(FOV_ESTIMATED, rr.LineStrips3D([sg.sensor_footprint(camera, R_est).astype(np.float32)],
                                               colors=C_FOV_EST, radii=rr.Radius.ui_points(1.5)), static=True)
    if R_true is not None:
        rec.log(FOV_TRUE, rr.LineStrips3D([sg.sensor_footprint(camera, R_true).astype(np.float32)],
                                          colors=C_FOV_TRUE, radii=rr.Radius.ui_points(1.0)), static=True)
    # --- the camera: pose, intrinsics, image
    if R_view is not None:
        rec.log(CAMERA, _pose(R_view), static=True)
    rec.log(IMAGE, *_pinhole(camera, color=C_FOV_EST), static=True)
    if R_true is not None:
        rec.log(TRUE_CAMERA, _pose(R_true), static=True)
        rec.log(TRUE_CAMERA, *_pinhole(camera, color=C_FOV_TRUE), static=True)
    shown, note = display_image(image)
    rec.log(IMAGE, rr.Image(shown, color_model="L").compress(jpeg_quality=JPEG_QUALITY), static=True)
    cents = result.centroids
    n = len(cents)
    if n:
        rec.log(CENTROIDS, rr.Points2D(_rerun_uv(cents.uv), radii=rr.Radius.ui_points(4.0), colors=C_CENTROID,
                                       labels=[f"#{k}" for k in range(n)], show_labels=True, draw_order=20),
                static=True)
        if R_view is not None:
            v = camera.unproject(cents.uv) @ R_view  # v_icrs = R^T v_cam
            rec.log(OBSERVED, rr.Points3D(v.astype(np.float32), radii=0.004, colors=C_OBSERVED,
                                          labels=[f"#{k}" for k in range(n)], show_labels=False), static=True)
    # --- the matches
    if result.matches:
        rows = np.array([catalog.index_of(m["hip"]) for m in result.matches])
        labels = [f"HIP {m['hip']} (#{m['index']})" for m in result.matches]
        rec.log(MATCHES, rr.Points3D(catalog.xyz[rows].astype(np.float32), radii=0.006, colors=C_MATCH,
                                     labels=labels, show_labels=len(labels) <= MAX_SHOWN_LABELS), static=True)
        uv, _ = camera.project(catalog.xyz[rows] @ R_est.T)
        rec.log(IMAGE_MATCHES, rr.Points2D(_rerun_uv(uv), radii=rr.Radius.ui_points(7.0), colors=C_MATCH + (110,),
                                           labels=[f"HIP {m['hip']}" for m in result.matches], show_labels=False,
                                           draw_order=10), static=True)
    # --- where the simulator drew stars
    if truth is not None:
        stars = truth.get("stars", [])
        if stars:
            uv = np.array([[s["u_noisy"], s["v_noisy"]] for s in stars])
            rec.log(TRUTH_STARS, rr.Points2D(_rerun_uv(uv), radii=rr.Radius.ui_points(10.0), colors=C_TRUTH + (60,),
                                             labels=[f"HIP {s['hip']}" for s in stars], show_labels=False,
                                             draw_order=5), static=True)
        false = truth.get("false_stars", [])
        if false:
            uv = np.array([[f["u"], f["v"]] for f in false])
            rec.log(TRUTH_FALSE_STARS, rr.Points2D(_rerun_uv(uv), radii=rr.Radius.ui_points(10.0),
                                                   colors=C_FALSE + (140,), labels=["false star"] * len(false),
                                                   show_labels=True, draw_order=6), static=True)
    return note


def _write_steps(rec, steps, result, catalog, R_view, first: int = 0,
                 shown: tuple[set[str], set[str]] | None = None) -> tuple[set[str], set[str]]:
    """Log `steps` at step numbers first, first + 1, ... (`result`: anything with .camera and .centroids).
    shown: the extras and series drawn by the step before `first` (cleared when a step lacks them);
    returns those of the last step, for the next call."""
    camera = result.camera
    cents = result.centroids
    obs_icrs = camera.unproject(cents.uv) @ R_view if (R_view is not None and len(cents)) else None
    shown_extra, shown_series = (set(), set()) if shown is None else (set(shown[0]), set(shown[1]))
    outlines: dict[str, tuple] = {}  # per extra name: (the dict, its outline) last drawn, in this call
    for k, step in enumerate(steps, start=first):
        rec.set_time(TIMELINE, sequence=k)
        rec.log(STEP_LOG, rr.TextLog(f"[{step.kind}] {step.note}", level=step.kind))
        for name, value in step.numbers.items():
            if value is None:
                continue
            try:
                x = float(value)
            except (TypeError, ValueError):
                continue
            if math.isfinite(x):
                rec.log(f"{STEP_NUMBERS}/{_entity_name(name)}", rr.Scalars(x))
        # candidate groups: great-circle arcs on the sphere (replaced every step, empty when none)
        rows = [g for g in step.groups if all(0 <= int(i) < len(catalog) for i in g)]
        rec.log(CANDIDATES, rr.LineStrips3D(_arc_strips(catalog.xyz, rows), colors=C_CANDIDATE,
                                            radii=rr.Radius.ui_points(1.0)))
        obs = [int(i) for i in step.observed if 0 <= int(i) < len(cents)]
        labels = [f"#{i}" for i in obs]
        rec.log(IMAGE_STEP, rr.Points2D(_rerun_uv(cents.uv[obs]) if obs else np.zeros((0, 2), np.float32),
                                        radii=rr.Radius.ui_points(9.0), colors=C_STEP_OBS + (170,), labels=labels,
                                        show_labels=False, draw_order=15))
        if obs_icrs is not None:
            rec.log(STEP_OBSERVED, rr.Points3D(obs_icrs[obs].astype(np.float32).reshape(-1, 3), radii=0.008,
                                               colors=C_STEP_OBS, labels=labels, show_labels=True))
        cat = [int(i) for i in step.catalog if 0 <= int(i) < len(catalog)]
        rec.log(STEP_CATALOG, rr.Points3D(catalog.xyz[cat].astype(np.float32).reshape(-1, 3), radii=0.005,
                                          colors=C_STEP_CAT))
        # method-specific extras: (N, 3) unit vectors as points, outlines as line strips, 1-D floats as bar charts
        now_extra, now_series = set(), set()
        for name, value in step.extra.items():
            ename = _entity_name(name)
            last = outlines.get(ename)
            if isinstance(value, dict) and ename in shown_extra and last is not None and last[0] is value:
                now_extra.add(ename)  # the same dict as the step before (a GA stage's box): drawn already
                continue
            poly = sg.outline_polyline(value)
            if poly is not None:
                poly = poly.astype(np.float32)
                if ename in shown_extra and last is None:  # points at the step before: not under the outline
                    rec.log(f"{STEP_EXTRA}/{ename}", rr.Clear(recursive=False))
                if ename not in shown_extra or last is None or not np.array_equal(last[1], poly):
                    rec.log(f"{STEP_EXTRA}/{ename}", rr.LineStrips3D(poly[None], colors=C_OUTLINE,
                                                                     radii=rr.Radius.ui_points(1.5)))
                outlines[ename] = (value, poly)  # an unchanged outline is not logged again
                now_extra.add(ename)
                continue
            was_outline = outlines.pop(ename, None) is not None
            pts = _unit_rows(value)
            if pts is not None:
                if was_outline and ename in shown_extra:  # an outline at the step before: not under the points
                    rec.log(f"{STEP_EXTRA}/{ename}", rr.Clear(recursive=False))
                rec.log(f"{STEP_EXTRA}/{ename}", rr.Points3D(pts, radii=0.004, colors=C_EXTRA))
                now_extra.add(ename)
                continue
            s = _series(value)
            if s is not None:
                rec.log(f"{STEP_SERIES}/{ename}", rr.BarChart(s))
                now_series.add(ename)
        for ename in shown_extra - now_extra:  # an extra drawn at the previous step but not at this one
            rec.log(f"{STEP_EXTRA}/{ename}", rr.Clear(recursive=False))
            outlines.pop(ename, None)
        for ename in shown_series - now_series:
            rec.log(f"{STEP_SERIES}/{ename}", rr.Clear(recursive=False))
        shown_extra, shown_series = now_extra, now_series
    return shown_extra, shown_series


# ============================================================================ simulated cases

def case_attitude(seed: int) -> np.ndarray:
    """The attitude of case `seed`: uniform on SO(3), drawn from numpy's Generator(seed)."""
    return random_attitudes(1, np.random.default_rng(int(seed)))[0]


@dataclass
class Case:
    """One simulated, solved case."""

    method: str
    variant: str
    scenario: str
    seed: int
    frame: Any  # simulate.SimulatedFrame
    result: Any  # pipeline.SolveResult
    solver: Any  # pipeline.Solver
    outcome: str  # correct | inconclusive | incorrect (bench.score_trial)
    meta: dict = field(default_factory=dict)


class CaseRunner:
    """Simulates and solves cases of one method / variant / scenario, keeping the solver loaded."""

    def __init__(self, method: str, scenario: str, variant: str = "paper", catalog=None):
        from skyview.catalog import load_guide_catalog
        from skyview.identify import METHODS
        from skyview.pipeline import Solver
        from skyview.scenarios import get_scenario

        if method not in METHODS:
            raise BadInput(f"unknown method {method!r}: choose from {', '.join(METHODS)}")
        self.scenario = get_scenario(scenario)
        self.method, self.variant = method, variant
        self.catalog = catalog if catalog is not None else load_guide_catalog()
        self.camera = self.scenario.camera()
        self.solver = Solver(self.camera, method, mag_limit=self.scenario.mag_limit, sigma_rad=self.scenario.sigma_rad,
                             catalog=self.catalog, variant=variant, max_stars=self.scenario.max_stars)

    def run(self, seed: int) -> Case:
        from skyview.bench import score_trial
        from skyview.simulate import SensorModel, simulate_image

        sc = self.scenario
        t0 = time.perf_counter()
        frame = simulate_image(self.catalog, self.camera, case_attitude(seed), SensorModel(), seed=int(seed),
                               mag_limit=sc.mag_limit, n_false_stars=sc.n_false_stars,
                               false_star_placement=sc.false_star_placement, position_noise_rad=sc.noise_rad)
        sim_ms = (time.perf_counter() - t0) * 1e3
        result = self.solver.solve_array(frame.image)
        outcome, _ = score_trial(result, frame.truth)
        meta = {"method": self.method, "variant": self.variant, "scenario": f"{sc.name}: {sc.description}",
                "seed": int(seed), "outcome against truth": outcome,
                "stars drawn": len(frame.truth["stars"]), "simulate ms": round(sim_ms, 2),
                "remake": f"skyview record --method {self.method} --variant {self.variant} "
                          f"--scenario {sc.name} --seed {int(seed)}"}
        return Case(self.method, self.variant, sc.name, int(seed), frame, result, self.solver, outcome, meta)

    def record(self, case: Case, path: str | os.PathLike, force: bool = False) -> RecordInfo:
        return record_solve(path, case.result, case.frame.image, catalog=self.solver.catalog,
                            truth=case.frame.truth, force=force, meta=case.meta)


def record_case(path: str | os.PathLike, method: str, scenario: str, seed: int, *, variant: str = "paper",
                force: bool = False, catalog=None) -> tuple[RecordInfo, Case]:
    """Simulate case `seed` of `scenario`, solve it with `method` and record it at `path`."""
    check_output_path(path, force)  # fail before the slow part
    runner = CaseRunner(method, scenario, variant, catalog)
    case = runner.run(seed)
    return runner.record(case, path, force), case


# ============================================================================ bench failures

class FailureRecorder:
    """`run_bench(on_trial=...)` callback: one recording per trial that is not correct.

    Files are `<folder>/<method>-<variant>-<scenario>-seed<bench seed>-trial<k>-<outcome>.rrd`; an existing
    name gets a -2, -3, ... suffix (nothing is overwritten). The trial dict gains a "recording" entry.
    """

    def __init__(self, folder: str | os.PathLike, *, method: str, variant: str, scenario: str, seed: int):
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise BadInput(f"{self.folder} is not a folder")
        if not self.folder.parent.is_dir():
            raise BadInput(f"folder {self.folder.parent} does not exist")
        try:
            self.folder.mkdir(exist_ok=True)
        except OSError as exc:
            raise BadInput(f"cannot create the folder {self.folder}: {exc.strerror}") from None
        if not os.access(self.folder, os.W_OK | os.X_OK):
            raise BadInput(f"cannot write into {self.folder}: permission denied")
        self.stem = f"{method}-{variant}-{scenario}-seed{seed}"
        self.scenario = scenario
        self.bench_seed = seed
        self.written: list[RecordInfo] = []

    def __call__(self, trial: dict, frame, result, solver) -> None:
        if trial["outcome"] == "correct":
            return
        base = f"{self.stem}-trial{trial['trial']:04d}-{trial['outcome']}"
        p, k = self.folder / f"{base}.rrd", 1
        while p.exists():
            k += 1
            p = self.folder / f"{base}-{k}.rrd"
        meta = {"method": result.method, "variant": result.variant, "scenario": self.scenario,
                "bench seed": self.bench_seed, "trial": trial["trial"], "image seed": trial["seed"],
                "outcome against truth": trial["outcome"]}
        info = record_solve(p, result, frame.image, catalog=solver.catalog, truth=frame.truth, meta=meta)
        trial["recording"] = str(p)
        self.written.append(info)


# ============================================================================ examples

def record_examples(out_dir: str | os.PathLike = "recordings", *, force: bool = False, say=print) -> list[dict]:
    """Regenerate the example recordings: every method in METHODS on its paper's scenario (the first seed
    from EXAMPLE_SEED_START that it solves correctly; a sequence method, SEQUENCE_EXAMPLES, records its
    paper's frame sequence, `record_sequence.record_example`), and one failure case (FAILURE_EXAMPLE, paper
    variant: the first seed that ends inconclusive with at least 6 stars drawn and the false star among
    the observed stars its steps used). Writes
    `<method>-<scenario>.rrd`, `failure-<method>-<scenario>.rrd` and a manifest `index.json`."""
    from skyview.catalog import load_guide_catalog
    from skyview.identify import METHODS
    from skyview.scenarios import SCENARIOS

    out = Path(out_dir)
    if not out.is_dir():
        raise BadInput(f"folder {out} does not exist")
    plan: list[tuple[str, str, bool]] = []
    for method in METHODS:
        scenario = SEQUENCE_EXAMPLES.get(method, EXAMPLE_SCENARIOS.get(method))
        if scenario is None:
            say(f"skipped {method}: no default scenario for it in skyview.record.EXAMPLE_SCENARIOS")
        elif scenario not in SCENARIOS:
            say(f"skipped {method}: its scenario {scenario!r} does not exist yet")
        else:
            plan.append((method, scenario, False))
    fm, fs = FAILURE_EXAMPLE
    if fm in METHODS and fs in SCENARIOS:
        plan.append((fm, fs, True))
    else:
        say(f"skipped the failure example: method {fm!r} or scenario {fs!r} is missing")
    names = [f"{'failure-' if fail else ''}{m}-{s}.rrd" for m, s, fail in plan]
    for name in names:
        check_output_path(out / name, force)
    if (out / MANIFEST).exists() and not force:
        raise BadInput(f"{out / MANIFEST} exists; use --force to overwrite it")
    catalog = load_guide_catalog()
    entries = []
    for (method, scenario, fail), name in zip(plan, names):
        if method in SEQUENCE_EXAMPLES and not fail:  # a sequence: the paper's experiment, frame by frame
            from skyview.record_sequence import record_example

            entry = record_example(out / name, scenario=scenario, catalog=catalog, force=force)
            if entry is None:
                say(f"skipped {name}: no seed in {EXAMPLE_SEED_START}..{EXAMPLE_SEED_START + EXAMPLE_SEED_TRIES - 1} "
                    f"identifies its last frame")
                continue
            entries.append(entry)
            say(f"wrote {out / name}: {entry['status']} (seed {entry['seed']}), {entry['frames']} frames identified at "
                f"{entry['identified_frames']}, {entry['steps']} steps, {entry['bytes'] / 1e6:.2f} MB in "
                f"{entry['write_ms']:.0f} ms")
            continue
        runner = CaseRunner(method, scenario, "paper", catalog)
        chosen = None
        for seed in range(EXAMPLE_SEED_START, EXAMPLE_SEED_START + EXAMPLE_SEED_TRIES):
            case = runner.run(seed)
            if fail:
                good = _false_star_failure(case)
            else:
                good = case.outcome == "correct"
            if good:
                chosen = case
                break
        if chosen is None:
            last = EXAMPLE_SEED_START + EXAMPLE_SEED_TRIES - 1
            say(f"skipped {name}: no suitable seed in {EXAMPLE_SEED_START}..{last}")
            continue
        info = runner.record(chosen, out / name, force=force)
        entry = {"file": name, "method": method, "variant": "paper", "scenario": scenario, "seed": chosen.seed,
                 "status": chosen.result.status, "outcome": chosen.outcome,
                 "reason": chosen.result.reason, "steps": info.steps, "bytes": info.bytes,
                 "write_ms": round(info.write_ms, 1), "solve_ms": round(chosen.result.time_ms.get("total", 0.0), 1)}
        entries.append(entry)
        say(f"wrote {out / name}: {chosen.result.status} (seed {chosen.seed}), {info.steps} steps, "
            f"{info.bytes / 1e6:.2f} MB in {info.write_ms:.0f} ms")
    manifest = {"command": "skyview record --examples --force", "files": entries}
    tmp = out / f".{MANIFEST}.tmp{os.getpid()}"
    try:
        tmp.write_text(json.dumps(manifest, indent=1) + "\n")
        os.replace(tmp, out / MANIFEST)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise BadInput(f"cannot write {out / MANIFEST}: {exc.strerror}") from None
    return entries


def _false_star_failure(case: Case) -> bool:
    """Inconclusive, with at least 6 stars drawn, and a false star among the observed stars the steps used."""
    ident = case.result.identification
    if ident is None or ident.status != "inconclusive" or len(case.frame.truth["stars"]) < 6:
        return False
    uv = case.result.centroids.uv
    used = {int(i) for s in ident.steps for i in s.observed}
    for f in case.frame.truth["false_stars"]:
        if len(uv):
            d = np.hypot(uv[:, 0] - f["u"], uv[:, 1] - f["v"])
            if d.min() < 3.0 and int(np.argmin(d)) in used:
                return True
    return False


def read_manifest(out_dir: str | os.PathLike = "recordings") -> dict:
    return json.loads((Path(out_dir) / MANIFEST).read_text())


__all__ = ["record_solve", "record_case", "record_examples", "check_output_path", "display_image",
           "result_markdown", "blueprint", "CaseRunner", "Case", "FailureRecorder", "RecordInfo", "case_attitude",
           "read_manifest"]
