"""`skyview` command line: demo, simulate, solve, bench, sequences, coverage, record, replay, view, cache,
catalog, experiment.

One module per group of subcommands, each with its `cmd_*` functions and `add_parsers(sub)`; the options
several commands share, and their choices (read once from the method, variant and statistic registries),
are in `skyview.cli.common`.

Exit codes: 0 success (solved), 1 ran but did not solve, 2 bad input. Errors are one line on stderr;
set SKYVIEW_DEBUG=1 to see a traceback for an unexpected error.
"""

from __future__ import annotations

import json
import os
import sys

from skyview.cli import bench, cache, coverage, demo, experiment, sequence, solve, view
from skyview.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_INTERNAL,
    EXIT_NOT_SOLVED,
    EXIT_SOLVED,
    Parser,
    method_names,
    scenario_names,
)
from skyview.cli.view import resolve_recording
from skyview.core.errors import BadInput, SkyviewError

GROUPS = (demo, solve, bench, coverage, sequence, view, cache, experiment)  # the order of `skyview --help`


def build_parser() -> Parser:
    p = Parser(prog="skyview", description="Where is the star tracker pointing? Simulate, identify, solve, compare.",
               epilog=f"'skyview COMMAND --help' shows each command's options. Methods (--method): "
                      f"{', '.join(method_names())}. Scenarios (--scenario): {', '.join(scenario_names())}. Angles "
                      f"are in degrees unless an option says otherwise; FOVs are horizontal (across the image width).")
    p.add_argument("--version", action="version", version=f"skyview {__import__('skyview').__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser, metavar="COMMAND")
    for group in GROUPS:
        group.add_parsers(sub)
    return p


def _error(message: str, code: int, want_json: bool) -> int:
    """One line on stderr; with --json also one JSON object on stdout."""
    print(f"skyview: {message}", file=sys.stderr)
    if want_json:
        try:
            text = message.removeprefix("error: ")  # the field says it is an error already
            print(json.dumps({"status": "error", "exit_code": code, "error": text}))
        except (BrokenPipeError, OSError):
            pass
    return code


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    want_json = "--json" in argv and argv[:1] != ["experiment"]  # an experiment's --json names a file
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except BadInput as exc:
        return _error(f"error: {exc}", EXIT_BAD_INPUT, want_json)
    except SkyviewError as exc:
        return _error(str(exc), EXIT_BAD_INPUT, want_json)
    except KeyboardInterrupt:  # (with --json, a script reading stdout gets its one object: interrupted)
        print("skyview: interrupted", file=sys.stderr)
        if want_json:
            try:
                print(json.dumps({"status": "interrupted", "exit_code": 130}))
            except (BrokenPipeError, OSError):
                pass
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


__all__ = ["main", "build_parser", "resolve_recording", "EXIT_SOLVED", "EXIT_NOT_SOLVED", "EXIT_BAD_INPUT",
           "EXIT_INTERNAL"]

if __name__ == "__main__":
    sys.exit(main())
