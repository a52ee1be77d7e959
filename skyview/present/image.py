"""The one image stretch and label placement of every sink (`skyview.present.drawables`'s image half).

`stretch` turns a sensor image into 8 bit for display (the viewer's panel and texture, the recording);
`layout_labels` puts labels beside their stars, on no other label and no star, the most important first
(hiding those with no room); `place_labels` is its one-sided form. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    from skyview.core.errors import BadInput

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


# Where a label may sit around its star, tried in this order: right, left (level with the star, then
# raised and lowered by half its height), above, below (steps of the star's radius + gap + half the box;
# x right, y down: image and screen pixels).
LABEL_SIDES = ((1, 0), (-1, 0), (1, -0.5), (1, 0.5), (-1, -0.5), (-1, 0.5), (0, -1), (0, 1))


@dataclass(frozen=True)
class LabelLayout:
    """Where the labels go: `shown` (N,) bool; `centre` (N, 2) each shown box's centre (NaN where hidden);
    `size` (N, 2) width and height. Units: those of the anchors."""

    shown: np.ndarray
    centre: np.ndarray
    size: np.ndarray

    def boxes(self) -> np.ndarray:
        """(K, 4) the shown boxes as (x0, y0, x1, y1)."""
        c, h = self.centre[self.shown], self.size[self.shown] / 2.0
        return np.concatenate([c - h, c + h], axis=1)


def layout_labels(anchors: np.ndarray, sizes: np.ndarray, priority: np.ndarray, *, anchor_radius=0.0,
                  stars: np.ndarray | None = None, star_radius=0.0, gap: float = 2.0, apart: float = 0.0,
                  bounds=None, taken: np.ndarray | None = None, sides=LABEL_SIDES) -> LabelLayout:
    """Labels beside their stars, none on another label or on a shown star: greedy, most important first.

    anchors: (N, 2) the labelled stars, in a view's pixels (or any 2-D units); sizes: (N, 2) each label's
    width and height; priority: (N,) lower first (a magnitude: the brightest star keeps its label);
    anchor_radius: () or (N,) the drawn radius of each labelled star (its label keeps `gap` beyond it);
    stars: (M, 2) every other star drawn, with star_radius () or (M,): no label box may cover one (the
    labelled stars are avoided too; None: labels avoid only each other); bounds: (x0, y0, x1, y1) the
    boxes must lie inside, or (A, 4) such areas tried in turn (every side in the first, then the next);
    apart: how much nearer its own star a label must be than any other; taken:
    (K, 4) boxes (x0, y0, x1, y1) of labels placed before, which these must not overlap. Each label
    takes the first of `sides` where its box overlaps no box placed before, covers no star, is nearer its
    own star than any other labelled one by `apart` (it reads as that star's) and stays in bounds;
    a label with no such side is hidden (a more important one keeps its place).
    """
    xy = np.asarray(anchors, dtype=np.float64).reshape(-1, 2)
    n = len(xy)
    size = np.array(np.broadcast_to(np.asarray(sizes, dtype=np.float64), xy.shape))
    r_own = np.broadcast_to(np.asarray(anchor_radius, dtype=np.float64), (n,))
    avoid = stars is not None
    pts = xy if stars is None else np.concatenate([xy, np.asarray(stars, dtype=np.float64).reshape(-1, 2)])
    rad = np.concatenate([r_own, np.broadcast_to(np.asarray(star_radius, dtype=np.float64), (len(pts) - n,))])
    # the labelled stars other than each label's own (a mark within its radius is its own)
    other = np.hypot(*(xy[None, :, :] - xy[:, None, :]).transpose(2, 0, 1)) >= np.maximum(r_own, 1e-9)[:, None]
    shown = np.zeros(n, dtype=bool)
    centre = np.full((n, 2), np.nan)
    boxes = np.zeros((0, 4)) if taken is None else np.asarray(taken, dtype=np.float64).reshape(-1, 4)
    areas = [None] if bounds is None else [np.asarray(b, dtype=np.float64) for b in np.reshape(bounds, (-1, 4))]
    for i in np.argsort(np.asarray(priority, dtype=np.float64), kind="stable"):
        half = size[i] / 2.0
        for area, (dx, dy) in ((a, s) for a in areas for s in sides):
            c = xy[i] + np.array([dx * (r_own[i] + gap + half[0]), dy * (r_own[i] + gap + half[1])])
            lo, hi = c - half, c + half
            if area is not None and (np.any(lo < area[:2]) or np.any(hi > area[2:])):
                continue
            if len(boxes) and np.any((lo[0] < boxes[:, 2]) & (hi[0] > boxes[:, 0]) & (lo[1] < boxes[:, 3])
                                     & (hi[1] > boxes[:, 1])):
                continue  # on a label placed before
            if avoid:
                near = np.clip(pts, lo, hi) - pts  # from each star to the nearest point of the box
                clear = np.sqrt(np.einsum("ij,ij->i", near, near)) - rad  # each star's mark's distance from it
                if np.any(clear < 0) or np.any(np.all((pts > lo) & (pts < hi), axis=1)):
                    continue  # on a star
                if np.any(clear[:n][other[i]] < clear[i] + apart):
                    continue  # nearer another labelled star than its own: it would read as that star's label
            shown[i], centre[i] = True, c
            boxes = np.concatenate([boxes, [[lo[0], lo[1], hi[0], hi[1]]]])
            break
    return LabelLayout(shown, centre, size)


def place_labels(xy: np.ndarray, priority: np.ndarray, sizes: np.ndarray, gap: float = 2.0) -> np.ndarray:
    """Which labels to show so that none overlaps another: greedy, most important first.

    xy: (N, 2) label anchors (any 2-D units: pixels, degrees); priority: (N,) lower first (a magnitude:
    the brightest star keeps its label); sizes: (N, 2) label width and height in the same units; the
    box sits beside the anchor, to its right (`layout_labels` with one side and no stars to avoid).
    Returns a bool mask: True for the labels kept.
    """
    return layout_labels(xy, sizes, priority, gap=gap, sides=((1, 0),)).shown
