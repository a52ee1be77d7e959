"""Rerun recordings (.rrd) of a frame sequence solved by the stochastic method.

Long (about 700 lines) because a sequence recording is one document in sections (drawing helpers, the
result document, the blueprint, frame by frame writing, the paper's experiment runner) that share one
frame/step timeline layout.

`record_sequence(path, seq_result, images, truths=...)` writes one `sequence.SequenceResult`: every frame
on a `frame` timeline (the sequence index), and every step of every frame on the `step` timeline, which
runs on across frames (frame 0's steps are 0, 1; frame 1's 2, 3, 4; ...). `record_paper_sequence`
simulates the paper's experiment (Udomkesmalee et al.: the boresight on Betelgeuse, 10 deg turns along
right ascension, 5 frames, 0.6 mag magnitude noise; docs/stochastic.md), solves it and records it
(`skyview record --method stochastic`); `skyview solve-sequence PATH --record OUT.rrd` records a sequence
read from disk. The sky, the colours, the image stretch, the step drawing and the safe writing are
`skyview.record.draw`'s (steps are `skyview.present.drawables` StepViews, as in the viewer); this module adds
what a sequence has and a single image does not. Entity paths
(docs/recordings.md) — those of `skyview.record.recording` with the same meaning, per frame:

    sky/catalog, sky/grid               the guide catalog and the RA/Dec grid (static)
    sky/fov/estimated, sky/fov/true     the frame's footprint at its estimated (when identified) / true attitude
    sky/observed                        the frame's centroids under its shown attitude
    sky/matches, camera/image/matches   the frame's verified matches (when identified)
    camera, camera/image                the frame's camera pose (shown attitude), pinhole and image
    camera/image/centroids              the frame's centroids, labelled with their brightness rank
    camera/image/truth/...              where the simulator drew stars and false stars (truth known)
    truth/camera                        the frame's true camera (truth known)
    sky/step/<role>, camera/image/step/<role>  the step's drawables; steps/log, steps/numbers/<unit>/<n>
    result                              the sequence summary (Markdown, static)

and its own:

    sky/path/true                       the true boresight path over the frames (static, truth known)
    sky/designated                      the frame's designated star, ringed, under the shown attitude
    camera/image/designated             the designated star ringed in the image
    sky/hypotheses                      the leading hypotheses' catalog stars, sized and tinted by posterior
    sky/true_designated                 the catalog star the designated star really is (truth known), ringed
    sequence/above_prior                Scalars: how many stars have a posterior above the prior 1/N
    sequence/posterior/top_posterior    Scalars: the leading star's posterior
    sequence/posterior/true_posterior   Scalars: the true designated star's posterior (truth known)
    sequence/posterior/true_sequence_posterior  Scalars: the posterior of the true sequence (its row)

"The shown attitude" of a frame is its estimated attitude when the frame was identified, else the true
one when known, else the attitude of the nearest identified frame carried by the known turns (when the
turns are given); without any, the frame has no camera pose and no 3D centroids.
"""

from __future__ import annotations

import hashlib
import math
import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from skyview.core import sky_geometry as sg
from skyview.core.attitude import attitude_error_arcsec, east_north, quat_from_R, radec_roll_from_R
from skyview.core.errors import BadInput
from skyview.present.drawables import posterior_figures, step_views
from skyview.record import draw as D
from skyview.record.recording import write_matches
from skyview.simulate.scoring import sequence_truth

FRAME_TIMELINE = "frame"
STEP_TIMELINE = D.TIMELINE

# Entity paths of a sequence recording (besides skyview.record.recording's, which keep their meaning per frame).
TRUE_PATH = "sky/path/true"
DESIGNATED = "sky/designated"
IMAGE_DESIGNATED = "camera/image/designated"
HYPOTHESES = "sky/hypotheses"
TRUE_DESIGNATED = "sky/true_designated"
SEQUENCE = "sequence"
ABOVE_PRIOR = "sequence/above_prior"
POSTERIOR = "sequence/posterior"
TOP_POSTERIOR = "sequence/posterior/top_posterior"
TRUE_POSTERIOR = "sequence/posterior/true_posterior"
TRUE_SEQUENCE_POSTERIOR = "sequence/posterior/true_sequence_posterior"
SERIES = {  # per-frame series: entity path -> (the frame stat it plots, colour, legend)
    ABOVE_PRIOR: ("above_prior", (120, 170, 255), "stars above the prior 1/N"),
    TOP_POSTERIOR: ("top_posterior", (255, 190, 40), "leading star"),
    TRUE_POSTERIOR: ("true_posterior", (80, 220, 120), "true star"),
    TRUE_SEQUENCE_POSTERIOR: ("true_sequence_posterior", (0, 200, 255), "true sequence (its row)"),
}

C_DESIGNATED = (255, 255, 255)
C_HYP_LOW = (110, 80, 170)  # a hypothesis with posterior ~0 ...
C_HYP_HIGH = (255, 190, 40)  # ... and one with posterior 1
DESIGNATED_RING_RAD = math.radians(0.6)
TRUE_RING_RAD = math.radians(1.0)
DESIGNATED_RING_PX = 16.0
RING_POINTS = 33

# The paper's experiment as `skyview record --method stochastic` simulates it (docs/stochastic.md).
PAPER_SCENARIO = "udomkesmalee30"
PAPER_FRAMES = 5
PAPER_STEP_DEG = 10.0
PAPER_SIGMA_MAG = 0.6
RECORD_NOISE_ARCSEC = 10.0  # the paper's "10" read as arcseconds: the sequence is identified and verified
NOISE_NOTE = ("Position noise 10 arcsec per axis: the paper's \"10\" read as arcseconds, so that the sequence is "
              "identified and its attitude verified. At the 1 deg reading (the scenario's own noise) the posterior "
              "converges too, but no attitude can be verified (docs/stochastic.md).")


@dataclass
class SequenceRecordInfo(D.RecordInfo):
    """What `record_sequence` wrote: RecordInfo (steps = entries on the step timeline, all frames) plus
    the number of frames and the identified frame (the latest verified one, None when none)."""

    frames: int = 0
    frame: int | None = None
    identified: list[int] | None = None  # every identified (verified) frame


# ============================================================================ drawing helpers

def _ring3d(d: np.ndarray, radius_rad: float) -> np.ndarray:
    """A small circle of angular radius `radius_rad` about the unit vector d, on the unit sphere."""
    e, n = east_north(np.asarray(d, dtype=np.float64))
    t = np.linspace(0.0, 2.0 * np.pi, RING_POINTS)
    s = math.sin(radius_rad)
    pts = math.cos(radius_rad) * d[None, :] + s * (np.cos(t)[:, None] * e[None, :] + np.sin(t)[:, None] * n[None, :])
    return pts.astype(np.float32)


def _ring2d(uv: np.ndarray, radius_px: float) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * np.pi, RING_POINTS)
    c = D.rerun_uv(uv)[0]
    return np.stack([c[0] + radius_px * np.cos(t), c[1] + radius_px * np.sin(t)], axis=1).astype(np.float32)


def hypothesis_style(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Radius on the unit sphere and RGB colour of hypotheses of posterior p (absolute, so that frames
    compare): sqrt(p) from small and dim purple (p = 0) to large and gold (p = 1)."""
    t = np.sqrt(np.clip(np.asarray(p, dtype=np.float64), 0.0, 1.0))
    radii = (0.004 + 0.018 * t).astype(np.float32)
    lo, hi = np.array(C_HYP_LOW, dtype=np.float64), np.array(C_HYP_HIGH, dtype=np.float64)
    colors = np.round(lo[None, :] + t[:, None] * (hi - lo)[None, :]).astype(np.uint8)
    return radii, colors


class _Frames:
    """Logs per-frame entities and clears, at a frame, those drawn at an earlier frame but not at this one
    (an entity never drawn is never created)."""

    def __init__(self, rec):
        self.rec = rec
        self.drawn: set[str] = set()

    def log(self, path: str, *archetypes, static: bool = False) -> None:
        self.rec.log(path, *archetypes, static=static)
        self.drawn.add(path)

    def clear(self, path: str) -> None:
        if path in self.drawn:
            self.rec.log(path, rr.Clear(recursive=False))
            self.drawn.discard(path)


def shown_attitudes(seq_result, true_R: list | None, turns: list | None) -> tuple[list, list[str]]:
    """Per frame, the attitude the recording shows and where it comes from: "estimated" (the frame was
    identified), "true", "carried from frame j" (the nearest identified frame through the known turns,
    R_{k+1} = dR_cam R_k), or None / "none"."""
    ids = seq_result.identifications
    K = len(ids)
    out: list = [None] * K
    how = ["none"] * K
    for k, r in enumerate(ids):
        if r.identified and r.R is not None:
            out[k], how[k] = np.asarray(r.R, dtype=np.float64), "estimated"
        elif true_R is not None and true_R[k] is not None:
            out[k], how[k] = np.asarray(true_R[k], dtype=np.float64), "true"
    done = [k for k in range(K) if how[k] == "estimated"]
    if turns is not None and len(turns) == K - 1 and done:
        for k in range(K):
            if out[k] is not None:
                continue
            j = min(done, key=lambda j: (abs(j - k), -j))
            R = np.asarray(ids[j].R, dtype=np.float64)
            if j < k:
                for i in range(j, k):
                    R = np.asarray(turns[i], dtype=np.float64) @ R
            else:
                for i in range(j - 1, k - 1, -1):
                    R = np.asarray(turns[i], dtype=np.float64).T @ R
            out[k], how[k] = R, f"carried from frame {j}"
    return out, how


def _truth_rows(seq_result, truths):
    """Per frame, the true catalog row of every observed star (from the result, else from the sidecars)."""
    if seq_result.truth is not None:
        return seq_result.truth
    if truths is None or not seq_result.observations:
        return None
    from skyview.solver.sequence import truth_rows

    return [truth_rows(o.uv, t, seq_result.catalog) for o, t in zip(seq_result.observations, truths)]


def frame_figures(seq_result, rows=None) -> list[dict]:
    """Per frame, the figures a recording shows, read from the steps' Posterior layers
    (`present.posterior_figures`) and scored against the truth rows here (`skyview.simulate.scoring`), not
    taken from the method: designated, top_rows, top_mass, top_hips, top_posterior, above_prior,
    true_row, true_posterior, true_sequence_posterior (`scoring.sequence_truth`); plus the method's own
    count of field stars (stars)."""
    cat = seq_result.catalog
    out = []
    scored = sequence_truth(seq_result.identifications, rows)
    for k, r in enumerate(seq_result.identifications):
        f = dict(posterior_figures(r.steps) or {})
        f.update({key: scored[k][key] for key in ("true_row", "true_posterior", "true_sequence_posterior")})
        f["top_hips"] = [int(cat.hip[c]) for c in f.get("top_rows", [])]
        f["stars"] = r.stats.get("stars")
        out.append(f)
    return out


def sequence_outcome(seq_result, rows=None) -> str:
    """correct (the last frame identified, no identified frame with a wrong match), incorrect (a wrong
    match anywhere), inconclusive (not identified at the last frame), or unknown (no truth: solved/failed)."""
    ids = seq_result.identifications
    if rows is None:
        rows = seq_result.truth
    if rows is None:
        return "solved" if (ids and ids[-1].identified) else "failed"
    for k, r in enumerate(ids):
        if r.identified and any(int(rows[k][o]) != int(c) for o, c in r.matches.items()):
            return "incorrect"
    return "correct" if (ids and ids[-1].identified) else "inconclusive"


# ============================================================================ the result document

def _f(v: Any, fmt: str = ".3f") -> str:
    if v is None:
        return "-"
    try:
        return format(float(v), fmt)
    except (TypeError, ValueError):
        return str(v)


def sequence_markdown(seq_result, *, true_R: list | None = None, rows: list | None = None, meta: dict | None = None,
                      reference: dict | None = None, notes: list[str] | None = None, how: list[str] | None = None,
                      image_note: str = "") -> str:
    """The sequence as Markdown: the per-frame posterior table (beside the paper's Table 2 when
    `reference` is given), the identified frame, its attitude and its error against the truth."""
    ids = seq_result.identifications
    cat = seq_result.catalog
    K = len(ids)
    k_id = seq_result.frame
    N = len(cat)
    done = [k for k, r in enumerate(ids) if r.identified]
    head = (f"{K} frames, identified at frame{'s' if len(done) > 1 else ''} {', '.join(map(str, done))}" if done
            else f"{K} frames, not identified")
    lines = [f"# {seq_result.method} ({seq_result.variant}): sequence of {head}", ""]
    if k_id is None and ids:
        lines += [f"**Reason (last frame):** {ids[-1].reason}", ""]
    if meta:
        lines += ["| | |", "|---|---|"] + [f"| {k} | {D.fmt(v)} |" for k, v in meta.items()] + [""]
    for n in notes or []:
        lines += [n, ""]
    lines += ["## Frames", "",
              f"{N} hypotheses (catalog stars), prior 1/{N} = {1.0 / N:.5f}. *Above 1/N*: stars whose posterior "
              "is above the prior; *P(true)*: the posterior of the star the designated star really is; "
              "*P(true seq.)*: the posterior of the sequence (row) that started on the true star.", ""]
    cols = ["frame", "centroids", "stars", "designated", "above 1/N", "leading HIP", "P(leading)", "true HIP",
            "P(true)", "P(true seq.)"]
    if reference:
        cols += ["paper: above 1/N", "paper: P(true)"]
    cols += ["status", "shown attitude"]
    lines += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    figs = frame_figures(seq_result, rows)
    for k, r in enumerate(ids):
        st = figs[k]
        n_c = len(seq_result.centroids[k]) if seq_result.centroids is not None else (
            len(seq_result.observations[k]) if seq_result.observations else None)
        tr = st.get("true_row")
        true_hip = int(cat.hip[tr]) if tr is not None and tr >= 0 else None
        cells = [str(k), _f(n_c, "d") if n_c is not None else "-", _f(st.get("stars"), "d") if st.get("stars")
                 is not None else "-", "-" if st.get("designated") is None else f"#{st['designated']}",
                 _f(st.get("above_prior"), "d") if st.get("above_prior") is not None else "-",
                 str(st["top_hips"][0]) if st.get("top_hips") else "-", _f(st.get("top_posterior")),
                 "-" if true_hip is None else str(true_hip), _f(st.get("true_posterior")),
                 _f(st.get("true_sequence_posterior"))]
        if reference:
            a, p = reference.get("above_prior", []), reference.get("true_posterior", [])
            cells += [str(a[k]) if k < len(a) else "", str(p[k]) if k < len(p) else ""]
        status = r.status if r.identified else f"{r.status}"
        cells += [status, (how[k] if how else "-")]
        lines.append("| " + " | ".join(cells) + " |")
    if reference and reference.get("what"):
        lines += ["", f"*paper:* {reference['what']}."]
    if k_id is not None:
        r = ids[k_id]
        ra, dec, roll = radec_roll_from_R(r.R)
        q = quat_from_R(r.R)
        v = r.verification or {}
        lines += ["", f"## Attitude (estimated, frame {k_id})", "",
                  f"- RA **{math.degrees(ra):.5f}°**, Dec **{math.degrees(dec):+.5f}°**, roll "
                  f"**{math.degrees(roll):+.4f}°**",
                  f"- quaternion [w x y z]: {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}",
                  f"- designated star HIP {int(cat.hip[r.matches[figs[k_id]['designated']]])}"
                  if figs[k_id].get("designated") in r.matches else "- designated star: -",
                  f"- {len(r.matches)} stars matched; verification: "
                  + ", ".join(f"{k} {D.fmt(v[k])}" for k in ("n_agree", "n_tested", "p_false", "p_magnitudes")
                              if k in v)]
        obs = seq_result.observations[k_id] if seq_result.observations else None
        lines += ["", "| # | u | v | HIP | Hp |", "|---|---|---|---|---|"]
        for o, c in sorted(r.matches.items()):
            u, vv = (obs.uv[o] if obs is not None else (float("nan"), float("nan")))
            lines.append(f"| {o} | {u:.2f} | {vv:.2f} | {int(cat.hip[c])} | {float(cat.mag[c]):.2f} |")
    if true_R is not None:
        lines += ["", "## Truth", ""]
        for k in range(K):
            if true_R[k] is None:
                continue
            ra, dec, roll = radec_roll_from_R(np.asarray(true_R[k], dtype=float))
            line = f"- frame {k}: RA {math.degrees(ra):.5f}°, Dec {math.degrees(dec):+.5f}°, roll {math.degrees(roll):+.4f}°"
            r = ids[k]
            if r.identified and r.R is not None:
                e = attitude_error_arcsec(r.R, np.asarray(true_R[k], dtype=float))
                line += (f"; error: boresight **{e['boresight']:.2f}\"**, roll **{e['roll']:.1f}\"**, total "
                         f"{e['total']:.2f}\"")
                if rows is not None:
                    wrong = [o for o, c in r.matches.items() if int(rows[k][o]) != int(c)]
                    line += f"; wrong matches: **{len(wrong)}**"
            lines.append(line)
    t = seq_result.time_ms
    if t:
        lines += ["", "## Time (ms)", "", "| stage | ms |", "|---|---|"] + [f"| {k} | {v:.2f} |" for k, v in t.items()]
    if image_note:
        lines += ["", f"*Images:* {image_note}; every frame is stretched the same way from its own background."]
    if seq_result.database_key:
        import json

        lines += ["", "*Database key:* `" + json.dumps(seq_result.database_key, sort_keys=True, default=str) + "`"]
    return "\n".join(lines) + "\n"


# ============================================================================ the blueprint

def sequence_eye(R_view: np.ndarray | None) -> D.SkyEye | None:
    """The sky view's opening eye: from the sphere's centre side, looking at the middle of the path (the
    blueprint's, and the one the HIP labels are laid out for)."""
    if R_view is None:
        return None
    R_view = np.asarray(R_view, dtype=np.float64)
    b, up = R_view[2], -R_view[1]
    return D.SkyEye(-0.6 * b - 0.05 * up, b, up)


def sequence_blueprint(R_view: np.ndarray | None, plots: list) -> rrb.Blueprint:
    """The 3D sky (from the sphere's centre, looking at the middle of the path), the sensor image, the
    posterior plots over the frames, and tabs with the step log, the result and the bar charts."""
    eye = None
    sky_eye = sequence_eye(R_view)
    if sky_eye is not None:
        eye = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=sky_eye.position.tolist(),
                                look_target=sky_eye.target.tolist(), eye_up=sky_eye.up.tolist())
    sky = rrb.Spatial3DView(name="sky", origin="/", contents=["/sky/**", "/camera/**", "/truth/**"],
                            background=[5, 8, 16], line_grid=rrb.LineGrid3D(visible=False), eye_controls=eye,
                            spatial_information=D.NO_AXES)
    tabs = [rrb.TextLogView(name="step log", origin=f"/{D.STEP_LOG}"),
            rrb.TextDocumentView(name="result", origin=f"/{D.RESULT}")]
    seen: set[str] = set()
    tabs += [pl for pl in plots if not (pl.name in seen or seen.add(pl.name))]  # one plot per unit
    plots = rrb.Horizontal(
        rrb.TimeSeriesView(name="posterior over frames", origin=f"/{POSTERIOR}", axis_y=rrb.ScalarAxis(range=(0.0, 1.0)),
                           plot_legend=rrb.Corner2D.LeftTop),
        rrb.TimeSeriesView(name="stars above 1/N", origin=f"/{ABOVE_PRIOR}", plot_legend=rrb.Corner2D.RightTop),
        column_shares=[3, 2])
    right = rrb.Vertical(rrb.Spatial2DView(name="image", origin=f"/{D.IMAGE}"), plots, rrb.Tabs(*tabs, active_tab=0),
                         row_shares=[5, 3, 3])
    return rrb.Blueprint(rrb.Horizontal(sky, right, column_shares=[3, 2]),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed", timeline=FRAME_TIMELINE))


# ============================================================================ writing

def record_sequence(path: str | os.PathLike, seq_result, images: list[np.ndarray], *, truths: list[dict] | None = None,
                    turns: list[np.ndarray] | None = None, force: bool = False, meta: dict | None = None,
                    notes: list[str] | None = None, reference: dict | None = None,
                    name: str | None = None) -> SequenceRecordInfo:
    """Write `seq_result` (a sequence.SequenceResult of `images`, one per frame; None for a frame that could
    not be read) as a Rerun recording.

    truths: the simulator's per-frame truth dicts when known (true attitude, drawn stars, false stars);
    without them the result's own `true_R` (and truth rows) are used when it has them. turns: the known
    turns (dR_cam, one fewer than frames), to carry an identified attitude to the frames that have
    neither an estimate nor a truth. meta / notes: key-values and sentences for the result document;
    reference: the paper's Table 2 ({"above_prior": [...], "true_posterior": [...]}) for its table.
    Same path rules as `record.record_solve` (checked first; nothing overwritten unless `force`).
    """
    t0 = time.perf_counter()
    p = D.check_output_path(path, force)
    ids = list(seq_result.identifications)
    K = len(ids)
    if K == 0:
        raise BadInput("the sequence has no frames to record")
    images = [None if im is None else np.asarray(im) for im in images]
    camera = seq_result.camera
    if len(images) != K:
        raise BadInput(f"{len(images)} images for a sequence of {K} frames")
    for k, im in enumerate(images):
        if im is not None and im.shape != (camera.height, camera.width):
            raise BadInput(f"image {k} is {im.shape[-1]}x{im.shape[0]} but the camera is {camera.width}x{camera.height}")
    if truths is not None and len(truths) != K:
        raise BadInput(f"{len(truths)} truth sidecars for a sequence of {K} frames")
    if turns is not None and len(turns) != K - 1:
        raise BadInput(f"{len(turns)} turns for a sequence of {K} frames (need {K - 1})")
    catalog = seq_result.catalog
    true_R = ([np.asarray(t["R"], dtype=np.float64) for t in truths] if truths is not None
              else ([np.asarray(R, dtype=np.float64) for R in seq_result.true_R] if seq_result.true_R is not None
                    else None))
    rows = _truth_rows(seq_result, truths)
    figs = frame_figures(seq_result, rows)
    shown, how = shown_attitudes(seq_result, true_R, turns)
    if seq_result.centroids is not None:
        centroids = [np.asarray(c.uv, dtype=np.float64).reshape(-1, 2) for c in seq_result.centroids]
    else:  # solved from observation vectors: draw what the method saw
        centroids = [np.asarray(o.uv, dtype=np.float64).reshape(-1, 2) for o in seq_result.observations]
    if len(centroids) != K:
        raise BadInput(f"the result has centroids for {len(centroids)} of its {K} frames")
    steps = [list(r.steps) for r in ids]
    views = [step_views(ss, catalog.xyz, len(uv), camera=camera, hip=catalog.hip) for ss, uv in zip(steps, centroids)]
    with_view = [R for R in shown if R is not None]
    R_mid = shown[K // 2] if shown[K // 2] is not None else (with_view[len(with_view) // 2] if with_view else None)

    title = name or p.stem
    digest = hashlib.sha1()
    for im in images:
        digest.update(b"-" if im is None else np.ascontiguousarray(im).tobytes())
    rec_id = str(uuid.uuid5(uuid.NAMESPACE_URL, f"skyview:{title}:{seq_result.method}:{seq_result.variant}:"
                                                f"sequence:{digest.hexdigest()}"))
    n_steps = sum(len(s) for s in steps)
    with D.open_recording(p, rec_id, title, sequence_blueprint(R_mid, [p for vv in views for p in D.unit_plots(vv)])) as rec:
        _write_static(rec, seq_result, true_R, figs)
        image_note = ""
        fr = _Frames(rec)
        first = 0
        drawn: set[str] = set()
        for k in range(K):
            rec.set_time(FRAME_TIMELINE, sequence=k)
            rec.set_time(STEP_TIMELINE, sequence=first)
            note = _write_frame(fr, k, seq_result, images[k], centroids[k], shown[k],
                                None if true_R is None else true_R[k], None if truths is None else truths[k], figs[k],
                                eye=sequence_eye(R_mid))
            if note:
                image_note = image_note or f"frame {k}: {note}"
            for i, v in enumerate(views[k]):
                rec.set_time(STEP_TIMELINE, sequence=first + i)
                drawn = D.log_step(rec, v, centroids[k], drawn)
            at = next((first + i for i, s in enumerate(steps[k]) if s.kind == "update"),
                      first + max(len(steps[k]) - 1, 0))
            rec.set_time(STEP_TIMELINE, sequence=at)
            for path_, (key, _, _) in SERIES.items():
                v = figs[k].get(key)
                if v is not None and math.isfinite(float(v)):
                    rec.log(path_, rr.Scalars(float(v)))
            first += len(steps[k])
        rec.log(D.RESULT, rr.TextDocument(
            sequence_markdown(seq_result, true_R=true_R, rows=rows, meta=meta, reference=reference, notes=notes,
                              how=how, image_note=image_note), media_type=rr.MediaType.MARKDOWN), static=True)
    k_id = seq_result.frame
    return SequenceRecordInfo(path=p, bytes=p.stat().st_size, write_ms=(time.perf_counter() - t0) * 1e3,
                              steps=n_steps, status="solved" if k_id is not None else "failed", frames=K, frame=k_id,
                              identified=[k for k, r in enumerate(ids) if r.identified])


def _write_static(rec, seq_result, true_R, figs) -> None:
    catalog, camera = seq_result.catalog, seq_result.camera
    D.log_sky(rec, catalog)
    rec.log(D.IMAGE, *D.pinhole(camera, color=D.C_FOV_EST), static=True)
    if true_R is not None:
        rec.log(D.TRUE_CAMERA, *D.pinhole(camera, color=D.C_FOV_TRUE), static=True)
        b = [np.asarray(R, dtype=np.float64)[2] for R in true_R]
        if len(b) >= 2:
            arcs = [sg.great_circle_arc(b[k], b[k + 1], 24) for k in range(len(b) - 1)]
            rec.log(TRUE_PATH, rr.LineStrips3D([np.concatenate(arcs).astype(np.float32)], colors=D.C_TRUTH,
                                               radii=rr.Radius.ui_points(1.0)), static=True)
    for path_, (key, color, label) in SERIES.items():  # the legend of each series the frames have
        if all(f.get(key) is None for f in figs):
            continue
        rec.log(path_, rr.SeriesLines(colors=color, names=label, widths=2.0), rr.SeriesPoints(
            colors=color, names=label, markers="circle", marker_sizes=4.0), static=True)


def _write_frame(fr: _Frames, k: int, seq_result, image, uv_c: np.ndarray, R_view, R_true, truth, st: dict, *,
                 eye: D.SkyEye | None = None) -> str:
    """Everything of frame k that is not a step (logged at its frame and its first step); returns how the
    image was stretched for display."""
    camera, catalog = seq_result.camera, seq_result.catalog
    r = seq_result.identifications[k]
    R_est = np.asarray(r.R, dtype=np.float64) if (r.identified and r.R is not None) else None
    # --- the camera: pose, image, centroids
    if R_view is not None:
        fr.log(D.CAMERA, D.pose(R_view))
    else:
        fr.clear(D.CAMERA)
    if image is None:  # (a frame that could not be read: no picture, its error in the result)
        fr.clear(D.IMAGE)
        note = ""
    else:
        shown_img, note = D.display_image(image)
        fr.log(D.IMAGE, rr.Image(shown_img, color_model="L").compress(jpeg_quality=D.JPEG_QUALITY))
    n = len(uv_c)
    labels = [f"#{i}" for i in range(n)]
    fr.log(D.CENTROIDS, rr.Points2D(D.rerun_uv(uv_c) if n else np.zeros((0, 2), np.float32),
                                      radii=rr.Radius.ui_points(4.0), colors=D.C_CENTROID, labels=labels,
                                      show_labels=False, draw_order=20))
    if R_view is not None and n:
        v = camera.unproject(uv_c) @ R_view
        fr.log(D.OBSERVED, rr.Points3D(v.astype(np.float32), radii=0.004, colors=D.C_OBSERVED, labels=labels,
                                         show_labels=False))
    else:
        fr.clear(D.OBSERVED)
    # --- footprints and the true camera
    if R_est is not None:
        fr.log(D.FOV_ESTIMATED, rr.LineStrips3D([sg.sensor_footprint(camera, R_est).astype(np.float32)],
                                                  colors=D.C_FOV_EST, radii=rr.Radius.ui_points(1.5)))
    else:
        fr.clear(D.FOV_ESTIMATED)
    if R_true is not None:
        fr.log(D.FOV_TRUE, rr.LineStrips3D([sg.sensor_footprint(camera, R_true).astype(np.float32)],
                                             colors=D.C_FOV_TRUE, radii=rr.Radius.ui_points(1.0)))
        fr.log(D.TRUE_CAMERA, D.pose(R_true))
    # --- the designated star, ringed in the image and on the sky
    d = st.get("designated")
    if d is not None and 0 <= int(d) < n:
        d = int(d)
        fr.log(IMAGE_DESIGNATED, rr.LineStrips2D([_ring2d(uv_c[d:d + 1], DESIGNATED_RING_PX)],
                                                  colors=C_DESIGNATED, radii=rr.Radius.ui_points(1.5),
                                                  labels=[f"designated #{d}"], show_labels=True, draw_order=25))
        if R_view is not None:
            v_d = camera.unproject(uv_c[d:d + 1])[0] @ R_view
            fr.log(DESIGNATED, rr.LineStrips3D([_ring3d(v_d, DESIGNATED_RING_RAD)], colors=C_DESIGNATED,
                                                radii=rr.Radius.ui_points(1.5), labels=[f"designated #{d}"],
                                                show_labels=True))
        else:
            fr.clear(DESIGNATED)
    else:
        fr.clear(IMAGE_DESIGNATED)
        fr.clear(DESIGNATED)
    # --- the leading hypotheses and the true designated star
    top = [int(c) for c in st.get("top_rows", []) if 0 <= int(c) < len(catalog)]
    post = np.asarray(st.get("top_mass", [])[:len(top)], dtype=np.float64)
    if top:
        radii, colors = hypothesis_style(post)
        fr.log(HYPOTHESES, rr.Points3D(catalog.xyz[top].astype(np.float32), radii=radii, colors=colors,
                                        labels=[f"HIP {int(catalog.hip[c])}: {p:.3f}" for c, p in zip(top, post)],
                                        show_labels=True))
    else:
        fr.clear(HYPOTHESES)
    tr = st.get("true_row")
    if tr is not None and 0 <= int(tr) < len(catalog):
        tr = int(tr)
        fr.log(TRUE_DESIGNATED, rr.LineStrips3D([_ring3d(catalog.xyz[tr], TRUE_RING_RAD)], colors=D.C_TRUTH,
                                                 radii=rr.Radius.ui_points(1.5),
                                                 labels=[f"true: HIP {int(catalog.hip[tr])}"], show_labels=True))
    else:
        fr.clear(TRUE_DESIGNATED)
    # --- the verified matches
    if R_est is not None and r.matches:
        write_matches(fr, sorted((int(o), int(c)) for o, c in r.matches.items()), catalog, camera, R_est, False,
                      stars_uv=uv_c, eye=eye)
    else:
        for path_ in (D.MATCHES, D.MATCH_LABELS, D.IMAGE_MATCHES, D.IMAGE_LABELS):
            fr.clear(path_)
    # --- where the simulator drew stars
    if truth is not None:
        stars = truth.get("stars", [])
        if stars:
            uv = np.array([[s.get("u_noisy", s["u"]), s.get("v_noisy", s["v"])] for s in stars])
            fr.log(D.TRUTH_STARS, rr.Points2D(D.rerun_uv(uv), radii=rr.Radius.ui_points(10.0),
                                                colors=D.C_TRUTH + (60,), labels=[f"HIP {s['hip']}" for s in stars],
                                                show_labels=False, draw_order=5))
        else:
            fr.clear(D.TRUTH_STARS)
        false = truth.get("false_stars", [])
        if false:
            uv = np.array([[f["u"], f["v"]] for f in false])
            fr.log(D.TRUTH_FALSE_STARS, rr.Points2D(D.rerun_uv(uv), radii=rr.Radius.ui_points(10.0),
                                                      colors=D.C_FALSE + (140,), labels=["false star"] * len(false),
                                                      show_labels=True, draw_order=6))
        else:
            fr.clear(D.TRUTH_FALSE_STARS)
    return note


# ============================================================================ the paper's experiment

@dataclass
class SequenceCase:
    """One simulated, solved sequence of the paper's experiment."""

    scenario: str
    variant: str
    seed: int  # the bench seed: this is run 0 of `skyview bench-sequence --noise-arcsec 10 --seed SEED`
    run_seed: int  # the seed of the images and the magnitude noise
    sim: Any  # simulate.SimulatedSequence
    result: Any  # sequence.SequenceResult
    outcome: str  # correct | inconclusive | incorrect
    meta: dict
    sim_ms: float


class PaperSequenceRunner:
    """The paper's experiment at image level, set up as `sequence.bench_sequence` sets it up (start on
    Betelgeuse, roll 0; 10 deg turns along RA; 5 frames; PAPER_SENSOR; the scenario's camera, catalog
    limit and false stars; 0.6 mag magnitude noise on the measured brightness), with the position noise
    read as 10 arcsec. `run(seed)` is run 0 of `bench_sequence(scenario, seed=seed, position_noise_rad=10")`:
    the same images, the same noise, the same posteriors."""

    def __init__(self, scenario: str = PAPER_SCENARIO, variant: str = "paper", catalog=None,
                 noise_arcsec: float = RECORD_NOISE_ARCSEC, n_frames: int = PAPER_FRAMES):
        from skyview.core.catalog import load_guide_catalog
        from skyview.simulate.scenarios import get_scenario
        from skyview.solver.sequence import PAPER_SENSOR, SequenceSolver, zero_point

        if variant not in ("paper", "improved"):
            raise BadInput(f"unknown variant {variant!r}: choose from paper, improved")
        self.scenario = get_scenario(scenario)
        self.variant = variant
        self.noise_arcsec = float(noise_arcsec)
        self.noise_rad = math.radians(self.noise_arcsec / 3600.0)
        self.n_frames = int(n_frames)
        self.camera = self.scenario.camera()
        self.catalog = catalog if catalog is not None else load_guide_catalog()
        self.sensor = PAPER_SENSOR
        pix = self.camera.pixel_scale_rad * self.scenario.centroid_sigma_px
        self.sigma_rad = float(np.hypot(self.noise_rad, pix))  # as bench_sequence (image level)
        self.solver = SequenceSolver(self.camera, "stochastic", mag_limit=self.scenario.mag_limit,
                                     sigma_rad=self.sigma_rad, catalog=self.catalog, variant=variant,
                                     method_params={"mag_zero_point": zero_point(self.sensor)})

    def run(self, seed: int) -> SequenceCase:
        from skyview.simulate.render import HIP_BETELGEUSE, R_pointing_at, simulate_sequence, turn_along_ra

        sc = self.scenario
        # bench_sequence's seeds: run i has integers(0, 2**31 - 1, size=n_runs)[i] of default_rng(seed)
        run_seed = int(np.random.default_rng(int(seed)).integers(0, 2**31 - 1, size=1)[0])
        t0 = time.perf_counter()
        sim = simulate_sequence(self.catalog, self.camera, R_pointing_at(self.catalog, HIP_BETELGEUSE),
                                self.n_frames, turn_along_ra(math.radians(PAPER_STEP_DEG)), self.sensor,
                                seed=run_seed, mag_limit=sc.mag_limit, position_noise_rad=self.noise_rad,
                                n_false_stars=sc.n_false_stars, false_star_placement=sc.false_star_placement)
        sim_ms = (time.perf_counter() - t0) * 1e3
        turns = [sim.dR_cam(k) for k in range(self.n_frames - 1)]
        res = self.solver.solve_images([f.image for f in sim.frames], turns, [f.truth for f in sim.frames],
                                       sigma_mag=PAPER_SIGMA_MAG, seed=run_seed)
        outcome = sequence_outcome(res)
        meta = {"method": "stochastic", "variant": self.variant, "scenario": f"{sc.name}: {sc.description}",
                "experiment": (f"the paper's: boresight on Betelgeuse (HIP {HIP_BETELGEUSE}), roll 0, "
                               f"{PAPER_STEP_DEG:g} deg turns along right ascension, {self.n_frames} frames"),
                "position noise": f"{self.noise_arcsec:g} arcsec per axis (+ {sc.centroid_sigma_px:g} px centroiding)",
                "magnitude noise": f"{PAPER_SIGMA_MAG:g} mag (1 sigma, on the measured brightness)",
                "sensor": f"exposure {self.sensor.exposure_s:g} s, {self.sensor.bit_depth}-bit",
                "seed": int(seed), "image seed": run_seed, "outcome against truth": outcome,
                "simulate ms": round(sim_ms, 2),
                "remake": f"skyview record --method stochastic --variant {self.variant} --scenario {sc.name} "
                          f"--seed {int(seed)}",
                "same as": f"run 0 of skyview bench-sequence --scenario {sc.name} --noise-arcsec "
                           f"{self.noise_arcsec:g} --variant {self.variant} --seed {int(seed)}"}
        return SequenceCase(sc.name, self.variant, int(seed), run_seed, sim, res, outcome, meta, sim_ms)

    def record(self, case: SequenceCase, path: str | os.PathLike, force: bool = False) -> SequenceRecordInfo:
        from skyview.solver.sequence import PAPER_TABLE2

        sim = case.sim
        notes = [NOISE_NOTE]
        if self.noise_arcsec != RECORD_NOISE_ARCSEC:
            notes = [f"Position noise {self.noise_arcsec:g} arcsec per axis."]
        return record_sequence(path, case.result, [f.image for f in sim.frames], truths=[f.truth for f in sim.frames],
                               turns=[sim.dR_cam(k) for k in range(len(sim.frames) - 1)], force=force,
                               meta=case.meta, notes=notes,
                               reference={**PAPER_TABLE2, "what": "the paper's Table 2 (one run, 1 deg noise)"})


def record_paper_sequence(path: str | os.PathLike, seed: int = 0, *, scenario: str = PAPER_SCENARIO,
                          variant: str = "paper", force: bool = False, catalog=None
                          ) -> tuple[SequenceRecordInfo, SequenceCase]:
    """Simulate the paper's experiment (run 0 of bench seed `seed`), solve it and record it at `path`."""
    D.check_output_path(path, force)  # fail before the slow part
    runner = PaperSequenceRunner(scenario, variant, catalog)
    case = runner.run(seed)
    return runner.record(case, path, force), case


def record_example(path: Path, *, scenario: str = PAPER_SCENARIO, catalog=None, force: bool = False,
                   seed_start: int = 1, tries: int = 40) -> dict | None:
    """The example recording of the paper's experiment: the first seed from `seed_start` whose sequence the
    paper variant identifies at its last frame with no wrong match. Returns its manifest entry (None when
    no seed in the range qualifies)."""
    runner = PaperSequenceRunner(scenario, "paper", catalog)
    for seed in range(seed_start, seed_start + tries):
        case = runner.run(seed)
        if case.outcome == "correct":
            break
    else:
        return None
    info = runner.record(case, path, force=force)
    res = case.result
    return {"file": Path(path).name, "method": "stochastic", "variant": "paper", "scenario": scenario,
            "seed": case.seed, "status": info.status, "outcome": case.outcome,
            "reason": "" if res.solved else res.identifications[-1].reason, "steps": info.steps,
            "bytes": info.bytes, "write_ms": round(info.write_ms, 1),
            "solve_ms": round(sum(res.time_ms.values()), 1), "frames": info.frames, "identified_frames": info.identified,
            "noise_arcsec": runner.noise_arcsec,
            "true_posterior": [None if f.get("true_posterior") is None else round(f["true_posterior"], 4)
                               for f in frame_figures(res, _truth_rows(res, [f.truth for f in case.sim.frames]))]}
