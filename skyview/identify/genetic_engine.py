"""The continuous genetic algorithm of Haupt & Haupt (Practical Genetic Algorithms, ch. 3), the engine
of `skyview.identify.genetic` and `skyview.experiments.genetic_map`: no sky, no star, no step record.

    Sizes       initial random chromosomes, steady-state population, survivors (checked)
    GeneSpace   where the genes live: a box per gene, periodic genes (RA, roll), sine genes (Dec)
    run_ga      selection (rank weighting), crossover (one blended gene, the rest swapped), mutation
                (random genes of all but the best), the generation loop with its convergence, stall
                and stop tests; only new or changed chromosomes are evaluated
    GAResult    the best chromosome, its cost, the history, the final population

The method module keeps the paper's encoding (genes -> sky directions) and fitness (eqs. 3 and 4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from skyview.core.errors import BadInput


@dataclass(frozen=True)
class Sizes:
    """Population sizes of one GA: initial random chromosomes, steady-state population, survivors."""

    initial: int
    population: int
    survivors: int

    def __post_init__(self):
        if not (2 <= self.survivors < self.population <= self.initial):
            raise BadInput(f"GA sizes need 2 <= survivors < population <= initial, got {self.initial} / "
                           f"{self.population} / {self.survivors}")


@dataclass(frozen=True)
class GeneSpace:
    """Where the genes live: a box [lo, hi] per gene; periodic genes wrap (RA, roll); `sine` genes are
    latitudes sampled uniformly in sin (uniform on the sphere)."""

    lo: tuple[float, ...]
    hi: tuple[float, ...]
    periodic: tuple[bool, ...] = ()
    sine: tuple[bool, ...] = ()

    @property
    def d(self) -> int:
        return len(self.lo)

    def _flag(self, flags, j) -> bool:
        return bool(flags[j]) if len(flags) > j else False

    def sample_gene(self, j: int, n: int, rng: np.random.Generator) -> np.ndarray:
        lo, hi = self.lo[j], self.hi[j]
        if self._flag(self.sine, j):
            return np.arcsin(rng.uniform(np.sin(lo), np.sin(hi), size=n))
        return rng.uniform(lo, hi, size=n)

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return np.stack([self.sample_gene(j, n, rng) for j in range(self.d)], axis=1)

    def blend(self, a: np.ndarray, b: np.ndarray, beta: np.ndarray, j: np.ndarray) -> np.ndarray:
        """a - beta (a - b) for gene j of each pair (the shorter way round for periodic genes)."""
        diff = a - b
        if not any(self.periodic):
            return a - beta * diff
        per = np.array([self._flag(self.periodic, k) for k in range(self.d)])[j]
        lo = np.asarray(self.lo)[j]
        span = (np.asarray(self.hi) - np.asarray(self.lo))[j]
        diff = np.where(per, (diff + span / 2) % span - span / 2, diff)
        out = a - beta * diff
        return np.where(per, lo + (out - lo) % span, out)


@dataclass
class GAResult:
    genes: np.ndarray  # the best chromosome
    cost: float
    converged: bool
    generations: int
    evaluations: int
    history: list[float]  # best cost after the initial population (index 0) and each generation
    population: np.ndarray  # final population, best first
    costs: np.ndarray
    stalled: bool = False


def run_ga(cost: Callable[[np.ndarray], np.ndarray], space: GeneSpace, sizes: Sizes, rng: np.random.Generator, *,
           mutation_rate: float, threshold: float, max_generations: int, stall_generations: int | None = None,
           initial: np.ndarray | None = None, stop: Callable[[], bool] | None = None,
           on_generation: Callable[[int, np.ndarray, np.ndarray, int], None] | None = None) -> GAResult:
    """Minimise `cost` (population (P, d) -> (P,)) with Haupt & Haupt's continuous GA.

    The initial `sizes.initial` random chromosomes (or the given `initial` ones) are evaluated and the
    best `sizes.population` kept. Each generation the best `sizes.survivors` survive; the rest of the
    population are offspring of pairs drawn by rank weighting (P_n = (N_keep - n + 1) / sum); a
    pair's crossover gene is blended with a random beta and the genes after it are swapped; then
    ceil(mutation_rate x (population - 1) x genes) genes of all but the best chromosome (drawn with
    replacement, as Haupt's code) are replaced by random values. Only new or changed chromosomes are
    evaluated. Converged when the best cost is <= threshold (checked after the initial population and
    after every generation). stall_generations: give up when the best cost has not improved for that
    many generations. stop(): checked every generation, True abandons the run (not converged).
    on_generation(g, population, costs, evaluations) sees every generation, best first.
    """
    d = space.d
    pop = space.sample(sizes.initial, rng) if initial is None else np.asarray(initial, dtype=np.float64)
    c = np.asarray(cost(pop), dtype=np.float64)
    evaluations = len(pop)
    order = np.argsort(c, kind="stable")[:sizes.population]
    pop, c = pop[order], c[order]
    history = [float(c[0])]
    if on_generation is not None:
        on_generation(0, pop, c, evaluations)
    keep = sizes.survivors
    n_off = sizes.population - keep
    n_pairs = (n_off + 1) // 2
    ranks = np.arange(1, keep + 1)
    cdf = np.cumsum((keep - ranks + 1) / np.sum(ranks))
    cdf[-1] = 1.0
    n_mut = int(math.ceil(mutation_rate * (sizes.population - 1) * d))
    rows = np.arange(n_pairs)
    gene_index = np.arange(d)[None, :]
    gen = 0
    best_at = 0
    stalled = False
    while c[0] > threshold and gen < max_generations:
        if stall_generations is not None and gen - best_at >= stall_generations:
            stalled = True
            break
        if stop is not None and stop():
            break
        gen += 1
        u = rng.random((2, n_pairs))
        mom, dad = pop[np.searchsorted(cdf, u[0])], pop[np.searchsorted(cdf, u[1])]
        alpha = rng.integers(0, d, size=n_pairs) if d > 1 else np.zeros(n_pairs, dtype=np.int64)
        beta = rng.random(n_pairs)
        after = gene_index > alpha[:, None]
        k1 = np.where(after, dad, mom)
        k2 = np.where(after, mom, dad)
        ma_, da_ = mom[rows, alpha], dad[rows, alpha]
        k1[rows, alpha] = space.blend(ma_, da_, beta, alpha)
        k2[rows, alpha] = space.blend(da_, ma_, -beta, alpha)  # d + beta (m - d)
        pop = np.concatenate([pop[:keep], k1, k2[:n_off - n_pairs]])
        changed = np.zeros(sizes.population, dtype=bool)
        changed[keep:] = True
        if n_mut:
            mr = rng.integers(1, sizes.population, size=n_mut)
            mg = rng.integers(0, d, size=n_mut) if d > 1 else np.zeros(n_mut, dtype=np.int64)
            for j in range(d):
                sel = mr[mg == j]
                if len(sel):
                    pop[sel, j] = space.sample_gene(j, len(sel), rng)
            changed[mr] = True
        todo = np.flatnonzero(changed)
        c = c.copy()
        c[todo] = cost(pop[todo])
        evaluations += len(todo)
        order = np.argsort(c, kind="stable")
        pop, c = pop[order], c[order]
        if c[0] < history[-1]:
            best_at = gen
        history.append(float(c[0]))
        if on_generation is not None:
            on_generation(gen, pop, c, evaluations)
    return GAResult(genes=pop[0].copy(), cost=float(c[0]), converged=bool(c[0] <= threshold), generations=gen,
                    evaluations=evaluations, history=history, population=pop, costs=c, stalled=stalled)
