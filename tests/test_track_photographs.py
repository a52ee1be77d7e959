"""Tracking a photograph's sequence with the default pipeline (no method, no depth given): the tracked catalog as
deep as the lost-in-space solve's, the frames measured as `solve` measures them, trailed frames measured whole."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from skyview.core.attitude import attitude_error_arcsec
from skyview.detect.centroids import load_image
from skyview.solver.pipeline import solve_image
from skyview.solver.track import LOST_IN_SPACE, TRACKING, Tracker

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())
NAME = sorted(REFERENCE)[0]


def _shifted(image: np.ndarray, n: int, du: float = 4.0, dv: float = 2.0) -> list[np.ndarray]:
    """n frames of the photograph moved by (du, dv) px a frame: a slow drift of the camera."""
    h, w = image.shape
    return [cv2.warpAffine(image, np.float32([[1, 0, k * du], [0, 1, k * dv]]), (w, h),
                           borderMode=cv2.BORDER_REPLICATE) for k in range(n)]


def _trailed(image: np.ndarray, length: int, angle_deg: float) -> np.ndarray:
    """The photograph blurred along a centred line (a star's uniform trail in an untracked exposure)."""
    k = np.zeros((length + 1, length + 1), np.float32)
    c = length / 2.0
    for t in np.linspace(-c, c, 4 * length):
        k[int(round(c + t * math.sin(math.radians(angle_deg)))), int(round(c + t * math.cos(math.radians(angle_deg))))] = 1
    out = cv2.filter2D(image.astype(np.float32), -1, k / k.sum(), borderType=cv2.BORDER_REFLECT)
    return np.clip(out, 0, 65535).astype(np.uint16)


def _tracked_like_solved(frames, images, min_matches: int, boresight_arcsec: float, total_arcsec: float):
    """Frame 0 lost-in-space, the others tracked, each at the attitude the default pipeline solves that frame
    at on its own."""
    assert [f.mode for f in frames] == [LOST_IN_SPACE] + [TRACKING] * (len(frames) - 1)
    for fr, im in zip(frames, images):
        assert fr.solved, fr.reason
        alone = solve_image(im, deep=False)
        assert alone.solved
        err = attitude_error_arcsec(fr.R, alone.R)
        assert err["boresight"] < boresight_arcsec and err["total"] < total_arcsec, (fr.frame, err)
        assert len(fr.matches) >= min_matches, (fr.frame, len(fr.matches))
    return frames


def test_a_photographs_drift_is_tracked_with_the_catalog_as_deep_as_its_solve(catalog):
    """An 11 deg photograph holds a handful of Hp 6 stars: the tracker, given no depth, tracks with the catalog as
    deep as the blind solve went (Hp ~8.3), so frame 0 keeps every match of the solve and the tracked frames
    a dozen or more (at Hp 6: 4 matches, the attitude of those alone); a new sequence starts at Hp 6 again."""
    images = _shifted(load_image(REAL / NAME), 4)
    tracker = Tracker(None, None, catalog=catalog)
    assert tracker.mag_limit == 6.0
    frames = tracker.run(images)
    first = solve_image(images[0], deep=False)
    assert tracker.mag_limit == pytest.approx(first.mag_limit) and first.mag_limit > 7.0
    assert len(frames[0].matches) == len(first.matches) >= 30
    assert {m["hip"] for m in frames[0].matches} == {m["hip"] for m in first.matches}
    _tracked_like_solved(frames, images, min_matches=10, boresight_arcsec=3.0, total_arcsec=60.0)
    tracker.reset()
    assert tracker.mag_limit == 6.0 and len(tracker.catalog) < len(catalog.brighter_than(first.mag_limit))
    given = Tracker(None, None, catalog=catalog, mag_limit=6.0)
    given.run(images[:1])
    assert given.mag_limit == 6.0  # a depth given is kept


def test_a_trailed_photographs_sequence_is_measured_whole_and_tracked_at_mid_exposure(catalog):
    """Every star a 24 px trail: the lost-in-space frame is measured as `solve` measures it (each trail whole, at
    its middle), and so is every tracked frame (the windows' centroid of a round star would take a trail's
    part near the predicted place: 0.2 deg of roll off); each frame lands where its own solve does."""
    images = _shifted(_trailed(load_image(REAL / NAME), 24, 35.0), 3)
    frames = Tracker(None, None, catalog=catalog).run(images)
    assert all(f.centroids.params.get("trailed") for f in frames)
    _tracked_like_solved(frames, images, min_matches=20, boresight_arcsec=10.0, total_arcsec=60.0)  # 40"/px
