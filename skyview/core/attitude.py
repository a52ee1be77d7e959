"""Attitude conventions and estimators.

`R` is the 3x3 rotation with v_cam = R @ v_icrs: its rows are the camera axes (x right, y down,
z boresight) expressed in ICRS. Quaternions are scalar-first [w, x, y, z] for the same rotation,
with w >= 0. RA/Dec are those of the boresight (row 2); roll is the angle of the image-up direction
(-y camera axis) from celestial north towards east, so roll 0 is north up, east to the left.

Estimators (Wahba's problem, weights w_i = 1 / sigma_i^2): Markley's SVD method and Davenport's
q-method. Both report the attitude covariance of the QUEST measurement model,
P = (sum_i w_i (I - b_i b_i^T))^-1 in the camera frame.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from skyview.core.catalog import radec_to_vec, vec_to_radec

RAD_TO_ARCSEC = 180.0 / np.pi * 3600.0
try:  # the gufunc behind np.linalg.svd (numpy 1.x and 2.x); np.linalg.svd where it is not there
    from numpy.linalg._umath_linalg import svd_f as _SVD_F
except ImportError:  # pragma: no cover
    _SVD_F = None


# ------------------------------------------------------------------------- conventions

def east_north(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local east and north unit vectors at direction b (east = z x b / |z x b|, north = b x east).

    At the celestial poles east is taken along the RA that atan2 gives for b (the limit of z x b).
    """
    b = np.asarray(b, dtype=np.float64)
    ra, _ = vec_to_radec(b)
    east = np.array([-np.sin(ra), np.cos(ra), 0.0])
    north = np.cross(b, east)
    return east, north / np.linalg.norm(north)


def cross3(a, b) -> np.ndarray:
    """The cross product of two 3-vectors: np.cross's numbers (the same products and differences, in
    the same order) without its axis handling (~15 us a call: sweeps make millions)."""
    a0, a1, a2 = (float(x) for x in a)
    b0, b1, b2 = (float(x) for x in b)
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def R_from_radec_roll(ra_rad: float, dec_rad: float, roll_rad: float) -> np.ndarray:
    """Attitude for a boresight at (RA, Dec) and a roll (image up from north towards east)."""
    return attitudes_from_radec_roll(ra_rad, dec_rad, roll_rad)[0]


def attitudes_from_radec_roll(ra_rad: np.ndarray, dec_rad: np.ndarray, roll_rad: np.ndarray) -> np.ndarray:
    """R_from_radec_roll for arrays of orientations (radians): (N, 3, 3), the rows x, y, boresight (the
    boresight b, east e = [-sin ra, cos ra, 0], north n = b x e, image up u = cos(roll) n + sin(roll) e,
    y = -u, x = y x b)."""
    ra, dec, roll = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (ra_rad, dec_rad, roll_rad))
    b = radec_to_vec(ra, dec)
    east = np.stack([-np.sin(ra), np.cos(ra), np.zeros_like(ra)], axis=-1)
    north = np.cross(b, east)
    y = -(np.cos(roll)[:, None] * north + np.sin(roll)[:, None] * east)
    return np.stack([np.cross(y, b), y, b], axis=1)


def radec_roll_from_R(R: np.ndarray) -> tuple[float, float, float]:
    """(RA in [0, 2pi), Dec, roll in (-pi, pi]) of an attitude, radians."""
    R = np.asarray(R, dtype=np.float64)
    b = R[2]
    ra, dec = vec_to_radec(b)
    east, north = east_north(b)
    up = -R[1]
    roll = float(np.arctan2(up @ east, up @ north))
    return float(ra), float(dec), roll


def quat_from_R(R: np.ndarray) -> np.ndarray:
    """Scalar-first quaternion [w, x, y, z] (w >= 0) of the rotation R (v_cam = R v_icrs).

    scipy's Rotation.from_matrix(R).as_quat(scalar_first=True) to the bit (the same largest of the
    diagonal and trace, the same sums, the same normalisation: tests/test_verify.py compares them),
    in Python floats for a matrix orthogonal to 1e-13 (every estimate's), without importing
    scipy.spatial (~0.1 s); any other matrix goes to scipy (which orthogonalises it, or refuses it)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3) and np.all(np.abs(R @ R.T - _EYE3) <= 1e-13) and _det3(R) > 0:
        (a, b, c), (d, e, f), (g, h, i) = R.tolist()
        tr = a + e + i
        diag = [a, e, i, tr]
        k = diag.index(max(diag))  # the first of the largest, as argmax
        if k == 0:
            x, y, z, w = 1 - tr + 2 * a, d + b, g + c, h - f
        elif k == 1:
            x, y, z, w = d + b, 1 - tr + 2 * e, h + f, c - g
        elif k == 2:
            x, y, z, w = g + c, h + f, 1 - tr + 2 * i, d - b
        else:
            x, y, z, w = h - f, c - g, d - b, 1 + tr
        n = math.sqrt(x * x + y * y + z * z + w * w)
        q = np.array([w / n, x / n, y / n, z / n])
    else:
        from scipy.spatial.transform import Rotation  # (imported here: scipy.spatial costs ~0.1 s to import)

        q = Rotation.from_matrix(R).as_quat(scalar_first=True)
    return -q if q[0] < 0 else q


def rotvec_from_R(R: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle, radians) of R: scipy's Rotation.from_matrix(R).as_rotvec()
    to the bit (from the same quaternion, w >= 0, with the same series below 1e-3 rad), without
    importing scipy.spatial for an orthogonal R."""
    w, x, y, z = quat_from_R(R).tolist()
    angle = 2 * math.atan2(math.sqrt(x * x + y * y + z * z), w)
    if angle <= 1e-3:
        a2 = angle * angle
        scale = 2 + a2 / 12 + 7 * a2 * a2 / 2880
    else:
        scale = angle / math.sin(angle / 2)
    return np.array([scale * x, scale * y, scale * z])


def R_from_quat(q_wxyz: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q_wxyz, dtype=np.float64), scalar_first=True).as_matrix()


def random_attitudes(n: int, rng: np.random.Generator) -> np.ndarray:
    """n attitudes uniform on SO(3), shape (n, 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=rng).as_matrix().reshape(n, 3, 3)


def orthonormalize(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


# ------------------------------------------------------------------------- estimators

class AttitudeEstimate:
    """An attitude estimate: R (v_cam = R v_icrs), its covariance (3x3 rad^2, small rotation about
    camera x, y, z) and the Wahba loss 1/2 sum w |b - R r|^2 (unitless with w in 1/rad^2; computed
    when first asked for, from the pairs the estimate was made of: most callers never ask)."""

    __slots__ = ("R", "covariance", "_loss", "_pairs")

    def __init__(self, R: np.ndarray, covariance: np.ndarray, loss: float | None = None, *, pairs=None):
        if loss is None and pairs is None:
            raise ValueError("an attitude estimate needs its loss or the pairs it was made of")
        self.R = R
        self.covariance = covariance
        self._loss = None if loss is None else float(loss)
        self._pairs = pairs  # (b, r, w): w one weight or one per pair

    @property
    def loss(self) -> float:
        if self._loss is None:
            b, r, w = self._pairs
            resid = b - r @ self.R.T
            self._loss = 0.5 * float(np.sum(w * np.sum(resid * resid, axis=1)))
        return self._loss

    def __repr__(self) -> str:
        return f"AttitudeEstimate(R={self.R!r}, covariance={self.covariance!r}, loss={self.loss!r})"

    @property
    def sigma_boresight_arcsec(self) -> float:
        """1-sigma pointing error of the boresight, per cross-boresight axis (RMS of x and y)."""
        return float(np.sqrt(0.5 * (self.covariance[0, 0] + self.covariance[1, 1])) * RAD_TO_ARCSEC)

    @property
    def sigma_roll_arcsec(self) -> float:
        """1-sigma error of the rotation about the boresight."""
        return float(np.sqrt(self.covariance[2, 2]) * RAD_TO_ARCSEC)


def _weights(n: int, sigma: float | np.ndarray) -> np.ndarray:
    if isinstance(sigma, (float, int)) and not isinstance(sigma, bool):  # the usual case: one sigma for all
        if not sigma > 0:
            raise ValueError("measurement sigma must be positive")
        return np.full(n, 1.0 / (float(sigma) * float(sigma)))
    s = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (n,))
    if np.any(s <= 0):
        raise ValueError("measurement sigma must be positive")
    return 1.0 / (s * s)


def _inverse_3x3(F) -> np.ndarray | None:
    """Inverse of a symmetric 3x3 matrix (nested lists of Python floats) by cofactors; None when it is near
    singular (then pinv)."""
    (a, b, c), (_, d, e), (_, _, f) = F
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * c00 + b * c01 + c * c02
    scale = max(abs(a), abs(d), abs(f))
    if not (scale > 0 and abs(det) > 1e-9 * scale ** 3):
        return None
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    # each cofactor / det in Python: the numbers of np.array(cofactors) / det
    c00, c01, c02, c11, c12, c22 = c00 / det, c01 / det, c02 / det, c11 / det, c12 / det, c22 / det
    return np.array([[c00, c01, c02], [c01, c11, c12], [c02, c12, c22]])


_EYE3 = np.eye(3)


def attitude_covariance(b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """QUEST model covariance (sum w_i (I - b_i b_i^T))^-1, camera frame, rad^2 (the pseudo-inverse
    when the matrix is singular: all vectors parallel)."""
    return _covariance(w.sum(), (b * w[:, None]).T @ b)


def _covariance(w_sum: float, bwb: np.ndarray) -> np.ndarray:
    """attitude_covariance from sum w_i and sum w_i b_i b_i^T."""
    # F = w_sum I - bwb in Python floats, as numpy computes it: the diagonal w_sum * 1 - bwb_ii, off it
    # w_sum * 0 - bwb_ij = 0.0 - bwb_ij (w_sum > 0; the same zero's sign too)
    (p, q, r), (s, t, u), (x, y, z) = bwb.tolist()
    w_sum = float(w_sum)
    F = [[w_sum - p, 0.0 - q, 0.0 - r], [0.0 - s, w_sum - t, 0.0 - u], [0.0 - x, 0.0 - y, w_sum - z]]
    inv = _inverse_3x3(F)
    return np.linalg.pinv(np.array(F)) if inv is None else inv


_W_SUMS: dict[tuple[int, float], float] = {}


def _weight_sum(n: int, w: float) -> float:
    """np.full(n, w).sum(), remembered: numpy's pairwise sum of n equal weights (not n * w, which
    rounds differently), computed once per (n, w) instead of two numpy calls per estimate."""
    key = (n, w)
    s = _W_SUMS.get(key)
    if s is None:
        if len(_W_SUMS) > 4096:
            _W_SUMS.clear()
        s = _W_SUMS[key] = float(np.full(n, w).sum())
    return s


def _svd3(B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """U, V^T of a 3x3 matrix: the LAPACK routine np.linalg.svd calls, without its wrapper (checks,
    error-state context: ~4 us of its ~8); np.linalg.svd itself (and its LinAlgError) for input that
    is not finite."""
    if _SVD_F is None or B.dtype != np.float64 or not math.isfinite(sum(B.ravel().tolist())):
        U, _, Vt = np.linalg.svd(B)
        return U, Vt
    U, _, Vt = _SVD_F(B)  # float64: the "d->ddd" loop np.linalg.svd names, found without the signature
    return U, Vt


def _finish(R: np.ndarray, b: np.ndarray, r: np.ndarray, w: np.ndarray) -> AttitudeEstimate:
    return AttitudeEstimate(R, attitude_covariance(b, w), pairs=(b, r, w))


def _proper(U: np.ndarray, Vt: np.ndarray) -> np.ndarray:
    """U V^T, with the axis of the smallest singular value flipped when det(U) det(V) = -1."""
    if _det3(U) * _det3(Vt) < 0:
        U = U.copy()
        U[:, 2] = -U[:, 2]
    return U @ Vt


def proper_rotation(B: np.ndarray) -> np.ndarray:
    """The proper rotation R maximising trace(R^T B) for a 3x3 attitude profile matrix B = sum b_i r_i^T
    (Markley's SVD step, unweighted: U diag(1, 1, det U det V) V^T), without np.linalg's wrappers."""
    return _proper(*_svd3(np.asarray(B, dtype=np.float64)))


def svd_attitude(b: np.ndarray, r: np.ndarray, sigma: float | np.ndarray = 1.0) -> AttitudeEstimate:
    """Markley's SVD solution of Wahba's problem: b_i ~ R r_i (b: camera, r: ICRS), proper R.

    With one sigma for every pair (the usual case) the same numbers are computed with a scalar
    weight (b * w is b * w[:, None] for equal weights, element for element), so the answer is the
    general path's to the last bit, in about half its time (a star tracker's few stars make
    every numpy call's overhead count)."""
    b = np.asarray(b, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if len(b) < 2 or b.shape != r.shape:
        raise ValueError("need at least two matched vector pairs of the same shape")
    if isinstance(sigma, (float, int)) and not isinstance(sigma, bool):
        if not sigma > 0:
            raise ValueError("measurement sigma must be positive")
        w = 1.0 / (float(sigma) * float(sigma))
        bw = b * w
        U, Vt = _svd3(bw.T @ r)
        return AttitudeEstimate(_proper(U, Vt), _covariance(_weight_sum(len(b), w), bw.T @ b), pairs=(b, r, w))
    w = _weights(len(b), sigma)
    U, Vt = _svd3((b * w[:, None]).T @ r)
    return _finish(_proper(U, Vt), b, r, w)


_REMEMBERED: dict[tuple, AttitudeEstimate] = {}
_REMEMBERED_LOCK = threading.Lock()
REMEMBER_MAX = 8


def _memo_key(b: np.ndarray, r: np.ndarray, sigma) -> tuple | None:
    if not (isinstance(sigma, (float, int)) and not isinstance(sigma, bool)):
        return None
    b = np.ascontiguousarray(b, dtype=np.float64)
    r = np.ascontiguousarray(r, dtype=np.float64)
    return b.shape, b.tobytes(), r.tobytes(), float(sigma)


def remember_svd(b: np.ndarray, r: np.ndarray, sigma: float, est: AttitudeEstimate) -> None:
    """Keep `est` = svd_attitude(b, r, sigma) for `recall_svd` (the last REMEMBER_MAX of them): the
    shared verification ends in the estimate from every match, and the solver's attitude stage
    estimates the same thing again from the same numbers."""
    key = _memo_key(b, r, sigma)
    if key is None:
        return
    with _REMEMBERED_LOCK:
        _REMEMBERED.pop(key, None)
        _REMEMBERED[key] = est
        while len(_REMEMBERED) > REMEMBER_MAX:
            del _REMEMBERED[next(iter(_REMEMBERED))]


def svd_attitude_remembered(b: np.ndarray, r: np.ndarray, sigma: float | np.ndarray = 1.0) -> AttitudeEstimate:
    """svd_attitude(b, r, sigma): a remembered estimate of exactly these numbers (`remember_svd`;
    R and the covariance copied), else a new one."""
    b = np.asarray(b, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    key = _memo_key(b, r, sigma)
    est = None
    if key is not None:
        with _REMEMBERED_LOCK:
            est = _REMEMBERED.get(key)
    if est is None:
        return svd_attitude(b, r, sigma)
    w = 1.0 / (float(sigma) * float(sigma))
    return AttitudeEstimate(est.R.copy(), est.covariance.copy(), pairs=(b, r, w))


def _det3(M: np.ndarray) -> float:
    """Determinant of a 3x3 matrix (+-1 for the orthogonal factors of an SVD), without np.linalg.det's
    per-call overhead."""
    (a, b, c), (d, e, f), (g, h, i) = M.tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def q_method_attitude(b: np.ndarray, r: np.ndarray, sigma: float | np.ndarray = 1.0) -> AttitudeEstimate:
    """Davenport's q-method: the eigenvector of K with the largest eigenvalue."""
    b = np.asarray(b, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if len(b) < 2 or b.shape != r.shape:
        raise ValueError("need at least two matched vector pairs of the same shape")
    w = _weights(len(b), sigma)
    B = (b * w[:, None]).T @ r
    S = B + B.T
    z = np.array([B[1, 2] - B[2, 1], B[2, 0] - B[0, 2], B[0, 1] - B[1, 0]])
    tr = np.trace(B)
    K = np.zeros((4, 4))
    K[:3, :3] = S - tr * np.eye(3)
    K[:3, 3] = z
    K[3, :3] = z
    K[3, 3] = tr
    vals, vecs = np.linalg.eigh(K)
    qv, q4 = vecs[:3, -1], vecs[3, -1]  # Markley's vector-first quaternion of the attitude matrix
    qx = np.array([[0, -qv[2], qv[1]], [qv[2], 0, -qv[0]], [-qv[1], qv[0], 0]])
    R = (q4 * q4 - qv @ qv) * np.eye(3) + 2.0 * np.outer(qv, qv) - 2.0 * q4 * qx
    return _finish(R, b, r, w)


ESTIMATORS = {"svd": svd_attitude, "q-method": q_method_attitude}


# ------------------------------------------------------------------------- errors

def attitude_error_arcsec(R_est: np.ndarray, R_true: np.ndarray) -> dict:
    """Difference between two attitudes, in the camera frame of the truth.

    boresight: angle between the two boresights; cross_x / cross_y: the small rotation about the
    camera x and y axes; roll: about the boresight; total: the whole rotation angle. Arcseconds.
    """
    dR = np.asarray(R_est) @ np.asarray(R_true).T
    phi = rotvec_from_R(dR)
    # atan2 of the cross and dot products: exact for small angles, and insensitive to rows that are
    # unit only to a few digits (a reference attitude printed to 8 digits: arccos would add ~20")
    a, b = np.asarray(R_est, dtype=np.float64)[2], np.asarray(R_true, dtype=np.float64)[2]
    return {
        "boresight": float(np.arctan2(np.linalg.norm(cross3(a, b)), a @ b) * RAD_TO_ARCSEC),
        "cross_x": float(phi[0] * RAD_TO_ARCSEC),
        "cross_y": float(phi[1] * RAD_TO_ARCSEC),
        "roll": float(phi[2] * RAD_TO_ARCSEC),
        "total": float(np.linalg.norm(phi) * RAD_TO_ARCSEC),
    }
