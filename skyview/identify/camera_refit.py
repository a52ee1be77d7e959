"""The end of a blind solve, for a hypothesis from any source: the camera fitted and the shared verification.

Given observed-to-catalog matches on a rough camera (a blind pattern at the FOV it implies, or a
calibrated method's answer at the FOV a user typed): the catalog stars of the frame, the brightest
`depth_factor` times as many as the centroids used, are projected; the camera is fitted to the matches
(`skyview.core.camera_fit`: attitude, focal length, k1 and k2 where the stars support them) and the
stars re-matched, twice; then the shared verification (`skyview.identify.verify`) with the fitted camera,
the catalog to the frame's depth and the measured residual noise. Only a verified answer is reported,
without the stars that a companion could blend with (`verify.resolved_matches`).
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from skyview.core.camera import Camera
from skyview.core.camera_fit import fit_camera
from skyview.core.catalog import GuideCatalog
from skyview.core.special import binomial_sf
from skyview.identify import database
from skyview.identify.base import Hypothesis, Identification, Identifier, PixelStars, Search, Step, VerificationFrame
from skyview.identify.verify import CALIBRATED, RADIUS_SIGMAS, NearStars, frame_stars, resolved_matches

CAP = 200  # catalog rows a step lists at most


@dataclass(frozen=True)
class BlindParams:
    """The blind search (angles in degrees)."""

    fov_min_deg: float = 5.0  # horizontal FOV searched when none is given
    fov_max_deg: float = 40.0
    pattern_stars: int = 16  # brightest centroids combined four at a time (in batches, brightest first)
    verify_stars: int = 40  # brightest centroids the frame is checked with
    ratio_tolerance: float = 0.006  # edge ratios agree within this
    ladder_deg2: float = 60.0  # an assumed FOV F covers the FOVs within a factor 1 + ladder_deg2 / F^2
    # the same through a fisheye, whose angles depend far less on the scale assumed than a pinhole's
    fisheye_ladder_deg2: float = 1500.0
    depth_factor: float = 2.0  # catalog stars projected per centroid used
    quick_radius_px: float = 4.0
    quick_threshold: float = 1e-3
    max_checks: int = 400  # quick checks at most
    time_budget_s: float = 5.0  # seconds of the search's own CPU time (`Search.cpu0`: not a slow disk's or a busy core's)


GROW_RADII = (4.0, 2.0, 1.0)  # `CameraRefit.refit(grow=True)`: its matchings' radii, in quick radii


class NearestPixels:
    """The nearest of a few points of the image (the brightest centroids, tens of them) to many others,
    within a radius: cKDTree.query(q, k=1, distance_upper_bound=r)'s answers (distance inf and index
    len(points) where none is within r), from one (queries x points) distance table, so that a solve
    needs no scipy.spatial (~0.2 s to import in every process)."""

    def __init__(self, points: np.ndarray):
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 2)

    def query(self, q: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(q, dtype=np.float64).reshape(-1, 2)
        n = len(self.points)
        if n == 0 or len(q) == 0:
            return np.full(len(q), np.inf), np.full(len(q), n, dtype=np.intp)
        diff = q[:, None, :] - self.points[None, :, :]
        d = np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2)
        j = np.argmin(d, axis=1)
        best = d[np.arange(len(q)), j]
        miss = ~(best <= distance_upper_bound)
        return np.where(miss, np.inf, best), np.where(miss, n, j)


class CameraRefit(Identifier):
    """The camera fitted to a hypothesis' stars and the hypothesis verified with it, on the full guide
    catalog (`name`: the method reported; `database_key`: the database the hypothesis came from). An
    `Identifier` whose hypotheses bring their own `VerificationFrame` (the fitted camera, the catalog to
    the frame's depth, the measured noise): the shared verification and the one `Identification`."""

    name = "blind"
    title = "the blind search"
    min_stars = 0  # the search says itself what it lacks (four stars for a pattern, two matches for a refit)
    statistic = CALIBRATED
    threshold = None
    radius_sigmas = RADIUS_SIGMAS
    sigma_rad = float("nan")  # every hypothesis brings the noise measured from its fit
    camera = None  # ... and the camera fitted to it

    def __init__(self, catalog: GuideCatalog, params: BlindParams | None = None, *, name: str | None = None,
                 database_key: dict | None = None):
        self.catalog = database.with_cached_sky_index(catalog)
        self.params = params or BlindParams()
        if name is not None:
            self.name = name
        self.database_key = database_key or {}
        self._depths: dict[float, tuple[GuideCatalog, np.ndarray]] = {}

    def hypotheses(self, search: Search):
        """A refit has no search of its own: its one hypothesis is given (`refit`)."""
        search.reasons.append("a refit verifies a given hypothesis: call refit()")
        return
        yield  # (a generator, as the template's drive expects)

    def catalog_to(self, mag: float) -> tuple[GuideCatalog, np.ndarray]:
        """The catalog to `mag` (rounded up to a quarter magnitude) and the row of each of its stars in the
        full one, cached with its tree."""
        m = min(math.ceil(mag * 4.0) / 4.0, float(self.catalog.mag.max()))
        depth = self._depths.get(m)
        if depth is None:
            keep = self.catalog.mag <= m
            depth = self._depths[m] = (self.catalog.select(keep, f"mag<={m:g}"), np.flatnonzero(keep))
        return depth

    def refit(self, uv: np.ndarray, matches: dict[int, int], camera: Camera, R: np.ndarray, *, checks: int = 1,
              steps: list[Step] | None = None, method: str | None = None, grow: bool = False) -> Identification:
        """A verified hypothesis of another source (observed index -> row of this catalog, on `camera` at
        attitude `R`), its camera fitted and verified again as a blind one is; `checks` hypotheses were
        tried to find it (the Bonferroni factor). The observed stars beyond verify_stars are not used.
        method: the method the result names (default: this refit's `name`). grow: the camera is another lens
        model fitted to stars near the centre, its scale only as good as they tell: the first matching reaches
        GROW_RADII times the quick radius (the stars farther out, where a scale error moves them most), each
        fit and matching after it closer."""
        search = self.begin(PixelStars(np.asarray(uv, dtype=np.float64).reshape(-1, 2), camera.width, camera.height))
        if method is not None:
            search.result.method = method
        search.steps.extend(steps or [])
        return self.run(search, self._refitted(search, matches, camera, R, checks, grow))

    def _refitted(self, search: Search, matches: dict[int, int], camera: Camera, R: np.ndarray, checks: int,
                  grow: bool = False):
        uv = search.obs.uv
        n_obs = min(len(uv), self.params.verify_stars)
        seed = sorted(o for o in matches if o < n_obs)
        if len(seed) < 2:
            search.reasons.append(f"{len(seed)} of the matched stars are among the brightest {n_obs}: a fit needs two")
            return
        obs = np.array(seed, dtype=np.int64)
        rows = np.array([matches[o] for o in seed], dtype=np.int64)
        quick = {"agree": {}, "camera": camera, "R": np.asarray(R, dtype=np.float64)}
        ver = yield from self._fitted(search, uv, n_obs, obs, rows, quick, max(1, int(checks)), grow=grow)
        if not ver.passed:
            search.reasons.append(ver.reason)

    def _frame_rows(self, cam: Camera, R: np.ndarray, n_obs: int, near: NearStars) -> np.ndarray:
        """Catalog rows on the sensor for (cam, R) (`verify.frame_stars`; `near`: the hypothesis' stars fetched
        around the frame, kept from one fit to the next), the brightest depth_factor * n_obs of them."""
        on = frame_stars(self.catalog, cam, R, near=near)
        keep = max(int(self.params.depth_factor * n_obs), 8)
        return on[np.argsort(self.catalog.mag[on], kind="stable")[:keep]]

    def _match(self, uv, n_obs, obs_tree, cam, R, radius_px, near: NearStars):
        rows = self._frame_rows(cam, R, n_obs, near)
        if len(rows) == 0:
            return {}, rows
        puv, _ = cam.project(self.catalog.xyz[rows] @ R.T)
        d, j = obs_tree.query(puv, k=1, distance_upper_bound=radius_px)
        ok = np.isfinite(d)
        pairs = {}
        for ci in np.argsort(d)[: int(ok.sum())]:  # nearest first, each observed star once
            o = int(j[ci])
            if o not in pairs:
                pairs[o] = int(rows[ci])
        return pairs, rows

    def _quick(self, uv, n_obs, obs_tree, obs4, rows4, cam, R) -> dict:
        p = self.params
        near = NearStars(self.catalog)  # the catalog around this hypothesis' frame, for its fits too
        pairs, rows = self._match(uv, n_obs, obs_tree, cam, R, p.quick_radius_px, near)
        hyp = set(int(i) for i in obs4)
        agree = {o: c for o, c in pairs.items() if o not in hyp and c not in set(rows4.tolist())}
        n_tested = n_obs - 4
        density = len(rows) / (cam.width * cam.height)  # catalog stars per pixel
        p1 = min(1.0, density * math.pi * p.quick_radius_px ** 2)
        # the chance for this hypothesis alone: a filter before the camera fit, whose verification counts every
        # hypothesis checked (Bonferroni); counted here too, the true pattern of a field whose brightest
        # detections are not stars (a lit roof, a planet) came too late to pass the filter
        prob = float(min(1.0, binomial_sf(len(agree), n_tested, p1))) if agree else 1.0
        passed = prob < p.quick_threshold
        note = f"{len(agree)} of {n_tested} other stars land on the {len(rows)} brightest catalog stars, " \
               f"chance {prob:.1e}"
        return {"passed": passed, "n_agree": len(agree), "n_tested": n_tested, "p": prob, "note": note,
                "agree": agree, "camera": cam, "R": R, "near": near}

    def _fitted(self, search: Search, uv, n_obs, obs4, rows4, quick, checks, rows_reversed: bool = False,
                grow: bool = False) -> Generator:
        """The camera fitted to a hypothesis' stars (with those the quick check found), re-matched, then the
        hypothesis yielded for the shared verification on the fitted camera, the catalog to the frame's
        depth and the measured noise; `checks`: the hypotheses checked so far on this image (Bonferroni);
        rows_reversed: uv are the image's with its rows turned over (a mirror image), said in the stats when
        accepted. Returns the verification."""
        p = self.params
        obs_tree = NearestPixels(uv[:n_obs])
        matches = {**{int(o): int(c) for o, c in zip(obs4, rows4)}, **quick["agree"]}
        cam, R = quick["camera"], quick["R"]
        near = quick.get("near") or NearStars(self.catalog)
        fit, fitted_on = None, None
        # the attitude and the scale first, then the distortion too, each followed by matching again
        passes = ((p.quick_radius_px, False), (max(1.5, 0.5 * p.quick_radius_px), None))
        if cam.fisheye:  # a fisheye's distortion moves its stars by pixels from the first fit: fitted throughout
            passes = ((p.quick_radius_px, None), (p.quick_radius_px, None), (max(1.5, 0.5 * p.quick_radius_px), None))
        if grow:  # (`refit`'s grow: wide first, then closer)
            passes = tuple((k * p.quick_radius_px, None) for k in GROW_RADII) + passes[-1:]
        for radius, distortion in passes:
            idx = np.array(sorted(matches))
            fit = fit_camera(uv[idx], self.catalog.xyz[[matches[i] for i in idx]], cam, R,
                             fit_k1=distortion, fit_k2=distortion)
            cam, R, fitted_on = fit.camera, fit.R, dict(matches)
            pairs, _ = self._match(uv, n_obs, obs_tree, cam, R, max(radius, 3.0 * fit.rms_px), near)
            # (grow: the seed came through another lens and is not forced into the stars matched through this one)
            matches = dict(pairs) if grow and len(pairs) >= 4 else {**{int(o): int(c) for o, c in zip(obs4, rows4)},
                                                                     **pairs}
        idx = np.array(sorted(matches))
        if matches != fitted_on:  # the last matching changed the stars: fit once more
            fit = fit_camera(uv[idx], self.catalog.xyz[[matches[i] for i in idx]], cam, R)
            cam, R = fit.camera, fit.R
        search.steps.append(Step("fit", f"camera fitted to {len(idx)} stars: FOV {cam.fov_deg:.3f} deg, "
                                        f"k1 {cam.k1:+.4f}, k2 {cam.k2:+.4f}, residual {fit.rms_px:.2f} px per axis",
                                 observed=[int(i) for i in idx], catalog=[int(matches[i]) for i in idx][:CAP],
                                 numbers={"fov_deg": cam.fov_deg, "k1": cam.k1, "k2": cam.k2, "rms_px": fit.rms_px,
                                          "stars": len(idx)}))
        # the shared verification: the fitted camera, the catalog to the frame's depth, measured noise
        frame = self._frame_rows(cam, R, n_obs, near)
        mag_limit = float(self.catalog.mag[frame].max()) if len(frame) else float(self.catalog.mag.max())
        cat, parent_rows = self.catalog_to(mag_limit)
        sigma_px = max(fit.rms_px if np.isfinite(fit.rms_px) else 0.5, 0.25)
        sigma_rad = sigma_px * cam.pixel_scale_rad
        deep = self.catalog.mag[rows4] <= cat.mag.max()  # the hypothesis' stars in the depth's catalog
        if grow:  # the hypothesis: the seed's stars that this lens matched to the same catalog stars
            deep &= np.array([matches.get(int(o)) == int(c) for o, c in zip(obs4, rows4)], dtype=bool)
        hyp = dict(zip(np.asarray(obs4)[deep].tolist(), np.searchsorted(parent_rows, rows4[deep]).tolist()))
        found = {"checks": checks, "fov_deg": cam.fov_deg, "k1": cam.k1, "k2": cam.k2, "mag_limit": mag_limit,
                 "fit_rms_px": fit.rms_px, **({"rows_reversed": True} if rows_reversed else {})}

        def accepted(ver) -> None:  # reported without the stars a companion could blend with
            result = search.result
            result.matches = resolved_matches(dict(ver.matches), self.catalog, cam.pixel_scale_rad)
            result.camera, result.mag_limit, result.sigma_rad = cam, mag_limit, sigma_rad
            search.stats.clear()
            search.stats.update(found, unresolved_pairs_left_out=len(ver.matches) - len(result.matches))

        return (yield Hypothesis(matches=hyp, count=checks - search.n_hypotheses,
                                 numbers={"fov_deg": cam.fov_deg, "mag_limit": mag_limit}, on_accept=accepted,
                                 frame=VerificationFrame(cam.unproject(uv[:n_obs]), cat, cam, sigma_rad, parent_rows)))
