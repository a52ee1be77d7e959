"""One viewer session (a browser tab): its panel, its 3-D scene, its worker and its camera.

A session solves in a background thread (`worker.Worker`, latest request wins), so the page stays
responsive while a slow method runs; the panel shows the progress. Every callback is guarded: bad input
shows an error in the panel, the server keeps running.
"""

from __future__ import annotations

import contextlib
import math
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import Callable

import numpy as np
import viser
from viser import uplot

from skyview.camera import Camera
from skyview.errors import BadInput
from skyview.identify import VARIANTS
from skyview.present import default_plot_key, numeric_keys, series
from skyview.viewer import panel as P
from skyview.viewer.picture import annotate, decode_image_bytes, panel_base, stretch, texture
from skyview.viewer.run import (VIEWER_METHODS, Run, SceneConfig, Solvers, Source, check_fov, check_method, compare,
                                needs_sequence, random_pointing, sigma_for, simulate, solve)
from skyview.viewer.scene import STAR_NAMES, SkyScene, nearest_star, ray_to_sphere
from skyview.viewer.sequence_run import (SequenceConfig, SequenceRun, TrackedSequenceRun, solve_sequence_run,
                                         track_sequence_run)
from skyview.viewer.worker import Worker

PLAY_INTERVAL_S = 0.7
FRAME_INTERVAL_S = 1.5  # Play the frames: each frame redraws the sensor image, the camera and its steps
WIDE_FOV_DEG = 70.0
REFERENCE_TAN = math.tan(math.radians(30.0))  # star sizes are tuned for a 60-degree view


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
        self.run: Run | None = None  # the image on screen (with a sequence: the frame shown)
        self.seq: SequenceRun | None = None  # the sequence on screen, if any
        self.tracked: TrackedSequenceRun | None = None  # a tracked sequence on screen, if any
        self.frame_index: int | None = None
        self.upload: Source | None = initial
        self.step_index: int | None = None
        self.error: str = ""
        self.timings: dict[str, float] = {}
        self.compare_rows: list[dict] = []
        self._compare_source = None  # the image the comparison table is of
        self._closed = False
        self._mute = False  # programmatic control changes do not trigger solves
        self._playing = False
        self._play_id = 0
        self._playing_frames = False
        self._frame_play_id = 0
        self._frame_plot = None
        self._panel_base: np.ndarray | None = None
        self._camera_pending: tuple[str, np.ndarray] | None = None
        self._view_applied: tuple | None = None
        self._zoom_applied = 1.0
        self._last_boresight: np.ndarray | None = None
        self._last_camera: Camera | None = None
        self._plot = None
        owner.gui.configure_theme(dark_mode=True, control_width="large", show_logo=False, show_share_button=False,
                                  brand_color=(255, 184, 48))
        owner.gui.main_panel.dock_right()
        owner.gui.main_panel.set_width(400)
        self.sky = SkyScene(owner.scene)
        self.panel = P.build_panel(owner.gui, list(VIEWER_METHODS), list(VARIANTS), config or SceneConfig(),
                                   coverage_label=None if coverage is None else
                                   f"Sky coverage: {coverage.config.method}, {coverage.config.fov_deg:g}°")
        with self.atomic():
            self.sky.setup()
            # the sky before the first solve: the guide catalog at the scenario's limit
            self.sky.draw_catalog(solvers.base_catalog.brighter_than(float(self.panel.mag.value)))
        if method is not None:  # the method to start with (`skyview demo --method`), before the first solve
            self.panel.method.value = method
        if variant is not None:
            self.panel.variant.value = variant
        self._wire()
        self.panel.back.visible = initial is not None
        self.worker = Worker(self._show_exception)
        self._ticker = threading.Thread(target=self._tick, name="skyview-viewer-ticker", daemon=True)
        self._ticker.start()
        self.request_solve()
        if coverage is not None:
            self.show_coverage(True)
        if bench_report is not None:  # the six methods compared on a bench's images, beside this image's
            from skyview.compare import format_markdown

            self.panel.bench_table.content = ("---\n\n## Every method on the same images (`skyview bench "
                                              "--compare`)\n\n" + format_markdown(bench_report))

    # ------------------------------------------------------------------ plumbing
    def atomic(self):
        return self.owner.atomic()

    def close(self) -> None:
        self._closed = True
        self._playing = False
        self._playing_frames = False
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
        self.error = message
        with self.atomic():
            self.panel.error.content = f"<span style='color:rgb(255,110,110)'><b>Error:</b> {_escape(message)}</span>"
            self.panel.error.visible = True
        if self.client is not None:
            self.client.add_notification("skyview", message, color="red", auto_close_seconds=8.0)

    def clear_error(self) -> None:
        if self.error:
            self.error = ""
            self.panel.error.visible = False

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Block until no job is running or waiting (tests and scripts)."""
        return self.worker.wait_idle(timeout)

    # ------------------------------------------------------------------ wiring
    def _wire(self) -> None:
        p = self.panel
        for h in (p.ra, p.dec, p.roll, p.fov, p.resolution, p.noise, p.false_stars, p.dropped, p.seed):
            h.on_update(self._guard(lambda _e: self._scenario_changed()))
        for h in (p.mag, p.variant):
            h.on_update(self._guard(lambda _e: self._solver_changed()))
        for h in (p.n_frames, p.turn, p.turn_step):  # only a sequence (a sequence method, or tracking) uses them
            h.on_update(self._guard(lambda _e: self._solver_changed() if self._sequence_wanted() else None))
        p.track.on_update(self._guard(lambda _e: self._method_changed()))
        p.method.on_update(self._guard(lambda _e: self._method_changed()))
        p.paper_camera.on_click(self._guard(lambda _e: self.use_paper_camera()))
        p.frame.on_update(self._guard(lambda _e: self.set_frame(int(p.frame.value))))
        p.play_frames.on_click(self._guard(lambda _e: self.toggle_play_frames()))
        p.solve.on_click(self._guard(lambda _e: self.request_solve()))
        p.compare.on_click(self._guard(lambda _e: self.request_compare()))
        p.random.on_click(self._guard(lambda _e: self.randomise()))
        p.upload.on_upload(self._guard(self._on_upload))
        p.back.on_click(self._guard(lambda _e: self.use_simulation()))
        p.step.on_update(self._guard(lambda _e: self.set_step(int(p.step.value))))
        p.play.on_click(self._guard(lambda _e: self.toggle_play()))
        p.plot_key.on_update(self._guard(lambda _e: self._draw_plot()))
        p.export.on_click(self._guard(self._on_export))
        p.boresight.on_click(self._guard(lambda _e: self.point_view("boresight")))
        p.wide.on_click(self._guard(lambda _e: self.point_view("wide")))
        for what, h in p.checks.items():
            h.on_update(self._guard(lambda e, what=what: self._toggle(what, bool(e.target.value))))
        self.owner.scene.on_click()(self._guard(self._on_scene_click))
        if self.client is not None:
            self.client.camera.on_update(self._guard(self._on_camera))

    def _scenario_changed(self) -> None:
        if self._mute:
            return
        self.upload = None  # moving a scenario control returns to the simulation
        self.panel.back.visible = False
        if self.panel.auto.value:
            self.request_solve()

    def _solver_changed(self) -> None:
        if not self._mute and self.panel.auto.value:
            self.request_solve()

    def _method_changed(self) -> None:
        self.panel.seq_controls.visible = self._sequence_wanted()
        self._solver_changed()

    def _sequence_wanted(self) -> bool:
        """A sequence is solved: the method identifies over sequences, or tracking is ticked."""
        return needs_sequence(self.panel.method.value) or bool(self.panel.track.value)

    def sequence_config(self) -> SequenceConfig:
        """The sequence the controls describe (validated: BadInput names a bad control)."""
        p = self.panel
        return SequenceConfig(n_frames=p.n_frames.value, turn=p.turn.value, step_deg=p.turn_step.value).checked()

    def use_paper_camera(self) -> None:
        """Udomkesmalee et al.'s camera: a 30-degree field, 1024 x 1024, catalog to Hp 4.5."""
        p = self.panel
        self._mute = True
        try:
            p.fov.value = P.PAPER_CAMERA["fov_deg"]
            p.resolution.value = P.PAPER_CAMERA["resolution"]
            p.mag.value = P.PAPER_CAMERA["mag_limit"]
        finally:
            self._mute = False
        self._scenario_changed()

    def config(self) -> SceneConfig:
        """The scenario the controls describe (validated: BadInput names a bad control)."""
        p = self.panel
        return SceneConfig(ra_deg=p.ra.value, dec_deg=p.dec.value, roll_deg=p.roll.value, fov_deg=p.fov.value,
                           resolution=p.resolution.value, mag_limit=p.mag.value, noise_arcsec=p.noise.value,
                           false_stars=p.false_stars.value, dropped=p.dropped.value, seed=p.seed.value).checked()

    def randomise(self) -> None:
        ra, dec, roll = random_pointing(np.random.default_rng())
        self._mute = True
        try:
            self.panel.ra.value, self.panel.dec.value, self.panel.roll.value = ra, dec, roll
        finally:
            self._mute = False
        self._scenario_changed()

    def use_simulation(self) -> None:
        self.upload = None
        self.panel.back.visible = False
        self.request_solve()

    def _on_upload(self, event) -> None:
        f = event.target.value
        fov = check_fov(self.panel.upload_fov.value)
        image = decode_image_bytes(f.content, f.name or "the upload")
        self.load_image(image, fov, f.name or "upload")

    def load_image(self, image: np.ndarray, fov_deg: float, name: str) -> None:
        """Solve a user's image (upload, or `--image`) instead of the simulation."""
        fov = check_fov(fov_deg)
        Camera.from_fov(fov, image.shape[1], image.shape[0])  # validates the size
        self.upload = Source(image=image, fov_deg=fov, name=name)
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
        if self.upload is not None:
            return self.upload
        return simulate(self.config(), self.solvers.base_catalog)

    def _label(self, text: str) -> None:
        busy = self.worker.busy
        if busy is not None:
            self.worker.busy = (text, busy[1])

    def _job_solve(self, t_request: float) -> None:
        method, variant = check_method(self.panel.method.value, self.panel.variant.value)
        if self.upload is None and needs_sequence(method):
            seq = solve_sequence_run(self.config(), self.sequence_config(), method, variant, self.solvers,
                                     label=self._label)
            if self.worker.superseded:
                return
            self._label("drawing")
            self.show_sequence(seq, t_request)
            return
        if self.upload is None and self.panel.track.value:
            tracked = track_sequence_run(self.config(), self.sequence_config(), method, variant, self.solvers,
                                         label=self._label)
            if self.worker.superseded:
                return
            self._label("drawing")
            self.show_tracked(tracked, t_request)
            return
        self._label("simulating" if self.upload is None else "loading the image")
        source = self._source()
        mag = float(self.panel.mag.value)
        if not self.solvers.cached(source.camera, method, variant, mag, sigma_for(source)):
            self._label(f"loading the {method} database (built once per camera and catalog, then cached)")
        else:
            self._label(f"solving with {method} ({variant})")
        run = solve(source, method, variant, mag, self.solvers)
        if self.worker.superseded:
            return
        self._label("drawing")
        self.show_run(run, t_request)

    def _job_compare(self, methods=None) -> None:
        source = self.run.source if self.run is not None else self._source()
        mag = float(self.panel.mag.value)

        def progress(k, n, what):
            self.worker.progress = 100.0 * k / max(n, 1)
            self._label(f"comparing: {what} ({k + 1 if k < n else n}/{n})")

        rows = compare(source, mag, self.solvers, progress, methods)
        self.compare_rows = rows
        self._compare_source = source
        with self.atomic():
            self.panel.compare_table.content = P.compare_markdown(rows, source.name)
        if self.client is not None:
            self.client.add_notification("Comparison done", f"{len(rows)} runs: see the Result tab",
                                         auto_close_seconds=5.0)

    # ------------------------------------------------------------------ drawing a run
    def show_run(self, run: Run, t_request: float | None = None) -> None:
        """Show one solved image (no sequence)."""
        with self.lock, self.atomic():
            self._playing_frames = False
            self._drop_tracked()
            self.seq = None
            self.frame_index = None
            self.panel.seq_box.visible = False
            if self._frame_plot is not None:
                self._frame_plot.remove()
                self._frame_plot = None
            self.sky.draw_track(None, None)
        self._draw_run(run, t_request)

    def show_sequence(self, seq: SequenceRun, t_request: float | None = None) -> None:
        """Show a solved sequence, on its last frame (the final state)."""
        n = len(seq)
        with self.lock, self.atomic():
            self._playing_frames = False
            self._drop_tracked()
            self.seq = seq
            self._frames_controls(n)
            self.sky.draw_track(seq.frames[0].source.camera, [f.R_true for f in seq.frames])
            self._draw_frame_plot()
        self._draw_run(seq.frames[n - 1], t_request)

    def show_tracked(self, seq: TrackedSequenceRun, t_request: float | None = None) -> None:
        """Show a tracked sequence (any single-frame method) on its last frame: the footprints of its
        frames coloured by mode, lock lost and regained, and the frame's own image, steps and result."""
        n = len(seq)
        with self.lock, self.atomic():
            self._playing_frames = False
            self._drop_tracked()
            self.seq = None
            self.tracked = seq
            self._frames_controls(n)
            if self._frame_plot is not None:
                self._frame_plot.remove()
                self._frame_plot = None
            self.sky.draw_track(None, None)
            seq.show(self.owner.scene, n - 1)
        self._draw_run(seq.frames[n - 1], t_request)

    def _frames_controls(self, n: int) -> None:
        """The frame slider and player for a sequence of n frames, on its last frame."""
        self.frame_index = n - 1
        p = self.panel
        self._mute = True
        try:
            p.frame.max = max(1, n - 1)
            p.frame.value = n - 1
            p.frame.disabled = n == 1
        finally:
            self._mute = False
        p.play_frames.label = "Play the frames"
        p.play_frames.disabled = n == 1
        p.seq_box.visible = True

    def _drop_tracked(self) -> None:
        if self.tracked is not None:
            self.tracked.hide()
            self.tracked = None

    def _frames_on_screen(self):
        """The sequence whose frames the slider shows: a sequence method's or a tracked one (or None)."""
        return self.seq if self.seq is not None else self.tracked

    def set_frame(self, k: int) -> None:
        """Show frame k of the sequence: its image, centroids, camera, steps and result."""
        if self._mute or self._frames_on_screen() is None:
            return
        seq = self._frames_on_screen()
        if not 0 <= k < len(seq):
            self._mute = True
            try:
                self.panel.frame.value = self.frame_index if self.frame_index is not None else len(seq) - 1
            finally:
                self._mute = False
            raise BadInput(f"frame {k} is outside 0..{len(seq) - 1}")
        t0 = time.perf_counter()
        with self.lock:
            if self._frames_on_screen() is not seq:
                return
            self.frame_index = k
            if seq is self.tracked:
                seq.set_frame(self.owner.scene, k)  # the footprint of the frame shown
            self._draw_run(seq.frames[k])
        self.timings["frame_ms"] = (time.perf_counter() - t0) * 1e3

    def _status_text(self) -> str:
        if self.seq is not None and self.frame_index is not None:
            return P.sequence_status_markdown(self.seq, self.frame_index)
        return P.status_markdown(self.run) if self.run is not None else ""

    def _draw_run(self, run: Run, t_request: float | None = None) -> None:
        t0 = time.perf_counter()
        tex = texture(run.source.image)
        base = panel_base(stretch(run.source.image))
        n = len(run.drawables)
        with self.lock, self.atomic():
            self._playing = False
            self.run = run
            self._panel_base = base
            if self._compare_source is not None and run.source is not self._compare_source:
                # a comparison is of one image: it leaves the Result tab when another image is shown
                self.compare_rows, self._compare_source = [], None
                self.panel.compare_table.content = ""
            self.clear_error()
            self.sky.draw_catalog(run.catalog)
            self.sky.draw_run(run, tex)
            keys = numeric_keys(run.drawables)
            p = self.panel
            self._mute = True
            try:
                default = default_plot_key(run.drawables)
                p.plot_key.options = tuple(keys) if default is not None else ("-", *keys)  # "-": no plot
                p.plot_key.value = default or "-"
                p.step.disabled = n == 0
                p.step.max = max(1, n - 1)
                p.step.value = max(0, n - 1)
            finally:
                self._mute = False
            p.play.label = "Play the steps"
            self.step_index = None
            self._show_step(n - 1 if n else None)
            self._draw_plot()
            seq, k = self._frames_on_screen(), self.frame_index
            if seq is not None and k is not None:
                p.frame_text.content = P.frame_markdown(seq, k) if seq is self.seq else seq.frame_markdown(k)
                if self._frame_plot is not None:
                    self._frame_plot.data = self._frame_plot_data(k)
            p.status.content = self._status_text()
        self.timings["draw_ms"] = (time.perf_counter() - t0) * 1e3
        if t_request is not None:
            self.timings["update_ms"] = (time.perf_counter() - t_request) * 1e3
        viewer_ms = {"update (control to scene)": self.timings.get("update_ms", float("nan")),
                     "drawing": self.timings["draw_ms"]}
        text = P.result_markdown(run, viewer_ms)
        if seq is not None and k is not None:
            whole = P.sequence_markdown(seq) if seq is self.seq else seq.markdown()
            text = f"{whole}\n\n---\n\n**Frame {k}** (shown)  \n{text}"
        self.panel.result.content = text
        R = run.R_shown
        if R is not None and self.panel.follow.value:
            cam = run.source.camera
            if self._last_boresight is None or cam != self._last_camera:
                self.point_view("boresight")  # first run, or another sensor: fit it in the view
            elif float(self._last_boresight @ R[2]) < math.cos(math.radians(0.25 * run.source.fov_deg)):
                self.point_view("follow")  # the pointing moved: follow it, keep the zoom
            self._last_boresight, self._last_camera = R[2].copy(), cam

    # ------------------------------------------------------------------ steps
    def set_step(self, k: int) -> None:
        if self._mute:
            return
        t0 = time.perf_counter()
        with self.lock, self.atomic():
            self._show_step(k)
        self.timings["step_ms"] = (time.perf_counter() - t0) * 1e3

    def _show_step(self, k: int | None) -> None:
        run = self.run
        if run is None:
            return
        if k is not None and not 0 <= k < len(run.drawables):
            k = None
        self.step_index = k
        d = self.sky.show_step(run, k)
        p = self.panel
        p.step_text.content = P.step_markdown(run, d)
        hl = d.observed if d is not None else ()
        pat = d.pattern if d is not None else None
        # the outcomes (identified, wrong match, ...) only once the identification is made (the last step)
        outcomes = run.outcomes if d is None or d.final else ["unidentified"] * len(run.outcomes)
        p.image.image = annotate(self._panel_base, run.source.image.shape, run.result.centroids.uv, outcomes,
                                 highlight=hl, pattern=pat)
        if self._plot is not None and k is not None:
            self._plot.data = self._plot_data(k)

    def _plot_data(self, k: int | None):
        run = self.run
        key = self.panel.plot_key.value
        n = len(run.drawables) if run else 0
        x = np.arange(1, n + 1, dtype=np.float64)
        y = series(run.drawables, key) if run and key != "-" else np.full(n, np.nan)
        cur = np.full(n, np.nan)
        if k is not None and 0 <= k < n:
            cur[k] = y[k]
        return (x, y, cur)

    def _draw_plot(self) -> None:
        run = self.run
        if self._mute or run is None:
            return
        with self.lock:
            if self._plot is not None:
                self._plot.remove()
                self._plot = None
            key = self.panel.plot_key.value
            if not run.drawables or key == "-":
                return
            y = series(run.drawables, key)
            positive = np.isfinite(y) & (y > 0)
            log = bool(positive.sum() >= 2 and np.nanmax(y[positive]) / np.nanmin(y[positive]) > 50
                       and not np.any(np.isfinite(y) & (y < 0)))
            with self.panel.plot_box:
                self._plot = self.owner.gui.add_uplot(
                    data=self._plot_data(self.step_index),
                    series=(
                        uplot.Series(label="step"),
                        uplot.Series(label=key, stroke=P.PLOT_COLORS[0], width=2,
                                           points={"show": True, "size": 5, "fill": P.PLOT_COLORS[0]}),
                        uplot.Series(label="now", stroke="transparent",
                                           points={"show": True, "size": 11, "fill": P.PLOT_COLORS[1]}),
                    ),
                    scales={"x": {"time": False}, "y": {"distr": 3 if log else 1}},
                    legend={"show": True, "live": False},
                    aspect=1.8,
                )

    def toggle_play(self) -> None:
        if self._playing:
            self._playing = False
            self.panel.play.label = "Play the steps"
            return
        run = self.run
        if run is None or not run.drawables:
            return
        self._playing = True
        self._play_id += 1
        me = self._play_id  # a Pause then Play starts a new player; the old one stops at its next tick
        self.panel.play.label = "Pause"
        start = 0 if self.step_index is None or self.step_index >= len(run.drawables) - 1 else self.step_index + 1

        def playing() -> bool:
            return self._playing and self._play_id == me and self.run is run and not self._closed

        def play():
            k = start
            while playing() and k < len(run.drawables):
                self.panel.step.value = k  # fires set_step
                k += 1
                time.sleep(PLAY_INTERVAL_S)
            if self._play_id == me and self.run is run:
                self._playing = False
                self.panel.play.label = "Play the steps"

        threading.Thread(target=self._guard(play), name="skyview-viewer-play", daemon=True).start()

    # ------------------------------------------------------------------ frames
    def _frame_plot_data(self, k: int | None):
        """x = frame; stars above the prior, the leading star's and the true star's posterior, and the
        frame shown (marked on the leading star's posterior)."""
        ser = self.seq.series()
        n = len(self.seq)
        now = np.full(n, np.nan)
        if k is not None and 0 <= k < n:
            now[k] = ser["top_posterior"][k]
        return (np.arange(n, dtype=np.float64), ser["above_prior"], ser["top_posterior"], ser["true_posterior"], now)

    def _draw_frame_plot(self) -> None:
        if self._frame_plot is not None:
            self._frame_plot.remove()
            self._frame_plot = None
        seq = self.seq
        n = len(seq)
        c = P.FRAME_PLOT_COLORS

        def line(label, color, scale, width=2.0, dash=None):
            s = uplot.Series(label=label, scale=scale, stroke=color, width=width,
                             points={"show": True, "size": 6, "fill": color})
            if dash:
                s["dash"] = dash
            return s

        above = seq.series()["above_prior"]
        top = max(1, math.ceil(math.log10(max(float(np.nanmax(above)) if np.isfinite(above).any() else 1.0, 2.0))))
        decades = tuple(float(10 ** i) for i in range(top + 1))  # a log axis labelled by decades only
        with self.panel.frame_plot_box:
            self._frame_plot = self.owner.gui.add_uplot(
                data=self._frame_plot_data(self.frame_index),
                series=(
                    uplot.Series(label="frame"),
                    line("stars above 1/N", c[0], "n"),
                    line("P(leading star)", c[1], "p", 2.5),
                    line("P(true star)", c[2], "p", 1.5, (4, 5)),
                    uplot.Series(label="frame shown", scale="p", stroke=c[3], width=0,
                                 points={"show": True, "size": 14, "fill": "transparent", "stroke": c[3],
                                         "width": 2}),
                ),
                scales={"x": {"time": False, "range": (-0.3, max(n - 1, 0) + 0.3)},
                        "n": {"distr": 3, "log": 10, "range": (1.0, decades[-1])}, "p": {"range": (0.0, 1.0)}},
                axes=(
                    uplot.Axis(scale="x", label="frame", incrs=(1, 2, 5, 10), space=18, size=28, labelSize=16),
                    uplot.Axis(scale="n", side=3, label="stars above 1/N", splits=decades,
                               values=tuple(f"{int(v):d}" for v in decades), size=42, labelSize=16),
                    uplot.Axis(scale="p", side=1, label="posterior", splits=(0.0, 0.25, 0.5, 0.75, 1.0),
                               values=("0", ".25", ".5", ".75", "1"), size=36, labelSize=16, grid={"show": False}),
                ),
                legend={"show": True, "live": False},
                aspect=1.6,
                padding=(10, 8, 0, 0),
            )

    def toggle_play_frames(self) -> None:
        """Play the frames from the first (or the next one) to the last; Pause stops."""
        p = self.panel
        if self._playing_frames:
            self._playing_frames = False
            p.play_frames.label = "Play the frames"
            return
        seq = self._frames_on_screen()
        if seq is None or len(seq) < 2:
            return
        self._playing_frames = True
        self._frame_play_id += 1
        me = self._frame_play_id
        p.play_frames.label = "Pause"
        k0 = self.frame_index
        start = 0 if k0 is None or k0 >= len(seq) - 1 else k0 + 1

        def playing() -> bool:
            return (self._playing_frames and self._frame_play_id == me and self._frames_on_screen() is seq
                    and not self._closed)

        def play():
            k = start
            while playing() and k < len(seq):
                p.frame.value = k  # fires set_frame
                k += 1
                if k < len(seq):
                    time.sleep(FRAME_INTERVAL_S)
            if self._frame_play_id == me and self._frames_on_screen() is seq:
                self._playing_frames = False
                p.play_frames.label = "Play the frames"

        threading.Thread(target=self._guard(play), name="skyview-viewer-frames", daemon=True).start()

    # ------------------------------------------------------------------ view
    def _toggle(self, what: str, on: bool) -> None:
        if what == "coverage":
            self.show_coverage(on)
            return
        with self.lock, self.atomic():
            self.sky.set_visible(what, on)
            if what == "candidates" and on and self.run is not None:
                self.sky.show_step(self.run, self.step_index)

    def show_coverage(self, on: bool) -> None:
        """The sky-coverage map on the sphere (or not), captioned for the FOV this tab is looking at."""
        if self.coverage is None:
            return
        with self.lock:
            if on:
                run = self.run
                fov = run.source.fov_deg if run is not None else float(self.panel.fov.value)
                self.coverage.show(self.owner.scene, fov_deg=fov)
            else:
                self.coverage.hide()

    def point_view(self, mode: str) -> None:
        """Put this tab's camera at the sphere's centre, looking down the boresight ('boresight' fits
        the sensor in the view, 'wide' shows the sky around it, 'follow' keeps the zoom)."""
        run = self.run
        R = run.R_shown if run is not None else None
        if R is None or self.client is None:
            return
        cam = self.client.camera
        if cam._state.update_timestamp == 0.0 or not cam.image_height:  # the tab has not reported its view yet
            self._camera_pending = (mode, R)
            return
        self._apply_view(mode, R, run.source.camera)

    def _apply_view(self, mode: str, R: np.ndarray, camera: Camera) -> None:
        cam = self.client.camera
        if mode == "boresight":
            aspect = cam.image_width / cam.image_height
            half_v = math.radians(camera.fov_v_deg) / 2.0
            half_h = math.radians(camera.fov_deg) / 2.0
            fov = 2.0 * math.atan(1.2 * max(math.tan(half_v), math.tan(half_h) / aspect))
        elif mode == "wide":
            fov = math.radians(WIDE_FOV_DEG)
        else:
            fov = cam.fov
        with self.client.atomic():
            cam.position = (0.0, 0.0, 0.0)
            cam.look_at = tuple(R[2])
            cam.up_direction = tuple(-R[1])
            cam.fov = fov
        self._view_applied = (mode, R, camera, (cam.image_width, cam.image_height), fov)
        self._set_zoom(cam.fov, 1.0)

    def _on_camera(self, cam) -> None:
        if self._camera_pending is not None and self.run is not None and cam.image_height:
            mode, R = self._camera_pending
            self._camera_pending = None
            self._apply_view(mode, R, self.run.source.camera)
            return
        applied = self._view_applied
        if applied is not None and applied[0] == "boresight" and (cam.image_width, cam.image_height) != applied[3]:
            untouched = (abs(cam.fov - applied[4]) < 1e-6 and np.linalg.norm(cam.position) < 1e-9
                         and np.allclose(cam.look_at, applied[1][2], atol=1e-9))
            if untouched:  # the page changed size before the user moved: fit the sensor again
                self._apply_view("boresight", applied[1], applied[2])
                return
        dist = float(np.linalg.norm(np.asarray(cam.look_at) - np.asarray(cam.position)))
        self._set_zoom(cam.fov, dist)

    def _set_zoom(self, fov: float, dist: float) -> None:
        """Keep stars alike at every zoom; show the field's small labels only when it fills the view."""
        span = math.tan(fov / 2.0) * max(dist, 0.05)  # half-height of the view at the sphere
        z = max(0.03, min(3.0, span / REFERENCE_TAN)) ** 0.85
        run = self.run
        detail = run is None or span < 3.0 * math.tan(math.radians(run.source.camera.fov_v_deg) / 2.0)
        if abs(math.log(z / self._zoom_applied)) > 0.1 or detail != self.sky.detail:
            self._zoom_applied = z
            with self.lock, self.atomic():
                self.sky.set_zoom(z)
                self.sky.set_detail(detail)

    def _on_scene_click(self, event) -> None:
        run = self.run
        if run is None:
            return
        p = ray_to_sphere(event.ray_origin, event.ray_direction)
        if p is None:
            return
        fov = self.client.camera.fov if self.client is not None else math.radians(60.0)
        row = nearest_star(run.catalog, p, max(fov / 40.0, math.radians(0.02)))
        self.pick_star(row)

    def pick_star(self, row: int | None) -> None:
        run = self.run
        if run is None:
            return
        with self.lock, self.atomic():
            if row is None:
                self.sky.show_pick(run.catalog, None)
                self.panel.picked.content = "No catalog star there (click closer to a star)."
                return
            hip, mag = int(run.catalog.hip[row]), float(run.catalog.mag[row])
            ra, dec = (float(np.degrees(a[row])) for a in run.catalog.ra_dec)
            name = STAR_NAMES.get(hip)
            self.sky.show_pick(run.catalog, row, f"{name + ' · ' if name else ''}HIP {hip} · Hp {mag:.2f}")
            self.panel.picked.content = P.star_markdown(hip, mag, ra, dec, name)

    # ------------------------------------------------------------------ export
    def export_rrd(self, path: str | Path) -> Path:
        """Write the current run as a Rerun recording (skyview.record)."""
        try:
            from skyview.record import record_solve
        except ImportError as exc:
            raise BadInput(f"the Rerun recorder is not available here ({exc})") from None

        run = self.run
        if run is None:
            raise BadInput("nothing to export yet: solve an image first")
        info = record_solve(path, run.result, run.source.image, catalog=run.catalog, truth=run.source.truth,
                            force=True, meta={"image": run.source.name}, name=f"skyview-{run.result.method}")
        return Path(info.path)

    def _on_export(self, _event) -> None:
        if self.run is None:
            raise BadInput("nothing to export yet: solve an image first")
        name = f"skyview-{self.run.result.method}-{self.run.result.variant}.rrd"
        with tempfile.TemporaryDirectory(prefix="skyview-rrd-") as d:
            path = self.export_rrd(Path(d) / name)
            data = path.read_bytes()
        if self.client is not None:
            self.client.send_file_download(name, data)
            self.client.add_notification("Recording ready", f"{name} ({len(data) / 1e6:.2f} MB): open it with "
                                         f"`skyview replay {name}` or the Rerun viewer", auto_close_seconds=8.0)

    # ------------------------------------------------------------------ progress
    def _tick(self) -> None:
        shown = False
        while not self._closed:
            busy = self.worker.busy
            if busy is not None and time.monotonic() - busy[1] > 0.3:
                label, t0 = busy
                with contextlib.suppress(Exception):
                    self.panel.progress.value = self.worker.progress if self.worker.progress is not None else 100.0
                    self.panel.progress.animated = self.worker.progress is None
                    self.panel.progress.visible = True
                    self.panel.status.content = f"⏳ {_escape(label)}… {time.monotonic() - t0:.1f} s"
                    shown = True
            elif busy is None and shown:
                with contextlib.suppress(Exception):
                    self.panel.progress.visible = False
                    if self.run is not None:
                        self.panel.status.content = self._status_text()
                shown = False
            time.sleep(0.2)


def _escape(text: str) -> str:
    return str(text).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
