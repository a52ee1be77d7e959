"""Sequences in the viewer: the stochastic method's multi-frame identification, and tracking for any method.

Tracking (`track_sequence_run`, `TrackedSequenceRun`): for a single-image method the same simulated
frames are solved by `skyview.solver.track.Tracker` (the code of `skyview solve-sequence --method M`): frame
0 lost-in-space, then tracked frames, back to lost-in-space when lock is lost. Every frame becomes a
`Run` (its centroids: the windows' when tracked), and `TrackedSequenceRun.show(scene, k)` draws on a
viser scene the footprints along the path coloured by each frame's mode (lost-in-space orange,
tracking green, not solved red, at the estimated attitude, else the true one), the frame numbers with
their mode, "lock lost" / "lock regained" where they happened, and frame k outlined in white;
`frame_markdown(k)` and `markdown()` say the same in words.

The stochastic method:

The stochastic method (`skyview.identify.stochastic`) updates a posterior frame by frame; one frame
alone is only its prior update. For such a method (`run.needs_sequence`) the viewer simulates N
frames from the scene's attitude with a known turn between them (`simulate.simulate_sequence`),
solves them together with `sequence.SequenceSolver` (the same code as `skyview solve-sequence`) and
turns every frame into a `Run`, so that each frame is drawn, stepped through and exported like a
single image. No identification logic here.

The photometric zero point comes from the simulator's sensor, as `sequence.solve_sequence` takes it
from a simulated sequence's sidecar: `mag_zero_point = zero_point(sensor)`, `mag_cut = limit + 0.25`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from skyview.core.catalog import GuideCatalog
from skyview.core.errors import BadInput
from skyview.core.sky_geometry import polylines_as_segments, sensor_footprint
from skyview.identify.base import FAILED, IDENTIFIED, Identification
from skyview.simulate.render import SensorModel, Turn, simulate_sequence, turn_about_camera_axis, turn_along_ra
from skyview.solver.pipeline import NOT_SOLVED, SOLVED, SolveResult, result_from_identification
from skyview.solver.sequence import SequenceResult, SequenceSolver, zero_point
from skyview.viewer.run import (
    ARCSEC,
    MAG_RANGE,
    Run,
    SceneConfig,
    Solvers,
    Source,
    _num,
    check_method,
    make_run,
    needs_sequence,
    sigma_for,
)

# Turn kinds, as the panel names them -> how the camera turns between frames.
TURNS = ("pan about camera y", "along RA")
FRAMES_RANGE = (1, 20)
STEP_RANGE_DEG = (0.0, 45.0)
MAG_CUT_MARGIN = 0.25  # the statistics keep stars down to the catalog limit + this (as solve_sequence)
# The per-frame numbers the viewer plots across the frames (Identification.stats of each frame).
SERIES = ("above_prior", "top_posterior", "true_posterior")


def sensor() -> SensorModel:
    """The viewer's simulated sensor (the same as `run.simulate`'s single images)."""
    return SensorModel()


@dataclass(frozen=True)
class SequenceConfig:
    """How many frames, and the known turn between consecutive ones."""

    n_frames: int = 5
    turn: str = TURNS[0]
    step_deg: float = 10.0

    def checked(self) -> "SequenceConfig":
        n = _num("frames", self.n_frames, *FRAMES_RANGE)
        if n != int(n):
            raise BadInput(f"frames {self.n_frames} is not a whole number")
        if self.turn not in TURNS:
            raise BadInput(f"unknown turn {self.turn!r}: choose from {', '.join(TURNS)}")
        return replace(self, n_frames=int(n), step_deg=_num("turn step (deg)", self.step_deg, *STEP_RANGE_DEG))

    def turn_per_frame(self) -> Turn:
        step = math.radians(self.step_deg)
        return turn_about_camera_axis("y", step) if self.turn == TURNS[0] else turn_along_ra(step)

    def describe(self) -> str:
        what = "panning about the camera's y axis" if self.turn == TURNS[0] else "along right ascension"
        return f"{self.n_frames} frame{'s' if self.n_frames != 1 else ''}, {self.step_deg:g}° turns {what}"


@dataclass
class SequenceRun:
    """A solved sequence: one `Run` per frame, the `SequenceResult` and the settings behind it."""

    frames: list[Run]
    result: SequenceResult
    scene: SceneConfig
    config: SequenceConfig
    time_ms: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def method(self) -> str:
        return self.result.method

    @property
    def variant(self) -> str:
        return self.result.variant

    @property
    def identified(self) -> list[int]:
        """Frames whose identification was verified."""
        return [k for k, f in enumerate(self.frames) if f.result.solved]

    @property
    def frame(self) -> int | None:
        """The latest verified frame (the sequence's answer), or None."""
        return self.result.frame

    def series(self) -> dict[str, np.ndarray]:
        """Per frame: stars above the prior 1/N, the leading star's posterior and the true designated
        star's posterior (NaN where a frame does not report it), from each frame's stats and, for the
        truth, from the scorer (`SequenceResult.truth_figures`)."""
        out = {}
        scored = self.result.truth_figures()
        for key in SERIES:
            vals = [(tf if key.startswith("true_") else r.stats).get(key)
                    for r, tf in zip(self.result.identifications, scored)]
            out[key] = np.array([np.nan if v is None else float(v) for v in vals], dtype=np.float64)
        return out


def simulate_frames(scene: SceneConfig, config: SequenceConfig, catalog: GuideCatalog
                    ) -> tuple[list[Source], list[np.ndarray]]:
    """The scene's attitude and N - 1 known turns: one `Source` per frame, and the turns (dR_cam)."""
    scene, config = scene.checked(), config.checked()
    camera = scene.camera()
    t0 = time.perf_counter()
    sim = simulate_sequence(catalog, camera, scene.R, config.n_frames, config.turn_per_frame(), sensor(),
                            seed=scene.seed, mag_limit=scene.mag_limit, n_false_stars=scene.false_stars,
                            n_dropped=scene.dropped, position_noise_rad=scene.noise_arcsec * ARCSEC)
    each_ms = (time.perf_counter() - t0) * 1e3 / config.n_frames
    n = config.n_frames
    sources = []
    for k, f in enumerate(sim.frames):
        t = f.truth
        cfg = replace(scene, ra_deg=round(t["ra_deg"] % 360.0, 4), dec_deg=round(t["dec_deg"], 4),
                      roll_deg=round(t["roll_deg"], 4))
        name = (f"simulated frame {k} (frames 0–{n - 1}): RA {t['ra_deg'] % 360.0:.2f}°, Dec {t['dec_deg']:+.2f}°, "
                f"roll {t['roll_deg']:.2f}°")
        sources.append(Source(image=f.image, fov_deg=scene.fov_deg, name=name, truth=t, config=cfg,
                              simulate_ms=each_ms))
    return sources, [sim.dR_cam(k) for k in range(n - 1)]


def sequence_solver(solvers: Solvers, source: Source, method: str, variant: str, mag_limit: float
                    ) -> tuple[SequenceSolver, object]:
    """The `SequenceSolver` for this camera, method, variant and limit, shared like the single-image
    solvers, with the zero point of the viewer's sensor."""
    zp = zero_point(sensor())
    sigma = sigma_for(source)
    camera = source.camera
    mag_cut = mag_limit + MAG_CUT_MARGIN
    key = ("sequence", camera, method, variant, round(mag_limit, 3), round(sigma, 12), round(zp, 6))
    params = {"mag_zero_point": zp, "mag_cut": mag_cut}
    return solvers.get_or_build(key, lambda catalog: SequenceSolver(
        camera, method, mag_limit=mag_limit, sigma_rad=sigma, catalog=catalog, method_params=params,
        variant=variant))


def sequence_cached(solvers: Solvers, source: Source, method: str, variant: str, mag_limit: float) -> bool:
    key = ("sequence", source.camera, method, variant, round(mag_limit, 3), round(sigma_for(source), 12),
           round(zero_point(sensor()), 6))
    return solvers.has(key)


def frame_result(seq_solver: SequenceSolver, res: SequenceResult, k: int) -> SolveResult:
    """Frame k of a sequence as the `SolveResult` a single image would give (attitude from the
    matches, 1-sigma, residuals, match list: the pipeline's own `result_from_identification`)."""
    ident = res.identifications[k]
    return result_from_identification(
        res.centroids[k], res.observations[k], ident, camera=seq_solver.camera, catalog=seq_solver.catalog,
        method=seq_solver.method, variant=seq_solver.variant, sigma_rad=seq_solver.sigma_rad,
        database_key=seq_solver.identifier.database_key,
        identify_ms=float(ident.stats.get("time_s", float("nan"))) * 1e3)


def _simulated(scene: SceneConfig, config: SequenceConfig, solvers: Solvers, say):
    """The checked controls and the simulated frames: (scene, config, magnitude limit, sources, turns)."""
    scene, config = scene.checked(), config.checked()
    mag_limit = _num("magnitude limit", scene.mag_limit, *MAG_RANGE)
    say(f"simulating {config.n_frames} frames")
    sources, turns = simulate_frames(scene, config, solvers.base_catalog)
    return scene, config, mag_limit, sources, turns


def solve_sequence_run(scene: SceneConfig, config: SequenceConfig, method: str, variant: str, solvers: Solvers,
                       label=None) -> SequenceRun:
    """Simulate the sequence the controls describe and solve it; every frame becomes a `Run`.

    label: called with a short text before each stage (the panel's progress line)."""
    say = label or (lambda _text: None)
    method, variant = check_method(method, variant)
    if not needs_sequence(method):
        raise BadInput(f"method {method!r} identifies single images, not sequences")
    t0 = time.perf_counter()
    scene, config, mag_limit, sources, turns = _simulated(scene, config, solvers, say)
    t1 = time.perf_counter()
    if not sequence_cached(solvers, sources[0], method, variant, mag_limit):
        say(f"loading the {method} database (built once per camera and catalog, then cached)")
    seq_solver, lock = sequence_solver(solvers, sources[0], method, variant, mag_limit)
    say(f"solving {config.n_frames} frames with {method} ({variant})")
    with lock:
        res = seq_solver.solve_images([s.image for s in sources], turns, [s.truth for s in sources])
    t3 = time.perf_counter()
    n = config.n_frames
    frames = []
    for k, (src, ident) in enumerate(zip(sources, res.identifications)):
        result = frame_result(seq_solver, res, k)
        identify_ms = result.time_ms["identify"]
        time_ms = {"simulate": src.simulate_ms, "centroid": res.time_ms.get("centroid", float("nan")) / n,
                   "identify": identify_ms, "attitude": result.time_ms.get("attitude", 0.0)}
        time_ms["total"] = sum(time_ms.values())
        frames.append(make_run(src, result, seq_solver.catalog, seq_solver.max_stars, time_ms))
    total = {"simulate": (t1 - t0) * 1e3, "centroid": res.time_ms.get("centroid", float("nan")),
             "identify": res.time_ms.get("identify", float("nan")), "total": (t3 - t0) * 1e3}
    return SequenceRun(frames=frames, result=res, scene=scene, config=config, time_ms=total)


# ============================================================================ tracking, any method

MODE_RGB = {"lost_in_space": (255, 150, 40), "tracking": (90, 230, 130), "not solved": (230, 60, 60)}
CURRENT_RGB = (255, 255, 255)
TRACK_NODE = "/tracked_sequence"


@dataclass
class TrackedSequenceRun:
    """A tracked sequence: one `Run` per frame and the tracker's `TrackFrame` of each."""

    frames: list[Run]
    tracked: list  # skyview.solver.track.TrackFrame, one per frame
    scene: SceneConfig
    config: SequenceConfig
    method: str
    variant: str
    gyros: bool  # the known turns were given to the tracker (else it predicts from its rate)
    time_ms: dict[str, float] = field(default_factory=dict)
    handles: list = field(default_factory=list)
    current: object = None  # the outline of the frame shown
    shown: int | None = None  # the frame outlined

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def modes(self) -> list[str]:
        """Per frame: "lost_in_space", "tracking" or "not solved"."""
        return [f.mode if f.solved else "not solved" for f in self.tracked]

    def lock_events(self) -> list[tuple[int, str, str]]:
        """(frame, "lost" | "regained", why): lock is lost where tracking gave up on a frame (or a frame
        was not solved), regained at the next solved frame."""
        out, locked = [], False
        for f in self.tracked:
            if f.lost_lock or (locked and not f.solved):
                out.append((f.frame, "lost", f.lost_lock or f.reason))
                locked = False
            if f.solved and not locked:
                if f.frame > 0:
                    out.append((f.frame, "regained", f"by {f.mode.replace('_', '-')}"))
                locked = True
        return out

    def attitudes(self) -> list[np.ndarray | None]:
        """Per frame: the estimated attitude, else the true one, else None."""
        return [f.R if f.R is not None else r.R_true for f, r in zip(self.tracked, self.frames)]

    # ------------------------------------------------------------------ drawing
    def show(self, scene, k: int | None = None) -> None:
        """Draw the footprints along the path on a viser scene, coloured by mode, with frame labels and
        the lock events; frame k (default the last) outlined."""
        self.hide()
        camera = self.frames[0].source.camera
        Rs = self.attitudes()
        lost = {e[0] for e in self.lock_events() if e[1] == "lost"}
        regained = {e[0] for e in self.lock_events() if e[1] == "regained"}
        for mode, rgb in MODE_RGB.items():
            lines = [sensor_footprint(camera, R) for R, m in zip(Rs, self.modes) if m == mode and R is not None]
            if lines:
                self.handles.append(scene.add_line_segments(
                    f"{TRACK_NODE}/{mode.replace(' ', '_')}", polylines_as_segments(lines).astype(np.float32), rgb,
                    thickness=2.0, thickness_units="screen"))
        top = np.array([0.0, -0.9 * camera.height / (2.0 * camera.fy), 1.0])
        top /= np.linalg.norm(top)
        for f, R, m in zip(self.tracked, Rs, self.modes):
            if R is None:
                continue
            text = f"{f.frame} · {m.replace('_', '-')}"
            if f.frame in lost:
                text += " · lock lost"
            if f.frame in regained:
                text += " · lock regained"
            self.handles.append(scene.add_label(f"{TRACK_NODE}/labels/{f.frame}", text,
                                                position=tuple(float(x) for x in R.T @ top),
                                                font_screen_scale=0.75, anchor="top-center"))
        self.set_frame(scene, len(self) - 1 if k is None else k)

    def set_frame(self, scene, k: int) -> None:
        """Outline frame k (the frame being played)."""
        if not 0 <= k < len(self):
            raise BadInput(f"frame {k} is not in the sequence (frames 0-{len(self) - 1})")
        if self.current is not None:
            self.current.remove()
            self.current = None
        R = self.attitudes()[k]
        if R is not None:
            seg = polylines_as_segments([sensor_footprint(self.frames[0].source.camera, R)]).astype(np.float32)
            self.current = scene.add_line_segments(f"{TRACK_NODE}/current", seg, CURRENT_RGB, thickness=4.0,
                                                   thickness_units="screen")
        self.shown = k

    def hide(self) -> None:
        for h in self.handles:
            h.remove()
        self.handles = []
        if self.current is not None:
            self.current.remove()
            self.current = None

    # ------------------------------------------------------------------ words
    def frame_markdown(self, k: int) -> str:
        f, run = self.tracked[k], self.frames[k]
        m = self.modes[k]
        head = f"**Frame {k}** (frames 0–{len(self) - 1}) · {m.replace('_', '-')}"
        if f.solved:
            head += f", {len(f.matches)} stars matched, {f.time_ms.get('total', float('nan')):.2f} ms"
            if run.error_arcsec:
                head += f" · error vs truth {run.error_arcsec['total']:.1f}″, {run.wrong_matches} wrong"
        else:
            head += f": {f.reason}"
        notes = [f"lock {e[1]}: {e[2]}" for e in self.lock_events() if e[0] == k]
        if f.relative_rotvec_rad is not None:
            notes.append(f"turned {np.degrees(np.linalg.norm(f.relative_rotvec_rad)):.4f}° since frame {f.relative_to}")
        return head + ("\n\n" + " · ".join(notes) if notes else "")

    def markdown(self) -> str:
        n_trk = self.modes.count("tracking")
        lines = [f"**Tracking** with **{self.method}** ({self.variant}) over a sequence of {self.config.describe()}"
                 f" ({'turns given, as gyros would' if self.gyros else 'turns predicted from the rate'}): "
                 f"{n_trk} tracked, {self.modes.count('lost_in_space')} lost-in-space, "
                 f"{self.modes.count('not solved')} not solved", "",
                 "| frame | mode | matches | ms | error (″) | lock |", "|---|---|---|---|---|---|"]
        ev = {}
        for k, what, _ in self.lock_events():
            ev.setdefault(k, []).append(what)
        for f, run, m in zip(self.tracked, self.frames, self.modes):
            err = f"{run.error_arcsec['total']:.1f}" if run.error_arcsec else "-"
            lines.append(f"| {f.frame} | {m.replace('_', '-')} | {len(f.matches)} | "
                         f"{f.time_ms.get('total', float('nan')):.2f} | {err} | {', '.join(ev.get(f.frame, [])) or '-'} |")
        return "\n".join(lines) + "\n"


def _track_result(fr, tracker, method: str, variant: str, camera) -> SolveResult:
    """A tracked frame as the `SolveResult` the viewer draws (matches as an identification)."""
    from skyview.detect.centroids import Centroids

    cat = tracker.catalog
    rows = {}
    for m in fr.matches:
        try:
            rows[int(m["index"])] = cat.index_of(int(m["hip"]))
        except KeyError:
            continue
    ident = Identification(method=method, status=IDENTIFIED if fr.solved else FAILED, matches=rows, steps=[],
                           reason=fr.reason, R=fr.R, attitude_covariance=fr.covariance,
                           verification={"p_false": fr.p_false})
    cov = fr.covariance
    sig = (None, None) if cov is None else (float(np.sqrt(0.5 * (cov[0, 0] + cov[1, 1])) / ARCSEC),
                                            float(np.sqrt(cov[2, 2]) / ARCSEC))
    return SolveResult(status=SOLVED if fr.solved else NOT_SOLVED, reason=fr.reason, method=method, variant=variant,
                       camera=camera, centroids=fr.centroids if fr.centroids is not None else Centroids.empty(),
                       identification=ident, R=fr.R, sigma_boresight_arcsec=sig[0], sigma_roll_arcsec=sig[1],
                       matches=list(fr.matches), time_ms=dict(fr.time_ms), epoch=cat.epoch,
                       sigma_rad=tracker.sigma_rad, mag_limit=tracker.mag_limit)


def track_sequence_run(scene: SceneConfig, config: SequenceConfig, method: str, variant: str, solvers: Solvers,
                       gyros: bool = True, label=None) -> TrackedSequenceRun:
    """Simulate the sequence the controls describe and track it with `method` (`skyview.solver.track.Tracker`):
    frame 0 lost-in-space, then tracking; gyros: give the tracker the known turns (else it predicts
    from the rate of its last attitudes). Every frame becomes a `Run`."""
    from skyview.solver.track import Tracker

    say = label or (lambda _text: None)
    method, variant = check_method(method, variant)
    if needs_sequence(method):
        raise BadInput(f"the {method} method identifies over the sequence itself (solve_sequence_run), "
                       f"it does not track")
    t0 = time.perf_counter()
    scene, config, mag_limit, sources, turns = _simulated(scene, config, solvers, say)
    t1 = time.perf_counter()
    camera = sources[0].camera
    sigma = sigma_for(sources[0])
    key = ("track", camera, method, variant, round(mag_limit, 3), round(sigma, 12))
    say(f"loading the {method} database for lost-in-space (built once per camera and catalog, then cached)")
    tracker, lock = solvers.get_or_build(key, lambda catalog: Tracker(
        camera, method, mag_limit=mag_limit, sigma_rad=sigma, variant=variant, catalog=catalog))
    say(f"tracking {config.n_frames} frames with {method} ({variant}) for lost-in-space")
    with lock:
        tracker.reset()
        tracked = [tracker.process(s.image, turns[k - 1] if (k and gyros) else None) for k, s in enumerate(sources)]
    t2 = time.perf_counter()
    frames = [make_run(src, _track_result(fr, tracker, method, variant, camera), tracker.catalog, tracker.max_stars,
                       {"simulate": src.simulate_ms, **fr.time_ms})
              for src, fr in zip(sources, tracked)]
    return TrackedSequenceRun(frames=frames, tracked=tracked, scene=scene, config=config, method=method,
                              variant=variant, gyros=bool(gyros),
                              time_ms={"simulate": (t1 - t0) * 1e3, "track": (t2 - t1) * 1e3,
                                       "total": (time.perf_counter() - t0) * 1e3})
