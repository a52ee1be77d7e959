"""Sequences in the viewer: methods that identify over frames with known turns (the stochastic one).

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

from skyview.catalog import GuideCatalog
from skyview.errors import BadInput
from skyview.pipeline import SolveResult, result_from_identification
from skyview.sequence import SequenceResult, SequenceSolver, zero_point
from skyview.simulate import SensorModel, Turn, simulate_sequence, turn_about_camera_axis, turn_along_ra
from skyview.viewer.run import (ARCSEC, MAG_RANGE, Run, SceneConfig, Solvers, Source, _num, check_method,
                                make_run, needs_sequence, sigma_for)

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
        star's posterior (NaN where a frame does not report it), from each frame's stats."""
        out = {}
        for key in SERIES:
            vals = [r.stats.get(key) for r in self.result.identifications]
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


def solve_sequence_run(scene: SceneConfig, config: SequenceConfig, method: str, variant: str, solvers: Solvers,
                       label=None) -> SequenceRun:
    """Simulate the sequence the controls describe and solve it; every frame becomes a `Run`.

    label: called with a short text before each stage (the panel's progress line)."""
    say = label or (lambda _text: None)
    method, variant = check_method(method, variant)
    if not needs_sequence(method):
        raise BadInput(f"method {method!r} identifies single images, not sequences")
    scene, config = scene.checked(), config.checked()
    mag_limit = _num("magnitude limit", scene.mag_limit, *MAG_RANGE)
    say(f"simulating {config.n_frames} frames")
    t0 = time.perf_counter()
    sources, turns = simulate_frames(scene, config, solvers.base_catalog)
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
