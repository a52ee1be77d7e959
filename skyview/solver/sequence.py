"""Sequences of frames with known relative rotations: images -> designated stars -> attitude.

The stochastic method (`skyview.identify.stochastic`, Udomkesmalee et al. 1994) identifies over a
sequence of frames whose relative rotation is known. This module feeds it: it reads a sequence
(`load_sequence`: what `simulate.save_sequence` writes, or any `sequence.json` with the images and
the turns), centroids every frame, and runs the recursion (`SequenceSolver`, `solve_sequence`);
`skyview.bench.sequence` measures it, including the paper's own experiment.

The known turn between frames k and k+1 is dR_cam, in the CAMERA frame: v_cam_{k+1} = dR_cam @
v_cam_k (R_{k+1} = dR_cam @ R_k). That is what gyros measure and what `save_sequence` records as
relative[k]["dR_cam"]. A minimal sequence.json of one's own:

    {"images": ["a.png", "b.png"], "relative": [{"dR_cam": [[...], [...], [...]]}],
     "camera": {"width": 1024, "height": 1024, "fx": ..., "fy": ..., "cx": ..., "cy": ...}}

(or pass fov_deg instead of "camera"; image paths are relative to the sequence.json).

Magnitudes. The paper's statistics use the stars' magnitudes; an image gives brightness (summed
background-subtracted ADU). m = ZP - 2.5 log10(brightness), with the instrument's photometric zero
point ZP = 2.5 log10(zero_point_e_per_s * exposure_s / gain): the magnitude of a star that gives
1 ADU (`zero_point`; the simulator's sidecar carries its sensor, so ZP is known for simulated
sequences, as a calibrated flight instrument knows its own). The paper's 0.6 mag (1 sigma)
magnitude noise is applied to the MEASURED brightness: b' = b 10^(-0.4 e), e ~ N(0, sigma_mag), the
same as m' = m + e (`perturb_magnitudes`); the simulator itself renders by Hp.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from skyview.core.attitude import attitude_error_arcsec, quat_from_R, radec_roll_from_R
from skyview.core.camera import Camera
from skyview.core.catalog import DEFAULT_EPOCH, GuideCatalog, load_guide_catalog
from skyview.core.errors import BadInput, SkyviewError
from skyview.detect.centroids import Centroids, detect_centroids, load_image
from skyview.identify import make_identifier
from skyview.identify.base import Identification, Observation, is_sequence_method
from skyview.identify.synthetic import add_noise
from skyview.simulate.render import SensorModel
from skyview.solver.result import matched_stars, observation
from skyview.solver.solution_json import solution_dict

# The paper's experiment rendered without saturating Sirius (Hp -1.1 saturates at 0.1 s; at 0.01 s
# the limit is Hp -2.0) and with Hp 4.5 stars still at SNR ~ 20.
PAPER_SENSOR = SensorModel(exposure_s=0.01)
# The paper's Table 2 and 100-run figure (Udomkesmalee et al. 1994), for the reports.
PAPER_TABLE2 = {"above_prior": [138, 54, 15, 4, 1], "true_posterior": [0.021, 0.161, 0.685, 0.971, 0.997],
                "catalog_stars": 918}
PAPER_100_RUNS = {"mean": 0.976, "min": 0.709, "max": 0.999}
MATCH_PX = 3.0  # a centroid within this of a rendered star is that star (truth)
STARTS = ("betelgeuse", "random")
TURNS = ("ra", "pan")
LEVELS = ("image", "vector")
DESIGNATIONS = ("observed", "true")
DEFAULT_SEQUENCE_METHOD = "stochastic"  # what a sequence on disk is solved with when no method is named


# ------------------------------------------------------------------------------------ inputs

def zero_point(sensor: SensorModel | dict) -> float:
    """The magnitude of a star that gives 1 ADU of brightness: 2.5 log10(zp_e_per_s * t / gain)."""
    s = sensor if isinstance(sensor, SensorModel) else SensorModel.from_dict(
        {k: v for k, v in dict(sensor).items() if k in SensorModel.__dataclass_fields__})
    return float(2.5 * math.log10(s.zero_point_e_per_s * s.exposure_s / s.gain))


def perturb_magnitudes(obs: Observation, sigma_mag: float, rng: np.random.Generator) -> Observation:
    """The paper's magnitude noise on the measured brightness: b' = b 10^(-0.4 e), e ~ N(0, sigma_mag)."""
    if sigma_mag <= 0 or len(obs) == 0:
        return obs
    e = rng.normal(0.0, sigma_mag, size=len(obs))
    return Observation(obs.vectors, obs.uv, np.asarray(obs.brightness, dtype=np.float64) * 10.0 ** (-0.4 * e),
                       obs.sigma_rad)


def truth_rows(uv: np.ndarray, truth: dict, catalog: GuideCatalog) -> np.ndarray:
    """The catalog row of the star rendered at each position (within MATCH_PX); -1: none, a false
    star, or a star not in this catalog."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(uv), -1, dtype=np.int64)
    stars = truth.get("stars", [])
    pts = [(s.get("u_noisy", s["u"]), s.get("v_noisy", s["v"])) for s in stars]
    hips = [int(s["hip"]) for s in stars]
    pts += [(f["u"], f["v"]) for f in truth.get("false_stars", [])]
    hips += [-1] * len(truth.get("false_stars", []))
    if not pts or not len(uv):
        return out
    d, j = cKDTree(np.array(pts)).query(uv)
    for i, (dd, jj) in enumerate(zip(d, j)):
        if dd <= MATCH_PX and hips[jj] >= 0:
            try:
                out[i] = catalog.index_of(hips[jj])
            except KeyError:
                out[i] = -1
    return out


def vector_frame(catalog: GuideCatalog, camera: Camera, R: np.ndarray, sigma_rad: float, rng: np.random.Generator
                 ) -> tuple[Observation, np.ndarray]:
    """A frame without an image (the paper's own simulation): the catalog stars whose perturbed
    directions land on the sensor (stars just outside may come in), brightness 10^(-0.4 Hp) (zero
    point 0), brightest first. Returns the observation and the true catalog row of every star."""
    R = np.asarray(R, dtype=np.float64)
    cone = catalog.within(R[2], camera.half_diagonal_rad + 5.0 * sigma_rad)
    v = add_noise(catalog.xyz[cone] @ R.T, sigma_rad, rng) if len(cone) else np.zeros((0, 3))
    if len(v):
        uv, front = camera.project(v)
        keep = front & camera.in_image(uv)
    else:
        uv, keep = np.zeros((0, 2)), np.zeros(0, dtype=bool)
    rows = cone[keep]
    order = np.argsort(catalog.mag[rows], kind="stable")
    rows = rows[order]
    obs = Observation(vectors=v[keep][order], uv=uv[keep][order],
                      brightness=10.0 ** (-0.4 * catalog.mag[rows].astype(np.float64)), sigma_rad=float(sigma_rad))
    return obs, rows


class SequenceFrames(Sequence):
    """The images of a sequence on disk, read one at a time as they are asked for (memory flat over a long
    run, whatever its length). `read(k)`: frame k's image, or the BadInput that says why it cannot be used
    (unreadable, or not the sequence's size), for a loop that goes on past it; frames[k] raises that error."""

    def __init__(self, paths: list[Path], shape: tuple[int, int], first: tuple[int, np.ndarray] | None = None):
        self.paths = list(paths)
        self.shape = tuple(shape)
        self._first = first  # (index, image) of the frame load_sequence read for the size: not read twice

    def __len__(self) -> int:
        return len(self.paths)

    def read(self, k: int) -> np.ndarray | BadInput:
        if self._first is not None and self._first[0] == k:
            im, self._first = self._first[1], None
            return im
        im = _read_frame(self.paths[k])
        if isinstance(im, np.ndarray) and im.shape != self.shape:
            return BadInput(f"{self.paths[k].name} is {im.shape[1]}x{im.shape[0]}, the sequence's frames are "
                            f"{self.shape[1]}x{self.shape[0]}")
        return im

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        im = self.read(range(len(self))[k])
        if isinstance(im, BadInput):
            raise im
        return im


def _read_frame(path: Path) -> np.ndarray | BadInput:
    """The image at path, or the error that says why it cannot be read."""
    try:
        return load_image(path)
    except (BadInput, SkyviewError) as exc:
        return exc if isinstance(exc, BadInput) else BadInput(str(exc))


def frame_or_error(images, k: int) -> np.ndarray | BadInput:
    """Frame k of a list of images or of `SequenceFrames` (its image, or why it cannot be used)."""
    return images.read(k) if isinstance(images, SequenceFrames) else images[k]


@dataclass
class SequenceInput:
    """A sequence read from disk: its images (`SequenceFrames`: read as they are asked for), the turns
    between them (dR_cam), the camera, and the simulator's sensor and truth when the sidecar has them."""

    images: SequenceFrames
    turns: list[np.ndarray]
    camera: Camera
    paths: list[Path]
    sensor: dict | None = None
    truths: list[dict] | None = None


def _rotation(m: Any, what: str) -> np.ndarray:
    try:
        R = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise BadInput(f"{what} is not a 3x3 matrix") from None
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise BadInput(f"{what} is not a finite 3x3 matrix")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise BadInput(f"{what} is not a proper rotation matrix")
    return R


def load_sequence(path: str | Path, fov_deg: float | None = None) -> SequenceInput:
    """Read a sequence: a sequence.json (or the folder holding one) with "images" and "relative"
    (len(images) - 1 entries with "dR_cam"), as `simulate.save_sequence` writes it. The camera comes
    from fov_deg (and the image size) when given, else from the sidecar. Only the first frame that can be
    read is read here (the sequence's size); the others are read as they are solved (`SequenceFrames`),
    and one that cannot be read is that frame's error, not the sequence's (none readable: BadInput)."""
    p = Path(path)
    if p.is_dir():
        p = p / "sequence.json"
    if not p.exists():
        raise BadInput(f"sequence file {p} does not exist")
    try:
        meta = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BadInput(f"{p} is not readable JSON: {exc}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("images"), list) or not meta["images"]:
        raise BadInput(f"{p} has no list of images")
    names = meta["images"]
    rel = meta.get("relative", [])
    if not isinstance(rel, list) or len(rel) != len(names) - 1:
        raise BadInput(f"{p}: {len(names)} images need {len(names) - 1} relative turns, found "
                       f"{len(rel) if isinstance(rel, list) else 'none'}")
    turns = []
    for k, r in enumerate(rel):
        if not isinstance(r, dict) or "dR_cam" not in r:
            raise BadInput(f"{p}: relative[{k}] has no dR_cam")
        turns.append(_rotation(r["dR_cam"], f"{p}: relative[{k}].dR_cam"))
    folder = p.parent.resolve()
    paths = []
    for n in names:
        q = (p.parent / str(n))
        # image names are files in the sequence's own folder: "../x" or an absolute path would let a
        # sequence.json read any file of the machine
        if not isinstance(n, str) or Path(n).is_absolute() or folder not in q.resolve().parents:
            raise BadInput(f"{p}: image {n!r} is not a file in the sequence's folder")
        paths.append(q)
    # the first frame that can be read gives the sequence's size (and, with fov_deg, its camera); the others
    # are read as they are solved: one that cannot be read, or is another size, is that frame's error
    first, errors = None, []
    for k, q in enumerate(paths):
        im = _read_frame(q)
        if isinstance(im, np.ndarray):
            first = (k, im)
            break
        errors.append(im)
    if first is None:
        raise BadInput(f"none of the {len(paths)} images of {p} can be read (the first: {errors[0]})")
    H, W = first[1].shape
    images = SequenceFrames(paths, (H, W), first)
    frames = meta.get("frames") if isinstance(meta.get("frames"), list) else None
    cam_d = meta.get("camera") or (frames[0].get("camera") if frames and isinstance(frames[0], dict) else None)
    if fov_deg is not None:
        camera = Camera.from_fov(fov_deg, W, H)
    elif isinstance(cam_d, dict):
        try:
            camera = Camera.from_dict(cam_d)
        except (KeyError, TypeError, ValueError):
            raise BadInput(f"{p}: the camera in the sidecar is incomplete") from None
        if (camera.width, camera.height) != (W, H):
            raise BadInput(f"{p}: the camera is {camera.width}x{camera.height} but the images are {W}x{H}")
    else:
        raise BadInput(f"{p} does not describe the camera: give the field of view (fov_deg / --fov-deg)")
    sensor = frames[0].get("sensor") if frames and isinstance(frames[0], dict) else meta.get("sensor")
    truths = frames if frames and len(frames) == len(images) and all("stars" in f for f in frames) else None
    return SequenceInput(images=images, turns=turns, camera=camera, paths=paths,
                         sensor=sensor if isinstance(sensor, dict) else None, truths=truths)


# ------------------------------------------------------------------------------------ solving

@dataclass
class SequenceResult:
    """The outcome of a sequence: one Identification per frame, and the attitude of the latest
    verified frame (`frame`), or none."""

    identifications: list[Identification]
    catalog: GuideCatalog
    camera: Camera
    method: str
    variant: str
    centroids: list[Centroids] | None = None
    observations: list[Observation] = field(default_factory=list)
    truth: list[np.ndarray] | None = None
    true_R: list[np.ndarray] | None = None
    time_ms: dict[str, float] = field(default_factory=dict)
    database_key: dict = field(default_factory=dict)
    mag_zero_point: float | None = None
    errors: dict[int, str] = field(default_factory=dict)  # frame -> why it could not be used (no stars from it)

    @property
    def frame(self) -> int | None:
        done = [k for k, r in enumerate(self.identifications) if r.identified]
        return done[-1] if done else None

    @property
    def solved(self) -> bool:
        return self.frame is not None

    def truth_figures(self) -> list[dict]:
        """Per frame, the truth scored after the fact (`skyview.simulate.scoring.sequence_truth`: true_row,
        true_posterior, true_rank, true_sequence_posterior; None without truth): the method never sees it."""
        from skyview.simulate.scoring import sequence_truth

        return sequence_truth(self.identifications, self.truth)

    @property
    def R(self) -> np.ndarray | None:
        return None if self.frame is None else self.identifications[self.frame].R

    def wrong_matches(self, k: int) -> list[int]:
        """Observed indices of frame k whose reported identity is not the true one (needs truth)."""
        if self.truth is None:
            return []
        r = self.identifications[k]
        return [int(o) for o, c in r.matches.items() if int(self.truth[k][o]) != int(c)]

    def frame_dict(self, k: int) -> dict:
        """Frame k in the solution's one JSON shape (`skyview.solver.solution_json`), then the stochastic
        method's own figures for it (the identification's status, stars, hypotheses above the prior, the
        leading posteriors) and, with truth, how it scored."""
        r = self.identifications[k]
        st = r.stats
        ok = bool(r.identified)
        matches = matched_stars(self.catalog, self.observations[k].uv, r.matches) if ok else []
        out: dict[str, Any] = {"frame": k, **solution_dict(
            status="solved" if ok else ("error" if k in self.errors else "failed"), reason=r.reason or r.status, R=r.R if ok else None,
            p_false=r.verification.get("p_false") if ok else None, method=self.method, variant=self.variant,
            camera=self.camera, epoch=self.catalog.epoch,
            n_centroids=len(self.centroids[k]) if self.centroids is not None else 0, matches=matches)}
        out.update({
            "identification_status": r.status, "stars": st.get("stars"), "designated": st.get("designated"),
            "above_prior": st.get("above_prior"), "top_posterior": st.get("top_posterior"),
            "top_hips": st.get("top_hips", [])[:5], "posterior_top": st.get("posterior_top", [])[:5],
            "x": st.get("x"),
        })
        tf = self.truth_figures()[k] if self.truth is not None else {}
        if k in self.errors:
            out["error"] = self.errors[k]
        if tf.get("true_row") is not None:
            out["true_hip"] = int(self.catalog.hip[tf["true_row"]])
            out["true_posterior"] = tf["true_posterior"]
        if ok:
            if self.truth is not None:
                out["wrong_matches"] = len(self.wrong_matches(k))
            if self.true_R is not None:
                out["error_arcsec"] = attitude_error_arcsec(r.R, self.true_R[k])
        return out

    def to_dict(self) -> dict:
        out: dict[str, Any] = {"status": "solved" if self.solved else "failed", "method": self.method,
                               "variant": self.variant, "n_frames": len(self.identifications)}
        if self.solved:
            k = self.frame
            ra, dec, roll = radec_roll_from_R(self.R)
            out.update({"frame": k, "R": np.asarray(self.R).tolist(), "quaternion": quat_from_R(self.R).tolist(),
                        "ra_deg": math.degrees(ra), "dec_deg": math.degrees(dec), "roll_deg": math.degrees(roll)})
        else:
            last = self.identifications[-1] if self.identifications else None
            out["reason"] = last.reason if last is not None else "no frames"
        out.update({"frames": [self.frame_dict(k) for k in range(len(self.identifications))],
                    "catalog_stars": len(self.catalog), "mag_zero_point": self.mag_zero_point,
                    "camera": self.camera.to_dict(), "epoch": self.catalog.epoch,
                    "frames_unusable": sorted(self.errors),
                    "time_ms": {k: round(v, 3) for k, v in self.time_ms.items()},
                    "database_key": self.database_key})
        return out


class SequenceSolver:
    """Catalog + camera + a sequence method's database, ready for many sequences.

    method_params go to the identifier (e.g. mag_zero_point, mag_cut, Q, p_identify); only sequence
    methods (`is_sequence_method`: the stochastic one) can run a sequence.
    """

    def __init__(self, camera: Camera, method: str = DEFAULT_SEQUENCE_METHOD, *, mag_limit: float = 4.5,
                 sigma_rad: float | None = None, epoch: float = DEFAULT_EPOCH, catalog: GuideCatalog | None = None,
                 method_params: dict | None = None, variant: str = "paper", max_stars: int = 40,
                 k_sigma: float = 5.0):
        if sigma_rad is not None and not (np.isfinite(sigma_rad) and sigma_rad > 0):
            raise BadInput("the measurement sigma must be a positive number")
        if int(max_stars) < 1:
            raise BadInput("max_stars must be at least 1")
        base = catalog if catalog is not None else load_guide_catalog(epoch=epoch)
        self.catalog = base.brighter_than(mag_limit)
        if len(self.catalog) < 10:
            raise BadInput(f"only {len(self.catalog)} catalog stars are brighter than mag {mag_limit}")
        self.camera = camera
        self.method = method
        self.variant = variant
        self.max_stars = int(max_stars)
        self.k_sigma = float(k_sigma)
        self.sigma_rad = float(sigma_rad) if sigma_rad is not None else 0.5 * camera.pixel_scale_rad
        self.method_params = dict(method_params or {})
        self.identifier = make_identifier(method, self.catalog, camera, self.sigma_rad, variant=variant,
                                          **self.method_params)
        if not is_sequence_method(self.identifier):
            raise BadInput(f"method {method!r} identifies single frames only; use '{DEFAULT_SEQUENCE_METHOD}' for a "
                           f"sequence")

    def solve_observations(self, observations: list[Observation], turns: list[np.ndarray],
                           truth: list[np.ndarray] | None = None, designated: list[int | None] | None = None,
                           true_R: list[np.ndarray] | None = None) -> SequenceResult:
        t0 = time.perf_counter()
        ids = self.identifier.identify_sequence(observations, turns, designated=designated)
        return SequenceResult(identifications=ids, catalog=self.catalog, camera=self.camera, method=self.method,
                              variant=self.variant, observations=list(observations), truth=truth, true_R=true_R,
                              time_ms={"identify": (time.perf_counter() - t0) * 1e3},
                              database_key=self.identifier.database_key,
                              mag_zero_point=getattr(self.identifier, "mag_zero_point", None))

    def solve_images(self, images: list[np.ndarray] | SequenceFrames, turns: list[np.ndarray],
                     truths: list[dict] | None = None, sigma_mag: float = 0.0, seed: int = 0) -> SequenceResult:
        """Centroid every image and run the sequence. truths: the simulator's per-frame sidecars (for
        the record); sigma_mag > 0 perturbs the measured magnitudes (the paper's experiment). A frame of
        `SequenceFrames` that cannot be read (or a BadInput in the list) is a frame without stars: the
        method carries its hypotheses across it with the turn, and the result says why (`errors`)."""
        if not len(images):
            raise BadInput("a sequence needs at least one image")
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        cents, obs, errors = [], [], {}
        for k in range(len(images)):
            im = frame_or_error(images, k)
            if isinstance(im, BadInput):
                errors[k] = str(im)
                c = Centroids.empty(image_shape=(self.camera.height, self.camera.width))
            else:
                if im.ndim != 2 or im.shape != (self.camera.height, self.camera.width):
                    raise BadInput(f"image of shape {im.shape} does not fit the camera "
                                   f"{self.camera.width}x{self.camera.height}")
                c = detect_centroids(im, k_sigma=self.k_sigma)
            cents.append(c)
            obs.append(perturb_magnitudes(observation(c, self.camera, self.sigma_rad, self.max_stars), sigma_mag, rng))
        t1 = time.perf_counter()
        truth = true_R = None
        if truths is not None:
            truth = [truth_rows(o.uv, t, self.catalog) for o, t in zip(obs, truths)]
            true_R = [np.asarray(t["R"], dtype=np.float64) for t in truths]
        res = self.solve_observations(obs, turns, truth=truth, true_R=true_R)
        res.centroids = cents
        res.errors = errors
        for k, msg in errors.items():
            res.identifications[k].reason = f"the frame could not be used: {msg}"
        res.time_ms = {"centroid": (t1 - t0) * 1e3, **res.time_ms}
        return res


def solve_sequence(path: str | Path, *, fov_deg: float | None = None, mag_limit: float = 4.5,
                   sigma_rad: float | None = None, mag_zero_point: float | None = None, mag_cut: float | None = None,
                   variant: str = "paper", method_params: dict | None = None, use_truth: bool = True,
                   method: str = DEFAULT_SEQUENCE_METHOD, **kwargs) -> SequenceResult:
    """Solve a sequence on disk (see `load_sequence`) with a sequence method (the stochastic one).

    The photometric zero point comes from mag_zero_point, else from the simulator's sensor in the
    sidecar; with one, stars fainter than mag_cut (default mag_limit + 0.25) stay out of the
    statistics. Without one, mu_m is used relative to the designated star and every detected star
    counts. Other keyword arguments go to `SequenceSolver` (epoch, max_stars, k_sigma, catalog).
    """
    seq = load_sequence(path, fov_deg)
    params = dict(method_params or {})
    zp = mag_zero_point
    if zp is None and seq.sensor is not None:
        try:
            zp = zero_point(seq.sensor)
        except (BadInput, TypeError, ValueError):
            zp = None
    if zp is not None:
        params.setdefault("mag_zero_point", float(zp))
        params.setdefault("mag_cut", float(mag_limit + 0.25 if mag_cut is None else mag_cut))
    elif mag_cut is not None:
        raise BadInput("a magnitude cut needs the photometric zero point (mag_zero_point / --mag-zero-point)")
    solver = SequenceSolver(seq.camera, method, mag_limit=mag_limit, sigma_rad=sigma_rad,
                            method_params=params, variant=variant, **kwargs)
    return solver.solve_images(seq.images, seq.turns, seq.truths if use_truth else None)
