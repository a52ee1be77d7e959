"""The one image stretch and label placement of every sink (`skyview.present`'s image half).

`stretch` turns a sensor image into 8 bit for display (the viewer's panel and texture, the recording);
`place_labels` keeps the labels that do not overlap a more important one. Pure numpy.
"""

from __future__ import annotations

import numpy as np

def _levels(f: np.ndarray) -> tuple[float, float, float]:
    """Background median, noise sigma (MAD) and maximum, from a subsample."""
    sample = np.asarray(f[:: max(1, f.shape[0] // 256), :: max(1, f.shape[1] // 256)], dtype=np.float64)
    bg = float(np.median(sample))
    sigma = 1.4826 * float(np.median(np.abs(sample - bg)))
    hi = float(np.max(f))
    if sigma <= 0:
        sigma = max((hi - bg) / 1000.0, 1e-6)
    return bg, sigma, hi


def _curve(x: np.ndarray, bg: float, sigma: float, hi: float, floor_sigmas: float) -> np.ndarray:
    soft = 3.0 * sigma
    top = max(min(hi - bg, 400.0 * sigma) + floor_sigmas * sigma, soft)  # the brightest stars may saturate
    y = np.arcsinh(np.maximum(x - bg + floor_sigmas * sigma, 0.0) / soft) / np.arcsinh(top / soft)
    return np.clip(y * 255.0 + 0.5, 0, 255).astype(np.uint8)


def stretch(image: np.ndarray, floor_sigmas: float = 2.0) -> np.ndarray:
    """8-bit display version of an 8- or 16-bit (or float) star image: the one stretch of every sink.

    asinh stretch: the background sits just above black, noise stays visible, stars do not all
    saturate (white at 400 sigma above the background); works the same for a 16-bit simulator frame and
    an 8-bit photograph. Integer images go through a look-up table. floor_sigmas: how many noise sigmas
    below the background map to black (negative: the background itself is black).
    """
    from skyview.errors import BadInput

    a = np.asarray(image)
    if a.size == 0:
        raise BadInput("the image is empty")
    bg, sigma, hi = _levels(a)
    if a.dtype in (np.uint8, np.uint16):
        lut = _curve(np.arange(256 if a.dtype == np.uint8 else 65536, dtype=np.float64), bg, sigma, hi, floor_sigmas)
        return lut[a]
    return _curve(a.astype(np.float64), bg, sigma, hi, floor_sigmas)


TEXTURE_FLOOR_SIGMAS = -2.5  # the sensor image on the sky (viewer texture, recording): black background


def stretch_note(image: np.ndarray, floor_sigmas: float = 2.0) -> str:
    a = np.asarray(image)
    bg, sigma, hi = _levels(a)
    bits = f"{a.dtype.itemsize * 8}-bit" if np.issubdtype(a.dtype, np.integer) else str(a.dtype)
    return (f"{bits} image shown with an asinh stretch to 8 bit (black at the background {bg:.1f} "
            f"{-floor_sigmas:+g} sigma, softening 3 sigma = {3 * sigma:.1f}, white at min(max, 400 sigma))")


def place_labels(xy: np.ndarray, priority: np.ndarray, sizes: np.ndarray, gap: float = 2.0) -> np.ndarray:
    """Which labels to show so that none overlaps another: greedy, most important first.

    xy: (N, 2) label anchors (any 2-D units: pixels, degrees); priority: (N,) lower first (a magnitude:
    the brightest star keeps its label); sizes: (N, 2) label width and height in the same units; the
    box sits beside the anchor, to its right. Returns a bool mask: True for the labels kept.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    sizes = np.broadcast_to(np.asarray(sizes, dtype=np.float64), xy.shape)
    keep = np.zeros(len(xy), dtype=bool)
    boxes: list[np.ndarray] = []
    for i in np.argsort(np.asarray(priority, dtype=np.float64), kind="stable"):
        lo = xy[i] + np.array([gap, -sizes[i, 1] / 2])
        hi = lo + sizes[i]
        if all(np.any(hi <= b[0]) or np.any(lo >= b[1]) for b in boxes):
            keep[i] = True
            boxes.append(np.array([lo, hi]))
    return keep
