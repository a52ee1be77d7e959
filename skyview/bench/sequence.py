"""Monte Carlo of a sequence method over frame sequences: the stochastic method on Udomkesmalee et al.'s
own experiment by default (`skyview bench-sequence`, docs/stochastic.md).

Each run simulates a sequence (image level: the OpenCV simulator and the centroider; vector level: the
paper's perturbed catalog directions), identifies it with `skyview.solver.sequence.SequenceSolver` and scores
every frame against the truth; the summary sets the posterior of the true star beside the paper's
Table 2 and 100-run figure.
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter

import numpy as np

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.catalog import load_guide_catalog
from skyview.core.errors import BadInput
from skyview.detect.centroids import detect_centroids
from skyview.simulate.render import (
    HIP_BETELGEUSE,
    R_pointing_at,
    Turn,
    simulate_sequence,
    turn_about_camera_axis,
    turn_along_ra,
)
from skyview.simulate.scenarios import Scenario
from skyview.solver.result import observation
from skyview.solver.sequence import (
    DESIGNATIONS,
    LEVELS,
    PAPER_100_RUNS,
    PAPER_SENSOR,
    PAPER_TABLE2,
    STARTS,
    TURNS,
    SequenceSolver,
    perturb_magnitudes,
    truth_rows,
    vector_frame,
    zero_point,
)


def _turn(kind: str, step_rad: float) -> Turn:
    if kind == "ra":
        return turn_along_ra(step_rad)
    if kind == "pan":
        return turn_about_camera_axis("y", step_rad)
    raise BadInput(f"unknown turn {kind!r}: choose from {', '.join(TURNS)}")


def bench_sequence(scenario: Scenario, n_runs: int = 100, *, n_frames: int = 5, start: str = "betelgeuse",
                   turn: str = "ra", step_deg: float = 10.0, level: str = "image",
                   position_noise_rad: float | None = None, sigma_mag: float = 0.6, designation: str = "observed",
                   variant: str = "paper", method_params: dict | None = None, seed: int = 0,
                   progress: bool = True, hypothesis: str = "attitude") -> dict:
    """Monte Carlo of the stochastic method over sequences (the paper's experiment by default).

    start: "betelgeuse" (boresight on HIP 27989, roll 0, as the paper) or "random" (uniform on
    SO(3)); turn: "ra" (step_deg along right ascension, the paper) or "pan" (step_deg about the
    camera y axis); level: "image" (the OpenCV simulator + centroider, sensor PAPER_SENSOR) or
    "vector" (perturbed catalog directions, the paper's own simulation); position_noise_rad: 1 sigma
    per axis (default: the scenario's); sigma_mag: the magnitude noise; designation: "observed"
    (the rule f on the noisy frame) or "true" (the star the true boresight designates, as the
    paper's test software can); hypothesis: "attitude" (rows carry attitudes, the turn is given in
    the camera frame, dR_cam) or "boresight" (the paper taken literally: "the boresight is on star s",
    shifted by the inertial turn T = R_{k+1}^T R_k). Each run has its own noise (seeded from seed and
    the run index).
    """
    if n_runs < 1 or n_frames < 1:
        raise BadInput("the number of runs and of frames must be at least 1")
    for name, v, allowed in (("start", start, STARTS), ("turn", turn, TURNS), ("level", level, LEVELS),
                             ("designation", designation, DESIGNATIONS)):
        if v not in allowed:
            raise BadInput(f"unknown {name} {v!r}: choose from {', '.join(allowed)}")
    noise = scenario.noise_rad if position_noise_rad is None else float(position_noise_rad)
    if not (np.isfinite(noise) and noise >= 0) or not (np.isfinite(sigma_mag) and sigma_mag >= 0):
        raise BadInput("the position and magnitude noise must be >= 0")
    camera = scenario.camera()
    pix = camera.pixel_scale_rad * scenario.centroid_sigma_px
    sigma = float(np.hypot(noise, pix)) if level == "image" else max(noise, 1e-6)
    catalog_all = load_guide_catalog()
    params = dict(method_params or {})
    if hypothesis != "attitude":
        params["hypothesis"] = hypothesis
    sensor = PAPER_SENSOR
    params.setdefault("mag_zero_point", zero_point(sensor) if level == "image" else 0.0)
    t0 = time.perf_counter()
    solver = SequenceSolver(camera, "stochastic", mag_limit=scenario.mag_limit, sigma_rad=sigma,
                            catalog=catalog_all, method_params=params, variant=variant)
    setup_ms = (time.perf_counter() - t0) * 1e3
    cat = solver.catalog
    trn = _turn(turn, math.radians(step_deg))
    rng0 = np.random.default_rng(seed)
    R_starts = (random_attitudes(n_runs, rng0) if start == "random"
                else np.repeat(R_pointing_at(catalog_all, HIP_BETELGEUSE)[None], n_runs, axis=0))
    run_seeds = rng0.integers(0, 2**31 - 1, size=n_runs)
    runs = []
    tally: Counter = Counter()
    t_start = time.perf_counter()
    for i in range(n_runs):
        rng = np.random.default_rng(int(run_seeds[i]))
        ts = time.perf_counter()
        if level == "image":
            sim = simulate_sequence(catalog_all, camera, R_starts[i], n_frames, trn, sensor, seed=int(run_seeds[i]),
                                    mag_limit=scenario.mag_limit, position_noise_rad=noise,
                                    n_false_stars=scenario.n_false_stars,
                                    false_star_placement=scenario.false_star_placement)
            Rs = [f.R for f in sim.frames]
            turns = [sim.dR_cam(k) for k in range(n_frames - 1)]
            cents = [detect_centroids(f.image) for f in sim.frames]
            obs = [perturb_magnitudes(observation(c, camera, sigma), sigma_mag, rng) for c in cents]
            truth = [truth_rows(o.uv, f.truth, cat) for o, f in zip(obs, sim.frames)]
        else:
            Rs = [R_starts[i]]
            for _ in range(n_frames - 1):
                Rs.append(trn.apply(Rs[-1]))
            turns = [Rs[k + 1] @ Rs[k].T for k in range(n_frames - 1)]
            pairs = [vector_frame(cat, camera, R, noise if noise > 0 else 0.0, rng) for R in Rs]
            obs = [perturb_magnitudes(o, sigma_mag, rng) for o, _ in pairs]
            truth = [t for _, t in pairs]
        t_sim = time.perf_counter() - ts
        des = None
        if designation == "true":
            des = []
            for R, tr in zip(Rs, truth):
                f_b = int(cat.tree.query(R[2])[1])
                hit = np.flatnonzero(tr == f_b)
                des.append(int(hit[0]) if len(hit) else None)
        if hypothesis == "boresight":  # the inertial turn of the boresight: R_{k+1} = R_k T^T
            turns = [Rs[k + 1].T @ Rs[k] for k in range(n_frames - 1)]
        res = solver.solve_observations(obs, turns, truth=truth, designated=des, true_R=Rs)
        frames = []
        first_id = None
        wrong_any = False
        scored = res.truth_figures()  # the truth, scored here (skyview.simulate.scoring), not by the method
        for k, r in enumerate(res.identifications):
            st, tf = r.stats, scored[k]
            fb = int(cat.tree.query(Rs[k][2])[1])
            fr = {"stars": st.get("stars"), "above_prior": st.get("above_prior"),
                  "true_posterior": tf["true_posterior"],
                  "true_sequence_posterior": tf["true_sequence_posterior"],
                  "top_posterior": st.get("top_posterior"), "status": r.status,
                  "designated_is_f": (tf["true_row"] == fb) if tf["true_row"] is not None else None}
            if r.identified:
                wrong = res.wrong_matches(k)
                err = attitude_error_arcsec(r.R, Rs[k])
                fr.update(wrong_matches=len(wrong), n_matches=len(r.matches), err_total_arcsec=err["total"],
                          p_false=r.verification.get("p_false"))
                wrong_any |= bool(wrong)
                if first_id is None:
                    first_id = k
            frames.append(fr)
        last = res.identifications[-1]
        if wrong_any:
            outcome = "incorrect"
        elif last.identified:
            outcome = "correct"
        else:
            outcome = "inconclusive"
        tally[outcome] += 1
        runs.append({"run": i, "seed": int(run_seeds[i]), "outcome": outcome, "first_identified": first_id,
                     "frames": frames, "time_ms": {"simulate": t_sim * 1e3, "identify": res.time_ms["identify"]}})
        if progress and (i + 1) % max(1, n_runs // 10) == 0:
            el = time.perf_counter() - t_start
            print(f"bench-sequence {i + 1}/{n_runs} ok={tally['correct']} inconcl={tally['inconclusive']} "
                  f"WRONG={tally['incorrect']} {el / (i + 1):.2f} s/run", flush=True,
                  file=sys.stderr)
    return _summarize(runs, scenario, solver, dict(
        n_runs=n_runs, n_frames=n_frames, start=start, turn=turn, step_deg=step_deg, level=level,
        position_noise_rad=noise, position_noise_deg=math.degrees(noise), sigma_rad=sigma, sigma_mag=sigma_mag,
        designation=designation, variant=variant, seed=seed, method_params=params, hypothesis=hypothesis,
        sensor=sensor.to_dict() if level == "image" else None), setup_ms)


def _summarize(runs: list[dict], scenario: Scenario, solver: SequenceSolver, setup: dict, setup_ms: float) -> dict:
    K = setup["n_frames"]
    per_frame = []
    for k in range(K):
        p = np.array([r["frames"][k]["true_posterior"] for r in runs if r["frames"][k]["true_posterior"] is not None])
        ps = np.array([r["frames"][k]["true_sequence_posterior"] for r in runs
                       if r["frames"][k]["true_sequence_posterior"] is not None])
        a = np.array([r["frames"][k]["above_prior"] for r in runs], dtype=float)
        f_ok = [r["frames"][k]["designated_is_f"] for r in runs if r["frames"][k]["designated_is_f"] is not None]
        per_frame.append({
            "frame": k,
            "true_posterior": _describe(p), "true_sequence_posterior": _describe(ps),
            "above_prior_mean": float(a.mean()), "above_prior_median": float(np.median(a)),
            "identified": sum(r["frames"][k]["status"] == "identified" for r in runs),
            "identified_by_now": sum(r["first_identified"] is not None and r["first_identified"] <= k for r in runs),
            "designated_is_f": float(np.mean(f_ok)) if f_ok else None,
            "stars_mean": float(np.mean([r["frames"][k]["stars"] or 0 for r in runs])),
        })
    errs = [f["err_total_arcsec"] for r in runs for f in r["frames"] if "err_total_arcsec" in f]
    counts = {o: sum(r["outcome"] == o for r in runs) for o in ("correct", "inconclusive", "incorrect")}
    wrong_frames = sum(1 for r in runs for f in r["frames"] if f.get("wrong_matches"))
    id_frames = sum(1 for r in runs for f in r["frames"] if f["status"] == "identified")
    return {
        "method": "stochastic", "scenario": scenario.to_dict(), "setup": setup,
        "catalog_stars": len(solver.catalog),
        "run0": {"above_prior": [f["above_prior"] for f in runs[0]["frames"]],
                 "true_posterior": [f["true_posterior"] for f in runs[0]["frames"]]},
        "per_frame": per_frame,
        "final_true_posterior": per_frame[-1]["true_posterior"],
        "outcomes_last_frame": counts,
        "identified_frames": id_frames, "wrong_frames": wrong_frames,
        "first_identified": dict(sorted(Counter(str(r["first_identified"]) for r in runs).items())),
        "attitude_error_total_arcsec": _describe(np.array(errs)),
        "time_ms": {"simulate": _describe(np.array([r["time_ms"]["simulate"] for r in runs])),
                    "identify_sequence": _describe(np.array([r["time_ms"]["identify"] for r in runs]))},
        "setup_ms": setup_ms, "database": solver.identifier.database_info,
        "paper": {"table2": PAPER_TABLE2, "runs100": PAPER_100_RUNS},
        "runs": runs,
    }


def _describe(a: np.ndarray) -> dict:
    a = np.asarray(a, dtype=float)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "mean": float(a.mean()), "median": float(np.median(a)), "min": float(a.min()),
            "p05": float(np.percentile(a, 5)), "max": float(a.max())}


def format_sequence_markdown(s: dict) -> str:
    st = s["setup"]
    sc = s["scenario"]
    noise = st["position_noise_deg"]
    noise_txt = f"{noise:g} deg" if noise >= 0.1 else f"{noise * 3600:.1f} arcsec"
    lines = [
        f"# stochastic ({st['variant']}) on {sc['name']}: {st['n_runs']} runs of {st['n_frames']} frames",
        "",
        f"{sc['fov_deg']:g} deg FOV, {s['catalog_stars']} catalog stars (Hp <= {sc['mag_limit']:g}; the paper's "
        f"Yale subset had {PAPER_TABLE2['catalog_stars']}); start {st['start']}, {st['step_deg']:g} deg turns "
        f"({st['turn']}); level {st['level']}; position noise {noise_txt} (1 sigma per axis), magnitude noise "
        f"{st['sigma_mag']:g} mag; designated star: {st['designation']}; seed {st['seed']}.",
        "",
        "## Per frame (mean over runs; run 0 beside the paper's Table 2)",
        "",
        "| frame | stars above 1/N (mean) | run 0 | paper | P(true star) mean | median | run 0 | paper "
        "| identified by now |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for k, f in enumerate(s["per_frame"]):
        tp = f["true_posterior"]
        pa = PAPER_TABLE2["above_prior"][k] if k < 5 else ""
        pp = PAPER_TABLE2["true_posterior"][k] if k < 5 else ""
        r0a = s["run0"]["above_prior"][k]
        r0p = s["run0"]["true_posterior"][k]
        lines.append(f"| {k} | {f['above_prior_mean']:.1f} | {r0a} | {pa} | {tp.get('mean', float('nan')):.3f} | "
                     f"{tp.get('median', float('nan')):.3f} | "
                     f"{'' if r0p is None else format(r0p, '.3f')} | {pp} | {f['identified_by_now']} |")
    fp = s["final_true_posterior"]
    lines += ["", f"After {st['n_frames']} frames the posterior of the true star has mean {fp.get('mean', 0):.3f}, "
                  f"median {fp.get('median', 0):.3f}, range {fp.get('min', 0):.3f} - {fp.get('max', 0):.3f} "
                  f"(paper, 100 runs after 5 steps: mean {PAPER_100_RUNS['mean']}, range {PAPER_100_RUNS['min']} - "
                  f"{PAPER_100_RUNS['max']})."]
    o = s["outcomes_last_frame"]
    lines += ["", "## Identification (shared verification)", "",
              f"Last frame: correct {o['correct']}, inconclusive {o['inconclusive']}, incorrect {o['incorrect']}. "
              f"Frames identified: {s['identified_frames']}, with a wrong match: {s['wrong_frames']}. "
              f"First identified frame (None = never): {s['first_identified']}."]
    e = s["attitude_error_total_arcsec"]
    if e.get("n"):
        lines.append(f"Attitude error of identified frames (total rotation): median {e['median']:.1f}\", "
                     f"max {e['max']:.1f}\".")
    t = s["time_ms"]["identify_sequence"]
    lines += ["", f"Time per sequence (identify, ms, noisy shared machine): median {t['median']:.0f}, "
                  f"max {t['max']:.0f}. Designated star = f(true boresight) in "
                  + ", ".join(f"{100 * f['designated_is_f']:.0f} %" for f in s["per_frame"]
                              if f["designated_is_f"] is not None) + " of the frames."]
    return "\n".join(lines) + "\n"
