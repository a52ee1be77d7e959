"""All six methods, both variants, on the same images: `skyview bench --compare`.

The table no paper has. Every method and variant solves

- the same simulated images: trial k of every method renders the same attitude with the same noise
  seed (the attitudes and seeds are drawn once for the largest trial count; a slow method runs the
  first `n_slow` of them), scored against the truth as `skyview bench` scores them (`skyview.bench.runner`):
  correct, inconclusive, incorrect (solved with any wrong match), the method's own first answer
  before verification, broken down by the catalog stars in the field, with identification time and
  attitude accuracy;
- the same real photographs (tests/data/real-images/, calibrated mode: each photograph's FOV given
  exactly, no distortion model; Juang et al.'s night-sky test): correct when the boresight is within
  0.1 deg of the reference, wrong when solved farther off.

Every method ends in the same shared verification (`skyview.identify.verify`). The report is a dict
(`run_compare`), written as JSON (format: `compare_json` below, read by the viewer's compare panel)
and Markdown (`format_markdown`).
"""

from __future__ import annotations

import json
import platform
import re
import time
from pathlib import Path

import numpy as np

from skyview.bench.runner import OUTCOMES, summarize
from skyview.bench.trials import TrialContext, run_trial
from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.catalog import load_guide_catalog
from skyview.core.errors import BadInput
from skyview.identify import METHODS, VARIANTS
from skyview.simulate.render import SensorModel
from skyview.simulate.scenarios import Scenario
from skyview.solver.pipeline import MethodSolver


def method_order() -> tuple[str, ...]:
    """Every method of the registry, in its order (`skyview.identify.METHODS`: a method registered at run
    time is compared too)."""
    return tuple(METHODS)


def slow_methods() -> tuple[str, ...]:
    """The methods whose `slow` flag says an identification takes seconds: run on the first n_slow images."""
    return tuple(m for m in METHODS if getattr(METHODS[m], "slow", False))
STAR_BINS = ((0, 3, "0-3"), (4, 4, "4"), (5, 5, "5"), (6, 6, "6"), (7, 7, "7"), (8, 10, "8-10"),
             (11, 10**6, "11+"))
REAL_IMAGES = Path(__file__).resolve().parents[2] / "tests" / "data" / "real-images"
REAL_MAX_ERROR_DEG = 0.1
FORMAT_VERSION = 1


def star_bin(n_stars: int) -> str:
    """The label of the stars-in-the-field bin of n_stars."""
    for lo, hi, label in STAR_BINS:
        if lo <= n_stars <= hi:
            return label
    raise ValueError(f"no bin for {n_stars} stars")


def _row(summary: dict) -> dict:
    """One table row from a `skyview.bench.runner.summarize` summary."""
    trials = summary["trials"]
    by_bin = {label: {"trials": 0, **{o: 0 for o in OUTCOMES}} for _, _, label in STAR_BINS}
    for t in trials:
        b = by_bin[star_bin(int(t["stars_in_fov"]))]
        b["trials"] += 1
        b[t["outcome"]] += 1
    acc = summary["attitude_accuracy"]
    ident = summary["time_ms"].get("identify", {})
    total = summary["time_ms"].get("total", {})
    unv = summary.get("unverified_counts")
    reasons: dict[str, int] = {}
    for t in trials:
        if t["outcome"] != "correct":
            key = str(t.get("cause") or _short(t.get("reason") or ""))
            reasons[key] = reasons.get(key, 0) + 1
    return {
        "method": summary["method"], "variant": summary["variant"], "n": summary["n"],
        "params": summary["method_params"],
        **{o: summary["counts"][o] for o in OUTCOMES},
        "unverified": unv,
        "by_stars": by_bin,
        "failure_reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])[:6]),
        "identify_ms": {k: ident.get(k) for k in ("median", "p95", "mean")},
        "total_ms": {k: total.get(k) for k in ("median", "p95", "mean")},
        "accuracy": ({"solved": acc["solved"], "boresight_median_arcsec": acc["boresight_error_arcsec"]["median"],
                      "cross_rms_arcsec": acc["cross_axis_rms_arcsec"], "roll_rms_arcsec": acc["roll_rms_arcsec"]}
                     if acc else None),
        "database": {k: v for k, v in summary["database"].items()
                     if isinstance(v, (int, float, str)) and k not in ("path", "key")},
    }


def _short(reason: str) -> str:
    """A failure reason with its numbers as N, to count alike reasons together ("9 pivots" and "3 pivots"
    are one reason): the first clause, at most 14 words."""
    clause = re.sub(r"[-+]?\d[\d.,]*(e[-+]?\d+)?", "N", reason.split(";")[0]).strip()
    words = clause.split()
    return (" ".join(words[:14]) + (" ..." if len(words) > 14 else "")) or "none"


def run_simulated(scenario: Scenario, n: int, seed: int, *, n_slow: int, methods=None,
                  variants=VARIANTS, progress=None, slow=None) -> dict:
    """Every method and variant (default: the registry's) on the same n simulated images of the scenario
    (the first n_slow for the slow methods)."""
    methods = method_order() if methods is None else tuple(methods)
    slow = slow_methods() if slow is None else tuple(slow)
    if n < 1 or n_slow < 1:
        raise BadInput("the number of images (-n, --compare-slow-n) must be at least 1")
    rng = np.random.default_rng(seed)
    attitudes = random_attitudes(n, rng)
    seeds = rng.integers(0, 2**31 - 1, size=n)
    catalog = load_guide_catalog()
    camera = scenario.camera()
    rows = []
    for method in methods:
        m_n = min(n, n_slow) if method in slow else n
        for variant in variants:
            t0 = time.perf_counter()
            solver = MethodSolver(camera, method, mag_limit=scenario.mag_limit, sigma_rad=scenario.sigma_rad,
                                  catalog=catalog, variant=variant, max_stars=scenario.max_stars)
            setup_ms = (time.perf_counter() - t0) * 1e3
            ctx = TrialContext(solver=solver, catalog=catalog, camera=camera, scenario=scenario,
                                sensor=SensorModel(), attitudes=attitudes[:m_n], seeds=seeds[:m_n])
            trials = []
            for k in range(m_n):
                trials.append(run_trial(ctx, k)[0])
                if progress is not None:
                    progress(f"{method} ({variant})", k + 1, m_n)
            rows.append(_row(summarize(method, scenario, seed, trials, setup_ms, solver)))
    return {"scenario": scenario.to_dict(), "n": n, "n_slow": min(n, n_slow), "slow_methods": list(slow),
            "seed": seed, "bins": [label for _, _, label in STAR_BINS], "rows": rows}


def run_real(folder: Path = REAL_IMAGES, methods=None, variants=VARIANTS, progress=None, *,
             blind: bool = True, names: list[str] | None = None) -> dict:
    """Every method and variant on the real photographs, each told its FOV exactly (calibrated mode),
    and (blind=True) the default pipeline told nothing. names: a subset of the photographs."""
    from skyview.detect.centroids import load_image
    from skyview.solver.pipeline import solve_image

    ref_path = Path(folder) / "reference.json"
    if not ref_path.is_file():
        raise BadInput(f"no real photographs at {folder} (reference.json missing)")
    ref = json.loads(ref_path.read_text())
    images = {name: load_image(Path(folder) / name) for name in sorted(ref) if names is None or name in names}
    methods = method_order() if methods is None else tuple(methods)
    jobs = [(m, v) for m in methods for v in variants] + ([(None, "improved")] if blind else [])
    rows = []
    for method, variant in jobs:
        per_image, times = {}, []
        for name, image in images.items():
            t0 = time.perf_counter()
            if method is None:  # blind: no FOV at all
                result = solve_image(image)
            else:
                result = solve_image(image, ref[name]["fov_deg"], method, fov_error=0.0, variant=variant)
            times.append((time.perf_counter() - t0) * 1e3)
            if result.solved:
                err = attitude_error_arcsec(result.R, np.array(ref[name]["R"]))["boresight"] / 3600.0
                per_image[name] = "correct" if err < REAL_MAX_ERROR_DEG else "wrong"
            else:
                per_image[name] = "inconclusive"
            if progress is not None:
                progress(f"real: {method or 'blind'} ({variant})", len(per_image), len(images))
        outcomes = list(per_image.values())
        rows.append({"method": method or "blind (default pipeline, no FOV)", "variant": variant,
                     "images": len(images), **{o: outcomes.count(o) for o in ("correct", "wrong", "inconclusive")},
                     "time_ms_median": float(np.median(times)), "per_image": per_image})
    return {"folder": str(Path(folder).name), "images": len(images), "max_error_deg": REAL_MAX_ERROR_DEG,
            "rows": rows}


def run_compare(scenario: Scenario, n: int, seed: int, *, n_slow: int = 30, real: bool = True,
                methods=None, progress=None) -> dict:
    """The whole comparison: simulated images (and the real photographs unless real=False)."""
    t0 = time.perf_counter()
    report = {"kind": "compare", "version": FORMAT_VERSION,
              "simulated": run_simulated(scenario, n, seed, n_slow=n_slow, methods=methods, progress=progress)}
    if real:
        report["real"] = run_real(methods=methods, progress=progress)
    report["machine"] = {"python": platform.python_version(), "cpu": platform.processor() or platform.machine(),
                         "cores": __import__("os").cpu_count()}
    report["wall_s"] = time.perf_counter() - t0
    return report


def _pct(k: int, n: int) -> str:
    return f"{100 * k / n:.1f} %" if n else "—"


def _ms(v) -> str:
    return "—" if v is None else (f"{v:.1f}" if v < 100 else f"{v:.0f}")


def format_markdown(report: dict) -> str:
    """The comparison as Markdown tables (what docs/benchmarks.md keeps)."""
    sim = report["simulated"]
    sc = sim["scenario"]
    slow = ", ".join(sim.get("slow_methods") or []) or "slow methods"
    lines = [f"### Simulated: `{sc['name']}`, {sim['n']} attitudes ({slow}: the first {sim['n_slow']}), seed "
             f"{sim['seed']}", "",
             f"{sc['description']}.", "",
             "| method | variant | n | correct | inconclusive | wrong | unverified: correct / wrong | identify ms "
             "median / p95 | cross-boresight RMS | roll RMS |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sim["rows"]:
        u = r["unverified"]
        unv = f"{_pct(u['correct'], r['n'])} / {_pct(u['incorrect'], r['n'])}" if u else "—"
        acc = r["accuracy"]
        lines.append(f"| {r['method']} | {r['variant']} | {r['n']} | {_pct(r['correct'], r['n'])} | "
                     f"{_pct(r['inconclusive'], r['n'])} | **{r['incorrect']}** | {unv} | "
                     f"{_ms(r['identify_ms']['median'])} / {_ms(r['identify_ms']['p95'])} | "
                     f"{acc['cross_rms_arcsec']:.1f}″ | {acc['roll_rms_arcsec']:.0f}″ |" if acc else
                     f"| {r['method']} | {r['variant']} | {r['n']} | {_pct(r['correct'], r['n'])} | "
                     f"{_pct(r['inconclusive'], r['n'])} | **{r['incorrect']}** | {unv} | "
                     f"{_ms(r['identify_ms']['median'])} / {_ms(r['identify_ms']['p95'])} | — | — |")
    bins = sim["bins"]
    first = sim["rows"][0]["by_stars"] if sim["rows"] else {}
    lines += ["", "Correct by catalog stars in the field (trials per bin in the header; genetic: its own counts):",
              "", "| method | variant | " + " | ".join(f"{b} ({first.get(b, {}).get('trials', 0)})" for b in bins) + " |",
              "|---|---|" + "---|" * len(bins)]
    for r in sim["rows"]:
        cells = []
        for b in bins:
            c = r["by_stars"][b]
            cells.append(f"{100 * c['correct'] / c['trials']:.0f} %" if c["trials"] else "—")
            if c["incorrect"]:
                cells[-1] += f" ({c['incorrect']} wrong)"
        lines.append(f"| {r['method']} | {r['variant']} | " + " | ".join(cells) + " |")
    lines += ["", "Most frequent reasons a frame was not identified:", ""]
    for r in sim["rows"]:
        if r["failure_reasons"]:
            lines.append(f"- {r['method']} ({r['variant']}): "
                         + "; ".join(f"{k} {v}" for k, v in list(r["failure_reasons"].items())[:3]))
    real = report.get("real")
    if real:
        lines += ["", f"### Real photographs: {real['images']} in `tests/data/real-images/`, calibrated mode", "",
                  f"Each method told the photograph's FOV exactly (no distortion model); correct: boresight within "
                  f"{real['max_error_deg']:g}° of the reference.", "",
                  "| method | variant | correct | wrong | inconclusive | time per image (median) |",
                  "|---|---|---|---|---|---|"]
        for r in real["rows"]:
            lines.append(f"| {r['method']} | {r['variant']} | {r['correct']} / {r['images']} | **{r['wrong']}** | "
                         f"{r['inconclusive']} | {_ms(r['time_ms_median'])} ms |")
    m = report.get("machine", {})
    lines += ["", f"Machine: Python {m.get('python')}, {m.get('cores')} cores; whole run {report.get('wall_s', 0):.0f} s."]
    return "\n".join(lines) + "\n"


def load_compare(path: str | Path) -> dict:
    """A report written by `skyview bench --compare` (its JSON), checked; BadInput with one line otherwise."""
    p = Path(path)
    try:
        report = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BadInput(f"{p} is not a comparison written by skyview bench --compare ({type(exc).__name__})") from None
    if not (isinstance(report, dict) and report.get("kind") == "compare" and report.get("version") == 1
            and isinstance(report.get("simulated"), dict) and "rows" in report["simulated"]):
        raise BadInput(f"{p} is not a comparison written by skyview bench --compare (kind 'compare', version 1)")
    return report


def compare_json(report: dict) -> str:
    """The JSON the viewer's compare panel reads: {"kind": "compare", "version": 1, "simulated": {scenario,
    n, n_slow, seed, bins, rows: [{method, variant, n, correct, inconclusive, incorrect, unverified,
    by_stars: {bin: {trials, correct, inconclusive, incorrect}}, failure_reasons, identify_ms, total_ms,
    accuracy, database, params}]}, "real": {images, max_error_deg, rows: [{method, variant, images, correct,
    wrong, inconclusive, time_ms_median, per_image}]}, machine, wall_s}."""
    return json.dumps(report, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))


def save_compare(report: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """Write STEM.json and STEM.md into out_dir (atomically, each through a temporary file)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = (out_dir / f"{stem}.json", out_dir / f"{stem}.md")
    for path, text in zip(paths, (compare_json(report), format_markdown(report))):
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(text)
        tmp.replace(path)
    return paths


def cli_compare(scenario: Scenario, n: int, seed: int, n_slow: int, real: bool, out_dir: Path, quiet: bool) -> int:
    """`skyview bench --compare`: run, print the Markdown, save JSON and Markdown; exit 0 (a wrong
    identification is reported in the tables and on stderr, as `skyview bench` does)."""
    import sys

    def progress(what: str, done: int, total: int) -> None:
        if not quiet and (done == total or sys.stderr.isatty()):
            sys.stderr.write(f"\rcompare: {what} {done}/{total}" + ("\n" if done == total else ""))
            sys.stderr.flush()

    report = run_compare(scenario, n, seed, n_slow=n_slow, real=real, progress=progress)
    print(format_markdown(report))
    j, m = save_compare(report, out_dir, f"compare-{scenario.name}-n{n}-seed{seed}")
    print(f"saved {j} and {m}")
    wrong = sum(r["incorrect"] for r in report["simulated"]["rows"])
    wrong += sum(r["wrong"] for r in report.get("real", {}).get("rows", []))
    if wrong:
        print(f"skyview: {wrong} wrong identification(s) in the comparison (see the tables)", file=sys.stderr)
    return 0
