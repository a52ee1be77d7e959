"""What the viewer runs: a scenario or an image, solved by the same `MethodSolver` as the CLI.

No identification logic here: a `Run` is the simulator's image and truth, the pipeline's
`SolveResult`, and what `skyview.present.drawables` derives from them for drawing. Solvers (catalog + method database)
are cached and shared by every browser tab; one solve at a time per solver.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from skyview.core.attitude import R_from_radec_roll, attitude_error_arcsec, radec_roll_from_R, random_attitudes
from skyview.core.camera import Camera, check_fov_deg
from skyview.core.catalog import GuideCatalog, load_guide_catalog
from skyview.core.errors import BadInput
from skyview.identify import METHODS, VARIANTS
from skyview.identify.base import is_sequence_method
from skyview.present.drawables import StepView, match_groups, step_views
from skyview.simulate.render import SensorModel, simulate_image
from skyview.simulate.scoring import centroid_outcomes
from skyview.solver.pipeline import (
    DEFAULT_CENTROID_SIGMA_PX,
    MIRROR_NOTE,
    NEGATIVE_NOTE,
    BlindSolver,
    MethodSolver,
    SolveResult,
    inverted,
    looks_negative,
)

ARCSEC = math.pi / 180.0 / 3600.0
RESOLUTIONS = ("512x512", "1024x1024", "1280x1024", "2048x2048")
FOV_RANGE_DEG = (0.5, 90.0)
MAG_RANGE = (2.0, 7.5)


def _num(name: str, value, lo: float, hi: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise BadInput(f"{name} {value!r} is not a number") from None
    if not math.isfinite(v) or not lo <= v <= hi:
        raise BadInput(f"{name} {value} is outside [{lo:g}, {hi:g}]")
    return v


def _count(name: str, value, hi: int) -> int:
    v = _num(name, value, 0, hi)
    if v != int(v):
        raise BadInput(f"{name} {value} is not a whole number")
    return int(v)


def parse_resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(p) for p in str(text).lower().split("x"))
    except ValueError:
        raise BadInput(f"resolution {text!r} is not WIDTHxHEIGHT") from None
    if not (64 <= w <= 4096 and 64 <= h <= 4096):
        raise BadInput(f"resolution {text} is outside 64..4096 pixels a side")
    return w, h


def check_fov(fov_deg) -> float:
    check_fov_deg(fov_deg)
    return _num("FOV (deg)", fov_deg, *FOV_RANGE_DEG)


BLIND = "blind"  # the default pipeline: blind four-star patterns, the camera fitted (skyview.identify.blind)


def viewer_methods() -> tuple[str, ...]:
    """The viewer's method list: the default pipeline first (the viewer opens on it), then the registry's
    methods as they are now (a method registered at run time included)."""
    return (BLIND, *METHODS)


def check_method(method, variant) -> tuple[str, str]:
    if method not in viewer_methods():
        raise BadInput(f"unknown method {method!r}: choose from {', '.join(viewer_methods())}")
    if variant not in VARIANTS:
        raise BadInput(f"unknown variant {variant!r}: choose from {', '.join(VARIANTS)}")
    return str(method), str(variant)


@dataclass(frozen=True)
class SceneConfig:
    """A simulated scene: attitude, camera, catalog limit and disturbances (degrees / arcsec at the UI)."""

    ra_deg: float = 83.8
    dec_deg: float = -5.4
    roll_deg: float = 30.0
    fov_deg: float = 8.0
    resolution: str = "1024x1024"
    mag_limit: float = 6.0
    noise_arcsec: float = 0.0
    false_stars: int = 0
    dropped: int = 0
    seed: int = 1

    def checked(self) -> "SceneConfig":
        """The same config with every field validated (BadInput names the bad one)."""
        parse_resolution(self.resolution)
        return replace(
            self,
            ra_deg=_num("RA (deg)", self.ra_deg, 0.0, 360.0),
            dec_deg=_num("Dec (deg)", self.dec_deg, -90.0, 90.0),
            roll_deg=_num("roll (deg)", self.roll_deg, -180.0, 180.0),
            fov_deg=check_fov(self.fov_deg),
            mag_limit=_num("magnitude limit", self.mag_limit, *MAG_RANGE),
            noise_arcsec=_num("centroid noise (arcsec)", self.noise_arcsec, 0.0, 600.0),
            false_stars=_count("false stars", self.false_stars, 50),
            dropped=_count("dropped stars", self.dropped, 50),
            seed=_count("seed", self.seed, 2**31 - 1),
        )

    @property
    def R(self) -> np.ndarray:
        return R_from_radec_roll(math.radians(self.ra_deg), math.radians(self.dec_deg), math.radians(self.roll_deg))

    def camera(self) -> Camera:
        w, h = parse_resolution(self.resolution)
        return Camera.from_fov(self.fov_deg, w, h)


def random_pointing(rng: np.random.Generator) -> tuple[float, float, float]:
    """(RA, Dec, roll) in degrees of an attitude drawn uniformly over the rotations."""
    ra, dec, roll = radec_roll_from_R(random_attitudes(1, rng)[0])
    return round(math.degrees(ra), 2) % 360.0, round(math.degrees(dec), 2), round(math.degrees(roll), 2)


@dataclass
class Source:
    """The image being solved, with its FOV and, when simulated, its truth."""

    image: np.ndarray
    fov_deg: float
    name: str
    truth: dict | None = None
    config: SceneConfig | None = None
    simulate_ms: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    fitted: bool = False  # fov_deg, k1, k2 were fitted to the stars by the blind front end
    depth_mag: float | None = None  # the catalog depth the image shows (from the blind front end)
    lens: str = "pinhole"  # the camera model (skyview.core.camera): a fisheye's when one was fitted
    rows_reversed: bool = False  # `image` is the one given with its rows turned over (a mirror image of the sky)

    @property
    def camera(self) -> Camera:
        return Camera.from_fov(self.fov_deg, self.image.shape[1], self.image.shape[0], k1=self.k1, k2=self.k2,
                               model=self.lens)


@dataclass
class Run:
    """One solved image and everything the viewer draws from it."""

    source: Source
    result: SolveResult
    catalog: GuideCatalog  # the solver's guide catalog: step rows index it
    n_used: int  # centroids given to the identifier (the brightest max_stars)
    outcomes: list[str]
    drawables: list[StepView]  # one per step (skyview.present.drawables)
    matches: dict[int, int]  # observed index -> catalog row
    match_groups: list[tuple[int, ...]]
    error_arcsec: dict | None = None
    wrong_matches: int | None = None
    time_ms: dict = field(default_factory=dict)

    @property
    def R_true(self) -> np.ndarray | None:
        t = self.source.truth
        return None if not t else np.asarray(t["R"], dtype=np.float64)

    @property
    def R_shown(self) -> np.ndarray | None:
        """The attitude the camera is drawn at: the estimate, else the truth, else unknown."""
        return self.result.R if self.result.R is not None else self.R_true


class Solvers:
    """Solvers keyed by camera, method, variant, catalog limit and sigma; at most `size` kept.

    `get_or_build` caches other solvers the same way (the sequence solvers of `sequence_run`)."""

    def __init__(self, size: int = 12, slots: int | None = None):
        from skyview.viewer.solve_queue import SolveQueue

        self._size = size
        self.queue = SolveQueue(slots)  # every tab's solves take turns here (first come, first served)
        self._lock = threading.Lock()
        self._items: OrderedDict[tuple, tuple[MethodSolver, threading.Lock]] = OrderedDict()
        self._building: dict[tuple, threading.Lock] = {}
        self._catalog: GuideCatalog | None = None

    @property
    def base_catalog(self) -> GuideCatalog:
        with self._lock:
            if self._catalog is None:
                self._catalog = load_guide_catalog()
            return self._catalog

    def get(self, camera: Camera, method: str, variant: str, mag_limit: float,
            sigma_rad: float) -> tuple[MethodSolver, threading.Lock]:
        """The single-image `MethodSolver` for this configuration (built once, then shared)."""
        key = (camera, method, variant, round(float(mag_limit), 3), round(float(sigma_rad), 12))
        return self.get_or_build(key, lambda catalog: MethodSolver(camera, method, catalog=catalog, mag_limit=mag_limit,
                                                                   sigma_rad=sigma_rad, variant=variant))

    def get_or_build(self, key: tuple, build) -> tuple[object, threading.Lock]:
        """The item cached under `key`, else `build(base_catalog)` (one build per key at a time), with a
        lock that serialises its use."""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
            build_lock = self._building.setdefault(key, threading.Lock())
        catalog = self.base_catalog
        with build_lock:
            with self._lock:
                if key in self._items:
                    return self._items[key]
            item = build(catalog)
            with self._lock:
                self._items[key] = (item, threading.Lock())
                self._building.pop(key, None)
                while len(self._items) > self._size:
                    self._items.popitem(last=False)
                return self._items[key]

    def has(self, key: tuple) -> bool:
        with self._lock:
            return key in self._items

    def cached(self, camera: Camera, method: str, variant: str, mag_limit: float, sigma_rad: float) -> bool:
        return self.has((camera, method, variant, round(float(mag_limit), 3), round(float(sigma_rad), 12)))


def simulate(config: SceneConfig, catalog: GuideCatalog) -> Source:
    config = config.checked()
    camera = config.camera()
    t0 = time.perf_counter()
    frame = simulate_image(catalog, camera, config.R, SensorModel(), seed=config.seed, mag_limit=config.mag_limit,
                           n_false_stars=config.false_stars, n_dropped=config.dropped,
                           position_noise_rad=config.noise_arcsec * ARCSEC)
    name = f"simulated: RA {config.ra_deg:g}°, Dec {config.dec_deg:+g}°, roll {config.roll_deg:g}°"
    return Source(image=frame.image, fov_deg=config.fov_deg, name=name, truth=frame.truth, config=config,
                  simulate_ms=(time.perf_counter() - t0) * 1e3)


def sigma_for(source: Source) -> float:
    """The per-star sigma the solver assumes: half a pixel (the CLI's default) plus the simulated noise."""
    pix = DEFAULT_CENTROID_SIGMA_PX * source.camera.pixel_scale_rad
    noise = source.config.noise_arcsec * ARCSEC if source.config else 0.0
    return float(math.hypot(pix, noise))


def solve(source: Source, method: str, variant: str, mag_limit: float, solvers: Solvers, label=None) -> Run:
    """Centroid and identify `source` with `method`; derive the drawables. label(text): told what is
    being done (the viewer's progress line)."""
    say = label or (lambda _text: None)
    method, variant = check_method(method, variant)
    mag_limit = _num("magnitude limit", mag_limit, *MAG_RANGE)
    if method == BLIND:  # the default pipeline: no FOV, depth from the image, the camera fitted
        source, result = blind_solve(source, solvers)
        blind = blind_solver_for(solvers)[0]
        time_ms = {"simulate": source.simulate_ms, **result.time_ms} if source.truth else dict(result.time_ms)
        # (the result's own catalog: a narrow field is solved in the deep catalog, whose rows its matches index)
        catalog = result.catalog if result.catalog is not None else blind.catalog
        return make_run(with_fitted_camera(source, result), result, catalog, blind.max_stars, time_ms)
    source = fit_camera_blind(source, solvers)
    if source.depth_mag is not None:  # a user's image: the depth it shows, not the panel's limit
        mag_limit = source.depth_mag
    camera = source.camera
    if not solvers.cached(camera, method, variant, mag_limit, sigma_for(source)):
        say(f"loading the {method} database (built once per camera and catalog, then cached)")
    else:
        say(f"solving with {method} ({variant})")
    solver, lock = solvers.get(camera, method, variant, mag_limit, sigma_for(source))
    with lock:
        result = solver.solve_array(source.image, measure_all=True)  # every detected star drawn
    if source.rows_reversed:  # (the blind front end found a mirror image: the method read it turned over)
        result = mirrored(result)
    time_ms = {"simulate": source.simulate_ms, **result.time_ms} if source.truth else dict(result.time_ms)
    return make_run(source, result, solver.catalog, solver.max_stars, time_ms)


def blind_solver_for(solvers: Solvers) -> tuple[BlindSolver, threading.Lock]:
    """The viewer's one blind solver (its pattern database memory-mapped once, shared by the tabs)."""
    return solvers.get_or_build((BLIND,), lambda catalog: BlindSolver(catalog=catalog))


AUTO_DEPTH_MAX = 7.5  # deeper catalogs make the pair and triangle databases large


def fit_camera_blind(source: Source, solvers: Solvers) -> Source:
    """A user's image (no truth) gets its camera from the blind front end: FOV and distortion fitted to
    its stars, as `skyview solve --method M` does; the FOV typed in the panel is kept when the blind
    search fails. Simulated scenes keep their exact camera (the papers' calibrated mode)."""
    if source.truth is not None or source.fitted:
        return source
    source, res = blind_solve(source, solvers)
    return with_fitted_camera(source, res)


def blind_solve(source: Source, solvers: Solvers) -> tuple[Source, SolveResult]:
    """The blind search on the source's image, every detected star measured (to draw them all). A user's
    image found to be a mirror image of the sky (a star diagonal's, a flipped export: the result's
    `rows_reversed`) comes back with the image so turned, which the result's pixels describe: it is drawn on
    the sky the right way round. A simulated scene is never searched as one. A user's image that does not solve
    and is a negative of the sky (`pipeline.looks_negative`) comes back inverted, its stars bright."""
    blind, lock = blind_solver_for(solvers)
    with lock:
        result = blind.solve_array(source.image, measure_all=True, mirror=source.truth is None)
        if not result.solved and source.truth is None and looks_negative(source.image):
            # a negative of the sky: solved, and drawn, with its values inverted (its stars bright)
            neg = inverted(source.image)
            other = blind.solve_array(neg, measure_all=True, mirror=True)
            if other.solved:
                other.notes.append(NEGATIVE_NOTE)
                source, result = replace(source, image=neg), other
    if result.rows_reversed:  # a mirror image: the image turned over is the one the result describes
        source = replace(source, image=np.ascontiguousarray(source.image[::-1]), rows_reversed=not source.rows_reversed)
        result.rows_reversed = False
    return source, (mirrored(result) if source.rows_reversed else result)


def mirrored(result: SolveResult) -> SolveResult:
    """A result of the image turned over (`Source.rows_reversed`), said so when it solved."""
    result.rows_reversed = result.solved
    if result.solved and MIRROR_NOTE not in result.notes:
        result.notes.append(MIRROR_NOTE)
    return result


def with_fitted_camera(source: Source, result: SolveResult) -> Source:
    """The source drawn with the camera its solve fitted (FOV, k1, k2, depth): every drawing of the image
    (frustum, texture, rings, the identification) then agrees with the stars. The FOV a user typed, or a
    simulated scene's exact camera, stays when nothing was fitted."""
    if not (result.solved and result.camera_fitted):
        return source
    cam = result.camera
    depth = min(float(np.ceil(result.mag_limit * 4.0) / 4.0), AUTO_DEPTH_MAX) if result.mag_limit else None
    return dataclasses.replace(source, fov_deg=cam.fov_deg, k1=cam.k1, k2=cam.k2, fitted=True, depth_mag=depth,
                               lens=cam.model)


def make_run(source: Source, result: SolveResult, catalog: GuideCatalog, max_stars: int,
             time_ms: dict | None = None) -> Run:
    """A `Run` from a solved image: centroid outcomes (scored against the truth when simulated), step
    drawables, match triangles and the error against the truth."""
    ident = result.identification
    uv = result.centroids.uv
    n_used = min(len(uv), int(max_stars))
    matches = dict(ident.matches) if ident is not None and ident.identified else {}
    outcomes = centroid_outcomes(len(uv), n_used, matches, uv, catalog.hip, source.truth)
    drawables = step_views(ident.steps if ident else [], catalog.xyz, n_used, camera=result.camera, hip=catalog.hip)
    run = Run(source=source, result=result, catalog=catalog, n_used=n_used, outcomes=outcomes,
              drawables=drawables, matches=matches, match_groups=match_groups(matches, uv),
              time_ms=dict(result.time_ms) if time_ms is None else dict(time_ms))
    if source.truth and result.R is not None:
        run.error_arcsec = attitude_error_arcsec(result.R, np.asarray(source.truth["R"]))
        run.wrong_matches = sum(o == "wrong match" for o in outcomes)
    return run


def needs_sequence(method: str) -> bool:
    """Whether `method` identifies over a sequence of frames (a `SequenceIdentifier`): one image alone is
    then only its first step."""
    cls = METHODS.get(method)
    return cls is not None and is_sequence_method(cls)


SEQUENCE_NOTE = ("one frame only: this method identifies over a sequence of frames with known turns "
                 "(choose it as the Method to run a sequence)")


def compare(source: Source, mag_limit: float, solvers: Solvers, progress=None, methods=None) -> list[dict]:
    """Every method in METHODS (or `methods`), both variants, on the same image: one row each."""
    rows = []
    jobs = [(m, v) for m in (METHODS if methods is None else methods) for v in VARIANTS if m != BLIND]
    if methods is None or BLIND in methods:
        jobs.insert(0, (BLIND, "improved"))  # the default pipeline has one variant
    for k, (m, v) in enumerate(jobs):
        if progress is not None:
            progress(k, len(jobs), f"{m} ({v})")
        t0 = time.perf_counter()
        try:
            run = solve(source, m, v, mag_limit, solvers)
        except Exception as exc:  # one method's failure is a row of the table, not the end of the comparison
            reason = str(exc) if isinstance(exc, BadInput) else f"{type(exc).__name__}: {exc}"
            rows.append({"method": m, "variant": v, "status": "error", "reason": reason, "steps": 0,
                         "time_ms": (time.perf_counter() - t0) * 1e3, "error_arcsec": None, "matches": 0,
                         "wrong_matches": None})
            continue
        r = run.result
        reason = r.reason
        if needs_sequence(m) and not r.solved:
            reason = f"{SEQUENCE_NOTE}: {r.reason}" if r.reason else SEQUENCE_NOTE
        rows.append({"method": m, "variant": v, "status": r.status, "reason": reason,
                     "needs_sequence": needs_sequence(m) and not r.solved,
                     "steps": len(r.identification.steps) if r.identification else 0,
                     "time_ms": r.time_ms.get("total", float("nan")),
                     "error_arcsec": run.error_arcsec, "matches": len(r.matches),
                     "wrong_matches": run.wrong_matches})
    if progress is not None:
        progress(len(jobs), len(jobs), "done")
    return rows


def record_run(run: Run, path) -> Path:
    """Write a run as a Rerun recording (skyview.record.recording): the viewer's Export button."""
    try:
        from skyview.record.recording import record_solve
    except ImportError as exc:
        raise BadInput(f"the Rerun recorder is not available here ({exc})") from None
    info = record_solve(path, run.result, run.source.image, catalog=run.catalog, truth=run.source.truth,
                        force=True, meta={"image": run.source.name}, name=f"skyview-{run.result.method}")
    return Path(info.path)
