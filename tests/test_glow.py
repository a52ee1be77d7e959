"""A bright glow in the frame (the Moon, a lamp's halo): the sky changes faster than the background map's 64 px
blocks follow, and the map's error there must not make stars of the noise (`detect_stars`' own-background check)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from skyview.core.attitude import attitude_error_arcsec
from skyview.detect.centroids import detect_centroids, load_image
from skyview.detect.stars import detect_stars
from skyview.solver.pipeline import solve_image

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())


def _with_moon(image: np.ndarray, centre: tuple[int, int], glow: float, scale_px: float, seed: int) -> np.ndarray:
    """The photograph with a saturated disk of 40 px radius at `centre` and its glow: `glow` of the full scale at
    the disk's edge, falling by e every `scale_px`, with the glow's photon noise (a gain of 2 e-/ADU)."""
    f = image.astype(np.float32)
    H, W = f.shape
    yy, xx = np.mgrid[0:H, 0:W]
    r = np.hypot(xx - centre[0], yy - centre[1])
    light = glow * (65535.0 - float(np.median(f))) * np.exp(-np.maximum(r - 40.0, 0.0) / scale_px)
    f += light + np.random.default_rng(seed).normal(0.0, 1.0, f.shape).astype(np.float32) * np.sqrt(0.5 * light)
    f[r <= 40.0] = 65535.0
    return np.clip(f, 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("index, centre", [(5, (200, 150)), (0, (520, 380))])
def test_the_moons_glow_does_not_outrank_the_stars(index, centre):
    """A glow of 90 % of the full scale falling over 150 px: the map lies ~1,000 ADU (5-7 sigma) below the sky
    around the disk and the noise's peaks there had 34-36 of the 40 first places; they are taken out or ranked by
    their own surroundings, the stars come first again, and the frame solves (it did not)."""
    name = sorted(REFERENCE)[index]
    plain = load_image(REAL / name)
    image = _with_moon(plain, centre, 0.9, 150.0, seed=index)
    own = detect_centroids(plain, k_sigma=5.0).uv  # the photograph's stars
    stars = detect_stars(image, max_stars=100)
    assert stars.params["n_background_rejected"] > 50
    d = np.hypot(*(stars.uv[:40, None, :] - own[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    assert np.count_nonzero(d < 2.0) >= 27
    res = solve_image(image, deep=False)
    assert res.solved, res.reason
    assert attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))["boresight"] < 60.0


def test_stars_on_a_background_the_map_follows_are_left_as_they_are():
    """The eight photographs (a map, not one level, for each): no detection taken out; a star ranked by its own
    surroundings only where a brighter neighbour's light lies on its border (two stars in all)."""
    for name in sorted(REFERENCE):
        stars = detect_stars(load_image(REAL / name))
        assert stars.params["background_flat"] is False and stars.params["n_background_rejected"] == 0
        assert stars.params["n_background_rebrightened"] <= 1
