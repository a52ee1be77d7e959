"""Frames whose stars are trails: the camera turned against the sky during the exposure.

An untracked exposure (a camera on a tripod, a telescope whose mount does not follow) draws every star
as the same short line: the sky's motion across the sensor, the same length and direction for all of
them. The centroider measures a star in a window of at most 17 px around its brightest pixel, and splits
a blob with several peaks into several stars. A trail of ten pixels or more is then measured near one of
its ends, or split into two or three "stars" along it, at the same place along every trail. The pattern
search still identifies the stars, but the attitude is the camera's at that moment of the exposure (up
to half a trail from mid-exposure) with a 1-sigma that does not say so.

`trailed_frame` recognises such a frame: most of its brightest detections are elongated, most of their
second moments (in a window around each) share one direction, and the line they draw is at least
TRAIL_MIN_LENGTH_PX long. `trail_stars` then measures every blob above the detection threshold whole, as
one star at its intensity-weighted centre: the middle of the trail, where the star was at mid-exposure.
Round stars (any star tracker's frames, a tracked or short exposure) never pass the test, and their
centroids are the centroider's, unchanged.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from skyview.detect.centroids import MIN_EXTENDED_PX, Centroids, estimate_background, row_median, to_gray

TRAILED_FRACTION = 0.6  # at least this share of the brightest detections elongated ...
TRAIL_CHECK_STARS = 15  # ... of this many (and at least TRAIL_MIN_STARS of them measured)
TRAIL_MIN_STARS = 8
TRAIL_MIN_LENGTH_PX = 10.0  # shorter trails: the centroider's window holds them (errors of a few arcsec)
TRAIL_ANGLE_TOLERANCE_DEG = 10.0  # ... in one direction (as many of them within this of their mean direction)
TRAIL_WINDOW = 24  # the moments' window: +-24 px (trails up to ~45 px seen whole from their middle)
TRAIL_FLOOR = 0.1  # a trail's pixels: above the threshold and this fraction of its brightest
TRAIL_AREA_WIDTHS = 12.0  # a blob larger than this many (trail length + 6 px) x 6 px is not a star's trail


def _window_moments(img: np.ndarray, uv: np.ndarray, threshold: float, radius: int = TRAIL_WINDOW) -> np.ndarray:
    """(n, 3) second moments (cxx, cyy, cxy) of the pixels around each position uv that lie above the threshold
    and TRAIL_FLOOR of the window's brightest (the window's border median taken as its background); NaN for a
    position too near the border or with fewer than three such pixels."""
    H, W = img.shape
    out = np.full((len(uv), 3), np.nan)
    c = np.rint(uv).astype(np.int64)
    inside = (c[:, 0] >= radius) & (c[:, 0] < W - radius) & (c[:, 1] >= radius) & (c[:, 1] < H - radius)
    k = np.flatnonzero(inside)
    if len(k) == 0:
        return out
    d = np.arange(-radius, radius + 1)
    win = img.reshape(-1).take((c[k, 1] * W + c[k, 0])[:, None, None] + (d[:, None] * W + d[None, :])[None])
    win = win.astype(np.float64)
    border = np.concatenate([win[:, [0, -1], :].reshape(len(k), -1), win[:, 1:-1, [0, -1]].reshape(len(k), -1)],
                            axis=1)
    win -= row_median(border)[:, None, None]
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


def trailed_frame(image: np.ndarray, c: Centroids) -> tuple[float, float] | None:
    """(length px, direction deg in [0, 180)) of the trail every star of the frame draws, or None for a frame
    of round stars (the module docstring: most of the brightest detections elongated, in one direction, at
    least TRAIL_MIN_LENGTH_PX long)."""
    k = min(TRAIL_CHECK_STARS, len(c))
    if k < TRAIL_MIN_STARS or np.count_nonzero(c.elongated[:k]) < TRAILED_FRACTION * k or not c.threshold > 0:
        return None
    m = _window_moments(to_gray(image), c.uv[:k], c.threshold)
    ok = np.isfinite(m).all(axis=1)
    if np.count_nonzero(ok) < TRAIL_MIN_STARS:
        return None
    length, angle2 = _trail_shape(m[ok])
    # the direction most of them share (a window that holds a neighbour's trail too measures another)
    mean2 = math.atan2(float(np.mean(np.sin(angle2))), float(np.mean(np.cos(angle2))))
    along = np.abs(np.angle(np.exp(1j * (angle2 - mean2)))) <= math.radians(2.0 * TRAIL_ANGLE_TOLERANCE_DEG)
    if np.count_nonzero(along) < max(TRAIL_MIN_STARS, TRAILED_FRACTION * np.count_nonzero(ok)):
        return None
    median_length = float(row_median(length[along][None])[0])
    if median_length < TRAIL_MIN_LENGTH_PX:
        return None
    a2 = angle2[along]
    direction = math.degrees(0.5 * math.atan2(float(np.mean(np.sin(a2))), float(np.mean(np.cos(a2))))) % 180.0
    return median_length, direction


def trail_stars(image: np.ndarray, c: Centroids, trail: tuple[float, float], *, min_pixels: int = 2,
                max_stars: int | None = None, background_block: int = 64, **_unused) -> Centroids:
    """The stars of a trailed frame (`trailed_frame`'s trail: length px, direction deg), each blob above the
    detection threshold of `c` (the centroider's pass on the same image) measured whole: its
    intensity-weighted centre (mid-exposure), its summed brightness, its pixels and brightest value, its
    axis ratio; brightest first, the first max_stars kept (the others counted in n_unmeasured). Blobs of
    fewer than min_pixels pixels are hot pixels or noise; blobs larger than a trail can be (TRAIL_AREA_WIDTHS)
    are extended (a roof, the Moon). The statistics (background, noise, threshold, hot pixels) are c's. Memory:
    the frame as float32 and its labels as int32, 8 bytes a pixel (800 MB at the 100-megapixel limit)."""
    img = to_gray(image)
    H, W = img.shape
    resid = img.astype(np.float32)  # (the frame less its background, in place: two full-frame maps at most)
    if resid.dtype.kind == "f" and not np.isfinite(resid).all():  # as the centroider does: the others' median
        resid[~np.isfinite(resid)] = np.float32(np.median(resid[np.isfinite(resid)]))
    bkg = estimate_background(resid, background_block)[0]
    resid -= np.float32(bkg) if np.isscalar(bkg) else bkg.astype(np.float32)
    mask = (resid > np.float32(c.threshold)).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
    fi = np.flatnonzero(mask)
    lab_px = lab.reshape(-1)[fi]
    w = resid.reshape(-1)[fi].astype(np.float64)
    x, y = (fi % W).astype(np.float64), (fi // W).astype(np.float64)
    s = np.bincount(lab_px, weights=w, minlength=n)
    sx, sy = np.bincount(lab_px, weights=w * x, minlength=n), np.bincount(lab_px, weights=w * y, minlength=n)
    area = stats[:, cv2.CC_STAT_AREA].astype(np.int64)
    peak = np.full(n, -np.inf)
    np.maximum.at(peak, lab_px, np.asarray(img).reshape(-1)[fi].astype(np.float64))
    length = trail[0]
    too_big = max(MIN_EXTENDED_PX, TRAIL_AREA_WIDTHS * (length + 6.0) * 6.0)
    comp = np.arange(1, n)
    keep = comp[(area[1:] >= min_pixels) & (area[1:] <= too_big) & (s[1:] > 0)]
    n_extended = int(np.count_nonzero(area[1:] > too_big))
    n_small = int(np.count_nonzero(area[1:] < min_pixels))
    uv = np.stack([sx[keep] / s[keep], sy[keep] / s[keep]], axis=1)
    mx, my = uv[:, 0], uv[:, 1]
    sxx = np.bincount(lab_px, weights=w * x * x, minlength=n)[keep] / s[keep] - mx * mx
    syy = np.bincount(lab_px, weights=w * y * y, minlength=n)[keep] / s[keep] - my * my
    sxy = np.bincount(lab_px, weights=w * x * y, minlength=n)[keep] / s[keep] - mx * my
    root = np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
    lam1, lam2 = 0.5 * (sxx + syy) + root, np.maximum(0.5 * (sxx + syy) - root, 1e-12)
    ratio = np.sqrt(np.maximum(lam1, 0.0) / lam2)
    x0, y0 = stats[keep, cv2.CC_STAT_LEFT], stats[keep, cv2.CC_STAT_TOP]
    x1, y1 = x0 + stats[keep, cv2.CC_STAT_WIDTH], y0 + stats[keep, cv2.CC_STAT_HEIGHT]
    edge = (x0 == 0) | (y0 == 0) | (x1 >= W) | (y1 >= H)
    top = float(np.iinfo(img.dtype).max) if img.dtype.kind in "ui" else math.inf
    order = np.argsort(-s[keep], kind="stable")
    n_all = len(order)
    if max_stars is not None:
        order = order[: int(max_stars)]
    saturated = peak[keep] >= top
    params = {**c.params, "trailed": {"length_px": float(length), "direction_deg": float(trail[1])}}
    return Centroids(uv=uv[order], brightness=s[keep][order], peak=peak[keep][order], n_pixels=area[keep][order],
                     saturated=saturated[order], elongated=ratio[order] > 1.4, edge=edge[order],
                     blended=np.zeros(len(order), dtype=bool), axis_ratio=ratio[order],
                     background_level=c.background_level, noise_sigma=c.noise_sigma, threshold=c.threshold,
                     n_hot_pixels_rejected=c.n_hot_pixels_rejected, n_small_rejected=n_small,
                     n_extended_rejected=n_extended, n_unmeasured=n_all - len(order),
                     n_unmeasured_saturated=int(np.count_nonzero(saturated)) - int(np.count_nonzero(saturated[order])),
                     psf_sigma_px=c.psf_sigma_px, estimator="trail", image_shape=(H, W), params=params)
