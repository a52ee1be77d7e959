"""One viewer session (a browser tab): the coordinator of its panel, 3-D scene, worker, players and camera.

What the tab shows is one `state.ViewState` (the image, the sequence and its frame, the step); the
session turns panel events into changes of that state and draws them: the scene (`scene.SkyScene`),
the panel's text (`panel`), the plots (`plot_control`), the camera (`camera_control`); one `Player`
plays the steps and another the frames of a sequence. A session solves in a background thread
(`worker.Worker`, latest request wins), so the page stays responsive while a slow method runs; the
panel shows the progress. Every callback is guarded: bad input shows an error in the panel, the
server keeps running.
"""

from __future__ import annotations

import functools
import json
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import Callable

import numpy as np
import viser

from skyview.core.camera import Camera
from skyview.core.errors import BadInput
from skyview.core.jsonable import plain
from skyview.identify import VARIANTS
from skyview.present.constellations import image_figures
from skyview.present.sky_grid import image_grid
from skyview.viewer import panel as P
from skyview.viewer.camera_control import CameraControl
from skyview.viewer.geometry import nearest_star, ray_to_sphere, undistorted
from skyview.viewer.picture import annotate, decode_image_bytes, panel_base, stretch, texture
from skyview.viewer.player import Player
from skyview.viewer.plot_control import FramePlot, StepPlot
from skyview.viewer.run import (
    Run,
    SceneConfig,
    Solvers,
    Source,
    check_fov,
    check_method,
    compare,
    needs_sequence,
    random_pointing,
    record_run,
    simulate,
    solve,
    viewer_methods,
)
from skyview.viewer.scene import SkyScene
from skyview.viewer.sequence_run import SequenceRun, TrackedSequenceRun, solve_sequence_run, track_sequence_run
from skyview.viewer.solve_queue import Superseded
from skyview.viewer.state import Quiet, ViewState
from skyview.viewer.worker import Worker

PLAY_INTERVAL_S = 0.7
FRAME_INTERVAL_S = 1.5  # Play the frames: each frame redraws the sensor image, the camera and its steps


def bundled_photographs() -> list[Path]:
    """The real photographs that come with skyview (tests/data/real-images of a source checkout), by name."""
    from skyview.core.catalog import REPO_ROOT

    folder = REPO_ROOT / "tests" / "data" / "real-images"
    return sorted(p for p in folder.glob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff"))


def reported(fn: Callable) -> Callable:
    """A user's action: its errors go to the panel (BadInput as one line), the server keeps running."""

    @functools.wraps(fn)
    def wrapped(self, *args, **kwargs):
        return self._guard(fn)(self, *args, **kwargs)

    return wrapped


class Session:
    """The panel, the 3-D scene and the state of one browser tab (or of the server, in tests).

    owner: a viser `ClientHandle` (one tab) or `ViserServer` (everything it draws goes to every tab).
    initial: an image to start on (`skyview view --image`), else the default simulated scene (config).
    method / variant: the method the panel starts on (default: the first in the list, paper).
    """

    def __init__(self, owner, solvers: Solvers, *, initial: Source | None = None,
                 config: SceneConfig | None = None, method: str | None = None, variant: str | None = None,
                 coverage=None, bench_report: dict | None = None):
        self.owner = owner
        self.coverage = coverage  # a viewer.coverage_layer.CoverageLayer (`skyview view --coverage DIR`)
        self.client = owner if isinstance(owner, viser.ClientHandle) else None
        self.solvers = solvers
        self.lock = threading.RLock()
        self.state = ViewState(upload=initial)
        self._quiet = Quiet()  # programmatic control changes do not trigger solves
        self._closed = False
        self._panel_base: np.ndarray | None = None  # the sensor image of the run on screen, before annotation
        self._panel_grid = None  # its RA/Dec lines (skyview.present.sky_grid), when solved
        self._panel_figures = None  # the constellation figures over it (skyview.present.constellations)
        self.sky = SkyScene(owner.scene)
        self.panel = p = P.build_panel(owner.gui, list(viewer_methods()), list(VARIANTS), config or SceneConfig(),
                                       photos=tuple(p.name for p in bundled_photographs()),
                                       coverage_label=None if coverage is None else coverage.label)
        self.step_plot = StepPlot(p.plot_key, p.step_plot)
        self.frame_plot = FramePlot(p.frame_plot)
        self.camera = CameraControl(self.client, self.sky, self.lock, self.atomic)
        self.step_player = Player(p.play, lambda k: setattr(p.step, "value", k), interval_s=PLAY_INTERVAL_S,
                                  label="Play the steps", on_error=self._show_exception)
        self.frame_player = Player(p.play_frames, lambda k: setattr(p.frame, "value", k), interval_s=FRAME_INTERVAL_S,
                                   label="Play the frames", min_length=2, on_error=self._show_exception)
        with self.atomic():
            self.sky.setup()
            # the sky before the first solve: the guide catalog at the scenario's limit
            self.sky.draw_catalog(solvers.base_catalog.brighter_than(float(p.mag.value)))
        if method is not None:  # the method to start with (`skyview demo --method`), before the first solve
            p.method.value = method
        if variant is not None:
            p.variant.value = variant
        self._wire()
        p.back.visible = initial is not None
        self.worker = Worker(self._show_exception)
        self.worker.watch(p.show_busy, self._show_idle)
        p.upload.disabled = False  # wired and with a worker: an upload is taken from now on
        self.request_solve()
        if coverage is not None:
            self.show_coverage(True)
        if bench_report is not None:  # the six methods compared on a bench's images, beside this image's
            p.bench_table.content = P.bench_markdown(bench_report)

    # ------------------------------------------------------------------ what is on screen (ViewState)
    run = property(lambda self: self.state.run, doc="The image on screen (with a sequence: the frame shown).")
    seq = property(lambda self: self.state.seq, doc="A sequence method's sequence on screen, if any.")
    tracked = property(lambda self: self.state.tracked, doc="A tracked sequence on screen, if any.")
    frame_index = property(lambda self: self.state.frame, doc="The frame shown of the sequence on screen.")
    step_index = property(lambda self: self.state.step, doc="The step shown (None: the whole identification).")
    error = property(lambda self: self.state.error, doc="The error line in the panel ('' when none).")
    timings = property(lambda self: self.state.timings, doc="ms of the last update, draw, step and frame.")
    compare_rows = property(lambda self: self.state.compare_rows, doc="The comparison table's rows.")

    @property
    def rings_drawn(self) -> int:
        """How many of the brightest detections are ringed (the View tab's "Detections drawn")."""
        return max(1, int(self.panel.detections.value))

    def set_detections_drawn(self) -> None:
        """The View tab's "Detections drawn" moved: the run on screen drawn again with that many rings."""
        run = self.state.run
        if self._quiet or run is None:
            return
        self._draw_run(run)

    # ------------------------------------------------------------------ plumbing
    def atomic(self):
        return self.owner.atomic()

    def quietly(self) -> Quiet:
        """`with session.quietly():` set panel controls without a solve per control."""
        return self._quiet

    def close(self) -> None:
        self._closed = True
        self.step_player.stop()
        self.frame_player.stop()
        self.worker.close()

    def _guard(self, fn: Callable) -> Callable:
        """A callback that reports its errors in the panel instead of raising."""

        def wrapped(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except Exception as exc:  # noqa: BLE001 - the server keeps running
                self._show_exception(exc)
                return None

        return wrapped

    def _show_exception(self, exc: Exception) -> None:
        if isinstance(exc, BadInput):
            self.show_error(str(exc))
        else:
            traceback.print_exception(exc, file=sys.stderr)
            self.show_error(f"internal error: {type(exc).__name__}: {exc}")

    def show_error(self, message: str) -> None:
        self.state.error = message
        with self.atomic():
            self.panel.show_error(message)
        if self.client is not None:
            self.client.add_notification("skyview", message, color="red", auto_close_seconds=8.0)

    def clear_error(self) -> None:
        if self.state.error:
            self.state.error = ""
            self.panel.error.visible = False

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Block until no job is running or waiting (tests and scripts)."""
        return self.worker.wait_idle(timeout)

    # ------------------------------------------------------------------ wiring
    def _wire(self) -> None:
        p, g = self.panel, self._guard
        for h in (p.ra, p.dec, p.roll, p.fov, p.resolution, p.noise, p.false_stars, p.dropped, p.seed):
            h.on_update(g(lambda _e: self._scenario_changed()))
        for h in (p.mag, p.variant):
            h.on_update(g(lambda _e: self._solver_changed()))
        for h in (p.n_frames, p.turn, p.turn_step):  # only a sequence (a sequence method, or tracking) uses them
            h.on_update(g(lambda _e: self._solver_changed() if p.sequence_wanted() else None))
        p.track.on_update(g(lambda _e: self._method_changed()))
        p.method.on_update(g(lambda _e: self._method_changed()))
        p.paper_camera.on_click(g(lambda _e: self.use_paper_camera()))
        p.frame.on_update(g(lambda _e: self.set_frame(int(p.frame.value))))
        p.play_frames.on_click(g(lambda _e: self.toggle_play_frames()))
        p.solve.on_click(g(lambda _e: self.request_solve()))
        p.compare.on_click(g(lambda _e: self.request_compare()))
        p.random.on_click(g(lambda _e: self.randomise()))
        p.upload.on_upload(lambda e: self.receive_upload(e.target.value.name, e.target.value.content))
        p.gallery.on_update(g(lambda e: self.load_bundled(str(e.target.value))))
        p.back.on_click(g(lambda _e: self.use_simulation()))
        p.step.on_update(g(lambda _e: self.set_step(int(p.step.value))))
        p.play.on_click(g(lambda _e: self.toggle_play()))
        p.plot_key.on_update(g(lambda _e: self._plot_key_changed()))
        p.export.on_click(g(self._on_export))
        p.export_json.on_click(g(self._on_export_json))
        p.boresight.on_click(g(lambda _e: self.point_view("boresight")))
        p.wide.on_click(g(lambda _e: self.point_view("wide")))
        p.detections.on_update(g(lambda _e: self.set_detections_drawn()))
        for what, h in p.checks.items():
            h.on_update(g(lambda e, what=what: self.set_layer(what, bool(e.target.value))))
        self.owner.scene.on_click()(lambda e: self.click_sky(e.ray_origin, e.ray_direction))
        if self.client is not None:
            self.client.camera.on_update(g(lambda cam: self.camera.on_camera(cam, self.state.run)))

    def _scenario_changed(self) -> None:
        if self._quiet:
            return
        self.state.upload = None  # moving a scenario control returns to the simulation
        self.panel.back.visible = False
        if self.panel.auto.value:
            self.request_solve()

    def _solver_changed(self) -> None:
        if not self._quiet and self.panel.auto.value:
            self.request_solve()

    def _method_changed(self) -> None:
        self.panel.seq_controls.visible = self.panel.sequence_wanted()
        self._solver_changed()

    def use_paper_camera(self) -> None:
        """Udomkesmalee et al.'s camera: a 30-degree field, 1024 x 1024, catalog to Hp 4.5."""
        with self.quietly():
            self.panel.set_paper_camera()
        self._scenario_changed()

    def randomise(self) -> None:
        """A random pointing (RA, Dec, roll), solved."""
        with self.quietly():
            self.panel.set_pointing(*random_pointing(np.random.default_rng()))
        self._scenario_changed()

    def use_simulation(self) -> None:
        self.state.upload = None
        self.panel.back.visible = False
        self.request_solve()

    @reported
    def receive_upload(self, name: str | None, content: bytes) -> None:
        """An image uploaded through the panel, with the panel's "FOV hint" (errors go to the panel)."""
        fov = check_fov(self.panel.upload_fov.value)
        image = decode_image_bytes(content, name or "the upload")
        self.load_image(image, fov, name or "upload")

    def load_bundled(self, name: str) -> None:
        """One of the bundled photographs chosen in the panel's gallery, solved as an upload is."""
        if self._quiet or name == P.NO_PHOTO:
            return
        path = next((p for p in bundled_photographs() if p.name == name), None)
        if path is None:
            raise BadInput(f"{name!r} is not one of the bundled photographs")
        from skyview.detect.centroids import load_image

        self.load_image(load_image(path), check_fov(self.panel.upload_fov.value), name)

    def load_image(self, image: np.ndarray, fov_deg: float, name: str) -> None:
        """Solve a user's image (upload, or `--image`) instead of the simulation."""
        if self._closed:  # the tab closed while its upload arrived: nothing to show it on
            return
        fov = check_fov(fov_deg)
        Camera.from_fov(fov, image.shape[1], image.shape[0])  # validates the size
        self.state.upload = Source(image=image, fov_deg=fov, name=name)
        self.panel.back.visible = True
        self.request_solve()

    # ------------------------------------------------------------------ jobs
    def request_solve(self) -> None:
        t_request = time.perf_counter()
        self.worker.submit("solving", lambda: self._job_solve(t_request))

    def request_compare(self, methods=None) -> None:
        """Run every method (or `methods`) on the current image; the table goes to the Result tab."""
        self.worker.submit("comparing the methods", lambda: self._job_compare(methods))

    def _source(self) -> Source:
        if self.state.upload is not None:
            return self.state.upload
        return simulate(self.panel.scene_config(), self.solvers.base_catalog)

    def _job_solve(self, t_request: float) -> None:
        method, variant = check_method(self.panel.method.value, self.panel.variant.value)
        say, simulated = self.worker.relabel, self.state.upload is None
        try:
            # the solve takes its turn with every other tab's (first come, first served); the drawing does not
            with self.solvers.queue.turn(say, stale=lambda: self.worker.superseded):
                if simulated and (needs_sequence(method) or self.panel.track.value):
                    make = solve_sequence_run if needs_sequence(method) else track_sequence_run
                    shown = make(self.panel.scene_config(), self.panel.sequence_config(), method, variant,
                                 self.solvers, label=say)
                    draw = self.show_sequence
                else:
                    say("simulating" if simulated else "loading the image")
                    shown = solve(self._source(), method, variant, float(self.panel.mag.value), self.solvers,
                                  label=say)
                    draw = self.show_run
        except Superseded:  # a newer request, or the tab closed, while it waited: nothing to show
            return
        if self.worker.superseded:
            return
        say("drawing")
        draw(shown, t_request)

    def _job_compare(self, methods=None) -> None:
        source = self.run.source if self.run is not None else self._source()
        mag = float(self.panel.mag.value)

        def progress(k, n, what):
            self.worker.progress = 100.0 * k / max(n, 1)
            self.worker.relabel(f"comparing: {what} ({k + 1 if k < n else n}/{n})")

        try:
            with self.solvers.queue.turn(self.worker.relabel, stale=lambda: self.worker.superseded):
                rows = compare(source, mag, self.solvers, progress, methods)
        except Superseded:
            return
        self.state.compare_rows, self.state.compare_source = rows, source
        with self.atomic():
            self.panel.compare_table.content = P.compare_markdown(rows, source.name)
        if self.client is not None:
            self.client.add_notification("Comparison done", f"{len(rows)} runs: see the Result tab",
                                         auto_close_seconds=5.0)

    # ------------------------------------------------------------------ what goes on screen
    def show_run(self, run: Run, t_request: float | None = None) -> None:
        """Show one solved image (no sequence)."""
        self._show_frames(None)
        self._draw_run(run, t_request)

    def show_sequence(self, seq: SequenceRun | TrackedSequenceRun, t_request: float | None = None) -> None:
        """Show a sequence on its last frame (the final state): a sequence method's with its track and
        its plot across frames; a tracked one (any single-frame method) with the footprints of its frames
        coloured by mode, lock lost and regained. The frame's own image, steps and result below."""
        self._show_frames(seq)
        self._draw_run(seq.frames[-1], t_request)

    def _show_frames(self, seq: SequenceRun | TrackedSequenceRun | None) -> None:
        """The sequence on screen (None: a single image), on its last frame: its track, plot and slider."""
        with self.lock, self.atomic():
            self.frame_player.stop()
            if self.state.tracked is not None:
                self.state.tracked.hide()
            self.state.sequence = seq
            self.state.frame = None if seq is None else len(seq) - 1
            is_seq = isinstance(seq, SequenceRun)
            self.sky.draw_track(seq.frames[0].source.camera if is_seq else None,
                                [f.R_true for f in seq.frames] if is_seq else None)
            self.frame_plot.draw(seq if is_seq else None, self.state.frame)
            if isinstance(seq, TrackedSequenceRun):
                seq.show(self.owner.scene, len(seq) - 1)
            p = self.panel
            p.seq_box.visible = seq is not None
            if seq is None:
                return
            n = len(seq)
            with self.quietly():
                p.frame.max = max(1, n - 1)
                p.frame.value = n - 1
                p.frame.disabled = n == 1
            self.frame_player.reset(n)

    def set_frame(self, k: int) -> None:
        """Show frame k of the sequence: its image, centroids, camera, steps and result."""
        seq = self.state.sequence
        if self._quiet or seq is None:
            return
        if not 0 <= k < len(seq):
            with self.quietly():
                self.panel.frame.value = self.frame_index if self.frame_index is not None else len(seq) - 1
            raise BadInput(f"frame {k} is outside 0..{len(seq) - 1}")
        t0 = time.perf_counter()
        with self.lock:
            if self.state.sequence is not seq:
                return
            self.state.frame = k
            if isinstance(seq, TrackedSequenceRun):
                seq.set_frame(self.owner.scene, k)  # the footprint of the frame shown
            self._draw_run(seq.frames[k])
        self.state.timings["frame_ms"] = (time.perf_counter() - t0) * 1e3

    def _draw_run(self, run: Run, t_request: float | None = None) -> None:
        t0 = time.perf_counter()
        tex = texture(run.source.image)
        if not run.source.camera.fisheye:  # (a fisheye's is drawn through its own lens: `SkyScene.draw_run`)
            tex = undistorted(tex, run.source.camera)  # the lens's distortion taken out
        base = panel_base(stretch(run.source.image))
        # the RA/Dec grid of a solved image, through the camera of its solve
        grid = image_grid(run.result.camera, run.result.R) if run.result.solved else None
        figures = image_figures(run.result.camera, run.result.R) if run.result.solved else None
        n = len(run.drawables)
        st, p = self.state, self.panel
        with self.lock, self.atomic():
            self.step_player.reset(n)
            st.run = run
            self._panel_base, self._panel_grid, self._panel_figures = base, grid, figures
            if st.forget_stale_comparison():  # a comparison is of one image: it leaves with it
                p.compare_table.content = ""
            self.clear_error()
            self.sky.draw_catalog(run.catalog)
            self.sky.draw_run(run, tex, max_rings=self.rings_drawn)
            with self.quietly():
                self.step_plot.options(run.drawables)
                p.step.disabled = n == 0
                p.step.max = max(1, n - 1)
                p.step.value = max(0, n - 1)
            self.step_plot.draw(run.drawables, n - 1 if n else None)
            self._show_step(n - 1 if n else None, mark=False)
            if st.sequence is not None and st.frame is not None:
                p.frame_text.content = st.frame_text()
                self.frame_plot.mark(st.frame)
            if run.source.truth is None and st.sequence is None:  # a user's image: what was found
                with self.quietly():
                    p.show_found(run)
            p.status.content = st.status_text()
        st.timings["draw_ms"] = (time.perf_counter() - t0) * 1e3
        if t_request is not None:
            st.timings["update_ms"] = (time.perf_counter() - t_request) * 1e3
        viewer_ms = {"update (control to scene)": st.timings.get("update_ms", float("nan")),
                     "drawing": st.timings["draw_ms"]}
        p.result.content = st.result_text(viewer_ms)
        if p.follow.value:
            self.camera.follow(run)

    # ------------------------------------------------------------------ steps
    def set_step(self, k: int) -> None:
        if self._quiet:
            return
        t0 = time.perf_counter()
        with self.lock, self.atomic():
            self._show_step(k)
        self.state.timings["step_ms"] = (time.perf_counter() - t0) * 1e3

    def _show_step(self, k: int | None, mark: bool = True) -> None:
        run = self.state.run
        if run is None:
            return
        if k is not None and not 0 <= k < len(run.drawables):
            k = None
        self.state.step = k
        d = self.sky.show_step(run, k)
        self.panel.step_text.content = P.step_markdown(run, d)
        hl = d.observed if d is not None else ()
        pat = d.pattern if d is not None else None
        # the outcomes (identified, wrong match, ...) only once the identification is made (the last step)
        outcomes = run.outcomes if d is None or d.final else ["unidentified"] * len(run.outcomes)
        n = self.rings_drawn
        self.panel.image.image = annotate(self._panel_base, run.source.image.shape, run.result.centroids.uv[:n],
                                          outcomes[:n], highlight=hl, pattern=pat, grid=self._panel_grid,
                                          figures=self._panel_figures)
        if mark and k is not None:
            self.step_plot.mark(k)

    def _plot_key_changed(self) -> None:
        run = self.state.run
        if not self._quiet and run is not None:
            with self.lock:
                self.step_plot.draw(run.drawables, self.state.step)

    def toggle_play(self) -> None:
        """Play the steps from the first (or the next one) to the last; Pause stops."""
        run = self.state.run
        if run is None:
            return
        self.step_player.toggle(len(run.drawables), self.state.step,
                                still=lambda: self.state.run is run and not self._closed)

    def toggle_play_frames(self) -> None:
        """Play the frames from the first (or the next one) to the last; Pause stops."""
        seq = self.state.sequence
        if seq is None:
            return
        self.frame_player.toggle(len(seq), self.state.frame,
                                 still=lambda: self.state.sequence is seq and not self._closed)

    # ------------------------------------------------------------------ view
    def set_layer(self, what: str, on: bool) -> None:
        """Show or hide a layer of the View tab's list (`panel.checks`: stars, grid, candidates, coverage…)."""
        if what == "coverage":
            self.show_coverage(on)
            return
        with self.lock, self.atomic():
            self.sky.set_visible(what, on)
            if what == "candidates" and on and self.state.run is not None:
                self.sky.show_step(self.state.run, self.state.step)

    def show_coverage(self, on: bool) -> None:
        """The sky-coverage map on the sphere (or not), captioned for the FOV this tab is looking at."""
        if self.coverage is None:
            return
        with self.lock:
            if on:
                run = self.state.run
                fov = run.source.fov_deg if run is not None else float(self.panel.fov.value)
                self.coverage.show(self.owner.scene, fov_deg=fov)
            else:
                self.coverage.hide()

    def point_view(self, mode: str) -> None:
        """Put this tab's camera at the sphere's centre, looking down the boresight ('boresight' fits
        the sensor in the view, 'wide' shows the sky around it, 'follow' keeps the zoom)."""
        self.camera.point(mode, self.state.run)

    @reported
    def click_sky(self, ray_origin, ray_direction) -> None:
        """A click on the sphere (a ray from the tab's camera): name the catalog star nearest to it."""
        run = self.state.run
        if run is None:
            return
        p = ray_to_sphere(ray_origin, ray_direction)
        if p is None:
            return
        self.pick_star(nearest_star(run.catalog, p, max(self.camera.fov_rad / 40.0, np.radians(0.02))))

    def pick_star(self, row: int | None) -> None:
        run = self.state.run
        if run is None:
            return
        label, text = P.picked_star(run.catalog, row)
        with self.lock, self.atomic():
            self.sky.show_pick(run.catalog, row, label)
            self.panel.picked.content = text

    # ------------------------------------------------------------------ export
    def export_rrd(self, path: str | Path) -> Path:
        """Write the run on screen as a Rerun recording (skyview.record.recording)."""
        if self.state.run is None:
            raise BadInput("nothing to export yet: solve an image first")
        return record_run(self.state.run, path)

    def _on_export(self, _event) -> None:
        run = self.state.run
        if run is None:
            raise BadInput("nothing to export yet: solve an image first")
        name = f"skyview-{run.result.method}-{run.result.variant}.rrd"
        with tempfile.TemporaryDirectory(prefix="skyview-rrd-") as d:
            path = self.export_rrd(Path(d) / name)
            data = path.read_bytes()
        if self.client is not None:
            self.client.send_file_download(name, data)
            self.client.add_notification("Recording ready", f"{name} ({len(data) / 1e6:.2f} MB): open it with "
                                         f"`skyview replay {name}` or the Rerun viewer", auto_close_seconds=8.0)

    def result_json(self) -> tuple[str, str]:
        """(file name, text) of the image on screen's result in the one JSON shape of a solution
        (`skyview.solver.solution_json`: what `skyview solve --json` prints), with the image's name."""
        run = self.state.run
        if run is None:
            raise BadInput("nothing to download yet: solve an image first")
        out = plain({**run.result.to_dict(), "image": run.source.name}, nan_as_none=True)
        stem = Path(run.source.name).stem or "image"
        return f"{stem}-skyview.json", json.dumps(out, indent=1, allow_nan=False)

    def _on_export_json(self, _event) -> None:
        name, text = self.result_json()
        if self.client is not None:
            self.client.send_file_download(name, text.encode())

    # ------------------------------------------------------------------ progress
    def _show_idle(self) -> None:
        self.panel.show_idle(self.state.status_text() if self.state.run is not None else None)
