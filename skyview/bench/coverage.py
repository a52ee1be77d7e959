"""Sky coverage: where on the celestial sphere does a method identify? Swept on Dask.

`skyview coverage --method M --fov-deg F --mag-limit L [--variant paper|improved] [--nside N]
[--rolls K] [--grid healpix|sun] [--scheduler ADDRESS] [--out DIR]`

Orientations. `grid="healpix"`: the boresight at the centre of every pixel of an equal-area HEALPix
grid (`astropy_healpix`, nested order; 12 nside^2 directions), each with `rolls` roll angles, roll
r of direction p = 360 (r + u_p) / rolls deg with u_p uniform from the seed (every direction gets
its own roll offset, so K rolls sample the roll evenly). `grid="sun"`: the boresight grid of Sun et
al. 2017 (section 3.3; `skyview.experiments.ellipticity_sweep.grid`): RA 0..360 deg inclusive by 1 deg x
Dec -89..89 by 0.5 deg = 128,877 orientations, roll 0. `sample=N`: a seeded random N of the grid's
orientations (kept in the grid's order), e.g. to measure a subset of Sun's grid.

Frames are vector-level, as Sun et al.'s (`identify.synthetic.synthetic_frame`): the catalog stars
(Hp <= mag_limit, as the sky shows them) on the sensor, Gaussian tangent-plane noise of
`noise_rad` (default half a pixel), brightest first. Each identifier gets the same catalog. The
outcome of an orientation: "solved" (identified, every match right), "wrong" (identified with a wrong
match), "inconclusive" (not identified); with the stars in the field and the identification time.
A sequence method (the stochastic one: a single frame is only its prior update) is swept with its own
multi-frame identification: each orientation starts a sequence of `frames` (SEQUENCE_FRAMES) vector
frames turning FOV/3 about the camera y axis, the turn given, identified together
(`identify_sequence`); the orientation's outcome is that of the last frame identified.

Engine. The orientations are cut into tasks of `chunk` orientations; each task runs on a Dask worker
(`run_task`: the worker builds the catalog, camera, identifier and orientations once per configuration
and keeps them; a task's single frames are made in one pass, `synthetic_frames`, and identified
together, `identify_batch`: the same answers as one by one) and its records are written to
DIR/chunks/task-NNNNN.npz as it completes (atomic rename).
Run again on the same DIR with the same configuration and only the missing tasks run: an
interrupted sweep resumes. `scheduler=None` starts a `LocalCluster` on this machine (n_workers
processes, one thread each, 127.0.0.1, no dashboard); an address ("tcp://host:8786") uses that
cluster with no change in code (the workers need skyview installed); "inline" runs the tasks in
this process (the single-process answer the tests compare with): `skyview.bench.coverage_sweep`
runs it, `skyview.bench.executor` is the engine. The outputs (`coverage_map`):
coverage.json (summary), coverage.md (table), coverage.png (Mollweide map), coverage.rrd.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from skyview.core.errors import BadInput

GRIDS = ("healpix", "sun")
OUTCOMES = ("solved", "inconclusive", "wrong")
SOLVED, INCONCLUSIVE, WRONG = 0, 1, 2
DEFAULT_CHUNK = 64
MAX_NSIDE = 1024
SEQUENCE_FRAMES = 5  # a sequence method (stochastic) identifies over this many frames per orientation
DEFAULT_NOISE_PX = 0.5  # vector-level noise per axis, in pixels of the camera (as the centroider's default sigma)
BATCH_FRAMES = 256  # single frames made and identified together (a task's memory: this many frames at a time)
TASK_FIELDS = ("index", "ra_deg", "dec_deg", "roll_deg", "stars", "outcome", "time_ms")


@dataclass(frozen=True)
class CoverageConfig:
    method: str
    variant: str = "paper"
    fov_deg: float = 20.0
    mag_limit: float = 6.0
    nside: int = 8
    rolls: int = 2
    grid: str = "healpix"
    width: int = 1024
    noise_urad: float | None = None  # None: DEFAULT_NOISE_PX pixels
    seed: int = 0
    chunk: int = DEFAULT_CHUNK
    max_stars: int = 40  # the brightest stars of a field given to the identifier (as `MethodSolver`'s default)
    sample: int | None = None  # a seeded random subset of this many orientations of the grid (None: all)
    frames: int | None = None  # frames per orientation (a sequence); None: 1, SEQUENCE_FRAMES for a sequence method

    def checked(self) -> "CoverageConfig":
        from skyview.identify import METHODS, VARIANTS
        from skyview.identify.base import is_sequence_method

        if self.method not in METHODS:
            raise BadInput(f"unknown method {self.method!r}: choose from {', '.join(sorted(METHODS))}")
        if self.variant not in VARIANTS:
            raise BadInput(f"unknown variant {self.variant!r}: choose from {', '.join(VARIANTS)}")
        if self.grid not in GRIDS:
            raise BadInput(f"unknown grid {self.grid!r}: choose from {', '.join(GRIDS)}")
        if not (math.isfinite(self.fov_deg) and 0.5 <= self.fov_deg <= 90):
            raise BadInput(f"--fov-deg {self.fov_deg:g} must be between 0.5 and 90")
        if not (math.isfinite(self.mag_limit) and -2 < self.mag_limit <= 9):
            raise BadInput(f"--mag-limit {self.mag_limit:g} must be between -2 and 9 (the guide catalog's depth)")
        if not (1 <= self.nside <= MAX_NSIDE and self.nside & (self.nside - 1) == 0):
            raise BadInput(f"--nside {self.nside} must be a power of 2 between 1 and {MAX_NSIDE}")
        if not (1 <= self.rolls <= 360):
            raise BadInput(f"--rolls {self.rolls} must be between 1 and 360")
        if not (1 <= self.chunk <= 100_000):
            raise BadInput(f"--chunk {self.chunk} must be between 1 and 100000")
        if self.noise_urad is not None and not (math.isfinite(self.noise_urad) and self.noise_urad >= 0):
            raise BadInput("--noise-urad must be a non-negative number")
        if not (3 <= self.max_stars <= 1000):
            raise BadInput(f"--max-stars {self.max_stars} must be between 3 and 1000")
        if not (16 <= self.width <= 16384):
            raise BadInput(f"--width {self.width} must be between 16 and 16384 pixels")
        if self.sample is not None and not (1 <= self.sample <= 100_000_000):
            raise BadInput(f"--sample {self.sample} must be a positive number of orientations")
        sequence = is_sequence_method(METHODS[self.method])
        frames = (SEQUENCE_FRAMES if sequence else 1) if self.frames is None else int(self.frames)
        if not (1 <= frames <= 50):
            raise BadInput(f"--frames {self.frames} must be between 1 and 50")
        if frames > 1 and not sequence:
            raise BadInput(f"the {self.method} method identifies single frames: leave out --frames")
        return replace(self, frames=frames)

    @property
    def noise_rad(self) -> float:
        if self.noise_urad is not None:
            return float(self.noise_urad) * 1e-6
        from skyview.core.camera import Camera

        return DEFAULT_NOISE_PX * Camera.from_fov(self.fov_deg, self.width).pixel_scale_rad

    def to_dict(self) -> dict:
        return asdict(self)

    def describe(self) -> str:
        where = (f"HEALPix nside {self.nside} ({12 * self.nside ** 2} directions) x {self.rolls} rolls"
                 if self.grid == "healpix" else "Sun et al.'s grid (RA 1 deg x Dec 0.5 deg, roll 0)")
        if self.sample is not None:
            where += f", a random {self.sample} of them"
        if self.frames and self.frames > 1:
            where += (f"; each orientation a sequence of {self.frames} frames turning {self.fov_deg / 3:g} deg "
                      f"about the camera y axis (its answer: the last verified frame)")
        return (f"{self.method} ({self.variant}), {self.fov_deg:g} deg FOV, {self.width} px, Hp <= {self.mag_limit:g}, "
                f"noise {self.noise_rad * 1e6:.1f} urad, {where}, seed {self.seed}")


# ============================================================================ orientations

def orientations(cfg: CoverageConfig) -> np.ndarray:
    """(N, 3) RA, Dec, roll (degrees) of every orientation of the sweep, in task order (with `sample`:
    a seeded random subset of the grid's, in the grid's order)."""
    ori = _grid_orientations(cfg)
    if cfg.sample is not None and cfg.sample < len(ori):
        pick = np.random.default_rng([cfg.seed, 2]).choice(len(ori), size=int(cfg.sample), replace=False)
        ori = ori[np.sort(pick)]
    return ori


def _grid_orientations(cfg: CoverageConfig) -> np.ndarray:
    if cfg.grid == "sun":
        from skyview.experiments.ellipticity_sweep import grid

        ra, dec = grid(1.0, 0.5)
        R, D = np.meshgrid(ra, dec)
        return np.stack([R.ravel(), D.ravel(), np.zeros(R.size)], axis=1)
    from astropy_healpix import HEALPix

    hp = HEALPix(nside=cfg.nside, order="nested")
    lon, lat = hp.healpix_to_lonlat(np.arange(hp.npix))
    ra, dec = np.asarray(lon.deg), np.asarray(lat.deg)
    u = np.random.default_rng([cfg.seed, 1]).uniform(size=hp.npix)
    roll = 360.0 * (np.arange(cfg.rolls)[None, :] + u[:, None]) / cfg.rolls
    roll = (roll + 180.0) % 360.0 - 180.0
    return np.stack([np.repeat(ra, cfg.rolls), np.repeat(dec, cfg.rolls), roll.ravel()], axis=1)


def n_tasks(cfg: CoverageConfig, n: int | None = None) -> int:
    n = len(orientations(cfg)) if n is None else n
    return (n + cfg.chunk - 1) // cfg.chunk


# ============================================================================ one task (on a worker)

_WORKER: dict = {}


def _worker_state(cfg: CoverageConfig):
    key = json.dumps(cfg.to_dict(), sort_keys=True)
    if _WORKER.get("key") != key:
        from skyview.core.camera import Camera
        from skyview.core.catalog import load_guide_catalog
        from skyview.identify import make_identifier

        cat = load_guide_catalog().brighter_than(cfg.mag_limit)
        cam = Camera.from_fov(cfg.fov_deg, cfg.width)
        params = {"mag_zero_point": 0.0} if (cfg.frames or 1) > 1 else {}  # vector frames: brightness 10^(-0.4 Hp)
        ident = make_identifier(cfg.method, cat, cam, cfg.noise_rad if cfg.noise_rad > 0 else 1e-6,
                                variant=cfg.variant, **params)
        _WORKER.clear()
        _WORKER.update(key=key, cat=cat, cam=cam, ident=ident, ori=orientations(cfg))  # (made once, not per task)
    return _WORKER["cat"], _WORKER["cam"], _WORKER["ident"], _WORKER["ori"]


def _brightest(obs, k: int):
    if len(obs) <= k:
        return obs
    return replace(obs, vectors=obs.vectors[:k], uv=obs.uv[:k], brightness=obs.brightness[:k])


def _sequence_outcome(cfg: CoverageConfig, cat, cam, ident, R0: np.ndarray, first, rng) -> tuple[int, float]:
    """A sequence method's outcome at one orientation: cfg.frames vector frames from R0 (frame 0 is
    `first`), turning fov/3 about the camera y axis each (the turn given, as the method takes it),
    identified together (`identify_sequence`); the answer is the last frame identified: solved when
    its matches are all right. (outcome, identification time in ms for the whole sequence)"""
    from skyview.identify.synthetic import synthetic_frame
    from skyview.simulate.render import turn_about_camera_axis

    turn = turn_about_camera_axis("y", math.radians(cfg.fov_deg / 3.0))
    frames, Rk = [first], R0
    for _ in range(cfg.frames - 1):
        Rk = turn.apply(Rk)
        frames.append(synthetic_frame(cat, cam, Rk, cfg.noise_rad, rng))
    turns = [frames[k + 1].R @ frames[k].R.T for k in range(len(frames) - 1)]
    t0 = time.perf_counter()
    ids = ident.identify_sequence([_brightest(f.obs, cfg.max_stars) for f in frames], turns)
    ms = (time.perf_counter() - t0) * 1e3
    done = [k for k, r in enumerate(ids) if r.identified]
    if not done:
        return INCONCLUSIVE, ms
    k = done[-1]
    return (SOLVED if frames[k].all_right(ids[k].matches) else WRONG), ms


def run_task(cfg_dict: dict, task: int) -> dict[str, np.ndarray]:
    """Identify the orientations of task `task`: arrays of TASK_FIELDS (one entry per orientation).
    Orientation i's noise comes from the seed and i alone: any split into tasks gives the same answer."""
    from skyview.core.attitude import attitudes_from_radec_roll
    from skyview.identify.synthetic import synthetic_frame, synthetic_frames

    t_task = time.perf_counter()
    cfg = CoverageConfig(**cfg_dict)
    cat, cam, ident, ori = _worker_state(cfg)
    idx = np.arange(task * cfg.chunk, min((task + 1) * cfg.chunk, len(ori)))
    stars = np.zeros(len(idx), dtype=np.int32)
    outcome = np.zeros(len(idx), dtype=np.int8)
    times = np.zeros(len(idx))
    Rs = attitudes_from_radec_roll(*np.radians(ori[idx]).T)

    def rng(i):
        return np.random.default_rng([cfg.seed, int(i)])

    if (cfg.frames or 1) > 1:
        for n, i in enumerate(idx.tolist()):
            r = rng(i)
            f = synthetic_frame(cat, cam, Rs[n], cfg.noise_rad, r)
            stars[n] = len(f.obs)
            outcome[n], times[n] = _sequence_outcome(cfg, cat, cam, ident, Rs[n], f, r)
    else:
        # single frames, BATCH_FRAMES at a time (the memory of a task of any size bounded): made at once
        # (`synthetic_frames`: the same stars and noise draws as one by one) and identified together
        # (`identify_batch`: the same answers as one by one)
        for a in range(0, len(idx), BATCH_FRAMES):
            frames = synthetic_frames(cat, cam, Rs[a:a + BATCH_FRAMES], cfg.noise_rad,
                                      [rng(i) for i in idx[a:a + BATCH_FRAMES].tolist()])
            results = ident.identify_batch([_brightest(f.obs, cfg.max_stars) for f in frames])
            for n, (f, r) in enumerate(zip(frames, results), start=a):  # (each result let go once read)
                stars[n] = len(f.obs)
                times[n] = r.stats["time_s"] * 1e3
                outcome[n] = INCONCLUSIVE if not r.identified else SOLVED if f.all_right(r.matches) else WRONG
    return {"index": idx, "ra_deg": ori[idx, 0], "dec_deg": ori[idx, 1], "roll_deg": ori[idx, 2], "stars": stars,
            "outcome": outcome, "time_ms": times, "task_s": np.float64(time.perf_counter() - t_task)}


def load_results(out: str | Path) -> dict[str, np.ndarray]:
    """Every task's records, concatenated in orientation order."""
    files = sorted((Path(out) / "chunks").glob("task-*.npz"))
    files = [p for p in files if not p.stem.endswith(".tmp")]
    if not files:
        raise BadInput(f"{out} holds no coverage results")
    parts, busy = [], 0.0
    for p in files:
        with np.load(p) as z:
            parts.append({k: z[k] for k in TASK_FIELDS})
            busy += float(z["task_s"]) if "task_s" in z.files else 0.0
    res = {k: np.concatenate([p[k] for p in parts]) for k in TASK_FIELDS}
    order = np.argsort(res["index"], kind="stable")
    out = {k: v[order] for k, v in res.items()}
    out["worker_s"] = np.float64(busy)  # seconds the workers spent on the tasks (one core each)
    return out


def load_config(out: str | Path) -> CoverageConfig:
    path = Path(out) / "config.json"
    try:
        return CoverageConfig(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError) as exc:
        raise BadInput(f"{out} is not a coverage folder (no readable config.json: {exc})") from None
