"""The constellation figures (skyview.present.constellations): the data as read, in the catalog's frame, and
drawn over a solved image where the photograph's stars are."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyview.core.attitude import R_from_radec_roll
from skyview.core.camera import Camera
from skyview.present.constellations import constellations, figure_polylines, image_figures
from skyview.simulate.render import SensorModel, simulate_image
from skyview.solver.pipeline import BlindSolver


def test_the_88_constellations_each_with_its_figure_and_name():
    c = constellations()
    assert len(c) == 88
    assert all(k.lines and all(len(line) >= 2 for line in k.lines) for k in c.values())
    assert c["Ori"].name == "Orion" and c["UMa"].name == "Ursa Major" and c["Cru"].name == "Crux"
    assert c["Ser"].name == "Serpens" and len(c["Ser"].lines) >= 2  # Caput and Cauda, one constellation
    for line in figure_polylines():
        assert np.allclose(np.linalg.norm(line, axis=1), 1.0)


def test_figure_vertices_are_catalog_stars_in_the_catalogs_frame(catalog):
    """The figures join stars: their vertices are (to proper motion since J2000) guide-catalog stars, so the
    data are read in the catalog's frame (RA from d3-celestial's -180..180 longitude). The exception is
    xi UMa, a close double the guide catalog leaves out."""
    bright = catalog.xyz[catalog.mag <= 6.5]
    vertices = np.concatenate(figure_polylines())
    nearest = np.empty(len(vertices))
    for k in range(0, len(vertices), 200):
        cos = np.clip(vertices[k:k + 200] @ bright.T, -1.0, 1.0).max(axis=1)
        nearest[k:k + 200] = np.degrees(np.arccos(cos))
    assert len(vertices) > 800
    assert np.mean(nearest < 0.02) > 0.99 and np.median(nearest) < 0.005
    # Betelgeuse (HIP 27989) is a vertex of Orion's figure
    betelgeuse = catalog.xyz[np.flatnonzero(catalog.hip == 27989)[0]]
    orion = np.concatenate(constellations()["Ori"].lines)
    assert np.degrees(np.arccos(np.clip(orion @ betelgeuse, -1, 1)).min()) < 0.02


def test_figures_over_a_solved_image_sit_on_its_stars(catalog):
    """A 40-degree field on Orion (with barrel distortion), solved blind: drawn through the solution's fitted
    camera, every figure vertex inside the image lands on a detected star, and the lines join them."""
    true = Camera.from_fov(40.0, 1024, 768, k1=-0.05)
    R = R_from_radec_roll(math.radians(84.0), math.radians(2.0), math.radians(15.0))
    frame = simulate_image(catalog.brighter_than(6.0), true, R, SensorModel(), seed=3, mag_limit=6.0)
    result = BlindSolver(catalog=catalog).solve_array(frame.image)
    assert result.solved
    figs = {f.abbr: f for f in image_figures(result.camera, result.R)}
    assert "Ori" in figs and figs["Ori"].name == "Orion"
    cents = result.centroids.uv
    checked = 0
    for f in figs.values():
        for line in constellations()[f.abbr].lines:
            uv, front = result.camera.project(line @ result.R.T)
            inside = front & result.camera.in_image(uv) & (uv[:, 0] > 4) & (uv[:, 1] > 4) & (
                uv[:, 0] < true.width - 5) & (uv[:, 1] < true.height - 5)
            for p in uv[inside]:
                assert np.hypot(*(cents - p).T).min() < 2.0, (f.abbr, p)
                checked += 1
        for run in f.runs:  # the drawn lines stay inside the sensor
            assert np.all((run >= -0.5) & (run <= [true.width - 0.5, true.height - 0.5]))
    assert checked >= 10
    # a figure's anchor is inside the image
    x, y = figs["Ori"].anchor
    assert 0 <= x < true.width and 0 <= y < true.height


def test_the_panel_image_draws_the_figures_and_their_names(catalog):
    from skyview.viewer.picture import FIGURE_RGB, annotate

    cam = Camera.from_fov(40.0, 1024, 768)
    R = R_from_radec_roll(math.radians(84.0), math.radians(2.0), math.radians(15.0))
    figs = image_figures(cam, R)
    base = np.zeros((384, 512), np.uint8)
    with_figs = annotate(base, (768, 1024), np.zeros((0, 2)), [], figures=figs)
    without = annotate(base, (768, 1024), np.zeros((0, 2)), [])
    assert not without.any()
    drawn = np.all(np.abs(with_figs.astype(int) - FIGURE_RGB) < 40, axis=2)
    assert drawn.sum() > 300
    # each run's midpoint (scaled to the panel) is on a drawn line
    for f in figs:
        for run in f.runs:
            mid = np.round((run[len(run) // 2] + 0.5) * 0.5 - 0.5).astype(int)
            y0, x0 = mid[1], mid[0]
            assert with_figs[max(0, y0 - 1):y0 + 2, max(0, x0 - 1):x0 + 2].any(), f.abbr


@pytest.mark.parametrize("lens", ["equidistant"])
def test_a_fisheye_sky_shows_many_figures(lens):
    """An all-sky fisheye: the figures are sampled along their great circles and bent by the lens, none
    outside the image circle's sensor."""
    cam = Camera.from_fov(180.0, 1024, 1024, model=lens)
    R = R_from_radec_roll(math.radians(90.0), math.radians(45.0), 0.0)
    figs = image_figures(cam, R)
    assert len(figs) > 20
    for f in figs:
        for run in f.runs:
            assert np.all(np.isfinite(run))
