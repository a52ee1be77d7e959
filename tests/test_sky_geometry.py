"""Drawable geometry: arcs stay on the sphere and on the great circle, the footprint matches the FOV."""

import numpy as np
import pytest

from skyview.core.attitude import R_from_radec_roll
from skyview.core.camera import Camera
from skyview.core.catalog import radec_to_vec
from skyview.core.sky_geometry import (
    arcs_as_segments,
    great_circle_arc,
    group_edges,
    group_segments,
    radec_grid,
    sensor_footprint,
    star_radius,
)


def test_arc_is_on_the_sphere_and_the_great_circle():
    a, b = radec_to_vec(0.1, 0.2), radec_to_vec(0.5, -0.1)
    arc = great_circle_arc(a, b, 20)
    np.testing.assert_allclose(np.linalg.norm(arc, axis=1), 1.0, atol=1e-12)
    normal = np.cross(a, b)
    np.testing.assert_allclose(arc @ normal, 0.0, atol=1e-12)
    np.testing.assert_allclose(arc[0], a) and np.testing.assert_allclose(arc[-1], b)
    steps = np.arccos(np.clip(np.sum(arc[1:] * arc[:-1], axis=1), -1, 1))
    np.testing.assert_allclose(steps, np.arccos(a @ b) / 19, rtol=1e-9)


def test_batched_arcs_equal_single_arcs():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(5, 3)); a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = rng.normal(size=(5, 3)); b /= np.linalg.norm(b, axis=1, keepdims=True)
    segs = arcs_as_segments(a, b, 6).reshape(5, 5, 2, 3)
    for k in range(5):
        arc = great_circle_arc(a[k], b[k], 6)
        np.testing.assert_allclose(segs[k, :, 0], arc[:-1], atol=1e-12)
        np.testing.assert_allclose(segs[k, :, 1], arc[1:], atol=1e-12)


def test_triangles_close_and_pairs_do_not():
    assert group_edges([(1, 2)]).tolist() == [[1, 2]]
    assert group_edges([(1, 2, 3)]).tolist() == [[1, 2], [2, 3], [3, 1]]
    xyz = np.eye(3)
    assert group_segments(xyz, [(0, 1, 2)], 5).shape == (12, 2, 3)


def test_footprint_corners_are_at_the_half_diagonal():
    cam = Camera.from_fov(8.0, 1024, 768)
    R = R_from_radec_roll(1.0, 0.4, 0.3)
    fp = sensor_footprint(cam, R, 8)
    np.testing.assert_allclose(fp[0], fp[-1])
    ang = np.degrees(np.arccos(np.clip(fp @ R[2], -1, 1)))
    assert ang.max() == pytest.approx(np.degrees(cam.half_diagonal_rad), rel=1e-9)
    assert ang.min() == pytest.approx(np.degrees(np.arctan(384 / cam.fy)), rel=1e-6)


def test_grid_and_sizes():
    lines = radec_grid(30, 30)
    assert len(lines) == 12 + 5
    assert all(np.allclose(np.linalg.norm(p, axis=1), 1) for p in lines)
    r = star_radius(np.array([-1.5, 0.0, 6.0, 9.0]))
    assert r[0] >= r[1] > r[2] >= r[3] > 0
