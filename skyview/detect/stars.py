"""Stars of any image: the centroider at the scale of the image's stars, with trails taken out.

`skyview.detect.centroids.detect_centroids` measures stars whose PSF is a few pixels wide, as a star
tracker's optics make them. Photographs from other cameras are not always so: a 24-megapixel
camera, a slightly defocused lens or an image upscaled on export spreads each star over tens of
pixels, and bright stars saturate into flat disks. The centroider's measurement window (at most 17
px) then sees only a flat core: every saturated star gets the same brightness, the brightest-first
order that every pattern search starts from is lost, and the positions are biased.

`detect_stars` runs the centroider once, and when the stars it found are wide it bins the image
(integer factor, pixel average: `cv2.resize` INTER_AREA) until they are about a pixel
in sigma, detects again on the binned image and maps the positions back to the full image's pixels.
Stars so wide that few of them clear the threshold pixel by pixel (a defocused lens) are found the
same way: when the first pass finds fewer than a dozen, the image binned 2, 4 and 8 times is tried,
and a binning that finds at least twice as many is kept.
Faint frames (a star tracker's short exposure, 8 bits, a background of 1-2 DN) show few stars above
the threshold pixel by pixel: when fewer than a dozen are found and binning does not help, the frame
filtered by its PSF (`matched_filter_stars`, about twice the signal to noise) is searched, its hot
pixels taken out first, and kept when it finds at least three more. A frame that draws its stars narrower
than a pixel (a web-sized copy of a photograph) shows them as single pixels taken for hot pixels: when those
outnumber the stars, the frame upsampled twice is searched (`undersampled_stars`).
Then `skyview.detect.trails.trail_members` takes out satellite, aircraft and meteor trails broken into
rows of fragments. Star trackers' own images (compact PSF, no trails) pass through unchanged.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import cv2
import numpy as np

from skyview.core.errors import BadInput
from skyview.detect.centroids import Centroids, detect_centroids, row_median, to_gray
from skyview.detect.hot_pixels import patch_hot_pixels
from skyview.detect.trailed import elongated_every_way, long_trail, trail_stars, trailed_frame_read
from skyview.detect.trails import fragment_width_px, trail_members
from skyview.detect.windows import background_windows

TARGET_SIGMA_PX = 1.1  # the PSF sigma the centroider is made for: bin by floor(sigma / this)
MAX_BINNING = 16
FEW_STARS = 12  # fewer detections than this: try the image binned (stars too wide to detect), then the matched filter
MATCHED_FILTER_GAIN = 3  # the matched filter's stars are kept when they are at least this many more
MIN_BINNED_SIDE = 64  # never bin an image below this many pixels a side
UNDERSAMPLED_POINTS = 2  # a sparse frame whose hot pixels and one-pixel blobs outnumber its stars this many times
UNDERSAMPLED_MAX_PIXELS = 4_000_000  # ... is searched upsampled twice when it has at most this many pixels
UNDERSAMPLED_SIGMA_PX = 0.6  # ... and its measured stars (if any) are narrower than this
HOT_PIXEL_CENTRE_PX = 0.02  # found upsampled this close to a pixel's centre on both axes: a hot pixel
WIDTH_CHECK_STARS = 15  # the brightest detections whose widths say whether a frame's stars are wide
LOCAL_PEAK_FRACTION = 0.6  # a detection on a background map stands this share of k_sigma above its own border ...
LOCAL_MISFIT_SIGMAS = 1.0  # ... and is ranked by its own border where that lies this many sigma above the map
# A star is measured on its pixels above this fraction of its peak (so that the background's structure
# and its neighbours stay out); the RMS radius of a Gaussian cut there is this fraction of sigma:
PEAK_FRACTION = 0.1
TRUNCATED_MOMENT = math.sqrt(1.0 - math.log(1.0 / PEAK_FRACTION) * PEAK_FRACTION / (1.0 - PEAK_FRACTION))


def star_moments(image: np.ndarray, c: Centroids, idx: np.ndarray, radius: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """(sigma, flux) of detections `idx` of `c`, measured in the image around their centroids.

    Each star is measured on its pixels above the detection threshold and above a tenth of its peak
    (the width of a Gaussian so cut is corrected for), within an aperture that grows
    with its measured width (3 sigma + 2 px, from 4 px up to `radius`): sigma^2 = <r^2> / 2 and flux
    the background-subtracted sum. A saturated star is measured as the disk it is: its width is an
    upper bound on the PSF (as wide as that on the sensor) and its flux grows with the disk, where the
    centroider's window sees only the flat core. NaN for a star too near the border or with no pixel
    above the threshold.
    """
    img = to_gray(image)
    idx = np.asarray(idx, dtype=np.int64)
    sigma, flux = np.full(len(idx), np.nan), np.full(len(idx), np.nan)
    if len(idx) == 0 or not c.threshold > 0:
        return sigma, flux
    win, inside = background_windows(img, c.uv[idx], radius)
    uv = c.uv[idx][inside]
    if len(uv) == 0:
        return sigma, flux
    d = np.arange(-radius, radius + 1, dtype=np.float64)
    peak = win[:, radius - 1: radius + 2, radius - 1: radius + 2].max(axis=(1, 2))
    floor = np.maximum(c.threshold, PEAK_FRACTION * peak)[:, None, None]
    # the pixels above the floor, listed once (a star's few dozen of its window's 49 x 49): the aperture's
    # sums over them
    k, iy, ix = np.nonzero(win > floor)
    value = win[k, iy, ix]
    r2 = (d[ix] - (uv[k, 0] - np.rint(uv[k, 0]))) ** 2 + (d[iy] - (uv[k, 1] - np.rint(uv[k, 1]))) ** 2
    aperture = np.full(len(uv), 4.0)
    s_in, f_in = np.full(len(uv), np.nan), np.zeros(len(uv))
    for _ in range(5):
        w = np.where(r2 <= aperture[k] ** 2, value, 0.0)
        f_in = np.bincount(k, weights=w, minlength=len(uv))
        s_in = np.sqrt(np.bincount(k, weights=w * r2, minlength=len(uv)) / (2.0 * np.maximum(f_in, 1e-300))
                       ) / TRUNCATED_MOMENT
        s_in[f_in <= 0] = np.nan
        aperture = np.clip(3.0 * np.nan_to_num(s_in, nan=1.0) + 2.0, 4.0, float(radius))
    sigma[inside], flux[inside] = s_in, np.where(f_in > 0, f_in, np.nan)
    return sigma, flux


def psf_sigma_from_moments(image: np.ndarray, c: Centroids, brightest: int = WIDTH_CHECK_STARS) -> float:
    """The PSF sigma (pixels) of the image's stars: the median `star_moments` width of the brightest
    detections; NaN when fewer than three could be measured."""
    return _median_width(star_moments(image, c, np.arange(min(brightest, len(c))))[0])


def _median_width(sigma: np.ndarray) -> float:
    sigma = sigma[np.isfinite(sigma)]
    return float(row_median(sigma[None])[0]) if len(sigma) >= 3 else math.nan


def binning_for(sigma: float) -> int:
    """The integer binning that brings stars of PSF sigma `sigma` (pixels) near TARGET_SIGMA_PX
    (1 = leave the image; also when sigma is unknown)."""
    if not math.isfinite(sigma):
        return 1
    return int(min(MAX_BINNING, max(1, math.floor(sigma / TARGET_SIGMA_PX))))


def bin_image(image: np.ndarray, b: int) -> np.ndarray:
    """The image averaged over b x b pixel blocks (float32; a ragged right / bottom edge cropped)."""
    img = to_gray(image)
    H, W = img.shape
    h, w = H // b, W // b
    return cv2.resize(img[: h * b, : w * b].astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)


def detect_stars(image: np.ndarray, *, k_sigma: float = 5.0, binning: int | None = None,
                 reject_trails: bool = True, faint_search: bool = True, **kwargs) -> Centroids:
    """Centroids of the stars in `image`, brightest first, in the full image's pixels.

    binning: None measures the stars and bins when they are wide (see the module docstring); 1
    never bins; an integer >= 2 bins by that factor. reject_trails: take out rows of trail
    fragments. faint_search: a frame of fewer than FEW_STARS stars is searched again through the
    matched filter (`matched_filter_stars`), after a width check when its stars look compact; False
    leaves those for later (`params["faint_search"]` is then "deferred" and `fainter_stars` runs them:
    a solver tries the stars it has first, ~7.5 ms saved on a sparse frame that solves). Other keyword
    arguments go to `detect_centroids`. The binning used and the number of trail fragments taken out are in
    `params["binning"]` and `params["n_trail_rejected"]`; with `max_stars`, fragments taken out of the brightest
    measured give their places to the detections after them (the first max_stars of every detection measured).
    """
    if binning is not None and (int(binning) != binning or binning < 1):
        raise BadInput(f"binning={binning} must be a positive integer")
    c = detect_centroids(image, k_sigma=k_sigma, **kwargs)
    H, W = np.shape(image)[:2]
    trail, long_asked = trailed_frame_read(image, c) if binning is None else (None, False)
    if trail is not None:  # every star a trail (an untracked exposure): each measured whole, at mid-exposure
        c = trail_stars(image, c, trail, k_sigma=k_sigma, **kwargs)
        return _without_trails(dataclasses.replace(c, params={**c.params, "binning": 1}), reject_trails)
    b, cb, binned = (1 if binning is None else int(binning)), None, None
    moments = None  # the width check's (sigma, flux) of the brightest stars, when it ran
    first_flux = True  # the width check's fluxes are those of the first stars of c (None: of others)
    if binning is None:
        # the centroider measured its stars' width from the unsaturated bright ones: when they are
        # compact and there are enough, there is nothing to bin, the brightest saturated or not (wide blobs
        # among them that are not saturated, yet did not measure that width, are not stars of these optics: a
        # nebula's knots, a glow); when no star measured it (1.2 px assumed), only if none of the brightest is
        # saturated (a defocused lens saturates its bright stars into wide disks)
        compact = (math.isfinite(c.psf_sigma_px) and c.psf_sigma_px < 1.5
                   and (c.params.get("psf_measured", False) or not c.saturated[:WIDTH_CHECK_STARS].any()))
        # few compact stars and faint_search=False: the width check (is the frame one of wide stars that
        # binning would gather?) waits with the matched filter for `fainter_stars`
        deferred = not faint_search and compact and len(c) < FEW_STARS
        if (not compact or len(c) < FEW_STARS) and not deferred:
            # the width of the brightest that are not elongated (tracks, a storm of cosmic rays blurred by a JPEG,
            # are as wide as they are long: they made such a frame look defocused, and binned it)
            pick = np.flatnonzero(~c.elongated)[:WIDTH_CHECK_STARS]
            if len(pick) < min(3, len(c)):
                pick = np.arange(min(WIDTH_CHECK_STARS, len(c)))
            moments = star_moments(image, c, pick)
            if not np.array_equal(pick, np.arange(len(pick))):
                first_flux = None  # (not the first stars': their fluxes are measured again below)
            sigma = _median_width(moments[0])  # = psf_sigma_from_moments(image, c)
            b = binning_for(sigma)
            if b == 1 and len(c) < FEW_STARS and not sigma < 1.5:
                # so wide that few stars clear the threshold pixel by pixel: binning gathers their light
                for trial in (2, 4, 8):
                    if min(H, W) // trial < MIN_BINNED_SIDE:
                        break
                    bt = bin_image(image, trial)
                    ct = detect_centroids(bt, k_sigma=k_sigma, **_binned_kwargs(kwargs, trial))
                    if len(ct) >= max(FEW_STARS, 2 * len(c)):
                        b, cb, binned = trial, ct, bt
                        break
    if b > 1 and binning is None and not long_asked:
        # stars that look wide may be trails too long for the vote's windows (each a row of fragments): those are
        # measured whole along the trail, not binned (unless the frame was read so already and had none)
        trail = long_trail(image, c, k_sigma=k_sigma)
        if trail is not None:
            c = trail_stars(image, c, trail, k_sigma=k_sigma, **kwargs)
            return _without_trails(dataclasses.replace(c, params={**c.params, "binning": 1}), reject_trails)
    if b > 1 and min(H, W) // b >= MIN_BINNED_SIDE:
        if cb is None:
            binned = bin_image(image, b)
            cb = detect_centroids(binned, k_sigma=k_sigma, **_binned_kwargs(kwargs, b))
        # pixel centre (j) of a binned image <- pixels b*j .. b*j + b - 1 of the full image
        c = dataclasses.replace(
            cb, uv=cb.uv * b + (b - 1) / 2.0, brightness=cb.brightness * b * b, n_pixels=cb.n_pixels * b * b,
            psf_sigma_px=cb.psf_sigma_px * b, threshold=cb.threshold, image_shape=(H, W),
            params={**cb.params, "binning": b})
    else:
        b, binned = 1, image
        c = dataclasses.replace(c, params={**c.params, "binning": 1})
        if binning is None and len(c) < FEW_STARS:
            if faint_search:
                cm = matched_filter_stars(image, c, k_sigma=k_sigma, **kwargs)
                if len(cm) >= len(c) + MATCHED_FILTER_GAIN:
                    c, moments = cm, None  # (other stars: the width check's moments are not theirs)
                elif looks_undersampled(c):
                    cu = undersampled_stars(image, k_sigma=k_sigma, **kwargs)
                    if len(cu) >= len(c) + MATCHED_FILTER_GAIN:
                        c, moments = cu, None
            else:
                c.params["faint_search"] = "deferred"
    c = _saturated_by_aperture(binned, c, b, moments[1] if moments is not None and b == 1 and first_flux else None)
    if b == 1:
        kept = _on_their_own_background(image, c, k_sigma)
        m = kwargs.get("max_stars")
        if (kept.params.get("n_background_rejected") or kept.params.get("n_background_rebrightened")) \
                and c.n_unmeasured and m is not None:
            # measured places lost to the map's error, or ranks it gave: every detection measured, the first m kept
            kept = _first(_every_detection(image, c, k_sigma, kwargs), int(m))
        c = kept
        wide = not_stars_of_the_optics(image, c)
        if wide.any() and not wide.all():
            # blobs far wider than a star of the frame's PSF and of their peak (a nebula's knots, a glow's
            # ripples, a caption's letters) are ranked after the stars; where they held measured places, every
            # detection is measured and ranked so, the first m kept
            if c.n_unmeasured and m is not None:
                every = _every_detection(image, c, k_sigma, kwargs)
                c = _first(_stars_first(every, not_stars_of_the_optics(image, every)), int(m))
            else:
                c = _stars_first(c, wide)
    if binning is None and b == 1 and elongated_every_way(image, c):
        c = _round_first(c)
    out = _without_trails(c, reject_trails)
    m = kwargs.get("max_stars")
    if out.params["n_trail_rejected"] and c.n_unmeasured and m is not None:
        # trail fragments held places among the brightest m measured (a satellite's row of them, or a caption's:
        # a camera's date stamp, a watermark, each letter a blob brighter than the stars): the stars after them
        # fill those places, the first m of every detection measured, trails taken out of them all
        full = detect_stars(image, k_sigma=k_sigma, binning=binning, reject_trails=reject_trails,
                            faint_search=faint_search, **{**kwargs, "max_stars": None})
        return _first(full, int(m))
    return out


def _every_detection(image: np.ndarray, c: Centroids, k_sigma: float, kwargs: dict) -> Centroids:
    """Every detection of an unbinned frame measured (`c`: its brightest measured, with their params), its
    saturated stars' brightness from their disks and each read against its own background, as detect_stars
    reads the measured ones."""
    full = detect_centroids(image, k_sigma=k_sigma, **{**kwargs, "max_stars": None})
    full = dataclasses.replace(full, params={**c.params, **full.params, "binning": 1})
    return _on_their_own_background(image, _saturated_by_aperture(image, full, 1), k_sigma)


EXTENDED_AREAS = 4.0  # a blob over this many times the area a star of its peak spreads above the threshold ...
EXTENDED_EXTRA_PX = 4  # ... and this many pixels more is not a star of the frame's optics


def _psf_measured_compact(c: Centroids) -> bool:
    """Whether the frame's bright unsaturated stars measured its PSF under 1.5 px (and it has a threshold): the frames
    whose stars the blob tests (`extended_for_their_peak`, `flat_topped`) can tell drawn or extended light from."""
    s = c.psf_sigma_px
    return bool(c.params.get("psf_measured")) and math.isfinite(s) and s < 1.5 and c.threshold > 0


def extended_for_their_peak(c: Centroids) -> np.ndarray:
    """(N,) bool: the unsaturated detections whose blob covers more than EXTENDED_AREAS times the area a star of
    their peak would spread above the threshold, plus EXTENDED_EXTRA_PX (a Gaussian PSF of sigma s whose peak
    stands P above the background covers 2 pi s^2 ln(P / threshold) pixels above it), where the frame's PSF was
    measured compact (under 1.5 px) by its bright unsaturated stars: a nebula's knots, a glow the map does not
    follow, a caption's letters. The peak is read against the frame's level (a brighter local background makes
    the area a star may cover larger: never a star taken for a blob). None where the PSF was not measured."""
    n = len(c)
    s = c.psf_sigma_px
    if n == 0 or not _psf_measured_compact(c):
        return np.zeros(n, dtype=bool)
    above = np.maximum(c.peak - c.background_level, c.threshold)
    area = 2.0 * math.pi * (s * s + 1.0 / 12.0) * np.log(above / c.threshold)
    return ~c.saturated & (c.n_pixels > EXTENDED_AREAS * area + EXTENDED_EXTRA_PX)


FLAT_TOP_RATIO = 0.8  # a blob whose pixels above the threshold are fewer than this share of a star's of its peak ...
FLAT_TOP_HALF_AREAS = 2.0  # ... for as many above half its peak, and whose pixels above half its peak exceed this
FLAT_TOP_EXTRA_PX = 4  # many times (plus this many) the core of the frame's PSF, ...
FLAT_TOP_MIN_PEAK = 3.0  # ... its peak this many thresholds or more above its surroundings, is drawn, not a star
FLAT_TOP_RADIUS = 6  # px: the half-size of the window its pixels are counted in


def flat_topped(image: np.ndarray, c: Centroids) -> np.ndarray:
    """(N,) bool: the detections whose light is a plateau, not a star's peak (and the saturated ones whose core is
    strokes: `_saturated_strokes`), where the frame's PSF was measured compact (under 1.5 px): a label's or a
    caption's letters, a drawn mark. A Gaussian star whose
    peak stands P above its surroundings covers 2 pi s^2 ln(P / T) pixels above the threshold T and 2 pi s^2 ln 2
    above half its peak: their ratio is ln(P / T) / ln 2 whatever its width. A letter's strokes, one line of
    one brightness, put most of their pixels above half the peak: the ratio is near 1. A detection is drawn when,
    counted in the (2 FLAT_TOP_RADIUS + 1)^2 window around it less its border's median (`background_windows`),
    the ratio is under FLAT_TOP_RATIO of a star's and its pixels above half the peak exceed FLAT_TOP_HALF_AREAS
    times the PSF's core (2 pi s^2 ln 2) plus FLAT_TOP_EXTRA_PX (the photographs' stars: 1-6 such pixels; the
    letters of a chart's labels: 18 or more). Only peaks FLAT_TOP_MIN_PEAK thresholds or more above their
    surroundings are judged (the ratio of a fainter star is too near 1 to tell)."""
    n = len(c)
    out = np.zeros(n, dtype=bool)
    s = c.psf_sigma_px
    if n == 0 or not _psf_measured_compact(c):
        return out
    core = 2.0 * math.pi * (s * s + 1.0 / 12.0) * math.log(2.0)
    need = FLAT_TOP_HALF_AREAS * core + FLAT_TOP_EXTRA_PX
    img = to_gray(image)
    _saturated_strokes(img, c, out)
    # (a letter's own blob may be small: the plateau counted is its word's, as far as the window reaches)
    cand = np.flatnonzero(~c.saturated & (c.n_pixels > core)
                          & (c.peak - c.background_level >= FLAT_TOP_MIN_PEAK * c.threshold))
    if len(cand) == 0:
        return out
    # a first look, 7 x 7 around each peak against the frame's level: a star of a PSF under 1.5 px puts all but a
    # pixel or two of those above half its peak in its 3 x 3 centre (sun20's and the photographs' stars: 1,663 of
    # 1,676 with two or fewer beyond it); a stroke through the centre leaves it on both sides (drawn letters: 3+)
    H, W = img.shape
    # (column, row), a window reaching past the image's edge moved inside it: the look only passes detections on
    # to the count below, which leaves out windows that do not fit)
    ji = np.minimum(np.maximum(np.rint(c.uv[cand]).astype(np.int64), 3), np.array([W - 4, H - 4]))
    v = img.reshape(-1).take((ji[:, 1] * W + ji[:, 0])[:, None] + _window7_offsets(W)).astype(np.float64)
    half = np.maximum.reduce(v[:, :9], axis=1)
    half += c.background_level  # (v's level read as the frame's: (max + level) / 2 is half the peak above it)
    half *= 0.5
    cand = cand[np.add.reduce(v[:, 9:] >= half[:, None], axis=1) >= 3]
    if len(cand) == 0:
        return out
    r = FLAT_TOP_RADIUS
    win, inside = background_windows(img, c.uv[cand], r)
    if len(win) == 0:
        return out
    cand = cand[inside]
    peak = win[:, r - 1:r + 2, r - 1:r + 2].max(axis=(1, 2))
    t = float(c.threshold)
    judged = peak >= FLAT_TOP_MIN_PEAK * t
    above_t = np.count_nonzero((win >= t).reshape(len(win), -1), axis=1)
    above_half = np.count_nonzero((win >= 0.5 * peak[:, None, None]).reshape(len(win), -1), axis=1)
    star_ratio = np.log(np.maximum(peak, t) / t) / math.log(2.0)
    out[cand] = judged & (above_half > need) & (above_t < FLAT_TOP_RATIO * star_ratio * above_half)
    return out


STROKE_CORE = 0.9  # a saturated detection's core: its window's pixels at this share of its top or more ...
STROKE_MIN_PX = 6  # ... of this many pixels or more, ...
STROKE_SPREAD = 2.0  # ... spread this many times a disk's moment of inertia or more, is drawn strokes, not a star


def _saturated_strokes(img: np.ndarray, c: Centroids, out: np.ndarray) -> None:
    """Mark in `out` the saturated detections whose saturated core is strokes, not a disk: letters drawn at the
    image's full value (white labels, text drawn without anti-aliasing). A star saturates into a disk, whose
    STROKE_MIN_PX or more core pixels (the largest connected part of those at STROKE_CORE of the top of its window
    or more, the window FLAT_TOP_RADIUS in half-size less its border's median: one disk of a close pair) have the
    moment of inertia of a disk, N^2 / 2 pi about their centre (the photographs' saturated stars: 0.95-1.01 of it);
    a letter's strokes spread the same pixels out (3 times it and more)."""
    if not c.saturated.any():
        return
    sat = np.flatnonzero(c.saturated)
    r = FLAT_TOP_RADIUS
    win, inside = background_windows(img, c.uv[sat], r)
    if len(win) == 0:
        return
    sat = sat[inside]
    top = win.reshape(len(win), -1).max(axis=1)
    core = _largest_part(win >= STROKE_CORE * top[:, None, None])  # (one disk of a saturated pair, not both)
    n = np.count_nonzero(core, axis=1)
    xy = _window_xy(r)  # (pixels, 2) offsets
    m1 = core @ xy / np.maximum(n, 1)[:, None]
    inertia = core @ (xy * xy).sum(axis=1) - n * (m1 * m1).sum(axis=1)
    out[sat] = (n >= STROKE_MIN_PX) & (inertia > STROKE_SPREAD * n * n / (2.0 * math.pi))


def _largest_part(masks: np.ndarray) -> np.ndarray:
    """(n, side * side) bool: of each (side, side) mask of `masks`, its largest 8-connected part (the first where two
    are as large): one cv2.connectedComponents over the masks stacked with a blank row between them."""
    n, side = masks.shape[0], masks.shape[1]
    stack = np.zeros((n, side + 1, side), dtype=np.uint8)
    stack[:, :side] = masks
    _, lab = cv2.connectedComponents(stack.reshape(-1, side), connectivity=8, ltype=cv2.CV_32S)
    lab = lab.reshape(n, side + 1, side)[:, :side].reshape(n, -1)
    size = np.bincount(lab.ravel())
    size[0] = 0
    best = lab[np.arange(n), size[lab].argmax(axis=1)]
    return (lab == best[:, None]) & (best[:, None] > 0)


@functools.lru_cache(maxsize=4)
def _window_xy(r: int) -> np.ndarray:
    """(pixels, 2) float: the (dx, dy) of each pixel of a (2r + 1)^2 window, row-major."""
    d = np.arange(-r, r + 1, dtype=np.float64)
    yy, xx = np.meshgrid(d, d, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


@functools.lru_cache(maxsize=8)
def _window7_offsets(W: int) -> np.ndarray:
    """Flat offsets in a width-W image of a 7 x 7 window's pixels: the 3 x 3 centre first (9), then the others."""
    d = np.arange(-3, 4)
    off = (d[:, None] * W + d[None, :]).ravel()
    centre = ((np.abs(d)[:, None] <= 1) & (np.abs(d)[None, :] <= 1)).ravel()
    return np.concatenate([off[centre], off[~centre]])


def not_stars_of_the_optics(image: np.ndarray, c: Centroids) -> np.ndarray:
    """(N,) bool: detections that are not stars drawn by the frame's optics, to be ranked after the stars: blobs far
    wider than a star of their peak (`extended_for_their_peak`: a nebula's knots, a glow's ripples) and plateaus
    (`flat_topped`: letters, drawn marks)."""
    return extended_for_their_peak(c) | flat_topped(image, c)


def _stars_first(c: Centroids, wide: np.ndarray) -> Centroids:
    """c with the detections `wide` after the others, each group in its order; how many: params["extended_last"]."""
    out = take(c, np.argsort(wide, kind="stable"))
    out.params["extended_last"] = int(np.count_nonzero(wide))
    return out


def _on_their_own_background(image: np.ndarray, c: Centroids, k_sigma: float) -> Centroids:
    """c read against each detection's own surroundings where the background map misses the sky: around the Moon's
    glow or a lamp's halo the sky changes faster than the map's 64 px blocks follow, the map lies below it by many
    sigma over whole regions, the noise's peaks there cross the threshold by the map's error and their window sums
    add it up, so that they outrank the stars. Each detection's surroundings: the border of a window of half-size
    max(3 PSF sigmas, the measuring window's half-size + 1, 4 px), its median the local background, its noise the
    MAD of the border less the plane through it (a glow's slope taken out), never below the frame's sigma (and the
    frame's sigma where the border lies less than half a sigma above the map: such a detection stands more than
    LOCAL_PEAK_FRACTION x k_sigma of them above its border anyway).

    - A detection whose peak (the brightest pixel of its 3 x 3 centre) stands less than LOCAL_PEAK_FRACTION x
      k_sigma local sigmas above its border's median is taken out (`params["n_background_rejected"]`): a star found
      on a true background stands k_sigma sigma or more above it, and its border's median lies within a quarter
      of a sigma of the map.
    - A detection whose border lies LOCAL_MISFIT_SIGMAS frame sigmas or more above the map (the brightness it was
      ranked by, less its window's sum against the border's median, over the window's area) is ranked by that
      local sum instead (`params["n_background_rebrightened"]`); the others keep their brightness and order.

    Only frames whose background is a map (`params["background_flat"]` False) are read."""
    n = len(c)
    if n == 0 or c.params.get("background_flat", True) or not c.noise_sigma > 0:
        return c
    img = to_gray(image)
    h = int(c.params.get("window_used", 7)) // 2
    radius = max(4, h + 1, int(math.ceil(3.0 * c.psf_sigma_px)) if math.isfinite(c.psf_sigma_px) else 4)
    win, inside = background_windows(img, c.uv, radius)  # (each less its border's median)
    if len(win) == 0:
        return c
    centre = win[:, radius - 1: radius + 2, radius - 1: radius + 2].max(axis=(1, 2))
    local = win[:, radius - h: radius + h + 1, radius - h: radius + h + 1].sum(axis=(1, 2))
    misfit = (c.brightness[inside] - local) / (2 * h + 1) ** 2  # the border's median above the map, per pixel
    # the local noise where the map misses (elsewhere a detection stands k_sigma sigma above the map and its
    # border's median within half a sigma of it: it passes with the frame's sigma)
    noise = np.full(len(win), c.noise_sigma)
    suspect = np.flatnonzero(misfit >= 0.5 * c.noise_sigma)
    if len(suspect):
        ring, x, y = _ring(radius)
        r = win[suspect][:, ring]
        r = r - r.mean(axis=1, keepdims=True)
        r -= np.outer(r @ x / (x @ x), x) + np.outer(r @ y / (y @ y), y)  # (a symmetric ring: x and y orthogonal)
        noise[suspect] = np.maximum(c.noise_sigma, 1.4826 * row_median(np.abs(r - row_median(r)[:, None])))
    keep = np.ones(n, dtype=bool)
    # (a saturated star keeps its place and brightness: its core is flat at the top, its border may hold its wings)
    unsat = ~c.saturated[inside]
    keep[inside] = (centre >= LOCAL_PEAK_FRACTION * k_sigma * noise) | ~unsat
    redo = np.zeros(n, dtype=bool)
    redo[inside] = (misfit >= LOCAL_MISFIT_SIGMAS * c.noise_sigma) & unsat
    dropped, rebright = n - int(np.count_nonzero(keep)), int(np.count_nonzero(redo & keep))
    params = {**c.params, "n_background_rejected": dropped, "n_background_rebrightened": rebright}
    if dropped == 0 and rebright == 0:
        return dataclasses.replace(c, params=params)
    brightness = c.brightness.copy()
    brightness[np.flatnonzero(inside)[redo[inside]]] = local[redo[inside]]
    c = dataclasses.replace(c, brightness=brightness, params=params)
    kept = np.flatnonzero(keep)
    return take(c, kept[np.argsort(-brightness[kept], kind="stable")] if rebright else kept)


@functools.lru_cache(maxsize=16)
def _ring(radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The border of a (2 radius + 1)^2 window (a mask) and its pixels' column and row offsets from the centre."""
    d = np.arange(-radius, radius + 1, dtype=np.float64)
    ring = np.zeros((2 * radius + 1, 2 * radius + 1), dtype=bool)
    ring[[0, -1], :] = ring[:, [0, -1]] = True
    x, y = np.broadcast_to(d[None, :], ring.shape)[ring], np.broadcast_to(d[:, None], ring.shape)[ring]
    for a in (ring, x, y):
        a.flags.writeable = False
    return ring, x, y


def _round_first(c: Centroids) -> Centroids:
    """A frame whose brightest detections are mostly elongated in no direction they share (`elongated_every_way`:
    not trails, which share one however short): cosmic-ray tracks that a JPEG blurred wider than the centroider's
    streak test, a storm of them, or stars smeared by a lens's coma at the edges: the detections not elongated first (brightest first among
    them), the elongated after them in their order, so that the pattern searches start from round stars. How
    many were put last: params["elongated_last"]."""
    order = np.argsort(c.elongated, kind="stable")
    out = take(c, order)
    out.params["elongated_last"] = int(np.count_nonzero(c.elongated))
    return out


def _without_trails(c: Centroids, reject_trails: bool) -> Centroids:
    """c without the satellite, aircraft and meteor trails broken into rows of fragments (`trail_members`), when
    reject_trails; how many were taken out in params["n_trail_rejected"]."""
    n_trail = 0
    if reject_trails and len(c):
        trail = trail_members(c.uv, max_width_px=fragment_width_px(c.psf_sigma_px))
        n_trail = int(trail.sum())
        if n_trail:
            c = take(c, ~trail)
    c.params["n_trail_rejected"] = n_trail
    return c


def fainter_stars(image: np.ndarray, c: Centroids, *, k_sigma: float = 5.0, reject_trails: bool = True,
                  **kwargs) -> Centroids | None:
    """What `detect_stars(faint_search=False)` left for later on a sparse frame (its centroids `c`): the
    stars detect_stars finds at once (its width check, binning, the matched filter), bit for bit; None when
    nothing was left for later or they are the stars of `c` again."""
    if c.params.get("faint_search") != "deferred":
        return None
    full = detect_stars(image, k_sigma=k_sigma, reject_trails=reject_trails, **kwargs)
    if full.params.get("binning", 1) == 1 and "matched_filter_sigma_px" not in full.params \
            and "upsampled" not in full.params:
        return None
    return full


def looks_undersampled(c: Centroids) -> bool:
    """Whether a sparse frame's point-like rejections (hot pixels, one-pixel blobs) outnumber its stars
    UNDERSAMPLED_POINTS times over (counting MATCHED_FILTER_GAIN more stars), and the stars it did measure are
    narrower than UNDERSAMPLED_SIGMA_PX (or too faint to measure the PSF): the stars may be drawn narrower than
    a pixel, each a single bright pixel (`undersampled_stars`); a frame of at most UNDERSAMPLED_MAX_PIXELS that
    shows at least one star (those straddling pixels). (Hot pixels beside stars of a well-sampled PSF, or alone
    on a frame of none, are hot pixels.)"""
    H, W = c.image_shape
    points = int(c.n_hot_pixels_rejected) + int(c.n_small_rejected)
    narrow = not c.params.get("psf_measured") or c.psf_sigma_px < UNDERSAMPLED_SIGMA_PX
    return len(c) >= 1 and H * W <= UNDERSAMPLED_MAX_PIXELS and narrow and \
        points >= UNDERSAMPLED_POINTS * (len(c) + MATCHED_FILTER_GAIN)


def undersampled_stars(image: np.ndarray, *, k_sigma: float = 5.0, **kwargs) -> Centroids:
    """Stars of a frame that draws them narrower than a pixel (a web-sized copy of a photograph, a sensor behind
    optics in sharp focus): most are single bright pixels, which the centroider takes for hot pixels (no
    neighbour reaches 15 % of them) or leaves out as one-pixel blobs. The frame upsampled twice (bilinear: each
    pixel a peak its upsampled neighbours share) is searched and the positions mapped back (pixel x of the
    upsampled frame lies at (x + 0.5) / 2 - 0.5 of this one; window sums and areas a quarter, the PSF sigma a
    half). A hot pixel is found as a star too: the solver tries these only after the frame's own stars did not
    solve (`fainter_stars`). params["upsampled"] is 2."""
    gray = to_gray(image)
    H, W = gray.shape
    up = cv2.resize(gray, (2 * W, 2 * H), interpolation=cv2.INTER_LINEAR)
    block = 2 * int(kwargs.get("background_block", 64))  # (the background's blocks keep their size on the sky)
    cu = detect_centroids(up, k_sigma=k_sigma, **{**kwargs, "background_block": block})
    cu = dataclasses.replace(cu, uv=(cu.uv + 0.5) / 2.0 - 0.5, brightness=cu.brightness / 4.0,
                             n_pixels=np.maximum(1, cu.n_pixels // 4), psf_sigma_px=cu.psf_sigma_px / 2.0,
                             image_shape=(H, W), params={**cu.params, "binning": 1, "upsampled": 2})
    # a pixel whose neighbours hold none of its light (a hot pixel: it never went through the optics) lands on
    # its own centre to the noise's share; a star narrower than a pixel still lends its neighbours some
    off_centre = (np.abs(cu.uv - np.round(cu.uv)) > HOT_PIXEL_CENTRE_PX).any(axis=1)
    n_hot = int(np.count_nonzero(~off_centre))
    return dataclasses.replace(take(cu, off_centre), n_hot_pixels_rejected=cu.n_hot_pixels_rejected + n_hot) \
        if n_hot else cu


def matched_filter_stars(image: np.ndarray, c: Centroids, *, k_sigma: float = 5.0, **kwargs) -> Centroids:
    """Stars of a faint frame found through a filter matched to the PSF (`c`: the first pass's centroids).

    A star a few times the noise spreads its light over ~4 pi sigma^2 pixels: the frame convolved with
    the PSF (a Gaussian of the stars' sigma, 1.1 px when too few were measured) raises its signal to
    noise by sqrt(pi) sigma (about 2x, 0.75 mag deeper) at the same false-detection rate, the noise
    being measured on the filtered frame as on any other. Hot pixels are taken out first
    (`patch_hot_pixels`: the filter would spread one into a star-like blob). The centroids are measured
    on the filtered frame (a symmetric filter moves no isolated star's centroid); its noise, threshold
    and `params["matched_filter_sigma_px"]` say so."""
    gray = to_gray(image)
    psf = c.psf_sigma_px if math.isfinite(c.psf_sigma_px) and 0.5 <= c.psf_sigma_px <= 3.0 else TARGET_SIGMA_PX
    f, n_hot = patch_hot_pixels(gray, c.background_level, c.noise_sigma) if c.noise_sigma > 0 else (
        gray.astype(np.float32), 0)
    smooth = cv2.GaussianBlur(f, (0, 0), psf)
    cm = detect_centroids(smooth, k_sigma=k_sigma, **kwargs)
    return dataclasses.replace(cm, n_hot_pixels_rejected=cm.n_hot_pixels_rejected + n_hot,
                               params={**cm.params, "binning": 1, "matched_filter_sigma_px": float(psf)})


def _binned_kwargs(kwargs: dict, b: int) -> dict:
    """The centroider's options for an image binned b times: the background keeps its size on the sky."""
    block = int(kwargs.get("background_block", 64))
    return {**kwargs, "background_block": max(8, block // b)}


def _first(c: Centroids, m: int) -> Centroids:
    """The first m centroids of c, the others counted as detected but not measured (`Centroids.n_unmeasured`)."""
    if len(c) <= m:
        return c
    rest = c.saturated[m:]
    out = take(c, np.arange(m))
    return dataclasses.replace(out, n_unmeasured=c.n_unmeasured + len(c) - m,
                               n_unmeasured_saturated=c.n_unmeasured_saturated + int(np.count_nonzero(rest)))


def take(c: Centroids, keep: np.ndarray) -> Centroids:
    """The centroids selected by a boolean mask or index array, order kept."""
    per_star = {f.name: getattr(c, f.name)[keep] for f in dataclasses.fields(c)
                if isinstance(getattr(c, f.name), np.ndarray) and np.shape(getattr(c, f.name))[:1] == (len(c),)}
    return dataclasses.replace(c, **per_star, params=dict(c.params))


def _saturated_by_aperture(image: np.ndarray, c: Centroids, b: int, known_flux: np.ndarray | None = None
                           ) -> Centroids:
    """Saturated stars' brightness from their whole disk (`star_moments`), brightest first again.

    The centroider sums a window around the peak, which for a saturated star holds only its flat
    core: every saturated star would seem equally bright. `image` is the image the centroids were
    measured on (binned by b; c's positions are in full-image pixels). known_flux: `star_moments`'s flux
    of c's first stars, measured already (by the width check, b = 1): a star's moments do not depend on
    the others measured with it, so those are not measured again."""
    sat = np.flatnonzero(c.saturated)
    if len(sat) == 0:
        return c
    scaled = dataclasses.replace(c, uv=(c.uv - (b - 1) / 2.0) / b) if b > 1 else c
    if known_flux is not None:
        flux = np.empty(len(sat))
        seen = sat < len(known_flux)
        flux[seen] = known_flux[sat[seen]]
        if not seen.all():
            flux[~seen] = star_moments(image, scaled, sat[~seen])[1]
        flux *= b * b
    else:
        flux = star_moments(image, scaled, sat)[1] * b * b
    brightness = c.brightness.copy()
    brightness[sat] = np.fmax(brightness[sat], flux)
    order = np.argsort(-brightness, kind="stable")
    out = take(dataclasses.replace(c, brightness=brightness), order)
    return out
