"""Drawable geometry on the celestial sphere, shared by the Viser viewer and the Rerun recorder.

Pure numpy: great-circle arcs between stars, the sensor footprint on the sky, an RA/Dec grid, outlines
of regions of the sky (a polygon of great-circle arcs, a small circle), and the sizes and colours of
stars from their magnitudes. Nothing here knows about a viewer or a step.
"""

from __future__ import annotations

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import radec_to_vec


def great_circle_arc(a: np.ndarray, b: np.ndarray, n_points: int = 16) -> np.ndarray:
    """(n_points, 3) unit vectors along the shorter great circle from a to b (slerp)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    omega = np.arccos(np.clip(a @ b, -1.0, 1.0))
    t = np.linspace(0.0, 1.0, n_points)[:, None]
    if omega < 1e-12:
        return np.repeat(a[None, :], n_points, axis=0)
    return (np.sin((1 - t) * omega) * a + np.sin(t * omega) * b) / np.sin(omega)


def arcs_as_segments(starts: np.ndarray, ends: np.ndarray, n_points: int = 8) -> np.ndarray:
    """Great-circle arcs between many pairs of unit vectors, as line segments (M * (n-1), 2, 3).

    Vectorised slerp: one batched call draws every candidate pair or triangle side of a step.
    """
    a = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
    if len(a) == 0:
        return np.zeros((0, 2, 3))
    omega = np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0))[:, None, None]
    t = np.linspace(0.0, 1.0, n_points)[None, :, None]
    s = np.sin(omega)
    safe = np.where(s < 1e-12, 1.0, s)
    pts = np.where(s < 1e-12, a[:, None, :] * np.ones_like(t),
                   (np.sin((1 - t) * omega) * a[:, None, :] + np.sin(t * omega) * b[:, None, :]) / safe)
    return np.stack([pts[:, :-1], pts[:, 1:]], axis=2).reshape(-1, 2, 3)


def group_edges(groups: list[tuple[int, ...]] | np.ndarray) -> np.ndarray:
    """Edges (E, 2) of catalog-row tuples: a pair is one edge, a triangle (or more) a closed polygon."""
    edges = []
    for g in groups:
        g = [int(x) for x in g]
        if len(g) == 2:
            edges.append((g[0], g[1]))
        elif len(g) > 2:
            edges.extend((g[k], g[(k + 1) % len(g)]) for k in range(len(g)))
    return np.array(edges, dtype=np.int64).reshape(-1, 2)


def group_segments(xyz: np.ndarray, groups, n_points: int = 8) -> np.ndarray:
    """Great-circle segments for every edge of every group (catalog rows into xyz)."""
    e = group_edges(groups)
    if len(e) == 0:
        return np.zeros((0, 2, 3))
    return arcs_as_segments(xyz[e[:, 0]], xyz[e[:, 1]], n_points)


OUTLINE_EDGE_POINTS = 9  # points per great-circle edge of an outline polygon (8 segments)
OUTLINE_CIRCLE_POINTS = 97  # points around an outline small circle (96 segments, first == last)


def polygon_outline(corners: np.ndarray, n_per_edge: int = OUTLINE_EDGE_POINTS) -> np.ndarray:
    """A closed polygon on the sphere ((M, 3), first == last): corners (K, 3) unit vectors, K >= 3, in order
    around the region, joined by great-circle arcs (the last corner joins the first)."""
    c = np.asarray(corners, dtype=np.float64).reshape(-1, 3)
    c = c / np.linalg.norm(c, axis=1)[:, None]
    segs = arcs_as_segments(c, np.roll(c, -1, axis=0), max(2, int(n_per_edge)))
    poly = np.concatenate([segs[:, 0], segs[-1:, 1]])
    poly[-1] = poly[0]  # exactly closed
    return poly


def small_circle(center: np.ndarray, radius_rad: float, n_points: int = OUTLINE_CIRCLE_POINTS) -> np.ndarray:
    """The small circle at angular radius `radius_rad` around the unit vector `center`, closed ((n, 3))."""
    c = np.asarray(center, dtype=np.float64).reshape(3)
    c = c / np.linalg.norm(c)
    e = np.cross([0.0, 0.0, 1.0], c) if abs(c[2]) < 0.9 else np.cross([1.0, 0.0, 0.0], c)
    e /= np.linalg.norm(e)
    n = np.cross(c, e)
    t = np.linspace(0.0, 2.0 * np.pi, max(4, int(n_points)))[:, None]
    poly = np.cos(radius_rad) * c + np.sin(radius_rad) * (np.cos(t) * e + np.sin(t) * n)
    poly[-1] = poly[0]
    return poly


def sensor_footprint(camera: Camera, R: np.ndarray, n_per_edge: int = 16) -> np.ndarray:
    """ICRS unit vectors around the sensor border (closed polyline, (4 n + 1, 3))."""
    w, h = camera.width - 0.5, camera.height - 0.5
    t = np.linspace(0.0, 1.0, n_per_edge, endpoint=False)
    top = np.stack([-0.5 + t * (w + 0.5), np.full_like(t, -0.5)], 1)
    right = np.stack([np.full_like(t, w), -0.5 + t * (h + 0.5)], 1)
    bottom = np.stack([w - t * (w + 0.5), np.full_like(t, h)], 1)
    left = np.stack([np.full_like(t, -0.5), h - t * (h + 0.5)], 1)
    uv = np.concatenate([top, right, bottom, left, top[:1]])
    return camera.unproject(uv) @ np.asarray(R)  # v_icrs = R^T v_cam


SENSOR_MESH_POINTS = 65  # `sensor_mesh`: a grid of this many points a side (a 180 deg lens: 2.8 deg apart)


def sensor_mesh(camera: Camera, n: int = SENSOR_MESH_POINTS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sensor as a mesh of the directions its pixels see, where no plane holds its image (a fisheye's): an
    n x n grid of pixel positions from edge to edge (-0.5 to W - 0.5), each point's camera-frame unit vector (the
    lens's own projection, k1 and k2 included), and the two triangles of each grid cell; a cell with a corner
    the lens does not see (beyond an equisolid lens's 180 deg from its axis) is left out. Drawn at a depth with
    the image as its texture, its stars lie where their directions cross it. (directions (V, 3), triangles
    (F, 3), pixels (V, 2))"""
    u, v = np.meshgrid(np.linspace(-0.5, camera.width - 0.5, n), np.linspace(-0.5, camera.height - 0.5, n))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    d = camera.unproject(pixels)
    seen = np.isfinite(d).all(axis=1)
    k = np.arange(n * n).reshape(n, n)
    a, b, c, e = k[:-1, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], axis=1), np.stack([b, c, e], axis=1)])
    return np.where(seen[:, None], d, 0.0), faces[seen[faces].all(axis=1)], pixels


def radec_grid(ra_step_deg: float = 30.0, dec_step_deg: float = 15.0, n_points: int = 90) -> list[np.ndarray]:
    """Polylines of constant RA (meridians) and constant Dec (parallels) as ICRS unit vectors."""
    lines = []
    dec = np.radians(np.linspace(-90, 90, n_points))
    for ra in np.arange(0.0, 360.0, ra_step_deg):
        lines.append(radec_to_vec(np.full_like(dec, np.radians(ra)), dec))
    ra = np.radians(np.linspace(0, 360, 2 * n_points))
    for d in np.arange(-90.0 + dec_step_deg, 90.0, dec_step_deg):
        lines.append(radec_to_vec(ra, np.full_like(ra, np.radians(d))))
    return lines


def polylines_as_segments(lines: list[np.ndarray]) -> np.ndarray:
    """Polylines to one (S, 2, 3) segment array (one batched draw call)."""
    segs = [np.stack([p[:-1], p[1:]], axis=1) for p in lines if len(p) > 1]
    return np.concatenate(segs) if segs else np.zeros((0, 2, 3))


def star_radius(mag: np.ndarray, r_bright: float = 0.010, r_faint: float = 0.0025,
                mag_bright: float = -1.0, mag_faint: float = 6.5) -> np.ndarray:
    """Point radius on the unit sphere: brighter stars larger (linear in magnitude, clipped)."""
    t = np.clip((np.asarray(mag, dtype=np.float64) - mag_bright) / (mag_faint - mag_bright), 0.0, 1.0)
    return r_bright + t * (r_faint - r_bright)


def star_color(mag: np.ndarray, bv: np.ndarray | None = None) -> np.ndarray:
    """uint8 RGB: tint from B-V (blue-white to orange) when known, dimmed with magnitude."""
    mag = np.asarray(mag, dtype=np.float64)
    if bv is None:
        bv = np.full_like(mag, 0.6)
    bv = np.nan_to_num(np.asarray(bv, dtype=np.float64), nan=0.6)
    t = np.clip((bv + 0.3) / 2.0, 0.0, 1.0)[:, None]
    blue = np.array([170.0, 200.0, 255.0])
    orange = np.array([255.0, 190.0, 120.0])
    rgb = (1 - t) * blue + t * orange
    dim = np.clip(1.0 - 0.09 * np.clip(mag - 1.0, 0.0, None), 0.35, 1.0)[:, None]
    return np.clip(rgb * dim, 0, 255).astype(np.uint8)


def magnitude_bins(mag: np.ndarray, edges=(-2.0, 1.0, 2.5, 4.0, 5.0, 6.0, 7.0, 99.0)) -> list[np.ndarray]:
    """Indices of stars per magnitude bin (one point cloud per bin where point size is per cloud)."""
    mag = np.asarray(mag)
    return [np.flatnonzero((mag >= lo) & (mag < hi)) for lo, hi in zip(edges[:-1], edges[1:])]
