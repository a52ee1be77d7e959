"""One presentation, two sinks: the viewer and the recorder draw the same drawables for the same step.

A real solve (the triangle method on the default Orion scene, and the genetic method with its search
box), each step turned into a `present.StepView`; the viser scene (a real server on 127.0.0.1) and the
Rerun archetypes of `record_draw` must hold, role by role, the same geometry in the same colours.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
import viser

from skyview.present import drawables as present
from skyview.record.draw import step_archetypes, step_path
from skyview.viewer.run import SceneConfig, Solvers, simulate, solve
from skyview.viewer.scene import NODES, SkyScene


def _rgb(batch) -> np.ndarray:
    """(N, 3) uint8 colours of a Rerun color batch (packed 0xRRGGBBAA)."""
    packed = np.asarray(batch.as_arrow_array().to_numpy(zero_copy_only=False), dtype=np.uint32)
    return np.stack([(packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255], axis=1).astype(np.uint8)


def _xyz(batch, width: int) -> np.ndarray:
    """The coordinates of a Rerun position / strip batch as (N, width) floats (nested lists flattened)."""
    arr = batch.as_arrow_array()
    while hasattr(arr, "flatten") and (pa.types.is_list(arr.type) or pa.types.is_fixed_size_list(arr.type)
                                       or pa.types.is_large_list(arr.type)):
        arr = arr.flatten()
    return np.asarray(arr.to_numpy(zero_copy_only=False), dtype=np.float64).reshape(-1, width)


@pytest.fixture(scope="module")
def solvers():
    return Solvers()


@pytest.fixture(scope="module")
def server():
    s = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield s
    s.stop()


@pytest.mark.parametrize("method, variant, cfg", [
    ("triangle", "improved", SceneConfig()),
    pytest.param("genetic", "improved", SceneConfig(ra_deg=107.9, dec_deg=-8.9, roll_deg=-170.0, fov_deg=20.0),
                 marks=pytest.mark.slow),
])
def test_viewer_and_recorder_draw_the_same_drawables(method, variant, cfg, solvers, server):
    run = solve(simulate(cfg, solvers.base_catalog), method, variant, cfg.mag_limit, solvers)
    assert run.result.solved, run.result.reason
    sky = SkyScene(server.scene)
    sky.setup()
    sky.draw_run(run, None)
    uv = run.result.centroids.uv
    roles_seen: set[str] = set()
    checked = 0
    for k, view in enumerate(run.drawables):
        if k % max(1, len(run.drawables) // 12) and k != len(run.drawables) - 1:
            continue  # a dozen steps spread over the solve, and the last
        sky.show_step(run, k)
        rr_arch = step_archetypes(view, uv)
        assert set(rr_arch) == {step_path(r) for r in view.drawables}  # the same roles, no more, no fewer
        for role in present.SKY_ROLES + present.IMAGE_ROLES:
            node = sky.h.get(role)
            d = view.drawables.get(role)
            if d is None:
                assert node is None or not node.visible, (k, role)  # drawn by neither
                continue
            roles_seen.add(role)
            arch = rr_arch[step_path(role)]
            assert node.visible, (k, role)
            if isinstance(d, present.SkyPoints):
                np.testing.assert_allclose(node.points, _xyz(arch.positions, 3), atol=1e-6)
                np.testing.assert_array_equal(node.colors, _rgb(arch.colors))
            elif isinstance(d, present.SkyLines):
                strips = _xyz(arch.strips, 3).reshape(-1, 2, 3)
                np.testing.assert_allclose(node.points, strips, atol=1e-6)
                assert np.all(node.colors == np.array(d.color, np.uint8)) and np.all(_rgb(arch.colors) == d.color)
            else:  # image roles: the same stars (rings in the viewer, points in the recording), one colour
                assert np.all(node.colors == np.array(d.color, np.uint8)) and np.all(_rgb(arch.colors) == d.color)
                if isinstance(d, present.ImageMarks):
                    assert len(_xyz(arch.positions, 2)) == len(d.observed)
                    assert len(node.points) % len(d.observed) == 0
            checked += 1
        # the identification: only at the last step
        assert sky.h["match_stars"].visible == view.final, k
    assert checked >= 6
    want = {"triangle": {"candidates", "candidate_stars", "observed", "pattern"},
            "genetic": {"points", "outline", "observed"}}[method]
    assert want <= roles_seen, roles_seen
    assert NODES["points"] == "/steps/points"


def test_star_names_that_would_collide_hide_the_fainter(server):
    """Orion's belt (Alnitak 1.7, Alnilam 1.6, Mintaka 2.1, ~1.4 deg apart): all named when zoomed on
    it, only the brightest, Alnilam, in a wide view where the labels would overlap."""
    from skyview.core.catalog import load_guide_catalog

    sky = SkyScene(server.scene)
    sky.setup()
    sky.draw_catalog(load_guide_catalog().brighter_than(6.0))
    names = {int(h.name.rsplit("/", 1)[1]): h for h in sky.h["names"]}
    belt = {"Alnitak": 26727, "Alnilam": 26311, "Mintaka": 25930}
    sky.set_zoom(0.12)  # an 8-degree field filling the view
    assert all(names[h].visible for h in belt.values())
    sky.set_zoom(2.0)  # the wide sky
    assert names[belt["Alnilam"]].visible and not names[belt["Alnitak"]].visible
    assert not names[belt["Mintaka"]].visible
    shown = sum(h.visible for h in names.values())
    assert 5 < shown < len(names)  # elsewhere names stay
    sky.set_visible("names", False)
    assert not any(h.visible for h in names.values())


def test_sequence_methods_are_found_by_their_interface_not_an_attribute():
    from skyview.identify import METHODS
    from skyview.identify.base import SequenceIdentifier, is_sequence_method

    assert [m for m in METHODS if is_sequence_method(METHODS[m])] == ["stochastic"]
    assert issubclass(METHODS["stochastic"], SequenceIdentifier)


def _boxes_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3])


def _box_star_clearance(box: np.ndarray, xy: np.ndarray, r: float) -> np.ndarray:
    """How far each star's mark (centre xy, radius r) is from the box: negative when it is under it."""
    near = np.clip(xy, box[:2], box[2:]) - xy
    return np.hypot(near[:, 0], near[:, 1]) - r


@pytest.mark.parametrize("seed", range(6))
def test_labels_sit_beside_their_stars_on_no_label_and_no_star(seed):
    """A crowded field (60 stars, 25 labelled, 300 x 200 px): the shown labels' boxes overlap no other, cover
    no star's mark (labelled or not) and stay in bounds; each sits beside its own star, nearer to it than
    to any other labelled star; a label is hidden only where every side was taken."""
    rng = np.random.default_rng(seed)
    stars = rng.uniform([0, 0], [300, 200], size=(60, 2))
    anchors, others = stars[:25], stars[25:]
    sizes = np.stack([rng.uniform(30, 70, 25), np.full(25, 12.0)], axis=1)
    mag = rng.uniform(0, 6, 25)
    lay = present.layout_labels(anchors, sizes, mag, anchor_radius=4.0, stars=others, star_radius=3.0, gap=2.0,
                                apart=2.0, bounds=(0, 0, 300, 200))
    boxes = lay.boxes()
    assert 3 <= len(boxes) < 25  # crowded: some shown, some hidden
    for k, b in enumerate(boxes):
        assert b[0] >= 0 and b[1] >= 0 and b[2] <= 300 and b[3] <= 200
        assert not any(_boxes_overlap(b, c) for c in boxes[k + 1:])
        assert np.all(_box_star_clearance(b, others, 3.0) >= 0) and np.all(_box_star_clearance(b, anchors, 4.0) >= 0)
    for i in np.flatnonzero(lay.shown):
        box = np.concatenate([lay.centre[i] - lay.size[i] / 2, lay.centre[i] + lay.size[i] / 2])
        clear = _box_star_clearance(box, anchors, 4.0)
        assert 2.0 - 1e-9 <= clear[i] <= np.hypot(1, 0.5) * (4.0 + 2.0) - 4.0  # beside it, `gap` away (or a bit more)
        assert np.all(np.delete(clear, i) >= clear[i] + 2.0 - 1e-9)  # it reads as its own star's label


def test_of_two_colliding_labels_the_brightest_keeps_its_place():
    """Two stars whose labels, both to the right, would overlap: with one side only the brighter one is
    shown, whichever comes first; with every side the fainter moves below its star instead of hiding."""
    xy = np.array([[100.0, 100.0], [120.0, 106.0]])
    sizes = np.array([[40.0, 10.0], [40.0, 10.0]])
    for mag in ([3.0, 1.0], [1.0, 3.0]):
        one_side = present.layout_labels(xy, sizes, np.array(mag), gap=1.0, sides=((1, 0),))
        assert one_side.shown.tolist() == [mag[0] < mag[1], mag[1] < mag[0]]
    both = present.layout_labels(xy, sizes, np.array([1.0, 3.0]), gap=1.0)
    assert both.shown.all()
    np.testing.assert_allclose(both.centre, [[121.0, 100.0], [120.0, 112.0]])  # right of it; below it
    # a label whose box would cover another star is moved: to the right it would cover the star at x = 104
    near = present.layout_labels(np.array([[100.0, 100.0], [104.0, 100.0]]), sizes, np.array([1.0, 3.0]), gap=1.0,
                                 stars=np.zeros((0, 2)))
    assert near.centre[0, 0] < 100 and near.centre[1, 0] > 104
    # no room at all (the box is bigger than the bounds): hidden, not drawn out of bounds
    none = present.layout_labels(xy, sizes, np.array([1.0, 2.0]), bounds=(90, 90, 120, 120))
    assert not none.shown.any() and np.isnan(none.centre).all()
    # place_labels (the viewer's one-sided form) is layout_labels to the right, with no stars to avoid
    keep = present.place_labels(xy, np.array([3.0, 1.0]), sizes, gap=1.0)
    assert keep.tolist() == [False, True]


def test_the_ra_dec_grid_lies_on_its_own_coordinates_through_any_lens():
    # every point of every line, taken back through the camera, has the line's RA (meridians) or Dec (parallels)
    import math

    from skyview.core.attitude import R_from_radec_roll
    from skyview.core.camera import Camera
    from skyview.core.catalog import vec_to_radec
    from skyview.present.sky_grid import dec_label, image_grid, ra_label

    cases = [(Camera.from_fov(11.4, 1024, 768, k1=-0.01), (350.0, 60.0, 20.0)),
             (Camera.from_fov(1.2, 1024, 768), (130.1, 19.7, -75.0)),
             (Camera.from_fov(180.0, 1024, 1024, model="equisolid"), (10.0, 80.0, 0.0))]
    for cam, (ra, dec, roll) in cases:
        R = R_from_radec_roll(*(math.radians(x) for x in (ra, dec, roll)))
        grid = image_grid(cam, R)
        kinds = {g.kind for g in grid}
        assert kinds == {"ra", "dec"} and 3 <= len(grid) <= 40, (cam.fov_deg, [(g.kind, g.label) for g in grid])
        for g in grid:
            uv = np.concatenate(g.runs)
            assert cam.in_image(uv).all()
            a, d = (np.degrees(x) for x in vec_to_radec(cam.unproject(uv) @ R))
            if g.kind == "dec":
                np.testing.assert_allclose(d, g.value_deg, atol=1e-6)
                assert g.label == dec_label(g.value_deg)
            else:
                far = np.abs(d) < 89.9  # (at a pole every meridian meets)
                np.testing.assert_allclose(((a[far] - g.value_deg + 180) % 360) - 180, 0.0, atol=1e-6)
                assert g.label == ra_label(g.value_deg)
    assert (dec_label(-5.5), dec_label(42.0), ra_label(85.0), ra_label(0.0)) == ("-5°30'", "+42°", "5h40m", "0h")
