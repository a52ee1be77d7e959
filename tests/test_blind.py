"""Blind solving: scale-free patterns, the camera fitted, real photographs against a reference."""

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from skyview.core.attitude import R_from_radec_roll, attitude_error_arcsec, radec_roll_from_R
from skyview.core.camera import Camera
from skyview.core.camera_fit import fit_camera
from skyview.core.errors import BadInput
from skyview.detect.centroids import load_image
from skyview.identify import database
from skyview.identify import patterns as pdb
from skyview.identify.blind import fov_ladder
from skyview.simulate.render import SensorModel, simulate_image
from skyview.simulate.truth import wrong_matches
from skyview.solver.pipeline import BlindSolver, as_image, solve_image

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())


@pytest.fixture(scope="module")
def blind(catalog):
    return BlindSolver(catalog=catalog)


# ---------------------------------------------------------------------------------- invariants

def test_edge_ratios_do_not_change_with_rotation_or_scale():
    rng = np.random.default_rng(1)
    cam = Camera.from_fov(10.0, 1024, 768)
    uv = rng.uniform([0, 0], [1024, 768], (4, 2))
    v = cam.unproject(uv)
    r0, big0 = pdb.edge_ratios(pdb.separations(v))
    for _ in range(5):
        R = Rotation.random(random_state=rng).as_matrix()
        r1, big1 = pdb.edge_ratios(pdb.separations(v @ R.T))
        assert np.allclose(r0, r1, atol=1e-12) and big1 == pytest.approx(big0, rel=1e-12)
    # a field 10 % wider: the ratios barely move (the pinhole is nearly scale-free), the size does
    r2, big2 = pdb.edge_ratios(pdb.separations(Camera.from_fov(11.0, 1024, 768).unproject(uv)))
    assert np.abs(r2 - r0).max() < 1e-3 and big2 / big0 == pytest.approx(1.1, rel=0.01)


def test_keys_pack_and_look_up():
    rng = np.random.default_rng(2)
    q = rng.integers(0, 100, (500, pdb.N_RATIOS))
    keys = pdb.pack_key(q)
    assert len(np.unique(keys)) == len(np.unique(q, axis=0))
    bits = pdb.table_bits(len(keys))
    bucket = pdb.bucket_of(keys, bits)
    order = np.lexsort((keys, bucket))
    start = np.searchsorted(bucket[order], np.arange((1 << bits) + 1))
    needles = np.r_[keys[:50], pdb.pack_key(np.full((1, 5), 200))]
    ni, ti = pdb.lookup(keys[order], start, needles)
    for n in range(50):
        assert set(order[ti[ni == n]]) == set(np.flatnonzero(keys == needles[n]))
    assert not np.any(ni == 50)  # a key that is not stored finds nothing


@pytest.mark.slow
def test_level_patterns_enumerates_each_four_once_by_its_largest_edge():
    rng = np.random.default_rng(3)
    v = rng.normal(size=(40, 3)) * [0.05, 0.05, 1.0]
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    lo, hi = 0.03, 0.06
    got = pdb.level_patterns(v, lo, hi)
    got_sets = {tuple(sorted(p)) for p in got.tolist()}
    assert len(got_sets) == len(got)  # no four twice
    want = set()
    for quad in itertools.combinations(range(len(v)), 4):
        big = pdb.separations(v[list(quad)]).max()
        if lo <= big < hi:
            want.add(quad)
    assert got_sets == want


def test_fov_ladder_covers_the_range_with_few_steps():
    ladder = fov_ladder(5.0, 40.0, 60.0)
    lo_edges = [c / s for c, s in ladder]
    hi_edges = [c * s for c, s in ladder]
    assert lo_edges[0] <= 5.0 and hi_edges[-1] >= 40.0 * 0.999
    assert all(h >= l2 * 0.999 for h, l2 in zip(hi_edges[:-1], lo_edges[1:]))  # no gap
    assert len(ladder) <= 8 and len(fov_ladder(10.3, 12.6, 60.0)) == 1


def test_pattern_database_refuses_a_size_over_its_budget(catalog):
    with pytest.raises(BadInput, match="memory budget"):
        pdb.build(catalog, pdb.PatternParams(), budget_mb=10)


# ---------------------------------------------------------------------------------- camera fit

def test_fit_camera_recovers_fov_and_distortion(catalog):
    true = Camera.from_fov(20.0, 1024, 768, k1=0.08)
    R = R_from_radec_roll(math.radians(120.0), math.radians(-30.0), math.radians(40.0))
    idx, uv = true.visible(R, catalog.brighter_than(6.5).xyz)
    xyz = catalog.brighter_than(6.5).xyz[idx]
    uv = uv + np.random.default_rng(4).normal(0.0, 0.1, uv.shape)
    start = Camera.from_fov(21.0, 1024, 768)
    R0 = Rotation.from_rotvec([2e-3, -1e-3, 3e-3]).as_matrix() @ R
    fit = fit_camera(uv, xyz, start, R0)
    assert "k1" in fit.fitted
    assert fit.camera.fov_deg == pytest.approx(20.0, rel=2e-4)
    assert fit.camera.k1 == pytest.approx(0.08, abs=0.005)
    assert attitude_error_arcsec(fit.R, R)["boresight"] < 2.0
    assert fit.rms_px == pytest.approx(0.1, rel=0.3)
    # with no distortion in the stars, the chi-square test leaves k1 out
    idx, uv = Camera.from_fov(20.0, 1024, 768).visible(R, catalog.brighter_than(6.5).xyz)
    uv = uv + np.random.default_rng(5).normal(0.0, 0.1, uv.shape)
    assert "k1" not in fit_camera(uv, xyz if len(xyz) == len(uv) else catalog.brighter_than(6.5).xyz[idx],
                                  start, R0).fitted


@pytest.mark.parametrize("terms", [(True, True, True), (True, False, False), (False, True, False), (True, True, False),
                                   (False, False, True)])
def test_the_fits_closed_form_jacobian_is_the_models_derivative(catalog, monkeypatch, terms):
    """The pinhole fit's Jacobian (closed form) against central differences of the same model, at a point
    away from the start (a rotation, a scale and distortion all off), with each set of free terms (the focal
    length, k1, k2: each column in its place)."""
    import skyview.core.camera_fit as cf

    true = Camera.from_fov(20.0, 1024, 768, k1=0.08, k2=-0.02)
    R = R_from_radec_roll(math.radians(120.0), math.radians(-30.0), math.radians(40.0))
    idx, uv = true.visible(R, catalog.brighter_than(6.5).xyz)
    xyz = catalog.brighter_than(6.5).xyz[idx]
    checked = []

    def spy(fun, p0, lo, hi, *, fun_jac=None, **kw):
        p = p0 + np.array([3e-3, -2e-3, 4e-3, 0.02, 0.01, -0.005][:len(p0)])
        h = 1e-6
        numeric = np.stack([(fun(p + h * e) - fun(p - h * e)) / (2 * h) for e in np.eye(len(p))], axis=1)
        res, jac = fun_jac(p)
        checked.append((float(np.abs(jac - numeric).max() / np.abs(numeric).max()), float(np.abs(res - fun(p)).max())))
        return original(fun, p0, lo, hi, fun_jac=fun_jac, **kw)

    original = cf.robust_gauss_newton
    monkeypatch.setattr(cf, "robust_gauss_newton", spy)
    fit = cf._fit(uv, xyz, Camera.from_fov(21.0, 1024, 768), R, *terms)
    assert len(checked) == 1 and checked[0][0] < 1e-7 and checked[0][1] < 1e-6  # the same residuals (px)
    if terms == (True, True, True):
        assert fit.camera.fov_deg == pytest.approx(20.0, rel=1e-6) and fit.rms_px < 1e-3


# ---------------------------------------------------------------------------------- real photographs

@pytest.mark.parametrize("name", sorted(REFERENCE))
def test_real_photograph_solves_blind(blind, name):
    ref = REFERENCE[name]
    image = load_image(REAL / name)
    assert image.dtype == np.uint16 and image.shape == (768, 1024)
    res = blind.solve_array(image)
    assert res.solved, res.reason
    err = attitude_error_arcsec(res.R, np.array(ref["R"]))
    assert err["boresight"] < 0.1 * 3600.0
    _, _, roll = radec_roll_from_R(res.R)
    assert abs((math.degrees(roll) - ref["roll_deg"] + 180.0) % 360.0 - 180.0) < 0.5
    assert res.camera.fov_deg == pytest.approx(ref["fov_deg"], rel=0.005)
    assert res.camera_fitted and len(res.matches) >= 15
    d = res.to_dict()
    assert d["fov_deg"] == pytest.approx(res.camera.fov_deg)
    assert d["plate_scale_arcsec_per_px"] == pytest.approx(3600 * ref["fov_deg"] / 1024, rel=0.01)
    json.dumps(d, allow_nan=False)


@pytest.mark.slow
def test_real_photograph_with_a_wrong_fov_estimate_and_a_method(blind):
    name = sorted(REFERENCE)[0]
    ref = REFERENCE[name]
    res = solve_image(REAL / name, fov_deg=ref["fov_deg"] * 1.07, method="angle", variant="improved")
    assert res.solved, res.reason
    assert res.method == "angle" and res.camera_fitted
    assert attitude_error_arcsec(res.R, np.array(ref["R"]))["boresight"] < 60.0
    # an exact but wrong FOV (the calibrated mode) is not solved, and never wrongly
    bad = solve_image(REAL / name, fov_deg=ref["fov_deg"] * 1.07, method="angle", fov_error=0.0)
    assert not bad.solved


def test_wcs_round_trip_lands_on_the_centroids(blind, catalog):
    pytest.importorskip("astropy")
    from skyview.io.wcs import solution_wcs

    name = "2019-07-29T204726_Alt40_Azi45_Try1.png"
    res = blind.solve_array(load_image(REAL / name))
    assert res.solved and res.camera.k1 != 0.0
    w = solution_wcs(res.R, res.camera)
    assert w.wcs.ctype[0] == "RA---TAN-SIP"
    rows = [catalog.index_of(m["hip"]) for m in res.matches]
    ra, dec = np.degrees(np.array([catalog.ra_dec[0][rows], catalog.ra_dec[1][rows]]))
    px = w.all_world2pix(np.stack([ra, dec], axis=1), 0)
    uv = np.array([[m["u"], m["v"]] for m in res.matches])
    assert np.abs(px - uv).max() < 2.0 and np.median(np.hypot(*(px - uv).T)) < 0.5
    # the boresight is CRVAL and lands on the principal point
    assert w.wcs_world2pix([[w.wcs.crval[0], w.wcs.crval[1]]], 0) == pytest.approx(
        np.array([[res.camera.cx, res.camera.cy]]), abs=1e-6)


# ---------------------------------------------------------------------------------- simulated

@pytest.mark.parametrize("fov,mag,k1", [(20.0, 6.5, 0.05), (10.0, 7.0, -0.05), (30.0, 6.0, 0.0),
                                        (70.0, 5.5, -0.08)])  # a wide-angle lens: the database's widest level
def test_simulated_field_solves_blind_with_distortion(blind, catalog, fov, mag, k1):
    cam = Camera.from_fov(fov, 1024, 768, k1=k1)
    R = R_from_radec_roll(math.radians(250.0), math.radians(35.0), math.radians(-70.0))
    frame = simulate_image(catalog, cam, R, SensorModel(), seed=7, mag_limit=mag)
    res = blind.solve_array(frame.image)
    assert res.solved, res.reason
    assert attitude_error_arcsec(res.R, R)["boresight"] < 30.0
    assert res.camera.fov_deg == pytest.approx(fov, rel=0.005)
    wrong = wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in res.matches], frame.truth)
    assert len(wrong) == 0


def test_blank_and_random_images_are_not_solved(blind):
    rng = np.random.default_rng(8)
    noise = rng.normal(100, 5, (768, 1024)).astype(np.float32)
    for u, v in rng.uniform([10, 10], [1014, 758], (30, 2)):  # 30 random "stars": no sky pattern
        noise[int(v) - 1:int(v) + 2, int(u) - 1:int(u) + 2] += rng.uniform(200, 2000)
    res = blind.solve_array(noise)
    assert not res.solved and res.reason


# ---------------------------------------------------------------------------------- inputs

def test_as_image_takes_colour_and_any_memory_order():
    rng = np.random.default_rng(9)
    grey = rng.integers(0, 4000, (64, 80)).astype(np.uint16)
    assert np.array_equal(as_image(np.asfortranarray(grey)), grey)
    assert as_image(grey.T).shape == (80, 64) and as_image(grey.T).flags.c_contiguous
    colour = np.stack([grey, grey, grey], axis=2)
    assert as_image(colour).shape == (64, 80)
    assert as_image(grey.astype(np.float64)).dtype == np.float32
    for bad in ([[1, 2], [3, 4]], None, b"png", np.zeros((4, 4)), np.zeros((30, 30), dtype=complex)):
        with pytest.raises(BadInput):
            as_image(bad)


def test_fov_error_out_of_range_is_bad_input():
    img = np.zeros((64, 64), dtype=np.uint16)
    with pytest.raises(BadInput, match="FOV error"):
        solve_image(img, fov_deg=10.0, fov_error=1.5)


def test_database_is_memory_mapped_and_a_damaged_file_is_rebuilt(tmp_path, monkeypatch):
    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    key = {"method": "test-mmap", "n": 1}
    built = {"a": np.arange(1000, dtype=np.int64), "b": np.ones((10, 4), dtype=np.int32)}
    arrays, info = database.load_or_build(key, lambda: built, mmap=True)
    assert info["source"] == "built"
    arrays, info = database.load_or_build(key, lambda: pytest.fail("rebuilt"), mmap=True)
    assert info["source"] == "cache" and isinstance(arrays["a"], np.memmap)
    assert np.array_equal(arrays["a"], built["a"]) and np.array_equal(arrays["b"], built["b"])
    path = database.database_path(key)
    path.write_bytes(path.read_bytes()[:2000])  # truncated
    arrays, info = database.load_or_build(key, lambda: built, mmap=True)
    assert info["source"] == "built"


def test_database_with_a_missing_array_is_rebuilt_and_the_cache_stays_in_budget(tmp_path, monkeypatch, capsys):
    import zipfile

    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    key = {"method": "test-names", "n": 2}
    built = {"a": np.arange(10), "b": np.arange(5)}
    database.load_or_build(key, lambda: built)
    path = database.database_path(key)
    # rewrite the file without array "b"
    with zipfile.ZipFile(path) as zin:
        members = {n: zin.read(n) for n in zin.namelist() if n != "b.npy"}
    with zipfile.ZipFile(path, "w") as zout:
        for n, data in members.items():
            zout.writestr(n, data)
    for mmap in (False, True):
        arrays, info = database.load_or_build(key, lambda: built, mmap=mmap)
        assert info["source"] == "built" and set(arrays) == {"a", "b"}
        assert "damaged" in capsys.readouterr().err
        with zipfile.ZipFile(path) as zin:
            members = {n: zin.read(n) for n in zin.namelist() if n != "b.npy"}
        with zipfile.ZipFile(path, "w") as zout:
            for n, data in members.items():
                zout.writestr(n, data)
    # least recently used go first when the cache is over its budget
    monkeypatch.setenv("SKYVIEW_CACHE_MB", "0.05")
    big = {"x": np.zeros(4000)}  # 32 kB each
    import os
    import time as _t
    database.load_or_build({"method": "old", "n": 1}, lambda: big)
    old = database.database_path({"method": "old", "n": 1})
    os.utime(old, (_t.time() - 100, _t.time() - 100))
    database.load_or_build({"method": "new", "n": 1}, lambda: big)
    assert not old.exists() and database.database_path({"method": "new", "n": 1}).exists()


def test_a_roof_a_tree_and_a_gradient_in_the_frame_do_not_stop_a_blind_solve(blind, catalog):
    """Real photographs have foreground: a lit roof edge, a tree, sky glow. They are not stars."""
    import cv2

    from skyview.detect.centroids import detect_centroids

    R = R_from_radec_roll(math.radians(250.0), math.radians(35.0), math.radians(-70.0))
    frame = simulate_image(catalog, Camera.from_fov(15.0, 1024, 768), R, SensorModel(), seed=3, mag_limit=9.0)
    img = frame.image.astype(np.float32)
    img[650:, :] += 3000 + 20 * np.arange(1024)[None, :]  # a roof edge, brighter to the right
    cv2.circle(img, (150, 300), 60, 2500, -1)  # a tree lit from below
    img += np.linspace(0, 800, 1024)[None, :]  # sky glow
    img = np.clip(img, 0, 65535).astype(np.uint16)
    cents = detect_centroids(img)
    assert cents.n_extended_rejected >= 2 and cents.n_pixels[:16].max() < 400
    res = blind.solve_array(img)
    assert res.solved and attitude_error_arcsec(res.R, R)["boresight"] < 10.0
    assert res.camera.fov_deg == pytest.approx(15.0, rel=0.002)
    assert not wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in res.matches], frame.truth)


def test_a_colour_jpeg_of_a_real_photograph_solves_blind(blind):
    """The same photograph as an 8-bit colour JPEG (as a phone or a camera writes it)."""
    import cv2

    name = sorted(REFERENCE)[2]
    img16 = load_image(REAL / name).astype(np.float32)
    lo, hi = np.percentile(img16, [1, 99.99])
    img8 = np.clip((img16 - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
    colour = cv2.merge([img8, img8, img8])
    ok, buf = cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 85])
    decoded = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    res = blind.solve_array(decoded)
    assert res.solved, res.reason
    assert attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))["boresight"] < 0.1 * 3600
    assert res.camera.fov_deg == pytest.approx(REFERENCE[name]["fov_deg"], rel=0.005)


def _stretched(name: str) -> np.ndarray:
    """The photograph stretched to 8 bits as a photographer's export has it: the black point 2 sigma under the sky,
    the sky at 25."""
    img16 = load_image(REAL / name).astype(np.float64)
    med = float(np.median(img16))
    sigma = 1.4826 * float(np.median(np.abs(img16 - med)))
    return np.clip((img16 - (med - 2 * sigma)) * (25.0 / (2 * sigma)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("k", [1, 5])
def test_a_photograph_with_a_caption_and_a_watermark_solves_blind(k):
    """A camera's date stamp and a photographer's watermark: each letter a blob brighter than the stars, rows of
    them taken out as trails, where they held most of the brightest 80 measured places; the stars after them fill
    those places (`detect_stars`), and the photograph solves."""
    import cv2

    import skyview

    name = sorted(REFERENCE)[k]
    img8 = _stretched(name)
    colour = cv2.cvtColor(img8, cv2.COLOR_GRAY2BGR)
    cv2.putText(colour, "2019-07-29 20:47:26  ISO 3200  f/2.8  10s", (10, 753), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                (255, 255, 255), 1, cv2.LINE_AA)
    cv2.putText(colour, "(c) A. Photographer", (794, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (200, 200, 255), 1,
                cv2.LINE_AA)
    res = skyview.solve(colour)
    assert res.solved, res.reason
    assert attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))["boresight"] < 0.1 * 3600
    assert res.camera.fov_deg == pytest.approx(REFERENCE[name]["fov_deg"], rel=0.005)


_LABEL_STYLES = {  # (font, scale, BGR colour, thickness, line type)
    "antialiased": (0, 0.5, (120, 220, 255), 1, 16),  # cv2.FONT_HERSHEY_SIMPLEX, cv2.LINE_AA
    "white, no anti-aliasing": (0, 0.5, (255, 255, 255), 1, 8),  # cv2.LINE_8: every stroke pixel saturated
    "small, green": (0, 0.45, (0, 255, 0), 1, 16),  # a peak of ~4 thresholds
}


@pytest.mark.parametrize("k, style", [(0, "antialiased"), (6, "antialiased"), (3, "white, no anti-aliasing"),
                                      (5, "small, green")])
def test_a_photograph_with_a_chart_s_labels_solves_blind(k, style):
    """Star names written over the photograph, as a chart or an annotated export has them: each letter a blob
    brighter than most stars, compact enough to measure a star's PSF and too short a row to be a trail. Their
    light is a plateau, not a star's peak, and letters drawn at the image's full value are strokes of saturated
    pixels, not a disk (`stars.flat_topped`): ranked after the stars, and the photograph solves; on the photograph
    itself no star is taken for one."""
    import cv2

    import skyview
    from skyview.detect.stars import detect_stars, flat_topped, not_stars_of_the_optics

    name = sorted(REFERENCE)[k]
    img8 = _stretched(name)
    chart = cv2.cvtColor(img8, cv2.COLOR_GRAY2BGR)
    font, scale, colour, thickness, line = _LABEL_STYLES[style]
    rng = np.random.default_rng(5)
    boxes = []
    for word in ("Vega", "Lyra", "Cygnus", "Deneb", "Altair", "M57", "Hercules", "Draco", "Albireo", "Sagitta"):
        x, y = int(rng.integers(20, 904)), int(rng.integers(20, 748))
        cv2.putText(chart, word, (x, y), font, scale, colour, thickness, line)
        boxes.append((x - 3, y - 14, x + 10 * len(word) + 3, y + 5))
    stars = detect_stars(chart)
    drawn = flat_topped(chart, stars)
    on_words = np.array([any(b[0] <= u <= b[2] and b[1] <= v <= b[3] for b in boxes) for u, v in stars.uv])
    assert drawn.sum() >= 30 and not (drawn & ~on_words).any()  # letters only
    last = not_stars_of_the_optics(chart, stars)  # (with the blobs wider than a star of their peak)
    assert last[drawn].all() and not last[:len(stars) - last.sum()].any()  # the stars first
    assert stars.params["extended_last"] == last.sum()
    assert not flat_topped(img8, detect_stars(img8)).any()
    res = skyview.solve(chart)
    assert res.solved, res.reason
    assert attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))["boresight"] < 0.1 * 3600


@pytest.mark.parametrize("bits, psf", [(8, 1.1), (16, 1.45), (8, 0.7)])
def test_no_star_is_taken_for_a_drawn_plateau(catalog, bits, psf):
    """Simulated frames over Orion, Sirius and the Pleiades, 8-bit ones saturating dozens of stars, PSFs up to the
    1.5 px the plateau test stops at: `stars.flat_topped` takes no saturated star for strokes (a close pair's two
    disks are not one stroke) and no star standing alone for a plateau; the few it ranks last are stars within 8 px
    of another star (a tight group, or a faint star in a bright one's wing: their light does form a plateau)."""
    from skyview.detect.stars import detect_stars, flat_topped

    for k, (ra, dec) in enumerate([(84.0, -2.0), (101.3, -16.7), (56.8, 24.1)]):
        R = R_from_radec_roll(math.radians(ra), math.radians(dec), math.radians(20.0 * k))
        frame = simulate_image(catalog, Camera.from_fov(20.0, 1024, 1024), R,
                               SensorModel(bit_depth=bits, psf_sigma_px=psf, exposure_s=0.3), seed=k, mag_limit=7.0)
        stars = detect_stars(frame.image)
        assert len(stars) >= 30 and (bits == 16 or stars.saturated.sum() >= 5)
        drawn = flat_topped(frame.image, stars)
        assert not (drawn & stars.saturated).any() and drawn.sum() <= 0.03 * len(stars)
        # every star ranked last has a second rendered star (detected or merged into its blob) within 8 px
        drawn_stars = np.array([[st["u"], st["v"]] for st in frame.truth["stars"]])
        d = np.sort(np.hypot(*(stars.uv[drawn][:, None, :] - drawn_stars[None, :, :]).transpose(2, 0, 1)), axis=1)
        assert (d[:, 1] < 8.0).all()


def _with_a_nebula(name):
    """The photograph stretched to 8 bits (the sky at 25) under a nebula of 90 over a region of 250 x 150 px,
    its knots ~30 px apart: far wider than a star of the photograph's 0.6 px PSF, and out of the background
    map's reach (64 px blocks)."""
    img16 = load_image(REAL / name).astype(np.float64)
    med = float(np.median(img16))
    sigma = 1.4826 * float(np.median(np.abs(img16 - med)))
    img8 = np.clip((img16 - (med - 2 * sigma)) * (25.0 / (2 * sigma)), 0, 255)
    h, w = img8.shape
    y, x = np.mgrid[0:h, 0:w]
    glow = np.exp(-(((x - 0.4 * w) / (0.12 * w)) ** 2 + ((y - 0.5 * h) / (0.1 * h)) ** 2))
    return np.clip(img8 + 90.0 * glow * (1 + 0.5 * np.sin(x / 7.0) * np.sin(y / 9.0)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("k", [1, 5])
def test_a_photograph_with_a_nebula_solves_blind(k):
    """A nebula's knots are wide blobs brighter than most stars: taken for the frame's stars they made it look
    defocused (binned 9x: nothing left to solve); blobs far wider than a star of the PSF the bright stars
    measured are not stars of these optics (`stars.extended_for_their_peak`): not binned for, ranked last."""
    import skyview
    from skyview.detect.stars import detect_stars, extended_for_their_peak

    name = sorted(REFERENCE)[k]
    image = _with_a_nebula(name)
    stars = detect_stars(image)
    assert stars.params["binning"] == 1 and stars.params["extended_last"] >= 10
    wide = extended_for_their_peak(stars)
    first = np.flatnonzero(~wide)
    assert not wide[:len(first)].any()  # the stars first
    # the knots sit in the nebula, the stars ranked first outside it or on it alike
    knots = stars.uv[wide]
    assert np.all(np.abs(knots[:, 0] - 0.4 * 1024) < 0.3 * 1024) and np.all(np.abs(knots[:, 1] - 384) < 0.25 * 768)
    assert not extended_for_their_peak(detect_stars(load_image(REAL / name))).any()  # none on the photograph
    res = skyview.solve(image)
    assert res.solved, res.reason
    assert attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))["boresight"] < 0.1 * 3600


@pytest.mark.parametrize("k", [0, 1])
def test_a_quarter_size_copy_of_a_photograph_solves_blind(k):
    """A copy a quarter the size (256 x 192, as a web page shows it): the stars narrower than a pixel, each a
    single bright pixel the centroider takes for a hot pixel (1-2 stars found); the frame upsampled twice
    finds them (`stars.undersampled_stars`) where they are in the photograph, and it solves."""
    import cv2
    from scipy.spatial import cKDTree

    import skyview
    from skyview.detect.centroids import detect_centroids
    from skyview.detect.stars import detect_stars

    name = sorted(REFERENCE)[k]
    full = load_image(REAL / name)
    small = cv2.resize(full, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    assert len(detect_centroids(small)) <= 2
    stars = detect_stars(small)
    assert stars.params["upsampled"] == 2 and len(stars) >= 8
    d = cKDTree((detect_stars(full).uv + 0.5) / 4.0 - 0.5).query(stars.uv)[0]
    assert np.mean(d < 0.5) >= 0.8  # where the photograph's stars are, to half a (small) pixel
    res = skyview.solve(small)
    assert res.solved, res.reason
    assert attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))["boresight"] < 0.1 * 3600
    assert res.camera.fov_deg == pytest.approx(REFERENCE[name]["fov_deg"], rel=0.02)


@pytest.mark.slow
def test_mirrored_photographs_solve_turned_over_or_not_at_all(blind):
    """A mirror image has the same edge ratios as the sky but the wrong handedness: no rotation fits it as it
    is. Searched as a mirror image (the default) it solves with its rows turned over, at the photograph's own
    attitude (turned half a turn after a left-right flip); not searched so (mirror=False) it fails, never
    verifying a wrong attitude."""
    half_turn = np.diag([-1.0, -1.0, 1.0])
    for name in sorted(REFERENCE)[:2]:  # (all 16 flips of the eight solve turned over: docs/benchmarks.md)
        image = load_image(REAL / name)
        ref = np.array(REFERENCE[name]["R"])
        for flip, expected in ((np.fliplr, half_turn @ ref), (np.flipud, ref)):
            flipped = np.ascontiguousarray(flip(image))
            res = blind.solve_array(flipped, mirror=False)
            assert not res.solved and res.reason and not res.rows_reversed
            res = blind.solve_array(flipped)
            assert res.solved and res.rows_reversed
            err = attitude_error_arcsec(res.R, expected)
            assert err["boresight"] < 120.0 and err["roll"] < 600.0, (name, flip.__name__, err)


def test_lookup_drops_only_patterns_of_sizes_it_cannot_use(blind, monkeypatch):
    """The look-up drops a pattern whose level's band of sizes cannot give an FOV in the rung's range
    before reading its stars. What that rests on: every stored pattern's largest edge, as the look-up
    measures it, lies in its level's band (a sample of the table). Then the candidates are those of the
    look-up without the filter (on the 12 brightest stars of a real photograph, the whole FOV range),
    and the filter did drop hits."""
    ident = blind.identifier
    sample = np.arange(0, len(ident.rows), 50)
    largest = pdb.edge_ratios(pdb.separations(ident.catalog.xyz[ident.rows[sample]]))[1]
    hi = np.radians(ident.pattern_params.levels())[ident.level[sample]]
    assert ((largest >= hi / ident.pattern_params.step) & (largest < hi)).all()
    levels = np.radians(ident.pattern_params.levels())  # and the filter's bands hold the levels' bands
    assert (ident._band[0] <= levels / ident.pattern_params.step).all() and (ident._band[1] >= levels).all()

    uv = blind.solve_array(load_image(REAL / sorted(REFERENCE)[0])).centroids.uv[:12]
    quads = np.array(list(itertools.combinations(range(len(uv)), 4)), dtype=np.int64)
    batch = np.arange(len(quads))
    lo, hi = ident.fov_range_deg
    band = ident._band
    monkeypatch.setattr(ident, "_band", (np.zeros_like(band[0]), np.full_like(band[1], np.inf)))
    every = ident._lookup(uv, quads, batch, 1024, 768, lo, hi)
    monkeypatch.setattr(ident, "_band", band)
    kept = []
    sizes_fit = ident._sizes_fit
    monkeypatch.setattr(ident, "_sizes_fit", lambda *a: kept.append(sizes_fit(*a)) or kept[-1])
    filtered = ident._lookup(uv, quads, batch, 1024, 768, lo, hi)
    assert len(every["pattern"]) > 20
    for k in ("quad", "pattern", "fov", "err"):
        assert np.array_equal(every[k], filtered[k]), k
    kept = np.concatenate(kept)
    assert 0 < kept.sum() < 0.8 * len(kept)


def test_the_lookup_steps_tell_how_the_hits_thin_to_the_verified_pattern(blind):
    """A real photograph's blind steps: the pattern table's hits across the sky (their patterns' centres,
    in both hemispheres), those of a size that fits, those whose ratios agree (one per quad and pattern),
    each stage keeping fewer; the verified hypothesis's four catalog stars are a candidate the thinning kept."""
    from skyview.identify.layers import SkyPlaces

    res = blind.solve_array(load_image(REAL / sorted(REFERENCE)[0]))
    assert res.solved
    steps = res.identification.steps
    assert [st.kind for st in steps[:3]] == ["lookup", "prune", "prune"] and steps[3].kind == "hypothesis"
    hits, sized, agree = steps[:3]
    n = [st.numbers["candidates"] for st in steps[:3]]
    assert n[0] == hits.numbers["hits"] > n[1] > n[2] >= 1 and agree.numbers["agree"] >= n[2]
    assert f"{n[0]:.0f} hits" in hits.note and f"{n[1]:.0f} are of a size" in sized.note
    places = [st.layer(SkyPlaces) for st in steps[:3]]
    assert places[2] is None and places[0].total > places[1].total >= 1
    assert places[0].total <= n[0] and places[1].total <= n[1]  # distinct patterns, each drawn once
    xyz = places[0].xyz
    assert xyz.dtype == np.float32 and np.allclose(np.linalg.norm(xyz, axis=1), 1.0, atol=1e-5)
    assert (xyz[:, 2] > 0.3).any() and (xyz[:, 2] < -0.3).any()  # across the sky
    assert 1 <= len(agree.groups) <= min(200, n[2]) and all(len(g) == 4 for g in agree.groups)
    verified = next(st for st in reversed(steps) if st.kind == "hypothesis")
    assert set(verified.catalog) in [set(g) for g in agree.groups]


def test_the_default_pipeline_measures_the_stars_it_can_use_with_the_same_answer(catalog):
    """A dense frame (200 detections): the default pipeline measures its brightest measured_stars and counts
    the rest (given the FOV, its first try's 40 when that answers); the answer, blind and with the FOV given,
    is the one measuring every star gives, bit for bit; measure_all (the viewer, `skyview solve --record`)
    measures them all."""
    from skyview.simulate.scenarios import get_scenario
    from skyview.solver.pipeline import MEASURED_STARS, measured_stars

    sc = get_scenario("blind20")
    kw = {**sc.render_kwargs(), "mag_limit": 9.0}
    R = R_from_radec_roll(math.radians(280.0), math.radians(-20.0), math.radians(15.0))  # toward the Milky Way
    image = simulate_image(catalog, sc.camera(), R, sc.sensor(), seed=3, **kw).image
    assert measured_stars(40) == MEASURED_STARS and measured_stars(80) == 160
    for fov in (None, 20.0):
        some = solve_image(image, fov_deg=fov)
        every = solve_image(image, fov_deg=fov, measure_all=True)
        assert some.solved and every.solved
        assert len(every.centroids) == every.centroids.n_detected > MEASURED_STARS
        n = MEASURED_STARS if fov is None else 40
        assert len(some.centroids) == n and some.centroids.n_detected == every.centroids.n_detected
        assert np.array_equal(some.centroids.uv, every.centroids.uv[:n])
        assert np.array_equal(some.R, every.R) and some.matches == every.matches
        assert attitude_error_arcsec(some.R, R)["boresight"] < 10.0


# ---------------------------------------------------------------------------------- FOV given: fast path first

def _frame(catalog, fov, seed):
    """A frame of the blind8 scenario's kind (field stars to Hp 9, vignetting, a sky gradient) at `fov`."""
    from dataclasses import replace

    from skyview.simulate.scenarios import SCENARIOS

    sc = replace(SCENARIOS["blind8"], fov_deg=fov)
    cam = sc.camera()
    R = R_from_radec_roll(np.radians(83.8 + 7 * seed), np.radians(-5.4 + 3 * seed), np.radians(30.0))
    return cam, R, simulate_image(catalog, cam, R, SensorModel(), seed=seed, **sc.render_kwargs())


@pytest.mark.parametrize("seed", [1, 2])
def test_a_right_fov_is_solved_by_the_fast_path_and_a_wrong_one_by_the_blind_search(catalog, seed):
    """`skyview solve IMG --fov-deg F`: at the right FOV the improved angle method answers (no pattern
    search); 6 % off, it does not verify and the blind search over F +- 10 % solves and fits the camera.
    Both right, star by star."""
    cam, R, frame = _frame(catalog, 12.0, seed)
    fast = solve_image(frame.image, fov_deg=12.0)
    assert fast.solved and fast.method == "angle" and fast.variant == "improved" and not fast.camera_fitted
    assert attitude_error_arcsec(fast.R, R)["boresight"] < 5.0
    widened = solve_image(frame.image, fov_deg=12.0 * 1.06)
    assert widened.solved and widened.method == "blind" and widened.camera_fitted
    assert widened.camera.fov_deg == pytest.approx(12.0, rel=2e-3)
    assert any("did not verify" in n for n in widened.notes)  # the first try is reported
    assert widened.time_ms["identify"] > 0
    for res in (fast, widened):
        assert not wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in res.matches], frame.truth)


@pytest.mark.parametrize("scale", [1.0, 1.06, 1.0113])
def test_the_fast_path_measures_its_brightest_stars_alone_and_answers_as_with_every_star(catalog, monkeypatch,
                                                                                       scale):
    """Given an FOV, the first try reads the brightest max_stars: they alone are measured first. Where it
    verifies (the right FOV) that is the answer; where it does not (6 % off: the blind search) or its camera is
    off (1.1 % off: refitted), the stars the searches after it read are measured and it is handed to them. The
    answer is the one of measuring them all first, number for number."""
    from skyview.solver import pipeline

    _, _, frame = _frame(catalog, 12.0, 1)  # blind8's kind: ~100 stars detected
    lean = solve_image(frame.image, fov_deg=12.0 * scale)
    with monkeypatch.context() as m:
        m.setattr(pipeline, "_brightest_first", lambda *a: None)  # every star the searches read, measured first
        full = solve_image(frame.image, fov_deg=12.0 * scale)
    assert lean.solved and full.solved and lean.method == full.method
    assert np.array_equal(lean.R, full.R) and lean.matches == full.matches and lean.notes == full.notes
    assert lean.camera == full.camera and lean.camera_fitted == full.camera_fitted
    assert lean.identification.verification == full.identification.verification
    assert lean.centroids.n_detected == full.centroids.n_detected > 40
    if scale == 1.0:  # verified at the FOV given: only the brightest 40 measured
        assert len(lean.centroids) == 40 and not lean.camera_fitted
        np.testing.assert_array_equal(lean.centroids.uv, full.centroids.uv[:40])
    else:  # widened (the blind search) or refitted: every star they read measured, as before
        assert lean.camera_fitted and len(lean.centroids) == len(full.centroids) > 40
        np.testing.assert_array_equal(lean.centroids.uv, full.centroids.uv)


def test_the_calibrated_mode_never_widens(catalog):
    _, _, frame = _frame(catalog, 12.0, 1)
    res = solve_image(frame.image, fov_deg=12.0 * 1.06, fov_error=0.0)
    assert not res.solved and res.method == "angle"  # exact FOV asked for: no blind search behind it


def test_an_fov_typed_a_little_off_is_fitted_when_the_answer_rests_on_a_group_off_the_boresight(catalog,
                                                                                                     monkeypatch):
    """A 20 deg frame (sun20's kind) given an FOV 1.13 % short: the fast path's first angle (the one with the
    fewest candidates, short) identifies a group of stars that fits at the wrong scale, and the attitude
    fitted to it is right at the group and 5.5 px off at the boresight. The similarity of the matched stars
    taken to the boresight says so, the camera is fitted and the stars matched again: the boresight within a
    tenth of a pixel; when that refit does not verify, the blind search fits it. Without the check the answer
    keeps the typed camera and its error."""
    from skyview.core.attitude import random_attitudes
    from skyview.simulate.scenarios import get_scenario
    from skyview.solver import pipeline

    sc = get_scenario("sun20")
    R = random_attitudes(100, np.random.default_rng(7))[54]
    frame = simulate_image(catalog, sc.camera(), R, sc.sensor(), seed=54, **sc.render_kwargs())
    px = 3600.0 * 20.0 / 1024  # arcsec a pixel
    res = solve_image(frame.image, fov_deg=20.0 * (1 - 0.0113))
    assert res.solved and res.method == "angle" and res.camera_fitted  # the fast path's answer, refitted
    assert res.camera.fov_deg == pytest.approx(20.0, rel=1e-4)
    assert attitude_error_arcsec(res.R, R)["boresight"] < 0.1 * px
    assert not wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in res.matches], frame.truth)
    # a refit that does not verify: the blind search fits the camera from the start
    with monkeypatch.context() as m:
        m.setattr(pipeline, "_refit_camera", lambda fast, *a: fast)
        blind = solve_image(frame.image, fov_deg=20.0 * (1 - 0.0113))
    assert blind.solved and blind.method == "blind" and blind.camera_fitted
    assert attitude_error_arcsec(blind.R, R)["boresight"] < 0.1 * px
    assert any("did not fit it" in n for n in blind.notes)
    # ... and when the blind search fails too (searching only +-0.2 % around the FOV typed, 1.1 % off), the
    # first try's answer is what there is: kept, its camera as given, and said so
    with monkeypatch.context() as m:
        m.setattr(pipeline, "_refit_camera", lambda fast, *a: fast)
        kept = solve_image(frame.image, fov_deg=20.0 * (1 - 0.0113), fov_error=0.002)
    assert kept.solved and kept.method == "angle" and not kept.camera_fitted
    assert any("neither the camera refitted" in n for n in kept.notes) and kept.searches
    monkeypatch.setattr(pipeline, "_boresight_moved", lambda *a: False)
    kept = solve_image(frame.image, fov_deg=20.0 * (1 - 0.0113))
    assert kept.solved and not kept.camera_fitted and attitude_error_arcsec(kept.R, R)["boresight"] > 3 * px


def test_the_boresight_check_keeps_a_right_camera_and_flags_one_it_cannot_pin():
    """`_boresight_moved` on tangent-plane positions: stars over the field at the right scale keep the camera;
    a group off the boresight whose attitude was fitted at a scale 2 % off (residuals e (x - mean)) moves it
    (the shift -e mean is beyond its standard errors); two stars close together pin it to a pixel only
    when their noise is small. Its closed form is the 4-parameter least-squares fit, solved as one."""
    from skyview.solver.pipeline import _boresight_moved

    rng = np.random.default_rng(3)
    px, sigma = 3.4e-4, 3e-5  # a pixel, the noise (rad)
    spread = rng.uniform(-0.15, 0.15, (30, 2))
    assert not _boresight_moved(spread, rng.normal(0, sigma, (30, 2)), sigma, px, 3.0)
    group = np.array([0.12, 0.05]) + rng.uniform(-0.03, 0.03, (8, 2))
    e = 0.02
    d = e * (group - group.mean(axis=0)) + rng.normal(0, sigma, (8, 2))
    assert _boresight_moved(group, d, sigma, px, 3.0)
    exact = rng.normal(0, sigma, (8, 2))
    assert not _boresight_moved(group, exact, sigma, px, 3.0)  # the same group at the right scale: pinned
    # two of them, at the fast path's half-pixel sigma: the boresight is pinned to ~2 px only
    assert _boresight_moved(group[:2], exact[:2], 0.5 * px, px, 3.0)
    assert not _boresight_moved(spread[:2] * 4, exact[:2], 0.5 * px, px, 3.0)  # two far apart across it: pinned
    assert _boresight_moved(group[[0, 0]], exact[:2], sigma, px, 3.0)  # two stars at one place: nothing fixed
    # the closed form is the least-squares fit of d = t + w J x + s x (rows interleaved x, y): the same shift,
    # and the shift's variance from the normal equations' inverse
    A = np.zeros((16, 4))
    A[0::2, 0] = A[1::2, 1] = 1.0
    A[0::2, 2], A[1::2, 2] = -group[:, 1], group[:, 0]
    A[0::2, 3], A[1::2, 3] = group[:, 0], group[:, 1]
    coef, rss = np.linalg.lstsq(A, d.ravel(), rcond=None)[:2]
    var_t = float(rss[0]) / 12 * float(np.trace(np.linalg.inv(A.T @ A)[:2, :2]))
    shift2 = float(coef[0] ** 2 + coef[1] ** 2)
    for z in (0.5 * math.sqrt(shift2 / var_t), 0.99 * math.sqrt(shift2 / var_t), 1.01 * math.sqrt(shift2 / var_t)):
        assert _boresight_moved(group, d, 1e-12, 1.0, z) == (shift2 > z * z * var_t)


def test_blend_table_is_the_ball_query_it_replaces(catalog):
    """resolved_matches reads one table: each star's chord to its nearest companion that could blend with
    it. On 3,000 random stars it must give what the k-d tree's ball query gives at every blend radius."""
    from skyview.core.catalog import chord
    from skyview.identify.verify import BLEND_DELTA_MAG, BLEND_REACH_RAD, blend_table

    table = blend_table(catalog)
    rows = np.random.default_rng(4).choice(len(catalog), 3000, replace=False)
    for radius_deg in (0.005, 0.05, 0.5, math.degrees(BLEND_REACH_RAD) * 0.99):
        lim = float(chord(math.radians(radius_deg)))
        near = catalog.tree.query_ball_point(catalog.xyz[rows], lim)
        expect = np.array([any(k != r and catalog.mag[k] <= catalog.mag[r] + BLEND_DELTA_MAG for k in nb)
                           for r, nb in zip(rows, near)])
        assert np.array_equal(table[rows] <= lim, expect), radius_deg
        assert expect.any() or radius_deg < 0.01


def test_resolved_matches_leaves_out_a_blended_pair(catalog):
    from skyview.identify.verify import BLEND_RADIUS_PX, blend_table, resolved_matches

    table = blend_table(catalog)
    bright = np.flatnonzero(catalog.mag < 7.0)
    pair = int(bright[np.argmin(table[bright])])  # the closest blend among stars to Hp 7
    alone = [int(r) for r in bright[np.argsort(table[bright])[::-1][:5]]]
    scale = 1.2 * table[pair] / BLEND_RADIUS_PX  # a pixel scale at which the pair is within the radius
    matches = {0: pair, **{k + 1: r for k, r in enumerate(alone)}}
    kept = resolved_matches(matches, catalog, scale)
    assert 0 not in kept and all(k + 1 in kept for k in range(len(alone)))
    assert resolved_matches(matches, catalog, 0.5 * table[pair] / BLEND_RADIUS_PX) == matches  # resolved there
    # a camera of over 0.4 deg a pixel (beyond the table's reach): the k-d tree asked star by star
    from skyview.identify.verify import BLEND_REACH_RAD

    huge = 1.5 * BLEND_REACH_RAD / BLEND_RADIUS_PX
    near = catalog.tree.query_ball_point(catalog.xyz[alone], float(np.sqrt(2 - 2 * np.cos(huge * BLEND_RADIUS_PX))))
    expect = {k + 1 for k, (r, nb) in enumerate(zip(alone, near))
              if not any(j != r and catalog.mag[j] <= catalog.mag[r] + 2.5 for j in nb)}
    wide = resolved_matches({k + 1: r for k, r in enumerate(alone)}, catalog, huge)
    assert set(wide) == (expect if len(expect) >= 2 else set(range(1, len(alone) + 1)))


# ------------------------------------------------------------------ fields whose brightest detections are not stars

def _lit_roof(image: np.ndarray, seed: int) -> np.ndarray:
    """The photograph with a lit roof over its lower half (a bright gradient with a wavy edge) and a dozen
    lamps and windows brighter than any star on it and above it, as a photograph from a town has them."""
    import cv2

    rng = np.random.default_rng(seed)
    img = image.astype(np.float64)
    H, W = img.shape
    top = float(np.percentile(img, 99.99))
    y0 = int(H * (0.45 + 0.1 * rng.random()))
    yy, xx = np.mgrid[:H, :W]
    roof = yy > y0 + 30 * np.sin(xx / 90.0 + seed)
    out = img.copy()
    out[roof] = np.median(img) + 0.3 * top * (1 - (yy[roof] - y0) / H)
    for _ in range(int(rng.integers(8, 20))):
        cv2.circle(out, (int(rng.integers(0, W)), int(rng.integers(y0, H))), int(rng.integers(2, 6)),
                   float(top * rng.uniform(0.8, 3.0)), -1)
    for _ in range(6):
        cv2.circle(out, (int(rng.integers(0, W)), int(rng.integers(int(y0 * 0.7), y0))), 3, float(top * 2), -1)
    return np.clip(out, 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("k", [0, 7])
def test_a_lit_roof_and_lamps_brighter_than_the_stars_do_not_hide_them(k):
    # the brightest detections are lamps and roof edges. The roof's edges are blobs far wider than a star of their
    # peak (`stars.extended_for_their_peak`), the unsaturated lamps' disks plateaus (`stars.flat_topped`): both
    # ranked after the stars, and the search needs no slide past them (before the plateaus were told apart, 5 of
    # the 8 photographs so lit solved only by sliding the pattern window down the brightness order)
    from skyview.detect.stars import detect_stars, flat_topped

    name = sorted(REFERENCE)[k]
    img = _lit_roof(load_image(REAL / name), seed=k)
    res = solve_image(img, deep=False)
    assert res.solved, res.reason
    ref = REFERENCE[name]
    R_ref = R_from_radec_roll(math.radians(ref["ra_deg"]), math.radians(ref["dec_deg"]), math.radians(ref["roll_deg"]))
    assert attitude_error_arcsec(res.R, R_ref)["boresight"] < 120.0
    assert abs(res.camera.fov_deg / ref["fov_deg"] - 1.0) < 0.005
    stars = detect_stars(img)
    assert stars.params["extended_last"] >= 10 and flat_topped(img, stars).any()
    assert not any(st.kind == "lookup" and min(st.observed) >= 8 for st in res.identification.steps)


def test_the_pattern_window_slides_past_bright_detections_that_are_not_stars():
    """Ten bright points no test tells from stars (a town's saturated lamps, a plane's lights) lead the brightness
    order: no pattern of them verifies, and the pattern stars slide down the order to the stars (issue 27, item 3);
    with the window held on the brightest, nothing verifies."""
    from skyview.detect.stars import detect_stars

    name = sorted(REFERENCE)[7]
    img = load_image(REAL / name)
    H, W = img.shape
    stars = detect_stars(img).uv[:40]
    lamps = np.random.default_rng(7).uniform([20, 0.6 * H], [W - 20, H - 20], size=(10, 2))
    uv = np.concatenate([lamps, stars])
    identifier = BlindSolver(deep=False).identifier
    ident = identifier.identify(uv, W, H)
    assert ident.identified
    assert any(st.kind == "lookup" and min(st.observed) >= 8 for st in ident.steps)
    assert not set(ident.matches) & set(range(10))  # no lamp matched
    ref = REFERENCE[name]
    R_ref = R_from_radec_roll(math.radians(ref["ra_deg"]), math.radians(ref["dec_deg"]), math.radians(ref["roll_deg"]))
    assert attitude_error_arcsec(ident.R, R_ref)["boresight"] < 120.0
    assert not identifier.identify(uv, W, H, slide=False).identified


def test_the_blind_search_is_an_identifier_whose_hypotheses_the_shared_verification_decides(blind):
    """The blind search yields its hypotheses into the template every method runs in (issue 29): each one that
    passes its quick check is fitted and verified on its own terms (the fitted camera, the catalog to the
    frame's depth, the measured noise), counted with every check made (Bonferroni); one `Identification`."""
    from skyview.detect.stars import detect_stars
    from skyview.identify.base import IDENTIFIED, Identifier

    name = sorted(REFERENCE)[0]
    img = load_image(REAL / name)
    uv = detect_stars(img).uv[:40]
    identifier = blind.identifier
    assert isinstance(identifier, Identifier)
    ident = identifier.identify(uv, img.shape[1], img.shape[0])
    assert ident.status == IDENTIFIED and ident.method == "blind"
    kinds = [st.kind for st in ident.steps]
    assert kinds[-2:] == ["fit", "verify"] and "lookup" in kinds and "hypothesis" in kinds
    ver = ident.verification
    assert ver["passed"] and ver["n_hypotheses"] == ident.stats["checks"] >= 1
    # what the verification found: the fitted camera, the depth and the noise it verified with
    ref = REFERENCE[name]
    assert abs(ident.camera.fov_deg / ref["fov_deg"] - 1.0) < 0.005
    assert ident.mag_limit == ident.stats["mag_limit"] and ident.sigma_rad > 0
    # the matches name rows of the full guide catalog (the verification ran on the catalog to the depth)
    assert max(identifier.catalog.mag[list(ident.matches.values())]) <= ident.mag_limit
    R_ref = R_from_radec_roll(math.radians(ref["ra_deg"]), math.radians(ref["dec_deg"]), math.radians(ref["roll_deg"]))
    assert attitude_error_arcsec(ident.R, R_ref)["boresight"] < 120.0
    uv_cat, _ = ident.camera.project(identifier.catalog.xyz[list(ident.matches.values())] @ ident.R.T)
    assert np.median(np.hypot(*(uv_cat - uv[list(ident.matches)]).T)) < 1.0
    # an FOV outside what the database covers: the search cannot run, and says why
    outside = identifier.identify(uv, img.shape[1], img.shape[0], fov_deg=150.0, fov_error=0.05, checks_before=7)
    assert outside.status == "failed" and "covers FOVs" in outside.reason and outside.camera is None
    assert outside.stats["checks"] == 7  # the checks of the searches before it still count for the next


def test_a_distorted_lens_at_the_fov_given_is_refitted_and_keeps_its_method(catalog):
    """`--fov-deg F` on a lens with k1 = 0.05: the improved angle method verifies at the FOV given, its
    stars say the camera is off, and the refit (`CameraRefit.refit`, through the template's verification)
    fits k1 and verifies again; the identification still names the angle method, with the first one's
    stars counted and time, and the refit's own time beside them."""
    from dataclasses import replace

    from skyview.simulate.scenarios import SCENARIOS

    cam = Camera.from_fov(12.0, 1024, 768, k1=0.05)
    R = R_from_radec_roll(np.radians(90.8), np.radians(-2.4), np.radians(30.0))
    frame = simulate_image(catalog, cam, R, SensorModel(), seed=1,
                           **replace(SCENARIOS["blind8"], fov_deg=12.0).render_kwargs())
    res = solve_image(frame.image, fov_deg=12.0)
    assert res.solved and res.method == "angle" and res.camera_fitted and res.camera.k1 > 0.02
    ident = res.identification
    assert ident.method == "angle" and ident.camera is res.camera and ident.verification["passed"]
    assert ident.stats["stars"] == 40 and ident.stats["refit_time_s"] > 0 and ident.stats["checks"] >= 1
    assert attitude_error_arcsec(res.R, R)["boresight"] < 5.0
    assert not wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in res.matches], frame.truth)


def test_a_refit_without_its_hypothesis_says_so(catalog):
    """A CameraRefit has no search of its own: identified without the hypothesis `refit` gives, it says why."""
    from skyview.identify.base import INCONCLUSIVE, PixelStars
    from skyview.identify.camera_refit import CameraRefit

    refit = CameraRefit(catalog)
    ident = refit.run(refit.begin(PixelStars(np.zeros((5, 2)), 640, 480)))
    assert ident.status == INCONCLUSIVE and "refit()" in ident.reason and ident.camera is None


def test_a_cold_database_is_asked_for_the_pages_a_lookup_reads(tmp_path, monkeypatch):
    """`database.prefetch` asks the kernel for exactly the pages that hold the rows a look-up will read, one
    call per run of pages (so a cold page cache reads them together), and the blind search does so in its
    first search only."""
    import mmap

    arr = np.lib.format.open_memmap(tmp_path / "t.npy", mode="w+", dtype=np.int64, shape=(10_000,))
    arr[:] = np.arange(10_000)
    arr.flush()
    mapped = np.load(tmp_path / "t.npy", mmap_mode="r")
    asked = []

    class Map:  # the map's madvise, recorded
        def __init__(self, m):
            self.m = m

        def __len__(self):
            return len(self.m)

        def madvise(self, option, start=0, length=0):
            asked.append((option, start, length))

    monkeypatch.setattr(mapped, "_mmap", Map(mapped._mmap), raising=False)
    rows = np.array([0, 1, 600, 5000, 5001, 9999])
    database.prefetch(mapped, rows)
    page = mmap.PAGESIZE
    lead = mapped.offset % mmap.ALLOCATIONGRANULARITY
    wanted = sorted({(lead + r * 8) // page for r in rows.tolist()})
    got = sorted({p for _, s, n in asked for p in range(s // page, (s + n - 1) // page + 1)})
    assert got == wanted and all(o == mmap.MADV_WILLNEED for o, _, _ in asked)
    assert len(asked) == len(wanted) - sum(b - a == 1 for a, b in zip(wanted, wanted[1:]))  # runs
    database.prefetch(np.arange(5), np.array([1, 2]))  # not a map: nothing to ask

    # the blind search prefetches while its database is cold (its first search), not after
    solver = BlindSolver(deep=False)
    calls = []
    monkeypatch.setattr(database, "prefetch", lambda m, r: calls.append(len(r)))
    name = sorted(REFERENCE)[0]
    img = load_image(REAL / name)
    first = solver.solve_array(img)
    n_first = len(calls)
    again = solver.solve_array(img)
    assert n_first > 0 and len(calls) == n_first  # none on the second solve
    assert first.solved and again.solved
