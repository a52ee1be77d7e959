"""Simulator: PSF integration, geometry against the catalog, noise model, files, slews."""

from __future__ import annotations

import json
import math
import os

import cv2
import numpy as np
import pytest

from skyview.core.attitude import east_north, radec_roll_from_R, random_attitudes
from skyview.core.camera import Camera
from skyview.core.catalog import load_guide_catalog
from skyview.core.errors import BadInput
from skyview.detect.centroids import detect_centroids
from skyview.simulate.render import (
    HIP_BETELGEUSE,
    R_pointing_at,
    SensorModel,
    betelgeuse_ra_sequence,
    jpeg_roundtrip,
    load_truth,
    render_stars,
    save_frame,
    save_sequence,
    simulate_image,
    simulate_sequence,
    to_uint8,
    turn_about_camera_axis,
    turn_along_ra,
)
from skyview.simulate.truth import wrong_matches

# noiseless, linear sensor: 1 e- = 1 ADU, no offset, no background, nothing saturates
CLEAN = SensorModel(gain_e_per_adu=1.0, bias_e=0.0, sky_background_e_per_px_s=0.0, dark_current_e_per_px_s=0.0,
                    read_noise_e=0.0, n_hot_pixels=0, full_well_e=1e9)


@pytest.fixture(scope="module")
def cat():
    return load_guide_catalog()


@pytest.fixture(scope="module")
def betel_frame(cat, cam):
    return simulate_image(cat, cam, R_pointing_at(cat, HIP_BETELGEUSE), seed=3)


def _near(uv, points, r):
    """For each point, whether some uv lies within r pixels."""
    if len(uv) == 0:
        return np.zeros(len(points), dtype=bool)
    d = np.linalg.norm(np.asarray(uv)[None, :, :] - np.asarray(points)[:, None, :], axis=2)
    return d.min(axis=1) <= r


# ------------------------------------------------------------------------------------ PSF

def test_psf_integrates_to_total_electrons_and_centre():
    rng = np.random.default_rng(0)
    for _ in range(5):
        u, v = rng.uniform(20, 40, size=2)
        for sigma in (0.6, 1.1, 2.0):
            img = render_stars((64, 64), [[u, v]], [12345.0], sigma)
            assert img.sum() == pytest.approx(12345.0, rel=1e-7)
            jj, ii = np.meshgrid(np.arange(64), np.arange(64))
            assert (img * jj).sum() / img.sum() == pytest.approx(u, abs=0.01)
            assert (img * ii).sum() / img.sum() == pytest.approx(v, abs=0.01)


def test_psf_pixel_convention_and_clipping_at_edge():
    # a star at an integer position is centred on that pixel: symmetric about it
    img = render_stars((32, 32), [[10.0, 20.0]], [1000.0], 1.0)
    assert np.unravel_index(np.argmax(img), img.shape) == (20, 10)
    assert img[20, 9] == pytest.approx(img[20, 11]) and img[19, 10] == pytest.approx(img[21, 10])
    # at u = 10.5 the light is shared equally between columns 10 and 11
    img = render_stars((32, 32), [[10.5, 20.0]], [1000.0], 1.0)
    assert img[20, 10] == pytest.approx(img[20, 11])
    # a star on the border loses the part of its light that falls off the sensor
    img = render_stars((32, 32), [[-0.5, 16.0]], [1000.0], 1.0)
    assert img.sum() == pytest.approx(500.0, rel=1e-6)


def test_isolated_star_electrons_noiseless_and_noisy(cat, cam):
    R = R_pointing_at(cat, HIP_BETELGEUSE)
    f = simulate_image(cat, cam, R, CLEAN, noise=False, mag_limit=6.0)
    uv = f.rendered_uv
    checked = 0
    for k, s in enumerate(f.truth["stars"]):
        others = np.delete(uv, k, axis=0)
        if (min(s["u"], s["v"]) < 12 or max(s["u"], s["v"]) > 1011
                or (len(others) and np.min(np.linalg.norm(others - uv[k], axis=1)) < 25)):
            continue
        j, i = int(round(s["u"])), int(round(s["v"]))
        total = f.image[i - 8:i + 9, j - 8:j + 9].astype(np.float64).sum()
        # only rounding to whole ADU (the far wings below 0.5 e- round to 0) separates the two
        assert abs(total - s["electrons"]) <= max(10.0, 4e-3 * s["electrons"])
        assert s["electrons"] == pytest.approx(CLEAN.electrons(s["mag"]))
        checked += 1
    assert checked >= 3
    # with shot + read noise, within 5 sigma of the expected count
    sensor = CLEAN.replace(read_noise_e=5.0, bias_e=100.0)
    g = simulate_image(cat, cam, R, sensor, seed=1)
    s = max((s for s in g.truth["stars"] if 12 < s["u"] < 1011 and 12 < s["v"] < 1011), key=lambda s: s["mag"])
    j, i = int(round(s["u"])), int(round(s["v"]))
    total = g.image[i - 8:i + 9, j - 8:j + 9].astype(np.float64).sum() - 100.0 * 17 * 17
    assert abs(total - s["electrons"]) < 5 * math.sqrt(s["electrons"] + 17 * 17 * 25.0)


# ------------------------------------------------------------------------------------ geometry

def test_betelgeuse_at_centre_east_left_north_up(cat, cam, betel_frame):
    f = betel_frame
    t = f.truth
    betel = [s for s in t["stars"] if s["hip"] == HIP_BETELGEUSE]
    assert len(betel) == 1
    assert betel[0]["u"] == pytest.approx(cam.cx, abs=1e-6)
    assert betel[0]["v"] == pytest.approx(cam.cy, abs=1e-6)
    assert abs(t["roll_deg"]) < 1e-9
    c = detect_centroids(f.image)
    assert np.linalg.norm(c.uv[0] - [cam.cx, cam.cy]) < 0.2  # the brightest thing in the image
    # every star: east of the boresight -> smaller u, north -> smaller v; and it is in the image
    b = cat.xyz[cat.index_of(HIP_BETELGEUSE)]
    east, north = east_north(b)
    n_checked = 0
    for s in t["stars"]:
        x = cat.xyz[cat.index_of(s["hip"])]
        de, dn = x @ east, x @ north
        if abs(de) > 1e-3:
            assert np.sign(s["u"] - cam.cx) == -np.sign(de)
        if abs(dn) > 1e-3:
            assert np.sign(s["v"] - cam.cy) == -np.sign(dn)
        n_checked += 1
    assert n_checked >= 5
    bright = [(s["u"], s["v"]) for s in t["stars"] if s["snr"] > 20]
    assert _near(c.uv, bright, 1.0).all()


def test_roll_rotates_the_image(cat, cam):
    # roll 90 deg: image up is east, so a star north of the boresight is on the right
    R90 = R_pointing_at(cat, HIP_BETELGEUSE, math.radians(90.0))
    f = simulate_image(cat, cam, R90, CLEAN, noise=False)
    b = cat.xyz[cat.index_of(HIP_BETELGEUSE)]
    east, north = east_north(b)
    for s in f.truth["stars"]:
        x = cat.xyz[cat.index_of(s["hip"])]
        if abs(x @ north) > 1e-3:
            assert np.sign(s["u"] - cam.cx) == np.sign(x @ north)
        if abs(x @ east) > 1e-3:
            assert np.sign(s["v"] - cam.cy) == -np.sign(x @ east)


def test_truth_contents(cat, cam, betel_frame):
    t = betel_frame.truth
    for key in ("camera", "R", "quaternion", "ra_deg", "dec_deg", "roll_deg", "epoch", "stars", "false_stars",
                "dropped", "sensor", "seed", "mag_limit", "position_noise_rad"):
        assert key in t
    json.dumps(t, allow_nan=False)
    assert t["epoch"] == cat.epoch
    assert Camera.from_dict(t["camera"]) == cam
    assert SensorModel.from_dict(t["sensor"]) == SensorModel()
    assert all(s["mag"] <= 6.0 for s in t["stars"])
    mags = [s["mag"] for s in t["stars"]]
    assert mags == sorted(mags)
    # every catalog star of the field is either rendered or listed as off the sensor
    R = np.asarray(t["R"])
    idx, _ = cam.visible(R, cat.xyz[cat.mag <= 6.0])
    assert {int(h) for h in cat.hip[cat.mag <= 6.0][idx]} == {s["hip"] for s in t["stars"]}


# ------------------------------------------------------------------------------------ noise model

def test_sensor_defaults_and_roundtrip():
    s = SensorModel()
    assert 30.0 <= s.snr_of_mag(6.0) <= 50.0
    assert 0.0 < s.saturation_mag() < 1.5  # Hp ~0 stars saturate a bit, Hp 2 stars do not
    assert 1.0 <= s.psf_sigma_px <= 1.2
    assert SensorModel.from_dict(json.loads(json.dumps(s.to_dict()))) == s
    with pytest.raises(BadInput):
        SensorModel(bit_depth=12)
    with pytest.raises(BadInput):
        SensorModel.from_dict({"exposure_s": 0.1, "gian": 2.0})
    with pytest.raises(BadInput):
        SensorModel(exposure_s=-1.0)


def test_seeded_reproducibility(cat, cam):
    R = random_attitudes(1, np.random.default_rng(42))[0]
    kw = dict(n_false_stars=2, n_dropped=1, position_noise_rad=87e-6)
    a = simulate_image(cat, cam, R, seed=7, **kw)
    b = simulate_image(cat, cam, R, seed=7, **kw)
    c = simulate_image(cat, cam, R, seed=8, **kw)
    assert np.array_equal(a.image, b.image)
    assert a.truth == b.truth
    assert not np.array_equal(a.image, c.image)


@pytest.mark.parametrize("bits,dtype", [(8, np.uint8), (16, np.uint16)])
def test_bit_depths_and_saturation(cat, bits, dtype):
    # odd width: the boresight falls on a pixel centre, where a Hp 0.5 star saturates the default sensor
    # (on a pixel corner its light is shared by four pixels and it stays just below the full well)
    cam = Camera.from_fov(8.0, 1025)
    sensor = SensorModel(bit_depth=bits)
    f = simulate_image(cat, cam, R_pointing_at(cat, HIP_BETELGEUSE), sensor, seed=0)
    assert f.image.dtype == dtype and f.image.shape == (1025, 1025)
    top = (1 << bits) - 1
    j, i = int(round(cam.cx)), int(round(cam.cy))
    assert f.image[i - 1:i + 2, j - 1:j + 2].max() == top  # Betelgeuse (Hp 0.5) saturates
    # background sits on the bias, not clipped at zero
    assert np.median(f.image) == pytest.approx((sensor.bias_e + sensor.background_e_per_px) / sensor.gain, abs=1.5)
    assert np.mean(f.image == 0) < 1e-4
    c = detect_centroids(f.image)
    assert c.saturated[np.argmin(np.linalg.norm(c.uv - [cam.cx, cam.cy], axis=1))]


def test_full_well_clips_charge(cat, cam):
    sensor = CLEAN.replace(full_well_e=1000.0)
    f = simulate_image(cat, cam, R_pointing_at(cat, HIP_BETELGEUSE), sensor, noise=False)
    assert f.image.max() == 1000


def test_hot_pixels_in_image_and_rejected(cat, cam):
    sensor = SensorModel(n_hot_pixels=25, hot_pixel_e=5000.0)
    R = random_attitudes(1, np.random.default_rng(3))[0]
    f = simulate_image(cat, cam, R, sensor, seed=2)
    hot = np.array(f.truth["hot_pixels"])
    assert hot.shape == (25, 2)
    bg = np.median(f.image)
    assert (f.image[hot[:, 1], hot[:, 0]] > bg + 5000.0 / sensor.gain * 0.8).all()
    c = detect_centroids(f.image)
    away = ~_near(f.rendered_uv, hot, 8.0)  # hot pixels that do not sit on a star
    assert c.n_hot_pixels_rejected >= away.sum()
    assert not _near(c.uv, hot[away], 1.5).any()


@pytest.mark.parametrize("placement", ["sensor", "disk"])
def test_false_stars(cat, cam, placement):
    R = random_attitudes(1, np.random.default_rng(5))[0]
    f = simulate_image(cat, cam, R, seed=4, n_false_stars=4, false_star_placement=placement,
                       false_star_mag_range=(3.0, 4.0))
    fs = f.truth["false_stars"]
    assert len(fs) == 4
    assert all(3.0 <= s["mag"] <= 4.0 for s in fs)
    uv = np.array([[s["u"], s["v"]] for s in fs])
    assert cam.in_image(uv).all()
    c = detect_centroids(f.image)
    assert _near(c.uv, uv, 0.5).all()
    if placement == "disk":
        ang = np.degrees(np.arccos(cam.unproject(uv)[:, 2]))
        assert (ang <= cam.fov_deg / 2 + 1e-6).all()


def test_dropped_stars_are_absent(cat, cam):
    R = R_pointing_at(cat, HIP_BETELGEUSE)
    full = simulate_image(cat, cam, R, seed=1)
    f = simulate_image(cat, cam, R, seed=1, n_dropped=3)
    dropped = f.truth["dropped"]
    assert len(dropped) == 3
    hips = {s["hip"] for s in f.truth["stars"]}
    assert not hips & set(dropped)
    assert hips | set(dropped) == {s["hip"] for s in full.truth["stars"]}
    where = np.array([[s["u"], s["v"]] for s in full.truth["stars"] if s["hip"] in dropped])
    c = detect_centroids(f.image)
    assert not _near(c.uv, where, 2.0).any()
    half = simulate_image(cat, cam, R, seed=1, n_dropped=0.5)
    assert len(half.truth["dropped"]) == round(0.5 * len(full.truth["stars"]))
    with pytest.raises(BadInput):
        simulate_image(cat, cam, R, n_dropped=-1)


def test_position_noise_moves_rendered_stars(cat, cam):
    R = R_pointing_at(cat, HIP_BETELGEUSE)
    sigma = 87e-6
    f = simulate_image(cat, cam, R, seed=9, position_noise_rad=sigma, mag_limit=7.5)
    d = f.rendered_uv - f.star_uv
    assert len(d) > 30
    expected_px = sigma * cam.fx
    assert np.sqrt(np.mean(d * d)) == pytest.approx(expected_px, rel=0.3)
    assert f.truth["position_noise_rad"] == sigma
    # the true position is the one without jitter
    g = simulate_image(cat, cam, R, seed=9, mag_limit=7.5)
    true_g = {s["hip"]: (s["u"], s["v"]) for s in g.truth["stars"]}
    for s in f.truth["stars"]:
        if s["hip"] in true_g:
            assert np.allclose((s["u"], s["v"]), true_g[s["hip"]])


def test_distortion_uses_camera_projection(cat):
    cam = Camera.from_fov(8.0, 1024, k1=-0.3)
    R = R_pointing_at(cat, HIP_BETELGEUSE)
    f = simulate_image(cat, cam, R, CLEAN, noise=False)
    for s in f.truth["stars"]:
        uv, _ = cam.project((cat.xyz[cat.index_of(s["hip"])] @ R.T)[None])
        assert np.allclose(uv[0], [s["u"], s["v"]])


# ------------------------------------------------------------------------------------ files

def test_save_frame_roundtrip_and_no_overwrite(tmp_path, betel_frame):
    png = tmp_path / "field.png"
    p, j = save_frame(betel_frame, png)
    assert p == png and j == tmp_path / "field.json"
    back = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint16 and np.array_equal(back, betel_frame.image)
    assert load_truth(png) == json.loads(json.dumps(betel_frame.truth))
    assert load_truth(j)["stars"] == load_truth(png)["stars"]
    before = (png.read_bytes(), j.read_bytes())
    with pytest.raises(BadInput, match="already exists"):
        save_frame(betel_frame, png)
    assert (png.read_bytes(), j.read_bytes()) == before
    # the sidecar alone existing also blocks the write
    png.unlink()
    with pytest.raises(BadInput, match="field.json"):
        save_frame(betel_frame, png)
    assert not png.exists()
    save_frame(betel_frame, png, force=True)
    assert png.exists()
    assert sorted(x.name for x in tmp_path.iterdir()) == ["field.json", "field.png"]  # no temp files left


def test_save_frame_bad_paths(tmp_path, betel_frame):
    with pytest.raises(BadInput, match="does not exist"):
        save_frame(betel_frame, tmp_path / "missing" / "x.png")
    with pytest.raises(BadInput, match=r"\.png"):
        save_frame(betel_frame, tmp_path / "x.tif")
    with pytest.raises(BadInput):
        load_truth(tmp_path / "nothing.png")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(BadInput):
        load_truth(tmp_path / "bad.json")
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            with pytest.raises(BadInput, match="not writable"):
                save_frame(betel_frame, ro / "x.png")
        finally:
            ro.chmod(0o700)


def test_eight_bit_png(tmp_path, cat, cam):
    f = simulate_image(cat, cam, R_pointing_at(cat, HIP_BETELGEUSE), SensorModel(bit_depth=8), seed=0)
    save_frame(f, tmp_path / "a.png")
    back = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint8 and np.array_equal(back, f.image)


# ------------------------------------------------------------------------------------ slews

def test_sequence_relative_rotations(cat, cam):
    R0 = random_attitudes(1, np.random.default_rng(11))[0]
    turn = turn_about_camera_axis([0.3, -0.5, 0.8], math.radians(2.0))
    seq = simulate_sequence(cat, cam, R0, 4, turn, CLEAN, noise=False)
    assert len(seq) == 4 and len(seq.relative) == 3
    for k in range(3):
        Rk, Rk1 = seq.frames[k].R, seq.frames[k + 1].R
        rel = seq.relative[k]
        dR = np.asarray(rel["dR_cam"])
        assert np.allclose(Rk1, dR @ Rk, atol=1e-12)
        assert np.allclose(Rk1, Rk @ np.asarray(rel["rot_icrs"]).T, atol=1e-12)
        assert np.allclose(np.asarray(rel["turn_cam"]), dR.T)
        rv = np.asarray(rel["turn_rotvec_cam_rad"])
        assert np.allclose(rv, math.radians(2.0) * np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))
        assert rel["turn_angle_deg"] == pytest.approx(2.0)
        # a star seen in both frames moves as dR_cam says
        common = {s["hip"] for s in seq.frames[k].truth["stars"]} & {s["hip"] for s in seq.frames[k + 1].truth["stars"]}
        for hip in list(common)[:5]:
            v_k = cat.xyz[cat.index_of(hip)] @ Rk.T
            assert np.allclose(dR @ v_k, cat.xyz[cat.index_of(hip)] @ Rk1.T)
    assert seq.frames[1].truth["seed"] != seq.frames[0].truth["seed"]


def test_pan_right_moves_stars_left(cat, cam):
    R0 = R_pointing_at(cat, HIP_BETELGEUSE)
    seq = simulate_sequence(cat, cam, R0, 2, turn_about_camera_axis("y", math.radians(1.0)), CLEAN, noise=False)
    a = {s["hip"]: s for s in seq.frames[0].truth["stars"]}
    b = {s["hip"]: s for s in seq.frames[1].truth["stars"]}
    assert HIP_BETELGEUSE in b
    for hip in set(a) & set(b):
        assert b[hip]["u"] < a[hip]["u"] - 100  # ~128 px per degree at 8 deg / 1024 px
        assert abs(b[hip]["v"] - a[hip]["v"]) < 5


def test_betelgeuse_ra_sequence(cat, cam, tmp_path):
    seq = betelgeuse_ra_sequence(cat, cam, n_frames=3, step_deg=10.0, sensor=SensorModel(bit_depth=8), seed=5)
    ra0, dec0, roll0 = radec_roll_from_R(seq.frames[0].R)
    b = cat.xyz[cat.index_of(HIP_BETELGEUSE)]
    assert np.allclose(seq.frames[0].R[2], b)
    for k, fr in enumerate(seq.frames):
        ra, dec, roll = radec_roll_from_R(fr.R)
        assert math.degrees((ra - ra0) % (2 * math.pi)) == pytest.approx(10.0 * k)
        assert dec == pytest.approx(dec0) and roll == pytest.approx(roll0, abs=1e-9)
    for k in range(2):
        assert np.allclose(seq.frames[k + 1].R, seq.dR_cam(k) @ seq.frames[k].R, atol=1e-12)
    # files: a folder gets frame_000.png ... + sequence.json; nothing is overwritten
    written = save_sequence(seq, tmp_path)
    names = sorted(p.name for p in written)
    assert names == ["frame_000.json", "frame_000.png", "frame_001.json", "frame_001.png", "frame_002.json",
                     "frame_002.png", "sequence.json"]
    st = load_truth(tmp_path / "sequence.json")
    assert st["n_frames"] == 3 and len(st["relative"]) == 2 and "dR_cam" in st["conventions"]
    assert np.allclose(st["relative"][0]["dR_cam"], seq.dR_cam(0))
    with pytest.raises(BadInput, match="already exists"):
        save_sequence(seq, tmp_path)
    save_sequence(seq, tmp_path, force=True)
    # a stem: slew_000.png ... + slew.json
    out = tmp_path / "sub"
    out.mkdir()
    save_sequence(seq, out / "slew")
    assert (out / "slew.json").exists() and (out / "slew_002.png").exists()
    with pytest.raises(BadInput, match="does not exist"):
        save_sequence(seq, tmp_path / "nope" / "slew")


def test_turn_axis_spellings():
    a = turn_about_camera_axis("y", 0.1).matrix
    assert np.allclose(turn_about_camera_axis(1, 0.1).matrix, a)
    assert np.allclose(turn_about_camera_axis([0, 2.0, 0], 0.1).matrix, a)
    with pytest.raises(BadInput):
        turn_about_camera_axis("w", 0.1)
    with pytest.raises(BadInput):
        turn_about_camera_axis([0, 0, 0], 0.1)


def test_turn_along_ra_is_icrs_turn():
    t = turn_along_ra(math.radians(10.0))
    assert t.frame == "icrs"
    R0 = random_attitudes(1, np.random.default_rng(2))[0]
    R1 = t.apply(R0)
    assert np.allclose(R1, t.dR_cam(R0) @ R0)
    ra0, dec0, _ = radec_roll_from_R(R0)
    ra1, dec1, _ = radec_roll_from_R(R1)
    assert math.degrees((ra1 - ra0) % (2 * math.pi)) == pytest.approx(10.0)
    assert dec1 == pytest.approx(dec0)


# ------------------------------------------------------------------------------------ real-world effects

# a flat, noiseless sky of 1000 e- per pixel, 1 e- = 1 ADU: the image is the illumination map
FLAT = CLEAN.replace(sky_background_e_per_px_s=10000.0)  # x 0.1 s exposure


@pytest.fixture(scope="module")
def odd_cam():
    return Camera.from_fov(8.0, 201, 151)  # odd sizes: the principal point is a pixel centre


def _flat(cat, cam, **kw):
    return simulate_image(cat, cam, np.eye(3), FLAT, noise=False, mag_limit=-5.0, **kw).image.astype(float)


def test_effects_off_change_nothing(cat, cam):
    R = R_pointing_at(cat, HIP_BETELGEUSE)
    a = simulate_image(cat, cam, R, seed=4, n_false_stars=1, position_noise_rad=2e-5)
    b = simulate_image(cat, cam, R, seed=4, n_false_stars=1, position_noise_rad=2e-5, faint_extra_mag=0.0,
                       vignetting=0.0, sky_gradient=0.0, jpeg_quality=None)
    assert np.array_equal(a.image, b.image) and a.image.dtype == b.image.dtype == np.uint16
    assert a.truth == b.truth and "effects" not in a.truth and a.jpeg is None
    assert all("faint" not in st and "vignetting" not in st for st in a.truth["stars"])


def test_vignetting_darkens_the_corners_by_the_stated_fraction(cat, odd_cam):
    flat = _flat(cat, odd_cam)
    assert np.all(flat == 1000.0)
    img = _flat(cat, odd_cam, vignetting=0.3)
    centre = img[75, 100]
    assert centre == 1000.0
    for corner in (img[0, 0], img[0, -1], img[-1, 0], img[-1, -1]):
        assert corner / centre == pytest.approx(0.7, abs=1e-3)
    assert img[75, 0] > img[0, 0] and img[75, 50] > img[75, 0]  # falls off monotonically outwards
    # natural vignetting: cos^4 of the corner's off-axis angle
    cos4 = _flat(cat, odd_cam, vignetting="cos4")
    theta = np.arccos(odd_cam.unproject([[0.0, 0.0]])[0, 2])
    assert cos4[0, 0] / 1000.0 == pytest.approx(np.cos(theta) ** 4, abs=1e-3)
    with pytest.raises(BadInput, match="vignetting"):
        _flat(cat, odd_cam, vignetting=1.0)
    with pytest.raises(BadInput, match="vignetting"):
        _flat(cat, odd_cam, vignetting="cos3")


def test_vignetting_dims_stars_and_truth_records_it(cat, cam):
    R = R_pointing_at(cat, HIP_BETELGEUSE)
    plain = simulate_image(cat, cam, R, CLEAN, noise=False)
    vig = simulate_image(cat, cam, R, CLEAN, noise=False, vignetting=0.5)
    assert [st["hip"] for st in plain.truth["stars"]] == [st["hip"] for st in vig.truth["stars"]]
    for a, b in zip(plain.truth["stars"], vig.truth["stars"]):
        assert 0.5 <= b["vignetting"] <= 1.0
        assert b["electrons"] == pytest.approx(a["electrons"] * b["vignetting"])
    assert vig.image.sum() < plain.image.sum()
    assert vig.truth["effects"]["vignetting_corner_falloff"] == 0.5


def test_sky_gradient_is_linear_across_the_frame(cat, odd_cam):
    img = _flat(cat, odd_cam, sky_gradient=0.2)
    assert img[:, 0].mean() == pytest.approx(900.0, abs=0.6) and img[:, -1].mean() == pytest.approx(1100.0, abs=0.6)
    assert img[:, 100].mean() == pytest.approx(1000.0, abs=0.6) and np.all(np.diff(img[75]) >= 0)
    down = _flat(cat, odd_cam, sky_gradient=0.2, sky_gradient_deg=90.0)
    assert down[0].mean() == pytest.approx(900.0, abs=0.6) and down[-1].mean() == pytest.approx(1100.0, abs=0.6)
    with pytest.raises(BadInput, match="gradient"):
        _flat(cat, odd_cam, sky_gradient=1.5)


def test_faint_field_stars_only_when_asked_and_scored_as_stars(cat, cam):
    R = R_pointing_at(cat, HIP_BETELGEUSE)
    off = simulate_image(cat, cam, R, CLEAN, noise=False, mag_limit=6.0)
    on = simulate_image(cat, cam, R, CLEAN, noise=False, mag_limit=6.0, faint_extra_mag=1.5)
    assert max(st["mag"] for st in off.truth["stars"]) <= 6.0
    faint = [st for st in on.truth["stars"] if st["faint"]]
    bright = [st for st in on.truth["stars"] if not st["faint"]]
    assert len(faint) > 10 and all(6.0 < st["mag"] <= 7.5 for st in faint)
    assert [(st["hip"], st["u"], st["v"]) for st in bright] == [(st["hip"], st["u"], st["v"]) for st in off.truth["stars"]]
    assert on.truth["effects"]["n_faint"] == len(faint) and on.truth["effects"]["render_mag_limit"] == 7.5
    # they are in the image ...
    for st in faint[:5]:
        assert on.image[int(round(st["v"])), int(round(st["u"]))] > 0
        assert off.image[int(round(st["v"])), int(round(st["u"]))] == 0 or st["hip"] in off.hips
    # ... and naming one correctly is not a wrong match, naming it as another star is
    st = faint[0]
    assert wrong_matches([(0, st["u"], st["v"], st["hip"])], on.truth) == []
    assert wrong_matches([(0, st["u"], st["v"], bright[0]["hip"])], on.truth) == [0]
    # capped at the guide catalog's depth
    deep = simulate_image(cat, cam, R, CLEAN, noise=False, mag_limit=6.0, faint_extra_mag=5.0)
    assert deep.truth["effects"]["render_mag_limit"] == 9.0 and max(st["mag"] for st in deep.truth["stars"]) <= 9.0
    with pytest.raises(BadInput, match="faint_extra_mag"):
        simulate_image(cat, cam, R, faint_extra_mag=-1.0)


def test_jpeg_roundtrip_8_and_16_bit():
    rng = np.random.default_rng(0)
    img8 = rng.integers(0, 60, (120, 160)).astype(np.uint8)
    back = jpeg_roundtrip(img8, 80)
    assert back.dtype == np.uint8 and back.shape == img8.shape and not np.array_equal(back, img8)
    assert np.abs(back.astype(int) - img8).mean() < 20
    img16 = (rng.normal(130, 13, (120, 160))).astype(np.uint16)
    as8, scale = to_uint8(img16)
    assert as8.dtype == np.uint8 and scale == pytest.approx(13, rel=0.1)  # one step per noise sigma
    assert jpeg_roundtrip(img16, 90).shape == img16.shape
    for bad in (0, 101, 50.0, True, None):
        with pytest.raises(BadInput, match="quality"):
            jpeg_roundtrip(img8, bad)


def test_jpeg_frame_keeps_its_bytes_and_saves_as_jpg(tmp_path, cat, cam):
    R = R_pointing_at(cat, HIP_BETELGEUSE)
    raw = simulate_image(cat, cam, R, SensorModel(bit_depth=8), seed=1)
    f = simulate_image(cat, cam, R, SensorModel(bit_depth=8), seed=1, jpeg_quality=70)
    assert f.image.dtype == np.uint8 and f.image.shape == raw.image.shape and not np.array_equal(f.image, raw.image)
    assert f.truth["effects"]["jpeg_quality"] == 70 and f.truth["stars"] == raw.truth["stars"]
    p, j = save_frame(f, tmp_path / "f.jpg")
    assert p.read_bytes() == f.jpeg and j == tmp_path / "f.json"
    assert np.array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), f.image)
    assert load_truth(p)["effects"]["jpeg_quality"] == 70
    # a frame simulated without JPEG can still be saved as one (quality 95, said in its truth)
    save_frame(raw, tmp_path / "raw.jpg")
    assert load_truth(tmp_path / "raw.jpg")["saved_as_jpeg"]["quality"] == 95
    f16 = simulate_image(cat, cam, R, seed=1, jpeg_quality=90)
    assert f16.image.dtype == np.uint8 and f16.truth["effects"]["jpeg_scale_adu_per_step"] > 1


def test_cli_simulate_effects_and_jpeg(tmp_path, capsys):
    from skyview.cli import main

    code = main(["simulate", "--ra", "83.8", "--dec", "-5.4", "--faint-extra-mag", "1.5", "--vignetting", "0.3",
                 "--sky-gradient", "0.2", "--jpeg-quality", "80", "--out", str(tmp_path / "x.png")])
    assert code == 0 and "JPEG quality 80" in capsys.readouterr().out
    assert sorted(q.name for q in tmp_path.iterdir()) == ["x.jpg", "x.json"]
    t = load_truth(tmp_path / "x.jpg")
    assert t["effects"]["vignetting"] == 0.3 and any(st.get("faint") for st in t["stars"])
    assert main(["simulate", "--ra", "83.8", "--dec", "-5.4", "--out", str(tmp_path / "y.jpg")]) == 0
    assert load_truth(tmp_path / "y.json")["effects"]["jpeg_quality"] == 95
    for flags in (["--jpeg-quality", "0"], ["--jpeg-quality", "101"], ["--vignetting", "1"],
                  ["--sky-gradient", "-0.1"], ["--faint-extra-mag", "-1"]):
        assert main(["simulate", "--ra", "1", "--dec", "1", "--out", str(tmp_path / "z.png"), *flags]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "error" in err
