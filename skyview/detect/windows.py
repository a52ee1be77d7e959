"""Windowed centroiding for tracking: measure stars only around their predicted positions, all at once.

A tracked frame knows where the catalog stars should land (the predicted attitude) and how far off
they may be (the bound from the prediction's covariance). `window_centers` gives each predicted star
a square window of side 2 h + 1, h = ceil(bound + the PSF's reach + a margin) (one h for all: the
largest), and `measure_windows` measures every window in one pass of numpy, without a call per star:

1. the K windows are gathered with one fancy index into a (K, S, S) stack (pixels beyond the image
   border repeat the border pixel: a star there is flagged `edge`);
2. per window, the background is the median of the window's border pixels (4 S - 4 of them) and the
   noise their MAD (x 1.4826), floored at half the windows' median noise (a window whose border is
   flat by chance does not get a zero threshold);
3. the star is the brightest 3x3 sum of the window (a lone hot pixel cannot win over a star's
   core); it is found when its brightest pixel is k_sigma noise above the background and at least
   `min_pixels` pixels of its 3x3 neighbourhood are above that threshold;
4. its centroid is the Gaussian-weighted centroid of a sub-window of side m = 2 ceil(2.5 s) + 1
   around that peak, s^2 = psf^2 + 1/12 (the PSF integrated over a pixel): a weight of the PSF's own
   width, iterated with the step doubled, which for a Gaussian star is the fixed point at its
   centre reached in one step (x_new = x + 2 (weighted mean - x)); `ITERATIONS` steps;
5. flags: `saturated` (a sub-window pixel at the saturation level: the dtype's maximum for an
   integer image), `edge` (the sub-window reaches past the window's side or the image border: the
   star's light may be cut, or the star may be one the next window holds better).

`centroid_windows` turns the measured windows into `Centroids` (brightest first; the same star found
by two overlapping windows is kept once) with, per centroid, the solid angle of its window: the
tracking verification's chance agreement is that of a random detection within its window (a window
is searched precisely where a catalog star is expected).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skyview.detect.centroids import Centroids, row_median

PSF_REACH_SIGMAS = 3.0  # a star's light reaches this many PSF sigmas: the window grows by it
MAX_HALF_PX = 100  # a bound wider than this (pixels) is no tracking: lost-in-space instead
DEFAULT_PSF_SIGMA_PX = 1.2
ITERATIONS = 3  # Gaussian-weighted centroid steps (each doubled: one step suffices for a Gaussian star)
_MAD_TO_SIGMA = 1.4826


@dataclass
class WindowStars:
    """One entry per window (K windows): what `measure_windows` found in it."""
    found: np.ndarray  # (K,) bool: a star above the threshold
    uv: np.ndarray  # (K, 2) centroid (image pixels; NaN when not found)
    brightness: np.ndarray  # (K,) background-subtracted sum over the sub-window
    peak: np.ndarray  # (K,) brightest raw pixel of the sub-window
    n_pixels: np.ndarray  # (K,) sub-window pixels above the threshold
    saturated: np.ndarray  # (K,) bool
    edge: np.ndarray  # (K,) bool: the sub-window reaches past the window side or the image border
    background: np.ndarray  # (K,) border median
    noise: np.ndarray  # (K,) border MAD sigma (floored)
    peak_index: np.ndarray  # (K,) flat image index of the peak pixel (-1 when not found)


@dataclass
class WindowCentroids:
    centroids: Centroids  # in image pixels, brightest first
    box_sr: np.ndarray  # (N,) solid angle of the window each centroid was found in
    boxes: np.ndarray  # (K, 4) int: x0, y0, x1, y1 (exclusive, clipped to the image) of every window
    n_pixels: int  # pixels read (the windows' area)
    window: np.ndarray  # (N,) the window each centroid came from


def background_windows(img: np.ndarray, uv: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(windows, inside): of the positions uv (N, 2) at least `radius` px inside the grey image (`inside`, (N,)
    bool; the others are left out), the (n, 2 radius + 1, 2 radius + 1) float64 windows around the pixel nearest
    each, each less the median of its border pixels (the local background: vignetting, glow). One index array
    gathers them all."""
    H, W = img.shape
    inside = ((uv[:, 0] >= radius) & (uv[:, 0] < W - radius - 1) & (uv[:, 1] >= radius)
              & (uv[:, 1] < H - radius - 1))
    uv = uv[inside]
    di = np.arange(-radius, radius + 1, dtype=np.int64)
    centre = np.rint(uv[:, 1]).astype(np.int64) * W + np.rint(uv[:, 0]).astype(np.int64)
    win = img.reshape(-1).take(centre[:, None, None] + (di[:, None] * W + di[None, :])[None]).astype(np.float64)
    if len(uv):
        border = np.concatenate([win[:, [0, -1], :].reshape(len(uv), -1), win[:, 1:-1, [0, -1]].reshape(len(uv), -1)],
                                axis=1)
        win -= row_median(border)[:, None, None]
    return win, inside


def window_centers(uv: np.ndarray, half_px: np.ndarray | float, width: int, height: int
                   ) -> tuple[np.ndarray, int]:
    """The windows' centre pixels (K, 2: column, row) and their common half-size h (the largest
    ceil(half_px)); windows whose centre lies off the image are dropped."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    c = np.rint(uv).astype(np.int64)
    on = (c[:, 0] >= 0) & (c[:, 0] < width) & (c[:, 1] >= 0) & (c[:, 1] < height)
    hp = np.broadcast_to(np.asarray(half_px, dtype=np.float64), (len(uv),))
    h = int(math.ceil(float(hp.max()))) if len(hp) else 0
    return c[on], max(h, 2)


def _clamp(a, lo, hi):
    return np.minimum(np.maximum(a, lo), hi)  # np.clip, without its dispatch cost on small arrays


def _sub_side(psf_sigma_px: float) -> int:
    s_eff = math.sqrt(psf_sigma_px ** 2 + 1.0 / 12.0)
    return 2 * int(math.ceil(2.5 * s_eff)) + 1


def measure_windows(image: np.ndarray, centers: np.ndarray, half: int, *, psf_sigma_px: float | None = None,
                    k_sigma: float = 5.0, min_pixels: int = 2, saturation_level: float | None = None,
                    iterations: int = ITERATIONS) -> WindowStars:
    """Measure the star in each of the K windows of side 2 half + 1 centred on `centers` (column,
    row) of a 2-D image: see the module docstring. All windows at once (numpy)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError("measure_windows needs a 2-D (grey) image")
    H, W = img.shape
    c = np.asarray(centers, dtype=np.int64).reshape(-1, 2)
    K = len(c)
    S = 2 * int(half) + 1
    psf = float(psf_sigma_px) if psf_sigma_px and np.isfinite(psf_sigma_px) else DEFAULT_PSF_SIGMA_PX
    m = min(_sub_side(psf), S - 2 if (S - 2) % 2 else S - 3)
    r = m // 2
    off = np.arange(-half, half + 1)
    rows = c[:, 1, None] + off  # (K, S)
    cols = c[:, 0, None] + off
    stack = img[_clamp(rows, 0, H - 1)[:, :, None], _clamp(cols, 0, W - 1)[:, None, :]].astype(np.float64)

    # background and noise from the border
    border = np.concatenate([stack[:, 0, :], stack[:, -1, :], stack[:, 1:-1, 0], stack[:, 1:-1, -1]], axis=1)
    bkg = row_median(border)
    noise = _MAD_TO_SIGMA * row_median(np.abs(border - bkg[:, None]))
    floor = 0.5 * float(row_median(noise[None])[0]) if K else 0.0
    if floor <= 0:
        floor = 1.0 if img.dtype.kind in "ui" else max(float(np.median(np.abs(bkg))) * 1e-6, 1e-12)
    noise = np.maximum(noise, floor)
    thr = bkg + k_sigma * noise

    # the brightest 3x3 sum, kept r pixels inside the window when it can be
    rows3 = stack[:, :-2] + stack[:, 1:-1] + stack[:, 2:]
    box3 = rows3[:, :, :-2] + rows3[:, :, 1:-1] + rows3[:, :, 2:]
    flat = box3.reshape(K, -1).argmax(axis=1)
    pr = flat // (S - 2) + 1  # window row/column of the peak (3x3 centre)
    pc = flat % (S - 2) + 1
    kk = np.arange(K)[:, None, None]
    n3 = ((stack[kk, pr[:, None, None] + np.arange(-1, 2)[:, None], pc[:, None, None] + np.arange(-1, 2)]
           > thr[:, None, None]).sum(axis=(1, 2)))
    # the sub-window around the peak, moved inside the window where it would cross a side
    cr = _clamp(pr, r, S - 1 - r)
    cc = _clamp(pc, r, S - 1 - r)
    so = np.arange(-r, r + 1)
    sub = stack[kk, (cr[:, None] + so)[:, :, None], (cc[:, None] + so)[:, None, :]]  # (K, m, m)
    vals = sub - bkg[:, None, None]
    peak_raw = sub.reshape(K, -1).max(axis=1)
    found = (peak_raw > thr) & (n3 >= min_pixels)

    # Gaussian-weighted centroid, relative to the sub-window centre
    s2 = psf ** 2 + 1.0 / 12.0
    g = so.astype(np.float64)
    pos = np.clip(vals, 0.0, None)
    tot = pos.sum(axis=(1, 2))
    safe = np.where(tot > 0, tot, 1.0)
    x = (pos.sum(axis=1) @ g) / safe  # intensity-weighted start
    y = (pos.sum(axis=2) @ g) / safe
    for _ in range(int(iterations)):
        wx = np.exp(-0.5 * (g[None, :] - x[:, None]) ** 2 / s2)  # separable weight (K, m)
        wy = np.exp(-0.5 * (g[None, :] - y[:, None]) ** 2 / s2)
        wv = vals * wy[:, :, None] * wx[:, None, :]
        sw = wv.sum(axis=(1, 2))
        ok = sw > 0
        sw = np.where(ok, sw, 1.0)
        mx = (wv.sum(axis=1) @ g) / sw
        my = (wv.sum(axis=2) @ g) / sw
        x = np.where(ok, _clamp(x + 2.0 * (mx - x), -r, r), x)
        y = np.where(ok, _clamp(y + 2.0 * (my - y), -r, r), y)
    u = c[:, 0] - half + cc + x
    v = c[:, 1] - half + cr + y
    # edge: the sub-window had to move (the peak is within r of a window side), or it reads pixels
    # repeated from beyond the image border
    img_r = c[:, 1, None] - half + cr[:, None] + so
    img_c = c[:, 0, None] - half + cc[:, None] + so
    off_image = (img_r[:, 0] < 0) | (img_r[:, -1] >= H) | (img_c[:, 0] < 0) | (img_c[:, -1] >= W)
    edge = (cr != pr) | (cc != pc) | off_image
    if saturation_level is None:
        sat_level = float(np.iinfo(img.dtype).max) if img.dtype.kind in "ui" else math.inf
    else:
        sat_level = float(saturation_level)
    saturated = peak_raw >= sat_level
    peak_index = np.where(found, (c[:, 1] - half + pr) * W + (c[:, 0] - half + pc), -1)
    uv = np.stack([u, v], axis=1)
    uv[~found] = np.nan
    return WindowStars(found=found, uv=uv, brightness=vals.sum(axis=(1, 2)), peak=peak_raw,
                       n_pixels=(sub > thr[:, None, None]).sum(axis=(1, 2)), saturated=saturated, edge=edge,
                       background=bkg, noise=noise, peak_index=peak_index)


def window_boxes(centers: np.ndarray, half: int, width: int, height: int) -> np.ndarray:
    """(K, 4) x0, y0, x1, y1 (exclusive) of the windows, clipped to the image."""
    c = np.asarray(centers, dtype=np.int64).reshape(-1, 2)
    b = np.concatenate([c - half, c + half + 1], axis=1)
    b[:, 0::2] = _clamp(b[:, 0::2], 0, width)
    b[:, 1::2] = _clamp(b[:, 1::2], 0, height)
    return b


def centroid_windows(image: np.ndarray, centers: np.ndarray, half: int, pixel_scale_rad: float, *,
                     k_sigma: float = 5.0, psf_sigma_px: float | None = None,
                     saturation_level: float | None = None) -> WindowCentroids:
    """The stars found in the windows (`measure_windows`) as `Centroids` in image pixels, brightest
    first, each star once (two overlapping windows that found the same peak pixel give one centroid),
    with the solid angle of the window each was found in."""
    img = np.asarray(image)
    H, W = img.shape[:2]
    c = np.asarray(centers, dtype=np.int64).reshape(-1, 2)
    boxes = window_boxes(c, half, W, H)
    n_px = int(np.sum((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])))
    params = {"k_sigma": k_sigma, "windows": int(len(c)), "window_side": 2 * int(half) + 1, "window_pixels": n_px}
    if len(c) == 0:
        return WindowCentroids(Centroids.empty(image_shape=(H, W), params=params), np.zeros(0), boxes, 0,
                               np.zeros(0, dtype=np.int64))
    ws = measure_windows(img, c, half, psf_sigma_px=psf_sigma_px, k_sigma=k_sigma,
                         saturation_level=saturation_level)
    idx = np.flatnonzero(ws.found)
    _, first = np.unique(ws.peak_index[idx], return_index=True)  # one centroid per peak pixel
    idx = idx[np.sort(first)]
    idx = idx[np.argsort(-ws.brightness[idx], kind="stable")]
    n = len(idx)
    noise = float(row_median(ws.noise[None])[0])
    psf = float(psf_sigma_px) if psf_sigma_px and np.isfinite(psf_sigma_px) else DEFAULT_PSF_SIGMA_PX
    cents = Centroids(uv=ws.uv[idx], brightness=ws.brightness[idx], peak=ws.peak[idx],
                      n_pixels=ws.n_pixels[idx].astype(np.int64), saturated=ws.saturated[idx],
                      elongated=np.zeros(n, dtype=bool), edge=ws.edge[idx], blended=np.zeros(n, dtype=bool),
                      axis_ratio=np.full(n, np.nan), background_level=float(row_median(ws.background[None])[0]),
                      noise_sigma=noise, threshold=k_sigma * noise,
                      psf_sigma_px=psf, estimator="window-gauss", image_shape=(H, W), params=params)
    b = boxes[idx]
    area = ((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])).astype(np.float64)
    return WindowCentroids(cents, area * pixel_scale_rad ** 2, boxes, n_px, idx)
