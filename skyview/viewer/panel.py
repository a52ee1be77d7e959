"""The side panel: its widgets, and the text it shows for results, steps and comparisons.

`build_panel` lays out the controls in a viser `GuiApi` (one browser tab's or the server's); the
`*_markdown` functions turn `Run` objects into the panel's text. No callbacks here: `app` wires them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skyview.attitude import radec_roll_from_R
from skyview.viewer.picture import HIGHLIGHT_RGB, OUTCOME_RGB
from skyview.viewer.run import FOV_RANGE_DEG, RESOLUTIONS, Run, SceneConfig
from skyview.viewer.steps import StepDrawable, format_number

PLOT_COLORS = ("#e848d2", "#ffd23c")


@dataclass
class Panel:
    """Handles of every widget of one session's panel."""

    status: object
    progress: object
    error: object
    image: object
    legend: object
    tabs: object
    # steps
    step: object
    play: object
    step_text: object
    plot_key: object
    plot_box: object  # folder holding the uPlot (re-created when the series change)
    # scenario
    ra: object
    dec: object
    roll: object
    random: object
    fov: object
    resolution: object
    mag: object
    noise: object
    false_stars: object
    dropped: object
    seed: object
    method: object
    variant: object
    auto: object
    solve: object
    compare: object
    upload_fov: object
    upload: object
    back: object
    # result
    result: object
    compare_table: object
    export: object
    # view
    boresight: object
    wide: object
    follow: object
    checks: dict
    picked: object


def _rgb(c) -> str:
    return f"rgb({c[0]},{c[1]},{c[2]})"


def legend_markdown() -> str:
    items = [f"<span style='color:{_rgb(c)}'>◯</span> {name}" for name, c in OUTCOME_RGB.items()]
    items.append(f"<span style='color:{_rgb(HIGHLIGHT_RGB)}'>◎</span> used by this step")
    return "<small>" + " &nbsp; ".join(items) + "</small>"


def build_panel(gui, methods: list[str], variants: list[str], cfg: SceneConfig) -> Panel:
    """Lay out the panel; returns the handles."""
    gui.add_markdown("**skyview** &nbsp;·&nbsp; where is the camera pointing?")
    status = gui.add_markdown("starting…")
    progress = gui.add_progress_bar(100.0, animated=True, visible=False)
    error = gui.add_markdown("", visible=False)
    image = gui.add_image(np.zeros((8, 8, 3), np.uint8), format="jpeg", jpeg_quality=80)
    legend = gui.add_markdown(legend_markdown())
    tabs = gui.add_tab_group()

    with tabs.add_tab("Steps", icon="player-play"):
        step = gui.add_slider("Step", min=0, max=1, step=1, initial_value=0, disabled=True)
        play = gui.add_button("Play the steps", icon="player-play")
        step_text = gui.add_markdown("")
        plot_key = gui.add_dropdown("Plot across steps", ("-",), initial_value="-")
        plot_box = gui.add_folder("Candidates per step", expand_by_default=True)

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
        auto = gui.add_checkbox("Solve on every change", initial_value=True)
        solve = gui.add_button("Solve", icon="target")
        compare = gui.add_button("Compare every method", icon="table")
        gui.add_markdown("**Your own image** (PNG / JPEG)")
        upload_fov = gui.add_number("Image FOV (deg)", initial_value=cfg.fov_deg, min=FOV_RANGE_DEG[0],
                                    max=FOV_RANGE_DEG[1], step=0.1, hint="horizontal full field of view")
        upload = gui.add_upload_button("Upload and solve", icon="upload", mime_type="image/png,image/jpeg")
        back = gui.add_button("Back to the simulation", visible=False)

    with tabs.add_tab("Result", icon="report-analytics"):
        result = gui.add_markdown("")
        export = gui.add_button("Export this run as .rrd", icon="download")
        compare_table = gui.add_markdown("")

    with tabs.add_tab("View", icon="eye"):
        boresight = gui.add_button("Look down the boresight", icon="focus-2")
        wide = gui.add_button("Wide sky", icon="world")
        follow = gui.add_checkbox("Follow the boresight", initial_value=True)
        checks = {
            "stars": gui.add_checkbox("Catalog stars", initial_value=True),
            "grid": gui.add_checkbox("RA/Dec grid", initial_value=True),
            "names": gui.add_checkbox("Bright star names", initial_value=True),
            "image": gui.add_checkbox("Sensor image on the frustum", initial_value=True),
            "numbers": gui.add_checkbox("Centroid numbers", initial_value=True),
            "hips": gui.add_checkbox("HIP ids of the matched stars", initial_value=False),
            "true": gui.add_checkbox("True attitude (simulated)", initial_value=True),
            "candidates": gui.add_checkbox("Step candidates", initial_value=True),
            "matches": gui.add_checkbox("Matched triangles", initial_value=True),
        }
        picked = gui.add_markdown("Click a star on the sphere for its HIP number and magnitude.")

    return Panel(status=status, progress=progress, error=error, image=image, legend=legend, tabs=tabs,
                 step=step, play=play, step_text=step_text, plot_key=plot_key, plot_box=plot_box,
                 ra=ra, dec=dec, roll=roll, random=random, fov=fov, resolution=resolution, mag=mag, noise=noise,
                 false_stars=false_stars, dropped=dropped, seed=seed, method=method, variant=variant, auto=auto,
                 solve=solve, compare=compare, upload_fov=upload_fov, upload=upload, back=back,
                 result=result, compare_table=compare_table, export=export, boresight=boresight, wide=wide,
                 follow=follow, checks=checks, picked=picked)


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
        return (f"<span style='color:rgb(90,230,130)'>● solved</span> by {head}: RA {ra:.3f}° Dec {dec:+.3f}° "
                f"roll {roll:+.2f}°{err} · {len(r.matches)}/{len(r.centroids)} stars")
    return f"<span style='color:rgb(255,150,40)'>● not solved</span> by {head}: {r.reason}"


def result_markdown(run: Run, viewer_ms: dict | None = None) -> str:
    """Status, attitude, sigma, error against truth and time per stage."""
    r = run.result
    lines = [f"**{'Solved' if r.solved else 'Not solved'}** by **{r.method}** ({r.variant})  ",
             f"image: {run.source.name}, FOV {run.source.fov_deg:g}° ({r.camera.width}×{r.camera.height})  "]
    if not r.solved:
        lines.append(f"reason: {r.reason}  ")
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


def step_markdown(run: Run, d: StepDrawable | None) -> str:
    n = len(run.drawables)
    if d is None:
        return "No steps: the method did not run (no stars, or too few)." if n == 0 else ""
    lines = [f"**Step {d.index + 1} / {n} · {d.kind}**  ", d.note, ""]
    if d.numbers:
        lines += ["| number | value |", "|---|---|"]
        lines += [f"| {k} | {format_number(v)} |" for k, v in d.numbers.items()]
        lines.append("")
    obs = ", ".join(str(int(i)) for i in d.observed[:24]) + (" …" if len(d.observed) > 24 else "")
    parts = [f"observed: {obs or '-'}", f"candidate stars: {len(d.candidates)}", f"groups drawn: {d.n_groups}"]
    if d.weights is not None:
        parts.append(f"candidates tinted by {d.weight_name} (magenta low, yellow high)")
    if len(d.points):
        parts.append(f"{len(d.points)} points on the sphere: {d.points_name}")
    if d.attitudes:
        parts.append(f"{len(d.attitudes)} attitude footprint(s)")
    lines.append(" · ".join(parts))
    for e in d.extras:
        lines.append(f"  \n{e}")
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
        lines.append(f"| {r['method']} | {r['variant']} | {status} | {r['steps']} | {r['time_ms']:.1f} ms | "
                     f"{err_s} | {r['matches']} |")
    return "\n".join(lines)


def star_markdown(hip: int, mag: float, ra_deg: float, dec_deg: float, name: str | None) -> str:
    title = f"**{name}** · " if name else ""
    return f"{title}**HIP {hip}** · Hp {mag:.2f}  \nRA {ra_deg:.4f}° · Dec {dec_deg:+.4f}°"
