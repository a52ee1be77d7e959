"""Frames whose stars are trails: the camera turned against the sky during the exposure.

An untracked exposure (a camera on a tripod, a telescope whose mount does not follow) draws every star
as the same short line: the sky's motion across the sensor, the same length and direction for all of
them. The centroider measures a star in a window of at most 17 px around its brightest pixel, and splits
a blob with several peaks into several stars. A trail of ten pixels or more is then measured near one of
its ends, or split into two or three "stars" along it, at the same place along every trail. The pattern
search still identifies the stars, but the attitude is the camera's at that moment of the exposure (up
to half a trail from mid-exposure) with a 1-sigma that does not say so.

`trailed_frame` recognises such a frame: most of its brightest detections are elongated (`may_be_trailed`);
then, among the brightest that are neither saturated (a bleed column is elongated too) nor fragments of a
satellite's or an aircraft's trail (`skyview.detect.trails`), most are, their second moments (in a window
around each) share one direction, and the line they draw is at least TRAIL_MIN_LENGTH_PX long.
`trail_stars` then filters the frame along that line (a matched filter: a faint trail's fragments join,
its signal to noise grows by about the square root of its length) and measures every blob of the filtered
frame whole, as one star at its intensity-weighted centre: the middle of the trail, where the star was at
mid-exposure. Blobs that are not one trail (two run together, a satellite's, one cut by the border) are
left out. Round stars (any star tracker's frames, a tracked or short exposure) never pass the test, and
their centroids are the centroider's, unchanged.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from skyview.detect.centroids import Centroids, estimate_background, row_median, to_gray
from skyview.detect.hot_pixels import patch_hot_pixels
from skyview.detect.trails import fragment_width_px, trail_members
from skyview.detect.windows import background_windows

TRAILED_FRACTION = 0.6  # at least this share of the brightest detections elongated ...
TRAIL_CHECK_STARS = 15  # ... of this many (and at least TRAIL_MIN_STARS of them measured)
TRAIL_MIN_STARS = 8
TRAIL_MIN_LENGTH_PX = 10.0  # shorter trails: the centroider's window holds them (errors of a few arcsec)
TRAIL_ANGLE_TOLERANCE_DEG = 10.0  # ... in one direction: at least TRAIL_MIN_STARS and half of them within this
TRAIL_AGREE_FRACTION = 0.5  # of their mean direction (a window can hold a neighbour's trail, which skews it)
TRAIL_WINDOW = 24  # the moments' window: +-24 px (trails up to ~45 px seen whole from their middle)
TRAIL_FLOOR = 0.1  # a trail's pixels: above the threshold and this fraction of its brightest
TRAIL_VOTE_DEPTH = 40  # the vote reads the brightest this many detections at most
TRAIL_LONGEST = 2.2  # a filtered blob longer than this many trails (plus 4 px) is two run together, or a satellite's
TRAIL_SHAPE_ANGLE_DEG = 20.0  # a filtered blob of half a trail or more along another direction is not a star's


def _window_moments(img: np.ndarray, uv: np.ndarray, threshold: float, radius: int = TRAIL_WINDOW) -> np.ndarray:
    """(n, 3) second moments (cxx, cyy, cxy) of the pixels around each position uv that lie above the threshold
    and TRAIL_FLOOR of the window's brightest (the window's border median taken as its background); NaN for a
    position too near the border or with fewer than three such pixels."""
    out = np.full((len(uv), 3), np.nan)
    win, inside = background_windows(img, uv, radius)
    k = np.flatnonzero(inside)
    if len(k) == 0:
        return out
    d = np.arange(-radius, radius + 1)
    floor = np.maximum(threshold, TRAIL_FLOOR * win.max(axis=(1, 2)))[:, None, None]
    w = np.where(win > floor, win, 0.0)
    s = w.sum(axis=(1, 2))
    n_px = np.count_nonzero(w, axis=(1, 2))
    x, y = d[None, None, :].astype(np.float64), d[None, :, None].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx, my = (w * x).sum(axis=(1, 2)) / s, (w * y).sum(axis=(1, 2)) / s
        dx, dy = x - mx[:, None, None], y - my[:, None, None]
        m = np.stack([(w * dx * dx).sum(axis=(1, 2)), (w * dy * dy).sum(axis=(1, 2)),
                      (w * dx * dy).sum(axis=(1, 2))], axis=1) / s[:, None]
    m[n_px < 3] = np.nan
    out[k] = m
    return out


def _trail_shape(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(length px, doubled angle rad) of the line whose second moments are m = (cxx, cyy, cxy): a uniform line
    of length L has variance L^2 / 12 along it (the PSF's adds to both axes and cancels in the difference)."""
    root = np.sqrt(np.maximum(0.25 * (m[:, 0] - m[:, 1]) ** 2 + m[:, 2] ** 2, 0.0))  # half of lambda1 - lambda2
    return np.sqrt(12.0 * 2.0 * root), np.arctan2(2.0 * m[:, 2], m[:, 0] - m[:, 1])


def may_be_trailed(c: Centroids) -> bool:
    """Whether most of the brightest detections of `c` are elongated: the first test of `trailed_frame`, on the
    first TRAIL_CHECK_STARS detections (which measuring more or fewer of the faint ones does not change)."""
    k = min(TRAIL_CHECK_STARS, len(c))
    return k >= TRAIL_MIN_STARS and np.count_nonzero(c.elongated[:k]) >= TRAILED_FRACTION * k and c.threshold > 0


def _direction_vote(image: np.ndarray, c: Centroids, saturated_too: bool = False):
    """The vote of `trailed_frame`: among the brightest detections that are neither saturated (unless saturated_too)
    nor a satellite's fragments, when most are elongated, their (length px, doubled angle rad) and which of them
    point the way most do (within TRAIL_ANGLE_TOLERANCE_DEG); None when there are not TRAIL_MIN_STARS such
    detections measured or most of them are not elongated."""
    if not may_be_trailed(c):
        return None
    depth = min(TRAIL_VOTE_DEPTH, len(c))
    fragments = trail_members(c.uv[:depth], max_width_px=fragment_width_px(c.psf_sigma_px))
    vote = np.flatnonzero(~fragments if saturated_too else ~c.saturated[:depth] & ~fragments)
    vote = vote[:TRAIL_CHECK_STARS]
    if len(vote) < TRAIL_MIN_STARS or np.count_nonzero(c.elongated[vote]) < TRAILED_FRACTION * len(vote):
        return None
    m = _window_moments(to_gray(image), c.uv[vote], c.threshold)
    ok = np.isfinite(m).all(axis=1)
    if np.count_nonzero(ok) < TRAIL_MIN_STARS:
        return None
    length, angle2 = _trail_shape(m[ok])
    # the direction most of them share (a window that holds a neighbour's trail too measures another)
    mean2 = math.atan2(float(np.mean(np.sin(angle2))), float(np.mean(np.cos(angle2))))
    along = np.abs(np.angle(np.exp(1j * (angle2 - mean2)))) <= math.radians(2.0 * TRAIL_ANGLE_TOLERANCE_DEG)
    return length, angle2, along


def shared_direction(along: np.ndarray) -> bool:
    """Whether a vote's detections point one way: TRAIL_MIN_STARS and TRAIL_AGREE_FRACTION of them or more."""
    return bool(np.count_nonzero(along) >= max(TRAIL_MIN_STARS, TRAIL_AGREE_FRACTION * len(along)))


def elongated_every_way(image: np.ndarray, c: Centroids) -> bool:
    """Whether most of the brightest detections, saturated or not, are elongated (`may_be_trailed`) in no direction
    they share: not stars trailed, however short (their trails share one), nor bleeding columns (one too), but
    tracks (cosmic rays that a JPEG blurred past the centroider's streak test, a storm of them) or a lens's coma."""
    vote = _direction_vote(image, c, saturated_too=True)
    return vote is not None and not shared_direction(vote[2])


def trailed_frame(image: np.ndarray, c: Centroids) -> tuple[float, float] | None:
    """(length px, direction deg in [0, 180)) of the trail every star of the frame draws, or None for a frame
    of round stars (the module docstring)."""
    vote = _direction_vote(image, c)
    if vote is None or not shared_direction(vote[2]):
        return None
    length, angle2, along = vote
    median_length = float(row_median(length[along][None])[0])
    if median_length < TRAIL_MIN_LENGTH_PX:
        return None
    a2 = angle2[along]
    direction = math.degrees(0.5 * math.atan2(float(np.mean(np.sin(a2))), float(np.mean(np.cos(a2))))) % 180.0
    return median_length, direction


def line_kernel(length: float, direction_deg: float) -> np.ndarray:
    """A line of `length` px through the centre of an odd square, at direction_deg (image axes: u right, v
    down), its pixels equal and summing to 1; symmetric about the centre (a point's offsets and their
    negatives), so that filtering moves no blob's centroid."""
    r = max(1, int(math.ceil(length / 2.0)))
    t = np.linspace(0.0, length / 2.0, 2 * r + 1)
    cos, sin = math.cos(math.radians(direction_deg)), math.sin(math.radians(direction_deg))
    du, dv = np.sign(cos) * np.floor(np.abs(t * cos) + 0.5), np.sign(sin) * np.floor(np.abs(t * sin) + 0.5)
    k = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
    k[(r + dv).astype(int), (r + du).astype(int)] = 1.0
    k[(r - dv).astype(int), (r - du).astype(int)] = 1.0
    return k / k.sum()


def trail_stars(image: np.ndarray, c: Centroids, trail: tuple[float, float], *, k_sigma: float = 5.0,
                min_pixels: int = 2, max_stars: int | None = None, background_block: int = 64,
                saturation_level: float | None = None, **_unused) -> Centroids:
    """The stars of a trailed frame (`trailed_frame`'s trail: length px, direction deg): the frame, its hot
    pixels patched and its background taken out, filtered along the trail (`line_kernel`), its blobs above
    k_sigma times the filtered frame's own noise each measured whole: the intensity-weighted centre
    (mid-exposure), the summed brightness, the pixels, the brightest raw value, the axis ratio; brightest
    first, the first max_stars kept (the others counted in n_unmeasured). Left out: blobs of fewer than
    min_pixels pixels, blobs cut by the border, and blobs that are not one star's trail (longer than
    TRAIL_LONGEST trails, or half a trail long in another direction: two trails run together, a satellite).
    Saturated: a raw value at saturation_level (None: the dtype's largest, or the frame's largest when five
    pixels or more share it, as the centroider decides). Memory: about 10 bytes a pixel (1 GB at the
    100-megapixel limit)."""
    img = to_gray(image)
    H, W = img.shape
    raw = img
    if raw.dtype.kind == "f" and not np.isfinite(raw).all():  # as the centroider does: the others' median
        raw = np.where(np.isfinite(raw), raw, np.float32(np.nanmedian(raw))).astype(np.float32)
    f, n_hot = patch_hot_pixels(raw, c.background_level, c.noise_sigma) if c.noise_sigma > 0 else (
        raw.astype(np.float32), 0)
    bkg = estimate_background(f, background_block)[0]
    if np.isscalar(bkg):
        f -= np.float32(bkg)
    else:
        np.subtract(f, bkg, out=f, dtype=np.float32)
    del bkg
    length, direction = trail
    smooth = cv2.filter2D(f, -1, line_kernel(length, direction), borderType=cv2.BORDER_REPLICATE)
    del f
    noise = estimate_background(smooth, background_block)[2]
    mask = (smooth > np.float32(k_sigma * noise)).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
    fi = np.flatnonzero(mask)
    del mask
    lab_px = lab.reshape(-1)[fi]
    del lab
    w = smooth.reshape(-1)[fi].astype(np.float64)
    del smooth
    x, y = (fi % W).astype(np.float64), (fi // W).astype(np.float64)

    def sums(weights):
        return np.bincount(lab_px, weights=weights, minlength=n)[1:]

    s, area = sums(w), stats[1:, cv2.CC_STAT_AREA].astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx, my = sums(w * x) / s, sums(w * y) / s
        sxx, syy, sxy = sums(w * x * x) / s - mx * mx, sums(w * y * y) / s - my * my, sums(w * x * y) / s - mx * my
    root = np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
    lam1, lam2 = 0.5 * (sxx + syy) + root, np.maximum(0.5 * (sxx + syy) - root, 1e-12)
    long_axis = np.sqrt(12.0 * 2.0 * root)  # a filtered trail: about 1.4 trails (a line filtered by a line)
    doubled = np.arctan2(2.0 * sxy, sxx - syy) - math.radians(2.0 * direction)
    off = np.degrees(np.abs(np.angle(np.exp(1j * doubled)))) / 2.0  # from the trail's direction
    x0, y0 = stats[1:, cv2.CC_STAT_LEFT], stats[1:, cv2.CC_STAT_TOP]
    x1, y1 = x0 + stats[1:, cv2.CC_STAT_WIDTH], y0 + stats[1:, cv2.CC_STAT_HEIGHT]
    edge = (x0 == 0) | (y0 == 0) | (x1 >= W) | (y1 >= H)
    one_trail = ((long_axis <= TRAIL_LONGEST * length + 4.0)
                 & ((long_axis < 0.5 * length) | (off <= TRAIL_SHAPE_ANGLE_DEG)))
    small = area < min_pixels
    keep = np.flatnonzero(~small & ~edge & one_trail & (s > 0))
    peak = np.full(n, -np.inf)
    np.maximum.at(peak, lab_px, np.asarray(raw, dtype=np.float64).reshape(-1)[fi])
    peak = peak[1:]
    if saturation_level is not None:
        top = float(saturation_level)
    else:
        top = float(np.iinfo(img.dtype).max) if img.dtype.kind in "ui" else math.inf
        frame_max = float(np.max(raw))
        if frame_max < top and np.count_nonzero(raw == frame_max) >= 5:
            top = frame_max
    ratio = np.sqrt(np.maximum(lam1, 0.0) / lam2)
    order = keep[np.argsort(-s[keep], kind="stable")]
    n_all = len(order)
    if max_stars is not None:
        order = order[: int(max_stars)]
    saturated = peak >= top
    params = {**c.params, "trailed": {"length_px": float(length), "direction_deg": float(direction)}}
    return Centroids(uv=np.stack([mx[order], my[order]], axis=1), brightness=s[order], peak=peak[order],
                     n_pixels=area[order], saturated=saturated[order], elongated=ratio[order] > 1.4,
                     edge=edge[order], blended=np.zeros(len(order), dtype=bool), axis_ratio=ratio[order],
                     background_level=c.background_level, noise_sigma=c.noise_sigma, threshold=c.threshold,
                     n_hot_pixels_rejected=n_hot, n_small_rejected=int(np.count_nonzero(small)),
                     n_extended_rejected=int(np.count_nonzero(~one_trail & ~small)), n_unmeasured=n_all - len(order),
                     n_unmeasured_saturated=int(np.count_nonzero(saturated[keep]) - np.count_nonzero(saturated[order])),
                     psf_sigma_px=c.psf_sigma_px, estimator="trail", image_shape=(H, W), params=params)
