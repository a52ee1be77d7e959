"""`skyview` command line: demo, simulate, solve, bench, record, replay, catalog.

Exit codes: 0 success (solved), 1 ran but did not solve, 2 bad input. Errors are one line on stderr;
set SKYVIEW_DEBUG=1 to see a traceback for an unexpected error.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from skyview.errors import BadInput, SkyviewError

EXIT_SOLVED, EXIT_NOT_SOLVED, EXIT_BAD_INPUT, EXIT_INTERNAL = 0, 1, 2, 3
ARCSEC = np.pi / 180 / 3600


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2 (argparse prints usage + message otherwise)
        raise BadInput(f"{message} (see '{self.prog} --help')")


def _float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not np.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return v


def _write_text_new(path: Path, text: str, force: bool) -> None:
    """Write a file atomically; refuse to overwrite unless force; one-line errors."""
    path = Path(path)
    if path.exists() and not force:
        raise BadInput(f"{path} exists; use --force to overwrite it")
    if not path.parent.is_dir():
        raise BadInput(f"folder {path.parent} does not exist")
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise BadInput(f"cannot write {path}: {exc.strerror}") from None


def _check_new_file(path: str | Path | None, force: bool, what: str = "") -> Path | None:
    """Before any work: the file may be written (its folder exists and is writable; an existing file
    only with --force). One-line BadInput otherwise."""
    if path is None:
        return None
    p = Path(path)
    if p.is_dir():
        raise BadInput(f"{what or p} is a folder, not a file: {p}")
    if p.exists() and not force:
        raise BadInput(f"{p} exists; use --force to overwrite it")
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise BadInput(f"cannot write {p}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise BadInput(f"cannot write {p}: the folder {folder} is not writable")
    return p


def _check_out_folder(path: str | Path) -> Path:
    """Before any work: the output folder exists (made now if need be) and a file can be written in it."""
    import tempfile

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise BadInput(f"{p} is not a folder")
    try:
        p.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=p):
            pass
    except OSError as exc:
        raise BadInput(f"cannot write results into {p}: {exc.strerror or exc}") from None
    return p


# ----------------------------------------------------------------------------- commands

def cmd_simulate(a) -> int:
    from skyview.attitude import R_from_radec_roll
    from skyview.camera import Camera
    from skyview.catalog import load_guide_catalog
    from skyview.centroid import max_image_pixels
    from skyview.simulate import (JPEG_DEFAULT_QUALITY, SensorModel, is_jpeg_path, save_frame, save_sequence,
                                  simulate_image, simulate_sequence)

    if not -90.0 <= a.dec <= 90.0:
        raise BadInput(f"declination {a.dec} deg is outside [-90, 90]")
    if a.seed < 0:
        raise BadInput(f"--seed {a.seed} must be a whole number >= 0")
    if a.frames < 1:
        raise BadInput(f"--frames {a.frames} must be at least 1")
    if a.width < 16 or (a.height is not None and a.height < 16):
        raise BadInput("--width and --height must be at least 16 pixels")
    if a.width * (a.height or a.width) > max_image_pixels():
        raise BadInput(f"a {a.width} x {a.height or a.width} image is more than the {max_image_pixels() / 1e6:.0f} MP "
                       f"skyview handles (SKYVIEW_MAX_PIXELS raises it)")
    if a.jpeg_quality is not None and not 1 <= a.jpeg_quality <= 100:
        raise BadInput(f"--jpeg-quality {a.jpeg_quality} must be in 1..100")
    if a.faint_extra_mag < 0:
        raise BadInput(f"--faint-extra-mag {a.faint_extra_mag} must be >= 0")
    if not 0.0 <= a.vignetting < 1.0:
        raise BadInput(f"--vignetting {a.vignetting} must be a fraction in [0, 1)")
    if not 0.0 <= a.sky_gradient <= 1.0:
        raise BadInput(f"--sky-gradient {a.sky_gradient} must be a fraction in [0, 1]")
    out = Path(a.out)
    if a.jpeg_quality is not None and out.suffix.lower() == ".png":
        out = out.with_suffix(".jpg")  # --jpeg-quality writes a JPEG
    jpeg_quality = a.jpeg_quality if a.jpeg_quality is not None else (
        JPEG_DEFAULT_QUALITY if is_jpeg_path(out) else None)
    camera = Camera.from_fov(a.fov_deg, a.width, a.height, k1=a.distortion[0], k2=a.distortion[1])
    sensor = SensorModel(bit_depth=a.bit_depth, **({"exposure_s": a.exposure_s} if a.exposure_s else {}))
    catalog = load_guide_catalog(epoch=a.epoch)
    R = R_from_radec_roll(np.radians(a.ra), np.radians(a.dec), np.radians(a.roll))
    kw = dict(seed=a.seed, mag_limit=a.mag_limit, n_false_stars=a.false_stars, n_dropped=a.dropped,
              position_noise_rad=a.noise_arcsec * ARCSEC)
    effects = dict(faint_extra_mag=a.faint_extra_mag, vignetting=a.vignetting, sky_gradient=a.sky_gradient,
                   sky_gradient_deg=a.sky_gradient_deg, jpeg_quality=jpeg_quality)
    kw.update({k: v for k, v in effects.items() if v})  # effects left off are not passed
    if a.frames > 1:
        seq = simulate_sequence(catalog, camera, R, a.frames, _turn(a), sensor, **kw)
        paths = save_sequence(seq, out, force=a.force)
        print(f"wrote {len(seq.frames)} frames and {paths[-1]}")
        return EXIT_SOLVED
    frame = simulate_image(catalog, camera, R, sensor, **kw)
    img, js = save_frame(frame, out, force=a.force)
    n_faint = sum(1 for st in frame.truth["stars"] if st.get("faint"))
    print(f"wrote {img} ({camera.width}x{camera.height}, {len(frame.truth['stars'])} stars"
          + (f" of which {n_faint} fainter than Hp {a.mag_limit:g}" if a.faint_extra_mag else "")
          + f", {len(frame.truth['false_stars'])} false"
          + (f", JPEG quality {jpeg_quality}" if jpeg_quality is not None else "") + f") and truth {js}")
    return EXIT_SOLVED


def _turn(a):
    from skyview.simulate import turn_about_camera_axis

    axis = {"x": 0, "y": 1, "z": 2}[a.turn_axis]
    return turn_about_camera_axis(axis, np.radians(a.turn_deg))


def read_truth(truth_path: Path) -> dict | None:
    """A skyview truth sidecar (as `skyview simulate` writes it), or None if the file is not one."""
    try:
        truth = json.loads(Path(truth_path).read_text())
        R = np.asarray(truth["R"], dtype=float)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) or not isinstance(truth.get("stars", []), list):
            return None
        return truth
    except (OSError, ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError):
        return None


def _result_with_truth(result, truth_path: Path | None) -> dict:
    from skyview.attitude import attitude_error_arcsec
    from skyview.truth import wrong_matches

    out = result.to_dict()
    if truth_path is None:
        return out
    truth = read_truth(truth_path)
    if truth is None:
        raise BadInput(f"{truth_path} is not a skyview truth sidecar")
    R_true = np.asarray(truth["R"], dtype=float)
    entry = {"path": str(truth_path), "ra_deg": truth.get("ra_deg"), "dec_deg": truth.get("dec_deg"),
             "roll_deg": truth.get("roll_deg")}
    if result.R is not None:
        entry["error_arcsec"] = attitude_error_arcsec(result.R, R_true)
        wrong = len(wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in result.matches], truth))
        entry["wrong_matches"] = wrong
    out["truth"] = entry
    return out


def _print_human(out: dict, file=sys.stdout) -> None:
    if out["status"] == "solved":
        s = out["sigma_arcsec"]
        print(f"solved by {out['method']}: RA {out['ra_deg']:.5f} deg  Dec {out['dec_deg']:+.5f} deg  "
              f"roll {out['roll_deg']:+.4f} deg", file=file)
        print(f"  1-sigma: boresight {s['boresight']:.2f} arcsec, roll {s['roll']:.1f} arcsec; "
              f"{out['n_matches']} of {out['n_centroids']} centroids matched; "
              f"P(false) {out['verification'].get('p_false', float('nan')):.2e}", file=file)
        q = out["quaternion"]
        print(f"  quaternion [w x y z]: {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}", file=file)
        d = out.get("distortion") or {}
        print(f"  camera{' (fitted)' if out.get('camera_fitted') else ''}: FOV {out['fov_deg']:.4f} deg, "
              f"{out['plate_scale_arcsec_per_px']:.3f} arcsec/px, k1 {d.get('k1', 0.0):+.4f}, "
              f"k2 {d.get('k2', 0.0):+.4f}; catalog to Hp {out.get('mag_limit') or 0:.2f}", file=file)
    else:
        print(f"not solved by {out['method']}: {out.get('reason', '')} ({out['n_centroids']} centroids)", file=file)
    for note in out.get("notes", []):
        print(f"  note: {note}", file=file)
    t = out["time_ms"]
    print("  time: " + ", ".join(f"{k} {v:.1f} ms" for k, v in t.items()), file=file)
    if "truth" in out and "error_arcsec" in out["truth"]:
        e, wrong = out["truth"]["error_arcsec"], out["truth"].get("wrong_matches")
        print(f"  against the {'truth' if wrong is not None else 'reference'}: boresight {e['boresight']:.2f} "
              f"arcsec, roll {e['roll']:.1f} arcsec" + (f", {wrong} wrong matches" if wrong is not None else ""),
              file=file)


def cmd_solve(a) -> int:
    from skyview.centroid import load_image
    from skyview.fits_image import row_order
    from skyview.pipeline import solve_image

    path = Path(a.image)
    image = load_image(path)
    order = row_order(path)  # a FITS file's ROWORDER ("" if it has none), None for other files
    if int(image.max()) == int(image.min()):
        raise BadInput(f"{path} is blank (every pixel is {int(image.min())}): there is no sky to solve")
    params = {}
    if a.sigma_arcsec is not None:
        if a.sigma_arcsec <= 0:
            raise BadInput("--sigma-arcsec must be positive")
        params["sigma_rad"] = a.sigma_arcsec * ARCSEC
    method_params = _method_params(a)
    output = _check_new_file(a.output, a.force)
    if a.record:  # check the recording's path before solving (the recorder is imported only when asked)
        from skyview.record_draw import check_output_path

        check_output_path(a.record, a.force)
    _check_new_file(a.wcs, a.force)
    if a.method is None and method_params:
        raise BadInput("--param and --statistic go with --method (the default pipeline has no method parameters)")
    result = solve_image(image, a.fov_deg, a.method, fov_error=a.fov_error, mag_limit=a.mag_limit, epoch=a.epoch,
                         estimator=a.estimator, max_stars=a.max_stars, k_sigma=a.k_sigma,
                         distortion=tuple(a.distortion), method_params=method_params or None,
                         variant=a.variant, memory_mb=a.memory_mb, progress=_progress_line,
                         try_flipped_rows=order == "", **params)
    truth = None
    if a.truth:
        truth = Path(a.truth)
    elif not a.no_truth and path.with_suffix(".json").exists():
        # a JSON file beside the image is used only if it is a skyview sidecar (a camera's or another
        # program's JSON is left alone)
        truth = path.with_suffix(".json") if read_truth(path.with_suffix(".json")) is not None else None
    out = _result_with_truth(result, truth)
    out["image"] = str(path)
    advice = "" if result.solved else failure_advice(a, result)
    if advice:
        out["advice"] = advice
    if a.record:
        _record_solve(a, result, image, truth, path)
    if a.wcs and result.solved:
        from skyview.wcs import write_wcs

        # for the file's own pixel grid: a FITS file read bottom row first, unless solved the other way up
        rows_reversed_on_read = order not in (None, "TOP-DOWN")
        write_wcs(a.wcs, result.R, result.camera, force=a.force,
                  rows_reversed=rows_reversed_on_read != result.rows_reversed)
        out["wcs"] = str(a.wcs)
    text = json.dumps(out, indent=1 if a.json else None, allow_nan=False)
    if output is not None:
        _write_text_new(output, text + "\n", a.force)
    if a.json:
        print(text)
    else:
        _print_human(out)
    if not result.solved:
        print(f"skyview: not solved: {result.reason}" + (f"; {advice}" if advice else ""), file=sys.stderr)
        return EXIT_NOT_SOLVED
    return EXIT_SOLVED


def failure_advice(a, result) -> str:
    """The likely cause of a failed `skyview solve` and what to try, where the pipeline's reason does not
    already say it (the blind pipeline explains its own failures: pipeline.explain_failure)."""
    n = len(result.centroids)
    fov = a.fov_deg
    exact = fov is not None and a.fov_error == 0.0
    tips: list[str] = []
    if n < 4 and "too few stars" not in result.reason:
        tips.append(f"the image shows {n} star{'s' if n != 1 else ''} (at least 4 are needed): a longer exposure "
                    f"or a lower --k-sigma (now {a.k_sigma:g}) may find more")
    if a.method is not None:
        name = f"the {a.method} method ({a.variant} variant)"
        if exact:
            tips.append(f"{name} at exactly {fov:g} deg verified no match: if the FOV is not exact, leave out "
                        f"--fov-error 0 (the blind front end then fits the camera) or --fov-deg")
        elif result.camera_fitted:
            tips.append(f"the blind front end solved this image and fitted the camera, but {name} verified no "
                        f"match on it: leave out --method for the blind solution")
        else:
            tips.append(f"{name} ran at --fov-deg {fov:g} as given (the blind front end did not solve the image, "
                        f"so no camera was fitted): check the FOV, or leave out --method")
        if a.variant == "paper":
            tips.append("--variant improved identifies more fields than the paper's parameters (docs/benchmarks.md)")
    elif exact:
        tips.append(f"the improved angle method at exactly {fov:g} deg verified no match: if the FOV is not exact, "
                    f"leave out --fov-error 0 (to search FOV +-10 %) or --fov-deg (to search blind)")
    return "; ".join(tips)


def _progress_line(line: str) -> None:
    print(f"skyview: {line.strip()}", file=sys.stderr, flush=True)


def _record_solve(a, result, image, truth_path: Path | None, image_path: Path) -> None:
    from skyview.catalog import load_guide_catalog
    from skyview.record import record_solve

    truth = read_truth(truth_path) if truth_path is not None else None
    catalog = load_guide_catalog(epoch=a.epoch)  # the rows the solver used
    if result.method != "blind":
        catalog = catalog.brighter_than(result.mag_limit if result.mag_limit is not None else 6.0)
    info = record_solve(a.record, result, image, catalog=catalog, truth=truth, force=a.force,
                        meta={"image": str(image_path), "fov_deg": a.fov_deg, "truth": str(truth_path or "-")})
    print(f"recorded {info.path} ({info.steps} steps, {info.bytes / 1e6:.2f} MB, written in {info.write_ms:.0f} ms)",
          file=sys.stderr)


def cmd_demo(a) -> int:
    from skyview.attitude import R_from_radec_roll, attitude_error_arcsec
    from skyview.camera import Camera
    from skyview.catalog import REPO_ROOT, load_guide_catalog
    from skyview.pipeline import Solver, blind_solver
    from skyview.simulate import SensorModel, simulate_image
    from skyview.truth import wrong_matches

    t0 = time.perf_counter()
    catalog = load_guide_catalog()
    camera = Camera.from_fov(a.fov_deg, 1024)
    R = R_from_radec_roll(np.radians(a.ra), np.radians(a.dec), np.radians(a.roll))
    frame = simulate_image(catalog, camera, R, SensorModel(), seed=a.seed, mag_limit=6.0)
    print(f"1. simulated a {camera.width}x{camera.height} image, FOV {a.fov_deg:g} deg, pointing RA {a.ra:g} "
          f"Dec {a.dec:+g} roll {a.roll:g} deg: {len(frame.truth['stars'])} stars of Hp <= 6.0")

    def with_truth(result, R_true, truth=None) -> dict:
        out = result.to_dict()
        if result.R is not None:
            wrong = (len(wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in result.matches], truth))
                     if truth is not None else None)
            out["truth"] = {"error_arcsec": attitude_error_arcsec(result.R, R_true), "wrong_matches": wrong}
        return out

    solver = Solver(camera, a.method, catalog=catalog, variant=a.variant)
    print(f"\n2. {a.method} ({a.variant}), told the exact FOV (database loaded in "
          f"{solver.setup_ms['database_load']:.0f} ms; a first run builds and caches it):")
    result = solver.solve_array(frame.image)
    out = with_truth(result, R, frame.truth)
    _print_human(out)
    if a.record:  # the demo's own recording: an earlier demo's is replaced
        from skyview.record import record_solve

        info = record_solve(a.record, result, frame.image, catalog=solver.catalog, truth=frame.truth, force=True,
                            meta={"command": "skyview demo", "seed": a.seed})
        print(f"  recorded every step in {info.path} ({info.bytes / 1e6:.2f} MB): skyview replay {info.path}")
    blind = blind_solver(catalog=catalog, progress=_progress_line)
    print(f"\n3. the default pipeline, blind: no FOV given (the pattern database of the whole sky loaded in "
          f"{blind.setup_ms['database_load']:.0f} ms; a first run builds it once, ~15-20 s):")
    bres = blind.solve_array(frame.image)
    _print_human(with_truth(bres, R, frame.truth))
    photos = REPO_ROOT / "tests" / "data" / "real-images"
    if (photos / "reference.json").exists():
        from skyview.centroid import load_image

        ref = json.loads((photos / "reference.json").read_text())
        name = sorted(ref)[0]
        print(f"\n4. a real photograph, blind ({name}, {photos.relative_to(REPO_ROOT)}; its reference attitude "
              f"is cedar-solve's):")
        pres = blind.solve_array(load_image(photos / name))
        _print_human(with_truth(pres, np.asarray(ref[name]["R"])))
    print(f"\ntotal {1e3 * (time.perf_counter() - t0):.0f} ms. Next: skyview solve YOUR_PHOTO.jpg, skyview view")
    if a.json:
        print(json.dumps(out))
    code = EXIT_SOLVED if result.solved and bres.solved else EXIT_NOT_SOLVED
    if a.no_view or not (sys.stdin.isatty() and sys.stdout.isatty()):
        # headless (--no-view, a script, a pipe, a test): print and exit, never block
        print("(viewer not opened: --no-view or not a terminal; 'skyview view' opens it)")
        return code
    from skyview.viewer.app import serve
    from skyview.viewer.run import SceneConfig

    print(f"\n5. the viewer on this solved scene ({a.method}, {a.variant}): step through how it was identified.")
    serve(config=SceneConfig(ra_deg=a.ra % 360.0, dec_deg=a.dec, roll_deg=a.roll, fov_deg=a.fov_deg, seed=a.seed),
          method=a.method, variant=a.variant, say=lambda line: print(line, flush=True))
    return code


def _param_value(text: str):
    """A --param value: JSON when it parses (numbers, true/false, null, lists), else the text itself."""
    try:
        return json.loads(text)
    except ValueError:
        return text


def _method_params(a) -> dict:
    """--statistic and every --param KEY=VALUE, as the identifier's keyword parameters."""
    params = {}
    if getattr(a, "statistic", None):
        params["statistic"] = a.statistic
    for item in getattr(a, "param", None) or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip().isidentifier():
            raise BadInput(f"--param {item!r} is not KEY=VALUE (e.g. --param workers=2)")
        params[key.strip()] = _param_value(value.strip())
    return params


def _interruptible() -> None:
    """Ctrl-C (and SIGTERM) raise KeyboardInterrupt, even in a process started from a background job,
    which inherits SIGINT ignored: a long bench must stop when asked and save what it finished."""
    import signal

    def _raise(_signum, _frame):
        raise KeyboardInterrupt

    if threading_main():
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _raise)


def threading_main() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def cmd_bench(a) -> int:
    from skyview.bench import format_markdown, run_bench, save_results

    _interruptible()
    if a.jpeg_quality is not None and not 1 <= a.jpeg_quality <= 100:
        raise BadInput(f"--jpeg-quality {a.jpeg_quality} must be in 1..100")
    if a.scheduler is not None and (a.speed or a.blind or a.compare or a.centroids):
        raise BadInput("--scheduler runs the Monte Carlo bench of one method: leave out --speed, --blind, "
                       "--compare and --centroids")
    if a.speed:
        return _bench_speed(a)
    if a.blind:
        return _bench_blind(a)
    if a.fov_error is not None:
        raise BadInput("--fov-error goes with --blind (the calibrated bench gives the exact FOV)")
    if a.compare:  # every method, both variants, the same images (skyview.compare)
        from skyview.compare import cli_compare

        if a.method or a.param or a.jobs != 1:
            raise BadInput("--compare runs every method with its own parameters: leave out --method, --param, --jobs")
        a.scenario = a.scenario or "cole8"
        out_dir = _check_out_folder(a.out)
        return cli_compare(_bench_scenario(a), a.n, a.seed, a.compare_slow_n, not a.no_real, out_dir, a.quiet)
    a.method = a.method or "angle"
    a.scenario = a.scenario or "cole8"
    _check_out_folder(a.out)  # before the Monte Carlo, not after it
    if a.centroids:
        from skyview.centroid_bench import format_markdown as fmt_c, measure_centroid_accuracy

        res = measure_centroid_accuracy(n_images=a.n, seed=a.seed,
                                        progress=None if a.quiet else _centroid_progress(a.n))
        print(fmt_c(res))
        j, m = save_results(res, Path(a.out), f"centroids-n{a.n}-seed{a.seed}", markdown=fmt_c(res))
        print(f"saved {j} and {m}")
        return EXIT_SOLVED
    scenario = _bench_scenario(a)
    from skyview.identify import METHODS

    if a.method == "blind" and scenario.name == "slew":
        a.method, a.variant = None, "improved"  # tracking with the default blind pipeline for lost-in-space
    elif a.method not in METHODS:
        raise BadInput(f"unknown method {a.method!r}: choose from {', '.join(METHODS)}"
                       + (" (or blind, with --scenario slew)" if scenario.name == "slew" else ""))
    method_params = _method_params(a)
    out_dir = _check_out_folder(a.out)
    if a.jobs < 1:
        raise BadInput("--jobs must be at least 1")
    if a.jobs > 1 and a.record_failures:
        raise BadInput("--record-failures records in one process: leave out --jobs")
    if a.record_failures and scenario.name != a.scenario:
        raise BadInput("--record-failures replays the named scenario: leave out --k1/--jpeg-quality/... with it")
    on_trial = None
    if a.record_failures:  # the recorder is imported only when asked: unrecorded benches stay as fast
        from skyview.record_cases import FailureRecorder

        on_trial = FailureRecorder(a.record_failures, method=a.method, variant=a.variant, scenario=scenario.name,
                                   seed=a.seed)
    if a.scheduler is not None and (a.jobs != 1 or a.record_failures):
        raise BadInput("--scheduler runs the trials on Dask: leave out --jobs and --record-failures")
    if a.workers < 1:
        raise BadInput("--workers must be at least 1")
    summary = run_bench(a.method, scenario, a.n, seed=a.seed, method_params=method_params or None,
                        variant=a.variant, progress=not a.quiet, on_trial=on_trial, jobs=a.jobs,
                        scheduler=a.scheduler, workers=a.workers)
    md = format_markdown(summary)
    print(md)
    tag = (f"-{a.variant}" if a.variant != "paper" else "") + (f"-{a.statistic}" if a.statistic else "")
    j, m = save_results(summary, out_dir, f"{a.method}{tag}-{_file_tag(scenario.name)}-n{a.n}-seed{a.seed}")
    print(f"saved {j} and {m}")
    if on_trial is not None:
        print(f"recorded {len(on_trial.written)} failed trials into {on_trial.folder}")
    return _bench_faults(summary)
    return EXIT_SOLVED


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


def _file_tag(name: str) -> str:
    """A scenario name with its changes ('blind8[k1=0.05]') as a file-name part ('blind8-k10.05')."""
    return name.replace("[", "-").replace("]", "").replace(",", "-").replace("=", "")


def _bench_scenario(a):
    """The --scenario with the effect flags (--k1, --jpeg-quality, ...) applied; one-line errors."""
    from skyview.scenarios import get_scenario
    from skyview.simulate import check_jpeg_quality, sky_gradient_factor, vignetting_falloff

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
    from skyview.bench import save_results
    from skyview.speed_bench import DEFAULT_METHODS, format_markdown, run_speed_bench

    if a.blind or a.centroids or a.record_failures or a.jobs != 1 or a.fov_error is not None:
        raise BadInput("--speed times one process with the exact FOV: leave out --blind, --centroids, "
                       "--record-failures, --jobs and --fov-error")
    a.scenario = a.scenario or "cole8"
    scenario = _bench_scenario(a)
    methods = ((a.method, a.variant),) if a.method and a.method != "blind" else DEFAULT_METHODS
    out_dir = _check_out_folder(a.out)
    if a.rounds < 1:
        raise BadInput("--rounds must be at least 1")
    summary = run_speed_bench(scenario, a.n, seed=a.seed, methods=methods, peers=not a.no_peers,
                              python=a.peers_python, rounds=a.rounds, progress=not a.quiet)
    md = format_markdown(summary)
    print(md)
    j, m = save_results(summary, out_dir, f"speed-{_file_tag(scenario.name)}-n{a.n}-seed{a.seed}", markdown=md)
    print(f"saved {j} and {m}")
    return EXIT_SOLVED


def _bench_blind(a) -> int:
    from skyview.bench import format_blind_markdown, run_blind_bench, save_results

    for flag, given in (("--method", a.method), ("--centroids", a.centroids), ("--param", a.param),
                        ("--record-failures", a.record_failures), ("--statistic", a.statistic),
                        ("--variant", a.variant != "paper")):
        if given:
            raise BadInput(f"{flag} does not go with --blind (the blind bench runs the default blind pipeline)")
    a.scenario = a.scenario or "blind8"
    _check_out_folder(a.out)
    scenario = _bench_scenario(a)
    if a.fov_error is not None:
        from skyview.pipeline import check_fov_error

        check_fov_error(a.fov_error)
    if a.jobs < 1:
        raise BadInput("--jobs must be at least 1")
    out_dir = _check_out_folder(a.out)
    summary = run_blind_bench(scenario, a.n, seed=a.seed, fov_error=a.fov_error, progress=not a.quiet, jobs=a.jobs)
    md = format_blind_markdown(summary)
    print(md)
    tag = "nofov" if a.fov_error is None else f"fov{a.fov_error:g}"
    j, m = save_results(summary, out_dir, f"blind-{_file_tag(scenario.name)}-{tag}-n{a.n}-seed{a.seed}", markdown=md)
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


def cmd_record(a) -> int:
    if a.path is not None and a.out is not None:
        raise BadInput(f"give the output once: {a.path} or --out {a.out}")
    target = a.path if a.path is not None else a.out
    if a.examples:
        from skyview.record_examples import MANIFEST, record_examples

        out = Path(target) if target else Path("recordings")
        entries = record_examples(out, force=a.force)
        print(f"wrote {len(entries)} example recordings and {out / MANIFEST}")
        return EXIT_SOLVED
    from skyview.identify import METHODS
    from skyview.identify.base import is_sequence_method

    if is_sequence_method(METHODS[a.method]):  # a sequence method: the paper's experiment, frame by frame
        return _record_stochastic(a, target)
    from skyview.record_cases import record_case

    scenario = a.scenario or "cole8"
    out = Path(target) if target else Path(f"{a.method}-{scenario}-{a.seed}.rrd")
    info, case = record_case(out, a.method, scenario, a.seed, variant=a.variant, force=a.force)
    r = case.result
    print(f"recorded {info.path}: {a.method} ({a.variant}) on {scenario}, seed {a.seed}: {r.status}"
          f"{'' if r.solved else ' (' + r.reason + ')'}, {case.outcome} against truth; {info.steps} steps, "
          f"{info.bytes / 1e6:.2f} MB written in {info.write_ms:.0f} ms (solve {r.time_ms.get('total', 0.0):.0f} ms)")
    return EXIT_SOLVED


def _record_stochastic(a, target) -> int:
    from skyview.record_sequence import PAPER_SCENARIO, record_paper_sequence

    scenario = a.scenario or PAPER_SCENARIO
    out = Path(target) if target else Path(f"stochastic-{scenario}-{a.seed}.rrd")
    info, case = record_paper_sequence(out, a.seed, scenario=scenario, variant=a.variant, force=a.force)
    r = case.result
    post = [r_.stats.get("true_posterior") for r_ in r.identifications]
    done = (f"identified at frame{'s' if len(info.identified) > 1 else ''} {', '.join(map(str, info.identified))}"
            if info.identified else f"not identified ({r.identifications[-1].reason})")
    print(f"recorded {info.path}: stochastic ({a.variant}) on {scenario}, the paper's experiment at 10 arcsec, seed "
          f"{a.seed}: {info.frames} frames, {done}, {case.outcome} against truth; P(true star) "
          + " ".join("-" if p is None else f"{p:.3f}" for p in post)
          + f"; {info.steps} steps, {info.bytes / 1e6:.2f} MB written in {info.write_ms:.0f} ms "
          f"(solve {sum(r.time_ms.values()):.0f} ms)")
    return EXIT_SOLVED


def resolve_recording(recording: str | None, example: str | None) -> Path:
    """The .rrd to replay: a path as given; a relative one that does not exist here looked up in skyview's
    own folder (where recordings/ lives); or --example NAME: recordings/NAME-*.rrd."""
    from skyview.catalog import REPO_ROOT

    if example is not None:
        if recording is not None:
            raise BadInput(f"give a recording or --example, not both ({recording}, --example {example})")
        found = _example_recordings()
        if example not in found:
            raise BadInput(f"no example recording {example!r}: choose from {', '.join(found) or 'none'} "
                           f"(in {REPO_ROOT / 'recordings'}; 'skyview record --examples --force' regenerates them)")
        return found[example]
    if recording is None:
        raise BadInput(f"give a .rrd file, or --example NAME ({', '.join(_example_recordings()) or 'none found'})")
    path = Path(recording).expanduser()
    if not path.exists() and not path.is_absolute() and (REPO_ROOT / path).exists():
        return REPO_ROOT / path
    return path


def cmd_replay(a) -> int:
    from skyview.record_replay import replay

    path = resolve_recording(a.recording, a.example)
    return replay(path, web=True if a.web else None, host=a.host, port=a.port, grpc_port=a.grpc_port)


def cmd_solve_sequence(a) -> int:
    from skyview.sequence import solve_sequence

    if a.sigma_arcsec is not None and a.sigma_arcsec <= 0:
        raise BadInput("--sigma-arcsec must be positive")
    if a.p_identify is not None and not 0 < a.p_identify <= 1:
        raise BadInput("--p-identify must be in (0, 1]")
    paths = list(a.path)
    one = len(paths) == 1 and (Path(paths[0]).is_dir() or Path(paths[0]).suffix.lower() == ".json")
    # no --method on a sequence (folder or sequence.json): the stochastic method, as always; image
    # paths, or any other method: tracking (skyview.track)
    if a.method == "stochastic" or (a.method is None and one):
        if not one:
            raise BadInput("the stochastic method reads one sequence (a folder or a sequence.json with the turns), "
                           "not image paths: give --method for tracking")
        if a.no_turns:
            raise BadInput("--no-turns goes with tracking: the stochastic method needs the turns")
        a.path = paths[0]
        return _solve_sequence_stochastic(a, solve_sequence)
    return _solve_sequence_track(a, paths, one)


def _solve_sequence_stochastic(a, solve_sequence) -> int:
    output = _check_new_file(a.output, a.force)
    if a.record:  # check the recording's path before solving (the recorder is imported only when asked)
        from skyview.record_draw import check_output_path

        check_output_path(a.record, a.force)
    method_params = {} if a.p_identify is None else {"p_identify": a.p_identify}
    res = solve_sequence(a.path, fov_deg=a.fov_deg, mag_limit=4.5 if a.mag_limit is None else a.mag_limit,
                         sigma_rad=None if a.sigma_arcsec is None else a.sigma_arcsec * ARCSEC,
                         mag_zero_point=a.mag_zero_point, mag_cut=a.mag_cut, variant=a.variant,
                         method_params=method_params, use_truth=not a.no_truth, epoch=a.epoch,
                         max_stars=a.max_stars, k_sigma=a.k_sigma)
    out = res.to_dict()
    out["sequence"] = str(a.path)
    if a.record:
        _record_sequence(a, res)
    text = json.dumps(out, indent=1 if a.json else None)
    if output is not None:
        _write_text_new(output, text + "\n", a.force)
    if a.json:
        print(text)
    else:
        for f in out["frames"]:
            line = (f"frame {f['frame']}: {f.get('n_centroids', f['stars'])} centroids, {f['above_prior']} stars above "
                    f"the prior, leading HIP {f['top_hips'][0] if f['top_hips'] else '-'} at {f['top_posterior']:.3f}")
            if f.get("true_hip") is not None:
                line += f" (true HIP {f['true_hip']}: {f['true_posterior']:.3f})"
            line += f" -> {f['status']}"
            if f["status"] == "identified":
                line += f", {f['n_matches']} matches, P(false) {f['p_false']:.1e}"
            print(line)
        if res.solved:
            print(f"solved at frame {out['frame']}: RA {out['ra_deg']:.5f} deg  Dec {out['dec_deg']:+.5f} deg  "
                  f"roll {out['roll_deg']:+.4f} deg")
    if not res.solved:
        print(f"skyview: not solved: {out.get('reason', '')}", file=sys.stderr)
        return EXIT_NOT_SOLVED
    return EXIT_SOLVED


def _solve_sequence_track(a, paths: list[str], one: bool) -> int:
    """Tracking (skyview.track): one JSON line per frame with --json, else a line per frame."""
    from skyview.attitude import attitude_error_arcsec
    from skyview.camera import Camera
    from skyview.centroid import load_image
    from skyview.sequence import load_sequence
    from skyview.track import Tracker, body_turn_rotvec
    from skyview.truth import wrong_matches

    stochastic_only = [o for o, v in (("--p-identify", a.p_identify), ("--mag-zero-point", a.mag_zero_point),
                                      ("--mag-cut", a.mag_cut)) if v is not None]
    if stochastic_only:
        raise BadInput(f"{', '.join(stochastic_only)} go{'es' if len(stochastic_only) == 1 else ''} with the "
                       f"stochastic method, not with tracking")
    output = _check_new_file(a.output, a.force)
    if a.record:  # checked before tracking (skyview.record_track writes it after)
        if not str(a.record).lower().endswith(".rrd"):
            raise BadInput(f"{a.record}: a recording's name ends in .rrd")
        _check_new_file(a.record, a.force)
    truths = None
    if one:
        seq = load_sequence(paths[0], a.fov_deg)
        images, turns, camera, names = seq.images, seq.turns, seq.camera, [str(p) for p in seq.paths]
        truths = None if a.no_truth else seq.truths
    else:
        for p in paths:
            if Path(p).is_dir() or Path(p).suffix.lower() == ".json":
                raise BadInput(f"{p}: give one sequence (a folder or sequence.json) or image paths, not both")
        images = [load_image(p) for p in paths]
        shapes = {im.shape for im in images}
        if len(shapes) != 1:
            raise BadInput(f"the images differ in size: {sorted(shapes)}")
        H, W = images[0].shape
        camera = Camera.from_fov(a.fov_deg, W, H) if a.fov_deg is not None else None
        turns, names = None, list(paths)
    if a.no_turns:
        turns = None
    method = None if a.method in (None, "blind") else a.method
    tracker = Tracker(camera, method, mag_limit=a.mag_limit, variant=a.variant, epoch=a.epoch,
                      sigma_rad=None if a.sigma_arcsec is None else a.sigma_arcsec * ARCSEC,
                      max_stars=a.max_stars, k_sigma=a.k_sigma, progress=_progress_line)
    lines, failed, tracked = [], [], []
    for k, img in enumerate(images):
        fr = tracker.process(img, None if (k == 0 or turns is None) else turns[k - 1])
        tracked.append(fr)
        d = fr.to_dict()
        d = {"frame": k, "image": names[k], **{key: v for key, v in d.items() if key not in ("frame", "R")}}
        d["method"] = a.method or "blind"
        if truths is not None and fr.solved:
            R_true = np.asarray(truths[k]["R"], dtype=np.float64)
            d["error_arcsec"] = attitude_error_arcsec(fr.R, R_true)
            d["wrong_matches"] = len(wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in fr.matches],
                                                   truths[k]))
            if fr.relative_to is not None:
                tru = body_turn_rotvec(np.asarray(truths[fr.relative_to]["R"], dtype=np.float64), R_true)
                d["relative_error_arcsec"] = float(np.degrees(np.linalg.norm(fr.relative_rotvec_rad - tru)) * 3600)
        if not fr.solved:
            failed.append(k)
        text = json.dumps(d, allow_nan=False)
        lines.append(text)
        if a.json:
            print(text, flush=True)
        else:
            t = d["time_ms"]
            if fr.solved:
                rel = (f", turned {d['relative_angle_deg']:.4f} deg since frame {d['relative_to']}"
                       if "relative_to" in d else "")
                line = (f"frame {k}: {d['mode']:<13} RA {d['ra_deg']:.5f}  Dec {d['dec_deg']:+.5f}  roll "
                        f"{d['roll_deg']:+.4f} deg{rel}, {d['n_matches']} matches, {t['total']:.1f} ms")
                if "error_arcsec" in d:
                    line += (f" (against truth: {d['error_arcsec']['total']:.1f} arcsec, {d['wrong_matches']} wrong "
                             f"matches)")
            else:
                line = f"frame {k}: not solved ({d['mode']}): {d.get('reason', '')}, {t['total']:.1f} ms"
            print(line, flush=True)
    if output is not None:
        _write_text_new(output, "\n".join(lines) + "\n", a.force)
    if a.record:
        from skyview.record_track import record_track

        info = record_track(a.record, tracked, images, tracker.camera, tracker.catalog, truths=truths,
                            method=a.method or "blind", force=a.force)
        print(f"recorded {info.frames} frames into {info.path} ({info.bytes / 1e6:.1f} MB)", file=sys.stderr)
    if failed:
        print(f"skyview: {len(failed)} of {len(images)} frames not solved: frame{'s' if len(failed) > 1 else ''} "
              f"{', '.join(map(str, failed))}", file=sys.stderr)
        return EXIT_NOT_SOLVED
    return EXIT_SOLVED


def _record_sequence(a, res) -> None:
    from skyview.record_sequence import record_sequence
    from skyview.sequence import load_sequence

    seq = load_sequence(a.path, a.fov_deg)  # the images (solve_sequence read them too) and the turns
    truths = None if a.no_truth else seq.truths
    info = record_sequence(a.record, res, seq.images, truths=truths, turns=seq.turns, force=a.force,
                           meta={"sequence": str(a.path), "frames": len(seq.images), "variant": a.variant,
                                 "truth": "the simulator's sidecars" if truths is not None else "-"})
    done = (f"identified at frame{'s' if len(info.identified) > 1 else ''} {', '.join(map(str, info.identified))}"
            if info.identified else "not identified")
    print(f"recorded {info.path} ({info.frames} frames, {done}, {info.steps} steps, {info.bytes / 1e6:.2f} MB, "
          f"written in {info.write_ms:.0f} ms)", file=sys.stderr)


def cmd_bench_sequence(a) -> int:
    from skyview.bench import save_results
    from skyview.scenarios import get_scenario
    from skyview.sequence import bench_sequence, format_sequence_markdown

    scenario = get_scenario(a.scenario)
    if a.noise_deg is not None and a.noise_arcsec is not None:
        raise BadInput("give --noise-deg or --noise-arcsec, not both")
    noise = (np.radians(a.noise_deg) if a.noise_deg is not None
             else a.noise_arcsec * ARCSEC if a.noise_arcsec is not None else None)
    out_dir = _check_out_folder(a.out)
    summary = bench_sequence(scenario, a.n, n_frames=a.frames, start=a.start, turn=a.turn, step_deg=a.step_deg,
                             level=a.level, position_noise_rad=noise, sigma_mag=a.mag_noise,
                             designation=a.designation, variant=a.variant, seed=a.seed, progress=not a.quiet,
                             hypothesis=a.hypothesis)
    md = format_sequence_markdown(summary)
    print(md)
    note = sequence_note(summary)
    if note:
        print(note)
    noise_tag = f"-noise{summary['setup']['position_noise_deg'] * 3600:.0f}as"
    stem = (f"stochastic{'-' + a.variant if a.variant != 'paper' else ''}-{scenario.name}-{a.start}-{a.turn}-{a.level}"
            f"{noise_tag}-{a.designation}{'-boresight' if a.hypothesis == 'boresight' else ''}-n{a.n}-seed{a.seed}")
    j, m = save_results(summary, out_dir, stem, markdown=md)
    print(f"saved {j} and {m}")
    return EXIT_SOLVED


def sequence_note(summary: dict) -> str:
    """What a bench-sequence result means when no sequence was identified at a noise of a degree or so
    (the paper's experiment): that is the expected result (docs/stochastic.md), not a fault."""
    from skyview.sequence import PAPER_100_RUNS

    st = summary["setup"]
    counts = summary["outcomes_last_frame"]
    if counts.get("correct", 0) or counts.get("incorrect", 0) or st["position_noise_deg"] < 0.5:
        return ""
    fp = summary["final_true_posterior"]
    mean = fp.get("mean")
    posterior = (f"The paper's own measure is the posterior of the true star: here its mean after {st['n_frames']} "
                 f"frames is {mean:.3f}, the paper's {PAPER_100_RUNS['mean']} (100 runs); the posterior converges "
                 f"more slowly here than in the paper's Table 2. " if mean is not None else "")
    return (f"note: {summary['outcomes_last_frame'].get('inconclusive', 0)} of {st['n_runs']} sequences inconclusive, "
            f"0 identified: this is the expected result at {st['position_noise_deg']:g} deg of position noise. "
            f"The match radius is then several degrees, a catalog star lies that close to almost any direction, "
            f"and no attitude can pass the verification (nothing is reported, nothing wrong). {posterior}"
            f"With --noise-arcsec 10 (the other reading of the paper's '10') the paper variant identifies 99 of "
            f"100 Betelgeuse sequences by frame 4 (docs/stochastic.md).")


def cmd_catalog(a) -> int:
    from skyview.catalog import ASSET_PATH, build_guide_catalog, load_guide_catalog, save_guide_catalog

    if a.action == "build":
        out = Path(a.out) if a.out else ASSET_PATH
        if out.suffix != ".npz":
            raise BadInput(f"{out}: the guide catalog is written as a .npz file")
        # the shipped catalog is rebuilt in place by design; another existing file only with --force
        _check_new_file(out, a.force or a.out is None)
        t0 = time.perf_counter()
        cat = build_guide_catalog(epoch=a.epoch, mag_limit=a.mag_limit)
        t1 = time.perf_counter()
        try:
            save_guide_catalog(cat, out)
        except OSError as exc:
            raise BadInput(f"cannot write {out}: {exc.strerror}") from None
        t2 = time.perf_counter()
        t3 = time.perf_counter()
        load_guide_catalog(out)
        t4 = time.perf_counter()
        print(f"wrote {out}: {len(cat)} stars (Hp <= {a.mag_limit:g}) at epoch {a.epoch:g}, "
              f"{out.stat().st_size / 1e6:.2f} MB; build {1e3 * (t1 - t0):.0f} ms, write {1e3 * (t2 - t1):.0f} ms, "
              f"load {1e3 * (t4 - t3):.1f} ms")
        return EXIT_SOLVED
    cat = load_guide_catalog(Path(a.path) if a.path else None)
    info = cat.describe()
    info["brighter_than"] = {m: int((cat.mag <= m).sum()) for m in (4.5, 6.0, 6.5, 7.3, 8.0)}
    print(json.dumps(info, indent=1))
    return EXIT_SOLVED


def cmd_cache(a) -> int:
    from skyview.catalog import cache_dir
    from skyview.identify.database import cached_databases, clear_cache

    if a.action == "clear":
        n, b = clear_cache(a.method)
        print(f"removed {n} cached database file(s), {b / 2 ** 20:.1f} MB, from {cache_dir() / 'databases'}")
        return EXIT_SOLVED
    rows = cached_databases()
    total = sum(r["bytes"] for r in rows)
    print(f"{cache_dir() / 'databases'}: {len(rows)} database(s), {total / 2 ** 20:.1f} MB "
          f"(SKYVIEW_CACHE moves it; 'skyview cache clear' empties it)")
    for r in rows:
        print(f"  {r['bytes'] / 2 ** 20:9.1f} MB  {time.strftime('%Y-%m-%d %H:%M', time.localtime(r['used']))}  "
              f"{Path(r['path']).name}")
    return EXIT_SOLVED


def cmd_view(a) -> int:
    from skyview.viewer.app import serve

    if not 0 <= a.port <= 65535:
        raise BadInput(f"--port {a.port} is not a TCP port (0-65535)")
    return serve(host=a.host, port=a.port, image=a.image, fov_deg=a.fov_deg, coverage=a.coverage,
                 compare=a.compare,
                 say=lambda line: print(line, flush=True))


# ----------------------------------------------------------------------------- parser

def _method_names() -> tuple[str, ...]:
    from skyview.identify import METHODS

    return tuple(METHODS)


def _scenario_names() -> tuple[str, ...]:
    from skyview.scenarios import SCENARIOS

    return tuple(SCENARIOS)


def _example_recordings() -> dict[str, Path]:
    """The example recordings in the repository's recordings/ by their first name part: 'angle' ->
    recordings/angle-cole8.rrd, 'failure' -> recordings/failure-angle-cole8-false.rrd."""
    from skyview.catalog import REPO_ROOT

    found: dict[str, Path] = {}
    for p in sorted((REPO_ROOT / "recordings").glob("*-*.rrd")):
        found.setdefault(p.name.split("-", 1)[0], p)
    return found


def _statistic_arg(parser, extra: str = "") -> None:
    parser.add_argument("--statistic", choices=("calibrated", "tetra3"), default=None,
                        help=f"{extra}verification statistic, calibrated (default) or tetra3")


def _variant_arg(parser, extra: str = "") -> None:
    parser.add_argument("--variant", choices=("paper", "improved"), default="paper",
                        help=f"{extra}paper (default): the paper's parameters; improved: the method's improvements "
                             f"(docs/methods.md)")


def build_parser() -> argparse.ArgumentParser:
    from skyview.catalog import DEFAULT_BUILD_MAG_LIMIT, DEFAULT_EPOCH

    methods = _method_names()
    scenarios = _scenario_names()
    method_list = ", ".join(methods)
    scenario_list = ", ".join(scenarios)
    epoch_help = f"epoch of the catalog positions (proper motion applied), Julian year (default {DEFAULT_EPOCH:g})"
    p = _Parser(prog="skyview", description="Where is the star tracker pointing? Simulate, identify, solve, compare.",
                epilog=f"'skyview COMMAND --help' shows each command's options. Methods (--method): {method_list}. "
                       f"Scenarios (--scenario): {scenario_list}. Angles are in degrees unless an option says "
                       f"otherwise; FOVs are horizontal (across the image width).")
    p.add_argument("--version", action="version", version=f"skyview {__import__('skyview').__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser, metavar="COMMAND")

    d = sub.add_parser("demo", help="simulate a default sky (Orion), solve it and open the viewer on it",
                       description="Simulate a 1024 x 1024 image (Hp <= 6), solve it with one method at the "
                                   "exact FOV (saved step by step as demo.rrd) and with the default blind pipeline "
                                   "(no FOV), and solve one of the real photographs in tests/data/ blind; each "
                                   "compared with its truth. In a terminal it then opens the viewer on the solved "
                                   "scene (prints its URL; Ctrl-C stops it).")
    d.add_argument("--ra", type=_float, default=83.8, help="boresight right ascension, deg (default 83.8)")
    d.add_argument("--dec", type=_float, default=-5.4, help="boresight declination, deg (default -5.4)")
    d.add_argument("--roll", type=_float, default=30.0,
                   help="roll: image up from north towards east, deg (default 30)")
    d.add_argument("--fov-deg", type=_float, default=8.0, help="horizontal full field of view, deg (default 8)")
    d.add_argument("--seed", type=int, default=1, help="random seed of the image noise, an integer >= 0 (default 1)")
    d.add_argument("--method", choices=methods, default="angle", metavar="METHOD",
                   help=f"identification method: {method_list} (default angle)")
    _variant_arg(d)
    d.add_argument("--json", action="store_true", help="also print the result as JSON")
    d.add_argument("--record", default="demo.rrd", metavar="PATH",
                   help="save the method's solve, step by step, as a Rerun recording (default demo.rrd in this "
                        "folder, replacing an earlier demo's; '' for none)")
    d.add_argument("--no-view", action="store_true",
                   help="do not open the viewer at the end (it opens only in a terminal: in a script or a pipe "
                        "the demo prints and exits)")
    d.set_defaults(func=cmd_demo)

    s = sub.add_parser("simulate", help="render a star-field image (PNG) and its truth sidecar (JSON)",
                       description="Render a star-field image at a given attitude (and a truth sidecar IMAGE.json); "
                                   "with --frames, a slew sequence with known turns (a folder with sequence.json).")
    s.add_argument("--ra", type=_float, required=True, help="boresight right ascension, deg")
    s.add_argument("--dec", type=_float, required=True, help="boresight declination, deg (-90 to 90)")
    s.add_argument("--roll", type=_float, default=0.0, help="image up from north towards east, deg (default 0)")
    s.add_argument("--fov-deg", type=_float, default=8.0, help="horizontal full field of view, deg (default 8)")
    s.add_argument("--width", type=int, default=1024, help="image width, pixels (default 1024)")
    s.add_argument("--height", type=int, default=None, help="image height, pixels (default: the width)")
    s.add_argument("--seed", type=int, default=0, help="random seed of the noise, an integer >= 0 (default 0)")
    s.add_argument("--mag-limit", type=_float, default=6.0,
                   help="render stars with Hp <= this, Hipparcos magnitude (default 6)")
    s.add_argument("--false-stars", type=int, default=0,
                   help="number of bright blobs that are not stars (debris) (default 0)")
    s.add_argument("--dropped", type=int, default=0, help="number of catalog stars left out of the image (default 0)")
    s.add_argument("--noise-arcsec", type=_float, default=0.0,
                   help="extra 1-sigma jitter of star directions, arcsec (default 0)")
    s.add_argument("--bit-depth", type=int, choices=(8, 16), default=8, help="bits per pixel: 8 or 16 (default 8)")
    s.add_argument("--exposure-s", type=_float, default=None, help="exposure time, seconds (default: the sensor's)")
    s.add_argument("--distortion", type=_float, nargs=2, default=(0.0, 0.0), metavar=("K1", "K2"),
                   help="OpenCV radial distortion coefficients k1 k2 (dimensionless, on normalised coordinates; "
                        "default 0 0)")
    s.add_argument("--epoch", type=_float, default=DEFAULT_EPOCH, help=epoch_help)
    s.add_argument("--frames", type=int, default=1, help="a slew sequence of this many frames (default 1)")
    s.add_argument("--turn-deg", type=_float, default=1.0, help="turn between frames, deg (with --frames; default 1)")
    s.add_argument("--turn-axis", choices=("x", "y", "z"), default="y",
                   help="camera axis of the turn: x, y or z (default y)")
    s.add_argument("--faint-extra-mag", type=_float, default=0.0,
                   help="also render field stars this many magnitudes fainter than --mag-limit (to Hp 9 at most); "
                        "truth marks them faint")
    s.add_argument("--vignetting", type=_float, default=0.0,
                   help="fraction of light lost at the image corners, 0-1 (cos^4-shaped falloff)")
    s.add_argument("--sky-gradient", type=_float, default=0.0,
                   help="fraction by which the sky background changes across the frame, 0-1")
    s.add_argument("--sky-gradient-deg", type=_float, default=0.0,
                   help="direction the sky brightens towards, deg (0 = image right, 90 = image down)")
    s.add_argument("--jpeg-quality", type=int, default=None,
                   help="write a JPEG at this quality, 1-100 (16-bit images scaled to 8 bit by the background "
                        "noise first); an --out ending in .jpg alone means quality 95")
    s.add_argument("--out", required=True,
                   help="output PNG or JPEG (.jpg) (truth next to it as .json); with --frames a folder")
    s.add_argument("--force", action="store_true", help="overwrite existing files")
    s.set_defaults(func=cmd_simulate)

    v = sub.add_parser("solve", help="image -> attitude (blind: no field of view needed)",
                       description="Solve a star-field image (PNG, TIFF, JPEG, FITS; grey or colour). With no options "
                                   "it runs the default pipeline: blind four-star patterns over a horizontal FOV "
                                   "of about 2.5-81 deg, then the camera (FOV, k1, k2) fitted to the stars and the "
                                   "shared verification. Exit code 0 solved, 1 not solved (the reason and what to "
                                   "try on stderr), 2 bad input.")
    v.add_argument("image", help="the image file (PNG, TIFF, JPEG, BMP, WebP, FITS, ...; 8/16-bit or float, grey or "
                   "colour)")
    v.add_argument("--fov-deg", type=_float, default=None,
                   help="horizontal full field of view, deg, as far as it is known (default: searched blind)")
    v.add_argument("--fov-error", type=_float, default=0.1,
                   help="how far --fov-deg may be off, as a fraction (default 0.1 = +-10 %%; 0 = exact: the "
                        "papers' calibrated mode)")
    v.add_argument("--method", choices=methods, default=None, metavar="METHOD",
                   help=f"an identification method: {method_list}; default: the default pipeline (blind, camera "
                        f"fitted)")
    _variant_arg(v, "with --method: ")
    v.add_argument("--wcs", default=None, metavar="FILE.wcs",
                   help="also write the solution as a FITS WCS header (TAN-SIP), for DS9 / astropy")
    v.add_argument("--memory-mb", type=_float, default=None,
                   help="memory budget for building the blind database, MB (default 1024)")
    v.add_argument("--json", action="store_true", help="print one JSON object")
    v.add_argument("--sigma-arcsec", type=_float, default=None,
                   help="1-sigma centroid direction error, arcsec (default: half a pixel)")
    v.add_argument("--mag-limit", type=_float, default=None,
                   help="guide catalog limit, Hipparcos magnitude Hp (default: from the image; methods other "
                        "than angle: 6)")
    v.add_argument("--epoch", type=_float, default=DEFAULT_EPOCH, help=epoch_help)
    v.add_argument("--estimator", choices=("svd", "q-method"), default="svd",
                   help="attitude estimator: svd (Markley, default) or q-method (Davenport)")
    _statistic_arg(v, "with --method: ")
    v.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="a method parameter by its name (docs/methods.md), repeatable: e.g. --param workers=2 "
                        "(genetic: both cores), --param p_identify=0.99")
    v.add_argument("--max-stars", type=int, default=40,
                   help="use at most this many brightest centroids (a count; default 40)")
    v.add_argument("--k-sigma", type=_float, default=5.0,
                   help="detection threshold, in sigmas of the measured background noise (default 5)")
    v.add_argument("--distortion", type=_float, nargs=2, default=(0.0, 0.0), metavar=("K1", "K2"),
                   help="radial distortion of a calibrated camera: OpenCV k1 k2, dimensionless (with "
                        "--fov-error 0; default 0 0)")
    v.add_argument("--truth", default=None,
                   help="truth sidecar (JSON) to compare with (default: IMAGE.json if present)")
    v.add_argument("--no-truth", action="store_true", help="do not look for a truth sidecar")
    v.add_argument("--output", default=None, help="also write the JSON result to this file")
    v.add_argument("--force", action="store_true", help="overwrite existing --output, --wcs, --record files")
    v.add_argument("--record", default=None, metavar="PATH.rrd",
                   help="also save the solve as a Rerun recording (open it with 'skyview replay')")
    v.set_defaults(func=cmd_solve)

    b = sub.add_parser("bench", help="Monte Carlo identification statistics for a method and scenario",
                       description="Random attitudes (uniform on SO(3)): simulate, centroid, solve, score against "
                                   "the truth. Results go to --out as JSON and Markdown.")
    b.add_argument("--method", choices=(*methods, "blind"), default=None, metavar="METHOD",
                   help=f"identification method: {method_list} (default angle); blind (the default pipeline) "
                        f"with --scenario slew")
    _variant_arg(b)
    b.add_argument("--scenario", choices=scenarios, default=None, metavar="SCENARIO",
                   help=f"scenario (skyview.scenarios): {scenario_list} (default cole8, with --blind blind8)")
    b.add_argument("--blind", action="store_true",
                   help="solve with the blind pipeline (no FOV, or one off by up to --fov-error) and score the "
                        "fitted FOV too")
    b.add_argument("--fov-error", type=_float, default=None,
                   help="with --blind: give the solver the true FOV x (1 + u), u uniform in +-this fraction "
                        "(default: no FOV at all)")
    b.add_argument("--jpeg-quality", type=int, default=None, help="images go through a JPEG at this quality (1-100)")
    b.add_argument("--k1", type=_float, default=None,
                   help="radial distortion k1 of the simulated camera (OpenCV, dimensionless)")
    b.add_argument("--k2", type=_float, default=None,
                   help="radial distortion k2 of the simulated camera (OpenCV, dimensionless)")
    b.add_argument("--vignetting", type=_float, default=None,
                   help="fraction of light lost at the image corners, 0-1 (overrides the scenario's)")
    b.add_argument("--sky-gradient", type=_float, default=None,
                   help="fraction by which the sky background changes across the frame, 0-1 (overrides the "
                        "scenario's)")
    b.add_argument("--faint-extra-mag", type=_float, default=None,
                   help="also render stars this many magnitudes below the scenario's limit (overrides it)")
    b.add_argument("-n", type=int, default=100, help="number of random attitudes (trials; default 100)")
    b.add_argument("--seed", type=int, default=0, help="random seed of the trials (default 0)")
    _statistic_arg(b)
    b.add_argument("--speed", action="store_true",
                   help="time each stage (decode, centroids, identification, attitude) of the improved angle "
                        "method (or --method/--variant) and the blind pipeline, and tetra3rs on the same images "
                        "when its virtualenv exists (benchmarks/README.md); prints the ratio")
    b.add_argument("--peers-python", default=None, help="with --speed: python of the tetra3rs virtualenv "
                   "(default $SKYVIEW_PEERS_PYTHON or .venv-peers/bin/python)")
    b.add_argument("--no-peers", action="store_true", help="with --speed: skyview alone")
    b.add_argument("--rounds", type=int, default=2, help="with --speed: passes over the images, the solvers "
                   "taking turns; each image keeps its fastest (default 2)")
    b.add_argument("--centroids", action="store_true",
                   help="measure centroid accuracy (pixels, by SNR) instead, over -n images")
    b.add_argument("--compare", action="store_true",
                   help="every method, both variants, on the same -n simulated images of --scenario (default cole8) "
                        "and on the real photographs (calibrated mode); tables by stars in the field (skyview.compare)")
    b.add_argument("--compare-slow-n", type=int, default=30,
                   help="with --compare: images for the genetic method (the first of the -n; default 30)")
    b.add_argument("--no-real", action="store_true", help="with --compare: leave out the real photographs")
    b.add_argument("--out", default="bench-results", help="folder for the JSON and Markdown results")
    b.add_argument("--quiet", action="store_true", help="no progress bar")
    b.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="a method parameter by its name (docs/methods.md), repeatable: e.g. --param workers=2 "
                        "(genetic: both cores), --param p_identify=0.99")
    b.add_argument("--jobs", type=int, default=1,
                   help="trials run in this many processes (same outcomes as 1; the per-trial times then "
                        "include the sharing of the cores)")
    b.add_argument("--record-failures", default=None, metavar="DIR",
                   help="save a Rerun recording of every trial that is not correct into DIR (created if missing)")
    b.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the trials on Dask (skyview.bench_dask): 'local' for a LocalCluster on this machine, "
                        "or a scheduler's address (tcp://host:8786); same outcomes as the local run")
    b.add_argument("--workers", type=int, default=2, help="with --scheduler local: worker processes (default 2)")
    b.set_defaults(func=cmd_bench)

    from skyview.coverage import add_coverage_parser  # skyview coverage (docs/coverage.md)

    add_coverage_parser(sub, _float)

    q = sub.add_parser("solve-sequence", help="a sequence of frames -> attitude per frame (tracking; stochastic "
                                              "on a sequence without --method)",
                       description="Solve frames in time order. --method stochastic (the default for a folder or "
                                   "sequence.json, as `skyview simulate --frames` writes it) identifies over the "
                                   "whole sequence (Udomkesmalee et al.). Any other method, or image paths, tracks "
                                   "(docs/tracking.md): the first frame lost-in-space, then each frame from the "
                                   "prediction of the last, lost-in-space again when lock is lost. Exit code 0 every "
                                   "frame solved, 1 some not, 2 bad input.")
    q.add_argument("path", nargs="+", metavar="FRAMES",
                   help="sequence.json or its folder (with the turns between frames), or image paths in time order")
    q.add_argument("--method", choices=(*methods, "blind"), default=None, metavar="METHOD",
                   help=f"lost-in-space method for tracking: {method_list}, or blind (the default pipeline; the "
                        f"default for image paths); stochastic: the multi-frame method (the default for a sequence)")
    q.add_argument("--no-turns", action="store_true",
                   help="tracking: ignore the sequence's turns and predict from the rate of the last two attitudes")
    q.add_argument("--fov-deg", type=_float, default=None, help="horizontal full FOV, deg (default: the sidecar's camera)")
    _variant_arg(q)
    q.add_argument("--mag-limit", type=_float, default=None,
                   help="guide catalog limit, Hp (default: stochastic 4.5, the paper's; tracking 6)")
    q.add_argument("--sigma-arcsec", type=_float, default=None,
                   help="1-sigma direction error of a star, arcsec (default: half a pixel)")
    q.add_argument("--mag-zero-point", type=_float, default=None,
                   help="magnitude of a star giving 1 unit of brightness (default: from the sidecar's sensor)")
    q.add_argument("--mag-cut", type=_float, default=None,
                   help="leave fainter stars out of the statistics, Hp (default: mag-limit + 0.25 with a zero point)")
    q.add_argument("--p-identify", type=_float, default=None,
                   help="posterior probability at which a star dominates, 0-1 (default 0.95)")
    q.add_argument("--epoch", type=_float, default=DEFAULT_EPOCH, help=epoch_help)
    q.add_argument("--max-stars", type=int, default=40,
                   help="use at most this many brightest centroids per frame (a count; default 40)")
    q.add_argument("--k-sigma", type=_float, default=5.0,
                   help="detection threshold, in sigmas of the measured background noise (default 5)")
    q.add_argument("--no-truth", action="store_true", help="ignore the simulator's truth in the sidecar")
    q.add_argument("--json", action="store_true",
                   help="print JSON: one object (stochastic), one line per frame (tracking)")
    q.add_argument("--output", default=None, help="also write the JSON result (tracking: the JSON lines) to this file")
    q.add_argument("--force", action="store_true", help="overwrite existing --output and --record files")
    q.add_argument("--record", default=None, metavar="PATH.rrd",
                   help="also save the sequence as a Rerun recording, frame by frame (open it with 'skyview replay')")
    q.set_defaults(func=cmd_solve_sequence)

    bs = sub.add_parser("bench-sequence", help="Monte Carlo of the stochastic method over frame sequences "
                                               "(default: the paper's experiment)",
                        description="The stochastic method over frame sequences; the defaults are Udomkesmalee et "
                                    "al.'s Table 2 experiment (Betelgeuse, 10 deg steps in RA, 1 deg noise: see "
                                    "docs/stochastic.md for what to expect).")
    bs.add_argument("--scenario", choices=scenarios, default="udomkesmalee30", metavar="SCENARIO",
                    help=f"scenario (skyview.scenarios): {scenario_list} (default udomkesmalee30, the paper's)")
    bs.add_argument("-n", type=int, default=100, help="number of runs (sequences; default 100)")
    bs.add_argument("--frames", type=int, default=5, help="frames per sequence (default 5)")
    bs.add_argument("--start", choices=("betelgeuse", "random"), default="betelgeuse",
                    help="betelgeuse: the paper's start; random: attitudes uniform on SO(3)")
    bs.add_argument("--turn", choices=("ra", "pan"), default="ra",
                    help="ra: along right ascension (the paper); pan: about the camera y axis")
    bs.add_argument("--step-deg", type=_float, default=10.0, help="turn between frames, deg (default 10)")
    bs.add_argument("--level", choices=("image", "vector"), default="image",
                    help="image: simulator + centroider; vector: perturbed catalog directions (the paper's own)")
    bs.add_argument("--noise-deg", type=_float, default=None,
                    help="position noise, deg, 1 sigma per axis (default: the scenario's; udomkesmalee30: 1 deg)")
    bs.add_argument("--noise-arcsec", type=_float, default=None,
                    help="position noise, arcsec, 1 sigma per axis (instead of --noise-deg)")
    bs.add_argument("--mag-noise", type=_float, default=0.6, help="magnitude noise, 1 sigma, mag (the paper: 0.6)")
    bs.add_argument("--designation", choices=("observed", "true"), default="observed",
                    help="observed: the star nearest the boresight in the noisy frame; true: f(true boresight)")
    bs.add_argument("--hypothesis", choices=("attitude", "boresight"), default="attitude",
                    help="attitude: each hypothesis carries an attitude, turns in the camera frame (gyros); "
                         "boresight: the paper taken literally, 'the boresight is on star s' shifted by the "
                         "inertial turn (docs/stochastic.md)")
    _variant_arg(bs)
    bs.add_argument("--seed", type=int, default=0, help="random seed of the runs (default 0)")
    bs.add_argument("--out", default="bench-results", help="folder for the JSON and Markdown results")
    bs.add_argument("--quiet", action="store_true", help="no progress lines")
    bs.set_defaults(func=cmd_bench_sequence)

    r = sub.add_parser("record", help="simulate a scenario case, solve it and save it as a Rerun recording (.rrd); "
                                      "--method stochastic records the paper's frame sequence")
    r.add_argument("--method", choices=methods, default="angle", metavar="METHOD",
                   help=f"identification method: {method_list} (default angle)")
    _variant_arg(r)
    r.add_argument("--scenario", choices=scenarios, default=None, metavar="SCENARIO",
                   help=f"scenario: {scenario_list} (default cole8; for --method stochastic udomkesmalee30, the "
                        f"paper's experiment)")
    r.add_argument("--seed", type=int, default=0,
                   help="the case: its attitude and image noise (stochastic: run 0 of "
                        "bench-sequence --noise-arcsec 10 --seed SEED)")
    r.add_argument("path", nargs="?", default=None, metavar="OUT.rrd", help="the .rrd file (same as --out)")
    r.add_argument("--out", default=None,
                   help="the .rrd file (default METHOD-SCENARIO-SEED.rrd); with --examples the folder (default recordings)")
    r.add_argument("--force", action="store_true", help="overwrite existing recordings")
    r.add_argument("--examples", action="store_true",
                   help="regenerate the example recordings: each method on its paper's scenario (stochastic: its "
                        "frame sequence), and one failure")
    r.set_defaults(func=cmd_record)

    examples = ", ".join(_example_recordings()) or "none found"
    rp = sub.add_parser("replay", help="open a recording in the Rerun viewer (the web viewer when there is no desktop)",
                        description="Open a .rrd recording in the Rerun viewer. A relative path that does not exist "
                                    "here is looked up in skyview's own folder (so 'skyview replay "
                                    "recordings/angle-cole8.rrd' works from anywhere).")
    rp.add_argument("recording", nargs="?", default=None, help="a .rrd file (or --example METHOD)")
    rp.add_argument("--example", default=None, metavar="NAME",
                    help=f"open the shipped example recording recordings/NAME-*.rrd: {examples}")
    rp.add_argument("--web", action="store_true", help="serve the web viewer even when there is a desktop")
    rp.add_argument("--host", default="127.0.0.1", help="address to listen on (default: this machine only)")
    rp.add_argument("--port", type=int, default=9090, help="web viewer HTTP port (0: any free port; default 9090)")
    rp.add_argument("--grpc-port", type=int, default=0,
                    help="port that serves the recording to the viewer (default: any free port)")
    rp.set_defaults(func=cmd_replay)

    k = sub.add_parser("cache", help="list or clear the cached databases")
    ksub = k.add_subparsers(dest="action", required=True, parser_class=_Parser, metavar="ACTION")
    ksub.add_parser("list", help="the cached databases, their size and last use")
    kc = ksub.add_parser("clear", help="delete the cached databases (they are rebuilt when next needed)")
    kc.add_argument("--method", default=None, metavar="NAME",
                    help=f"only this database's files: patterns (the blind database) or a method ({method_list})")
    k.set_defaults(func=cmd_cache)

    c = sub.add_parser("catalog", help="build or describe the guide catalog")
    csub = c.add_subparsers(dest="action", required=True, parser_class=_Parser, metavar="ACTION")
    cb = csub.add_parser("build", help="derive the guide catalog from Hipparcos-2 (hip2.dat)")
    cb.add_argument("--epoch", type=_float, default=DEFAULT_EPOCH, help=epoch_help)
    cb.add_argument("--mag-limit", type=_float, default=DEFAULT_BUILD_MAG_LIMIT,
                    help=f"keep stars with Hp <= this, Hipparcos magnitude (default {DEFAULT_BUILD_MAG_LIMIT:g})")
    cb.add_argument("--out", default=None, help="the .npz file (default: the shipped assets/guide_catalog.npz)")
    cb.add_argument("--force", action="store_true", help="overwrite an existing --out file")
    ci = csub.add_parser("info", help="describe a guide catalog")
    ci.add_argument("path", nargs="?", help="a guide catalog .npz (default: the shipped one)")
    c.set_defaults(func=cmd_catalog)

    w = sub.add_parser("view", help="the browser viewer: sky, field of view, image, identification steps")
    w.add_argument("--image", default=None, help="start on this image (PNG / JPEG) instead of a simulated sky")
    w.add_argument("--fov-deg", type=_float, default=None,
                   help="horizontal full field of view of --image, deg (without --image: of the simulated camera)")
    w.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default: this machine only; 0.0.0.0 opens it to the network)")
    w.add_argument("--port", type=int, default=8080, help="HTTP port (the next free one if it is taken; default 8080)")
    w.add_argument("--coverage", metavar="DIR", default=None,
                   help="draw this sky-coverage map (the folder of `skyview coverage --out DIR`) on the sphere")
    w.add_argument("--compare", metavar="FILE.json", default=None,
                   help="show this comparison of every method (the JSON of `skyview bench --compare`) in the "
                        "Result tab")
    w.set_defaults(func=cmd_view)
    return p


def _error(message: str, code: int, want_json: bool) -> int:
    """One line on stderr; with --json also one JSON object on stdout."""
    print(f"skyview: {message}", file=sys.stderr)
    if want_json:
        try:
            print(json.dumps({"status": "error", "exit_code": code, "error": message}))
        except (BrokenPipeError, OSError):
            pass
    return code


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    want_json = "--json" in argv
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except BadInput as exc:
        return _error(f"error: {exc}", EXIT_BAD_INPUT, want_json)
    except SkyviewError as exc:
        return _error(str(exc), EXIT_BAD_INPUT, want_json)
    except KeyboardInterrupt:
        print("skyview: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `skyview solve ... | head`: the reader left; not an error of ours
        try:
            sys.stdout = open(os.devnull, "w")
        except OSError:
            pass
        return EXIT_SOLVED
    except MemoryError:
        return _error("error: not enough memory for this input (a smaller image, field or catalog depth, or "
                      "more memory)", EXIT_BAD_INPUT, want_json)
    except Exception as exc:  # one line for the user; the traceback on request
        if os.environ.get("SKYVIEW_DEBUG"):
            raise
        return _error(f"internal error: {type(exc).__name__}: {exc} (SKYVIEW_DEBUG=1 shows the traceback)",
                      EXIT_INTERNAL, want_json)


if __name__ == "__main__":
    sys.exit(main())
