"""Mirror images of the sky: an odd number of mirrors in the light path (a star diagonal's) or an export
flipped. Such an image has the sky's edge ratios with the wrong handedness, so no rotation fits it as read;
the blind searches check each pattern that fits the catalog's only as a mirror image as one of the image with
its rows turned over (a left-right mirror is that turned half a turn), and say so (`rows_reversed`)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from skyview.core.attitude import attitude_error_arcsec
from skyview.detect.centroids import load_image
from skyview.solver.pipeline import solve_image

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())
NAME = sorted(REFERENCE)[0]
HALF_TURN = np.diag([-1.0, -1.0, 1.0])  # the camera turned half a turn about its boresight


@pytest.fixture(scope="module")
def photo():
    return load_image(REAL / NAME)


@pytest.fixture(scope="module")
def mirrored(photo):
    """The photograph mirrored left to right, solved (the guide catalog's searches only: no deep catalog)."""
    image = np.ascontiguousarray(photo[:, ::-1])
    return image, solve_image(image, deep=False)


def test_a_left_right_mirror_image_solves_turned_over_at_the_photographs_attitude(photo, mirrored):
    image, res = mirrored
    assert res.solved and res.rows_reversed and res.method == "blind"
    assert any("mirror image" in note for note in res.notes)
    # rows turned over after a left-right mirror: the photograph turned half a turn, seen by the same camera
    ref = REFERENCE[NAME]
    err = attitude_error_arcsec(res.R, HALF_TURN @ np.array(ref["R"]))
    assert err["boresight"] < 120.0 and err["roll"] < 600.0
    assert res.camera.fov_deg == pytest.approx(ref["fov_deg"], rel=0.01)
    # the matches' pixels are the turned image's: each matched star lies where R and the camera put it
    assert len(res.matches) >= 15
    for m in res.matches:
        u, v = m["u"], m["v"]
        assert res.centroids.uv[m["index"]] == pytest.approx((u, v))
    uv = np.array([(m["u"], m["v"]) for m in res.matches])
    xyz = res.catalog.xyz[[res.catalog.index_of(m["hip"]) for m in res.matches]]
    px = np.hypot(*(res.camera.project(xyz @ res.R.T)[0] - uv).T)
    assert np.median(px) < 1.0
    # ... and in the turned image those are stars (each pixel on a blob's peak), in the image as given mostly not
    def on_blobs(img):
        img = img.astype(float)
        peaks = []
        for u, v in np.rint(uv).astype(int):
            win = img[max(v - 7, 0): v + 8, max(u - 7, 0): u + 8]
            floor = np.median(win)
            peaks.append(img[v, u] - floor > 0.5 * (win.max() - floor) and win.max() - floor > 100)
        return np.mean(peaks)

    assert on_blobs(image[::-1]) > 0.9 and on_blobs(image) < 0.3
    d = res.to_dict()
    assert d["rows_reversed"] is True and d["solved"]


def test_the_photograph_as_read_is_not_reported_reversed_and_the_mirror_can_be_left_out(photo, mirrored):
    res = solve_image(photo, deep=False)
    assert res.solved and not res.rows_reversed and res.to_dict()["rows_reversed"] is False
    not_tried = solve_image(mirrored[0], deep=False, mirror=False)
    assert not not_tried.solved and not not_tried.rows_reversed


def test_random_dots_solve_neither_way():
    """Dots at random have no sky pattern, read either way round: not solved, nothing reported turned over."""
    rng = np.random.default_rng(8)
    noise = rng.normal(100, 5, (480, 640)).astype(np.float32)
    for u, v in rng.uniform([10, 10], [630, 470], (20, 2)):
        noise[int(v) - 1:int(v) + 2, int(u) - 1:int(u) + 2] += rng.uniform(200, 2000)
    for mirror in (None, False):
        res = solve_image(noise, deep=False, mirror=mirror)
        assert not res.solved and not res.rows_reversed and res.to_dict()["rows_reversed"] is False


def test_the_api_and_the_cli_say_rows_reversed_and_the_wcs_fits_the_file_as_it_is(tmp_path, mirrored):
    import skyview

    image, res = mirrored
    path = tmp_path / "diagonal.png"
    cv2.imwrite(str(path), image)
    sol = skyview.solve(path)
    assert sol.solved and sol.rows_reversed and sol.to_dict()["rows_reversed"] is True
    assert not skyview.solve(path, mirror=False).solved
    # the WCS of the image as given maps a matched star's pixel there (its row turned back) onto the star
    w_given = sol.wcs(rows_as_given=True)
    m = sol.matches[0]
    sky = w_given.pixel_to_world(m.u, image.shape[0] - 1 - m.v)
    assert abs(sky.dec.deg - m.dec_deg) * 3600 < 60 and abs(((sky.ra.deg - m.ra_deg + 180) % 360 - 180)
                                                           * np.cos(np.radians(m.dec_deg))) * 3600 < 60
    wcs_path = tmp_path / "diagonal.wcs"
    out = subprocess.run([sys.executable, "-m", "skyview", "solve", str(path), "--json", "--no-deep",
                          "--wcs", str(wcs_path)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    assert d["solved"] and d["rows_reversed"] is True and any("mirror image" in n for n in d["notes"])
    # the WCS header is for the file's own pixels: a matched star's pixel in the file (its row turned back)
    # maps to the star's place on the sky
    from astropy.io import fits
    from astropy.wcs import WCS

    w = WCS(fits.getheader(wcs_path))
    H = image.shape[0]
    u = np.array([m["u"] for m in d["matches"]])
    v = H - 1 - np.array([m["v"] for m in d["matches"]])
    ra, dec = w.all_pix2world(u, v, 0)
    sep = np.degrees(np.arccos(np.clip(
        np.sin(np.radians(dec)) * np.sin(np.radians([m["dec_deg"] for m in d["matches"]]))
        + np.cos(np.radians(dec)) * np.cos(np.radians([m["dec_deg"] for m in d["matches"]]))
        * np.cos(np.radians(ra - np.array([m["ra_deg"] for m in d["matches"]]))), -1, 1))) * 3600
    assert np.median(sep) < 60.0
    # --no-mirror: not solved, exit 1
    out = subprocess.run([sys.executable, "-m", "skyview", "solve", str(path), "--json", "--no-deep", "--no-mirror"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 1 and json.loads(out.stdout)["rows_reversed"] is False


def test_an_image_that_is_no_mirror_image_runs_the_same_searches_either_way():
    """The mirror image's checks have a budget of their own: on images of nine random dots (no sky either way)
    the searches that run are the same with the mirror searched or not (the guide catalog's short search is
    not made to look cut short by them, which would run its whole search again), each counting its checks."""
    rng = np.random.default_rng(3)
    for _ in range(2):
        dots = rng.normal(100, 5, (480, 640)).astype(np.float32)
        for u, v in rng.uniform([10, 10], [630, 470], (9, 2)):
            dots[int(v) - 1:int(v) + 2, int(u) - 1:int(u) + 2] += rng.uniform(200, 2000)
        kinds = {}
        for mirror in (False, True):
            res = solve_image(dots, mirror=mirror)
            assert not res.solved
            kinds[mirror] = [s["kind"] for s in res.searches]
            assert all(s["hypotheses"] >= 0 for s in res.searches)
        assert kinds[True] == kinds[False]


def test_a_method_on_the_camera_a_mirror_image_fitted_reads_it_turned_over(photo):
    """`--method M` with no FOV: the blind front end finds the mirror image and fits the camera; the method then
    reads the stars of the image turned over, and says so."""
    res = solve_image(np.ascontiguousarray(photo[:, ::-1]), method="angle", variant="improved", deep=False)
    assert res.solved and res.method == "angle" and res.rows_reversed and res.camera_fitted
    err = attitude_error_arcsec(res.R, HALF_TURN @ np.array(REFERENCE[NAME]["R"]))
    assert err["boresight"] < 120.0


def test_the_viewer_run_of_a_method_on_a_mirror_image_says_rows_reversed():
    """In the viewer a method other than blind runs on the camera the blind front end fitted: on a mirror image
    that is the image turned over, and the method's result says so (JSON and notes)."""
    from skyview.viewer.run import Solvers, Source, solve

    name = sorted(REFERENCE)[2]
    image = np.ascontiguousarray(load_image(REAL / name)[:, ::-1])
    run = solve(Source(image=image, fov_deg=10.0, name="diagonal.png"), "angle", "improved", 6.0, Solvers())
    assert run.source.rows_reversed and np.array_equal(run.source.image, image[::-1])
    assert run.result.solved and run.result.rows_reversed and run.result.to_dict()["rows_reversed"] is True
    assert any("mirror image" in n for n in run.result.notes)
    err = attitude_error_arcsec(run.result.R, HALF_TURN @ np.array(REFERENCE[name]["R"]))
    assert err["boresight"] < 120.0
