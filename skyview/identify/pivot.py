"""What the two pivoting methods of Cole & Crassidis (angle and triangle) share.

- `PivotParams`: their common parameters (the bound beta, the pivot limit, the candidate cap, the
  order of the patterns, the pattern stars, the pivoting rule, backtracking) and the checks of each;
- `Chain`: the outcome of one pivoting chain (unique / empty / ambiguous, its hypotheses, its
  suspects, its figures);
- `Restarts`: the backtracking driver. The first chain uses every star; a chain that ends empty or
  whose hypothesis fails verification names suspect stars, and each suspect gives a restart without
  it (at most max_dropped stars dropped at once, each set of dropped stars once, never fewer than 3
  pattern stars left), at most max_restarts restarts. The angle method restarts in queue order, the
  triangle method passes its blame-based pick;
- `PivotMethod`: the template's hooks they share (min_stars = 3, the failure reason that numbers the
  chains) and the choice among hypotheses that differ only by unresolved close pairs;
- the array helpers both joins use (`by_star`, `pair_indices`).
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from skyview.core.attitude import svd_attitude
from skyview.core.errors import BadInput
from skyview.identify.base import Hypothesis, Identifier, Search, Step
from skyview.identify.params import MethodParams
from skyview.identify.verify import angular_distance

ORDERS = ("largest", "fewest")
# the paper's pairwise list pruning: a common star anywhere ("lists") or on the shared observed
# star(s) ("shared-star"); beyond the paper: full assignments joined on the shared star(s) ("join")
PIVOTINGS = ("shared-star", "lists", "join")
MAX_EQUIVALENT = 16  # at most this many hypotheses are compared for unresolved close pairs
_INT16_MAX = int(np.iinfo(np.int16).max)  # `by_star`'s radix-sortable keys fit below it


@dataclass(frozen=True)
class PivotParams(MethodParams):
    """The parameters the angle and triangle methods share (each module's docstring explains them)."""

    beta: float = 3.0
    max_pivots: int | None = 9
    max_candidates: int = 10_000
    order: str = "largest"
    backtrack: bool = False
    max_restarts: int = 10
    max_dropped: int = 1
    max_stars: int | None = None
    pivoting: str = "shared-star"
    kvector_fit: str = "line"

    def __post_init__(self):
        if not (np.isfinite(self.beta) and self.beta > 0):
            raise BadInput(f"beta must be positive, not {self.beta!r}")
        if self.max_pivots is not None and int(self.max_pivots) < 0:
            raise BadInput("max_pivots must be >= 0 or None (unlimited)")
        if int(self.max_candidates) < 1:
            raise BadInput("max_candidates must be at least 1")
        if self.order not in ORDERS:
            raise BadInput(f"unknown order {self.order!r}: choose from {', '.join(ORDERS)}")
        if self.max_stars is not None and int(self.max_stars) < 3:
            raise BadInput("max_stars must be at least 3 or None (all)")
        if self.pivoting not in PIVOTINGS:
            raise BadInput(f"unknown pivoting {self.pivoting!r}: choose from {', '.join(PIVOTINGS)}")
        super().__post_init__()
        if self.kvector_fit not in ("line", "parabola"):
            raise BadInput("kvector_fit must be 'line' or 'parabola'")
        if int(self.max_restarts) < 0 or int(self.max_dropped) < 0:
            raise BadInput("max_restarts and max_dropped must be >= 0")


def next_by_priority(mask: np.ndarray, priority: np.ndarray) -> int:
    """The pattern of highest priority (lowest rank) among `mask`, or -1 when none is left."""
    idx = mask.nonzero()[0]  # the methods, not numpy's Python wrappers (np.flatnonzero, np.argmin): ~3 us
    return int(idx[priority[idx].argmin()]) if len(idx) else -1


def take_pattern(done: np.ndarray, priority: np.ndarray, too_many, skip, among: np.ndarray | None = None) -> int:
    """The next pattern of a chain: the highest-priority one (`among` those allowed, default all) not `done`
    whose candidates are not `too_many(k)` (those are marked done and `skip(k)` records them); -1 when none
    is left. Marks the one taken done."""
    while True:
        k = next_by_priority(~done if among is None else among & ~done, priority)
        if k < 0:
            return -1
        done[k] = True
        if not too_many(k):
            return k
        skip(k)


def uses_any(excluded: frozenset, n: int, *stars: np.ndarray) -> np.ndarray:
    """Which patterns (angles, triangles: their observed stars in the arrays `stars`, of n observed
    stars) use an excluded star: the ones a chain leaves out from the start."""
    out = np.zeros(len(stars[0]), dtype=bool)
    if excluded:
        ex = np.zeros(n, dtype=bool)
        ex[list(excluded)] = True
        for s in stars:
            out |= ex[s]
    return out


@dataclass
class Chain:
    """One pivoting chain: its outcome ("unique", "empty" or "ambiguous") and why, the observed stars
    it used and its hypotheses H ((n_hypotheses, len(used)) catalog rows), the stars to restart
    without (suspects, most suspect first), the triangle that emptied the set (culprit), its figures
    per pick / pivot, the hypothesis sent to verification (best) and what the paper's method reports
    (answer: the triangle method's one star set left, also when it fits in no vertex order)."""

    outcome: str
    reason: str
    used: list[int]
    H: np.ndarray
    suspects: list[int] = field(default_factory=list)
    culprit: list[int] = field(default_factory=list)
    pivots: int = 0
    candidates: list[int] = field(default_factory=list)
    hypotheses: list[int] = field(default_factory=list)
    best: np.ndarray | None = None
    answer: np.ndarray | None = None


class Restarts:
    """The backtracking driver: iterate it for the stars each chain leaves out (an empty set first),
    and tell it the suspects of a chain that failed (`failed`). Each restart is recorded as a
    'backtrack' step."""

    def __init__(self, steps: list[Step], stars: int, *, backtrack: bool, max_restarts: int, max_dropped: int,
                 pick: Callable[[list[frozenset]], int] | None = None):
        self.steps, self.stars, self.backtrack, self.max_dropped = steps, stars, backtrack, max_dropped
        self.budget = 1 + (max_restarts if backtrack else 0)
        self.pick = pick
        self.queue: list[frozenset] = [frozenset()]
        self.seen = {frozenset()}
        self.chains = 0

    def __iter__(self) -> Iterator[frozenset]:
        while self.queue and self.chains < self.budget:
            excluded = self.queue.pop(self.pick(self.queue) if self.pick is not None else 0)
            if excluded:
                self.steps.append(Step("backtrack", f"restart without observed star(s) {sorted(excluded)}",
                                       observed=sorted(excluded), numbers={"restart": self.chains}))
            self.chains += 1
            yield excluded

    def failed(self, excluded: frozenset, suspects) -> None:
        """Queue a restart without each suspect (with backtracking, while fewer than max_dropped are out)."""
        if not (self.backtrack and len(excluded) < self.max_dropped):
            return
        for s in suspects:
            e2 = excluded | {int(s)}
            if e2 not in self.seen and self.stars - len(e2) >= 3:
                self.seen.add(e2)
                self.queue.append(e2)


class PivotMethod(Identifier):
    """What the angle and triangle methods share on the template: the search (`hypotheses`: chains,
    restarted without suspect stars), the failure reason, the choice among equivalent hypotheses.

    A method writes `_patterns(search)` (its observed patterns: (context, pattern stars)), `_chain` /
    `_chain_lists` (one chain by joins / by the paper's lists), `_proposals` (what a unique chain
    sends to verification) and `_chain_stats` (its figures); `blame_restarts` picks the restart whose
    dropped star the failed patterns point at most (each pattern that emptied the set blames its
    stars, a failed verification its stars by half), otherwise restarts go in queue order.
    """

    min_stars = 3
    blame_restarts = False

    def hypotheses(self, search: Search):
        """Chains (restarted without suspect stars when backtracking); each chain that ends unique
        proposes its hypotheses (`_proposals`); a failed one names its suspects."""
        V, sigma, steps = search.V, search.sigma, search.steps
        ctx, m = self._patterns(search)
        blame = np.zeros(m)
        pick = (lambda queue: int(np.argmax([blame[list(e)].sum() if e else 0.0 for e in queue]))) \
            if self.blame_restarts else None  # ties: first queued
        restarts = Restarts(steps, m, backtrack=self.backtrack, max_restarts=self.max_restarts,
                            max_dropped=self.max_dropped, pick=pick)
        chain_of = self._chain if self.pivoting == "join" else self._chain_lists
        chains: list[Chain] = []
        try:
            for excluded in restarts:
                chain = chain_of(V, excluded, ctx, steps)
                chains.append(chain)
                suspects: list[int] = []
                if chain.outcome == "unique":
                    rows = self._proposals(V, chain, sigma)
                    for row in rows:
                        chain.best = row
                        ver = yield Hypothesis(dict(zip(chain.used, row.tolist())))
                    chain.best = rows[0]  # the paper's answer, when none verified: the first
                    search.reasons.append(f"verification failed: {ver.reason}")
                    suspects = chain.used[::-1]
                    blame[chain.used] += 0.5
                else:
                    search.reasons.append(chain.reason)
                    if chain.outcome == "empty":
                        suspects = chain.suspects
                        blame[chain.culprit] += 1.0
                restarts.failed(excluded, suspects)
        finally:  # also when the search ends at an accepted hypothesis (the generator is closed)
            if chains:
                head, tail = self._chain_stats(ctx, m, chains)
                last = chains[-1]
                search.stats.update({
                    **head,
                    "pivots": last.pivots,
                    "pivots_total": int(sum(c.pivots for c in chains)),
                    "stars_used": len(last.used),
                    "candidates": last.candidates,
                    "hypotheses": last.hypotheses,
                    "chains": len(chains),
                    "verifications": search.verifications,
                    **tail,
                })

    @abstractmethod
    def _patterns(self, search: Search) -> tuple[dict, int]:
        """The observed patterns of the frame and their look-ups (the chains' context), and how many
        stars form them."""

    @abstractmethod
    def _chain(self, V: np.ndarray, excluded: frozenset, ctx: dict, steps: list[Step]) -> Chain:
        """One chain by joins (pivoting="join"), without the `excluded` observed stars."""

    @abstractmethod
    def _chain_lists(self, V: np.ndarray, excluded: frozenset, ctx: dict, steps: list[Step]) -> Chain:
        """One chain by the paper's pairwise list pruning (pivoting="shared-star" / "lists")."""

    def _proposals(self, V: np.ndarray, chain: Chain, sigma: float) -> list[np.ndarray]:
        """What a unique chain sends to verification, in order: the best fit of its hypotheses."""
        return [self._best(V, chain.used, chain.H, sigma)]

    def _chain_stats(self, ctx: dict, m: int, chains: list[Chain]) -> tuple[dict, dict]:
        """The method's own figures, shown before and after the shared ones."""
        return {}, {}

    def configure(self, catalog, camera, sigma_rad: float, params: dict):
        """The template's `configure`, then the shared parameters as numbers of their type."""
        p = super().configure(catalog, camera, sigma_rad, params)
        self.beta = float(p.beta)
        self.max_pivots = None if p.max_pivots is None else int(p.max_pivots)
        self.max_candidates = int(p.max_candidates)
        self.max_stars = None if p.max_stars is None else int(p.max_stars)
        self.backtrack = bool(p.backtrack)
        self.max_restarts = int(p.max_restarts)
        self.max_dropped = int(p.max_dropped)
        self.radius_sigmas = float(p.radius_sigmas)
        return p

    def failure_reason(self, search: Search) -> str:
        """The one chain's reason, or every chain's, numbered."""
        r = search.reasons
        return r[0] if len(r) == 1 else "; ".join(f"chain {k + 1}: {x}" for k, x in enumerate(r))

    def _equivalent(self, H: np.ndarray, tol: float) -> bool:
        """A few hypotheses that put every observed star on catalog stars closer than tol to each other.

        Catalog stars closer than the match radius cannot be told apart at this noise (unresolved
        close pairs): such hypotheses are one pattern. Verification leaves their stars out of the
        reported matches.
        """
        if len(H) < 2 or len(H) > MAX_EQUIVALENT:
            return False
        xyz = self.catalog.xyz
        return bool((angular_distance(xyz[H], xyz[H[:1]]) <= tol).all())

    def _best(self, V: np.ndarray, used: list[int], H: np.ndarray, sigma: float) -> np.ndarray:
        """Among equivalent hypotheses, the one that fits the observed stars best."""
        if len(H) == 1:
            return H[0]
        b = V[used]
        losses = [svd_attitude(b, self.catalog.xyz[h], sigma).loss for h in H]
        return H[int(np.argmin(losses))]


def by_star(cp: np.ndarray, cq: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The candidates grouped by their star on p (catalog rows < m): cq in that order (stable), and
    per catalog star the start and size of its block (= np.searchsorted on the sorted cp, without a
    binary search per hypothesis; the sort is numpy's radix sort on 16-bit keys when they fit). The
    start of an empty block is 0 (its size says there is nothing to read)."""
    key = cp.astype(np.int16) if m <= _INT16_MAX else cp
    order = key.argsort(kind="stable")
    size = np.bincount(cp, minlength=m)
    # each block starts where the sorted keys change: O(len(cp)), where a cumulative sum over all m
    # catalog stars costs ~12 us (numpy's cumsum is not vectorised) for ~1,000 candidates
    ks = key.take(order)  # (take: an index without numpy's index parsing)
    first = (ks[1:] != ks[:-1]).nonzero()[0] + 1
    start = np.zeros(m, dtype=np.int64)
    start[ks.take(first)] = first  # the first block starts at 0
    return cq.take(order), start, size


@lru_cache(maxsize=256)
def pair_indices(n: int) -> tuple[np.ndarray, np.ndarray]:
    """np.triu_indices(n, 1), made once per star count (it costs ~0.2 ms a call), read-only."""
    ii, jj = np.triu_indices(n, 1)
    ii.flags.writeable = False
    jj.flags.writeable = False
    return ii, jj
