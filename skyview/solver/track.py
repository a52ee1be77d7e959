"""Tracking mode for every identification method: solve once lost-in-space, then follow the stars.

Long (over 500 lines) because `Tracker` is one state machine (lost-in-space, predicted windows,
verification of the tracked matches, loss of lock) whose stages share its state; the rest is short.

`Tracker` solves the first frame lost-in-space (LIS) with the given method through `MethodSolver` (or, with
no method, the default pipeline: the blind solver, then the improved angle method at the given FOV,
as `solve_image` runs them). For every later frame it

1. predicts the attitude: the last solved attitude R_j turned by the known turn dR_cam from the
   sequence (gyros) when one is given, else by the angular rate estimated from the last two solved
   attitudes, else (one solved frame, no turn) left where it was;
2. predicts where the catalog stars land, and gives each a match bound from the covariance of that
   prediction: the attitude covariance of frame j, plus the rate's (from the two attitudes it came
   from), plus TURN_SIGMA per frame of prediction (an unknown change of rate, a gyro error; wider,
   STILL_SIGMA, when nothing is known of the motion). The bound of star i is
   RADIUS_SIGMAS sqrt(sigma^2 + s_i^2), s_i the largest standard deviation of its predicted
   position (`verify.predicted_sigma`, the same construction as `verify.star_radii`) and sigma the
   centroid direction noise;
3. measures the frame (`process`): only windows around the brightest TRACK_STARS predicted stars,
   all at once (`track_window.centroid_windows`: a (K, S, S) stack, border background, a
   Gaussian-weighted centroid per window); `Tracker(..., windows=False)` and `process_centroids`
   take whole-image centroids instead;
4. identifies the frame where the prediction expects it: `identify.tracking.TrackedIdentifier`, an
   `Identifier` whose hypotheses go through the template and the shared verification like the six
   methods'. The observed centroids are matched to the catalog stars around the predicted field by
   nearest neighbour within the bound (one-to-one; a centroid with two catalog stars within its bound is
   left out), refined once when some were left out; the hypotheses are the tracked matches' best spread
   three, tested by every other observed star (`verify.verify`; a windowed frame with the chance of one
   star taken within its window, `Observation.window_sr`), then, when those are refused or fewer than
   MIN_TRACK_MATCHES stars matched, the prediction itself (`verify.verify_prediction`): 2 matched stars
   (3 when the motion is unknown) on their predicted places, P(false) below the shared threshold. The
   hypotheses verified for the frame are counted together (Bonferroni). A passed verification extends
   and re-estimates the attitude from every agreeing star, exactly as for a lost-in-space solve.

Loss of lock (fewer stars, or the verification refused) falls back to LIS for that frame; a frame that neither solves is coasted on the motion model
(mode COASTING, for MAX_COAST_FRAMES at most) or reported failed, and the next one is predicted from the
last solved frame (the prediction's bound grows with the frames in between).

Each frame's `TrackFrame`: mode ("lost_in_space" | "tracking"), status, the attitude, the rotation
from the last solved frame (rotation vector of the camera body, camera axes of that frame, degrees:
the same convention as a sequence's relative[k]["turn_rotvec_cam_rad"]), the matches and the time.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from skyview.core.attitude import RAD_TO_ARCSEC, quat_from_R, radec_roll_from_R, svd_attitude
from skyview.core.camera import Camera
from skyview.core.catalog import DEFAULT_EPOCH, GuideCatalog, load_guide_catalog
from skyview.core.errors import BadInput
from skyview.detect.centroids import Centroids, detect_centroids
from skyview.detect.stars import detect_stars
from skyview.detect.windows import DEFAULT_PSF_SIGMA_PX, MAX_HALF_PX, PSF_REACH_SIGMAS, centroid_windows, window_centers
from skyview.identify.base import Identification, Observation
from skyview.identify.tracking import Prediction, TrackedIdentifier, match_radii, rotation_matrix, rotvec
from skyview.identify.verify import RADIUS_SIGMAS
from skyview.solver.pipeline import (
    ANGLE_MAX_DEPTH,
    BLIND,
    DEFAULT_CENTROID_SIGMA_PX,
    DEFAULT_FOV_ERROR,
    NOT_SOLVED,
    PAPER_MAG_LIMIT,
    SOLVED,
    BlindSolver,
    MethodSolver,
    SolveResult,
    as_image,
    blind_solver,
)
from skyview.solver.result import matched_stars, observation
from skyview.solver.solution_json import solution_dict

LOST_IN_SPACE = "lost_in_space"
TRACKING = "tracking"
MIN_TRACK_MATCHES = 3  # fewer tracked matches than this: lock is lost (two give an attitude, a third tests it)
TURN_SIGMA_RAD = float(np.radians(30.0 / 3600.0))  # 1 sigma per axis, per predicted frame (rate change, gyro)
STILL_SIGMA_RAD = float(np.radians(0.05))  # the motion is unknown (one solved frame, no turn given)
MAX_TRACK_TRIES = 2  # tracked hypotheses verified per frame before falling back to LIS
# a frame verified by the prediction alone needs this many matched stars: two when the motion is known (a turn
# given, or the rate of earlier attitudes), three when it is not (one solved frame, no turn)
PREDICTION_MIN_STARS = {"turn": 2, "rate": 2, "still": 3}
MAX_COAST_FRAMES = 5  # a frame that neither tracks nor solves lost-in-space is coasted on the motion model this long
COASTING = "coasting"
TRACK_STARS = 16  # a tracked frame measures windows around the brightest this many predicted stars
WINDOW_MARGIN_PX = 2.0  # a window's half-size: the match bound + the PSF's reach + this
FIELD_MARGIN_RAD = float(np.radians(0.5))  # catalog stars this far beyond the frame's corners are candidates


@dataclass
class TrackFrame:
    frame: int
    mode: str  # LOST_IN_SPACE | TRACKING | COASTING (the mode that produced the result, or coasting on the motion)
    status: str  # SOLVED | NOT_SOLVED
    reason: str = ""
    R: np.ndarray | None = None
    covariance: np.ndarray | None = None  # rad^2, camera axes
    relative_to: int | None = None  # the frame the relative rotation is from (the last solved one)
    relative_rotvec_rad: np.ndarray | None = None  # turn of the camera body since relative_to (camera axes)
    matches: list[dict] = field(default_factory=list)  # [{index, u, v, hip, mag}]
    n_centroids: int = 0
    p_false: float | None = None
    lost_lock: str = ""  # why tracking gave up on this frame (then LIS ran)
    predicted_by: str = ""  # "turn" | "rate" | "still" | "" (LIS only)
    time_ms: dict[str, float] = field(default_factory=dict)
    lis_result: SolveResult | None = None
    centroids: Centroids | None = None  # what the frame measured: window centroids when tracked in windows
    # the solution's context, stamped by the Tracker: the camera, the method (the tracker's for a tracked frame,
    # the lost-in-space solve's otherwise), the catalog depth and epoch
    camera: Camera | None = None
    camera_fitted: bool = False
    verified_by: str = ""  # a tracked frame: "hypothesis" (three matches tested by the rest) | "prediction"
    prediction: tuple | None = field(default=None, repr=False)  # (R, covariance) the frame was predicted at
    identification: Identification | None = field(default=None, repr=False)  # a tracked frame's (its steps)
    method: str | None = None
    variant: str | None = None
    mag_limit: float | None = None
    epoch: float | None = None

    @property
    def solved(self) -> bool:
        return self.status == SOLVED

    @property
    def relative_rotvec_deg(self) -> list[float] | None:
        return None if self.relative_rotvec_rad is None else np.degrees(self.relative_rotvec_rad).tolist()

    def to_dict(self) -> dict[str, Any]:
        """The solution's one JSON shape (`skyview.solver.solution_json`), then the frame's: its number,
        mode, prediction, why lock was lost, the turn since the last solved frame."""
        sigma = None
        if self.R is not None and self.covariance is not None:
            c = self.covariance
            sigma = (float(np.sqrt(0.5 * (c[0, 0] + c[1, 1])) * RAD_TO_ARCSEC), float(np.sqrt(c[2, 2]) * RAD_TO_ARCSEC))
        notes = self.lis_result.notes if self.lis_result is not None else ()
        out: dict[str, Any] = {"frame": self.frame, **solution_dict(
            status=self.status, reason=self.reason, notes=notes, R=self.R if self.solved else None,
            sigma_arcsec=sigma, p_false=self.p_false, method=self.method, variant=self.variant, camera=self.camera,
            camera_fitted=self.camera_fitted, mag_limit=self.mag_limit, epoch=self.epoch,
            n_centroids=self.n_centroids, matches=self.matches, time_ms=self.time_ms)}
        out.update({"mode": self.mode, "verified_by": self.verified_by or None, "predicted_by": self.predicted_by or None,
                    "lost_lock": self.lost_lock})
        if self.mode == COASTING and self.prediction is not None:
            R, P = self.prediction
            a, d, r = radec_roll_from_R(R)
            out["coasted"] = {"R": np.asarray(R).tolist(), "quaternion": quat_from_R(R).tolist(),
                              "ra_deg": float(np.degrees(a)), "dec_deg": float(np.degrees(d)),
                              "roll_deg": float(np.degrees(r)),
                              "sigma_arcsec": {"boresight": float(np.sqrt(0.5 * (P[0, 0] + P[1, 1])) * RAD_TO_ARCSEC),
                                               "roll": float(np.sqrt(P[2, 2]) * RAD_TO_ARCSEC)}}
        if self.relative_rotvec_rad is not None:
            out["relative_to"] = self.relative_to
            out["relative_rotvec_deg"] = self.relative_rotvec_deg
            out["relative_angle_deg"] = float(np.degrees(np.linalg.norm(self.relative_rotvec_rad)))
        return out


def body_turn_rotvec(R_from: np.ndarray, R_to: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of the camera body's turn from attitude R_from to R_to, in the camera axes
    of R_from: rotvec(dR_cam^T), dR_cam = R_to R_from^T (a sequence's turn_rotvec_cam_rad)."""
    dR = np.asarray(R_to) @ np.asarray(R_from).T
    return Rotation.from_matrix(dR.T).as_rotvec()


def _subset(c: Centroids, keep: np.ndarray) -> Centroids:
    """The centroids at indices keep (order kept)."""
    if len(keep) == len(c):
        return c
    return replace(c, uv=c.uv[keep], brightness=c.brightness[keep], peak=c.peak[keep], n_pixels=c.n_pixels[keep],
                   saturated=c.saturated[keep], elongated=c.elongated[keep], edge=c.edge[keep],
                   blended=c.blended[keep], axis_ratio=c.axis_ratio[keep])


class Tracker:
    """Lost-in-space once, then tracking, frame after frame (`process`), for any method.

    camera: the camera (its FOV and distortion); None only with method None (the blind pipeline then
    fits it on the first lost-in-space frame, and tracking uses the fitted camera). method: an
    identification method for lost-in-space (through `MethodSolver`), or None for the default pipeline.
    mag_limit: the catalog depth for tracking and for the method (default Hp 6, as `solve_image`'s
    methods; with method None and no depth given, tracking then goes as deep as the first lost-in-space solve,
    whose depth the blind pipeline takes from the image: `_follow_depth`). Other keyword arguments go to
    `MethodSolver` (method_params, estimator, ...).
    """

    def __init__(self, camera: Camera | None = None, method: str | None = None, *, mag_limit: float | None = None,
                 sigma_rad: float | None = None, variant: str = "paper", epoch: float = DEFAULT_EPOCH,
                 catalog: GuideCatalog | None = None, max_stars: int = 40, k_sigma: float = 5.0,
                 method_params: dict | None = None, fov_error: float = DEFAULT_FOV_ERROR,
                 turn_sigma_rad: float = TURN_SIGMA_RAD, still_sigma_rad: float = STILL_SIGMA_RAD,
                 min_matches: int = MIN_TRACK_MATCHES, blind: BlindSolver | None = None, progress=None,
                 windows: bool = True, track_stars: int = TRACK_STARS):
        if method == BLIND:
            method = None
        if method is not None and camera is None:
            raise BadInput(f"the {method} method needs the camera: give the field of view (--fov-deg), or leave "
                           f"out --method to track with the blind pipeline")
        if sigma_rad is not None and not (np.isfinite(sigma_rad) and sigma_rad > 0):
            raise BadInput("the measurement sigma must be a positive number")
        if int(max_stars) < 3:
            raise BadInput("max_stars must be at least 3 to track")
        if int(min_matches) < 3:
            raise BadInput("tracking needs at least 3 matches (two give the attitude, a third tests it)")
        self.base = catalog if catalog is not None else load_guide_catalog(epoch=epoch)
        self.method = method
        self.variant = variant
        self._camera_fitted = False
        self._depth_given = mag_limit is not None
        self.mag_limit = float(mag_limit) if mag_limit is not None else PAPER_MAG_LIMIT
        self.given_sigma = sigma_rad
        self.max_stars = int(max_stars)
        self.k_sigma = float(k_sigma)
        self.fov_error = DEFAULT_FOV_ERROR if fov_error is None else float(fov_error)
        self.turn_sigma = float(turn_sigma_rad)
        self.still_sigma = float(still_sigma_rad)
        self.min_matches = int(min_matches)
        self.windows = bool(windows)
        self.track_stars = int(track_stars)
        if self.track_stars < MIN_TRACK_MATCHES + 1:
            raise BadInput(f"tracking needs windows around at least {MIN_TRACK_MATCHES + 1} stars")
        self.camera = camera
        self.catalog = self.base.brighter_than(self.mag_limit)
        self._solver: MethodSolver | None = None
        self._fallback: MethodSolver | None = None
        self._blind = blind
        self._progress = progress
        self._method_params = dict(method_params or {})
        if method is not None:
            self._solver = MethodSolver(camera, method, mag_limit=self.mag_limit, sigma_rad=sigma_rad, epoch=epoch,
                                        catalog=self.base, max_stars=max_stars, k_sigma=k_sigma,
                                        method_params=method_params, variant=variant)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        if not self._depth_given and self.mag_limit != PAPER_MAG_LIMIT:  # a new sequence: the depth found again
            self.mag_limit, self._fallback = PAPER_MAG_LIMIT, None
            self.catalog = self.base.brighter_than(self.mag_limit)
        self.frame = -1
        self.history: list[tuple[int, np.ndarray, np.ndarray]] = []  # (frame, R, covariance) of solved frames
        self._turns_since: list[np.ndarray] = []  # turns given since the last solved frame
        self.rate: np.ndarray | None = None  # filtered turn per frame (rotation vector, camera axes, rad)
        self.rate_covariance: np.ndarray | None = None
        self._psf_sigma_px: float | None = None  # measured on the last whole-image centroiding
        self._detection_density = 0.0  # detections per sr of the last whole-image centroiding
        self._trailed = False  # the last whole frame's stars were trails

    @property
    def sigma_rad(self) -> float:
        if self.given_sigma is not None:
            return float(self.given_sigma)
        return DEFAULT_CENTROID_SIGMA_PX * self.camera.pixel_scale_rad

    @property
    def lis_name(self) -> str:
        return self.method or "default pipeline (blind)"

    # ------------------------------------------------------------------ frames
    def process(self, image, turn: np.ndarray | None = None) -> TrackFrame:
        """One frame: an image (path or array). turn: dR_cam from the previous frame to this one
        (v_cam_now = dR_cam v_cam_before), when known; None: predicted from the rate."""
        return self._stamped(self._process(image, turn))

    def _stamped(self, res: TrackFrame) -> TrackFrame:
        """The frame with the solution's context (`TrackFrame.to_dict` writes it); a frame that neither
        tracked nor solved lost-in-space within MAX_COAST_FRAMES of the last solved one, with the motion
        known, is coasted: its attitude is the prediction (reported apart, not as a solution)."""
        if (not res.solved and res.prediction is not None and res.predicted_by in ("turn", "rate") and self.history
                and res.frame - self.history[-1][0] <= MAX_COAST_FRAMES):
            gap = res.frame - self.history[-1][0]
            res.mode = COASTING
            res.reason = (f"coasting on the motion model ({res.predicted_by}; {gap} frame{'s' if gap > 1 else ''} "
                          f"since frame {self.history[-1][0]}, the last solved): {res.reason or res.lost_lock}")
        lis = res.lis_result
        res.camera = lis.camera if lis is not None and lis.camera is not None else self.camera
        res.camera_fitted = lis.camera_fitted if lis is not None else self._camera_fitted
        res.method = lis.method if lis is not None else (self.method or BLIND)
        res.variant = lis.variant if lis is not None else self.variant
        res.mag_limit = self.mag_limit
        res.epoch = float(self.base.epoch)
        return res

    def _process(self, image, turn: np.ndarray | None = None) -> TrackFrame:
        img = as_image(image)
        if self.camera is not None and img.shape != (self.camera.height, self.camera.width):
            raise BadInput(f"image is {img.shape[1]}x{img.shape[0]} but the camera is "
                           f"{self.camera.width}x{self.camera.height}")
        if self.windows and self.history and self.camera is not None and not self._trailed:
            return self._process_windowed(img, turn)
        t0 = time.perf_counter()
        cents = self._whole_frame(img)
        t_c = (time.perf_counter() - t0) * 1e3
        self._note_psf(cents)
        out = self._process_centroids(cents, img.shape[1], img.shape[0], turn)
        out.time_ms = {"centroid": t_c, **out.time_ms}
        out.time_ms["total"] = t_c + out.time_ms.get("track", 0.0) + out.time_ms.get("lost_in_space", 0.0)
        return out

    def _whole_frame(self, img: np.ndarray) -> Centroids:
        """Every star of a frame measured whole (lost-in-space, or a tracked frame that lost lock): as the default
        pipeline measures them when it solves (`detect_stars`: wide stars binned, a sparse frame searched through
        the matched filter, trails measured whole, a satellite's fragments left out), or the centroider's stars
        for a method (the papers' conditions)."""
        if self.method is None:
            return detect_stars(img, k_sigma=self.k_sigma)
        return detect_centroids(img, k_sigma=self.k_sigma)

    def _note_psf(self, cents: Centroids) -> None:
        # a trailed frame (its stars measured whole, `skyview.detect.trailed`): the next one is measured whole too,
        # the windows' round-star centroid would take a trail's part near the prediction for the star
        self._trailed = "trailed" in cents.params
        if np.isfinite(cents.psf_sigma_px) and len(cents) >= 3:
            self._psf_sigma_px = float(cents.psf_sigma_px)
        if self.camera is not None:  # detections per steradian of the last whole frame
            self._detection_density = len(cents) / self.camera.solid_angle_sr

    def _process_windowed(self, img: np.ndarray, turn: np.ndarray | None) -> TrackFrame:
        """A tracked frame: centroids only in windows around the predicted stars (`track_window`), the
        matching and the windowed verification; on loss of lock the whole image is centroided and
        solved lost-in-space."""
        self._advance(turn)
        res = TrackFrame(frame=self.frame, mode=TRACKING, status=NOT_SOLVED)
        t0 = time.perf_counter()
        R_pred, P_pred, how = self._prediction()
        res.predicted_by = how
        rows = self._field(R_pred)
        centers, half = self._windows(rows, R_pred, P_pred, img.shape[1], img.shape[0])
        win = None
        if len(centers):
            win = centroid_windows(img, centers, half, self.camera.pixel_scale_rad, k_sigma=self.k_sigma,
                                   psf_sigma_px=self._psf_sigma_px)
        t1 = time.perf_counter()
        times = {"centroid_windows": (t1 - t0) * 1e3}
        if win is None:
            res.lost_lock = f"no predicted star within a window's reach ({how})"
        else:
            keep = np.flatnonzero(~win.centroids.edge)  # light cut by a window side or the image border
            cents = _subset(win.centroids, keep)
            res.n_centroids = len(cents)
            res.centroids = cents
            ok = self._track(cents, res, prediction=(R_pred, P_pred, how), box_sr=win.box_sr[keep], rows=rows)
            times["track"] = (time.perf_counter() - t1) * 1e3
            if ok:
                times["total"] = sum(times.values())
                res.time_ms = times
                self._solved(res)
                return res
        t2 = time.perf_counter()
        cents = self._whole_frame(img)
        t3 = time.perf_counter()
        self._note_psf(cents)
        res.n_centroids = len(cents)
        res.centroids = cents
        times["centroid"] = (t3 - t2) * 1e3
        if len(cents) == 0:
            res.reason = "no stars found in the image (blank or empty sky)"
        else:
            self._lost_in_space(cents, img.shape[1], img.shape[0], res)
            times["lost_in_space"] = (time.perf_counter() - t3) * 1e3
        times["total"] = sum(times.values())
        res.time_ms = times
        if res.solved:
            self._solved(res)
        return res

    def _field(self, R: np.ndarray) -> np.ndarray:
        """Catalog rows around the predicted field: within the half-diagonal + FIELD_MARGIN of R's
        boresight (one tree query per frame; the windows and the matching use these rows)."""
        cam = self.camera
        return self.catalog.within(R[2], cam.half_diagonal_rad + FIELD_MARGIN_RAD)

    def _windows(self, near: np.ndarray, R: np.ndarray, P: np.ndarray, width: int, height: int
                 ) -> tuple[np.ndarray, int]:
        """The windows to centroid (`track_window.window_centers`: centre pixels, common half-size): around
        the brightest track_stars predicted catalog stars (of the field rows `near`), of half-size the
        largest match bound (pixels) + the PSF's reach + a margin; none when a bound exceeds MAX_HALF_PX."""
        cam = self.camera
        none = (np.zeros((0, 2), dtype=np.int64), 0)
        if len(near) == 0:
            return none
        v = self.catalog.xyz[near] @ R.T
        uv, front = cam.project(v)
        on = front & cam.in_image(uv, margin=-10.0)
        if not np.any(on):
            return none
        rows, v, uv = near[on], v[on], uv[on]
        order = np.argsort(self.catalog.mag[rows], kind="stable")[:self.track_stars]
        v, uv = v[order], uv[order]
        sigma = self.sigma_rad
        bound = match_radii(v, P, sigma, RADIUS_SIGMAS * sigma)  # the match bound (`TrackedIdentifier.match`)
        psf = self._psf_sigma_px or DEFAULT_PSF_SIGMA_PX
        half = bound / cam.pixel_scale_rad + PSF_REACH_SIGMAS * psf + WINDOW_MARGIN_PX
        if np.any(half > MAX_HALF_PX):
            return none
        return window_centers(uv, half, width, height)

    def skip(self, turn: np.ndarray | None = None) -> None:
        """A frame that could not be read (or was of another camera): counted, so that the motion model
        predicts the next frame across the gap, and not solved. turn: its turn from the frame before,
        when known."""
        self._advance(turn)

    def _advance(self, turn: np.ndarray | None) -> None:
        self.frame += 1
        if self.frame > 0:
            self._turns_since.append(None if turn is None else np.asarray(turn, dtype=np.float64))

    def process_centroids(self, centroids: Centroids, width: int, height: int,
                          turn: np.ndarray | None = None) -> TrackFrame:
        """One frame from its whole-image centroids (the tracked matches verified by the shared
        `verify.verify` against the whole frame)."""
        return self._stamped(self._process_centroids(centroids, width, height, turn))

    def _process_centroids(self, centroids: Centroids, width: int, height: int,
                           turn: np.ndarray | None = None) -> TrackFrame:
        self._advance(turn)
        k = self.frame
        res = TrackFrame(frame=k, mode=TRACKING if self.history else LOST_IN_SPACE, status=NOT_SOLVED,
                         n_centroids=len(centroids), centroids=centroids)
        times: dict[str, float] = {}
        if len(centroids) == 0:
            res.reason = "no stars found in the image (blank or empty sky)"
            res.time_ms = {"track": 0.0}
            return res
        if self.history:
            t0 = time.perf_counter()
            prediction = self._prediction()
            ok = self._track(centroids, res, prediction=prediction, rows=self._field(prediction[0]))
            times["track"] = (time.perf_counter() - t0) * 1e3
            if ok:
                res.time_ms = times
                self._solved(res)
                return res
        t0 = time.perf_counter()
        self._lost_in_space(centroids, width, height, res)
        times["lost_in_space"] = (time.perf_counter() - t0) * 1e3
        res.time_ms = times
        if res.solved:
            self._solved(res)
        return res

    def run(self, images: Sequence, turns: Sequence[np.ndarray] | None = None) -> list[TrackFrame]:
        """Every frame in order; turns[k] (dR_cam from frame k to k+1) when known."""
        if turns is not None and len(turns) != max(len(images) - 1, 0):
            raise BadInput(f"{len(images)} frames need {len(images) - 1} turns, got {len(turns)}")
        return [self.process(im, None if (k == 0 or turns is None) else turns[k - 1])
                for k, im in enumerate(images)]

    # ------------------------------------------------------------------ internals
    def _observation(self, centroids: Centroids) -> tuple[np.ndarray, np.ndarray]:
        obs = observation(centroids, self.camera, 0.0, self.max_stars)  # sigma: the tracker's own
        return obs.vectors, obs.uv

    def _solved(self, res: TrackFrame) -> None:
        if self.history:
            j, Rj, Pj = self.history[-1]
            res.relative_to = j
            res.relative_rotvec_rad = -rotvec(res.R @ Rj.T)  # body_turn_rotvec(Rj, res.R)
            self._update_rate(Rj, Pj, res.R, res.covariance, res.frame - j)
        self.history = (self.history + [(res.frame, res.R, res.covariance)])[-2:]
        self._turns_since = []

    def _update_rate(self, Ri: np.ndarray, Pi: np.ndarray, Rj: np.ndarray, Pj: np.ndarray, gap: int) -> None:
        """Constant-rate Kalman filter on the turn per frame w (camera axes): the measurement is the
        turn between two solved attitudes over their gap, with covariance (P_i + P_j) / gap^2; between
        measurements the rate may change by turn_sigma per frame (process noise). A measurement that
        disagrees with the rate by more than 5 sigma (the motion changed) restarts the filter from it."""
        z = rotvec(Rj @ Ri.T) / gap
        Rz = (Pi + Pj) / gap ** 2
        if self.rate is None:
            self.rate, self.rate_covariance = z, Rz
            return
        Pp = self.rate_covariance + gap * self.turn_sigma ** 2 * np.eye(3)
        S = Pp + Rz
        d = z - self.rate
        if float(d @ np.linalg.solve(S, d)) > 25.0 * 3:
            self.rate, self.rate_covariance = z, Rz
            return
        K = Pp @ np.linalg.inv(S)
        self.rate = self.rate + K @ d
        self.rate_covariance = (np.eye(3) - K) @ Pp

    def _prediction(self) -> tuple[np.ndarray, np.ndarray, str]:
        """The predicted attitude of this frame, its covariance (camera axes, rad^2), and what it came from."""
        j, Rj, Pj = self.history[-1]
        n = self.frame - j  # frames since the last solved one
        if self._turns_since and all(t is not None for t in self._turns_since):
            R = Rj
            for t in self._turns_since:
                R = t @ R
            P = Pj + (n * self.turn_sigma) ** 2 * np.eye(3)
            return R, P, "turn"
        if self.rate is not None:  # the filtered rate (per frame, the camera's turn in its own axes)
            R = rotation_matrix(self.rate * n) @ Rj
            P = Pj + n ** 2 * self.rate_covariance + (n * self.turn_sigma) ** 2 * np.eye(3)
            return R, P, "rate"
        return Rj, Pj + (self.still_sigma ** 2 + (n * self.turn_sigma) ** 2) * np.eye(3), "still"

    def _track(self, centroids: Centroids, res: TrackFrame, prediction, rows: np.ndarray,
               box_sr: np.ndarray | None = None) -> bool:
        """The frame identified where the prediction expects it (`identify.tracking.TrackedIdentifier`: the
        tracked hypotheses, then the prediction itself, through the shared verification)."""
        R_pred, P_pred, how = prediction
        res.predicted_by = how
        res.prediction = (R_pred, P_pred)
        b, uv = self._observation(centroids)
        # the chance that a star of the predicted field lies within a detection's bound by accident: the
        # density of stars there, the density the catalog's around the field or the detections' of the last
        # whole frame, whichever is higher (a window holds a detection by construction; an accident needs
        # one placed within its bound)
        cap = self.camera.half_diagonal_rad + FIELD_MARGIN_RAD
        density = max(len(rows) / (2.0 * np.pi * (1.0 - np.cos(cap))), self._detection_density)
        expected = Prediction(R_pred, P_pred, how, rows, density, PREDICTION_MIN_STARS.get(how, 3))
        tracked = TrackedIdentifier(self.catalog, self.camera, self.sigma_rad, min_matches=self.min_matches,
                                    tries=MAX_TRACK_TRIES)
        obs = Observation(vectors=b, uv=uv, brightness=centroids.brightness[:len(b)], sigma_rad=self.sigma_rad,
                          window_sr=None if box_sr is None else box_sr[:len(b)])
        ident = tracked.identify_predicted(obs, expected)
        res.identification = ident
        if not ident.identified:
            res.lost_lock = ident.reason
            return False
        res.mode, res.status = TRACKING, SOLVED
        res.R, res.covariance = ident.R, ident.attitude_covariance
        res.p_false = float(ident.verification["p_false"])
        res.matches = matched_stars(self.catalog, uv, ident.matches)
        res.verified_by = ident.stats["verified_by"]
        res.lost_lock = ""
        return True

    def _follow_depth(self, lis: SolveResult) -> None:
        """With no depth given, the tracking catalog as deep as a blind lost-in-space solve's, when that is deeper
        (the blind pipeline takes its depth from the image: an 11 deg photograph shows a handful of stars of Hp 6
        and dozens to Hp 8, and the attitude and the tracked matches are made of the catalog's stars)."""
        depth = lis.mag_limit
        if self._depth_given or depth is None or not math.isfinite(depth) or depth <= self.mag_limit:
            return
        self.mag_limit, self._fallback = float(depth), None
        self.catalog = self.base.brighter_than(self.mag_limit)

    def _lost_in_space(self, centroids: Centroids, width: int, height: int, res: TrackFrame) -> None:
        res.mode = LOST_IN_SPACE
        if self.method is not None:
            lis = self._solver.solve_centroids(centroids)
        else:
            if self._blind is None:
                # (deep=False: a field narrower than the guide catalog reaches could not be tracked in it)
                self._blind = blind_solver(self.base.epoch, max_stars=self.max_stars, k_sigma=self.k_sigma,
                                           progress=self._progress, deep=False)
            fov = self.camera.fov_deg if self.camera is not None else None
            # (a sequence is tracked in its frames' own pixels: a mirror image is not taken, whose pixels turn over)
            lis = self._blind.solve_centroids(centroids, width, height, fov_deg=fov, fov_error=self.fov_error,
                                              mirror=False)
            if lis.solved:
                self.camera = lis.camera  # track with the camera the stars fitted
                self._camera_fitted = lis.camera_fitted
                self._follow_depth(lis)
            elif self.camera is not None:  # the default pipeline's second stage: improved angle at the FOV
                if self._fallback is None:
                    # (no deeper than `solve_image` builds this one: a deeper angle database is gigabytes)
                    depth = min(self.mag_limit, ANGLE_MAX_DEPTH)
                    self._fallback = MethodSolver(self.camera, "angle", mag_limit=depth,
                                                  sigma_rad=self.given_sigma, catalog=self.base,
                                                  max_stars=self.max_stars, k_sigma=self.k_sigma, variant="improved")
                first = lis.reason
                lis = self._fallback.solve_centroids(centroids)
                if not lis.solved:
                    lis.reason = f"{first}; then the improved angle method: {lis.reason}"
        res.lis_result = lis
        ident = lis.identification
        res.p_false = (ident.verification.get("p_false") if lis.solved and ident is not None and ident.verification
                       else None)  # (an unsolved frame's last verification refused its hypothesis)
        if not lis.solved:
            res.reason = lis.reason
            if res.lost_lock:
                res.reason = f"lost lock ({res.lost_lock}); lost-in-space: {lis.reason}"
            return
        # the attitude and its covariance from the matches that are in the tracking catalog, with the
        # tracking camera (the same one for a method; the fitted one for the blind pipeline)
        b, uv = self._observation(centroids)
        pairs = []
        for m in lis.matches:
            try:
                pairs.append((int(m["index"]), self.catalog.index_of(int(m["hip"]))))
            except KeyError:  # fainter than the tracking catalog
                continue
        pairs = [(o, c) for o, c in pairs if o < len(b)]
        if len(pairs) >= 2:
            idx = np.array([o for o, _ in pairs])
            est = svd_attitude(b[idx], self.catalog.xyz[[c for _, c in pairs]], self.sigma_rad)
            res.R, res.covariance = est.R, est.covariance
            res.matches = matched_stars(self.catalog, uv, dict(pairs))
        else:
            res.R = lis.R
            P = np.diag([(lis.sigma_boresight_arcsec or 60.0) ** 2] * 2 + [(lis.sigma_roll_arcsec or 600.0) ** 2])
            res.covariance = P / RAD_TO_ARCSEC ** 2
            res.matches = list(lis.matches)
        res.status = SOLVED
        res.reason = ""


def track_images(images: Sequence, camera: Camera | None = None, method: str | None = None,
                 turns: Sequence[np.ndarray] | None = None, **kwargs) -> list[TrackFrame]:
    """Track a list of images (paths or arrays) in time order; see `Tracker`."""
    return Tracker(camera, method, **kwargs).run(images, turns)
