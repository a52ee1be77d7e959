"""Quick vector-level measurement of an identification method (no images): Cole & Crassidis section IV.

    skyview experiment measure --method angle --n 300 [--false-stars 1] [--json out.json]

Random attitudes uniform on SO(3); the catalog stars on the sensor, with Gaussian tangent-plane
noise; optionally one false star placed as in the paper (within half the FOV of the boresight).
Each configuration runs on the same frames. Reported per configuration:

- correct / inconclusive / failed / incorrect (identified with any wrong match), after verification;
- "paper" columns: the first pivoting chain alone, without verification (the paper's criterion:
  a unique hypothesis is an answer), as correct / incorrect / no answer;
- pivots of the final chain (mean, sd), observed stars used, median and p95 identification time.

The full bench of the project is `skyview bench`; this is the method's own quick check.
"""

from __future__ import annotations

import json
import time

import numpy as np

from skyview.core.attitude import random_attitudes
from skyview.core.camera import Camera
from skyview.core.catalog import load_guide_catalog
from skyview.core.errors import BadInput
from skyview.identify import METHODS, make_identifier
from skyview.identify.synthetic import synthetic_frame

ANGLE_CONFIGS = {
    "paper": {},
    "fewest": {"order": "fewest"},
    "backtrack": {"backtrack": True},
    "loops+backtrack": {"close_loops": True, "backtrack": True, "pivoting": "join"},  # loops act in the join
    "tetra3-statistic": {"statistic": "tetra3"},
}


def run(method: str, configs: dict, n: int, seed: int, fov_deg: float, width: int, mag: float,
        sigma: float, false_stars: int) -> dict:
    cat = load_guide_catalog().brighter_than(mag)
    cam = Camera.from_fov(fov_deg, width)
    rng = np.random.default_rng(seed)
    Rs = random_attitudes(n, rng)
    frames = [synthetic_frame(cat, cam, R, sigma, rng, false_stars=false_stars) for R in Rs]
    n_true = np.array([f.n_true for f in frames])
    out = {"setup": {"method": method, "n": n, "seed": seed, "fov_deg": fov_deg, "width": width, "mag": mag,
                     "sigma_rad": sigma, "false_stars": false_stars, "catalog_stars": len(cat),
                     "stars_median": float(np.median(n_true)),
                     "fields_with_4_or_more": float(np.mean(n_true >= 4))},
           "configs": {}}
    for name, params in configs.items():
        ident = make_identifier(method, cat, cam, sigma, **params)
        counts = {"correct": 0, "inconclusive": 0, "failed": 0, "incorrect": 0}
        paper = {"correct": 0, "incorrect": 0, "none": 0}
        pivots, used, times, pfalse = [], [], [], []
        for f in frames:
            t0 = time.perf_counter()
            r = ident.identify(f.obs)
            times.append(time.perf_counter() - t0)
            if r.identified:
                ok = f.all_right(r.matches)
                counts["correct" if ok else "incorrect"] += 1
                pfalse.append(r.verification.get("p_false", np.nan))
            else:
                counts[r.status] += 1
            fc = r.stats.get("first_chain")
            if fc and fc["outcome"] == "unique":
                ok = f.all_right(fc["matches"])
                paper["correct" if ok else "incorrect"] += 1
            else:
                paper["none"] += 1
            if len(f.obs) >= 3:
                pivots.append(r.stats.get("pivots", 0))
                used.append(r.stats.get("stars_used", 0))
        info = ident.database_info
        pf = np.array(pfalse)
        out["configs"][name] = {
            "params": params,
            "rates": {k: v / n for k, v in counts.items()},
            "counts": counts,
            "paper_no_verification": {k: v / n for k, v in paper.items()},
            "pivots_mean": float(np.mean(pivots)) if pivots else None,
            "pivots_sd": float(np.std(pivots)) if pivots else None,
            "stars_used_mean": float(np.mean(used)) if used else None,
            "time_ms_median": float(np.median(times) * 1e3),
            "time_ms_p95": float(np.percentile(times, 95) * 1e3),
            "identified_with_p_false_above_1e-4": float(np.mean(pf >= 1e-4)) if len(pf) else None,
            "p_false_max": float(np.max(pf)) if len(pf) else None,
            "database": {k: info.get(k) for k in ("key_string", "pairs", "pairs_within_fov", "nbytes",
                                                   "file_bytes", "build_s", "load_s", "source")},
        }
    return out


def database_build(method: str, fov_deg: float, width: int, mag: float, sigma: float) -> dict:
    """Build the method's database in a throw-away cache and load it again: times and sizes."""
    from skyview.experiments import throwaway_cache

    cat = load_guide_catalog().brighter_than(mag)
    cam = Camera.from_fov(fov_deg, width)
    with throwaway_cache():
        built = make_identifier(method, cat, cam, sigma).database_info
        loaded = make_identifier(method, cat, cam, sigma).database_info
    keep = ("pairs", "pairs_within_fov", "fov_deg", "max_sep_deg", "nbytes", "file_bytes", "catalog_stars")
    return {**{k: built.get(k) for k in keep}, "build_s": built["build_s"], "load_s": loaded["load_s"],
            "key_string": built["key_string"]}


def add_arguments(ap) -> None:
    ap.add_argument("--method", default="angle", choices=list(METHODS), help="the method (default angle)")
    ap.add_argument("--n", type=int, default=300, help="random attitudes (default 300)")
    ap.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    ap.add_argument("--fov-deg", type=float, default=8.0, help="full field of view, deg (default 8)")
    ap.add_argument("--width", type=int, default=1024, help="sensor width, pixels (default 1024)")
    ap.add_argument("--mag", type=float, default=6.0, help="catalog and sky limit, Hp (default 6)")
    ap.add_argument("--sigma", type=float, default=87e-6, help="per-axis noise, radians")
    ap.add_argument("--false-stars", type=int, nargs="+", default=[0, 1],
                    help="false stars per frame, one run per value (default 0 1)")
    ap.add_argument("--configs", nargs="+", default=None, choices=list(ANGLE_CONFIGS), metavar="CONFIG",
                    help=f"angle only: a subset of {', '.join(ANGLE_CONFIGS)}")
    ap.add_argument("--json", default=None, help="write the figures to this file")


def command(a) -> int:
    configs = ANGLE_CONFIGS if a.method == "angle" else {"default": {}}
    if a.configs:
        if a.method != "angle":
            raise BadInput("--configs goes with --method angle")
        configs = {k: configs[k] for k in a.configs}
    report = {"database": database_build(a.method, a.fov_deg, a.width, a.mag, a.sigma), "runs": []}
    db = report["database"]
    print(f"database {db['key_string']}: {db['pairs']} pairs ({db['pairs_within_fov']} within the "
          f"{db['fov_deg']:g} deg FOV, all up to the {db['max_sep_deg']:.2f} deg diagonal), "
          f"{db['nbytes'] / 1e6:.2f} MB in memory, {db['file_bytes'] / 1e6:.2f} MB on disk, "
          f"built in {db['build_s'] * 1e3:.0f} ms, loaded in {db['load_s'] * 1e3:.1f} ms")
    for fs in a.false_stars:
        res = run(a.method, configs, a.n, a.seed, a.fov_deg, a.width, a.mag, a.sigma, fs)
        report["runs"].append(res)
        s = res["setup"]
        print(f"\n{a.n} attitudes, {fs} false star(s); stars per field median {s['stars_median']:g}, "
              f"{100 * s['fields_with_4_or_more']:.0f}% with >= 4")
        print(f"{'config':18s} {'correct':>8s} {'inconcl':>8s} {'failed':>7s} {'wrong#':>6s} | "
              f"{'paper: ok':>9s} {'wrong':>6s} {'none':>6s} | {'pivots':>11s} {'used':>5s} | "
              f"{'t50 ms':>7s} {'t95 ms':>7s}")
        for name, c in res["configs"].items():
            r, p = c["rates"], c["paper_no_verification"]
            print(f"{name:18s} {100 * r['correct']:7.1f}% {100 * r['inconclusive']:7.1f}% {100 * r['failed']:6.1f}% "
                  f"{c['counts']['incorrect']:6d} | {100 * p['correct']:8.1f}% {100 * p['incorrect']:5.1f}% "
                  f"{100 * p['none']:5.1f}% | {c['pivots_mean']:5.2f}+-{c['pivots_sd']:4.2f} "
                  f"{c['stars_used_mean']:5.2f} | {c['time_ms_median']:7.2f} {c['time_ms_p95']:7.2f}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(report, fh, indent=1, default=float)
    return 0


if __name__ == "__main__":  # `python -m skyview.experiments.measure` is `skyview experiment measure`
    import sys

    from skyview.cli import main

    raise SystemExit(main(["experiment", "measure", *sys.argv[1:]]))
