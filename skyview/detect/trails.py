"""Trails among detections: satellites, aircraft and meteors crossing the exposure.

A trail that the centroider sees as one long blob is rejected there as extended. But a trail that
breaks up — an aircraft's blinking lights, a satellite trail cut into 8 x 8 blocks by JPEG, a faint
trail that crosses the threshold only in places — arrives as a row of compact, evenly bright
"stars" on a straight line. Such a row outshines the real stars and fills the brightest slots that
every pattern search starts from.

`trail_members` finds such rows geometrically. Among the brightest detections, every pair defines
a line; a line that `min_members` or more of them lie on (within `max_width_px`), without a gap
longer than `max_gap_px` between neighbours along it and over at least 15 widths, is a trail. Its
line is refitted, and every detection on it within the trail's extent — bright or faint — is a
trail member.

Stars of the sky almost never do this. Among the 40 brightest detections of a 1-megapixel frame
(about 4e-5 per square pixel), a run of five on one line to 1.5 px with gaps under 130 px is expected
about once in a few thousand frames, and what is lost then is five stars, never a wrong answer.
A tight double, a close triple or a cluster is not a line, and Orion's belt is three stars.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

MIN_LENGTH_WIDTHS = 15.0  # a trail runs at least this many widths: shorter rows are a tight group


def trail_members(uv: np.ndarray, *, max_width_px: float = 1.5, max_gap_px: float | None = None,
                  min_members: int = 5, brightest: int = 40) -> np.ndarray:
    """(N,) bool: which detections (pixel positions `uv`, (N, 2), brightest first) belong to a trail.

    max_width_px: the largest distance of a fragment from the trail's line; max_gap_px: the largest
    gap between neighbouring fragments along it (default: a tenth of the detections' extent,
    at least 40 px); min_members: the fewest fragments among the `brightest` detections that make
    a trail.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    out = np.zeros(len(uv), dtype=bool)
    if len(uv) < min_members:
        return out
    if max_gap_px is None:
        extent = float(np.hypot(*np.ptp(uv, axis=0)))
        max_gap_px = max(40.0, 0.1 * extent)
    free = np.ones(len(uv), dtype=bool)
    while True:  # one trail at a time, the longest first
        cand = np.flatnonzero(free)[:brightest]
        line = _longest_line(uv[cand], max_width_px, max_gap_px, min_members)
        if line is None:
            return out
        centre, axis, t_lo, t_hi = line
        d = uv - centre
        across = np.abs(d @ np.array([-axis[1], axis[0]]))
        along = d @ axis
        on = free & (across <= max_width_px) & (along >= t_lo - max_gap_px) & (along <= t_hi + max_gap_px)
        out |= on
        free &= ~on


def fragment_width_px(psf_sigma_px: float) -> float:
    """How far a trail's fragments may lie from its line (trail_members' max_width_px) for stars of this PSF sigma:
    three quarters of it, at least 1.5 px (also when it is unknown)."""
    return max(1.5, 0.75 * psf_sigma_px) if math.isfinite(psf_sigma_px) else 1.5


@lru_cache(maxsize=64)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """np.triu_indices(n, k=1), made once per n (read-only)."""
    i, j = np.triu_indices(n, k=1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


def _longest_line(p: np.ndarray, width: float, gap: float, min_members: int):
    """(centre, unit direction, extent along it from, to) of the longest run of points of p on one line
    (within `width`, neighbours within `gap` along it), refitted to its members; None when no run has
    `min_members` points."""
    n = len(p)
    if n < min_members:
        return None
    i, j = _pairs(n)
    dirs = p[j] - p[i]
    lengths = np.hypot(dirs[:, 0], dirs[:, 1])
    ok = (lengths > 0) & (lengths <= gap * (min_members - 1))
    i, j, dirs, lengths = i[ok], j[ok], dirs[ok] / lengths[ok, None], lengths[ok]
    if len(i) == 0:
        return None
    # each point's distance from each pair's line, |(p_m - p_i) x d|, as one product: (pairs, n)
    normal = np.stack([dirs[:, 1], -dirs[:, 0]], axis=1)
    across = np.abs(normal @ p.T - np.einsum("ij,ij->i", normal, p[i])[:, None])
    members = across <= width
    counts = np.count_nonzero(members, axis=1)
    if int(counts.max()) < min_members:  # (the usual frame: no line holds enough of them)
        return None
    best = None
    for k in np.argsort(-counts, kind="stable"):
        if counts[k] < min_members or (best is not None and counts[k] <= len(best)):
            break
        idx = np.flatnonzero(members[k])
        t = (p[idx] - p[i[k]]) @ dirs[k]
        order = np.argsort(t)
        idx, t = idx[order], t[order]
        # split the points on the line into runs at gaps longer than `gap`; keep the longest run
        cuts = np.flatnonzero(np.diff(t) > gap) + 1
        runs = np.split(np.arange(len(idx)), cuts)
        run = max(runs, key=len)
        if t[run[-1]] - t[run[0]] < MIN_LENGTH_WIDTHS * width:  # a tight group, not a line
            continue
        if len(run) >= min_members and (best is None or len(run) > len(best)):
            best = idx[run]
    if best is None:
        return None
    q = p[best]
    centre = q.mean(axis=0)
    evals, evecs = np.linalg.eigh((q - centre).T @ (q - centre) / len(q))
    axis = evecs[:, 1]
    if np.sqrt(max(evals[0], 0.0)) > width:
        return None
    t = (q - centre) @ axis
    return centre, axis, float(t.min()), float(t.max())
