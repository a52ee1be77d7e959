"""The previous implementation of `skyview.detect.centroids.detect_centroids`, kept as the reference the fast
path is tested against (tests/test_centroid.py: the same detections, flags and positions to the
tolerances stated there, on simulated frames, JPEG, gradients, odd inputs and the real photographs).

Not used by skyview itself. It is the straightforward form of the algorithm described in
`skyview.detect.centroids`'s docstring (a full-frame float residual, connectedComponentsWithStats, window
gathers, numpy.median backgrounds), easier to read than the fast path and slower (11-17 ms against
about 1.2-1.5 ms for an 8-bit 1024 x 1024 star-tracker frame on this project's machine).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.special import erf

from skyview.core.errors import BadInput
from skyview.detect.centroids import (
    _CLIP_K,
    _CLIP_STD,
    _MAD_TO_SIGMA,
    DEFAULT_ESTIMATOR,
    ESTIMATORS,
    EXTENDED_PSF_AREAS,
    MIN_EXTENDED_PX,
    Centroids,
    _cog,
    _is_adc_max,
    _psf_models,
    _upsample,
    to_gray,
)


def _estimate_background_reference(f: np.ndarray, block: int = 64) -> tuple[np.ndarray | float, float, float]:
    """The original estimate_background (np.median based), kept as the reference of the fast one.

    (background map or scalar, median background level, noise sigma) of a float32 image.

    Block medians on a sub-sampled grid, interpolated bilinearly between block centres and
    extrapolated linearly beyond the outer ones (so a gradient is followed up to the borders).
    """
    H, W = f.shape
    step = 4 if min(H, W) >= 256 else (2 if min(H, W) >= 64 else 1)
    off = step // 2  # samples centred in their blocks (to half a pixel)
    sub = f[off::step, off::step]
    sh, sw = sub.shape
    bs = max(4, block // step)  # samples per block side
    gh, gw = max(1, sh // bs), max(1, sw // bs)
    by, bx = sh // gh, sw // gw
    cells = sub[: gh * by, : gw * bx].reshape(gh, by, gw, bx).transpose(0, 2, 1, 3).reshape(gh, gw, by * bx)
    grid = np.median(cells, axis=2).astype(np.float32)
    level = float(np.median(grid))
    if gh * gw > 1:
        r = (sub - _upsample(grid, by, bx, sh, sw)).ravel()
    else:
        r = (sub - level).ravel()
    mad = float(np.median(np.abs(r - np.median(r))))
    s0 = _MAD_TO_SIGMA * mad
    is_int = bool(np.all(np.floor(sub) == sub))  # integer-valued data (e.g. from uint images)
    floor = 1.0 if is_int else max(1e-12, 1e-9 * float(np.abs(sub).max()))
    clip = _CLIP_K * max(s0, floor)
    rc = r[np.abs(r) <= clip]
    sigma = float(rc.std()) / _CLIP_STD if rc.size > 10 else s0
    sigma = max(sigma, 0.5 if is_int else floor)
    # flat: no block deviates from the level by more than 0.5 sigma, by more than its own noise
    # allows (the median of n samples scatters by 1.25 sigma / sqrt(n)) or, on integer data, by more
    # than 1 (medians of integers are quantised); then one level is used
    tol = max(0.5 * sigma, 4.5 * 1.2533 * sigma / math.sqrt(by * bx), 1.0 if is_int else 0.0)
    if gh * gw == 1 or float(np.abs(grid - level).max()) <= tol:
        return level, level, sigma
    return _upsample(grid, by * step, bx * step, H, W), level, sigma


def _detect_centroids_reference(image: np.ndarray, *, k_sigma: float = 5.0, window: int | None = None,
                                min_pixels: int = 2, estimator: str = DEFAULT_ESTIMATOR,
                                psf_sigma_px: float | None = None, saturation_level: float | None = None,
                                max_axis_ratio: float = 1.4, background_block: int = 64, iterations: int = 6,
                                deblend: bool = True) -> Centroids:
    """The original detect_centroids (full-frame float32 copy, connectedComponentsWithStats, np.median
    statistics), kept unchanged as the reference that tests compare `detect_centroids` against.

    Find stars in a 2-D image and measure their sub-pixel centroids (see the module docstring).

    window: odd side of the square measurement window (pixels) around each blob's brightest pixel;
    None picks 2*ceil(2.5 sigma_eff) + 1 from the measured PSF (sigma_eff^2 = sigma^2 + 1/12).
    psf_sigma_px: PSF sigma for the fit and iwcog; None measures it from the bright stars
    (3-point log-curvature), falling back to 1.2 px. A blank (constant) image gives zero centroids.
    A colour (BGR/BGRA) image is converted to grey; any other non-2-D array is BadInput.
    deblend: split a blob with several peaks (each >= 2.5 px from a brighter one, with a dip of at
    least 20 % and 3 sigma between them) into one centroid per peak, flagged `blended`; with the
    "fit" estimator each one is refitted after subtracting its neighbours' fitted PSFs.
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
    f = img.astype(np.float32, copy=False)
    if img.dtype.kind == "f" and not np.all(np.isfinite(f)):
        f = np.where(np.isfinite(f), f, np.float32(np.nanmedian(np.where(np.isfinite(f), f, np.nan))))
    if img.dtype.kind in "ui":
        dtype_max = float(np.iinfo(img.dtype).max)
    else:
        dtype_max = math.inf
    fmin, fmax = float(f.min()), float(f.max())
    if fmax == fmin:
        return Centroids.empty(background_level=fmin, noise_sigma=0.0, estimator=estimator,
                               image_shape=(H, W), params={**params, "background_flat": True})

    bkg, level, sigma = _estimate_background_reference(f, background_block)
    params["background_flat"] = isinstance(bkg, float)  # one level for the whole frame, or a map
    thr = float(k_sigma) * sigma
    if isinstance(bkg, float):
        resid = None
        mask = f > np.float32(bkg + thr)
    else:
        resid = f - bkg
        mask = resid > np.float32(thr)
    empty = dict(background_level=level, noise_sigma=sigma, threshold=thr, estimator=estimator,
                 image_shape=(H, W), params=params)
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return Centroids.empty(**empty)
    # hot pixels: above the threshold while all 8 neighbours stay near the background, which no PSF
    # wider than ~0.5 px does. They are counted, taken out of the mask and repaired (median of the
    # neighbours) so that they neither make a blob nor pull the centroid of a star they touch.
    if idx.size <= 20000:
        nb = _gather(f, bkg, resid, idx // W, idx % W, 1)[0]
        centre = nb[:, 1, 1].copy()
        nb[:, 1, 1] = -np.inf
        nb_max = nb.reshape(len(idx), -1).max(axis=1)
    else:  # a large bright area (limb, glare): a ring max filter is cheaper than 3x3 gathers
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
        nb_raw = _gather(f, bkg, resid, hp // W, hp % W, 1)[2]
        ring = np.delete(nb_raw.reshape(n_hot, 9), 4, axis=1)
        repaired = np.median(ring, axis=1).astype(np.float32)
        if np.shares_memory(f, img):
            f = f.copy()
        f.reshape(-1)[hp] = repaired
        if resid is not None:
            resid.reshape(-1)[hp] = repaired - bkg.reshape(-1)[hp]
        mask.reshape(-1)[hp] = False
        idx = idx[~hotpix]
    empty["n_hot_pixels_rejected"] = n_hot
    if idx.size == 0:
        return Centroids.empty(**empty)
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8,
                                                               ltype=cv2.CV_32S)
    lab = labels.reshape(-1)[idx]
    raw = f.reshape(-1)[idx]
    val = raw - bkg if resid is None else resid.reshape(-1)[idx]
    order = np.lexsort((val, lab))
    lab_s = lab[order]
    last = np.flatnonzero(np.r_[lab_s[1:] != lab_s[:-1], True])  # index of each label's maximum
    peak_flat = idx[order[last]]
    peak_val = val[order[last]]
    area = stats[1:, cv2.CC_STAT_AREA].astype(np.int64)
    pi, pj = peak_flat // W, peak_flat % W

    # saturation level: the dtype maximum, a given level, or a plateau at the image's top value
    sat = dtype_max if saturation_level is None else float(saturation_level)
    top = float(raw.max())
    n_top = int(np.count_nonzero(raw == top))
    if top < sat and top > 0 and ((n_top >= 2 and _is_adc_max(top)) or n_top >= 5):
        sat = top  # e.g. 12-bit data in a 16-bit file: a plateau at 4095
    blob_max = np.full(n_lab - 1, -np.inf)
    np.maximum.at(blob_max, lab - 1, raw)
    saturated_all = blob_max >= sat

    small = area < int(min_pixels)
    # hot pixels side by side, a cosmic ray: a blob of 2-4 pixels, its peak 50 sigma or more, every pixel
    # around it (outside it) below 6 % of the peak; taken out and patched, each pixel with the median of its
    # neighbours outside the blob
    hot_blob = np.zeros(len(area), dtype=bool)
    src = f if resid is None else resid
    off = 0.0 if resid is not None else bkg
    for b in np.flatnonzero((area >= 2) & (area <= 4) & (peak_val >= 50.0 * sigma)):
        x0, y0, w, h = stats[b + 1, :4]
        ys, xs = slice(max(y0 - 1, 0), y0 + h + 1), slice(max(x0 - 1, 0), x0 + w + 1)
        mine = labels[ys, xs] == b + 1
        ring = cv2.dilate(mine.view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~mask[ys, xs]
        if (src[ys, xs][ring].astype(np.float64) - off).max() < 0.06 * peak_val[b]:
            hot_blob[b] = True
    if hot_blob.any():
        if np.shares_memory(f, img):
            f = f.copy()
        members = np.flatnonzero(np.isin(labels.reshape(-1), np.flatnonzero(hot_blob) + 1))
        fixed = []
        for fi in members:
            i, j = divmod(int(fi), W)
            nb = [(a, c) for a in range(i - 1, i + 2) for c in range(j - 1, j + 2)
                  if 0 <= a < H and 0 <= c < W and not mask[a, c]]
            fixed.append(float(np.median([f[a, c] for a, c in nb])) if nb else
                         float(bkg if resid is None else bkg[i, j]))  # (a corner's: the background)
        f.reshape(-1)[members] = np.float32(fixed)
        if resid is not None:
            resid.reshape(-1)[members] = np.float32(fixed) - bkg.reshape(-1)[members]
        n_hot += len(members)
        empty["n_hot_pixels_rejected"] = n_hot
    keep = np.flatnonzero(~small & ~hot_blob)
    n_small = int((small & ~hot_blob).sum())
    if keep.size == 0:
        return Centroids.empty(n_small_rejected=n_small, **empty)

    pi, pj, area, saturated, peak_val = pi[keep], pj[keep], area[keep], saturated_all[keep], peak_val[keep]
    peak_raw = blob_max[keep]
    comp = keep + 1  # connected-component label of each entry
    if deblend:
        extra = _split_blends(f, bkg, resid, idx, lab, val, raw, comp, area, pi, pj, sigma, sat)
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

    # PSF width from the 3-point log curvature of bright, unsaturated stars away from the border
    v3, valid3, _ = _gather(f, bkg, resid, pi, pj, 1)
    g_ok, g_uv, g_s2 = _gauss3(v3, 1, pi, pj)
    # lines narrower than any optics draws (cosmic rays, bad columns) in the 7 x 7 window (or the one given):
    # the variance across their long axis (pixels above 2 sigma, plus 1/12) below 0.2 px^2, axis ratio above 2.5,
    # the peak 20 sigma or more
    hs = int(window) // 2 if window is not None else 3
    streak = _streaks(_gather(f, bkg, resid, pi, pj, hs)[0], hs, sigma) & (peak_val >= 20.0 * sigma)
    if psf_sigma_px is None:
        good = g_ok & ~saturated & valid3.all(axis=(1, 2)) & (peak_val > 20.0 * sigma) & ~streak
        params["psf_measured"] = bool(good.any())  # by the bright unsaturated stars (none: 1.2 px assumed)
        s_eff = float(np.sqrt(np.median(g_s2[good]))) if good.any() else math.sqrt(1.2 ** 2 + 1.0 / 12.0)
        s_eff = float(np.clip(s_eff, 0.4, 5.0))
        psf_used = float(np.sqrt(max(s_eff ** 2 - 1.0 / 12.0, 0.04)))
    else:
        psf_used = float(psf_sigma_px)
        s_eff = math.sqrt(psf_used ** 2 + 1.0 / 12.0)
    h = int(window) // 2 if window is not None else int(np.clip(math.ceil(2.5 * s_eff), 2, 8))
    params["window_used"] = 2 * h + 1
    area_limit = max(MIN_EXTENDED_PX, EXTENDED_PSF_AREAS * math.pi * (3.0 * s_eff) ** 2)
    streak &= ~(area > area_limit)
    n_streaks = int(streak.sum())
    if n_streaks:  # left out before the measurement (a blended neighbour is fitted without it)
        k = ~streak
        pi, pj, comp, area, saturated, blended = pi[k], pj[k], comp[k], area[k], saturated[k], blended[k]
        peak_val, peak_raw, g_ok, g_uv = peak_val[k], peak_raw[k], g_ok[k], g_uv[k]

    vals, valid, rawv = _gather(f, bkg, resid, pi, pj, h)
    edge = ~valid.all(axis=(1, 2))
    d = np.arange(-h, h + 1, dtype=np.float64)
    X = pj[:, None, None] + d[None, None, :]  # column (u) of each window pixel
    Y = pi[:, None, None] + d[None, :, None]  # row (v)

    uv_cog = _cog(vals, X, Y, pi, pj)
    if estimator == "cog":
        uv = uv_cog
    elif estimator == "gauss3":
        uv_iw = _iwcog(vals, X, Y, uv_cog, s_eff, h, pi, pj, iterations)
        uv = np.where((g_ok & ~saturated)[:, None], g_uv, uv_iw)
    elif estimator == "iwcog":
        uv = _iwcog(vals, X, Y, uv_cog, s_eff, h, pi, pj, iterations)
    else:
        uv_iw = _iwcog(vals, X, Y, uv_cog, s_eff, h, pi, pj, iterations)
        use = valid & (rawv < sat)  # saturated pixels carry no shape information: the wings do
        uv, amp = _psf_fit(vals, use, X, Y, uv_iw, psf_used, h, pi, pj, iterations)
        if blended.any():
            # each blended star starts at its own peak; three rounds of: subtract the neighbours'
            # current PSF models from its window, refit it (kept within 1.5 px of its peak)
            b = np.flatnonzero(blended)
            uv_b = np.where(g_ok[b, None], g_uv[b], np.stack([pj[b], pi[b]], axis=1).astype(np.float64))
            frac = _psf_models(pj[b, None].astype(np.float64), pi[b, None].astype(np.float64), uv_b,
                               np.ones(len(b)), psf_used)[:, 0, 0]
            amp_b = peak_val[b] / np.maximum(frac, 1e-6)
            # ordered pairs (star, neighbour) of the same blob close enough to overlap
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
                uv_b, amp_b = _psf_fit(vb, use[b], X[b], Y[b], uv_b, psf_used, h, pi[b], pj[b], iterations,
                                       max_shift=1.5)
            uv[b] = uv_b
            vals[b] = vb

    brightness = vals.sum(axis=(1, 2))
    ratio = _axis_ratio(vals, X, Y, uv, sigma)
    # noise alone gives axis ratios up to ~1.75 below a 20-sigma peak, < 1.3 above it: judge blobs
    # with peak >= 20 sigma against max_axis_ratio, 10-20 sigma against a stricter line, fainter not
    psnr = peak_val / sigma
    ratio_limit = max_axis_ratio + 0.5 * np.clip((20.0 - psnr) / 10.0, 0.0, 1.0)
    elongated = (ratio > ratio_limit) & (psnr >= 10.0)
    # extended objects (a lit roof or tree, the Moon, a galaxy's core, glare): blobs far larger than any
    # star's footprint, even a saturated one, are not stars and would take the brightest places
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
        params=params, n_extended_rejected=n_extended, n_streaks_rejected=n_streaks,
    )


# the plain forms of the fast path's _gauss3_fast and _axis_ratio_mm (tests/test_centroid.py compares them)

_G3_STENCIL = np.array([[1.0, 1.0], [-2.0, 0.0], [1.0, -1.0]])


def _gauss3(vals, h, pi, pj):
    """Three-point Gaussian fit on the 3x3 marginals: (ok, uv, effective sigma^2); u and v as one (N, 2)."""
    c = vals[:, h - 1: h + 2, h - 1: h + 2]
    m = np.empty((len(c), 2, 3))
    c.sum(axis=1, out=m[:, 0])  # along u
    c.sum(axis=2, out=m[:, 1])  # along v
    pos = m > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        # the log-parabola's curvature lg0 - 2 lg1 + lg2 and slope lg0 - lg2 of both axes: one product
        cs = np.log(np.where(pos, m, 1.0)) @ _G3_STENCIL  # (N, 2, 2)
        cxy = cs[:, :, 0]
        d = cs[:, :, 1] / (2.0 * cxy)
        inv = 1.0 / cxy
        s2 = -0.5 * (inv[:, 0] + inv[:, 1])
    ok = pos.reshape(-1, 6).all(axis=1) & ((cxy < 0) & (np.abs(d) < 1.0)).all(axis=1)
    uv = np.empty((len(c), 2))
    uv[:, 0], uv[:, 1] = pj, pi
    uv += np.where(ok[:, None], d, 0.0)
    return ok, uv, np.where(ok, s2, np.nan)


def _streaks(vals, h, sigma):
    """Windows (centred on their blob's brightest pixel) holding a line narrower than the optics draw: about the
    weighted centre of the pixels above 2 sigma, the variance across the long axis (plus 1/12) below 0.2 px^2
    and the axis ratio above 2.5."""
    out = np.zeros(len(vals), dtype=bool)
    d = np.arange(-h, h + 1, dtype=np.float64)
    for k, v in enumerate(vals):
        w = np.where(v > 2.0 * sigma, v, 0.0)
        s = w.sum()
        if s <= 0:
            continue
        x, y = (w.sum(axis=0) @ d) / s, (w.sum(axis=1) @ d) / s
        dx, dy = d[None, :] - x, d[:, None] - y
        cov = np.array([[(w * dx * dx).sum(), (w * dx * dy).sum()], [(w * dx * dy).sum(), (w * dy * dy).sum()]]) / s
        lo, hi = np.linalg.eigvalsh(cov + np.eye(2) / 12.0)
        out[k] = lo < 0.2 and hi > 6.25 * max(lo, 1e-12)
    return out


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


def _gather(f, bkg, resid, pi, pj, h):
    """(2h+1)^2 windows around (pi, pj): background-subtracted values (0 off the image), the mask
    of pixels on the image, and the raw values."""
    H, W = f.shape
    d = np.arange(-h, h + 1)
    rows = pi[:, None, None] + d[None, :, None]
    cols = pj[:, None, None] + d[None, None, :]
    valid = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)
    rc = np.clip(rows, 0, H - 1)
    cc = np.clip(cols, 0, W - 1)
    raw = f[rc, cc].astype(np.float64)
    vals = resid[rc, cc].astype(np.float64) if resid is not None else raw - bkg
    vals[~valid] = 0.0
    return vals, valid, raw


def _iwcog(vals, X, Y, uv0, s_eff, h, pi, pj, iterations):
    """Iteratively weighted CoG with a Gaussian weight of the PSF's width.

    For a Gaussian PSF of width s and weight width s_w centred at the current estimate c, the
    weighted CoG lies at (x0 s_w^2 + c s^2) / (s^2 + s_w^2): stepping by (s^2 + s_w^2) / s_w^2 times
    the difference (2 with s_w = s) converges on the true centre x0 in a few iterations.
    """
    sw2 = s_eff * s_eff
    gainf = 2.0
    u = uv0[:, 0].copy()
    v = uv0[:, 1].copy()
    ok_all = np.ones(len(u), dtype=bool)
    for _ in range(iterations):
        g = np.exp(-((X - u[:, None, None]) ** 2 + (Y - v[:, None, None]) ** 2) / (2.0 * sw2))
        w = vals * g
        s = w.sum(axis=(1, 2))
        ok = s > 0
        ok_all &= ok
        s = np.where(ok, s, 1.0)
        cu = (w * X).sum(axis=(1, 2)) / s
        cv = (w * Y).sum(axis=(1, 2)) / s
        u = np.where(ok, u + gainf * (cu - u), u)
        v = np.where(ok, v + gainf * (cv - v), v)
        u = np.clip(u, pj - h, pj + h)
        v = np.clip(v, pi - h, pi + h)
    bad = ~ok_all | ~np.isfinite(u) | ~np.isfinite(v)
    u[bad] = uv0[bad, 0]
    v[bad] = uv0[bad, 1]
    return np.stack([u, v], axis=1)


def _psf_fit(vals, use, X, Y, uv0, s, h, pi, pj, iterations, max_shift=None):
    """Least-squares fit of a pixel-integrated Gaussian PSF (amplitude, u, v; sigma fixed).

    Model of pixel (x, y): A * [Phi((x+1/2-u)/s) - Phi((x-1/2-u)/s)] * [same in y]: exact for a
    Gaussian PSF at any sampling, so it has no pixel-phase bias; pixels off the image or saturated
    are left out. Gauss-Newton from the iwcog position, steps limited to 0.5 px.
    """
    n_st = len(vals)
    x = X[:, 0, :]  # (N, n) column coordinates
    y = Y[:, :, 0]  # (N, n) row coordinates
    w = use.astype(np.float64)
    u = uv0[:, 0].copy()
    v = uv0[:, 1].copy()
    k = 1.0 / (s * math.sqrt(2.0))
    c = 1.0 / (s * math.sqrt(2.0 * math.pi))

    def prof(t, t0):
        hi = (t + 0.5 - t0[:, None]) * k
        lo = (t - 0.5 - t0[:, None]) * k
        p = 0.5 * (erf(hi) - erf(lo))
        dp = -c * (np.exp(-hi * hi) - np.exp(-lo * lo))  # d p / d t0
        return p, dp

    fu, _ = prof(x, u)
    fv, _ = prof(y, v)
    P = fv[:, :, None] * fu[:, None, :]
    A = (w * vals * P).sum(axis=(1, 2)) / np.maximum((w * P * P).sum(axis=(1, 2)), 1e-300)
    ok = np.isfinite(A) & (A > 0)
    for _ in range(max(3, iterations)):
        fu, dfu = prof(x, u)
        fv, dfv = prof(y, v)
        P = fv[:, :, None] * fu[:, None, :]
        J = np.stack([P, A[:, None, None] * fv[:, :, None] * dfu[:, None, :],
                      A[:, None, None] * dfv[:, :, None] * fu[:, None, :]], axis=-1).reshape(n_st, -1, 3)
        r = ((vals - A[:, None, None] * P) * w).reshape(n_st, -1)
        Jw = J * w.reshape(n_st, -1, 1)
        JTJ = np.einsum("nki,nkj->nij", Jw, J) + 1e-9 * np.eye(3)
        JTr = np.einsum("nki,nk->ni", Jw, r)
        try:
            step = np.linalg.solve(JTJ, JTr[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        step = np.where(np.isfinite(step), step, 0.0)
        A = A + step[:, 0]
        u = u + np.clip(step[:, 1], -0.5, 0.5)
        v = v + np.clip(step[:, 2], -0.5, 0.5)
    lim = h if max_shift is None else max_shift
    ok &= np.isfinite(u) & np.isfinite(v) & (A > 0) & (np.abs(u - pj) <= lim) & (np.abs(v - pi) <= lim)
    uv = np.stack([np.where(ok, u, uv0[:, 0]), np.where(ok, v, uv0[:, 1])], axis=1)
    return uv, np.where(ok, A, 0.0)


def _split_blends(f, bkg, resid, idx, lab, val, raw, comp, area, pi, pj, sigma, sat, min_sep=2.5,
                  max_area=1000, max_peaks=8):
    """Secondary peaks of multi-peak blobs: (component, row, col, value, raw) arrays, or None.

    A peak is a pixel not below any of its 8 neighbours, not saturated, at least `min_sep` px from
    every accepted (brighter) peak of its blob, and separated from the nearest one by a dip: the
    lowest pixel on the straight line between them is at least max(3 sigma, 20 %) below it.
    Blobs larger than max_area pixels (not stars: a limb, a glint) are left whole; at most
    max_peaks peaks per blob.
    """
    H, W = f.shape
    big = comp[(area >= 6) & (area <= max_area)]
    if big.size == 0:
        return None
    sel = np.isin(lab, big)
    sidx, slab, sval, sraw = idx[sel], lab[sel], val[sel], raw[sel]
    ri, rj = sidx // W, sidx % W
    nb = _gather(f, bkg, resid, ri, rj, 1)[0]
    nb[:, 1, 1] = -np.inf
    ismax = (sval >= nb.reshape(len(sval), -1).max(axis=1)) & (sraw < sat)
    if not ismax.any():
        return None
    c_lab, c_val, c_i, c_j, c_raw = slab[ismax], sval[ismax], ri[ismax], rj[ismax], sraw[ismax]
    where = {int(c): k for k, c in enumerate(comp)}
    out = []
    for L in np.unique(c_lab):
        m = np.flatnonzero(c_lab == L)
        k0 = where[int(L)]
        if len(m) == 1 and c_i[m[0]] == pi[k0] and c_j[m[0]] == pj[k0]:
            continue
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
            seg = resid[si, sj] if resid is not None else f[si, sj] - bkg
            if v - float(seg.min()) >= max(3.0 * sigma, 0.2 * v):
                acc.append((i, j))
                out.append((int(L), i, j, v, float(c_raw[q])))
    if not out:
        return None
    o = np.array(out, dtype=np.float64)
    return o[:, 0].astype(np.int64), o[:, 1].astype(np.int64), o[:, 2].astype(np.int64), o[:, 3], o[:, 4]
