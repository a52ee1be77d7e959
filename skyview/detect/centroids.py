"""Image -> star centroids with OpenCV: background, noise, detection, sub-pixel position, flags.

(Longer than skyview's other modules, ~1000 lines: the image loading, the fast path below and the
estimators it shares with tests/oracles/centroid_reference.py are one algorithm timed per stage (issue 11:
<= 1.5 ms a 1024 x 1024 frame); the former, simpler implementation it is tested against is in
tests/oracles/centroid_reference.py.)

Pixel convention (DESIGN.md): pixel centres at integer coordinates, (0, 0) the centre of the
top-left pixel; u = column (x, right), v = row (y, down).

Steps of `detect_centroids`:

1. Background: median of 64 px blocks (sampled every 4th pixel of every 4th row; of every 8th row on
   frames of 512 px or more a side: 128 samples a block, and the noise below from half of those),
   bilinear map between block centres
   extrapolated linearly to the borders; a single level when no block departs from it by more than
   0.5 sigma or than the blocks' own noise (the usual case, and the fast one). Noise sigma: 1.4826 x MAD of the
   background-subtracted samples, refined by a 3.5-sigma clipped standard deviation (which stays
   right on integer images whose noise is ~1 ADU, where the MAD is quantised).
2. Detection: pixels above background + k_sigma * sigma. A pixel above it whose 8 neighbours all
   stay near the background (below max(3 sigma, 15 % of it)) is a hot pixel: counted, removed
   from the mask and repaired with its neighbours' median, so it neither becomes a star nor pulls
   the centroid of a faint star it touches (this assumes a PSF sigma of at least ~0.5 px, as star
   trackers defocus to get). Then 8-connected components of the pixels above it (cv2 on an image
   compacted to the rows and columns that hold one); blobs smaller than min_pixels are dropped; so are
   hot pixels side by side and cosmic-ray hits, blobs of 2-4 pixels of 50 sigma or more whose surroundings
   stay below 6 % of their peak (`_hot_clusters`: patched as a hot pixel is); a blob with several separated
   peaks is split (deblend). Lines narrower than the optics draw (a cosmic ray's track, a bad column: 20
   sigma or more, variance across under 0.2 px^2, `_sharp_streaks`) neither measure the PSF nor count as
   stars (`n_streaks_rejected`).
3. Position in a window around each blob's brightest pixel (side 2*ceil(2.5 sigma_eff) + 1, 7 px for
   the default PSF), background subtracted. Estimators (`estimator=`):
   "fit" (default): least-squares fit of a pixel-integrated Gaussian PSF (amplitude and position,
   width fixed to the PSF sigma measured from the image), Gauss-Newton until its step, or the error
   its last two steps say is left, is below 1e-4 px, from the "gauss3" position for a star whose
   three-point fit gives the PSF's width to 30 %, from the iwcog position for the others (saturated,
   blended, odd shapes);
   saturated pixels and pixels off the image are left out, so saturated and edge stars keep an
   unbiased centre;
   "iwcog": iteratively Gaussian-weighted centre of gravity, each step scaled by
   (sigma_psf^2 + sigma_w^2) / sigma_w^2 so that it converges on the centre of a Gaussian PSF;
   "cog": plain centre of gravity of the positive background-subtracted intensity;
   "gauss3": three-point Gaussian (log-parabola) fit on the 3x3 marginals, falling back to "iwcog"
   when a value is not positive or the star is saturated.
   skyview.bench.centroids measures them on the same images (100 fields, 8 deg, 1024 px, default
   SensorModel): RMS per axis at SNR >= 20 is 0.056 px for "fit", 0.063 iwcog, 0.095 cog, 0.096
   gauss3; "fit" is the best in every SNR bin (iwcog suffers at saturated and edge stars).
4. Brightness = summed background-subtracted intensity in the window; peak = highest raw pixel
   value; flags: saturated (a pixel at the ADC maximum of the dtype, at `saturation_level`, or at
   the image's top value when that value forms a plateau), elongated (second-moment axis ratio above
   max_axis_ratio for blobs with peak >= 20 sigma, above max_axis_ratio + 0.5 at 10 sigma, not
   judged below: blends and streaks), edge (window crosses the border). Sorted by brightness, brightest first.

Fast forms (issue 11) and what each keeps; tests/test_centroid.py checks them against the slow forms:
- frame pass: the maxima of 4-row bands (`_band_max`, one reduction over 4 W contiguous values, about
  twice the speed of per-row maxima), then only the crossing bands compared: the same pixel indices.
- block medians of an integer frame sorted in its own dtype (the same order as its float32 values),
  the middle two converted to float32 and averaged: the same grid.
- the bilinear map at the samples the noise uses from two products with cached weights
  (`_upsample_at`: cv2.resize's weights on the extrapolated ring): the map to float32 rounding
  (~1e-7 relative).
- median and MAD of the noise samples from one SIMD partition each (`_median_part`): np.median's
  values bit for bit; the clipped standard deviation from float64 sums (one of products): np.std's
  float32 result to ~1e-7 relative. The noise sigma moves by ~1e-7 relative, the threshold with it.
- a uint8 frame whose block medians are all equal (the usual flat sky; blocks of 2^k samples): the map is
  that level exactly and the noise comes from the samples' 256-bin histogram (`_u8_noise`): the same
  median, MAD and clipped sums as the per-sample path, bit for bit.
- the above-threshold pixels of the crossing bands found 8 bytes at a time first (`_flatnonzero_sparse`):
  the same indices.
- the deblender's walk over each blob's local maxima, brightest first, every blob at once (`_dipped_peaks`:
  round r tests each blob's r-th candidate against the peaks the blob accepted before it, the lines' points
  as np.linspace makes them): the same peaks in the same order (a dense 60 deg field's thousands of blobs in
  a few dozen batched steps, not one numpy call per candidate; a sparse frame's few candidates walked one at a
  time in Python numbers, `_dipped_peaks_walk`, as before).
- small things on Python numbers (a few dozen items, where numpy's per-call cost dominates): the fit's
  stop test (the same float64 operations), the histogram noise above.
- 3 x 3 neighbourhoods of the above-threshold pixels on a flat sky read in the frame's dtype as 9
  rows (the ring's maximum from contiguous rows, the background subtracted after it: the same
  numbers; pixels in the first or last column or row get the gather's zero-padded neighbourhood, read
  with indices clipped to the image).
- each blob's brightest pixel by np.maximum.at and a table by label (`_label_peaks`: the last pixel
  at the maximum in index order, what the last of np.lexsort((val, lab)) per label is): the same peak.
- the fit: the products of the two profiles it uses (not the unused fourth), no weights when no pixel
  is left out, the updates without index copies while every star iterates: ~1e-14 px. With every
  pixel used (the usual case) the model is separable, so the 3 x 3 Gram matrix is the product of the
  two axes' 2 x 2 Grams of (profile, derivative) (`_GUV`) and the products with the data are
  (fv, dfv) V (fu, dfu)^T: two small batched products instead of the (N, 3, n^2) model; the system
  solved for (A + dA, A du, A dv) (no residual vector), the determinant by one product, the first step's
  stop test step > _FIT_TOL alone (with no previous step the error left is step^2 / 1e-12): the same
  positions to ~1e-13 px (tested against the weighted form: `test_separable_fit_is_the_weighted_form`).
- `_gauss3_fast`: the log-parabola's curvature and slope negated and doubled (exact), so no division
  by zero and no error-state switch: _gauss3's numbers. `_axis_ratio_mm`: every second moment from one
  chain of batched products (Dy w Dx^T): _axis_ratio's ratio to ~1e-15 relative.
- iwcog's weighted sums by batched matrix products instead of einsum: ~1e-13 px.
- small trims with the same numbers: cv2's 16-bit labels on a compacted image of fewer than 65,535
  pixels; no on-image mask when every window lies inside the image; the deblender's pixels beside a
  hot one found by looking the hot pixels' neighbours up in the sorted pixel list.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import math
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from skyview.core.errors import BadInput
from skyview.core.special import erf

ESTIMATORS = ("fit", "iwcog", "cog", "gauss3")
DEFAULT_ESTIMATOR = "fit"
_MAD_TO_SIGMA = 1.4826
MIN_EXTENDED_PX = 400  # a blob is "extended" above max(this, EXTENDED_PSF_AREAS x the PSF's 3-sigma disk)
EXTENDED_PSF_AREAS = 40.0
_CLIP_K = 3.5
# std of a unit normal truncated to +-3.5 sigma
_CLIP_STD = math.sqrt(1.0 - 2 * _CLIP_K * math.exp(-_CLIP_K ** 2 / 2) / math.sqrt(2 * math.pi) / math.erf(_CLIP_K / math.sqrt(2)))


def _flatnonzero(x: np.ndarray) -> np.ndarray:
    """np.flatnonzero(x) without its Python-level wrappers (a microsecond a call, ~10 calls a frame)."""
    return x.ravel().nonzero()[0]


def _flatnonzero_sparse(m: np.ndarray) -> np.ndarray:
    """np.flatnonzero of a C-contiguous bool array with few True values: on large arrays (128 KiB or
    more: below, its dozen calls cost more than the scan they save) the 8-byte words holding one found
    first (a SIMD compare of an eighth as many items), then the bytes of those words alone (the same
    indices, ascending)."""
    b = m.reshape(-1)
    if b.size % 8 or b.size < 1 << 17:
        return b.nonzero()[0]
    w = (b.view(np.uint64) != 0).nonzero()[0]
    p = b.reshape(-1, 8)[w].reshape(-1).nonzero()[0]
    return (w[p >> 3] << 3) | (p & 7)


# ============================================================================ result

@dataclass
class Centroids:
    uv: np.ndarray  # (N, 2) float64 pixel positions (u = column, v = row)
    brightness: np.ndarray  # (N,) summed background-subtracted intensity in the window (image units)
    peak: np.ndarray  # (N,) highest raw pixel value of the blob (image units, background included)
    n_pixels: np.ndarray  # (N,) pixels above the detection threshold in the blob (shared when blended)
    saturated: np.ndarray  # (N,) bool
    elongated: np.ndarray  # (N,) bool
    edge: np.ndarray  # (N,) bool: the measurement window crosses the image border
    blended: np.ndarray  # (N,) bool: one of several peaks split from the same blob
    axis_ratio: np.ndarray  # (N,) second-moment axis ratio (>= 1), NaN when not measured
    background_level: float = 0.0  # median background (image units)
    noise_sigma: float = 0.0  # background noise sigma (image units)
    threshold: float = 0.0  # detection threshold above the background (k_sigma * noise_sigma)
    n_hot_pixels_rejected: int = 0
    n_small_rejected: int = 0  # other blobs smaller than min_pixels
    n_extended_rejected: int = 0  # blobs far larger than a star (roof, tree, Moon, glare)
    n_streaks_rejected: int = 0  # lines narrower than the optics draw (cosmic rays, bad columns): `_sharp_streaks`
    n_unmeasured: int = 0  # fainter stars detected but not measured (detect_centroids' max_stars)
    # of them, the saturated ones: their window sums hold only a flat core, so their whole-disk brightness
    # (`skyview.detect.stars`) may rank them among the measured ones
    n_unmeasured_saturated: int = 0
    psf_sigma_px: float = float("nan")  # PSF sigma used by iwcog (measured or given)
    estimator: str = DEFAULT_ESTIMATOR
    image_shape: tuple[int, int] = (0, 0)
    params: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    @property
    def n_detected(self) -> int:
        """Stars detected: those measured here and the fainter ones left unmeasured (max_stars)."""
        return len(self) + int(self.n_unmeasured)

    def to_list(self) -> list[dict]:
        """One JSON-ready dict per centroid, brightest first."""
        out = []
        for k in range(len(self)):
            ar = float(self.axis_ratio[k])
            out.append({
                "u": float(self.uv[k, 0]), "v": float(self.uv[k, 1]),
                "brightness": float(self.brightness[k]), "peak": float(self.peak[k]),
                "n_pixels": int(self.n_pixels[k]), "saturated": bool(self.saturated[k]),
                "elongated": bool(self.elongated[k]), "edge": bool(self.edge[k]),
                "blended": bool(self.blended[k]),
                "axis_ratio": ar if math.isfinite(ar) else None,
            })
        return out

    def to_dict(self) -> dict:
        """Summary numbers plus the list of centroids (JSON-ready)."""
        return {
            "n": len(self), "background_level": self.background_level, "noise_sigma": self.noise_sigma,
            "threshold": self.threshold, "n_hot_pixels_rejected": self.n_hot_pixels_rejected,
            "n_small_rejected": self.n_small_rejected, "n_extended_rejected": self.n_extended_rejected,
            "n_streaks_rejected": self.n_streaks_rejected,
            "n_unmeasured": self.n_unmeasured, "n_unmeasured_saturated": self.n_unmeasured_saturated,
            "psf_sigma_px": self.psf_sigma_px if math.isfinite(self.psf_sigma_px) else None,
            "estimator": self.estimator, "image_shape": list(self.image_shape), "params": self.params,
            "centroids": self.to_list(),
        }

    @classmethod
    def empty(cls, **kw) -> "Centroids":
        z = np.zeros(0)
        b = np.zeros(0, dtype=bool)
        return cls(uv=np.zeros((0, 2)), brightness=z, peak=z.copy(), n_pixels=np.zeros(0, dtype=np.int64),
                   saturated=b, elongated=b.copy(), edge=b.copy(), blended=b.copy(), axis_ratio=z.copy(), **kw)


# ============================================================================ loading

def to_gray(image: np.ndarray) -> np.ndarray:
    """2-D image from a 2-D, (H, W, 1), BGR or BGRA array (OpenCV channel order)."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 1:
        return a[:, :, 0]
    if a.ndim == 3 and a.shape[2] in (3, 4):
        if a.dtype not in (np.uint8, np.uint16, np.float32):
            a = a.astype(np.float32)
        code = cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(np.ascontiguousarray(a), code)
    return a


MAX_IMAGE_PIXELS_DEFAULT = 100_000_000  # 100 megapixels; SKYVIEW_MAX_PIXELS overrides


def max_image_pixels() -> int:
    """The largest image (width x height) skyview decodes: SKYVIEW_MAX_PIXELS, else 100 megapixels."""
    env = os.environ.get("SKYVIEW_MAX_PIXELS")
    try:
        return int(float(env)) if env else MAX_IMAGE_PIXELS_DEFAULT
    except ValueError:
        raise BadInput(f"SKYVIEW_MAX_PIXELS={env!r} is not a number") from None


def header_size(data: bytes | np.ndarray) -> tuple[int, int] | None:
    """(width, height) read from the header of a PNG, JPEG, TIFF, BMP or WebP file without decoding
    it; None for other formats or a header that cannot be read."""
    b = bytes(data[:65536]) if not isinstance(data, bytes) else data[:65536]
    try:
        if b[:8] == b"\x89PNG\r\n\x1a\n" and b[12:16] == b"IHDR":
            return int.from_bytes(b[16:20], "big"), int.from_bytes(b[20:24], "big")
        if b[:2] == b"\xff\xd8":  # JPEG: walk the markers to a start-of-frame
            i = 2
            while i + 9 < len(b):
                if b[i] != 0xFF:
                    i += 1
                    continue
                marker = b[i + 1]
                if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7 or marker == 0xFF:
                    i += 1 if marker == 0xFF else 2
                    continue
                length = int.from_bytes(b[i + 2:i + 4], "big")
                if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                    return int.from_bytes(b[i + 7:i + 9], "big"), int.from_bytes(b[i + 5:i + 7], "big")
                i += 2 + length
            return None
        if b[:4] in (b"II*\x00", b"MM\x00*"):  # TIFF: tags 256 (width) and 257 (height) of the first IFD
            order = "little" if b[:2] == b"II" else "big"
            off = int.from_bytes(b[4:8], order)
            n = int.from_bytes(b[off:off + 2], order)
            w = h = None
            for k in range(n):
                e = b[off + 2 + 12 * k: off + 14 + 12 * k]
                tag, typ = int.from_bytes(e[0:2], order), int.from_bytes(e[2:4], order)
                val = int.from_bytes(e[8:10], order) if typ == 3 else int.from_bytes(e[8:12], order)
                if tag == 256:
                    w = val
                elif tag == 257:
                    h = val
            return (w, h) if w and h else None
        if b[:2] == b"BM":
            return abs(int.from_bytes(b[18:22], "little", signed=True)), abs(int.from_bytes(b[22:26], "little",
                                                                                              signed=True))
        if b[:4] == b"RIFF" and b[8:12] == b"WEBP":
            if b[12:16] == b"VP8X":
                return 1 + int.from_bytes(b[24:27], "little"), 1 + int.from_bytes(b[27:30], "little")
            if b[12:16] == b"VP8 ":
                return int.from_bytes(b[26:28], "little") & 0x3FFF, int.from_bytes(b[28:30], "little") & 0x3FFF
    except (IndexError, ValueError):
        return None
    return None


def check_pixel_count(data: bytes | np.ndarray, name: str) -> None:
    """Refuse an image whose header announces more pixels than max_image_pixels(), before decoding."""
    size = header_size(data)
    limit = max_image_pixels()
    if size is not None and size[0] * size[1] > limit:
        raise BadInput(f"{name} is {size[0]} x {size[1]} pixels ({size[0] * size[1] / 1e6:.0f} MP), more than the "
                       f"{limit / 1e6:.0f} MP skyview decodes (set SKYVIEW_MAX_PIXELS to raise the limit)")


def finite_image(img: np.ndarray, name: str = "the image") -> np.ndarray:
    """A float image with its NaN / infinite pixels (masked, dead or overflowed) replaced by the median
    of the finite ones; BadInput when no pixel is finite. Integer images are returned as they are."""
    if img.dtype.kind != "f":
        return img
    ok = np.isfinite(img)
    if ok.all():
        return img
    if not ok.any():
        raise BadInput(f"{name} has no finite pixel value (all NaN or infinite)")
    out = img.copy()
    out[~ok] = np.median(img[ok])
    return out


_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def _c_stderr_silenced():
    """The process's file descriptor 2 pointed at the null device for the block: libpng writes its own line
    ("libpng error: Not enough image data") to stderr on a damaged PNG, past OpenCV's logging, and an error
    is one line. (The block is a decode: a line another thread writes to stderr meanwhile is lost.)"""
    with _STDERR_LOCK:
        try:
            saved = os.dup(2)
        except OSError:  # no stderr to silence
            yield
            return
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(null, 2)
            finally:
                os.close(null)
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


_CAMERA_RAW = frozenset((".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".orf", ".rw2", ".raf",
                         ".pef", ".srw", ".3fr", ".iiq", ".erf", ".kdc", ".mrw", ".x3f", ".dng"))  # cameras' raw formats


def camera_raw_message(name: str | os.PathLike) -> str:
    """What to do with a camera's raw file that nothing here decodes (by its name's extension), or ''."""
    suffix = Path(name).suffix
    if suffix.lower() not in _CAMERA_RAW:
        return ""
    return (f"{name} is a camera raw file ({suffix}), which OpenCV does not read: export it as a 16-bit TIFF or PNG "
            "(or FITS, or a JPEG) first")


def load_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file (PNG, TIFF, JPEG, ... anything cv2 decodes, and FITS) unchanged in depth, as grey.

    Raises BadInput with one line for a missing file, a directory, an empty file, a file OpenCV
    cannot decode and an image of size 0.
    """
    p = Path(path)
    if not p.exists():
        if p.is_symlink():
            raise BadInput(f"image {p} is a symbolic link that leads to no file (its target is missing, or a loop)")
        raise BadInput(f"image {p} does not exist")
    if p.is_dir():
        raise BadInput(f"image {p} is a directory, not an image file")
    try:
        data = np.fromfile(p, dtype=np.uint8)
    except OSError as exc:
        raise BadInput(f"image {p} cannot be read: {exc.strerror or exc}") from None
    if data.size == 0:
        raise BadInput(f"image {p} is empty (0 bytes)")
    check_pixel_count(data, f"image {p}")
    if data[:9].tobytes() == b"SIMPLE  =":  # FITS (skyview.io.fits: rows turned to top-first)
        from skyview.io.fits import read_fits
        return finite_image(read_fits(p, max_image_pixels())[0], f"image {p}")
    png = data[:8].tobytes() == b"\x89PNG\r\n\x1a\n"
    if png and b"IEND" not in data[-65536:].tobytes():
        raise BadInput(f"{p} is not an image OpenCV can read: a truncated PNG (it ends before its last chunk, IEND)")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        with _c_stderr_silenced() if png else contextlib.nullcontext():
            img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None:
        if data[:2].tobytes() == b"\xff\xd8" and b"\xff\xd9" not in data[-64:].tobytes():
            raise BadInput(f"{p} is not an image OpenCV can read: a truncated JPEG (it ends before its end marker, EOI)")
        raise BadInput(camera_raw_message(p) or f"{p} is not an image OpenCV can read")
    img = to_gray(img)
    if img.size == 0 or img.ndim != 2:
        raise BadInput(f"image {p} is empty (size {img.shape})")
    return finite_image(img, f"image {p}")


# ============================================================================ background / noise


def _median_sorted(s: np.ndarray) -> np.ndarray:
    """np.median along the last axis of an already sorted array (same value, same dtype)."""
    n = s.shape[-1]
    if n % 2:
        return s[..., n // 2]
    return (s[..., n // 2 - 1] + s[..., n // 2]) / s.dtype.type(2)


def _few_values(s: np.ndarray, k: int) -> bool:
    """np.unique(s).size < k for a small finite sample, from one sort and its steps (np.unique's wrappers
    cost several times more; this picks a median's method, whose value is the same either way)."""
    s = np.sort(s)
    return int(np.count_nonzero(s[1:] != s[:-1])) + 1 < k


def row_median(a: np.ndarray) -> np.ndarray:
    """Median of each row of a 2-D array (np.median's value, through one partition; and without np.median's
    NaN check, whose first call imports numpy.ma: ~10 ms of a process's start). For an even count the element
    below the middle is the largest of the left part: numpy's SIMD selection at one index and a maximum run
    two to five times faster than its partition at two (40 vs 24 us for 100 rows of 40)."""
    n = a.shape[1]
    h = n // 2
    p = np.partition(a, h, axis=1)
    if n % 2:
        return p[:, h]
    return 0.5 * (p[:, :h].max(axis=1) + p[:, h])


def _median_part(x: np.ndarray):
    """np.median of a 1-D array (the same value, in its dtype) from its middle order statistics: for an
    even count the mean of the two middle ones, from one partition at the middle (numpy's SIMD selection,
    ~25 us on 16,384 float32 values where a sort takes ~80 us, np.median's two-element partition ~115 us
    and np.median ~240 us; for an even count the element below the middle is the largest of the left part)."""
    n = x.size
    k = n // 2
    if n > 4096 and _few_values(x[::64], 32):
        # few distinct values (a noise of ~1 step of an integer image): numpy's selection slows ten-fold
        # on so many ties, its SIMD sort does not (the same median)
        return _median_sorted(np.sort(x))
    p = np.partition(x, k)
    if n % 2:
        return p[k]
    return (p[:k].max() + p[k]) / x.dtype.type(2)


def _background_stats(f: np.ndarray, block: int = 64):
    """(grid, block height, block width, level, sigma, flat) of a 2-D image of any real dtype (its
    float32 values), from a sub-sample: every `sx`-th pixel of every `sy`-th row, sx = 4 and sy = 8 on
    an image of 512 px or more a side (32,768 samples of a 1024 x 1024 frame, 128 per 64 px block),
    sx = sy = 4 / 2 / 1 on smaller ones (the reference's sample, `_estimate_background_reference`).

    grid: the median of each block's samples; level: the median of the grid; sigma: 1.4826 x the MAD
    of the samples less the bilinear map of the grid, refined by their 3.5-sigma clipped standard
    deviation; on the large images
    sigma comes from half the samples, a checkerboard of them (16,384 on 1024 x 1024: ~0.6 % noise on
    sigma; both pixel phases of the column step kept, as JPEG's 8 x 8 blocks want); flat: no block departs
    from the level by more than max(0.5 sigma, 4.5 x the scatter of a median of its samples, 1 on
    integer data). Sorts (of integers in their own dtype) and single-element partitions replace
    np.median (SIMD sorts and selections are several times faster than its two-element partitions)."""
    H, W = f.shape
    step = 4 if min(H, W) >= 256 else (2 if min(H, W) >= 64 else 1)
    sy, sx = (2 * step if min(H, W) >= 512 else step), step
    native = f.dtype in _NATIVE_DTYPES  # integers exact in float32: sorted in their own dtype (the same order)
    sub = f[sy // 2::sy, sx // 2::sx]
    if not native:
        sub = sub.astype(np.float32)
    sh, sw = sub.shape
    bsy, bsx = max(4, block // sy), max(4, block // sx)  # samples per block side
    gh, gw = max(1, sh // bsy), max(1, sw // bsx)
    by, bx = sh // gh, sw // gw
    cells = sub[: gh * by, : gw * bx].reshape(gh, by, gw, bx).transpose(0, 2, 1, 3).reshape(gh, gw, by * bx)
    # (8- and 16-bit integers sorted as int32: the same order; numpy's SIMD sorts cover 32- and 64-bit
    # types on every x86-64 with AVX2, 16-bit ones only with AVX-512 (VBMI2): a 16-bit sort is ~15 times
    # slower without it, an 8-bit one ~30 times; the int32 copy costs ~10 us of a 1024 x 1024 frame)
    cs = np.sort(cells.astype(np.int32) if native else cells, axis=2)
    if native:  # the middle value(s) as float32: np.median of the float32 samples
        m = cs.shape[2]
        mid = cs[:, :, m // 2].astype(np.float32)
        grid = (cs[:, :, m // 2 - 1].astype(np.float32) + mid) / np.float32(2) if m % 2 == 0 else mid
    else:
        grid = _median_sorted(cs).astype(np.float32)
    const = float(grid.min()) == float(grid.max())  # every block median the same (the usual flat sky)
    # = np.median(grid), without its overhead (of equal values: that value, (c + c) / 2 being c exactly)
    level = float(grid.flat[0]) if const else float(_median_sorted(np.sort(grid, axis=None)))
    # the samples less the bilinear map of the grid (_upsample's, at the samples used: _upsample_at);
    # on large frames the noise comes from half the samples (16,384 of a 1024 x 1024 frame), in a
    # checkerboard: every other sample of the even sample rows, the others of the odd ones (both
    # phases of the 4-pixel column step, as the reference's sample has them: JPEG's 8 x 8 blocks);
    # an integer sample less the float32 map is float32 (the values of its float32 copy less the map)
    parts = ((0, 2), (1, 2)) if sy > sx else ((0, 1),)
    n_r = sum(-(-(sh - a) // st) * -(-(sw - a) // st) for a, st in parts)  # the parts' sizes
    # a uint8 frame whose block medians are all equal (the usual flat sky) on blocks of 2^k x 2^l samples
    # (16 x 8 on 1024 x 1024), or on one block: the statistics from the samples' 256-bin histogram
    # (_u8_noise: the same numbers; its float32 counts are exact below 2^24 samples)
    dyadic = gh * gw == 1 or (by & (by - 1) == 0 and bx & (bx - 1) == 0)
    if f.dtype == np.uint8 and dyadic and n_r < 1 << 24 and const:
        covered = gh * by == sh and gw * bx == sw  # (the blocks hold every sample: 1024 x 1024)
        is_int, sigma = True, _u8_noise(_u8_hist(sub, parts, n_r, cells if covered else None), level, n_r)
    else:
        r = np.empty(n_r, dtype=np.float32)
        o = 0
        for a, st in parts:
            s_part = sub[a::st, a::st]
            bg = _upsample_at(grid, by, bx, sh, sw, a, st) if gh * gw > 1 else np.float32(level)
            np.subtract(s_part, bg, out=r[o:o + s_part.size].reshape(s_part.shape))
            o += s_part.size
        med = _median_part(r)
        mad = float(_median_part(np.abs(r - med)))  # |r - med| in float32: the deviations a sort would give
        s0 = _MAD_TO_SIGMA * mad
        is_int = f.dtype.kind in "ui" or bool(np.all(np.floor(sub) == sub))
        floor = 1.0 if is_int else max(1e-12, 1e-9 * float(np.abs(sub).max()))
        clip = _CLIP_K * max(s0, floor)
        c32 = np.float32(clip)  # |r| <= clip in float32, as the reference compares
        rc = r[np.abs(r) <= c32]  # = (r >= -c32) & (r <= c32): |r| is exact in float32, NaN fails both
        if rc.size > 10:
            # the standard deviation from one sum and one sum of products in float64 (np.std's float32
            # pairwise sums agree to ~1e-7 relative); einsum, not a BLAS dot, which spreads 16,000 products
            # over threads and waits for a busy core
            r64 = rc.astype(np.float64)
            mean = float(r64.sum()) / rc.size
            sigma = math.sqrt(max(float(np.einsum("i,i->", r64, r64)) / rc.size - mean * mean, 0.0)) / _CLIP_STD
        else:
            sigma = s0
    sigma = max(sigma, 0.5 if is_int else floor)
    tol = max(0.5 * sigma, 4.5 * 1.2533 * sigma / math.sqrt(by * bx), 1.0 if is_int else 0.0)
    flat = gh * gw == 1 or const or float(np.abs(grid - level).max()) <= tol  # (const: 0 <= tol)
    return grid, by * sy, bx * sx, level, sigma, flat


# The uint8 noise of _background_stats from a histogram. Where every block median equals the level c (a
# half-integer) and a block spans a power of two b of samples along each axis, the bilinear map
# (_upsample_at) is c exactly: its weights are then dyadic (multiples of 1 / (2 b), at most 3 in size)
# and those of a point sum to 1, so every product with c and every partial sum is exact in float32 (c has
# at most 9 significant bits); each sample's r = x - c is then exact in float32, and the median, the MAD
# and the clipped sums are functions of the 256 values' counts. (Other block sizes round the weights:
# the map is c only to ~1e-7, and the general path keeps those numbers.)


def _u8_hist(sub: np.ndarray, parts, n: int, cells: np.ndarray | None = None) -> np.ndarray:
    """The 256-bin histogram (float64 counts) of the uint8 samples sub[a::st, a::st] of each part; from
    `cells` (every sample of sub in contiguous blocks of an even number of rows and columns: each part's
    samples are the same positions of every block) when given."""
    if cells is not None:
        gh, gw, _ = cells.shape
        by, bx = sub.shape[0] // gh, sub.shape[1] // gw
        if len(parts) == 1 or (by % 2 == 0 and bx % 2 == 0):  # (parts: all samples, or the checkerboard)
            mask = None if len(parts) == 1 else _checkerboard(gh * gw, by, bx)
            c2 = np.ascontiguousarray(cells.reshape(-1, bx))
            return cv2.calcHist([c2], [0], mask, [256], [0, 256]).reshape(-1).astype(np.float64)
    buf = np.empty(n, dtype=np.uint8)
    o = 0
    for a, st in parts:
        s_part = sub[a::st, a::st]
        buf[o:o + s_part.size].reshape(s_part.shape)[...] = s_part
        o += s_part.size
    return cv2.calcHist([buf], [0], None, [256], [0, 256]).reshape(-1).astype(np.float64)  # (counts exact in float32)


@functools.lru_cache(maxsize=8)
def _checkerboard(n_blocks: int, by: int, bx: int) -> np.ndarray:
    """(n_blocks * by, bx) uint8 mask of the samples (i, j) of each by x bx block with i, j both even or
    both odd: _background_stats's two noise parts."""
    m = np.zeros((by, bx), dtype=np.uint8)
    m[0::2, 0::2] = m[1::2, 1::2] = 1
    return np.tile(m, (n_blocks, 1))


def _u8_noise(hist: np.ndarray, level: float, n: int) -> float:
    """_background_stats's noise sigma before its floor (1.4826 x MAD, refined by the 3.5-sigma clipped
    standard deviation) of n uint8 samples less the constant map `level`, from their histogram, in Python
    numbers over the occupied bins (a few dozen: fewer calls than numpy's on 256 bins). Every value is
    exact in float32 and in float64 alike: r = x - level (half-integers), the median and the MAD (means of
    two half- or quarter-integers below 512), |r - median|, and count x r, count x r^2 and their sums
    (integers times half-integers, far below 2^53; the per-sample float64 sums of the general path are
    exact too, whatever their order): the same median, MAD, mean and sigma."""
    occupied = hist.nonzero()[0]
    r = (occupied - level).tolist()  # ascending
    cnt = hist[occupied].tolist()
    mid = (n // 2 - 1, n // 2) if n % 2 == 0 else (n // 2,)  # the middle sample(s), sorted
    med = _middle(r, cnt, mid)
    dev = sorted(zip([abs(x - med) for x in r], cnt))
    s0 = _MAD_TO_SIGMA * _middle([d for d, _ in dev], [c for _, c in dev], mid)
    clip = float(np.float32(_CLIP_K * max(s0, 1.0)))  # (the floor of integer data: 1; compared in float32)
    inside = [(x, c) for x, c in zip(r, cnt) if abs(x) <= clip]
    n_in = sum(c for _, c in inside)
    if n_in <= 10:
        return s0
    mean = sum(c * x for x, c in inside) / n_in
    return math.sqrt(max(sum(c * x * x for x, c in inside) / n_in - mean * mean, 0.0)) / _CLIP_STD


def _middle(values: list, counts: list, mid: tuple) -> float:
    """The median of a sample given as ascending values with counts, from its middle position(s) `mid`:
    the middle value, or the mean of the middle two (exact here, as in float32)."""
    out = []
    seen = 0
    for v, c in zip(values, counts):
        seen += c
        while len(out) < len(mid) and mid[len(out)] < seen:
            out.append(v)
        if len(out) == len(mid):
            break
    return out[0] if len(out) == 1 else (out[0] + out[1]) / 2


def estimate_background(f: np.ndarray, block: int = 64) -> tuple[np.ndarray | float, float, float]:
    """(background map or scalar, median background level, noise sigma) of an image (any real dtype;
    the statistics are those of its float32 values).

    Block medians on a sub-sampled grid, interpolated bilinearly between block centres and
    extrapolated linearly beyond the outer ones (so a gradient is followed up to the borders).
    """
    grid, by, bx, level, sigma, flat = _background_stats(f, block)
    if flat:
        return level, level, sigma
    return _upsample(grid, by, bx, f.shape[0], f.shape[1]), level, sigma


@functools.lru_cache(maxsize=64)
def _map_weights(n_out: int, n_blocks: int, b: int, start: int, step: int) -> np.ndarray:
    """(rows, n_blocks) float32 weights that give _upsample's map along one axis at the coordinates
    start, start + step, ... < n_out from the n_blocks block values: cv2.resize's linear weights on the
    grid with its extrapolated ring (source coordinate (y + b + 0.5) / b - 0.5 in the ring's nodes, the
    last node repeated beyond it), times the ring's extrapolation (2 g[0] - g[1], 2 g[-1] - g[-2])."""
    y = np.arange(start, n_out, step, dtype=np.float64)
    src = (y + b + 0.5) / b - 0.5
    i0 = np.floor(src).astype(np.int64)
    frac = src - i0
    last = i0 >= n_blocks + 1
    i0[last], frac[last] = n_blocks + 1, 0.0
    R = np.zeros((y.size, n_blocks + 3))
    R[np.arange(y.size), i0] = 1.0 - frac
    R[np.arange(y.size), i0 + 1] += frac
    E = np.zeros((n_blocks + 3, n_blocks))  # the ring's nodes from the block values (+ an unused one)
    E[1:n_blocks + 1] = np.eye(n_blocks)
    if n_blocks > 1:
        E[0, :2], E[n_blocks + 1, -2:] = (2.0, -1.0), (-1.0, 2.0)
    else:
        E[0, 0] = E[n_blocks + 1, 0] = 1.0
    return (R @ E).astype(np.float32)


def _upsample_at(grid: np.ndarray, by: int, bx: int, H: int, W: int, start: int, step: int) -> np.ndarray:
    """_upsample(grid, by, bx, H, W)[start::step, start::step] from two products with cached weights
    (the same interpolation: the values agree to float32 rounding, ~1e-7 relative)."""
    g = np.asarray(grid, dtype=np.float32)
    return _map_weights(H, g.shape[0], by, start, step) @ g @ _map_weights(W, g.shape[1], bx, start, step).T


def _upsample(grid: np.ndarray, by: int, bx: int, H: int, W: int, out: np.ndarray | None = None) -> np.ndarray:
    """(H, W) map from block values at block centres ((i + 0.5) * by - 0.5, (j + 0.5) * bx - 0.5):
    bilinear between centres, linear extrapolation beyond the outer ones (one extra ring of blocks
    extrapolated from the outer two, then sampled at every pixel's place on that grid by one
    cv2.warpAffine: cv2.resize's half-pixel convention, without resizing the ring and cropping it, a
    third of the time; the values agree with resize-and-crop's to float32 rounding)."""
    g = grid.astype(np.float32)
    gh, gw = g.shape
    p = np.empty((gh + 2, gw + 2), dtype=np.float32)
    p[1:-1, 1:-1] = g
    p[0, 1:-1] = 2 * g[0] - g[1] if gh > 1 else g[0]
    p[-1, 1:-1] = 2 * g[-1] - g[-2] if gh > 1 else g[0]
    p[:, 0] = 2 * p[:, 1] - p[:, 2] if gw > 1 else p[:, 1]
    p[:, -1] = 2 * p[:, -2] - p[:, -3] if gw > 1 else p[:, 1]
    # pixel y of the map lies at (y + 0.5) / by - 0.5 on the block grid, + 1 on the ringed one
    to_grid = np.array([[1.0 / bx, 0.0, 0.5 / bx + 0.5], [0.0, 1.0 / by, 0.5 / by + 0.5]])
    return cv2.warpAffine(p, to_grid, (W, H), dst=out, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


SCRATCH_MAX_PIXELS = 1 << 22  # frames up to 4 MP keep their two float32 work maps for the next frame


class _WorkMaps:
    """The background and residual maps of detect_centroids, kept for the next frame of the same size: a
    fresh few-MB array pays its page faults on every frame (on this project's machine as much as the passes
    that fill it). A pair is lent to one call at a time (any thread: the viewer runs a thread per tab) and
    at most `keep` pairs are kept (the oldest goes), so the memory held is bounded: 2 x keep x 16 MB at
    most (frames over SCRATCH_MAX_PIXELS get fresh arrays, freed after)."""

    def __init__(self, keep: int):
        self.keep = max(1, int(keep))
        self._free: list[tuple[np.ndarray, np.ndarray]] = []
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def pair(self, H: int, W: int):
        """A (background, residual) pair of float32 (H, W) arrays for one call, or (None, None) (fresh ones
        made by the call) for a frame over SCRATCH_MAX_PIXELS. Nothing the call returns may refer to them."""
        if not 0 < H * W <= SCRATCH_MAX_PIXELS:
            yield None, None
            return
        with self._lock:  # (by position: a list's remove would compare the arrays)
            at = next((k for k, p in enumerate(self._free) if p[0].shape == (H, W)), None)
            got = self._free.pop(at) if at is not None else None
        if got is None:
            got = (np.empty((H, W), dtype=np.float32), np.empty((H, W), dtype=np.float32))
        try:
            yield got
        finally:
            with self._lock:
                self._free.append(got)
                del self._free[: max(0, len(self._free) - self.keep)]


_WORK_MAPS = _WorkMaps(os.cpu_count() or 2)


# ============================================================================ detection


# ============================================================================ detection (fast path)

_NATIVE_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.int16))  # exact in float32, cv2-native
_GATHER_HOT_MAX = 20000  # above: hot-pixel test with a ring max filter (as the reference)
_NB9_ROWS = np.repeat(np.arange(-1, 2), 3)  # the 3 x 3 neighbourhood, row-major: row and column offsets
_NB9_COLS = np.tile(np.arange(-1, 2), 3)
_RING8 = np.array([0, 1, 2, 3, 5, 6, 7, 8])  # the neighbourhood less its centre


class _Pixels:
    """Pixel values of an image, read as float32 (as the reference's float32 copy holds them), with
    the repaired hot pixels patched in: no full-frame copy of a native uint8/uint16/int16 image."""

    __slots__ = ("flat", "hp", "hv")

    def __init__(self, f: np.ndarray):
        self.flat = f.reshape(-1)
        self.hp = None  # sorted flat indices of repaired pixels
        self.hv = None  # their float32 values

    def take(self, fi: np.ndarray, dtype=np.float32) -> np.ndarray:
        """The values at flat indices fi as `dtype` (float32, or float64: the same values)."""
        v = self.flat[fi].astype(dtype)
        if self.hp is not None:
            pos = self.hp.searchsorted(fi)
            np.minimum(pos, len(self.hp) - 1, out=pos)
            hit = self.hp[pos] == fi
            if hit.any():
                v[hit] = self.hv[pos[hit]]
        return v


@functools.lru_cache(maxsize=64)
def _window_offsets(h: int, W: int) -> np.ndarray:
    """(2h + 1, 2h + 1) flat-index offsets of a window's pixels from its centre in a width-W image."""
    d = np.arange(-h, h + 1)
    return d[:, None] * W + d[None, :]


@functools.lru_cache(maxsize=64)
def _ring_offsets(W: int, centre: bool) -> np.ndarray:
    """Flat-index offsets of the 3 x 3 neighbourhood, row-major ((9, 1), centre included) or of its 8
    neighbours ((8,), centre left out) in a width-W image."""
    o = _NB9_ROWS * W + _NB9_COLS
    return o[:, None] if centre else o[_RING8]


def _gather_px(px, H, W, bkg, resid, pi, pj, h):
    """_gather reading through a _Pixels: (values - background (0 off the image), on-image mask, raw);
    the mask is None when every window lies inside the image (the usual case: all True)."""
    n = len(pi)
    if n and pi.min() >= h and pi.max() < H - h and pj.min() >= h and pj.max() < W - h:
        # every window inside the image (the usual case): no clipping, no masking
        valid = None
        fi = (pi * W + pj)[:, None, None] + _window_offsets(h, W)
        raw = px.take(fi, np.float64)
        vals = resid.reshape(-1)[fi].astype(np.float64) if resid is not None else raw - bkg
        return vals, valid, raw
    d = np.arange(-h, h + 1)
    rows = pi[:, None, None] + d[None, :, None]
    cols = pj[:, None, None] + d[None, None, :]
    valid = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)
    fi = np.minimum(np.maximum(rows, 0), H - 1) * W + np.minimum(np.maximum(cols, 0), W - 1)
    raw = px.take(fi, np.float64)
    vals = resid.reshape(-1)[fi].astype(np.float64) if resid is not None else raw - bkg
    vals[~valid] = 0.0
    return vals, valid, raw


def _neighbour_max(px, H, W, bkg, resid, fi: np.ndarray) -> np.ndarray:
    """Largest background-subtracted value among the 8 neighbours of the pixels at flat indices fi (0
    for a neighbour off the image): what `_gather_px(..., 1)[0]` gives with its centre left out, maxed,
    without the (n, 3, 3) index arrays for the pixels away from the border. The background is subtracted
    after the max (float32 -> float64 is exact and subtracting a scalar keeps order: the same number)."""
    out = np.empty(fi.size, dtype=np.float64)
    i, j = fi // W, fi % W
    inner = (i > 0) & (i < H - 1) & (j > 0) & (j < W - 1)
    k = _flatnonzero(inner)
    if k.size:
        nf = fi[k][:, None] + _ring_offsets(W, False)
        v = (resid.reshape(-1)[nf] if resid is not None else px.take(nf)).max(axis=1).astype(np.float64)
        out[k] = v if resid is not None else v - bkg
    b = _flatnonzero(~inner)
    if b.size:
        nb = _gather_px(px, H, W, bkg, resid, i[b], j[b], 1)[0]
        nb[:, 1, 1] = -np.inf
        out[b] = nb.reshape(b.size, -1).max(axis=1)
    return out


def _label_sparse(idx: np.ndarray, W: int) -> tuple[np.ndarray, int]:
    """8-connected labels (1..n) of the pixels at sorted flat indices idx of a width-W image, and n + 1
    (cv2's count): cv2.connectedComponents on a compacted image that keeps only the rows and the columns
    holding a pixel, in order, with one blank row (column) wherever rows (columns) were skipped, so that
    two pixels touch there exactly when they touch in the image. Components are numbered as cv2
    numbers them in the compacted image (which can differ from its numbering of the full mask: only the
    order of stars of equal brightness depends on it)."""
    if W & (W - 1) == 0:  # a power of two (1024): a shift and a mask, the same numbers as divmod
        r, c = idx >> (W.bit_length() - 1), idx & (W - 1)
    else:
        r, c = np.divmod(idx, W)
    step = np.empty(r.size, dtype=np.int64)
    step[0] = 1
    np.minimum(r[1:] - r[:-1], 2, out=step[1:])  # idx is sorted: rows ascend
    cr = np.cumsum(step)
    used = np.zeros(W, dtype=bool)
    used[c] = True
    uc = _flatnonzero(used)
    cstep = np.empty(uc.size, dtype=np.int64)
    cstep[0] = 1
    np.minimum(uc[1:] - uc[:-1], 2, out=cstep[1:])
    col_map = np.empty(W, dtype=np.int64)
    col_map[uc] = np.cumsum(cstep)
    n_cols = int(col_map[uc[-1]]) + 2
    img = np.zeros((int(cr[-1]) + 2, n_cols), dtype=np.uint8)
    flat = cr * n_cols + col_map[c]  # flat indices in the compacted image: one take, not a 2-D fancy index
    img.reshape(-1)[flat] = 1
    # 16-bit labels (cv2 is faster writing them) when even one label a pixel cannot overflow them: the same
    # algorithm, the same numbers
    ltype = cv2.CV_16U if img.size < 65535 else cv2.CV_32S
    n, lab = cv2.connectedComponents(img, connectivity=8, ltype=ltype)
    return lab.reshape(-1)[flat].astype(np.int64), int(n)


def _label_peaks(lab: np.ndarray, val: np.ndarray, n_lab: int) -> np.ndarray:
    """For labels 1 .. n_lab - 1 (each holding a pixel), the position of the label's brightest pixel
    in lab / val, the last one where several share its value: what the last of each label in
    np.lexsort((val, lab)) is, without the sort (the label's maximum by np.maximum.at, then the pixels
    at it written to a table by label in ascending order: the last write of a label stays)."""
    lab_max = np.full(n_lab, -np.inf, dtype=val.dtype)
    np.maximum.at(lab_max, lab, val)
    at_max = _flatnonzero(val == lab_max[lab])
    top = np.empty(n_lab, dtype=np.int64)
    top[lab[at_max]] = at_max
    return top[1:]


@functools.lru_cache(maxsize=None)
def _int_range(dtype: np.dtype) -> tuple[int, int]:
    """(min, max) of an integer dtype (np.iinfo, which costs tens of microseconds a call)."""
    info = np.iinfo(dtype)
    return int(info.min), int(info.max)


def _above(f: np.ndarray, t32: np.float32) -> np.ndarray:
    """f > t32 (f as float32), on the native array: an integer image is compared with floor(t32)."""
    if f.dtype.kind in "ui" and math.isfinite(float(t32)):
        lo, hi = _int_range(f.dtype)
        ti = math.floor(float(t32))
        if ti >= hi:
            return np.zeros(f.shape, dtype=bool)
        if ti < lo:
            return np.ones(f.shape, dtype=bool)
        return f > f.dtype.type(ti)
    return f > t32 if f.dtype == np.float32 else f.astype(np.float32) > t32


_BAND = 4  # rows per band of _band_max: the maxima of 4-row runs are one SIMD pass at ~half a row max's cost


def _band_max(f: np.ndarray) -> np.ndarray:
    """The maximum of each run of _BAND rows of f (a last, shorter run included): one pass over the frame;
    a reduction over 4 W contiguous values runs at about twice the speed of one over W."""
    H, W = f.shape
    n = H // _BAND
    m = f[: n * _BAND].reshape(n, _BAND * W).max(axis=1)
    return np.r_[m, f[n * _BAND:].max()] if H % _BAND else m


def _above_idx(f: np.ndarray, t32: np.float32, band_max: np.ndarray | None = None) -> np.ndarray:
    """np.flatnonzero(_above(f, t32)): when the maxima of the bands of _BAND rows (one SIMD pass;
    `band_max` (_band_max(f)) if given) leave at most half the bands above the threshold, only those
    bands are compared (the same indices, ascending)."""
    H, W = f.shape
    t = None
    if f.dtype == np.float32:
        t = t32
    elif f.dtype.kind in "ui" and math.isfinite(float(t32)):
        ti = math.floor(float(t32))
        lo, hi = _int_range(f.dtype)
        if lo <= ti < hi:
            t = f.dtype.type(ti)
    if t is None:
        return _flatnonzero(_above(f, t32))
    bands = _flatnonzero((_band_max(f) if band_max is None else band_max) > t)
    if bands.size > -(-H // _BAND) // 2:
        return _flatnonzero_sparse(f > t)
    if H % _BAND:  # a shorter last band: its rows listed one by one
        rows = (bands[:, None] * _BAND + np.arange(_BAND)).ravel()
        rows = rows[rows < H]
        q = _flatnonzero_sparse(f[rows] > t)
        return rows[q // W] * W + q % W
    bw = _BAND * W
    q = _flatnonzero_sparse(f.reshape(H // _BAND, bw)[bands] > t)
    return bands[q // bw] * bw + q % bw


def detect_centroids(image: np.ndarray, *, k_sigma: float = 5.0, window: int | None = None, min_pixels: int = 2,
                     estimator: str = DEFAULT_ESTIMATOR, psf_sigma_px: float | None = None,
                     saturation_level: float | None = None, max_axis_ratio: float = 1.4,
                     background_block: int = 64, iterations: int = 6, deblend: bool = True,
                     max_stars: int | None = None) -> Centroids:
    """Find stars in a 2-D image and measure their sub-pixel centroids: `_detect_centroids` (its docstring
    says how) with a pair of work maps lent for the call (`_WorkMaps`). Within `detections_kept`, a frame
    detected before (the same image object, the same options) is measured again from its detection, and an
    answer given before is given again (a copy of its params)."""
    shape = np.shape(image)
    options = dict(k_sigma=k_sigma, window=window, min_pixels=min_pixels, estimator=estimator,
                   psf_sigma_px=psf_sigma_px, saturation_level=saturation_level, max_axis_ratio=max_axis_ratio,
                   background_block=background_block, iterations=iterations, deblend=deblend)

    def detect(stage_out: list | None = None) -> Centroids:
        with _WORK_MAPS.pair(*(shape[:2] if len(shape) >= 2 else (0, 0))) as maps:
            return _detect_centroids(image, **options, max_stars=max_stars, maps=maps, stage_out=stage_out)

    kept = _DETECTIONS.get()
    if kept is None or not isinstance(image, np.ndarray) or len(shape) < 2 \
            or shape[0] * shape[1] > DETECTIONS_KEPT_MAX_PIXELS:
        return detect()
    _check_max_stars(max_stars)
    key = tuple(options.items())
    entry = next((e for e in kept if e[0] is image and e[1] == key), None)  # (image, key, measure, answers)
    if entry is None:
        stage: list = []
        answer = detect(stage)
        entry = (image, key, stage[0] if stage else None, {max_stars: answer})
        kept.append(entry)
    elif max_stars not in entry[3]:
        entry[3][max_stars] = entry[2](max_stars) if entry[2] is not None else detect()
    out = entry[3][max_stars]
    return dataclasses.replace(out, params=dict(out.params))


DETECTIONS_KEPT_MAX_PIXELS = 16_000_000  # `detections_kept` keeps frames up to this size
_DETECTIONS: contextvars.ContextVar[list | None] = contextvars.ContextVar("skyview_detections_kept", default=None)


@contextlib.contextmanager
def detections_kept():
    """Within it, each frame (an image object, up to DETECTIONS_KEPT_MAX_PIXELS) is detected once per set of
    options: on a flat sky its threshold, labels and blends are kept, and a `detect_centroids` of it with another
    max_stars only measures (a solve that reads the brightest stars first and more of them after: the same
    centroids, field for field, as detecting it again); under a background map (whose work maps are lent, not
    kept) it is detected again; an answer asked for again is given again. The frames, their detections and
    answers are held until the outermost such block ends (nested blocks share it)."""
    if _DETECTIONS.get() is not None:
        yield
        return
    token = _DETECTIONS.set([])
    try:
        yield
    finally:
        _DETECTIONS.reset(token)


def _check_max_stars(max_stars) -> None:
    if max_stars is not None and (isinstance(max_stars, bool) or int(max_stars) != max_stars or max_stars < 1):
        raise BadInput(f"max_stars={max_stars} must be a whole number >= 1 (or None: every star)")


def _detect_centroids(image: np.ndarray, *, k_sigma: float = 5.0, window: int | None = None, min_pixels: int = 2,
                      estimator: str = DEFAULT_ESTIMATOR, psf_sigma_px: float | None = None,
                      saturation_level: float | None = None, max_axis_ratio: float = 1.4,
                      background_block: int = 64, iterations: int = 6, deblend: bool = True,
                      max_stars: int | None = None, maps: tuple = (None, None),
                      stage_out: list | None = None) -> Centroids:
    """Find stars in a 2-D image and measure their sub-pixel centroids (see the module docstring).
    stage_out: a list the measurement of this detection is appended to, as a function of max_stars, for
    `detections_kept` (none where nothing is left to measure, nor under a background map: the maps are lent).

    window: odd side of the square measurement window (pixels) around each blob's brightest pixel;
    None picks 2*ceil(2.5 sigma_eff) + 1 from the measured PSF (sigma_eff^2 = sigma^2 + 1/12).
    psf_sigma_px: PSF sigma for the fit and iwcog; None measures it from the bright stars
    (3-point log-curvature), falling back to 1.2 px. A blank (constant) image gives zero centroids.
    A colour (BGR/BGRA) image is converted to grey; any other non-2-D array is BadInput.
    deblend: split a blob with several peaks (each >= 2.5 px from a brighter one, with a dip of at
    least 20 % and 3 sigma between them) into one centroid per peak, flagged `blended`; with the
    "fit" estimator each one is refitted after subtracting its neighbours' fitted PSFs.
    max_stars: measure only the brightest max_stars stars, as a star tracker does (the rest are
    counted in `n_unmeasured`): each detected star's window sum ranks it before any position is
    measured, so the answer is the first max_stars centroids of the whole set, field for field, at
    a fraction of the cost in a dense field. None measures every star.

    The former implementation, `_detect_centroids_reference` (tests/oracles/centroid_reference.py), is what this
    one is tested against (tests/test_centroid.py states the tolerances): the same noise sigma to ~2 %
    (from a half and a quarter of its sub-sample on frames of 512 px or more), the same stars above
    12.5 sigma with the same flags and peaks, positions within 2e-3 px on a flat sky (observed <= 1.5e-4
    px but for unresolved pairs) and 0.02 px under a background map. Computed without a float copy of
    a uint8/uint16/int16 frame (the fast forms and what each one keeps are listed in the module
    docstring, "Fast forms"): background statistics from the sub-sampled pixels, a scalar threshold on
    the native image when the background is flat (only the 4-row bands whose maximum crosses it
    compared), only the above-threshold pixels labelled, each one's 3 x 3 neighbourhood read once for
    the hot-pixel test, its repair and the deblender, hot pixels patched on read instead of in a copy,
    one window gather for the PSF width and the estimators when the 7 px window is the one wanted, the
    PSF fits of all stars batched (3 x 3 normal equations solved by their adjugates).
    """
    if estimator not in ESTIMATORS:
        raise BadInput(f"unknown centroid estimator {estimator!r}: choose one of {', '.join(ESTIMATORS)}")
    if window is not None and (int(window) < 3 or int(window) % 2 == 0):
        raise BadInput(f"window={window} must be an odd number >= 3")
    if not (k_sigma > 0):
        raise BadInput(f"k_sigma={k_sigma} must be positive")
    _check_max_stars(max_stars)
    img = np.ascontiguousarray(to_gray(image))  # any memory order (Fortran, transposed views)
    if img.ndim != 2:
        raise BadInput(f"image must be 2-D (grey) or BGR/BGRA, got an array of shape {np.shape(image)}")
    if img.dtype.kind not in "uif":
        raise BadInput(f"image dtype {img.dtype} is not a number type")
    H, W = img.shape
    params = {"k_sigma": k_sigma, "window": window, "min_pixels": int(min_pixels),
              "max_axis_ratio": max_axis_ratio}
    if H < 3 or W < 3:
        raise BadInput(f"image of shape {img.shape} is too small to search for stars")
    if img.dtype in _NATIVE_DTYPES:
        f = img  # read as float32 value by value (exact): no full-frame copy
    else:
        f = img.astype(np.float32, copy=False)
        if img.dtype.kind == "f" and not np.all(np.isfinite(f)):
            f = np.where(np.isfinite(f), f, np.float32(np.nanmedian(np.where(np.isfinite(f), f, np.nan))))
    dtype_max = float(_int_range(img.dtype)[1]) if img.dtype.kind in "ui" else math.inf

    band_max = _band_max(f)  # first: the one full pass brings the frame into the cache for what follows
    grid, gby, gbx, level, sigma, flat = _background_stats(f, background_block)
    thr = float(k_sigma) * sigma
    params["background_flat"] = bool(flat)  # (one level for the whole frame, or a map: `detect_stars` reads it)
    if flat:
        bkg, resid = level, None
        idx = _above_idx(f, np.float32(bkg + thr), band_max)
    else:
        bkg = _upsample(grid, gby, gbx, H, W, out=maps[0])  # (maps: the grey image's size, as the image's)
        # (OpenCV's subtraction: np.subtract's float32 numbers from a uint8 / uint16 / int16 or float32 frame,
        # ~20 % faster than numpy's mixed-type loop)
        resid = cv2.subtract(f, bkg, dst=maps[1], dtype=cv2.CV_32F)
        idx = _above_idx(resid, np.float32(thr))
    empty = dict(background_level=level, noise_sigma=sigma, threshold=thr, estimator=estimator,
                 image_shape=(H, W), params=params)
    if idx.size == 0:
        # a constant image has no pixel above the threshold: told apart here, not by a full-frame pass first
        fmin, fmax, _, _ = cv2.minMaxLoc(f)  # f: uint8 / uint16 / int16 or float32
        if fmax == fmin:
            return Centroids.empty(background_level=float(fmin), noise_sigma=0.0, estimator=estimator,
                                   image_shape=(H, W), params=params)
        return Centroids.empty(**empty)
    px = _Pixels(f)
    # hot pixels (see the reference): counted, taken out of the mask, repaired on read
    nb9 = None  # (9, n): each pixel's raw 3 x 3 neighbourhood (values exact in float32), row-major
    i_lo, i_hi = idx[0] // W, idx[-1] // W  # idx ascends
    if resid is None and idx.size <= _GATHER_HOT_MAX and H > 2 and W > 2:
        # a flat sky (the usual case): the 3 x 3 values read in their own dtype as 9 rows of n, the ring's
        # maximum from contiguous rows; the background is subtracted after the max (float64 of an exact
        # value less a scalar keeps the order: the numbers of the gather below). Pixels in the first or
        # last column are read there too: their row wraps into the next one, so those get the gather's
        # zero-padded neighbourhood, and so do pixels in the first or last row (their indices clipped to
        # the image for this read)
        j = idx % W
        nbi = _ring_offsets(W, True) + idx
        border_rows = i_lo == 0 or i_hi == H - 1
        if border_rows:
            np.minimum(np.maximum(nbi, 0, out=nbi), H * W - 1, out=nbi)
        nb9 = f.reshape(-1)[nbi]
        nb_max = np.maximum(nb9[:4].max(axis=0), nb9[5:].max(axis=0)).astype(np.float64) - bkg
        centre = nb9[4].astype(np.float64) - bkg
        at_side = (j == 0) | (j == W - 1)
        if border_rows:
            at_side |= (idx < W) | (idx >= (H - 1) * W)
        side = _flatnonzero(at_side)
        if side.size:
            # their zero-padded neighbourhoods: the gather's own numbers (no hot pixel repaired yet)
            v, _, raw9 = _gather_px(px, H, W, bkg, None, idx[side] // W, j[side], 1)
            nb9[:, side] = raw9.reshape(-1, 9).T  # (the frame's values: exact in its dtype)
            v = v.reshape(-1, 9)
            v[:, 4] = -np.inf
            nb_max[side] = v.max(axis=1)
    elif idx.size <= _GATHER_HOT_MAX:
        # each pixel's 3 x 3 neighbourhood, once: the hot-pixel test, the repair and the deblender's
        # local-maximum test read it
        nb_vals, _, nb_raw = _gather_px(px, H, W, bkg, resid, idx // W, idx % W, 1)
        nb = nb_vals.reshape(idx.size, 9)
        nb9 = nb_raw.reshape(idx.size, 9).T
        centre = nb[:, 4].copy()
        nb[:, 4] = -np.inf
        nb_max = nb.max(axis=1)
    else:
        src = f if resid is None else resid
        ring = np.ones((3, 3), np.uint8)
        ring[1, 1] = 0
        nb_max = cv2.dilate(src, ring).reshape(-1)[idx].astype(np.float64)
        centre = src.reshape(-1)[idx].astype(np.float64)
        if resid is None:
            nb_max -= bkg
            centre -= bkg
    hotpix = nb_max < np.maximum(3.0 * sigma, 0.15 * centre)
    n_hot = int(np.count_nonzero(hotpix))  # (a bool sum casts to int first: several times slower)
    hp = None
    if n_hot:
        hp = idx[hotpix]
        if nb9 is not None:
            ring = nb9[:, hotpix][_RING8].T.astype(np.float64)
        else:
            ring = np.delete(_gather_px(px, H, W, bkg, resid, hp // W, hp % W, 1)[2].reshape(n_hot, 9), 4, axis=1)
        ring.sort(axis=1)  # (ring is this step's own copy)
        repaired = _median_sorted(ring).astype(np.float32)  # = np.median(ring, axis=1)
        px.hp, px.hv = hp, repaired
        if resid is not None:
            resid.reshape(-1)[hp] = repaired - bkg.reshape(-1)[hp]
        keep_px = ~hotpix
        idx, nb_max = idx[keep_px], nb_max[keep_px]
        raw = nb9[4, keep_px].astype(np.float32) if nb9 is not None else None
    else:
        raw = nb9[4].astype(np.float32) if nb9 is not None else None
    empty["n_hot_pixels_rejected"] = n_hot
    if idx.size == 0:
        return Centroids.empty(**empty)
    lab, n_lab = _label_sparse(idx, W)
    if raw is None:
        raw = px.take(idx)
    val = raw - bkg if resid is None else resid.reshape(-1)[idx]
    top_px = _label_peaks(lab, val, n_lab)
    peak_flat = idx[top_px]
    peak_val = val[top_px]
    area = np.bincount(lab, minlength=n_lab)[1:].astype(np.int64)
    pi, pj = peak_flat // W, peak_flat % W

    sat = dtype_max if saturation_level is None else float(saturation_level)
    top = float(raw.max())
    if top < sat and top > 0:  # (the count only where it can matter)
        n_top = int(np.count_nonzero(raw == top))
        if (n_top >= 2 and _is_adc_max(top)) or n_top >= 5:
            sat = top
    if resid is None:  # raw - level: the highest value is the highest raw value
        blob_max = raw[top_px].astype(np.float64)
    else:
        blob_max = np.full(n_lab - 1, -np.inf)
        np.maximum.at(blob_max, lab - 1, raw)
    saturated_all = blob_max >= sat

    small = area < int(min_pixels)
    hot_blobs = _hot_clusters(px, H, W, bkg, resid, idx, lab, area, peak_val, sigma)
    if hot_blobs is not None:  # (taken out as hot pixels are: counted with them, not as stars)
        n_hot += int(area[hot_blobs].sum())
        empty["n_hot_pixels_rejected"] = n_hot
        small[hot_blobs] = False
        out = np.zeros(len(area), dtype=bool)
        out[hot_blobs] = True
        keep = _flatnonzero(~small & ~out)
    else:
        keep = _flatnonzero(~small)
    n_small = int(np.count_nonzero(small))
    if keep.size == 0:
        return Centroids.empty(n_small_rejected=n_small, **empty)

    pi, pj, area, saturated, peak_val = pi[keep], pj[keep], area[keep], saturated_all[keep], peak_val[keep]
    peak_raw = blob_max[keep]
    comp = keep + 1
    if deblend:
        extra = _split_blends_px(px, H, W, bkg, resid, idx, lab, val, raw, comp, area, pi, pj, sigma, sat, nb_max, hp)
        if extra is not None:
            e_comp, e_pi, e_pj, e_val, e_raw = extra
            e_area = area[np.searchsorted(comp, e_comp)]
            cat = np.concatenate  # (np.r_'s result, without its index-trick overhead)
            pi, pj = cat((pi, e_pi)), cat((pj, e_pj))
            comp, area = cat((comp, e_comp)), cat((area, e_area))
            peak_val, peak_raw = cat((peak_val, e_val)), cat((peak_raw, e_raw))
            saturated = cat((saturated, np.zeros(len(e_comp), dtype=bool)))
    blended = np.zeros(len(comp), dtype=bool)
    if len(comp) > len(keep):  # the components split in several: a lookup table by label (np.isin's answer)
        split = np.zeros(int(comp.max()) + 1, dtype=bool)
        split[comp[len(keep):]] = True
        blended = split[comp]

    def gather(h):
        return _gather_px(px, H, W, bkg, resid, pi, pj, h)

    def measure(m, params=dict(params)):  # (the params as they are before any measurement: each one's copy)
        return _measure(gather, pi, pj, comp, area, saturated, blended, peak_val, peak_raw, sat, sigma, level, thr,
                        n_hot, n_small, H, W, estimator=estimator, psf_sigma_px=psf_sigma_px, window=window,
                        iterations=iterations, max_axis_ratio=max_axis_ratio, params=dict(params), max_stars=m)

    if stage_out is not None and resid is None:  # (a flat sky's: nothing it keeps refers to the maps lent)
        stage_out.append(measure)
    return measure(max_stars)


HOT_CLUSTER_MAX_PX = 4  # a blob this small, its peak this many sigma or more, ...
HOT_CLUSTER_MIN_PEAK = 50.0
HOT_CLUSTER_RING = 0.06  # ... every pixel around it below this fraction of its peak: hot pixels, a cosmic ray


def _hot_clusters(px, H, W, bkg, resid, idx, lab, area, peak_val, sigma) -> np.ndarray | None:
    """The blobs (0-based, ascending) of 2 .. HOT_CLUSTER_MAX_PX pixels that are hot pixels side by side or a
    cosmic ray's hit, not a star: the peak (`peak_val`, background subtracted) HOT_CLUSTER_MIN_PEAK noise
    sigma or more and every pixel touching the blob from outside below HOT_CLUSTER_RING of it. A star spreads its light over its PSF: the faintest ring a
    star's blob can have is a 2 x 2 blob of a star centred on a pixel corner, at 4.8 % of its peak for a PSF of
    sigma 0.5 px, 10.4 % at 0.6 px (the photographs of tests/data: 0.63 px), 40 % at 1 px; at 50 sigma a star
    of 0.6 px clears the bound by more than 2 sigma in each of its four nearest ring pixels (and one wider than
    that has them above the threshold: its blob is larger). A star sharper than ~0.52 px centred near a pixel
    corner, at 50-100 sigma, is taken for hot pixels (no lens or star tracker focuses that sharp: the
    photographs' 0.63 px are the sharpest seen). Hot pixels two by two come by chance (~40 pairs
    among 3,000 hot pixels on a megapixel frame, all brighter than its stars) and from cosmic rays. Their
    pixels are patched (`_Pixels`: each with the median of its neighbours outside the blob) so that they pull
    no star's centroid either. None when there is none."""
    cand = _flatnonzero((area >= 2) & (area <= HOT_CLUSTER_MAX_PX) & (peak_val >= HOT_CLUSTER_MIN_PEAK * sigma))
    if cand.size == 0:
        return None
    on = np.zeros(len(area) + 1, dtype=bool)
    on[cand + 1] = True
    sel = _flatnonzero(on[lab])  # the pixels of the candidate blobs
    fi = idx[sel]
    vals, valid, raw = _gather_px(px, H, W, bkg, resid, fi // W, fi % W, 1)
    n = fi.size
    vals, raw = vals.reshape(n, 9), raw.reshape(n, 9)
    nb = fi[:, None] + _ring_offsets(W, True).T  # (n, 9) flat indices (off the image: masked by `valid`)
    pos = np.minimum(idx.searchsorted(nb), idx.size - 1)
    member = idx[pos] == nb  # a neighbour above the threshold: 8-connected, so a pixel of the same blob
    if valid is not None:
        member |= ~valid.reshape(n, 9)  # (off the image: neither the blob nor its ring)
    ring_max = np.full(len(area) + 1, -np.inf)
    np.maximum.at(ring_max, lab[sel], np.where(member, -np.inf, vals).max(axis=1))
    hot = ring_max[cand + 1] < HOT_CLUSTER_RING * peak_val[cand]
    if not hot.any():
        return None
    hot_blobs = cand[hot]
    mine = np.zeros(len(area) + 1, dtype=bool)
    mine[hot_blobs + 1] = True
    k = _flatnonzero(mine[lab[sel]])
    outside = ~member[k]
    has = outside.any(axis=1)
    # (a pixel whose neighbours are all the blob's or off the image, in a corner: the background there)
    repaired = np.full(k.size, float(bkg)) if resid is None else raw[k, 4] - vals[k, 4]
    if has.any():
        repaired[has] = np.nanmedian(np.where(outside[has], raw[k][has], np.nan), axis=1)
    repaired = repaired.astype(np.float32)
    hp, hv = fi[k], repaired
    if px.hp is not None:
        hp, hv = np.concatenate((px.hp, hp)), np.concatenate((px.hv, hv))
    order = np.argsort(hp, kind="stable")
    px.hp, px.hv = hp[order], hv[order]
    if resid is not None:
        resid.reshape(-1)[fi[k]] = repaired - bkg.reshape(-1)[fi[k]]
    return hot_blobs


def _measure(gather, pi, pj, comp, area, saturated, blended, peak_val, peak_raw, sat, sigma, level, thr, n_hot,
             n_small, H, W, *, estimator, psf_sigma_px, window, iterations, max_axis_ratio, params,
             max_stars=None) -> Centroids:
    """Steps 3-4 of detect_centroids on the detected peaks (as in the reference): PSF width, window,
    positions, brightness, flags, extended-blob rejection, brightest-first order."""
    # one gather of the window the PSF usually asks for (7 x 7 for sigma 1.1 px, or the given window);
    # a second one only when the measured PSF wants another size
    h0 = int(window) // 2 if window is not None else 3
    vals, valid, rawv = gather(h0)
    g_ok, g_uv, g_s2 = _gauss3_fast(vals, h0, pi, pj)
    g_unsat = g_ok & ~saturated  # a three-point fit of an unsaturated star
    # (cosmic rays: they neither measure the PSF nor count as stars)
    streak = peak_val >= STREAK_MIN_PEAK * sigma
    bright = _flatnonzero(streak)
    if bright.size:
        streak[bright] = _sharp_streaks(vals[bright], h0, sigma)
    if psf_sigma_px is None:
        good = g_unsat & (peak_val > 20.0 * sigma) & ~streak
        if valid is not None:  # (None: every window inside the image)
            good &= valid[:, h0 - 1:h0 + 2, h0 - 1:h0 + 2].all(axis=(1, 2))
        g = np.sort(g_s2[good])  # _median_sorted of the sorted values = np.median
        params["psf_measured"] = bool(g.size)  # by the bright unsaturated stars (none: 1.2 px assumed)
        s_eff = math.sqrt(float(_median_sorted(g))) if g.size else math.sqrt(1.2 ** 2 + 1.0 / 12.0)
        s_eff = min(max(s_eff, 0.4), 5.0)
        psf_used = math.sqrt(max(s_eff ** 2 - 1.0 / 12.0, 0.04))
    else:
        psf_used = float(psf_sigma_px)
        s_eff = math.sqrt(psf_used ** 2 + 1.0 / 12.0)
    h = int(window) // 2 if window is not None else min(max(math.ceil(2.5 * s_eff), 2), 8)
    params["window_used"] = 2 * h + 1

    if h < h0:  # the narrower windows are the middles of those gathered: the same pixels, the same numbers
        cut = slice(h0 - h, h0 + h + 1)
        vals, rawv = np.ascontiguousarray(vals[:, cut, cut]), np.ascontiguousarray(rawv[:, cut, cut])
        if valid is not None:
            valid = np.ascontiguousarray(valid[:, cut, cut])
    elif h > h0:
        vals, valid, rawv = gather(h)
    extended = area > max(MIN_EXTENDED_PX, EXTENDED_PSF_AREAS * math.pi * (3.0 * s_eff) ** 2)
    n_extended = int(np.count_nonzero(extended))
    streak &= ~extended
    n_streaks = int(np.count_nonzero(streak))
    if n_streaks:  # (left out as the extended blobs are, counted apart)
        extended = extended | streak
        n_extended = int(np.count_nonzero(extended))
    brightness = vals.sum(axis=(1, 2))  # final for a star that is not blended (only the deblender changes vals)
    keep_s = ~extended if n_extended else None
    if max_stars is not None:
        measured = _brightest(brightness, blended, extended, comp, int(max_stars))
        if measured is not None:
            keep_s = measured
    n_eligible = len(pi) - n_extended
    n_sat_eligible = int(np.count_nonzero(saturated & ~extended if n_extended else saturated))
    use = separable = separable_b = None
    if estimator == "fit":
        use = rawv < sat if valid is None else valid & (rawv < sat)  # the pixels the PSF fit uses
        if keep_s is not None:
            # the fit's form (separable products, or weights where a pixel is left out) is chosen on the whole
            # set, for the single stars and for the blended ones, so that a star's position does not depend on
            # which others are measured (the two forms agree to rounding, not bit for bit)
            separable, separable_b = bool(use.all()), bool(use[blended].all())
    if keep_s is not None:
        keep_s = _flatnonzero(keep_s)
        pi, pj, comp, area, saturated, blended = pi[keep_s], pj[keep_s], comp[keep_s], area[keep_s], \
            saturated[keep_s], blended[keep_s]
        peak_val, peak_raw, brightness, vals, rawv = peak_val[keep_s], peak_raw[keep_s], brightness[keep_s], \
            vals[keep_s], rawv[keep_s]
        g_ok, g_uv, g_s2, g_unsat = g_ok[keep_s], g_uv[keep_s], g_s2[keep_s], g_unsat[keep_s]
        if valid is not None:
            valid = valid[keep_s]
        if use is not None:
            use = use[keep_s]
    edge = np.zeros(len(pi), dtype=bool) if valid is None else ~valid.all(axis=(1, 2))
    d = np.arange(-h, h + 1, dtype=np.float64)
    X = pj[:, None, None] + d[None, None, :]
    Y = pi[:, None, None] + d[None, :, None]

    uv_cog = _cog(vals, X, Y, pi, pj) if estimator != "fit" else None
    if estimator == "cog":
        uv = uv_cog
    elif estimator == "gauss3":
        uv_iw = _iwcog_sep(vals, X, Y, uv_cog, s_eff, h, pi, pj, iterations)
        uv = np.where(g_unsat[:, None], g_uv, uv_iw)
    elif estimator == "iwcog":
        uv = _iwcog_sep(vals, X, Y, uv_cog, s_eff, h, pi, pj, iterations)
    else:
        # the fit of a star that looks like the PSF (its three-point fit worked and gave the PSF's width
        # to 30 %) starts from the three-point fit: it converges on the least-squares position the
        # reference reaches from its iwcog start, without the iwcog iterations; the others (saturated,
        # blended, JPEG blocks, noise) start from the iwcog position, as in the reference
        def iwcog_of(sel):  # the iwcog positions of the stars sel, from their own cog (each star's is its own)
            v_s, x_s, y_s, pi_s, pj_s = vals[sel], X[sel], Y[sel], pi[sel], pj[sel]
            return _iwcog_sep(v_s, x_s, y_s, _cog(v_s, x_s, y_s, pi_s, pj_s), s_eff, h, pi_s, pj_s, iterations)

        psf_like = g_unsat & (np.abs(g_s2 - s_eff * s_eff) < 0.3 * s_eff * s_eff)
        iw = _flatnonzero(~psf_like)
        start = g_uv.copy()
        if iw.size:
            start[iw] = iwcog_of(iw)
        uv, amp = _psf_fit_sep(vals, use, X, Y, start, psf_used, h, pi, pj, iterations, separable=separable)
        failed = _flatnonzero((amp <= 0) & psf_like)
        if failed.size:  # no fit: the iwcog position, as the reference gives
            uv[failed] = iwcog_of(failed)
        if blended.any():
            b = _flatnonzero(blended)
            uv_b = np.where(g_ok[b, None], g_uv[b], np.stack([pj[b], pi[b]], axis=1).astype(np.float64))
            frac = _psf_models(pj[b, None].astype(np.float64), pi[b, None].astype(np.float64), uv_b,
                               np.ones(len(b)), psf_used)[:, 0, 0]
            amp_b = peak_val[b] / np.maximum(frac, 1e-6)
            sa, sb = _pairs_within_groups(comp[b])  # (a, b) of one component, in meshgrid "ij" raveled order
            near = ((sa != sb)
                    & (np.abs(pi[b][sa] - pi[b][sb]) <= 2 * h + 1) & (np.abs(pj[b][sa] - pj[b][sb]) <= 2 * h + 1))
            sa, sb = sa[near], sb[near]
            vals = vals.copy()
            v_b, X_b, Y_b, use_b, pi_b, pj_b = vals[b], X[b], Y[b], use[b], pi[b], pj[b]  # (each read once)
            x_a, y_a = X_b[sa, 0, :], Y_b[sa, :, 0]
            for _round in range(3):
                vb = v_b.copy()
                if len(sa):
                    models = _psf_models(x_a, y_a, uv_b[sb], amp_b[sb], psf_used)
                    np.subtract.at(vb, sa, models)
                uv_b, amp_b = _psf_fit_sep(vb, use_b, X_b, Y_b, uv_b, psf_used, h, pi_b, pj_b, iterations,
                                           max_shift=1.5, separable=separable_b)
            uv[b] = uv_b
            vals[b] = vb
            brightness[b] = vb.sum(axis=(1, 2))  # (brightness is this call's own array)

    ratio = _axis_ratio_mm(vals, X[:, 0, :], Y[:, :, 0], uv, sigma)
    psnr = peak_val / sigma
    ratio_limit = max_axis_ratio + 0.5 * np.minimum(np.maximum((20.0 - psnr) / 10.0, 0.0), 1.0)
    elongated = (ratio > ratio_limit) & (psnr >= 10.0)
    order = (-brightness).argsort(kind="stable")
    if max_stars is not None:
        order = order[:int(max_stars)]
    return Centroids(
        uv=uv[order].astype(np.float64, copy=False), brightness=brightness[order].astype(np.float64, copy=False),
        peak=peak_raw[order].astype(np.float64, copy=False), n_pixels=area[order], saturated=saturated[order],
        elongated=elongated[order], edge=edge[order], blended=blended[order], axis_ratio=ratio[order],
        background_level=level, noise_sigma=sigma, threshold=thr, n_hot_pixels_rejected=n_hot,
        n_small_rejected=n_small, psf_sigma_px=psf_used, estimator=estimator, image_shape=(H, W),
        params=params, n_extended_rejected=n_extended - n_streaks, n_streaks_rejected=n_streaks,
        n_unmeasured=n_eligible - len(order),
        n_unmeasured_saturated=n_sat_eligible - int(np.count_nonzero(saturated[order])),
    )


STREAK_MIN_RATIO = 2.5  # a line: its second moments' axis ratio above this ...
STREAK_MAX_MINOR_VAR = 0.2  # ... and its variance across (px^2, a pixel's 1/12 added) below this ...
STREAK_MIN_PEAK = 20.0  # ... its peak this many sigma or more (a star's wings, 16 % of it or more, above 2 sigma)


@functools.lru_cache(maxsize=16)
def _moment_basis(h: int) -> np.ndarray:
    """(n^2, 6) the window's pixel offsets from its centre (n = 2h + 1, row-major): 1, dx, dy, dx^2, dy^2, dx dy."""
    d = np.arange(-h, h + 1, dtype=np.float64)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    dx, dy = dx.ravel(), dy.ravel()
    return np.stack([np.ones_like(dx), dx, dy, dx * dx, dy * dy, dx * dy], axis=1)


def _sharp_streaks(vals: np.ndarray, h: int, sigma: float) -> np.ndarray:
    """(N,) bool: which windows (N, 2h + 1, 2h + 1), background subtracted, centred on their blob's brightest
    pixel, hold a line narrower than any optics draws: a cosmic ray's track, a bad column, not a star. The
    pixels above 2 sigma weighted by their values: the variance across the blob's long axis, plus a pixel's
    1/12, below STREAK_MAX_MINOR_VAR (0.2 px^2: sigma 0.45 px) with an axis ratio above STREAK_MIN_RATIO. A
    star's light passes through the optics, so its variance across any axis is at least the PSF's sigma^2
    plus 1/6 (0.26 for a PSF of 0.3 px, sharper than any star tracker or lens is focused); a 1-pixel line's
    is 1/12 (0.083), 0.14 along an aliased diagonal. Satellite and star trails are drawn through the optics:
    as wide across as the PSF, not streaks. The caller judges only peaks of STREAK_MIN_PEAK sigma or more: on
    a fainter star of a sharp PSF (0.6 px) the pixels beside its core stay below 2 sigma, and two of them in a
    row would look like a line."""
    n_st = len(vals)
    if n_st == 0:
        return np.zeros(0, dtype=bool)
    w = np.where(vals > 2.0 * sigma, vals, 0.0).reshape(n_st, -1)
    m = w @ _moment_basis(h)
    s = m[:, 0]
    ok = s > 0
    s = np.where(ok, s, 1.0)
    mx, my = m[:, 1] / s, m[:, 2] / s
    cxx, cyy, cxy = m[:, 3] / s - mx * mx, m[:, 4] / s - my * my, m[:, 5] / s - mx * my
    half = 0.5 * (cxx + cyy) + 1.0 / 12.0
    disc = np.hypot(0.5 * (cxx - cyy), cxy)
    minor, major = half - disc, half + disc
    return ok & (minor < STREAK_MAX_MINOR_VAR) & (major > STREAK_MIN_RATIO ** 2 * np.maximum(minor, 1e-12))


def _pairs_within_groups(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every ordered pair (a, b) of indices with labels[a] == labels[b] (a == b included), in the order
    np.divmod(np.arange(n * n), n) lists them (a, then b): the pairs of the whole n x n grid that share a
    label, without the grid (a field split into thousands of blended peaks made it gigabytes)."""
    n = len(labels)
    if n == 0:
        e = np.zeros(0, dtype=np.int64)
        return e, e
    order = np.argsort(labels, kind="stable")
    sl = labels[order]
    starts = np.flatnonzero(np.r_[True, sl[1:] != sl[:-1]])
    sizes = np.diff(np.r_[starts, n])
    per = np.repeat(sizes, sizes)  # each element's group size
    a_sorted = np.repeat(np.arange(n), per)
    first = np.repeat(np.repeat(starts, sizes), per)
    offset = np.arange(len(a_sorted)) - np.repeat(np.cumsum(np.r_[0, per[:-1]]), per)
    a, b = order[a_sorted], order[first + offset]
    o = np.lexsort((b, a))
    return a[o], b[o]


def _brightest(brightness, blended, extended, comp, n: int) -> np.ndarray | None:
    """Which stars to measure so that the n brightest are among them (None: all that are not extended).

    An unblended star's window sum `brightness` is its final brightness. A blended one's is its window
    sum less its neighbours' fitted PSFs (positive amplitudes): at most its window sum. The n-th
    brightest of the final set is at least the n-th brightest unblended star's, so no star whose window
    sum is below that can be among the n; the stars of a blob are fitted together, so a blob with one
    blended star that can be among them is measured whole. The brightest-first order of what is
    measured, cut to n, is then the whole set's (a stable sort, ties kept in index order)."""
    eligible = ~extended
    unblended = eligible & ~blended
    n_unblended = int(np.count_nonzero(unblended))
    if int(np.count_nonzero(eligible)) <= n or n_unblended < n:
        return None
    nth = np.partition(brightness[unblended], n_unblended - n)[n_unblended - n]
    bright = brightness >= nth
    in_blend = eligible & blended
    ranks = np.zeros(int(comp.max()) + 1, dtype=bool)  # by blob label: a blended star of it can rank
    ranks[comp[in_blend & bright]] = True
    return (unblended & bright) | (in_blend & ranks[comp])


# ---------------------------------------------------------------------------- fast estimators
# The same estimators as _iwcog / _psf_fit, rearranged for speed (the fast path uses them; the
# reference keeps the originals): the Gaussian weight and the PSF model are separable, so sums run
# over rows and columns; the 3x3 normal equations are batched and solved in closed form; a star
# leaves the Gauss-Newton loop once its step, or the error its last two steps predict is left, is
# below _FIT_TOL (the reference always makes max(3, iterations) steps). From the same start, positions
# agree with the originals to ~1e-4 px.

_FIT_TOL = 1e-4  # px: the Gauss-Newton fit of a star stops once its step (or the error left) is below this


def _iwcog_sep(vals, X, Y, uv0, s_eff, h, pi, pj, iterations):
    """_iwcog with the separable weight exp(-dx^2/2s^2) exp(-dy^2/2s^2), u and v stepped together as
    one (n, 2) array, the weighted sums as batched products (the reference's positions to ~1e-13 px)."""
    XY = np.empty((len(X), 2, X.shape[2]))  # (n, 2, w): columns, rows
    XY[:, 0], XY[:, 1] = X[:, 0, :], Y[:, :, 0]
    k = -1.0 / (2.0 * s_eff * s_eff)
    uv = np.array(uv0, dtype=np.float64)
    lo = np.empty((len(uv), 2))  # the window: the peak pixel +- h (exact in float64)
    lo[:, 0], lo[:, 1] = pj, pi
    hi = lo + h
    lo -= h
    ok_all = None  # each star's weights positive at every step (None: all were)
    cg = np.empty_like(XY)
    for _ in range(iterations):
        g = XY - uv[:, :, None]
        np.square(g, out=g)
        g *= k
        np.exp(g, out=g)  # (n, 2, w): the weights along u and along v
        # sums over rows of vals * gy, over columns of vals * gx: batched products (einsum's sums)
        np.matmul(g[:, 1, None, :], vals, out=cg[:, 0, None, :])
        np.matmul(vals, g[:, 0, :, None], out=cg[:, 1, :, None])
        cg *= g
        s = cg[:, 0].sum(axis=1)
        if s.size and s.min() > 0:  # every window has weight (the usual case): the same step without the
            # masks (a NaN minimum fails the test, as (s > 0).all() fails)
            uv = uv + 2.0 * ((cg * XY).sum(axis=2) / s[:, None] - uv)  # gain 2: converges on a Gaussian's centre
        else:
            ok = s > 0
            ok_all = ok if ok_all is None else ok_all & ok
            c = (cg * XY).sum(axis=2) / np.where(ok, s, 1.0)[:, None]
            uv = np.where(ok[:, None], uv + 2.0 * (c - uv), uv)
        uv = np.minimum(np.maximum(uv, lo), hi)  # = np.clip, without its per-call overhead
    bad = ~np.isfinite(uv).all(axis=1)
    if ok_all is not None:
        bad |= ~ok_all
    if bad.any():
        uv[bad] = uv0[bad]
    return uv


_QV, _QU = np.array([0, 0, 1]), np.array([0, 1, 0])  # P, dP/du, dP/dv: v and u profile (0) or derivative (1)
# the adjugate of a symmetric 3 x 3 matrix from its 9 entries (row-major): rows r1 x r2, r2 x r0, r0 x r1
_ADJ3 = np.array([[4, 5, 3, 7, 8, 6, 1, 2, 0], [8, 6, 7, 2, 0, 1, 5, 3, 4],
                  [5, 3, 4, 8, 6, 7, 2, 0, 1], [7, 8, 6, 1, 2, 0, 4, 5, 3]])
# the Gram matrix of the unweighted separable model from each axis's 2 x 2 Gram of (profile, derivative):
# S[a, b] = (u factors of a . u factors of b) (v factors of a . v factors of b); the per-axis Grams come
# flattened as axis * 4 + kind_a * 2 + kind_b (axis 0 = u, 1 = v): the u then the v entries of S, row-major
_GUV = np.concatenate([(2 * _QU[:, None] + _QU[None, :]).ravel(), (4 + 2 * _QV[:, None] + _QV[None, :]).ravel()])


def _psf_fit_sep(vals, use, X, Y, uv0, s, h, pi, pj, iterations, max_shift=None, separable=None):
    """Least-squares fit of a pixel-integrated Gaussian PSF of sigma s (amplitude and position) to the
    windows `vals` (N, n, n), pixels where `use` is False left out (saturated, off the image), by
    Gauss-Newton from uv0 (steps limited to 0.5 px; the amplitude starts at its linear least-squares
    value): the reference's _psf_fit, computed on the separable model (the u and v profiles of all stars
    from one erf and one exp of their pixel edges, the normal equations from the two axes' Grams when no
    pixel is left out (else from one batched product), the 3 x 3 systems solved by their adjugates); a
    star stops once its step, or the error left after it (step^2 / (previous step - step): the rest of a
    geometric series with its last two steps' ratio), is below _FIT_TOL (near the minimum Gauss-Newton contracts by a small ratio, so a 1e-3 px step
    after a 0.05 px one leaves ~2e-5 px: the step that would only confirm it is not made).
    separable: use the separable products (every pixel of every window used) or the weighted ones; None
    chooses by `use`. (uv (N, 2), amplitude (N,)); where the fit fails, uv0 and amplitude 0."""
    n_st = len(vals)
    n = vals.shape[1]
    if n_st == 0:
        return np.zeros((0, 2)), np.zeros(0)
    edges = np.empty((n_st, 2, n + 1))  # (N, 2, n + 1) pixel edges along u and v
    edges[:, 0] = X[:, 0, :1]  # each window's first column and row
    edges[:, 1] = Y[:, :1, 0]
    edges += np.arange(n + 1) - 0.5
    if use.all() if separable is None else separable:  # no pixel left out (the usual case): no weights
        w = vw = None
    else:
        w = use.reshape(n_st, 1, n * n).astype(np.float64)
        vw = vals.reshape(n_st, n * n, 1) * w.reshape(n_st, n * n, 1)
    uv = np.array(uv0, dtype=np.float64)
    A = None
    k = 1.0 / (s * math.sqrt(2.0))
    # the profiles' and the derivatives' factors, by the first axis of T below
    scale = np.array([0.5, -1.0 / (s * math.sqrt(2.0 * math.pi))])[:, None, None, None]
    act = np.arange(n_st)
    prev = None  # each star's last step (px); None before the first
    with np.errstate(divide="ignore", invalid="ignore"):  # (a context: half the cost of two np.seterr calls)
        for _ in range(max(3, iterations)):
            m = act.size
            if m == 0:
                break
            every = m == n_st  # no star has stopped yet: no index copies
            z = ((edges if every else edges[act]) - (uv if every else uv[act])[:, :, None]) * k
            T = np.empty((2, m, 2, n + 1))  # [erf or exp][star][u or v] at the pixel edges (contiguous outputs)
            erf(z, out=T[0])
            z *= z
            np.negative(z, out=z)
            np.exp(z, out=T[1])
            Qk = T[:, :, :, 1:] - T[:, :, :, :-1]  # [profile or its derivative][star][u or v]
            Qk *= scale  # 0.5 (exact) and the Gaussian's scale c, after the differences (the same to rounding)
            Q = Qk.transpose(1, 2, 0, 3)  # (m, 2, 2, n): [u or v][profile or its derivative]
            if w is None:
                # no pixel left out: the model is separable, P = fv fu, dP/du = fv dfu, dP/dv = dfv fu, so
                # the Gram matrix is made of the two axes' 2 x 2 Grams (_GUV) and the products with the data
                # are (fv, dfv) V (fu, dfu)^T: the same sums as the (m, 3, n*n) products below, regrouped
                Q = np.ascontiguousarray(Q)  # (the products of the contiguous layout, as before)
                G = (Q @ Q.transpose(0, 1, 3, 2)).reshape(m, 8)[:, _GUV]
                S9 = G[:, :9] * G[:, 9:]
                B = Q[:, 1] @ ((vals if every else vals[act]) @ Q[:, 0].transpose(0, 2, 1))
                b = B.reshape(m, 4)[:, :3]  # (m, 3): P, dP/du, dP/dv with the data
            else:
                # (m, 3, n*n): P = fv fu, dP/du = fv dfu, dP/dv = dfv fu
                M = np.empty((m, 3, n, n))
                np.multiply(Q[:, 1, 0, None, :, None], Q[:, 0, :, None, :], out=M[:, :2])  # fv fu, fv dfu
                np.multiply(Q[:, 1, 1, :, None], Q[:, 0, 0, None, :], out=M[:, 2])  # dfv fu
                M = M.reshape(m, 3, n * n)
                S9 = ((M * (w if every else w[act])) @ M.transpose(0, 2, 1)).reshape(m, 9)  # weighted Gram
                b = (M @ (vw if every else vw[act]))[:, :, 0]  # (m, 3) weighted products with the data
            if A is None:
                A = b[:, 0] / S9[:, 0]  # the linear least-squares amplitude at uv0
            Aa = A if every else A[act]
            # S3 y = b for y = (A + dA, A du, A dv) (S3 x = b - A S3 e0 for x = (dA, A du, A dv), less
            # the residual's products): the new amplitude, and A times the step
            g = S9[:, _ADJ3]
            adj = (g[:, 0] * g[:, 1] - g[:, 2] * g[:, 3]).reshape(m, 3, 3)
            # the 3 x 3 products written out, element by element: a star's numbers do not depend on the
            # batch (a batched matmul sums differently when one star is left than when several are)
            y = adj[:, :, 0] * b[:, 0, None] + adj[:, :, 1] * b[:, 1, None] + adj[:, :, 2] * b[:, 2, None]
            y /= (S9[:, 0] * adj[:, 0, 0] + S9[:, 1] * adj[:, 0, 1] + S9[:, 2] * adj[:, 0, 2])[:, None]  # determinant
            y[:, 1:] /= Aa[:, None]  # (A + dA, du, dv)
            if not math.isfinite(float(y.sum())):  # a singular system or a zero amplitude: no step there
                bad = ~np.isfinite(y)
                y[:, 1:][bad[:, 1:]] = 0.0
                y[:, 0] = np.where(bad[:, 0], Aa, y[:, 0])
            d = y[:, 1:]
            np.minimum(np.maximum(d, -0.5, out=d), 0.5, out=d)
            # a star stops once its step, or the error its steps predict are left (the next steps of a
            # contraction with the ratio of its last two: step^2 / (previous step - step)), is below _FIT_TOL
            ad = np.abs(d)
            step = np.maximum(ad[:, 0], ad[:, 1])  # = ad.max(axis=1), without a reduction's overhead
            if prev is None:  # no previous step: the error left (step^2 / 1e-12) is above _FIT_TOL wherever step is
                go = step > _FIT_TOL
            else:  # the stop test on Python numbers (the same float64 operations, on a few dozen stars)
                go = [st > _FIT_TOL and st * st / max(pv - st, 1e-12) > _FIT_TOL
                      for st, pv in zip(step.tolist(), (prev if every else prev[act]).tolist())]
            if every:  # the same updates without the index copies (always after the first step)
                A = y[:, 0]
                uv += d
                prev = step
            else:
                A[act] = y[:, 0]
                uv[act] += d
                prev[act] = step
            act = act[go]
    lim = h if max_shift is None else max_shift
    # a finite positive amplitude and a finite position within lim of the peak (NaN and infinities fail
    # these comparisons: no separate isfinite)
    ok = (A > 0) & (A < np.inf) & (np.abs(uv[:, 0] - pj) <= lim) & (np.abs(uv[:, 1] - pi) <= lim)
    if ok.all():  # (the usual case: uv and A are this call's own arrays)
        return uv, A
    return np.where(ok[:, None], uv, uv0), np.where(ok, A, 0.0)


def _split_blends_px(px, H, W, bkg, resid, idx, lab, val, raw, comp, area, pi, pj, sigma, sat, nb_max, hot,
                     min_sep=2.5, max_area=1000, max_peaks=8):
    """_split_blends reading through a _Pixels (same rules, same results). nb_max: the largest of each
    pixel's 8 neighbours read before the hot pixels `hot` (sorted flat indices, or None) were repaired;
    read again for the pixels next to one."""
    big = comp[(area >= 6) & (area <= max_area)]
    if big.size == 0:
        return None
    is_big = np.zeros(int(lab.max()) + 1, dtype=bool)  # a lookup table by label
    is_big[big] = True
    nbm = nb_max
    if hot is not None:
        # the pixels of idx (sorted) next to a hot one: the few neighbours looked up in idx, not idx in them
        near_hot = (hot[:, None] + _ring_offsets(W, False)).ravel()
        pos = idx.searchsorted(near_hot)
        np.minimum(pos, idx.size - 1, out=pos)
        hit = idx[pos] == near_hot
        if hit.any():
            redo = np.unique(pos[hit])  # ascending, each once (two hot pixels can share a neighbour)
            nbm = nb_max.copy()
            nbm[redo] = _neighbour_max(px, H, W, bkg, resid, idx[redo])
    # the local maxima of the blobs looked at, in index order: only those pixels are read further
    cand = _flatnonzero(is_big[lab] & (val >= nbm) & (raw < sat))
    if cand.size == 0:
        return None
    dipped = _dipped_peaks if cand.size > _WALK_MAX_CANDIDATES else _dipped_peaks_walk
    return dipped(px, W, bkg, resid, idx[cand], val[cand], raw[cand], lab[cand], comp, pi, pj, sigma, min_sep,
                  max_peaks)


_WALK_MAX_CANDIDATES = 256  # candidate maxima up to which the walk in Python numbers is the faster form (143: 55 us
# against 80 us batched; 1090: 1.57 ms against 0.39 ms)


def _dipped_peaks_walk(px, W, bkg, resid, c_flat, c_val, c_raw, c_lab, comp, pi, pj, sigma, min_sep, max_peaks):
    """`_dipped_peaks` one candidate at a time, in Python numbers (a sparse frame's few candidates, where numpy's
    per-call cost dominates): each blob by label, its local maxima brightest first (ties in index order), each
    tested against the blob's accepted peaks as they stand."""
    c_flat, c_val, c_raw = c_flat.tolist(), c_val.tolist(), c_raw.tolist()
    blobs = {}
    for q, L in enumerate(c_lab.tolist()):
        blobs.setdefault(L, []).append(q)
    k_of = {L: k for k, L in enumerate(comp.tolist())}
    pil, pjl = pi.tolist(), pj.tolist()
    out = []
    for L in sorted(blobs):
        m = blobs[L]
        k0 = k_of[L]
        if len(m) == 1 and c_flat[m[0]] == pil[k0] * W + pjl[k0]:
            continue  # the blob's only local maximum is its peak: nothing to split
        acc = [(pil[k0], pjl[k0])]
        for q in sorted(m, key=lambda q: -c_val[q]):  # brightest first, ties in index order (a stable sort)
            if len(acc) >= max_peaks:
                break
            (i, j), v = divmod(c_flat[q], W), c_val[q]
            d = [math.hypot(i - a, j - b) for a, b in acc]
            n_near = min(range(len(d)), key=d.__getitem__)  # np.argmin(d): the first nearest
            if d[n_near] < min_sep:
                continue
            a, b = acc[n_near]
            t = np.linspace(0.0, 1.0, int(math.ceil(2 * d[n_near])) + 1)
            si = np.rint(i + t * (a - i)).astype(np.int64)
            sj = np.rint(j + t * (b - j)).astype(np.int64)
            seg = resid[si, sj] if resid is not None else px.take(si * W + sj) - bkg
            if v - float(seg.min()) >= max(3.0 * sigma, 0.2 * v):
                acc.append((i, j))
                out.append((L, i, j, v, c_raw[q]))
    if not out:
        return None
    o = np.array(out, dtype=np.float64)
    return o[:, 0].astype(np.int64), o[:, 1].astype(np.int64), o[:, 2].astype(np.int64), o[:, 3], o[:, 4]


def _dipped_peaks(px, W, bkg, resid, c_flat, c_val, c_raw, c_lab, comp, pi, pj, sigma, min_sep, max_peaks):
    """The secondary peaks of _split_blends_px from its candidates (each blob's local maxima, in index order):
    the walk (`_dipped_peaks_walk`), every blob at once. Each blob takes its candidates brightest first (ties in index
    order); a candidate at least min_sep from the blob's accepted peaks (its peak first) is accepted when the
    lowest pixel on the line to the nearest of them (np.linspace's points, rounded) lies max(3 sigma, 20 %) of
    it below it; at most max_peaks a blob. Round r looks at every blob's r-th candidate at once (each blob's
    accepted peaks depend only on its earlier candidates): the same distances (square roots of whole numbers),
    points, pixels and comparisons as the walk one candidate at a time. (components, rows, columns, values,
    raw values) in the walk's order (blobs by label, then as accepted), or None."""
    order = np.lexsort((np.arange(c_flat.size), -c_val, c_lab))  # by blob, brightest first, ties in index order
    c_flat, c_val, c_raw, c_lab = c_flat[order], c_val[order].astype(np.float64), c_raw[order], c_lab[order]
    first = np.flatnonzero(np.r_[True, c_lab[1:] != c_lab[:-1]])  # each blob's first candidate
    count = np.diff(np.r_[first, c_lab.size])
    k_of = np.empty(int(comp.max()) + 1, dtype=np.int64)
    k_of[comp] = np.arange(comp.size)
    k0 = k_of[c_lab[first]]
    peak_i, peak_j = pi[k0].astype(np.int64), pj[k0].astype(np.int64)
    # a blob whose only local maximum is its peak: nothing to split
    live = ~((count == 1) & (c_flat[first] == peak_i * W + peak_j))
    n_b = first.size
    acc_i = np.zeros((n_b, max_peaks), dtype=np.int64)
    acc_j = np.zeros((n_b, max_peaks), dtype=np.int64)
    acc_i[:, 0], acc_j[:, 0] = peak_i, peak_j
    n_acc = np.ones(n_b, dtype=np.int64)
    slot = np.arange(max_peaks)
    taken = []  # (blob, round, candidate) of each accepted peak
    for r in range(int(count.max()) if n_b else 0):
        b = np.flatnonzero(live & (count > r) & (n_acc < max_peaks))
        if b.size == 0:
            continue
        q = first[b] + r
        i, j = c_flat[q] // W, c_flat[q] % W
        d2 = (i[:, None] - acc_i[b]) ** 2 + (j[:, None] - acc_j[b]) ** 2  # whole numbers
        d2 = np.where(slot[None, :] < n_acc[b, None], d2, np.iinfo(np.int64).max)
        near = d2.argmin(axis=1)  # the first nearest
        d = np.sqrt(d2[np.arange(b.size), near].astype(np.float64))
        far = d >= min_sep
        if not far.any():
            continue
        b, q, i, j, near, d = b[far], q[far], i[far], j[far], near[far], d[far]
        a_i, a_j = acc_i[b, near], acc_j[b, near]
        # np.linspace(0, 1, n) of each line: k (1 / (n - 1)), its last point 1 exactly
        n_pts = np.ceil(2.0 * d).astype(np.int64) + 1
        ends = np.cumsum(n_pts)
        starts = ends - n_pts
        k = np.arange(ends[-1]) - np.repeat(starts, n_pts)
        t = k * np.repeat(1.0 / (n_pts - 1), n_pts)
        t[ends - 1] = 1.0
        ii, jj = np.repeat(i, n_pts), np.repeat(j, n_pts)
        si = np.rint(ii + t * (np.repeat(a_i, n_pts) - ii)).astype(np.int64)
        sj = np.rint(jj + t * (np.repeat(a_j, n_pts) - jj)).astype(np.int64)
        seg = resid.reshape(-1)[si * W + sj] if resid is not None else px.take(si * W + sj) - bkg
        low = np.minimum.reduceat(seg, starts).astype(np.float64)
        v = c_val[q]
        ok = v - low >= np.maximum(3.0 * sigma, 0.2 * v)
        if ok.any():
            b, q = b[ok], q[ok]
            acc_i[b, n_acc[b]], acc_j[b, n_acc[b]] = c_flat[q] // W, c_flat[q] % W
            n_acc[b] += 1
            taken.append(np.stack([b, np.full(b.size, r), q]))
    if not taken:
        return None
    t_b, _, t_q = np.concatenate(taken, axis=1)[:, np.lexsort(np.concatenate(taken, axis=1)[[1, 0]])]
    return (c_lab[t_q].astype(np.int64), (c_flat[t_q] // W).astype(np.int64), (c_flat[t_q] % W).astype(np.int64),
            c_val[t_q], c_raw[t_q].astype(np.float64))


# ============================================================================ helpers


def _cog(vals, X, Y, pi, pj):
    w = np.maximum(vals, 0.0)
    sw = w.sum(axis=(1, 2))
    ok = sw > 0
    uv = np.empty((len(w), 2))
    if ok.all():  # (the usual case: the same numbers without the masks)
        uv[:, 0] = (w * X).sum(axis=(1, 2)) / sw
        uv[:, 1] = (w * Y).sum(axis=(1, 2)) / sw
        return uv
    sw = np.where(ok, sw, 1.0)
    uv[:, 0] = np.where(ok, (w * X).sum(axis=(1, 2)) / sw, pj)
    uv[:, 1] = np.where(ok, (w * Y).sum(axis=(1, 2)) / sw, pi)
    return uv


# -2 x the log-parabola's curvature and minus its slope: t = 2 (2 lg1 - lg0 - lg2), e = lg2 - lg0
_G3_STENCIL_NEG = np.array([[-2.0, -1.0], [4.0, 0.0], [-2.0, 1.0]])


def _gauss3_fast(vals, h, pi, pj):
    """`centroid_reference._gauss3` without an error-state switch: the curvature and slope come negated
    and doubled (t = -2 c, exact), so the offset e / t and sigma^2 = 1/t_u + 1/t_v are the same
    numbers; t is kept >= 1e-300 (no division by zero: a star with t <= 0 fails the test anyway) and
    the test c < 0 and |d| < 1 reads |e| < t."""
    n_st = len(vals)
    c = vals[:, h - 1: h + 2, h - 1: h + 2]
    m = np.empty((n_st, 2, 3))
    c.sum(axis=1, out=m[:, 0])  # along u
    c.sum(axis=2, out=m[:, 1])  # along v
    good = np.empty((n_st, 8), dtype=bool)  # the 6 marginals positive, then |e| < t on both axes
    pos = good[:, :6].reshape(n_st, 2, 3)
    np.greater(m, 0.0, out=pos)
    cs = np.log(np.where(pos, m, 1.0)) @ _G3_STENCIL_NEG  # (N, 2, 2): t and e of both axes
    ct, e = cs[:, :, 0], cs[:, :, 1]
    np.less(np.abs(e), ct, out=good[:, 6:])
    ok = good.all(axis=1)
    t = np.maximum(ct, 1e-300)
    d = e / t
    inv = 1.0 / t
    uv = np.empty((n_st, 2))
    uv[:, 0], uv[:, 1] = pj, pi
    uv += np.where(ok[:, None], d, 0.0)
    return ok, uv, np.where(ok, inv[:, 0] + inv[:, 1], np.nan)


def _axis_ratio_mm(vals, x, y, uv, sigma):
    """`centroid_reference._axis_ratio` from one chain of batched products: with Dx = (1, dx, dx^2) by
    column (x: (N, n) column coordinates) and Dy = (1, dy, dy^2) by row, Dy w Dx^T holds every moment
    (sum w, sum w dx^2, sum w dy^2, sum w dx dy); the half-difference of the eigenvalues by np.hypot.
    The same sums in another order: the same ratio to ~1e-15 relative."""
    w = np.where(vals > 2.0 * sigma, vals, 0.0)
    n_st, n = x.shape
    D = np.empty((n_st, 2, 3, n))  # [u or v][1, d, d^2]
    D[:, :, 0] = 1.0
    np.subtract(x, uv[:, 0, None], out=D[:, 0, 1])
    np.subtract(y, uv[:, 1, None], out=D[:, 1, 1])
    np.square(D[:, :, 1], out=D[:, :, 2])
    m = (D[:, 1] @ w @ D[:, 0].transpose(0, 2, 1)).reshape(n_st, 9)  # [dy power * 3 + dx power]
    s = m[:, 0]
    ok = s > 0
    every = bool(ok.all())  # (the usual case: no masks)
    q = m[:, _MOMENTS] / (s if every else np.where(ok, s, 1.0))[:, None]  # mxx, myy, mxy less the pixel's 1/12
    half_tr = (q[:, 0] + q[:, 1]) * 0.5 + 1.0 / 12.0
    disc = np.hypot((q[:, 0] - q[:, 1]) * 0.5, q[:, 2])
    l2 = np.maximum(half_tr - disc, 1e-12)
    ratio = np.sqrt((half_tr + disc) / l2)
    return ratio if every else np.where(ok, ratio, np.nan)


_MOMENTS = np.array([2, 6, 4])  # sum w dx^2, sum w dy^2, sum w dx dy in _axis_ratio_mm's 3 x 3 moments


def _is_adc_max(x: float) -> bool:
    """x is 2^k - 1 for an ADC of 8 to 16 bits."""
    return any(x == (1 << k) - 1 for k in range(8, 17))


def _psf_models(x, y, uv, A, s):
    """(M, ny, nx) pixel-integrated Gaussians of amplitudes A (M,) centred at uv (M, 2), each on
    its own grid of columns x (M, nx) by rows y (M, ny)."""
    k = 1.0 / (s * math.sqrt(2.0))
    fu = 0.5 * (erf((x + 0.5 - uv[:, :1]) * k) - erf((x - 0.5 - uv[:, :1]) * k))
    fv = 0.5 * (erf((y + 0.5 - uv[:, 1:]) * k) - erf((y - 0.5 - uv[:, 1:]) * k))
    return A[:, None, None] * fv[:, :, None] * fu[:, None, :]


