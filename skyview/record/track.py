"""A tracked sequence as a Rerun recording, on a `frame` timeline (`skyview solve-sequence ... --record PATH.rrd`).

Written with rerun directly (`rr.RecordingStream`, `set_time("frame", sequence=k)`), from the
tracker's per-frame results (`skyview.solver.track.TrackFrame`) and the images:

static: `sky/stars` (the tracking catalog's stars near the path, unit sphere), `sky/true_path` (the
true boresights, when the truth is known), `result` (a Markdown table: frame, mode, matches, time,
error), the camera's `Pinhole` under `camera`;
per frame k (timeline `frame`): `camera` (Transform3D at the estimated attitude, else the true one),
`camera/image` (the frame, JPEG-compressed), `camera/image/centroids` (what the frame measured: the
windows' centroids when tracked), `camera/image/matches` (the matched ones, labelled with HIP),
`sky/footprint` (the frame's footprint, coloured by mode: lost-in-space orange, tracking green, not
solved red), `sky/path` (the estimated boresights so far), `log` (a TextLog line: mode, lock lost /
regained), and the scalars `plots/mode` (1 tracking, 0 lost-in-space, -1 not solved),
`plots/matches`, `plots/time_ms`, `plots/relative_error_arcsec` and `plots/error_arcsec` (with truth).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr

from skyview.core.attitude import attitude_error_arcsec
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog
from skyview.core.errors import BadInput
from skyview.core.sky_geometry import sensor_footprint

FRAME_TIMELINE = "frame"
MODE_VALUE = {"tracking": 1.0, "lost_in_space": 0.0}
MODE_RGB = {"tracking": (90, 230, 130), "lost_in_space": (255, 150, 40), "not solved": (230, 60, 60)}
TRUTH_RGB = (120, 160, 255)
STAR_RGB = (230, 230, 230)
JPEG_QUALITY = 80


@dataclass
class TrackRecordInfo:
    path: Path
    bytes: int
    frames: int
    modes: list[str]


def _mode(fr) -> str:
    return fr.mode if fr.solved else "not solved"


def _body_turn(R_from: np.ndarray, R_to: np.ndarray) -> np.ndarray:
    from skyview.solver.track import body_turn_rotvec

    return body_turn_rotvec(R_from, R_to)


def _table(frames, errors: list[dict | None], rel_errors: list[float | None], method: str) -> str:
    lines = [f"# Tracking with {method}", "",
             "| frame | mode | status | matches | time (ms) | error vs truth (\") | relative rotation error (\") | lock |",
             "|---|---|---|---|---|---|---|---|"]
    for fr, e, r in zip(frames, errors, rel_errors):
        lock = f"lost: {fr.lost_lock}" if fr.lost_lock else ""
        lines.append(f"| {fr.frame} | {fr.mode.replace('_', '-')} | {fr.status} | {len(fr.matches)} | "
                     f"{fr.time_ms.get('total', float('nan')):.2f} | {'-' if e is None else f'{e:.1f}'} | "
                     f"{'-' if r is None else f'{r:.1f}'} | {lock or '-'} |")
    return "\n".join(lines) + "\n"


def record_track(path: str | os.PathLike, frames: list, images: list[np.ndarray], camera: Camera,
                 catalog: GuideCatalog, *, truths: list[dict] | None = None, method: str = "",
                 force: bool = False) -> TrackRecordInfo:
    """Write a tracked sequence (`Tracker.process`'s TrackFrames of `images`, in order) as a .rrd.
    truths: the simulator's per-frame truth (with "R") when known. Nothing is overwritten unless force."""
    p = Path(path)
    if p.suffix.lower() != ".rrd":
        raise BadInput(f"{p}: a recording's name ends in .rrd")
    if p.exists() and not force:
        raise BadInput(f"{p} exists: give another name or --force")
    if not p.parent.is_dir():
        raise BadInput(f"{p.parent} is not a folder")
    K = len(frames)
    if K == 0 or len(images) != K:
        raise BadInput(f"{len(images)} images for {K} tracked frames")
    if truths is not None and len(truths) != K:
        raise BadInput(f"{len(truths)} truth sidecars for {K} frames")
    true_R = None if truths is None else [np.asarray(t["R"], dtype=np.float64) for t in truths]
    shown = [fr.R if fr.R is not None else (None if true_R is None else true_R[k]) for k, fr in enumerate(frames)]
    errors = [attitude_error_arcsec(fr.R, true_R[k])["total"] if (true_R is not None and fr.solved) else None
              for k, fr in enumerate(frames)]
    rel = [float(np.linalg.norm(fr.relative_rotvec_rad - _body_turn(true_R[fr.relative_to], true_R[k])) * 206264.806)
           if (true_R is not None and fr.relative_rotvec_rad is not None) else None for k, fr in enumerate(frames)]
    tmp = p.with_name(f".{p.name}.tmp{os.getpid()}.rrd")
    rec = rr.RecordingStream("skyview", recording_id=f"skyview-track-{p.stem}-{method}", send_properties=False)
    rec.set_log_time_enabled(False)  # the same inputs give the same contents
    try:
        rec.save(str(tmp))
        _write(rec, frames, images, camera, catalog, true_R, shown, errors, rel, method)
        rec.flush()
        rec.disconnect()
        os.replace(tmp, p)
    except OSError as exc:
        raise BadInput(f"cannot write {p}: {exc.strerror or exc}") from None
    finally:
        if tmp.exists():
            tmp.unlink()
    return TrackRecordInfo(path=p, bytes=p.stat().st_size, frames=K, modes=[_mode(f) for f in frames])


def _write(rec, frames, images, camera, catalog, true_R, shown, errors, rel, method) -> None:
    boresights = np.array([R[2] for R in shown if R is not None]).reshape(-1, 3)
    reach = camera.half_diagonal_rad * 1.5
    near = (np.unique(np.concatenate([catalog.within(b, reach) for b in boresights])) if len(boresights)
            else np.zeros(0, dtype=np.int64))
    rec.log("sky/stars", rr.Points3D(catalog.xyz[near].astype(np.float32), colors=STAR_RGB,
                                     radii=0.002), static=True)
    if true_R is not None:
        rec.log("sky/true_path", rr.LineStrips3D([np.array([R[2] for R in true_R], dtype=np.float32)],
                                                 colors=TRUTH_RGB), static=True)
    rec.log("camera", rr.Pinhole(focal_length=[camera.fx, camera.fy], principal_point=[camera.cx, camera.cy],
                                 width=camera.width, height=camera.height, image_plane_distance=0.1),
            static=True)
    rec.log("result", rr.TextDocument(_table(frames, errors, rel, method), media_type=rr.MediaType.MARKDOWN),
            static=True)
    path_so_far: list[np.ndarray] = []
    for k, (fr, img) in enumerate(zip(frames, images)):
        rec.set_time(FRAME_TIMELINE, sequence=k)
        mode = _mode(fr)
        img8 = np.asarray(img)
        if img8.dtype != np.uint8:  # a 16-bit frame, stretched for the picture
            lo, hi = np.percentile(img8, [1.0, 99.9])
            img8 = np.clip((img8.astype(np.float64) - lo) * 255.0 / max(hi - lo, 1e-9), 0, 255).astype(np.uint8)
        rec.log("camera/image", rr.Image(img8, color_model="L").compress(jpeg_quality=JPEG_QUALITY))
        uv = (fr.centroids.uv if fr.centroids is not None else np.zeros((0, 2))).astype(np.float32)
        rec.log("camera/image/centroids", rr.Points2D(uv, colors=(255, 220, 0), radii=4.0))
        if fr.matches:
            rec.log("camera/image/matches", rr.Points2D(np.array([[m["u"], m["v"]] for m in fr.matches],
                                                                 dtype=np.float32),
                                                        labels=[f"HIP {m['hip']}" for m in fr.matches],
                                                        colors=MODE_RGB[mode], radii=6.0))
        else:
            rec.log("camera/image/matches", rr.Clear(recursive=False))
        R = shown[k]
        if R is not None:
            rec.log("camera", rr.Transform3D(mat3x3=R, relation=rr.TransformRelation.ChildFromParent))
            rec.log("sky/footprint", rr.LineStrips3D([sensor_footprint(camera, R).astype(np.float32)],
                                                     colors=MODE_RGB[mode]))
        if fr.solved:
            path_so_far.append(fr.R[2])
            rec.log("sky/path", rr.LineStrips3D([np.array(path_so_far, dtype=np.float32)],
                                                colors=MODE_RGB["tracking"]))
        text = f"frame {k}: {mode.replace('_', '-')}"
        if fr.lost_lock:
            text += f", lock lost ({fr.lost_lock})"
        if not fr.solved:
            text += f": {fr.reason}"
        rec.log("log", rr.TextLog(text, level="WARN" if (fr.lost_lock or not fr.solved) else "INFO"))
        rec.log("plots/mode", rr.Scalars(MODE_VALUE.get(mode, -1.0)))
        rec.log("plots/matches", rr.Scalars(float(len(fr.matches))))
        rec.log("plots/time_ms", rr.Scalars(float(fr.time_ms.get("total", 0.0))))
        if errors[k] is not None:
            rec.log("plots/error_arcsec", rr.Scalars(float(errors[k])))
        if rel[k] is not None:
            rec.log("plots/relative_error_arcsec", rr.Scalars(float(rel[k])))
