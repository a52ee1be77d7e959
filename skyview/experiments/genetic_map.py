"""The paper's own experiment (Paladugu, Williams & Schoen): the spiral GA on a random star map.

    skyview experiment genetic_map [--runs 100] [--seed 0] [--fov-stars 15 20] [--json out.json]
    skyview experiment genetic_map --verify-sky [--fov-deg 8] [--frames 300] [--attempts 10]
                                        [--false-stars 0] [--outliers 0|1] [--outlier-min-stars N]
                                        [--seed 0]

The second form is the real-sky check of `verify_every_answer` (below): every answer
of the GA on the celestial sphere (vector-level frames) through the shared verification.

The map: 1,000 stars uniform on a 300 x 300 map (-150 to +150), the FOV a 25 x 25 square. The
bore-sight of the image is the origin of the map and its rotation phi is random (the paper's example
uses 60 deg). The image holds the map stars in the FOV square around the origin, in image
coordinates turned by phi, without noise (the paper adds none). As in the paper, the FOV square of a
candidate position is taken in map axes (the distance vector must not depend on the unknown roll, and
the image's stars are those of the map-aligned square): the candidate's stars are the map stars in
the 25 x 25 square around it.

The GA is the one of `skyview.identify.genetic` (Haupt & Haupt's continuous GA) with the paper's
numbers: m = 20 stars in the distance vector (zeros at the beginning when fewer), a first GA of 300 /
150 / 80 over the whole map converging at a cost of 3.0, a spiral GA of 100 / 50 / 30 in a box of
+-Delta = 1.1 x the previous best cost around the best position converging at 1.0, a third (the
paper's statistics criterion) at 0.001882, then the roll GA (120 / 60 / 30, eq. 4) converging at
sum_k min(pi, eps_b / R_k), eps_b = 3 C / n from the final position cost C. A stage that does not
converge within 600 generations restarts the whole search. Mutation 6 %.

--fov-stars LO HI draws maps until the FOV at the origin holds LO..HI stars: the paper reports its
statistics "for situations when the stars in the FOV varied from 15 to 20", while 1,000 stars on the
map put only 6.9 stars in a 25 x 25 FOV on average.

Reported: the bore-sight error (x, y: mean and standard deviation, units) beside the paper's
(x mean -0.0018544, sd 0.0020563; y mean -0.00009245, sd 0.000657), the roll error, generations per
stage, restarts and time.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from skyview.core.errors import BadInput
from skyview.identify.genetic import (
    PAPER_BOX_FACTOR,
    PAPER_DELTAS,
    PAPER_FIRST,
    PAPER_M,
    PAPER_MAX_GENERATIONS,
    PAPER_MUTATION_RATE,
    PAPER_ROLL,
    PAPER_SPIRAL,
    GeneSpace,
    Sizes,
    angle_cost,
    angle_partners,
    distance_cost,
    distance_vector,
    roll_threshold,
    run_ga,
    wrap_angle,
)

MAP_STARS = 1000
MAP_HALF = 150.0
FOV_HALF = 12.5
KD_NEIGHBOURS = 48  # neighbours fetched per position (a 25 x 25 FOV's circumscribed circle holds ~11)
PAPER_STATS = {"x_mean": -0.0018544, "x_sd": 0.0020563, "y_mean": -0.00009245, "y_sd": 0.000657}
PAPER_EXAMPLE = {"stage1_cost": 2.1825, "stage1_xy": (-0.0363, 0.2010), "delta": 2.40075,
                 "stage2_cost": 0.0065, "stage2_xy": (-0.0059, -0.0031), "roll_deg": 60.0001,
                 "roll_cost": 0.0003712}


def make_map(rng: np.random.Generator, n_stars: int = MAP_STARS, half: float = MAP_HALF) -> np.ndarray:
    """(n, 2) stars uniform on [-half, half]^2."""
    return rng.uniform(-half, half, size=(n_stars, 2))


class MapField:
    """The image of one map and the costs of candidate positions (vectorised over the population)."""

    def __init__(self, stars: np.ndarray, phi_true: float, m: int = PAPER_M, fov_half: float = FOV_HALF,
                 center: tuple[float, float] = (0.0, 0.0)):
        self.stars = np.asarray(stars, dtype=np.float64)
        self.tree = cKDTree(self.stars)
        self.m = int(m)
        self.fov_half = float(fov_half)
        R, rows = self.window(np.array([center], dtype=np.float64))
        self.D_a = distance_vector(R, self.m)[0]
        rel = self.stars[rows[0][np.isfinite(R[0])]] - np.asarray(center)
        # image coordinates: the map turned by -phi (so theta_map = theta_image + phi)
        c, s = math.cos(phi_true), math.sin(phi_true)
        img = rel @ np.array([[c, -s], [s, c]])
        self.image = img[np.argsort(np.hypot(img[:, 0], img[:, 1]), kind="stable")][:self.m]
        self.n = len(self.image)
        self.theta_a = _pad_front(np.arctan2(self.image[:, 1], self.image[:, 0]), self.m)

    def window(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P, m) distances (inf: none) and rows of the m stars nearest each position inside its FOV square.

        A cKDTree query of the K nearest stars within the square's circumscribed circle, those outside
        the square dropped; rows whose K-th neighbour is still inside the circle are redone exhaustively.
        """
        P = np.atleast_2d(np.asarray(P, dtype=np.float64))
        K = min(len(self.stars), KD_NEIGHBOURS)
        dist, idx = self.tree.query(P, k=K, distance_upper_bound=self.fov_half * math.sqrt(2.0) + 1e-9)
        dist, idx = dist.reshape(len(P), K), idx.reshape(len(P), K)
        found = np.isfinite(dist)
        rel = self.stars[np.where(found, idx, 0)] - P[:, None, :]
        inside = found & np.all(np.abs(rel) <= self.fov_half, axis=2)
        dist = np.where(inside, dist, np.inf)
        o = np.argsort(dist, axis=1, kind="stable")[:, :self.m]
        R, rows = np.take_along_axis(dist, o, axis=1), np.take_along_axis(idx, o, axis=1)
        if R.shape[1] < self.m:
            pad = self.m - R.shape[1]
            R = np.concatenate([R, np.full((len(P), pad), np.inf)], axis=1)
            rows = np.concatenate([rows, np.full((len(P), pad), -1)], axis=1)
        full = np.flatnonzero(found[:, -1]) if K < len(self.stars) else np.zeros(0, dtype=np.int64)
        if len(full):
            R[full], rows[full] = self._window_exhaustive(P[full])
        return R, rows

    def _window_exhaustive(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self.stars[None, :, :] - P[:, None, :]
        inside = np.all(np.abs(d) <= self.fov_half, axis=2)
        dist = np.where(inside, np.hypot(d[..., 0], d[..., 1]), np.inf)
        k = min(self.m, dist.shape[1])
        part = np.argpartition(dist, k - 1, axis=1)[:, :k]
        dk = np.take_along_axis(dist, part, axis=1)
        o = np.argsort(dk, axis=1, kind="stable")
        R, rows = np.take_along_axis(dk, o, axis=1), np.take_along_axis(part, o, axis=1)
        if k < self.m:
            R = np.concatenate([R, np.full((len(P), self.m - k), np.inf)], axis=1)
            rows = np.concatenate([rows, np.full((len(P), self.m - k), -1)], axis=1)
        return R, rows

    def cost(self, P: np.ndarray) -> np.ndarray:
        """Eq. 3 for candidate positions P (n, 2)."""
        R, _ = self.window(P)
        return distance_cost(self.D_a, distance_vector(R, self.m))

    def roll_problem(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """theta_i (padded like D_i), D_i and the eq. 4 partners at position p."""
        R, rows = self.window(p[None, :])
        D_i = distance_vector(R, self.m)[0]
        real = np.isfinite(R[0])
        rel = self.stars[rows[0][real]] - p
        theta_i = _pad_front(np.arctan2(rel[:, 1], rel[:, 0]), self.m)
        return theta_i, D_i, angle_partners(self.D_a, D_i)


def _pad_front(x: np.ndarray, m: int) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)[:m]
    return np.concatenate([np.zeros(m - len(x)), x])


@dataclass
class MapRun:
    x: float
    y: float
    roll_error_deg: float
    stars_in_fov: int
    costs: list[float]  # final best cost of each position stage
    roll_cost: float
    generations: list[int]  # of the successful attempt, per stage (position stages, then roll)
    restarts: int
    evaluations: int
    time_s: float
    histories: list[list[float]] = field(default_factory=list)
    boxes: list[float] = field(default_factory=list)  # +-Delta of each spiral stage
    failures: dict[str, int] = field(default_factory=dict)  # restarts caused by each stage

    def to_dict(self) -> dict:
        return self.__dict__.copy()


def solve_map(field_: MapField, phi_true: float, rng: np.random.Generator, *, deltas=PAPER_DELTAS,
              box_factor: float = PAPER_BOX_FACTOR, max_generations: int = PAPER_MAX_GENERATIONS,
              mutation_rate: float = PAPER_MUTATION_RATE, max_restarts: int = 200,
              map_half: float = MAP_HALF) -> MapRun | None:
    """The paper's GA chain on one map; None when max_restarts restarts did not converge."""
    t0 = time.perf_counter()
    first, spiral, roll = Sizes(*PAPER_FIRST), Sizes(*PAPER_SPIRAL), Sizes(*PAPER_ROLL)
    evaluations = 0
    failures: dict[str, int] = {}

    def fail(stage: str) -> None:
        failures[stage] = failures.get(stage, 0) + 1

    for attempt in range(max_restarts + 1):
        res = run_ga(field_.cost, GeneSpace((-map_half, -map_half), (map_half, map_half)), first, rng,
                     mutation_rate=mutation_rate, threshold=deltas[0], max_generations=max_generations)
        evaluations += res.evaluations
        if not res.converged:
            fail("stage 1")
            continue
        costs, gens, hists, boxes = [res.cost], [res.generations], [res.history], []
        best = res.genes
        ok = True
        for stage, th in enumerate(deltas[1:], start=2):
            half = box_factor * costs[-1]
            space = GeneSpace((best[0] - half, best[1] - half), (best[0] + half, best[1] + half))
            res = run_ga(field_.cost, space, spiral, rng, mutation_rate=mutation_rate, threshold=th,
                         max_generations=max_generations)
            evaluations += res.evaluations
            if not res.converged:
                fail(f"stage {stage}")
                ok = False
                break
            best = res.genes
            costs.append(res.cost)
            gens.append(res.generations)
            hists.append(res.history)
            boxes.append(half)
        if not ok:
            continue
        theta_i, D_i, partners = field_.roll_problem(best)
        th_roll = roll_threshold(field_.D_a, 0.0, costs[-1])
        res = run_ga(lambda g: angle_cost(field_.theta_a, theta_i, g[:, 0], partners),
                     GeneSpace((0.0,), (2 * np.pi,), periodic=(True,)), roll, rng, mutation_rate=mutation_rate,
                     threshold=th_roll, max_generations=max_generations)
        evaluations += res.evaluations
        if not res.converged:
            fail("roll")
            continue
        err = float(np.degrees(wrap_angle(res.genes[0] - phi_true)))
        return MapRun(x=float(best[0]), y=float(best[1]), roll_error_deg=err, stars_in_fov=field_.n, costs=costs,
                      roll_cost=res.cost, generations=gens + [res.generations], restarts=attempt,
                      evaluations=evaluations, time_s=time.perf_counter() - t0,
                      histories=hists + [res.history], boxes=boxes, failures=failures)
    return None


def reproduce(runs: int = 100, seed: int = 0, fov_stars: tuple[int, int] | None = None,
              example: bool = False, max_restarts: int = 200, deltas: tuple[float, ...] = PAPER_DELTAS,
              progress: bool = True) -> dict:
    """Run the paper's simulation `runs` times; statistics of the bore-sight and roll errors."""
    rng = np.random.default_rng(seed)
    out: list[MapRun] = []
    failed = 0
    maps_drawn = 0
    for k in range(runs):
        while True:
            stars = make_map(rng)
            maps_drawn += 1
            f = MapField(stars, 0.0)
            if fov_stars is None or fov_stars[0] <= f.n <= fov_stars[1]:
                break
        phi = math.radians(60.0) if example else float(rng.uniform(0.0, 2.0 * np.pi))
        f = MapField(stars, phi)
        r = solve_map(f, phi, rng, deltas=deltas, max_restarts=max_restarts)
        if r is None:
            failed += 1
        else:
            out.append(r)
        if progress:
            print(f"run {k + 1}/{runs}: " + ("no convergence" if r is None else
                  f"x {r.x:+.6f} y {r.y:+.6f} roll err {r.roll_error_deg:+.5f} deg, {r.stars_in_fov} stars, "
                  f"restarts {r.restarts} {r.failures}, generations {r.generations}, {r.time_s:.1f} s"), flush=True)
    return summarize(out, failed, runs, seed, fov_stars, maps_drawn, deltas)


def _ms(a) -> dict:
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "mean": float(a.mean()), "sd": float(a.std(ddof=1)) if a.size > 1 else 0.0,
            "median": float(np.median(a)), "max_abs": float(np.abs(a).max())}


def summarize(out: list[MapRun], failed: int, runs: int, seed: int, fov_stars, maps_drawn: int,
              deltas: tuple[float, ...] = PAPER_DELTAS) -> dict:
    gens = np.array([r.generations for r in out]) if out else np.zeros((0, 4))
    return {
        "runs": runs, "converged": len(out), "not_converged": failed, "seed": seed,
        "fov_stars": list(fov_stars) if fov_stars else None, "maps_drawn": maps_drawn, "deltas": list(deltas),
        "x": _ms([r.x for r in out]), "y": _ms([r.y for r in out]),
        "roll_error_deg": _ms([r.roll_error_deg for r in out]),
        "stars_in_fov": _ms([r.stars_in_fov for r in out]),
        "stage_costs": [_ms([r.costs[i] for r in out]) for i in range(len(deltas))] if out else [],
        "restarts_by_stage": {k: int(sum(r.failures.get(k, 0) for r in out))
                              for k in sorted({k for r in out for k in r.failures})},
        "roll_cost": _ms([r.roll_cost for r in out]),
        "generations_per_stage_mean": gens.mean(axis=0).tolist() if len(gens) else [],
        "generations_per_stage_median": np.median(gens, axis=0).tolist() if len(gens) else [],
        "restarts": _ms([r.restarts for r in out]),
        "time_s": _ms([r.time_s for r in out]),
        "paper": PAPER_STATS,
        "example_run": out[0].to_dict() if out else None,
    }


def format_report(s: dict) -> str:
    p = s["paper"]
    lines = [f"Paladugu et al. synthetic map, deltas {s['deltas']}: {s['converged']} of {s['runs']} runs converged "
             f"(seed {s['seed']}"
             + (f", FOV holding {s['fov_stars'][0]}-{s['fov_stars'][1]} stars" if s["fov_stars"] else "") + ")",
             "", "| | mean | sd | paper mean | paper sd |", "|---|---|---|---|---|"]
    if s["converged"]:
        lines += [f"| x (units) | {s['x']['mean']:.3g} | {s['x']['sd']:.3g} | {p['x_mean']:.3g} | {p['x_sd']:.3g} |",
                  f"| y (units) | {s['y']['mean']:.3g} | {s['y']['sd']:.3g} | {p['y_mean']:.3g} | {p['y_sd']:.3g} |",
                  f"| roll error (deg) | {s['roll_error_deg']['mean']:.3g} | {s['roll_error_deg']['sd']:.3g} | "
                  f"(example: 1e-4) | |",
                  "", f"Stars in the FOV: mean {s['stars_in_fov']['mean']:.1f}; restarts: mean "
                  f"{s['restarts']['mean']:.2f}, max {s['restarts']['max_abs']:.0f} "
                  f"(by stage: {s['restarts_by_stage']}); "
                  f"generations per stage (mean) "
                  + ", ".join(f"{g:.0f}" for g in s["generations_per_stage_mean"])
                  + f"; time per run: median {s['time_s']['median']:.2f} s."]
    return "\n".join(lines) + "\n"


def add_arguments(ap) -> None:
    ap.add_argument("--runs", type=int, default=100, help="maps to solve (default 100)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ap.add_argument("--fov-stars", type=int, nargs=2, metavar=("LO", "HI"), default=None,
                    help="only maps whose FOV at the origin holds LO..HI stars")
    ap.add_argument("--example", action="store_true", help="roll 60 deg as in the paper's example")
    ap.add_argument("--max-restarts", type=int, default=200, help="restarts of the whole search per map (default 200)")
    ap.add_argument("--deltas", type=float, nargs="+", default=list(PAPER_DELTAS),
                    help="convergence costs of the position GAs (default 3.0 1.0 0.001882)")
    ap.add_argument("--json", default=None, help="write the statistics here (never overwrites)")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    sky = ap.add_argument_group("--verify-sky: every real-sky GA answer through the shared verification")
    sky.add_argument("--verify-sky", action="store_true", help="run the real-sky check instead of the map")
    sky.add_argument("--fov-deg", type=float, default=8.0, help="full field of view, deg (default 8)")
    sky.add_argument("--frames", type=int, default=300, help="vector-level frames (default 300)")
    sky.add_argument("--attempts", type=int, default=10, help="GA attempts per frame (default 10)")
    sky.add_argument("--false-stars", type=int, default=0, help="false stars per frame (default 0)")
    sky.add_argument("--sigma-urad", type=float, default=87.0, help="per-axis noise, microradians (default 87)")
    sky.add_argument("--outliers", type=int, default=None, choices=(0, 1),
                     help="eq. 3 forgives one star (default: the improved variant's, from 10 stars)")
    sky.add_argument("--outlier-min-stars", type=int, default=None,
                     help="stars from which --outliers 1 applies (at least 3)")


def command(a) -> int:
    if a.verify_sky:
        if a.frames < 1 or a.attempts < 1 or a.false_stars < 0 or not a.sigma_urad > 0:
            raise BadInput("--frames and --attempts must be >= 1, --false-stars >= 0, --sigma-urad > 0")
        if a.outlier_min_stars is not None and a.outlier_min_stars < 3:
            raise BadInput("--outlier-min-stars must be at least 3")
        extra = {k: v for k, v in (("outliers", a.outliers), ("outlier_min_stars", a.outlier_min_stars))
                 if v is not None}
        print(json.dumps(verify_every_answer(a.fov_deg, a.frames, a.attempts, a.false_stars, a.sigma_urad * 1e-6,
                                             seed=a.seed, **extra)))
        return 0
    if a.runs < 1:
        raise BadInput("--runs must be at least 1")
    if a.fov_stars and not (0 <= a.fov_stars[0] <= a.fov_stars[1]):
        raise BadInput("--fov-stars needs 0 <= LO <= HI")
    if any(d <= 0 for d in a.deltas):
        raise BadInput("--deltas must be positive")
    path = Path(a.json) if a.json else None
    if path is not None and path.exists():
        raise BadInput(f"{path} exists: not overwritten")
    s = reproduce(a.runs, a.seed, tuple(a.fov_stars) if a.fov_stars else None, a.example, a.max_restarts,
                  tuple(a.deltas), progress=not a.quiet)
    print(format_report(s))
    if path is not None:
        path.write_text(json.dumps(s, indent=1))
    return 0


def verify_every_answer(fov_deg: float = 8.0, frames: int = 300, attempts: int = 10, false_stars: int = 0,
                        sigma_rad: float = 87e-6, mag_limit: float = 6.0, seed: int = 0,
                        **params) -> dict:
    """Vector-level check of the guard: random attitudes (Cole & Crassidis frames), `attempts` GA
    attempts per frame with the improved parameters (and `params`), EVERY answer sent to the shared
    verification (until one passes, counting hypotheses as identify does), each scored against the
    truth. Returns the tally: answers, wrong answers, wrong answers that passed, right ones passed and
    rejected."""
    from skyview.core.attitude import random_attitudes
    from skyview.core.camera import Camera
    from skyview.core.catalog import load_guide_catalog
    from skyview.identify.genetic import IMPROVED_PARAMS, GeneticMethod
    from skyview.identify.synthetic import synthetic_frame
    from skyview.identify.verify import match_radius, verify

    cat = load_guide_catalog().brighter_than(mag_limit)
    cam = Camera.from_fov(fov_deg, 1024)
    g = GeneticMethod(cat, cam, sigma_rad, **{**IMPROVED_PARAMS, "max_restarts": attempts - 1, **params})
    rng = np.random.default_rng(seed)
    r = match_radius(sigma_rad, g.radius_sigmas)
    tally = {"frames": 0, "answers": 0, "wrong_answers": 0, "wrong_passed": 0, "right_passed": 0,
             "right_rejected": 0, "time_s": 0.0}
    t0 = time.perf_counter()
    for t in range(frames):
        R = random_attitudes(1, rng)[0]
        f = synthetic_frame(cat, cam, R, sigma_rad, rng, false_stars=false_stars)
        V = f.obs.vectors
        if len(V) < 3 or g._field(V, f.obs.brightness, sigma_rad).n < g.min_stars:
            continue
        tally["frames"] += 1
        n_hyp = 0
        for k in range(attempts):
            att = g._attempt(V, f.obs.brightness, sigma_rad, t, k)
            if att.outcome != "answer":
                continue
            hyp, n_pair = g._hypothesis(V, att.matches, r)
            if hyp is None:
                continue
            n_hyp += n_pair
            ver = verify(V, hyp, cat, cam, sigma_rad, n_hypotheses=n_hyp, radius_rad=r)
            right = f.all_right(hyp)
            tally["answers"] += 1
            if not right:
                tally["wrong_answers"] += 1
                tally["wrong_passed"] += int(ver.passed)
            elif ver.passed:
                tally["right_passed"] += 1
            else:
                tally["right_rejected"] += 1
            if ver.passed:
                break
    tally["time_s"] = time.perf_counter() - t0
    return tally


if __name__ == "__main__":  # `python -m skyview.experiments.genetic_map` is `skyview experiment genetic_map`
    import sys

    from skyview.cli import main

    raise SystemExit(main(["experiment", "genetic_map", *sys.argv[1:]]))
