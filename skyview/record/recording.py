"""Rerun recordings (.rrd) of one solve that replay step by step.

`record_solve(path, result, image, catalog=..., truth=...)` writes one solve: the celestial sphere, the
camera at the estimated (and true) attitude, the sensor image with its centroids, every identification
step on a `step` timeline and the result. It only renders: what a step shows is `skyview.present.drawables`'s
`StepView` (the viewer draws the same), scoring against the truth is `skyview.simulate.scoring`'s. Simulated
cases, bench failures and the examples are `skyview.record.cases` and `skyview.record.examples`; frame
sequences `skyview.record.sequence`. Open a recording with `skyview replay FILE.rrd`.

Entity paths (see docs/recordings.md; constants in `skyview.record.draw`):

    sky/catalog                 guide catalog stars (static; radius and colour from magnitude)
    sky/grid                    RA/Dec grid, 30 deg in RA, 15 deg in Dec (static)
    sky/fov/estimated           sensor footprint at the estimated attitude (static, when solved)
    sky/fov/true                sensor footprint at the true attitude (static, when known)
    sky/observed                every centroid's direction, under the shown attitude (static)
    sky/step/<role>             the step's sky roles: candidates (arcs of the surviving hypotheses),
                                candidate_stars, points (a GA population, a posterior's stars),
                                attitudes (footprints), outline (the region searched)
    sky/matches                 the identified stars, from the last step on
    sky/matches/labels          their HIP labels beside them: those that collide with no label and no star at
                                the sky view's opening eye (the rest are on the image)
    camera                      camera pose: Transform3D(mat3x3=R, relation=ChildFromParent)
    camera/image                Pinhole + the sensor image (JPEG, the viewer's stretch)
    camera/photo                a fisheye's image in 3-D: the sensor's mesh textured with it (no Pinhole holds it)
    camera/image/centroids      centroids (static), labelled with their brightness rank (#0 brightest)
    camera/image/step/<role>    the stars the step measured (observed, pattern) and those measured before (known)
    camera/image/matches        matched catalog stars reprojected with the estimated attitude (last step on)
    camera/image/labels         their HIP labels beside them, without collisions (last step on)
    camera/image/truth/stars    where the simulator drew the catalog stars (when truth is known)
    camera/image/truth/false_stars  where it drew false stars (debris), labelled beside them (.../labels)
    truth/camera                camera pose and frustum at the true attitude (when known)
    steps/log                   one TextLog entry per step: "[kind] note" and what it shows
    steps/numbers/<unit>/<name> one Scalars series per `Step.numbers` entry, one plot per unit
    result                      the result as a Markdown document (static), with why it failed

"The shown attitude" is the estimated attitude when the image was solved, else the true one when it is
known; without either, the 3D view has no observed stars (the image still has them).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
import uuid

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from skyview.core import sky_geometry as sg
from skyview.core.attitude import attitude_error_arcsec, radec_roll_from_R
from skyview.core.catalog import designation
from skyview.core.errors import BadInput
from skyview.present.drawables import step_views
from skyview.present.text import result_lines
from skyview.record.draw import (
    C_CENTROID,
    C_FALSE,
    C_FOV_EST,
    C_FOV_TRUE,
    C_MATCH,
    C_OBSERVED,
    C_TRUTH,
    CAMERA,
    CENTROIDS,
    FOV_ESTIMATED,
    FOV_TRUE,
    IMAGE,
    IMAGE_LABELS,
    IMAGE_MATCHES,
    IMAGE_ROW_SHARES,
    JPEG_QUALITY,
    MATCH_LABELS,
    MATCHES,
    NO_AXES,
    OBSERVED,
    PHOTO,
    RESULT,
    SKY_COLUMN_SHARES,
    SKY_MATCH_RADIUS,
    SKY_OBSERVED_RADIUS,
    STEP_LOG,
    TIMELINE,
    TRUE_CAMERA,
    TRUTH_FALSE_LABELS,
    TRUTH_FALSE_STARS,
    TRUTH_STARS,
    RecordInfo,
    SkyEye,
    catalog_radii,
    check_output_path,
    display_image,
    fisheye_photo,
    fmt,
    image_labels,
    log_sky,
    log_step,
    open_recording,
    pinhole,
    pose,
    rerun_uv,
    sky_labels,
    unit_plots,
)
from skyview.simulate.scoring import score_trial

# ============================================================================ the result document

def result_markdown(result, *, truth: dict | None = None, meta: dict | None = None,
                    image_note: str = "", wrong: list[int] | None = None, label_note: str = "") -> str:
    """The result as Markdown: `present.result_lines` (status, why not, attitude, sigma, verification,
    time), the matches, the error against the truth; label_note: which stars the views label."""
    lines = [f"# {result.method} ({result.variant}): {result.status}", ""]
    if result.reason:
        lines += [f"**Reason:** {result.reason}", ""]
    lines += ["| | |", "|---|---|"] + [f"| {a} | {b} |" for a, b in result_lines(result)] + [""]
    if meta:
        lines += ["| | |", "|---|---|"] + [f"| {k} | {fmt(v)} |" for k, v in meta.items()] + [""]
    if result.R is not None:
        d = result.to_dict()
        q = d["quaternion"]
        lines += ["## Attitude (estimated)", "",
                  f"- RA **{d['ra_deg']:.5f}°**, Dec **{d['dec_deg']:+.5f}°**, roll **{d['roll_deg']:+.4f}°**",
                  f"- quaternion [w x y z]: {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}", ""]
    ident = result.identification
    lines += ["## Identification", "",
              f"- {len(result.centroids)} centroids, {len(result.matches)} matched"
              + (f", {len(ident.steps)} steps, status {ident.status}" if ident else "")]
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
    if image_note:
        lines += ["", f"*Image:* {image_note}."]
    if label_note:
        lines += ["", f"*Labels:* {label_note}."]
    if result.database_key:
        lines += ["", "*Database key:* `" + json.dumps(result.database_key, sort_keys=True) + "`"]
    return "\n".join(lines) + "\n"


# ============================================================================ the blueprint

def blueprint(R_view: np.ndarray | None, plots: list) -> rrb.Blueprint:
    """It opens on the 3D sky (looking out along the boresight from behind the camera), the image with its
    centroids and the step log; the step numbers, one plot per unit, and the result are tabs."""
    eye = None
    if R_view is not None:  # the labels of the sky are laid out for this eye (record_draw.sky_labels)
        e = SkyEye.behind(R_view)
        eye = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=e.position.tolist(),
                                look_target=e.target.tolist(), eye_up=e.up.tolist())
    sky = rrb.Spatial3DView(name="sky", origin="/", contents=["/sky/**", "/camera/**", "/truth/**"],
                            background=[5, 8, 16], line_grid=rrb.LineGrid3D(visible=False), eye_controls=eye,
                            spatial_information=NO_AXES)
    tabs = [rrb.TextLogView(name="step log", origin=f"/{STEP_LOG}"),
            rrb.TextDocumentView(name="result", origin=f"/{RESULT}")] + list(plots)
    right = rrb.Vertical(rrb.Spatial2DView(name="image", origin=f"/{IMAGE}"), rrb.Tabs(*tabs, active_tab=0),
                         row_shares=list(IMAGE_ROW_SHARES))
    return rrb.Blueprint(rrb.Horizontal(sky, right, column_shares=list(SKY_COLUMN_SHARES)),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed", timeline=TIMELINE))


# ============================================================================ writing

def record_solve(path: str | os.PathLike, result, image: np.ndarray, *, catalog, truth: dict | None = None,
                 force: bool = False, meta: dict | None = None, name: str | None = None) -> RecordInfo:
    """Write `result` (a pipeline.SolveResult of `image`) as a Rerun recording at `path`.

    catalog: the guide catalog the solver used (`MethodSolver.catalog`: step rows and matches are rows of it).
    truth: the simulator's truth dict when known (true attitude, drawn stars, false stars). meta: extra
    key/values for the result document. The file is written next to `path` and moved into place only when
    complete: nothing is overwritten unless `force`, and a failed write leaves nothing behind.
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
                       f"{', '.join(map(str, missing[:5]))}: it is not the one the solver used "
                       f"(pass MethodSolver.catalog)")
    R_est = None if result.R is None else np.asarray(result.R, dtype=np.float64)
    R_true = None if truth is None else np.asarray(truth["R"], dtype=np.float64)
    R_view = R_est if R_est is not None else R_true
    ident = result.identification
    steps = list(ident.steps) if ident else []
    views = step_views(steps, catalog.xyz, len(result.centroids), camera=camera, hip=catalog.hip)
    wrong = score_trial(result, truth)[1] if truth is not None else None

    title = name or p.stem
    # the same solve of the same image gets the same id (reproducible); different ones never merge in a viewer
    digest = hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()
    rec_id = str(uuid.uuid5(uuid.NAMESPACE_URL, f"skyview:{title}:{result.method}:{result.variant}:{digest}"))
    with open_recording(p, rec_id, title, blueprint(R_view, unit_plots(views))) as rec:
        image_note, taken = _write_static(rec, result, image, catalog, truth, R_est, R_true, R_view)
        drawn: set[str] = set()
        for k, v in enumerate(views):
            rec.set_time(TIMELINE, sequence=k)
            drawn = log_step(rec, v, result.centroids.uv, drawn)
        if views:  # the identification, from the last step on (a step shows what is known at that step)
            rec.set_time(TIMELINE, sequence=len(views) - 1)
        label_note = _write_matches(rec, result, catalog, R_est, truth, taken, static=not views)
        rec.log(RESULT, rr.TextDocument(result_markdown(result, truth=truth, meta=meta, image_note=image_note,
                                                        wrong=wrong, label_note=label_note),
                                        media_type=rr.MediaType.MARKDOWN),
                static=True)
    return RecordInfo(path=p, bytes=p.stat().st_size, write_ms=(time.perf_counter() - t0) * 1e3,
                      steps=len(steps), status=result.status)


def _has_hip(catalog, hip: int) -> bool:
    try:
        catalog.index_of(hip)
    except KeyError:
        return False
    return True


def _marks_uv(result, truth) -> np.ndarray:
    """Every star marked in the image: the centroids and, when known, where the simulator drew stars."""
    uv = [np.asarray(result.centroids.uv, dtype=np.float64).reshape(-1, 2)]
    if truth is not None:
        uv += [np.array([[s["u_noisy"], s["v_noisy"]] for s in truth.get("stars", [])]).reshape(-1, 2),
               np.array([[f["u"], f["v"]] for f in truth.get("false_stars", [])]).reshape(-1, 2)]
    return np.concatenate(uv)


def _write_static(rec, result, image, catalog, truth, R_est, R_true, R_view) -> tuple[str, np.ndarray]:
    """The static entities; returns the image note and the screen boxes of the labels placed (false stars)."""
    camera = result.camera
    log_sky(rec, catalog)
    if R_est is not None:
        rec.log(FOV_ESTIMATED, rr.LineStrips3D([sg.sensor_footprint(camera, R_est).astype(np.float32)],
                                               colors=C_FOV_EST, radii=rr.Radius.ui_points(1.5)), static=True)
    if R_true is not None:
        rec.log(FOV_TRUE, rr.LineStrips3D([sg.sensor_footprint(camera, R_true).astype(np.float32)],
                                          colors=C_FOV_TRUE, radii=rr.Radius.ui_points(1.0)), static=True)
    # --- the camera: pose, intrinsics, image
    if R_view is not None:
        rec.log(CAMERA, pose(R_view), static=True)
    rec.log(IMAGE, *pinhole(camera, color=C_FOV_EST), static=True)
    if R_true is not None:
        rec.log(TRUE_CAMERA, pose(R_true), static=True)
        rec.log(TRUE_CAMERA, *pinhole(camera, color=C_FOV_TRUE), static=True)
    shown, note = display_image(image)
    rec.log(IMAGE, rr.Image(shown, color_model="L").compress(jpeg_quality=JPEG_QUALITY), static=True)
    if camera.fisheye and R_view is not None:  # (in 3-D where its lens saw each pixel: no plane holds it)
        rec.log(PHOTO, fisheye_photo(camera, shown), static=True)
    cents = result.centroids
    n = len(cents)
    if n:
        rec.log(CENTROIDS, rr.Points2D(rerun_uv(cents.uv), radii=rr.Radius.ui_points(4.0), colors=C_CENTROID,
                                       labels=[f"#{k}" for k in range(n)], show_labels=False, draw_order=20),
                static=True)
        if R_view is not None:
            v = camera.unproject(cents.uv) @ R_view  # v_icrs = R^T v_cam
            rec.log(OBSERVED, rr.Points3D(v.astype(np.float32), radii=SKY_OBSERVED_RADIUS, colors=C_OBSERVED,
                                          labels=[f"#{k}" for k in range(n)], show_labels=False), static=True)
    # --- where the simulator drew stars
    if truth is not None:
        stars = truth.get("stars", [])
        if stars:
            uv = np.array([[s["u_noisy"], s["v_noisy"]] for s in stars])
            rec.log(TRUTH_STARS, rr.Points2D(rerun_uv(uv), radii=rr.Radius.ui_points(10.0), colors=C_TRUTH + (60,),
                                             labels=[f"HIP {s['hip']}" for s in stars], show_labels=False,
                                             draw_order=5), static=True)
        false = truth.get("false_stars", [])
        if false:
            uv = np.array([[f["u"], f["v"]] for f in false])
            rec.log(TRUTH_FALSE_STARS, rr.Points2D(rerun_uv(uv), radii=rr.Radius.ui_points(10.0),
                                                   colors=C_FALSE + (140,), labels=["false star"] * len(false),
                                                   show_labels=False, draw_order=6), static=True)
            at, texts, taken = image_labels(uv, ["false star"] * len(false), np.zeros(len(false)), camera,
                                            _marks_uv(result, truth))
            rec.log(TRUTH_FALSE_LABELS, rr.Points2D(at, radii=0.0, labels=texts, show_labels=True, colors=C_FALSE,
                                                    draw_order=31), static=True)
            return note, taken
    return note, np.zeros((0, 4))


def write_matches(rec, matches: list[tuple[int, int]], catalog, camera, R_est, static: bool, *,
                  stars_uv: np.ndarray | None = None, stars_xyz: np.ndarray | None = None,
                  taken: np.ndarray | None = None, eye: SkyEye | None = None) -> str:
    """The identification: (observed index, catalog row) pairs on the sky and in the image, with HIP labels
    beside the stars, on no other label and no star (`record_draw.image_labels`, `record_draw.sky_labels`:
    the brightest first, hidden where there is no room). stars_uv / stars_xyz: the other stars marked in
    the image / on the sky (the catalog's are avoided on the sky too); taken: screen boxes of the image's
    labels placed before (`record_draw.image_labels`); eye: the sky view's opening eye (default
    `SkyEye.behind(R_est)`, as `blueprint`). Returns a sentence saying which stars each view labels."""
    if not matches:
        return ""
    rows = np.array([c for _, c in matches], dtype=np.int64)
    xyz = catalog.xyz[rows]
    mag = np.asarray(catalog.mag)[rows]
    rec.log(MATCHES, rr.Points3D(xyz.astype(np.float32), radii=SKY_MATCH_RADIUS, colors=C_MATCH, show_labels=False),
            static=static)
    others = [catalog.xyz] + ([] if stars_xyz is None else [np.asarray(stars_xyz, dtype=np.float64).reshape(-1, 3)])
    radii = [catalog_radii(catalog)] + ([] if stars_xyz is None else [np.full(len(others[1]), SKY_OBSERVED_RADIUS)])
    at, sky_texts = sky_labels(xyz, [f"{designation(catalog.hip[c])} (#{o})" for o, c in matches], mag,
                               eye or SkyEye.behind(R_est), np.concatenate(others), np.concatenate(radii))
    rec.log(MATCH_LABELS, rr.Points3D(at, radii=0.0, labels=sky_texts, show_labels=True, colors=C_MATCH),
            static=static)
    uv, _ = camera.project(xyz @ np.asarray(R_est).T)
    rec.log(IMAGE_MATCHES, rr.Points2D(rerun_uv(uv), radii=rr.Radius.ui_points(7.0), colors=C_MATCH + (110,),
                                       show_labels=False, draw_order=10), static=static)
    anchors, shown, _ = image_labels(uv, [designation(catalog.hip[c]) for _, c in matches], mag, camera, stars_uv,
                                     taken)
    rec.log(IMAGE_LABELS, rr.Points2D(anchors, radii=0.0, labels=shown, show_labels=True, colors=C_MATCH,
                                      draw_order=30), static=static)
    return (f"the image labels {len(shown)} of the {len(matches)} identified stars and the sky {len(sky_texts)}, "
            f"beside them, the brightest first; a label that would cover another label or a star is left out "
            f"(the sky's at the view it opens on: the rest are on the image, every match is in the table above)")


def _write_matches(rec, result, catalog, R_est, truth, taken, static: bool) -> str:
    if not result.matches or R_est is None:
        return ""
    pairs = [(int(m["index"]), int(catalog.index_of(m["hip"]))) for m in result.matches]
    observed = result.camera.unproject(result.centroids.uv) @ R_est  # v_icrs = R^T v_cam
    return write_matches(rec, pairs, catalog, result.camera, R_est, static, stars_uv=_marks_uv(result, truth),
                         stars_xyz=observed, taken=taken)


__all__ = ["record_solve", "result_markdown", "blueprint", "write_matches"]
