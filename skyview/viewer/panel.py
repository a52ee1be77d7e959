"""The side panel: its widgets, and the text it shows for results, steps and comparisons.

`build_panel` lays out the controls in a viser `GuiApi` (one browser tab's or the server's); the
`*_markdown` functions turn `Run` objects into the panel's text. No callbacks here: `session` wires them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from viser import (
    GuiButtonHandle,
    GuiCheckboxHandle,
    GuiDropdownHandle,
    GuiFolderHandle,
    GuiImageHandle,
    GuiMarkdownHandle,
    GuiNumberHandle,
    GuiSliderHandle,
    GuiTabGroupHandle,
    GuiUploadButtonHandle,
    GuiUplotHandle,
)

from skyview.core.attitude import radec_roll_from_R
from skyview.core.catalog import GAIA_ID_MIN, designation
from skyview.present.drawables import LEGEND, OUTCOME_RGB, PALETTE, StepView
from skyview.present.text import blind_summary, format_number, step_summary, why_not
from skyview.viewer.geometry import STAR_NAMES, constellations_in_view
from skyview.viewer.plot_control import add_frame_plot, add_step_plot
from skyview.viewer.run import FOV_RANGE_DEG, RESOLUTIONS, SEQUENCE_NOTE, Run, SceneConfig, needs_sequence
from skyview.viewer.sequence_run import FRAMES_RANGE, STEP_RANGE_DEG, TURNS, SequenceConfig, SequenceRun

PAPER_CAMERA = {"fov_deg": 30.0, "resolution": "1024x1024", "mag_limit": 4.5}  # Udomkesmalee et al.'s camera


NO_PHOTO = "-"  # the gallery's first entry: no bundled photograph chosen
DETECTIONS_DRAWN = 150  # rings drawn by default: a photograph of 800+ detections stays readable
# what the upload's file dialog offers (MIME types and extensions, as an HTML input's `accept`): what
# `picture.decode_image_bytes` reads
UPLOAD_TYPES = ("image/png,image/jpeg,image/tiff,image/webp,image/bmp,.png,.jpg,.jpeg,.tif,.tiff,.webp,.bmp,"
                ".fits,.fit,.fts,.fz")

@dataclass
class Panel:
    """Handles of every widget of one session's panel (viser's handle types: a slider's or a number's
    `.value` is what the user set, a markdown's `.content` what it says)."""

    status: GuiMarkdownHandle
    progress: object  # viser's GuiProgressBarHandle (not exported by viser 1.1.1)
    error: GuiMarkdownHandle
    image: GuiImageHandle
    legend: GuiMarkdownHandle
    tabs: GuiTabGroupHandle
    # frames (a sequence)
    seq_box: GuiFolderHandle  # shown when a sequence is on screen
    frame: GuiSliderHandle
    play_frames: GuiButtonHandle
    frame_text: GuiMarkdownHandle
    frame_plot: GuiUplotHandle  # across the frames of a sequence method's sequence (updated in place)
    # steps
    step: GuiSliderHandle
    play: GuiButtonHandle
    step_text: GuiMarkdownHandle
    plot_key: GuiDropdownHandle
    step_plot: GuiUplotHandle  # the chosen number across the steps (updated in place)
    # scenario
    ra: GuiSliderHandle
    dec: GuiSliderHandle
    roll: GuiSliderHandle
    random: GuiButtonHandle
    fov: GuiSliderHandle
    resolution: GuiDropdownHandle
    mag: GuiSliderHandle
    noise: GuiSliderHandle
    false_stars: GuiSliderHandle
    dropped: GuiSliderHandle
    seed: GuiNumberHandle
    method: GuiDropdownHandle
    variant: GuiDropdownHandle
    seq_controls: GuiFolderHandle  # shown when the method identifies over sequences (or tracks one)
    track: GuiCheckboxHandle  # track a sequence with a single-frame method
    bench_table: GuiMarkdownHandle  # a `skyview bench --compare` report (view --compare FILE)
    n_frames: GuiSliderHandle
    turn: GuiDropdownHandle
    turn_step: GuiSliderHandle
    paper_camera: GuiButtonHandle
    auto: GuiCheckboxHandle
    solve: GuiButtonHandle
    compare: GuiButtonHandle
    upload_fov: GuiNumberHandle
    upload: GuiUploadButtonHandle
    gallery: GuiDropdownHandle  # the bundled photographs, one click each
    back: GuiButtonHandle
    # result
    result: GuiMarkdownHandle
    compare_table: GuiMarkdownHandle
    export: GuiButtonHandle
    export_json: GuiButtonHandle
    # view
    boresight: GuiButtonHandle
    wide: GuiButtonHandle
    follow: GuiCheckboxHandle
    detections: GuiSliderHandle  # how many of the brightest detections are ringed
    checks: dict[str, GuiCheckboxHandle]
    picked: GuiMarkdownHandle

    def show_error(self, message: str) -> None:
        self.error.content = f"<span style='color:rgb(255,110,110)'><b>Error:</b> {_escape(message)}</span>"
        self.error.visible = True

    def show_busy(self, label: str, elapsed_s: float, progress: float | None) -> None:
        """A job has been running for elapsed_s: its progress (0-100, None: unknown) and what it does."""
        self.progress.value = progress if progress is not None else 100.0
        self.progress.animated = progress is None
        self.progress.visible = True
        self.status.content = f"⏳ {_escape(label)}… {elapsed_s:.1f} s"

    def show_idle(self, status: str | None) -> None:
        """The job ended: the progress bar leaves, the status line says `status` (None: unchanged)."""
        self.progress.visible = False
        if status is not None:
            self.status.content = status

    def set_paper_camera(self) -> None:
        """Udomkesmalee et al.'s camera (PAPER_CAMERA) in the scenario's controls."""
        self.fov.value = PAPER_CAMERA["fov_deg"]
        self.resolution.value = PAPER_CAMERA["resolution"]
        self.mag.value = PAPER_CAMERA["mag_limit"]

    def set_pointing(self, ra_deg: float, dec_deg: float, roll_deg: float) -> None:
        self.ra.value, self.dec.value, self.roll.value = ra_deg, dec_deg, roll_deg

    def show_found(self, run) -> None:
        """A user's image solved: the Scenario tab shows what was found (the pointing, the fitted FOV, the
        depth the image shows) instead of the simulator's last values, and the method and variant that
        ran; "Back to the simulation" then renders the sky the photograph shows. Call quietly."""
        r, src = run.result, run.source
        if r.method in self.method.options:
            self.method.value = r.method
        if r.variant in self.variant.options:
            self.variant.value = r.variant
        if not r.solved:
            return
        ra, dec, roll = (math.degrees(x) for x in radec_roll_from_R(r.R))
        self.set_pointing(round(ra % 360.0, 3), round(dec, 3), round((roll + 180.0) % 360.0 - 180.0, 3))
        fov = round(src.fov_deg, 3)
        self.fov.value = min(max(fov, self.fov.min), self.fov.max)
        # the next photograph of this camera starts from it (a pinhole's hint: a fisheye's FOV is beyond it)
        self.upload_fov.value = min(max(fov, FOV_RANGE_DEG[0]), FOV_RANGE_DEG[1])
        if src.depth_mag is not None:
            self.mag.value = min(max(float(src.depth_mag), self.mag.min), self.mag.max)

    def sequence_wanted(self) -> bool:
        """A sequence is solved: the method identifies over sequences, or tracking is ticked."""
        return needs_sequence(self.method.value) or bool(self.track.value)

    def scene_config(self) -> SceneConfig:
        """The scenario the controls describe (validated: BadInput names a bad control)."""
        return SceneConfig(ra_deg=self.ra.value, dec_deg=self.dec.value, roll_deg=self.roll.value,
                           fov_deg=self.fov.value, resolution=self.resolution.value, mag_limit=self.mag.value,
                           noise_arcsec=self.noise.value, false_stars=self.false_stars.value,
                           dropped=self.dropped.value, seed=self.seed.value).checked()

    def sequence_config(self) -> SequenceConfig:
        """The sequence the controls describe (validated: BadInput names a bad control)."""
        return SequenceConfig(n_frames=self.n_frames.value, turn=self.turn.value,
                              step_deg=self.turn_step.value).checked()


def _escape(text: str) -> str:
    return str(text).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _rgb(c) -> str:
    return f"rgb({c[0]},{c[1]},{c[2]})"


def legend_markdown() -> str:
    """Every colour on screen: the centroid outcomes (at the last step) and the step roles (skyview.present.drawables)."""
    items = [f"<span style='color:{_rgb(c)}'>◯</span> {name}" for name, c in OUTCOME_RGB.items()]
    items += [f"<span style='color:{_rgb(PALETTE[k])}'>■</span> {text}" for k, text in LEGEND.items()]
    return "<small>" + " &nbsp; ".join(items) + "</small>"


def build_panel(gui, methods: list[str], variants: list[str], cfg: SceneConfig, photos: tuple[str, ...] = (),
                coverage_label: str | None = None) -> Panel:
    """Lay out the panel (docked right, dark); returns the handles."""
    gui.configure_theme(dark_mode=True, control_width="large", show_logo=False, show_share_button=False,
                        brand_color=(255, 184, 48))
    gui.main_panel.dock_right()
    gui.main_panel.set_width(400)
    gui.add_markdown("**skyview** &nbsp;·&nbsp; where is the camera pointing?")
    # a user's own photograph first: the upload is the first thing on the page
    # disabled until the session behind it is ready (`Session.__init__` enables it): an upload sent before its
    # callback is wired would be dropped
    upload = gui.add_upload_button("Upload and solve", icon="upload", mime_type=UPLOAD_TYPES,
                                   hint="your own star photograph (PNG / JPEG / TIFF / FITS): solved blind, no FOV "
                                        "needed", disabled=True)
    upload_fov = gui.add_number("FOV hint (deg)", initial_value=cfg.fov_deg, min=FOV_RANGE_DEG[0],
                                max=FOV_RANGE_DEG[1], step=0.1,
                                hint="a hint only (horizontal field of view): the FOV is fitted to the stars")
    gallery = gui.add_dropdown("Or a bundled photograph", (NO_PHOTO, *photos), initial_value=NO_PHOTO,
                               visible=bool(photos), hint="real photographs that come with skyview, solved blind")
    back = gui.add_button("Back to the simulation", visible=False)
    status = gui.add_markdown("starting…")
    progress = gui.add_progress_bar(100.0, animated=True, visible=False)
    error = gui.add_markdown("", visible=False)
    image = gui.add_image(np.zeros((8, 8, 3), np.uint8), format="jpeg", jpeg_quality=80)
    legend = gui.add_markdown(legend_markdown())
    tabs = gui.add_tab_group()

    seq_cfg = SequenceConfig()
    with tabs.add_tab("Steps", icon="player-play"):
        seq_box = gui.add_folder("Frames of the sequence", visible=False)
        with seq_box:
            frame = gui.add_slider("Frame", min=0, max=1, step=1, initial_value=0, disabled=True,
                                   hint="frames are numbered from 0, as in the method's steps")
            play_frames = gui.add_button("Play the frames", icon="player-track-next")
            frame_text = gui.add_markdown("")
            frame_plot = add_frame_plot(gui)
        step = gui.add_slider("Step", min=0, max=1, step=1, initial_value=0, disabled=True)
        play = gui.add_button("Play the steps", icon="player-play")
        step_text = gui.add_markdown("")
        plot_key = gui.add_dropdown("Plot across steps", ("-",), initial_value="-")
        with gui.add_folder("The chosen number across the steps", expand_by_default=True):
            step_plot = add_step_plot(gui)

    with tabs.add_tab("Scenario", icon="adjustments"):
        ra = gui.add_slider("RA (deg)", min=0.0, max=360.0, step=0.1, initial_value=cfg.ra_deg)
        dec = gui.add_slider("Dec (deg)", min=-90.0, max=90.0, step=0.1, initial_value=cfg.dec_deg)
        roll = gui.add_slider("Roll (deg)", min=-180.0, max=180.0, step=0.1, initial_value=cfg.roll_deg)
        random = gui.add_button("Random attitude", icon="dice-5")
        fov = gui.add_slider("FOV (deg)", min=1.0, max=60.0, step=0.5, initial_value=cfg.fov_deg,
                             hint="horizontal full field of view")
        resolution = gui.add_dropdown("Resolution", RESOLUTIONS, initial_value=cfg.resolution)
        mag = gui.add_slider("Mag limit (Hp)", min=3.0, max=7.5, step=0.1, initial_value=cfg.mag_limit,
                             hint="guide catalog and rendering limit")
        noise = gui.add_slider("Centroid noise (\")", min=0.0, max=120.0, step=1.0, initial_value=cfg.noise_arcsec,
                               hint="1-sigma jitter of each star's direction, arcsec")
        false_stars = gui.add_slider("False stars", min=0, max=10, step=1, initial_value=cfg.false_stars)
        dropped = gui.add_slider("Dropped stars", min=0, max=10, step=1, initial_value=cfg.dropped)
        seed = gui.add_number("Seed", initial_value=cfg.seed, min=0, step=1)
        method = gui.add_dropdown("Method", tuple(methods), initial_value=methods[0])
        variant = gui.add_dropdown("Variant", tuple(variants), initial_value=variants[0],
                                   hint="the paper's parameters, or the method's improvements")
        track = gui.add_checkbox("Track a sequence", initial_value=False,
                                 hint="any single-frame method: frame 0 lost-in-space, then tracking "
                                      "(skyview.solver.track); the sequence is set below")
        seq_controls = gui.add_folder("Sequence", visible=needs_sequence(methods[0]))
        with seq_controls:
            gui.add_markdown("<small>This method identifies over a <b>sequence</b> of frames with a known turn "
                             "between them: N frames from the attitude above. It needs many stars per frame "
                             "(the paper: 30° field, Hp ≤ 4.5).</small>")
            n_frames = gui.add_slider("Frames", min=FRAMES_RANGE[0], max=FRAMES_RANGE[1], step=1,
                                      initial_value=seq_cfg.n_frames)
            turn = gui.add_dropdown("Turn", TURNS, initial_value=seq_cfg.turn,
                                    hint="the known turn between consecutive frames")
            turn_step = gui.add_slider("Turn step (deg)", min=STEP_RANGE_DEG[0], max=STEP_RANGE_DEG[1], step=0.5,
                                       initial_value=seq_cfg.step_deg)
            paper_camera = gui.add_button("The paper's camera (30°, Hp ≤ 4.5)", icon="camera")
        auto = gui.add_checkbox("Solve on every change", initial_value=True)
        solve = gui.add_button("Solve", icon="target")
        compare = gui.add_button("Compare every method", icon="table")

    with tabs.add_tab("Result", icon="report-analytics"):
        result = gui.add_markdown("")
        export = gui.add_button("Export this run as .rrd", icon="download")
        export_json = gui.add_button("Download the result (JSON)", icon="download")
        compare_table = gui.add_markdown("")
        bench_table = gui.add_markdown("")  # `skyview view --compare FILE`: a bench --compare report

    with tabs.add_tab("View", icon="eye"):
        boresight = gui.add_button("Look down the boresight", icon="focus-2")
        wide = gui.add_button("Wide sky", icon="world")
        follow = gui.add_checkbox("Follow the boresight", initial_value=True)
        detections = gui.add_slider("Detections drawn", min=10, max=2000, step=10, initial_value=DETECTIONS_DRAWN,
                                    hint="the brightest detections ringed on the image (the identification "
                                         "uses its own brightest stars, whatever is drawn)")
        checks = {
            "stars": gui.add_checkbox("Catalog stars", initial_value=True),
            "grid": gui.add_checkbox("RA/Dec grid", initial_value=True),
            "constellations": gui.add_checkbox("Constellation figures", initial_value=True),
            "names": gui.add_checkbox("Bright star names", initial_value=True),
            "image": gui.add_checkbox("Sensor image on the frustum", initial_value=True),
            "numbers": gui.add_checkbox("Centroid numbers", initial_value=True),
            "hips": gui.add_checkbox("HIP ids of the matched stars", initial_value=False),
            "true": gui.add_checkbox("True attitude (simulated)", initial_value=True),
            "candidates": gui.add_checkbox("Step candidates", initial_value=True),
            "matches": gui.add_checkbox("Matched triangles", initial_value=True),
            "track": gui.add_checkbox("Footprints of a sequence's frames", initial_value=True),
        }
        if coverage_label is not None:  # `skyview view --coverage DIR`
            checks["coverage"] = gui.add_checkbox(coverage_label, initial_value=True)
        picked = gui.add_markdown("Click a star on the sphere for its HIP number and magnitude.")

    return Panel(status=status, progress=progress, error=error, image=image, legend=legend, tabs=tabs,
                 seq_box=seq_box, frame=frame, play_frames=play_frames, frame_text=frame_text,
                 frame_plot=frame_plot, step=step, play=play, step_text=step_text, plot_key=plot_key,
                 step_plot=step_plot,
                 ra=ra, dec=dec, roll=roll, random=random, fov=fov, resolution=resolution, mag=mag, noise=noise,
                 false_stars=false_stars, dropped=dropped, seed=seed, method=method, variant=variant,
                 seq_controls=seq_controls, track=track, n_frames=n_frames, turn=turn, turn_step=turn_step,
                 paper_camera=paper_camera, auto=auto,
                 solve=solve, compare=compare, upload_fov=upload_fov, upload=upload, gallery=gallery, back=back,
                 result=result, compare_table=compare_table, bench_table=bench_table, export=export,
                 export_json=export_json,
                 boresight=boresight, wide=wide,
                 follow=follow, detections=detections, checks=checks, picked=picked)


# ---------------------------------------------------------------------------------------------- text

def _deg(v: float, signed: bool = False) -> str:
    return f"{v:+.4f}°" if signed else f"{v:.4f}°"


def _arcsec(v: float | None) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.2f}″" if abs(v) < 100 else f"{v:.0f}″"


def status_markdown(run: Run) -> str:
    r = run.result
    head = f"{r.method} ({r.variant})"
    if r.solved:
        ra, dec, roll = (math.degrees(x) for x in radec_roll_from_R(r.R))
        err = ""
        if run.error_arcsec:
            err = f" · error {_arcsec(run.error_arcsec['boresight'])}"
        where = ""
        if run.source.truth is None:  # a user's image: where it is, in words (IAU constellations)
            where = " · in " + ", ".join(constellations_in_view(r.camera, r.R)[:3])
        mirrored = " · a mirror image (drawn turned over)" if getattr(r, "rows_reversed", False) else ""
        return (f"<span style='color:rgb(90,230,130)'>● solved</span> by {head}: RA {ra:.3f}° Dec {dec:+.3f}° "
                f"roll {roll:+.2f}°{err} · {len(r.matches)}/{len(r.centroids)} stars{where}{mirrored}")
    note = (" (one image only: this method identifies over a sequence of frames, which the viewer runs on "
            "simulated scenes)") if needs_sequence(r.method) else ""
    why = _escape(blind_summary(r)) if r.method == "blind" else r.reason
    return f"<span style='color:rgb(255,150,40)'>● not solved</span> by {head}: {why}{note}"


def _fov_text(run) -> str:
    """The FOV as given, or as fitted to the stars (with the distortion): a user's image, or the blind
    pipeline's result."""
    r = run.result
    if getattr(r, "camera_fitted", False) or getattr(run.source, "fitted", False):
        return f"{r.camera.fov_deg:.3f}° (fitted to the stars; k1 {r.camera.k1:+.3f})"
    return f"{run.source.fov_deg:g}°"


def result_markdown(run: Run, viewer_ms: dict | None = None) -> str:
    """Status, attitude, sigma, error against truth and time per stage."""
    r = run.result
    lines = [f"**{'Solved' if r.solved else 'Not solved'}** by **{r.method}** ({r.variant})  ",
             f"image: {run.source.name}, FOV {_fov_text(run)} ({r.camera.width}×{r.camera.height})  "]
    if not r.solved:
        lines.append(f"**Why:** {why_not(r)}  ")
        lines.append(f"\n<small>the solver's own words: {_escape(r.reason)}</small>  ")
    for note in getattr(r, "notes", ()):  # how the image was read or searched (a mirror image, a narrow field, ...)
        lines.append(f"<small>note: {_escape(note)}</small>  ")
    rows = [("centroids", f"{len(r.centroids)} (brightest {run.n_used} used)"),
            ("matched", f"{len(r.matches)}")]
    if r.R is not None:
        ra, dec, roll = (math.degrees(x) for x in radec_roll_from_R(r.R))
        rows += [("RA", _deg(ra)), ("Dec", _deg(dec, True)), ("roll", _deg(roll, True)),
                 ("1σ boresight / roll", f"{_arcsec(r.sigma_boresight_arcsec)} / {_arcsec(r.sigma_roll_arcsec)}")]
        ver = r.identification.verification if r.identification else {}
        if "p_false" in ver:
            rows.append(("P(false match)", format_number(float(ver["p_false"]))))
    if run.source.truth:
        t = run.source.truth
        rows.append(("truth", f"RA {t['ra_deg']:.4f}° Dec {t['dec_deg']:+.4f}° roll {t['roll_deg']:+.3f}°"))
        if run.error_arcsec:
            e = run.error_arcsec
            rows.append(("error vs truth", f"boresight {_arcsec(e['boresight'])}, roll {_arcsec(e['roll'])}"))
            rows.append(("wrong matches", str(run.wrong_matches)))
    for k, v in run.time_ms.items():
        rows.append((f"time: {k}", f"{v:.1f} ms"))
    for k, v in (viewer_ms or {}).items():
        rows.append((f"viewer: {k}", f"{v:.0f} ms"))
    lines.append("")
    lines.append("| | |")
    lines.append("|---|---|")
    lines += [f"| {a} | {b} |" for a, b in rows]
    return "\n".join(lines)


def step_markdown(run: Run, d: StepView | None) -> str:
    n = len(run.drawables)
    if d is None:
        return "No steps: the method did not run (no stars, or too few)." if n == 0 else ""
    lines = [f"**Step {d.index + 1} / {n} · {d.kind}**  ", d.note, ""]
    if d.numbers:
        lines += ["| number | value |", "|---|---|"]
        lines += [f"| {k} | {format_number(v)} |" for k, v in d.numbers.items()]
        lines.append("")
    lines.append(step_summary(d))
    for e in d.text:
        lines.append(f"  \n{e}")
    legend = " &nbsp; ".join(f"<span style='color:{_rgb(c)}'>■</span> {t}" for t, c in d.legend())
    if legend:
        lines.append(f"\n<small>{legend}</small>")
    if d.final and not run.result.solved:
        lines.append(f"\n**Not solved.** {why_not(run.result)}")
    return "\n".join(lines)


def compare_markdown(rows: list[dict], image_name: str) -> str:
    lines = [f"**Every method on the same image** ({image_name})", "",
             "| method | variant | status | steps | time | error | matched |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        err = r.get("error_arcsec")
        err_s = _arcsec(err["boresight"]) if err else "-"
        if r.get("wrong_matches"):
            err_s += f" ({r['wrong_matches']} wrong)"
        status = r["status"] if r["status"] != "error" else f"error: {r.get('reason', '')}"
        if r.get("needs_sequence"):
            status += " (one frame: needs a sequence)"
        lines.append(f"| {r['method']} | {r['variant']} | {status} | {r['steps']} | {r['time_ms']:.1f} ms | "
                     f"{err_s} | {r['matches']} |")
    if any(r.get("needs_sequence") for r in rows):
        lines += ["", f"<small>One frame of a sequence method: {SEQUENCE_NOTE.split(': ', 1)[1]}.</small>"]
    return "\n".join(lines)


def _band(star_id: int) -> str:
    """The magnitude a catalog number's star is given in: Hipparcos Hp, or Gaia G for a Gaia DR3 star."""
    return "G" if int(star_id) >= GAIA_ID_MIN else "Hp"


def star_markdown(hip: int, mag: float, ra_deg: float, dec_deg: float, name: str | None) -> str:
    title = f"**{name}** · " if name else ""
    return f"{title}**{designation(hip)}** · {_band(hip)} {mag:.2f}  \nRA {ra_deg:.4f}° · Dec {dec_deg:+.4f}°"


def bench_markdown(report: dict) -> str:
    """A `skyview bench --compare` report under this image's result (`skyview view --compare FILE`)."""
    from skyview.bench.compare import format_markdown

    return "---\n\n## Every method on the same images (`skyview bench --compare`)\n\n" + format_markdown(report)


def picked_star(catalog, row: int | None) -> tuple[str, str]:
    """A star clicked on the sphere (a catalog row, None: none near the click): its label on the
    sphere and what the View tab says of it."""
    if row is None:
        return "", "No catalog star there (click closer to a star)."
    hip, mag = int(catalog.hip[row]), float(catalog.mag[row])
    ra, dec = (float(np.degrees(a[row])) for a in catalog.ra_dec)
    name = STAR_NAMES.get(hip)
    return f"{name + ' · ' if name else ''}{designation(hip)} · {_band(hip)} {mag:.2f}", star_markdown(hip, mag, ra, dec, name)


# ---------------------------------------------------------------------------------------------- sequences

def _frames(seq: SequenceRun) -> str:
    n = len(seq)
    return "one frame" if n == 1 else f"frames 0–{n - 1}"


def _hip_name(hip: int) -> str:
    name = STAR_NAMES.get(int(hip))
    return designation(hip) + (f" ({name})" if name else "")


def _listing(ks: list[int]) -> str:
    """Frame numbers with runs compressed: 1, 3–5, 9."""
    if not ks:
        return "none"
    runs: list[list[int]] = []
    for k in ks:
        if runs and k == runs[-1][-1] + 1:
            runs[-1].append(k)
        else:
            runs.append([k])
    return ", ".join(f"{r[0]}–{r[-1]}" if len(r) > 2 else ", ".join(map(str, r)) for r in runs)


def sequence_status_markdown(seq: SequenceRun, k: int) -> str:
    """The status line of a sequence: which frame was identified (or not), its error, the frame shown."""
    head = f"{seq.method} ({seq.variant})"
    shown = f" · showing frame {k}"
    if seq.frame is not None:
        first = seq.identified[0]
        run = seq.frames[seq.frame]
        err = f" · frame {seq.frame}: error {_arcsec(run.error_arcsec['total'])}" if run.error_arcsec else ""
        return (f"<span style='color:rgb(90,230,130)'>● identified</span> by {head} at frame {first} "
                f"({_frames(seq)}; verified at {_listing(seq.identified)}){err}{shown}")
    last = seq.result.identifications[-1] if seq.result.identifications else None
    reason = f": {last.reason}" if last is not None and last.reason else ""
    return (f"<span style='color:rgb(255,150,40)'>● not identified</span> in {_frames(seq)} by {head}"
            f"{reason}{shown}")


def frame_markdown(seq: SequenceRun, k: int) -> str:
    """What frame k of a sequence says: identified or not, the posterior's summary, error vs truth."""
    run = seq.frames[k]
    ident = seq.result.identifications[k]
    st = ident.stats
    lines = []
    if run.result.solved:
        err = ""
        if run.error_arcsec:
            e = run.error_arcsec
            err = (f" · error vs truth {_arcsec(e['total'])} (boresight {_arcsec(e['boresight'])}, roll "
                   f"{_arcsec(e['roll'])}) · {run.wrong_matches} wrong match{'es' if run.wrong_matches != 1 else ''}")
        lines.append(f"**Frame {k}** ({_frames(seq)}) · <span style='color:rgb(90,230,130)'>identified</span>, "
                     f"{len(run.result.matches)} stars matched{err}")
    else:
        lines.append(f"**Frame {k}** ({_frames(seq)}) · <span style='color:rgb(255,150,40)'>not identified</span>"
                     f"{': ' + ident.reason if ident.reason else ''}")
    parts = []
    if st.get("above_prior") is not None:
        parts.append(f"{int(st['above_prior'])} of {len(seq.result.catalog)} stars above the prior")
    if st.get("top_hips"):
        parts.append(f"leading {_hip_name(st['top_hips'][0])} at {format_number(float(st['top_posterior']))}")
    truth = seq.result.truth_figures()[k]  # scored against the truth (skyview.simulate.scoring), not by the method
    if truth["true_row"] is not None:
        hip = int(seq.result.catalog.hip[truth["true_row"]])
        parts.append(f"true star {_hip_name(hip)} at {format_number(float(truth['true_posterior']))}")
    if parts:
        lines.append(" · ".join(parts))
    return "\n\n".join(lines)


def sequence_markdown(seq: SequenceRun) -> str:
    """The Result tab's head for a sequence: settings, which frames were identified, a row per frame."""
    sc = seq.scene
    lines = [f"**{'Identified' if seq.frame is not None else 'Not identified'}** by **{seq.method}** "
             f"({seq.variant}) over a sequence of {seq.config.describe()}, from RA {sc.ra_deg:g}° Dec "
             f"{sc.dec_deg:+g}° roll {sc.roll_deg:g}°  "]
    if seq.frame is not None:
        run = seq.frames[seq.frame]
        err = f"; error vs truth {_arcsec(run.error_arcsec['total'])}" if run.error_arcsec else ""
        lines.append(f"identified at frame {seq.identified[0]}; verified at frames {_listing(seq.identified)}; "
                     f"the answer is frame {seq.frame}'s attitude{err}  ")
    else:
        lines.append("no frame verified: the posterior has not concentrated on one star (or the leading "
                     "hypotheses did not verify)  ")
    ser = seq.series()
    lines += ["", "| frame | status | above 1/N | leading | P | P(true) | error |", "|---|---|---|---|---|---|---|"]
    for k, run in enumerate(seq.frames):
        st = seq.result.identifications[k].stats
        lead = f"HIP {st['top_hips'][0]}" if st.get("top_hips") else "-"
        err = _arcsec(run.error_arcsec["total"]) if run.error_arcsec else "-"
        if run.wrong_matches:
            err += f" ({run.wrong_matches} wrong)"
        lines.append(f"| {k} | {seq.result.identifications[k].status} | {format_number(ser['above_prior'][k])} | "
                     f"{lead} | {format_number(ser['top_posterior'][k])} | {format_number(ser['true_posterior'][k])} "
                     f"| {err} |")
    lines.append("")
    lines.append(" · ".join(f"{name} {v:.0f} ms" for name, v in seq.time_ms.items()) + f" ({len(seq)} frames)")
    return "\n".join(lines)
