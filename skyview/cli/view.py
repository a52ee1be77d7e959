"""`skyview view` (the browser viewer), `skyview record` (a case solved and saved as a Rerun recording) and
`skyview replay` (a recording opened in the Rerun viewer)."""

from __future__ import annotations

from pathlib import Path

from skyview.cli.common import EXIT_SOLVED, add_method, add_scenario, add_variant, float_arg
from skyview.core.errors import BadInput


def cmd_record(a) -> int:
    if a.path is not None and a.out is not None:
        raise BadInput(f"give the output once: {a.path} or --out {a.out}")
    target = a.path if a.path is not None else a.out
    if a.examples:
        from skyview.record.examples import MANIFEST, record_examples

        out = Path(target) if target else Path("recordings")
        entries = record_examples(out, force=a.force)
        print(f"wrote {len(entries)} example recordings and {out / MANIFEST}")
        return EXIT_SOLVED
    from skyview.identify import METHODS
    from skyview.identify.base import is_sequence_method

    if is_sequence_method(METHODS[a.method]):  # a sequence method: the paper's experiment, frame by frame
        return _record_sequence_case(a, target)
    from skyview.record.cases import record_case

    scenario = a.scenario or "cole8"
    out = Path(target) if target else Path(f"{a.method}-{scenario}-{a.seed}.rrd")
    info, case = record_case(out, a.method, scenario, a.seed, variant=a.variant, force=a.force)
    r = case.result
    print(f"recorded {info.path}: {a.method} ({a.variant}) on {scenario}, seed {a.seed}: {r.status}"
          f"{'' if r.solved else ' (' + r.reason + ')'}, {case.outcome} against truth; {info.steps} steps, "
          f"{info.bytes / 1e6:.2f} MB written in {info.write_ms:.0f} ms (solve {r.time_ms.get('total', 0.0):.0f} ms)")
    return EXIT_SOLVED


def _record_sequence_case(a, target) -> int:
    from skyview.record.sequence import PAPER_SCENARIO, record_paper_sequence

    scenario = a.scenario or PAPER_SCENARIO
    out = Path(target) if target else Path(f"{a.method}-{scenario}-{a.seed}.rrd")
    info, case = record_paper_sequence(out, a.seed, scenario=scenario, variant=a.variant, force=a.force)
    r = case.result
    post = [f["true_posterior"] for f in r.truth_figures()]  # scored against the truth (skyview.simulate.scoring)
    done = (f"identified at frame{'s' if len(info.identified) > 1 else ''} {', '.join(map(str, info.identified))}"
            if info.identified else f"not identified ({r.identifications[-1].reason})")
    print(f"recorded {info.path}: {a.method} ({a.variant}) on {scenario}, the paper's experiment at 10 arcsec, seed "
          f"{a.seed}: {info.frames} frames, {done}, {case.outcome} against truth; P(true star) "
          + " ".join("-" if p is None else f"{p:.3f}" for p in post)
          + f"; {info.steps} steps, {info.bytes / 1e6:.2f} MB written in {info.write_ms:.0f} ms "
          f"(solve {sum(r.time_ms.values()):.0f} ms)")
    return EXIT_SOLVED


def example_recordings() -> dict[str, Path]:
    """The example recordings in the repository's recordings/ by their first name part: 'angle' ->
    recordings/angle-cole8.rrd, 'failure' -> recordings/failure-angle-cole8-false.rrd."""
    from skyview.core.catalog import REPO_ROOT

    found: dict[str, Path] = {}
    for p in sorted((REPO_ROOT / "recordings").glob("*-*.rrd")):
        found.setdefault(p.name.split("-", 1)[0], p)
    return found


def resolve_recording(recording: str | None, example: str | None) -> Path:
    """The .rrd to replay: a path as given; a relative one that does not exist here looked up in skyview's
    own folder (where recordings/ lives); or --example NAME: recordings/NAME-*.rrd."""
    from skyview.core.catalog import REPO_ROOT

    if example is not None:
        if recording is not None:
            raise BadInput(f"give a recording or --example, not both ({recording}, --example {example})")
        found = example_recordings()
        if example not in found:
            raise BadInput(f"no example recording {example!r}: choose from {', '.join(found) or 'none'} "
                           f"(in {REPO_ROOT / 'recordings'}; 'skyview record --examples --force' regenerates them)")
        return found[example]
    if recording is None:
        raise BadInput(f"give a .rrd file, or --example NAME ({', '.join(example_recordings()) or 'none found'})")
    path = Path(recording).expanduser()
    if not path.exists() and not path.is_absolute() and (REPO_ROOT / path).exists():
        return REPO_ROOT / path
    return path


def cmd_replay(a) -> int:
    from skyview.record.replay import replay

    path = resolve_recording(a.recording, a.example)
    return replay(path, web=True if a.web else None, host=a.host, port=a.port, grpc_port=a.grpc_port)


def cmd_view(a) -> int:
    from skyview.viewer.app import serve

    if not 0 <= a.port <= 65535:
        raise BadInput(f"--port {a.port} is not a TCP port (0-65535)")
    if a.photo is not None and a.image is not None and a.photo != a.image:
        raise BadInput("give the photograph once: as PHOTO or as --image")
    return serve(host=a.host, port=a.port, image=a.photo or a.image, fov_deg=a.fov_deg, coverage=a.coverage,
                 compare=a.compare, say=lambda line: print(line, flush=True))


def add_parsers(sub) -> None:
    r = sub.add_parser("record", help="simulate a scenario case, solve it and save it as a Rerun recording (.rrd); "
                                      "--method stochastic records the paper's frame sequence")
    add_method(r, "angle", "identification method: {methods} (default angle)")
    add_variant(r)
    add_scenario(r, None, "default cole8; for --method stochastic udomkesmalee30, the paper's experiment")
    r.add_argument("--seed", type=int, default=0,
                   help="the case: its attitude and image noise (stochastic: run 0 of "
                        "bench-sequence --noise-arcsec 10 --seed SEED)")
    r.add_argument("path", nargs="?", default=None, metavar="OUT.rrd", help="the .rrd file (same as --out)")
    r.add_argument("--out", default=None,
                   help="the .rrd file (default METHOD-SCENARIO-SEED.rrd); with --examples the folder "
                        "(default recordings)")
    r.add_argument("--force", action="store_true", help="overwrite existing recordings")
    r.add_argument("--examples", action="store_true",
                   help="regenerate the example recordings: each method on its paper's scenario (stochastic: its "
                        "frame sequence), and one failure")
    r.set_defaults(func=cmd_record)

    examples = ", ".join(example_recordings()) or "none found"
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

    w = sub.add_parser("view", help="the browser viewer: sky, field of view, image, identification steps")
    w.add_argument("photo", nargs="?", default=None, metavar="PHOTO",
                   help="open on this photograph (PNG / JPEG / TIFF / FITS), solved blind (the same as --image)")
    w.add_argument("--image", default=None, help="start on this image (PNG / JPEG / TIFF / FITS) instead of a simulated sky")
    w.add_argument("--fov-deg", type=float_arg, default=None,
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
