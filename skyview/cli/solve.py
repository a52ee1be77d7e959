"""`skyview solve`: one image -> attitude (the default blind pipeline, or one method), with its text and
JSON reports."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from skyview.cli.common import (
    ARCSEC,
    EXIT_NOT_SOLVED,
    EXIT_SOLVED,
    add_detection,
    add_epoch,
    add_method,
    add_outputs,
    add_param,
    add_sigma,
    add_statistic,
    add_variant,
    check_new_file,
    check_recording_path,
    float_arg,
    method_params,
    progress_line,
    read_truth,
    write_text_new,
    wrong_match_count,
)
from skyview.core.errors import BadInput


def against_truth(result, R_true: np.ndarray, truth: dict | None) -> dict:
    """The attitude error of a solved result and (with a truth sidecar) how many of its matches are wrong."""
    from skyview.core.attitude import attitude_error_arcsec

    return {"error_arcsec": attitude_error_arcsec(result.R, R_true),
            "wrong_matches": None if truth is None else wrong_match_count(result.matches, truth)}


def _result_with_truth(result, truth_path: Path | None) -> dict:
    out = result.to_dict()
    if truth_path is None:
        return out
    truth = read_truth(truth_path)
    if truth is None:
        raise BadInput(f"{truth_path} is not a skyview truth sidecar")
    entry = {"path": str(truth_path), "ra_deg": truth.get("ra_deg"), "dec_deg": truth.get("dec_deg"),
             "roll_deg": truth.get("roll_deg")}
    if result.R is not None:
        entry.update(against_truth(result, np.asarray(truth["R"], dtype=float), truth))
    out["truth"] = entry
    return out


def print_human(out: dict, file=sys.stdout) -> None:
    """A solve result (its `to_dict()`, with "truth" when compared) as a few lines of text."""
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
        lens = (out.get("camera") or {}).get("model", "pinhole")
        print(f"  camera{' (fitted)' if out.get('camera_fitted') else ''}"
              f"{'' if lens == 'pinhole' else f', {lens} fisheye'}: FOV {out['fov_deg']:.4f} deg, "
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
    from skyview.detect.centroids import load_image
    from skyview.io.fits import row_order
    from skyview.solver.pipeline import solve_image

    path = Path(a.image)
    image = load_image(path)
    order = row_order(path)  # a FITS file's ROWORDER ("" if it has none), None for other files
    lo, hi = float(image.min()), float(image.max())
    if hi == lo:  # (exactly: a float image of 0..1 is not blank because its values share an integer part)
        raise BadInput(f"{path} is blank (every pixel is {lo:g}): there is no sky to solve")
    params = {}
    if a.sigma_arcsec is not None:
        if a.sigma_arcsec <= 0:
            raise BadInput("--sigma-arcsec must be positive")
        params["sigma_rad"] = a.sigma_arcsec * ARCSEC
    mparams = method_params(a)
    output = check_new_file(a.output, a.force)
    check_recording_path(a.record, a.force)
    check_new_file(a.wcs, a.force)
    if a.method is None and mparams:
        raise BadInput("--param and --statistic go with --method (the default pipeline has no method parameters)")
    result = solve_image(image, a.fov_deg, a.method, fov_error=a.fov_error, mag_limit=a.mag_limit, epoch=a.epoch,
                         estimator=a.estimator, max_stars=a.max_stars, k_sigma=a.k_sigma,
                         distortion=tuple(a.distortion), method_params=mparams or None,
                         variant=a.variant, memory_mb=a.memory_mb, progress=progress_line,
                         try_flipped_rows=order == "", mirror=False if a.no_mirror else None,
                         deep=False if a.no_deep else None,
                         measure_all=bool(a.record), **params)
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
        from skyview.io.wcs import write_wcs

        # for the file's own pixel grid: a FITS file read bottom row first, unless solved the other way up
        rows_reversed_on_read = order not in (None, "TOP-DOWN")
        write_wcs(a.wcs, result.R, result.camera, force=a.force,
                  rows_reversed=rows_reversed_on_read != result.rows_reversed)
        out["wcs"] = str(a.wcs)
    text = json.dumps(out, indent=1 if a.json else None, allow_nan=False)
    if output is not None:
        write_text_new(output, text + "\n", a.force)
    if a.json:
        print(text)
    else:
        print_human(out)
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


def _record_solve(a, result, image, truth_path: Path | None, image_path: Path) -> None:
    from skyview.record.recording import record_solve

    truth = read_truth(truth_path) if truth_path is not None else None
    if result.rows_reversed:  # the image as it solved (its pixels are the ones the result's describe)
        image = np.ascontiguousarray(image[::-1])
    info = record_solve(a.record, result, image, catalog=result.catalog, truth=truth, force=a.force,
                        meta={"image": str(image_path), "fov_deg": a.fov_deg, "truth": str(truth_path or "-")})
    print(f"recorded {info.path} ({info.steps} steps, {info.bytes / 1e6:.2f} MB, written in {info.write_ms:.0f} ms)",
          file=sys.stderr)


def add_parsers(sub) -> None:
    v = sub.add_parser("solve", help="image -> attitude (blind: no field of view needed)",
                       description="Solve a star-field image (PNG, TIFF, JPEG, FITS; grey or colour). With no options "
                                   "it runs the default pipeline: blind four-star patterns over a horizontal FOV "
                                   "of about 2.5-81 deg, then the camera (FOV, k1, k2) fitted to the stars and the "
                                   "shared verification. Exit code 0 solved, 1 not solved (the reason and what to "
                                   "try on stderr), 2 bad input.")
    v.add_argument("image", help="the image file (PNG, TIFF, JPEG, BMP, WebP, FITS, ...; 8/16-bit or float, grey or "
                   "colour)")
    v.add_argument("--fov-deg", type=float_arg, default=None,
                   help="horizontal full field of view, deg, as far as it is known (default: searched blind)")
    v.add_argument("--fov-error", type=float_arg, default=None,
                   help="how far --fov-deg may be off, as a fraction (0.1 = +-10 %%; 0 = exact: the papers' "
                        "calibrated mode); default: +-10 %%, then from a 2.5th to 2.5 times --fov-deg when nothing "
                        "solves within it (a note says how far --fov-deg was off)")
    add_method(v, None, "an identification method: {methods}; default: the default pipeline (blind, camera fitted)")
    add_variant(v, "with --method: ")
    v.add_argument("--wcs", default=None, metavar="FILE.wcs",
                   help="also write the solution as a FITS WCS header (TAN-SIP), for DS9 / astropy")
    v.add_argument("--memory-mb", type=float_arg, default=None,
                   help="memory budget for building the blind database, MB (default 1024)")
    v.add_argument("--json", action="store_true", help="print one JSON object")
    v.add_argument("--no-deep", action="store_true",
                   help="never search the deep catalog (Hipparcos-2 + Gaia DR3 to G 10) for a field narrower than "
                        "the guide catalog reaches (~0.7-3.1 deg; by default after the blind search fails on an image "
                        "of 5 or more stars; its database is built the first time: ~45 s, ~400 MB)")
    v.add_argument("--no-mirror", action="store_true",
                   help="do not take the image for a mirror image of the sky (by default the blind searches check "
                        "patterns that fit only mirrored too, as a star diagonal or a flipped export makes them; one "
                        "found so is reported with its rows turned over: rows_reversed in the JSON)")
    add_sigma(v, "centroid direction error")
    v.add_argument("--mag-limit", type=float_arg, default=None,
                   help="guide catalog limit, Hipparcos magnitude Hp (default: from the image; methods other "
                        "than angle: 6)")
    add_epoch(v)
    v.add_argument("--estimator", choices=("svd", "q-method"), default="svd",
                   help="attitude estimator: svd (Markley, default) or q-method (Davenport)")
    add_statistic(v, "with --method: ")
    add_param(v)
    add_detection(v)
    v.add_argument("--distortion", type=float_arg, nargs=2, default=(0.0, 0.0), metavar=("K1", "K2"),
                   help="radial distortion of a calibrated camera: OpenCV k1 k2, dimensionless (with "
                        "--fov-error 0; default 0 0)")
    v.add_argument("--truth", default=None,
                   help="truth sidecar (JSON) to compare with (default: IMAGE.json if present)")
    v.add_argument("--no-truth", action="store_true", help="do not look for a truth sidecar")
    add_outputs(v, output="also write the JSON result to this file",
                force="overwrite existing --output, --wcs, --record files",
                record="also save the solve as a Rerun recording (open it with 'skyview replay')")
    v.set_defaults(func=cmd_solve)
