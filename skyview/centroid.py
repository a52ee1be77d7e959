"""Image -> star centroids with OpenCV: background, noise, detection, sub-pixel position, flags.

(Longer than skyview's other modules: the fast path below and the shared estimators are one algorithm
that is timed per stage; the former, simpler implementation it is tested against is in
`skyview.centroid_reference`.)

Pixel convention (DESIGN.md): pixel centres at integer coordinates, (0, 0) the centre of the
top-left pixel; u = column (x, right), v = row (y, down).

Steps of `detect_centroids`:

1. Background: median of 64 px blocks (sampled every 4th pixel), bilinear map between block centres
   extrapolated linearly to the borders; a single level when no block departs from it by more than
   0.5 sigma or than the blocks' own noise (the usual case, and the fast one). Noise sigma: 1.4826 x MAD of the
   background-subtracted samples, refined by a 3.5-sigma clipped standard deviation (which stays
   right on integer images whose noise is ~1 ADU, where the MAD is quantised).
2. Detection: pixels above background + k_sigma * sigma. A pixel above it whose 8 neighbours all
   stay near the background (below max(3 sigma, 15 % of it)) is a hot pixel: counted, removed
   from the mask and repaired with its neighbours' median, so it neither becomes a star nor pulls
   the centroid of a faint star it touches (this assumes a PSF sigma of at least ~0.5 px, as star
   trackers defocus to get). Then 8-connected components (cv2.connectedComponentsWithStats); blobs
   smaller than min_pixels are dropped; a blob with several separated peaks is split (deblend).
3. Position in a window around each blob's brightest pixel (side 2*ceil(2.5 sigma_eff) + 1, 7 px for
   the default PSF), background subtracted. Estimators (`estimator=`):
   "fit" (default): least-squares fit of a pixel-integrated Gaussian PSF (amplitude and position,
   width fixed to the PSF sigma measured from the image), Gauss-Newton from the iwcog position;
   saturated pixels and pixels off the image are left out, so saturated and edge stars keep an
   unbiased centre;
   "iwcog": iteratively Gaussian-weighted centre of gravity, each step scaled by
   (sigma_psf^2 + sigma_w^2) / sigma_w^2 so that it converges on the centre of a Gaussian PSF;
   "cog": plain centre of gravity of the positive background-subtracted intensity;
   "gauss3": three-point Gaussian (log-parabola) fit on the 3x3 marginals, falling back to "iwcog"
   when a value is not positive or the star is saturated.
   skyview.centroid_bench measures them on the same images (100 fields, 8 deg, 1024 px, default
   SensorModel): RMS per axis at SNR >= 20 is 0.056 px for "fit", 0.063 iwcog, 0.095 cog, 0.096
   gauss3; "fit" is the best in every SNR bin (iwcog suffers at saturated and edge stars).
4. Brightness = summed background-subtracted intensity in the window; peak = highest raw pixel
   value; flags: saturated (a pixel at the ADC maximum of the dtype, at `saturation_level`, or at
   the image's top value when that value forms a plateau), elongated (second-moment axis ratio above
   max_axis_ratio for blobs with peak >= 20 sigma, above max_axis_ratio + 0.5 at 10 sigma, not
   judged below: blends and streaks), edge (window crosses the border). Sorted by brightness, brightest first.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.special import erf

from skyview.errors import BadInput

ESTIMATORS = ("fit", "iwcog", "cog", "gauss3")
DEFAULT_ESTIMATOR = "fit"
_MAD_TO_SIGMA = 1.4826
MIN_EXTENDED_PX = 400  # a blob is "extended" above max(this, EXTENDED_PSF_AREAS x the PSF's 3-sigma disk)
EXTENDED_PSF_AREAS = 40.0
_CLIP_K = 3.5
# std of a unit normal truncated to +-3.5 sigma
_CLIP_STD = math.sqrt(1.0 - 2 * _CLIP_K * math.exp(-_CLIP_K ** 2 / 2) / math.sqrt(2 * math.pi) / math.erf(_CLIP_K / math.sqrt(2)))


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
    psf_sigma_px: float = float("nan")  # PSF sigma used by iwcog (measured or given)
    estimator: str = DEFAULT_ESTIMATOR
    image_shape: tuple[int, int] = (0, 0)
    params: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.uv.shape[0])

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


def load_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file (PNG, TIFF, JPEG, ... anything cv2 decodes, and FITS) unchanged in depth, as grey.

    Raises BadInput with one line for a missing file, a directory, an empty file, a file OpenCV
    cannot decode and an image of size 0.
    """
    p = Path(path)
    if not p.exists():
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
    if data[:9].tobytes() == b"SIMPLE  =":  # FITS (skyview.fits_image: rows turned to top-first)
        from skyview.fits_image import read_fits
        return finite_image(read_fits(p, max_image_pixels())[0], f"image {p}")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None:
        raise BadInput(f"{p} is not an image OpenCV can read")
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


def _kth_of_two_sorted(a: np.ndarray, b: np.ndarray, k: int):
    """The k-th smallest (0-based) element of the union of two sorted 1-D arrays (a bisection on
    how many come from a: O(log n) scalar steps, no merge)."""
    lo, hi = max(0, k + 1 - b.size), min(k + 1, a.size)
    while lo < hi:
        i = (lo + hi) // 2
        if a[i] < b[k - i]:
            lo = i + 1
        else:
            hi = i
    j = k + 1 - lo
    if lo == 0:
        return b[j - 1]
    if j == 0:
        return a[lo - 1]
    return max(a[lo - 1], b[j - 1])


def _median_abs_dev_sorted(rs: np.ndarray, med) -> np.ndarray:
    """_median_sorted(np.sort(np.abs(rs - med))) of a sorted 1-D array, without the second sort: the
    deviations below the median (med - rs, read backwards) and above it (rs - med) are two sorted runs
    (|x - m| and m - x are the same float), whose middle element(s) a bisection finds; the same value."""
    p = int(np.searchsorted(rs, med, side="left"))
    below = med - rs[:p][::-1]
    above = rs[p:] - med
    n = rs.size
    if n % 2:
        return _kth_of_two_sorted(below, above, n // 2)
    lo = _kth_of_two_sorted(below, above, n // 2 - 1)
    hi = _kth_of_two_sorted(below, above, n // 2)
    return (lo + hi) / rs.dtype.type(2)


def _background_stats(f: np.ndarray, block: int = 64):
    """(grid, block height, block width, sample step, level, sigma, flat) of a 2-D image of any real
    dtype: the statistics of `_estimate_background_reference` computed from the sub-sampled pixels
    only (converted to float32, as the reference sees them) with sorts instead of np.median
    (SIMD sorts are several times faster than the partitions np.median does); the same numbers."""
    H, W = f.shape
    step = 4 if min(H, W) >= 256 else (2 if min(H, W) >= 64 else 1)
    off = step // 2
    sub = f[off::step, off::step].astype(np.float32)
    sh, sw = sub.shape
    bs = max(4, block // step)
    gh, gw = max(1, sh // bs), max(1, sw // bs)
    by, bx = sh // gh, sw // gw
    cells = sub[: gh * by, : gw * bx].reshape(gh, by, gw, bx).transpose(0, 2, 1, 3).reshape(gh, gw, by * bx)
    grid = _median_sorted(np.sort(cells, axis=2)).astype(np.float32)
    level = float(_median_sorted(np.sort(grid, axis=None)))  # = np.median(grid), without its overhead
    if gh * gw > 1:
        r = (sub - _upsample(grid, by, bx, sh, sw)).ravel()
    else:
        r = (sub - level).ravel()
    rs = np.sort(r)
    med = _median_sorted(rs)
    mad = float(_median_abs_dev_sorted(rs, med))
    s0 = _MAD_TO_SIGMA * mad
    is_int = f.dtype.kind in "ui" or bool(np.all(np.floor(sub) == sub))
    floor = 1.0 if is_int else max(1e-12, 1e-9 * float(np.abs(sub).max()))
    clip = _CLIP_K * max(s0, floor)
    rc = r[np.abs(r) <= clip]
    sigma = float(rc.std()) / _CLIP_STD if rc.size > 10 else s0
    sigma = max(sigma, 0.5 if is_int else floor)
    tol = max(0.5 * sigma, 4.5 * 1.2533 * sigma / math.sqrt(by * bx), 1.0 if is_int else 0.0)
    flat = gh * gw == 1 or float(np.abs(grid - level).max()) <= tol
    return grid, by * step, bx * step, level, sigma, flat


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


def _upsample(grid: np.ndarray, by: int, bx: int, H: int, W: int) -> np.ndarray:
    """(H, W) map from block values at block centres ((i + 0.5) * by - 0.5, (j + 0.5) * bx - 0.5):
    bilinear between centres, linear extrapolation beyond the outer ones (one extra ring of blocks
    extrapolated from the outer two, then cv2.resize and crop)."""
    g = grid.astype(np.float32)
    if g.shape[0] > 1:
        g = np.vstack([2 * g[:1] - g[1:2], g, 2 * g[-1:] - g[-2:-1]])
    else:
        g = np.vstack([g, g, g])
    if g.shape[1] > 1:
        g = np.hstack([2 * g[:, :1] - g[:, 1:2], g, 2 * g[:, -1:] - g[:, -2:-1]])
    else:
        g = np.hstack([g, g, g])
    big = cv2.resize(g, (g.shape[1] * bx, g.shape[0] * by), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(big[by: by + H, bx: bx + W])


# ============================================================================ detection


# ============================================================================ detection (fast path)

_NATIVE_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.int16))  # exact in float32, cv2-native
_SPARSE_LABEL_MAX = 4000  # above-threshold pixels labelled as a graph; more: cv2.connectedComponents
_GATHER_HOT_MAX = 20000  # above: hot-pixel test with a ring max filter (as the reference)


class _Pixels:
    """Pixel values of an image, read as float32 (as the reference's float32 copy holds them), with
    the repaired hot pixels patched in: no full-frame copy of a native uint8/uint16/int16 image."""

    __slots__ = ("flat", "hp", "hv")

    def __init__(self, f: np.ndarray):
        self.flat = f.reshape(-1)
        self.hp = None  # sorted flat indices of repaired pixels
        self.hv = None  # their float32 values

    def take(self, fi: np.ndarray) -> np.ndarray:
        v = self.flat[fi].astype(np.float32)
        if self.hp is not None:
            pos = np.searchsorted(self.hp, fi)
            np.minimum(pos, len(self.hp) - 1, out=pos)
            hit = self.hp[pos] == fi
            if hit.any():
                v[hit] = self.hv[pos[hit]]
        return v


def _gather_px(px, H, W, bkg, resid, pi, pj, h):
    """_gather reading through a _Pixels: (values - background (0 off the image), on-image mask, raw)."""
    d = np.arange(-h, h + 1)
    n = len(pi)
    if n and pi.min() >= h and pi.max() < H - h and pj.min() >= h and pj.max() < W - h:
        # every window inside the image (the usual case): no clipping, no masking
        valid = np.ones((n, 2 * h + 1, 2 * h + 1), dtype=bool)
        fi = (pi * W + pj)[:, None, None] + (d[:, None] * W + d[None, :])[None]
        raw = px.take(fi).astype(np.float64)
        vals = resid.reshape(-1)[fi].astype(np.float64) if resid is not None else raw - bkg
        return vals, valid, raw
    rows = pi[:, None, None] + d[None, :, None]
    cols = pj[:, None, None] + d[None, None, :]
    valid = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)
    fi = np.clip(rows, 0, H - 1) * W + np.clip(cols, 0, W - 1)
    raw = px.take(fi).astype(np.float64)
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
    k = np.flatnonzero(inner)
    if k.size:
        offs = np.array([-W - 1, -W, -W + 1, -1, 1, W - 1, W, W + 1], dtype=np.int64)
        nf = fi[k][:, None] + offs
        v = (resid.reshape(-1)[nf] if resid is not None else px.take(nf)).max(axis=1).astype(np.float64)
        out[k] = v if resid is not None else v - bkg
    b = np.flatnonzero(~inner)
    if b.size:
        nb = _gather_px(px, H, W, bkg, resid, i[b], j[b], 1)[0]
        nb[:, 1, 1] = -np.inf
        out[b] = nb.reshape(b.size, -1).max(axis=1)
    return out


def _label_sparse(idx: np.ndarray, W: int) -> tuple[np.ndarray, int]:
    """8-connected labels (1..n) of the pixels at sorted flat indices idx of a width-W image, numbered
    in raster order of each component's first pixel; (labels, n + 1) like cv2's count."""
    n = idx.size
    col = idx % W
    heads, tails = [], []
    for off, side in ((1, 1), (W - 1, -1), (W, 0), (W + 1, 1)):  # right, below-left, below, below-right
        tgt = idx + off
        pos = np.searchsorted(idx, tgt)
        np.minimum(pos, n - 1, out=pos)
        ok = idx[pos] == tgt
        if side > 0:
            ok &= col < W - 1
        elif side < 0:
            ok &= col > 0
        heads.append(np.flatnonzero(ok))
        tails.append(pos[ok])
    a = np.concatenate(heads).astype(np.int64)
    b = np.concatenate(tails).astype(np.int64)
    # union-find by label propagation with pointer jumping: each link pulls both ends down to the
    # smaller root until no link joins two roots (a few rounds for star-sized blobs)
    root = np.arange(n, dtype=np.int64)
    while a.size:
        ra, rb = root[a], root[b]
        diff = ra != rb
        if not diff.any():
            break
        ra, rb = ra[diff], rb[diff]
        lo, hi = np.minimum(ra, rb), np.maximum(ra, rb)
        np.minimum.at(root, hi, lo)
        while True:  # compress: every pixel points at its root
            nxt = root[root]
            if np.array_equal(nxt, root):
                break
            root = nxt
    _, labels = np.unique(root, return_inverse=True)
    k = int(labels.max()) + 1 if n else 0
    # number the components as cv2 does (provisional labels per 2x2 block, in raster order of the
    # blocks: rows in pairs, columns in pairs), so that ties in brightness keep the reference order
    key = (idx // W // 2) * W + col // 2
    first = np.full(k, np.iinfo(np.int64).max)
    np.minimum.at(first, labels, key)
    rank = np.empty(k, dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(1, k + 1)
    return rank[labels], int(k) + 1


def _above(f: np.ndarray, t32: np.float32) -> np.ndarray:
    """f > t32 (f as float32), on the native array: an integer image is compared with floor(t32)."""
    if f.dtype.kind in "ui" and math.isfinite(float(t32)):
        info = np.iinfo(f.dtype)
        ti = math.floor(float(t32))
        if ti >= info.max:
            return np.zeros(f.shape, dtype=bool)
        if ti < info.min:
            return np.ones(f.shape, dtype=bool)
        return f > f.dtype.type(ti)
    return f > t32 if f.dtype == np.float32 else f.astype(np.float32) > t32


def detect_centroids(image: np.ndarray, *, k_sigma: float = 5.0, window: int | None = None, min_pixels: int = 2,
                     estimator: str = DEFAULT_ESTIMATOR, psf_sigma_px: float | None = None,
                     saturation_level: float | None = None, max_axis_ratio: float = 1.4,
                     background_block: int = 64, iterations: int = 6, deblend: bool = True) -> Centroids:
    """Find stars in a 2-D image and measure their sub-pixel centroids (see the module docstring).

    window: odd side of the square measurement window (pixels) around each blob's brightest pixel;
    None picks 2*ceil(2.5 sigma_eff) + 1 from the measured PSF (sigma_eff^2 = sigma^2 + 1/12).
    psf_sigma_px: PSF sigma for the fit and iwcog; None measures it from the bright stars
    (3-point log-curvature), falling back to 1.2 px. A blank (constant) image gives zero centroids.
    A colour (BGR/BGRA) image is converted to grey; any other non-2-D array is BadInput.
    deblend: split a blob with several peaks (each >= 2.5 px from a brighter one, with a dip of at
    least 20 % and 3 sigma between them) into one centroid per peak, flagged `blended`; with the
    "fit" estimator each one is refitted after subtracting its neighbours' fitted PSFs.

    Same detections, flags and statistics as `_detect_centroids_reference` (the former
    implementation), positions within 1e-4 px (the PSF fit of a star stops once its steps are below
    that), computed without a float copy of a uint8/uint16/int16 frame: background statistics from
    the sub-sampled pixels (one sort; the MAD read from the two sorted runs of deviations), a scalar
    threshold on the native image when the background is flat, only the above-threshold pixels
    labelled (union-find over their 8-neighbour links; a full-frame cv2.connectedComponents when
    there are many), hot pixels patched on read instead of in a copy.
    """
    if estimator not in ESTIMATORS:
        raise BadInput(f"unknown centroid estimator {estimator!r}: choose one of {', '.join(ESTIMATORS)}")
    if window is not None and (int(window) < 3 or int(window) % 2 == 0):
        raise BadInput(f"window={window} must be an odd number >= 3")
    if not (k_sigma > 0):
        raise BadInput(f"k_sigma={k_sigma} must be positive")
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
    dtype_max = float(np.iinfo(img.dtype).max) if img.dtype.kind in "ui" else math.inf

    grid, gby, gbx, level, sigma, flat = _background_stats(f, background_block)
    thr = float(k_sigma) * sigma
    if flat:
        bkg, resid = level, None
        mask = _above(f, np.float32(bkg + thr))
    else:
        bkg = _upsample(grid, gby, gbx, H, W)
        resid = np.subtract(f, bkg, dtype=np.float32)
        mask = resid > np.float32(thr)
    empty = dict(background_level=level, noise_sigma=sigma, threshold=thr, estimator=estimator,
                 image_shape=(H, W), params=params)
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        # a constant image has no pixel above the threshold: told apart here, not by a full-frame pass first
        fmin, fmax, _, _ = cv2.minMaxLoc(f)  # f: uint8 / uint16 / int16 or float32
        if fmax == fmin:
            return Centroids.empty(background_level=float(fmin), noise_sigma=0.0, estimator=estimator,
                                   image_shape=(H, W), params=params)
        return Centroids.empty(**empty)
    px = _Pixels(f)
    # hot pixels (see the reference): counted, taken out of the mask, repaired on read
    if idx.size <= _GATHER_HOT_MAX:
        nb_max = _neighbour_max(px, H, W, bkg, resid, idx)
        centre = (px.take(idx).astype(np.float64) - bkg if resid is None
                  else resid.reshape(-1)[idx].astype(np.float64))
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
    n_hot = int(hotpix.sum())
    if n_hot:
        hp = idx[hotpix]
        nb_raw = _gather_px(px, H, W, bkg, resid, hp // W, hp % W, 1)[2]
        ring = np.delete(nb_raw.reshape(n_hot, 9), 4, axis=1)
        repaired = np.median(ring, axis=1).astype(np.float32)
        px.hp, px.hv = hp, repaired
        if resid is not None:
            resid.reshape(-1)[hp] = repaired - bkg.reshape(-1)[hp]
        mask.reshape(-1)[hp] = False
        idx = idx[~hotpix]
    empty["n_hot_pixels_rejected"] = n_hot
    if idx.size == 0:
        return Centroids.empty(**empty)
    if idx.size <= _SPARSE_LABEL_MAX:
        lab, n_lab = _label_sparse(idx, W)
    else:
        n_lab, labels = cv2.connectedComponents(mask.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
        lab = labels.reshape(-1)[idx].astype(np.int64)
    raw = px.take(idx)
    val = raw - bkg if resid is None else resid.reshape(-1)[idx]
    order = np.lexsort((val, lab))
    lab_s = lab[order]
    last = np.flatnonzero(np.r_[lab_s[1:] != lab_s[:-1], True])  # index of each label's maximum
    peak_flat = idx[order[last]]
    peak_val = val[order[last]]
    area = np.bincount(lab, minlength=n_lab)[1:].astype(np.int64)
    pi, pj = peak_flat // W, peak_flat % W

    sat = dtype_max if saturation_level is None else float(saturation_level)
    top = float(raw.max())
    n_top = int(np.count_nonzero(raw == top))
    if top < sat and top > 0 and ((n_top >= 2 and _is_adc_max(top)) or n_top >= 5):
        sat = top
    blob_max = np.full(n_lab - 1, -np.inf)
    np.maximum.at(blob_max, lab - 1, raw)
    saturated_all = blob_max >= sat

    small = area < int(min_pixels)
    keep = np.flatnonzero(~small)
    n_small = int(small.sum())
    if keep.size == 0:
        return Centroids.empty(n_small_rejected=n_small, **empty)

    pi, pj, area, saturated, peak_val = pi[keep], pj[keep], area[keep], saturated_all[keep], peak_val[keep]
    peak_raw = blob_max[keep]
    comp = keep + 1
    if deblend:
        extra = _split_blends_px(px, H, W, bkg, resid, idx, lab, val, raw, comp, area, pi, pj, sigma, sat)
        if extra is not None:
            e_comp, e_pi, e_pj, e_val, e_raw = extra
            e_area = area[np.searchsorted(comp, e_comp)]
            pi, pj = np.r_[pi, e_pi], np.r_[pj, e_pj]
            comp, area = np.r_[comp, e_comp], np.r_[area, e_area]
            peak_val, peak_raw = np.r_[peak_val, e_val], np.r_[peak_raw, e_raw]
            saturated = np.r_[saturated, np.zeros(len(e_comp), dtype=bool)]
    blended = np.zeros(len(comp), dtype=bool)
    if len(comp) > len(keep):
        blended = np.isin(comp, comp[len(keep):])

    def gather(h):
        return _gather_px(px, H, W, bkg, resid, pi, pj, h)

    return _measure(gather, pi, pj, comp, area, saturated, blended, peak_val, peak_raw, sat, sigma, level, thr,
                    n_hot, n_small, H, W, estimator=estimator, psf_sigma_px=psf_sigma_px, window=window,
                    iterations=iterations, max_axis_ratio=max_axis_ratio, params=params)


def _measure(gather, pi, pj, comp, area, saturated, blended, peak_val, peak_raw, sat, sigma, level, thr, n_hot,
             n_small, H, W, *, estimator, psf_sigma_px, window, iterations, max_axis_ratio, params) -> Centroids:
    """Steps 3-4 of detect_centroids on the detected peaks (as in the reference): PSF width, window,
    positions, brightness, flags, extended-blob rejection, brightest-first order."""
    v3, valid3, _ = gather(1)
    g_ok, g_uv, g_s2 = _gauss3(v3, 1, pi, pj)
    if psf_sigma_px is None:
        good = g_ok & ~saturated & valid3.all(axis=(1, 2)) & (peak_val > 20.0 * sigma)
        s_eff = float(np.sqrt(np.median(g_s2[good]))) if good.any() else math.sqrt(1.2 ** 2 + 1.0 / 12.0)
        s_eff = float(np.clip(s_eff, 0.4, 5.0))
        psf_used = float(np.sqrt(max(s_eff ** 2 - 1.0 / 12.0, 0.04)))
    else:
        psf_used = float(psf_sigma_px)
        s_eff = math.sqrt(psf_used ** 2 + 1.0 / 12.0)
    h = int(window) // 2 if window is not None else int(np.clip(math.ceil(2.5 * s_eff), 2, 8))
    params["window_used"] = 2 * h + 1

    vals, valid, rawv = gather(h)
    edge = ~valid.all(axis=(1, 2))
    d = np.arange(-h, h + 1, dtype=np.float64)
    X = pj[:, None, None] + d[None, None, :]
    Y = pi[:, None, None] + d[None, :, None]

    uv_cog = _cog(vals, X, Y, pi, pj)
    if estimator == "cog":
        uv = uv_cog
    elif estimator == "gauss3":
        uv_iw = _iwcog_sep(vals, X, Y, uv_cog, s_eff, h, pi, pj, iterations)
        uv = np.where((g_ok & ~saturated)[:, None], g_uv, uv_iw)
    elif estimator == "iwcog":
        uv = _iwcog_sep(vals, X, Y, uv_cog, s_eff, h, pi, pj, iterations)
    else:
        uv_iw = _iwcog_sep(vals, X, Y, uv_cog, s_eff, h, pi, pj, iterations)
        use = valid & (rawv < sat)
        uv, amp = _psf_fit_sep(vals, use, X, Y, uv_iw, psf_used, h, pi, pj, iterations)
        if blended.any():
            b = np.flatnonzero(blended)
            uv_b = np.where(g_ok[b, None], g_uv[b], np.stack([pj[b], pi[b]], axis=1).astype(np.float64))
            frac = _psf_models(pj[b, None].astype(np.float64), pi[b, None].astype(np.float64), uv_b,
                               np.ones(len(b)), psf_used)[:, 0, 0]
            amp_b = peak_val[b] / np.maximum(frac, 1e-6)
            sa, sb = np.meshgrid(np.arange(len(b)), np.arange(len(b)), indexing="ij")
            sa, sb = sa.ravel(), sb.ravel()
            near = ((sa != sb) & (comp[b][sa] == comp[b][sb])
                    & (np.abs(pi[b][sa] - pi[b][sb]) <= 2 * h + 1) & (np.abs(pj[b][sa] - pj[b][sb]) <= 2 * h + 1))
            sa, sb = sa[near], sb[near]
            vals = vals.copy()
            vb = vals[b]
            for _round in range(3):
                vb = vals[b].copy()
                if len(sa):
                    models = _psf_models(X[b][sa, 0, :], Y[b][sa, :, 0], uv_b[sb], amp_b[sb], psf_used)
                    np.subtract.at(vb, sa, models)
                uv_b, amp_b = _psf_fit_sep(vb, use[b], X[b], Y[b], uv_b, psf_used, h, pi[b], pj[b], iterations,
                                       max_shift=1.5)
            uv[b] = uv_b
            vals[b] = vb

    brightness = vals.sum(axis=(1, 2))
    ratio = _axis_ratio(vals, X, Y, uv, sigma)
    psnr = peak_val / sigma
    ratio_limit = max_axis_ratio + 0.5 * np.clip((20.0 - psnr) / 10.0, 0.0, 1.0)
    elongated = (ratio > ratio_limit) & (psnr >= 10.0)
    extended = area > max(MIN_EXTENDED_PX, EXTENDED_PSF_AREAS * math.pi * (3.0 * s_eff) ** 2)
    n_extended = int(extended.sum())
    if n_extended:
        keep_s = ~extended
        uv, brightness, peak_raw, area = uv[keep_s], brightness[keep_s], peak_raw[keep_s], area[keep_s]
        saturated, elongated, edge, blended, ratio = (saturated[keep_s], elongated[keep_s], edge[keep_s],
                                                      blended[keep_s], ratio[keep_s])
    order = np.argsort(-brightness, kind="stable")
    return Centroids(
        uv=uv[order].astype(np.float64), brightness=brightness[order].astype(np.float64),
        peak=peak_raw[order].astype(np.float64), n_pixels=area[order], saturated=saturated[order],
        elongated=elongated[order], edge=edge[order], blended=blended[order], axis_ratio=ratio[order],
        background_level=level, noise_sigma=sigma, threshold=thr, n_hot_pixels_rejected=n_hot,
        n_small_rejected=n_small, psf_sigma_px=psf_used, estimator=estimator, image_shape=(H, W),
        params=params, n_extended_rejected=n_extended,
    )


# ---------------------------------------------------------------------------- fast estimators
# The same estimators as _iwcog / _psf_fit, rearranged for speed (the fast path uses them; the
# reference keeps the originals): the Gaussian weight and the PSF model are separable, so sums run
# over rows and columns; the 3x3 normal equations are batched and solved in closed form; a star
# leaves the Gauss-Newton loop once its steps are below _FIT_TOL (the reference always makes
# max(3, iterations) steps). Positions agree with the originals to ~3e-5 px.

_FIT_TOL = 1e-4  # px: the Gauss-Newton fit of a star stops once its steps are below this


def _iwcog_sep(vals, X, Y, uv0, s_eff, h, pi, pj, iterations):
    """_iwcog with the separable weight exp(-dx^2/2s^2) exp(-dy^2/2s^2), u and v stepped together as
    one (n, 2) array (the same sums in the same order as stepping them apart: the same positions)."""
    XY = np.stack([X[:, 0, :], Y[:, :, 0]], axis=1).astype(np.float64)  # (n, 2, w): columns, rows
    k = -1.0 / (2.0 * s_eff * s_eff)
    uv = np.array(uv0, dtype=np.float64)
    c0 = np.stack([pj, pi], axis=1)
    lo, hi = c0 - h, c0 + h
    ok_all = np.ones(len(uv), dtype=bool)
    for _ in range(iterations):
        g = np.exp(k * (XY - uv[:, :, None]) ** 2)  # (n, 2, w): the weights along u and along v
        col = np.einsum("nij,ni->nj", vals, g[:, 1])  # sum over rows of vals * gy
        row = np.einsum("nij,nj->ni", vals, g[:, 0])
        cg = np.stack([col, row], axis=1) * g
        s = cg[:, 0].sum(axis=1)
        ok = s > 0
        ok_all &= ok
        c = (cg * XY).sum(axis=2) / np.where(ok, s, 1.0)[:, None]
        uv = np.where(ok[:, None], uv + 2.0 * (c - uv), uv)  # gain 2: converges on a Gaussian's centre
        uv = np.minimum(np.maximum(uv, lo), hi)  # = np.clip, without its per-call overhead
    bad = ~ok_all | ~np.isfinite(uv).all(axis=1)
    uv[bad] = uv0[bad]
    return uv


def _psf_fit_sep(vals, use, X, Y, uv0, s, h, pi, pj, iterations, max_shift=None):
    """_psf_fit (pixel-integrated Gaussian, amplitude and position, Gauss-Newton from uv0, steps
    limited to 0.5 px, saturated / off-image pixels left out), computed on the separable profiles."""
    n_st = len(vals)
    n = vals.shape[1]
    x = X[:, 0, :]
    y = Y[:, :, 0]
    w = use.reshape(n_st, n * n).astype(np.float64)
    vf = vals.reshape(n_st, n * n)
    u = uv0[:, 0].copy()
    v = uv0[:, 1].copy()
    k = 1.0 / (s * math.sqrt(2.0))
    c = 1.0 / (s * math.sqrt(2.0 * math.pi))

    def prof(t, t0):
        hi = (t + 0.5 - t0[:, None]) * k
        lo = (t - 0.5 - t0[:, None]) * k
        p = 0.5 * (erf(hi) - erf(lo))
        dp = -c * (np.exp(-hi * hi) - np.exp(-lo * lo))
        return p, dp

    fu, _ = prof(x, u)
    fv, _ = prof(y, v)
    P = (fv[:, :, None] * fu[:, None, :]).reshape(n_st, -1)
    A = (w * vf * P).sum(axis=1) / np.maximum((w * P * P).sum(axis=1), 1e-300)
    ok = np.isfinite(A) & (A > 0)
    act = np.arange(n_st)
    for _ in range(max(3, iterations)):
        if act.size == 0:
            break
        ua, va, Aa, wa = u[act], v[act], A[act], w[act]
        fu, dfu = prof(x[act], ua)
        fv, dfv = prof(y[act], va)
        # rows: P, d P / d u, d P / d v (per unit amplitude), each (n_act, n*n)
        M = (np.stack([fv, fv, dfv], axis=1)[:, :, :, None]
             * np.stack([fu, dfu, fu], axis=1)[:, :, None, :]).reshape(len(act), 3, n * n)
        e = (vf[act] - Aa[:, None] * M[:, 0]) * wa
        Mw = M * wa[:, None, :]
        G = Mw @ M.transpose(0, 2, 1)  # (n_act, 3, 3)
        g = (Mw @ e[:, :, None])[:, :, 0]
        sc = np.stack([np.ones_like(Aa), Aa, Aa], axis=1)
        G = G * sc[:, :, None] * sc[:, None, :]
        G[:, [0, 1, 2], [0, 1, 2]] += 1e-9
        g = g * sc
        # closed-form solve of the symmetric 3x3 systems
        a00, a01, a02, a11, a12, a22 = G[:, 0, 0], G[:, 0, 1], G[:, 0, 2], G[:, 1, 1], G[:, 1, 2], G[:, 2, 2]
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        det = a00 * c00 + a01 * c01 + a02 * c02
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s0 = (c00 * g[:, 0] + c01 * g[:, 1] + c02 * g[:, 2]) * inv
            s1 = (c01 * g[:, 0] + c11 * g[:, 1] + c12 * g[:, 2]) * inv
            s2 = (c02 * g[:, 0] + c12 * g[:, 1] + c22 * g[:, 2]) * inv
        s0 = np.where(np.isfinite(s0), s0, 0.0)
        s1 = np.where(np.isfinite(s1), s1, 0.0)
        s2 = np.where(np.isfinite(s2), s2, 0.0)
        A[act] = Aa + s0
        du = np.minimum(np.maximum(s1, -0.5), 0.5)
        dv = np.minimum(np.maximum(s2, -0.5), 0.5)
        u[act] = ua + du
        v[act] = va + dv
        act = act[(np.abs(du) > _FIT_TOL) | (np.abs(dv) > _FIT_TOL)]
    lim = h if max_shift is None else max_shift
    ok &= np.isfinite(u) & np.isfinite(v) & (A > 0) & (np.abs(u - pj) <= lim) & (np.abs(v - pi) <= lim)
    uv = np.stack([np.where(ok, u, uv0[:, 0]), np.where(ok, v, uv0[:, 1])], axis=1)
    return uv, np.where(ok, A, 0.0)


def _split_blends_px(px, H, W, bkg, resid, idx, lab, val, raw, comp, area, pi, pj, sigma, sat, min_sep=2.5,
                     max_area=1000, max_peaks=8):
    """_split_blends reading through a _Pixels (same rules, same results)."""
    big = comp[(area >= 6) & (area <= max_area)]
    if big.size == 0:
        return None
    sel = np.isin(lab, big)
    sidx, slab, sval, sraw = idx[sel], lab[sel], val[sel], raw[sel]
    ri, rj = sidx // W, sidx % W
    ismax = (sval >= _neighbour_max(px, H, W, bkg, resid, sidx)) & (sraw < sat)
    if not ismax.any():
        return None
    c_lab, c_val, c_i, c_j, c_raw = slab[ismax], sval[ismax], ri[ismax], rj[ismax], sraw[ismax]
    # a blob whose only local maximum is its peak has nothing to split: those are set aside at once
    labs, first, counts = np.unique(c_lab, return_index=True, return_counts=True)
    k0s = np.searchsorted(comp, labs)  # comp is ascending
    lone = (counts == 1) & (c_i[first] == pi[k0s]) & (c_j[first] == pj[k0s])
    out = []
    for L, k0 in zip(labs[~lone].tolist(), k0s[~lone].tolist()):
        m = np.flatnonzero(c_lab == L)
        acc = [(int(pi[k0]), int(pj[k0]))]
        for q in m[np.argsort(-c_val[m], kind="stable")]:
            if len(acc) >= max_peaks:
                break
            i, j, v = int(c_i[q]), int(c_j[q]), float(c_val[q])
            d = [math.hypot(i - a, j - b) for a, b in acc]
            n_near = int(np.argmin(d))
            if d[n_near] < min_sep:
                continue
            a, b = acc[n_near]
            t = np.linspace(0.0, 1.0, int(math.ceil(2 * d[n_near])) + 1)
            si = np.rint(i + t * (a - i)).astype(np.int64)
            sj = np.rint(j + t * (b - j)).astype(np.int64)
            seg = resid[si, sj] if resid is not None else px.take(si * W + sj) - bkg
            if v - float(seg.min()) >= max(3.0 * sigma, 0.2 * v):
                acc.append((i, j))
                out.append((int(L), i, j, v, float(c_raw[q])))
    if not out:
        return None
    o = np.array(out, dtype=np.float64)
    return o[:, 0].astype(np.int64), o[:, 1].astype(np.int64), o[:, 2].astype(np.int64), o[:, 3], o[:, 4]


# ============================================================================ helpers


def _cog(vals, X, Y, pi, pj):
    w = np.maximum(vals, 0.0)
    sw = w.sum(axis=(1, 2))
    ok = sw > 0
    sw = np.where(ok, sw, 1.0)
    u = np.where(ok, (w * X).sum(axis=(1, 2)) / sw, pj)
    v = np.where(ok, (w * Y).sum(axis=(1, 2)) / sw, pi)
    return np.stack([u, v], axis=1)


def _gauss3(vals, h, pi, pj):
    """Three-point Gaussian fit on the 3x3 marginals: (ok, uv, effective sigma^2)."""
    c = vals[:, h - 1: h + 2, h - 1: h + 2]
    mx = c.sum(axis=1)  # (N, 3) along u
    my = c.sum(axis=2)  # (N, 3) along v
    ok = (mx > 0).all(axis=1) & (my > 0).all(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        lx = np.log(np.where(mx > 0, mx, 1.0))
        ly = np.log(np.where(my > 0, my, 1.0))
        cx = lx[:, 0] - 2 * lx[:, 1] + lx[:, 2]
        cy = ly[:, 0] - 2 * ly[:, 1] + ly[:, 2]
        du = (lx[:, 0] - lx[:, 2]) / (2.0 * cx)
        dv = (ly[:, 0] - ly[:, 2]) / (2.0 * cy)
        s2 = -0.5 * (1.0 / cx + 1.0 / cy)
    ok &= (cx < 0) & (cy < 0) & (np.abs(du) < 1.0) & (np.abs(dv) < 1.0)
    uv = np.stack([pj + np.where(ok, du, 0.0), pi + np.where(ok, dv, 0.0)], axis=1)
    return ok, uv, np.where(ok, s2, np.nan)


def _axis_ratio(vals, X, Y, uv, sigma):
    """sqrt(l1 / l2) of the intensity second moments (pixels above 2 sigma) about the centroid."""
    w = np.where(vals > 2.0 * sigma, vals, 0.0)
    s = w.sum(axis=(1, 2))
    ok = s > 0
    s = np.where(ok, s, 1.0)
    dx = X - uv[:, 0, None, None]
    dy = Y - uv[:, 1, None, None]
    mxx = (w * dx * dx).sum(axis=(1, 2)) / s + 1.0 / 12.0
    myy = (w * dy * dy).sum(axis=(1, 2)) / s + 1.0 / 12.0
    mxy = (w * dx * dy).sum(axis=(1, 2)) / s
    tr = mxx + myy
    disc = np.sqrt(np.maximum((mxx - myy) ** 2 / 4.0 + mxy ** 2, 0.0))
    l1 = tr / 2.0 + disc
    l2 = np.maximum(tr / 2.0 - disc, 1e-12)
    return np.where(ok, np.sqrt(l1 / l2), np.nan)


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


