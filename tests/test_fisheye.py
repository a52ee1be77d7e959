"""Wide and fisheye lenses (issue 27, item 4): the equidistant and equisolid camera models, their fit, their
WCS, and blind solving of simulated 120 deg and 180 deg all-sky frames against the simulator's truth."""

import json

import numpy as np
import pytest

from skyview.core.attitude import R_from_radec_roll, attitude_error_arcsec, random_attitudes
from skyview.core.camera import EQUIDISTANT, EQUISOLID, Camera
from skyview.core.camera_fit import fit_camera
from skyview.core.catalog import vec_to_radec
from skyview.core.errors import BadInput
from skyview.simulate.render import simulate_image
from skyview.simulate.scenarios import get_scenario
from skyview.solver.pipeline import NARROW_AFTER_CHECKS, BlindSolver


@pytest.mark.parametrize("model", [EQUIDISTANT, EQUISOLID])
@pytest.mark.parametrize("k1,k2", [(0.0, 0.0), (0.02, -0.002)])
def test_fisheye_projection_round_trips_and_follows_its_law(model, k1, k2):
    cam = Camera.from_fov(180.0, 1024, 768, k1=k1, k2=k2, model=model)
    uv = np.random.default_rng(0).uniform([0, 0], [1023, 767], (500, 2))
    v = cam.unproject(uv)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
    back, front = cam.project(v)
    assert front.all()
    np.testing.assert_allclose(back, uv, atol=1e-8)
    # the law: the radius in pixels against the off-axis angle (distortion on the angle)
    th = np.arccos(v[:, 2])
    thd = th * (1 + k1 * th ** 2 + k2 * th ** 4)
    r = np.hypot(uv[:, 0] - cam.cx, uv[:, 1] - cam.cy) / cam.fx
    np.testing.assert_allclose(r, thd if model == EQUIDISTANT else 2 * np.sin(thd / 2), atol=1e-9)
    if k1 == 0.0:
        assert cam.fov_deg == pytest.approx(180.0)
        # the edge of the width is 90 deg off axis
        assert np.degrees(np.arccos(cam.unproject([[-0.5, cam.cy]])[0, 2])) == pytest.approx(90.0)


def test_an_equisolid_lens_is_equal_area_and_the_pinhole_refuses_180_degrees():
    cam = Camera.from_fov(180.0, 1024, 1024, model=EQUISOLID)
    assert cam.solid_angle_sr == pytest.approx(1024 * 1024 / cam.fx ** 2, rel=0.01)  # every pixel within r = 2
    with pytest.raises(BadInput, match="fisheye"):
        Camera.from_fov(180.0, 1024)
    with pytest.raises(BadInput):
        Camera.from_fov(360.0, 1024, model=EQUIDISTANT)
    assert Camera.from_dict(cam.to_dict()) == cam


@pytest.mark.parametrize("model,ctype", [(EQUIDISTANT, "ARC"), (EQUISOLID, "ZEA")])
def test_a_fisheye_solution_writes_the_wcs_of_its_lens(model, ctype):
    from skyview.io.wcs import solution_wcs

    R = R_from_radec_roll(np.radians(83.8), np.radians(-5.4), np.radians(30.0))
    for k1, tol in ((0.0, 1e-6), (0.02, 0.2)):
        cam = Camera.from_fov(150.0, 1024, 768, k1=k1, model=model)
        w = solution_wcs(R, cam)
        assert w.wcs.ctype[0].startswith(f"RA---{ctype}")
        uv = np.random.default_rng(1).uniform([0, 0], [1023, 767], (300, 2))
        ra, dec = np.degrees(vec_to_radec(cam.unproject(uv) @ R))
        px = np.array(w.all_world2pix(ra, dec, 0)).T
        assert np.abs(px - uv).max() < tol


def test_fit_camera_recovers_a_fisheyes_focal_length_and_distortion():
    truth = Camera.from_fov(120.0, 1280, 960, k1=0.015, model=EQUIDISTANT)
    R = R_from_radec_roll(1.0, 0.3, 0.2)
    rng = np.random.default_rng(2)
    uv = rng.uniform([0, 0], [1279, 959], (60, 2))
    xyz = truth.unproject(uv) @ R
    start = Camera.from_fov(110.0, 1280, 960, model=EQUIDISTANT)
    fit = fit_camera(uv + rng.normal(0, 0.1, uv.shape), xyz, start, R)
    assert fit.camera.model == EQUIDISTANT and "k1" in fit.fitted
    assert fit.camera.fov_deg == pytest.approx(120.0, abs=0.05) and fit.camera.k1 == pytest.approx(0.015, abs=0.002)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["fisheye120", "allsky180"])
def test_a_fisheye_sky_is_solved_blind(catalog, name):
    sc = get_scenario(name)
    cam = sc.camera()
    solver = BlindSolver(catalog=catalog, deep=False)
    for seed in range(2):
        R = random_attitudes(seed + 1, np.random.default_rng(seed))[-1]
        fr = simulate_image(catalog, cam, R, sc.sensor(), seed=seed, **sc.render_kwargs())
        res = solver.solve_array(fr.image)
        assert res.solved, res.reason
        assert res.camera.fisheye and any("fisheye" in n for n in res.notes)
        assert attitude_error_arcsec(res.R, R)["boresight"] < 0.5 * cam.pixel_scale_rad * 206265
        # the fisheye's first hypotheses are checked before the guide catalog's whole pinhole search (the
        # pinhole's first NARROW_AFTER_CHECKS, its own and a mirror image's, a batch over; its whole search checks
        # some 2,000), then the fisheye that solves
        assert [s["kind"] for s in res.searches] == ["pinhole", "fisheye"], res.searches
        assert res.searches[0]["hypotheses"] <= 3 * NARROW_AFTER_CHECKS and res.searches[1]["solved"]
        # the lens: the same pixels for the same directions as the true one, wherever the stars are
        uv = np.array([[m["u"], m["v"]] for m in res.matches])
        np.testing.assert_allclose(res.camera.project(cam.unproject(uv) @ R @ res.R.T)[0], uv, atol=0.6)


@pytest.mark.slow
def test_the_cli_solves_an_all_sky_frame_given_its_180_degrees(tmp_path, catalog, capsys):
    import cv2

    from skyview.cli import main

    sc = get_scenario("allsky180")
    R = random_attitudes(1, np.random.default_rng(5))[0]
    fr = simulate_image(catalog, sc.camera(), R, sc.sensor(), seed=5, **sc.render_kwargs())
    png = tmp_path / "allsky.png"
    cv2.imwrite(str(png), fr.image)
    assert main(["solve", str(png), "--fov-deg", "180", "--json", "--no-truth", "--wcs", str(tmp_path / "a.wcs")]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["camera"]["model"] in (EQUIDISTANT, EQUISOLID) and d["camera_fitted"]
    # within two pixels (632"/px at the centre): the lens fitted to the stars it matched
    assert attitude_error_arcsec(np.array(d["R"]), R)["boresight"] < 2 * sc.camera().pixel_scale_rad * 206265
    from astropy.io import fits

    assert fits.getheader(tmp_path / "a.wcs")["CTYPE1"][5:8] in ("ARC", "ZEA")


def test_a_paper_method_at_a_fisheyes_fov_is_one_clear_error(capsys, tmp_path):
    import cv2

    from skyview.cli import main

    png = tmp_path / "sky.png"
    cv2.imwrite(str(png), np.random.default_rng(0).integers(0, 40, (64, 64), dtype=np.uint8))
    assert main(["solve", str(png), "--fov-deg", "200", "--method", "angle"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pinhole" in err[0] and "leave out --method" in err[0]


@pytest.mark.slow
@pytest.mark.parametrize("fov, seed, given", [(88.0, 641, None), (100.0, 381, 105.0)])
def test_a_wide_rectilinear_lens_is_told_from_a_fisheye(catalog, fov, seed, given):
    """A 14 mm-class rectilinear lens (88 deg, 100 deg across 1280 x 960), wider than the pinhole search reaches,
    is found by the fisheye search, whose lens fits the stars it first matches near the centre: it was reported
    as an equidistant fisheye 106.8 deg and 112.7 deg across (the sky 3-5 deg off at the edges). The pinhole
    fitted to those stars, grown outwards (`CameraRefit.refit(grow=True)`), holds more of them: the rectilinear
    lens at its FOV, every pixel where the true camera puts it."""
    from skyview.core.camera import PINHOLE
    from skyview.simulate.render import SensorModel
    from skyview.solver.pipeline import solve_image

    cam = Camera.from_fov(fov, 1280, 960)
    R = random_attitudes(1, np.random.default_rng(seed))[0]
    fr = simulate_image(catalog, cam, R, SensorModel(), seed=seed, mag_limit=6.5, faint_extra_mag=2.5)
    res = solve_image(fr.image, fov_deg=given, deep=False)
    assert res.solved, res.reason
    assert res.camera.model == PINHOLE and res.camera.fov_deg == pytest.approx(fov, rel=2e-3)
    assert any("rectilinear" in n for n in res.notes)
    corners = np.array([[0.0, 0.0], [1279.0, 0.0], [0.0, 959.0], [1279.0, 959.0], [639.5, 479.5]])
    sky_true, sky = cam.unproject(corners) @ R, res.camera.unproject(corners) @ res.R
    assert np.degrees(np.arccos(np.clip(np.sum(sky_true * sky, axis=1), -1, 1))).max() < 0.05


# the 21 detections of a sharpened (unsharp-masked) photograph whose sky was stretched near white, most of them
# noise in its top corners: the blind fisheye search's patterns of them imply FOVs at which an equisolid lens
# cannot see the corner stars (beyond 180 deg from its axis its rays do not exist)
CORNER_DETECTIONS = np.array([
    (49.747420774219215, 301.4670930625355),
    (107.18226563781207, 63.513364417680336),
    (2.9517533392650757, 71.62772411635882),
    (806.4967885480859, 90.08073815563297),
    (693.0370397828399, 37.37937749755095),
    (803.8656402389781, 53.57385982414461),
    (15.608880391806771, 38.619204423202106),
    (60.51444795631527, 19.25731760144578),
    (957.2560082413887, 94.75735945407185),
    (3.0926179602712134, 162.11948117159773),
    (44.439796853070426, 16.47249636184801),
    (14.243946884678698, 12.369232993232483),
    (24.506712910878655, 9.55297553711659),
    (969.0615460305047, 7.664418495832319),
    (31.314476064319372, 31.293250530826228),
    (1016.8165705348335, 5.103901381216428),
    (5.6349576858518535, 22.670299346102755),
    (17.843013741754334, 15.660498954333676),
    (5.770878407805562, 12.92913782245102),
    (7.329246337680691, 73.15465313937206),
    (15.786080012714569, 4.274419933576729),
])


def test_a_fisheye_search_passes_over_stars_its_lens_cannot_see():
    """A pattern whose implied FOV puts a star past an equisolid lens's 180 deg (no ray: NaN) is no hypothesis:
    the search goes on and answers (here: nothing to find), where its attitude fit raised LinAlgError."""
    from skyview.solver.pipeline import blind_solver

    beyond = ~np.isfinite(Camera.from_fov(240.0, 1024, 768, model=EQUISOLID).unproject(CORNER_DETECTIONS)).all(axis=1)
    assert beyond.any()  # some of these stars are beyond the lens at the widest FOV searched
    ident = blind_solver().identifier.identify(CORNER_DETECTIONS, 1024, 768, fov_deg=200.0, fov_error=0.2,
                                               model=EQUISOLID)
    assert not ident.identified and ident.reason
