"""Frames, pixels, attitude and roll exactly as docs/conventions.md says."""

import numpy as np
import pytest

from skyview.core.attitude import (
    R_from_quat,
    R_from_radec_roll,
    attitude_error_arcsec,
    east_north,
    q_method_attitude,
    quat_from_R,
    radec_roll_from_R,
    random_attitudes,
    svd_attitude,
)
from skyview.core.camera import Camera, check_fov_deg
from skyview.core.catalog import radec_to_vec, vec_to_radec
from skyview.core.errors import BadInput

RNG = np.random.default_rng(20251125)


def test_unit_vector_of_a_star_follows_icrs_formula():
    ra, dec = np.radians(30.0), np.radians(60.0)
    v = radec_to_vec(ra, dec)
    np.testing.assert_allclose(v, [0.5 * np.cos(ra), 0.5 * np.sin(ra), np.sin(dec)], atol=1e-15)
    ra2, dec2 = vec_to_radec(v)
    assert ra2 == pytest.approx(ra) and dec2 == pytest.approx(dec)


def test_rows_of_R_are_camera_axes_in_icrs():
    R = R_from_radec_roll(np.radians(83.8), np.radians(-5.4), np.radians(30))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # the boresight is row 2 and maps to +z
    np.testing.assert_allclose(R @ R[2], [0, 0, 1], atol=1e-14)
    np.testing.assert_allclose(R[2], radec_to_vec(np.radians(83.8), np.radians(-5.4)), atol=1e-14)


@pytest.mark.parametrize("ra,dec,roll", [(0, 0, 0), (83.8, -5.4, 30), (250, 45, -170), (359.9, -89.0, 90),
                                         (10, 89.5, 179.0)])
def test_radec_roll_round_trip(ra, dec, roll):
    R = R_from_radec_roll(np.radians(ra), np.radians(dec), np.radians(roll))
    ra2, dec2, roll2 = np.degrees(radec_roll_from_R(R))
    assert ra2 == pytest.approx(ra, abs=1e-9)
    assert dec2 == pytest.approx(dec, abs=1e-9)
    assert roll2 == pytest.approx(roll, abs=1e-9)


def test_roll_zero_is_north_up_east_left():
    cam = Camera.from_fov(10, 1000)
    ra0, dec0 = np.radians(100.0), np.radians(20.0)
    R = R_from_radec_roll(ra0, dec0, 0.0)
    north = radec_to_vec(ra0, dec0 + np.radians(1))
    east = radec_to_vec(ra0 + np.radians(1), dec0)
    (un, vn), (ue, ve) = cam.project(np.stack([north, east]) @ R.T)[0]
    assert vn < cam.cy - 50 and abs(un - cam.cx) < 1  # north is up
    assert ue < cam.cx - 50 and abs(ve - cam.cy) < 5  # east is to the left


def test_roll_90_turns_image_up_to_east():
    ra0, dec0 = np.radians(10.0), np.radians(-30.0)
    R = R_from_radec_roll(ra0, dec0, np.radians(90))
    east, north = east_north(R[2])
    np.testing.assert_allclose(-R[1], east, atol=1e-12)


def test_quaternion_is_scalar_first_and_round_trips():
    # 90 deg about camera-frame z: v_cam = R v
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    q = quat_from_R(R)
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)
    for R in random_attitudes(20, RNG):
        q = quat_from_R(R)
        assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(R_from_quat(q), R, atol=1e-12)


def test_pinhole_pixel_convention():
    cam = Camera.from_fov(8.0, 1024, 768)
    assert (cam.cx, cam.cy) == (511.5, 383.5)
    assert cam.fov_deg == pytest.approx(8.0)
    # the left edge of pixel 0 and the right edge of pixel W-1 are at +-FOV/2
    v = cam.unproject(np.array([[-0.5, cam.cy], [1023.5, cam.cy]]))
    assert np.degrees(np.arccos(v[0] @ v[1])) == pytest.approx(8.0, abs=1e-9)
    # +x right = increasing u, +y down = increasing v
    uv, _ = cam.project(np.array([[0.01, 0.02, 1.0]]))
    u, w = uv[0]
    assert u > cam.cx and w > cam.cy
    assert u == pytest.approx(cam.fx * 0.01 + cam.cx) and w == pytest.approx(cam.fy * 0.02 + cam.cy)


@pytest.mark.parametrize("k1,k2", [(0.0, 0.0), (-0.2, 0.05), (0.15, 0.0)])
def test_project_unproject_round_trip(k1, k2):
    cam = Camera.from_fov(20.0, 1024, 1024, k1=k1, k2=k2)
    uv = RNG.uniform(-0.5, 1023.5, size=(200, 2))
    v = cam.unproject(uv)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
    uv2, front = cam.project(v)
    assert front.all()
    np.testing.assert_allclose(uv2, uv, atol=1e-6)


def test_unproject_undistorted_is_the_pinhole_formula():
    """The undistorted camera's direct path gives the model's numbers to the last bit: (x, y, 1) / |.|
    with x = (u - cx) / fx, y = (v - cy) / fy, for one pixel or many, any numeric input."""
    cam = Camera(width=640, height=480, fx=1800.0, fy=1750.0, cx=300.25, cy=250.75)
    uv = RNG.uniform(-20.0, 700.0, size=(37, 2))
    xyz = np.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy, np.ones(len(uv))], axis=1)
    want = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    assert np.array_equal(cam.unproject(uv), want)
    assert np.array_equal(cam.unproject(uv[3]), want[3:4])  # one pixel: a (1, 3) array
    assert np.array_equal(cam.unproject(uv.astype(np.float32)), cam.unproject(uv.astype(np.float32).astype(float)))
    assert np.array_equal(cam.unproject([[12, 34]]), cam.unproject(np.array([[12.0, 34.0]])))
    assert cam.unproject(np.zeros((0, 2))).shape == (0, 3)


def test_behind_the_camera_is_not_visible():
    cam = Camera.from_fov(8.0, 512)
    uv, front = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    assert list(front) == [False, True] and np.isnan(uv[0]).all()


@pytest.mark.parametrize("fov", [0, -5, 180, 200, float("nan"), "wide"])
def test_impossible_fov_is_bad_input(fov):
    with pytest.raises(BadInput):
        check_fov_deg(fov)


def _noisy_pairs(R, n, sigma):
    r = RNG.normal(size=(n, 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    b = r @ R.T + RNG.normal(scale=sigma, size=(n, 3))
    return b / np.linalg.norm(b, axis=1, keepdims=True), r


@pytest.mark.parametrize("estimator", [svd_attitude, q_method_attitude])
def test_estimators_recover_known_rotation_exactly_without_noise(estimator):
    for R in random_attitudes(10, RNG):
        b, r = _noisy_pairs(R, 5, 0.0)
        est = estimator(b, r, 1e-4)
        np.testing.assert_allclose(est.R, R, atol=1e-12)
        assert np.linalg.det(est.R) == pytest.approx(1.0)


def test_estimators_agree_and_covariance_predicts_the_scatter():
    """With star-like geometry (8 deg field) the reported sigma matches the Monte Carlo scatter."""
    sigma = 20e-6
    R = R_from_radec_roll(1.0, 0.3, 0.2)
    cam = Camera.from_fov(8.0, 1024)
    uv = RNG.uniform(0, 1023, size=(12, 2))
    r = cam.unproject(uv) @ R  # ICRS directions of stars in the field
    errs, sig_b, sig_r = [], [], []
    for _ in range(400):
        b = r @ R.T + RNG.normal(scale=sigma, size=r.shape)
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        e1, e2 = svd_attitude(b, r, sigma), q_method_attitude(b, r, sigma)
        np.testing.assert_allclose(e1.R, e2.R, atol=1e-10)
        err = attitude_error_arcsec(e1.R, R)
        errs.append([err["cross_x"], err["cross_y"], err["roll"]])
        sig_b.append(e1.sigma_boresight_arcsec)
        sig_r.append(e1.sigma_roll_arcsec)
    errs = np.array(errs)
    cross_rms = np.sqrt(np.mean(errs[:, :2] ** 2))
    roll_rms = np.sqrt(np.mean(errs[:, 2] ** 2))
    assert cross_rms == pytest.approx(np.mean(sig_b), rel=0.15)
    assert roll_rms == pytest.approx(np.mean(sig_r), rel=0.15)
    assert np.mean(sig_r) > 5 * np.mean(sig_b)  # roll is the weak axis of a narrow field


def test_attitude_error_components():
    R = R_from_radec_roll(0.5, 0.1, 0.0)
    small = np.radians(10 / 3600)
    Rz = np.array([[np.cos(small), -np.sin(small), 0], [np.sin(small), np.cos(small), 0], [0, 0, 1]])
    err = attitude_error_arcsec(Rz @ R, R)
    assert err["roll"] == pytest.approx(10.0, rel=1e-6)
    assert err["boresight"] == pytest.approx(0.0, abs=1e-3)


def test_covariance_and_weights_match_the_general_linear_algebra():
    """The closed-form 3x3 inverse, the scalar-sigma weights and the determinant sign give what
    np.linalg.pinv / det / broadcast weights give; all-parallel vectors fall back to the pseudo-inverse."""
    from skyview.core.attitude import _weights, attitude_covariance
    for R in random_attitudes(20, RNG):
        n = int(RNG.integers(2, 12))
        b, r = _noisy_pairs(R, n, 1e-4)
        sig = RNG.uniform(1e-5, 1e-3, n)
        for s in (float(sig[0]), np.float64(sig[0]), sig):
            w = 1.0 / np.broadcast_to(np.asarray(s, dtype=np.float64), (n,)) ** 2
            np.testing.assert_array_equal(_weights(n, s), w)
            F = w.sum() * np.eye(3) - (b * w[:, None]).T @ b
            np.testing.assert_allclose(attitude_covariance(b, w), np.linalg.pinv(F), rtol=1e-9, atol=0)
        est = svd_attitude(b, r, 1e-4)
        U, _, Vt = np.linalg.svd((b / 1e-8).T @ r)
        np.testing.assert_allclose(est.R, U @ np.diag([1.0, 1.0, np.linalg.det(U) * np.linalg.det(Vt)]) @ Vt,
                                   atol=1e-12)
    b = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(attitude_covariance(b, np.ones(2)), np.linalg.pinv(2 * np.eye(3) - b.T @ b))
    for bad in (0.0, -1.0, np.array([1.0, 0.0])):
        with pytest.raises(ValueError):
            svd_attitude(b, b, bad)


def test_proper_rotation_is_markleys_svd_step():
    """proper_rotation(sum b r^T) is svd_attitude's rotation (equal weights), and a proper one even when
    the profile matrix holds a reflection."""
    from skyview.core.attitude import proper_rotation, random_attitudes, svd_attitude

    rng = np.random.default_rng(5)
    for R in random_attitudes(20, rng):
        r = rng.normal(size=(6, 3))
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        b = r @ R.T + rng.normal(0.0, 1e-4, (6, 3))
        assert np.array_equal(proper_rotation(b.T @ r), svd_attitude(b, r).R)
        assert np.allclose(proper_rotation(b.T @ r), R, atol=1e-3)
    mirror = np.diag([1.0, 1.0, -1.0])
    Rm = proper_rotation(mirror)
    assert np.isclose(np.linalg.det(Rm), 1.0) and np.allclose(Rm @ Rm.T, np.eye(3))


def test_half_diagonal_is_the_farthest_corners_angle():
    """Camera.half_diagonal_rad (a pinhole's from its corners in Python floats) is the angle between the
    boresight and the farthest corner's unprojected ray, for off-centre, non-square and distorted cameras."""
    from skyview.core.camera import Camera

    rng = np.random.default_rng(8)
    for _ in range(300):
        w, h = (int(x) for x in rng.integers(16, 6000, 2))
        f = float(rng.uniform(0.3, 20.0)) * w
        cam = Camera(w, h, f, f * float(rng.uniform(0.95, 1.05)), float(rng.uniform(0, w)), float(rng.uniform(0, h)),
                     float(rng.choice([0.0, 1.0]) * rng.uniform(-0.1, 0.1)), float(rng.choice([0.0, 1.0]) * rng.uniform(-0.02, 0.02)))
        corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
        expected = float(np.max(np.arccos(np.clip(cam.unproject(corners)[:, 2], -1.0, 1.0))))
        assert cam.half_diagonal_rad == pytest.approx(expected, rel=1e-12, abs=1e-15)
