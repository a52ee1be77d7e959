"""Frames whose stars are trails (an untracked exposure): recognised, each trail measured whole at its middle
(the star at mid-exposure), and solved there; frames of round stars never taken for trailed ones."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.camera import Camera
from skyview.detect.centroids import detect_centroids, load_image
from skyview.detect.stars import detect_stars
from skyview.detect.trailed import trailed_frame
from skyview.simulate.render import SensorModel, simulate_image
from skyview.solver.pipeline import solve_image

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())


def _line_kernel(length: int, angle_deg: float) -> np.ndarray:
    """A centred line of `length` px at angle_deg (image axes, v down), normalised: a star's uniform trail."""
    k = np.zeros((length + 1, length + 1), np.float32)
    c = length / 2.0
    for t in np.linspace(-c, c, 4 * length):
        k[int(round(c + t * math.sin(math.radians(angle_deg)))), int(round(c + t * math.cos(math.radians(angle_deg))))] = 1
    return k / k.sum()


def _trailed(image: np.ndarray, length: int, angle_deg: float) -> np.ndarray:
    out = cv2.filter2D(image.astype(np.float32), -1, _line_kernel(length, angle_deg), borderType=cv2.BORDER_REFLECT)
    return np.clip(out, 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("name, angle", [(sorted(REFERENCE)[6], 35.0), (sorted(REFERENCE)[7], 0.0)])
def test_a_photograph_trailed_24_px_solves_at_mid_exposure(name, angle):
    """The photograph blurred along a 24 px line (the sky's motion in an untracked exposure): the frame is
    recognised as trailed, at the trail's length and direction; every trail is one star, measured at its
    middle; the solve lands on the photograph's own attitude (mid-exposure) and says why in a note."""
    image = _trailed(load_image(REAL / name), 24, angle)
    c = detect_centroids(image, k_sigma=5.0)
    trail = trailed_frame(image, c)
    assert trail is not None
    length, direction = trail
    assert length == pytest.approx(24.0, abs=4.0)
    assert abs((direction - angle + 90.0) % 180.0 - 90.0) < 5.0
    stars = detect_stars(image)
    assert stars.params["trailed"]["length_px"] == pytest.approx(length) and stars.estimator == "trail"
    # one star per trail, at its middle: the brightest 40 (what the verification reads) lie on the photograph's
    # own stars (the centroider's on the photograph itself), not on fragments of their trails
    own = detect_centroids(load_image(REAL / name), k_sigma=5.0).uv
    d = np.hypot(*(stars.uv[:40, None, :] - own[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    assert np.mean(d < 3.0) >= 0.85 and len(stars) < len(c)
    res = solve_image(image, deep=False)
    assert res.solved and any("trail" in n for n in res.notes)
    err = attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))
    assert err["boresight"] < 120.0, err


def test_trails_are_measured_at_their_middle():
    """Stars drawn as 20 px trails at 60 deg on a noisy 16-bit frame: each detected once, at the trail's
    middle to a small fraction of a pixel, brightest first."""
    rng = np.random.default_rng(4)
    H, W = 600, 800
    centres = np.zeros((0, 2))
    while len(centres) < 40:  # trails apart (30 px): each its own blob
        p = rng.uniform([60, 60], [W - 60, H - 60])
        if len(centres) == 0 or np.hypot(*(centres - p).T).min() > 30:
            centres = np.vstack([centres, p])
    flux = np.sort(rng.uniform(2e4, 2e5, 40))[::-1]
    point = np.zeros((H, W), np.float32)
    yy, xx = np.mgrid[-6:7, -6:7]
    for (u, v), f in zip(centres, flux):  # a round PSF (sigma 1.2 px) at each sub-pixel centre
        iu, iv = int(u), int(v)
        g = np.exp(-((xx - (u - iu)) ** 2 + (yy - (v - iv)) ** 2) / (2 * 1.2 ** 2))
        point[iv - 6: iv + 7, iu - 6: iu + 7] += f * g / g.sum()
    trailed = cv2.filter2D(point, -1, _line_kernel(20, 60.0), borderType=cv2.BORDER_CONSTANT)
    image = np.clip(trailed + rng.normal(500, 8, (H, W)), 0, 65535).astype(np.uint16)
    stars = detect_stars(image)
    assert "trailed" in stars.params and len(stars) == 40
    d = np.hypot(*(stars.uv[:, None, :] - centres[None, :, :]).transpose(2, 0, 1))
    nearest = d.argmin(axis=1)
    assert np.sort(nearest).tolist() == list(range(40))  # each trail once
    assert np.median(d.min(axis=1)) < 0.15 and d.min(axis=1).max() < 0.5
    assert np.all(np.diff(stars.brightness) <= 0)


def test_round_stars_are_never_taken_for_trails():
    """The real photographs, trails of 8 px (which the centroider's window holds) and simulated frames of
    round stars, dense and sparse, 8 and 16 bits: no trail recognised, the stars the centroider's."""
    frames = [load_image(REAL / name) for name in sorted(REFERENCE)]
    frames.append(_trailed(frames[0], 8, 35.0))
    from skyview.core.catalog import load_guide_catalog

    cat = load_guide_catalog()
    for k, (fov, bits, mag) in enumerate(((20.0, 16, 9.0), (8.0, 8, 6.5), (12.0, 16, 7.5))):
        cam = Camera.from_fov(fov, 1024, 768)
        R = random_attitudes(1, np.random.default_rng(k))[0]
        frames.append(simulate_image(cat, cam, R, SensorModel(bit_depth=bits), seed=k, mag_limit=mag).image)
    for image in frames:
        c = detect_centroids(image, k_sigma=5.0)
        assert trailed_frame(image, c) is None
        assert "trailed" not in detect_stars(image).params


def test_dashes_of_an_aircraft_and_bleeding_stars_are_not_taken_for_trailed_stars():
    """Elongated detections that are not the stars' own trails: an aircraft's dashes (12 px, brighter than
    the stars: fragments of one line, `trail_members`) and saturated stars bleeding along their columns
    (±16 px). The frame's round stars keep the centroider's measurement."""
    from skyview.core.catalog import load_guide_catalog
    from skyview.simulate.scenarios import get_scenario

    sc = get_scenario("blind8")
    cat = load_guide_catalog()
    R = random_attitudes(1, np.random.default_rng(11))[0]
    frame = simulate_image(cat, sc.camera(), R, SensorModel(), seed=11, **sc.render_kwargs())
    dashed = frame.image.copy()
    peak = float(np.percentile(dashed, 99.99))
    for k in range(10):
        p0 = (120 + 40 * k, 600 - 25 * k)
        cv2.line(dashed, p0, (p0[0] + 11, p0[1] - 7), peak, 2)
    bleeding = frame.image.copy()
    top = np.iinfo(bleeding.dtype).max
    c = detect_centroids(frame.image, k_sigma=5.0)
    for u, v in np.rint(c.uv[:12]).astype(int):
        bleeding[max(v - 16, 0): v + 17, max(u - 1, 0): u + 2] = top
    for image in (dashed, bleeding):
        c = detect_centroids(image, k_sigma=5.0)
        assert trailed_frame(image, c) is None
        assert "trailed" not in detect_stars(image).params


def _long_exposure_trail(image: np.ndarray, length: int, angle_deg: float, seed: int) -> np.ndarray:
    """The photograph as an exposure long enough to trail its stars `length` px: each star's light, length / 4
    times what it was, spread along the line, the sky's noise grown with the exposure (the background level kept)."""
    f = image.astype(np.float32)
    level = float(np.median(f))
    noise = 1.4826 * float(np.median(np.abs(f - level)))
    gain = length / 4.0
    out = level + gain * cv2.filter2D(f - level, -1, _line_kernel(length, angle_deg), borderType=cv2.BORDER_REFLECT)
    out += np.random.default_rng(seed).normal(0.0, noise * math.sqrt(gain), f.shape).astype(np.float32)
    return np.clip(out, 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("index, length, angle", [(2, 60, 35.0), (7, 60, 120.0), (4, 96, 35.0)])
def test_trails_longer_than_the_vote_reads_are_measured_whole(index, length, angle):
    """Trails of 60-96 px, longer than the vote's windows: the centroider breaks each into a row of fragments,
    which looked like satellites' pieces or like wide stars (the frame was binned 7-9 times, or nothing was left
    to vote: none of these solved). The smoothed frame's blobs (`long_trail`) give the trail's length and
    direction; each trail is one star at its middle and the solve lands on the photograph's own attitude."""
    name = sorted(REFERENCE)[index]
    image = _long_exposure_trail(load_image(REAL / name), length, angle, seed=index)
    stars = detect_stars(image)
    trail = stars.params.get("trailed")
    assert trail is not None and stars.params["binning"] == 1
    assert trail["length_px"] == pytest.approx(length, rel=0.15)
    assert abs((trail["direction_deg"] - angle + 90.0) % 180.0 - 90.0) < 3.0
    res = solve_image(image, deep=False)
    assert res.solved, res.reason
    err = attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))
    pixel_arcsec = REFERENCE[name]["fov_deg"] * 3600.0 / REFERENCE[name]["width"]
    assert err["boresight"] < 0.1 * length * pixel_arcsec, err


def test_parallel_satellites_over_round_stars_are_not_trails():
    """Two long parallel lines (satellites of one train side by side, 300 px) over a photograph's round stars:
    most detections are round, so the long-trail vote is never asked, and the stars stay the centroider's."""
    name = sorted(REFERENCE)[3]
    image = load_image(REAL / name).copy()
    peak = float(np.percentile(image, 99.95))
    for dv in (0, 40):
        cv2.line(image, (200, 300 + dv), (480, 410 + dv), peak, 2)
    c = detect_centroids(image, k_sigma=5.0)
    assert trailed_frame(image, c) is None
    stars = detect_stars(image)
    assert "trailed" not in stars.params and stars.params["binning"] == 1
    res = solve_image(image, deep=False)
    assert res.solved and attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))["boresight"] < 60.0
