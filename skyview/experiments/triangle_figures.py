"""The spherical-triangle method's own figures (Cole & Crassidis 2006, section III): its database, the polar
moment's convergence with the recursion depth (Fig. 7), the simulated polar-moment sigma against the
stored bound (Fig. 8), and the area sigma of eqs. 20-24 against a Monte Carlo.

    skyview experiment triangle_figures [--fov-deg 8] [--width 1024] [--mag 6] [--triangles 1000] [--seed 1]
        [--json out.json]

The database is built in a throw-away cache (10-20 s at 8 deg), then loaded again to time it.
"""

from __future__ import annotations

import json
import time

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import load_guide_catalog
from skyview.core.errors import BadInput
from skyview.experiments import throwaway_cache
from skyview.identify import spherical as sph
from skyview.identify.synthetic import add_noise
from skyview.identify.triangle import TriangleMethod
from skyview.identify.triangle_database import MOMENT_SIGMA_REF_RAD, moment_convergence, triangle_counts


def report(fov_deg: float = 8.0, width: int = 1024, mag: float = 6.0, sigma: float = MOMENT_SIGMA_REF_RAD,
           n_triangles: int = 1000, seed: int = 1) -> dict:
    """Database figures (built in a throw-away cache, then loaded), the polar moment's convergence with
    the recursion depth (Fig. 7), its simulated sigma bound (Fig. 8) and the area sigma of eqs. 20-24
    against a Monte Carlo."""
    cat = load_guide_catalog().brighter_than(mag)
    cam = Camera.from_fov(fov_deg, width)
    with throwaway_cache():
        built = TriangleMethod(cat, cam, sigma)
        t0 = time.perf_counter()
        loaded = TriangleMethod(cat, cam, sigma)
        init_s = time.perf_counter() - t0
    info = built.database_info
    counts = triangle_counts(cat, built.max_radius_rad, np.radians(fov_deg))
    out = {"database": {"catalog_stars": len(cat), "triangles": info["triangles"], **counts,
                        "nbytes": info["nbytes"], "file_bytes": info["file_bytes"], "build_s": info["build_s"],
                        "load_s": loaded.database_info["load_s"], "index_s": loaded.database_info["index_s"],
                        "init_s": init_s, "moment_sigma_coef": info["moment_sigma_coef"]}}
    rng = np.random.default_rng(seed)
    tri = built.tri[rng.choice(len(built.tri), size=n_triangles, replace=False)].astype(np.int64)
    conv = moment_convergence(cat.xyz, tri, range(0, 8))
    out["convergence"] = {
        f"{d}->{d + 1}": {"median": float(np.median(np.abs(conv[d + 1] - conv[d]) / conv[d + 1])),
                          "max": float(np.max(np.abs(conv[d + 1] - conv[d]) / conv[d + 1]))} for d in range(1, 7)}
    out["depth_3_vs_7"] = float(np.median(np.abs(conv[3] - conv[7]) / conv[7]))
    I, s = built.moment_sigma_samples.T
    line = built.moment_sigma_coef[0] + built.moment_sigma_coef[1] * I
    out["moment_sigma"] = {"samples": len(I), "line_over_sd_median": float(np.median(line / s)),
                           "line_over_sd_min": float(np.min(line / s))}
    V = cat.xyz[tri[:300]]
    mc = np.array([np.std(sph.area(*(add_noise(np.repeat(V[k, c][None], 300, 0), sigma, rng) for c in range(3))))
                   for k in range(len(V))])
    a, b, c = sph.sides(V[:, 0], V[:, 1], V[:, 2])
    paper = sph.area_sigma_paper(a, b, c, sigma)
    stars = sph.area_sigma_stars(V[:, 0], V[:, 1], V[:, 2], sigma)
    q = [0.05, 0.5, 0.95]
    out["area_sigma_mc"] = {"mc_over_eq24": np.quantile(mc / paper, q).tolist(),
                            "mc_over_stars": np.quantile(mc / stars, q).tolist(), "quantiles": q}
    return out


def add_arguments(ap) -> None:
    ap.add_argument("--fov-deg", type=float, default=8.0, help="full field of view, deg (default 8)")
    ap.add_argument("--width", type=int, default=1024, help="sensor width, pixels (default 1024)")
    ap.add_argument("--mag", type=float, default=6.0, help="catalog limit, Hp (default 6)")
    ap.add_argument("--triangles", type=int, default=1000, help="triangles sampled for Figs. 7-8 (default 1000)")
    ap.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    ap.add_argument("--json", default=None, help="write the figures to this file")


def command(a) -> int:
    if not 1 <= a.triangles <= 100_000:
        raise BadInput("--triangles must be 1..100000")
    if not 0.5 <= a.fov_deg <= 20:
        raise BadInput("--fov-deg must be 0.5..20 (the database grows with the cube of the FOV)")
    out = report(a.fov_deg, a.width, a.mag, n_triangles=a.triangles, seed=a.seed)
    text = json.dumps(out, indent=2)
    if a.json:
        with open(a.json, "w") as fh:
            fh.write(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":  # `python -m skyview.experiments.triangle_figures` is `skyview experiment triangle_figures`
    import sys

    from skyview.cli import main

    raise SystemExit(main(["experiment", "triangle_figures", *sys.argv[1:]]))
