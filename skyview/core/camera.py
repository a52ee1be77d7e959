"""Pinhole camera in the OpenCV convention (see docs/conventions.md).

Camera frame: +x right (increasing u), +y down (increasing v), +z along the boresight. Pixel centres
are at integer coordinates, (0, 0) is the centre of the top-left pixel, and the principal point
defaults to ((W-1)/2, (H-1)/2). The user's FOV is the horizontal full angle across the W pixels,
edge to edge: fx = W / (2 tan(fov/2)). Optional radial distortion (Brown, k1 and k2 on normalised
coordinates: x_d = x (1 + k1 r^2 + k2 r^4)), the same model as OpenCV's first two coefficients.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache

import cv2
import numpy as np

from skyview.core.errors import BadInput


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

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_fov(cls, fov_deg: float, width: int = 1024, height: int | None = None,
                 k1: float = 0.0, k2: float = 0.0) -> "Camera":
        """Square pixels, principal point at the image centre, horizontal full FOV in degrees."""
        height = width if height is None else height
        check_fov_deg(fov_deg)
        if int(width) < 16 or int(height) < 16:
            raise BadInput(f"image size {width}x{height} is too small (at least 16x16 pixels)")
        f = width / (2.0 * np.tan(np.radians(fov_deg) / 2.0))
        return cls(int(width), int(height), float(f), float(f), (width - 1) / 2.0, (height - 1) / 2.0,
                   float(k1), float(k2))

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(**{k: d[k] for k in ("width", "height", "fx", "fy", "cx", "cy")},
                   k1=d.get("k1", 0.0), k2=d.get("k2", 0.0))

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
        """Horizontal full FOV, degrees."""
        return float(np.degrees(2.0 * np.arctan(self.width / (2.0 * self.fx))))

    @property
    def fov_v_deg(self) -> float:
        """Vertical full FOV, degrees."""
        return float(np.degrees(2.0 * np.arctan(self.height / (2.0 * self.fy))))

    @property
    def half_diagonal_rad(self) -> float:
        """Angle from the boresight to the farthest image corner (radius of the circumscribed cone)."""
        corners = np.array([[-0.5, -0.5], [self.width - 0.5, -0.5], [-0.5, self.height - 0.5],
                            [self.width - 0.5, self.height - 0.5]])
        return float(np.max(np.arccos(np.clip(self.unproject(corners)[:, 2], -1.0, 1.0))))

    @property
    def pixel_scale_rad(self) -> float:
        """Angle subtended by one pixel at the principal point (radians per pixel)."""
        return float(1.0 / self.fx)

    @property
    def solid_angle_sr(self) -> float:
        """Solid angle of the whole sensor (exact for an undistorted pinhole)."""
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

    def project(self, v_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame directions (N, 3) -> pixels (N, 2) and a mask of those in front (z > 0).

        Directions behind the camera get NaN pixels.
        """
        v = np.atleast_2d(np.asarray(v_cam, dtype=np.float64))
        front = v[:, 2] > 1e-12
        z = np.where(front, v[:, 2], 1.0)
        xy = self._distort(v[:, :2] / z[:, None])
        uv = np.empty((len(v), 2))
        uv[:, 0] = self.fx * xy[:, 0] + self.cx
        uv[:, 1] = self.fy * xy[:, 1] + self.cy
        uv[~front] = np.nan
        return uv, front

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> camera-frame unit vectors (N, 3)."""
        uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
        if not self.distorted and uv.ndim == 2 and uv.shape[1] == 2:
            # the general path's numbers in fewer numpy calls: x = (u - cx) / fx and y likewise (both
            # columns at once, element by element), z = 1, then v / sqrt(add.reduce(v * v)), which is
            # what np.linalg.norm computes for real rows
            c, f = _centre_focal(self)
            v = np.ones((len(uv), 3))
            np.divide(uv - c, f, out=v[:, :2])
            return v / np.sqrt(np.add.reduce(v * v, axis=1, keepdims=True))
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


@lru_cache(maxsize=64)
def _centre_focal(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """[cx, cy] and [fx, fy] as arrays, made once per camera (unproject's constants)."""
    return np.array([camera.cx, camera.cy]), np.array([camera.fx, camera.fy])


def check_fov_deg(fov_deg: float) -> None:
    """An FOV the pinhole model can represent: 0 < FOV < 180 degrees."""
    try:
        f = float(fov_deg)
    except (TypeError, ValueError):
        raise BadInput(f"FOV {fov_deg!r} is not a number") from None
    if not np.isfinite(f) or f <= 0.0 or f >= 180.0:
        raise BadInput(f"FOV {fov_deg} deg is impossible for a pinhole camera: it must be in (0, 180)")
