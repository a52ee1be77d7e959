"""What every solver shares around an identifier: centroids in, `SolveResult` out.

`observation` turns the brightest centroids into the identifier's input (camera-frame unit vectors,
brightness, the direction sigma): `MethodSolver`, `BlindSolver`, `SequenceSolver` and the viewer's runs all
call it. `result_from_identification` turns an identification back into a `SolveResult`: the attitude
from every match, its 1-sigma from the residuals, and the matches with the catalog rows they refer to
(HIP, RA/Dec at the catalog's epoch, magnitude), so a sink (JSON, text, the typed API, a recording)
never re-opens the catalog to name a matched star. `SolveResult.catalog` is the catalog the solver
used, the one the identification's step rows index.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from skyview.core.attitude import ESTIMATORS, RAD_TO_ARCSEC, svd_attitude_remembered
from skyview.core.camera import Camera
from skyview.core.catalog import DEFAULT_EPOCH, GuideCatalog, designation
from skyview.core.jsonable import plain
from skyview.detect.centroids import Centroids
from skyview.identify.base import Identification, Observation
from skyview.solver.solution_json import solution_dict

SOLVED = "solved"
NOT_SOLVED = "failed"


def observation(centroids: Centroids, camera: Camera, sigma_rad: float, max_stars: int = 40) -> Observation:
    """The brightest `max_stars` centroids as camera-frame unit vectors, brightest first (the centroider's
    order), with their pixel positions, brightness and the per-star direction sigma."""
    n = min(len(centroids), int(max_stars))
    uv = centroids.uv[:n]
    return Observation(vectors=camera.unproject(uv) if n else np.zeros((0, 3)), uv=uv,
                       brightness=centroids.brightness[:n], sigma_rad=float(sigma_rad))


def matched_stars(catalog: GuideCatalog, uv: np.ndarray, matches: dict[int, int],
                  residuals_rad: np.ndarray | None = None) -> list[dict]:
    """The matches (observed index -> catalog row; `uv` the observed pixels) as [{index, u, v, hip,
    ra_deg, dec_deg, mag, residual_arcsec}], by observed index: the catalog rows they refer to, ready
    for any sink."""
    idx = sorted(matches)
    if not idx:
        return []
    rows = np.array([matches[i] for i in idx], dtype=np.int64)
    res = None if residuals_rad is None else (np.asarray(residuals_rad) * RAD_TO_ARCSEC).tolist()
    return _matched_rows(catalog, uv, np.array(idx, dtype=np.int64), rows, res)


def _matched_rows(catalog: GuideCatalog, uv: np.ndarray, idx: np.ndarray, rows: np.ndarray,
                  residuals_arcsec: list[float] | None) -> list[dict]:
    """`matched_stars` of the observed stars idx (increasing, not none) matched to the catalog rows
    `rows` (RA/Dec: `GuideCatalog.radec_deg_of`, the numbers of its table), with their residuals in
    arcsec (a list) or none."""
    ra, dec = catalog.radec_deg_of(rows)
    # Python numbers from tolist: what int() / float() of each array element gives
    cols = (idx.tolist(), *np.asarray(uv, dtype=np.float64)[idx].T.tolist(), catalog.hip[rows].tolist(),
            ra.tolist(), dec.tolist(), catalog.mag[rows].tolist())
    if residuals_arcsec is None:
        return [{"index": i, "u": u, "v": v, "hip": h, "name": designation(h), "ra_deg": a, "dec_deg": d, "mag": m}
                for i, u, v, h, a, d, m in zip(*cols)]
    return [{"index": i, "u": u, "v": v, "hip": h, "name": designation(h), "ra_deg": a, "dec_deg": d, "mag": m,
             "residual_arcsec": e} for i, u, v, h, a, d, m, e in zip(*cols, residuals_arcsec)]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross of two (n, 3) arrays (the same products and differences), without its axis handling."""
    c = np.empty(a.shape)
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    np.multiply(a1, b2, out=c[:, 0])
    c[:, 0] -= a2 * b1
    np.multiply(a2, b0, out=c[:, 1])
    c[:, 1] -= a0 * b2
    np.multiply(a0, b1, out=c[:, 2])
    c[:, 2] -= a1 * b0
    return c


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
    matches: list[dict] = field(default_factory=list)  # matched_stars: [{index, u, v, hip, ra_deg, dec_deg, mag, ...}]
    time_ms: dict[str, float] = field(default_factory=dict)
    database_key: dict[str, Any] = field(default_factory=dict)
    epoch: float = DEFAULT_EPOCH
    sigma_rad: float = 0.0  # assumed per-star direction sigma
    sigma_measured_rad: float | None = None  # from the match residuals (a posteriori)
    residuals_arcsec: list[float] = field(default_factory=list)
    mag_limit: float | None = None  # the catalog depth the solve used (Hp)
    camera_fitted: bool = False  # the camera (FOV, distortion) was fitted to the stars, not given
    notes: list[str] = field(default_factory=list)  # how the input was read, when it matters (FITS rows)
    rows_reversed: bool = False  # solved with the image's rows turned over (a mirror image, a FITS file's other order)
    catalog: GuideCatalog | None = field(default=None, repr=False)  # the solver's: the step rows index it
    # the blind searches that ran, in order: {"kind": "pinhole" | "narrow" | "fisheye", "fov_deg": [lo, hi],
    # "stars": centroids searched, "hypotheses": candidate attitudes checked, "solved": bool}
    searches: list[dict] = field(default_factory=list)

    @property
    def solved(self) -> bool:
        return self.status == SOLVED

    def to_dict(self) -> dict:
        """The solution's one JSON shape (`skyview.solver.solution_json`), then what this solve adds: the
        verification and identification statistics, the database, the assumed and measured sigma."""
        ident = self.identification
        ver = ident.verification if ident is not None and isinstance(ident.verification, dict) else {}
        out = solution_dict(
            status=self.status, reason=self.reason, notes=self.notes, R=self.R if self.solved else None,
            sigma_arcsec=(self.sigma_boresight_arcsec, self.sigma_roll_arcsec) if self.solved else None,
            p_false=ver.get("p_false") if self.solved else None, method=self.method, variant=self.variant,
            camera=self.camera, camera_fitted=self.camera_fitted, rows_reversed=self.rows_reversed and self.solved,
            mag_limit=self.mag_limit, epoch=self.epoch, n_centroids=self.centroids.n_detected, matches=self.matches,
            time_ms=self.time_ms)
        out.update({
            "verification": plain(ver, nan_as_none=True),
            "identification": {"status": ident.status, "steps": len(ident.steps),
                               **plain(ident.stats, nan_as_none=True)} if ident else None,
            "database_key": self.database_key,
            "sigma_assumed_arcsec": self.sigma_rad * RAD_TO_ARCSEC,
            "sigma_measured_arcsec": (None if self.sigma_measured_rad is None
                                      else self.sigma_measured_rad * RAD_TO_ARCSEC),
        })
        return out


def result_from_identification(centroids: Centroids, obs: Observation, ident: Identification | None, *,
                               camera: Camera, catalog: GuideCatalog, method: str, variant: str, sigma_rad: float,
                               estimator: str = "svd", database_key: dict | None = None,
                               identify_ms: float = 0.0) -> SolveResult:
    """The `SolveResult` of an identification of `obs` (the observation of `centroids`): the attitude
    from every match by `estimator`, its 1-sigma, the matches with their catalog rows and residuals.
    `MethodSolver` uses it for each image; a sequence uses it for each of its frames (ident=None: nothing was
    identified because the image has no stars)."""
    t1 = time.perf_counter()
    common = dict(method=method, variant=variant, camera=camera, centroids=centroids,
                  database_key=database_key or {}, epoch=catalog.epoch, sigma_rad=sigma_rad, catalog=catalog)
    if ident is None or len(centroids) == 0:
        hot = int(centroids.n_hot_pixels_rejected) if centroids is not None else 0
        reason = ("no stars found in the image (blank or empty sky)" if not hot else
                  f"no stars found in the image: its {hot} bright points are single pixels (or a few side by side) "
                  "with dark neighbours, taken for a sensor's hot pixels")
        return SolveResult(status=NOT_SOLVED, reason=reason,
                           identification=None, time_ms={"identify": 0.0, "attitude": 0.0, "solve": 0.0},
                           **common)
    result = SolveResult(status=NOT_SOLVED, reason=ident.reason or ident.status, identification=ident, **common)
    if ident.identified:
        idx = sorted(ident.matches)
        rows = np.array([ident.matches[i] for i in idx], dtype=np.int64)
        idx = np.array(idx, dtype=np.int64)
        b, r = obs.vectors[idx], catalog.xyz[rows]
        # the svd estimate from every match is the one the shared verification ended in: remembered
        est = (svd_attitude_remembered if estimator == "svd" else ESTIMATORS[estimator])(b, r, sigma_rad)
        result.status, result.reason = SOLVED, ""
        result.R = est.R
        # The reported 1-sigma uses the noise measured from the residuals when there are enough
        # matches (2n - 3 degrees of freedom >= 5), else the assumed sigma.
        # (np.linalg.norm(c, axis=1) and np.sum(resid ** 2), written as the reductions they are)
        c = _cross(b, r @ est.R.T)
        resid = np.sqrt(np.add.reduce(c * c, axis=1))
        dof = 2 * len(idx) - 3
        scale = 1.0
        if dof >= 5:
            result.sigma_measured_rad = math.sqrt(float(np.add.reduce(resid * resid)) / dof)
            scale = result.sigma_measured_rad / sigma_rad
        result.sigma_boresight_arcsec = est.sigma_boresight_arcsec * scale
        result.sigma_roll_arcsec = est.sigma_roll_arcsec * scale
        result.residuals_arcsec = (resid * RAD_TO_ARCSEC).tolist()
        result.matches = _matched_rows(catalog, obs.uv, idx, rows, result.residuals_arcsec)
    attitude_ms = (time.perf_counter() - t1) * 1e3
    result.time_ms = {"identify": identify_ms, "attitude": attitude_ms, "solve": identify_ms + attitude_ms}
    return result
