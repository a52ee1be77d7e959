"""Centroiding: positions against known truth, detection, flags, bad input."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from skyview.bench.centroids import _match, format_markdown, measure_centroid_accuracy
from skyview.core.attitude import random_attitudes
from skyview.core.camera import Camera
from skyview.core.catalog import load_guide_catalog
from skyview.core.errors import BadInput
from skyview.detect.centroids import (
    DEFAULT_ESTIMATOR,
    ESTIMATORS,
    Centroids,
    detect_centroids,
    estimate_background,
    load_image,
)
from skyview.simulate.render import SensorModel, render_stars, simulate_image


def _star_image(uv, electrons, shape=(128, 128), sigma=1.1, bias=100.0, noise=0.0, seed=0, dtype=np.uint16):
    img = render_stars(shape, np.atleast_2d(uv), np.atleast_1d(electrons).astype(float), sigma) + bias
    if noise:
        img += np.random.default_rng(seed).normal(0.0, noise, shape)
    top = np.iinfo(dtype).max
    return np.clip(np.rint(img), 0, top).astype(dtype)


def _nearest_err(det_uv, true_uv):
    d = np.linalg.norm(np.asarray(det_uv)[:, None, :] - np.asarray(true_uv)[None, :, :], axis=2)
    return d.min(axis=0)


@pytest.fixture(scope="module")
def cat():
    return load_guide_catalog()


# ------------------------------------------------------------------------------------ positions

@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_noiseless_subpixel_positions(estimator):
    rng = np.random.default_rng(1)
    grid = np.stack(np.meshgrid(np.arange(16, 240, 16), np.arange(16, 240, 16)), -1).reshape(-1, 2)
    uv = grid + rng.uniform(-0.5, 0.5, grid.shape)
    img = _star_image(uv, np.full(len(uv), 20000.0), shape=(256, 256))
    c = detect_centroids(img, estimator=estimator)
    assert len(c) == len(uv)
    err = _nearest_err(c.uv, uv)
    assert err.max() < (0.02 if estimator == "cog" else 0.005)
    assert c.psf_sigma_px == pytest.approx(1.1, abs=0.02)


def test_default_estimator_is_the_fit():
    assert DEFAULT_ESTIMATOR == "fit"


def test_accuracy_on_noisy_simulated_images(cat):
    """RMS < 0.1 px (radial) for stars with SNR >= 20, on a handful of simulated 8-deg fields."""
    cam = Camera.from_fov(8.0, 1024)
    Rs = random_attitudes(4, np.random.default_rng(2024))
    errs, missed, false = [], 0, 0
    for k, R in enumerate(Rs):
        f = simulate_image(cat, cam, R, seed=100 + k, mag_limit=7.5)
        true_uv = f.rendered_uv
        snr = np.array([s["snr"] for s in f.truth["stars"]])
        c = detect_centroids(f.image)
        m = _match(c.uv, true_uv, 2.0)
        false += int((m < 0).sum())
        ok = m >= 0
        strong = snr[m[ok]] >= 20
        errs.append((c.uv[ok] - true_uv[m[ok]])[strong])
        missed += int(np.sum(snr >= 20)) - int(strong.sum())
    e = np.concatenate(errs)
    assert len(e) >= 40
    rms_radial = np.sqrt(np.mean(np.sum(e * e, axis=1)))
    assert rms_radial < 0.1
    assert np.abs(e.mean(axis=0)).max() < 0.02  # no systematic offset (pixel convention)
    assert missed <= 1 and false == 0


def test_eight_bit_image(cat):
    cam = Camera.from_fov(8.0, 1024)
    R = random_attitudes(1, np.random.default_rng(8))[0]
    f = simulate_image(cat, cam, R, SensorModel(bit_depth=8), seed=1, mag_limit=6.5)
    c = detect_centroids(f.image)
    strong = np.array([s["snr"] for s in f.truth["stars"]]) >= 20
    err = _nearest_err(c.uv, f.rendered_uv[strong])
    assert strong.sum() >= 3 and err.max() < 0.5
    assert 0.5 < c.noise_sigma < 2.0  # ~1 ADU read noise in 8 bit, not the quantised MAD


# ------------------------------------------------------------------------------------ detection

def test_blank_and_constant_images_give_no_centroids():
    for img in (np.zeros((64, 64), np.uint8), np.full((64, 64), 700, np.uint16), np.full((50, 70), 3.5)):
        c = detect_centroids(img)
        assert len(c) == 0 and c.uv.shape == (0, 2)
        assert c.to_list() == []
    # pure noise: nothing
    noise = np.random.default_rng(0).normal(100, 5, (256, 256))
    assert len(detect_centroids(noise)) == 0


def test_bad_arrays():
    with pytest.raises(BadInput):
        detect_centroids(np.zeros(100))
    with pytest.raises(BadInput):
        detect_centroids(np.zeros((4, 4, 4, 4)))
    with pytest.raises(BadInput):
        detect_centroids(np.zeros((0, 10)))
    with pytest.raises(BadInput):
        detect_centroids(np.zeros((32, 32)), estimator="magic")
    with pytest.raises(BadInput):
        detect_centroids(np.zeros((32, 32)), window=4)


def test_colour_image_is_converted():
    img = _star_image([[40.3, 50.7]], [30000.0], dtype=np.uint8, bias=10, noise=1.0)
    bgr = np.dstack([img, img, img])
    a, b = detect_centroids(img), detect_centroids(bgr)
    assert len(a) == len(b) == 1
    assert np.allclose(a.uv, b.uv, atol=0.05)


def test_hot_pixels_rejected_and_counted():
    rng = np.random.default_rng(4)
    img = rng.normal(200, 10, (256, 256))
    hot = [(20, 30), (100, 200), (250, 5), (128, 128)]
    for i, j in hot:
        img[i, j] += 3000
    img = np.rint(img).astype(np.uint16)
    c = detect_centroids(img)
    assert len(c) == 0
    assert c.n_hot_pixels_rejected == len(hot)
    # a real star next to them is kept
    img2 = img + _star_image([[60.2, 70.6]], [5000.0], shape=(256, 256), bias=0)
    c2 = detect_centroids(img2)
    assert len(c2) == 1 and c2.n_hot_pixels_rejected == len(hot)
    assert np.linalg.norm(c2.uv[0] - [60.2, 70.6]) < 0.1


def test_hot_pixel_touching_a_faint_star():
    # the hot pixel joins the star's blob through a halo pixel: it must not become the centroid
    rng = np.random.default_rng(7)
    img = render_stars((96, 96), [[40.3, 50.6]], [3000.0], 1.1) + 200 + rng.normal(0, 10, (96, 96))
    img[50, 43] = 200 + 4000  # 2.7 px from the star
    img[51, 42] = max(img[51, 42], 260.0)  # a halo pixel above the threshold links them
    c = detect_centroids(np.rint(img).astype(np.uint16))
    assert len(c) == 1 and c.n_hot_pixels_rejected == 1
    assert np.linalg.norm(c.uv[0] - [40.3, 50.6]) < 0.2


def test_background_gradient():
    rng = np.random.default_rng(3)
    uv = np.column_stack([rng.uniform(10, 502, 25), rng.uniform(10, 502, 25)])
    yy, xx = np.mgrid[0:512, 0:512]
    sky = 100 + 600 * xx / 512 + 300 * np.exp(-((xx - 150) ** 2 + (yy - 350) ** 2) / (2 * 150.0 ** 2))
    img = render_stars((512, 512), uv, np.full(25, 4000.0), 1.1) + sky + rng.normal(0, 10, (512, 512))
    c = detect_centroids(np.rint(img).astype(np.uint16))
    assert len(c) == 25  # every star, nothing from the gradient
    assert _nearest_err(c.uv, uv).max() < 0.25
    assert 9.0 < c.noise_sigma < 12.0


def test_flat_sky_uses_one_level():
    rng = np.random.default_rng(5)
    for noise, dtype in ((10.0, np.uint16), (1.0, np.uint8)):
        img = _star_image(rng.uniform(10, 500, (30, 2)), np.full(30, 3000.0 * noise / 10), shape=(512, 512),
                          bias=20, noise=noise, dtype=dtype, seed=int(noise))
        bkg, level, sigma = estimate_background(img.astype(np.float32))
        assert isinstance(bkg, float) and level == pytest.approx(20, abs=1)
        assert sigma == pytest.approx(np.hypot(noise, 1 / np.sqrt(12)), rel=0.1)


def test_sorted_by_brightness_and_json():
    uv = np.array([[30.0, 30.0], [90.2, 40.1], [60.7, 100.3]])
    e = np.array([2000.0, 30000.0, 8000.0])
    c = detect_centroids(_star_image(uv, e, noise=3.0))
    assert len(c) == 3
    assert np.all(np.diff(c.brightness) < 0)
    assert np.allclose(c.uv[0], uv[1], atol=0.05)
    assert c.brightness[0] == pytest.approx(30000.0, rel=0.02)  # ADU = e- here
    lst = json.loads(json.dumps(c.to_list()))
    assert len(lst) == 3 and set(lst[0]) >= {"u", "v", "brightness", "peak", "n_pixels", "saturated", "elongated",
                                             "edge"}
    json.dumps(c.to_dict(), allow_nan=False)
    assert isinstance(c, Centroids)


def test_saturation_flags():
    # 8-bit ADC maximum
    img = _star_image([[40.0, 40.0], [90.3, 90.6]], [20000.0, 800.0], dtype=np.uint8, bias=10, noise=1.0)
    assert img.max() == 255
    c = detect_centroids(img)
    assert len(c) == 2
    assert c.saturated.tolist() == [True, False]
    assert np.linalg.norm(c.uv[0] - [40.0, 40.0]) < 0.1  # fitted from the unsaturated wings
    # 12-bit data in a 16-bit container: a plateau at 4095
    img16 = np.minimum(_star_image([[40.4, 60.3], [100.0, 30.0]], [200000.0, 3000.0], noise=3.0), 4095)
    c = detect_centroids(img16)
    assert c.saturated.tolist() == [True, False]
    assert np.linalg.norm(c.uv[0] - [40.4, 60.3]) < 0.1
    # an explicit level
    c = detect_centroids(_star_image([[50.0, 50.0]], [10000.0], noise=2.0), saturation_level=1000)
    assert c.saturated.tolist() == [True]


def test_edge_flag_and_edge_star_position():
    img = _star_image([[1.2, 60.4], [64.0, 64.0]], [20000.0, 20000.0], noise=2.0)
    c = detect_centroids(img)
    assert len(c) == 2
    at_edge = np.argmin(c.uv[:, 0])
    assert c.edge[at_edge] and not c.edge[1 - at_edge]
    assert np.linalg.norm(c.uv[at_edge] - [1.2, 60.4]) < 0.05


def test_elongated_streak_and_round_star():
    # a short streak (smeared star) and a round star
    streak_uv = np.column_stack([np.linspace(30, 36, 25), np.full(25, 40.0)])
    img = _star_image(streak_uv, np.full(25, 1000.0)) + _star_image([[90.0, 90.0]], [25000.0], bias=0)
    c = detect_centroids(img)
    assert len(c) == 2
    streak = np.argmin(c.uv[:, 0])
    assert c.elongated[streak] and c.axis_ratio[streak] > 1.6
    assert not c.elongated[1 - streak]


def test_blended_pair_is_split():
    uv = np.array([[50.3, 60.2], [54.3, 63.2]])  # 5 px apart, one blob
    img = _star_image(uv, [20000.0, 10000.0], noise=3.0)
    c = detect_centroids(img)
    assert len(c) == 2 and c.blended.all()
    assert _nearest_err(c.uv, uv).max() < 0.05
    no = detect_centroids(img, deblend=False)
    assert len(no) == 1


# ------------------------------------------------------------------------------------ load_image

def test_load_image_errors(tmp_path):
    with pytest.raises(BadInput, match="does not exist"):
        load_image(tmp_path / "nope.png")
    with pytest.raises(BadInput, match="directory"):
        load_image(tmp_path)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(BadInput, match="empty"):
        load_image(tmp_path / "empty.png")
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not really a png")
    with pytest.raises(BadInput, match="is not an image OpenCV can read"):
        load_image(tmp_path / "corrupt.png")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(BadInput, match="is not an image OpenCV can read"):
        load_image(tmp_path / "notes.txt")


def test_load_image_formats(tmp_path):
    img16 = _star_image([[30.2, 40.7]], [20000.0], noise=3.0)
    cv2.imwrite(str(tmp_path / "a.png"), img16)
    back = load_image(tmp_path / "a.png")
    assert back.dtype == np.uint16 and np.array_equal(back, img16)
    cv2.imwrite(str(tmp_path / "a.tif"), img16)
    assert np.array_equal(load_image(tmp_path / "a.tif"), img16)
    img8 = _star_image([[30.2, 40.7]], [5000.0], dtype=np.uint8, bias=10, noise=1.0)
    cv2.imwrite(str(tmp_path / "c.jpg"), cv2.cvtColor(img8, cv2.COLOR_GRAY2BGR))
    g = load_image(tmp_path / "c.jpg")
    assert g.ndim == 2 and g.dtype == np.uint8
    c = detect_centroids(g)
    assert len(c) == 1 and np.linalg.norm(c.uv[0] - [30.2, 40.7]) < 0.15


# ------------------------------------------------------------------------------------ bench

def test_bench_small_run(cat):
    r = measure_centroid_accuracy(n_images=2, seed=1, estimators=("fit", "cog"), catalog=cat)
    assert set(r["estimators"]) == {"fit", "cog"}
    json.dumps(r, allow_nan=False)
    fit = r["estimators"]["fit"]
    assert fit["snr_ge_20"]["n"] > 0 and fit["false_detections_per_image"] == 0
    assert sum(b["n"] for b in fit["by_snr"]) > 0
    md = format_markdown(r)
    assert "| SNR |" in md and "`fit`" in md


# ------------------------------------------------------------------------------------ fast path = reference
# detect_centroids (fast path) against _detect_centroids_reference (the former implementation, kept
# unchanged), on the same images. The fast path estimates the background from another sub-sample on
# frames of 512 px or more a side (every 4th pixel of every 8th row instead of every 4th row: half the
# samples; the noise from half of those), starts the PSF fit of PSF-like stars from the three-point fit
# instead of the iwcog position and stops it when its steps say it has converged, so the comparison has
# tolerances:
# - noise sigma and threshold within 3 % (observed <= 1.4 %), background level within max(0.25 sigma, 1 ADU
#   on integer data), the PSF width within 2 %, the same options and window;
# - every detection of 4 pixels or more whose peak is 2.5 times the threshold (12.5 sigma; smaller ones can
#   turn into hot pixels or single pixels with the threshold) found by both, one to one within 0.5 px, with
#   the same peak value and saturated / edge / blended flags; at 50 sigma and above, the axis ratio within
#   5 % and the same elongated flag (unless the ratio is within 0.1 of the limit);
# - their positions within 2e-3 px on a flat sky (95 % within 2e-4 px; observed <= 1.1e-4 px for single
#   stars, the same least-squares minimum, and 1.2e-3 px for an unresolved pair, deblend off, whose
#   minimum lies in a flat valley), 0.02 px where the sky needs a background map (gradient, vignetting,
#   real photographs: the map's block medians come from other samples; observed <= 0.011 px), both far
#   below the 0.056 px centroid error at SNR >= 20; blends within 0.05 px; on the JPEG frame 95 % within
#   0.02 px and all within 0.1 px, and up to 2 strong detections a frame found by one only (8-bit JPEG
#   blocks at the 0.5 ADU noise floor make detections that are no PSF: flat tops, blocks that split into
#   other blends with the threshold, least-squares fits with several minima);
# - brightness within 0.2 % (a blend's, less its neighbours' fitted PSFs: 5 %) + the window's area times the
#   difference of the background levels (+ 0.5 sigma per pixel under a map);
# - those among the brightest 40 of the reference among the 45 brightest of the fast path (brightness order).

from oracles.centroid_reference import _detect_centroids_reference, _estimate_background_reference  # noqa: E402

from skyview.detect.centroids import _background_stats, _label_sparse  # noqa: E402

_REAL = sorted((__import__("pathlib").Path(__file__).parent / "data" / "real-images").glob("*.png"))


def _assert_close(fast, ref, pos_tol=2e-3, integer=True, unmatched=0):
    for k in ("estimator", "image_shape", "params"):
        assert getattr(fast, k) == getattr(ref, k), k
    assert fast.noise_sigma == pytest.approx(ref.noise_sigma, rel=0.03)
    assert fast.threshold == pytest.approx(ref.threshold, rel=0.03)
    d_level = abs(fast.background_level - ref.background_level)
    assert d_level <= max(0.25 * ref.noise_sigma, 1.0 if integer else 0.0)
    assert fast.psf_sigma_px == pytest.approx(ref.psf_sigma_px, rel=0.02, nan_ok=True)
    strong_r = np.flatnonzero((ref.peak - ref.background_level >= 2.5 * ref.threshold) & (ref.n_pixels >= 4))
    strong_f = np.flatnonzero((fast.peak - fast.background_level >= 2.5 * fast.threshold) & (fast.n_pixels >= 4))
    m = _match(ref.uv[strong_r], fast.uv, 0.5)
    assert (m < 0).sum() <= unmatched, f"{int((m < 0).sum())} of {len(strong_r)} strong reference detections not found"
    back = _match(fast.uv[strong_f], ref.uv, 0.5)
    assert (back < 0).sum() <= unmatched, f"{int((back < 0).sum())} of {len(strong_f)} strong fast detections not found"
    strong_r, m = strong_r[m >= 0], m[m >= 0]
    for k in ("peak", "saturated", "edge", "blended"):
        assert np.array_equal(getattr(fast, k)[m], getattr(ref, k)[strong_r]), k
    bright = ref.peak[strong_r] - ref.background_level >= 50.0 * ref.noise_sigma  # moments above 2 sigma: steady
    np.testing.assert_allclose(fast.axis_ratio[m][bright], ref.axis_ratio[strong_r][bright], rtol=0.05, equal_nan=True)
    clear = bright & ~(np.abs(ref.axis_ratio[strong_r] - ref.params["max_axis_ratio"]) <= 0.1)
    assert np.array_equal(fast.elongated[m][clear], ref.elongated[strong_r][clear])
    err = np.abs(fast.uv[m] - ref.uv[strong_r]).max(axis=1)
    tol = np.where(ref.blended[strong_r], max(pos_tol, 0.05), pos_tol)
    if (err > tol).any():
        worst = strong_r[np.argmax(err - tol)]
        raise AssertionError(f"{fast.estimator}: position differences up to {err.max():.2e} px at {ref.uv[worst]}")
    area = fast.params.get("window_used", 0) ** 2
    b_tol = (np.where(ref.blended[strong_r], 0.05, 2e-3) * np.abs(ref.brightness[strong_r])
             + area * (d_level + (0.5 * ref.noise_sigma if pos_tol > 2e-3 else 0.0)))
    d_b = np.abs(fast.brightness[m] - ref.brightness[strong_r]) - b_tol
    assert (d_b <= 1e-6).all(), f"brightness {ref.brightness[strong_r][np.argmax(d_b)]} off by {d_b.max()} + tolerance"
    top = strong_r[strong_r < 40]  # the same brightest stars
    assert (_match(ref.uv[top], fast.uv[:45], 0.5) >= 0).all()
    return err


@pytest.mark.parametrize("case", ["16bit", "8bit", "gradient", "jpeg80", "float64"])
def test_fast_path_matches_reference_on_simulated_frames(cat, case):
    cam = Camera.from_fov(8.0, 1024, 768 if case in ("gradient", "jpeg80") else None)
    sensor = SensorModel(bit_depth=8, n_hot_pixels=30) if case == "8bit" else SensorModel(n_hot_pixels=30)
    if case in ("gradient", "jpeg80"):  # a bright sky (2000 e-/px/s) makes vignetting and gradient show
        sensor = SensorModel(n_hot_pixels=30, sky_background_e_per_px_s=2000.0)
    extra = {}
    if case in ("gradient", "jpeg80"):
        extra = dict(vignetting=0.3, sky_gradient=0.2, faint_extra_mag=1.0)
    if case == "jpeg80":
        extra["jpeg_quality"] = 80
    n_found = 0
    for k, R in enumerate(random_attitudes(3, np.random.default_rng(77))):
        img = simulate_image(cat, cam, R, sensor, seed=k, mag_limit=8.5, **extra).image
        if case == "float64":
            img = img.astype(np.float64) / 7.0
        for est in (ESTIMATORS if k == 0 else ("fit",)):
            ref = _detect_centroids_reference(img, estimator=est)
            fast = detect_centroids(img, estimator=est)
            err = _assert_close(fast, ref, pos_tol={"gradient": 0.02, "jpeg80": 0.1}.get(case, 2e-3),
                                integer=case != "float64", unmatched=2 if case == "jpeg80" else 0)
            assert np.quantile(err, 0.95) <= (0.02 if case in ("gradient", "jpeg80") else 2e-4)
            n_found += len(fast)
        if case in ("8bit", "16bit"):
            assert fast.n_hot_pixels_rejected > 0
            assert abs(fast.n_hot_pixels_rejected - ref.n_hot_pixels_rejected) <= 2
        if case in ("gradient", "jpeg80"):
            assert not _background_stats(img)[-1]  # the background map path
    assert n_found > 30


@pytest.mark.parametrize("path", _REAL, ids=[p.stem for p in _REAL])
def test_fast_path_matches_reference_on_real_photographs(path):
    img = load_image(path)
    ref = _detect_centroids_reference(img)
    fast = detect_centroids(img)
    assert len(fast) >= 30
    assert abs(len(fast) - len(ref)) <= max(3, 0.05 * len(ref))
    _assert_close(fast, ref, pos_tol=0.02)


def test_fast_path_matches_reference_on_odd_inputs():
    """Memory order, colour, int16 and float32 input, small images, options, saturation, blends."""
    rng = np.random.default_rng(5)
    uv = rng.uniform(10, 240, (40, 2))
    img = _star_image(uv, rng.uniform(2e3, 8e4, 40), shape=(256, 256), noise=3.0)  # uint16, some saturated
    img[100, 100] = 60000  # a hot pixel
    pair = _star_image([[60.0, 60.0], [63.2, 61.0]], [30000.0, 20000.0], shape=(256, 256), bias=0)
    img = np.clip(img.astype(np.int64) + pair, 0, 65535).astype(np.uint16)
    big = _star_image(rng.uniform(10, 1000, (60, 2)), rng.uniform(2e3, 8e4, 60), shape=(1024, 1024), noise=3.0)
    cases = [
        (img, {}), (img.astype(np.int16) // 2, {}), (img.astype(np.float32), {}),
        (np.dstack([(img >> 8).astype(np.uint8)] * 3), {}),
        (img, dict(window=9, psf_sigma_px=1.1, k_sigma=3.0, min_pixels=4, deblend=False, saturation_level=40000)),
        (img[:40, :30], {}), (img, dict(background_block=32, iterations=3)), (big, {}),
    ]
    for im, kw in cases:
        for est in ESTIMATORS:
            fast = detect_centroids(im, estimator=est, **kw)
            _assert_close(fast, _detect_centroids_reference(im, estimator=est, **kw),
                          integer=np.asarray(im).dtype.kind in "ui")
            assert fast.n_hot_pixels_rejected == (1 if im is img and not kw else fast.n_hot_pixels_rejected)
    # the memory order of the same pixels changes nothing
    for est in ESTIMATORS:
        a = detect_centroids(img, estimator=est)
        for other in (np.asfortranarray(img), img.T.copy().T):
            b = detect_centroids(other, estimator=est)
            assert np.array_equal(a.uv, b.uv) and np.array_equal(a.brightness, b.brightness)
        t = detect_centroids(img.T, estimator=est)
        assert np.allclose(np.sort(t.uv[:, ::-1], axis=0), np.sort(a.uv, axis=0), atol=1e-6)


def test_fast_background_statistics_near_the_reference_ones(cat):
    f = simulate_image(cat, Camera.from_fov(8.0, 1024, 768), np.eye(3), seed=3, mag_limit=8.0, vignetting=0.3,
                       sky_gradient=0.2).image
    for im in (f, f.astype(np.float32) * np.float32(0.3), np.random.default_rng(1).normal(50, 4, (300, 500))):
        ref = _estimate_background_reference(np.asarray(im, dtype=np.float32))
        new = estimate_background(im)
        sigma = ref[2]
        assert new[2] == pytest.approx(sigma, rel=0.03)
        assert abs(new[1] - ref[1]) <= 0.25 * sigma
        assert isinstance(new[0], float) == isinstance(ref[0], float)
        if not isinstance(ref[0], float):
            assert np.abs(np.asarray(new[0]) - np.asarray(ref[0])).max() <= 0.5 * sigma
        if min(np.shape(im)) < 512:  # the reference's own sample
            assert new[1] == ref[1] and new[2] == pytest.approx(sigma, rel=1e-6)


def test_median_and_mad_from_one_partition():
    """The median and the MAD from one partition each are np.median's values, bit for bit and in the
    same dtype (odd and even counts, ties at the median as on integer images)."""
    from skyview.detect.centroids import _median_part
    rng = np.random.default_rng(11)
    for k in range(2000):
        r = rng.normal(0.0, 3.0, int(rng.integers(1, 80))).astype(np.float32)
        if k % 3 == 0:
            r = np.round(r)  # ties at the median (integer images)
        med = _median_part(r)
        assert med == np.median(r) and np.asarray(med).dtype == np.float32
        mad = _median_part(np.abs(r - med))
        ref = np.median(np.abs(r - np.median(r)))
        assert mad == ref and np.asarray(mad).dtype == np.asarray(ref).dtype


def test_sparse_labels_are_cv2_components():
    """The compacted labelling finds cv2's components of the full mask (one to one)."""
    rng = np.random.default_rng(0)
    for t in range(320):
        # the last 20: compacted images of 65,535 pixels or more (cv2's 32-bit labels, not the 16-bit ones)
        H, W = (int(x) for x in rng.integers(3, 70, 2)) if t < 300 else (int(x) for x in rng.integers(300, 420, 2))
        m = rng.random((H, W)) < rng.uniform(0.01, 0.5)
        idx = np.flatnonzero(m)
        if idx.size == 0:
            continue
        n, lab = cv2.connectedComponents(m.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
        mine, n2 = _label_sparse(idx, W)
        theirs = lab.reshape(-1)[idx]
        assert n2 == n and mine.min() == 1 and mine.max() == n - 1
        pairs = np.unique(np.stack([mine, theirs], axis=1), axis=0)
        assert len(pairs) == n - 1  # the same partition of the pixels


def test_band_thresholding_finds_every_pixel_above():
    """_above_idx (4-row band maxima, then the crossing bands compared) = np.flatnonzero(_above(...)),
    on heights that are and are not multiples of the band, every native dtype and float32, few and many
    crossing bands."""
    from skyview.detect.centroids import _above, _above_idx, _band_max
    rng = np.random.default_rng(3)
    for H, W in ((64, 50), (67, 31), (5, 9), (3, 3), (130, 64)):
        for dtype in (np.uint8, np.uint16, np.int16, np.float32):
            f = rng.normal(100.0, 5.0, (H, W))
            f[rng.integers(0, H, 4), rng.integers(0, W, 4)] += 80.0  # a few bright pixels: few bands
            f = f.astype(dtype)
            for t in (130.4, 100.0, 60.0, 1e6, -1e6):
                t32 = np.float32(t)
                want = np.flatnonzero(_above(f, t32))
                assert np.array_equal(_above_idx(f, t32), want)
                assert np.array_equal(_above_idx(f, t32, _band_max(f)), want)


def test_background_map_at_the_noise_samples_is_the_upsampled_map():
    """_upsample_at (cached interpolation weights) gives _upsample's map (cv2.resize) at every
    sample, phase and step, to float32 rounding."""
    from skyview.detect.centroids import _upsample, _upsample_at
    rng = np.random.default_rng(4)
    for gh, gw, by, bx, H, W in ((16, 16, 8, 16, 128, 256), (3, 5, 8, 8, 30, 47), (1, 4, 8, 8, 9, 40),
                                 (2, 1, 4, 4, 11, 5), (4, 3, 5, 7, 23, 22)):
        g = (rng.normal(0.0, 30.0, (gh, gw)) + 1000.0).astype(np.float32)
        full = _upsample(g, by, bx, H, W)
        for start, step in ((0, 1), (0, 2), (1, 2)):
            at = _upsample_at(g, by, bx, H, W, start, step)
            assert at.dtype == np.float32
            np.testing.assert_allclose(at, full[start::step, start::step], rtol=1e-6, atol=0)


def test_hot_pixels_and_stars_at_the_side_columns():
    """Hot pixels and stars in the first and last columns and rows (the 3 x 3 neighbourhoods that
    wrap into the next row are read through the zero-padded gather): as the reference."""
    img = _star_image([[1.0, 40.0], [126.2, 70.3], [60.0, 60.0], [0.4, 100.0]], [20000.0, 15000.0, 30000.0, 9000.0],
                      shape=(128, 128), noise=3.0, seed=2)
    for (i, j) in ((20, 0), (90, 127), (50, 0), (0, 30), (127, 64)):
        img[i, j] = 5000  # hot pixels on the borders
    for im in (img, img[1:-1]):  # with and without hot pixels in the first and last rows
        for est in ESTIMATORS:
            fast = detect_centroids(im, estimator=est)
            ref = _detect_centroids_reference(im, estimator=est)
            assert fast.n_hot_pixels_rejected == ref.n_hot_pixels_rejected >= 3
            _assert_close(fast, ref)


def test_label_peaks_are_the_last_of_a_lexsort():
    """Each label's brightest pixel (the last in order among equal values) is what np.lexsort gives."""
    from skyview.detect.centroids import _label_peaks
    rng = np.random.default_rng(8)
    for _ in range(300):
        n_lab = int(rng.integers(2, 30))
        lab = np.r_[np.arange(1, n_lab), rng.integers(1, n_lab, int(rng.integers(0, 200)))]
        rng.shuffle(lab)
        val = rng.integers(0, 6, lab.size).astype(np.float32)  # many ties
        order = np.lexsort((val, lab))
        last = np.r_[lab[order][1:] != lab[order][:-1], True]
        assert np.array_equal(_label_peaks(lab, val, n_lab), order[last])


def _random_windows(rng, n_st, n=7, amp=(20.0, 5000.0), noise=3.0):
    """(n_st, n, n) background-subtracted windows of Gaussian stars off-centre by up to 1.5 px, with noise."""
    d = np.arange(n) - n // 2
    off = rng.uniform(-1.5, 1.5, (n_st, 2))
    s2 = rng.uniform(0.6, 2.5, n_st) ** 2
    g = np.exp(-((d[None, None, :] - off[:, 0, None, None]) ** 2 + (d[None, :, None] - off[:, 1, None, None]) ** 2)
               / (2 * s2[:, None, None]))
    return rng.uniform(*amp, n_st)[:, None, None] * g + rng.normal(0.0, noise, (n_st, n, n))


def test_fast_gauss3_and_axis_ratio_are_the_plain_forms():
    """_gauss3_fast (negated, doubled curvature; no error-state switch) gives _gauss3's numbers, including
    the windows it rejects (non-positive marginals, flat or rising profiles); _axis_ratio_mm (all moments
    from one chain of products) gives _axis_ratio's ratios to ~1e-15."""
    from oracles.centroid_reference import _axis_ratio, _gauss3

    from skyview.detect.centroids import _axis_ratio_mm, _gauss3_fast
    rng = np.random.default_rng(11)
    n_rejected = 0
    for trial in range(300):
        n_st, n = int(rng.integers(1, 40)), int(rng.choice([5, 7, 9]))
        vals = _random_windows(rng, n_st, n, amp=(0.0, 3000.0), noise=float(rng.uniform(0.5, 20.0)))
        pi, pj = rng.integers(10, 500, n_st), rng.integers(10, 500, n_st)
        with np.errstate(divide="ignore", invalid="ignore"):
            ok, uv, s2 = _gauss3(vals, n // 2, pi, pj)
        ok_f, uv_f, s2_f = _gauss3_fast(vals, n // 2, pi, pj)
        assert np.array_equal(ok, ok_f)
        np.testing.assert_allclose(uv_f, uv, rtol=0, atol=1e-12)
        np.testing.assert_allclose(s2_f, s2, rtol=1e-14, equal_nan=True)
        n_rejected += int((~ok).sum())
        d = np.arange(n, dtype=np.float64) - n // 2
        X, Y = pj[:, None, None] + d[None, None, :], pi[:, None, None] + d[None, :, None]
        sigma = float(rng.uniform(0.5, 30.0))
        ref = _axis_ratio(vals, X, Y, uv, sigma)
        np.testing.assert_allclose(_axis_ratio_mm(vals, X[:, 0, :], Y[:, :, 0], uv, sigma), ref, rtol=1e-12,
                                   equal_nan=True)
    assert n_rejected > 100  # the rejections were exercised


def test_separable_fit_is_the_weighted_form():
    """The PSF fit of windows with every pixel used (the Gram matrix from the two axes' 2 x 2 Grams and the
    products with the data as (fv, dfv) V (fu, dfu)^T) gives what the weighted products give: the same
    windows fitted in a batch with one star that has a pixel left out (which makes the whole batch take
    the weighted form; each star's steps are its own)."""
    from skyview.detect.centroids import _psf_fit_sep
    rng = np.random.default_rng(12)
    for trial in range(100):
        n_st, h = int(rng.integers(1, 40)), int(rng.choice([2, 3, 4]))
        n = 2 * h + 1
        vals = _random_windows(rng, n_st + 1, n, noise=float(rng.uniform(0.5, 10.0)))
        pi, pj = rng.integers(10, 500, n_st + 1), rng.integers(10, 500, n_st + 1)
        d = np.arange(-h, h + 1, dtype=np.float64)
        X, Y = pj[:, None, None] + d[None, None, :], pi[:, None, None] + d[None, :, None]
        uv0 = np.stack([pj, pi], axis=1) + rng.uniform(-0.7, 0.7, (n_st + 1, 2))
        use = np.ones(vals.shape, dtype=bool)
        use[-1, h, h] = False  # the extra star: its peak left out, as a saturated one
        s = float(rng.uniform(0.7, 2.0))
        uv_w, a_w = _psf_fit_sep(vals, use, X, Y, uv0, s, h, pi, pj, 6)
        k = slice(0, n_st)
        uv_s, a_s = _psf_fit_sep(vals[k], use[k], X[k], Y[k], uv0[k], s, h, pi[k], pj[k], 6)
        np.testing.assert_allclose(uv_s, uv_w[k], rtol=0, atol=1e-9)
        np.testing.assert_allclose(a_s, a_w[k], rtol=1e-9)


def test_a_star_fits_the_same_alone_as_in_any_batch():
    """Each star's PSF fit and iwcog, in either form of the fit, are the numbers it gets fitted alone, bit
    for bit: what lets detect_centroids(max_stars=N) measure a subset and give the whole set's first N
    (a batched 3 x 3 matmul summed differently once a single star was left iterating)."""
    from skyview.detect.centroids import _cog, _iwcog_sep, _psf_fit_sep
    rng = np.random.default_rng(21)
    for trial in range(40):
        n_st, h = int(rng.integers(2, 30)), int(rng.choice([2, 3, 4]))
        vals = _random_windows(rng, n_st, 2 * h + 1, noise=float(rng.uniform(0.5, 10.0)))
        pi, pj = rng.integers(10, 500, n_st), rng.integers(10, 500, n_st)
        d = np.arange(-h, h + 1, dtype=np.float64)
        X, Y = pj[:, None, None] + d[None, None, :], pi[:, None, None] + d[None, :, None]
        uv0 = np.stack([pj, pi], axis=1) + rng.uniform(-0.7, 0.7, (n_st, 2))
        use = np.ones(vals.shape, dtype=bool)
        s = float(rng.uniform(0.7, 2.0))
        cog = _cog(vals, X, Y, pi, pj)
        iw = _iwcog_sep(vals, X, Y, cog, s, h, pi, pj, 6)
        for separable in (True, False):
            uv, amp = _psf_fit_sep(vals, use, X, Y, uv0, s, h, pi, pj, 6, separable=separable)
            for k in range(n_st):
                one = slice(k, k + 1)
                uv_k, amp_k = _psf_fit_sep(vals[one], use[one], X[one], Y[one], uv0[one], s, h, pi[one], pj[one], 6,
                                           separable=separable)
                assert np.array_equal(uv_k[0], uv[k]) and amp_k[0] == amp[k]
        for k in range(n_st):
            one = slice(k, k + 1)
            assert np.array_equal(_iwcog_sep(vals[one], X[one], Y[one], cog[one], s, h, pi[one], pj[one], 6)[0],
                                  iw[k])


def test_median_of_large_quantised_samples():
    """Large samples with few distinct values (the noise of an 8-bit frame: ~1 step) take the sort, the
    others the partition: np.median's value either way, odd and even counts."""
    from skyview.detect.centroids import _median_part
    rng = np.random.default_rng(12)
    for sd, n in ((0.5, 16384), (1.0, 16385), (13.0, 16384), (0.3, 5001), (3.0, 9999)):
        r = np.round(rng.normal(0.0, sd, n)).astype(np.float32) - np.float32(0.5)
        med = _median_part(r)
        assert med == np.median(r) and np.asarray(med).dtype == np.float32
        dev = np.abs(r - med)
        assert _median_part(dev) == np.median(dev)


def test_median_of_large_samples():
    """The noise's median by one partition (`_median_part`): np.median's value, in float32, for odd and even
    counts, heavy tails, sorted input and ties."""
    from skyview.detect import centroids as cm
    rng = np.random.default_rng(13)
    for k in range(200):
        n = int(rng.integers(5000, 40000))
        r = [rng.normal(0.0, 30.0, n), rng.normal(0.0, 3.0, n) + rng.standard_cauchy(n),
             np.sort(rng.normal(0.0, 1.0, n)), np.round(rng.normal(0.0, 40.0, n)) - 0.25][k % 4].astype(np.float32)
        med = cm._median_part(r)
        assert med == np.median(r) and np.asarray(med).dtype == np.float32
        dev = np.abs(r - med)
        assert cm._median_part(dev) == np.median(dev)


def test_narrower_window_is_the_middle_of_the_first_gather():
    """A measured PSF that wants a narrower window than the 7 px first gathered takes its middle: the
    centroids of a 5 px window asked for outright, bit for bit."""
    catalog = load_guide_catalog()
    cam = Camera.from_fov(8.0, 512, 384)
    R = random_attitudes(1, np.random.default_rng(4))[0]
    frame = simulate_image(catalog, cam, R, SensorModel(psf_sigma_px=0.7), seed=2, mag_limit=8.0)
    auto = detect_centroids(frame.image)
    assert auto.params["window_used"] == 5 and len(auto) >= 10
    given = detect_centroids(frame.image, window=5)
    assert np.array_equal(auto.uv, given.uv) and np.array_equal(auto.brightness, given.brightness)


def test_eight_bit_frame_finds_the_sixteen_bit_stars():
    """The same field as an 8-bit frame (one step per noise sigma, `simulate.to_uint8`) gives the stars of
    the 16-bit frame above 20 sigma, at the same places to a small fraction of a pixel."""
    from skyview.simulate.render import to_uint8
    rng = np.random.default_rng(3)
    H = W = 512
    img = rng.normal(400.0, 12.0, (H, W))
    yy, xx = np.mgrid[0:H, 0:W]
    stars = [(40.3 + 47.1 * k % 430, 35.7 + 83.9 * k % 440, 2000.0 + 900.0 * (k % 4)) for k in range(12)]
    for u, v, a in stars:
        img += a * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.2 ** 2))
    im16 = np.clip(np.rint(img), 0, 65535).astype(np.uint16)
    c16 = detect_centroids(im16)
    c8 = detect_centroids(to_uint8(im16)[0])
    assert len(c16) == len(stars)
    for u, v, _ in stars:
        d16 = np.hypot(c16.uv[:, 0] - u, c16.uv[:, 1] - v).min()
        d8 = np.hypot(c8.uv[:, 0] - u, c8.uv[:, 1] - v).min()
        assert d16 < 0.05 and d8 < 0.15


def test_hot_pixels_beside_a_blended_pair_match_the_reference():
    # hot pixels touching the pixels of a blob the deblender looks at, one beside the fainter star's peak
    # (two of them sharing neighbours): those pixels' neighbour maxima are read again after the repair, as
    # the reference reads them; with the hot pixel's value kept there the fainter peak is no local maximum
    # and the pair is not split
    uv = np.array([[50.3, 60.2], [54.3, 63.2]])  # 5 px apart, one blob
    img = _star_image(uv, [20000.0, 10000.0], noise=3.0)
    for i, j in [(63, 55), (65, 55), (58, 50), (80, 20)]:  # row, column; (63, 55) and (65, 55) share row 64
        img[i, j] = 30000
    fast = detect_centroids(img)
    ref = _detect_centroids_reference(img)
    assert fast.n_hot_pixels_rejected == ref.n_hot_pixels_rejected >= 3
    assert len(fast) == len(ref) == 2 and fast.blended.all() and ref.blended.all()
    assert np.abs(fast.uv - ref.uv).max() < 2e-3
    assert _nearest_err(fast.uv, uv).max() < 0.15  # (a repaired pixel beside the fainter peak: ~0.07 px)


def test_few_values_counts_as_unique():
    from skyview.detect.centroids import _few_values
    rng = np.random.default_rng(5)
    for n_vals in (1, 5, 31, 32, 33, 200):
        x = rng.integers(0, n_vals, 256).astype(np.float32) - np.float32(0.3)
        for k in (8, 32, 64):
            assert _few_values(x, k) == (np.unique(x).size < k)


def test_uint8_noise_from_the_histogram_is_the_per_sample_path():
    """A uint8 frame whose block medians are all equal (blocks of 2^k samples, or one block) takes its noise
    from the samples' 256-bin histogram (_u8_noise; counted from the contiguous blocks where they hold every
    sample, else from a copy of the samples); the same frame as uint16 takes the per-sample path (the
    bilinear map, the partitions, the clipped sums): the same grid, level, sigma and flat flag, bit for
    bit; on blocks of other sizes (300 x 257: 18 samples a block) the general path is kept."""
    from skyview.detect.centroids import _background_stats
    rng = np.random.default_rng(5)
    shapes = [(1024, 1024), (600, 800), (300, 257), (100, 90), (40, 40), (512, 2048)]
    hist_path = set()
    for trial in range(72):
        H, W = shapes[trial % 6]
        level, noise = rng.uniform(2, 220), (rng.uniform(0.2, 0.6) if trial % 12 < 6 else rng.uniform(0.6, 8))
        img = np.clip(np.rint(rng.normal(level, noise, (H, W))), 0, 255).astype(np.uint8)
        img[rng.integers(0, H, 30), rng.integers(0, W, 30)] = 255  # hot pixels and stars: outliers
        a, b = _background_stats(img), _background_stats(img.astype(np.uint16))
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1:] == b[1:]
        if a[0].min() == a[0].max():
            hist_path.add((H, W))
    assert set(shapes) <= hist_path  # (every shape compared on the histogram path, or 300 x 257 on the other)


def test_sparse_nonzero_is_flatnonzero():
    from skyview.detect.centroids import _flatnonzero_sparse
    rng = np.random.default_rng(9)
    for shape in ((64, 4096), (33, 4096), (3, 5), (8,), (7, 8), (0, 8), (16, 1024)):  # (>= 128 KiB: the word scan)
        for p in (0.0, 0.001, 0.05, 0.5, 1.0):
            m = rng.random(shape) < p
            assert np.array_equal(_flatnonzero_sparse(m), np.flatnonzero(m))


def _same_first(full: Centroids, cut: Centroids, n: int) -> None:
    """cut holds the first n centroids of full, field for field, bit for bit."""
    k = min(n, len(full))
    assert len(cut) == k and cut.n_unmeasured == len(full) - k
    for f in dataclasses.fields(Centroids):
        a, b = getattr(full, f.name), getattr(cut, f.name)
        if isinstance(a, np.ndarray) and a.shape[:1] == (len(full),):
            assert np.array_equal(a[:k], b, equal_nan=True), f.name
        elif f.name != "n_unmeasured":
            assert a == b or (a != a and b != b), f.name


def test_brightest_stars_only_are_the_first_of_the_whole_set(cat):
    """max_stars=N measures the N brightest of the detected stars only, and they are the first N of the
    whole set, every field the same to the bit: on dense 20 deg frames (8 and 16 bit, many blends, stars
    cut by the border), a frame with saturated stars, a blended pair and a hot pixel, and one with an
    extended blob holding several peaks; every estimator, N below, at and above the number of stars."""
    cam = Camera.from_fov(20.0, 1024, 768)
    frames = [simulate_image(cat, cam, R, SensorModel(bit_depth=bd, n_hot_pixels=30), seed=k, mag_limit=9.0).image
              for k, (R, bd) in enumerate(zip(random_attitudes(2, np.random.default_rng(8)), (8, 16)))]
    rng = np.random.default_rng(5)
    img = _star_image(rng.uniform(3, 253, (40, 2)), rng.uniform(2e3, 8e4, 40), shape=(256, 256), noise=3.0)
    img[100, 100] = 60000  # a hot pixel
    pair = _star_image([[60.0, 60.0], [63.2, 61.0]], [30000.0, 20000.0], shape=(256, 256), bias=0)
    frames.append(np.clip(img.astype(np.int64) + pair, 0, 65535).astype(np.uint16))
    glare = _star_image([[128.0, 128.0], [137.0, 131.0], [120.0, 136.0]], [4e6, 3e6, 3e6], shape=(256, 256),
                        sigma=6.0, noise=3.0)  # one blob far larger than a star, with three peaks
    frames.append(np.maximum(frames[-1], glare))
    cut_blends = 0
    for im in frames:
        for est in ESTIMATORS:
            full = detect_centroids(im, estimator=est)
            assert full.n_unmeasured == 0
            for n in sorted({1, 5, 25, max(len(full) - 1, 1), len(full), len(full) + 5}):
                cut = detect_centroids(im, estimator=est, max_stars=n)
                _same_first(full, cut, n)
                cut_blends += int(est == "fit" and full.blended[n:].any() and full.blended[:n].any())
    assert len(detect_centroids(frames[0])) > 150 and detect_centroids(frames[-1]).n_extended_rejected == 1
    assert cut_blends >= 2  # blends on both sides of the cut
    for bad in (0, -3, 2.5, True):
        with pytest.raises(BadInput, match="max_stars"):
            detect_centroids(frames[2], max_stars=bad)


def test_solver_measures_only_the_stars_it_identifies_with(cat):
    """The calibrated solver measures its max_stars brightest stars only; the identification is the same
    as with every star measured (what the viewer asks for), and it is right."""
    from skyview.simulate.scoring import score_trial
    from skyview.solver.pipeline import MethodSolver
    cam = Camera.from_fov(20.0, 1024, 1024)
    frame = simulate_image(cat, cam, random_attitudes(1, np.random.default_rng(4))[0], SensorModel(), seed=2,
                           mag_limit=8.5)
    solver = MethodSolver(cam, "angle", variant="improved", catalog=cat, max_stars=30)
    res, res_all = solver.solve_array(frame.image), solver.solve_array(frame.image, measure_all=True)
    assert len(res.centroids) == 30 and res_all.centroids.n_unmeasured == 0
    assert res.centroids.n_detected == len(res_all.centroids) > 100
    assert res.centroids.to_dict()["n_unmeasured"] == len(res_all.centroids) - 30
    assert score_trial(res, frame.truth)[0] == "correct"
    assert res.matches == res_all.matches and np.array_equal(res.R, res_all.R)
    assert res.to_dict()["n_centroids"] == res.centroids.n_detected


@pytest.mark.slow
def test_time_centroiding_times_the_centroider_it_is_given():
    """The timing helper docs/benchmarks.md runs: both the package's centroider and the oracle, each
    call counted, the stars found per frame reported."""
    from skyview.bench.centroids import time_centroiding

    calls = []

    def counted(image):
        calls.append(image.shape)
        return _detect_centroids_reference(image)

    ours = time_centroiding(2)
    ref = time_centroiding(2, detect=counted)
    assert set(ours) == set(ref) == {"sim 8-bit 1024x1024", "sim 16-bit 1024x1024"}
    assert len(calls) == 2 * 3 and all(shape == (1024, 1024) for shape in calls)  # a warm-up + 2 per kind
    for kind in ours:
        assert ours[kind]["median_ms"] > 0 and ref[kind]["median_ms"] > 0
        assert ours[kind]["median_stars"] == ref[kind]["median_stars"] > 5  # the same stars, as test above checks


def test_pairs_within_groups_are_the_grids_pairs_that_share_a_label():
    # the deblender's pairs of one component, without the n x n grid (17,000 peaks on a lit roof made it 300M)
    from skyview.detect.centroids import _pairs_within_groups

    rng = np.random.default_rng(0)
    for n in (0, 1, 5, 40, 300):
        lab = rng.integers(0, max(1, n // 3), n)
        sa, sb = np.divmod(np.arange(n * n), n)
        keep = lab[sa] == lab[sb]
        a, b = _pairs_within_groups(lab)
        np.testing.assert_array_equal(a, sa[keep])
        np.testing.assert_array_equal(b, sb[keep])


def test_work_maps_kept_between_frames_leave_no_trace_in_the_answers():
    """detect_centroids keeps its background and residual maps for the next frame of the same size (their
    page faults cost as much as the passes that fill them): a frame's centroids are the same whatever was
    detected before, and nothing returned refers to the maps (the next frame would overwrite it)."""
    from skyview.detect import centroids as ce

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:256, 0:320]
    frames = []
    for k in range(3):
        img = 100.0 + 0.2 * xx + 0.1 * k * yy + rng.normal(0, 3, (256, 320))  # a gradient: the map is made
        for u, v in rng.uniform(20, 230, (12, 2)):
            img += 800.0 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.3 ** 2))
        frames.append(np.clip(img, 0, 65535).astype(np.uint16))
    first = [ce.detect_centroids(f) for f in frames]
    kept = [c.uv.copy() for c in first]
    again = [ce.detect_centroids(f) for f in reversed(frames)][::-1]
    with ce._WORK_MAPS.pair(256, 320) as a:
        pass
    with ce._WORK_MAPS.pair(256, 320) as b:
        assert b[1] is a[1]  # kept for the next frame of that size
        with ce._WORK_MAPS.pair(256, 320) as c:
            assert c[1] is not b[1]  # lent to one call at a time
    assert len(ce._WORK_MAPS._free) <= ce._WORK_MAPS.keep  # bounded
    for c, uv, d in zip(first, kept, again):
        assert len(c) >= 10 and np.array_equal(c.uv, uv) and np.array_equal(d.uv, uv)
        assert np.array_equal(c.brightness, d.brightness)


def test_row_median_is_numpys_median_row_by_row():
    """`row_median` (one selection at the middle, and for an even count the left part's largest): np.median's
    values, in the array's dtype, for odd and even counts, ties, sorted and reversed rows, one row and one column."""
    from skyview.detect.centroids import row_median

    rng = np.random.default_rng(21)
    shapes = [(100, 40), (7, 9), (3, 2), (50, 1000), (1, 1), (4, 6), (1, 4001), (300, 8)]
    for shape in shapes:
        for a in (rng.normal(size=shape), np.round(3 * rng.normal(size=shape)), rng.normal(size=shape).astype(np.float32),
                  np.sort(rng.normal(size=shape), axis=1)[:, ::-1]):
            got, want = row_median(a), np.median(a, axis=1)
            assert np.array_equal(got, want) and got.dtype == want.dtype, (shape, a.dtype)


@pytest.mark.parametrize("case", ["flat", "map"])
def test_blends_split_all_at_once_as_one_at_a_time(cat, monkeypatch, case):
    """The deblender's secondary peaks, every blob's r-th candidate tested at once (`_dipped_peaks`, a dense
    frame's form), are the walk's one candidate at a time (`_dipped_peaks_walk`, a sparse frame's), number for
    number: a dense 8-bit JPEG of 60 deg (thousands of blobs, hundreds split, some into several), on a flat sky
    and on a map, each frame's centroids found through the one and through the other."""
    import skyview.detect.centroids as centroids_module

    cam = Camera.from_fov(60.0, 800, 600)
    extra = dict(jpeg_quality=80, faint_extra_mag=2.0)
    if case == "map":
        extra.update(vignetting=0.4, sky_gradient=0.4)
    sensor = SensorModel(bit_depth=8, sky_background_e_per_px_s=2000.0 if case == "map" else 20.0)
    calls = []
    batched = centroids_module._dipped_peaks

    def counted(*args):
        calls.append(len(args[4]))
        return batched(*args)

    for k, R in enumerate(random_attitudes(2, np.random.default_rng(5))):
        img = simulate_image(cat, cam, R, sensor, seed=k, mag_limit=6.5, **extra).image
        assert _background_stats(img)[-1] == (case == "flat")
        monkeypatch.setattr(centroids_module, "_dipped_peaks", counted)
        fast = detect_centroids(img)
        monkeypatch.setattr(centroids_module, "_WALK_MAX_CANDIDATES", 10 ** 9)  # every frame walked
        walk = detect_centroids(img)
        monkeypatch.undo()
        assert fast.blended.sum() >= 80
        for f in dataclasses.fields(fast):
            a, b = getattr(fast, f.name), getattr(walk, f.name)
            assert (np.array_equal(a, b, equal_nan=True) if isinstance(a, np.ndarray) else a == b or a != a), f.name
    assert len(calls) == 2 and min(calls) >= 500  # the batched form ran, on hundreds of candidates
