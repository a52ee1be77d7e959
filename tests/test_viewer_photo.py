"""A user's own photograph in the viewer: drawn with the camera its solve fitted, so that every catalog star
sits on its blob — on the frustum's image plane, on the undistorted texture and in the panel, checked in the
session, from what the page receives over the websocket and in headless Chromium's own three.js scene — and
the Scenario tab shows what was found. Real photographs of two fields of view (an 11.4 deg lens with barrel
distortion, and a crop of it: 5.7 deg)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import viewer_session

from skyview.core.attitude import radec_roll_from_R
from skyview.detect.centroids import load_image
from skyview.viewer.geometry import image_plane_xy, undistorted
from skyview.viewer.picture import texture
from skyview.viewer.scene import NODES

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())
PHOTO = "2019-07-29T204726_Alt40_Azi45_Try1.png"  # the most distorted of the eight (k1 about -0.007 at the corner)


@pytest.fixture(scope="module")
def session():
    with viewer_session() as (server, s):
        yield server, s


def _upload(s, image: np.ndarray, name: str, typed_fov: float):
    ok, png = cv2.imencode(".png", image)
    s.panel.upload_fov.value = typed_fov  # a wrong hint: the FOV is fitted to the stars
    s.receive_upload(name, png.tobytes())
    assert s.wait_idle(60) and s.error == ""
    return s.run


def _crop(image: np.ndarray) -> np.ndarray:
    h, w = image.shape
    return np.ascontiguousarray(image[h // 4: h // 4 + h // 2, w // 4: w // 4 + w // 2])


@pytest.mark.slow
@pytest.mark.parametrize("crop", [False, True], ids=["11.4deg", "5.7deg-crop"])
def test_catalog_stars_sit_on_the_photographs_stars(session, crop):
    server, s = session
    image = load_image(REAL / PHOTO)
    if crop:
        image = _crop(image)
    run = _upload(s, image, "mine.png", typed_fov=8.0)
    r, cam = run.result, run.source.camera
    assert r.solved and r.method == "blind" and r.camera_fitted and run.source.fitted
    ref = REFERENCE[PHOTO]
    assert cam.fov_deg == pytest.approx(ref["fov_deg"] / (2.0 if crop else 1.0), rel=0.01)
    # the scene's camera is the fitted one, not the 8 deg typed
    assert (cam.fov_deg, cam.k1, cam.k2) == pytest.approx((r.camera.fov_deg, r.camera.k1, r.camera.k2), rel=1e-12)
    # the frustum is drawn at the fitted FOV
    frustum = server.scene.get_handle_by_name(NODES["frustum"])
    assert np.degrees(frustum.fov) == pytest.approx(cam.fov_v_deg, rel=1e-6)
    # every matched catalog star, turned into the camera frame, crosses the image plane on its ring
    idx = sorted(run.matches)
    rows = [run.matches[i] for i in idx]
    p = run.catalog.xyz[rows] @ r.R.T
    on_plane = p[:, :2] / p[:, 2:]
    rings = image_plane_xy(cam, r.centroids.uv[idx])
    px = np.hypot(*((on_plane - rings) * cam.fx).T)  # in the camera's pixels
    assert len(idx) >= 10 and np.median(px) < 0.5 and px.max() < 2.0
    # ... and on its blob in the undistorted texture drawn on the frustum
    tex = undistorted(texture(image), cam)[..., 0].astype(float)
    scale = tex.shape[1] / cam.width
    t_uv = (on_plane * [cam.fx, cam.fy] + [cam.cx, cam.cy] + 0.5) * scale - 0.5
    background = np.median(tex)
    bright = [tex[int(round(v)), int(round(u))] for u, v in t_uv
              if 1 <= u < tex.shape[1] - 1 and 1 <= v < tex.shape[0] - 1]
    rng = np.random.default_rng(0)  # the same test at random places of the texture: mostly the dark floor
    anywhere = tex[rng.integers(1, tex.shape[0] - 1, 500), rng.integers(1, tex.shape[1] - 1, 500)]
    assert np.mean(np.array(bright) > background + 15) > 0.9 and np.mean(anywhere > background + 15) < 0.1
    # the Scenario tab shows what was found, and the method and variant that ran
    ra, dec, roll = np.degrees(radec_roll_from_R(r.R))
    assert s.panel.ra.value == pytest.approx(ra % 360, abs=1e-3) and s.panel.dec.value == pytest.approx(dec, abs=1e-3)
    assert s.panel.fov.value == pytest.approx(cam.fov_deg, abs=1e-3)
    assert s.panel.upload_fov.value == pytest.approx(cam.fov_deg, abs=1e-3)
    assert s.panel.method.value == "blind" and s.panel.variant.value == "improved"
    assert "fitted" in s.panel.result.content
    assert " · in Cassiopeia" in s.panel.status.content  # where it is, in words (RA 355 deg, Dec +58 deg)


def test_a_mirror_image_is_drawn_turned_over_with_the_catalog_stars_on_its_stars(session):
    """A photograph mirrored left to right (a star diagonal's) solves with its rows turned over, and the viewer
    draws it so: the texture is the turned image, and every matched catalog star crosses the image plane on
    its ring and lands on its blob there."""
    server, s = session
    photo = load_image(REAL / PHOTO)
    run = _upload(s, np.ascontiguousarray(photo[:, ::-1]), "diagonal.png", typed_fov=8.0)
    r, cam = run.result, run.source.camera
    assert r.solved and r.rows_reversed and run.source.fitted
    assert np.array_equal(run.source.image, photo[::-1, ::-1])  # the mirror, turned over: drawn the sky's way
    idx = sorted(run.matches)
    p = run.catalog.xyz[[run.matches[i] for i in idx]] @ r.R.T
    on_plane = p[:, :2] / p[:, 2:]
    px = np.hypot(*((on_plane - image_plane_xy(cam, r.centroids.uv[idx])) * cam.fx).T)
    assert len(idx) >= 10 and np.median(px) < 0.5
    tex = undistorted(texture(run.source.image), cam)[..., 0].astype(float)
    scale = tex.shape[1] / cam.width
    t_uv = (on_plane * [cam.fx, cam.fy] + [cam.cx, cam.cy] + 0.5) * scale - 0.5
    bright = [tex[int(round(v)), int(round(u))] for u, v in t_uv
              if 1 <= u < tex.shape[1] - 1 and 1 <= v < tex.shape[0] - 1]
    assert np.mean(np.array(bright) > np.median(tex) + 15) > 0.9
    assert "mirror image" in s.panel.status.content and "mirror image" in s.panel.result.content


@pytest.mark.slow
def test_a_negative_is_solved_and_drawn_inverted(session):
    """A photograph exported as a negative (dark stars on a bright sky): the upload solves with its values inverted
    and the viewer draws it so, its stars bright under their rings, the note in the status."""
    server, s = session
    photo = load_image(REAL / PHOTO)
    run = _upload(s, 65535 - photo, "negative.png", typed_fov=11.4)
    r = run.result
    assert r.solved and any("negative" in n for n in r.notes)
    assert float(np.median(run.source.image)) < 0.5 * float(np.max(run.source.image))  # the stars bright again
    want = REFERENCE[PHOTO]
    ra, dec, _ = np.degrees(radec_roll_from_R(r.R))
    assert abs(((ra - want["ra_deg"] + 180) % 360 - 180) * np.cos(np.radians(dec))) < 0.02 and abs(dec - want["dec_deg"]) < 0.02
    assert "negative" in s.panel.status.content or "negative" in s.panel.result.content


def test_a_distorted_camera_moves_the_rings_and_the_texture_together():
    """image_plane_xy and undistorted agree: a star's pixel, undistorted, lands where the remapped texture
    shows it (a synthetic dot through a strongly distorted camera)."""
    from skyview.core.camera import Camera

    cam = Camera.from_fov(40.0, 640, 480, k1=-0.3, k2=0.05)
    v = np.array([[0.3, -0.2, 1.0]])
    uv, _ = cam.project(v)
    img = np.zeros((480, 640), np.uint8)
    cv2.circle(img, (int(round(uv[0, 0])), int(round(uv[0, 1]))), 2, 255, -1)
    flat = undistorted(img, cam)
    xy = image_plane_xy(cam, uv)[0]
    u0, v0 = xy * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    assert np.allclose(xy, v[0, :2], atol=1e-9)
    m = cv2.moments(flat.astype(np.float32))
    assert np.hypot(m["m10"] / m["m00"] - u0, m["m01"] / m["m00"] - v0) < 0.7
    assert np.hypot(*(uv[0] - [u0, v0])) > 10  # the lens moved it: the test would see a wrong remap


def test_a_busy_photograph_rings_its_brightest_detections_and_more_on_request(session):
    """800+ detections: the brightest DETECTIONS_DRAWN are ringed by default (on the frustum and in the
    panel image), the View tab's "Detections drawn" shows more; the identification is the same."""
    from skyview.core.attitude import R_from_radec_roll
    from skyview.core.camera import Camera
    from skyview.simulate.render import SensorModel, simulate_image
    from skyview.viewer.panel import DETECTIONS_DRAWN

    server, s = session
    cam = Camera.from_fov(45.0, 1600, 1200)
    R = R_from_radec_roll(np.radians(272.0), np.radians(-22.0), 0.0)  # the Milky Way in Sagittarius
    frame = simulate_image(s.solvers.base_catalog, cam, R, SensorModel(), seed=2, mag_limit=9.0)
    run = _upload(s, frame.image, "busy.png", typed_fov=45.0)
    n = len(run.result.centroids)
    assert n > 800 and run.result.solved
    rings = server.scene.get_handle_by_name(NODES["centroids"])
    per_ring = len(rings.points) // DETECTIONS_DRAWN
    assert len(rings.points) == DETECTIONS_DRAWN * per_ring
    matches = dict(run.matches)
    s.panel.detections.value = 2000
    assert s.wait_idle(30) and s.run is run and dict(s.run.matches) == matches
    rings = server.scene.get_handle_by_name(NODES["centroids"])
    assert len(rings.points) == n * per_ring
    s.panel.detections.value = DETECTIONS_DRAWN


def test_the_bundled_photographs_are_one_click_away(session):
    server, s = session
    names = [n for n in s.panel.gallery.options if n != "-"]
    assert sorted(names) == sorted(p.name for p in REAL.glob("*.png")) and s.panel.gallery.visible
    s.panel.gallery.value = PHOTO  # as a user picks it from the list
    assert s.wait_idle(60) and s.error == ""
    assert s.run.source.name == PHOTO and s.run.result.solved and s.run.source.fitted
    ra, dec, _ = np.degrees(radec_roll_from_R(s.run.result.R))
    ref = REFERENCE[PHOTO]
    # within 0.02 deg of cedar-solve's reference: this photograph is its most distorted (57" apart: README)
    assert abs(dec - ref["dec_deg"]) < 0.02 and abs((ra - ref["ra_deg"] + 180) % 360 - 180) < 0.02


def test_constellations_in_view_are_the_iau_ones_around_the_boresight():
    from skyview.core.attitude import R_from_radec_roll
    from skyview.core.camera import Camera
    from skyview.viewer.geometry import constellations_in_view

    orion = constellations_in_view(Camera.from_fov(8.0, 1024, 768), R_from_radec_roll(np.radians(83.8),
                                                                                        np.radians(-5.4), 0.3))
    assert orion == ["Orion"]  # the belt and the sword: one constellation
    wide = constellations_in_view(Camera.from_fov(40.0, 1024, 768), R_from_radec_roll(np.radians(83.8),
                                                                                       np.radians(-5.4), 0.3))
    # a 40 x 30 deg field on Orion reaches its neighbours on every side, the boresight's first
    assert wide[0] == "Orion" and {"Eridanus", "Monoceros", "Lepus", "Taurus"} <= set(wide) and len(set(wide)) == len(wide)


@pytest.mark.slow
def test_a_telescope_field_and_an_all_sky_frame_are_drawn_from_what_solved_them(session, catalog):
    # a 1.2 deg field solves in the deep catalog (its matches index that catalog's rows, not the guide
    # catalog's), a 180 deg all-sky frame through a fisheye; then a photograph of the usual kind again
    from skyview.core.attitude import attitude_error_arcsec, random_attitudes
    from skyview.core.camera import Camera
    from skyview.core.deep_catalog import load_deep_catalog
    from skyview.simulate.render import SensorModel, simulate_image
    from skyview.simulate.scenarios import get_scenario

    server, s = session
    deep = load_deep_catalog(catalog.epoch)
    R = random_attitudes(2, np.random.default_rng(7))
    narrow = simulate_image(deep, Camera.from_fov(1.2, 1024, 768), R[0], SensorModel(exposure_s=2.0), seed=1,
                            mag_limit=10.0)
    run = _upload(s, narrow.image, "m44.png", typed_fov=8.0)
    assert run.result.solved and run.catalog is run.result.catalog and len(run.catalog) > 400_000
    assert attitude_error_arcsec(run.result.R, R[0])["boresight"] < 5.0
    assert run.source.camera.fov_deg == pytest.approx(1.2, rel=1e-3)
    sc = get_scenario("allsky180")
    sky = simulate_image(catalog, sc.camera(), R[1], sc.sensor(), seed=2, **sc.render_kwargs())
    run = _upload(s, sky.image, "allsky.png", typed_fov=8.0)
    assert run.result.solved and run.source.camera.fisheye and run.source.camera.model == run.result.camera.model
    assert s.panel.upload_fov.value <= 90.0  # the next photograph's hint stays a pinhole's
    _assert_fisheye_drawn(s, run)
    run = _upload(s, load_image(REAL / PHOTO), "mine.png", typed_fov=8.0)
    assert run.result.solved and not run.source.camera.fisheye
    # the panel image carries the solved photograph's RA/Dec grid: the same panel drawn without it differs
    # along the lines
    from skyview.present.sky_grid import image_grid
    from skyview.viewer.picture import annotate, panel_base, stretch

    panel = np.asarray(s.panel.image.image)
    n = s.rings_drawn
    bare = annotate(panel_base(stretch(run.source.image)), run.source.image.shape, run.result.centroids.uv[:n],
                    run.outcomes[:n])
    assert panel.shape == bare.shape and np.count_nonzero(np.any(panel != bare, axis=2)) > 500
    assert image_grid(run.result.camera, run.result.R)


def _assert_fisheye_drawn(s, run) -> None:
    """An all-sky photograph in the 3-D scene: no frustum (none holds 180 deg) but a mesh over the sphere, textured
    with the photograph as it is (an unlit material, a JPEG texture), where every identified star's direction
    crosses the mesh at the texture coordinates of its own centroid; its rings on the sphere around those
    directions."""
    import json as json_module
    import struct

    from skyview.core.sky_geometry import sensor_mesh
    from skyview.viewer.scene import IMAGE_DEPTH

    cam = run.source.camera
    handle = s.sky.h["frustum"]
    assert type(handle).__name__ == "GlbHandle"
    for on in (False, True):  # the View tab's "image" switch hides and shows it
        s.sky.set_visible("image", on)
        assert handle.visible is on
    glb = handle.glb_data
    n_json = struct.unpack("<I", glb[12:16])[0]
    tree = json_module.loads(glb[20:20 + n_json])
    assert tree["extensionsUsed"] == ["KHR_materials_unlit"] and tree["images"][0]["mimeType"] == "image/jpeg"
    assert tree["materials"][0]["doubleSided"] and "KHR_materials_unlit" in tree["materials"][0]["extensions"]
    # the mesh: each matched star's direction (camera frame) through its triangle, read back as a pixel
    vertices, faces, pix = sensor_mesh(cam)
    # what the page receives is that mesh: its points at the image's depth, each with its pixel's texture
    # coordinate as glTF reads them (0, 0 the image's top-left corner)
    binary = glb[20 + n_json + 8:]

    def accessor(i):
        a = tree["accessors"][i]
        view = tree["bufferViews"][a["bufferView"]]
        width = {"VEC2": 2, "VEC3": 3}[a["type"]]
        return np.frombuffer(binary, np.float32, a["count"] * width,
                             view.get("byteOffset", 0) + a.get("byteOffset", 0)).reshape(-1, width)

    attributes = tree["meshes"][0]["primitives"][0]["attributes"]
    np.testing.assert_allclose(accessor(attributes["POSITION"]), vertices * IMAGE_DEPTH, atol=1e-6)
    np.testing.assert_allclose(accessor(attributes["TEXCOORD_0"]), (pix + 0.5) / [cam.width, cam.height], atol=1e-6)
    obs = sorted(run.result.identification.matches)
    assert len(obs) >= 10
    errors = []
    for o in obs:
        d = run.catalog.xyz[run.result.identification.matches[o]] @ run.result.R.T
        a, b, c = (vertices[faces[:, k]] for k in range(3))
        # the ray t d through each triangle (Moller-Trumbore, all triangles at once)
        e1, e2 = b - a, c - a
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            w1 = np.einsum("ij,ij->i", -a, p) / det
            q = np.cross(-a, e1)
            w2 = (q @ d) / det
            t = np.einsum("ij,ij->i", e2, q) / det
        hit = np.flatnonzero((w1 >= -1e-9) & (w2 >= -1e-9) & (w1 + w2 <= 1 + 1e-9) & (t > 0))
        assert len(hit), o
        f = faces[hit[0]]
        at = (1 - w1[hit[0]] - w2[hit[0]]) * pix[f[0]] + w1[hit[0]] * pix[f[1]] + w2[hit[0]] * pix[f[2]]
        errors.append(float(np.hypot(*(at - run.result.centroids.uv[o]))))
    assert np.median(errors) < 1.0 and max(errors) < 3.0, errors  # pixels of the photograph
    # the rings: around each centroid's direction, on the sphere
    rings = np.asarray(s.sky.h["centroids"].points, dtype=np.float64).reshape(-1, 14, 2, 3)[:, :, 0]
    centre = rings.mean(axis=1)
    want = cam.unproject(run.result.centroids.uv[:len(rings)])
    cosang = np.einsum("ij,ij->i", centre / np.linalg.norm(centre, axis=1, keepdims=True), want)
    assert np.degrees(np.arccos(np.clip(cosang, -1, 1))).max() < 0.05


@pytest.mark.slow
@pytest.mark.parametrize("crop", [False, True], ids=["11.4deg", "5.7deg-crop"])
def test_what_the_page_receives_puts_the_identified_stars_on_the_photographs_stars(crop):
    """The check a browser's user makes by eye, from what the page itself receives over the websocket
    (tests/viser_protocol.py): the photograph uploaded through the panel, then the frustum's pose, field of
    view and texture (the JPEG the page draws) and the identified stars' points on the sphere; each identified
    star, projected through that frustum, falls on a bright blob of that texture within 1.5 texture pixels."""
    import asyncio

    from viser_protocol import Tab, solve_by_upload

    from skyview.viewer.app import ViewerApp

    image = load_image(REAL / PHOTO)
    if crop:
        image = _crop(image)
    app = ViewerApp(port=0)

    async def drive():
        tab = await Tab.open(app.port)
        answer = await solve_by_upload(tab, "mine.png", cv2.imencode(".png", image)[1].tobytes())
        await asyncio.sleep(1.0)  # the scene's last windows after the answer
        nodes = {k: tab.scene.get(NODES[k]) for k in ("camera", "frustum", "match_stars")}
        await tab.close()
        return answer, nodes

    try:
        answer, nodes = asyncio.run(drive())
    finally:
        app.stop()
    assert answer["solved"] and all(nodes.values())
    frame, frustum, stars = nodes["camera"], nodes["frustum"]["props"], nodes["match_stars"]["props"]
    w, x, y, z = frame["wxyz"]  # camera -> world (viser's T_world_camera), OpenCV axes: +z along the boresight
    R_wc = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    p = np.asarray(stars["points"], dtype=np.float64).reshape(-1, 3) @ R_wc  # world -> camera
    assert len(p) >= 10 and np.all(p[:, 2] > 0)
    tex = cv2.imdecode(np.frombuffer(frustum["_image_data"], np.uint8), cv2.IMREAD_GRAYSCALE).astype(np.float64)
    Ht, Wt = tex.shape
    tan_v = np.tan(frustum["fov"] / 2.0)
    assert frustum["aspect"] == pytest.approx(image.shape[1] / image.shape[0], rel=1e-6)
    u = (p[:, 0] / p[:, 2] / (frustum["aspect"] * tan_v) + 1.0) * Wt / 2.0 - 0.5
    v = (p[:, 1] / p[:, 2] / tan_v + 1.0) * Ht / 2.0 - 0.5
    _assert_on_blobs(tex, u, v)


def _assert_on_blobs(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> None:
    """The points (u, v) (texture pixels, OpenCV's convention) fall on bright blobs of the grey texture: over
    90 % of them on a pixel 5 sigma above the background within 3 px, the blob's centre of light within 1 px
    of the point (median), 1.5 px (90 %)."""
    Ht, Wt = tex.shape
    background = np.median(tex)
    noise = 1.4826 * np.median(np.abs(tex - background))
    off, lit = [], []
    for uu, vv in zip(u, v):
        i, j = int(round(vv)), int(round(uu))
        if not (4 <= i < Ht - 4 and 4 <= j < Wt - 4):
            continue
        win = tex[i - 3:i + 4, j - 3:j + 4] - background
        lit.append(win.max() > 5 * noise)
        wgt = np.clip(win - 3 * noise, 0, None)
        if wgt.sum() > 0:
            yy, xx = np.mgrid[-3:4, -3:4]
            off.append(np.hypot((wgt * xx).sum() / wgt.sum() + j - uu, (wgt * yy).sum() / wgt.sum() + i - vv))
    assert len(lit) >= 10 and np.mean(lit) > 0.9, lit
    assert np.median(off) < 1.0 and np.percentile(off, 90) < 1.5, off


# what the browser holds: the frustum's textured plane (its corners in world coordinates, their uv, the texture's
# pixels as a PNG), the camera's position and the identified stars' points in world coordinates
JS_DRAWN = """([camera, stars]) => { const m = window.__viserMutable?.nodeRefFromName ?? {};
  const cam = m[camera], pts = m[stars]; if (!cam || !pts || !pts.visible) return null;
  let mesh = null; cam.traverse(x => { if (!mesh && x.isMesh && x.material?.map?.image) mesh = x; });
  if (!mesh) return null;
  cam.updateWorldMatrix(true, true); pts.updateWorldMatrix(true, true);
  const world = (o, a, k) => { const v = new o.position.constructor(a.getX(k), a.getY(k), a.getZ(k));
    return v.applyMatrix4(o.matrixWorld).toArray(); };
  const pos = mesh.geometry.attributes.position, uv = mesh.geometry.attributes.uv;
  const corners = [], uvs = []; for (let k = 0; k < pos.count; k++) { corners.push(world(mesh, pos, k));
    uvs.push([uv.getX(k), uv.getY(k)]); }
  const points = []; pts.traverse(x => { const a = x.geometry?.attributes?.position; if (!a) return;
    for (let k = 0; k < a.count; k++) points.push(world(x, a, k)); });
  const img = mesh.material.map.image, c = document.createElement('canvas');
  c.width = img.width; c.height = img.height; c.getContext('2d').drawImage(img, 0, 0);
  const origin = new cam.position.constructor().setFromMatrixPosition(cam.matrixWorld).toArray();
  return {corners, uvs, flipY: mesh.material.map.flipY, points, origin, png: c.toDataURL('image/png')}; }"""


def _texture_pixels(drawn: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texture (grey) and where each identified star's ray from the camera crosses the textured plane, in
    the texture's pixels (OpenCV's convention: (0, 0) the centre of the top-left pixel)."""
    import base64

    tex = cv2.imdecode(np.frombuffer(base64.b64decode(drawn["png"].split(",", 1)[1]), np.uint8),
                       cv2.IMREAD_GRAYSCALE).astype(np.float64)
    corners, uvs = np.asarray(drawn["corners"], float), np.asarray(drawn["uvs"], float)
    origin, points = np.asarray(drawn["origin"], float), np.asarray(drawn["points"], float)
    # the plane's affine map from uv: corner = c0 + uv @ A (a rectangle: exact in the four corners)
    A = np.linalg.lstsq(np.c_[np.ones(len(uvs)), uvs], corners, rcond=None)[0]
    c0, eu, ev = A[0], A[1], A[2]
    n = np.cross(eu, ev)
    d = points - origin
    t = ((c0 - origin) @ n) / (d @ n)
    assert np.all(t > 0)  # in front of the camera
    hit = origin + t[:, None] * d - c0
    uv = np.linalg.lstsq(np.c_[eu, ev], hit.T, rcond=None)[0].T  # (N, 2) texture coordinates
    H, W = tex.shape
    row = (1.0 - uv[:, 1]) if drawn["flipY"] else uv[:, 1]  # flipY: v = 1 is the image's first row
    return tex, uv[:, 0] * W - 0.5, row * H - 0.5


@pytest.mark.browser
def test_in_the_browser_the_identified_stars_sit_on_the_photographs_stars(tmp_path):
    """What a user checks by eye, read from the three.js scene of headless Chromium after uploading a bundled
    photograph, a crop of it (11.4 and 5.7 deg) and its mirror image (a star diagonal's) through the page's
    upload control (the crop as a FITS file): every identified star's ray from the drawn camera crosses the drawn
    texture on a bright blob of it."""
    pytest.importorskip("playwright.sync_api")
    from test_viewer import CHROMIUM, viewer_page

    if not Path(CHROMIUM).exists():
        pytest.skip(f"no chromium at {CHROMIUM} (apt-get install chromium)")
    from astropy.io import fits

    full = load_image(REAL / PHOTO)
    files = {}
    # (the mirror image last: drawn turned over, its texture the width of the crop's predecessor; the crop as
    # a telescope's FITS, its rows stored bottom-first)
    for name, image in (("full.png", full), ("crop.fits", _crop(full)), ("mirror.png", full[:, ::-1])):
        files[name] = (tmp_path / name, image.shape)
        if name.endswith(".fits"):
            fits.PrimaryHDU(image[::-1]).writeto(files[name][0])
        else:
            cv2.imwrite(str(files[name][0]), image)
    with viewer_page(tmp_path) as pg:
        for name, (path, shape) in files.items():
            pg.locator("input[type=file]").first.set_input_files(str(path))
            pg.wait_for_function(
                "([c, s, w]) => { const o = window.__viserMutable?.nodeRefFromName?.[c]; let ok = false;"
                " o?.traverse(x => { if (x.isMesh && x.material?.map?.image?.width === w) ok = true; });"
                " return ok && !!window.__viserMutable.nodeRefFromName[s]?.visible; }",
                arg=[NODES["camera"], NODES["match_stars"], shape[1]], timeout=120000)
            pg.wait_for_timeout(1000)  # the texture's image decoded
            drawn = pg.evaluate(JS_DRAWN, [NODES["camera"], NODES["match_stars"]])
            assert drawn is not None, name
            tex, u, v = _texture_pixels(drawn)
            assert tex.shape == shape[:2], (name, tex.shape)
            _assert_on_blobs(tex, u, v)
