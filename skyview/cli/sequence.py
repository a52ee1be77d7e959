"""`skyview solve-sequence` (a sequence method over frames with known turns, or tracking) and
`skyview bench-sequence` (the stochastic method's Monte Carlo, the paper's experiment by default)."""

from __future__ import annotations

import itertools
import json
import os
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
    add_scenario,
    add_sigma,
    add_variant,
    check_new_file,
    check_out_folder,
    check_recording_path,
    float_arg,
    progress_line,
    write_text_new,
    wrong_match_count,
)
from skyview.core.errors import BadInput, SkyviewError


def cmd_solve_sequence(a) -> int:
    from skyview.identify import METHODS
    from skyview.identify.base import is_sequence_method
    from skyview.solver.sequence import DEFAULT_SEQUENCE_METHOD

    if a.sigma_arcsec is not None and a.sigma_arcsec <= 0:
        raise BadInput("--sigma-arcsec must be positive")
    if a.p_identify is not None and not 0 < a.p_identify <= 1:
        raise BadInput("--p-identify must be in (0, 1]")
    paths = list(a.path)
    one = len(paths) == 1 and (Path(paths[0]).is_dir() or Path(paths[0]).suffix.lower() == ".json")
    # no --method on a sequence (folder or sequence.json): the sequence method, as always; image
    # paths, or a single-frame method: tracking (skyview.solver.track)
    method = a.method if a.method is not None or not one else DEFAULT_SEQUENCE_METHOD
    if method != "blind" and method is not None and is_sequence_method(METHODS[method]):
        if not one:
            raise BadInput(f"the {method} method reads one sequence (a folder or a sequence.json with the turns), "
                           f"not image paths: give --method for tracking")
        if a.no_turns:
            raise BadInput(f"--no-turns goes with tracking: the {method} method needs the turns")
        a.path, a.method = paths[0], method
        return _solve_sequence_method(a)
    return _solve_sequence_track(a, paths, one)


def _solve_sequence_method(a) -> int:
    from skyview.solver.sequence import solve_sequence

    output = check_new_file(a.output, a.force)
    check_recording_path(a.record, a.force)
    method_params = {} if a.p_identify is None else {"p_identify": a.p_identify}
    res = solve_sequence(a.path, fov_deg=a.fov_deg, mag_limit=4.5 if a.mag_limit is None else a.mag_limit,
                         sigma_rad=None if a.sigma_arcsec is None else a.sigma_arcsec * ARCSEC,
                         mag_zero_point=a.mag_zero_point, mag_cut=a.mag_cut, variant=a.variant,
                         method_params=method_params, use_truth=not a.no_truth, epoch=a.epoch,
                         max_stars=a.max_stars, k_sigma=a.k_sigma, method=a.method)
    out = res.to_dict()
    out["sequence"] = str(a.path)
    if a.record:
        _record_sequence(a, res)
    text = json.dumps(out, indent=1 if a.json else None)
    if output is not None:
        write_text_new(output, text + "\n", a.force)
    if a.json:
        print(text)
    else:
        for f in out["frames"]:
            if f["status"] == "error":
                print(f"frame {f['frame']}: error: {f['error']} (a frame without stars: the sequence goes on)")
                continue
            line = (f"frame {f['frame']}: {f.get('n_centroids', f['stars'])} centroids, {f['above_prior']} stars above "
                    f"the prior, leading HIP {f['top_hips'][0] if f['top_hips'] else '-'} at {f['top_posterior']:.3f}")
            if f.get("true_hip") is not None:
                line += f" (true HIP {f['true_hip']}: {f['true_posterior']:.3f})"
            line += f" -> {f['identification_status']}"
            if f["solved"]:
                line += f", {f['n_matches']} matches, P(false) {f['p_false']:.1e}"
            print(line)
        if res.solved:
            print(f"solved at frame {out['frame']}: RA {out['ra_deg']:.5f} deg  Dec {out['dec_deg']:+.5f} deg  "
                  f"roll {out['roll_deg']:+.4f} deg")
    if res.errors:
        bad = sorted(res.errors)
        print(f"skyview: {len(bad)} of {len(res.identifications)} frames could not be used: "
              f"frame{'s' if len(bad) > 1 else ''} {', '.join(map(str, bad))} (the method carried its hypotheses "
              f"across {'them' if len(bad) > 1 else 'it'} with the turns)", file=sys.stderr)
    if not res.solved:
        print(f"skyview: not solved: {out.get('reason', '')}", file=sys.stderr)
        return EXIT_NOT_SOLVED
    return EXIT_NOT_SOLVED if res.errors else EXIT_SOLVED


def _solve_sequence_track(a, paths: list[str], one: bool) -> int:
    """Tracking (skyview.solver.track): one JSON line per frame with --json, else a line per frame."""
    from skyview.core.attitude import attitude_error_arcsec
    from skyview.core.camera import Camera
    from skyview.solver.sequence import load_sequence
    from skyview.solver.solution_json import solution_dict
    from skyview.solver.track import Tracker, body_turn_rotvec

    sequence_only = [o for o, v in (("--p-identify", a.p_identify), ("--mag-zero-point", a.mag_zero_point),
                                    ("--mag-cut", a.mag_cut)) if v is not None]
    if sequence_only:
        raise BadInput(f"{', '.join(sequence_only)} go{'es' if len(sequence_only) == 1 else ''} with the "
                       f"stochastic method, not with tracking")
    output = check_new_file(a.output, a.force)
    if a.record:  # checked before tracking (skyview.record.track writes it after)
        if not str(a.record).lower().endswith(".rrd"):
            raise BadInput(f"{a.record}: a recording's name ends in .rrd")
        check_new_file(a.record, a.force)
    truths = None
    if one:
        seq = load_sequence(paths[0], a.fov_deg)
        # (read one at a time as the loop asks: a frame that cannot be read is that frame's error)
        images = (seq.images.read(k) for k in range(len(seq.images)))
        turns, camera, names = seq.turns, seq.camera, [str(p) for p in seq.paths]
        truths = None if a.no_truth else seq.truths
    else:
        for p in paths:
            if Path(p).is_dir() or Path(p).suffix.lower() == ".json":
                raise BadInput(f"{p}: give one sequence (a folder or sequence.json) or image paths, not both")
        # read one at a time (memory flat over a long run): a frame that cannot be read is that frame's
        # error; the first frame read gives the sequence's size (and the camera, when the FOV is given)
        frames, head = _frames(paths), []
        for item in frames:
            head.append(item)
            if isinstance(item, np.ndarray):
                break
        images = itertools.chain(head, frames)
        first = head[-1] if head and isinstance(head[-1], np.ndarray) else None
        if first is None:
            raise BadInput(f"none of the {len(paths)} frames could be read ({head[0] if head else 'no paths'})")
        camera = (Camera.from_fov(a.fov_deg, first.shape[1], first.shape[0])
                  if (a.fov_deg is not None and first is not None) else None)
        turns, names = None, list(paths)
    if a.no_turns:
        turns = None
    method = None if a.method in (None, "blind") else a.method
    tracker = Tracker(camera, method, mag_limit=a.mag_limit, variant=a.variant, epoch=a.epoch,
                      sigma_rad=None if a.sigma_arcsec is None else a.sigma_arcsec * ARCSEC,
                      max_stars=a.max_stars, k_sigma=a.k_sigma, progress=progress_line)
    failed, errors = [], []
    recorder = None
    if a.record:  # written frame by frame as the run goes (memory flat; a killed run keeps its frames)
        from skyview.record.track import TrackRecorder

        recorder = TrackRecorder(a.record, tracker.catalog, method=a.method or "blind", force=a.force)
    out_lines = _LineFile(output) if output is not None else None
    shape = None
    for k, img in enumerate(images):
        turn = None if (k == 0 or turns is None) else turns[k - 1]
        if isinstance(img, np.ndarray) and shape is None:
            shape = img.shape
        if isinstance(img, np.ndarray) and img.shape != shape:
            img = BadInput(f"{names[k]} is {img.shape[1]}x{img.shape[0]}, the sequence's frames are "
                           f"{shape[1]}x{shape[0]}")
        try:
            if not isinstance(img, np.ndarray):
                raise img
            fr = tracker.process(img, turn)
        except (BadInput, SkyviewError) as exc:  # this frame's error (its line, exit code 1); the run goes on
            tracker.skip(turn)
            errors.append(k)
            d = {"frame": k, "image": names[k], **solution_dict(status="error", reason=str(exc),
                                                                method=a.method or "blind", variant=a.variant),
                 "error": str(exc)}
            text = json.dumps(d, allow_nan=False)
            if out_lines is not None:
                out_lines.write(text)
            if recorder is not None:
                recorder.add_error(k, str(exc))
            print(text if a.json else f"frame {k}: error: {exc}", flush=True)
            continue
        if recorder is not None:
            recorder.add(fr, img, tracker.camera, None if truths is None else truths[k])
        d = fr.to_dict()
        d = {"frame": k, "image": names[k], **{key: v for key, v in d.items() if key != "frame"}}
        if truths is not None and fr.solved:
            R_true = np.asarray(truths[k]["R"], dtype=np.float64)
            d["error_arcsec"] = attitude_error_arcsec(fr.R, R_true)
            d["wrong_matches"] = wrong_match_count(fr.matches, truths[k])
            if fr.relative_to is not None:
                tru = body_turn_rotvec(np.asarray(truths[fr.relative_to]["R"], dtype=np.float64), R_true)
                d["relative_error_arcsec"] = float(np.degrees(np.linalg.norm(fr.relative_rotvec_rad - tru)) * 3600)
        if not fr.solved:
            failed.append(k)
        text = json.dumps(d, allow_nan=False)
        if out_lines is not None:
            out_lines.write(text)
        if a.json:
            print(text, flush=True)
        else:
            print(_track_line(k, d, fr.solved), flush=True)
    if out_lines is not None:
        out_lines.close()
    if recorder is not None:
        recorder.catalog = tracker.catalog  # (the stars drawn near the path: the depth tracking went to)
        info = recorder.close()
        print(f"recorded {info.frames} frames into {info.path} ({info.bytes / 1e6:.1f} MB"
              + (f"; frames {', '.join(map(str, errors))} could not be read" if errors else "") + ")",
              file=sys.stderr)
    n = len(names)
    if errors:
        print(f"skyview: {len(errors)} of {n} frames could not be solved at all: frame{'s' if len(errors) > 1 else ''} "
              f"{', '.join(map(str, errors))} (the others were solved as usual)", file=sys.stderr)
    if failed:
        print(f"skyview: {len(failed)} of {n} frames not solved: frame{'s' if len(failed) > 1 else ''} "
              f"{', '.join(map(str, failed))}", file=sys.stderr)
    return EXIT_NOT_SOLVED if (failed or errors) else EXIT_SOLVED


class _LineFile:
    """--output's JSON lines, written as the run goes to a file beside it and moved into place at the end
    (the path was checked before the run: never overwritten without --force)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.part")
        self.fh = open(self.tmp, "w", encoding="utf-8")

    def write(self, line: str) -> None:
        self.fh.write(line + "\n")
        self.fh.flush()

    def close(self) -> None:
        self.fh.close()
        os.replace(self.tmp, self.path)


def _frames(paths: list[str]):
    """The images of `paths`, read one at a time as the loop asks (memory flat over a long run); a file
    that cannot be read yields its BadInput instead of an image."""
    from skyview.detect.centroids import load_image

    for p in paths:
        try:
            yield load_image(p)
        except (BadInput, SkyviewError) as exc:
            yield exc


def _track_line(k: int, d: dict, solved: bool) -> str:
    """One tracked frame (its JSON dict) as a line of text."""
    t = d["time_ms"]
    if not solved:
        return f"frame {k}: not solved ({d['mode']}): {d.get('reason', '')}, {t['total']:.1f} ms"
    rel = f", turned {d['relative_angle_deg']:.4f} deg since frame {d['relative_to']}" if "relative_to" in d else ""
    line = (f"frame {k}: {d['mode']:<13} RA {d['ra_deg']:.5f}  Dec {d['dec_deg']:+.5f}  roll "
            f"{d['roll_deg']:+.4f} deg{rel}, {d['n_matches']} matches, {t['total']:.1f} ms")
    if "error_arcsec" in d:
        line += f" (against truth: {d['error_arcsec']['total']:.1f} arcsec, {d['wrong_matches']} wrong matches)"
    return line


def _record_sequence(a, res) -> None:
    from skyview.record.sequence import record_sequence
    from skyview.solver.sequence import load_sequence

    seq = load_sequence(a.path, a.fov_deg)  # the images (solve_sequence read them too) and the turns
    truths = None if a.no_truth else seq.truths
    images = [None if isinstance(im, BadInput) else im for im in map(seq.images.read, range(len(seq.images)))]
    info = record_sequence(a.record, res, images, truths=truths, turns=seq.turns, force=a.force,
                           meta={"sequence": str(a.path), "frames": len(seq.images), "variant": a.variant,
                                 "truth": "the simulator's sidecars" if truths is not None else "-"})
    done = (f"identified at frame{'s' if len(info.identified) > 1 else ''} {', '.join(map(str, info.identified))}"
            if info.identified else "not identified")
    print(f"recorded {info.path} ({info.frames} frames, {done}, {info.steps} steps, {info.bytes / 1e6:.2f} MB, "
          f"written in {info.write_ms:.0f} ms)", file=sys.stderr)


def cmd_bench_sequence(a) -> int:
    from skyview.bench.runner import save_results
    from skyview.bench.sequence import bench_sequence, format_sequence_markdown
    from skyview.simulate.scenarios import get_scenario

    scenario = get_scenario(a.scenario)
    if a.noise_deg is not None and a.noise_arcsec is not None:
        raise BadInput("give --noise-deg or --noise-arcsec, not both")
    noise = (np.radians(a.noise_deg) if a.noise_deg is not None
             else a.noise_arcsec * ARCSEC if a.noise_arcsec is not None else None)
    out_dir = check_out_folder(a.out)
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
    from skyview.solver.sequence import PAPER_100_RUNS

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


def add_parsers(sub) -> None:
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
    add_method(q, None, "lost-in-space method for tracking: {methods}, or blind (the default pipeline; the default "
                        "for image paths); stochastic: the multi-frame method (the default for a sequence)", blind=True)
    q.add_argument("--no-turns", action="store_true",
                   help="tracking: ignore the sequence's turns and predict from the rate of the last two attitudes")
    q.add_argument("--fov-deg", type=float_arg, default=None,
                   help="horizontal full FOV, deg (default: the sidecar's camera)")
    add_variant(q)
    q.add_argument("--mag-limit", type=float_arg, default=None,
                   help="guide catalog limit, Hp (default: stochastic 4.5, the paper's; tracking 6)")
    add_sigma(q, "direction error of a star")
    q.add_argument("--mag-zero-point", type=float_arg, default=None,
                   help="magnitude of a star giving 1 unit of brightness (default: from the sidecar's sensor)")
    q.add_argument("--mag-cut", type=float_arg, default=None,
                   help="leave fainter stars out of the statistics, Hp (default: mag-limit + 0.25 with a zero point)")
    q.add_argument("--p-identify", type=float_arg, default=None,
                   help="posterior probability at which a star dominates, 0-1 (default 0.95)")
    add_epoch(q)
    add_detection(q, " per frame")
    q.add_argument("--no-truth", action="store_true", help="ignore the simulator's truth in the sidecar")
    q.add_argument("--json", action="store_true",
                   help="print JSON: one object (stochastic), one line per frame (tracking)")
    add_outputs(q, output="also write the JSON result (tracking: the JSON lines) to this file",
                force="overwrite existing --output and --record files",
                record="also save the sequence as a Rerun recording, frame by frame (open it with 'skyview replay')")
    q.set_defaults(func=cmd_solve_sequence)

    bs = sub.add_parser("bench-sequence", help="Monte Carlo of the stochastic method over frame sequences "
                                               "(default: the paper's experiment)",
                        description="The stochastic method over frame sequences; the defaults are Udomkesmalee et "
                                    "al.'s Table 2 experiment (Betelgeuse, 10 deg steps in RA, 1 deg noise: see "
                                    "docs/stochastic.md for what to expect).")
    add_scenario(bs, "udomkesmalee30", "default udomkesmalee30, the paper's")
    bs.add_argument("-n", type=int, default=100, help="number of runs (sequences; default 100)")
    bs.add_argument("--frames", type=int, default=5, help="frames per sequence (default 5)")
    bs.add_argument("--start", choices=("betelgeuse", "random"), default="betelgeuse",
                    help="betelgeuse: the paper's start; random: attitudes uniform on SO(3)")
    bs.add_argument("--turn", choices=("ra", "pan"), default="ra",
                    help="ra: along right ascension (the paper); pan: about the camera y axis")
    bs.add_argument("--step-deg", type=float_arg, default=10.0, help="turn between frames, deg (default 10)")
    bs.add_argument("--level", choices=("image", "vector"), default="image",
                    help="image: simulator + centroider; vector: perturbed catalog directions (the paper's own)")
    bs.add_argument("--noise-deg", type=float_arg, default=None,
                    help="position noise, deg, 1 sigma per axis (default: the scenario's; udomkesmalee30: 1 deg)")
    bs.add_argument("--noise-arcsec", type=float_arg, default=None,
                    help="position noise, arcsec, 1 sigma per axis (instead of --noise-deg)")
    bs.add_argument("--mag-noise", type=float_arg, default=0.6, help="magnitude noise, 1 sigma, mag (the paper: 0.6)")
    bs.add_argument("--designation", choices=("observed", "true"), default="observed",
                    help="observed: the star nearest the boresight in the noisy frame; true: f(true boresight)")
    bs.add_argument("--hypothesis", choices=("attitude", "boresight"), default="attitude",
                    help="attitude: each hypothesis carries an attitude, turns in the camera frame (gyros); "
                         "boresight: the paper taken literally, 'the boresight is on star s' shifted by the "
                         "inertial turn (docs/stochastic.md)")
    add_variant(bs)
    bs.add_argument("--seed", type=int, default=0, help="random seed of the runs (default 0)")
    bs.add_argument("--out", default="bench-results", help="folder for the JSON and Markdown results")
    bs.add_argument("--quiet", action="store_true", help="no progress lines")
    bs.set_defaults(func=cmd_bench_sequence)
