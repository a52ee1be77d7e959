"""Centroid accuracy benchmark: simulated star fields with known truth -> detect -> compare.

`measure_centroid_accuracy` renders random attitudes (uniform on SO(3)) with skyview.simulate.render,
runs skyview.detect.centroids.detect_centroids with each estimator on the same images, matches every
detection to the nearest rendered object (catalog star or false star) within `match_radius_px`
(each object matched once, closest detection first) and reports:

- RMS position error by SNR bin, per axis (sqrt of the mean of du^2 and dv^2 pooled) and radial
  (sqrt of the mean of du^2 + dv^2), plus the mean bias per axis;
  SNR is the model SNR of the truth, not measured: S / sqrt(S + 4 pi sigma_psf^2 (B + D t + RN^2 + g^2/12))
  with S the star's expected electrons (SensorModel.snr);
- detection completeness by catalog magnitude (fraction of rendered stars matched);
- false detections per image (detections matching no rendered object);
- time per image of detect_centroids (and of the render, separately).

Called by `skyview bench --centroids`; `format_markdown` renders the result as tables.
"""

from __future__ import annotations

import math
import time
from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from skyview.core.attitude import random_attitudes
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, load_guide_catalog
from skyview.detect.centroids import DEFAULT_ESTIMATOR, ESTIMATORS, detect_centroids
from skyview.simulate.render import SensorModel, simulate_image

DEFAULT_SNR_BINS = (0.0, 10.0, 20.0, 40.0, 80.0, 160.0, math.inf)
GOAL_RMS_PX = 0.1
GOAL_SNR_MIN = 20.0


def _match(det_uv: np.ndarray, true_uv: np.ndarray, radius: float) -> np.ndarray:
    """For each detection, the index of its matched true object or -1 (one-to-one, closest first)."""
    out = np.full(len(det_uv), -1, dtype=np.int64)
    if len(det_uv) == 0 or len(true_uv) == 0:
        return out
    d, i = cKDTree(true_uv).query(det_uv, distance_upper_bound=radius)
    cand = np.flatnonzero(np.isfinite(d))
    taken = np.zeros(len(true_uv), dtype=bool)
    for k in cand[np.argsort(d[cand], kind="stable")]:
        if not taken[i[k]]:
            taken[i[k]] = True
            out[k] = i[k]
    return out


def _fnum(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _err_stats(err: np.ndarray) -> dict:
    n = len(err)
    if n == 0:
        return {"n": 0, "rms_axis_px": None, "rms_radial_px": None, "bias_u_px": None, "bias_v_px": None,
                "p95_radial_px": None}
    r2 = np.sum(err * err, axis=1)
    return {
        "n": int(n),
        "rms_axis_px": float(np.sqrt(np.mean(err * err))),
        "rms_radial_px": float(np.sqrt(np.mean(r2))),
        "bias_u_px": float(err[:, 0].mean()),
        "bias_v_px": float(err[:, 1].mean()),
        "p95_radial_px": float(np.percentile(np.sqrt(r2), 95)),
    }


def measure_centroid_accuracy(n_images: int = 100, seed: int = 0, fov_deg: float = 8.0, *, width: int = 1024,
                              height: int | None = None, mag_limit: float = 8.5, sensor: SensorModel | None = None,
                              estimators: Sequence[str] = ESTIMATORS, match_radius_px: float = 2.0,
                              k_sigma: float = 5.0, snr_bins: Sequence[float] = DEFAULT_SNR_BINS,
                              mag_bin_width: float = 0.5, n_false_stars: int = 0,
                              catalog: GuideCatalog | None = None,
                              progress: Callable[[int, int], None] | None = None) -> dict:
    """Monte Carlo centroid accuracy; returns a JSON-ready dict (see the module docstring).

    Stars down to mag_limit (default 8.5, fainter than the 6.0 identification limit, so that the
    low-SNR bins and the completeness roll-off are populated) are rendered with `sensor`
    (default SensorModel()); attitude k uses image seed `seed * 1_000_003 + k`.
    """
    sensor = SensorModel() if sensor is None else sensor
    estimators = list(estimators)
    for e in estimators:
        if e not in ESTIMATORS:
            raise ValueError(f"unknown estimator {e!r}")
    catalog = load_guide_catalog() if catalog is None else catalog
    camera = Camera.from_fov(fov_deg, width, height)
    rng = np.random.default_rng(seed)
    Rs = random_attitudes(int(n_images), rng)
    snr_edges = np.asarray(snr_bins, dtype=np.float64)

    errs: dict[str, list] = {e: [] for e in estimators}  # rows: du, dv, snr
    found: dict[str, list] = {e: [] for e in estimators}  # rows: mag, detected(0/1)
    false_det = {e: 0 for e in estimators}
    n_det = {e: 0 for e in estimators}
    n_elong = {e: 0 for e in estimators}
    n_hot = {e: 0 for e in estimators}
    t_det: dict[str, list] = {e: [] for e in estimators}
    t_render = []
    n_stars = []
    for k, R in enumerate(Rs):
        t0 = time.perf_counter()
        frame = simulate_image(catalog, camera, R, sensor, seed=seed * 1_000_003 + k, mag_limit=mag_limit,
                               n_false_stars=n_false_stars)
        t_render.append(time.perf_counter() - t0)
        stars = frame.truth["stars"]
        fs = frame.truth["false_stars"]
        n_stars.append(len(stars))
        true_uv = np.array([[s["u_noisy"], s["v_noisy"]] for s in stars]
                           + [[s["u"], s["v"]] for s in fs], dtype=np.float64).reshape(-1, 2)
        true_snr = np.array([s["snr"] for s in stars] + [s["snr"] for s in fs], dtype=np.float64)
        mags = np.array([s["mag"] for s in stars], dtype=np.float64)
        for e in estimators:
            t0 = time.perf_counter()
            c = detect_centroids(frame.image, estimator=e, k_sigma=k_sigma)
            t_det[e].append(time.perf_counter() - t0)
            m = _match(c.uv, true_uv, match_radius_px)
            ok = m >= 0
            n_det[e] += len(c)
            n_elong[e] += int(c.elongated.sum())
            n_hot[e] += c.n_hot_pixels_rejected
            false_det[e] += int((~ok).sum())
            if ok.any():
                d = c.uv[ok] - true_uv[m[ok]]
                errs[e].append(np.column_stack([d, true_snr[m[ok]]]))
            hit = np.zeros(len(stars), dtype=bool)
            hit[m[ok & (m < len(stars))]] = True
            found[e].append(np.column_stack([mags, hit]))
        if progress is not None:
            progress(k + 1, int(n_images))

    mag_lo = math.floor(min((float(np.min(np.concatenate(found[estimators[0]])[:, 0]))
                             if estimators and any(len(a) for a in found[estimators[0]]) else 0.0), 0.0))
    mag_edges = np.arange(mag_lo, mag_limit + mag_bin_width, mag_bin_width)
    nimg = max(int(n_images), 1)
    out_est = {}
    for e in estimators:
        E = np.concatenate(errs[e]) if errs[e] else np.zeros((0, 3))
        by_snr = []
        for lo, hi in zip(snr_edges[:-1], snr_edges[1:]):
            sel = (E[:, 2] >= lo) & (E[:, 2] < hi)
            by_snr.append({"snr_lo": _fnum(lo), "snr_hi": _fnum(hi), **_err_stats(E[sel, :2])})
        goal_sel = E[:, 2] >= GOAL_SNR_MIN
        F = np.concatenate(found[e]) if found[e] else np.zeros((0, 2))
        comp = []
        for lo, hi in zip(mag_edges[:-1], mag_edges[1:]):
            sel = (F[:, 0] >= lo) & (F[:, 0] < hi) if hi < mag_edges[-1] else (F[:, 0] >= lo) & (F[:, 0] <= hi)
            nt = int(sel.sum())
            if nt == 0:
                continue
            nd = int(F[sel, 1].sum())
            comp.append({"mag_lo": float(lo), "mag_hi": float(hi), "n_true": nt, "n_detected": nd,
                         "completeness": nd / nt})
        ts = np.asarray(t_det[e]) * 1e3
        snr20 = _err_stats(E[goal_sel, :2])
        out_est[e] = {
            "by_snr": by_snr,
            "snr_ge_20": snr20,
            "goal_met": bool(snr20["n"] > 0 and snr20["rms_radial_px"] <= GOAL_RMS_PX),
            "completeness_by_mag": comp,
            "detections_per_image": n_det[e] / nimg,
            "false_detections_per_image": false_det[e] / nimg,
            "false_detections_total": false_det[e],
            "elongated_per_image": n_elong[e] / nimg,
            "hot_pixels_rejected_per_image": n_hot[e] / nimg,
            "time_ms": {"mean": float(ts.mean()) if ts.size else None,
                        "median": float(np.median(ts)) if ts.size else None,
                        "p95": float(np.percentile(ts, 95)) if ts.size else None},
        }
    tr = np.asarray(t_render) * 1e3
    return {
        "config": {
            "n_images": int(n_images), "seed": int(seed), "fov_deg": float(fov_deg), "width": camera.width,
            "height": camera.height, "mag_limit": float(mag_limit), "k_sigma": float(k_sigma),
            "match_radius_px": float(match_radius_px), "n_false_stars": int(n_false_stars),
            "sensor": sensor.to_dict(), "sensor_derived": sensor.describe(),
            "snr_definition": "model SNR from the truth electrons S: S / sqrt(S + 4 pi sigma_psf^2 "
                              "(B + D t + RN^2 + g^2/12)) (SensorModel.snr), not measured",
            "rms_definition": "rms_axis: sqrt(mean(du^2, dv^2 pooled)); rms_radial: sqrt(mean(du^2 + dv^2))",
            "goal": f"rms_radial <= {GOAL_RMS_PX} px for SNR >= {GOAL_SNR_MIN:g}",
        },
        "stars_per_image": float(np.mean(n_stars)) if n_stars else 0.0,
        "render_ms": {"mean": float(tr.mean()) if tr.size else None,
                      "median": float(np.median(tr)) if tr.size else None},
        "default_estimator": DEFAULT_ESTIMATOR,
        "estimators": out_est,
    }


def _f(x, fmt="{:.3f}") -> str:
    return "-" if x is None else fmt.format(x)


def format_markdown(result: dict) -> str:
    """The benchmark result as Markdown tables."""
    cfg = result["config"]
    sd = cfg["sensor_derived"]
    est = result["estimators"]
    names = list(est)
    lines = [
        "## Centroid accuracy",
        "",
        f"{cfg['n_images']} random attitudes, seed {cfg['seed']}, FOV {cfg['fov_deg']:g} deg, "
        f"{cfg['width']}x{cfg['height']} px, stars to Hp {cfg['mag_limit']:g} "
        f"({result['stars_per_image']:.1f} per image), k_sigma {cfg['k_sigma']:g}, "
        f"match radius {cfg['match_radius_px']:g} px. Sensor: {cfg['sensor']['bit_depth']}-bit, "
        f"PSF sigma {cfg['sensor']['psf_sigma_px']:g} px, Hp 6.0 = {sd['electrons_hp6']:.0f} e- "
        f"(SNR {sd['snr_hp6']:.1f}), saturation at Hp {sd['saturation_hp']:.2f}.",
        "",
        f"SNR: {cfg['snr_definition']}. {cfg['rms_definition']}. Default estimator: "
        f"`{result['default_estimator']}`.",
        "",
        "### RMS error (px) by SNR: per axis / radial",
        "",
        "| SNR | n | " + " | ".join(f"`{n}`" for n in names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    bins = est[names[0]]["by_snr"] if names else []
    for b_i, b in enumerate(bins):
        hi = "inf" if b["snr_hi"] is None else f"{b['snr_hi']:g}"
        cells = []
        for n in names:
            s = est[n]["by_snr"][b_i]
            cells.append(f"{_f(s['rms_axis_px'])} / {_f(s['rms_radial_px'])}")
        lines.append(f"| {b['snr_lo']:g}-{hi} | {b['n']} | " + " | ".join(cells) + " |")
    cells = [f"**{_f(est[n]['snr_ge_20']['rms_axis_px'])} / {_f(est[n]['snr_ge_20']['rms_radial_px'])}**"
             for n in names]
    lines.append(f"| >= 20 | {est[names[0]]['snr_ge_20']['n'] if names else 0} | " + " | ".join(cells) + " |")
    lines += ["", f"Goal {cfg['goal']}: " + ", ".join(
        f"`{n}` {'met' if est[n]['goal_met'] else 'NOT met'}" for n in names), ""]
    lines += ["### Detection and time per image", "",
              "| estimator | detections | false | elongated | hot px rejected | detect ms (median / p95) |",
              "|---|---|---|---|---|---|"]
    for n in names:
        s = est[n]
        lines.append(f"| `{n}` | {s['detections_per_image']:.1f} | {s['false_detections_per_image']:.3f} | "
                     f"{s['elongated_per_image']:.2f} | {s['hot_pixels_rejected_per_image']:.2f} | "
                     f"{_f(s['time_ms']['median'], '{:.1f}')} / {_f(s['time_ms']['p95'], '{:.1f}')} |")
    lines += ["", f"Render time per image: {_f(result['render_ms']['median'], '{:.1f}')} ms (median).", ""]
    if names:
        comp = est[result["default_estimator"] if result["default_estimator"] in est else names[0]]
        lines += ["### Completeness by magnitude", "", "| Hp | stars | detected | completeness |",
                  "|---|---|---|---|"]
        for c in comp["completeness_by_mag"]:
            lines.append(f"| {c['mag_lo']:.1f}-{c['mag_hi']:.1f} | {c['n_true']} | {c['n_detected']} | "
                         f"{100 * c['completeness']:.1f} % |")
        lines.append("")
    return "\n".join(lines)


def time_centroiding(n_frames: int = 50, *, detect: Callable | None = None, real_images: Sequence[str] = (),
                     seed: int = 0) -> dict:
    """Median wall time (ms) of one centroider call per frame kind, over n_frames calls each:
    simulated 1024x1024 frames in 8 and 16 bit (default SensorModel, 8 deg, stars to Hp 8.5, ten
    attitudes cycled) and the given real photographs (cycled). detect: the centroider timed (default
    `detect_centroids`; the former implementation, `tests/oracles/centroid_reference.py`'s
    `_detect_centroids_reference`, to compare). Run it on one core (taskset -c 0, OMP_NUM_THREADS=1);
    OpenCV is set to one thread here."""
    import cv2

    from skyview.detect.centroids import load_image
    cv2.setNumThreads(1)
    fn = detect_centroids if detect is None else detect
    catalog = load_guide_catalog()
    cam = Camera.from_fov(8.0, 1024)
    Rs = random_attitudes(10, np.random.default_rng(seed))
    kinds = {f"sim {b}-bit 1024x1024": [simulate_image(catalog, cam, R, SensorModel(bit_depth=b), seed=k,
                                                         mag_limit=8.5).image for k, R in enumerate(Rs)]
             for b in (8, 16)}
    if real_images:
        kinds["real 16-bit 1024x768"] = [load_image(p) for p in real_images]
    out = {}
    for name, frames in kinds.items():
        fn(frames[0])  # warm-up
        ts, ns = [], []
        for k in range(n_frames):
            t0 = time.perf_counter()
            c = fn(frames[k % len(frames)])
            ts.append(time.perf_counter() - t0)
            ns.append(len(c))
        out[name] = {"median_ms": 1e3 * float(np.median(ts)), "median_stars": float(np.median(ns))}
    return out
