"""Stars of any image: wide stars are binned to the centroider's scale, trails are taken out."""

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.errors import BadInput
from skyview.detect.centroids import detect_centroids, load_image
from skyview.detect.stars import bin_image, detect_stars, psf_sigma_from_moments
from skyview.detect.trails import trail_members
from skyview.simulate.render import SensorModel, simulate_image
from skyview.simulate.scenarios import get_scenario
from skyview.solver.pipeline import BlindSolver

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())


def _frame(catalog, name="blind8", seed=3, **sensor):
    sc = get_scenario(name)
    R = random_attitudes(1, np.random.default_rng(seed))[0]
    return simulate_image(catalog, sc.camera(), R, SensorModel(**sensor), seed=seed, **sc.render_kwargs())


def test_trail_members_finds_a_dashed_line_and_not_a_cluster():
    rng = np.random.default_rng(0)
    stars = rng.uniform(0, 1000, (150, 2))
    t = np.linspace(0, 1, 12)[:, None]
    trail = np.array([100.0, 200.0]) + t * np.array([300.0, 90.0]) + rng.normal(0, 0.4, (12, 2))
    cluster = np.array([500.0, 500.0]) + rng.normal(0, 4.0, (6, 2))  # a tight group is not a line
    # brightest first: the trail's dashes and the cluster among the 20 brightest stars
    m = trail_members(np.vstack([stars[:20], trail, cluster, stars[20:]]), max_gap_px=35.0)
    assert m[20:32].all()
    assert not m[32:38].any()
    assert m[:20].sum() + m[38:].sum() <= 1  # a star that happens to lie on the trail at most
    assert not trail_members(stars).any()


def test_a_broken_satellite_trail_is_taken_out_and_the_stars_kept(catalog):
    frame = _frame(catalog, seed=11)
    img = frame.image.copy()
    peak = float(np.percentile(img, 99.99))
    # a bright trail broken into dashes (an aircraft's lights, a trail cut up by JPEG blocks)
    for k in range(10):
        p0 = (120 + 40 * k, 600 - 25 * k)
        cv2.line(img, p0, (p0[0] + 8, p0[1] - 5), peak, 2)
    plain = detect_centroids(img)
    stars = detect_stars(img)
    assert stars.params["n_trail_rejected"] >= 8
    truth = cKDTree(frame.rendered_uv)
    near_truth = lambda uv: truth.query(uv)[0] < 2.0  # noqa: E731
    # the dashes sat among the brightest detections; now the brightest ten are all stars
    assert not near_truth(plain.uv[:10]).all()
    assert near_truth(stars.uv[:10]).all()
    # no star was lost with the trail
    assert near_truth(stars.uv).sum() >= near_truth(plain.uv).sum() - 1


def test_the_brightest_measured_alone_are_the_first_of_all_measured_unless_a_trail_or_saturation_says_not(
        catalog):
    """`_brightest_first` (the FOV-given first try's stars): the brightest max_stars measured alone are, field
    for field, the first max_stars of the stars measured for the searches after it; where a saturated star was
    left unmeasured (its whole disk may rank it among them), it declines. A trail taken out among the brightest
    measured gives its places to the stars after it: the first max_stars of every detection measured, trails
    taken out of them all, so the first try keeps them (not measured again for the searches)."""
    from skyview.solver.pipeline import _brightest_first, measured_stars

    frame = _frame(catalog, seed=4)  # blind8: 31 stars detected
    every = detect_stars(frame.image, faint_search=False, max_stars=measured_stars(15))
    few = _brightest_first(frame.image, 5.0, 15)
    assert len(few) == 15 and few.n_detected == every.n_detected > 25 and few.n_unmeasured > 0
    for f in ("uv", "brightness", "peak", "n_pixels", "saturated", "elongated", "edge", "blended", "axis_ratio"):
        np.testing.assert_array_equal(getattr(few, f), getattr(every, f)[:15])
    assert few.psf_sigma_px == every.psf_sigma_px and few.noise_sigma == every.noise_sigma
    # an 8-bit frame saturates its bright stars: measuring only the brightest two leaves some unmeasured
    bright = _frame(catalog, name="sun20", seed=2, bit_depth=8)
    full, two = detect_centroids(bright.image), detect_centroids(bright.image, max_stars=2)
    assert int(full.saturated.sum()) >= 3 and two.n_unmeasured_saturated == int(full.saturated.sum()) - int(two.saturated.sum())
    assert full.n_unmeasured_saturated == 0 and _brightest_first(bright.image, 5.0, 2) is None
    # a trail taken out among them: a row of compact fragments, evenly bright (a satellite's trail crossing the
    # threshold only in places; drawn line segments would be plateaus, ranked last before any trail test)
    img = _frame(catalog, seed=11).image.copy()
    peak = float(np.percentile(img, 99.99))
    yy, xx = np.mgrid[:img.shape[0], :img.shape[1]]
    for k in range(10):
        spot = peak * np.exp(-((xx - 120.3 - 40 * k) ** 2 + (yy - 600.6 + 25 * k) ** 2) / (2 * 1.1 ** 2))
        img = np.minimum(img + np.rint(spot), np.iinfo(img.dtype).max).astype(img.dtype)
    few = detect_stars(img, faint_search=False, max_stars=20)
    every = detect_stars(img, faint_search=False, max_stars=None)
    assert few.params["n_trail_rejected"] >= 8 and len(few) == 20 and few.n_unmeasured == len(every) - 20 > 0
    for f in ("uv", "brightness", "peak", "n_pixels", "saturated", "elongated", "edge", "blended", "axis_ratio"):
        np.testing.assert_array_equal(getattr(few, f), getattr(every, f)[:20])
    twenty = _brightest_first(img, 5.0, 20)  # the first 20 of every detection, as the searches' would be
    np.testing.assert_array_equal(twenty.uv, every.uv[:20])
    np.testing.assert_array_equal(twenty.uv, detect_stars(img, faint_search=False, max_stars=measured_stars(20)).uv[:20])
    first = _brightest_first(img, 5.0, 40)  # every detection measured: the first try has them all
    assert first.params["n_trail_rejected"] >= 8 and first.n_unmeasured == 0
    np.testing.assert_array_equal(first.uv, every.uv)


def test_compact_stars_pass_unchanged(catalog):
    frame = _frame(catalog, seed=4)
    plain, stars = detect_centroids(frame.image), detect_stars(frame.image)
    assert stars.params["binning"] == 1 and stars.params["n_trail_rejected"] == 0
    np.testing.assert_array_equal(stars.uv, plain.uv)


def test_wide_stars_are_binned_and_measured_in_full_resolution_pixels(catalog):
    frame = _frame(catalog, seed=5, psf_sigma_px=4.5, exposure_s=1.6)  # a defocused lens
    plain, stars = detect_centroids(frame.image), detect_stars(frame.image)
    assert psf_sigma_from_moments(frame.image, plain) > 2.5
    assert stars.params["binning"] >= 2 and stars.image_shape == frame.image.shape
    d, i = cKDTree(frame.rendered_uv).query(stars.uv[:20])
    assert np.median(d) < 0.5  # positions in the full image's pixels
    # brightest first, as the truth (the simulator's truth lists the stars brightest first)
    assert np.median(i[:10]) < 15


def test_bin_image_averages_blocks_and_binning_is_checked():
    img = np.arange(36, dtype=np.uint16).reshape(6, 6)
    b = bin_image(img, 2)
    assert b.shape == (3, 3) and b[0, 0] == pytest.approx((0 + 1 + 6 + 7) / 4)
    with pytest.raises(BadInput):
        detect_stars(img, binning=0)


def test_an_upscaled_colour_jpeg_of_a_real_photograph_solves_blind(catalog):
    """Exported at 4x the size with stars saturated into disks (as a phone or a raw converter may)."""
    name = sorted(REFERENCE)[3]
    img = load_image(REAL / name)
    g8 = cv2.convertScaleAbs(img, alpha=255.0 / float(np.percentile(img, 99.9)))
    big = cv2.resize(g8, None, fx=4, fy=4, interpolation=cv2.INTER_CUBIC)
    ok, buf = cv2.imencode(".jpg", cv2.merge([big, big, big]), [cv2.IMWRITE_JPEG_QUALITY, 85])
    res = BlindSolver(catalog=catalog).solve_array(cv2.imdecode(buf, cv2.IMREAD_COLOR))
    assert res.solved, res.reason
    assert attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))["boresight"] < 120.0
    assert res.camera.fov_deg == pytest.approx(REFERENCE[name]["fov_deg"], rel=0.01)


def test_saturated_stars_only_at_the_border_are_kept_as_they_are():
    img = np.full((200, 300), 100, np.uint16)
    rng = np.random.default_rng(2)
    img = (img + rng.normal(0, 3, img.shape)).astype(np.uint16)
    for u, v in ((3, 100), (150, 2), (296, 190)):  # saturated disks within 24 px of the border
        cv2.circle(img, (u, v), 3, 65535, -1)
    for u, v in ((60, 60), (120, 140), (200, 80), (250, 150)):
        cv2.circle(img, (u, v), 1, 3000, -1)
    c = detect_stars(img)
    assert len(c) == 7 and c.saturated.sum() == 3


# ------------------------------------------------------------------ faint frames: the matched filter

def _faint_frame(catalog, seed):
    sc = get_scenario("faint6")
    R = random_attitudes(seed + 1, np.random.default_rng(seed))[-1]
    return simulate_image(catalog, sc.camera(), R, sc.sensor(), seed=seed, **sc.render_kwargs()), R


def _true_and_false(c, truth, radius=1.5):
    tu = np.array([[s["u"], s["v"]] for s in truth["stars"]])
    d = cKDTree(tu).query(c.uv)[0]
    return int(np.count_nonzero(d <= radius)), int(np.count_nonzero(d > radius))


def test_a_faint_8bit_frame_is_searched_through_the_matched_filter(catalog):
    # a star tracker's 30 ms frame, 8 bits, background ~2 DN: pixel by pixel the centroider finds a handful
    found_plain, found = [], []
    for seed in range(4):
        fr, R = _faint_frame(catalog, seed)
        assert 1.0 <= np.median(fr.image) <= 3.0 and fr.image.dtype == np.uint8
        plain = detect_centroids(fr.image)
        c = detect_stars(fr.image)
        assert c.params["matched_filter_sigma_px"] > 0
        true, false = _true_and_false(c, fr.truth)
        assert false <= 1 and c.n_hot_pixels_rejected >= 8  # the sensor's 8 hot pixels are not stars
        found_plain.append(len(plain))
        found.append(true)
        res = BlindSolver(catalog=catalog).solve_array(fr.image)
        assert res.solved and attitude_error_arcsec(res.R, R)["boresight"] < 10.0
    assert sum(found) >= 2 * sum(found_plain), (found, found_plain)


def test_the_faint_search_deferred_finds_what_detect_stars_finds_at_once(catalog):
    """A solver asks for the stars it can have cheaply first (`faint_search=False`) and for the matched filter's
    only when those do not solve: the stars it then gets are detect_stars' own, bit for bit; a frame with
    enough stars has nothing deferred."""
    from skyview.detect.stars import fainter_stars

    for seed in range(3):
        fr, _ = _faint_frame(catalog, seed)
        first = detect_stars(fr.image, faint_search=False)
        assert first.params["faint_search"] == "deferred" and "matched_filter_sigma_px" not in first.params
        later, at_once = fainter_stars(fr.image, first), detect_stars(fr.image)
        assert later is not None and len(later) > len(first)
        assert np.array_equal(later.uv, at_once.uv) and np.array_equal(later.brightness, at_once.brightness)
    dense = _frame(catalog, "blind8", seed=3).image
    c = detect_stars(dense, faint_search=False)
    assert "faint_search" not in c.params and fainter_stars(dense, c) is None
    # a sparse frame of compact stars (an 8 deg star tracker's): its width check waits too, and when detect_stars
    # would find nothing more, the stars at hand are its own
    checked = 0
    for seed in range(6):
        img = _frame(catalog, "cole8", seed=seed).image
        first, at_once = detect_stars(img, faint_search=False), detect_stars(img)
        if first.params.get("faint_search") != "deferred":
            continue
        later = fainter_stars(img, first)
        if later is None:
            assert np.array_equal(first.uv, at_once.uv) and np.array_equal(first.brightness, at_once.brightness)
        else:
            assert np.array_equal(later.uv, at_once.uv)
        checked += 1
    assert checked >= 3


def test_solve_image_reaches_a_faint_frames_stars_when_its_first_stars_do_not_solve(catalog):
    from skyview.solver.pipeline import solve_image

    fr, R = _faint_frame(catalog, 1)
    assert len(detect_stars(fr.image, faint_search=False)) < 8  # too few to solve on
    res = solve_image(fr.image)
    assert res.solved and attitude_error_arcsec(res.R, R)["boresight"] < 10.0
    assert res.centroids.params.get("matched_filter_sigma_px", 0) > 0  # solved on the matched filter's stars


def test_a_frame_with_enough_stars_never_goes_through_the_matched_filter(catalog):
    fr = _frame(catalog, "blind8", seed=3)
    c = detect_stars(fr.image)
    assert len(c) >= 12 and "matched_filter_sigma_px" not in c.params


def test_the_matched_filter_keeps_noise_out_of_an_empty_faint_frame(catalog):
    sc = get_scenario("faint6")
    empty = catalog.select(np.zeros(len(catalog), dtype=bool), "no stars")
    for seed in range(3):
        fr = simulate_image(empty, sc.camera(), np.eye(3), sc.sensor(), seed=seed, mag_limit=9.0)
        assert len(detect_stars(fr.image)) == 0


def test_patch_hot_pixels_takes_a_hot_pixel_and_leaves_a_star():
    from skyview.detect.hot_pixels import patch_hot_pixels

    img = np.full((40, 40), 2.0, np.float32)
    yy, xx = np.mgrid[:40, :40]
    img += 20.0 * np.exp(-((xx - 10.3) ** 2 + (yy - 12.6) ** 2) / (2 * 1.1 ** 2))
    img[30, 25] = 60.0
    out, n = patch_hot_pixels(img, 2.0, 1.0)
    assert n == 1 and out[30, 25] == 2.0
    np.testing.assert_array_equal(out[:25], img[:25])  # the star untouched


def test_saturated_fluxes_from_the_width_check_are_measured_again_the_same():
    """The saturated stars' disk fluxes that the width check measured already (its brightest stars) are the
    fluxes measuring them again gives, bit for bit (a star's moments do not depend on the stars measured
    with it), and they are the ones used: here two of the three saturated stars known, the third measured."""
    from skyview.detect.stars import _saturated_by_aperture, star_moments

    img = load_image(REAL / "2019-07-29T204726_Alt40_Azi-45_Try1.png")
    c = detect_centroids(img)
    assert np.flatnonzero(c.saturated).tolist() == [0, 1, 2]
    known = star_moments(img, c, np.arange(2))[1]
    together = star_moments(img, c, np.arange(3))[1]
    assert np.array_equal(together, np.r_[known, star_moments(img, c, np.array([2]))[1]])
    reused, measured = _saturated_by_aperture(img, c, 1, known), _saturated_by_aperture(img, c, 1)
    assert np.array_equal(reused.uv, measured.uv) and np.array_equal(reused.brightness, measured.brightness)
    # fluxes ten times larger, given as known, become the two stars' brightness: the known ones are read
    boosted = _saturated_by_aperture(img, c, 1, 10.0 * known)
    assert np.array_equal(np.sort(boosted.brightness)[::-1][:2], 10.0 * known)


def test_a_frame_looks_undersampled_only_when_its_point_like_pixels_outnumber_narrow_stars():
    """`looks_undersampled`: few stars, their hot pixels and one-pixel blobs twice their number and three more,
    and the stars it measured narrower than 0.6 px (or none measured the PSF); never on a frame over 4 MP."""
    import dataclasses

    from skyview.detect.centroids import Centroids
    from skyview.detect.stars import looks_undersampled

    def frame(n_hot, sigma, measured, shape=(192, 256)):
        c = Centroids.empty(n_hot_pixels_rejected=n_hot, n_small_rejected=2, psf_sigma_px=sigma, image_shape=shape,
                            params={"psf_measured": measured})
        return dataclasses.replace(c, uv=np.zeros((3, 2)), brightness=np.ones(3), peak=np.ones(3),
                                   n_pixels=np.ones(3, dtype=np.int64), saturated=np.zeros(3, dtype=bool),
                                   elongated=np.zeros(3, dtype=bool), edge=np.zeros(3, dtype=bool),
                                   blended=np.zeros(3, dtype=bool), axis_ratio=np.ones(3))

    assert looks_undersampled(frame(20, 0.45, True))  # 22 point-like >= 2 (3 + 3)
    assert looks_undersampled(frame(20, 1.2, False))  # no star measured the PSF (1.2 px assumed)
    assert not looks_undersampled(frame(20, 1.1, True))  # hot pixels beside well-sampled stars are hot pixels
    assert not looks_undersampled(frame(9, 0.45, True))  # 11 < 12
    assert not looks_undersampled(frame(20, 0.45, True, shape=(3000, 2000)))  # too large to upsample


def test_a_frame_read_twice_in_one_solve_is_detected_once(catalog, monkeypatch):
    """Given an FOV 3 % off, a dense wide field (a 60 deg 8-bit JPEG whose brightest detections include blobs that
    are not stars) is read three times: its brightest 40 for the first try (which ranks every detection, measured,
    past a blob that is not a star), then the 100 the blind search reads. Within one solve the frame is detected
    once (`detections_kept`: threshold, labels, blends) and each reading only measures; the answer is the one each
    reading detecting the frame again gives, number for number."""
    import contextlib

    import skyview.detect.centroids as centroids_module
    import skyview.solver.pipeline as pipeline
    from skyview.core.camera import Camera
    from skyview.solver.pipeline import solve_image

    detected = []
    detect = centroids_module._detect_centroids

    def counted(image, **kw):
        detected.append(kw.get("max_stars"))
        return detect(image, **kw)

    monkeypatch.setattr(centroids_module, "_detect_centroids", counted)
    cam = Camera.from_fov(60.0, 800, 600)
    for k, R in enumerate(random_attitudes(2, np.random.default_rng(5))):
        img = simulate_image(catalog, cam, R, SensorModel(bit_depth=8), seed=k, mag_limit=6.5, jpeg_quality=80,
                             faint_extra_mag=2.0).image
        detected.clear()
        once = solve_image(img, fov_deg=61.8)
        assert detected == [40]  # the first reading's detection; every detection and the 100 measured from it
        with monkeypatch.context() as m:
            m.setattr(pipeline, "detections_kept", contextlib.nullcontext)
            detected.clear()
            each = solve_image(img, fov_deg=61.8)
            assert detected == [40, None, 100, None]  # each reading detecting the frame again
        assert once.solved and each.solved and once.method == each.method == "blind"
        assert np.array_equal(once.R, each.R) and once.matches == each.matches
        for f in dataclasses.fields(once.centroids):
            a, b = getattr(once.centroids, f.name), getattr(each.centroids, f.name)
            assert (np.array_equal(a, b, equal_nan=True) if isinstance(a, np.ndarray) else a == b or a != a), f.name
