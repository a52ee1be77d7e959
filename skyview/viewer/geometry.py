"""The viewer's geometry on the celestial sphere (radius 1, seen from its centre), as pure functions.

Poses for viser (`pose_wxyz`), the frustum scale that puts the sensor image at a depth, where a click
ray meets the sphere and which catalog star is nearest to it, the fine RA/Dec grid around a boresight,
rings around centroids; and the proper names of the brightest stars. No viser scene here: `scene`
draws with these.
"""

from __future__ import annotations

import math

import numpy as np
import viser.transforms as vtf

from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, radec_to_vec, vec_to_radec
from skyview.core.sky_geometry import polylines_as_segments, sensor_mesh

# Proper names of the brightest stars (HIP -> name), for the sky labels.
STAR_NAMES = {
    32349: "Sirius", 30438: "Canopus", 91262: "Vega", 69673: "Arcturus", 71683: "Rigil Kentaurus",
    24436: "Rigel", 24608: "Capella", 7588: "Achernar", 37279: "Procyon", 27989: "Betelgeuse",
    68702: "Hadar", 60718: "Acrux", 97649: "Altair", 65474: "Spica", 80763: "Antares", 21421: "Aldebaran",
    62434: "Mimosa", 113368: "Fomalhaut", 37826: "Pollux", 102098: "Deneb", 49669: "Regulus",
    33579: "Adhara", 85927: "Shaula", 25336: "Bellatrix", 36850: "Castor", 25428: "Elnath",
    26311: "Alnilam", 61084: "Gacrux", 45238: "Miaplacidus", 26727: "Alnitak", 109268: "Alnair",
    11767: "Polaris", 25930: "Mintaka", 27366: "Saiph", 54061: "Dubhe", 53910: "Merak", 62956: "Alioth",
    65378: "Mizar", 67301: "Alkaid", 3179: "Schedar", 746: "Caph", 677: "Alpheratz", 15863: "Mirfak",
    14576: "Algol", 9884: "Hamal",
}

def pose_wxyz(R: np.ndarray) -> np.ndarray:
    """Camera -> world rotation of skyview's R (v_cam = R v_icrs) as viser's wxyz."""
    return vtf.SO3.from_matrix(np.asarray(R, dtype=np.float64).T).wxyz


def frustum_scale(camera: Camera, depth: float) -> float:
    """viser normalises its frustum's volume: the `scale` that puts the far plane at `depth`."""
    ty = camera.height / (2.0 * camera.fy)
    tx = camera.width / (2.0 * camera.fx)
    return float(depth * np.cbrt(tx * ty / 3.0))


def ray_to_sphere(origin, direction) -> np.ndarray | None:
    """Where a view ray leaves the unit sphere (the far root: the sky seen from inside)."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    b = o @ d
    c = o @ o - 1.0
    disc = b * b - c
    if disc < 0:
        return None
    t = -b + math.sqrt(disc)
    if t <= 0:
        return None
    p = o + t * d
    return p / np.linalg.norm(p)


def nice_step(fov_deg: float) -> float:
    """Fine-grid spacing: about a third of the field, from a round list."""
    for s in (0.25, 0.5, 1.0, 2.0, 5.0, 10.0):
        if s >= fov_deg / 4.0:
            return s
    return 15.0


def sky_grid_labels() -> list[tuple[str, np.ndarray]]:
    """The coarse grid's labels: hours along the equator, declinations along 0h and 12h, the poles."""
    labels = [(f"{hour}h", radec_to_vec(math.radians(15.0 * hour), math.radians(1.0))) for hour in range(0, 24, 2)]
    for ra_h in (0, 12):
        for dec in (-60, -30, 30, 60):
            labels.append((f"{dec:+d}°", radec_to_vec(math.radians(15.0 * ra_h + 1.0), math.radians(dec))))
    return labels + [("N pole", np.array([0.0, 0.0, 1.0])), ("S pole", np.array([0.0, 0.0, -1.0]))]


def local_grid(b: np.ndarray, radius_rad: float, step_deg: float, n_per_line: int = 80):
    """RA/Dec lines every `step_deg` within `radius_rad` of `b`: segments and label anchors.

    Returns (segments (S, 2, 3), labels [(text, xyz)]): meridians labelled along the grid parallel
    nearest to `b`, parallels along the nearest meridian.
    """
    ra0, dec0 = (math.degrees(x) for x in vec_to_radec(np.asarray(b, dtype=np.float64)))
    r = math.degrees(radius_rad)
    dec_lo, dec_hi = max(-90.0, dec0 - r), min(90.0, dec0 + r)
    cos_edge = math.cos(math.radians(max(abs(dec_lo), abs(dec_hi))))
    if dec_hi >= 89.999 or dec_lo <= -89.999 or cos_edge < 1e-3 or r / cos_edge >= 180:
        ra_lo, ra_hi = 0.0, 360.0
    else:
        half = r / cos_edge
        ra_lo, ra_hi = ra0 - half, ra0 + half
    lines = []
    ras = np.arange(math.ceil(ra_lo / step_deg) * step_deg, ra_hi + 1e-9, step_deg)
    ras = ras[ras < ra_lo + 360.0 - 1e-9] if ra_hi - ra_lo >= 360.0 else ras
    decs = np.arange(math.ceil(dec_lo / step_deg) * step_deg, dec_hi + 1e-9, step_deg)
    decs = decs[(decs > -90.0) & (decs < 90.0)]
    dd = np.radians(np.linspace(dec_lo, dec_hi, n_per_line))
    for ra in ras:
        lines.append(radec_to_vec(np.full_like(dd, math.radians(ra)), dd))
    rr = np.radians(np.linspace(ra_lo, ra_hi, 2 * n_per_line))
    for dec in decs:
        lines.append(radec_to_vec(rr, np.full_like(rr, math.radians(dec))))
    segs = polylines_as_segments(lines)
    if len(segs):
        mid = segs.mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        segs = segs[mid @ b >= math.cos(radius_rad)]
    labels = []
    if len(decs):
        d_near = float(decs[np.argmin(np.abs(decs - dec0))])
        for ra in ras:
            p = radec_to_vec(math.radians(ra), math.radians(d_near))
            if p @ b >= math.cos(radius_rad * 0.9):
                labels.append((f"{ra % 360:g}°", p))
    if len(ras):
        diff = (ras - ra0 + 180.0) % 360.0 - 180.0
        ra_near = float(ras[np.argmin(np.abs(diff))])
        for dec in decs:
            p = radec_to_vec(math.radians(ra_near), math.radians(dec))
            if p @ b >= math.cos(radius_rad * 0.9):
                labels.append((f"{dec:+g}°", p))
    return segs, labels


def ring_segments(xy: np.ndarray, radius: float, depth: float, n: int = 14) -> np.ndarray:
    """Circles (as segments) around points of the plane z = depth in the camera frame."""
    if len(xy) == 0:
        return np.zeros((0, 2, 3), dtype=np.float32)
    t = np.linspace(0.0, 2.0 * np.pi, n + 1)
    c = np.stack([np.cos(t), np.sin(t)], axis=1) * radius  # (n+1, 2)
    pts = xy[:, None, :] + c[None, :, :]  # (N, n+1, 2)
    p3 = np.concatenate([pts, np.full(pts.shape[:2] + (1,), depth)], axis=2)
    return np.stack([p3[:, :-1], p3[:, 1:]], axis=2).reshape(-1, 2, 3)


def nearest_star(catalog: GuideCatalog, direction: np.ndarray, max_angle_rad: float) -> int | None:
    """Row of the catalog star nearest to a direction, if within max_angle_rad."""
    d, i = catalog.tree.query(np.asarray(direction, dtype=np.float64))
    if not np.isfinite(d) or 2.0 * math.asin(min(1.0, d / 2.0)) > max_angle_rad:
        return None
    return int(i)


def image_plane_xy(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) -> where their directions cross the pinhole image plane at unit depth (x/z, y/z):
    with lens distortion, where the star is on the sky, not where the lens put it on the sensor, so that
    a ring drawn there sits on the catalog star and on the undistorted texture (`undistorted`)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if not camera.distorted:
        return (uv - np.array([camera.cx, camera.cy])) / np.array([camera.fx, camera.fy])
    v = camera.unproject(uv)
    return v[:, :2] / v[:, 2:]


def fisheye_photo_glb(camera: Camera, texture_rgb: np.ndarray, depth: float, jpeg_quality: int = 85) -> bytes:
    """The sensor's mesh (`core.sky_geometry.sensor_mesh`) at `depth`, textured with the photograph (an RGB texture of it, any size), as binary glTF: its
    texture a JPEG, its material unlit (KHR_materials_unlit: the photograph as it is, whatever the scene's lights)
    and seen from both sides."""
    import io
    import json
    import struct

    import cv2
    import trimesh
    from PIL import Image

    directions, faces, pixels = sensor_mesh(camera)
    vertices = directions * depth
    # texture coordinates: the image's left edge at 0, its top edge at 1 (trimesh's convention; its glTF export
    # turns them over)
    uv = np.stack([(pixels[:, 0] + 0.5) / camera.width, 1.0 - (pixels[:, 1] + 0.5) / camera.height], axis=1)
    ok, jpeg = cv2.imencode(".jpg", np.ascontiguousarray(texture_rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    image = Image.open(io.BytesIO(jpeg.tobytes()))  # (a JPEG's image: the glTF holds its bytes as a JPEG)
    material = trimesh.visual.material.PBRMaterial(baseColorTexture=image, doubleSided=True, metallicFactor=0.0,
                                                   roughnessFactor=1.0)
    mesh = trimesh.Trimesh(vertices, faces, visual=trimesh.visual.TextureVisuals(uv=uv, material=material),
                           process=False)
    glb = trimesh.exchange.gltf.export_glb(mesh)
    # the material unlit: the JSON chunk rewritten (the binary chunk after it as it is)
    n_json = struct.unpack("<I", glb[12:16])[0]
    tree = json.loads(glb[20:20 + n_json])
    for m in tree.get("materials", []):
        m.setdefault("extensions", {})["KHR_materials_unlit"] = {}
    tree["extensionsUsed"] = sorted(set(tree.get("extensionsUsed", [])) | {"KHR_materials_unlit"})
    text = json.dumps(tree, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    rest = glb[20 + n_json:]
    return struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(text) + len(rest)) + struct.pack(
        "<II", len(text), 0x4E4F534A) + text + rest


def sky_ring_segments(directions: np.ndarray, radius_rad: float, depth: float, n: int = 14) -> np.ndarray:
    """Circles (as segments) of angular radius `radius_rad` around unit directions (N, 3) of the camera frame, at
    `depth`: `ring_segments` for a fisheye's photograph, whose surface is a sphere, not a plane."""
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if len(d) == 0:
        return np.zeros((0, 2, 3), dtype=np.float32)
    e1 = np.cross(d, np.where(np.abs(d[:, 2:]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]]))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(d, e1)
    t = np.linspace(0.0, 2.0 * np.pi, n + 1)
    pts = depth * (math.cos(radius_rad) * d[:, None, :] + math.sin(radius_rad) * (
        np.cos(t)[None, :, None] * e1[:, None, :] + np.sin(t)[None, :, None] * e2[:, None, :]))
    return np.stack([pts[:, :-1], pts[:, 1:]], axis=2).reshape(-1, 2, 3)


def undistorted(image: np.ndarray, camera: Camera) -> np.ndarray:
    """The image (of the camera's sensor, or a resized texture of it) as an ideal pinhole of the same focal
    length and principal point would have taken it (OpenCV's remap with the camera's radial k1, k2): drawn
    on the frustum, its stars sit where their directions cross the image plane. An undistorted camera's
    image is returned as it is."""
    if not camera.distorted:
        return image
    import cv2

    h, w = image.shape[:2]
    sx, sy = w / camera.width, h / camera.height  # a texture: the camera's pixels scaled to its own
    K = np.array([[camera.fx * sx, 0.0, (camera.cx + 0.5) * sx - 0.5],
                  [0.0, camera.fy * sy, (camera.cy + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]])
    return cv2.undistort(image, K, np.array([camera.k1, camera.k2, 0.0, 0.0]), None, K)


def constellations_in_view(camera: Camera, R: np.ndarray, n: int = 7) -> list[str]:
    """The IAU constellations a solved field covers (astropy's constellation boundaries), the boresight's
    first, then the others by how much of an n x n grid of the image each holds."""
    import astropy.units as u
    from astropy.coordinates import SkyCoord, get_constellation

    us, vs = np.meshgrid(np.linspace(0, camera.width - 1, n), np.linspace(0, camera.height - 1, n))
    uv = np.column_stack([[camera.cx, *us.ravel()], [camera.cy, *vs.ravel()]])
    ra, dec = vec_to_radec(camera.unproject(uv) @ np.asarray(R, dtype=np.float64))  # v_icrs = R^T v_cam
    names = [str(x) for x in get_constellation(SkyCoord(ra=np.degrees(ra) * u.deg, dec=np.degrees(dec) * u.deg))]
    counts: dict[str, int] = {}
    for name in names[1:]:
        counts[name] = counts.get(name, 0) + 1
    return [names[0], *sorted((k for k in counts if k != names[0]), key=lambda k: -counts[k])]
