"""Fit the camera to identified stars: attitude, focal length (so the FOV) and radial distortion.

`fit_camera(uv, xyz, camera, R)` moves the attitude R, the focal length f (square pixels, principal
point kept at the camera's) and the radial distortion (k1, and k2 when asked) of OpenCV's model on
normalised coordinates (see `skyview.core.camera`) to minimise the pixel distance between the observed
centroids uv and the projected catalog directions xyz (ICRS). Robust least squares: the soft-L1
loss with a 1-pixel scale, so that one bad match does not drag the fit (`robust_gauss_newton`: the
loss of scipy's least_squares(loss="soft_l1"), minimised by reweighted Gauss-Newton, ten times
faster for these few parameters). Pure function of arrays, no state.

How much can be fitted: f needs two stars; k1 needs stars at different distances from the centre
(`min_stars_k1` = 6 and a spread of at least a fifth of the half-diagonal); k2 needs more
(`min_stars_k2` = 12, a spread of at least a third). With fewer the term stays at its given value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skyview.core.camera import Camera, fisheye_r, fisheye_theta

MIN_STARS_K1 = 6
MIN_STARS_K2 = 12
MAX_STRETCH = 0.25  # |k1 rc^2|, |k2 rc^4|: a radial stretch beyond 25 % at the corner is not this model's lens


@dataclass(frozen=True)
class CameraFit:
    camera: Camera
    R: np.ndarray
    residuals_px: np.ndarray  # (N,) distance of each star from its fitted projection
    rms_px: float  # per-axis RMS of the residuals
    fitted: tuple[str, ...]  # the terms that were free ("attitude", "f", "k1", "k2")


def _radial_spread(uv: np.ndarray, camera: Camera) -> float:
    r = np.hypot(uv[:, 0] - camera.cx, uv[:, 1] - camera.cy)
    half_diag = np.hypot(camera.width, camera.height) / 2.0
    return float((r.max() - r.min()) / half_diag) if len(r) else 0.0


def fit_camera(uv: np.ndarray, xyz: np.ndarray, camera: Camera, R: np.ndarray, *, fit_focal: bool = True,
               fit_k1: bool | None = None, fit_k2: bool | None = None) -> CameraFit:
    """Refine (R, f, k1, k2) from matched centroids uv (N, 2) and catalog directions xyz (N, 3).

    fit_k1 / fit_k2: True frees the term, False keeps the camera's value, None (default) frees it
    when the stars allow it (module docstring) and keeps it only when it lowers the squared residuals
    by more than chance would (a chi-square test with one degree of freedom at 0.1 %, the residual
    noise estimated from the larger model).
    """
    uv = np.asarray(uv, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(uv)
    spread = _radial_spread(uv, camera)
    auto_k1, auto_k2 = fit_k1 is None, fit_k2 is None
    if auto_k1:  # the models compared start from no distortion
        camera = Camera(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, model=camera.model)
    if auto_k1:
        fit_k1 = n >= MIN_STARS_K1 and spread >= 0.2
    if auto_k2:
        fit_k2 = bool(fit_k1) and n >= MIN_STARS_K2 and spread >= 0.33
    best = _fit(uv, xyz, camera, R, fit_focal and n >= 3, False, False) if (auto_k1 and fit_k1) else None
    if fit_k1:  # from the undistorted fit when there is one (the same minimum, fewer steps to it)
        with_k1 = _fit(uv, xyz, best.camera if best else camera, best.R if best else R, fit_focal and n >= 3,
                       True, False)
        best = with_k1 if best is None or _better(with_k1, best) else best
        if fit_k2 and "k1" in best.fitted:
            with_k2 = _fit(uv, xyz, best.camera, best.R, fit_focal and n >= 3, True, True)
            if not auto_k2 or _better(with_k2, best):
                best = with_k2
    if best is None:
        best = _fit(uv, xyz, camera, R, fit_focal and n >= 3, False, False)
    return best


CHI2_1DOF_0P1 = 10.83  # chi-square with one degree of freedom: P(> 10.83) = 0.001


def _better(big: CameraFit, small: CameraFit) -> bool:
    """Does the model with one more term fit significantly better?"""
    n = len(big.residuals_px)
    dof = 2 * n - (len(big.fitted) + 2 + ("f" in big.fitted) + ("k1" in big.fitted) + ("k2" in big.fitted) - 1)
    rss_big = float(np.sum(big.residuals_px ** 2))
    rss_small = float(np.sum(small.residuals_px ** 2))
    if dof <= 0 or rss_big <= 0:
        return False
    return (rss_small - rss_big) / (rss_big / dof) > CHI2_1DOF_0P1


def _rotvec_matrix(v: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues: I + a K + b K^2 with K^2 = v v' - |v|^2 I), its nine
    entries from Python floats (a dozen numpy calls on 3 x 3 arrays cost ~10 us a call, ~20 calls a fit)."""
    x, y, z = v.tolist()
    th2 = x * x + y * y + z * z
    th = math.sqrt(th2)
    if th < 1e-12:
        return np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])
    a = math.sin(th) / th
    b = (1.0 - math.cos(th)) / th ** 2
    return np.array([[1.0 + b * (x * x - th2), b * x * y - a * z, b * x * z + a * y],
                     [b * x * y + a * z, 1.0 + b * (y * y - th2), b * y * z - a * x],
                     [b * x * z - a * y, b * y * z + a * x, 1.0 + b * (z * z - th2)]])


def _left_jacobian(v: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian at the rotation vector v: exp(v + d) = exp(J d) exp(v) to first order in d
    (I + b K + c K^2, entry by entry as `_rotvec_matrix`)."""
    x, y, z = v.tolist()
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        return np.array([[1.0, -0.5 * z, 0.5 * y], [0.5 * z, 1.0, -0.5 * x], [-0.5 * y, 0.5 * x, 1.0]])
    th = math.sqrt(th2)
    b = (1.0 - math.cos(th)) / th2
    c = (th - math.sin(th)) / (th2 * th)
    return np.array([[1.0 + c * (x * x - th2), c * x * y - b * z, c * x * z + b * y],
                     [c * x * y + b * z, 1.0 + c * (y * y - th2), c * y * z - b * x],
                     [c * x * z - b * y, c * y * z + b * x, 1.0 + c * (z * z - th2)]])


def robust_gauss_newton(fun, p0: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, f_scale: float = 1.0,
                        max_iter: int = 30, tol: float = 1e-10, rtol: float = 1e-4, fun_jac=None) -> np.ndarray:
    """Minimise sum rho(fun(p)^2 / f_scale^2) with rho the soft-L1 loss 2 (sqrt(1 + z) - 1) (what
    scipy's least_squares(loss="soft_l1") minimises), p within [lo, hi]: iteratively reweighted
    Gauss-Newton with step halving (each step from the weighted normal equations); `fun_jac(p)` ->
    (fun(p), its Jacobian) computes both at once, sharing their work (each trial point's Jacobian is the
    next step's), else the Jacobian comes from forward differences. A handful of parameters
    and a few dozen stars: each iteration is a few small numpy calls (scipy's trust-region solver spends
    ten times as long in its own bookkeeping here). It stops when no parameter moves by more than `tol`
    (radians of attitude, the log of the focal length, the corner's stretch), or when a whole step (not
    halved) changed the residuals by less than `rtol` RMS (their own unit, pixels here: the weighted
    change the Gauss-Newton model predicts, step' J'WJ step): the reweighting's slow last steps change
    the answer by far less than its noise."""
    p = np.clip(np.asarray(p0, dtype=np.float64), lo, hi)

    def soft(r):  # the weights and the cost
        t = np.sqrt(1.0 + (r / f_scale) ** 2)
        return 1.0 / t, float(2.0 * np.sum(t - 1.0))

    def forward_differences(q, rq):
        h = 1e-7 * np.maximum(1.0, np.abs(q))
        J = np.empty((len(rq), len(q)))
        for j in range(len(q)):
            e = q.copy()
            e[j] += h[j]
            J[:, j] = (fun(e) - rq) / h[j]
        return J

    if fun_jac is not None:
        r, J = fun_jac(p)
    else:
        r = fun(p)
        J = None
    w, c = soft(r)
    for _ in range(max_iter):
        if J is None:
            J = forward_differences(p, r)
        Jw = J * w[:, None]
        normal = Jw.T @ J
        try:
            step = -np.linalg.solve(normal, Jw.T @ r)
        except np.linalg.LinAlgError:  # a parameter the stars do not constrain: the least-norm step
            step = -np.linalg.lstsq(J * np.sqrt(w)[:, None], r * np.sqrt(w), rcond=None)[0]
        change = float(step @ normal @ step)  # the weighted squared change of the residuals it predicts
        t = 1.0
        for _halve in range(8):
            q = np.minimum(np.maximum(p + t * step, lo), hi)  # (= np.clip, without its wrappers)
            rq, Jq = fun_jac(q) if fun_jac is not None else (fun(q), None)
            wq, cq = soft(rq)
            if cq <= c:
                break
            t *= 0.5
        else:
            break  # no step lowers the cost: at the minimum
        moved = float(np.max(np.abs(q - p)))
        p, r, J, w, c = q, rq, Jq, wq, cq
        # converged: nothing moves, or the whole Gauss-Newton step was taken and changed the residuals by
        # far less than their noise (a halved step is not a small one: the minimum may still be far)
        if moved < tol or (t == 1.0 and change < rtol * rtol * len(r)):
            break
    return p


def _fit(uv, xyz, camera: Camera, R, fit_focal: bool, fit_k1: bool, fit_k2: bool) -> CameraFit:
    """One least-squares fit with the given terms free. Distortion is fitted as the fractional stretch
    at the image corner (k1 rc^2, k2 rc^4 with rc the corner's normalised radius): well scaled for
    narrow and wide fields alike, and bounded by MAX_STRETCH."""
    n = len(uv)
    R0 = np.asarray(R, dtype=np.float64)
    f0 = camera.fx
    fisheye = camera.fisheye
    rc2 = (math.hypot(camera.width, camera.height) / 2.0 / f0) ** 2
    if fisheye:  # a fisheye's distortion is a polynomial in the off-axis angle: its corner's, squared
        rc2 = float(np.nan_to_num(fisheye_theta(np.asarray(np.sqrt(rc2)), camera.model), nan=np.pi / 2)) ** 2
    names = ("attitude",) + (("f",) if fit_focal else ()) + (("k1",) if fit_k1 else ()) + (("k2",) if fit_k2 else ())

    def unpack(p):  # (R, f, k1, k2; the last three Python floats: numpy scalars slow every operation)
        q = p.tolist()
        Rk = _rotvec_matrix(p[:3]) @ R0
        i = 3
        f = f0
        if fit_focal:
            f = f0 * math.exp(q[i])
            i += 1
        k1, k2 = camera.k1, camera.k2
        if fit_k1:
            k1 = q[i] / rc2
            i += 1
        if fit_k2:
            k2 = q[i] / rc2 ** 2
        return Rk, f, k1, k2

    def project(p):
        Rk, f, k1, k2 = unpack(p)
        v = xyz @ Rk.T
        if fisheye:
            rho = np.hypot(v[:, 0], v[:, 1])
            th = np.arctan2(rho, v[:, 2])
            t2 = th * th
            r = fisheye_r(th * (1.0 + k1 * t2 + k2 * t2 * t2), camera.model)
            s = np.where(rho > 1e-15, r / np.maximum(rho, 1e-300), 0.0)
            return np.stack([f * v[:, 0] * s + camera.cx, f * v[:, 1] * s + camera.cy], axis=1)
        z = np.maximum(v[:, 2], 1e-9)
        x, y = v[:, 0] / z, v[:, 1] / z
        r2 = x * x + y * y
        s = 1.0 + k1 * r2 + k2 * r2 * r2
        return np.stack([f * x * s + camera.cx, f * y * s + camera.cy], axis=1)

    p0 = np.zeros(3 + len(names) - 1)
    i = 3 + int(fit_focal)
    if fit_k1:
        p0[i] = camera.k1 * rc2
        i += 1
    if fit_k2:
        p0[i] = camera.k2 * rc2 ** 2
    lo = np.full(len(p0), -np.inf)
    hi = np.full(len(p0), np.inf)
    lo[3:], hi[3:] = -MAX_STRETCH, MAX_STRETCH
    if fit_focal:
        lo[3], hi[3] = -1.0, 1.0
    p0 = np.clip(p0, lo + 1e-12, hi - 1e-12)
    if 2 * n <= len(p0):
        d = project(p0) - uv
        return CameraFit(camera, R0, np.hypot(d[:, 0], d[:, 1]), float("nan"), ())
    # the residuals' constant parts and the catalog directions as rows of x, y, z: every array below is a
    # contiguous 1-d one (an operation on one costs a third of one on a broadcast (N, 2) view)
    cu0, cv0 = camera.cx - uv[:, 0], camera.cy - uv[:, 1]
    xyz_t = np.ascontiguousarray(xyz.T)
    n_p = len(p0)

    def residuals_and_jacobian(p):
        """The residuals of the pinhole model (the u of every star, then the v; the robust loss and the
        normal equations do not care for the order) and their derivatives by p."""
        Rk, f, k1, k2 = unpack(p)
        vx, vy, vz = Rk @ xyz_t  # the directions in the camera frame, one row per axis
        iz = 1.0 / np.maximum(vz, 1e-9)
        x, y = vx * iz, vy * iz
        r2 = x * x + y * y
        s = 1.0 + k1 * r2 + k2 * r2 * r2 if k2 else 1.0 + k1 * r2  # (+ 0 r2^2 changes no bit)
        fs = f * s
        JT = np.empty((n_p, 2, n))  # the Jacobian, parameter by parameter, for u and v of each star
        fx_s, fy_s = JT[3] if fit_focal else np.empty((2, n))  # f x s, f y s: the pixel offsets and d/d log f
        np.multiply(fs, x, out=fx_s)
        np.multiply(fs, y, out=fy_s)
        res = np.empty((2, n))  # (the u residuals, then the v residuals: the Jacobian's rows below)
        np.add(fx_s, cu0, out=res[0])
        np.add(fy_s, cv0, out=res[1])
        # d(u, v)/d(vector): rows (a, b, cu) and (b, d, cv) with a = f (s + ds x^2) / z, b = f ds x y / z,
        # d = f (s + ds y^2) / z, ds = 2 (k1 + 2 k2 r^2) (ds/dx = ds x), c. = -(x col_x + y col_y)
        g = f * iz
        gs = g * s
        gds = g * (2.0 * (k1 + 2.0 * k2 * r2)) if k2 else g * (2.0 * k1)
        gx, gy = gds * x, gds * y
        a = gs + gx * x
        b = gx * y
        d = gs + gy * y
        cu = -(a * x + b * y)
        cv = -(b * x + d * y)
        # by the rotation vector: (row x v) (-Jl) (the triple product), both rows in one product
        rows = np.empty((3, 2, n))
        rows[0, 0], rows[1, 0], rows[2, 0] = b * vz - cu * vy, cu * vx - a * vz, a * vy - b * vx
        rows[0, 1], rows[1, 1], rows[2, 1] = d * vz - cv * vy, cv * vx - b * vz, b * vy - d * vx
        JT[:3] = (-_left_jacobian(p[:3]).T @ rows.reshape(3, 2 * n)).reshape(3, 2, n)
        i = 3 + bool(fit_focal)
        if fit_k1 or fit_k2:
            fx_, fy_ = f * x, f * y
            if fit_k1:
                t = r2 / rc2
                np.multiply(fx_, t, out=JT[i, 0])
                np.multiply(fy_, t, out=JT[i, 1])
                i += 1
            if fit_k2:
                t = r2 * r2 / rc2 ** 2
                np.multiply(fx_, t, out=JT[i, 0])
                np.multiply(fy_, t, out=JT[i, 1])
        return res.reshape(2 * n), JT.reshape(n_p, 2 * n).T  # (2N, P): rows u0 .. uN-1, v0 .. vN-1

    x = robust_gauss_newton(lambda p: (project(p) - uv).T.ravel(), p0, lo, hi,  # (u of every star, then v)
                            fun_jac=None if fisheye else residuals_and_jacobian)
    Rk, f, k1, k2 = unpack(x)
    cam = Camera(camera.width, camera.height, float(f), float(f), camera.cx, camera.cy, float(k1), float(k2),
                 camera.model)
    d = project(x) - uv
    rms = float(np.sqrt(np.sum(d * d) / max(2 * n - len(p0), 1)))
    return CameraFit(cam, Rk, np.hypot(d[:, 0], d[:, 1]), rms, names)
