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
LONG_TRAIL_MAX_PIXELS = 2_000_000  # the long-trail vote (`long_trail`) reads a frame binned to this many pixels ...
LONG_TRAIL_SMOOTH_PX = 2.0  # ... smoothed by a Gaussian of this sigma ...
LONG_TRAIL_BLOBS = 15  # ... its brightest blobs that many at most ...
LONG_TRAIL_RATIO = 3.0  # ... voting when this many times longer than wide ...
LONG_TRAIL_MIN_VOTERS = 4  # ... and at least this many of them, on as many distinct lines, pointing one way ...
LONG_TRAIL_LENGTH_AGREE = 0.25  # ... as long as their median weighted by light to this fraction


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
    of round stars (the module docstring); where most detections are elongated but too few are left to vote
    (trails longer than the vote's windows, broken into rows of fragments), `long_trail`'s."""
    return trailed_frame_read(image, c)[0]


def trailed_frame_read(image: np.ndarray, c: Centroids) -> tuple[tuple[float, float] | None, bool]:
    """(`trailed_frame`'s answer, whether it is `long_trail`'s no with two voters: then no stricter
    `long_trail` of the same frame can say yes, and `detect_stars` does not smooth the frame again)."""
    vote = _direction_vote(image, c)
    if vote is None and may_be_trailed(c):  # (elongated, but fragments of trails longer than the vote's windows?)
        trail = long_trail(image, c, min_voters=2)
        return trail, trail is None
    if vote is None or not shared_direction(vote[2]):
        return None, False
    length, angle2, along = vote
    median_length = float(row_median(length[along][None])[0])
    if median_length < TRAIL_MIN_LENGTH_PX:
        return None, False
    a2 = angle2[along]
    direction = math.degrees(0.5 * math.atan2(float(np.mean(np.sin(a2))), float(np.mean(np.cos(a2))))) % 180.0
    if median_length >= TRAIL_WINDOW:
        # the windows may cut such trails short (they see +-TRAIL_WINDOW around a point that may lie anywhere on
        # one): the trails measured whole, when they are found longer in this direction
        whole = long_trail(image, c, min_voters=2)
        if whole is not None and whole[0] > median_length and _angle_apart(whole[1], direction) <= \
                TRAIL_ANGLE_TOLERANCE_DEG:
            return whole, False
    return (median_length, direction), False


def _angle_apart(a_deg: float, b_deg: float) -> float:
    """The angle between two directions (degrees, modulo 180)."""
    d = abs(a_deg - b_deg) % 180.0
    return min(d, 180.0 - d)


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


def _filtered_blobs(image: np.ndarray, c: Centroids, smooth, k_sigma: float, background_block: int,
                    saturation_level: float | None = None, patch_hot: bool = True,
                    saturated_px: np.ndarray | None = None):
    """The frame (`c`: its centroids), its hot pixels patched (unless not patch_hot) and its background taken out,
    filtered by `smooth` (float32 frame -> float32 frame), its 8-connected blobs above k_sigma times the filtered
    frame's own noise: a dict of per-blob arrays (weighted sum `s`, centre `mx`, `my`, second moments `sxx`, `syy`,
    `sxy`, `area`, `peak`: the brightest raw value, `saturated`: a raw value at saturation_level (None: the dtype's
    largest, or the frame's largest when five pixels or more share it, as the centroider decides) or, where
    `saturated_px` (a boolean frame) is given, a pixel of it, `edge`: cut by the border) and the number of hot
    pixels patched (`n_hot`). Memory: about 10 bytes a pixel."""
    img = to_gray(image)
    H, W = img.shape
    raw = img
    if raw.dtype.kind == "f" and not np.isfinite(raw).all():  # as the centroider does: the others' median
        raw = np.where(np.isfinite(raw), raw, np.float32(np.nanmedian(raw))).astype(np.float32)
    f, n_hot = patch_hot_pixels(raw, c.background_level, c.noise_sigma) if patch_hot and c.noise_sigma > 0 else (
        raw.astype(np.float32), 0)
    bkg = estimate_background(f, background_block)[0]
    if np.isscalar(bkg):
        f -= np.float32(bkg)
    else:
        np.subtract(f, bkg, out=f, dtype=np.float32)
    del bkg
    smooth = smooth(f)
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

    s = sums(w)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx, my = sums(w * x) / s, sums(w * y) / s
        sxx, syy, sxy = sums(w * x * x) / s - mx * mx, sums(w * y * y) / s - my * my, sums(w * x * y) / s - mx * my
    x0, y0 = stats[1:, cv2.CC_STAT_LEFT], stats[1:, cv2.CC_STAT_TOP]
    x1, y1 = x0 + stats[1:, cv2.CC_STAT_WIDTH], y0 + stats[1:, cv2.CC_STAT_HEIGHT]
    peak = np.full(n, -np.inf)
    np.maximum.at(peak, lab_px, np.asarray(raw, dtype=np.float64).reshape(-1)[fi])
    if saturated_px is None:
        saturated = peak[1:] >= _saturation_top(raw, saturation_level)
    else:
        saturated = np.bincount(lab_px, weights=saturated_px.reshape(-1)[fi], minlength=n)[1:] > 0
    return {"s": s, "mx": mx, "my": my, "sxx": sxx, "syy": syy, "sxy": sxy,
            "area": stats[1:, cv2.CC_STAT_AREA].astype(np.int64), "peak": peak[1:], "saturated": saturated,
            "edge": (x0 == 0) | (y0 == 0) | (x1 >= W) | (y1 >= H), "n_hot": n_hot}


def _saturation_top(raw: np.ndarray, saturation_level: float | None = None) -> float:
    """The raw value at which a pixel is saturated: saturation_level, else the dtype's largest, or the frame's
    largest when five pixels or more share it (as the centroider decides)."""
    if saturation_level is not None:
        return float(saturation_level)
    top = float(np.iinfo(raw.dtype).max) if raw.dtype.kind in "ui" else math.inf
    frame_max = float(np.max(raw))
    if frame_max < top and np.count_nonzero(raw == frame_max) >= 5:
        top = frame_max
    return top


def _axes(sxx: np.ndarray, syy: np.ndarray, sxy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The second moments' largest and smallest eigenvalues (the blob's variance along and across its axis)."""
    root = np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
    return 0.5 * (sxx + syy) + root, 0.5 * (sxx + syy) - root


def long_trail(image: np.ndarray, c: Centroids, k_sigma: float = 5.0, background_block: int = 64,
               min_voters: int = LONG_TRAIL_MIN_VOTERS) -> tuple[float, float] | None:
    """(length px, direction deg in [0, 180)) of trails too long for the vote's windows, or None.

    A trail longer than the vote's windows (TRAIL_WINDOW: ~45 px), its light spread thin, crosses the
    threshold only in places: the centroider sees each as a row of fragments, which the vote takes for a
    satellite's (`skyview.detect.trails`), or which look round and wide enough to make the frame binned. Here
    the frame is smoothed by a Gaussian of LONG_TRAIL_SMOOTH_PX (the fragments of one trail join; its signal
    to noise grows with it) and its blobs above k_sigma times the smoothed frame's noise are measured whole. Among
    the LONG_TRAIL_BLOBS brightest that do not touch the border, those at least TRAIL_MIN_LENGTH_PX long and
    LONG_TRAIL_RATIO times longer than wide vote: a frame of trails when at least `min_voters` of them,
    and TRAIL_AGREE_FRACTION of the voters, lie within TRAIL_ANGLE_TOLERANCE_DEG of one direction, and
    `min_voters` of those, on as many distinct lines (not one satellite's row of pieces), are as long as their
    median weighted by light (a faint trail crosses the threshold over part of its length only) to
    LONG_TRAIL_LENGTH_AGREE. That median is the length, their mean the direction. (`trailed_frame` asks for two
    where most detections are elongated already; `detect_stars`, about to bin a frame of wide stars, for
    LONG_TRAIL_MIN_VOTERS.) A frame of round stars has no such blobs; a satellite or an aircraft
    is one line, or a few side by side. A frame of more than LONG_TRAIL_MAX_PIXELS is read binned to that
    many. Costs one smoothing and one labelling of the frame (~16 ms for 1024 x 768, ~40 ms for 24 megapixels):
    run only where the vote could not decide or would cut the trails short, and before a frame of wide stars
    is binned."""
    img = to_gray(image)
    H, W = img.shape
    # a large frame is read binned to LONG_TRAIL_MAX_PIXELS or fewer (pixel averages: a hot pixel fades into its
    # block, the trails long enough to be here stay longer than TRAIL_MIN_LENGTH_PX)
    scale = math.ceil(math.sqrt(H * W / LONG_TRAIL_MAX_PIXELS)) if H * W > LONG_TRAIL_MAX_PIXELS else 1
    saturated_px = None
    if scale > 1:
        crop = img[: H // scale * scale, : W // scale * scale]
        size = (W // scale, H // scale)
        # (a binned pixel holding a saturated one is saturated: the block average hides it)
        saturated_px = cv2.resize((crop >= _saturation_top(crop)).astype(np.float32), size,
                                  interpolation=cv2.INTER_AREA) > 0
        img = cv2.resize(crop.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    blobs = _filtered_blobs(img, c, lambda f: cv2.GaussianBlur(f, (0, 0), LONG_TRAIL_SMOOTH_PX,
                                                                borderType=cv2.BORDER_REPLICATE),
                            k_sigma, background_block, patch_hot=scale == 1, saturated_px=saturated_px)
    # (saturated blobs do not vote: a bright star bleeds along its column)
    keep = np.flatnonzero(~blobs["edge"] & ~blobs["saturated"] & (blobs["area"] >= 3) & (blobs["s"] > 0))
    keep = keep[np.argsort(-blobs["s"][keep], kind="stable")][:LONG_TRAIL_BLOBS]
    if len(keep) < min_voters:
        return None
    m = np.stack([blobs["sxx"][keep], blobs["syy"][keep], blobs["sxy"][keep]], axis=1)
    length, angle2 = _trail_shape(m)
    lam1, lam2 = _axes(m[:, 0], m[:, 1], m[:, 2])
    length *= scale
    voter = (length >= TRAIL_MIN_LENGTH_PX) & (lam1 >= LONG_TRAIL_RATIO ** 2 * np.maximum(lam2, 1e-12))
    if np.count_nonzero(voter) < min_voters:
        return None
    a2 = angle2[voter]
    mean2 = math.atan2(float(np.mean(np.sin(a2))), float(np.mean(np.cos(a2))))
    along = np.abs(np.angle(np.exp(1j * (a2 - mean2)))) <= math.radians(2.0 * TRAIL_ANGLE_TOLERANCE_DEG)
    if np.count_nonzero(along) < max(min_voters, TRAIL_AGREE_FRACTION * len(a2)):
        return None
    a2, lengths, weight = a2[along], length[voter][along], blobs["s"][keep][voter][along]
    # the median length weighted by light: a faint trail crosses the threshold over part of its length only
    order = np.argsort(lengths, kind="stable")
    median_length = float(lengths[order][np.searchsorted(np.cumsum(weight[order]), 0.5 * float(weight.sum()))])
    same = np.abs(lengths - median_length) <= LONG_TRAIL_LENGTH_AGREE * median_length
    if np.count_nonzero(same) < min_voters:
        return None
    a2 = a2[same]
    mean2 = math.atan2(float(np.mean(np.sin(a2))), float(np.mean(np.cos(a2))))
    direction = math.degrees(0.5 * mean2) % 180.0
    # distinct lines: the voters' centres across the direction, apart by more than a trail's width
    cx, cy = blobs["mx"][keep][voter][along][same], blobs["my"][keep][voter][along][same]
    across = np.sort(-math.sin(0.5 * mean2) * cx + math.cos(0.5 * mean2) * cy) * scale
    width = 2.0 * fragment_width_px(c.psf_sigma_px) + 2.0 * LONG_TRAIL_SMOOTH_PX * scale
    if 1 + np.count_nonzero(np.diff(across) > width) < min_voters:
        return None
    return median_length, direction


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
    length, direction = trail
    kernel = line_kernel(length, direction)
    b = _filtered_blobs(image, c, lambda f: cv2.filter2D(f, -1, kernel, borderType=cv2.BORDER_REPLICATE), k_sigma,
                        background_block, saturation_level)
    s, mx, my, sxx, syy, sxy, area, edge = (b[k] for k in ("s", "mx", "my", "sxx", "syy", "sxy", "area", "edge"))
    peak, saturated, n_hot = b["peak"], b["saturated"], b["n_hot"]
    lam1, lam2 = _axes(sxx, syy, sxy)
    long_axis = np.sqrt(12.0 * (lam1 - lam2))  # a filtered trail: about 1.4 trails (a line filtered by a line)
    lam2 = np.maximum(lam2, 1e-12)
    doubled = np.arctan2(2.0 * sxy, sxx - syy) - math.radians(2.0 * direction)
    off = np.degrees(np.abs(np.angle(np.exp(1j * doubled)))) / 2.0  # from the trail's direction
    one_trail = ((long_axis <= TRAIL_LONGEST * length + 4.0)
                 & ((long_axis < 0.5 * length) | (off <= TRAIL_SHAPE_ANGLE_DEG)))
    small = area < min_pixels
    keep = np.flatnonzero(~small & ~edge & one_trail & (s > 0))
    ratio = np.sqrt(np.maximum(lam1, 0.0) / lam2)
    order = keep[np.argsort(-s[keep], kind="stable")]
    n_all = len(order)
    if max_stars is not None:
        order = order[: int(max_stars)]
    params = {**c.params, "trailed": {"length_px": float(length), "direction_deg": float(direction)}}
    return Centroids(uv=np.stack([mx[order], my[order]], axis=1), brightness=s[order], peak=peak[order],
                     n_pixels=area[order], saturated=saturated[order], elongated=ratio[order] > 1.4,
                     edge=edge[order], blended=np.zeros(len(order), dtype=bool), axis_ratio=ratio[order],
                     background_level=c.background_level, noise_sigma=c.noise_sigma, threshold=c.threshold,
                     n_hot_pixels_rejected=n_hot, n_small_rejected=int(np.count_nonzero(small)),
                     n_extended_rejected=int(np.count_nonzero(~one_trail & ~small)), n_unmeasured=n_all - len(order),
                     n_unmeasured_saturated=int(np.count_nonzero(saturated[keep]) - np.count_nonzero(saturated[order])),
                     psf_sigma_px=c.psf_sigma_px, estimator="trail", image_shape=(H, W), params=params)
