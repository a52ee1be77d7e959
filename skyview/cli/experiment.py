"""`skyview experiment NAME [OPTIONS]`: the experiments of skyview/experiments/ (a paper's own experiment,
a method's quick measurement), each also `python -m skyview.experiments.NAME`."""

from __future__ import annotations

import argparse
import importlib

from skyview.cli.common import Parser


def cmd_experiment(a) -> int:
    module = importlib.import_module(f"skyview.experiments.{a.name}")
    parser = Parser(prog=f"skyview experiment {a.name}", description=module.__doc__,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    module.add_arguments(parser)
    return module.command(parser.parse_args(a.args))


def add_parsers(sub) -> None:
    from skyview.experiments import EXPERIMENTS

    listing = "\n".join(f"  {name:<18} {line}" for name, line in EXPERIMENTS.items())
    e = sub.add_parser("experiment", help="run an experiment: a paper's own experiment or a method's quick "
                                          "measurement (skyview/experiments/)",
                       description=f"Experiments (each also 'python -m skyview.experiments.NAME'):\n{listing}\n\n"
                                   f"'skyview experiment NAME --help' shows an experiment's options.",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    e.add_argument("name", choices=tuple(EXPERIMENTS), metavar="NAME",
                   help=f"the experiment: {', '.join(EXPERIMENTS)}")
    e.add_argument("args", nargs=argparse.REMAINDER, metavar="...", help="the experiment's options")
    e.set_defaults(func=cmd_experiment)
