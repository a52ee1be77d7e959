"""The browser viewer: steps -> geometry without a browser, the scene a session draws, bad input in the
UI, the `skyview view` command, and a real headless-Chromium load of it.

The browser test starts `skyview view` on a free local port, loads it in Debian's chromium (through the
playwright package, never `playwright install`) with software WebGL, waits until the scene has
rendered, screenshots it and checks that stars are visible, steps through the identification, uploads
an image and opens a second tab. Screenshots are kept in the test's tmp
folder and copied to test-artifacts/ (gitignored). Figures (time to first render, bytes, step update
time) are printed with -s and written to test-artifacts/viewer-figures.json.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from helpers import viewer_session

from skyview.cli import main
from skyview.core import sky_geometry as sg
from skyview.core.attitude import R_from_radec_roll, attitude_error_arcsec, random_attitudes
from skyview.core.camera import Camera
from skyview.core.catalog import load_guide_catalog, radec_to_vec
from skyview.core.errors import BadInput
from skyview.identify import IDENTIFIED, make_identifier
from skyview.identify.base import Step
from skyview.identify.genetic import tangent_basis
from skyview.identify.layers import HYPOTHESES_SAMPLE, Attitudes, Hypotheses, Population, Posterior, SearchRegion
from skyview.identify.synthetic import synthetic_frame
from skyview.present import drawables as present
from skyview.simulate.scoring import centroid_outcomes
from skyview.viewer import picture
from skyview.viewer.geometry import frustum_scale, local_grid, nearest_star, pose_wxyz, ray_to_sphere
from skyview.viewer.panel import result_markdown, status_markdown, step_markdown
from skyview.viewer.run import SceneConfig, Solvers, compare, simulate, solve
from skyview.viewer.scene import NODES
from skyview.viewer.sequence_run import SequenceConfig, solve_sequence_run

REPO = Path(__file__).resolve().parents[1]
ARTIFACTS = REPO / "test-artifacts"
CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
FIGURES: dict = {}


def _keep(path: Path) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    shutil.copy(path, ARTIFACTS / path.name)


def _save_figures() -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    f = ARTIFACTS / "viewer-figures.json"
    old = json.loads(f.read_text()) if f.exists() else {}
    f.write_text(json.dumps({**old, **FIGURES}, indent=1) + "\n")


# ============================================================================ steps -> geometry

def _tiny_catalog():
    ra = np.radians([10.0, 12.0, 11.0, 50.0, 52.0, 200.0])
    dec = np.radians([5.0, 6.0, 8.0, -20.0, -21.0, 40.0])
    return radec_to_vec(ra, dec)


def test_steps_become_arcs_patterns_and_highlights():
    xyz = _tiny_catalog()
    st = [
        Step("pick", "picked angle 0-1", observed=[0, 1], catalog=[0, 1, 3, 4], groups=[(0, 1), (3, 4)],
             numbers={"candidates": 4, "hypotheses": 4}),
        Step("pivot", "pivoted", observed=[0, 1, 2], catalog=[0, 1, 2], groups=[(0, 1, 2)],
             numbers={"candidates": 9, "hypotheses_before": 4, "hypotheses_after": 1}),
        Step("verify", "verified", observed=list(range(8)), catalog=[0, 1, 2, 99], groups=[(0, 99)],
             numbers={"p_false": 1e-40}),
    ]
    d = present.step_views(st, xyz, n_observed=6, hip=np.arange(100, 106))
    assert [x.kind for x in d] == ["pick", "pivot", "verify"]
    # without hypotheses the step's groups are drawn: a pair is one edge (ARC_POINTS - 1 segments), a triangle three
    seg0, seg1 = d[0].drawables["candidates"].segments, d[1].drawables["candidates"].segments
    assert seg0.shape == (2 * (present.ARC_POINTS - 1), 2, 3)
    assert seg1.shape == (3 * (present.ARC_POINTS - 1), 2, 3)
    np.testing.assert_allclose(np.linalg.norm(seg1, axis=2), 1.0, atol=1e-6)  # on the sphere
    ends = seg0.reshape(-1, 3).astype(np.float64)  # the arcs start and end on the catalog stars of the group
    for row in (0, 1, 3, 4):
        assert np.min(np.linalg.norm(ends - xyz[row], axis=1)) < 1e-6
    # the observed pattern: a pair, a closed triangle; 8 stars are only highlighted (and 6, 7 are not valid)
    assert d[0].pattern.tolist() == [[0, 1]]
    assert sorted(map(sorted, d[1].pattern.tolist())) == [[0, 1], [0, 2], [1, 2]]
    assert len(d[2].pattern) == 0 and d[2].observed.tolist() == [0, 1, 2, 3, 4, 5]
    # what earlier steps measured is faded, not highlighted again
    assert "known" not in d[0].drawables and "known" not in d[1].drawables  # step 1 measures 0 and 1 again
    # rows outside the catalog are dropped, not drawn
    cs = d[2].drawables["candidate_stars"].xyz
    np.testing.assert_allclose(cs, xyz[[0, 1, 2]], atol=1e-6)
    assert "candidates" not in d[2].drawables
    # the plotted series: what is left after each step, so the candidates shrink pivot by pivot
    assert present.default_plot_key(d) == "hypotheses"
    np.testing.assert_array_equal(present.series(d, "hypotheses")[:2], [4, 1])
    assert np.isnan(present.series(d, "hypotheses")[2])
    assert present.numeric_keys(d)[:2] == ["candidates", "hypotheses"]
    # only the last step is final: the identification is drawn from there on
    assert [x.final for x in d] == [False, False, True]


def test_surviving_hypotheses_thin_and_a_sample_says_how_many():
    """Hypotheses layer: the arcs drawn are the survivors' (an even sample of at most 200), and the
    text gives the total."""
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(3000, 3))
    xyz /= np.linalg.norm(xyz, axis=1, keepdims=True)
    H0 = rng.integers(0, 3000, size=(950, 2))
    H1 = H0[:47]
    H2 = np.hstack([H0[:1], [[5]]])
    st = [Step("pick", "a", observed=[0, 1], layers=(Hypotheses.sample([0, 1], H0),)),
          Step("pivot", "b", observed=[1, 2], layers=(Hypotheses.sample([0, 1], H1),)),
          Step("pivot", "c", observed=[1, 3], layers=(Hypotheses.sample([0, 1, 3], H2),))]
    d = present.step_views(st, xyz, n_observed=4)
    drawn = [len(v.drawables["candidates"].segments) // (present.ARC_POINTS - 1) for v in d]
    layer = st[0].layer(Hypotheses)
    assert layer.total == 950 and len(layer.rows) == HYPOTHESES_SAMPLE == 500
    assert drawn[0] == len(np.unique(np.sort(layer.rows, axis=1), axis=0))  # one arc per distinct candidate pair
    # step 1 measured 1-2: star 2 is not assigned yet, so its hypotheses are drawn along the stars they assign
    assert drawn[1] == len(np.unique(np.sort(H1, axis=1), axis=0)) and drawn[2] == 1  # step 2: the pair 1-3
    assert drawn[0] > drawn[1] > drawn[2]  # the arcs thin as the hypotheses fall
    assert [v.surviving for v in d] == [950, 47, 1]
    assert "950 hypotheses survive (500 drawn" in d[0].text[0]
    # the sample spreads over all the survivors, first and last included
    assert (layer.rows[0] == H0[0]).all() and (layer.rows[-1] == H0[-1]).all()
    assert d[1].drawables["known"].observed.tolist() == [0]  # measured at step 0, not at step 1: faded


def test_step_layers_become_drawables():
    xyz = _tiny_catalog()
    R = R_from_radec_roll(0.3, 0.1, 0.2)
    pop = xyz[[0, 3, 5]].astype(np.float32)
    cam = Camera.from_fov(8.0, 512)
    st = [
        Step("generation", "GA generation", numbers={"best_cost": 3.0},
             layers=(Population(pop, np.array([3.0, 1.0, 2.0], np.float32)),)),
        Step("update", "posterior", catalog=[0, 1, 2],
             layers=(Posterior(np.array([0.1, 0.7, 0.2]), np.array([0, 1, 2]), np.array([0, 1, 2]),
                               np.array([0.1, 0.7, 0.2])),)),
        Step("answer", "attitude", layers=(Attitudes.of(R, name="GA answer"),)),
    ]
    d = present.step_views(st, xyz, n_observed=5, camera=cam, hip=np.arange(100, 106))
    pts = d[0].drawables["points"]
    assert pts.xyz.shape == (3, 3)
    hi, lo = np.array(present.PALETTE["points_high"]), np.array(present.PALETTE["points"])
    np.testing.assert_array_equal(pts.colors[1], hi)  # the lowest cost brightest
    np.testing.assert_array_equal(pts.colors[0], lo)
    assert "population: 3 individuals, best cost 1" in d[0].text[0]
    cs = d[1].drawables["candidate_stars"].colors  # the leading star tinted bright
    np.testing.assert_array_equal(cs[1], np.array(present.PALETTE["candidates_high"]))
    assert "HIP 101 0.700" in d[1].text[0]
    fp = d[2].drawables["attitudes"].segments  # the attitude's sensor footprint, around its boresight
    mid = fp.reshape(-1, 3).mean(0)
    assert _angle(mid / np.linalg.norm(mid), R[2]) < np.radians(1.0)
    assert d[2].legend()[-1][0].startswith("identified")  # the last step: the identification in the legend


def test_a_posterior_over_hypotheses_lights_their_stars_summed_per_star():
    rng = np.random.default_rng(5)
    xyz = rng.normal(size=(400, 3))
    xyz /= np.linalg.norm(xyz, axis=1, keepdims=True)
    post = np.full(400, 1e-9)
    post[[7, 8]] = [0.6, 0.3]  # hypotheses 7 and 8 ...
    rows = np.arange(400, dtype=np.int32)
    rows[[7, 8]] = 42  # ... both designate star 42 now (they moved with a known turn)
    post[100] = 0.1
    layer = Posterior(post.astype(np.float32), rows, np.array([42, 100]), np.array([0.9, 0.1]))
    d = present.step_views([Step("update", "posterior", layers=(layer,))], xyz, n_observed=0)[0]
    # summed per star (0.9 on star 42), the negligible ones left dark
    np.testing.assert_allclose(d.drawables["points"].xyz, xyz[[42, 100]], atol=1e-6)
    np.testing.assert_array_equal(d.drawables["points"].colors[0], np.array(present.PALETTE["points_high"]))
    # the scorer (not the method) reads the true star's posterior from the same layer
    from skyview.simulate.scoring import true_posterior

    (mass, rank), = true_posterior([Step("update", "p", layers=(layer,))], 42)
    assert abs(mass - 0.9) < 1e-6 and rank == 0
    assert true_posterior([Step("update", "p", layers=(layer,))], 100)[0][1] == 1
    # a GA population whose costs hold inf (invalid individuals) is still tinted: the lowest cost brightest
    ga = Step("generation", "GA", layers=(Population(xyz[:4].astype(np.float32),
                                                     np.array([1.0, np.inf, 3.0, 2.0], np.float32)),))
    g = present.step_views([ga], xyz, n_observed=0)[0].drawables["points"]
    np.testing.assert_array_equal(g.colors[0], np.array(present.PALETTE["points_high"]))
    np.testing.assert_array_equal(g.colors[1], np.array(present.PALETTE["points"]))


def _angle(a, b) -> np.ndarray:
    return np.arccos(np.clip(np.asarray(a) @ np.asarray(b), -1.0, 1.0))


def test_a_square_box_and_a_roll_circle_become_closed_lines_on_the_sphere():
    # a square box: four corners at known RA/Dec, in order around it
    corners = radec_to_vec(np.radians([40.0, 44.0, 44.0, 40.0]), np.radians([10.0, 10.0, 14.0, 14.0]))
    center = radec_to_vec(np.radians(42.0), np.radians(12.0))
    st = [Step("generation", "square", layers=(SearchRegion("square", center, 0.03, corners=corners),)),
          Step("generation", "roll", layers=(SearchRegion("roll", center, 0.05, radius_rad=0.05),)),
          Step("generation", "sky", layers=(SearchRegion("sky", None, np.pi),))]
    d = present.step_views(st, _tiny_catalog(), n_observed=0)
    # the square: a closed polyline through the 4 corners, every point on the sphere and on its edge's great circle
    poly = present.region_polyline(st[0].layer(SearchRegion))
    n = sg.OUTLINE_EDGE_POINTS - 1  # segments per edge
    assert len(poly) == 4 * n + 1
    np.testing.assert_allclose(poly[::n], np.vstack([corners, corners[:1]]), atol=1e-6)  # corners, loop closed
    np.testing.assert_allclose(np.linalg.norm(poly, axis=1), 1.0, atol=1e-9)
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        edge = poly[k * n:(k + 1) * n + 1]
        np.testing.assert_allclose(edge @ np.cross(a, b), 0.0, atol=1e-7)  # on the great circle through a and b
        np.testing.assert_allclose(_angle(edge, a) + _angle(edge, b), _angle(a, b), atol=1e-7)  # between them
    seg = d[0].drawables["outline"].segments
    assert seg.shape == (4 * n, 2, 3) and seg.dtype == np.float32
    np.testing.assert_allclose(seg[1:, 0], seg[:-1, 1], atol=1e-7)  # joined end to end ...
    np.testing.assert_allclose(seg[-1, 1], seg[0, 0], atol=1e-7)  # ... and closed
    assert "search region: square" in d[0].text[0]
    # the roll circle: every point at the radius from the centre, all the way round, closed
    circ = present.region_polyline(st[1].layer(SearchRegion))
    np.testing.assert_allclose(_angle(circ, center), 0.05, atol=1e-9)
    np.testing.assert_allclose(circ[0], circ[-1])
    np.testing.assert_allclose(circ[:-1].mean(axis=0) / np.linalg.norm(circ[:-1].mean(axis=0)), center, atol=1e-9)
    assert len(d[1].drawables["outline"].segments) == sg.OUTLINE_CIRCLE_POINTS - 1
    # the whole sky: no outline, only text
    assert "outline" not in d[2].drawables and "search region: sky" in d[2].text[0]


@pytest.fixture(scope="module")
def genetic_solve():
    """The genetic method (improved variant) on a seeded synthetic 20-degree frame, as in test_genetic.py."""
    cat = load_guide_catalog().brighter_than(6.0)
    cam = Camera.from_fov(20.0, 1024)
    ga = make_identifier("genetic", cat, cam, 87e-6, variant="improved", seed=3)
    rng = np.random.default_rng(42)
    f = synthetic_frame(cat, cam, random_attitudes(1, rng)[0], 87e-6, rng)
    r = ga.identify(f.obs)
    assert r.status == IDENTIFIED, r.reason
    return ga, cat, f, r


@pytest.mark.slow
def test_a_genetic_solve_draws_its_search_box_shrinking_around_the_truth(genetic_solve):
    ga, cat, f, r = genetic_solve
    d = present.step_views(r.steps, cat.xyz, n_observed=len(f.obs.vectors))
    gens = [(s, dd) for s, dd in zip(r.steps, d) if s.kind == "generation"]
    drawn = [(s, dd) for s, dd in gens if "outline" in dd.drawables]
    assert drawn and {s.layer(SearchRegion).kind for s, _ in drawn} == {"square", "roll"}
    b_true = f.R[2]
    halves: dict[int, list[float]] = {}
    for s, dd in gens:
        box = s.layer(SearchRegion)
        pop = s.layer(Population)
        if box.kind == "sky":  # the first GA searches the whole sky: nothing to outline
            assert "outline" not in dd.drawables
        elif box.kind == "square":
            seg = dd.drawables["outline"].segments
            np.testing.assert_allclose(seg[::sg.OUTLINE_EDGE_POINTS - 1, 0][:4], box.corners, atol=1e-6)
            # the true boresight is inside the box (gnomonic offsets within the half width)
            e, n = tangent_basis(box.center)
            xi, eta = (b_true @ e, b_true @ n) / (b_true @ box.center)
            assert max(abs(xi), abs(eta)) < box.half_width_rad
            if pop is not None:  # the stage's chromosomes live in the box
                assert np.all(_angle(pop.xyz.astype(np.float64), box.center) <= np.sqrt(2) * box.half_width_rad + 1e-6)
            h = halves.setdefault(int(s.numbers["attempt"]), [])
            if not h or h[-1] != box.half_width_rad:
                h.append(box.half_width_rad)
        else:  # the roll GA: a circle where the image-up directions of its chromosomes sit
            seg = dd.drawables["outline"].segments
            np.testing.assert_allclose(_angle(seg[:, 0].astype(np.float64), box.center), box.radius_rad, atol=1e-6)
            if pop is not None:
                np.testing.assert_allclose(_angle(pop.xyz.astype(np.float64), box.center), box.radius_rad, atol=1e-5)
            # centred on the spiral stages' answer, near the truth (within the last square's half width)
            assert _angle(box.center, b_true) < halves[int(s.numbers["attempt"])][-1]
    # the spiral stages of each attempt: a box of box_factor x the previous stage's cost, shrinking on this frame
    conv = [s for s in r.steps if s.kind == "converged"]
    for att, h in halves.items():
        assert len(h) == len(ga.deltas) - 1, h
        costs = [s.numbers["best_cost"] for s in conv if s.numbers["attempt"] == att][:len(h)]
        np.testing.assert_allclose(h, [ga.box_factor * c for c in costs], rtol=1e-9)
        assert all(b <= a for a, b in zip(h, h[1:])), h
    assert any(len(h) >= 2 for h in halves.values())


def test_match_triangles_and_centroid_outcomes():
    uv = np.array([[10.0, 10.0], [100.0, 10.0], [50.0, 90.0], [200.0, 200.0], [300.0, 40.0], [5.0, 300.0]])
    tri = present.match_groups({0: 10, 1: 11, 2: 12, 3: 13}, uv)
    assert all(len(t) == 3 for t in tri) and len(tri) == 2  # a Delaunay mesh of 4 points: 2 triangles
    assert present.match_groups({0: 10, 1: 11}, uv) == [(10, 11)]
    line = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    assert present.match_groups({0: 1, 1: 2, 2: 3}, line) == [(1, 2), (2, 3)]  # collinear: a chain
    hip = np.array([500, 501, 502, 503])
    truth = {"stars": [{"hip": 500, "u": 10.0, "v": 10.0}, {"hip": 509, "u": 100.0, "v": 10.0}],
             "false_stars": [{"u": 50.0, "v": 90.0}]}
    out = centroid_outcomes(6, 5, {0: 0, 1: 1}, uv, hip, truth)
    assert out == ["identified", "wrong match", "false star", "unidentified", "unidentified", "not used"]
    assert centroid_outcomes(2, 2, {0: 0}, uv[:2], hip, None) == ["identified", "unidentified"]


def test_labels_are_placed_without_collisions_brightest_first():
    xy = np.array([[0.0, 0.0], [5.0, 0.0], [100.0, 0.0], [103.0, 3.0]])
    keep = present.place_labels(xy, priority=np.array([2.0, 1.0, 3.0, 0.5]), sizes=np.array([[40.0, 10.0]] * 4))
    assert keep.tolist() == [False, True, False, True]  # of each overlapping pair the brighter keeps its label


def test_geometry_helpers():
    cam = Camera.from_fov(8.0, 1024, 768)
    # viser normalises the frustum volume: undo it so that the far plane sits at the requested depth
    tx, ty = cam.width / (2 * cam.fx), cam.height / (2 * cam.fy)
    s = frustum_scale(cam, 1.003)
    assert np.isclose(s / np.cbrt(tx * ty / 3.0), 1.003)
    # the pose is camera -> world: the camera's +z maps to the boresight (row 2 of R)
    import viser.transforms as vtf

    R = R_from_radec_roll(1.0, -0.4, 0.5)
    np.testing.assert_allclose(vtf.SO3(pose_wxyz(R)).as_matrix() @ [0, 0, 1], R[2], atol=1e-12)
    # a ray from inside the sphere leaves it in its own direction
    np.testing.assert_allclose(ray_to_sphere([0, 0, 0], [0, 3, 4]), [0, 0.6, 0.8])
    assert ray_to_sphere([0, 0, 5], [0, 0, 1]) is None
    # the local grid stays near the boresight and labels both coordinates
    b = radec_to_vec(np.radians(83.8), np.radians(-5.4))
    segs, labels = local_grid(b, np.radians(6.0), 2.0)
    mid = segs.mean(axis=1)
    assert np.all(mid @ b / np.linalg.norm(mid, axis=1) >= np.cos(np.radians(6.0)) - 1e-9)
    texts = [t for t, _ in labels]
    assert "84°" in texts and "-6°" in texts
    segs_pole, _ = local_grid(np.array([0.0, 0.0, 1.0]), np.radians(5.0), 1.0)
    assert len(segs_pole) > 0


def test_picture_stretch_decode_and_annotate():
    rng = np.random.default_rng(0)
    img = (1000 + rng.normal(0, 10, (200, 300))).astype(np.uint16)
    img[100:103, 150:153] = 30000
    g = picture.stretch(img)
    assert g.dtype == np.uint8 and g.shape == img.shape
    assert np.median(g) < 60 and g[101, 151] == 255
    ok, png = cv2.imencode(".png", img)
    assert picture.decode_image_bytes(png.tobytes(), "x.png").shape == (200, 300)
    for bad, why in [(b"", "empty"), (b"not an image at all", "not an image"),
                     (cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes(), "too small")]:
        with pytest.raises(Exception, match=why):
            picture.decode_image_bytes(bad, "x.png")
    base = picture.panel_base(g, size=150)
    out = picture.annotate(base, img.shape, np.array([[151.0, 101.0]]), ["identified"], highlight=[0])
    assert out.shape == (100, 150, 3)
    assert (np.abs(out.astype(int) - picture.OUTCOME_RGB["identified"]).sum(axis=2) < 40).any()
    assert (np.abs(out.astype(int) - picture.HIGHLIGHT_RGB).sum(axis=2) < 40).any()
    tex = picture.texture(img)
    assert tex.shape == (200, 300, 3) and np.median(tex) == 14  # the background is flat: small JPEG
    # centroid numbers never overlap: of two stars 4 px apart the brighter (lower number) keeps its
    # number, unless the step measures the other one
    p = np.array([[50.0, 50.0], [54.0, 51.0], [120.0, 50.0]])
    assert picture.numbers_placed(p, 5, 0.4, set()).tolist() == [True, False, True]
    assert picture.numbers_placed(p, 5, 0.4, {1}).tolist() == [False, True, True]


# ============================================================================ a session, server side

@pytest.fixture(scope="module")
def session():
    with viewer_session() as (server, s):
        # the viewer opens on the default pipeline (blind); these tests follow the angle method's steps
        assert s.panel.method.value == "blind" and s.run.result.method == "blind" and s.run.result.solved
        s.panel.method.value = "angle"
        assert s.wait_idle(60) and s.run.result.method == "angle"
        yield server, s


def _node(server, key: str):
    return server.scene.get_handle_by_name(NODES[key])


def test_session_draws_sky_camera_image_centroids_and_matches(session):
    server, s = session
    assert s.error == "" and s.run is not None and s.run.result.solved
    stars = [server.scene.get_handle_by_name(f"{NODES['stars']}/bin{k}") for k in range(7)]
    n_stars = sum(len(h.points) for h in stars if h is not None)
    assert n_stars == len(s.run.catalog) > 4000
    assert all(h.points.dtype == np.float32 for h in stars if h is not None)
    for key in ("grid", "frustum", "centroids", "footprint", "true_frustum", "matches", "match_stars", "candidates"):
        assert _node(server, key) is not None, key
    frustum = _node(server, "frustum")
    assert frustum.image is not None and frustum.image.shape[2] == 3  # the sensor image on the frustum
    n_match = len(s.run.matches)
    assert n_match >= 10 and len(_node(server, "match_stars").points) == n_match
    # the side panel: the annotated sensor image, the result with error against truth and stage times
    assert s.panel.image.image.shape[2] == 3
    md = s.panel.result.content
    for word in ("Solved", "RA", "Dec", "roll", "1σ", "error vs truth", "time: centroid", "time: identify"):
        assert word in md
    FIGURES["catalog_arrays_bytes"] = s.sky.bytes_catalog
    FIGURES["catalog_stars"] = len(s.run.catalog)
    FIGURES["server_update_ms"] = round(s.timings["update_ms"], 1)
    FIGURES["server_draw_ms"] = round(s.timings["draw_ms"], 1)


def test_step_slider_changes_the_candidates(session):
    server, s = session
    n = len(s.run.drawables)
    assert n >= 3
    cand, stars = _node(server, "candidates"), _node(server, "candidate_stars")
    seen, times = [], []
    for k in range(n):
        t = time.perf_counter()
        s.panel.step.value = k  # as the slider does
        times.append((time.perf_counter() - t) * 1e3)
        assert s.step_index == k and f"Step {k + 1} / {n}" in s.panel.step_text.content
        seen.append((cand.visible, len(cand.points) if cand.visible else 0,
                     stars.points.tobytes() if stars.visible else b""))
    assert len({x[2] for x in seen}) >= 3  # the lit candidate stars change from step to step
    assert seen[0][0] and seen[0][1] > 0  # the first step draws its candidate pairs across the sky
    assert _node(server, "observed").visible  # and rings the observed stars it used
    FIGURES["server_step_update_ms_median"] = round(float(np.median(times[1:])), 2)


def test_play_runs_through_the_steps_and_pause_stops(session, monkeypatch):
    server, s = session
    monkeypatch.setattr(s.step_player, "interval_s", 0.05)
    n = len(s.run.drawables)
    s.panel.step.value = n - 1
    s.toggle_play()  # from the last step, Play starts again at the first
    assert s.panel.play.label == "Pause"
    assert s.step_player.wait(10)
    assert s.step_index == n - 1 and s.panel.play.label == "Play the steps"
    monkeypatch.setattr(s.step_player, "interval_s", 5.0)
    s.toggle_play()
    time.sleep(0.2)
    assert s.step_index == 0
    s.toggle_play()  # pause
    time.sleep(0.1)
    assert not s.step_player.playing and s.panel.play.label == "Play the steps"


def test_bad_input_in_the_ui_shows_an_error_and_the_server_keeps_running(session):
    server, s = session
    s.panel.method.value = "no-such-method"  # what a crafted message could set
    assert s.wait_idle(30) and "unknown method" in s.error and s.panel.error.visible
    s.panel.method.value = "angle"
    assert s.wait_idle(30) and s.error == "" and s.run.result.solved
    s.receive_upload("notes.png", b"this is not an image")  # as the upload button does
    assert "not an image" in s.error
    s.panel.upload_fov.value = 0.0
    ok, png = cv2.imencode(".png", s.run.source.image)
    s.receive_upload("sky.png", png.tobytes())
    assert "FOV" in s.error
    s.panel.fov.value = 0.0  # out of the slider's range, as a crafted message could send
    assert s.wait_idle(30) and "FOV" in s.error
    s.panel.fov.value = 8.0
    assert s.wait_idle(30) and s.error == ""


def test_upload_solves_the_users_image(session):
    server, s = session
    frame = simulate(SceneConfig(ra_deg=250.0, dec_deg=30.0, roll_deg=-40.0, fov_deg=12.0, resolution="1280x1024"),
                     s.solvers.base_catalog)
    ok, png = cv2.imencode(".png", frame.image)
    s.panel.upload_fov.value = 12.0
    # the improved angle method: the paper's, as printed, leaves this 12 deg field ambiguous
    s.panel.variant.value = "improved"
    assert s.wait_idle(60)
    s.receive_upload("mine.png", png.tobytes())
    assert s.wait_idle(30) and s.error == ""
    assert s.run.source.name == "mine.png" and s.run.source.truth is None and s.run.result.solved
    err = np.degrees(np.arccos(np.clip(s.run.result.R[2] @ np.asarray(frame.truth["R"])[2], -1, 1))) * 3600
    assert err < 60 and "mine.png" in s.panel.result.content and s.panel.back.visible
    # an image with no stars: not solved, no pose, no camera or fine grid drawn, no steps to play
    noise = np.random.default_rng(3).normal(500, 5, (480, 640)).astype(np.uint16)
    ok, png = cv2.imencode(".png", noise)
    s.receive_upload("dark.png", png.tobytes())
    assert s.wait_idle(30) and s.error == "" and not s.run.result.solved
    assert _node(server, "frustum") is None and _node(server, "fine_grid") is None
    assert s.panel.step.disabled and "No steps" in s.panel.step_text.content and "not solved" in s.panel.status.content
    s.use_simulation()
    assert s.wait_idle(30) and s.run.source.truth is not None and _node(server, "frustum") is not None
    s.panel.variant.value = "paper"
    assert s.wait_idle(60)


def test_fits_and_tiff_uploads_solve_and_a_raw_file_says_what_to_do(session):
    """A telescope's FITS (rows bottom-first, as the standard stores them) and a 16-bit TIFF, uploaded: each
    solves, the FITS at the attitude of its rows read top-first; a camera's raw file gets one line saying what to
    export instead. The upload's file dialog offers them."""
    import io

    from astropy.io import fits

    from skyview.viewer.panel import UPLOAD_TYPES

    server, s = session
    frame = simulate(SceneConfig(ra_deg=120.0, dec_deg=-20.0, roll_deg=15.0, fov_deg=12.0, resolution="1024x768"),
                     s.solvers.base_catalog)
    truth_z = np.asarray(frame.truth["R"])[2]
    buf = io.BytesIO()
    fits.PrimaryHDU(frame.image[::-1].astype(np.uint16)).writeto(buf)  # FITS rows: bottom first
    ok, tif = cv2.imencode(".tiff", frame.image.astype(np.uint16))
    s.panel.variant.value = "improved"  # (the paper's angle method leaves a 12 deg field ambiguous)
    assert s.wait_idle(60)
    for name, data in (("m42.fits", buf.getvalue()), ("m42.tiff", tif.tobytes())):
        s.receive_upload(name, data)
        assert s.wait_idle(60) and s.error == "", (name, s.error)
        r = s.run.result
        assert r.solved and s.run.source.name == name
        assert np.degrees(np.arccos(np.clip(r.R[2] @ truth_z, -1, 1))) * 3600 < 60, name
    s.receive_upload("IMG_0001.CR2", b"II*\x00" + bytes(4000))
    assert "camera raw file (.CR2)" in s.error and "TIFF" in s.error
    assert all(t in UPLOAD_TYPES.split(",") for t in ("image/tiff", ".fits", ".fit", ".tif"))
    s.use_simulation()
    assert s.wait_idle(30) and s.error == ""
    s.panel.variant.value = "paper"
    assert s.wait_idle(60)


def test_clicking_a_star_names_it(session):
    server, s = session
    row = s.run.catalog.index_of(26311)  # Alnilam, in the default field
    s.click_sky((0.0, 0.0, 0.0), tuple(s.run.catalog.xyz[row] * 3.0))  # a click's ray, as the scene reports it
    assert "HIP 26311" in s.panel.picked.content and "Alnilam" in s.panel.picked.content
    assert _node(server, "pick") is not None


def test_labels_in_the_field_never_overlap_and_all_show_when_zoomed_in(session):
    """Centroid numbers and the fine grid's degrees give way to the star names and to each other (the
    brighter star's number first); zoomed in on the field, every one of them shows."""
    server, s = session
    run = s.run
    n = min(len(run.result.centroids), 40)
    labels = lambda key, k: [server.scene.get_handle_by_name(f"{NODES[key]}/{i}") for i in range(k)]  # noqa: E731
    try:
        for zoom, everything in ((0.02, True), (0.3, False)):  # zoom 0.3: the 8-degree field fills the view
            s.sky.set_zoom(zoom)
            nums = labels("numbers", n)
            shown = [i for i, h in enumerate(nums) if h.visible]
            if everything:
                grid = labels("fine_labels", len(s.sky.h["fine_labels"]))
                # every number; every degree but one of the two at the crossing of the labelled RA and Dec lines
                assert len(shown) == n and sum(h.visible for h in grid) == len(grid) - 1
                continue
            assert 0 in shown and 0 < len(shown) < n  # the brightest keeps its number, crowded ones give way
            # no two numbers shown overlap on screen (as Chromium draws them: 4.5 px a character and 3 px of
            # padding, 10 px high, beside the ring)
            per_px = 2.0 * np.tan(np.radians(30.0)) * zoom ** (1 / 0.85) / 860.0
            pos = {i: np.asarray(nums[i].position[:2], dtype=np.float64) / per_px for i in shown}
            for a in shown:
                for b in shown:
                    if a < b:
                        wa, wb = 4.5 * len(str(a)) + 3.0, 4.5 * len(str(b)) + 3.0
                        dx, dy = pos[b][0] - pos[a][0], pos[b][1] - pos[a][1]
                        assert dx >= wa or -dx >= wb or abs(dy) >= 10.0, (a, b, dx, dy)
    finally:
        s.sky.set_zoom(1.0)


@pytest.mark.slow
def test_the_page_stays_responsive_while_a_slow_method_runs(session, monkeypatch):
    import skyview.viewer.session as session_mod

    server, s = session
    real = session_mod.solve

    def slow(*args, **kwargs):
        time.sleep(1.5)
        return real(*args, **kwargs)

    monkeypatch.setattr(session_mod, "solve", slow)
    s.request_solve()
    time.sleep(0.8)
    assert s.panel.progress.visible and "⏳" in s.panel.status.content  # progress is shown
    t = time.perf_counter()
    s.panel.step.value = 0  # the controls still answer at once
    assert (time.perf_counter() - t) < 0.5 and s.step_index == 0
    assert s.wait_idle(30) and s.error == ""
    time.sleep(0.5)
    assert not s.panel.progress.visible


def test_compare_and_export(session, tmp_path):
    pytest.importorskip("skyview.record.recording")
    server, s = session
    s.request_compare(methods=["angle"])
    assert s.wait_idle(60)
    assert [(r["method"], r["variant"]) for r in s.compare_rows] == [("angle", "paper"), ("angle", "improved")]
    assert "| angle | improved | solved |" in s.panel.compare_table.content
    rrd = s.export_rrd(tmp_path / "run.rrd")
    assert rrd.stat().st_size > 10_000 and rrd.read_bytes()[:4] == b"RRF2"
    # another image on screen: the table of the former one leaves the Result tab
    s.panel.seed.value = int(s.panel.seed.value) + 1
    assert s.wait_idle(60)
    assert s.compare_rows == [] and s.panel.compare_table.content == ""
    s.panel.seed.value = int(s.panel.seed.value) - 1
    assert s.wait_idle(60)


ORION_30 = SceneConfig(ra_deg=83.8, dec_deg=-5.4, roll_deg=30.0, fov_deg=30.0, resolution="1024x1024", mag_limit=4.5,
                       noise_arcsec=10.0)  # the stochastic paper's camera and field, 10 arcsec of noise


@pytest.mark.parametrize("variant, turn", [("paper", "along RA"), ("improved", "pan about camera y")])
def test_a_stochastic_sequence_identifies_orion_with_known_truth(variant, turn):
    solvers = Solvers()
    seq = solve_sequence_run(ORION_30, SequenceConfig(n_frames=5, turn=turn, step_deg=10.0), "stochastic", variant,
                             solvers)
    res = seq.result
    assert len(seq) == len(res.identifications) == 5
    assert seq.frame == 4 and seq.identified[-1] == 4  # identified by the last frame
    if variant == "improved":
        assert seq.identified[0] <= 2  # the geometric check decides within a few frames
    for k in seq.identified:
        run = seq.frames[k]
        assert run.result.solved and run.wrong_matches == 0 and len(run.matches) >= 5
        assert run.error_arcsec["total"] < 60.0 and res.frame_dict(k)["wrong_matches"] == 0
        # the frame's SolveResult (from the pipeline's code) agrees with the sequence's own attitude
        assert attitude_error_arcsec(run.result.R, res.identifications[k].R)["total"] < 5.0
    for k in set(range(5)) - set(seq.identified):  # not identified: drawn at the truth
        assert not seq.frames[k].result.solved and np.allclose(seq.frames[k].R_shown, seq.frames[k].R_true)
    # the truth: the frames follow the known turn from the scene's attitude
    turn_obj = SequenceConfig(turn=turn).turn_per_frame()
    R = ORION_30.R
    for f in seq.frames:
        assert attitude_error_arcsec(f.R_true, R)["total"] < 1e-3
        R = turn_obj.apply(R)
    # the series the panel plots are the SequenceResult's per-frame stats
    ser = seq.series()
    for k in range(5):
        fd = res.frame_dict(k)
        for key in ("above_prior", "top_posterior", "true_posterior"):
            assert ser[key][k] == fd[key], (key, k)
    assert ser["above_prior"][0] > 50 and ser["above_prior"][-1] <= 5  # the hypotheses narrow frame by frame
    assert ser["true_posterior"][-1] > 0.95
    # every frame's steps are drawn from that frame's record
    for k, f in enumerate(seq.frames):
        assert [d.kind for d in f.drawables] == [st.kind for st in res.identifications[k].steps]
    upd = [d for d in seq.frames[0].drawables if d.kind == "update"][0]
    cs = upd.drawables["candidate_stars"]  # the leading stars, tinted by posterior
    assert len(cs.xyz) == 10 and len(np.unique(cs.colors, axis=0)) > 2
    assert len(upd.drawables["points"].xyz) > 50  # the posterior over the sky


def test_sequence_settings_are_checked():
    for bad, what in [(SequenceConfig(n_frames=0), "frames"), (SequenceConfig(n_frames=2.5), "whole"),
                      (SequenceConfig(turn="sideways"), "unknown turn"), (SequenceConfig(step_deg=-1), "turn step"),
                      (SequenceConfig(step_deg=float("nan")), "turn step")]:
        with pytest.raises(Exception, match=what):
            bad.checked()
    with pytest.raises(Exception, match="single images"):
        solve_sequence_run(ORION_30, SequenceConfig(), "angle", "paper", Solvers())


def test_compare_says_a_sequence_method_needs_a_sequence():
    from skyview.viewer.panel import compare_markdown

    solvers = Solvers()
    src = simulate(ORION_30, solvers.base_catalog)
    rows = compare(src, 4.5, solvers, methods=["stochastic"])
    paper = rows[0]
    assert paper["status"] == "failed" and paper["needs_sequence"] and "sequence of frames" in paper["reason"]
    assert "needs a sequence" in compare_markdown(rows, src.name)


def _set_quietly(s, **values):
    """Set panel controls without a solve per control (as `Session.randomise` does)."""
    with s.quietly():
        for name, v in values.items():
            getattr(s.panel, name).value = v


@pytest.mark.slow
def test_session_shows_a_stochastic_sequence_frame_by_frame(session, monkeypatch):
    server, s = session
    p = s.panel
    assert not p.seq_controls.visible and not p.seq_box.visible  # the default method runs single images
    _set_quietly(s, fov=30.0, resolution="1024x1024", mag=4.5, noise=10.0, variant="improved", n_frames=5,
                 turn="pan about camera y", turn_step=10.0)
    p.method.value = "stochastic"
    assert s.wait_idle(60) and s.error == "", s.error
    seq = s.seq
    assert seq is not None and len(seq) == 5 and p.seq_controls.visible and p.seq_box.visible
    assert s.frame_index == 4 and s.run is seq.frames[4] and p.frame.value == 4 and p.frame.max == 4
    assert not p.frame.disabled and _node(server, "track") is not None  # every frame's footprint
    # the result text: which frame was identified, the error against the truth
    first, err = seq.identified[0], seq.frames[4].error_arcsec["total"]
    assert "identified" in p.status.content and f"at frame {first}" in p.status.content
    assert f"identified at frame {first}" in p.result.content and "error vs truth" in p.result.content
    assert "Frame 4" in p.frame_text.content and "identified" in p.frame_text.content and err < 60
    # the plot across frames is the SequenceResult's per-frame stats, the shown frame marked
    x, above, top, true, now = p.frame_plot.data
    assert p.frame_plot.visible
    assert x.tolist() == [0, 1, 2, 3, 4]
    for k in range(5):
        fd = seq.result.frame_dict(k)
        assert (above[k], top[k], true[k]) == (fd["above_prior"], fd["top_posterior"], fd["true_posterior"])
    assert now[4] == top[4] and np.isnan(now[:4]).all()
    # the camera at frame 4's estimate; frame 0 (not identified) shows its own image at the truth
    cam, frustum = _node(server, "camera"), _node(server, "frustum")
    wxyz4, tex4, uv4 = cam.wxyz.copy(), frustum.image.copy(), s.run.result.centroids.uv.copy()
    assert abs(float(np.dot(wxyz4, pose_wxyz(seq.frames[4].result.R)))) > 1 - 1e-9
    p.frame.value = 0  # as the slider does
    assert s.frame_index == 0 and s.run is seq.frames[0] and not s.run.result.solved
    cam, frustum = _node(server, "camera"), _node(server, "frustum")
    assert abs(float(np.dot(cam.wxyz, pose_wxyz(seq.frames[0].R_true)))) > 1 - 1e-9
    assert abs(float(np.dot(cam.wxyz, wxyz4))) < 0.999  # turned by 40 degrees
    assert not np.array_equal(frustum.image, tex4)  # that frame's sensor image ...
    uv0 = s.run.result.centroids.uv
    assert len(uv0) != len(uv4) or not np.allclose(uv0, uv4)  # ... and its centroids
    assert "Frame 0" in p.frame_text.content and "not identified" in p.frame_text.content
    assert np.isnan(p.frame_plot.data[4][1:]).all() and p.frame_plot.data[4][0] == top[0]
    # that frame's steps in the Steps tab; its update lights the leading hypotheses, tinted by posterior
    kinds = [d.kind for d in s.run.drawables]
    assert kinds == [st.kind for st in seq.result.identifications[0].steps] and p.step.max == max(1, len(kinds) - 1)
    p.step.value = kinds.index("update")
    stars, pts = _node(server, "candidate_stars"), _node(server, "points")
    assert stars.visible and len(stars.points) == 10 and len(np.unique(stars.colors, axis=0)) > 2
    assert pts.visible and len(pts.points) > 50 and len(np.unique(pts.colors, axis=0)) > 5
    # a crafted frame number is an error in the panel, the session keeps its sequence
    p.frame.value = 99
    assert "outside 0..4" in s.error and s.seq is seq and s.frame_index == 0 and p.frame.value == 0
    # Play runs through the frames to the last
    monkeypatch.setattr(s.frame_player, "interval_s", 0.05)
    s.toggle_play_frames()
    assert s.frame_player.wait(20)
    assert s.frame_index == 4 and p.play_frames.label == "Play the frames"
    # back to a single-image method: no frames, no track; the default scene again
    _set_quietly(s, fov=8.0, mag=6.0, noise=0.0, variant="paper")
    p.method.value = "angle"
    assert s.wait_idle(60) and s.error == "" and s.seq is None and s.run.result.solved
    assert not p.seq_box.visible and not p.seq_controls.visible and _node(server, "track") is None
    assert not p.frame_plot.visible


def test_compare_covers_every_method_by_default():
    from skyview.identify import METHODS

    calls = []

    class Fake:
        base_catalog = None

    def fake_solve(source, m, v, mag, solvers):
        calls.append((m, v))
        raise RuntimeError("boom") if m == "angle" else ValueError("x")

    import skyview.viewer.run as run_mod

    orig = run_mod.solve
    run_mod.solve = fake_solve
    try:
        rows = compare(SimpleNamespace(name="img"), 6.0, Fake())
    finally:
        run_mod.solve = orig
    # the default pipeline (one variant) first, then every method in both variants
    assert calls[0] == ("blind", "improved") and [c[0] for c in calls[1:]][::2] == list(METHODS)
    assert all(r["status"] == "error" for r in rows)
    assert "RuntimeError: boom" in next(r for r in rows if r["method"] == "angle")["reason"]


def test_result_and_step_text_for_a_failure():
    solvers = Solvers()
    src = simulate(SceneConfig(ra_deg=10.0, dec_deg=80.0, fov_deg=2.0, mag_limit=4.0), solvers.base_catalog)
    run = solve(src, "angle", "paper", 4.0, solvers)
    assert not run.result.solved
    md = result_markdown(run)
    assert "Not solved" in md and "**Why:**" in md and "the solver's own words" in md
    assert run.result.reason.split(":")[0] in md
    text = step_markdown(run, run.drawables[0] if run.drawables else None)
    assert text


def test_nearest_star_picks_within_tolerance():
    solvers = Solvers()
    cat = solvers.base_catalog.brighter_than(6.0)
    row = cat.index_of(27989)  # Betelgeuse
    assert nearest_star(cat, cat.xyz[row], np.radians(0.1)) == row
    off = radec_to_vec(np.radians(88.79 + 5), np.radians(7.41 + 5))
    assert nearest_star(cat, off, np.radians(0.01)) is None


# ============================================================================ the command

def test_view_bad_arguments_exit_2(tmp_path, capsys):
    junk = tmp_path / "junk.png"
    junk.write_text("not an image")
    assert main(["view", "--image", str(junk), "--fov-deg", "12"]) == 2
    assert main(["view", "--image", str(tmp_path / "missing.png"), "--fov-deg", "12"]) == 2
    assert main(["view", "--fov-deg", "0"]) == 2
    assert main(["view", "--image", str(junk)]) == 2
    assert main(["view", "--port", "70000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 5 and all(line.startswith("skyview: error: ") for line in err)


def _start_view(*args) -> tuple[subprocess.Popen, str]:
    from skyview.solver.pipeline import blind_solver

    blind_solver()  # the viewer opens on the blind pipeline: its database built into the test cache first
    exe = Path(sys.executable).with_name("skyview")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "skyview"]
    p = subprocess.Popen(cmd + ["view", "--port", "0", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    line = p.stdout.readline()
    assert line.startswith("skyview viewer: http://127.0.0.1:"), (line, p.stderr.read() if p.poll() else "")
    return p, line.split()[2]


def _stop_view(p: subprocess.Popen) -> None:
    p.send_signal(signal.SIGINT)
    try:
        out, err = p.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        p.kill()  # do not leave a server behind
        p.communicate()
        raise
    assert p.returncode == 0, err
    assert "stopped" in out


def test_two_stop_signals_at_once_stop_the_viewer_once_without_a_traceback():
    """`kill` through a wrapper (timeout, a supervisor) delivers SIGTERM twice; a user presses Ctrl-C twice. A
    signal the kernel hands to one of viser's threads is answered too (the main thread naps WAKE_S at most)."""
    p, _url = _start_view()
    for sig in (signal.SIGTERM, signal.SIGTERM, signal.SIGINT):  # the kernel may hand each to any thread
        p.send_signal(sig)
    try:
        out, err = p.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        p.kill()
        p.communicate()
        raise
    assert p.returncode == 0 and "Traceback" not in err, err
    assert "stopped" in out


# ============================================================================ the browser

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
JS_HAS = "(n) => !!(window.__viserMutable?.nodeRefFromName?.[n])"
JS_RENDER = "() => window.__viserTestpoints?.rendererInfo?.render ?? null"
# (count, checksum) of what a node draws: its segments or points, and the sum of their coordinates
JS_GEOMETRY = """(n) => { const o = window.__viserMutable?.nodeRefFromName?.[n]; if (!o || !o.visible) return [0, 0];
  let c = 0, sum = 0; o.traverse(x => { const g = x.geometry?.attributes; if (!g) return;
    const a = g.instanceStart ?? g.position; c += a.count;
    const arr = a.data ? a.data.array : a.array; for (let i = 0; i < arr.length; i++) sum += arr[i]; });
  return [c, Math.round(sum * 1e4) / 1e4]; }"""


def _settle(pg, timeout_s: float = 30.0, quiet_s: float = 0.5) -> None:
    """The scene has rendered and the render-on-demand loop has gone quiet (fade-in done)."""
    pg.wait_for_function("() => (window.__viserTestpoints?.rendererInfo?.render?.points ?? 0) > 0",
                         timeout=timeout_s * 1000)
    end, last, since = time.monotonic() + timeout_s, -1, time.monotonic()
    while time.monotonic() < end:
        frame = pg.evaluate(JS_RENDER)["frame"]
        if frame != last:
            last, since = frame, time.monotonic()
        elif time.monotonic() - since > quiet_s:
            return
        pg.wait_for_timeout(50)
    raise TimeoutError("the render loop never settled")


def _chromium(playwright, tmp_path: Path):
    """Headless Chromium whose own files (dconf, caches) go to the test's folder, not the user's home."""
    home = tmp_path / "browser-home"
    home.mkdir(exist_ok=True)
    env = {**os.environ, "HOME": str(home), "XDG_CACHE_HOME": str(home / ".cache"),
           "XDG_CONFIG_HOME": str(home / ".config")}
    return playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS, env=env)


def _open(browser, url: str, nbytes: list | None = None):
    pg = browser.new_page(viewport={"width": 1400, "height": 860})
    external = []
    pg.on("request", lambda r: None if r.url.startswith(("http://127.0.0.1", "ws://127.0.0.1", "data:", "blob:"))
          else external.append(r.url))
    if nbytes is not None:
        pg.on("websocket", lambda ws: ws.on("framereceived", lambda d: nbytes.append(len(d))))
    t = time.perf_counter()
    pg.goto(url)
    pg.wait_for_function(JS_HAS, arg=NODES["frustum"], timeout=45000)
    pg.wait_for_function(JS_HAS, arg=f"{NODES['stars']}/bin3", timeout=45000)
    _settle(pg)
    pg.first_render_s = time.perf_counter() - t
    pg.external = external
    pg.add_style_tag(content=".mantine-Notifications-root{display:none!important}")
    return pg


def _control(pg, label: str):
    """The row of a labelled panel control."""
    return pg.locator("label", has_text=label).first.locator("xpath=ancestor::div[contains(@class,'Flex-root')][1]")


def _choose(pg, label: str, option: str) -> None:
    """Pick an option of a dropdown, as a user does."""
    _control(pg, label).locator("input").first.click()
    pg.get_by_role("option", name=option, exact=True).click()


def _type(pg, label: str, value) -> None:
    """Type a value into a slider's or number's box and press Enter."""
    box = _control(pg, label).locator("input:not([type='hidden'])").last
    box.fill(str(value))
    box.press("Enter")


JS_PANEL_TOP = ("() => document.querySelectorAll('*').forEach(e => { if (e.scrollHeight > e.clientHeight + 4) "
                "e.scrollTop = 0; })")  # the panel scrolled back to its top
JS_UPLOTS = "() => Object.values(window.__viserTestpoints?.uplots ?? {}).map(p => p.chart.data.length)"


# the largest distance between two points a node draws (its diameter; 0 when hidden)
JS_DIAMETER = """(n) => { const o = window.__viserMutable?.nodeRefFromName?.[n]; if (!o || !o.visible) return 0;
  const p = []; o.traverse(x => { const g = x.geometry?.attributes; if (!g) return;
    const a = g.instanceStart ?? g.position; const arr = a.data ? a.data.array : a.array;
    for (let i = 0; i + 2 < arr.length; i += 3) p.push([arr[i], arr[i + 1], arr[i + 2]]); });
  let d = 0; for (const a of p) for (const b of p) d = Math.max(d, Math.hypot(a[0] - b[0], a[1] - b[1], a[2] - b[2]));
  return d; }"""
# A genetic solve whose search box shrinks plainly (2.5 deg, then 0.6 deg half widths), near Sirius
GA_SCENE = {"FOV (deg)": 20.0, "RA (deg)": 107.9, "Dec (deg)": -8.9, "Roll (deg)": -170.0}


def _ga_box_steps() -> tuple[dict[int, tuple[str, float]], int]:
    """Step index -> (stage name, half width or radius) of the last generation of every boxed GA stage of
    the GA_SCENE solve (the server's solve is seeded: the same steps), and the number of steps."""
    cfg = SceneConfig(ra_deg=107.9, dec_deg=-8.9, roll_deg=-170.0, fov_deg=20.0)
    sv = Solvers()
    run = solve(simulate(cfg, sv.base_catalog), "genetic", "improved", cfg.mag_limit, sv)
    per_attempt: dict[int, dict[str, tuple[int, float]]] = {}
    for k, st in enumerate(run.result.identification.steps):
        box = st.layer(SearchRegion)
        if st.kind == "generation" and box.kind != "sky":
            name = "roll" if box.kind == "roll" else f"stage{int(st.numbers['stage'])}"
            per_attempt.setdefault(int(st.numbers["attempt"]), {})[name] = (k, box.half_width_rad)
    # the first attempt that went through every stage: two spiral squares and the roll circle
    last = next(v for _, v in sorted(per_attempt.items()) if len(v) >= 3)
    return {k: (name, h) for name, (k, h) in last.items()}, len(run.result.identification.steps)


def _montage(shots: list[Path], out: Path, captions: list[str]) -> None:
    """The 3-D views of the screenshots side by side (the middle of each, a caption on top)."""
    tiles = []
    for shot, cap in zip(shots, captions):
        img = cv2.imread(str(shot))[:, :1000]
        h, w = img.shape[:2]
        tile = np.ascontiguousarray(img[h // 2 - 330:h // 2 + 330, w // 2 - 330:w // 2 + 330])
        tile[:48] = (tile[:48] * 0.3).astype(np.uint8)  # a dark band under the caption
        cv2.putText(tile, cap, (14, 33), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (235, 235, 235), 2, cv2.LINE_AA)
        tile[:, -2:] = 90  # a thin divider
        tiles.append(tile)
    cv2.imwrite(str(out), np.concatenate(tiles, axis=1))


def _not_blank(png: Path, panel_from_x: int) -> float:
    gray = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)[:, :panel_from_x]
    return float((gray > 110).mean())


@pytest.mark.browser
@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"no chromium at {CHROMIUM} (apt-get install chromium)")
def test_browser_renders_the_viewer_and_steps_through(tmp_path):
    pw = pytest.importorskip("playwright.sync_api")
    proc, url = _start_view()
    try:
        with pw.sync_playwright() as p:
            browser = _chromium(p, tmp_path)
            try:
                frames: list[int] = []
                pg = _open(browser, url, frames)
                FIGURES["first_render_s"] = round(pg.first_render_s, 2)
                FIGURES["first_load_websocket_bytes"] = int(sum(frames))
                shot = tmp_path / "viewer-boresight.png"
                pg.screenshot(path=str(shot))
                _keep(shot)
                assert _not_blank(shot, 1000) > 0.002, "the 3-D view looks blank"
                assert pg.evaluate(JS_RENDER)["points"] > 4000  # the catalog went through a draw call
                for key in ("grid", "frustum", "centroids", "matches", "footprint"):
                    assert pg.evaluate(JS_HAS, NODES[key]), key
                pg.get_by_text("solved", exact=False).first.wait_for(timeout=10000)

                # the step slider, driven like a user: type a step into its number box
                row = pg.locator("label", has_text="Step").first.locator(
                    "xpath=ancestor::div[contains(@class,'Flex-root')][1]")
                box = row.locator("input:not([type='hidden'])").last
                counts = []
                for k in (0, 1):
                    t = time.perf_counter()
                    box.fill(str(k))
                    box.press("Enter")
                    pg.get_by_text(f"Step {k + 1} / ", exact=False).first.wait_for(timeout=10000)
                    FIGURES[f"step_{k}_round_trip_ms"] = round((time.perf_counter() - t) * 1e3)
                    pg.wait_for_timeout(300)
                    counts.append(tuple(pg.evaluate(JS_GEOMETRY, NODES[role])
                                        for role in ("candidates", "candidate_stars", "points")))
                # the blind look-up's hits on the sky at step 0, fewer (other ones) at step 1
                assert counts[0][2][0] > counts[1][2][0] > 0 and counts[0] != counts[1], counts
                # the wide view: candidates light up across the sky
                pg.get_by_role("tab", name="View").click()
                pg.get_by_role("button", name="Wide sky").click()
                box_tab = pg.get_by_role("tab", name="Steps")
                box_tab.click()
                box.fill("0")
                box.press("Enter")
                pg.wait_for_timeout(800)
                _settle(pg)
                wide = tmp_path / "viewer-wide-step1.png"
                pg.screenshot(path=str(wide))
                _keep(wide)
                assert _not_blank(wide, 1000) > 0.002

                # upload an image through the page, with its FOV, and solve it
                frame = simulate(SceneConfig(ra_deg=250.0, dec_deg=30.0, roll_deg=-40.0, fov_deg=12.0,
                                             resolution="1280x1024"), Solvers().base_catalog)
                png = tmp_path / "mine.png"
                cv2.imwrite(str(png), frame.image)
                pg.get_by_role("tab", name="Scenario").click()
                fov_box = pg.locator("label", has_text="FOV hint").first.locator(
                    "xpath=ancestor::div[contains(@class,'Flex-root')][1]").locator("input").first
                fov_box.fill("12")
                fov_box.press("Enter")
                pg.wait_for_timeout(300)
                t = time.perf_counter()
                pg.locator("input[type=file]").first.set_input_files(str(png))
                pg.get_by_role("tab", name="Result").click()
                # the upload's camera is fitted to its stars (blind), whatever FOV was typed
                pg.get_by_text("image: mine.png, FOV", exact=False).first.wait_for(timeout=30000)
                pg.get_by_text("fitted to the stars", exact=False).first.wait_for(timeout=10000)
                FIGURES["upload_to_result_s"] = round(time.perf_counter() - t, 2)
                pg.get_by_text("Solved by", exact=False).first.wait_for(timeout=10000)

                # a second tab gets its own session and renders too
                pg2 = _open(browser, url)
                shot2 = tmp_path / "viewer-second-tab.png"
                pg2.screenshot(path=str(shot2))
                _keep(shot2)
                assert _not_blank(shot2, 1000) > 0.002

                # the genetic method (20 deg, near Sirius): its population on the sphere (the (N, 3) extra of its
                # steps), tinted by cost, and its search box (the dict extra with corners / centre + radius)
                pg2.set_viewport_size({"width": 1400, "height": 1000})
                pg2.get_by_role("tab", name="Scenario").click()
                pg2.get_by_role("checkbox", name="Solve on every change").uncheck()
                for label, value in GA_SCENE.items():
                    _type(pg2, label, value)
                    pg2.wait_for_timeout(200)
                _choose(pg2, "Variant", "improved")
                _choose(pg2, "Method", "genetic")
                box_steps, n_steps = _ga_box_steps()
                pg2.get_by_role("button", name="Solve", exact=True).click()
                pg2.get_by_text("solved by genetic (improved): RA 107.900° Dec -8.900°", exact=False).first.wait_for(
                    timeout=60000)
                pg2.get_by_role("tab", name="View").click()
                pg2.get_by_role("button", name="Wide sky").click()
                pg2.get_by_role("tab", name="Steps").click()
                _type(pg2, "Step", 0)  # the first generation: a population over the whole sky, tinted by cost
                pg2.get_by_text(f"Step 1 / {n_steps} ", exact=False).first.wait_for(timeout=10000)  # the same solve
                pg2.get_by_text("population: ", exact=False).first.wait_for(timeout=10000)  # its best cost in words
                pg2.wait_for_timeout(500)
                population = pg2.evaluate(JS_GEOMETRY, NODES["points"])
                assert population[0] > 10, "no GA population drawn on the sphere"
                assert pg2.evaluate(JS_DIAMETER, NODES["outline"]) == 0  # the whole sky: no box
                pg2.evaluate(JS_PANEL_TOP)
                pg2.mouse.move(5, 5)
                _settle(pg2)
                ga = tmp_path / "viewer-genetic-population.png"
                pg2.screenshot(path=str(ga))
                _keep(ga)
                FIGURES["genetic_population_points"] = population[0]
                # down the boresight: the last generation of each spiral stage (a square) and of the roll GA
                # (a circle), the box shrinking around the population
                pg2.get_by_role("tab", name="View").click()
                pg2.get_by_role("button", name="Look down the boresight").click()
                pg2.get_by_role("checkbox", name="Matched triangles").uncheck()  # the box alone over the image
                pg2.get_by_role("tab", name="Steps").click()
                extents, shots = [], []
                for k, (stage, half) in box_steps.items():
                    _type(pg2, "Step", k)
                    pg2.get_by_text(f"Step {k + 1} / ", exact=False).first.wait_for(timeout=10000)
                    pg2.get_by_text("search region:", exact=False).first.wait_for(timeout=10000)
                    pg2.wait_for_timeout(500)
                    extents.append((stage, half, pg2.evaluate(JS_DIAMETER, NODES["outline"])))
                    pg2.evaluate(JS_PANEL_TOP)
                    pg2.mouse.move(5, 5)
                    _settle(pg2)
                    shot = tmp_path / f"viewer-genetic-box-{stage}.png"
                    pg2.screenshot(path=str(shot))
                    shots.append(shot)
                FIGURES["genetic_box_diameter"] = {st: round(x, 4) for st, _, x in extents}
                # what the page draws: a square of half width h (gnomonic) spans 2 sin(atan(sqrt(2) h)) corner to
                # corner, the roll circle of radius r 2 sin(r)
                for st, h, x in extents:
                    want = 2 * np.sin(h) if st == "roll" else 2 * np.sin(np.arctan(np.sqrt(2) * h))
                    assert x == pytest.approx(want, rel=2e-3), extents
                squares = [x for st, _, x in extents if st != "roll"]
                assert len(squares) >= 2 and all(b < a for a, b in zip(squares, squares[1:])), extents  # shrinking
                montage = tmp_path / "viewer-genetic-box.png"
                _montage(shots, montage, [f"{st}: half width {np.degrees(h):.2f} deg" if st != "roll" else
                                          f"roll: circle of radius {np.degrees(h):.1f} deg" for st, h, _ in extents])
                _keep(montage)
                for shot in shots:
                    _keep(shot)
                # back to Orion, with the triangles, for what follows
                pg2.get_by_role("tab", name="View").click()
                pg2.get_by_role("checkbox", name="Matched triangles").check()
                pg2.get_by_role("tab", name="Scenario").click()
                for label, value in (("RA (deg)", 83.8), ("Dec (deg)", -5.4), ("Roll (deg)", 30.0)):
                    _type(pg2, label, value)

                # the stochastic method: a sequence of frames, the posterior across them, frame by frame
                pg2.set_viewport_size({"width": 1400, "height": 1100})
                pg2.get_by_role("tab", name="Scenario").click()
                pg2.get_by_role("checkbox", name="Solve on every change").uncheck()
                _choose(pg2, "Method", "stochastic")
                _type(pg2, "Centroid noise", 10)
                pg2.get_by_role("button", name="The paper's camera").click()  # 30 deg, Hp <= 4.5
                t = time.perf_counter()
                pg2.get_by_role("button", name="Solve", exact=True).click()
                pg2.get_by_text("identified by stochastic (improved) at frame", exact=False).first.wait_for(
                    timeout=60000)
                FIGURES["sequence_solve_s"] = round(time.perf_counter() - t, 2)
                pg2.get_by_role("tab", name="Steps").click()
                assert _control(pg2, "Frame").count() == 1  # the frame slider, with its player
                assert pg2.get_by_role("button", name="Play the frames").is_visible()
                pg2.get_by_text("Frame 4 (frames 0–4) · identified", exact=False).first.wait_for(timeout=10000)
                assert pg2.evaluate(JS_HAS, NODES["track"])  # every frame's footprint
                assert 5 in pg2.evaluate(JS_UPLOTS)  # the plot across frames: x and four series
                rings4 = pg2.evaluate(JS_GEOMETRY, NODES["centroids"])
                pg2.wait_for_timeout(500)
                pg2.evaluate(JS_PANEL_TOP)
                pg2.mouse.move(5, 5)  # not hovering the panel's image (its expand button would show)
                _settle(pg2)
                seq_shot = tmp_path / "viewer-sequence.png"
                pg2.screenshot(path=str(seq_shot))
                _keep(seq_shot)
                assert _not_blank(seq_shot, 1000) > 0.002
                # frame 0: its own image and centroids, and its update step lighting the hypotheses
                t = time.perf_counter()
                _type(pg2, "Frame", 0)
                pg2.get_by_text("Frame 0 (frames 0–4) · not identified", exact=False).first.wait_for(timeout=10000)
                FIGURES["frame_switch_round_trip_ms"] = round((time.perf_counter() - t) * 1e3)
                pg2.wait_for_timeout(500)
                assert pg2.evaluate(JS_GEOMETRY, NODES["centroids"]) != rings4
                _type(pg2, "Step", 1)
                pg2.get_by_text("Step 2 / 2 · update", exact=False).first.wait_for(timeout=10000)
                pg2.get_by_role("tab", name="View").click()
                pg2.get_by_role("button", name="Wide sky").click()
                pg2.get_by_role("tab", name="Steps").click()
                pg2.wait_for_timeout(800)
                hypotheses = pg2.evaluate(JS_GEOMETRY, NODES["points"])
                assert hypotheses[0] > 50  # the posterior's leading stars lit across the sky
                pg2.evaluate(JS_PANEL_TOP)
                pg2.mouse.move(5, 5)
                _settle(pg2)
                wide0 = tmp_path / "viewer-sequence-frame0-wide.png"
                pg2.screenshot(path=str(wide0))
                _keep(wide0)
                assert pg.external == [] and pg2.external == []  # nothing fetched from outside
            finally:
                browser.close()
    finally:
        _stop_view(proc)
        print("\n[viewer figures]", json.dumps(FIGURES))
        _save_figures()


# the panel's scroll: its position, its height, and the smallest height it had since JS_SCROLL_WATCH
JS_SCROLL_WATCH = """() => { const e = document.querySelector('.mantine-ScrollArea-viewport'); window.__minHeight = 1e9;
  const seen = () => { window.__minHeight = Math.min(window.__minHeight, e.scrollHeight); };
  new MutationObserver(seen).observe(e, {subtree: true, childList: true, attributes: true}); e.onscroll = seen; }"""
JS_SCROLL = """() => { const e = document.querySelector('.mantine-ScrollArea-viewport');
  const m = window.__minHeight; window.__minHeight = 1e9; return [e.scrollTop, e.scrollHeight, m]; }"""


@pytest.mark.browser
@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"no chromium at {CHROMIUM} (apt-get install chromium)")
def test_browser_panel_keeps_its_scroll_when_a_run_is_redrawn():
    """A panel scrolled down (to the plot) stays where it is while a new run and its steps are drawn:
    its elements are updated in place, so it never shrinks for a moment (which made it jump)."""
    pw = pytest.importorskip("playwright.sync_api")
    from skyview.viewer.app import ViewerApp

    with contextlib.redirect_stdout(io.StringIO()):
        app = ViewerApp("127.0.0.1", 0, method="angle")
    try:
        with pw.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
            try:
                pg = browser.new_page(viewport={"width": 1400, "height": 860})
                pg.goto(app.url)
                pg.wait_for_function(JS_HAS, arg=NODES["frustum"], timeout=60000)
                s = next(iter(app.sessions.values()))
                assert s.wait_idle(60) and s.run.result.method == "angle" and len(s.run.drawables) >= 3
                pg.get_by_text("by angle (paper)", exact=False).first.wait_for(timeout=30000)
                pg.wait_for_timeout(800)
                pg.mouse.move(1200, 500)  # over the panel
                pg.mouse.wheel(0, 5000)  # down to the plot across the steps
                pg.wait_for_timeout(500)
                pg.evaluate(JS_SCROLL_WATCH)
                top, height, _ = pg.evaluate(JS_SCROLL)
                assert top > 100, "the panel did not scroll"
                for _ in range(2):
                    s.request_solve()  # the same scene again: a new run with the same text and plot
                    assert s.wait_idle(60) and s.error == ""
                    pg.wait_for_timeout(1200)
                    now, h, lowest = pg.evaluate(JS_SCROLL)
                    assert (now, h) == (top, height) and lowest >= height - 40, (top, height, now, h, lowest)
                s.panel.step.value = 0  # a step drawn: the image, the text and the plot's marker in place
                pg.wait_for_timeout(800)
                s.panel.step.value = len(s.run.drawables) - 1
                pg.wait_for_timeout(800)
                assert pg.evaluate(JS_SCROLL)[:2] == [top, height]
            finally:
                browser.close()
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            app.stop()


JS_VISIBLE = "(n) => { const o = window.__viserMutable?.nodeRefFromName?.[n]; return !!(o && o.visible); }"
ORION = {"RA (deg)": 83.8, "Dec (deg)": -5.4, "Roll (deg)": 30.0, "FOV (deg)": 8.0, "Mag limit (Hp)": 6.0}
# each single-image method on a scene it solves (svd on Orion: not solved, and says why)
STORY = [("angle", "improved", {}), ("triangle", "paper", {}), ("ellipticity", "improved", {}),
         ("genetic", "improved", GA_SCENE), ("svd", "improved", {})]
DOC_IMAGES = REPO / "docs" / "images"


def _scene_of(values: dict) -> SceneConfig:
    v = {**ORION, **values}
    return SceneConfig(ra_deg=v["RA (deg)"], dec_deg=v["Dec (deg)"], roll_deg=v["Roll (deg)"], fov_deg=v["FOV (deg)"],
                       mag_limit=v["Mag limit (Hp)"])


@pytest.mark.browser
@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"no chromium at {CHROMIUM} (apt-get install chromium)")
def test_browser_tells_each_methods_story_step_by_step(tmp_path):
    """A step is a state of knowledge: at step 0 no identification is drawn, the candidate arcs thin as
    the hypotheses fall, the last step shows the identification. Screenshots of each method's first, a
    middle and its last step (copied into docs/images when SKYVIEW_UPDATE_DOC_IMAGES=1)."""
    pw = pytest.importorskip("playwright.sync_api")
    sv = Solvers()
    plan = []
    for method, variant, scene in STORY:  # the server's solves are seeded: the same steps as here
        run = solve(simulate(_scene_of(scene), sv.base_catalog), method, variant, _scene_of(scene).mag_limit, sv)
        plan.append((method, variant, scene, run))
    proc, url = _start_view()
    try:
        with pw.sync_playwright() as p:
            browser = _chromium(p, tmp_path)
            try:
                pg = _open(browser, url)
                pg.get_by_role("tab", name="Scenario").click()
                pg.get_by_role("checkbox", name="Solve on every change").uncheck()
                story = {}
                for method, variant, scene, run in plan:
                    pg.get_by_role("tab", name="Scenario").click()
                    for label, value in {**ORION, **scene}.items():
                        _type(pg, label, value)
                        pg.wait_for_timeout(150)
                    _choose(pg, "Variant", variant)
                    _choose(pg, "Method", method)
                    pg.get_by_role("button", name="Solve", exact=True).click()
                    pg.get_by_text(f"by {method} ({variant})", exact=False).first.wait_for(timeout=120000)
                    n = len(run.drawables)
                    pg.get_by_role("tab", name="Steps").click()
                    seen = []
                    for label, k in (("first", 0), ("middle", n // 2), ("last", n - 1)):
                        _type(pg, "Step", k)
                        pg.get_by_text(f"Step {k + 1} / {n} · {run.drawables[k].kind}", exact=False).first.wait_for(
                            timeout=60000)
                        pg.wait_for_timeout(500)
                        seen.append((k, pg.evaluate(JS_GEOMETRY, NODES["candidates"])[0],
                                     pg.evaluate(JS_VISIBLE, NODES["match_stars"])))
                        pg.evaluate(JS_PANEL_TOP)
                        pg.mouse.move(5, 5)
                        _settle(pg)
                        shot = tmp_path / f"steps-{method}-{label}.png"
                        pg.screenshot(path=str(shot))
                        _keep(shot)
                        if os.environ.get("SKYVIEW_UPDATE_DOC_IMAGES") == "1":
                            DOC_IMAGES.mkdir(exist_ok=True)
                            cv2.imwrite(str(DOC_IMAGES / shot.name), cv2.imread(str(shot)))
                    story[method] = (run, seen)
                    if not run.result.solved:  # why not, in words, in the panel at the last step
                        pg.get_by_text("Not solved.", exact=False).first.wait_for(timeout=10000)
                # the identification is drawn only once it is made
                for method, (run, seen) in story.items():
                    assert seen[0][2] is False, (method, seen)
                    assert seen[-1][2] is run.result.solved, (method, seen)
                # the angle method's hypotheses fall 950 -> 248 -> 1: its candidate arcs on screen fall with them
                run, _ = story["angle"]
                surviving = [v.surviving for v in run.drawables[:3]]
                assert surviving[0] > surviving[1] > surviving[2] == 1, surviving
                pg.get_by_role("tab", name="Scenario").click()
                _choose(pg, "Method", "angle")  # the scene is Orion again (svd's), the variant improved
                pg.get_by_role("button", name="Solve", exact=True).click()
                pg.get_by_text("by angle (improved)", exact=False).first.wait_for(timeout=120000)
                pg.get_by_role("tab", name="Steps").click()
                arcs = []
                for k in range(3):
                    _type(pg, "Step", k)
                    pg.get_by_text(f"Step {k + 1} / {len(run.drawables)} · {run.drawables[k].kind}",
                                   exact=False).first.wait_for(timeout=60000)
                    pg.wait_for_timeout(500)
                    arcs.append(pg.evaluate(JS_GEOMETRY, NODES["candidates"])[0])
                FIGURES["angle_story_arcs"] = arcs
                _save_figures()
                assert arcs[0] > arcs[1] > arcs[2] > 0, arcs
            finally:
                browser.close()
    finally:
        _stop_view(proc)


@contextlib.contextmanager
def viewer_page(tmp_path: Path, *view_args):
    """A page of headless Chromium on a `skyview view` process of its own (view_args: its command line's);
    the browser closed and the viewer stopped (Ctrl-C, exit 0) afterwards."""
    pw = pytest.importorskip("playwright.sync_api")
    proc, url = _start_view(*view_args)
    try:
        with pw.sync_playwright() as p:
            browser = _chromium(p, tmp_path)
            try:
                yield _open(browser, url)
            finally:
                browser.close()
    finally:
        _stop_view(proc)


def _doc_shot(pg, shot: Path) -> None:
    """A screenshot kept in test-artifacts/, and in docs/images as a JPEG when SKYVIEW_UPDATE_DOC_IMAGES=1."""
    pg.screenshot(path=str(shot))
    _keep(shot)
    if os.environ.get("SKYVIEW_UPDATE_DOC_IMAGES") == "1":
        DOC_IMAGES.mkdir(exist_ok=True)
        cv2.imwrite(str(DOC_IMAGES / shot.with_suffix(".jpg").name), cv2.imread(str(shot)),
                    [cv2.IMWRITE_JPEG_QUALITY, 85])


@pytest.mark.browser
@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"no chromium at {CHROMIUM} (apt-get install chromium)")
def test_browser_tells_a_photographs_blind_story_step_by_step(tmp_path):
    """`skyview view PHOTO` opens on the photograph solved blind; its steps read from first to last: the
    pattern table's hits across the sky, how they thin, the hypothesis, the camera fit, the verification.
    On screen the hit patterns' places on the sky thin from the first step to the second, the candidates'
    arcs follow, and the identification is drawn only once it is made. A screenshot of each step (copied
    into docs/images when SKYVIEW_UPDATE_DOC_IMAGES=1)."""
    from skyview.detect.centroids import load_image
    from skyview.identify.layers import SkyPlaces
    from skyview.solver.pipeline import blind_solver

    real = Path(__file__).parent / "data" / "real-images"
    name = sorted(json.loads((real / "reference.json").read_text()))[0]
    steps = blind_solver().solve_array(load_image(real / name)).identification.steps  # the viewer's, seeded alike
    kinds = [st.kind for st in steps]
    assert kinds[:3] == ["lookup", "prune", "prune"] and kinds[-2:] == ["fit", "verify"]
    with viewer_page(tmp_path, str(real / name)) as pg:
        pg.get_by_text("by blind", exact=False).first.wait_for(timeout=120000)
        pg.get_by_role("tab", name="Steps").click()
        places, arcs, drawn = [], [], []
        for k, kind in enumerate(kinds):
            _type(pg, "Step", k)
            pg.get_by_text(f"Step {k + 1} / {len(kinds)} · {kind}", exact=False).first.wait_for(timeout=60000)
            pg.wait_for_timeout(500)
            places.append(pg.evaluate(JS_GEOMETRY, NODES["points"])[0])
            arcs.append(pg.evaluate(JS_GEOMETRY, NODES["candidates"])[0])
            drawn.append(pg.evaluate(JS_VISIBLE, NODES["match_stars"]))
            pg.evaluate(JS_PANEL_TOP)
            pg.mouse.move(5, 5)
            _settle(pg)
            _doc_shot(pg, tmp_path / f"steps-blind-photo-{k + 1}-{kind}.png")
        # the wide sky: the hits across the whole sky, then the ones whose size fits
        pg.get_by_role("tab", name="View").click()
        pg.get_by_role("button", name="Wide sky").click()
        pg.get_by_role("tab", name="Steps").click()
        for k in (0, 1):
            _type(pg, "Step", k)
            pg.get_by_text(f"Step {k + 1} / {len(kinds)} · {kinds[k]}", exact=False).first.wait_for(timeout=60000)
            pg.wait_for_timeout(500)
            pg.evaluate(JS_PANEL_TOP)
            pg.mouse.move(5, 5)
            _settle(pg)
            _doc_shot(pg, tmp_path / f"steps-blind-photo-wide-{k + 1}-{kinds[k]}.png")
    FIGURES["blind_photo_story"] = {"places": places, "arcs": arcs}
    _save_figures()
    n = [st.layer(SkyPlaces).total for st in steps[:2]]
    assert places[:2] == n and n[0] > n[1] > 0 and places[2] == 0, (places, n)  # the hits thinning, all drawn
    assert arcs[:2] == [0, 0] and arcs[2] > 0, arcs  # then the candidates' patterns
    assert drawn[0] is False and drawn[-1] is True, drawn


def test_view_command_serves_locally_and_stops_on_ctrl_c():
    proc, url = _start_view("--fov-deg", "12")
    try:
        assert url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url, timeout=10) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
    finally:
        _stop_view(proc)


@pytest.mark.slow
def test_view_stops_on_ctrl_c_even_when_started_with_sigint_ignored():
    """A background job (`cmd &` in a script, as CI may run the tests) starts its children with SIGINT
    ignored; the viewer must still stop on Ctrl-C."""
    exe = Path(sys.executable).with_name("skyview")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "skyview"]
    p = subprocess.Popen(cmd + ["view", "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        assert p.stdout.readline().startswith("skyview viewer: http://127.0.0.1:")
    except BaseException:
        p.kill()
        raise
    _stop_view(p)


def test_an_uploaded_photograph_gets_its_camera_fitted_blind():
    """A user's image needs no exact FOV: the blind front end fits FOV, distortion and depth first."""
    from pathlib import Path

    from skyview.detect.centroids import load_image
    from skyview.viewer.run import Solvers, Source, fit_camera_blind

    real = Path(__file__).parent / "data" / "real-images"
    ref = json.loads((real / "reference.json").read_text())
    name = sorted(ref)[0]
    src = fit_camera_blind(Source(image=load_image(real / name), fov_deg=8.0, name=name), Solvers())
    assert src.fitted and src.fov_deg == pytest.approx(ref[name]["fov_deg"], rel=0.005)
    assert src.depth_mag is not None and 6.5 <= src.depth_mag <= 7.5
    # a simulated scene keeps its exact camera
    sim = Source(image=load_image(real / name), fov_deg=8.0, name="sim", truth={"R": np.eye(3).tolist()})
    assert fit_camera_blind(sim, Solvers()) is sim


def test_a_host_that_cannot_be_bound_is_one_line_and_exit_2(capsys):
    """An address that is not this machine's fails at once (no hang), with one line."""
    from skyview.cli import main
    from skyview.viewer.app import check_host

    check_host("127.0.0.1")
    with pytest.raises(BadInput, match="cannot listen"):
        check_host("192.0.2.1")  # TEST-NET-1: never an address of this machine; bind() fails locally
    t0 = time.perf_counter()
    code = main(["view", "--host", "192.0.2.1", "--port", "0"])
    err = capsys.readouterr().err
    assert code == 2 and err.strip().startswith("skyview: error:") and len(err.strip().splitlines()) == 1
    assert time.perf_counter() - t0 < 10.0


def test_an_oversized_upload_is_refused_when_it_starts_not_after_it_arrived():
    """The browser announces the size first: over the limit, the server drops the transfer at once and
    buffers none of its parts; a small one is buffered as usual."""
    import asyncio

    from viser import _messages

    from skyview.viewer.app import ViewerApp
    from skyview.viewer.picture import MAX_UPLOAD_BYTES

    app = ViewerApp(port=0)
    try:
        gui = app.server.gui
        button = gui.add_upload_button("test upload")
        uuid = button._impl.uuid
        ws = gui._websock_interface
        big = _messages.FileTransferStartUpload(source_component_uuid=uuid, transfer_uuid="big", filename="big.png",
                                                mime_type="image/png", part_count=5000,
                                                size_bytes=MAX_UPLOAD_BYTES + 1)
        small = _messages.FileTransferStartUpload(source_component_uuid=uuid, transfer_uuid="small",
                                                  filename="small.png", mime_type="image/png", part_count=2,
                                                  size_bytes=1000)
        asyncio.run(ws._handle_incoming_message(0, big))
        asyncio.run(ws._handle_incoming_message(0, small))
        assert "big" not in gui._current_file_upload_states
        assert "small" in gui._current_file_upload_states
        part = _messages.FileTransferPart(source_component_uuid=uuid, transfer_uuid="big", part_index=0,
                                          content=b"x" * 1000)
        asyncio.run(ws._handle_incoming_message(0, part))
        assert "big" not in gui._current_file_upload_states  # its parts are not buffered
    finally:
        app.stop()


def test_the_blind_pipeline_is_a_method_of_the_viewer():
    """The default pipeline (no FOV, the camera fitted) in the Method menu: its steps are the look-up of
    patterns (its hits drawn across the sky, then thinned to the candidates), the hypotheses, the camera fit
    and the verification."""
    solvers = Solvers()
    src = simulate(SceneConfig(ra_deg=83.8, dec_deg=-5.4, roll_deg=30.0, fov_deg=12.0, mag_limit=6.5),
                   solvers.base_catalog)
    run = solve(src, "blind", "improved", 6.5, solvers)
    assert run.result.solved and run.result.method == "blind" and run.result.camera_fitted
    assert run.result.camera.fov_deg == pytest.approx(12.0, rel=0.005) and run.wrong_matches == 0
    kinds = [st.kind for st in run.result.identification.steps]
    assert kinds[:3] == ["lookup", "prune", "prune"] and "hypothesis" in kinds and kinds[-2:] == ["fit", "verify"]
    views = run.drawables
    assert len(views[0].drawables["points"].xyz) > len(views[1].drawables["points"].xyz) > 0  # the hits thinning
    assert "candidates" in views[2].drawables  # the candidate patterns, drawn on the sphere
    assert "fitted to the stars" in result_markdown(run)


@pytest.mark.browser
@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"no chromium at {CHROMIUM} (apt-get install chromium)")
def test_a_closed_tab_frees_its_session(tmp_path):
    """A tab's Session and its panel's callbacks hold each other: without a collection each closed tab kept
    ~9 MB until Python's next full collection. Three tabs opened and closed one after the other: each
    session is gone within a few seconds of its tab closing."""
    import gc
    import weakref

    pw = pytest.importorskip("playwright.sync_api")
    from skyview.viewer.app import ViewerApp

    app = ViewerApp("127.0.0.1", 0, method="angle")
    gc_was = gc.isenabled()
    gc.disable()  # only the app's own collection may free them
    try:
        with pw.sync_playwright() as p:
            browser = _chromium(p, tmp_path)
            try:
                for _ in range(3):
                    pg = browser.new_page()
                    pg.goto(app.url)
                    t0 = time.time()
                    while not app.sessions and time.time() - t0 < 30:
                        time.sleep(0.05)
                    (session,) = app.sessions.values()
                    assert session.wait_idle(60)
                    ref = weakref.ref(session)
                    del session
                    pg.close()
                    t0 = time.time()
                    while ref() is not None and time.time() - t0 < 10:
                        time.sleep(0.1)
                    assert ref() is None and not app.sessions
            finally:
                browser.close()
    finally:
        if gc_was:
            gc.enable()
        app.stop()


def test_the_progress_line_is_restored_before_wait_idle_returns():
    """A job shown as running ("⏳ solving… 0.5 s") is reported ended before wait_idle returns, and no
    late tick writes the progress line over the result afterwards."""
    from skyview.viewer.worker import Worker

    events: list[str] = []
    w = Worker(on_error=lambda exc: events.append(f"error {exc}"))
    w.watch(lambda label, s, p: events.append("busy"), lambda: events.append("idle"), after_s=0.05, every_s=0.01)
    try:
        for _ in range(3):
            w.submit("solving", lambda: time.sleep(0.2))
            assert w.wait_idle(5)
            assert "busy" in events and events[-1] == "idle"
            n = len(events)
            time.sleep(0.1)
            assert events[n:] == []
            events.clear()
    finally:
        w.close()


def test_a_photograph_that_does_not_solve_says_what_was_tried_in_words():
    """25 bright blobs on a flat grey frame (no sky): the status line stays one short line naming the
    searches; the Result tab lists each search (what, over which FOVs, how many candidate attitudes, why it
    failed) and what to try; the solver's own words are kept below."""
    import cv2

    from skyview.present.text import blind_searches, why_not
    from skyview.viewer.run import Source

    rng = np.random.default_rng(1)
    img = rng.normal(100, 5, (600, 800)).clip(0, 255).astype(np.uint8)
    for _ in range(25):
        cv2.circle(img, (int(rng.uniform(0, 800)), int(rng.uniform(0, 600))), 2, 250, -1)
    solvers = Solvers()
    run = solve(Source(image=img, fov_deg=10.0, name="blobs.png"), "blind", "improved", 6.0, solvers)
    r = run.result
    assert not r.solved
    searches = blind_searches(r)
    assert [s["fov"] for s in searches] == ["2.5-81°", "0.7-3.1°", "70-240°"]
    assert searches[0]["hypotheses"] > 100 and all("chance" in s["outcome"] for s in searches)
    # each search's own hypotheses: all but the last (the fisheye's whole search) are the count the pinhole search's
    # last verification was corrected for (its first hypotheses, the narrow fields', a fisheye's first ones, then
    # its whole search)
    assert [s["kind"] for s in r.searches] == ["pinhole", "narrow", "fisheye", "pinhole", "fisheye"]
    assert sum(s["hypotheses"] for s in r.searches[:-1]) == r.identification.stats["checks"]
    status = status_markdown(run)
    assert "not solved" in status and "pinhole 2.5-81°" in status and len(status) < 320
    story = why_not(r)
    assert story.count("\n- ") == 3 and "What to try" in story and "crop them out" in story
    md = result_markdown(run)
    assert "- a fisheye lens" in md and "the solver's own words" in md


def test_the_view_fitted_to_a_fisheye_stays_a_perspective_that_draws():
    """'boresight' fits the sensor in the tab's view: 1.2 times its field, but never more than MAX_FIT_FOV_DEG. A
    fisheye's 180 deg would ask for a perspective of 180 deg, which draws nothing (the all-sky photograph's
    view was a dark screen); an 8 deg sensor is fitted as before."""
    import contextlib
    import math
    from types import SimpleNamespace

    from skyview.core.camera import EQUISOLID, Camera
    from skyview.viewer.camera_control import MAX_FIT_FOV_DEG, CameraControl

    tab = SimpleNamespace(fov=1.0, position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, 1.0), up_direction=(0.0, -1.0, 0.0),
                          image_width=1200, image_height=800, _state=SimpleNamespace(update_timestamp=1.0))
    client = SimpleNamespace(camera=tab, atomic=contextlib.nullcontext)  # (a tab that reported its view)
    sky = SimpleNamespace(detail=False, set_zoom=lambda z: None, set_detail=lambda on: None)
    control = CameraControl(client, sky, contextlib.nullcontext(), contextlib.nullcontext)
    R = np.eye(3)
    for camera, want_deg in ((Camera.from_fov(180.0, 1024, 1024, model=EQUISOLID), MAX_FIT_FOV_DEG),
                             (Camera.from_fov(8.0, 1024, 768), 2.0 * math.degrees(math.atan(1.2 * math.tan(
                                 math.radians(Camera.from_fov(8.0, 1024, 768).fov_v_deg) / 2.0))))):
        run = SimpleNamespace(R_shown=R, source=SimpleNamespace(camera=camera, fov_deg=camera.fov_deg))
        control.point("boresight", run)
        assert math.degrees(tab.fov) == pytest.approx(want_deg, rel=1e-9)
        assert tab.look_at == tuple(R[2])
