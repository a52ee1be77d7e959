"""The angle method with pivoting (Cole & Crassidis 2006, section II).

Database. Every catalog star pair whose separation can appear in one image: the paper uses a
circular 8 deg FOV and keeps all angles <= 8 deg; our sensor is a rectangle, so the database covers
pairs up to the image DIAGONAL (2 x camera.half_diagonal_rad, rounded up on a 5 % grid so that one
database serves every camera below it: the database belongs to the sky, not to one camera). Pairs are sorted by angle and indexed
with a k-vector (`skyview.identify.kvector`). The database is cached on disk
(`skyview.identify.database`); its info reports the pairs within the FOV and the total.

Look-up. A measured angle theta has the bound beta * sigma_p with sigma_p = sqrt(2) sigma (eq. 14)
and beta = 3: the candidates are the catalog pairs with angle in [theta - beta sigma_p,
theta + beta sigma_p], each in both orientations.

Pivoting as printed (pivoting="shared-star", the default, section II-C). The first angle (the largest, or
with order="fewest" the one with the fewest candidates) gives a list of candidate catalog pairs. The
next angle shares an observed star with it; "any angles on either list that do not have a star in
common with at least one angle on the other list are rejected", and the following angle is compared
with the pruned list of the one before it only. The "star in common" is read as the catalog star on
the observed star the two angles share (each list holds its pairs in both orientations): under this
reading the paper's 55 % holds (vector level, 300 attitudes, seed 1, Hp <= 6.2: 55.7 % before
verification); with a common star anywhere (pivoting="lists", the print taken literally) 7 % (16.7 %
at Hp <= 6.0). The chain ends when a list holds one pair (that angle is identified), when no angle
sharing a star with the current one is left, or at the pivot limit. The answer is the two stars of
that angle (with pivoting="lists" the orientation is read from the neighbouring list; when it cannot
be told, both orientations go to verification); every other star is left to verify with.

Pivoting by joins (pivoting="join", beyond the paper, in `IMPROVED_PARAMS`). A hypothesis assigns a
catalog star to every observed star used so far. The first angle
(the largest, or with order="fewest" the one with the fewest candidates: the paper's "ideal"
ordering) gives one hypothesis per oriented candidate pair. Each pivot takes the next angle (largest
/ fewest first) that shares a star with the previous angle and joins it with the hypotheses on the
shared observed star: a hypothesis survives with every oriented candidate whose star on the shared
side is the hypothesis' star; when both stars of the new angle are already assigned (a closed loop)
the pair must be a candidate as it is. A catalog star is never assigned to two observed stars. The
join is vectorised (sort + searchsorted). The chain stops when exactly one hypothesis remains, when
no angle is left, or at the pivot limit (max_pivots = 9); an angle with more than
max_candidates = 10,000 oriented candidates is skipped. Stopping with one hypothesis is not yet an
identification: it goes to the shared verification (`skyview.identify.verify`), and only a verified
hypothesis is reported as identified.

Loop closing (option, default off). With close_loops=True a pivot first takes an angle between two
stars already assigned (closing a triangle: no new star, strong pruning) before adding a star, so the
chain usually ends unique with three stars and leaves the others to verify with; the paper's chain
often consumes every star of a sparse field, and a hypothesis with no star left cannot be verified.

Pattern stars (option, max_stars = 12 in IMPROVED_PARAMS, None in the paper). Only the brightest
max_stars observed stars form the angles the chain pivots on; every star still takes part in the
verification. A 20 deg field at Hp 6 holds ~40 stars (780 angles, each with thousands of catalog
pairs); the twelve brightest give 66 angles and the same identifications (vector level, cole8 and
sun20, with and without a false star).

Speed (beyond the paper, same results). A join groups the candidate pairs by their catalog star on
the shared observed star once (a radix sort and a bincount, `by_star`) and each hypothesis meets
its star's block (no binary search per hypothesis: ~0.1 ms instead of ~2.5 ms for 12,000 candidates
at 20 deg); after the first join only the candidates on the hypotheses' stars are grouped. A closed
loop is tested by the angle between the hypothesis' two catalog stars itself (`_close`: the database
holds every pair up to its range, and its angles are the same numbers). An angle's candidate range is
looked up when a chain first reads it (a frame's chains read a handful of its angles), the next angle
is picked in Python from each star's angles by priority (`_AngleWalk`), and steps record capped
samples (CAP rows, `Hypotheses.sample`), never the whole candidate lists, computed when a sink first
reads them (`LazyStep`).

Backtracking (option, default off as in the paper). When the hypotheses go to zero (a false star or an
angle outside its bound was used) or the unique hypothesis fails verification, the paper's method has
failed. With backtrack=True the chain is restarted without one suspect star: first the star whose
angle emptied the set (the one just added, or the newer of the two in a closed loop), then the other
stars of the chain, newest first; each restart again starts from the largest remaining angle. At
most max_restarts restarts and max_dropped stars dropped at once. Every verification counts in the
Bonferroni factor of the verification statistic, so no wrong attitude gets an easier pass. The
search loop, the restarts and the parameters it shares with the triangle method are in
`skyview.identify.pivot`.

Long (~600 lines, a docstring of 70) on purpose: by the identification template's contract
(`skyview.identify.base`) everything the method is lives in its one module: the paper's description, its
typed parameters, its search as a generator of hypotheses with its steps, and its improved variant; the
shared verification is not here.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache, partial

import numpy as np

from skyview.core.attitude import RAD_TO_ARCSEC
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog
from skyview.core.lru import LRU
from skyview.identify import database
from skyview.identify.base import Search
from skyview.identify.kvector import KVector
from skyview.identify.layers import Hypotheses
from skyview.identify.pivot import Chain, PivotMethod, PivotParams, by_star, pair_indices, take_pattern, uses_any
from skyview.identify.steps import LazyStep, Step
from skyview.identify.verify import angular_distance

CAP = 200  # catalog rows / groups kept in one step
CLOSE_BY_ANGLE = 0.999  # a closing angle below this fraction of the database's range is tested by its angle
DATABASE_VERSION = 1


def build_angle_database(catalog: GuideCatalog, max_sep_rad: float, fit: str = "line") -> dict[str, np.ndarray]:
    """Catalog pairs with separation <= max_sep_rad, sorted by angle, with their k-vector."""
    pairs = catalog.pairs_within(max_sep_rad)
    i, j = pairs[:, 0], pairs[:, 1]
    ang = angular_distance(catalog.xyz[i], catalog.xyz[j])
    keep = ang <= max_sep_rad
    i, j, ang = i[keep], j[keep], ang[keep]
    order = np.lexsort((j, i, ang))
    kv = KVector(ang[order], fit=fit, presorted=True)
    return {"pair_i": i[order].astype(np.int32), "pair_j": j[order].astype(np.int32), **kv.to_arrays()}


def load_pair_database(catalog: GuideCatalog, camera: Camera, kvector_fit: str = "line"
                       ) -> tuple[np.ndarray, np.ndarray, KVector, dict]:
    """The angle database that serves `camera` (pairs up to its diagonal rounded up on the 5 % grid of
    `database.angular_range`), loaded from the cache or built once: (pair_i, pair_j, k-vector, info).

    The angle method and the improved triangle method (which joins its triangles from these pairs)
    share it: one file per catalog and range. info holds the cache's figures, "key" and "max_sep_rad".
    The cached file is memory-mapped, not read through the zip reader: pair_i and pair_j stay its int32
    columns (a method widens the slices it reads: a process reads the few pages its look-ups touch), the
    sorted angles are copied into memory (below).
    """
    max_sep_rad = database.angular_range(2.0 * camera.half_diagonal_rad)
    params = {"max_sep_rad": max_sep_rad, "kvector_fit": kvector_fit, "version": DATABASE_VERSION}
    key = database.make_key("angle", params, catalog, None)
    path = database.database_path(key)
    kept = _LOADED.get(str(path))
    if kept is not None and kept[0] != _stamp(path):  # not the file that was mapped (rebuilt, evicted)
        _LOADED.pop(str(path))
        kept = None
    if kept is not None:
        database.touch(path)  # used: last in the cache's eviction order
        _, pair_i, pair_j, kv, info = kept
        return pair_i, pair_j, kv, {**info, "source": "cache", "load_s": 0.0, "build_s": None}
    # ~48 bytes and ~0.5 us a pair while it is built (the pair list, the angles, the sorted copies, the k-vector)
    n_pairs = database.pairs_estimate(len(catalog), max_sep_rad)
    what = (f"the angle database ({len(catalog):,} stars, pairs up to {np.degrees(max_sep_rad):.1f} deg, "
            f"~{n_pairs / 1e6:.1f} M pairs)")
    arrays, info = database.load_or_build(
        key, lambda: build_angle_database(catalog, max_sep_rad, kvector_fit),
        what=what, estimate_s=0.5e-6 * n_pairs, estimate_bytes=48 * n_pairs, mmap=True)
    info.update(max_sep_rad=max_sep_rad)
    kv = KVector.from_arrays(arrays)
    # the sorted angles are binary-searched for every angle of every frame: copied into the process's
    # memory, where the kernel backs them with huge pages (a 10-24 MB table searched through the file's
    # 4 kB pages misses the TLB at every level: sun20's 66 look-ups ~0.3 ms instead of ~0.1)
    kv.sorted_values = np.array(kv.sorted_values)
    stamp = _stamp(path)
    if info.get("source") == "cache" and stamp is not None:  # (one just built is in memory: not kept)
        _LOADED.put(str(path), (stamp, arrays["pair_i"], arrays["pair_j"], kv, dict(info)))
    return arrays["pair_i"], arrays["pair_j"], kv, info


# the pair databases this process has mapped, by file (the last MAX_LOADED): the solvers of the cameras whose
# diagonals round to one range (a user's photographs at FOVs a few per cent apart) share one map and one copy
# of its sorted angles (8 bytes a pair: ~10 MB for a 20 deg camera at Hp 6.25)
MAX_LOADED = 4
_LOADED = LRU(MAX_LOADED)


def _stamp(path) -> tuple[int, int, int] | None:
    """(device, inode, size) of a database file: a rebuilt one is another file (written aside, then renamed
    over it); None when it is not there."""
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_size


@dataclass(frozen=True)
class AngleParams(PivotParams):
    """The angle method's parameters (the paper's defaults; the module docstring explains each)."""

    close_loops: bool = False


PAPER = AngleParams()
# These options (not in the paper) identify 80.7 % of random 8 deg / Hp 6.0 fields instead of 65.7 %,
# and 75 % instead of 27 % with a false star, never wrongly (vector level, 300 attitudes, seed 1): join
# full assignments on the shared star, close triangles first so that stars are left to verify with,
# and restart without a suspect star when a chain fails.
IMPROVED = replace(PAPER, pivoting="join", close_loops=True, backtrack=True, max_stars=12)
IMPROVED_PARAMS = IMPROVED.changed()


class AngleMethod(PivotMethod):
    """Cole & Crassidis' angle method with pivoting, ending in the shared verification."""

    name = "angle"
    paper_scenario = "cole8"
    title = "the angle method"
    Params = AngleParams
    improved_params = IMPROVED_PARAMS

    def __init__(self, catalog: GuideCatalog, camera: Camera, sigma_rad: float, **params):
        p = self.configure(catalog, camera, sigma_rad, params)
        self.close_loops = bool(p.close_loops)

        # the database belongs to the sky: pairs up to the diagonal rounded up on a 5 % grid, so one
        # database serves every camera whose diagonal is below it
        self.pair_i, self.pair_j, self.kv, info = load_pair_database(catalog, camera, p.kvector_fit)
        self.max_sep_rad = info["max_sep_rad"]
        self.database_key = info["key"]
        fov = np.radians(camera.fov_deg)
        n_fov = int(np.searchsorted(self.kv.sorted_values, fov, side="right"))
        info.update(pairs=len(self.pair_i), pairs_within_fov=n_fov, fov_deg=float(camera.fov_deg),
                    max_sep_deg=float(np.degrees(self.max_sep_rad)), catalog_stars=len(catalog))
        self.database_info = info

    @property
    def n_patterns(self) -> int:
        return len(self.pair_i)

    # ------------------------------------------------------------------ identify (the template's parts)
    def _patterns(self, search: Search) -> tuple[dict, int]:
        """The angles of the pattern stars (the brightest max_stars), their candidate ranges and the
        order the chains take them in."""
        V, sigma = search.V, search.sigma
        m = search.n if self.max_stars is None else min(search.n, self.max_stars)  # the stars that form angles
        ii, jj = pair_indices(m)
        theta = angular_distance(V.take(ii, axis=0), V.take(jj, axis=0))
        bound = self.beta * np.sqrt(2.0) * sigma  # beta sigma_p, sigma_p = sqrt(2) sigma (eq. 14)
        counts = _Ranges(self.kv.sorted_values, theta, bound)
        if self.order == "largest":
            rank = np.argsort(-theta, kind="stable")
        else:  # the order needs every angle's count: one batch look-up
            counts.fill(*self.kv.ranges(theta - bound, theta + bound))
            rank = np.lexsort((-theta, counts.all()))
        priority = np.empty(len(theta), dtype=np.int64)
        priority[rank] = np.arange(len(theta))
        # the join chain picks its angles in Python (`_AngleWalk`): a handful of stars, where a numpy
        # mask over every angle per pivot costs more
        return dict(ii=ii, jj=jj, theta=theta, counts=counts, priority=priority, order=rank.tolist(),
                    pairs=_pair_lists(m), deg=np.degrees(theta).tolist(), bound=bound,
                    bound_arcsec=float(bound * RAD_TO_ARCSEC), tol=2.0 * search.radius), m

    def _proposals(self, V: np.ndarray, chain: Chain, sigma: float) -> list[np.ndarray]:
        """join: the best fit of equivalent hypotheses; lists: each orientation the lists left open."""
        return [self._best(V, chain.used, chain.H, sigma)] if self.pivoting == "join" else list(chain.H)

    def _chain_stats(self, ctx: dict, m: int, chains: list[Chain]) -> tuple[dict, dict]:
        first = chains[0]
        return {"pattern_stars": m}, {
            "bound_rad": float(ctx["bound"]),
            "first_chain": {"outcome": first.outcome,
                            "matches": ({int(o): int(c) for o, c in zip(first.used, first.best)}
                                        if first.best is not None else {})}}

    # ------------------------------------------------------------------ one pivoting chain
    def _numbers(self, ctx: dict, k: int) -> dict[str, float]:
        return {"angle_deg": ctx["deg"][k], "bound_arcsec": ctx["bound_arcsec"], "candidates": ctx["counts"][k]}

    def _skip(self, ctx: dict, k: int, steps: list[Step]) -> None:
        """Record angle k left out: more than max_candidates candidates."""
        i, j = int(ctx["ii"][k]), int(ctx["jj"][k])
        steps.append(Step("skip", f"skipped angle {i}-{j} ({np.degrees(ctx['theta'][k]):.3f} deg): "
                                  f"{ctx['counts'][k]} candidates > {self.max_candidates}", observed=[i, j],
                          numbers=self._numbers(ctx, k) | {"max_candidates": self.max_candidates}))

    def _chain(self, V: np.ndarray, excluded: frozenset, ctx: dict, steps: list[Step]) -> Chain:
        theta, deg, counts, order = ctx["theta"], ctx["deg"], ctx["counts"], ctx["order"]
        ii, jj = ctx["pairs"][:2]
        bound = ctx["bound"]
        # the angles left out: those done, and those of an excluded star
        done = [a in excluded or b in excluded for a, b in zip(ii, jj)] if excluded else [False] * len(ii)
        candidates: list[int] = []
        hyps: list[int] = []
        angle_numbers = partial(self._numbers, ctx)

        k = -1
        for c in order:  # the first angle: the highest priority whose candidates are not too many
            if not done[c]:
                done[c] = True
                if counts[c] <= self.max_candidates:
                    k = c
                    break
                self._skip(ctx, c, steps)
        if k < 0:
            return Chain("ambiguous", "no angle with at most max_candidates candidates to start from", [],
                         np.zeros((0, 0), dtype=np.int64))
        a, b = ii[k], jj[k]
        ci, cj = self._candidates(ctx, k)
        H = _both_orientations(ci, cj)
        used = [a, b]
        candidates.append(int(counts[k]))
        hyps.append(len(H))
        # (note, numbers and layer made when the step is read: of values no later step changes)
        steps.append(LazyStep("pick", note_of=partial(_pick_note, a, b, deg[k], bound, counts[k]),
                              observed=used.copy(), catalog_of=partial(_distinct, H),
                              groups_of=partial(_groups, ci, cj),
                              numbers_of=partial(_merged, angle_numbers, k, {"hypotheses": len(H)}),
                              layers_of=partial(_layer, tuple(used), H)))
        if len(H) == 0:
            return Chain("empty", f"no catalog pair matches the first angle {a}-{b}", used, H,
                          suspects=[b, a], candidates=candidates, hypotheses=hyps)
        prev = (a, b)
        pivots = 0
        walk = None
        while len(H) != 1 and not self._equivalent(H, ctx["tol"]):
            if self.max_pivots is not None and pivots >= self.max_pivots:
                steps.append(Step("stop", f"pivot limit {self.max_pivots} reached with {len(H)} hypotheses",
                                  observed=used.copy(), catalog=_distinct(H), numbers={"hypotheses": len(H)}))
                return Chain("ambiguous", f"{len(H)} hypotheses left after {pivots} pivots (the limit)", used, H,
                              pivots=pivots, candidates=candidates, hypotheses=hyps)
            if walk is None:  # made once a frame, for its first pivot
                walk = ctx.get("walk")
                if walk is None:
                    walk = ctx["walk"] = _AngleWalk(ctx)
            k = walk.next(done, used, prev, self.close_loops)
            if k < 0:
                steps.append(Step("stop", f"no angle left to pivot to; {len(H)} hypotheses",
                                  observed=used.copy(), catalog=_distinct(H), numbers={"hypotheses": len(H)}))
                return Chain("ambiguous", f"{len(H)} hypotheses left and no angle to pivot to", used, H,
                              pivots=pivots, candidates=candidates, hypotheses=hyps)
            done[k] = True
            p, q = ii[k], jj[k]
            if counts[k] > self.max_candidates:
                self._skip(ctx, k, steps)
                continue
            ci, cj = self._candidates(ctx, k)
            before = len(H)
            lo, hi = theta[k] - bound, theta[k] + bound
            if p in used and q in used and hi < CLOSE_BY_ANGLE * self.max_sep_rad:
                H, new = _close(H, used.index(p), used.index(q), self.catalog.xyz, lo, hi), None
            else:
                H, used, new = _join(H, used, p, q, ci, cj, len(self.catalog))
            pivots += 1
            candidates.append(int(counts[k]))
            hyps.append(len(H))
            steps.append(LazyStep("pivot", note_of=partial(_pivot_note, p, q, deg[k], counts[k], before, len(H)),
                                  observed=[p, q], catalog_of=partial(_distinct, H),
                                  groups_of=partial(_groups, ci, cj),
                                  numbers_of=partial(_merged, angle_numbers, k, {
                                      "hypotheses_before": before, "hypotheses_after": len(H), "pivot": pivots,
                                      "new_star": -1 if new is None else new}),
                                  layers_of=partial(_layer, tuple(used), H)))
            if len(H) == 0:
                if new is not None:
                    first_suspect = new
                else:  # closed loop: the newer of the two stars first
                    first_suspect = p if used.index(p) > used.index(q) else q
                rest = [s for s in used[::-1] if s != first_suspect]
                return Chain("empty", f"no hypothesis survives angle {p}-{q}", used, H,
                              suspects=[first_suspect] + rest, pivots=pivots, candidates=candidates,
                              hypotheses=hyps)
            prev = (p, q)
        return Chain("unique", "one hypothesis left" if len(H) == 1 else
                      f"{len(H)} hypotheses left that differ only by unresolved close pairs",
                      used, H, pivots=pivots, candidates=candidates, hypotheses=hyps)

    def _chain_lists(self, V: np.ndarray, excluded: frozenset, ctx: dict, steps: list[Step]) -> Chain:
        """The paper's pivoting: candidate lists of consecutive angles pruned against each other.

        A pair of either list survives when it shares a catalog star with at least one pair of the other
        list; the next angle shares an observed star with the current one and meets its pruned list
        only. Ends when a list holds one pair; H holds that angle's orientation(s) over its two stars.
        """
        ii, jj, theta, counts, priority = ctx["ii"], ctx["jj"], ctx["theta"], ctx["counts"], ctx["priority"]
        done = uses_any(excluded, len(V), ii, jj)
        candidates: list[int] = []
        hyps: list[int] = []
        numbers = partial(self._numbers, ctx)

        def next_angle(mask):
            return take_pattern(done, priority, lambda k: counts[k] > self.max_candidates,
                                lambda k: self._skip(ctx, k, steps), among=mask)

        k = next_angle(np.ones(len(theta), dtype=bool))
        if k < 0:
            return Chain("ambiguous", "no angle with at most max_candidates candidates to start from", [],
                          np.zeros((0, 0), dtype=np.int64))
        cur_obs = (int(ii[k]), int(jj[k]))
        cur = np.stack(self._candidates(ctx, k), axis=1)
        oriented = self.pivoting == "shared-star"
        if oriented:  # rows in the order of cur_obs, both orientations
            cur = np.concatenate([cur, cur[:, ::-1]])
        used = list(cur_obs)
        candidates.append(int(counts[k]))
        hyps.append(len(cur))
        steps.append(Step("pick", f"picked angle {cur_obs[0]}-{cur_obs[1]} ({np.degrees(theta[k]):.3f} deg): "
                                  f"{len(cur)} candidate pairs", observed=used.copy(), catalog=_distinct(cur),
                          groups=_groups(cur[:, 0], cur[:, 1]), numbers=numbers(k) | {"pairs": len(cur)},
                          layers=(Hypotheses.sample(list(cur_obs), cur),)))
        if len(cur) == 0:
            return Chain("empty", f"no catalog pair matches the first angle {cur_obs[0]}-{cur_obs[1]}", used,
                          np.zeros((0, 2), dtype=np.int64), suspects=used[::-1], candidates=candidates,
                          hypotheses=hyps)
        prev, prev_obs = None, None
        pivots = 0
        while _n_pairs(cur) != 1 and (prev is None or _n_pairs(prev) != 1):
            if self.max_pivots is not None and pivots >= self.max_pivots:
                steps.append(Step("stop", f"pivot limit {self.max_pivots} reached with {len(cur)} candidate pairs",
                                  observed=list(cur_obs), numbers={"pairs": len(cur)}))
                return Chain("ambiguous", f"{len(cur)} candidate pairs left after {pivots} pivots (the limit)", used,
                              cur, pivots=pivots, candidates=candidates, hypotheses=hyps)
            in_cur = np.zeros(len(V), dtype=bool)
            in_cur[list(cur_obs)] = True
            k = next_angle(in_cur[ii] | in_cur[jj])
            if k < 0:
                steps.append(Step("stop", f"no angle sharing a star with angle {cur_obs[0]}-{cur_obs[1]} is left; "
                                          f"{len(cur)} candidate pairs", observed=list(cur_obs),
                                  numbers={"pairs": len(cur)}))
                return Chain("ambiguous", f"{len(cur)} candidate pairs left and no angle to pivot to", used, cur,
                              pivots=pivots, candidates=candidates, hypotheses=hyps)
            new = np.stack(self._candidates(ctx, k), axis=1)
            new_obs = (int(ii[k]), int(jj[k]))
            before = len(cur)
            if oriented:  # the common catalog star must sit on the observed star the two angles share
                new = np.concatenate([new, new[:, ::-1]])
                s = (set(cur_obs) & set(new_obs)).pop()
                cs, ns = cur[:, cur_obs.index(s)], new[:, new_obs.index(s)]
                prev, prev_obs = cur[np.isin(cs, ns)], cur_obs
                cur, cur_obs = new[np.isin(ns, cs)], new_obs
            else:
                prev, prev_obs = cur[np.isin(cur, new).any(axis=1)], cur_obs
                cur, cur_obs = new[np.isin(new, cur).any(axis=1)], new_obs
            added = [s for s in new_obs if s not in used]
            used += added
            pivots += 1
            candidates.append(int(counts[k]))
            hyps.append(len(cur))
            steps.append(Step("pivot", f"pivoted to angle {new_obs[0]}-{new_obs[1]} ({np.degrees(theta[k]):.3f} deg): "
                                       f"{len(new)} candidate pairs, {len(cur)} share a star with the previous list "
                                       f"({before} -> {len(prev)})", observed=list(new_obs), catalog=_distinct(cur),
                              groups=_groups(cur[:, 0], cur[:, 1]),
                              numbers=numbers(k) | {"pairs": len(cur), "previous_before": before,
                                                    "previous_after": len(prev), "pivot": pivots},
                              layers=(Hypotheses.sample(list(cur_obs), cur),)))
            if len(cur) == 0:
                rest = [s for s in used[::-1] if s not in added]
                return Chain("empty", f"no candidate pair of angle {new_obs[0]}-{new_obs[1]} shares a star with the "
                                       "previous list", used, cur, suspects=added + rest, pivots=pivots,
                              candidates=candidates, hypotheses=hyps)
        one, one_obs, other, other_obs = ((cur, cur_obs, prev, prev_obs) if _n_pairs(cur) == 1
                                          else (prev, prev_obs, cur, cur_obs))
        H = one if oriented else _orient_pair(one[0], one_obs, other, other_obs)
        return Chain("unique", f"one candidate pair left for angle {one_obs[0]}-{one_obs[1]}", list(one_obs), H,
                      pivots=pivots, candidates=candidates, hypotheses=hyps)

    def _candidates(self, ctx: dict, k: int) -> tuple[np.ndarray, np.ndarray]:
        s, e = ctx["counts"].span(k)
        return np.array(self.pair_i[s:e], dtype=np.int64), np.array(self.pair_j[s:e], dtype=np.int64)


class _Ranges:
    """The candidate range of each angle of a frame (the slice [start, stop) of the database's sorted
    angles within theta +- bound) and its count of oriented candidates (`counts[k]` = 2 (stop - start)).

    A range is looked up when a chain first reads it: with order="largest" a frame's chains read a
    handful of its 66 angles, and each look-up is two binary searches in a table of up to ~700,000
    angles that is mostly out of the cache (~0.5 us of memory latency a query). The answers are those of
    `KVector.ranges` (the same searchsorted on the same bounds); `fill` takes a batch of them."""

    __slots__ = ("s", "theta", "bound", "start", "stop")

    def __init__(self, sorted_values: np.ndarray, theta: np.ndarray, bound: float):
        self.s, self.theta, self.bound = sorted_values, theta, bound
        self.start = [-1] * len(theta)
        self.stop = [-1] * len(theta)

    def fill(self, start: np.ndarray, stop: np.ndarray) -> None:
        self.start, self.stop = start.tolist(), stop.tolist()

    def span(self, k: int) -> tuple[int, int]:
        if self.start[k] < 0:
            t = self.theta[k]
            self.start[k] = int(self.s.searchsorted(t - self.bound, side="left"))
            self.stop[k] = int(self.s.searchsorted(t + self.bound, side="right"))
        return self.start[k], self.stop[k]

    def __getitem__(self, k) -> int:
        s, e = self.span(int(k))
        return 2 * (e - s)  # both orientations

    def all(self) -> np.ndarray:
        return np.array([self[k] for k in range(len(self.start))], dtype=np.int64)


# ---------------------------------------------------------------------- helpers

@lru_cache(maxsize=64)
def _pair_lists(m: int) -> tuple[list[int], list[int], list[list[int]]]:
    """`pair_indices(m)` as Python lists, and the angle between two stars s and t as table[s][t] (-1 for
    s == t); read-only by convention."""
    ii, jj = pair_indices(m)
    table = np.full((m, m), -1, dtype=np.int64)
    table[ii, jj] = table[jj, ii] = np.arange(len(ii))
    return ii.tolist(), jj.tolist(), table.tolist()


class _AngleWalk:
    """Which angle a join chain takes next, the first by priority among those not done: with
    close_loops one between two used stars, else one sharing a star with the previous angle, else one
    touching a used star (the masks of `next_by_priority`, answered from the few stars involved and
    their angles instead of a pass over every angle)."""

    def __init__(self, ctx: dict):
        self.angle = ctx["pairs"][2]  # angle[s][t]: the angle between stars s and t (-1: s == t)
        self.prio = ctx["priority"].tolist()

    def _first(self, stars, done: list[bool]) -> int:
        """The first angle by priority not done among those of `stars`, or -1."""
        prio = self.prio
        best, best_prio = -1, len(prio)
        for s in stars:
            for k in self.angle[s]:
                if k >= 0 and not done[k] and prio[k] < best_prio:
                    best, best_prio = k, prio[k]
        return best

    def next(self, done: list[bool], used: list[int], prev: tuple[int, int], close_loops: bool) -> int:
        if close_loops:
            prio = self.prio
            best, best_prio = -1, len(prio)
            for x in range(len(used)):
                row = self.angle[used[x]]
                for y in used[x + 1:]:
                    k = row[y]
                    if not done[k] and prio[k] < best_prio:
                        best, best_prio = k, prio[k]
            if best >= 0:
                return best
        k = self._first(prev, done)
        return k if k >= 0 else self._first(used, done)


def _join(H: np.ndarray, used: list[int], p: int, q: int, ci: np.ndarray, cj: np.ndarray, n_catalog: int | None = None):
    """Join hypotheses with the oriented candidates of angle (p, q) on the shared observed star(s).

    Returns (H', used', new): new is the observed star added (None for a closed loop). Vectorised:
    the candidates are grouped by their catalog star on the shared observed star (`by_star`), and
    each hypothesis meets the block of its star. n_catalog: the number of catalog rows (every row
    in H, ci and cj is below it), when the caller knows it.
    """
    cp = np.concatenate([ci, cj])  # catalog star of observed star p
    cq = np.concatenate([cj, ci])  # catalog star of observed star q
    if q in used and p not in used:  # make p the shared star
        p, q = q, p
        cp, cq = cq, cp
    if p not in used:
        raise ValueError("a pivot angle must share a star with the hypotheses")
    ip = used.index(p)
    m = n_catalog if n_catalog is not None else max(int(H.max(initial=0)), int(cp.max(initial=0))) + 1
    # only the candidates on the hypotheses' stars can join, so group just those (the same blocks in the same
    # order: the selection keeps the candidates' order and the grouping is stable) instead of sorting every
    # candidate of the angle (also for the first join's ~1,000 hypotheses: about a quarter are left)
    on = np.zeros(m, dtype=bool)
    on[H[:, ip]] = True
    sel = on[cp].nonzero()[0]
    cp, cq = cp.take(sel), cq.take(sel)
    cqs, start, size = by_star(cp, cq, m)
    v = H[:, ip]
    cnt = size.take(v)  # (take: an index without numpy's index parsing)
    rows = np.arange(len(H)).repeat(cnt)
    # each hypothesis meets its star's block: the block's start plus the rank within it
    newq = cqs.take(np.arange(int(cnt.sum())) + (start.take(v) - cnt.cumsum() + cnt).repeat(cnt))
    if q in used:  # closed loop: the pair (H[p], H[q]) must be a candidate as it is
        hit = newq == H[rows, used.index(q)]
        return H[np.bincount(rows[hit], minlength=len(H)) > 0], used, None
    k = H.shape[1]
    Hr = H.take(rows, axis=0)
    ok = Hr[:, 0] != newq  # a catalog star is never two observed stars
    for c in range(1, k):
        ok &= Hr[:, c] != newq
    H2 = np.empty((int(np.count_nonzero(ok)), k + 1), dtype=np.result_type(H, newq))
    H2[:, :k] = Hr[ok]
    H2[:, k] = newq[ok]
    return H2, used + [q], q


def _close(H: np.ndarray, ip: int, iq: int, xyz: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """`_join` of a closed loop: the hypotheses whose catalog stars on the angle's two observed stars
    (columns ip, iq) form a candidate pair. The candidates are every catalog pair whose database angle
    lies in [lo, hi] (the look-up is exact and the database holds every pair up to its range, which
    hi stays below), and the database's angle of a pair is `angular_distance` of its two stars (the same
    numbers, in either order): so the test is the angle itself, without grouping the candidates."""
    d = angular_distance(xyz[H[:, ip]], xyz[H[:, iq]])
    return H[(d >= lo) & (d <= hi)]


def _pick_note(a: int, b: int, deg: float, bound: float, n: int) -> str:
    return f"picked angle {a}-{b} ({deg:.3f} deg +- {bound * RAD_TO_ARCSEC:.1f}\"): {n} candidates"


def _pivot_note(p: int, q: int, deg: float, n: int, before: int, after: int) -> str:
    return f"pivoted to angle {p}-{q} ({deg:.3f} deg): {n} candidates, {before} -> {after} hypotheses"


def _merged(numbers, k: int, extra: dict) -> dict:
    """A step's figures: the angle's (numbers(k)) and the step's own."""
    return numbers(k) | extra


def _layer(used: tuple[int, ...], H: np.ndarray) -> tuple:
    return (Hypotheses.sample(used, H),)


def _both_orientations(ci: np.ndarray, cj: np.ndarray) -> np.ndarray:
    """The candidate pairs as rows over the angle's two observed stars, in both orientations
    (= np.concatenate([np.stack([ci, cj], axis=1), np.stack([cj, ci], axis=1)]))."""
    n = len(ci)
    H = np.empty((2 * n, 2), dtype=np.result_type(ci, cj))
    H[:n, 0], H[:n, 1], H[n:, 0], H[n:, 1] = ci, cj, cj, ci
    return H


def _n_pairs(P: np.ndarray) -> int:
    """How many distinct (unordered) catalog pairs the rows hold."""
    if len(P) <= 1:
        return len(P)
    return len(np.unique(np.sort(P, axis=1), axis=0))


def _orient_pair(one: np.ndarray, one_obs: tuple[int, int], other: np.ndarray | None,
                 other_obs: tuple[int, int] | None) -> np.ndarray:
    """The orientation(s) of the one catalog pair left for the observed angle one_obs, as rows over one_obs.

    The catalog star it shares with the neighbouring list sits on the observed star the two angles
    share; when neither or both of its stars are in that list (or there is no neighbour), both."""
    both = np.array([[one[0], one[1]], [one[1], one[0]]], dtype=np.int64)
    if other is None or not len(other):
        return both
    shared = set(one_obs) & set(other_obs)
    if len(shared) != 1:
        return both
    s = shared.pop()
    in_other = np.isin(one, other)
    if in_other[0] == in_other[1]:
        return both
    cat_s = int(one[0] if in_other[0] else one[1])
    cat_t = int(one[1] if in_other[0] else one[0])
    row = [cat_s, cat_t] if one_obs[0] == s else [cat_t, cat_s]
    return np.array([row], dtype=np.int64)


def _distinct(H: np.ndarray) -> list[int]:
    """The CAP smallest distinct catalog rows of H (= np.unique(H)[:CAP], without its per-call overhead)."""
    if not H.size:
        return []
    if H.size > 1024:  # many hypotheses: mark the rows present instead of sorting them all
        seen = np.zeros(int(H.max()) + 1, dtype=bool)
        seen[H.ravel()] = True
        return np.flatnonzero(seen)[:CAP].tolist()
    s = np.sort(H, axis=None)
    keep = np.empty(s.size, dtype=bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep][:CAP].tolist()


def _groups(ci: np.ndarray, cj: np.ndarray) -> list[tuple[int, int]]:
    return list(zip(ci[:CAP].tolist(), cj[:CAP].tolist()))
