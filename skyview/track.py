"""Tracking mode for every identification method: solve once lost-in-space, then follow the stars.

`Tracker` solves the first frame lost-in-space (LIS) with the given method through `Solver` (or, with
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
3. matches the observed centroids to the predicted catalog stars by nearest neighbour within the
   bound (one-to-one; a centroid with two catalog stars within its bound is left out), estimates the
   attitude from the matches (`svd_attitude`) and matches once more with the bound of that estimate;
4. runs the shared verification (`verify.verify`): the hypothesis is the tracked matches' best
   spread three (their attitude), tested by every other observed star; n_hypotheses counts the
   tracked hypotheses verified for the frame (Bonferroni). A passed verification extends and
   re-estimates the attitude from every agreeing star, exactly as for a lost-in-space solve.

Loss of lock (fewer than MIN_TRACK_MATCHES matches, or the verification refused) falls back to LIS for
that frame; a frame that neither solves is reported failed, and the next one is predicted from the
last solved frame (the prediction's bound grows with the frames in between).

Each frame's `TrackFrame`: mode ("lost_in_space" | "tracking"), status, the attitude, the rotation
from the last solved frame (rotation vector of the camera body, camera axes of that frame, degrees:
the same convention as a sequence's relative[k]["turn_rotvec_cam_rad"]), the matches and the time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from skyview.attitude import RAD_TO_ARCSEC, quat_from_R, radec_roll_from_R, svd_attitude
from skyview.camera import Camera
from skyview.catalog import DEFAULT_EPOCH, GuideCatalog, load_guide_catalog
from skyview.centroid import Centroids, detect_centroids
from skyview.errors import BadInput
from skyview.identify.verify import (MAX_RADIUS_RAD, RADIUS_SIGMAS, match_one_to_one, predicted_sigma, verify)
from skyview.pipeline import (BLIND, DEFAULT_CENTROID_SIGMA_PX, DEFAULT_FOV_ERROR, PAPER_MAG_LIMIT, SOLVED,
                              NOT_SOLVED, BlindSolver, SolveResult, Solver, as_image, blind_solver)

LOST_IN_SPACE = "lost_in_space"
TRACKING = "tracking"
MIN_TRACK_MATCHES = 3  # fewer tracked matches than this: lock is lost (two give an attitude, a third tests it)
HYPOTHESIS_STARS = 3  # tracked matches that make the verified hypothesis (the rest test it)
TURN_SIGMA_RAD = float(np.radians(30.0 / 3600.0))  # 1 sigma per axis, per predicted frame (rate change, gyro)
STILL_SIGMA_RAD = float(np.radians(0.05))  # the motion is unknown (one solved frame, no turn given)
MAX_TRACK_TRIES = 2  # tracked hypotheses verified per frame before falling back to LIS


@dataclass
class TrackFrame:
    frame: int
    mode: str  # LOST_IN_SPACE | TRACKING (the mode that produced the result)
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

    @property
    def solved(self) -> bool:
        return self.status == SOLVED

    @property
    def relative_rotvec_deg(self) -> list[float] | None:
        return None if self.relative_rotvec_rad is None else np.degrees(self.relative_rotvec_rad).tolist()

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"frame": self.frame, "status": self.status, "mode": self.mode}
        if self.reason:
            out["reason"] = self.reason
        if self.lost_lock:
            out["lost_lock"] = self.lost_lock
        if self.R is not None:
            ra, dec, roll = radec_roll_from_R(self.R)
            out.update({"ra_deg": float(np.degrees(ra)), "dec_deg": float(np.degrees(dec)),
                        "roll_deg": float(np.degrees(roll)), "quaternion": quat_from_R(self.R).tolist(),
                        "R": np.asarray(self.R).tolist()})
            if self.covariance is not None:
                c = self.covariance
                out["sigma_arcsec"] = {"boresight": float(np.sqrt(0.5 * (c[0, 0] + c[1, 1])) * RAD_TO_ARCSEC),
                                       "roll": float(np.sqrt(c[2, 2]) * RAD_TO_ARCSEC)}
        if self.relative_rotvec_rad is not None:
            out["relative_to"] = self.relative_to
            out["relative_rotvec_deg"] = self.relative_rotvec_deg
            out["relative_angle_deg"] = float(np.degrees(np.linalg.norm(self.relative_rotvec_rad)))
        out.update({"n_centroids": self.n_centroids, "n_matches": len(self.matches), "matches": self.matches,
                    "p_false": self.p_false, "predicted_by": self.predicted_by or None,
                    "time_ms": {k: round(v, 3) for k, v in self.time_ms.items()}})
        return out


def body_turn_rotvec(R_from: np.ndarray, R_to: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of the camera body's turn from attitude R_from to R_to, in the camera axes
    of R_from: rotvec(dR_cam^T), dR_cam = R_to R_from^T (a sequence's turn_rotvec_cam_rad)."""
    dR = np.asarray(R_to) @ np.asarray(R_from).T
    return Rotation.from_matrix(dR.T).as_rotvec()


def _spread_subset(vectors: np.ndarray, order: np.ndarray, k: int) -> list[int]:
    """k indices of `order` (brightest first) that spread far: the brightest, the farthest from it,
    then the one farthest from the line through the two (largest triangle)."""
    order = np.asarray(order, dtype=np.int64)
    if len(order) <= k:
        return order.tolist()
    v = vectors[order]
    first = 0
    second = int(np.argmax(np.linalg.norm(v - v[first], axis=1)))
    chosen = [first, second]
    if k >= 3:
        area = np.linalg.norm(np.cross(v[second] - v[first], v - v[first]), axis=1)
        area[chosen] = -1.0
        chosen.append(int(np.argmax(area)))
    return order[chosen].tolist()


class Tracker:
    """Lost-in-space once, then tracking, frame after frame (`process`), for any method.

    camera: the camera (its FOV and distortion); None only with method None (the blind pipeline then
    fits it on the first lost-in-space frame, and tracking uses the fitted camera). method: an
    identification method for lost-in-space (through `Solver`), or None for the default pipeline.
    mag_limit: the catalog depth for tracking and for the method (default Hp 6, as `solve_image`'s
    methods). Other keyword arguments go to `Solver` (method_params, estimator, ...).
    """

    def __init__(self, camera: Camera | None = None, method: str | None = None, *, mag_limit: float | None = None,
                 sigma_rad: float | None = None, variant: str = "paper", epoch: float = DEFAULT_EPOCH,
                 catalog: GuideCatalog | None = None, max_stars: int = 40, k_sigma: float = 5.0,
                 method_params: dict | None = None, fov_error: float = DEFAULT_FOV_ERROR,
                 turn_sigma_rad: float = TURN_SIGMA_RAD, still_sigma_rad: float = STILL_SIGMA_RAD,
                 min_matches: int = MIN_TRACK_MATCHES, blind: BlindSolver | None = None, progress=None):
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
        self.mag_limit = float(mag_limit) if mag_limit is not None else PAPER_MAG_LIMIT
        self.given_sigma = sigma_rad
        self.max_stars = int(max_stars)
        self.k_sigma = float(k_sigma)
        self.fov_error = float(fov_error)
        self.turn_sigma = float(turn_sigma_rad)
        self.still_sigma = float(still_sigma_rad)
        self.min_matches = int(min_matches)
        self.camera = camera
        self.catalog = self.base.brighter_than(self.mag_limit)
        self._solver: Solver | None = None
        self._fallback: Solver | None = None
        self._blind = blind
        self._progress = progress
        self._method_params = dict(method_params or {})
        if method is not None:
            self._solver = Solver(camera, method, mag_limit=self.mag_limit, sigma_rad=sigma_rad, epoch=epoch,
                                  catalog=self.base, max_stars=max_stars, k_sigma=k_sigma,
                                  method_params=method_params, variant=variant)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        self.frame = -1
        self.history: list[tuple[int, np.ndarray, np.ndarray]] = []  # (frame, R, covariance) of solved frames
        self._turns_since: list[np.ndarray] = []  # turns given since the last solved frame

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
        img = as_image(image)
        if self.camera is not None and img.shape != (self.camera.height, self.camera.width):
            raise BadInput(f"image is {img.shape[1]}x{img.shape[0]} but the camera is "
                           f"{self.camera.width}x{self.camera.height}")
        t0 = time.perf_counter()
        cents = detect_centroids(img, k_sigma=self.k_sigma)
        t_c = (time.perf_counter() - t0) * 1e3
        out = self.process_centroids(cents, img.shape[1], img.shape[0], turn)
        out.time_ms = {"centroid": t_c, **out.time_ms}
        out.time_ms["total"] = t_c + out.time_ms.get("track", 0.0) + out.time_ms.get("lost_in_space", 0.0)
        return out

    def process_centroids(self, centroids: Centroids, width: int, height: int,
                          turn: np.ndarray | None = None) -> TrackFrame:
        self.frame += 1
        k = self.frame
        if self.frame > 0 and turn is not None:
            self._turns_since.append(np.asarray(turn, dtype=np.float64))
        elif self.frame > 0:
            self._turns_since.append(None)
        res = TrackFrame(frame=k, mode=TRACKING if self.history else LOST_IN_SPACE, status=NOT_SOLVED,
                         n_centroids=len(centroids))
        times: dict[str, float] = {}
        if len(centroids) == 0:
            res.reason = "no stars found in the image (blank or empty sky)"
            res.time_ms = {"track": 0.0}
            return res
        if self.history:
            t0 = time.perf_counter()
            ok = self._track(centroids, res)
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
        n = min(len(centroids), self.max_stars)
        uv = centroids.uv[:n]
        return self.camera.unproject(uv), uv

    def _solved(self, res: TrackFrame) -> None:
        if self.history:
            j, Rj, _ = self.history[-1]
            res.relative_to = j
            res.relative_rotvec_rad = body_turn_rotvec(Rj, res.R)
        self.history = (self.history + [(res.frame, res.R, res.covariance)])[-2:]
        self._turns_since = []

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
        if len(self.history) == 2:
            i, Ri, Pi = self.history[0]
            gap = j - i
            w = Rotation.from_matrix(Rj @ Ri.T).as_rotvec() / gap  # per frame, in ICRS-fixed stars' camera turn
            R = Rotation.from_rotvec(w * n).as_matrix() @ Rj
            P_rate = (Pi + Pj) / gap ** 2
            P = Pj + n ** 2 * P_rate + (n * self.turn_sigma) ** 2 * np.eye(3)
            return R, P, "rate"
        return Rj, Pj + (self.still_sigma ** 2 + (n * self.turn_sigma) ** 2) * np.eye(3), "still"

    def _match(self, b: np.ndarray, R: np.ndarray, P: np.ndarray) -> dict[int, int]:
        """Observed index -> catalog row: nearest neighbours within the bound of prediction (R, P)."""
        sigma = self.sigma_rad
        cam = self.camera
        near = self.catalog.within(R[2], cam.half_diagonal_rad + np.radians(0.5))
        if len(near) == 0:
            return {}
        v = self.catalog.xyz[near] @ R.T
        uv, front = cam.project(v)
        on = front & cam.in_image(uv, margin=-10.0)
        rows, v = near[on], v[on]
        if len(rows) == 0:
            return {}
        s = predicted_sigma(b, P)  # at the observed directions (close to the predicted ones)
        radii = np.minimum(RADIUS_SIGMAS * np.sqrt(sigma ** 2 + s ** 2), MAX_RADIUS_RAD)
        qi, rj, _, amb = match_one_to_one(b, v, radii)
        bad = set(amb.tolist())
        return {int(q): int(rows[r]) for q, r in zip(qi, rj) if int(q) not in bad}

    def _track(self, centroids: Centroids, res: TrackFrame) -> bool:
        R_pred, P_pred, how = self._prediction()
        res.predicted_by = how
        b, uv = self._observation(centroids)
        sigma = self.sigma_rad
        matches = self._match(b, R_pred, P_pred)
        if len(matches) >= 2:  # refine with the matches, then match again with the tighter bound
            idx = np.array(sorted(matches))
            est = svd_attitude(b[idx], self.catalog.xyz[[matches[i] for i in idx]], sigma)
            resid = np.linalg.norm(np.cross(b[idx], self.catalog.xyz[[matches[i] for i in idx]] @ est.R.T), axis=1)
            if np.all(resid < RADIUS_SIGMAS * sigma * 3):
                matches = self._match(b, est.R, est.covariance)
        if len(matches) < self.min_matches:
            res.lost_lock = (f"{len(matches)} of {len(b)} stars matched the prediction ({how}); tracking needs "
                             f"{self.min_matches}")
            return False
        idx = np.array(sorted(matches))
        order = idx[np.argsort(-centroids.brightness[idx], kind="stable")]
        ver = None
        for t in range(MAX_TRACK_TRIES):
            # hypothesis: three well-spread tracked matches (the next try: three of the rest); every
            # other observed star tests it
            pool = order[t * HYPOTHESIS_STARS:]
            k = min(HYPOTHESIS_STARS, len(b) - 1, len(pool))
            if k < 2:
                break
            hyp_idx = _spread_subset(b, pool, k)
            ver = verify(b, {int(i): matches[int(i)] for i in hyp_idx}, self.catalog, self.camera, sigma,
                         n_hypotheses=t + 1)
            if ver.passed:
                break
        if ver is None or not ver.passed:
            res.lost_lock = ("verification refused the tracked matches: " + (ver.reason if ver else "no hypothesis"))
            return False
        res.mode = TRACKING
        res.status = SOLVED
        res.R = ver.R
        res.covariance = ver.covariance
        res.p_false = float(ver.p_false)
        res.matches = self._match_list(ver.matches, uv)
        return True

    def _match_list(self, matches: dict[int, int], uv: np.ndarray) -> list[dict]:
        cat = self.catalog
        return [{"index": int(o), "u": float(uv[o, 0]), "v": float(uv[o, 1]), "hip": int(cat.hip[c]),
                 "mag": float(cat.mag[c])} for o, c in sorted(matches.items())]

    def _lost_in_space(self, centroids: Centroids, width: int, height: int, res: TrackFrame) -> None:
        res.mode = LOST_IN_SPACE
        if self.method is not None:
            lis = self._solver.solve_centroids(centroids)
        else:
            if self._blind is None:
                self._blind = blind_solver(self.base.epoch, max_stars=self.max_stars, k_sigma=self.k_sigma,
                                           progress=self._progress)
            fov = self.camera.fov_deg if self.camera is not None else None
            lis = self._blind.solve_centroids(centroids, width, height, fov_deg=fov, fov_error=self.fov_error)
            if lis.solved:
                self.camera = lis.camera  # track with the camera the stars fitted
            elif self.camera is not None:  # the default pipeline's second stage: improved angle at the FOV
                if self._fallback is None:
                    self._fallback = Solver(self.camera, "angle", mag_limit=self.mag_limit, sigma_rad=self.given_sigma,
                                            catalog=self.base, max_stars=self.max_stars, k_sigma=self.k_sigma,
                                            variant="improved")
                first = lis.reason
                lis = self._fallback.solve_centroids(centroids)
                if not lis.solved:
                    lis.reason = f"{first}; then the improved angle method: {lis.reason}"
        res.lis_result = lis
        ident = lis.identification
        res.p_false = (ident.verification.get("p_false") if ident is not None and ident.verification else None)
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
            res.matches = self._match_list(dict(pairs), uv)
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
