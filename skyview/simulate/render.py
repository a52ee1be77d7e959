"""Star-field simulator: attitude + camera + catalog -> sensor image with known truth.

Long (over 900 lines) because the simulator is one chain in sections (sensor model, PSF rendering,
optics and sky effects, JPEG, frames, atomic file writing, slews) that share the pixel, sensor and truth
conventions this module defines once.

Conventions (docs: /work/shared/DESIGN.md): v_cam = R @ v_icrs; camera +x right (u), +y down (v),
+z boresight; pixel centres at integer coordinates, (0, 0) the centre of the top-left pixel, so
pixel (i, j) (row i, column j) covers u in [j - 0.5, j + 0.5] and v in [i - 0.5, i + 0.5].

Image chain, per frame:

1. Catalog stars with Hp <= mag_limit inside the field (optionally with a Gaussian direction jitter,
   `position_noise_rad`, per tangent-plane axis) are projected with the Camera (radial distortion
   included). Stars whose PSF centre falls off the sensor are not rendered; `n_dropped` more are
   removed at random; `n_false_stars` extra blobs not in the catalog are added.
2. Expected photo-electrons per star: zero_point_e_per_s * 10^(-0.4 Hp) * exposure_s, spread by a
   Gaussian PSF integrated exactly over each pixel (erf differences along u and v).
3. Sky background + dark current per pixel, hot pixels; Poisson shot noise on all of it; clip at the
   full well; electronic bias (pedestal) and Gaussian read noise; gain to ADU; rounding and clipping
   to the ADC range (8 or 16 bit).

Real-world effects, each off by default (off, the image is the same bit for bit as without them):

- faint_extra_mag: field stars below the catalog limit, rendered down to mag_limit + faint_extra_mag
  (at most Hp 9.0, the guide catalog's depth); truth lists them with "faint": true;
- vignetting: the optics' relative illumination falls off towards the corners (cos^4-shaped in the
  off-axis angle), applied to the stars and the sky, not to dark current or hot pixels;
- sky_gradient: the sky background varies linearly across the frame (light pollution, twilight);
- jpeg_quality: the image leaves the camera as a JPEG (8 bit; 16-bit images are scaled first, see
  to_uint8); the frame keeps the encoded bytes so a saved .jpg is exactly what was decoded;
- radial distortion (k1, k2) comes with the Camera and is applied by Camera.project.

Everything random comes from one numpy Generator seeded with `seed`: the same arguments give the
same image, bit for bit.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import erf

from skyview.core.attitude import R_from_radec_roll, quat_from_R, radec_roll_from_R
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, vec_to_radec
from skyview.core.errors import BadInput
from skyview.io.atomic import write_atomic

HIP_BETELGEUSE = 27989
_SQRT2 = math.sqrt(2.0)
FAINT_MAG_CAP = 9.0  # faint field stars are rendered at most to this Hp (the guide catalog's depth)
JPEG_DEFAULT_QUALITY = 95  # a .jpg written for a frame that was not simulated as a JPEG


# ============================================================================ sensor model

@dataclass(frozen=True)
class SensorModel:
    """Detector and optics of a star tracker, in physical units.

    Defaults describe a small CMOS star tracker (~30 mm aperture, 100 ms exposure, slightly
    defocused optics): a Hp 6.0 star gives ~2600 e- and SNR ~40, stars brighter than Hp ~0.5
    saturate their central pixel, the background is read-noise dominated.

    gain_e_per_adu=None picks a gain that suits the bit depth: 16 bit -> full_well_e / 65535 (the
    ADC range spans the full well), 8 bit -> read_noise_e (1 ADU per read-noise sigma, so faint
    stars survive quantisation and stars brighter than Hp ~3.7 saturate the 8-bit ADC).
    bias_e is the electronic pedestal added before the ADC so that read noise is not clipped at 0.
    """

    exposure_s: float = 0.1
    zero_point_e_per_s: float = 6.5e6  # photo-electrons per second from a Hp 0.0 star
    psf_sigma_px: float = 1.1
    sky_background_e_per_px_s: float = 20.0
    dark_current_e_per_px_s: float = 5.0
    read_noise_e: float = 10.0
    gain_e_per_adu: float | None = None
    bit_depth: int = 16
    full_well_e: float = 50000.0
    bias_e: float = 100.0
    n_hot_pixels: int = 8
    hot_pixel_e: float = 3000.0

    def __post_init__(self) -> None:
        if self.bit_depth not in (8, 16):
            raise BadInput(f"bit_depth {self.bit_depth} is not supported: use 8 or 16")
        for name in ("exposure_s", "zero_point_e_per_s", "psf_sigma_px", "full_well_e"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise BadInput(f"sensor {name}={v} must be a positive number")
        for name in ("sky_background_e_per_px_s", "dark_current_e_per_px_s", "read_noise_e",
                     "bias_e", "hot_pixel_e", "n_hot_pixels"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise BadInput(f"sensor {name}={v} must be a number >= 0")
        if self.gain_e_per_adu is not None and not (np.isfinite(self.gain_e_per_adu) and self.gain_e_per_adu > 0):
            raise BadInput(f"sensor gain_e_per_adu={self.gain_e_per_adu} must be positive (or None for auto)")

    # ---------------------------------------------------------------- derived quantities
    @property
    def adc_max(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def gain(self) -> float:
        """Effective gain in e-/ADU (resolves gain_e_per_adu=None)."""
        if self.gain_e_per_adu is not None:
            return float(self.gain_e_per_adu)
        if self.bit_depth == 16:
            return self.full_well_e / self.adc_max
        return max(self.read_noise_e, 1.0)

    @property
    def dtype(self) -> type:
        return np.uint16 if self.bit_depth == 16 else np.uint8

    @property
    def background_e_per_px(self) -> float:
        """Sky + dark electrons per pixel in one exposure (mean, before bias)."""
        return (self.sky_background_e_per_px_s + self.dark_current_e_per_px_s) * self.exposure_s

    @property
    def noise_equivalent_pixels(self) -> float:
        """4 pi sigma^2: the effective number of pixels of a Gaussian PSF (optimal weighting)."""
        return 4.0 * math.pi * self.psf_sigma_px ** 2

    def electrons(self, mag: float | np.ndarray) -> float | np.ndarray:
        """Expected photo-electrons of a star of Hipparcos magnitude `mag` in one exposure."""
        return self.zero_point_e_per_s * 10.0 ** (-0.4 * np.asarray(mag, dtype=np.float64)) * self.exposure_s

    def pixel_noise_e(self) -> float:
        """Per-pixel noise of the background in electrons: sqrt(B + D*t + RN^2 + gain^2/12)."""
        return math.sqrt(self.background_e_per_px + self.read_noise_e ** 2 + self.gain ** 2 / 12.0)

    def snr(self, electrons: float | np.ndarray) -> float | np.ndarray:
        """Model SNR of a star: S / sqrt(S + npix_eff * (B + D*t + RN^2 + gain^2/12)).

        npix_eff = 4 pi sigma_psf^2 (noise-equivalent area of a Gaussian PSF). Saturation ignored.
        """
        s = np.asarray(electrons, dtype=np.float64)
        return s / np.sqrt(s + self.noise_equivalent_pixels * self.pixel_noise_e() ** 2)

    def snr_of_mag(self, mag: float | np.ndarray) -> float | np.ndarray:
        return self.snr(self.electrons(mag))

    def saturation_mag(self) -> float:
        """Hp at which a star centred on a pixel fills that pixel to the ADC/full-well limit."""
        a = 0.5 / (self.psf_sigma_px * _SQRT2)
        frac = float(erf(a)) ** 2  # fraction of the flux in the central pixel
        cap_e = min(self.full_well_e, self.adc_max * self.gain - self.bias_e)
        return float(-2.5 * np.log10(cap_e / frac / (self.zero_point_e_per_s * self.exposure_s)))

    def describe(self) -> dict:
        """Derived numbers for reports and the truth sidecar."""
        return {
            "gain_e_per_adu": self.gain,
            "adc_max_adu": self.adc_max,
            "bias_adu": self.bias_e / self.gain,
            "background_e_per_px": self.background_e_per_px,
            "pixel_noise_e": self.pixel_noise_e(),
            "noise_equivalent_pixels": self.noise_equivalent_pixels,
            "electrons_hp6": float(self.electrons(6.0)),
            "snr_hp6": float(self.snr_of_mag(6.0)),
            "saturation_hp": self.saturation_mag(),
        }

    # ---------------------------------------------------------------- (de)serialisation
    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SensorModel":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise BadInput(f"unknown sensor field(s): {', '.join(unknown)}")
        return cls(**d)

    def replace(self, **changes: Any) -> "SensorModel":
        return SensorModel.from_dict({**self.to_dict(), **changes})


# ============================================================================ PSF rendering

def psf_window_radius(sigma_px: float) -> int:
    """Half-size of the square window a star is drawn in: flux outside is < 1e-8."""
    return max(2, int(math.ceil(5.5 * sigma_px)))


def render_stars(shape: tuple[int, int], uv: np.ndarray, electrons: np.ndarray, sigma_px: float,
                 out: np.ndarray | None = None) -> np.ndarray:
    """Add Gaussian PSFs at sub-pixel positions to a float image (electrons), integrated per pixel.

    Pixel (i, j) receives E * [Phi((j+0.5-u)/s) - Phi((j-0.5-u)/s)] * [Phi((i+0.5-v)/s) - Phi((i-0.5-v)/s)]
    with Phi the normal CDF: exact pixel integrals of a separable Gaussian, no rounding of the
    position. Each star is drawn in a (2r+1)^2 window around its nearest pixel; parts of the window
    off the sensor are dropped (stars near the edge are clipped naturally).
    """
    H, W = int(shape[0]), int(shape[1])
    img = np.zeros((H, W), dtype=np.float64) if out is None else out
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    e = np.asarray(electrons, dtype=np.float64).reshape(-1)
    if len(uv) == 0:
        return img
    r = psf_window_radius(sigma_px)
    n = 2 * r + 1
    ar = np.arange(n)
    j0 = np.rint(uv[:, 0]).astype(np.int64) - r  # first column of each window
    i0 = np.rint(uv[:, 1]).astype(np.int64) - r
    scale = 1.0 / (sigma_px * _SQRT2)
    edges_u = (j0[:, None] - 0.5 + np.arange(n + 1)[None, :] - uv[:, :1]) * scale
    edges_v = (i0[:, None] - 0.5 + np.arange(n + 1)[None, :] - uv[:, 1:]) * scale
    fu = 0.5 * np.diff(erf(edges_u), axis=1)  # (N, n) fraction of the flux per column
    fv = 0.5 * np.diff(erf(edges_v), axis=1)  # (N, n) per row
    patch = e[:, None, None] * fv[:, :, None] * fu[:, None, :]  # (N, rows, cols)
    rows = np.broadcast_to((i0[:, None] + ar)[:, :, None], patch.shape)
    cols = np.broadcast_to((j0[:, None] + ar)[:, None, :], patch.shape)
    ok = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)
    flat = rows[ok] * W + cols[ok]
    np.add.at(img.reshape(-1), flat, patch[ok])
    return img


# ============================================================================ optics and sky effects

def vignetting_falloff(camera: Camera, vignetting: float | str) -> float:
    """Fractional loss of illumination at the image corners (0 = none) for a vignetting setting.

    "cos4": natural vignetting, 1 - cos^4(theta_corner) with theta the off-axis angle of the corner
    pixel centre (pinhole geometry); a number f in [0, 1): that fraction itself.
    """
    if isinstance(vignetting, str):
        if vignetting != "cos4":
            raise BadInput(f"vignetting {vignetting!r} must be 'cos4' or a fraction in [0, 1)")
        return float(1.0 - _cos4(camera, np.array([0.0, camera.width - 1.0]),
                                 np.array([0.0, camera.height - 1.0])).min())
    try:
        f = float(vignetting)
    except (TypeError, ValueError):
        raise BadInput(f"vignetting {vignetting!r} must be 'cos4' or a fraction in [0, 1)") from None
    if not (np.isfinite(f) and 0.0 <= f < 1.0):
        raise BadInput(f"vignetting {vignetting} must be a fraction in [0, 1) (the loss at the corners) or 'cos4'")
    return f


def _cos4(camera: Camera, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """cos^4 of the off-axis angle at pixel (u, v) (broadcast over u and v; a fisheye's from its own
    projection)."""
    if camera.fisheye:
        uu, vv = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
        z = camera.unproject(np.stack([uu.ravel(), vv.ravel()], axis=1))[:, 2].reshape(uu.shape)
        return np.clip(z, 0.0, 1.0) ** 4
    x = (np.asarray(u, dtype=np.float64) - camera.cx) / camera.fx
    y = (np.asarray(v, dtype=np.float64) - camera.cy) / camera.fy
    return 1.0 / (1.0 + x * x + y * y) ** 2


def vignetting_factor(camera: Camera, u: np.ndarray, v: np.ndarray, vignetting: float | str) -> np.ndarray:
    """Relative illumination (1 at the principal point) at pixels (u, v), broadcast over u and v.

    The profile is cos^4-shaped in the off-axis angle theta and scaled so that the corner pixel
    centres receive 1 - vignetting_falloff: I = 1 - f * (1 - cos^4 theta) / (1 - cos^4 theta_corner).
    With "cos4" that is cos^4 theta itself. The pinhole angle is used (distortion ignored).
    """
    f = vignetting_falloff(camera, vignetting)
    c4 = _cos4(camera, u, v)
    if f == 0.0:
        return np.ones_like(c4)
    g_corner = 1.0 - _cos4(camera, np.array([0.0, camera.width - 1.0]), np.array([0.0, camera.height - 1.0])).min()
    return 1.0 - f * (1.0 - c4) / g_corner


def sky_gradient_factor(camera: Camera, u: np.ndarray, v: np.ndarray, gradient: float,
                        angle_deg: float = 0.0) -> np.ndarray:
    """Multiplier of the sky background at pixels (u, v): 1 + gradient * s, linear across the frame.

    s runs from -0.5 to +0.5 over the pixel centres along the direction angle_deg (0 = towards +u,
    image right; 90 = towards +v, image down), so the sky differs by the fraction `gradient` of its
    mean between the two far edges (corners) and keeps its mean at the centre.
    """
    g = float(gradient)
    if not (np.isfinite(g) and 0.0 <= g <= 1.0):
        raise BadInput(f"sky gradient {gradient} must be a fraction in [0, 1] of the background")
    a = math.radians(float(angle_deg))
    c, s = math.cos(a), math.sin(a)
    extent = max((camera.width - 1) * abs(c) + (camera.height - 1) * abs(s), 1e-12)
    t = ((np.asarray(u, dtype=np.float64) - camera.cx) * c + (np.asarray(v, dtype=np.float64) - camera.cy) * s) / extent
    return 1.0 + g * t


def check_jpeg_quality(quality: Any) -> int:
    """The JPEG quality as an int in 1..100, or BadInput."""
    if isinstance(quality, (bool, np.bool_)) or not isinstance(quality, (int, np.integer)) or not 1 <= quality <= 100:
        raise BadInput(f"JPEG quality {quality!r} must be an integer in 1..100")
    return int(quality)


def to_uint8(image: np.ndarray, scale: float | None = None) -> tuple[np.ndarray, float]:
    """An 8-bit copy of an image, and the scale used (input units per 8-bit step).

    uint8 images are returned unchanged (scale 1). Anything else is divided by `scale`, rounded and
    clipped to 0..255; scale=None takes the background noise, 1.4826 * MAD of the image (at least 1):
    one 8-bit step per noise sigma, as SensorModel's 8-bit gain (1 ADU per read-noise sigma), so the
    faint stars survive and stars saturate about where an 8-bit sensor's do. No offset is removed
    (the bias pedestal stays above 0 and the noise is not clipped).
    """
    img = np.asarray(image)
    if img.dtype == np.uint8:
        return img, 1.0
    a = img.astype(np.float32)
    if scale is None:
        med = float(np.median(a))
        scale = max(1.4826 * float(np.median(np.abs(a - med))), 1.0)
    scale = float(scale)
    if not (np.isfinite(scale) and scale > 0):
        raise BadInput(f"8-bit scale {scale} must be a positive number")
    out = np.clip(np.rint(a / np.float32(scale)), 0, 255).astype(np.uint8)
    return out, scale


def encode_jpeg(image: np.ndarray, quality: int) -> bytes:
    """JPEG bytes (OpenCV, baseline, grey) of an 8-bit image at `quality` (1..100)."""
    q = check_jpeg_quality(quality)
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise BadInput(f"JPEG needs an 8-bit image, not {img.dtype} (see to_uint8)")
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img), [int(cv2.IMWRITE_JPEG_QUALITY), q])
    if not ok:  # pragma: no cover
        raise BadInput("OpenCV could not encode the image as JPEG")
    return buf.tobytes()


def decode_jpeg(data: bytes) -> np.ndarray:
    """Decode JPEG bytes to a grey uint8 image."""
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:  # pragma: no cover
        raise BadInput("OpenCV could not decode the JPEG")
    return img


def jpeg_roundtrip(image: np.ndarray, quality: int, scale: float | None = None) -> np.ndarray:
    """The image as it comes back from a JPEG at `quality` (1..100): uint8, same shape.

    16-bit (or float) images are first made 8-bit by to_uint8 (divided by `scale`, by default the
    background noise sigma, see to_uint8).
    """
    q = check_jpeg_quality(quality)
    img8, _ = to_uint8(image, scale)
    return decode_jpeg(encode_jpeg(img8, q))


# ============================================================================ frames

@dataclass
class SimulatedFrame:
    image: np.ndarray  # (H, W) uint8 or uint16
    truth: dict  # JSON-ready, see simulate_image
    jpeg: bytes | None = None  # the encoded JPEG when simulated with jpeg_quality (image is its decoding)

    @property
    def R(self) -> np.ndarray:
        return np.asarray(self.truth["R"], dtype=np.float64)

    @property
    def star_uv(self) -> np.ndarray:
        """(N, 2) true catalog positions (u, v) of the rendered stars, brightest first."""
        return np.array([[s["u"], s["v"]] for s in self.truth["stars"]], dtype=np.float64).reshape(-1, 2)

    @property
    def rendered_uv(self) -> np.ndarray:
        """(N, 2) positions where the stars were drawn (u_noisy, v_noisy)."""
        return np.array([[s["u_noisy"], s["v_noisy"]] for s in self.truth["stars"]],
                        dtype=np.float64).reshape(-1, 2)

    @property
    def hips(self) -> np.ndarray:
        return np.array([s["hip"] for s in self.truth["stars"]], dtype=np.int64)


def _tangent_jitter(v: np.ndarray, sigma_rad: float, rng: np.random.Generator) -> np.ndarray:
    """Add an isotropic Gaussian vector in the tangent plane of each unit vector, renormalise."""
    g = rng.standard_normal(v.shape) * sigma_rad
    g -= np.sum(g * v, axis=1, keepdims=True) * v
    w = v + g
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def _check_R(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise BadInput("attitude R must be a finite 3x3 rotation matrix")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise BadInput("attitude R is not a proper rotation matrix (R R^T != I or det R < 0)")
    return R


def _n_to_drop(n_dropped: int | float, n_available: int) -> int:
    if isinstance(n_dropped, (bool, np.bool_)):
        raise BadInput("n_dropped must be a count (int) or a fraction in [0, 1)")
    if isinstance(n_dropped, (int, np.integer)):
        if n_dropped < 0:
            raise BadInput(f"n_dropped={n_dropped} must be >= 0")
        return int(min(n_dropped, n_available))
    f = float(n_dropped)
    if not (0.0 <= f < 1.0):
        raise BadInput(f"n_dropped={n_dropped}: a float is a fraction and must be in [0, 1)")
    return int(round(f * n_available))


def simulate_image(catalog: GuideCatalog, camera: Camera, R: np.ndarray, sensor: SensorModel | None = None,
                   *, seed: int = 0, mag_limit: float = 6.0, n_false_stars: int = 0,
                   false_star_placement: str = "sensor", false_star_mag_range: tuple[float, float] = (2.0, 5.0),
                   n_dropped: int | float = 0, position_noise_rad: float = 0.0,
                   noise: bool = True, faint_extra_mag: float = 0.0, vignetting: float | str = 0.0,
                   sky_gradient: float = 0.0, sky_gradient_deg: float = 0.0,
                   jpeg_quality: int | None = None, jpeg_scale: float | None = None,
                   image_circle_deg: float | None = None) -> SimulatedFrame:
    """Render the sky seen by `camera` at attitude R (v_cam = R @ v_icrs).

    - catalog stars with Hp <= mag_limit whose (jittered) PSF centre lands on the sensor are drawn;
      stars whose centre is off the sensor are not drawn even if their wings would reach it
      (listed in truth["off_sensor"] when within 5 sigma of the edge);
    - position_noise_rad: Gaussian direction jitter per tangent-plane axis added to each star's true
      direction before rendering (Cole & Crassidis: "add a Gaussian vector then normalise");
      truth keeps the true (u, v) and the rendered (u_noisy, v_noisy);
    - n_dropped: int count, or float fraction in [0, 1), of the on-sensor stars left out (truth["dropped"]);
    - n_false_stars: blobs that are not catalog stars, Hp uniform in false_star_mag_range;
      false_star_placement="sensor": uniform on the image; "disk": as Cole & Crassidis, the boresight
      plus a vector of random direction and a random length up to half the (horizontal) FOV,
      normalised (then jittered like a star); redrawn if it misses the sensor;
    - noise=False switches off shot noise and read noise (hot pixels, bias, quantisation and
      saturation remain; set their SensorModel fields to 0 to remove them).

    - image_circle_deg: only stars within this angle of the boresight are drawn (a circular all-sky
      fisheye sees the sky to its horizon, 90 deg, and the ground beyond).

    Real-world effects (all off by default; off, nothing changes, bit for bit):

    - faint_extra_mag (mag, >= 0): also render the field stars with mag_limit < Hp <=
      min(mag_limit + faint_extra_mag, 9.0); they are in truth["stars"] with "faint": true (so a
      solver that names them correctly is scored correct), and are dropped/jittered like the others;
    - vignetting: the fraction of light lost at the corner pixels, in [0, 1), with a cos^4-shaped
      profile (vignetting_factor), or "cos4" for natural cos^4 vignetting; scales the stars and the
      sky background (not dark current, not hot pixels); truth stars then carry "vignetting", and
      "electrons" is what reached the sensor;
    - sky_gradient: fraction in [0, 1] by which the sky background (not dark current) differs between
      the two far sides of the frame, linear along sky_gradient_deg (0 = towards +u, 90 = towards +v),
      mean unchanged (sky_gradient_factor);
    - jpeg_quality (1..100): the image is encoded as a JPEG with OpenCV and decoded back (uint8); a
      16-bit image is first divided by jpeg_scale ADU per 8-bit step (default: its background noise
      sigma, see to_uint8); the encoded bytes are kept in frame.jpeg.

    When any effect is on, truth["effects"] records the settings (and what they resolved to).
    """
    sensor = SensorModel() if sensor is None else sensor
    R = _check_R(R)
    if false_star_placement not in ("sensor", "disk"):
        raise BadInput(f"false_star_placement must be 'sensor' or 'disk', not {false_star_placement!r}")
    if int(n_false_stars) < 0:
        raise BadInput(f"n_false_stars={n_false_stars} must be >= 0")
    if not (np.isfinite(position_noise_rad) and position_noise_rad >= 0):
        raise BadInput(f"position_noise_rad={position_noise_rad} must be >= 0")
    lo_mag, hi_mag = (float(x) for x in false_star_mag_range)
    if hi_mag < lo_mag:
        raise BadInput(f"false_star_mag_range {false_star_mag_range} must be (brightest, faintest)")
    if not (np.isfinite(faint_extra_mag) and faint_extra_mag >= 0):
        raise BadInput(f"faint_extra_mag={faint_extra_mag} must be a number of magnitudes >= 0")
    falloff = vignetting_falloff(camera, vignetting)
    sky_gradient_factor(camera, 0.0, 0.0, sky_gradient, sky_gradient_deg)  # one-line error for a bad value
    if jpeg_quality is not None:
        check_jpeg_quality(jpeg_quality)
    # (the guide catalog's depth; a deeper catalog, skyview.core.deep_catalog, renders to its own)
    cap = max(FAINT_MAG_CAP, float(catalog.mag.max())) if len(catalog) else FAINT_MAG_CAP
    render_limit = max(float(mag_limit), min(float(mag_limit) + float(faint_extra_mag), cap))
    effects_on = bool(faint_extra_mag > 0 or falloff > 0 or sky_gradient > 0 or jpeg_quality is not None)
    rng = np.random.default_rng(seed)
    H, W = camera.height, camera.width
    sigma = sensor.psf_sigma_px

    # ---------------------------------------------------------------- catalog stars in the field
    boresight = R[2]
    margin_rad = 6.0 * sigma / camera.fx + 10.0 * position_noise_rad
    reach = camera.half_diagonal_rad + margin_rad
    if image_circle_deg is not None:  # a circular fisheye: nothing beyond its image circle (the horizon)
        reach = min(reach, np.radians(float(image_circle_deg)))
    cone = catalog.within(boresight, reach)
    cone = cone[catalog.mag[cone] <= (render_limit if faint_extra_mag > 0 else mag_limit)]
    cone = cone[np.argsort(catalog.mag[cone], kind="stable")]  # brightest first
    v_true = catalog.xyz[cone] @ R.T
    uv_true, front = camera.project(v_true)
    v_noisy = _tangent_jitter(v_true, position_noise_rad, rng) if position_noise_rad > 0 else v_true
    uv_noisy, front_n = camera.project(v_noisy)
    on = front & front_n & camera.in_image(uv_noisy)
    near = front_n & ~on & camera.in_image(uv_noisy, margin=-5.0 * sigma)
    off_sensor = [int(h) for h in catalog.hip[cone[near]]]
    idx_on = np.flatnonzero(on)

    k_drop = _n_to_drop(n_dropped, len(idx_on))
    drop_pos = np.sort(rng.choice(len(idx_on), size=k_drop, replace=False)) if k_drop else np.array([], int)
    keep = np.ones(len(idx_on), dtype=bool)
    keep[drop_pos] = False
    dropped = [int(catalog.hip[cone[idx_on[p]]]) for p in drop_pos]
    rend = idx_on[keep]
    mags = catalog.mag[cone[rend]].astype(np.float64)
    star_e = np.asarray(sensor.electrons(mags), dtype=np.float64)
    star_vig = None
    if falloff > 0:
        star_vig = vignetting_factor(camera, uv_noisy[rend, 0], uv_noisy[rend, 1], vignetting)
        star_e = star_e * star_vig

    # ---------------------------------------------------------------- false stars
    nf = int(n_false_stars)
    f_mag = rng.uniform(lo_mag, hi_mag, size=nf) if nf else np.zeros(0)
    f_uv = np.zeros((nf, 2))
    half_fov = math.radians(camera.fov_deg) / 2.0
    for k in range(nf):
        for _attempt in range(1000):
            if false_star_placement == "sensor":
                p = np.array([rng.uniform(-0.5, W - 0.5), rng.uniform(-0.5, H - 0.5)])
            else:
                phi = rng.uniform(0.0, 2.0 * math.pi)
                length = rng.uniform(0.0, half_fov)
                d = np.array([math.cos(phi), math.sin(phi), 0.0]) * length  # camera frame tangent vector
                v = np.array([[0.0, 0.0, 1.0]]) + d
                v /= np.linalg.norm(v)
                if position_noise_rad > 0:
                    v = _tangent_jitter(v, position_noise_rad, rng)
                p, fr = camera.project(v)
                p = p[0]
                if not fr[0]:
                    continue
            if camera.in_image(p[None])[0]:
                f_uv[k] = p
                break
        else:  # pragma: no cover - only with absurd distortion
            raise BadInput("could not place a false star on the sensor")
    f_e = np.asarray(sensor.electrons(f_mag), dtype=np.float64).reshape(-1)
    if falloff > 0 and nf:
        f_e = f_e * vignetting_factor(camera, f_uv[:, 0], f_uv[:, 1], vignetting)

    # ---------------------------------------------------------------- electrons -> ADU
    signal = np.zeros((H, W), dtype=np.float64)
    render_stars((H, W), np.concatenate([uv_noisy[rend], f_uv]), np.concatenate([star_e, f_e]), sigma, out=signal)
    n_hot = int(sensor.n_hot_pixels)
    hot_flat = rng.choice(H * W, size=min(n_hot, H * W), replace=False) if n_hot else np.zeros(0, np.int64)
    if n_hot:
        signal.reshape(-1)[hot_flat] += sensor.hot_pixel_e
    bg = sensor.background_e_per_px
    if falloff > 0 or sky_gradient > 0:  # a per-pixel background: sky x vignetting x gradient + dark
        uu, vv = np.arange(W, dtype=np.float64)[None, :], np.arange(H, dtype=np.float64)[:, None]
        sky = sensor.sky_background_e_per_px_s * sensor.exposure_s * np.ones((H, W))
        if falloff > 0:
            sky *= vignetting_factor(camera, uu, vv, vignetting)
        if sky_gradient > 0:
            sky *= sky_gradient_factor(camera, uu, vv, sky_gradient, sky_gradient_deg)
        bg = sky + sensor.dark_current_e_per_px_s * sensor.exposure_s
    if noise:
        # shot noise: background (uniform) + signal pixels; sums of independent Poissons are Poisson
        if np.ndim(bg):
            e = rng.poisson(bg).astype(np.float32)
        else:
            e = rng.poisson(bg, size=(H, W)).astype(np.float32) if bg > 0 else np.zeros((H, W), np.float32)
        nz = np.flatnonzero(signal)
        e.reshape(-1)[nz] += rng.poisson(signal.reshape(-1)[nz]).astype(np.float32)
    else:
        e = (signal + bg).astype(np.float32)
    np.minimum(e, np.float32(sensor.full_well_e), out=e)
    e += np.float32(sensor.bias_e)
    if noise and sensor.read_noise_e > 0:
        e += rng.standard_normal((H, W), dtype=np.float32) * np.float32(sensor.read_noise_e)
    adu = e * np.float32(1.0 / sensor.gain)
    np.rint(adu, out=adu)
    np.clip(adu, 0, sensor.adc_max, out=adu)
    image = adu.astype(sensor.dtype)
    jpeg = None
    if jpeg_quality is not None:
        img8, jpeg_scale = to_uint8(image, jpeg_scale)
        jpeg = encode_jpeg(img8, jpeg_quality)
        image = decode_jpeg(jpeg)

    # ---------------------------------------------------------------- truth
    ra, dec, roll = radec_roll_from_R(R)
    stars = []
    for k, i in enumerate(rend):
        c = cone[i]
        stars.append({
            "hip": int(catalog.hip[c]),
            "u": float(uv_true[i, 0]), "v": float(uv_true[i, 1]),
            "mag": float(mags[k]),
            "electrons": float(star_e[k]),
            "snr": float(sensor.snr(star_e[k])),
            "u_noisy": float(uv_noisy[i, 0]), "v_noisy": float(uv_noisy[i, 1]),
        })
        if faint_extra_mag > 0:
            stars[-1]["faint"] = bool(mags[k] > mag_limit)
        if star_vig is not None:
            stars[-1]["vignetting"] = float(star_vig[k])
    false_stars = [{"u": float(f_uv[k, 0]), "v": float(f_uv[k, 1]), "mag": float(f_mag[k]),
                    "electrons": float(f_e[k]), "snr": float(sensor.snr(f_e[k]))} for k in range(nf)]
    truth = {
        "camera": camera.to_dict(),
        "R": R.tolist(),
        "quaternion": [float(x) for x in quat_from_R(R)],
        "ra_deg": math.degrees(ra), "dec_deg": math.degrees(dec), "roll_deg": math.degrees(roll),
        "epoch": float(catalog.epoch),
        "stars": stars,
        "false_stars": false_stars,
        "false_star_placement": false_star_placement,
        "dropped": dropped,
        "off_sensor": off_sensor,
        "hot_pixels": [[int(f % W), int(f // W)] for f in hot_flat],  # [u, v]
        "sensor": sensor.to_dict(),
        "sensor_derived": sensor.describe(),
        "seed": int(seed) if isinstance(seed, (int, np.integer)) else seed,
        "mag_limit": float(mag_limit),
        "position_noise_rad": float(position_noise_rad),
        "noise": bool(noise),
        "notes": ("u, v: true catalog position (pixel centres at integers, (0,0) = centre of the "
                  "top-left pixel); u_noisy, v_noisy: where the star was drawn (after "
                  "position_noise_rad). Stars whose PSF centre is off the sensor are not rendered; "
                  "those within 5 PSF sigma of the edge are listed in off_sensor."),
    }
    if effects_on:
        truth["effects"] = {
            "faint_extra_mag": float(faint_extra_mag), "render_mag_limit": render_limit,
            "n_faint": sum(1 for st in stars if st.get("faint")),
            "vignetting": vignetting if isinstance(vignetting, str) else float(vignetting),
            "vignetting_corner_falloff": falloff,
            "sky_gradient": float(sky_gradient), "sky_gradient_deg": float(sky_gradient_deg),
            "jpeg_quality": None if jpeg_quality is None else int(jpeg_quality),
            "jpeg_scale_adu_per_step": None if jpeg_quality is None else float(jpeg_scale),
        }
    return SimulatedFrame(image=image, truth=truth, jpeg=jpeg)


# ============================================================================ writing files

def _check_folder(folder: Path) -> None:
    if not folder.exists():
        raise BadInput(f"folder {folder} does not exist")
    if not folder.is_dir():
        raise BadInput(f"{folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise BadInput(f"folder {folder} is not writable")


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def _check_png_path(png_path: str | os.PathLike) -> Path:
    p = Path(png_path)
    if p.suffix.lower() not in IMAGE_SUFFIXES:
        raise BadInput(f"{p}: the image path must end in .png or .jpg")
    _check_folder(p.parent if str(p.parent) else Path("."))
    return p


def is_jpeg_path(path: str | os.PathLike) -> bool:
    return Path(path).suffix.lower() in (".jpg", ".jpeg")


def _frame_files(frame: SimulatedFrame, path: Path) -> list[tuple[Path, bytes]]:
    """(image path, bytes) and (truth path, bytes) for one frame.

    A .jpg path gets the frame's own JPEG (simulated with jpeg_quality: the file decodes to exactly
    frame.image); a frame simulated without it is encoded at JPEG_DEFAULT_QUALITY after to_uint8, and
    its truth then says so ("saved_as_jpeg"). A .png path always gets the lossless frame.image.
    """
    truth = frame.truth
    if is_jpeg_path(path):
        if frame.jpeg is not None:
            data = frame.jpeg
        else:
            img8, scale = to_uint8(frame.image)
            data = encode_jpeg(img8, JPEG_DEFAULT_QUALITY)
            truth = {**truth, "saved_as_jpeg": {"quality": JPEG_DEFAULT_QUALITY, "scale_adu_per_step": scale}}
    else:
        data = _encode_png(frame.image)
    return [(path, data), (path.with_suffix(".json"), _json_bytes(truth))]


def _encode_png(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover
        raise BadInput("OpenCV could not encode the image as PNG")
    return buf.tobytes()


def _json_bytes(obj: Any) -> bytes:
    return (json.dumps(obj, indent=1, allow_nan=False) + "\n").encode()


def save_frame(frame: SimulatedFrame, png_path: str | os.PathLike, *, force: bool = False) -> tuple[Path, Path]:
    """Write the image (8 or 16 bit PNG, or a JPEG for a .jpg/.jpeg path, see _frame_files) and its
    truth sidecar (same stem, .json).

    Refuses (BadInput) a path not ending in .png/.jpg/.jpeg, a missing or unwritable folder, and
    existing files unless force=True. Both files are written to temporary files and moved into
    place, so a failure leaves neither half-written. Returns (image_path, json_path).
    """
    p = _check_png_path(png_path)
    items = _frame_files(frame, p)
    write_atomic(items, force)
    return p, items[1][0]


def load_truth(path: str | os.PathLike) -> dict:
    """Read a truth sidecar: give the .json itself or the image next to it (a frame or sequence.json)."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        p = p.with_suffix(".json")
    if not p.exists():
        raise BadInput(f"truth file {p} does not exist")
    if p.is_dir():
        raise BadInput(f"truth file {p} is a directory")
    try:
        with open(p, encoding="utf-8") as fh:
            return json.load(fh)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BadInput(f"truth file {p} is not readable JSON: {exc}") from None


# ============================================================================ slews

@dataclass(frozen=True)
class Turn:
    """A constant turn applied between consecutive frames.

    frame="camera": `matrix` is dR_cam, with v_cam_{k+1} = dR_cam @ v_cam_k (R_{k+1} = dR_cam @ R_k).
    frame="icrs": `matrix` is rot_icrs, the rotation of the camera body expressed in ICRS: the camera
    axes (as ICRS vectors) at k+1 are rot_icrs @ those at k, i.e. R_{k+1} = R_k @ rot_icrs.T.
    A constant turn in one frame is a constant turn in the other (dR_cam = R_k rot_icrs^T R_k^T).
    """

    matrix: np.ndarray
    frame: str = "camera"

    def __post_init__(self) -> None:
        m = np.asarray(self.matrix, dtype=np.float64)
        if self.frame not in ("camera", "icrs"):
            raise BadInput(f"turn frame must be 'camera' or 'icrs', not {self.frame!r}")
        object.__setattr__(self, "matrix", _check_R(m))

    def dR_cam(self, R_k: np.ndarray) -> np.ndarray:
        if self.frame == "camera":
            return self.matrix
        return R_k @ self.matrix.T @ R_k.T

    def apply(self, R_k: np.ndarray) -> np.ndarray:
        if self.frame == "camera":
            return self.matrix @ R_k
        return R_k @ self.matrix.T


_AXES = {"x": [1.0, 0.0, 0.0], "y": [0.0, 1.0, 0.0], "z": [0.0, 0.0, 1.0]}


def turn_about_camera_axis(axis: str | Sequence[float], angle_rad: float) -> Turn:
    """The camera body turns by +angle (right-handed) about one of its own axes ('x', 'y', 'z', 0, 1, 2
    or a 3-vector in the camera frame).

    Stars then move the other way: dR_cam = Rot(axis, -angle). E.g. ('y', +a) pans the boresight
    towards +x (image right), so stars move left; ('x', +a) tilts it towards -y (image up), so
    stars move down; ('z', +a) rolls it so stars turn counter-clockwise in the displayed image.
    """
    if isinstance(axis, (int, np.integer)) and not isinstance(axis, bool) and 0 <= int(axis) <= 2:
        axis = "xyz"[int(axis)]
    try:
        a = np.asarray(_AXES[axis] if isinstance(axis, str) and axis in _AXES else axis, dtype=np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) == 0:
        raise BadInput(f"turn axis {axis!r} must be 'x', 'y', 'z' or a non-zero 3-vector")
    a = a / np.linalg.norm(a)
    return Turn(Rotation.from_rotvec(-float(angle_rad) * a).as_matrix(), "camera")


def turn_along_ra(step_rad: float) -> Turn:
    """Turn about the ICRS pole so the boresight's RA grows by `step_rad` (Dec and roll unchanged).

    The Udomkesmalee et al. experiment: 10 deg steps "along the right ascension axis".
    """
    return Turn(Rotation.from_rotvec([0.0, 0.0, float(step_rad)]).as_matrix(), "icrs")


def R_pointing_at(catalog: GuideCatalog, hip: int, roll_rad: float = 0.0) -> np.ndarray:
    """Attitude whose boresight is on catalog star `hip` (at the catalog epoch), with `roll_rad`."""
    try:
        i = catalog.index_of(hip)
    except KeyError as exc:
        raise BadInput(str(exc.args[0])) from None
    ra, dec = vec_to_radec(catalog.xyz[i])
    return R_from_radec_roll(float(ra), float(dec), roll_rad)


@dataclass
class SimulatedSequence:
    frames: list[SimulatedFrame]
    relative: list[dict] = field(default_factory=list)  # len(frames) - 1 entries, see simulate_sequence

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def truth(self) -> dict:
        return {
            "n_frames": len(self.frames),
            "conventions": RELATIVE_CONVENTIONS,
            "frames": [f.truth for f in self.frames],
            "relative": self.relative,
        }

    def dR_cam(self, k: int) -> np.ndarray:
        """v_cam_{k+1} = dR_cam(k) @ v_cam_k."""
        return np.asarray(self.relative[k]["dR_cam"], dtype=np.float64)


RELATIVE_CONVENTIONS = {
    "dR_cam": "v_cam_{k+1} = dR_cam @ v_cam_k for any fixed star; R_{k+1} = dR_cam @ R_k",
    "turn_cam": "dR_cam.T: the active rotation of the camera body in the camera axes of frame k "
                "(what gyros integrate); turn_rotvec_cam_rad is its rotation vector",
    "rot_icrs": "the same turn in ICRS: camera axes at k+1 = rot_icrs @ camera axes at k; "
                "R_{k+1} = R_k @ rot_icrs.T",
}


def _relative(R_k: np.ndarray, R_k1: np.ndarray, k: int) -> dict:
    dR_cam = R_k1 @ R_k.T
    rot_icrs = R_k1.T @ R_k
    rv = Rotation.from_matrix(dR_cam.T).as_rotvec()
    return {
        "from": k, "to": k + 1,
        "dR_cam": dR_cam.tolist(),
        "turn_cam": dR_cam.T.tolist(),
        "turn_rotvec_cam_rad": rv.tolist(),
        "turn_angle_deg": float(np.degrees(np.linalg.norm(rv))),
        "rot_icrs": rot_icrs.tolist(),
    }


def simulate_sequence(catalog: GuideCatalog, camera: Camera, R0: np.ndarray, n_frames: int,
                      rotation_per_frame: Turn | np.ndarray, sensor: SensorModel | None = None, *,
                      seed: int = 0, **kwargs: Any) -> SimulatedSequence:
    """Frames k = 0..n_frames-1 with R_{k+1} = turn applied to R_k.

    rotation_per_frame: a Turn (see turn_about_camera_axis, turn_along_ra) or a 3x3 matrix taken as
    dR_cam (v_cam_{k+1} = dR_cam @ v_cam_k). Each frame gets its own seed drawn from `seed`
    (recorded in its truth); other keyword arguments go to simulate_image. `relative[k]` holds the
    turn from frame k to k+1 as dR_cam, turn_cam (= dR_cam.T, gyro convention), its rotation vector
    and angle, and rot_icrs.
    """
    if int(n_frames) < 1:
        raise BadInput(f"n_frames={n_frames} must be >= 1")
    turn = rotation_per_frame if isinstance(rotation_per_frame, Turn) else Turn(rotation_per_frame, "camera")
    seeds = np.random.SeedSequence(seed).generate_state(int(n_frames), dtype=np.uint32)
    Rs = [_check_R(R0)]
    for _ in range(int(n_frames) - 1):
        Rs.append(turn.apply(Rs[-1]))
    frames = [simulate_image(catalog, camera, Rk, sensor, seed=int(s), **kwargs) for Rk, s in zip(Rs, seeds)]
    for k, f in enumerate(frames):
        f.truth["sequence_index"] = k
        f.truth["sequence_seed"] = int(seed) if isinstance(seed, (int, np.integer)) else seed
    rel = [_relative(Rs[k], Rs[k + 1], k) for k in range(len(Rs) - 1)]
    return SimulatedSequence(frames=frames, relative=rel)


def betelgeuse_ra_sequence(catalog: GuideCatalog, camera: Camera, n_frames: int = 5, step_deg: float = 10.0,
                           roll_deg: float = 0.0, sensor: SensorModel | None = None, **kwargs: Any) -> SimulatedSequence:
    """The stochastic paper's slew: start with the boresight on Betelgeuse, step `step_deg` in RA."""
    R0 = R_pointing_at(catalog, HIP_BETELGEUSE, math.radians(roll_deg))
    return simulate_sequence(catalog, camera, R0, n_frames, turn_along_ra(math.radians(step_deg)), sensor, **kwargs)


def save_sequence(seq: SimulatedSequence, folder_or_stem: str | os.PathLike, *, force: bool = False) -> list[Path]:
    """Write a sequence: into an existing folder as frame_000.png/.json ... + sequence.json, or, for
    any other path, as <stem>_000.png/.json ... + <stem>.json (its folder must exist). Frames
    simulated with jpeg_quality are written as .jpg (their own JPEG bytes).

    Same rules as save_frame: nothing is overwritten without force, and if any file cannot be
    written none of the new files is left behind. Returns the paths written.
    """
    p = Path(folder_or_stem)
    if p.is_dir():
        folder, prefix, seq_json = p, "frame_", p / "sequence.json"
    else:
        if p.suffix.lower() in (*IMAGE_SUFFIXES, ".json"):
            p = p.with_suffix("")
        folder = p.parent if str(p.parent) else Path(".")
        _check_folder(folder)
        prefix, seq_json = p.name + "_", p.with_name(p.name + ".json")
    _check_folder(folder)
    items: list[tuple[Path, bytes]] = []
    names = []
    for k, f in enumerate(seq.frames):
        img = folder / f"{prefix}{k:03d}{'.jpg' if f.jpeg is not None else '.png'}"
        items += _frame_files(f, img)
        names.append(img.name)
    truth = seq.truth
    truth["images"] = names
    items.append((seq_json, _json_bytes(truth)))
    write_atomic(items, force)
    return [it[0] for it in items]
