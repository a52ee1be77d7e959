"""What a user's photograph costs: skyview blind beside tetra3rs blind on real photographs, and whole processes.

`skyview bench --speed --real DIR` (DIR holds the photographs and a reference.json of their attitudes, as
tests/data/real-images does). In this process, one photograph after the other, with the solvers taking
turns round by round (each photograph keeping its fastest round, as `bench --speed` does):

- skyview blind: `BlindSolver.solve_array` on the decoded photograph (what `skyview solve PHOTO` and
  `skyview.solve(image)` run: centroids, the pattern search over the whole blind FOV range, the camera fit,
  the verification, the attitude), no FOV given;
- tetra3rs 0.14 blind, when the peers virtualenv exists (benchmarks/README.md): in
  benchmarks/peers_worker.py, its own centroids and a database for skyview's whole blind FOV range (the
  same search space), timing itself around centroids + identification + attitude on the decoded image;
  twice: on its extractor's thread pool (every core, as its users run it) and on one thread
  (RAYON_NUM_THREADS=1, one core as skyview). Every solver's `cores`: its process's CPU time over the
  solve's wall time.

An answer is correct when its boresight is within MAX_ERROR_ARCSEC of the reference's.

Then whole processes, what a shell user waits for: `skyview solve PHOTO --json` (warm cache: the databases
built; the modules' bytecode written, as after any first run) for every photograph, `process_rounds` times
each, wall clock from start to exit; and, for
comparison, `python -c "import tetra3rs"` in the peers virtualenv (the import alone: a tetra3rs process
must also load its database, 0.4-0.6 GB for this range, before its first solve).
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from skyview.bench.speed import (
    DEFAULT_PEERS_PYTHON,
    PEER_ONE_THREAD,
    PEER_RUNS,
    cores_busy,
    peers_python,
    run_peers_worker,
)
from skyview.core.errors import BadInput

MAX_ERROR_ARCSEC = 120.0


def reference_photographs(folder: Path) -> list[dict]:
    """The photographs of `folder` with reference.json's attitude (R: v_cam = R v_icrs) and FOV."""
    ref_path = Path(folder) / "reference.json"
    if not ref_path.is_file():
        raise BadInput(f"{folder} has no reference.json (the photographs' attitudes: see tests/data/real-images)")
    try:
        ref = json.loads(ref_path.read_text())
    except (OSError, ValueError) as exc:
        raise BadInput(f"{ref_path} is not a readable JSON file: {exc}") from None
    if not isinstance(ref, dict):
        raise BadInput(f"{ref_path} must map each photograph's file name to its reference (R, fov_deg, width, "
                       f"height), as tests/data/real-images/reference.json does")
    out = []
    for name in sorted(ref):
        path = Path(folder) / name
        if not path.is_file():
            raise BadInput(f"{path} is listed in reference.json but missing")
        r = ref[name]
        try:
            R = np.asarray(r["R"], dtype=np.float64)
            item = {"name": name, "path": str(path.resolve()), "width": int(r["width"]), "height": int(r["height"]),
                    "R": R, "fov_deg": float(r["fov_deg"])}
        except (KeyError, TypeError, ValueError) as exc:
            raise BadInput(f"{ref_path}: the entry of {name} needs R (3 x 3), fov_deg, width and height "
                           f"({type(exc).__name__}: {exc})") from None
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise BadInput(f"{ref_path}: the R of {name} is not a 3 x 3 rotation matrix")
        out.append(item)
    if not out:
        raise BadInput(f"{ref_path} lists no photographs")
    return out


def boresight_error_arcsec(R_est, R_ref) -> float:
    c = float(np.clip(np.asarray(R_est, dtype=np.float64)[2] @ np.asarray(R_ref)[2], -1.0, 1.0))
    return math.degrees(math.acos(c)) * 3600.0


def _outcome(err: float | None) -> str:
    return "inconclusive" if err is None else ("correct" if err <= MAX_ERROR_ARCSEC else "incorrect")


def _time_skyview(solver, photos, decoded) -> list[dict]:
    solver.solve_array(decoded[0])  # warm-up (first-call costs), not timed or scored
    trials = []
    for im, img in zip(photos, decoded):
        c0, t0 = time.process_time(), time.perf_counter()
        res = solver.solve_array(img)
        wall, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        err = boresight_error_arcsec(res.R, im["R"]) if res.solved else None
        t = res.time_ms
        trials.append({"name": im["name"], "outcome": _outcome(err), "err_arcsec": err,
                       "centroid": t.get("centroid"), "identify": t.get("identify"), "total": t.get("total"),
                       "wall": wall, "cpu": cpu, "fov_deg": res.camera.fov_deg if res.solved else None})
    return trials


def _time_tetra3rs(photos, python: str, fov_range: tuple[float, float], cache_dir: Path,
                   threads: int | None = None) -> tuple[list[dict], dict]:
    answer = run_peers_worker(photos, python, cache_dir, ["tetra3rs-blind"], fov_deg=None,
                              blind_fov_range_deg=fov_range, threads=threads)
    by_name = {r["name"]: r for r in answer["results"].get("tetra3rs-blind", [])}
    trials = []
    for im in photos:
        r = by_name.get(im["name"], {"solved": False})
        err = boresight_error_arcsec(r["R"], im["R"]) if r.get("solved") else None
        trials.append({"name": im["name"], "outcome": _outcome(err), "err_arcsec": err, "total": r.get("time_ms"),
                       "cpu": r.get("cpu_ms"), "fov_deg": r.get("fov_deg")})
    return trials, {"setup": answer.get("setup", {}).get("tetra3rs-blind"), "versions": answer.get("versions")}


def _fastest(rounds: list[list[dict]]) -> list[dict]:
    out = []
    for ts in zip(*rounds):
        best = dict(min(ts, key=lambda t: math.inf if t.get("total") is None else t["total"]))
        best.update({k: ts[0][k] for k in ("outcome", "err_arcsec", "fov_deg")})
        out.append(best)
    return out


def _stats(values) -> dict:
    v = np.array([x for x in values if x is not None], dtype=np.float64)
    if len(v) == 0:
        return {"median": None, "p95": None, "min": None, "max": None}
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "min": float(v.min()),
            "max": float(v.max())}


def _summary(label: str, trials: list[dict]) -> dict:
    return {"label": label, "n": len(trials),
            "outcomes": {o: sum(t["outcome"] == o for t in trials) for o in ("correct", "inconclusive", "incorrect")},
            "stages_ms": {s: _stats(t.get(s) for t in trials) for s in ("centroid", "identify", "total")
                          if any(t.get(s) is not None for t in trials)},
            "cores": _stats(cores_busy(trials)), "trials": trials}


def process_times(photos, rounds: int, env: dict) -> list[float]:
    """Wall seconds of `skyview solve PHOTO --json` as a whole process, every photograph `rounds` times, after
    one untimed run (it writes the modules' bytecode, as any first run after an install does)."""
    walls = []
    for r in range(rounds + 1):
        for im in (photos[:1] if r == 0 else photos):
            t0 = time.perf_counter()
            proc = subprocess.run([sys.executable, "-m", "skyview", "solve", im["path"], "--json"],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            if r > 0:
                walls.append(time.perf_counter() - t0)
            if proc.returncode not in (0, 1):
                raise BadInput(f"skyview solve {im['name']} exited {proc.returncode}: {proc.stderr.strip()[-300:]}")
    return walls


def import_time(python: str, module: str, rounds: int) -> list[float]:
    walls = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        subprocess.run([python, "-c", f"import {module}"], check=True, env=dict(os.environ, PYTHONNOUSERSITE="1"))
        walls.append(time.perf_counter() - t0)
    return walls


def run_photo_speed(folder: Path, *, rounds: int = 2, process_rounds: int = 3, peers: bool = True,
                    python: str | None = None, progress: bool = True) -> dict:
    """The photograph speed benchmark (module docstring); a JSON-ready summary."""
    import cv2

    from skyview.core.catalog import cache_dir
    from skyview.detect.centroids import load_image
    from skyview.solver.pipeline import BlindSolver

    say = (lambda msg: print(msg, file=sys.stderr, flush=True)) if progress else (lambda msg: None)
    photos = reference_photographs(folder)
    cv2.setNumThreads(1)
    decoded = [load_image(im["path"]) for im in photos]
    solver = BlindSolver()
    py = peers_python(python) if peers else None
    note = None
    if peers and py is None:
        note = f"tetra3rs not run: no peers virtualenv at {DEFAULT_PEERS_PYTHON} (benchmarks/README.md)"
    runs: dict[str, list[list[dict]]] = {"skyview": [], "tetra3rs": [], PEER_ONE_THREAD: []}
    peer_info: dict = {}
    for r in range(max(1, int(rounds))):
        order = ["skyview", "tetra3rs"] if r % 2 == 0 else ["tetra3rs", "skyview"]
        for who in order:
            if who == "skyview":
                say(f"round {r + 1}: skyview blind on {len(photos)} photographs")
                runs["skyview"].append(_time_skyview(solver, photos, decoded))
            elif py is not None:
                for name, threads in PEER_RUNS:
                    say(f"round {r + 1}: {name} blind (database {solver.fov_range_deg[0]:.2f}-"
                        f"{solver.fov_range_deg[1]:.2f} deg) in {py}")
                    trials, peer_info = _time_tetra3rs(photos, py, tuple(solver.fov_range_deg), cache_dir() / "peers",
                                                       threads)
                    runs[name].append(trials)
    results = {"skyview": _summary("skyview blind (no FOV given): BlindSolver.solve_array, as `skyview solve PHOTO`",
                                   _fastest(runs["skyview"]))}
    if runs["tetra3rs"]:
        results["tetra3rs"] = {**_summary("tetra3rs 0.14 blind: its centroids, a database for skyview's whole blind "
                                          "FOV range, its thread pool on every core", _fastest(runs["tetra3rs"])),
                               **peer_info}
        results[PEER_ONE_THREAD] = {**_summary("tetra3rs 0.14 blind, the same, on one thread (RAYON_NUM_THREADS=1)",
                                               _fastest(runs[PEER_ONE_THREAD])), **peer_info}
    say(f"timing `skyview solve PHOTO --json` as a whole process, {process_rounds} x {len(photos)}")
    # as a user's machine runs it: Python keeps compiled bytecode (a shell with PYTHONDONTWRITEBYTECODE set
    # would compile every module on every start, ~0.1 s here)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    walls = process_times(photos, process_rounds, env)
    processes = {"skyview solve PHOTO --json (wall s)": _stats(walls)}
    if py is not None:
        processes["python -c 'import tetra3rs' in its virtualenv (wall s)"] = _stats(import_time(py, "tetra3rs",
                                                                                                  process_rounds))
    sk, t3, t3_one = (results.get(k, {}).get("stages_ms", {}).get("total", {}).get("median")
                      for k in ("skyview", "tetra3rs", PEER_ONE_THREAD))
    ratio = sk / t3 if sk and t3 else None
    ratio_one = sk / t3_one if sk and t3_one else None
    return {"kind": "photo-speed", "folder": str(folder), "n": len(photos), "rounds": int(rounds),
            "sizes": sorted({f"{im['width']}x{im['height']}" for im in photos}),
            "blind_fov_range_deg": list(solver.fov_range_deg), "results": results, "processes": processes,
            "ratio_to_tetra3rs": ratio, "ratio_to_tetra3rs_one_thread": ratio_one, "peer_note": note,
            "machine": {"python": platform.python_version(), "cpu": platform.machine(), "cores": os.cpu_count(),
                        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}}


def _f(x, fmt=".2f") -> str:
    return "—" if x is None else format(x, fmt)


def format_photo_markdown(s: dict) -> str:
    lines = [f"# Speed on real photographs: {s['folder']} ({s['n']} photographs, {', '.join(s['sizes'])})", "",
             f"No FOV given (blind over {s['blind_fov_range_deg'][0]:.2f}-{s['blind_fov_range_deg'][1]:.2f} deg). "
             f"Milliseconds per photograph (median / p95; each photograph's fastest of {s['rounds']} rounds, the "
             f"solvers taking turns), decoded image to attitude in one process. Correct: boresight within "
             f"{MAX_ERROR_ARCSEC:g}\" of the reference.", "",
             "`cores`: the process's CPU time (every thread's) over the wall time of the solve, median.", "",
             "| solver | correct | inconclusive | incorrect | centroid | identify | total | cores |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in s["results"].items():
        st, o = r["stages_ms"], r["outcomes"]
        cells = [f"{_f(st[k]['median'])} / {_f(st[k]['p95'])}" if k in st else "—"
                 for k in ("centroid", "identify", "total")]
        cores = (r.get("cores") or {}).get("median")
        lines.append(f"| {r['label']} | {o['correct']} | {o['inconclusive']} | {o['incorrect']} | " + " | ".join(cells)
                     + f" | {_f(cores, '.1f')} |")
    lines.append("")
    if s["ratio_to_tetra3rs"]:
        lines.append(f"skyview's median total over tetra3rs's: {s['ratio_to_tetra3rs']:.2f}x.")
        if s.get("ratio_to_tetra3rs_one_thread"):
            lines.append(f"Over tetra3rs's on one thread (both on one core): {s['ratio_to_tetra3rs_one_thread']:.2f}x.")
    elif s.get("peer_note"):
        lines.append(s["peer_note"] + ".")
    lines += ["", "Whole processes (seconds, wall clock from start to exit):", "",
              "| process | median | p95 | min | max |",
              "|---|---|---|---|---|"]
    for name, st in s["processes"].items():
        lines.append(f"| {name} | {_f(st['median'])} | {_f(st['p95'])} | {_f(st['min'])} | {_f(st['max'])} |")
    m = s["machine"]
    la = m.get("load_average")
    lines += ["", f"Machine: Python {m['python']}, {m['cpu']}, {m['cores']} cores"
              + (f", load average {la[0]:.2f} / {la[1]:.2f} / {la[2]:.2f} (1 / 5 / 15 min) at the end." if la else ".")]
    return "\n".join(lines) + "\n"
