"""FITS images: the standard's bottom-first rows, ROWORDER, colour and raw Bayer data, bad files."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from skyview.core.attitude import attitude_error_arcsec
from skyview.core.errors import BadInput
from skyview.detect.centroids import load_image
from skyview.io.fits import undeclared_row_order
from skyview.solver.pipeline import solve_image

fits = pytest.importorskip("astropy.io.fits")

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())
NAME = sorted(REFERENCE)[1]


@pytest.fixture(scope="module")
def photo():
    return load_image(REAL / NAME)


def _write(path, data, **header):
    hdu = fits.PrimaryHDU(data)
    for k, v in header.items():
        hdu.header[k] = v
    hdu.writeto(path)
    return path


def test_standard_fits_rows_are_read_bottom_first_and_solve(tmp_path, photo):
    # a FITS writer that follows the standard stores the picture's bottom row first
    path = _write(tmp_path / "sky.fits", np.ascontiguousarray(photo[::-1]), ROWORDER="BOTTOM-UP")
    img = load_image(path)
    assert img.dtype == np.uint16 and np.array_equal(img, photo)
    assert not undeclared_row_order(path)
    res = solve_image(path)
    assert res.solved and not res.notes
    assert attitude_error_arcsec(res.R, np.array(REFERENCE[NAME]["R"]))["boresight"] < 120.0


@pytest.mark.slow
def test_top_down_fits_declared_or_not(tmp_path, photo):
    declared = _write(tmp_path / "declared.fits", photo, ROWORDER="TOP-DOWN")
    assert np.array_equal(load_image(declared), photo)
    # not declared: read bottom-first (a mirror image), which cannot solve; the other way up is tried
    silent = _write(tmp_path / "silent.fit", photo)
    assert undeclared_row_order(silent)
    assert np.array_equal(load_image(silent), photo[::-1])
    res = solve_image(silent)
    assert res.solved and res.notes and "ROWORDER" in res.notes[0]
    assert "notes" in res.to_dict()
    import skyview

    solution = skyview.solve(silent)
    assert solution.solved and solution.notes and solution.to_dict()["notes"] == list(solution.notes)
    assert attitude_error_arcsec(res.R, np.array(REFERENCE[NAME]["R"]))["boresight"] < 120.0


def test_colour_cube_float_scaled_and_bayer_data_read_as_grey(tmp_path, photo):
    cube = np.stack([photo, photo, photo]).astype(np.float32)
    img = load_image(_write(tmp_path / "rgb.fits", cube[:, ::-1]))
    assert img.shape == photo.shape and np.allclose(img, photo)
    raw = load_image(_write(tmp_path / "raw.fits", np.ascontiguousarray(photo[::-1]), BAYERPAT="RGGB"))
    assert raw.shape == photo.shape and raw.dtype == np.uint16
    assert abs(float(np.median(raw)) - float(np.median(photo))) < 0.05 * float(np.median(photo))


@pytest.mark.parametrize("make, words", [
    (lambda p: _write(p, np.zeros((5, 64, 64), np.float32)), "data cube"),
    (lambda p: p.write_bytes(b"SIMPLE  =                    T" + b" " * 50 + b"garbage"), "FITS"),
    (lambda p: fits.HDUList([fits.PrimaryHDU()]).writeto(p), "no image"),
])
def test_bad_fits_files_are_one_line_errors(tmp_path, make, words):
    path = tmp_path / "bad.fits"
    make(path)
    with pytest.raises(BadInput, match=words):
        load_image(path)


def test_an_enormous_fits_header_is_refused_before_reading(tmp_path, monkeypatch):
    path = _write(tmp_path / "small.fits", np.zeros((64, 64), np.uint16))
    monkeypatch.setenv("SKYVIEW_MAX_PIXELS", "1000")
    with pytest.raises(BadInput, match="MP"):
        load_image(path)


@pytest.mark.slow
def test_cli_solves_a_fits_file_and_refuses_a_damaged_one(tmp_path, photo):
    good = _write(tmp_path / "sky.fits", np.ascontiguousarray(photo[::-1]))
    out = subprocess.run([sys.executable, "-m", "skyview", "solve", str(good), "--json"], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["status"] == "solved"
    bad = tmp_path / "bad.fits"
    bad.write_bytes(b"SIMPLE  =                    T" + b"\0" * 100)
    out = subprocess.run([sys.executable, "-m", "skyview", "solve", str(bad), "--json"], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "error" in json.loads(out.stdout)


@pytest.mark.slow
def test_cli_says_when_it_read_a_silent_fits_the_other_way_up(tmp_path, photo):
    silent = _write(tmp_path / "silent.fits", photo)  # top row first, and the header does not say so
    out = subprocess.run([sys.executable, "-m", "skyview", "solve", str(silent)], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert "note:" in out.stdout and "ROWORDER" in out.stdout


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::astropy.wcs.FITSFixedWarning")
def test_the_wcs_of_a_fits_file_is_for_its_own_rows(tmp_path, photo):
    """A FITS file stored bottom row first gets a WCS in its own pixel grid (DS9 overlays it)."""
    from astropy.wcs import WCS

    from skyview.core.catalog import vec_to_radec
    from skyview.detect.centroids import detect_centroids

    good = _write(tmp_path / "sky.fits", np.ascontiguousarray(photo[::-1]))
    wcs_path = tmp_path / "sky.wcs"
    out = subprocess.run([sys.executable, "-m", "skyview", "solve", str(good), "--wcs", str(wcs_path), "--json"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    w = WCS(fits.getheader(wcs_path))
    H = photo.shape[0]
    file_rows = fits.getdata(good)
    c = detect_centroids(file_rows)  # centroids in the file's own (bottom-first) rows
    # each matched star, from its catalog position through the WCS, lands on a centroid of the file's rows
    from skyview.core.catalog import load_guide_catalog

    cat = load_guide_catalog()
    rows = {int(h): i for i, h in enumerate(cat.hip)}
    d = []
    for m in res["matches"][:15]:
        ra, dec = vec_to_radec(cat.xyz[rows[m["hip"]]].astype(np.float64))
        x, y = w.all_world2pix([[np.degrees(ra), np.degrees(dec)]], 0)[0]
        d.append(np.min(np.hypot(c.uv[:, 0] - x, c.uv[:, 1] - y)))
        assert abs(y - (H - 1 - m["v"])) < 1.0  # the image's row v is the file's row H - 1 - v
    assert np.median(d) < 1.0
