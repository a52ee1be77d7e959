"""A tracked sequence as a Rerun recording, on a `frame` timeline (`skyview solve-sequence ... --record PATH.rrd`).

Written with rerun directly (`rr.RecordingStream`, `set_time("frame", sequence=k)`), frame by frame as the
tracker answers (`TrackRecorder`: memory flat over a long run, a killed run's frames kept in the file),
from the tracker's per-frame results (`skyview.solver.track.TrackFrame`) and the images:

static: the camera's `Pinhole` under `camera` (at the first frame with a camera); at the end `sky/stars`
(the tracking catalog's stars near the path, unit sphere), `sky/true_path` (the true boresights, when the
truth is known), `sky/path` (the solved boresights) and `result` (a Markdown table: frame, mode,
matches, time, error);
per frame k (timeline `frame`): `camera` (Transform3D at the estimated attitude, else the true one),
`camera/image` (the frame, JPEG-compressed), `camera/image/centroids` (what the frame measured: the
windows' centroids when tracked), `camera/image/matches` (the matched ones, labelled with HIP),
`sky/footprint` (the frame's footprint, coloured by mode: lost-in-space orange, tracking green, not
solved red), `sky/boresight` (the frame's solved boresight), `log` (a TextLog line: mode, lock lost /
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
from skyview.core.catalog import GuideCatalog, designation
from skyview.core.errors import BadInput
from skyview.core.sky_geometry import sensor_footprint

FRAME_TIMELINE = "frame"
MODE_VALUE = {"tracking": 1.0, "lost_in_space": 0.0}
MODE_RGB = {"tracking": (90, 230, 130), "lost_in_space": (255, 150, 40), "not solved": (230, 60, 60)}
TRUTH_RGB = (120, 160, 255)
STAR_RGB = (230, 230, 230)
JPEG_QUALITY = 80
FLUSH_EVERY = 8  # frames between flushes of the file


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


class TrackRecorder:
    """A tracked sequence written to its .rrd as it runs: each frame's images, points, scalars and log line
    go to the file when the frame is added (`add`), and only a few numbers per frame are kept (its mode,
    boresight and table row), so memory stays flat over ten thousand frames and a run that is killed
    leaves the frames done so far in the file. `close` adds what needs every frame (the catalog stars
    near the path, the path, the table) and returns the file's figures.

    The file is written in place: `path` must not exist unless force (checked here, before any frame)."""

    def __init__(self, path: str | os.PathLike, catalog: GuideCatalog, *, method: str = "", force: bool = False):
        p = Path(path)
        if p.suffix.lower() != ".rrd":
            raise BadInput(f"{p}: a recording's name ends in .rrd")
        if p.exists() and not force:
            raise BadInput(f"{p} exists: give another name or --force")
        if not p.parent.is_dir():
            raise BadInput(f"{p.parent} is not a folder")
        self.path, self.catalog, self.method = p, catalog, method
        self.rec = rr.RecordingStream("skyview", recording_id=f"skyview-track-{p.stem}-{method}", send_properties=False)
        self.rec.set_log_time_enabled(False)  # the same inputs give the same contents
        try:
            self.rec.save(str(p))
        except OSError as exc:
            raise BadInput(f"cannot write {p}: {exc.strerror or exc}") from None
        self.camera: Camera | None = None
        self.boresights: list[np.ndarray] = []  # shown attitudes' boresights (for the stars near the path)
        self.solved_path: list[np.ndarray] = []
        self.true_path: list[np.ndarray] = []
        self.rows: list[str] = []
        self.modes: list[str] = []
        self.true_R: dict[int, np.ndarray] = {}

    def add(self, fr, image: np.ndarray, camera: Camera | None, truth: dict | None = None) -> None:
        """Frame `fr` (a TrackFrame) of `image`, through `camera` (the tracker's, once it has one)."""
        rec, k = self.rec, int(fr.frame)
        if camera is not None and self.camera is None:
            self.camera = camera
            rec.log("camera", rr.Pinhole(focal_length=[camera.fx, camera.fy], principal_point=[camera.cx, camera.cy],
                                         width=camera.width, height=camera.height, image_plane_distance=0.1),
                    static=True)
        true_R = None if truth is None else np.asarray(truth["R"], dtype=np.float64)
        if true_R is not None:
            self.true_R[k] = true_R
            self.true_path.append(true_R[2])
        err = attitude_error_arcsec(fr.R, true_R)["total"] if (true_R is not None and fr.solved) else None
        rel = None
        if fr.relative_rotvec_rad is not None and true_R is not None and fr.relative_to in self.true_R:
            turn = _body_turn(self.true_R[fr.relative_to], true_R)
            rel = float(np.linalg.norm(fr.relative_rotvec_rad - turn) * 206264.806)
        mode = _mode(fr)
        self.modes.append(mode)
        self.rows.append(_row(fr, err, rel))
        rec.set_time(FRAME_TIMELINE, sequence=k)
        img8 = np.asarray(image)
        if img8.dtype != np.uint8:  # a 16-bit frame, stretched for the picture
            lo, hi = np.percentile(img8, [1.0, 99.9])
            img8 = np.clip((img8.astype(np.float64) - lo) * 255.0 / max(hi - lo, 1e-9), 0, 255).astype(np.uint8)
        rec.log("camera/image", rr.Image(img8, color_model="L").compress(jpeg_quality=JPEG_QUALITY))
        uv = (fr.centroids.uv if fr.centroids is not None else np.zeros((0, 2))).astype(np.float32)
        rec.log("camera/image/centroids", rr.Points2D(uv, colors=(255, 220, 0), radii=4.0))
        if fr.matches:
            rec.log("camera/image/matches", rr.Points2D(np.array([[m["u"], m["v"]] for m in fr.matches],
                                                                 dtype=np.float32),
                                                        labels=[designation(m["hip"]) for m in fr.matches],
                                                        colors=MODE_RGB[mode], radii=6.0))
        else:
            rec.log("camera/image/matches", rr.Clear(recursive=False))
        R = fr.R if fr.R is not None else true_R
        cam = camera or self.camera
        if R is not None:
            self.boresights.append(R[2])
            rec.log("camera", rr.Transform3D(mat3x3=R, relation=rr.TransformRelation.ChildFromParent))
            if cam is not None:
                rec.log("sky/footprint", rr.LineStrips3D([sensor_footprint(cam, R).astype(np.float32)],
                                                         colors=MODE_RGB[mode]))
        if fr.solved:  # the boresight of this frame (the whole path is written once, at the end)
            self.solved_path.append(fr.R[2])
            rec.log("sky/boresight", rr.Points3D(fr.R[2][None].astype(np.float32), colors=MODE_RGB["tracking"],
                                                 radii=0.004))
        text = f"frame {k}: {mode.replace('_', '-')}"
        if fr.lost_lock:
            text += f", lock lost ({fr.lost_lock})"
        if not fr.solved:
            text += f": {fr.reason}"
        rec.log("log", rr.TextLog(text, level="WARN" if (fr.lost_lock or not fr.solved) else "INFO"))
        rec.log("plots/mode", rr.Scalars(MODE_VALUE.get(mode, -1.0)))
        rec.log("plots/matches", rr.Scalars(float(len(fr.matches))))
        rec.log("plots/time_ms", rr.Scalars(float(fr.time_ms.get("total", 0.0))))
        if err is not None:
            rec.log("plots/error_arcsec", rr.Scalars(float(err)))
        if rel is not None:
            rec.log("plots/relative_error_arcsec", rr.Scalars(float(rel)))
        if len(self.modes) % FLUSH_EVERY == 0:  # on disk every few frames: a killed run loses at most these
            rec.flush()

    def add_error(self, k: int, message: str) -> None:
        """A frame that could not be read or solved at all: its line in the log and the table."""
        self.rec.set_time(FRAME_TIMELINE, sequence=int(k))
        self.rec.log("log", rr.TextLog(f"frame {k}: error: {message}", level="ERROR"))
        self.modes.append("error")
        self.rows.append(f"| {k} | - | error | 0 | - | - | - | {message} |")

    def close(self) -> TrackRecordInfo:
        """The parts that need every frame, then the file flushed and closed."""
        rec, cam = self.rec, self.camera
        try:
            if self.boresights and cam is not None:
                reach = cam.half_diagonal_rad * 1.5
                b = np.array(self.boresights)
                # the stars near the path: one query per frame would be ten thousand; the path thinned to one
                # boresight per half field covers the same stars
                keep = [0]
                for i in range(1, len(b)):
                    if float(b[i] @ b[keep[-1]]) < np.cos(0.5 * reach):
                        keep.append(i)
                near = np.unique(np.concatenate([self.catalog.within(b[i], reach) for i in keep]))
                rec.log("sky/stars", rr.Points3D(self.catalog.xyz[near].astype(np.float32), colors=STAR_RGB,
                                                 radii=0.002), static=True)
            if self.true_path:
                rec.log("sky/true_path", rr.LineStrips3D([np.array(self.true_path, dtype=np.float32)],
                                                         colors=TRUTH_RGB), static=True)
            if self.solved_path:
                rec.log("sky/path", rr.LineStrips3D([np.array(self.solved_path, dtype=np.float32)],
                                                    colors=MODE_RGB["tracking"]), static=True)
            head = [f"# Tracking with {self.method}", "",
                    "| frame | mode | status | matches | time (ms) | error vs truth (\") | relative rotation error (\") "
                    "| lock |", "|---|---|---|---|---|---|---|---|"]
            rec.log("result", rr.TextDocument("\n".join(head + self.rows) + "\n", media_type=rr.MediaType.MARKDOWN),
                    static=True)
            rec.flush()
            rec.disconnect()
        except OSError as exc:
            raise BadInput(f"cannot write {self.path}: {exc.strerror or exc}") from None
        return TrackRecordInfo(path=self.path, bytes=self.path.stat().st_size, frames=len(self.modes), modes=self.modes)


def _row(fr, err: float | None, rel: float | None) -> str:
    lock = f"lost: {fr.lost_lock}" if fr.lost_lock else ""
    return (f"| {fr.frame} | {fr.mode.replace('_', '-')} | {fr.status} | {len(fr.matches)} | "
            f"{fr.time_ms.get('total', float('nan')):.2f} | {'-' if err is None else f'{err:.1f}'} | "
            f"{'-' if rel is None else f'{rel:.1f}'} | {lock or '-'} |")
