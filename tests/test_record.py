"""Rerun recordings: written from a solve, read back with rerun-sdk's reader, replayed and rendered.

Reading: `rerun.chunk.RrdReader(path).stream()` yields chunks (entity path, rows, timelines, Arrow
record batch). Viewer tests start the real Rerun binary (rerun_cli/rerun, never the Python launcher)
on 127.0.0.1 and stop it by its PID; the screenshot tests need Mesa's software Vulkan driver
(Debian: mesa-vulkan-drivers) and are skipped, with that reason, without it.
"""

from __future__ import annotations

import dataclasses
import glob
import io
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest
import rerun as rr
import rerun.blueprint as rrb
from PIL import Image
from rerun.chunk import RrdReader

from skyview.cli import main
from skyview.core.errors import BadInput
from skyview.core.sky_geometry import OUTLINE_EDGE_POINTS
from skyview.identify.base import Step
from skyview.identify.layers import Hypotheses, Population, Posterior, SearchRegion
from skyview.present.drawables import PALETTE, region_polyline, step_views, unit_of
from skyview.record import draw as D
from skyview.record import recording as rec
from skyview.record.cases import CaseRunner
from skyview.record.replay import free_port, rerun_binary

ENV = {**os.environ, "RERUN_ANALYTICS": "0"}
HAS_LAVAPIPE = bool(glob.glob("/usr/share/vulkan/icd.d/lvp_icd*.json"))
_lavapipe = pytest.mark.skipif(not HAS_LAVAPIPE, reason="Rerun's headless viewer needs Mesa's software "
                               "Vulkan driver: apt-get install mesa-vulkan-drivers")


def needs_lavapipe(test):
    """A test that renders in Rerun's own (headless) viewer: marked `browser`, skipped without Mesa's Vulkan."""
    return pytest.mark.browser(_lavapipe(test))
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module", autouse=True)
def strict_rerun():
    rr.set_strict_mode(True)  # a bad log call raises instead of warning
    yield
    rr.set_strict_mode(False)


def read(path: Path) -> dict:
    """Per entity path: rows, static flag, timelines and the Arrow batches."""
    out: dict = defaultdict(lambda: {"rows": 0, "static": False, "timelines": set(), "batches": []})
    for ch in RrdReader(path).stream():
        e = out[ch.entity_path]
        e["rows"] += ch.num_rows
        e["static"] |= ch.is_static
        e["timelines"] |= set(ch.timeline_names)
        e["batches"].append(ch.to_record_batch())
    return dict(out)


def column(entity: dict, name: str) -> list:
    """All values of one component column, in step order for temporal data."""
    rows = []
    for b in entity["batches"]:
        if name in b.schema.names:
            steps = b.column("step").to_pylist() if "step" in b.schema.names else [None] * b.num_rows
            rows += list(zip(steps, b.column(name).to_pylist()))
    rows.sort(key=lambda r: -1 if r[0] is None else r[0])
    return [v for _, v in rows]


def one_line_error(err: str) -> bool:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    return len(lines) == 1 and lines[0].startswith("skyview:") and "Traceback" not in err


@pytest.fixture(scope="module")
def runner():
    return CaseRunner("angle", "cole8")


@pytest.fixture(scope="module")
def solved(runner, tmp_path_factory):
    """Case 8 of cole8: the paper's angle method identifies it."""
    case = runner.run(8)
    assert case.result.solved, case.result.reason
    path = tmp_path_factory.mktemp("rec") / "angle-cole8-8.rrd"
    info = runner.record(case, path)
    return case, path, info, read(path)


@pytest.fixture(scope="module")
def unsolved(runner, tmp_path_factory):
    """Case 12 of cole8: no angle is left to pivot to (not solved; truth still known)."""
    case = runner.run(12)
    assert not case.result.solved and case.result.identification.steps
    path = tmp_path_factory.mktemp("rec") / "angle-cole8-12.rrd"
    info = runner.record(case, path)
    return case, path, info, read(path)


# ============================================================================ contents

STATIC = {"/sky/catalog", "/sky/grid", "/sky/fov/true", "/sky/observed", "/camera", "/camera/image",
          "/camera/image/centroids", "/camera/image/truth/stars", "/truth/camera", "/result"}
PER_STEP = {"/sky/step/candidates", "/sky/step/candidate_stars", "/camera/image/step/observed", "/steps/log"}
IDENTIFICATION = {"/sky/matches", "/sky/matches/labels", "/camera/image/matches", "/camera/image/labels"}


def test_entity_paths(solved, unsolved):
    case, path, info, ents = solved
    assert STATIC | PER_STEP | IDENTIFICATION | {"/sky/fov/estimated"} <= set(ents)
    for e in STATIC | {"/sky/fov/estimated"}:
        assert ents[e]["static"] and not ents[e]["timelines"], e
    for e in PER_STEP:
        assert ents[e]["timelines"] == {"step"}, e
    # the identification appears at the last step, not before (a step shows what is known at that step)
    for e in IDENTIFICATION:
        assert ents[e]["timelines"] == {"step"} and not ents[e]["static"], e
        assert [k for k, _ in _by_step(ents[e], next(c for c in ents[e]["batches"][0].schema.names
                                                       if c.endswith(":positions")))] == [info.steps - 1], e
    names = {k for s in case.result.identification.steps for k, v in s.numbers.items() if v is not None}
    assert {f"/steps/numbers/{unit_of(k)}/{D.entity_name(k)}" for k in names} <= set(ents)
    assert len(RrdReader(path).recordings()) == 1
    # not solved: no estimated footprint or matches, everything else is there (camera at the true attitude)
    _, _, uinfo, uents = unsolved
    assert not unsolved[0].result.solved and uinfo.status == "failed"
    assert STATIC | PER_STEP <= set(uents)
    assert "/sky/fov/estimated" not in uents and not IDENTIFICATION & set(uents)
    M = np.array(column(uents["/camera"], "Transform3D:mat3x3")[0]).reshape(3, 3).T  # stored column-major
    np.testing.assert_allclose(M, unsolved[0].frame.truth["R"], atol=1e-6)


def test_steps_on_the_timeline(solved, unsolved):
    for case, _, info, ents in (solved, unsolved):
        steps = case.result.identification.steps
        assert info.steps == len(steps) > 0
        log = ents["/steps/log"]
        assert log["rows"] == len(steps)
        assert [v[0].split("\n")[0] for v in column(log, "TextLog:text")] == [f"[{s.kind}] {s.note}" for s in steps]
        assert [v[0] for v in column(log, "TextLog:level")] == [s.kind for s in steps]
        for b in log["batches"]:
            assert sorted(b.column("step").to_pylist()) == list(range(len(steps)))
        # the surviving hypotheses: arcs between their catalog stars, at each step that has some, cleared after
        views = step_views(steps, case.solver.catalog.xyz, len(case.result.centroids))
        cand = _by_step(ents["/sky/step/candidates"], "LineStrips3D:strips")
        want = [k for k, v in enumerate(views) if "candidates" in v.drawables]
        assert [k for k, _ in cand] == want and want
        for k, strips in cand:
            assert len(strips) == len(views[k].drawables["candidates"].segments)
            pts = np.array(strips[0])
            np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 1.0, atol=1e-5)
        obs = _by_step(ents["/camera/image/step/observed"], "Points2D:labels")
        assert [(k, list(x)) for k, x in obs] == [(k, [f"#{i}" for i in s.observed]) for k, s in enumerate(steps)
                                                  if s.observed]
        # numbers: one scalar series per name, under its unit, a value at each step that has it
        for name in {k for s in steps for k in s.numbers}:
            want = [float(s.numbers[name]) for s in steps if s.numbers.get(name) is not None
                    and np.isfinite(float(s.numbers[name]))]
            got = [v[0] for v in column(ents["/" + D.number_path(name)], "Scalars:scalars")]
            np.testing.assert_allclose(got, want)


def test_image_and_camera(solved):
    case, _, _, ents = solved
    cam = case.result.camera
    img = ents["/camera/image"]
    blob = column(img, "EncodedImage:blob")[0]
    assert column(img, "EncodedImage:media_type")[0] == ["image/jpeg"]
    data = np.frombuffer(bytes(blob[0]), dtype=np.uint8)
    decoded = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    assert decoded.shape == (cam.height, cam.width) == case.frame.image.shape
    assert len(data) < 300_000  # compressed: a raw 16-bit 1024^2 frame is 2 MB
    assert column(img, "Pinhole:resolution")[0] == [[cam.width, cam.height]]
    K = np.array(column(img, "Pinhole:image_from_camera")[0]).reshape(3, 3).T  # stored column-major
    # Rerun's pixel (0, 0) spans [0, 1]: skyview's principal point (W-1)/2 is Rerun's W/2
    np.testing.assert_allclose(K, [[cam.fx, 0, cam.width / 2], [0, cam.fy, cam.height / 2], [0, 0, 1]], rtol=1e-6)
    # the stretched 8-bit picture still shows the stars where the centroids are
    for u, v in case.result.centroids.uv[:5]:
        assert decoded[int(round(v)), int(round(u))] > 60


def test_matches_and_centroids(solved):
    case, _, _, ents = solved
    r = case.result
    cat = case.solver.catalog
    labels = column(ents["/sky/matches/labels"], "Points3D:labels")[0]
    assert set(labels) <= {f"HIP {m['hip']} (#{m['index']})" for m in r.matches} and len(labels) >= 2
    pos = np.array(column(ents["/sky/matches"], "Points3D:positions")[0])
    np.testing.assert_allclose(pos, cat.xyz[[cat.index_of(m["hip"]) for m in r.matches]], atol=1e-6)
    truth_hips = {s["hip"] for s in case.frame.truth["stars"]}
    assert {m["hip"] for m in r.matches} <= truth_hips
    cl = column(ents["/camera/image/centroids"], "Points2D:labels")[0]
    assert cl == [f"#{k}" for k in range(len(r.centroids))]
    cpos = np.array(column(ents["/camera/image/centroids"], "Points2D:positions")[0])
    np.testing.assert_allclose(cpos, r.centroids.uv + 0.5, atol=1e-3)
    # the matched stars reprojected into the image land on their centroids
    mpos = np.array(column(ents["/camera/image/matches"], "Points2D:positions")[0])
    np.testing.assert_allclose(mpos, [[m["u"] + 0.5, m["v"] + 0.5] for m in r.matches], atol=3.0)  # 87 urad noise
    assert len(column(ents["/sky/catalog"], "Points3D:positions")[0]) == len(cat)


def _label_boxes(anchors: np.ndarray, texts: list[str]) -> np.ndarray:
    """(K, 4) screen boxes of Rerun labels on points at `anchors` (screen pixels): centred under the point."""
    size = D.label_sizes(texts)
    drop = np.stack([np.zeros(len(size)), size[:, 1] / 2 + D.LABEL_DROP_PX], axis=1)
    centre = np.asarray(anchors, dtype=np.float64) + drop
    return np.concatenate([centre - size / 2, centre + size / 2], axis=1)


def _assert_apart(boxes: np.ndarray, stars: np.ndarray, radius) -> None:
    """No two boxes overlap, and no box comes within `radius` of a star."""
    for k, b in enumerate(boxes):
        for c in boxes[k + 1:]:
            assert not (b[0] < c[2] and c[0] < b[2] and b[1] < c[3] and c[1] < b[3]), (b, c)
        near = np.clip(stars, b[:2], b[2:]) - stars
        assert np.all(np.hypot(near[:, 0], near[:, 1]) >= np.broadcast_to(radius, len(stars)) - 1e-3), b


def test_labels_sit_beside_the_stars_on_no_label_and_no_star(solved):
    """Read back and drawn as Rerun draws a label (centred under its point, LABEL_HEIGHT_PX tall) at the
    layout's window: in the image view no label box overlaps another or a marked star (centroid, truth
    ring); in the sky view, at the blueprint's eye, none overlaps another or an identified, observed or
    catalog star. Each label is next to its own star; the result document says what is labelled."""
    case, _, _, ents = solved
    r, cat, cam = case.result, case.solver.catalog, case.result.camera
    # the image view, in its screen pixels
    s = D.image_scale(cam)
    texts = column(ents["/camera/image/labels"], "Points2D:labels")[0]
    at = np.array(column(ents["/camera/image/labels"], "Points2D:positions")[0])
    assert len(texts) >= 5 and set(texts) <= {f"HIP {m['hip']}" for m in r.matches}
    marks = np.concatenate([r.centroids.uv, [[t["u_noisy"], t["v_noisy"]] for t in case.frame.truth["stars"]]])
    boxes = _label_boxes(at * s, texts)
    _assert_apart(boxes, (marks + 0.5) * s, D.IMAGE_RING_PX)
    x0, y0, x1, y1 = D.image_view_bounds(cam)[-1]  # in the view: the image and the margins Rerun leaves beside it
    assert np.all(boxes[:, :2] >= [x0, y0]) and np.all(boxes[:, 2:] <= [x1, y1]) and x1 - x0 <= D.IMAGE_VIEW_PX[0]
    by_hip = {f"HIP {m['hip']}": np.array([m["u"], m["v"]]) for m in r.matches}
    for t, b in zip(texts, boxes):
        star = (by_hip[t] + 0.5) * s
        gap = np.hypot(*(np.clip(star, b[:2], b[2:]) - star))
        assert gap < D.IMAGE_RING_PX + 3 * D.LABEL_GAP_PX, t  # beside its star (the reprojected match: +-3 px)
    # the sky view, at the blueprint's eye
    eye = D.SkyEye.behind(r.R)
    texts = column(ents["/sky/matches/labels"], "Points3D:labels")[0]
    lpos = np.array(column(ents["/sky/matches/labels"], "Points3D:positions")[0])
    np.testing.assert_allclose(np.linalg.norm(lpos, axis=1), 1.0, atol=1e-5)  # on the sphere, among the stars
    px, _, F = eye.project(lpos)
    boxes = _label_boxes(px, texts)
    assert len(boxes) >= 2 and boxes.min() >= 0 and np.all(boxes[:, 2:] <= D.SKY_VIEW_PX)
    matched = cat.xyz[[cat.index_of(m["hip"]) for m in r.matches]]
    observed = cam.unproject(r.centroids.uv) @ r.R
    for xyz, radius in ((matched, D.SKY_MATCH_RADIUS), (observed, D.SKY_OBSERVED_RADIUS),
                        (cat.xyz, D.catalog_radii(cat))):
        p, z, _ = eye.project(xyz)
        front = z > 0.05
        _assert_apart(boxes, p[front], (np.broadcast_to(radius, len(xyz)) * F / np.where(front, z, 1))[front])
    text = column(ents["/result"], "TextDocument:text")[0][0]
    assert f"the image labels {len(column(ents['/camera/image/labels'], 'Points2D:labels')[0])} of the " \
           f"{len(r.matches)} identified stars and the sky {len(texts)}" in text


def test_camera_pose_direction(solved):
    """ChildFromParent with mat3x3 = R: the camera's +z (the image centre) is the boresight R[2] in ICRS."""
    case, _, _, ents = solved
    R = case.result.R
    M = np.array(column(ents["/camera"], "Transform3D:mat3x3")[0]).reshape(3, 3).T  # column-major
    assert column(ents["/camera"], "Transform3D:relation")[0] == [rr.TransformRelation.ChildFromParent.value]
    np.testing.assert_allclose(M, R, atol=1e-6)
    # child (camera) from parent (ICRS): v_cam = M v_icrs, so camera +z is M^T e_z in ICRS
    np.testing.assert_allclose(M.T @ [0, 0, 1], R[2], atol=1e-6)
    # and a matched star's pixel, unprojected and taken to ICRS the same way, is that star
    cam, cat = case.result.camera, case.solver.catalog
    m = min(case.result.matches, key=lambda m: np.hypot(m["u"] - cam.cx, m["v"] - cam.cy))
    d = M.T @ cam.unproject([[m["u"], m["v"]]])[0]
    assert np.degrees(np.arccos(np.clip(d @ cat.xyz[cat.index_of(m["hip"])], -1, 1))) * 3600 < 30


def test_result_document(solved, unsolved):
    text = column(solved[3]["/result"], "TextDocument:text")[0][0]
    r = solved[0].result
    assert text.startswith("# angle (paper): solved")
    for piece in ("RA **", "1σ boresight", "## Truth", "error: boresight", "wrong matches: **0**", "| time |",
                  "identify", "asinh stretch", "seed | 8"):
        assert piece in text, piece
    assert f"{np.degrees(np.arctan2(r.R[2, 1], r.R[2, 0])) % 360:.5f}" in text
    utext = column(unsolved[3]["/result"], "TextDocument:text")[0][0]
    assert "failed" in utext.splitlines()[0] and unsolved[0].result.reason in utext
    assert "| why |" in utext and "Try" in utext  # why not solved, in words, and what to try


def test_step_layers_are_drawn_by_role(solved, tmp_path):
    """Typed layers become the present module's roles: a population -> sky/step/points, hypotheses ->
    sky/step/candidates; a role absent at the next step is cleared; numbers plot by unit."""
    case = solved[0]
    rng = np.random.default_rng(0)
    pop = rng.normal(size=(30, 3))
    pop /= np.linalg.norm(pop, axis=1, keepdims=True)
    steps = [Step("generation", "gen 0", observed=[0, 1], numbers={"best cost": 3.5},
                  layers=(Population(pop.astype(np.float32), np.linspace(0, 1, 30)),
                          Hypotheses.sample([0, 1], np.array([[1, 2], [3, 4]])))),
             Step("generation", "gen 1", numbers={"best cost": 1.25},
                  layers=(Posterior(np.ones(7) / 7, np.arange(7), np.arange(3), np.ones(3) / 7),)),
             Step("verify", "done", numbers={"best cost": float("nan")})]
    ident = dataclasses.replace(case.result.identification, steps=steps)
    result = dataclasses.replace(case.result, identification=ident)
    path = tmp_path / "layers.rrd"
    info = rec.record_solve(path, result, case.frame.image, catalog=case.solver.catalog)
    ents = read(path)
    assert info.steps == 3
    pts = _by_step(ents["/sky/step/points"], "Points3D:positions")
    assert [k for k, _ in pts] == [0, 1]  # the population, then the posterior's stars
    np.testing.assert_allclose(np.array(pts[0][1]), pop, atol=1e-6)
    assert [k for k, _ in _by_step(ents["/sky/step/points"], "Clear:is_recursive")] == [2]
    assert [k for k, _ in _by_step(ents["/sky/step/candidates"], "LineStrips3D:strips")] == [0]
    assert [v[0] for v in column(ents["/steps/numbers/cost/best_cost"], "Scalars:scalars")] == [3.5, 1.25]
    assert not any(k.startswith(("/truth", "/camera/image/truth", "/sky/fov/true")) for k in ents)


def _by_step(entity: dict, name: str) -> list[tuple[int, object]]:
    """(step, value) of one component column, in step order."""
    rows = []
    for b in entity["batches"]:
        if name in b.schema.names:
            rows += list(zip(b.column("step").to_pylist(), b.column(name).to_pylist()))
    return sorted(rows, key=lambda r: r[0])


def test_a_search_region_is_drawn_as_a_closed_outline_and_cleared(solved, tmp_path):
    """A square search region -> one closed strip of great-circle edges at sky/step/outline; cleared after."""
    case = solved[0]
    c = np.array([[1.0, 0.01, 0.01], [0.01, 1.0, 0.01], [0.01, 0.01, 1.0], [0.6, 0.6, 0.6]])
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    box = SearchRegion("square", c.mean(0) / np.linalg.norm(c.mean(0)), 0.5, corners=c)
    steps = [Step("a", "box", layers=(box,)), Step("b", "nothing")]
    ident = dataclasses.replace(case.result.identification, steps=steps)
    path = tmp_path / "outline.rrd"
    rec.record_solve(path, dataclasses.replace(case.result, identification=ident), case.frame.image,
                     catalog=case.solver.catalog)
    x = read(path)["/sky/step/outline"]
    (k, strips), = _by_step(x, "LineStrips3D:strips")
    segs, n = np.array(strips), OUTLINE_EDGE_POINTS - 1
    assert k == 0 and len(segs) == 4 * n  # four edges of n segments each
    np.testing.assert_allclose(segs[::n, 0], c, atol=1e-6)  # through the corners, in order
    np.testing.assert_allclose(segs[-1, 1], c[0], atol=1e-6)  # closed
    assert [k for k, _ in _by_step(x, "Clear:is_recursive")] == [1]


@pytest.fixture(scope="module")
def genetic(tmp_path_factory):
    """Case 1 of sun20 solved by the genetic method (improved variant), recorded."""
    runner = CaseRunner("genetic", "sun20", variant="improved")
    case = runner.run(1)
    assert case.result.solved, case.result.reason
    path = tmp_path_factory.mktemp("rec") / "genetic-sun20-1.rrd"
    info = runner.record(case, path)
    return case, path, info, read(path)


@pytest.mark.slow
def test_a_genetic_search_box_is_recorded_as_an_outline(genetic):
    """A real genetic solve: its square boxes and roll circle (SearchRegion layers) become closed outlines
    at sky/step/outline at every step that has one (the whole-sky box has none)."""
    case, path, info, ents = genetic
    box = ents["/sky/step/outline"]
    assert box["timelines"] == {"step"} and not box["static"]
    steps = case.result.identification.steps
    want = [(k, region_polyline(s.layer(SearchRegion))) for k, s in enumerate(steps) if s.layer(SearchRegion)]
    want = [(k, p) for k, p in want if p is not None]
    assert {steps[k].layer(SearchRegion).kind for k, _ in want} == {"square", "roll"}
    strips = _by_step(box, "LineStrips3D:strips")
    assert [k for k, _ in strips] == [k for k, _ in want]
    for (k, poly), (_, got) in zip(want, strips):
        got = np.array(got, dtype=np.float64)
        np.testing.assert_allclose(got[:, 0], poly[:-1], atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(got.reshape(-1, 3), axis=1), 1.0, atol=1e-6)
        b = steps[k].layer(SearchRegion)
        if b.kind == "roll":  # the roll circle, at its radius from the found boresight
            np.testing.assert_allclose(np.arccos(np.clip(got[:, 0] @ b.center, -1, 1)), b.radius_rad, atol=1e-5)


# ============================================================================ paths and the CLI

def test_bad_paths_are_one_line_errors_and_overwrite_nothing(solved, tmp_path, capsys):
    case, _, _, _ = solved
    args = dict(result=case.result, image=case.frame.image, catalog=case.solver.catalog)
    with pytest.raises(BadInput, match="does not exist"):
        rec.record_solve(tmp_path / "missing" / "x.rrd", **args)
    with pytest.raises(BadInput, match=r"\.rrd"):
        rec.record_solve(tmp_path / "x.txt", **args)
    with pytest.raises(BadInput, match="is a folder"):
        (tmp_path / "d.rrd").mkdir()
        rec.record_solve(tmp_path / "d.rrd", **args)
    existing = tmp_path / "keep.rrd"
    existing.write_bytes(b"precious")
    with pytest.raises(BadInput, match="exists; use --force"):
        rec.record_solve(existing, **args)
    assert existing.read_bytes() == b"precious"
    if os.geteuid() == 0:  # root writes anywhere: use a folder no one can create files in
        locked = Path("/proc")
    else:
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o500)
    with pytest.raises(BadInput, match="cannot write"):
        rec.record_solve(locked / "x.rrd", **args)
    info = rec.record_solve(existing, force=True, **args)
    assert info.bytes == existing.stat().st_size > 1000 and existing.read_bytes()[:3] == b"RRF"
    left = sorted(p.name for p in tmp_path.iterdir())  # no temporary files left behind
    assert left == ["d.rrd", "keep.rrd"] + (["locked"] if locked != Path("/proc") else [])
    cat = case.solver.catalog
    other = cat.select(np.flatnonzero(cat.hip != case.result.matches[0]["hip"]), "one matched star removed")
    with pytest.raises(BadInput, match="not the one the solver used"):
        rec.record_solve(tmp_path / "other.rrd", **{**args, "catalog": other})
    # the CLI: one line, exit 2, before any work is done
    for argv in (["record", "--out", str(tmp_path / "missing" / "x.rrd")],
                 ["record", "--out", str(existing)],
                 ["record", "--out", str(tmp_path / "x.png")],
                 ["record", "--method", "nope", "--out", str(tmp_path / "n.rrd")],
                 ["replay", str(tmp_path / "none.rrd")],
                 ["replay", str(tmp_path / "d.rrd")]):
        code = main(argv)
        out, err = capsys.readouterr()
        assert code == 2 and one_line_error(err), (argv, err)
    (tmp_path / "fake.rrd").write_text("not a recording")
    assert main(["replay", str(tmp_path / "fake.rrd")]) == 2
    assert "not a Rerun recording" in capsys.readouterr().err


def test_record_command(tmp_path, capsys):
    out = tmp_path / "angle-cole8-8.rrd"
    assert main(["record", "--method", "angle", "--scenario", "cole8", "--seed", "8", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"recorded {out}" in text and "solved" in text and "MB" in text
    ents = read(out)
    assert {"/sky/catalog", "/camera/image", "/steps/log", "/result"} <= set(ents)
    assert main(["record", "--seed", "8", "--out", str(out)]) == 2  # exists
    capsys.readouterr()
    assert main(["record", "--seed", "8", "--out", str(out), "--force"]) == 0


@pytest.mark.slow
def test_solve_records_only_when_asked(tmp_path):
    png = tmp_path / "orion.png"
    assert main(["simulate", "--ra", "83.8", "--dec", "-5.4", "--roll", "30", "--fov-deg", "8", "--seed", "1",
                 "--out", str(png)]) == 0
    out = tmp_path / "orion.rrd"
    code = ("import json, sys; from skyview.cli import main; rc = main(sys.argv[1:]); "
            "print(json.dumps({'rc': rc, 'rerun': 'rerun' in sys.modules, 'rec': 'skyview.record.recording' in sys.modules}),"
            " file=sys.stderr)")
    plain = subprocess.run([sys.executable, "-c", code, "solve", str(png), "--fov-deg", "8", "--json"],
                           capture_output=True, text=True, timeout=120, env=ENV)
    flags = json.loads(plain.stderr.strip().splitlines()[-1])
    assert flags == {"rc": 0, "rerun": False, "rec": False}  # the unrecorded path never imports the recorder
    recorded = subprocess.run([sys.executable, "-c", code, "solve", str(png), "--fov-deg", "8", "--json",
                               "--record", str(out)], capture_output=True, text=True, timeout=120, env=ENV)
    assert json.loads(recorded.stderr.strip().splitlines()[-1])["rc"] == 0, recorded.stderr
    assert json.loads(recorded.stdout)["status"] == "solved"  # stdout stays pure JSON
    assert f"recorded {out}" in recorded.stderr
    ents = read(out)
    steps = json.loads(recorded.stdout)["identification"]["steps"]
    assert ents["/steps/log"]["rows"] == steps
    assert "/truth/camera" in ents  # the truth sidecar next to the image was used
    text = column(ents["/result"], "TextDocument:text")[0][0]
    assert "wrong matches: **0**" in text and str(png) in text


def test_bench_records_failed_trials(tmp_path, capsys):
    fails = tmp_path / "failures"
    assert main(["bench", "--method", "angle", "--scenario", "cole8", "-n", "3", "--seed", "0", "--quiet",
                 "--out", str(tmp_path / "results"), "--record-failures", str(fails)]) == 0
    out = capsys.readouterr().out
    summary = json.loads(next((tmp_path / "results").glob("*.json")).read_text())
    bad = [t for t in summary["trials"] if t["outcome"] != "correct"]
    assert len(bad) >= 1
    files = sorted(fails.glob("*.rrd"))
    assert [Path(t["recording"]).name for t in bad] == [f.name for f in files]
    assert all("recording" not in t for t in summary["trials"] if t["outcome"] == "correct")
    assert f"recorded {len(bad)} failed trials into {fails}" in out
    assert files[0].name.startswith("angle-paper-cole8-seed0-trial")
    assert read(files[0])["/steps/log"]["rows"] >= 1
    assert main(["bench", "-n", "1", "--quiet", "--out", str(tmp_path / "r2"),
                 "--record-failures", str(tmp_path / "no" / "such")]) == 2


def test_examples_regenerate(tmp_path, monkeypatch, capsys):
    """--examples: each method on its scenario (here only angle), a failure case, and the manifest."""
    import skyview.identify

    monkeypatch.setattr(skyview.identify, "METHODS", {"angle": skyview.identify.METHODS["angle"]})
    assert main(["record", "--examples", "--out", str(tmp_path)]) == 0
    said = capsys.readouterr().out
    manifest = json.loads((tmp_path / "index.json").read_text())
    names = [e["file"] for e in manifest["files"]]
    assert names == ["angle-cole8.rrd", "failure-angle-cole8-false.rrd"], said
    first, failure = manifest["files"]
    assert first["outcome"] == "correct" and failure["status"] == "failed"
    for e in manifest["files"]:
        ents = read(tmp_path / e["file"])
        assert ents["/steps/log"]["rows"] == e["steps"] and e["bytes"] == (tmp_path / e["file"]).stat().st_size
    assert "/camera/image/truth/false_stars" in read(tmp_path / "failure-angle-cole8-false.rrd")
    assert main(["record", "--examples", "--out", str(tmp_path)]) == 2  # exists without --force
    capsys.readouterr()


def test_committed_examples_are_small_and_readable():
    folder = REPO / "recordings"
    manifest = json.loads((folder / "index.json").read_text())
    assert manifest["files"] and any(e["file"].startswith("failure-") for e in manifest["files"])
    for e in manifest["files"]:
        p = folder / e["file"]
        assert p.stat().st_size == e["bytes"] < 3_000_000, e
        ents = read(p)
        assert ents["/steps/log"]["rows"] == e["steps"]
        assert {"/sky/catalog", "/camera/image", "/camera/image/centroids", "/result"} <= set(ents)


# ============================================================================ the viewer

def _listening_on(port: int) -> list[str]:
    """Local addresses listening on `port` (IPv4), from /proc/net/tcp."""
    addrs = []
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        ip_hex, port_hex = local.split(":")
        if state == "0A" and int(port_hex, 16) == port:
            addrs.append(socket.inet_ntoa(bytes.fromhex(ip_hex)[::-1]))
    return addrs


def _children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _connect(port: int, timeout_s: float = 30.0):
    from rerun.experimental import ViewerClient

    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        try:
            client = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
            client.get_state()
            return client
        except Exception:
            time.sleep(0.2)
    raise AssertionError("the headless Rerun viewer did not come up")


def _headless_viewer(*extra: str, size: str = "1280x800"):
    port = free_port()
    proc = subprocess.Popen([str(rerun_binary()), "--headless", "--bind", "127.0.0.1", "--port", str(port),
                             "--hide-welcome-screen", "--window-size", size, *extra],
                            env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return proc, port


@pytest.mark.slow
def test_replay_serves_the_web_viewer_on_localhost_and_stops(solved):
    _, path, info, _ = solved
    port, grpc = free_port(), free_port()
    proc = subprocess.Popen([sys.executable, "-m", "skyview", "replay", str(path), "--web", "--port", str(port),
                             "--grpc-port", str(grpc)], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("Rerun web viewer for"), line + proc.stderr.read()
        url = line.split(": ", 1)[1].strip()
        assert url.startswith(f"http://127.0.0.1:{port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}")
        with urllib.request.urlopen(url, timeout=10) as r:
            assert r.status == 200 and b"<html" in r.read(2000).lower()
        assert _listening_on(port) == ["127.0.0.1"] and _listening_on(grpc) == ["127.0.0.1"]
        kids = _children(proc.pid)
        assert len(kids) == 1 and Path(f"/proc/{kids[0]}/exe").resolve() == rerun_binary().resolve()
        if HAS_LAVAPIPE:  # a viewer connected to the served stream receives the whole recording
            vproc, vport = _headless_viewer(f"rerun+http://127.0.0.1:{grpc}/proxy", size="640x400")
            try:
                client = _connect(vport)
                deadline = time.monotonic() + 20
                while time.monotonic() < deadline:
                    state = client.get_state()
                    tl = [t for r in state.recordings for t in r.timelines if t.name == "step"]
                    if tl and (tl[0].start, tl[0].end) == (0, info.steps - 1):
                        break
                    time.sleep(0.2)
                assert tl and (tl[0].start, tl[0].end) == (0, info.steps - 1)
            finally:
                vproc.terminate()
                vproc.wait(timeout=10)
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        assert proc.wait(timeout=15) == 0
        assert "viewer stopped" in proc.stdout.read()
        deadline = time.monotonic() + 5
        while any(_alive(k) for k in kids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(k) for k in kids), "the Rerun binary outlived skyview replay"
        assert _listening_on(port) == [] and _listening_on(grpc) == []
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="module")
def viewer():
    if not HAS_LAVAPIPE:
        pytest.skip("Rerun's headless viewer needs Mesa's software Vulkan driver: apt-get install mesa-vulkan-drivers")
    proc, port = _headless_viewer()
    try:
        yield _connect(port)
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def _open(client, path: Path):
    client.open(str(path))
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        state = client.get_state()
        if not state.loading and state.recordings and state.views and not any(v.reports for v in state.views):
            return state
        time.sleep(0.1)
    return client.get_state()


def _shot(client, step: int, settle_s: float = 10.0) -> np.ndarray:
    """A screenshot at `step` once the picture has settled (two shots in a row alike): on a loaded
    machine the first shot after moving the time cursor can still show the previous frame."""
    client.set_time("step", sequence=step, play_state="paused")
    grab = lambda: np.asarray(Image.open(io.BytesIO(client.take_screenshot())).convert("RGB")).astype(int)  # noqa: E731
    last = grab()
    deadline = time.monotonic() + settle_s
    while time.monotonic() < deadline:
        time.sleep(0.25)
        now = grab()
        if np.array_equal(now, last):
            return now
        last = now
    return last


@needs_lavapipe
def test_viewer_renders_a_step(viewer, solved, tmp_path):
    case, path, info, _ = solved
    state = _open(viewer, path)
    views = {v.name: v for v in state.views}
    assert {"sky", "image", "step log", "result"} <= set(views) and any(n.startswith("step numbers (") for n in views)
    assert views["sky"].origin == "/" and views["image"].origin == "/camera/image"
    assert all(not v.reports for v in state.views), [(v.name, v.reports) for v in state.views]
    active = next(r for r in state.recordings if r.store_id == state.active_recording)
    assert any(t.name == "step" and (t.start, t.end) == (0, info.steps - 1) for t in active.timelines)
    first, last = _shot(viewer, 1), _shot(viewer, info.steps - 1)
    Image.fromarray(first.astype(np.uint8)).save(tmp_path / "step1.png")
    h, w, _ = first.shape
    sky = first[int(0.1 * h):int(0.9 * h), :int(0.55 * w)]
    assert sky.std() > 10 and (sky.max(axis=-1) > 120).mean() > 0.002, "the 3D sky looks blank"
    assert (np.abs(first - last).sum(-1) > 30).mean() > 1e-4  # moving the time cursor changed the picture


@needs_lavapipe
def test_viewer_puts_the_image_centre_on_the_camera_axis(viewer, solved, tmp_path):
    """Rendered by Rerun itself: pixels drawn in the image (2D, under the pinhole) land where their skyview
    directions (R^T unproject(u, v), 3D) are — at the image centre (camera +z) and off-centre (handedness)."""
    case = solved[0]
    cam, R = case.result.camera, case.result.R
    uv = np.array([[cam.cx, cam.cy], [cam.cx + 0.3 * cam.width, cam.cy - 0.2 * cam.height]])
    d = D.IMAGE_PLANE_DISTANCE
    xyz = (cam.unproject(uv) / cam.unproject(uv)[:, 2:3]) * d @ R  # on the image plane, in ICRS
    colors = [(255, 0, 0), (0, 0, 255)]
    b = R[2]
    bp = rrb.Blueprint(rrb.Spatial3DView(origin="/", background=[0, 0, 0], line_grid=rrb.LineGrid3D(visible=False),
                                         spatial_information=D.NO_AXES,
                                         eye_controls=rrb.EyeControls3D(position=(-0.4 * b + 0.3 * R[0]).tolist(),
                                                                        look_target=(0.8 * b).tolist(),
                                                                        eye_up=(-R[1]).tolist())),
                       collapse_panels=True)
    path = tmp_path / "axis.rrd"
    stream = rr.RecordingStream("skyview-axis-test", send_properties=False)
    stream.save(str(path), default_blueprint=bp)
    stream.log(D.CAMERA, D.pose(R), static=True)
    stream.log(D.IMAGE, *D.pinhole(cam, color=(40, 40, 40)), static=True)
    stream.set_time("step", sequence=0)
    stream.log("sky/probe", rr.Points3D(xyz.astype(np.float32), colors=colors, radii=rr.Radius.ui_points(6)))
    stream.set_time("step", sequence=1)
    stream.log("sky/probe", rr.Clear(recursive=False))
    stream.log(f"{D.IMAGE}/probe", rr.Points2D(D.rerun_uv(uv), colors=colors, radii=rr.Radius.ui_points(6)))
    stream.flush()
    stream.disconnect()
    _open(viewer, path)

    def centre(img, rgb):
        c = np.array(rgb)
        mask = (np.abs(img - c).sum(-1) < 120)
        assert mask.sum() > 10, f"no {rgb} marker in the picture"
        ys, xs = np.nonzero(mask)
        return np.array([xs.mean(), ys.mean()])

    s3, s2 = _shot(viewer, 0), _shot(viewer, 1)
    Image.fromarray(np.concatenate([s3, s2], 1).astype(np.uint8)).save(tmp_path / "axis.png")
    for rgb in colors:
        a, b2 = centre(s3, rgb), centre(s2, rgb)
        assert np.linalg.norm(a - b2) < 4.0, (rgb, a, b2)


@needs_lavapipe
def test_viewer_draws_the_genetic_search_box(genetic, tmp_path):
    """Rendered by Rerun (a viewer of its own: one that showed other recordings keeps their 3D eye): the
    orange outline (the palette's) is on screen at the first spiral-stage and the first roll step, not at the first
    (whole-sky) GA's."""
    case, path, info, _ = genetic
    steps = case.result.identification.steps
    first: dict[str, int] = {}
    for k, s in enumerate(steps):
        if s.layer(SearchRegion) is not None:
            first.setdefault(s.layer(SearchRegion).kind, k)
    proc, port = _headless_viewer()
    try:
        client = _connect(port)
        _open(client, path)

        def lavender(k: int) -> float:
            img = _shot(client, k)
            Image.fromarray(img.astype(np.uint8)).save(tmp_path / f"genetic-step{k}.png")
            sky = img[:, :int(0.6 * img.shape[1])]
            return float((np.abs(sky - np.array(PALETTE["outline"])).sum(-1) < 60).mean())

        none, square, roll = lavender(first["sky"]), lavender(first["square"]), lavender(first["roll"])
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert square > none + 2e-4 and roll > none + 2e-4, (none, square, roll)


def test_a_fisheye_photograph_is_recorded_where_its_lens_saw_it(tmp_path, catalog, solved):
    """`skyview solve ALLSKY --record`: Rerun's Pinhole has no fisheye model, so the image in 3-D is the sensor's
    mesh (`sky_geometry.sensor_mesh`) at IMAGE_PLANE_DISTANCE, textured with the image shown (Rerun's texture
    coordinates, the top-left corner at 0, 0), and the Pinhole's own plane is kept small; its 2-D view reads the
    image as before. A pinhole's recording has no such mesh."""
    from skyview.core.attitude import random_attitudes
    from skyview.core.sky_geometry import sensor_mesh
    from skyview.simulate.render import simulate_image
    from skyview.simulate.scenarios import get_scenario

    sc = get_scenario("allsky180")
    frame = simulate_image(catalog, sc.camera(), random_attitudes(1, np.random.default_rng(3))[0], sc.sensor(),
                           seed=3, **sc.render_kwargs())
    png, rrd = tmp_path / "allsky.png", tmp_path / "allsky.rrd"
    cv2.imwrite(str(png), frame.image)
    assert main(["solve", str(png), "--json", "--record", str(rrd)]) == 0
    entities = read(rrd)
    photo = entities["/camera/photo"]
    assert photo["static"]
    positions = np.array(column(photo, "Mesh3D:vertex_positions")[0], dtype=np.float64)
    texcoords = np.array(column(photo, "Mesh3D:vertex_texcoords")[0], dtype=np.float64)
    triangles = np.array(column(photo, "Mesh3D:triangle_indices")[0])
    from skyview.solver.pipeline import solve_image

    camera = solve_image(frame.image).camera  # (the same solve: the camera the recording drew)
    assert camera.fisheye
    directions, faces, pixels = sensor_mesh(camera)
    np.testing.assert_allclose(positions, directions * D.IMAGE_PLANE_DISTANCE, atol=1e-5)
    np.testing.assert_allclose(texcoords, (pixels + 0.5) / [camera.width, camera.height], atol=1e-6)
    assert np.array_equal(triangles, faces) and len(faces) > 7000
    plane = column(entities["/camera/image"], "Pinhole:image_plane_distance")[0]
    assert plane == pytest.approx([D.FISHEYE_IMAGE_PLANE], rel=1e-6)
    assert "/camera/photo" not in solved[3]  # a pinhole's image stays on its Pinhole's plane
    plane = column(solved[3]["/camera/image"], "Pinhole:image_plane_distance")[0]
    assert plane == pytest.approx([D.IMAGE_PLANE_DISTANCE], rel=1e-6)
