"""The typed public API: ``skyview.solve(image) -> Solution`` and ``skyview.Solver`` for many images.

Conventions (docs/conventions.md):

- ``R`` is the 3x3 rotation matrix that maps ICRS unit vectors to the OpenCV camera frame
  (x right, y down, z along the boresight): ``v_cam = R @ v_icrs``. Its rows are the camera axes
  in ICRS; ``R[2]`` is the boresight.
- ``quaternion`` is the same rotation, scalar first ``[w, x, y, z]``, with ``w >= 0``.
- ``ra_deg``, ``dec_deg``: the boresight, ICRS, degrees, at the catalog's epoch (positions
  propagated with proper motion to ``epoch``, a Julian year).
- ``roll_deg``: the angle of image-up (the camera's -y axis) from north towards east, degrees.
- ``fov_deg``: the *horizontal* full field of view (across the image width), degrees.
- Pixel coordinates ``(u, v)`` are OpenCV's: the centre of the top-left pixel is ``(0, 0)``.

Everything here is a thin, typed layer over `skyview.solver.pipeline.solve_image`; the underlying
`skyview.solver.pipeline.SolveResult` (with the identification's recorded steps) stays available as
``Solution.result``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from skyview.core.catalog import designation
from skyview.core.errors import BadInput, SkyviewError
from skyview.solver.solution_json import solution_dict

if TYPE_CHECKING:  # imported lazily at run time: `import skyview` stays fast
    from astropy.coordinates import SkyCoord
    from astropy.wcs import WCS
    from scipy.spatial.transform import Rotation

    from skyview.core.camera import Camera
    from skyview.solver.pipeline import SolveResult

__all__ = ["solve", "Solver", "Solution", "Match", "NotSolvedError", "Status", "MethodName", "VariantName",
           "EstimatorName", "ImageInput"]

Status = Literal["solved", "failed"]
"""``"solved"``: a verified attitude; ``"failed"``: none (``Solution.reason`` says why)."""
MethodName = str  # a name in skyview.identify.METHODS (the registry: a method added there is accepted here)
"""The identification methods (``skyview.identify.METHODS``); ``None`` is the default blind pipeline."""
VariantName = Literal["paper", "improved"]
EstimatorName = Literal["svd", "q-method"]
ImageInput = str | Path | np.ndarray
"""A file path or a numpy array (grey, or BGR/BGRA colour)."""

DEFAULT_EPOCH = 2025.0  # = skyview.core.catalog.DEFAULT_EPOCH (not imported: it loads scipy)
_ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0


class NotSolvedError(SkyviewError, ValueError):
    """Asked a not-solved `Solution` for something only an attitude has (a SkyCoord, a WCS, ...)."""


@dataclass(frozen=True)
class Match:
    """One identified star: centroid ``index`` (in the centroid list, brightest first) at pixel
    ``(u, v)``, matched to the catalog star ``name`` ("HIP 32349", or "Gaia DR3 ..." for a star of the deep
    catalog that Hipparcos lacks), catalog number ``hip`` (its HIP number, or that Gaia DR3 source id), of
    catalog magnitude ``mag`` (Hp; Gaia G for a Gaia star) at ``ra_deg``, ``dec_deg``
    (ICRS, at the solution's epoch: the catalog row itself, no catalog to open); ``residual_arcsec`` is
    the angle between the observed direction and the catalog star under the solved attitude."""

    index: int
    u: float
    v: float
    hip: int
    mag: float
    residual_arcsec: float
    ra_deg: float
    dec_deg: float
    name: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"index": self.index, "u": self.u, "v": self.v, "hip": self.hip, "name": self.name,
                "ra_deg": self.ra_deg,
                "dec_deg": self.dec_deg, "mag": self.mag, "residual_arcsec": _finite(self.residual_arcsec)}


def _finite(x: float | None) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _readonly(a: np.ndarray | None) -> np.ndarray | None:
    if a is None:
        return None
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False, repr=False)
class Solution:
    """The outcome of solving one image. Immutable; every angle in degrees, every sigma in arcsec.
    The attributes that need an attitude are ``None`` where the image was not solved.

    Attributes:
        status: ``"solved"`` or ``"failed"``; ``solved`` is the same as a bool.
        reason: why it failed, with the likely cause and what to try ("" when solved).
        method: ``"blind"`` (the default pipeline's pattern search) or the identification method.
        variant: ``"paper"`` or ``"improved"``.
        R: 3x3 rotation ICRS -> OpenCV camera frame (read-only array).
        quaternion: ``R`` as ``[w, x, y, z]``, scalar first, ``w >= 0`` (read-only array).
        ra_deg, dec_deg: the boresight, ICRS.
        roll_deg: image-up from north towards east.
        fov_deg: horizontal full field of view of the camera the solution used (fitted or given).
        plate_scale_arcsec_per_px: at the image centre.
        k1, k2: OpenCV radial distortion of that camera.
        camera: the `skyview.core.camera.Camera` itself.
        camera_fitted: True when FOV and distortion were fitted to the stars, False when given.
        rows_reversed: True when the image solved with its rows turned over (a mirror image of the sky, as
            a star diagonal or a flipped export makes it; or a FITS file read the other way up): ``R``, the
            camera, the matches' ``u, v`` and ``wcs()`` are then those of the image so turned (its row ``v``
            is row ``H - 1 - v`` of the image as given; ``wcs(rows_as_given=True)`` maps the image as given).
        mag_limit: the catalog depth (Hp) used.
        sigma_boresight_arcsec, sigma_roll_arcsec: 1-sigma of the attitude.
        p_false: probability that the verified match is a chance alignment.
        matches: the identified stars (`Match`).
        n_centroids: stars (centroids) detected in the image.
        time_ms: milliseconds per stage ("centroid", "identify", "attitude", "total", ...).
        epoch: Julian year of the catalog positions.
        result: the underlying `skyview.solver.pipeline.SolveResult` (identification steps, ...).
        notes: how the input was read, where it matters (a FITS file solved with its rows the other
            way up, ...).
    """

    status: Status
    reason: str
    method: str
    variant: str
    R: np.ndarray | None
    quaternion: np.ndarray | None
    ra_deg: float | None
    dec_deg: float | None
    roll_deg: float | None
    fov_deg: float | None
    plate_scale_arcsec_per_px: float | None
    k1: float | None
    k2: float | None
    camera: Camera | None
    camera_fitted: bool
    rows_reversed: bool
    mag_limit: float | None
    sigma_boresight_arcsec: float | None
    sigma_roll_arcsec: float | None
    p_false: float | None
    matches: tuple[Match, ...]
    n_centroids: int
    time_ms: Mapping[str, float]
    epoch: float
    result: SolveResult = field(repr=False)
    notes: tuple[str, ...] = ()

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_result(cls, result: SolveResult) -> Solution:
        """Wrap a `skyview.solver.pipeline.SolveResult`."""
        from skyview.core.attitude import quat_from_R, radec_roll_from_R

        solved = result.solved and result.R is not None
        R = _readonly(result.R) if solved else None
        ra = dec = roll = None
        q = None
        if R is not None:
            ra_r, dec_r, roll_r = radec_roll_from_R(R)
            ra, dec, roll = float(np.degrees(ra_r)), float(np.degrees(dec_r)), float(np.degrees(roll_r))
            q = _readonly(quat_from_R(R))
        cam = result.camera if solved else None
        ident = result.identification
        p_false = None
        if solved and ident is not None:
            p_false = _finite(ident.verification.get("p_false")) if isinstance(ident.verification, dict) else None
        matches = tuple(Match(index=int(m["index"]), u=float(m["u"]), v=float(m["v"]), hip=int(m["hip"]),
                              mag=float(m["mag"]), residual_arcsec=float(m.get("residual_arcsec", float("nan"))),
                              ra_deg=float(m["ra_deg"]), dec_deg=float(m["dec_deg"]),
                              name=m.get("name") or designation(int(m["hip"])))
                        for m in result.matches)
        return cls(
            status="solved" if solved else "failed",
            reason="" if solved else (result.reason or "not solved"),
            method=result.method, variant=result.variant,
            R=R, quaternion=q, ra_deg=ra, dec_deg=dec, roll_deg=roll,
            fov_deg=float(cam.fov_deg) if cam is not None else None,
            plate_scale_arcsec_per_px=float(cam.pixel_scale_rad * _ARCSEC_PER_RAD) if cam is not None else None,
            k1=float(cam.k1) if cam is not None else None,
            k2=float(cam.k2) if cam is not None else None,
            camera=cam, camera_fitted=bool(result.camera_fitted) if solved else False,
            rows_reversed=bool(result.rows_reversed) if solved else False,
            mag_limit=_finite(result.mag_limit),
            sigma_boresight_arcsec=_finite(result.sigma_boresight_arcsec) if solved else None,
            sigma_roll_arcsec=_finite(result.sigma_roll_arcsec) if solved else None,
            p_false=p_false, matches=matches, n_centroids=result.centroids.n_detected,
            time_ms=MappingProxyType({str(k): float(v) for k, v in result.time_ms.items()}),
            epoch=float(result.epoch), result=result, notes=tuple(getattr(result, "notes", ())))

    # ------------------------------------------------------------------ views
    @property
    def solved(self) -> bool:
        """True when a verified attitude was found."""
        return self.status == "solved"

    def __repr__(self) -> str:
        if not self.solved:
            return f"<Solution failed by {self.method} ({self.n_centroids} centroids): {self.reason}>"
        return (f"<Solution solved by {self.method}: RA {self.ra_deg:.5f} deg, Dec {self.dec_deg:+.5f} deg, roll "
                f"{self.roll_deg:+.4f} deg, FOV {self.fov_deg:.4f} deg{' (fitted)' if self.camera_fitted else ''}, "
                f"{len(self.matches)} of {self.n_centroids} centroids matched>")

    def _require_solved(self, what: str) -> np.ndarray:
        if not self.solved or self.R is None:
            raise NotSolvedError(f"the image was not solved ({self.reason}): there is no {what}; "
                                 f"check Solution.solved first")
        return self.R

    def to_dict(self) -> dict[str, Any]:
        """The solution's one JSON shape (`skyview.solver.solution_json`: the keys of `skyview solve --json`
        and of each `solve-sequence --json` line), plain JSON-able types (None for a missing or non-finite
        number)."""
        return solution_dict(
            status=self.status, reason=self.reason, notes=self.notes, R=self.R,
            sigma_arcsec=(self.sigma_boresight_arcsec, self.sigma_roll_arcsec) if self.solved else None,
            p_false=self.p_false, method=self.method, variant=self.variant, camera=self.camera,
            camera_fitted=self.camera_fitted, rows_reversed=self.rows_reversed, mag_limit=self.mag_limit,
            epoch=self.epoch,
            n_centroids=self.n_centroids, matches=[m.to_dict() for m in self.matches], time_ms=self.time_ms)

    def to_json(self, indent: int | None = None) -> str:
        """``to_dict()`` as strict JSON (no NaN or Infinity)."""
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    def skycoord(self) -> SkyCoord:
        """The boresight as an astropy ``SkyCoord`` (ICRS). Raises NotSolvedError when not solved."""
        self._require_solved("boresight")
        from astropy import units as u
        from astropy.coordinates import SkyCoord

        return SkyCoord(ra=self.ra_deg * u.deg, dec=self.dec_deg * u.deg, frame="icrs")

    def wcs(self, *, rows_as_given: bool = False) -> WCS:
        """The solution as an astropy ``WCS`` (TAN, with SIP for k1/k2), pixel (0-based, as OpenCV's
        ``(u, v)`` with astropy's ``origin=0``) <-> ICRS: of the image the solution describes, or, with
        rows_as_given, of the image as it was given when it solved with its rows turned over
        (``rows_reversed``: a mirror image). Raises NotSolvedError when not solved."""
        R = self._require_solved("WCS")
        from skyview.io.wcs import solution_wcs

        return solution_wcs(R, self.camera, rows_reversed=rows_as_given and self.rows_reversed)

    def rotation(self) -> Rotation:
        """``R`` as a scipy ``Rotation`` (ICRS -> camera frame). Raises NotSolvedError when not solved."""
        R = self._require_solved("rotation")
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(R)


def _check_method(method: str | None, variant: str, estimator: str) -> None:
    from skyview.identify import METHODS, VARIANTS

    if method is not None and method not in METHODS:
        raise BadInput(f"unknown method {method!r}: choose from {', '.join(METHODS)} (or None: the default pipeline)")
    if variant not in VARIANTS:
        raise BadInput(f"unknown variant {variant!r}: choose from {', '.join(VARIANTS)}")
    if estimator not in ("svd", "q-method"):
        raise BadInput(f"unknown estimator {estimator!r}: choose from svd, q-method")


def _pipeline_kwargs(*, fov_deg: float | None, fov_error: float | None, method: str | None, variant: str,
                     mag_limit: float | None, distortion: tuple[float, float], epoch: float, max_stars: int,
                     k_sigma: float, estimator: str, sigma_arcsec: float | None,
                     method_params: Mapping[str, Any] | None, memory_mb: float | None,
                     progress: Callable[[str], None] | None, mirror: bool = True) -> dict[str, Any]:
    from skyview.solver.pipeline import check_fov_error

    _check_method(method, variant, estimator)
    check_fov_error(fov_error)
    if len(tuple(distortion)) != 2:
        raise BadInput("distortion is (k1, k2)")
    if method is None and method_params:
        raise BadInput("method_params go with a method (the default pipeline has no method parameters)")
    kw: dict[str, Any] = dict(fov_deg=fov_deg, method=method,
                              fov_error=None if fov_error is None else float(fov_error), mag_limit=mag_limit,
                              distortion=(float(distortion[0]), float(distortion[1])), variant=variant,
                              epoch=float(epoch), max_stars=int(max_stars), k_sigma=float(k_sigma),
                              estimator=estimator, memory_mb=memory_mb, progress=progress, mirror=bool(mirror))
    if sigma_arcsec is not None:
        if not (math.isfinite(sigma_arcsec) and sigma_arcsec > 0):
            raise BadInput("sigma_arcsec must be a positive number")
        kw["sigma_rad"] = float(sigma_arcsec) / _ARCSEC_PER_RAD
    if method_params:
        kw["method_params"] = dict(method_params)
    return kw


def solve(image: ImageInput, /, *, fov_deg: float | None = None, fov_error: float | None = None,
          method: MethodName | None = None, variant: VariantName = "paper", mag_limit: float | None = None,
          distortion: tuple[float, float] = (0.0, 0.0), epoch: float = DEFAULT_EPOCH, max_stars: int = 40,
          k_sigma: float = 5.0, estimator: EstimatorName = "svd", sigma_arcsec: float | None = None,
          method_params: Mapping[str, Any] | None = None, memory_mb: float | None = None,
          progress: Callable[[str], None] | None = None, mirror: bool = True) -> Solution:
    """Solve one star-field image: where was the camera pointing?

    Args:
        image: a file path (PNG, TIFF, JPEG, FITS, ...; 8/16-bit or float, grey or colour) or a numpy array,
            2-D grey or 3-D BGR/BGRA (OpenCV's channel order), any real dtype and memory layout.
        fov_deg: the camera's *horizontal* full field of view in degrees, if known. None: searched
            blind (about 2.5-81 deg).
        fov_error: how far ``fov_deg`` may be off, a fraction in [0, 1) (0.1 = +-10 %). 0 means exact:
            the papers' calibrated mode (no camera fitting). None: +-10 %, then, when nothing solves
            within it, the FOVs from a 2.5th to 2.5 times ``fov_deg`` (a note says how far it was off).
        method: None runs the default pipeline (blind four-star patterns, the camera's FOV and
            distortion fitted to the stars; then, given an FOV, the improved angle method at it).
            ``"angle"``, ``"triangle"``, ``"svd"``, ``"ellipticity"``, ``"stochastic"``, ``"genetic"``
            run that method, on the camera the blind front end fitted unless ``fov_error == 0``
            (then ``fov_deg`` is required).
        variant: with a method: ``"paper"`` (the paper's parameters) or ``"improved"``.
        mag_limit: catalog depth, Hipparcos magnitude Hp. None: from the image (the angle method's
            improved variant and the blind pipeline), else Hp 6.
        distortion: OpenCV radial distortion (k1, k2) of a calibrated camera (used with ``fov_error=0``).
        epoch: Julian year to which catalog positions are propagated (proper motion).
        max_stars: use at most this many of the brightest detected stars.
        k_sigma: detection threshold, in sigmas of the measured background noise.
        estimator: attitude estimator, ``"svd"`` (Markley) or ``"q-method"`` (Davenport).
        sigma_arcsec: 1-sigma direction error of a star, arcsec (default: half a pixel).
        method_params: the method's own parameters by their paper names (docs/methods.md).
        memory_mb: memory budget for building the blind pattern database, MB (default 1024).
        progress: called with a line of text while a database is built (the first run only).
        mirror: the blind searches take the image for a mirror image of the sky too (a star diagonal's, a
            flipped export), reported with its rows turned over (``Solution.rows_reversed``); False: never.

    Returns:
        A `Solution`; ``solution.solved`` is False (with ``solution.reason``) when no
        verified attitude was found. Bad input (a missing file, an impossible FOV, an unknown
        method) raises `skyview.BadInput`.

    Solvers are cached per configuration, so a second call reuses the loaded databases; for many
    images with the same settings `Solver` keeps the settings in one place.
    """
    from skyview.solver.pipeline import solve_image

    kw = _pipeline_kwargs(fov_deg=fov_deg, fov_error=fov_error, method=method, variant=variant, mag_limit=mag_limit,
                          distortion=distortion, epoch=epoch, max_stars=max_stars, k_sigma=k_sigma,
                          estimator=estimator, sigma_arcsec=sigma_arcsec, method_params=method_params,
                          memory_mb=memory_mb, progress=progress, mirror=mirror)
    fov, meth = kw.pop("fov_deg"), kw.pop("method")
    return Solution.from_result(solve_image(image, fov, meth, **kw))


class Solver:
    """Many images, one set of settings (the arguments of `solve`, checked once here).

    The catalog and the databases are loaded on the first image and kept (the pipeline's cache of
    configured solvers); later images only centroid and identify.

    Examples:
        >>> solver = skyview.Solver(fov_deg=11.4)
        >>> for path in paths:
        ...     sol = solver.solve(path)
    """

    def __init__(self, *, fov_deg: float | None = None, fov_error: float | None = None, method: MethodName | None = None,
                 variant: VariantName = "paper", mag_limit: float | None = None,
                 distortion: tuple[float, float] = (0.0, 0.0), epoch: float = DEFAULT_EPOCH, max_stars: int = 40,
                 k_sigma: float = 5.0, estimator: EstimatorName = "svd", sigma_arcsec: float | None = None,
                 method_params: Mapping[str, Any] | None = None, memory_mb: float | None = None,
                 progress: Callable[[str], None] | None = None, mirror: bool = True) -> None:
        if fov_deg is not None:
            from skyview.core.camera import check_fov_deg

            check_fov_deg(fov_deg)
        self._kwargs = _pipeline_kwargs(
            fov_deg=fov_deg, fov_error=fov_error, method=method, variant=variant, mag_limit=mag_limit,
            distortion=distortion, epoch=epoch, max_stars=max_stars, k_sigma=k_sigma, estimator=estimator,
            sigma_arcsec=sigma_arcsec, method_params=method_params, memory_mb=memory_mb, progress=progress,
            mirror=mirror)

    @property
    def settings(self) -> Mapping[str, Any]:
        """The settings every image is solved with (read-only)."""
        return MappingProxyType(dict(self._kwargs))

    def solve(self, image: ImageInput, /) -> Solution:
        """Solve one image with this solver's settings (see `solve`)."""
        from skyview.solver.pipeline import solve_image

        kw = dict(self._kwargs)
        fov, method = kw.pop("fov_deg"), kw.pop("method")
        return Solution.from_result(solve_image(image, fov, method, **kw))

    def __repr__(self) -> str:
        shown = ", ".join(f"{k}={v!r}" for k, v in self._kwargs.items() if v is not None and k != "progress")
        return f"skyview.Solver({shown})"
