"""What never passed through the optics is not a star: hot pixels side by side and cosmic-ray tracks are left out
by the centroider (`_hot_clusters`, `_sharp_streaks`), stars of any sharpness a lens gives are kept, and frames
full of them solve."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from oracles.centroid_reference import _detect_centroids_reference

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.camera import Camera
from skyview.detect.centroids import detect_centroids
from skyview.simulate.render import SensorModel, simulate_image
from skyview.solver.pipeline import solve_image

RNG = np.random.default_rng(2026)
H, W = 400, 600
SKY, NOISE = 1000.0, 10.0


def _star(img: np.ndarray, u: float, v: float, flux: float, sigma: float) -> None:
    """A pixel-integrated Gaussian star added to img."""
    s = math.sqrt(2.0) * sigma
    x = np.arange(W)
    y = np.arange(H)
    from scipy.special import erf

    fx = 0.5 * (erf((x + 0.5 - u) / s) - erf((x - 0.5 - u) / s))
    fy = 0.5 * (erf((y + 0.5 - v) / s) - erf((y - 0.5 - v) / s))
    img += flux * np.outer(fy, fx)


def _field(sigma_psf: float, n_stars: int = 25):
    img = SKY + RNG.normal(0.0, NOISE, (H, W))
    # one star in each of n_stars cells of a grid 80 px apart (the artefacts go between them)
    cells = np.array([(u, v) for u in range(40, W - 30, 80) for v in range(40, H - 30, 80)], dtype=np.float64)
    uv = cells[RNG.permutation(len(cells))[:n_stars]] + RNG.uniform(-10, 10, (n_stars, 2))
    # peaks from ~60 to ~5000 sigma, at every sub-pixel phase (pixel centres, edges and corners included)
    uv[:8] = np.round(uv[:8]) + np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.5], [0.5, 0.5]] * 2)
    flux = np.geomspace(3e3, 3e5, n_stars) * (sigma_psf / 0.6) ** 2
    for (u, v), f in zip(uv, flux):
        _star(img, u, v, f, sigma_psf)
    return img, uv


def _far(points: np.ndarray, uv: np.ndarray, d: float = 8.0) -> np.ndarray:
    """The points at least d px from every star."""
    return points[np.hypot(*(points[:, None] - uv[None]).transpose(2, 0, 1)).min(axis=1) >= d]


@pytest.mark.parametrize("sigma_psf", [0.6, 1.0, 2.0])
def test_hot_pixel_pairs_and_cosmic_ray_tracks_are_left_out_and_stars_kept(sigma_psf):
    """Bright pairs and 2 x 2 squares of hot pixels and 1 px wide tracks 3-12 px long at every angle (each on
    its own), brighter than the stars, are none of them reported; every star is, whether its PSF is as sharp as the photographs'
    (0.6 px) or wide, and wherever it is centred on its pixel (a star centred on a pixel corner is a 2 x 2
    blob whose ring is its faintest: 10 % of its peak at 0.6 px)."""
    img, uv = _field(sigma_psf)
    # the artefacts 40 px apart (a grid of cells, each with one), none within 16 px of a star
    cells = np.array([(u, v) for u in range(20, W - 30, 40) for v in range(20, H - 30, 40)])
    spots = _far(cells + RNG.integers(-4, 5, cells.shape), uv, 16.0)
    RNG.shuffle(spots)
    pairs, tracks = spots[: len(spots) // 2], spots[len(spots) // 2:]
    for k, (u, v) in enumerate(pairs):
        du, dv = [(1, 0), (0, 1), (1, 1)][k % 3]
        img[v, u] += 40000.0
        img[v + dv, u + du] += 38000.0
        if k % 4 == 0:  # a 2 x 2 square
            img[v + 1, u] += 39000.0
            img[v, u + 1] += 39000.0
    layer = np.zeros((H, W), np.float32)
    for k, (u, v) in enumerate(tracks):
        length, angle = 3 + k % 10, math.radians(17.0 * k)
        cv2.line(layer, (int(u), int(v)), (int(round(u + length * math.cos(angle))),
                                           int(round(v + length * math.sin(angle)))), 1.0, 1)
    img += 30000.0 * layer
    frame = np.clip(img, 0, 65535).astype(np.uint16)
    c = detect_centroids(frame)
    ref = _detect_centroids_reference(frame)  # the plain form of the same rules finds the same stars
    assert (len(ref), ref.n_hot_pixels_rejected, ref.n_streaks_rejected) == (
        len(c), c.n_hot_pixels_rejected, c.n_streaks_rejected)
    assert np.abs(ref.uv - c.uv).max() < 2e-3
    found = np.hypot(*(c.uv[:, None] - uv[None]).transpose(2, 0, 1)).min(axis=0)
    assert (found < 0.3).all(), found  # every star, at its place
    d_star = np.hypot(*(c.uv[:, None] - uv[None]).transpose(2, 0, 1)).min(axis=1)
    assert (d_star < 1.0).all(), c.uv[d_star >= 1.0]  # nothing else
    assert c.n_hot_pixels_rejected >= 2 * len(pairs) and c.n_streaks_rejected >= 0.8 * len(tracks)
    assert c.psf_sigma_px == pytest.approx(sigma_psf, rel=0.15)  # the tracks measure no PSF


def test_a_satellite_trail_through_the_optics_is_not_a_cosmic_ray():
    """A trail drawn through the optics (as wide across as the PSF) is no streak: the centroider reports its
    pieces as before, and the trail filters (`skyview.detect.trails`) are the ones that judge it."""
    img = SKY + RNG.normal(0.0, NOISE, (H, W))
    layer = np.zeros((H, W), np.float32)
    cv2.line(layer, (50, 80), (550, 300), 1.0, 1)
    img += 5000.0 * cv2.GaussianBlur(layer, (0, 0), 1.0)
    c = detect_centroids(np.clip(img, 0, 65535).astype(np.uint16))
    assert c.n_streaks_rejected == 0 and len(c) >= 1


@pytest.mark.slow
@pytest.mark.parametrize("case", ["hot", "cosmic"])
def test_frames_full_of_hot_pixels_or_cosmic_rays_solve(catalog, case):
    """3,000 hot pixels of 20,000 e- (about 40 of them side by side, brighter than every star), or 150 cosmic-ray
    tracks 1-12 px long: the 40 brightest detections were not stars and nothing solved; each frame now solves
    blind, at its true attitude."""
    cam = Camera.from_fov(12.0, 1280, 720)
    sensor = SensorModel(n_hot_pixels=3000, hot_pixel_e=20000.0) if case == "hot" else SensorModel()
    for seed, R in enumerate(random_attitudes(2, np.random.default_rng(41))):
        frame = simulate_image(catalog, cam, R, sensor, seed=seed, mag_limit=6.5, faint_extra_mag=2.5)
        img = frame.image.astype(np.float64)
        if case == "cosmic":
            rng = np.random.default_rng(seed + 7)
            for _ in range(150):
                u, v = rng.integers(0, cam.width), rng.integers(0, cam.height)
                length, angle = rng.integers(1, 12), rng.uniform(0, np.pi)
                layer = np.zeros(img.shape, np.float32)
                cv2.line(layer, (int(u), int(v)), (int(u + length * np.cos(angle)), int(v + length * np.sin(angle))),
                         1.0, 1)
                img += rng.uniform(2000, 40000) * layer
        res = solve_image(np.clip(img, 0, 65535).astype(np.uint16), deep=False)
        assert res.solved, res.reason
        assert attitude_error_arcsec(res.R, R)["boresight"] < 20.0


@pytest.mark.parametrize("dtype", [np.float32, np.uint16])
@pytest.mark.parametrize("flat", [True, False])
def test_hot_pixels_in_a_corner_are_patched_with_the_background_there(dtype, flat):
    """A 2 x 2 hot cluster in the image's corner has no neighbour off the blob and on the image: its pixels take
    the background there (they took NaN, which spread into the star whose window holds the corner, and out of
    its JSON). The star at (6, 6), sigma 2 px: its window (+-6 px) holds the corner, its blob (~4.7 px) does not
    touch the cluster."""
    rng = np.random.default_rng(7)
    img = SKY + rng.normal(0.0, NOISE, (H, W))
    if not flat:
        img += np.linspace(0.0, 400.0, W)[None, :]
    _star(img, 6.0, 6.0, 2.0e4, 2.0)
    for u, v in ((200.0, 150.0), (400.0, 300.0), (500.0, 100.0)):  # (stars enough to measure the PSF)
        _star(img, u, v, 6e4, 2.0)
    img[0:2, 0:2] += 3000.0
    c = detect_centroids(img.astype(dtype))
    assert np.isfinite(c.brightness).all() and np.isfinite(c.uv).all()
    assert np.hypot(c.uv[:, 0] - 6.0, c.uv[:, 1] - 6.0).min() < 0.3 and c.n_hot_pixels_rejected >= 4
    ref = _detect_centroids_reference(img.astype(dtype))
    assert np.isfinite(ref.brightness).all() and len(ref) == len(c)


def _jpeg8(img: np.ndarray, quality: int = 85) -> np.ndarray:
    """A 16-bit frame stretched to 8 bits (1st to 99.95th percentile) and JPEG-compressed, as an export would."""
    a = img.astype(np.float64)
    lo, hi = np.percentile(a, 1), np.percentile(a, 99.95)
    ok, buf = cv2.imencode(".jpg", np.clip((a - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8),
                           [int(cv2.IMWRITE_JPEG_QUALITY), quality])
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)


def test_tracks_blurred_by_a_jpeg_go_after_the_round_stars_and_trails_do_not():
    """100 cosmic-ray tracks on a photograph exported as an 8-bit JPEG: the JPEG blurs them past the streak test
    and 38 of the 40 brightest detections are tracks, elongated every way; the round detections now come first
    (`elongated_last`) and the photograph solves at its reference (it did not). Stars trailed 8 px, elongated
    one way, keep their order."""
    import json
    from pathlib import Path

    from skyview.core.attitude import attitude_error_arcsec
    from skyview.detect.centroids import load_image
    from skyview.detect.stars import detect_stars

    real = Path(__file__).parent / "data" / "real-images"
    ref = json.loads((real / "reference.json").read_text())
    name = sorted(ref)[1]
    img = load_image(real / name).astype(np.float64)
    rng = np.random.default_rng(1)
    H_, W_ = img.shape
    for _ in range(100):
        u, v = rng.integers(0, W_), rng.integers(0, H_)
        length, angle = rng.integers(1, 12), rng.uniform(0, np.pi)
        layer = np.zeros(img.shape, np.float32)
        cv2.line(layer, (int(u), int(v)), (int(u + length * np.cos(angle)), int(v + length * np.sin(angle))), 1.0, 1)
        img += rng.uniform(3000, 40000) * layer
    frame = _jpeg8(np.clip(img, 0, 65535))
    stars = detect_stars(frame, max_stars=100)
    assert stars.params.get("elongated_last", 0) > 40 and not stars.elongated[:16].any()
    res = solve_image(frame, deep=False)
    assert res.solved, res.reason
    assert attitude_error_arcsec(res.R, np.array(ref[name]["R"]))["boresight"] < 120.0
    k = np.zeros((9, 9), np.float32)
    k[4, :] = 1.0 / 9.0  # an 8 px trail along u
    trailed = cv2.filter2D(load_image(real / name).astype(np.float32), -1, k, borderType=cv2.BORDER_REFLECT)
    assert "elongated_last" not in detect_stars(np.clip(trailed, 0, 65535).astype(np.uint16)).params
