"""`skyview coverage`: a method's sky coverage map, swept on Dask (skyview.bench.coverage, docs/coverage.md)."""

from __future__ import annotations

import json

from skyview.cli.common import EXIT_SOLVED, add_method, add_variant, float_arg
from skyview.core.errors import BadInput


def cmd_coverage(a) -> int:
    from skyview.bench.coverage import CoverageConfig
    from skyview.bench.coverage_sweep import run_coverage

    cfg = CoverageConfig(a.method, a.variant, fov_deg=a.fov_deg, mag_limit=a.mag_limit, nside=a.nside,
                         rolls=a.rolls, grid=a.grid, width=a.width, noise_urad=a.noise_urad, seed=a.seed,
                         chunk=a.chunk, max_stars=a.max_stars, sample=a.sample, frames=a.frames).checked()
    if not (1 <= a.workers <= 256):
        raise BadInput("--workers must be between 1 and 256")
    out = a.out or (f"coverage-results/{cfg.method}-{cfg.variant}-{cfg.fov_deg:g}deg-hp{cfg.mag_limit:g}-"
                    + (f"nside{cfg.nside}x{cfg.rolls}" if cfg.grid == "healpix" else "sun")
                    + (f"-sample{cfg.sample}" if cfg.sample is not None else ""))
    s = run_coverage(cfg, out, scheduler=a.scheduler, n_workers=a.workers, processes=not a.threads,
                     progress=not a.quiet)
    if a.json:
        print(json.dumps(s))
    else:
        from skyview.bench.coverage_map import format_markdown

        print(format_markdown(s), end="")
        print(f"wrote {out}/coverage.json, coverage.md, coverage.png, coverage.rrd")
    return EXIT_SOLVED


def add_parsers(sub) -> None:
    from skyview.bench.coverage import DEFAULT_CHUNK, DEFAULT_NOISE_PX, GRIDS, SEQUENCE_FRAMES

    c = sub.add_parser("coverage", help="sky coverage map of a method: sweep boresights on an equal-area grid "
                                        "(Dask; resumable)",
                       description="Sweeps boresight directions on an equal-area HEALPix grid (or Sun et al.'s "
                                   "grid), several rolls each, at vector level; records stars in the field and "
                                   "solved / inconclusive / wrong per orientation. Runs on a local Dask cluster "
                                   "(or --scheduler ADDRESS); results stream to DIR/chunks, so running the same "
                                   "command again resumes. Writes coverage.json, .md, .png (Mollweide) and .rrd.")
    add_method(c, None, "identification method: {methods}", required=True)
    add_variant(c)
    c.add_argument("--fov-deg", type=float_arg, required=True, help="horizontal full field of view, deg")
    c.add_argument("--mag-limit", type=float_arg, required=True, help="faintest catalog star seen, Hp")
    c.add_argument("--nside", type=int, default=8, help="HEALPix nside: 12 nside^2 directions (default 8: 768)")
    c.add_argument("--rolls", type=int, default=2, help="roll angles per direction (default 2)")
    c.add_argument("--grid", choices=GRIDS, default="healpix",
                   help="healpix (default) or sun: Sun et al.'s RA 1 deg x Dec 0.5 deg grid, roll 0 (128,877)")
    c.add_argument("--width", type=int, default=1024, help="sensor width in pixels (square sensor; default 1024)")
    c.add_argument("--noise-urad", type=float_arg, default=None,
                   help=f"direction noise per axis, microradians (default {DEFAULT_NOISE_PX} pixel)")
    c.add_argument("--max-stars", type=int, default=40, help="brightest stars given to the identifier (default 40)")
    c.add_argument("--seed", type=int, default=0, help="random seed (rolls, noise, --sample; default 0)")
    c.add_argument("--sample", type=int, default=None, metavar="N",
                   help="sweep a seeded random N of the grid's orientations (e.g. of Sun et al.'s 128,877)")
    c.add_argument("--frames", type=int, default=None,
                   help=f"frames per orientation for a sequence method (stochastic; default {SEQUENCE_FRAMES}): "
                        "a sequence turning FOV/3 per frame about the camera y axis")
    c.add_argument("--chunk", type=int, default=DEFAULT_CHUNK,
                   help=f"orientations per Dask task (default {DEFAULT_CHUNK})")
    c.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="Dask scheduler address (tcp://host:8786); default: a local cluster on this machine; "
                        "'inline': this process only")
    c.add_argument("--workers", type=int, default=2, help="local cluster: worker processes (default 2)")
    c.add_argument("--threads", action="store_true", help="local cluster: thread workers instead of processes")
    c.add_argument("--out", default=None, metavar="DIR",
                   help="folder for the results (default coverage-results/METHOD-VARIANT-FOV-MAG-GRID)")
    c.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    c.add_argument("--quiet", action="store_true", help="no progress line")
    c.set_defaults(func=cmd_coverage)
