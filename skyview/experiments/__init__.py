"""Experiments: a paper's own experiment reproduced, or a method measured outside the bench.

Each module is reachable as `skyview experiment NAME [OPTIONS]` and as `python -m skyview.experiments.NAME`,
with the same options and one-line errors (exit code 2). A module has `add_arguments(parser)`,
`command(args) -> int` (the exit code) and a `__main__` block that runs `skyview experiment NAME`; to add
one, write the module and add a line to EXPERIMENTS. Experiments may import anything in skyview; nothing in skyview.identify imports them.
"""

from __future__ import annotations

import contextlib
import os
import tempfile

EXPERIMENTS = {  # name -> one line for `skyview experiment --help`
    "ellipticity_sweep": "Sun et al. 2017's full-sky sweep of the ellipticity method (section 3.3, Table 3)",
    "genetic_map": "Paladugu et al.'s spiral GA on its random star map; --verify-sky: every real-sky answer "
                   "verified",
    "measure": "a method on vector-level frames (no images): Cole & Crassidis section IV's quick check",
    "triangle_figures": "Cole & Crassidis' triangle database, polar-moment convergence and sigma bounds (Figs. 7-8)",
}


@contextlib.contextmanager
def throwaway_cache():
    """SKYVIEW_CACHE pointed at a temporary folder for the block (a database built to be timed, then
    thrown away), restored after it."""
    old = os.environ.get("SKYVIEW_CACHE")
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["SKYVIEW_CACHE"] = tmp
        try:
            yield tmp
        finally:
            if old is None:
                os.environ.pop("SKYVIEW_CACHE", None)
            else:
                os.environ["SKYVIEW_CACHE"] = old
