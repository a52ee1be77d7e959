"""`skyview bench`: Monte Carlo identification statistics (one method, the blind pipeline, every method
compared, per-stage speed, centroid accuracy)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from skyview.cli.common import (
    EXIT_SOLVED,
    add_method,
    add_param,
    add_scenario,
    add_statistic,
    add_variant,
    check_out_folder,
    float_arg,
    method_params,
)
from skyview.core.errors import BadInput


def _interruptible() -> None:
    """Ctrl-C (and SIGTERM) raise KeyboardInterrupt, even in a process started from a background job,
    which inherits SIGINT ignored: a long bench must stop when asked and save what it finished."""
    import signal
    import threading

    def _raise(_signum, _frame):
        raise KeyboardInterrupt

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _raise)


def cmd_bench(a) -> int:
    from skyview.bench.runner import format_markdown, run_bench, save_results

    _interruptible()
    if a.jpeg_quality is not None and not 1 <= a.jpeg_quality <= 100:
        raise BadInput(f"--jpeg-quality {a.jpeg_quality} must be in 1..100")
    if a.scheduler is not None and (a.speed or a.blind or a.compare or a.centroids):
        raise BadInput("--scheduler runs the Monte Carlo bench of one method: leave out --speed, --blind, "
                       "--compare and --centroids")
    if a.speed:
        return _bench_speed(a)
    if a.bit_depth is not None:
        raise BadInput("--bit-depth goes with --speed (the other benches render as their scenario says)")
    if a.blind:
        return _bench_blind(a)
    if a.fov_error is not None:
        raise BadInput("--fov-error goes with --blind (the calibrated bench gives the exact FOV)")
    if a.compare:  # every method, both variants, the same images (skyview.bench.compare)
        from skyview.bench.compare import cli_compare

        if a.method or a.param or a.jobs != 1:
            raise BadInput("--compare runs every method with its own parameters: leave out --method, --param, --jobs")
        a.scenario = a.scenario or "cole8"
        out_dir = check_out_folder(a.out)
        return cli_compare(bench_scenario(a), a.n, a.seed, a.compare_slow_n, not a.no_real, out_dir, a.quiet)
    a.method = a.method or "angle"
    a.scenario = a.scenario or "cole8"
    check_out_folder(a.out)  # before the Monte Carlo, not after it
    if a.centroids:
        from skyview.bench.centroids import format_markdown as fmt_c
        from skyview.bench.centroids import measure_centroid_accuracy

        res = measure_centroid_accuracy(n_images=a.n, seed=a.seed,
                                        progress=None if a.quiet else _centroid_progress(a.n))
        print(fmt_c(res))
        j, m = save_results(res, Path(a.out), f"centroids-n{a.n}-seed{a.seed}", markdown=fmt_c(res))
        print(f"saved {j} and {m}")
        return EXIT_SOLVED
    scenario = bench_scenario(a)
    from skyview.identify import METHODS

    if a.method == "blind" and scenario.is_slew:
        a.method, a.variant = None, "improved"  # tracking with the default blind pipeline for lost-in-space
    elif a.method not in METHODS:
        raise BadInput(f"unknown method {a.method!r}: choose from {', '.join(METHODS)}"
                       + (" (or blind, with --scenario slew)" if scenario.is_slew else ""))
    mparams = method_params(a)
    out_dir = check_out_folder(a.out)
    if a.jobs < 1:
        raise BadInput("--jobs must be at least 1")
    if a.jobs > 1 and a.record_failures:
        raise BadInput("--record-failures records in one process: leave out --jobs")
    if a.record_failures and scenario.name != a.scenario:
        raise BadInput("--record-failures replays the named scenario: leave out --k1/--jpeg-quality/... with it")
    on_trial = None
    if a.record_failures:  # the recorder is imported only when asked: unrecorded benches stay as fast
        from skyview.record.cases import FailureRecorder

        on_trial = FailureRecorder(a.record_failures, method=a.method, variant=a.variant, scenario=scenario.name,
                                   seed=a.seed)
    if a.scheduler is not None and (a.jobs != 1 or a.record_failures):
        raise BadInput("--scheduler runs the trials on Dask: leave out --jobs and --record-failures")
    if a.workers < 1:
        raise BadInput("--workers must be at least 1")
    summary = run_bench(a.method, scenario, a.n, seed=a.seed, method_params=mparams or None,
                        variant=a.variant, progress=not a.quiet, on_trial=on_trial, jobs=a.jobs,
                        scheduler=a.scheduler, workers=a.workers)
    md = format_markdown(summary)
    print(md)
    tag = (f"-{a.variant}" if a.variant != "paper" else "") + (f"-{a.statistic}" if a.statistic else "")
    j, m = save_results(summary, out_dir, f"{a.method}{tag}-{file_tag(scenario.name)}-n{a.n}-seed{a.seed}")
    print(f"saved {j} and {m}")
    if on_trial is not None:
        print(f"recorded {len(on_trial.written)} failed trials into {on_trial.folder}")
    return _bench_faults(summary)


def _centroid_progress(total: int):
    """A progress line on stderr for `bench --centroids` (every image on a terminal, else every 10 %)."""
    t0 = time.perf_counter()
    tty = sys.stderr.isatty()
    last = [-1]

    def progress(done: int, n: int) -> None:
        frac = done / max(n, 1)
        rate = done / max(time.perf_counter() - t0, 1e-9)
        line = (f"centroids [{'#' * int(30 * frac):<30}] {done}/{n} images {rate:.1f}/s "
                f"eta {(n - done) / max(rate, 1e-9):.0f}s")
        if tty:
            sys.stderr.write("\r" + line + ("\n" if done == n else ""))
            sys.stderr.flush()
        elif int(frac * 10) > last[0]:
            last[0] = int(frac * 10)
            print(line, file=sys.stderr, flush=True)

    return progress


def file_tag(name: str) -> str:
    """A scenario name with its changes ('blind8[k1=0.05]') as a file-name part ('blind8-k10.05')."""
    return name.replace("[", "-").replace("]", "").replace(",", "-").replace("=", "")


def bench_scenario(a):
    """The --scenario with the effect flags (--k1, --jpeg-quality, ...) applied; one-line errors."""
    from skyview.simulate.render import check_jpeg_quality, sky_gradient_factor, vignetting_falloff
    from skyview.simulate.scenarios import get_scenario

    scenario = get_scenario(a.scenario)
    changed = scenario.with_changes(k1=a.k1, k2=a.k2, jpeg_quality=a.jpeg_quality, vignetting=a.vignetting,
                                    sky_gradient=a.sky_gradient, faint_extra_mag=a.faint_extra_mag)
    if a.faint_extra_mag is not None and a.faint_extra_mag < 0:
        raise BadInput(f"--faint-extra-mag {a.faint_extra_mag} must be >= 0")
    if changed.jpeg_quality is not None:
        check_jpeg_quality(changed.jpeg_quality)
    camera = changed.camera()
    vignetting_falloff(camera, changed.vignetting)
    sky_gradient_factor(camera, 0.0, 0.0, changed.sky_gradient)
    return changed


def _bench_speed(a) -> int:
    """`bench --speed`: per-stage times of skyview (and tetra3rs when its virtualenv exists), same images."""
    from skyview.bench.runner import save_results
    from skyview.bench.speed import DEFAULT_BIT_DEPTH, DEFAULT_METHODS, format_markdown, peers_python, run_speed_bench

    if a.blind or a.centroids or a.record_failures or a.jobs != 1 or a.fov_error is not None:
        raise BadInput("--speed times one process with the exact FOV: leave out --blind, --centroids, "
                       "--record-failures, --jobs and --fov-error")
    if a.rounds < 1:
        raise BadInput("--rounds must be at least 1")
    if a.peers_python and not a.no_peers:
        peers_python(a.peers_python)  # a path that is not there: an error before any folder or image is made
    if a.real is not None:
        return _bench_photo_speed(a)
    a.scenario = a.scenario or "cole8"
    scenario = bench_scenario(a)
    methods = ((a.method, a.variant),) if a.method and a.method != "blind" else DEFAULT_METHODS
    out_dir = check_out_folder(a.out)
    summary = run_speed_bench(scenario, a.n, seed=a.seed, methods=methods, peers=not a.no_peers,
                              python=a.peers_python, rounds=a.rounds, progress=not a.quiet,
                              bit_depth=a.bit_depth or DEFAULT_BIT_DEPTH)
    md = format_markdown(summary)
    print(md)
    j, m = save_results(summary, out_dir, f"speed-{file_tag(scenario.name)}-n{a.n}-seed{a.seed}", markdown=md)
    print(f"saved {j} and {m}")
    return EXIT_SOLVED


def _bench_photo_speed(a) -> int:
    """`bench --speed --real DIR`: skyview blind beside tetra3rs blind on real photographs, and whole processes."""
    from skyview.bench.photo_speed import format_photo_markdown, run_photo_speed
    from skyview.bench.runner import save_results

    folder = Path(a.real)
    if not folder.is_dir():
        raise BadInput(f"--real {a.real}: no such folder")
    out_dir = check_out_folder(a.out)
    summary = run_photo_speed(folder, rounds=a.rounds, peers=not a.no_peers, python=a.peers_python,
                              progress=not a.quiet)
    md = format_photo_markdown(summary)
    print(md)
    j, m = save_results(summary, out_dir, f"speed-real-{file_tag(folder.resolve().name)}", markdown=md)
    print(f"saved {j} and {m}")
    return EXIT_SOLVED


def _bench_blind(a) -> int:
    from skyview.bench.runner import format_blind_markdown, run_blind_bench, save_results

    for flag, given in (("--method", a.method), ("--centroids", a.centroids), ("--param", a.param),
                        ("--record-failures", a.record_failures), ("--statistic", a.statistic),
                        ("--variant", a.variant != "paper")):
        if given:
            raise BadInput(f"{flag} does not go with --blind (the blind bench runs the default blind pipeline)")
    a.scenario = a.scenario or "blind8"
    check_out_folder(a.out)
    scenario = bench_scenario(a)
    if a.fov_error is not None:
        from skyview.solver.pipeline import check_fov_error

        check_fov_error(a.fov_error)
    if a.jobs < 1:
        raise BadInput("--jobs must be at least 1")
    out_dir = check_out_folder(a.out)
    summary = run_blind_bench(scenario, a.n, seed=a.seed, fov_error=a.fov_error, progress=not a.quiet, jobs=a.jobs)
    md = format_blind_markdown(summary)
    print(md)
    tag = "nofov" if a.fov_error is None else f"fov{a.fov_error:g}"
    j, m = save_results(summary, out_dir, f"blind-{file_tag(scenario.name)}-{tag}-n{a.n}-seed{a.seed}", markdown=md)
    print(f"saved {j} and {m}")
    return _bench_faults(summary)


def _bench_faults(summary: dict) -> int:
    """What a bench lost to faults, in one line each; 130 after a Ctrl-C (what was finished is saved)."""
    lost = summary.get("trials_failed_to_run") or []
    if lost:
        print(f"skyview: {len(lost)} trial(s) could not run: {lost[0]['reason']} (listed in the JSON)",
              file=sys.stderr)
    if summary.get("interrupted"):
        print(f"skyview: interrupted: {summary['trials_finished']} of {summary['trials_requested']} trials "
              f"finished and saved", file=sys.stderr)
        return 130
    return EXIT_SOLVED


def add_parsers(sub) -> None:
    b = sub.add_parser("bench", help="Monte Carlo identification statistics for a method and scenario",
                       description="Random attitudes (uniform on SO(3)): simulate, centroid, solve, score against "
                                   "the truth. Results go to --out as JSON and Markdown.")
    add_method(b, None, "identification method: {methods} (default angle); blind (the default pipeline) with "
                        "--scenario slew", blind=True)
    add_variant(b)
    add_scenario(b, None, "default cole8, with --blind blind8")
    b.add_argument("--blind", action="store_true",
                   help="solve with the blind pipeline (no FOV, or one off by up to --fov-error) and score the "
                        "fitted FOV too")
    b.add_argument("--fov-error", type=float_arg, default=None,
                   help="with --blind: give the solver the true FOV x (1 + u), u uniform in +-this fraction "
                        "(default: no FOV at all)")
    b.add_argument("--jpeg-quality", type=int, default=None, help="images go through a JPEG at this quality (1-100)")
    b.add_argument("--k1", type=float_arg, default=None,
                   help="radial distortion k1 of the simulated camera (OpenCV, dimensionless)")
    b.add_argument("--k2", type=float_arg, default=None,
                   help="radial distortion k2 of the simulated camera (OpenCV, dimensionless)")
    b.add_argument("--vignetting", type=float_arg, default=None,
                   help="fraction of light lost at the image corners, 0-1 (overrides the scenario's)")
    b.add_argument("--sky-gradient", type=float_arg, default=None,
                   help="fraction by which the sky background changes across the frame, 0-1 (overrides the "
                        "scenario's)")
    b.add_argument("--faint-extra-mag", type=float_arg, default=None,
                   help="also render stars this many magnitudes below the scenario's limit (overrides it)")
    b.add_argument("-n", type=int, default=100, help="number of random attitudes (trials; default 100)")
    b.add_argument("--seed", type=int, default=0, help="random seed of the trials (default 0)")
    add_statistic(b)
    b.add_argument("--speed", action="store_true",
                   help="time each stage (decode, centroids, identification, attitude) of the improved angle "
                        "and triangle methods (or --method/--variant) and the blind pipeline, and tetra3rs on the same images "
                        "when its virtualenv exists (benchmarks/README.md); prints the ratio")
    b.add_argument("--peers-python", default=None, help="with --speed: python of the tetra3rs virtualenv "
                   "(default $SKYVIEW_PEERS_PYTHON or .venv-peers/bin/python)")
    b.add_argument("--no-peers", action="store_true", help="with --speed: skyview alone")
    b.add_argument("--rounds", type=int, default=2, help="with --speed: passes over the images, the solvers "
                   "taking turns; each image keeps its fastest (default 2)")
    b.add_argument("--real", default=None, metavar="DIR",
                   help="with --speed: the photographs in DIR (and its reference.json, as tests/data/real-images): "
                        "skyview blind beside tetra3rs blind, and `skyview solve PHOTO` as a whole process")
    b.add_argument("--bit-depth", type=int, choices=(8, 16), default=None,
                   help="with --speed: bits per pixel of the rendered images, 16 (default: the frames tetra3rs's "
                        "centroider is made for) or 8 (as `skyview simulate` writes them)")
    b.add_argument("--centroids", action="store_true",
                   help="measure centroid accuracy (pixels, by SNR) instead, over -n images")
    b.add_argument("--compare", action="store_true",
                   help="every method, both variants, on the same -n simulated images of --scenario (default cole8) "
                        "and on the real photographs (calibrated mode); tables by stars in the field (skyview.bench.compare)")
    b.add_argument("--compare-slow-n", type=int, default=30,
                   help="with --compare: images for the genetic method (the first of the -n; default 30)")
    b.add_argument("--no-real", action="store_true", help="with --compare: leave out the real photographs")
    b.add_argument("--out", default="bench-results", help="folder for the JSON and Markdown results")
    b.add_argument("--quiet", action="store_true", help="no progress bar")
    add_param(b)
    b.add_argument("--jobs", type=int, default=1,
                   help="trials run in this many worker processes (a Dask LocalCluster; same outcomes as 1; the "
                        "per-trial times then include the sharing of the cores)")
    b.add_argument("--record-failures", default=None, metavar="DIR",
                   help="save a Rerun recording of every trial that is not correct into DIR (created if missing)")
    b.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the trials on Dask (skyview.bench.dask_engine): 'local' for a LocalCluster on this machine, "
                        "or a scheduler's address (tcp://host:8786); same outcomes as the local run")
    b.add_argument("--workers", type=int, default=2, help="with --scheduler local: worker processes (default 2)")
    b.set_defaults(func=cmd_bench)
