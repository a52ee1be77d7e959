"""Camera models in the OpenCV convention (see docs/conventions.md): pinhole, and two fisheye lenses.

Camera frame: +x right (increasing u), +y down (increasing v), +z along the boresight. Pixel centres
are at integer coordinates, (0, 0) is the centre of the top-left pixel, and the principal point
defaults to ((W-1)/2, (H-1)/2). The user's FOV is the horizontal full angle across the W pixels,
edge to edge.

- `pinhole` (the default): the gnomonic projection, r = f tan(theta), so fx = W / (2 tan(fov/2)).
  Optional radial distortion (Brown, k1 and k2 on normalised coordinates: x_d = x (1 + k1 r^2 +
  k2 r^4)), the same model as OpenCV's first two coefficients. Fields below 180 deg.
- `equidistant`: r = f theta_d, theta_d = theta (1 + k1 theta^2 + k2 theta^4): OpenCV's fisheye model
  (cv2.fisheye, its first two coefficients), the lens of most all-sky and meteor cameras.
- `equisolid`: r = 2 f sin(theta_d / 2), the same theta_d: the equal-area fisheye.
  A fisheye's FOV may reach 360 deg (the image's width spans theta = FOV / 2 each side).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import cached_property, lru_cache

import cv2
import numpy as np

from skyview.core.errors import BadInput

PINHOLE = "pinhole"
EQUIDISTANT = "equidistant"
EQUISOLID = "equisolid"
MODELS = (PINHOLE, EQUIDISTANT, EQUISOLID)
FISHEYE_MODELS = (EQUIDISTANT, EQUISOLID)
# the horizontal FOVs the blind search looks for a fisheye at (skyview.identify.blind): all-sky and meteor
# cameras, 90-200 deg, and wide lenses from about where the pinhole search ends (~81 deg)
FISHEYE_FOV_RANGE_DEG = (70.0, 240.0)


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    model: str = PINHOLE

    def __post_init__(self):
        if self.model not in MODELS:
            raise BadInput(f"unknown camera model {self.model!r}: choose from {', '.join(MODELS)}")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_fov(cls, fov_deg: float, width: int = 1024, height: int | None = None,
                 k1: float = 0.0, k2: float = 0.0, model: str = PINHOLE) -> "Camera":
        """Square pixels, principal point at the image centre, horizontal full FOV in degrees."""
        height = width if height is None else height
        check_fov_deg(fov_deg, model)
        if int(width) < 16 or int(height) < 16:
            raise BadInput(f"image size {width}x{height} is too small (at least 16x16 pixels)")
        half = np.radians(fov_deg) / 2.0
        if model == PINHOLE:
            f = width / (2.0 * np.tan(half))
        else:
            f = width / 2.0 / fisheye_r(np.asarray(half), model)
        return cls(int(width), int(height), float(f), float(f), (width - 1) / 2.0, (height - 1) / 2.0,
                   float(k1), float(k2), model)

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(**{k: d[k] for k in ("width", "height", "fx", "fy", "cx", "cy")},
                   k1=d.get("k1", 0.0), k2=d.get("k2", 0.0), model=d.get("model", PINHOLE))

    @property
    def fisheye(self) -> bool:
        return self.model != PINHOLE

    def to_dict(self) -> dict:
        d = asdict(self)
        d["fov_deg"] = self.fov_deg
        return d

    # ------------------------------------------------------------------ geometry
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distorted(self) -> bool:
        return self.k1 != 0.0 or self.k2 != 0.0

    @property
    def fov_deg(self) -> float:
        """Horizontal full FOV, degrees (of the undistorted model)."""
        if self.fisheye:
            return float(np.degrees(2.0 * fisheye_theta(np.asarray(self.width / (2.0 * self.fx)), self.model)))
        return float(np.degrees(2.0 * np.arctan(self.width / (2.0 * self.fx))))

    @property
    def fov_v_deg(self) -> float:
        """Vertical full FOV, degrees (of the undistorted model)."""
        if self.fisheye:
            return float(np.degrees(2.0 * fisheye_theta(np.asarray(self.height / (2.0 * self.fy)), self.model)))
        return float(np.degrees(2.0 * np.arctan(self.height / (2.0 * self.fy))))

    @cached_property
    def half_diagonal_rad(self) -> float:
        """Angle from the boresight to the farthest image corner (radius of the circumscribed cone); computed
        once per camera (it unprojects the corners)."""
        if self.fisheye:
            corners = np.array([[-0.5, -0.5], [self.width - 0.5, -0.5], [-0.5, self.height - 0.5],
                                [self.width - 0.5, self.height - 0.5]])
            return float(np.max(np.arccos(np.clip(self.unproject(corners)[:, 2], -1.0, 1.0))))
        # a pinhole's corners in Python floats (the numpy calls of the general path cost ~25 us, and every
        # camera a fit makes asks once): the angle of (x, y, 1) from the axis, the distortion taken out first
        xs = ((-0.5 - self.cx) / self.fx, (self.width - 0.5 - self.cx) / self.fx)
        ys = ((-0.5 - self.cy) / self.fy, (self.height - 0.5 - self.cy) / self.fy)
        xy = [(x, y) for y in ys for x in xs]
        if self.distorted:
            xy = self._undistort(np.array(xy)).tolist()
        return max(math.acos(min(1.0, 1.0 / math.sqrt(x * x + y * y + 1.0))) for x, y in xy)

    @property
    def pixel_scale_rad(self) -> float:
        """Angle subtended by one pixel at the principal point (radians per pixel)."""
        return float(1.0 / self.fx)

    @property
    def solid_angle_sr(self) -> float:
        """Solid angle of the whole sensor (exact for an undistorted pinhole; a fisheye's summed over a
        grid of the sensor, its distortion left out)."""
        if self.fisheye:
            n = 129
            u = (np.arange(n) + 0.5) / n * self.width - 0.5
            v = (np.arange(n) + 0.5) / n * self.height - 0.5
            x = (u[None, :] - self.cx) / self.fx
            y = (v[:, None] - self.cy) / self.fy
            r = np.hypot(x, y)
            th = fisheye_theta(r, self.model)
            ok = th < np.pi
            # sky area per unit of normalised image area: sin(theta) dtheta / (r dr)
            with np.errstate(invalid="ignore", divide="ignore"):
                dens = np.where(r > 1e-12, np.sin(th) / np.maximum(r, 1e-12) * fisheye_dtheta_dr(r, self.model), 1.0)
            cell = (self.width / n / self.fx) * (self.height / n / self.fy)
            return float(np.sum(np.where(ok, dens, 0.0)) * cell)
        # solid angle of a rectangle [x0,x1]x[y0,y1] on the z=1 plane: sum of atan terms
        x = np.array([-0.5 - self.cx, self.width - 0.5 - self.cx]) / self.fx
        y = np.array([-0.5 - self.cy, self.height - 0.5 - self.cy]) / self.fy

        def F(a, b):
            return np.arctan(a * b / np.sqrt(1.0 + a * a + b * b))

        return float(F(x[1], y[1]) - F(x[0], y[1]) - F(x[1], y[0]) + F(x[0], y[0]))

    def _distort(self, xy: np.ndarray) -> np.ndarray:
        if not self.distorted:
            return xy
        r2 = np.sum(xy * xy, axis=-1, keepdims=True)
        return xy * (1.0 + self.k1 * r2 + self.k2 * r2 * r2)

    def _undistort(self, xy_d: np.ndarray) -> np.ndarray:
        if not self.distorted:
            return xy_d
        pts = np.ascontiguousarray(xy_d.reshape(-1, 1, 2), dtype=np.float64)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        und = cv2.undistortPoints(pts, np.eye(3), np.array([self.k1, self.k2, 0.0, 0.0]), None, None, None, crit)
        return und.reshape(xy_d.shape)

    def undistorted_normalised(self, xy_d: np.ndarray) -> np.ndarray:
        """Normalised image offsets ((u - cx) / fx, (v - cy) / fy) with the distortion taken out: where the
        same directions land through the model without k1, k2 (a fisheye: g(theta) along the same
        azimuth instead of g(theta_d))."""
        xy_d = np.asarray(xy_d, dtype=np.float64)
        if not self.fisheye:
            return self._undistort(xy_d)
        uv = xy_d * np.array([self.fx, self.fy]) + np.array([self.cx, self.cy])
        v = self._unproject_fisheye(np.atleast_2d(uv))
        rho = np.hypot(v[:, 0], v[:, 1])
        r = fisheye_r(np.arctan2(rho, v[:, 2]), self.model)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(rho > 1e-15, r / np.maximum(rho, 1e-300), 0.0)
        return v[:, :2] * s[:, None]

    def project(self, v_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame directions (N, 3) -> pixels (N, 2) and a mask of those in front (z > 0; a
        fisheye: less than 180 deg from the boresight, and where its distortion still maps outwards).

        Directions behind the camera get NaN pixels.
        """
        v = np.atleast_2d(np.asarray(v_cam, dtype=np.float64))
        if self.fisheye:
            return self._project_fisheye(v)
        front = v[:, 2] > 1e-12
        z = np.where(front, v[:, 2], 1.0)
        xy = self._distort(v[:, :2] / z[:, None])
        uv = np.empty((len(v), 2))
        uv[:, 0] = self.fx * xy[:, 0] + self.cx
        uv[:, 1] = self.fy * xy[:, 1] + self.cy
        uv[~front] = np.nan
        return uv, front

    def _theta_d(self, th: np.ndarray) -> np.ndarray:
        t2 = th * th
        return th * (1.0 + self.k1 * t2 + self.k2 * t2 * t2)

    def _project_fisheye(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rho = np.hypot(v[:, 0], v[:, 1])
        th = np.arctan2(rho, v[:, 2])
        # in front: short of the antipode, and where theta_d still grows with theta (a strong negative k
        # folds the image back beyond some angle)
        t2 = th * th
        grows = 1.0 + 3.0 * self.k1 * t2 + 5.0 * self.k2 * t2 * t2 > 0.0
        front = (th < np.pi - 1e-9) & grows
        r = fisheye_r(self._theta_d(th), self.model)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(rho > 1e-15, r / np.maximum(rho, 1e-300), 0.0)
        uv = np.empty((len(v), 2))
        uv[:, 0] = self.fx * v[:, 0] * s + self.cx
        uv[:, 1] = self.fy * v[:, 1] * s + self.cy
        uv[~front] = np.nan
        return uv, front

    def _unproject_fisheye(self, uv: np.ndarray) -> np.ndarray:
        x = (uv[:, 0] - self.cx) / self.fx
        y = (uv[:, 1] - self.cy) / self.fy
        r = np.hypot(x, y)
        th_d = fisheye_theta(r, self.model)
        th = th_d.copy()
        if self.distorted:  # theta (1 + k1 theta^2 + k2 theta^4) = theta_d: Newton from theta_d
            for _ in range(20):
                t2 = th * th
                g = th * (1.0 + self.k1 * t2 + self.k2 * t2 * t2) - th_d
                dg = 1.0 + 3.0 * self.k1 * t2 + 5.0 * self.k2 * t2 * t2
                step = g / np.where(np.abs(dg) > 1e-12, dg, 1e-12)
                th = th - step
                if float(np.max(np.abs(step), initial=0.0)) < 1e-14:
                    break
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.where(r > 1e-15, np.sin(th) / np.maximum(r, 1e-300), 0.0)
        return np.stack([x * c, y * c, np.cos(th)], axis=1)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> camera-frame unit vectors (N, 3)."""
        uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
        if self.fisheye:
            return self._unproject_fisheye(uv)
        if not self.distorted and uv.ndim == 2 and uv.shape[1] == 2:
            # the general path's numbers in fewer numpy calls: x = (u - cx) / fx and y likewise (both
            # columns at once, element by element), z = 1, then v / sqrt(add.reduce(v * v)), which is
            # what np.linalg.norm computes for real rows
            c, f = _centre_focal(self)
            return pinhole_rays(uv - c, f)
        xy_d = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)
        xy = self._undistort(xy_d)
        v = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Mask of pixel positions inside the sensor (edges at -0.5 and W-0.5), shrunk by `margin`."""
        uv = np.atleast_2d(uv)
        with np.errstate(invalid="ignore"):
            return ((uv[:, 0] >= -0.5 + margin) & (uv[:, 0] <= self.width - 0.5 - margin)
                    & (uv[:, 1] >= -0.5 + margin) & (uv[:, 1] <= self.height - 0.5 - margin))

    def visible(self, R: np.ndarray, xyz_icrs: np.ndarray, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Indices of ICRS directions that land on the sensor for attitude R, and their pixels."""
        v_cam = np.asarray(xyz_icrs) @ np.asarray(R).T
        uv, front = self.project(v_cam)
        ok = front & self.in_image(uv, margin)
        idx = np.flatnonzero(ok)
        return idx, uv[idx]


def rows_turned_over(uv: np.ndarray, height: int) -> np.ndarray:
    """Pixel positions (N, 2) in the image with its rows turned over: row v becomes row height - 1 - v (about
    the centre, where the camera's principal point lies: a ray's y changes sign)."""
    out = np.array(uv, dtype=np.float64).reshape(-1, 2)
    out[:, 1] = (height - 1) - out[:, 1]
    return out


def pinhole_rays(offsets: np.ndarray, focal) -> np.ndarray:
    """Unit vectors of undistorted pinhole pixels: offsets (..., N, 2) from the principal point over focal
    (broadcast: [fx, fy], or one focal length per camera shaped (K, 1, 1) for K cameras at once), z = 1,
    normalised as np.linalg.norm does for real rows (element by element: the numbers of one camera at a time)."""
    v = np.ones(np.broadcast_shapes(np.shape(offsets), np.shape(focal))[:-1] + (3,))
    np.divide(offsets, focal, out=v[..., :2])
    return v / np.sqrt(np.add.reduce(v * v, axis=-1, keepdims=True))


@lru_cache(maxsize=64)
def _centre_focal(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """[cx, cy] and [fx, fy] as arrays, made once per camera (unproject's constants)."""
    return np.array([camera.cx, camera.cy]), np.array([camera.fx, camera.fy])


def check_fov_deg(fov_deg: float, model: str = PINHOLE) -> None:
    """An FOV the model can represent: 0 < FOV < 180 degrees for a pinhole, < 360 for a fisheye."""
    try:
        f = float(fov_deg)
    except (TypeError, ValueError):
        raise BadInput(f"FOV {fov_deg!r} is not a number") from None
    top = 180.0 if model == PINHOLE else 360.0
    if not np.isfinite(f) or f <= 0.0 or f >= top:
        if model == PINHOLE:
            raise BadInput(f"FOV {fov_deg} deg is impossible for a pinhole camera: it must be in (0, 180) (a wider "
                           "lens is a fisheye: model='equidistant' or 'equisolid')")
        raise BadInput(f"FOV {fov_deg} deg is impossible for the {model} fisheye: it must be in (0, 360)")


def fisheye_r(theta: np.ndarray, model: str) -> np.ndarray:
    """Normalised image radius of the (distorted) off-axis angle theta: theta, or 2 sin(theta / 2)."""
    return theta if model == EQUIDISTANT else 2.0 * np.sin(theta / 2.0)


def fisheye_theta(r: np.ndarray, model: str) -> np.ndarray:
    """The inverse of fisheye_r (NaN beyond the equisolid lens's r = 2)."""
    if model == EQUIDISTANT:
        return np.asarray(r, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return 2.0 * np.arcsin(np.asarray(r, dtype=np.float64) / 2.0)


def fisheye_dtheta_dr(r: np.ndarray, model: str) -> np.ndarray:
    if model == EQUIDISTANT:
        return np.ones_like(r)
    with np.errstate(invalid="ignore", divide="ignore"):
        return 1.0 / np.sqrt(np.maximum(1.0 - (r / 2.0) ** 2, 1e-300))
