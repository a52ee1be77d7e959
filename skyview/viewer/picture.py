"""The sensor image for display: stretched to 8 bit, centroids marked, numbered and coloured.

The stretch and the colours are `skyview.present.drawables`'s (the recorder uses the same). Pure OpenCV / numpy: the viewer puts the result in its side panel and on the camera frustum.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from skyview.core.errors import BadInput
from skyview.detect.centroids import camera_raw_message, check_pixel_count, finite_image, max_image_pixels, to_gray
from skyview.io.fits import is_fits, read_fits
from skyview.present.drawables import OUTCOME_RGB, PALETTE, TEXTURE_FLOOR_SIGMAS, place_labels, stretch  # noqa: F401  (one palette, one stretch)

HIGHLIGHT_RGB = PALETTE["observed"]
MAX_UPLOAD_BYTES = 64 * 1024 * 1024


def decode_image_bytes(data: bytes, name: str = "upload") -> np.ndarray:
    """A grey image from the bytes of an uploaded PNG / JPEG / TIFF (any format OpenCV decodes) or FITS (row 0
    at the top unless its header says TOP-DOWN, as `skyview solve` reads it; one the other way up solves as a
    mirror image, its rows turned over)."""
    if not data:
        raise BadInput(f"{name} is empty (0 bytes)")
    if len(data) > MAX_UPLOAD_BYTES:
        raise BadInput(f"{name} is {len(data) / 1e6:.0f} MB: the viewer takes images up to "
                       f"{MAX_UPLOAD_BYTES // (1024 * 1024)} MB")
    if is_fits(data[:16]):
        return finite_image(read_fits(name, max_image_pixels(), content=bytes(data))[0], name)
    check_pixel_count(data, name)
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None:
        raise BadInput(camera_raw_message(name) or f"{name} is not an image (PNG, JPEG, TIFF or FITS expected)")
    img = to_gray(img)
    if img.ndim != 2 or img.size == 0:
        raise BadInput(f"{name} is not a usable image (shape {img.shape})")
    if img.shape[0] < 16 or img.shape[1] < 16:
        raise BadInput(f"{name} is {img.shape[1]}x{img.shape[0]}: too small (at least 16x16 pixels)")
    return img


def texture(image: np.ndarray, max_side: int = 1024, floor: int = 14) -> np.ndarray:
    """RGB texture of the sensor image for the 3-D frustum, at most max_side pixels a side.

    The background noise is cut (it would triple the JPEG for nothing at this scale): black below
    2.5 sigma above the background, lifted to a flat `floor` grey so that the sensor stays visible.
    """
    g = np.maximum(stretch(image, floor_sigmas=TEXTURE_FLOOR_SIGMAS), floor).astype(np.uint8)
    h, w = g.shape
    shrink = min(1.0, max_side / max(h, w))
    # a star is a few pixels wide: widen it so that it survives the texture's shrink on screen
    g = cv2.dilate(g, np.ones((3, 3) if shrink > 0.6 else (5, 5), np.uint8))
    return cv2.cvtColor(_fit(g, max_side), cv2.COLOR_GRAY2RGB)


def _fit(gray8: np.ndarray, max_side: int) -> np.ndarray:
    h, w = gray8.shape
    s = min(1.0, max_side / max(h, w))
    if s >= 1.0:
        return gray8
    return cv2.resize(gray8, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)


def panel_base(gray8: np.ndarray, size: int = 560) -> np.ndarray:
    """The stretched image resized for the side panel (largest side `size`); annotate draws on it."""
    h, w = gray8.shape
    s = size / max(h, w)
    if s < 0.75:  # keep faint stars: spread each over the pixels the shrink will average
        k = int(min(5, round(1.0 / s)))
        gray8 = cv2.dilate(gray8, np.ones((k, k), np.uint8))
    return cv2.resize(gray8, (max(1, round(w * s)), max(1, round(h * s))),
                      interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)


def annotate(base: np.ndarray, source_shape: tuple[int, int], uv: np.ndarray, outcomes: list[str], *,
             highlight=(), pattern=None, max_numbers: int = 40, grid=None, figures=None) -> np.ndarray:
    """RGB panel image: centroids ringed in their outcome colour and numbered by brightness.

    base: `panel_base` of the image; source_shape: (H, W) of the sensor image the centroids are in;
    highlight: centroid indices the current step uses (thick yellow ring); pattern: (E, 2) centroid
    index pairs joined by a line (the pair / triangle the step measured); grid: the RA/Dec lines of the
    solved image (`skyview.present.sky_grid.image_grid`), drawn under the rings, labelled where they
    enter the image; figures: the constellation figures over it (`skyview.present.constellations.
    image_figures`), with their names. Labels that would overlap one placed before them are left out
    (the constellations' names first, then the grid's).
    """
    img = base
    size = max(img.shape)
    s = img.shape[1] / source_shape[1]
    rgb = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    p = (uv + 0.5) * s - 0.5  # pixel centres scale about the sensor edge
    hl = {int(i) for i in highlight}
    r = max(5, round(size / 90))
    if grid or figures:
        _draw_sky_lines(rgb, grid or [], figures or [], s, round(max(0.35, size / 1600), 3))
    if pattern is not None:
        for a, b in np.asarray(pattern, dtype=np.int64).reshape(-1, 2):
            if a < len(p) and b < len(p):
                cv2.line(rgb, _pt(p[a]), _pt(p[b]), HIGHLIGHT_RGB, 1, cv2.LINE_AA)
    scale = round(max(0.35, size / 1400), 3)
    numbered = numbers_placed(p[:max_numbers], r, scale, hl)
    for i in range(len(p)):
        c = OUTCOME_RGB.get(outcomes[i] if i < len(outcomes) else "unidentified", OUTCOME_RGB["unidentified"])
        cv2.circle(rgb, _pt(p[i]), r, c, 1, cv2.LINE_AA)
        if i in hl:
            cv2.circle(rgb, _pt(p[i]), r + 3, HIGHLIGHT_RGB, 2, cv2.LINE_AA)
        if i < len(numbered) and numbered[i]:
            _label(rgb, str(i), int(round(p[i, 0] + r + 1)), int(round(p[i, 1] - r + 2)), scale, c)
    return rgb


GRID_RGB = (80, 150, 210)
FIGURE_RGB = (175, 150, 225)


def _draw_sky_lines(rgb: np.ndarray, grid, figures, s: float, scale: float) -> None:
    """The RA/Dec lines and the constellation figures (sensor pixels scaled by s), then their labels inside
    the image edge: a constellation's name at its anchor, a grid line's where it enters the image."""
    H, W = rgb.shape[:2]
    for items, colour in ((grid, GRID_RGB), (figures, FIGURE_RGB)):
        for g in items:
            for run in g.runs:
                q = np.round((np.asarray(run) + 0.5) * s - 0.5).astype(np.int32)
                cv2.polylines(rgb, [q.reshape(-1, 1, 2)], False, colour, 1, cv2.LINE_AA)
    # (text, colour, anchor in sensor pixels), in the order they claim their place
    labels = [(f.name, FIGURE_RGB, f.anchor) for f in figures] + [(g.label, GRID_RGB, g.anchor) for g in grid]
    if not labels:
        return
    anchors, sizes = [], []
    for text, _, anchor in labels:
        fill, _, top = _text_masks(text, scale)
        x, y = ((np.asarray(anchor) + 0.5) * s - 0.5)
        x = float(np.clip(x + 3, 2, W - fill.shape[1] - 2))
        y = float(np.clip(y + top + 3, top + 2, H - 4))
        anchors.append((x, y - top + fill.shape[0] / 2.0))
        sizes.append((fill.shape[1], fill.shape[0]))
    shown = place_labels(np.array(anchors), np.arange(len(anchors), dtype=np.float64), np.array(sizes), gap=2.0)
    for (text, colour, _), (x, y), ok in zip(labels, anchors, shown):
        if ok:
            fill, _, top = _text_masks(text, scale)
            _label(rgb, text, int(round(x)), int(round(y - fill.shape[0] / 2.0 + top)), scale, colour)


def numbers_placed(p: np.ndarray, r: int, scale: float, highlight: set[int]) -> np.ndarray:
    """Which centroid numbers to write so that none overlaps another: the step's stars first, then by
    brightness (`present.place_labels`). Each number sits at the upper right of its ring."""
    boxes = []
    for i in range(len(p)):
        fill, _, top = _text_masks(str(i), scale)
        boxes.append((p[i, 0] + r + 1, p[i, 1] - r + 2 - top + fill.shape[0] / 2.0, fill.shape[1], fill.shape[0]))
    b = np.array(boxes, dtype=np.float64).reshape(-1, 4)
    priority = np.arange(len(p), dtype=np.float64) - np.isin(np.arange(len(p)), list(highlight)) * len(p)
    return place_labels(b[:, :2], priority, b[:, 2:], gap=0.0)


@lru_cache(maxsize=512)
def _text_masks(text: str, scale: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Coverage masks (fill, dark outline) of a short text, and its baseline offset; rendered once."""
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    pad = 2
    m = np.zeros((h + base + 2 * pad, w + 2 * pad), np.uint8)
    cv2.putText(m, text, (pad, pad + h), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 1, cv2.LINE_AA)
    outline = cv2.dilate(m, np.ones((3, 3), np.uint8))
    return m, outline, pad + h


def _label(rgb: np.ndarray, text: str, x: int, y: int, scale: float, color) -> None:
    """Draw `text` with its baseline-left at (x, y) in `color` over a dark outline (clipped to the image)."""
    fill, outline, top = _text_masks(text, round(scale, 3))
    y0, x0 = y - top, x
    H, W = rgb.shape[:2]
    ya, xa = max(0, y0), max(0, x0)
    yb, xb = min(H, y0 + fill.shape[0]), min(W, x0 + fill.shape[1])
    if ya >= yb or xa >= xb:
        return
    sl = (slice(ya - y0, yb - y0), slice(xa - x0, xb - x0))
    region = rgb[ya:yb, xa:xb].astype(np.float32)
    o = outline[sl][:, :, None].astype(np.float32) / 255.0
    f = fill[sl][:, :, None].astype(np.float32) / 255.0
    region *= 1.0 - 0.85 * o
    region = region * (1.0 - f) + np.asarray(color, np.float32) * f
    rgb[ya:yb, xa:xb] = region.astype(np.uint8)


def _pt(xy) -> tuple[int, int]:
    return int(round(float(xy[0]))), int(round(float(xy[1])))
