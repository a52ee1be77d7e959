"""The typed Python API: skyview.solve -> Solution, skyview.Solver, as a user meets them."""

import dataclasses
import inspect
import json
import math
from pathlib import Path

import numpy as np
import pytest

import skyview
from skyview.solver.pipeline import SolveResult

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())
PHOTO = "2019-07-29T204726_Alt40_Azi-135_Try1.png"


def angle_between_deg(ra1, dec1, ra2, dec2) -> float:
    a1, d1, a2, d2 = map(math.radians, (ra1, dec1, ra2, dec2))
    c = math.sin(d1) * math.sin(d2) + math.cos(d1) * math.cos(d2) * math.cos(a1 - a2)
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


@pytest.fixture(scope="module")
def photo():
    return skyview.solve(REAL / PHOTO)


@pytest.fixture(scope="module")
def failed():
    return skyview.solve(np.full((128, 128), 17, np.uint8))


def test_a_real_photograph_as_attributes(photo):
    ref = REFERENCE[PHOTO]
    assert isinstance(photo, skyview.Solution)
    assert photo.status == "solved" and photo.solved and photo.reason == ""
    assert photo.method == "blind" and photo.camera_fitted
    assert angle_between_deg(photo.ra_deg, photo.dec_deg, ref["ra_deg"], ref["dec_deg"]) < 0.1
    assert abs((photo.roll_deg - ref["roll_deg"] + 180.0) % 360.0 - 180.0) < 0.1
    assert photo.fov_deg == pytest.approx(ref["fov_deg"], rel=0.005)
    assert photo.plate_scale_arcsec_per_px == pytest.approx(ref["fov_deg"] * 3600 / ref["width"], rel=0.01)
    assert photo.k1 is not None and photo.k2 is not None and photo.mag_limit is not None
    assert photo.sigma_boresight_arcsec > 0 and photo.sigma_roll_arcsec > 0 and photo.p_false < 1e-3
    assert len(photo.matches) >= 20 and photo.n_centroids >= len(photo.matches)
    m = photo.matches[0]
    assert isinstance(m, skyview.Match) and isinstance(m.hip, int) and m.residual_arcsec >= 0
    assert photo.time_ms["total"] > 0
    q = photo.quaternion
    assert q.shape == (4,) and q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
    assert isinstance(photo.result, SolveResult) and photo.result.identification is not None


def test_to_json_round_trip(photo, failed):
    for sol in (photo, failed):
        text = sol.to_json()
        assert "NaN" not in text and "Infinity" not in text
        back = json.loads(text)
        assert back == json.loads(json.dumps(sol.to_dict()))
        assert back["status"] == sol.status and back["ra_deg"] == sol.ra_deg
        assert len(back["matches"]) == len(sol.matches)
    back = json.loads(photo.to_json(indent=1))
    assert np.allclose(back["R"], photo.R) and np.allclose(back["quaternion"], photo.quaternion)
    assert back["matches"][0]["hip"] == photo.matches[0].hip


def test_skycoord_wcs_and_rotation_agree_with_R(photo):
    from skyview.core.attitude import R_from_quat

    R = photo.R
    assert np.allclose(photo.rotation().as_matrix(), R, atol=1e-12)
    assert np.allclose(R_from_quat(photo.quaternion), R, atol=1e-12)
    c = photo.skycoord()
    assert c.frame.name == "icrs"
    assert c.ra.deg == pytest.approx(photo.ra_deg) and c.dec.deg == pytest.approx(photo.dec_deg)
    b = R[2]  # the boresight in ICRS
    assert b @ np.array([math.cos(c.dec.rad) * math.cos(c.ra.rad), math.cos(c.dec.rad) * math.sin(c.ra.rad),
                         math.sin(c.dec.rad)]) == pytest.approx(1.0)
    w = photo.wcs()
    assert w.wcs.crval[0] == pytest.approx(photo.ra_deg) and w.wcs.crval[1] == pytest.approx(photo.dec_deg)
    cam = photo.camera
    px = w.all_world2pix([[photo.ra_deg, photo.dec_deg]], 0)[0]
    assert px == pytest.approx([cam.cx, cam.cy], abs=1e-6)  # CRVAL lands on the principal point
    # the catalog stars that were matched (their rows carried by the solution) land on their centroids
    # through the WCS (distortion included)
    radec = np.array([[m.ra_deg, m.dec_deg] for m in photo.matches])
    uv = np.array([[m.u, m.v] for m in photo.matches])
    err = np.linalg.norm(w.all_world2pix(radec, 0) - uv, axis=1)
    assert np.median(err) < 0.3 and err.max() < 1.0


def test_the_matches_carry_their_catalog_rows(photo):
    from skyview.core.catalog import load_guide_catalog, vec_to_radec

    cat = load_guide_catalog(epoch=photo.epoch)  # opened here only to check what the solution carries
    for m in photo.matches:
        row = cat.index_of(m.hip)
        ra, dec = np.degrees(vec_to_radec(cat.xyz[row]))
        assert (m.ra_deg, m.dec_deg) == pytest.approx((ra, dec), abs=1e-9) and m.mag == pytest.approx(cat.mag[row])
        assert m.to_dict()["ra_deg"] == m.ra_deg and m.to_dict()["hip"] == m.hip
    result = photo.result  # the SolveResult holds the catalog its identification's rows index
    assert result.catalog is not None and result.catalog.epoch == photo.epoch
    assert {m.hip for m in photo.matches} == {int(result.catalog.hip[r])
                                            for r in result.identification.matches.values()}


def test_a_failed_solution(failed):
    assert failed.status == "failed" and not failed.solved
    assert failed.reason and "no stars" in failed.reason
    assert failed.R is None and failed.quaternion is None and failed.ra_deg is None and failed.matches == ()
    for view in (failed.skycoord, failed.wcs, failed.rotation):
        with pytest.raises(skyview.NotSolvedError, match="not solved"):
            view()
    assert json.loads(failed.to_json())["R"] is None
    assert "failed" in repr(failed)


def test_a_solution_is_frozen(photo):
    with pytest.raises(dataclasses.FrozenInstanceError):
        photo.ra_deg = 0.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        photo.matches[0].hip = 1
    with pytest.raises(ValueError):
        photo.R[0, 0] = 1.0  # read-only array
    with pytest.raises(TypeError):
        photo.time_ms["total"] = 0.0


def test_solver_for_many_images(photo):
    solver = skyview.Solver(fov_deg=11.4)
    assert solver.settings["fov_deg"] == 11.4 and "Solver(" in repr(solver)
    sol = solver.solve(str(REAL / PHOTO))
    assert sol.solved and angle_between_deg(sol.ra_deg, sol.dec_deg, photo.ra_deg, photo.dec_deg) < 0.01
    with pytest.raises(skyview.BadInput, match="unknown method"):
        skyview.Solver(method="astrology")
    with pytest.raises(skyview.BadInput):
        skyview.Solver(fov_deg=200.0)
    with pytest.raises(skyview.BadInput):
        skyview.solve(REAL / PHOTO, fov_error=1.5)


def test_calibrated_method_on_a_simulated_image():
    from skyview.core.attitude import R_from_radec_roll
    from skyview.core.camera import Camera
    from skyview.core.catalog import load_guide_catalog
    from skyview.simulate.render import SensorModel, simulate_image

    camera = Camera.from_fov(8.0, 1024)
    R = R_from_radec_roll(np.radians(83.8), np.radians(-5.4), np.radians(30.0))
    frame = simulate_image(load_guide_catalog(), camera, R, SensorModel(), seed=1, mag_limit=6.0)
    sol = skyview.solve(frame.image, fov_deg=8.0, fov_error=0.0, method="angle")
    assert sol.solved and sol.method == "angle" and not sol.camera_fitted
    assert sol.ra_deg == pytest.approx(83.8, abs=0.01) and sol.roll_deg == pytest.approx(30.0, abs=0.05)
    assert sol.fov_deg == pytest.approx(8.0)


def test_the_old_call_and_the_public_surface():
    assert callable(skyview.solve_image)
    sig = inspect.signature(skyview.solve)
    assert not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.parameters.values())
    for name in ("fov_deg", "fov_error", "method", "variant", "mag_limit", "distortion", "epoch", "max_stars",
                 "k_sigma"):
        assert sig.parameters[name].kind is inspect.Parameter.KEYWORD_ONLY
    assert sig.return_annotation in ("Solution", skyview.Solution)
    for name in skyview.__all__:
        assert getattr(skyview, name) is not None
    assert (Path(skyview.__file__).parent / "py.typed").exists()
    assert skyview.solve.__doc__ and "ICRS" in inspect.getdoc(skyview.solver.api)
    res = skyview.solve_image(np.full((64, 64), 3, np.uint8))
    assert isinstance(res, SolveResult) and not res.solved
