"""Image -> centroids -> unit vectors -> identification -> verified attitude.

`Solver` holds what is slow to make (guide catalog, camera, the method's database) and solves many
images; `solve_image` is the one-call API. The CLI (`skyview solve`) and the bench both go through
`Solver`, so what is measured is what users run.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from skyview.attitude import ESTIMATORS, RAD_TO_ARCSEC, quat_from_R, radec_roll_from_R
from skyview.camera import Camera
from skyview.catalog import DEFAULT_EPOCH, GuideCatalog, load_guide_catalog
from skyview.centroid import Centroids, detect_centroids, load_image
from skyview.errors import BadInput
from skyview.identify import make_identifier
from skyview.identify.base import Identification, Observation

SOLVED = "solved"
NOT_SOLVED = "failed"
DEFAULT_CENTROID_SIGMA_PX = 0.5


@dataclass
class SolveResult:
    status: str  # "solved" | "failed"
    reason: str
    method: str
    variant: str
    camera: Camera
    centroids: Centroids
    identification: Identification | None
    R: np.ndarray | None = None
    sigma_boresight_arcsec: float | None = None
    sigma_roll_arcsec: float | None = None
    matches: list[dict] = field(default_factory=list)  # [{index, u, v, hip, mag}]
    time_ms: dict[str, float] = field(default_factory=dict)
    database_key: dict[str, Any] = field(default_factory=dict)
    epoch: float = DEFAULT_EPOCH
    sigma_rad: float = 0.0  # assumed per-star direction sigma
    sigma_measured_rad: float | None = None  # from the match residuals (a posteriori)
    residuals_arcsec: list[float] = field(default_factory=list)

    @property
    def solved(self) -> bool:
        return self.status == SOLVED

    def to_dict(self) -> dict:
        out: dict[str, Any] = {"status": self.status}
        if self.reason:
            out["reason"] = self.reason
        if self.R is not None:
            ra, dec, roll = radec_roll_from_R(self.R)
            out.update({
                "R": self.R.tolist(),
                "quaternion": quat_from_R(self.R).tolist(),
                "ra_deg": float(np.degrees(ra)),
                "dec_deg": float(np.degrees(dec)),
                "roll_deg": float(np.degrees(roll)),
                "sigma_arcsec": {"boresight": self.sigma_boresight_arcsec, "roll": self.sigma_roll_arcsec},
            })
        ident = self.identification
        out.update({
            "method": self.method,
            "variant": self.variant,
            "matches": self.matches,
            "n_centroids": len(self.centroids),
            "n_matches": len(self.matches),
            "verification": _jsonable(ident.verification) if ident else {},
            "identification": {"status": ident.status, "steps": len(ident.steps),
                               **_jsonable(ident.stats)} if ident else None,
            "time_ms": {k: round(v, 3) for k, v in self.time_ms.items()},
            "database_key": self.database_key,
            "epoch": self.epoch,
            "sigma_assumed_arcsec": self.sigma_rad * RAD_TO_ARCSEC,
            "sigma_measured_arcsec": (None if self.sigma_measured_rad is None
                                      else self.sigma_measured_rad * RAD_TO_ARCSEC),
            "camera": self.camera.to_dict(),
        })
        return out


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    return obj


class Solver:
    """A configured solver: catalog + camera + method database, ready for many images."""

    def __init__(self, camera: Camera, method: str = "angle", *, mag_limit: float = 6.0,
                 sigma_rad: float | None = None, epoch: float = DEFAULT_EPOCH,
                 catalog: GuideCatalog | None = None, estimator: str = "svd", max_stars: int = 40,
                 k_sigma: float = 5.0, method_params: dict | None = None, variant: str = "paper"):
        if estimator not in ESTIMATORS:
            raise BadInput(f"unknown estimator {estimator!r}: choose from {', '.join(ESTIMATORS)}")
        if sigma_rad is not None and not (np.isfinite(sigma_rad) and sigma_rad > 0):
            raise BadInput("the measurement sigma must be a positive number")
        if max_stars < 2:
            raise BadInput("max_stars must be at least 2")
        t0 = time.perf_counter()
        base = catalog if catalog is not None else load_guide_catalog(epoch=epoch)
        self.catalog = base.brighter_than(mag_limit)
        if len(self.catalog) < 10:
            raise BadInput(f"only {len(self.catalog)} catalog stars are brighter than mag {mag_limit}")
        t1 = time.perf_counter()
        self.camera = camera
        self.method = method
        self.estimator = estimator
        self.max_stars = int(max_stars)
        self.k_sigma = float(k_sigma)
        self.sigma_rad = float(sigma_rad) if sigma_rad is not None else DEFAULT_CENTROID_SIGMA_PX * camera.pixel_scale_rad
        self.variant = variant
        self.method_params = dict(method_params or {})
        self.identifier = make_identifier(method, self.catalog, camera, self.sigma_rad, variant=variant,
                                          **(method_params or {}))
        t2 = time.perf_counter()
        self.setup_ms = {"catalog_load": (t1 - t0) * 1e3, "database_load": (t2 - t1) * 1e3}

    # ------------------------------------------------------------------ stages
    def observation(self, centroids: Centroids) -> Observation:
        n = min(len(centroids), self.max_stars)
        uv = centroids.uv[:n]
        return Observation(vectors=self.camera.unproject(uv) if n else np.zeros((0, 3)), uv=uv,
                           brightness=centroids.brightness[:n], sigma_rad=self.sigma_rad)

    def solve_array(self, image: np.ndarray) -> SolveResult:
        if image.ndim != 2:
            raise BadInput(f"expected a single-channel image, got shape {image.shape}")
        if image.shape != (self.camera.height, self.camera.width):
            raise BadInput(f"image is {image.shape[1]}x{image.shape[0]} but the camera is "
                           f"{self.camera.width}x{self.camera.height}")
        t0 = time.perf_counter()
        centroids = detect_centroids(image, k_sigma=self.k_sigma)
        t1 = time.perf_counter()
        result = self.solve_centroids(centroids)
        result.time_ms = {"centroid": (t1 - t0) * 1e3, **result.time_ms}
        result.time_ms["total"] = result.time_ms["centroid"] + result.time_ms["solve"]
        return result

    def solve_centroids(self, centroids: Centroids) -> SolveResult:
        t0 = time.perf_counter()
        obs = self.observation(centroids)
        ident = self.identifier.identify(obs) if len(centroids) else None
        return result_from_identification(
            centroids, obs, ident, camera=self.camera, catalog=self.catalog, method=self.method,
            variant=self.variant, sigma_rad=self.sigma_rad, estimator=self.estimator,
            database_key=self.identifier.database_key, identify_ms=(time.perf_counter() - t0) * 1e3)

    def solve_path(self, path: str | Path) -> SolveResult:
        return self.solve_array(load_image(path))


def result_from_identification(centroids: Centroids, obs: Observation, ident: Identification | None, *,
                               camera: Camera, catalog: GuideCatalog, method: str, variant: str, sigma_rad: float,
                               estimator: str = "svd", database_key: dict | None = None,
                               identify_ms: float = 0.0) -> SolveResult:
    """The `SolveResult` of an identification of `obs` (the observation of `centroids`): the attitude
    from every match by `estimator`, its 1-sigma, the matches with their residuals. `Solver` uses it
    for each image; a sequence uses it for each of its frames (ident=None: nothing was identified
    because the image has no stars)."""
    t1 = time.perf_counter()
    common = dict(method=method, variant=variant, camera=camera, centroids=centroids,
                  database_key=database_key or {}, epoch=catalog.epoch, sigma_rad=sigma_rad)
    if ident is None or len(centroids) == 0:
        return SolveResult(status=NOT_SOLVED, reason="no stars found in the image (blank or empty sky)",
                           identification=None, time_ms={"identify": 0.0, "attitude": 0.0, "solve": 0.0},
                           **common)
    result = SolveResult(status=NOT_SOLVED, reason=ident.reason or ident.status, identification=ident, **common)
    if ident.identified:
        idx = np.array(sorted(ident.matches))
        rows = np.array([ident.matches[i] for i in idx])
        b, r = obs.vectors[idx], catalog.xyz[rows]
        est = ESTIMATORS[estimator](b, r, sigma_rad)
        result.status, result.reason = SOLVED, ""
        result.R = est.R
        # The reported 1-sigma uses the noise measured from the residuals when there are enough
        # matches (2n - 3 degrees of freedom >= 5), else the assumed sigma.
        resid = np.linalg.norm(np.cross(b, r @ est.R.T), axis=1)
        dof = 2 * len(idx) - 3
        scale = 1.0
        if dof >= 5:
            result.sigma_measured_rad = float(np.sqrt(np.sum(resid ** 2) / dof))
            scale = result.sigma_measured_rad / sigma_rad
        result.sigma_boresight_arcsec = est.sigma_boresight_arcsec * scale
        result.sigma_roll_arcsec = est.sigma_roll_arcsec * scale
        result.residuals_arcsec = (resid * RAD_TO_ARCSEC).tolist()
        result.matches = [{"index": int(i), "u": float(obs.uv[i, 0]), "v": float(obs.uv[i, 1]),
                           "hip": int(catalog.hip[k]), "mag": float(catalog.mag[k]),
                           "residual_arcsec": float(e * RAD_TO_ARCSEC)}
                          for i, k, e in zip(idx, rows, resid)]
    attitude_ms = (time.perf_counter() - t1) * 1e3
    result.time_ms = {"identify": identify_ms, "attitude": attitude_ms, "solve": identify_ms + attitude_ms}
    return result


_SOLVERS: dict[tuple, Solver] = {}


def solve_image(image: str | Path | np.ndarray, fov_deg: float, method: str = "angle", **kwargs) -> SolveResult:
    """Solve one image (a path or a 2-D array) for a camera of horizontal FOV `fov_deg`.

    Keyword arguments go to `Solver` (mag_limit, sigma_rad, epoch, estimator, max_stars, k_sigma,
    method_params, variant) plus `distortion=(k1, k2)`. Solvers are cached per configuration, so a second
    call reuses the loaded database.
    """
    img = load_image(image) if not isinstance(image, np.ndarray) else image
    if img.ndim != 2:
        raise BadInput(f"expected a single-channel image, got shape {img.shape}")
    k1, k2 = kwargs.pop("distortion", (0.0, 0.0))
    camera = Camera.from_fov(fov_deg, img.shape[1], img.shape[0], k1=k1, k2=k2)
    key = (camera, method, repr(sorted(kwargs.items())))
    solver = _SOLVERS.get(key)
    if solver is None:
        solver = _SOLVERS[key] = Solver(camera, method, **kwargs)
    return solver.solve_array(img)
