"""Speed benchmark: image to attitude, per stage, skyview beside tetra3rs on the same images in one run.

`run_speed_bench` renders n images of a scenario exactly as `skyview bench` does (one rng seeded with
`seed`: random_attitudes(n, rng), then the per-trial noise seeds rng.integers(0, 2**31 - 1, n);
scenario.camera(), scenario.render_kwargs(), SensorModel(bit_depth=bit_depth)), writes each one as a
PNG (16 bit by default, the ADC spanning the full well: the frames tetra3rs's own centroider is made
for; or 8 bit, as `skyview simulate` writes frames and as issue 11 states its centroid figure: one ADU
per read-noise sigma, stars brighter than Hp ~3.7 saturate, and tetra3rs's extractor with its default
settings finds few stars: benchmarks/README.md); the simulator's own JPEG bytes when the scenario
has jpeg_quality) into a work folder, then times, one image after the other, in this process:

- decode: `skyview.detect.centroids.load_image` of the file (reported apart; the totals below exclude it,
  and "total + decode" includes it);
- for each calibrated method (default: the improved angle and triangle methods, issue 11's pair;
  `methods=` or the CLI's `--method/--variant` choose others), one `MethodSolver` for the scenario's
  camera, exact FOV, `solve_array` on the decoded
  image: centroids, identification, attitude (verification is part of identification: every method
  ends in it), total; scored against the truth sidecar as `skyview bench` scores (a wrong match is
  incorrect);
- the default pipeline given the FOV (`solve_image(image, fov_deg=F)`: what `skyview solve IMG --fov-deg F`
  runs, the improved angle method at F first, the blind search over F +- 10 % when that does not verify),
  when `default_path=True`;
- the blind pipeline (`BlindSolver.solve_array`, no FOV), scored the same way, when `blind=True`.

Each solver gets one untimed warm-up solve first. With rounds=R (default 2) every solver, tetra3rs
included, goes over all the images R times, the solvers taking turns round by round (tetra3rs last in
the odd rounds, first in the even ones), and each
image keeps its fastest round (its stage times all from that round): on a machine shared with other
work this takes out most of what the others cost, for every solver alike. Medians and p95 are over
the n images.

Peers: when the separate peers virtualenv exists (benchmarks/README.md: tetra3rs 0.14 runs with
numpy < 2, skyview needs numpy 2, so they cannot share one environment), benchmarks/peers_worker.py
runs in it on the same files, right after skyview in the same run: tetra3rs with its own centroids,
a database for the true FOV +-2 % and the true FOV as its estimate (its calibrated mode), timing
itself in-process around centroids + identification + attitude on the decoded image (its decode
outside the timer, as skyview's). Scored by the boresight: within `max_error_px` pixels of the truth
= correct (it names Gaia stars, so star matches cannot be compared). The ratio printed is skyview's
median total over tetra3rs's median total.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from skyview.core.errors import BadInput

REPO = Path(__file__).resolve().parents[2]
PEERS_WORKER = REPO / "benchmarks" / "peers_worker.py"
DEFAULT_PEERS_PYTHON = REPO / ".venv-peers" / "bin" / "python"
DEFAULT_METHODS = (("angle", "improved"), ("triangle", "improved"))
BIT_DEPTHS = (8, 16)
DEFAULT_BIT_DEPTH = 16  # the frames tetra3rs's centroider is made for (8: as `skyview simulate` writes them)
STAGES = ("decode", "centroid", "identify", "attitude", "total", "total+decode")
MAX_ERROR_PX = 5.0
PEER_ONE_THREAD = "tetra3rs, 1 thread"  # tetra3rs with RAYON_NUM_THREADS=1: on one core, as skyview solves
# tetra3rs's runs (name, RAYON_NUM_THREADS): as its users run it (its extractor's thread pool on every core),
# and on one core, as skyview solves
PEER_RUNS = (("tetra3rs", None), (PEER_ONE_THREAD, 1))
RAD_TO_ARCSEC = 180.0 / math.pi * 3600.0


def _stats(values) -> dict:
    a = np.asarray([v for v in values if v is not None], dtype=np.float64)
    if a.size == 0:
        return {"n": 0, "median": None, "p95": None}
    return {"n": int(a.size), "median": float(np.median(a)), "p95": float(np.percentile(a, 95))}


def cores_busy(trials: list[dict]) -> list[float]:
    """The cores each trial's solve kept busy: its process's CPU time (every thread's, "cpu") over the wall
    time of the same span ("wall", or "total" where the solver timed itself)."""
    out = []
    for t in trials:
        span = t.get("wall") or t.get("total")
        if t.get("cpu") is not None and span:
            out.append(t["cpu"] / span)
    return out


def boresight_error_px(R_est, R_true, pixel_scale_rad: float) -> float:
    """Angle between the two boresights (row 2; atan2, exact for tiny angles) in pixels."""
    a, b = np.asarray(R_est, dtype=np.float64)[2], np.asarray(R_true, dtype=np.float64)[2]
    return float(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)) / pixel_scale_rad)


def render_images(scenario, n: int, seed: int, work: Path, catalog, bit_depth: int = DEFAULT_BIT_DEPTH
                  ) -> list[dict]:
    """n frames of `scenario` rendered as `skyview bench` renders them (the sensor's ADC of `bit_depth`
    bits), written to `work`: [{name, path, width, height, R (true), truth}]."""
    from skyview.core.attitude import random_attitudes
    from skyview.simulate.render import SensorModel, save_frame, simulate_image

    work.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    camera = scenario.camera()
    attitudes = random_attitudes(n, rng)
    seeds = rng.integers(0, 2**31 - 1, size=n)
    images = []
    for k in range(n):
        frame = simulate_image(catalog, camera, attitudes[k], SensorModel(bit_depth=bit_depth), seed=int(seeds[k]),
                               **scenario.render_kwargs())
        path = work / f"trial{k:04d}{'.jpg' if frame.jpeg is not None else '.png'}"
        save_frame(frame, path, force=True)  # the simulator's own JPEG bytes, or a lossless PNG
        images.append({"name": path.stem, "path": str(path), "width": camera.width, "height": camera.height,
                       "R": attitudes[k], "truth": frame.truth})
    return images


def _time_solver(label: str, solve, images: list[dict], decoded: list[np.ndarray], pixel_scale_rad: float) -> dict:
    """Warm-up, then solve every decoded image; per-trial stage times and outcomes."""
    from skyview.bench.runner import score_trial

    solve(decoded[0])
    trials = []
    for im, img in zip(images, decoded):
        c0, t0 = time.process_time(), time.perf_counter()
        res = solve(img)
        wall_ms = (time.perf_counter() - t0) * 1e3
        cpu_ms = (time.process_time() - c0) * 1e3
        outcome, wrong = score_trial(res, im["truth"])
        t = res.time_ms
        trials.append({"name": im["name"], "outcome": outcome, "wrong_matches": len(wrong),
                       "centroid": t.get("centroid"), "identify": t.get("identify"), "attitude": t.get("attitude"),
                       "total": t.get("total"), "wall": wall_ms, "cpu": cpu_ms, "decode": im["decode_ms"],
                       "total+decode": (t.get("total") or 0.0) + im["decode_ms"],
                       "centroids": res.centroids.n_detected, "matches": len(res.matches),
                       "err_px": (boresight_error_px(res.R, im["R"], pixel_scale_rad) if res.solved else None)})
    return {"label": label, "trials": trials}


def peers_python(explicit: str | None = None) -> str | None:
    """The peers virtualenv's python: the given one, $SKYVIEW_PEERS_PYTHON, or REPO/.venv-peers; None
    when there is none (the bench then runs skyview alone and says so)."""
    if explicit:  # asked for by name: that one or an error, never another one in its place
        if not Path(explicit).exists():
            raise BadInput(f"--peers-python {explicit} does not exist")
        return explicit
    for cand in (os.environ.get("SKYVIEW_PEERS_PYTHON"), str(DEFAULT_PEERS_PYTHON)):
        if cand and Path(cand).exists():
            return cand
    return None


def run_tetra3rs(images: list[dict], python: str, fov_deg: float, cache_dir: Path, threads: int | None = None
                 ) -> dict:
    """tetra3rs (calibrated: database for the true FOV +-2 %, told the true FOV) on the image files,
    in benchmarks/peers_worker.py inside the peers virtualenv; its answer as JSON. threads: the size of
    its extractor's thread pool (RAYON_NUM_THREADS); None leaves it its default, every core."""
    return run_peers_worker(images, python, cache_dir, ["tetra3rs-fov"], fov_deg=float(fov_deg),
                            blind_fov_range_deg=[fov_deg, fov_deg], threads=threads)


def run_peers_worker(images: list[dict], python: str, cache_dir: Path, solvers: list[str], *,
                     fov_deg: float | None, blind_fov_range_deg, threads: int | None = None) -> dict:
    """benchmarks/peers_worker.py in the peers virtualenv on the image files (its job format there); its
    answer as JSON. threads: RAYON_NUM_THREADS for it (tetra3rs's thread pool), None: its default."""
    if not PEERS_WORKER.exists():
        raise BadInput(f"the peers worker {PEERS_WORKER} is missing (it ships with the repository, not the wheel)")
    job = {"images": [{k: im[k] for k in ("name", "path", "width", "height")} for im in images],
           "cache_dir": str(cache_dir), "fov_deg": fov_deg, "blind_fov_range_deg": list(blind_fov_range_deg),
           "solvers": list(solvers)}
    env = dict(os.environ, PYTHONNOUSERSITE="1", OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    if threads is not None:
        env["RAYON_NUM_THREADS"] = str(int(threads))
    proc = subprocess.run([python, str(PEERS_WORKER)], input=json.dumps(job), text=True, stdout=subprocess.PIPE,
                          env=env)
    if proc.returncode != 0:
        raise BadInput(f"the peers worker failed (exit {proc.returncode}); see its messages above")
    return json.loads(proc.stdout)


def _peer_trials(answer: dict, images: list[dict], pixel_scale_rad: float, max_error_px: float,
                 threads: int | None = None) -> dict:
    res = answer["results"].get("tetra3rs-fov", [])
    by_name = {r["name"]: r for r in res}
    trials = []
    for im in images:
        r = by_name.get(im["name"], {"solved": False, "time_ms": None})
        err = boresight_error_px(r["R"], im["R"], pixel_scale_rad) if r.get("solved") else None
        outcome = "inconclusive" if err is None else ("correct" if err <= max_error_px else "incorrect")
        trials.append({"name": im["name"], "outcome": outcome, "total": r.get("time_ms"), "cpu": r.get("cpu_ms"),
                       "err_px": err, "centroids": r.get("centroids"), "matches": r.get("matches")})
    pool = "its thread pool on every core" if threads is None else f"{threads} thread{'s' if threads > 1 else ''}"
    return {"label": f"tetra3rs 0.14 (calibrated: database for the true FOV +-2 %, told the true FOV; {pool})",
            "trials": trials, "setup": answer.get("setup", {}).get("tetra3rs-fov"),
            "versions": answer.get("versions")}


def _fastest(rounds: list[dict]) -> dict:
    """One entry from the same solver's rounds: each image's times from its fastest round (by total),
    its outcome from the first round (the answers do not depend on the round)."""
    out = dict(rounds[0])
    out["trials"] = []
    for ts in zip(*(r["trials"] for r in rounds)):
        best = dict(min(ts, key=lambda t: math.inf if t.get("total") is None else t["total"]))
        best.update({k: ts[0][k] for k in ("outcome", "wrong_matches", "err_px", "matches", "centroids")
                     if k in ts[0]})
        out["trials"].append(best)
    return out


def _summarize(entry: dict) -> dict:
    trials = entry["trials"]
    n = len(trials)
    out = {"label": entry["label"], "n": n,
           "outcomes": {o: sum(t["outcome"] == o for t in trials) for o in ("correct", "inconclusive", "incorrect")},
           "stages_ms": {s: _stats(t.get(s) for t in trials) for s in STAGES if any(t.get(s) is not None
                                                                                    for t in trials)}}
    if any(t.get("cpu") is not None for t in trials):
        out["cpu_ms"] = _stats(t.get("cpu") for t in trials)
        out["cores"] = _stats(cores_busy(trials))
    for k in ("setup", "versions"):
        if entry.get(k):
            out[k] = entry[k]
    return out


def run_speed_bench(scenario, n: int, *, seed: int = 0, methods=DEFAULT_METHODS, blind: bool = True,
                    default_path: bool = True,
                    peers: bool = True, python: str | None = None, work_dir: Path | None = None,
                    max_error_px: float = MAX_ERROR_PX, rounds: int = 2, progress: bool = True,
                    bit_depth: int = DEFAULT_BIT_DEPTH) -> dict:
    """The speed benchmark (module docstring); a JSON-ready summary."""
    import cv2

    from skyview.core.catalog import load_guide_catalog
    from skyview.detect.centroids import load_image
    from skyview.solver.pipeline import BlindSolver, MethodSolver, solve_image

    if n < 1:
        raise BadInput("the number of images (-n) must be at least 1")
    if bit_depth not in BIT_DEPTHS:
        raise BadInput(f"bit depth {bit_depth} is not supported: use 8 or 16")
    py = peers_python(python) if peers else None  # (an --peers-python that is not there: before any work)
    cv2.setNumThreads(1)
    say = (lambda msg: print(msg, file=sys.stderr, flush=True)) if progress else (lambda msg: None)
    catalog = load_guide_catalog()
    camera = scenario.camera()
    tmp = None
    if work_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="skyview-speed-")
        work_dir = Path(tmp.name)
    try:
        say(f"rendering {n} {bit_depth}-bit images of {scenario.name} into {work_dir}")
        images = render_images(scenario, n, seed, Path(work_dir), catalog, bit_depth)
        decoded = []
        load_image(images[0]["path"])  # warm-up
        for im in images:
            t0 = time.perf_counter()
            decoded.append(load_image(im["path"]))
            im["decode_ms"] = (time.perf_counter() - t0) * 1e3
        setup, solvers = {}, []
        for method, variant in methods:
            t0 = time.perf_counter()
            solver = MethodSolver(camera, method, mag_limit=scenario.mag_limit, sigma_rad=scenario.sigma_rad,
                                  catalog=catalog, variant=variant, max_stars=scenario.max_stars)
            name = f"{method} ({variant})"
            setup[name] = {"solver_ms": (time.perf_counter() - t0) * 1e3, **solver.setup_ms}
            solvers.append((name, f"skyview {method} ({variant}), exact FOV", solver.solve_array))
        if default_path:  # what `skyview solve IMG --fov-deg F` and `skyview.solve(img, fov_deg=F)` run
            t0 = time.perf_counter()
            solve_image(decoded[0], fov_deg=scenario.fov_deg)  # its solvers built and kept, as in a process
            setup["default, FOV given"] = {"solver_ms": (time.perf_counter() - t0) * 1e3}
            solvers.append(("default, FOV given", "skyview's default pipeline given the FOV (+-10 %)",
                            lambda img: solve_image(img, fov_deg=scenario.fov_deg)))
        if blind:
            t0 = time.perf_counter()
            bsolver = BlindSolver(catalog=catalog, max_stars=40)
            setup["blind"] = {"solver_ms": (time.perf_counter() - t0) * 1e3, **bsolver.setup_ms}
            solvers.append(("blind", "skyview blind pipeline, no FOV", bsolver.solve_array))
        peer_note = None
        if peers and py is None:
            peer_note = (f"tetra3rs not run: no peers virtualenv at {DEFAULT_PEERS_PYTHON} (benchmarks/README.md "
                         f"says how to make one; or set SKYVIEW_PEERS_PYTHON / --peers-python)")
        cache = Path(os.environ.get("SKYVIEW_CACHE") or Path.home() / ".cache" / "skyview") / "peers"
        runs: dict[str, list[dict]] = {}
        def peer_round(r):
            for name, threads in PEER_RUNS:
                say(f"round {r + 1}: timing {name} in {py}")
                answer = run_tetra3rs(images, py, scenario.fov_deg, cache, threads=threads)
                runs.setdefault(name, []).append(_peer_trials(answer, images, camera.pixel_scale_rad,
                                                              max_error_px, threads))

        for r in range(max(1, int(rounds))):
            # tetra3rs goes first in every other round, so that neither side always meets the machine
            # in the state the other left it in
            if py is not None and r % 2 == 1:
                peer_round(r)
            for name, label, solve in solvers:
                say(f"round {r + 1}: timing {name}")
                runs.setdefault(name, []).append(_time_solver(label, solve, images, decoded, camera.pixel_scale_rad))
            if py is not None and r % 2 == 0:
                peer_round(r)
        results = {name: _summarize(_fastest(rs)) for name, rs in runs.items()}
    finally:
        if tmp is not None:
            tmp.cleanup()
    ratios, ratios_one = _ratios(results, "tetra3rs"), _ratios(results, PEER_ONE_THREAD)
    return {"kind": "speed", "scenario": scenario.to_dict(), "n": n, "seed": seed, "rounds": int(rounds),
            "bit_depth": int(bit_depth),
            "results": results,
            "setup_ms": setup, "ratio_to_tetra3rs": ratios, "ratio_to_tetra3rs_one_thread": ratios_one,
            "peer_note": peer_note,
            "machine": {"python": platform.python_version(), "cpu": platform.machine(), "cores": os.cpu_count(),
                        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}}


def _ratios(results: dict, peer_name: str) -> dict:
    """Each skyview solver's median total over the peer's (none without the peer)."""
    peer = results.get(peer_name, {}).get("stages_ms", {}).get("total", {}).get("median")
    if not peer:
        return {}
    return {name: r["stages_ms"]["total"]["median"] / peer for name, r in results.items()
            if not name.startswith("tetra3rs") and r["stages_ms"].get("total", {}).get("median") is not None}


def _f(x, fmt=".2f") -> str:
    return "—" if x is None else format(x, fmt)


def format_markdown(s: dict) -> str:
    sc = s["scenario"]
    depth = s.get("bit_depth", 16)  # (summaries saved before the option were 16-bit)
    lines = [f"# Speed: {sc['name']} ({s['n']} {depth}-bit images, seed {s['seed']})", "", sc["description"], "",
             f"Milliseconds per image (median / p95 over the images, each image's fastest of {s['rounds']} "
             "rounds, the solvers taking turns), one image after the other in one process. `total` is "
             "centroids + identification (verification included) + attitude on the decoded image; `decode` is "
             "reading the file, counted only in `total+decode`. tetra3rs times itself the same way "
             "(centroids + identification + attitude, decoded image). `cores` is the process's CPU time "
             "(every thread's) over the wall time of the solve, median over the images: skyview solves on one "
             "core; tetra3rs's centroid extractor runs on a thread pool of every core unless told otherwise "
             f"(`{PEER_ONE_THREAD}`: RAYON_NUM_THREADS=1).", "",
             "| solver | correct | inconclusive | incorrect | decode | centroid | identify | attitude | total | "
             "total+decode | cores |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in s["results"].items():
        st, o = r["stages_ms"], r["outcomes"]
        cells = [f"{_f(st[k]['median'])} / {_f(st[k]['p95'])}" if k in st else "—" for k in STAGES]
        cores = r.get("cores", {}).get("median")
        lines.append(f"| {name} | {o['correct']} | {o['inconclusive']} | {o['incorrect']} | "
                     + " | ".join(cells) + f" | {_f(cores, '.1f')} |")
    lines.append("")
    if s["ratio_to_tetra3rs"]:
        lines.append("Median total over tetra3rs's median total, same images, same run: "
                     + ", ".join(f"{k} {v:.2f}x" for k, v in s["ratio_to_tetra3rs"].items()) + ".")
        if s.get("ratio_to_tetra3rs_one_thread"):
            lines.append(f"Over {PEER_ONE_THREAD}'s (both on one core): "
                         + ", ".join(f"{k} {v:.2f}x" for k, v in s["ratio_to_tetra3rs_one_thread"].items()) + ".")
    elif s.get("peer_note"):
        lines.append(s["peer_note"] + ".")
    t3 = s["results"].get("tetra3rs")
    if t3 and t3.get("versions"):
        lines.append(f"tetra3rs {t3['versions'].get('tetra3rs')} in its own virtualenv (numpy "
                     f"{t3['versions'].get('numpy')}); scored by the boresight within {MAX_ERROR_PX:g} px.")
    m = s["machine"]
    la = m.get("load_average")
    lines += ["", f"Machine: Python {m['python']}, {m['cpu']}, {m['cores']} cores"
              + (f", load average {la[0]:.2f} / {la[1]:.2f} / {la[2]:.2f} (1 / 5 / 15 min) at the end." if la else ".")]
    return "\n".join(lines) + "\n"
