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

from skyview.attitude import R_from_radec_roll
from skyview.camera import Camera
from skyview.catalog import radec_to_vec
from skyview.cli import main
from skyview.identify.base import Step
from skyview.viewer import picture, steps
from skyview.viewer.panel import result_markdown, step_markdown
from skyview.viewer.run import SceneConfig, Solvers, compare, simulate, solve
from skyview.viewer.scene import NODES, frustum_scale, local_grid, nearest_star, pose_wxyz, ray_to_sphere

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
    d = steps.step_drawables(st, xyz, n_observed=6, hip=np.arange(100, 106))
    assert [x.kind for x in d] == ["pick", "pivot", "verify"]
    # a pair is one edge (ARC_POINTS - 1 segments), a triangle three
    assert d[0].segments.shape == (2 * (steps.ARC_POINTS - 1), 2, 3)
    assert d[1].segments.shape == (3 * (steps.ARC_POINTS - 1), 2, 3)
    np.testing.assert_allclose(np.linalg.norm(d[1].segments, axis=2), 1.0, atol=1e-6)  # on the sphere
    # the arcs start and end on the catalog stars of the group
    ends = d[0].segments.reshape(-1, 3).astype(np.float64)
    for row in (0, 1, 3, 4):
        assert np.min(np.linalg.norm(ends - xyz[row], axis=1)) < 1e-6
    # the observed pattern: a pair, a closed triangle; 8 stars are only highlighted (and 6, 7 are not valid)
    assert d[0].pattern.tolist() == [[0, 1]]
    assert sorted(map(sorted, d[1].pattern.tolist())) == [[0, 1], [0, 2], [1, 2]]
    assert len(d[2].pattern) == 0 and d[2].observed.tolist() == [0, 1, 2, 3, 4, 5]
    # rows outside the catalog are dropped, not drawn
    assert d[2].candidates.tolist() == [0, 1, 2] and d[2].n_groups == 0
    # the plotted series: what is left after each step, so the candidates shrink pivot by pivot
    assert steps.default_plot_key(d) == "hypotheses"
    np.testing.assert_array_equal(steps.series(d, "hypotheses")[:2], [4, 1])
    assert np.isnan(steps.series(d, "hypotheses")[2])
    assert steps.numeric_keys(d)[:2] == ["candidates", "hypotheses"]


def test_step_extras_follow_the_recorder_conventions():
    xyz = _tiny_catalog()
    R = R_from_radec_roll(0.3, 0.1, 0.2)
    pop = xyz[[0, 3, 5]].astype(np.float32)
    st = [
        Step("generation", "GA generation", numbers={"best_cost": 3.0},
             extra={"population": pop, "costs": np.array([3.0, 1.0, 2.0], np.float32), "box": {"w": 1}}),
        Step("update", "posterior", catalog=[0, 1, 2], extra={"posterior_top": np.array([0.1, 0.7, 0.2])}),
        Step("answer", "attitude", extra={"R": R, "boresight": R[2].copy()}),
        Step("hyp", "hypotheses", catalog=[0, 1], extra={"hypotheses": np.array([[0, 1], [1, 0]]), "used": [2, 5]}),
    ]
    d = steps.step_drawables(st, xyz, n_observed=5, hip=np.arange(100, 106))
    assert d[0].points.shape == (3, 3) and d[0].point_weights.tolist() == [1.0, 0.0, 0.5]
    assert "population" in d[0].points_name and any(e.startswith("box") for e in d[0].extras)
    np.testing.assert_allclose(d[1].weights, [0.0, 1.0, 1 / 6], atol=1e-12)  # tints the candidates
    assert len(d[2].attitudes) == 1 and d[2].points.shape == (1, 3)  # a rotation and a direction
    assert "HIP 100, HIP 101" in " ".join(d[3].extras) and "used: 2, 5" in d[3].extras


def test_match_triangles_and_centroid_outcomes():
    uv = np.array([[10.0, 10.0], [100.0, 10.0], [50.0, 90.0], [200.0, 200.0], [300.0, 40.0], [5.0, 300.0]])
    tri = steps.match_groups({0: 10, 1: 11, 2: 12, 3: 13}, uv)
    assert all(len(t) == 3 for t in tri) and len(tri) == 2  # a Delaunay mesh of 4 points: 2 triangles
    assert steps.match_groups({0: 10, 1: 11}, uv) == [(10, 11)]
    line = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    assert steps.match_groups({0: 1, 1: 2, 2: 3}, line) == [(1, 2), (2, 3)]  # collinear: a chain
    hip = np.array([500, 501, 502, 503])
    truth = {"stars": [{"hip": 500, "u": 10.0, "v": 10.0}, {"hip": 509, "u": 100.0, "v": 10.0}],
             "false_stars": [{"u": 50.0, "v": 90.0}]}
    out = steps.centroid_outcomes(6, 5, {0: 0, 1: 1}, uv, hip, truth)
    assert out == ["identified", "wrong match", "false star", "unidentified", "unidentified", "not used"]
    assert steps.centroid_outcomes(2, 2, {0: 0}, uv[:2], hip, None) == ["identified", "unidentified"]


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


# ============================================================================ a session, server side

@pytest.fixture(scope="module")
def session():
    import viser

    from skyview.viewer.session import Session

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    s = Session(server, Solvers())
    assert s.wait_idle(60)
    yield server, s
    s.close()
    with contextlib.redirect_stdout(io.StringIO()):
        server.stop()


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
    import skyview.viewer.session as session_mod

    server, s = session
    monkeypatch.setattr(session_mod, "PLAY_INTERVAL_S", 0.05)
    n = len(s.run.drawables)
    s.panel.step.value = n - 1
    s.toggle_play()  # from the last step, Play starts again at the first
    assert s.panel.play.label == "Pause"
    deadline = time.monotonic() + 10
    while s._playing and time.monotonic() < deadline:
        time.sleep(0.02)
    assert s.step_index == n - 1 and s.panel.play.label == "Play the steps"
    monkeypatch.setattr(session_mod, "PLAY_INTERVAL_S", 5.0)
    s.toggle_play()
    time.sleep(0.2)
    assert s.step_index == 0
    s.toggle_play()  # pause
    time.sleep(0.1)
    assert not s._playing and s.panel.play.label == "Play the steps"


def test_bad_input_in_the_ui_shows_an_error_and_the_server_keeps_running(session):
    server, s = session
    s.panel.method.value = "no-such-method"  # what a crafted message could set
    assert s.wait_idle(30) and "unknown method" in s.error and s.panel.error.visible
    s.panel.method.value = "angle"
    assert s.wait_idle(30) and s.error == "" and s.run.result.solved
    upload = lambda name, data: SimpleNamespace(target=SimpleNamespace(value=SimpleNamespace(name=name, content=data)))
    s._guard(s._on_upload)(upload("notes.png", b"this is not an image"))
    assert "not an image" in s.error
    s.panel.upload_fov.value = 0.0
    ok, png = cv2.imencode(".png", s.run.source.image)
    s._guard(s._on_upload)(upload("sky.png", png.tobytes()))
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
    ev = SimpleNamespace(target=SimpleNamespace(value=SimpleNamespace(name="mine.png", content=png.tobytes())))
    s._guard(s._on_upload)(ev)
    assert s.wait_idle(30) and s.error == ""
    assert s.run.source.name == "mine.png" and s.run.source.truth is None and s.run.result.solved
    err = np.degrees(np.arccos(np.clip(s.run.result.R[2] @ np.asarray(frame.truth["R"])[2], -1, 1))) * 3600
    assert err < 60 and "mine.png" in s.panel.result.content and s.panel.back.visible
    # an image with no stars: not solved, no pose, no camera or fine grid drawn, no steps to play
    noise = np.random.default_rng(3).normal(500, 5, (480, 640)).astype(np.uint16)
    ok, png = cv2.imencode(".png", noise)
    s._guard(s._on_upload)(SimpleNamespace(target=SimpleNamespace(value=SimpleNamespace(name="dark.png",
                                                                                         content=png.tobytes()))))
    assert s.wait_idle(30) and s.error == "" and not s.run.result.solved
    assert _node(server, "frustum") is None and _node(server, "fine_grid") is None
    assert s.panel.step.disabled and "No steps" in s.panel.step_text.content and "not solved" in s.panel.status.content
    s.use_simulation()
    assert s.wait_idle(30) and s.run.source.truth is not None and _node(server, "frustum") is not None


def test_clicking_a_star_names_it(session):
    server, s = session
    row = s.run.catalog.index_of(26311)  # Alnilam, in the default field
    ray = SimpleNamespace(ray_origin=(0.0, 0.0, 0.0), ray_direction=tuple(s.run.catalog.xyz[row] * 3.0))
    s._guard(s._on_scene_click)(ray)
    assert "HIP 26311" in s.panel.picked.content and "Alnilam" in s.panel.picked.content
    assert _node(server, "pick") is not None


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
    pytest.importorskip("skyview.record")
    server, s = session
    s.request_compare(methods=["angle"])
    assert s.wait_idle(60)
    assert [(r["method"], r["variant"]) for r in s.compare_rows] == [("angle", "paper"), ("angle", "improved")]
    assert "| angle | improved | solved |" in s.panel.compare_table.content
    rrd = s.export_rrd(tmp_path / "run.rrd")
    assert rrd.stat().st_size > 10_000 and rrd.read_bytes()[:4] == b"RRF2"


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
    assert [c[0] for c in calls][::2] == list(METHODS)
    assert all(r["status"] == "error" for r in rows) and "RuntimeError: boom" in rows[0]["reason"]


def test_result_and_step_text_for_a_failure():
    solvers = Solvers()
    src = simulate(SceneConfig(ra_deg=10.0, dec_deg=80.0, fov_deg=2.0, mag_limit=4.0), solvers.base_catalog)
    run = solve(src, "angle", "paper", 4.0, solvers)
    assert not run.result.solved
    assert "Not solved" in result_markdown(run) and "reason" in result_markdown(run)
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
    exe = Path(sys.executable).with_name("skyview")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "skyview"]
    p = subprocess.Popen(cmd + ["view", "--port", "0", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    line = p.stdout.readline()
    assert line.startswith("skyview viewer: http://127.0.0.1:"), (line, p.stderr.read() if p.poll() else "")
    return p, line.split()[2]


def _stop_view(p: subprocess.Popen) -> None:
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
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


def _not_blank(png: Path, panel_from_x: int) -> float:
    gray = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)[:, :panel_from_x]
    return float((gray > 110).mean())


@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"no chromium at {CHROMIUM} (apt-get install chromium)")
def test_browser_renders_the_viewer_and_steps_through(tmp_path):
    pw = pytest.importorskip("playwright.sync_api")
    proc, url = _start_view()
    try:
        with pw.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
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
                    counts.append((pg.evaluate(JS_GEOMETRY, NODES["candidates"]),
                                   pg.evaluate(JS_GEOMETRY, NODES["candidate_stars"])))
                assert counts[0][0][0] > 0 and counts[0] != counts[1], counts  # other candidates lit
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
                fov_box = pg.locator("label", has_text="Image FOV").first.locator(
                    "xpath=ancestor::div[contains(@class,'Flex-root')][1]").locator("input").first
                fov_box.fill("12")
                fov_box.press("Enter")
                pg.wait_for_timeout(300)
                t = time.perf_counter()
                pg.locator("input[type=file]").first.set_input_files(str(png))
                pg.get_by_role("tab", name="Result").click()
                pg.get_by_text("image: mine.png, FOV 12°", exact=False).first.wait_for(timeout=30000)
                FIGURES["upload_to_result_s"] = round(time.perf_counter() - t, 2)
                pg.get_by_text("Solved by", exact=False).first.wait_for(timeout=10000)

                # a second tab gets its own session and renders too
                pg2 = _open(browser, url)
                shot2 = tmp_path / "viewer-second-tab.png"
                pg2.screenshot(path=str(shot2))
                _keep(shot2)
                assert _not_blank(shot2, 1000) > 0.002
                assert pg.external == [] and pg2.external == []  # nothing fetched from outside
            finally:
                browser.close()
    finally:
        _stop_view(proc)
        print("\n[viewer figures]", json.dumps(FIGURES))
        _save_figures()


def test_view_command_serves_locally_and_stops_on_ctrl_c():
    proc, url = _start_view("--fov-deg", "12")
    try:
        assert url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url, timeout=10) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
    finally:
        _stop_view(proc)
