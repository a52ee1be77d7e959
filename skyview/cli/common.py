"""What every `skyview` command shares: the one-line parser, number parsing, file checks, progress lines,
and the options several commands take (each defined once, its choices read from the registries)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from skyview.core.errors import BadInput

EXIT_SOLVED, EXIT_NOT_SOLVED, EXIT_BAD_INPUT, EXIT_INTERNAL = 0, 1, 2, 3
ARCSEC = np.pi / 180 / 3600


class Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2 (argparse prints usage + message otherwise)
        raise BadInput(f"{message} (see '{self.prog} --help')")


def float_arg(text: str) -> float:
    """An argparse type: a finite number."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not np.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return v


def write_text_new(path: Path, text: str, force: bool) -> None:
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


def check_new_file(path: str | Path | None, force: bool, what: str = "") -> Path | None:
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


def check_out_folder(path: str | Path) -> Path:
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


def check_recording_path(path: str | None, force: bool) -> None:
    """Before solving: a --record path may be written (the recorder is imported only when asked)."""
    if path:
        from skyview.record.draw import check_output_path

        check_output_path(path, force)


def progress_line(line: str) -> None:
    print(f"skyview: {line.strip()}", file=sys.stderr, flush=True)


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


def wrong_match_count(matches: list[dict], truth: dict) -> int:
    """How many of a result's matches ([{index, u, v, hip, ...}]) the truth sidecar contradicts."""
    from skyview.simulate.truth import wrong_matches

    return len(wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in matches], truth))


# ----------------------------------------------------------------------------- method parameters

def _param_value(text: str):
    """A --param value: JSON when it parses (numbers, true/false, null, lists), else the text itself."""
    try:
        return json.loads(text)
    except ValueError:
        return text


def method_params(a) -> dict:
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


# ----------------------------------------------------------------------------- shared options

def method_names() -> tuple[str, ...]:
    from skyview.identify import METHODS

    return tuple(METHODS)


def scenario_names() -> tuple[str, ...]:
    from skyview.simulate.scenarios import SCENARIOS

    return tuple(SCENARIOS)


def add_method(parser, default: str | None, help: str, *, blind: bool = False, required: bool = False) -> None:
    """--method METHOD, its choices the registry's (plus 'blind' where the default pipeline may be named)."""
    methods = method_names()
    parser.add_argument("--method", choices=(*methods, "blind") if blind else methods, default=default,
                        required=required, metavar="METHOD", help=help.format(methods=", ".join(methods)))


def add_variant(parser, extra: str = "") -> None:
    from skyview.identify import VARIANTS

    parser.add_argument("--variant", choices=VARIANTS, default=VARIANTS[0],
                        help=f"{extra}paper (default): the paper's parameters; improved: the method's improvements "
                             f"(docs/methods.md)")


def add_statistic(parser, extra: str = "") -> None:
    from skyview.identify.verify import CALIBRATED, STATISTICS

    parser.add_argument("--statistic", choices=STATISTICS, default=None,
                        help=f"{extra}verification statistic: {', '.join(STATISTICS)} (default {CALIBRATED})")


def add_param(parser) -> None:
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                        help="a method parameter by its name (docs/methods.md), repeatable: e.g. --param workers=2 "
                             "(genetic: both cores), --param p_identify=0.99")


def add_scenario(parser, default: str | None, help_default: str) -> None:
    scenarios = ", ".join(scenario_names())
    parser.add_argument("--scenario", choices=scenario_names(), default=default, metavar="SCENARIO",
                        help=f"scenario (skyview.simulate.scenarios): {scenarios} ({help_default})")


def add_epoch(parser) -> None:
    from skyview.core.catalog import DEFAULT_EPOCH

    parser.add_argument("--epoch", type=float_arg, default=DEFAULT_EPOCH,
                        help=f"epoch of the catalog positions (proper motion applied), Julian year "
                             f"(default {DEFAULT_EPOCH:g})")


def add_detection(parser, per: str = "") -> None:
    """--max-stars and --k-sigma: which centroids the identifier sees."""
    parser.add_argument("--max-stars", type=int, default=40,
                        help=f"use at most this many brightest centroids{per} (a count; default 40)")
    parser.add_argument("--k-sigma", type=float_arg, default=5.0,
                        help="detection threshold, in sigmas of the measured background noise (default 5)")


def add_sigma(parser, what: str) -> None:
    parser.add_argument("--sigma-arcsec", type=float_arg, default=None,
                        help=f"1-sigma {what}, arcsec (default: half a pixel)")


def add_outputs(parser, *, output: str, force: str, record: str) -> None:
    """--output, --force and --record of the commands that solve."""
    parser.add_argument("--output", default=None, help=output)
    parser.add_argument("--force", action="store_true", help=force)
    parser.add_argument("--record", default=None, metavar="PATH.rrd", help=record)
