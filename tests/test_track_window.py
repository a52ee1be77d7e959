"""The tracking's windowed centroider (skyview.detect.windows) and its closed-form geometry
(skyview.identify.tracking) against the project's reference tools, on simulated frames with known truth."""

import math

import numpy as np
import pytest

from skyview.core.attitude import random_attitudes, svd_attitude
from skyview.core.camera import Camera
from skyview.core.catalog import load_guide_catalog
from skyview.detect.centroids import detect_centroids
from skyview.detect.windows import centroid_windows, measure_windows, window_centers
from skyview.identify.tracking import match_radii, nearest_one_to_one, rotation_matrix, rotvec, wahba
from skyview.identify.tracking import predicted_sigma as predicted_sigma_closed
from skyview.identify.verify import predicted_sigma, star_radii
from skyview.simulate.render import SensorModel, simulate_image

CAM = Camera.from_fov(12.0, 1024)


@pytest.fixture(scope="module")
def frames():
    cat = load_guide_catalog()
    rng = np.random.default_rng(5)
    return [simulate_image(cat, CAM, R, SensorModel(), seed=20 + i, mag_limit=6.5)
            for i, R in enumerate(random_attitudes(6, rng))]


def test_window_centroids_agree_with_the_whole_image_centroider(frames):
    """Windows around the 16 brightest stars, centred 2 px off (a prediction error): every star of
    SNR >= 20 away from a window side is found, at the position detect_centroids gives (< 0.05 px RMS;
    measured 0.0003 px), and both are as close to the truth."""
    rng = np.random.default_rng(0)
    d_det, d_true_w, d_true_d = [], [], []
    for f in frames:
        truth = f.truth["stars"]
        uv_true = f.rendered_uv
        snr = np.array([s["snr"] for s in truth])
        full = detect_centroids(f.image)
        sel = np.arange(min(16, len(uv_true)))
        centers, half = window_centers(uv_true[sel] + rng.normal(0.0, 2.0, (len(sel), 2)), 8.0, CAM.width, CAM.height)
        win = centroid_windows(f.image, centers, half, CAM.pixel_scale_rad, psf_sigma_px=full.psf_sigma_px)
        c = win.centroids
        for k in np.flatnonzero(~c.edge):
            j = int(np.argmin(np.linalg.norm(uv_true - c.uv[k], axis=1)))
            if snr[j] < 20:
                continue
            m = int(np.argmin(np.linalg.norm(full.uv - c.uv[k], axis=1)))
            d_det.append(full.uv[m] - c.uv[k])
            d_true_w.append(c.uv[k] - uv_true[j])
            d_true_d.append(full.uv[m] - uv_true[j])
        # every bright star inside the frame (not near the border) got its window's centroid
        inside = (np.all(uv_true[sel] > 12, axis=1) & np.all(uv_true[sel] < CAM.width - 12, axis=1)
                  & (snr[sel] >= 20))
        found = np.min(np.linalg.norm(uv_true[sel][inside, None] - c.uv[None], axis=2), axis=1)
        assert np.all(found < 0.5)
    rms = lambda a: float(np.sqrt(np.mean(np.sum(np.square(a), axis=1))))  # noqa: E731
    assert len(d_det) >= 60
    assert rms(d_det) < 0.05
    assert rms(d_true_w) < 0.1 and abs(rms(d_true_w) - rms(d_true_d)) < 0.01


def test_empty_saturated_and_edge_windows_are_flagged():
    img = np.full((64, 64), 100, dtype=np.uint16)
    img += np.random.default_rng(1).integers(0, 5, img.shape).astype(np.uint16)
    yy, xx = np.mgrid[:64, :64]
    star = lambda u, v, a: a * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.2 ** 2))  # noqa: E731
    img = np.minimum(img + star(20.3, 30.6, 2000) + star(45.0, 12.0, 200000) + star(60.0, 50.0, 2000),
                     65535).astype(np.uint16)
    img[5, 5] = 60000  # a hot pixel alone in a window
    ws = measure_windows(img, np.array([[20, 30], [45, 12], [5, 5], [40, 50], [56, 50]]), 6, psf_sigma_px=1.2)
    assert ws.found.tolist() == [True, True, False, False, True]
    assert np.allclose(ws.uv[0], [20.3, 30.6], atol=0.05)
    assert ws.saturated.tolist()[:2] == [False, True]
    assert not ws.edge[0] and ws.edge[4]  # the star at (60, 50) is at the side of the window centred at 56
    assert np.isnan(ws.uv[2]).all()


def test_overlapping_windows_give_one_centroid_per_star(frames):
    f = frames[0]
    uv = f.rendered_uv[:1]
    win = centroid_windows(f.image, np.rint(np.vstack([uv, uv + 3])).astype(int), 8, CAM.pixel_scale_rad)
    assert len(win.centroids) == 1 and win.window.tolist() == [0]


def test_closed_forms_match_the_reference_tools():
    rng = np.random.default_rng(2)
    b = rng.normal(size=(20, 3))
    b /= np.linalg.norm(b, axis=1)[:, None]
    A = rng.normal(size=(3, 3)) * 1e-4
    P = A @ A.T + np.diag([1e-10, 2e-10, 3e-9])
    assert np.allclose(predicted_sigma_closed(b, P), predicted_sigma(b, P), rtol=1e-9)
    assert np.allclose(match_radii(b, P, 1e-5, 3e-5), star_radii(b, P, 1e-5, 3e-5), rtol=1e-9)
    R = rotation_matrix(np.array([0.3, -0.2, 1.1]))
    assert np.allclose(R @ R.T, np.eye(3)) and np.allclose(rotvec(R), [0.3, -0.2, 1.1])
    r = rng.normal(size=(6, 3))
    r /= np.linalg.norm(r, axis=1)[:, None]
    obs = r @ R.T + rng.normal(0, 1e-5, r.shape)
    Rw, Pw = wahba(obs, r, 1e-5)
    ref = svd_attitude(obs, r, 1e-5)
    assert np.allclose(Rw, ref.R, atol=1e-12) and np.allclose(Pw, ref.covariance, rtol=1e-6)
    # nearest-neighbour matching: the ambiguous query (two refs within its radius) is left out
    ref_v = np.array([[0, 0, 1.0], [math.sin(1e-4), 0, math.cos(1e-4)], [0, math.sin(0.01), math.cos(0.01)]])
    q = np.array([[0, 0, 1.0], [0, math.sin(0.0101), math.cos(0.0101)]])
    qi, rj, left = nearest_one_to_one(q, ref_v, np.array([3e-4, 3e-4]))
    assert qi.tolist() == [1] and rj.tolist() == [2] and left == 1
