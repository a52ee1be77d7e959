"""The spherical-triangle method with pivoting (Cole & Crassidis 2006, section III).

This module is a little over ~500 lines on purpose: its docstring is the paper's description of
the method (~85 lines), and it holds both pivoting chains (the paper's lists and the joins), which
share their helpers. The databases, their build and the report's figures are in
`skyview.identify.triangle_database`, the look-up of an observed triangle in `triangle_lookup`, the
search loop, the backtracking restarts and what the angle method shares in `skyview.identify.pivot`.

Databases: the paper's stored triangle database (database="triangles", default) or, in the improved
variant, the candidates joined from the angle method's pair database (database="pairs");
`skyview.identify.triangle_database` describes which variant reads what, and why.
Bounds (beta = 3). Area: beta sigma_A with sigma_A from eqs. 20-24 (area_sigma="paper": H H^T with
the three sides independent, each with the variance of an angle between two stars, sigma_p^2 = 2 sigma^2
(eq. 13): then 0.24 % of true triangles fall outside the 3 sigma bound, the paper's "0.3 %";
"star-sigma": the star's sigma^2, 1.8 % outside; docs/methods.md), or with the covariance of the
sides of noisy stars (area_sigma="stars"; see `spherical`: eq. 24 under-states sigma_A by a median
factor 1.2 and up to 2, and over-states it for slivers). Polar moment: as the paper, a bound from
simulation, cached beside the database (a small file per camera circle: drawn from the stored
triangles that fit the camera, in their stored order, it is the line a database built for that camera
alone would hold; with database="pairs" from ~20,000 random catalog triangles, `build_moment_sigma`):
MOMENT_SIGMA_TRIANGLES = 1000 random catalog triangles x
MOMENT_SIGMA_TRIALS = 100 noisy measurements (tangent-plane error sigma_ref per axis), the standard
deviation of each one's polar moment over sigma_ref, and the lowest line sigma_I / sigma = c0 + c1 I
lying MOMENT_SIGMA_MARGIN = 10 % above all of them (a linear program): "a line slightly above the
maximum standard deviations". The bound is beta sigma (c0 + c1 I).

Look-up. The candidates of an observed triangle are the catalog triangles whose area lies in
[A - beta sigma_A, A + beta sigma_A] and whose polar moment lies in [I - beta sigma_I, I + beta sigma_I]:
two k-vector ranges and their intersection (the shorter range filtered by the other). Counting the
intersection for many observed triangles at once uses the area order cut into blocks of BLOCK
triangles with their polar-moment ranks sorted inside each block (`_count`).

Vertex order. Area and polar moment do not depend on the order of the vertices, so a candidate may
map onto the observed triangle in 6 orders. vertex_order="paper" (default): as the paper, a candidate
is a set of three catalog stars; the hypotheses keep all 6 orders, pivoting prunes (or joins) on the
shared observed stars (the paper's "two stars in common"), and the chain ends when ONE SET of
catalog stars is left; then its vertex order is taken from the sides and the handedness (below), and
a set that fits in no order is rejected (the paper would have reported it: see first_chain).
vertex_order="sides": every candidate is oriented at once, keeping the orders in which each observed
side matches its catalog side within beta sigma_p (sigma_p = sqrt(2) sigma, eq. 14) and the handedness
agrees: the sign of the triple product p.(q x r) is that of the catalog triangle in that order (a
rotation keeps it, a mirror flips it), tested where the observed sign is certain (beyond beta of its
sigma); after each pivot every pair of stars of a hypothesis must match its observed angle.

Pivoting as printed (pivoting="shared-star", the default; section III-E): each triangle's candidates
form a list; the next triangle shares two observed stars with the current one, and a candidate of
either list survives when two of its catalog stars sit, on those two observed stars, in some
candidate of the other list ("any solution in each list that does not have two stars in common with
at least one solution in the other lists is discarded"); the following triangle meets the pruned list
of the one before it only. The chain ends when a list holds one star set, when no triangle shares two
stars with the current one, or at the pivot limit; the answer is that triangle's three stars, every
other star is left to verify with. pivoting="lists": two common stars anywhere (the print taken
literally). pivoting="join" (beyond the paper, in IMPROVED_PARAMS; the former paper variant) is the
chain below.

Pivoting by joins. The first triangle is the one with the largest area (order="largest", default: the paper
starts the angle method with the largest angle, "which typically offers the fewest solutions"), or the
fewest candidates (order="fewest", the paper's "ideal" order: needs every triangle's candidates
counted). Each pivot takes the next triangle in that order that shares two stars with the previous
one (when none is left, two stars with any used star) and joins its candidates with the hypotheses on
the shared observed stars (a vectorised sort + searchsorted join, `join`): a hypothesis survives with
every candidate that puts the same catalog stars on the shared observed stars and gains the third
star (never a catalog star it already uses); a triangle of three used stars must match as it is.
The chain stops when one star set is left (or a few that differ only by unresolved close pairs),
when no triangle is left, or at the pivot limit (max_pivots = 3, the paper's); a triangle with more
than max_candidates = 10,000 candidates is skipped. The one hypothesis left then goes to the shared
verification (`skyview.identify.verify`); only a verified one is reported.

Options beyond the paper (`IMPROVED_PARAMS` = pivoting="join", vertex_order="sides", area_sigma="stars",
close_triangles, backtrack, max_stars=12; the paper's method is the default):
- close_triangles: a pivot first takes a triangle made only of stars already in the hypotheses (no
  new star, strong pruning), so the chain ends with few stars and leaves the others to verify with;
- backtrack: when the hypotheses go to zero (a false star, a bound missed) or the one left fails
  verification, restart without a suspect star: the one the failed triangles point at most (each
  triangle that emptied the set blames its three stars, a failed verification its stars by half),
  ties broken by the chain's own order (the star just added first, then the others, newest first);
  at most max_restarts restarts, max_dropped stars at once. Every verification counts in the
  Bonferroni factor of the verification statistic, so no wrong attitude gets an easier pass.

Not in the paper, in IMPROVED_PARAMS: max_stars = 12 caps the stars that form triangles (the brightest;
every star still takes part in verification): the paper's CPU time grew to 400 s with more than 20
stars in the FOV. The paper variant forms triangles from every star (max_stars=None). database="pairs"
(above) is in IMPROVED_PARAMS too; it needs vertex_order="sides" and pivoting="join".
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from math import comb, sqrt

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog
from skyview.core.errors import BadInput
from skyview.identify import database as database_module
from skyview.identify import spherical as sph
from skyview.identify.angle import load_pair_database
from skyview.identify.base import Search
from skyview.identify.layers import Hypotheses
from skyview.identify.pivot import (
    MAX_EQUIVALENT,
    Chain,
    PivotMethod,
    PivotParams,
    next_by_priority,
    pair_indices,
    take_pattern,
    uses_any,
)
from skyview.identify.steps import LazyStep, Step
from skyview.identify.triangle_database import (
    MOMENT_PARAMS,
    MOMENT_SAMPLE_TRIANGLES,
    MOMENT_SIGMA_VERSION,
    build_moment_sigma,
    load_triangle_database,
)
from skyview.identify.triangle_lookup import _PERMS, CAP, SMALL, SQ2, TriangleLookup, _groups, _n_sets
from skyview.identify.verify import angular_distance

# eq. 24 with the pair sigma sqrt(2) sigma ("paper": its 3 sigma bound then holds), with the star sigma
# ("star-sigma", the print's other reading), or the full covariance of the sides ("stars")
AREA_SIGMAS = ("paper", "star-sigma", "stars")
VERTEX_ORDERS = ("paper", "sides")
# where the candidates of an observed triangle come from: the stored triangle database ("triangles", the
# paper's), or joined from the angle database's pairs and then filtered by area and polar moment ("pairs")
DATABASES = ("triangles", "pairs")
DEG2_PER_SR = float(np.degrees(1.0) ** 2)


# ---------------------------------------------------------------------- the method

@dataclass(frozen=True)
class TriangleParams(PivotParams):
    """The triangle method's parameters (the paper's defaults; the module docstring explains each)."""

    max_pivots: int | None = 3
    area_sigma: str = "paper"
    vertex_order: str = "paper"
    depth: int = sph.MOMENT_DEPTH
    close_triangles: bool = False
    kvector_fit: str = "parabola"
    database: str = "triangles"

    def __post_init__(self):
        if self.area_sigma not in AREA_SIGMAS:
            raise BadInput(f"unknown area_sigma {self.area_sigma!r}: choose from {', '.join(AREA_SIGMAS)}")
        if self.vertex_order not in VERTEX_ORDERS:
            raise BadInput(f"unknown vertex_order {self.vertex_order!r}: choose from {', '.join(VERTEX_ORDERS)}")
        if not (0 <= int(self.depth) <= 8):
            raise BadInput("depth must be between 0 and 8")
        super().__post_init__()
        if self.database not in DATABASES:
            raise BadInput(f"unknown database {self.database!r}: choose from {', '.join(DATABASES)}")
        if self.database == "pairs" and (self.vertex_order != "sides" or self.pivoting != "join"):
            raise BadInput("database='pairs' joins oriented triangles: it needs vertex_order='sides' and "
                           "pivoting='join'")


PAPER = TriangleParams()
IMPROVED = replace(PAPER, vertex_order="sides", close_triangles=True, backtrack=True, area_sigma="stars",
                   pivoting="join", max_stars=12, database="pairs")
IMPROVED_PARAMS = IMPROVED.changed()


class TriangleMethod(TriangleLookup, PivotMethod):
    """Cole & Crassidis' spherical-triangle method with pivoting, ending in the shared verification."""

    name = "triangle"
    paper_scenario = "cole8"
    title = "the spherical-triangle method"
    Params = TriangleParams
    improved_params = IMPROVED_PARAMS
    blame_restarts = True

    def __init__(self, catalog: GuideCatalog, camera: Camera, sigma_rad: float, **params):
        p = self.configure(catalog, camera, sigma_rad, params)
        self.depth = int(p.depth)
        self.close_triangles = bool(p.close_triangles)
        # the database belongs to the sky: caps up to the half-diagonal rounded up on the 5 % grid of
        # database.angular_range, so one database serves every camera whose half-diagonal is below it
        self.max_radius_rad = database_module.angular_range(camera.half_diagonal_rad)
        if self.database == "pairs":
            self._init_pairs(catalog, camera)
            return
        fields, info = load_triangle_database(catalog, camera, self.max_radius_rad, self.depth, p.kvector_fit,
                                              self.name)
        vars(self).update(fields)
        self._n_patterns = len(self.tri)
        self.database_info = info

    def _init_pairs(self, catalog: GuideCatalog, camera: Camera) -> None:
        """No triangle database: the angle database's pairs (shared with the angle method) and the
        polar-moment sigma line (a small database of its own)."""

        pair_i, pair_j, self.kv_pairs, info = load_pair_database(catalog, camera)
        # both stars of each pair side by side: the pairs of an angle range are one contiguous block (`join_pairs`)
        self.pair_ends = np.stack([pair_i, pair_j], axis=1).astype(np.int64)  # (from the int32 columns)
        self.pair_i, self.pair_j = self.pair_ends[:, 0], self.pair_ends[:, 1]
        self.pair_max_sep_rad = float(info["max_sep_rad"])
        params = {"max_radius_rad": self.max_radius_rad, "depth": self.depth, "moment_sigma": MOMENT_PARAMS,
                  "sample": MOMENT_SAMPLE_TRIANGLES, "version": MOMENT_SIGMA_VERSION}
        mkey = database_module.make_key("triangle-moment", params, catalog, None)
        arrays, minfo = database_module.load_or_build(
            mkey, lambda: build_moment_sigma(catalog, self.max_radius_rad, self.depth),
            what="the polar-moment sigma line of the triangle method", estimate_s=2.0)
        self.moment_sigma_coef = np.asarray(arrays["moment_sigma_coef"], dtype=np.float64)
        self.moment_sigma_samples = np.asarray(arrays["moment_sigma_samples"])
        # the key recorded in results names both databases the method reads
        self.database_key = database_module.make_key(self.name, {"database": "pairs", "pairs": info["key"],
                                                                 "moment_sigma": mkey}, catalog, None)
        info.update(database="pairs", pairs=len(self.pair_i), max_sep_deg=float(np.degrees(self.pair_max_sep_rad)),
                    max_radius_deg=float(np.degrees(self.max_radius_rad)), fov_deg=float(camera.fov_deg),
                    catalog_stars=len(catalog), moment_sigma_coef=self.moment_sigma_coef.tolist(),
                    moment_sigma_key=minfo["key_string"], moment_sigma_source=minfo["source"])
        self._n_patterns = len(self.pair_i)
        self.database_info = info

    @property
    def n_patterns(self) -> int:
        """Patterns in the database (the tetra3 statistic divides its threshold by this): the stored
        triangles, or with database="pairs" the pairs."""
        return self._n_patterns

    def consistent(self, V: np.ndarray, used: list[int], triangles: list[list[int]], H: np.ndarray,
                   sigma: float, t: dict | None = None) -> np.ndarray:
        """The hypotheses whose every pair of stars matches the observed angle within beta sigma_p and
        whose every triangle of the chain has the observed handedness where that is certain (t: the
        frame's observed triangles, `triangle_bounds`, which hold the triple products and their sigmas
        of the chain's triangles: measured, the same numbers)."""
        if len(H) == 0:
            return H
        tol = self.beta * SQ2 * sigma
        x, y = pair_indices(len(used))  # every pair of stars at once
        if t is not None and len(H) * len(x) <= SMALL:
            return self._consistent_few(V, used, triangles, H, t, tol)
        xyz = self.catalog.xyz
        col = {s: c for c, s in enumerate(used)}
        u = np.asarray(used)
        obs_angle = angular_distance(V[u[x]], V[u[y]])
        P = xyz[H]
        ok = np.all(np.abs(angular_distance(P[:, x], P[:, y]) - obs_angle) <= tol, axis=1)
        T = np.asarray(triangles)  # every triangle of the chain at once
        if t is not None:
            k = [_triangle_index(*tri, len(t["V"])) for tri in triangles]
            tr, trs = t["triple"][k], t["triple_sigma"][k]
        else:
            A, B, C = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
            tr, trs = sph.triple(A, B, C), sph.triple_sigma(A, B, C, sigma)
        certain = np.abs(tr) > self.beta * trs
        if np.any(certain):
            c = np.array([[col[s] for s in tri] for tri in T[certain].tolist()])  # (t, 3) columns of H
            Pc = P[:, c]  # (h, t, 3 vertices, 3)
            hand = np.sign(sph.triple(Pc[:, :, 0], Pc[:, :, 1], Pc[:, :, 2])) == np.sign(tr[certain])
            ok &= np.all(hand, axis=1)
        return H[ok]

    def _consistent_few(self, V: np.ndarray, used: list[int], triangles: list[list[int]], H: np.ndarray, t: dict,
                        tol: float) -> np.ndarray:
        """`consistent` for a few hypotheses, in plain floats: the same angles (the chords summed as
        np.linalg.norm sums them, then one np.arcsin call for all of them: numpy's arcsin differs from
        math's in the last bit) and the same signs of the triple products."""
        x, y = pair_indices(len(used))
        pairs = list(zip(x.tolist(), y.tolist()))
        cat = self.catalog.xyz[H].tolist()  # (h, stars, 3)
        half = []
        for pts in [V[used].tolist()] + cat:  # the observed stars, then each hypothesis'
            for i, j in pairs:
                a, b = pts[i], pts[j]
                d0, d1, d2 = a[0] - b[0], a[1] - b[1], a[2] - b[2]
                half.append(min(max(sqrt(d0 * d0 + d1 * d1 + d2 * d2) / 2.0, 0.0), 1.0))
        angle = (2.0 * np.arcsin(np.array(half))).tolist()  # = angular_distance
        n = len(pairs)
        obs = angle[:n]
        ok = [all(abs(angle[n * (h + 1) + p] - obs[p]) <= tol for p in range(n)) for h in range(len(H))]
        col = {s: c for c, s in enumerate(used)}
        for tri in triangles:
            k = _triangle_index(*tri, len(t["V"]))
            tr = float(t["triple"][k])
            if not abs(tr) > self.beta * float(t["triple_sigma"][k]):
                continue  # the observed handedness is not certain
            c0, c1, c2 = (col[s] for s in tri)
            for h, pts in enumerate(cat):
                if ok[h]:
                    ok[h] = sph.sign(sph.dot3(pts[c0], sph.cross3(pts[c1], pts[c2]))) == sph.sign(tr)
        return H[np.array(ok, dtype=bool)]

    # ------------------------------------------------------------------ identify (the template's parts)
    def _patterns(self, search: Search) -> tuple[dict, int]:
        """The observed triangles of the pattern stars (the brightest max_stars; measured and looked up
        as the order needs) and the order the chains take them in."""
        V, sigma = search.V, search.sigma
        m = search.n if self.max_stars is None else min(search.n, self.max_stars)
        t = self.triangle_bounds(V[:m], sigma, lookup=self.order == "fewest")
        # the lower the priority, the sooner a chain takes the triangle (`next_by_priority`)
        priority = -t["area"]  # largest first; a tie: the lower index first (argmin's and a stable sort's)
        if self.order == "fewest" or np.isnan(priority).any():  # (NaN: no order; none from unit vectors)
            rank = (np.lexsort((priority, t["counts"])) if self.order == "fewest"
                    else priority.argsort(kind="stable"))
            priority = np.empty(len(rank), dtype=np.int64)
            priority[rank] = np.arange(len(rank))  # the ranks
        t["priority"] = priority
        t["tol"] = 2.0 * search.radius
        t["sigma"] = sigma
        t["stars"] = m
        return t, m

    def _proposals(self, V: np.ndarray, chain: Chain, sigma: float) -> list[np.ndarray]:
        chain.answer = self._best(V, chain.used, chain.H, sigma)
        return [chain.answer]

    def _chain_stats(self, t: dict, m: int, chains: list[Chain]) -> tuple[dict, dict]:
        first = chains[0]
        # the paper's own criterion: the answer of the first chain, before our vertex-order check and the
        # verification ("unique" also when that one star set fits in no vertex order)
        return {"triangle_stars": m, "triangles": len(t["area"])}, {
            "first_chain": {"outcome": "unique" if first.answer is not None else first.outcome,
                            "matches": (dict(zip(map(int, first.used), first.answer.tolist()))
                                        if first.answer is not None else {}),
                            "vertex_order_ok": first.best is not None}}

    # ------------------------------------------------------------------ one pivoting chain
    def _row(self, t: dict, k: int) -> tuple:
        """Observed triangle k's figures as they are now (numpy scalars: copies), for a step's lazy note and
        numbers (t's arrays are filled in for other triangles later; a row, once measured, stays)."""
        sides = t.get("side_counts", {}).get(k, (-1, -1)) if self.database == "pairs" else None
        return (t["ti"][k], t["tj"][k], t["tk"][k], t["area"][k], t["area_bound"][k], t["moment"][k],
                t["moment_bound"][k], t["counts"][k], sides,
                None if sides is not None else (t["e1"][k] - t["s1"][k], t["e2"][k] - t["s2"][k]))

    def _numbers(self, t: dict, k: int) -> dict[str, float]:
        return _row_numbers(self._row(t, k))

    def _label(self, t: dict, k: int) -> str:
        return _row_label(self._row(t, k))

    def _skip(self, t: dict, k: int, steps: list[Step]) -> None:
        """Record observed triangle k left out: more than max_candidates candidates."""
        steps.append(Step("skip", f"skipped {self._label(t, k)}: {t['counts'][k]} candidates > {self.max_candidates}",
                          observed=[int(t["ti"][k]), int(t["tj"][k]), int(t["tk"][k])],
                          numbers=self._numbers(t, k) | {"max_candidates": self.max_candidates}))

    def _chain(self, V: np.ndarray, excluded: frozenset, t: dict, steps: list[Step]) -> Chain:
        ti, tj, tk, counts, priority = t["ti"], t["tj"], t["tk"], t["counts"], t["priority"]
        sigma, m = t["sigma"], t["stars"]
        done = uses_any(excluded, m, ti, tj, tk)
        candidates: list[int] = []
        hyps: list[int] = []

        pick_next = partial(next_by_priority, priority=priority)
        k = take_pattern(done, priority, lambda k: self.count_of(t, k) > self.max_candidates,
                         lambda k: self._skip(t, k, steps))
        if k < 0:
            return Chain("ambiguous", "no triangle with at most max_candidates candidates to start from", [],
                         np.zeros((0, 0), dtype=np.int64))
        H, groups_of = self.oriented_candidates(t, k, sigma)
        first = k
        used = [int(ti[k]), int(tj[k]), int(tk[k])]
        triangles = [used.copy()]
        n_sets = _n_sets(H)
        candidates.append(int(counts[k]))
        hyps.append(n_sets)
        row = self._row(t, k)
        steps.append(LazyStep("pick", note_of=partial(_pick_note, row, len(H) if self.vertex_order == "sides" else None),
                              observed=used.copy(), catalog_of=partial(_distinct, H), groups_of=groups_of,
                              numbers_of=partial(_row_numbers, row, {"hypotheses": len(H), "sets": n_sets}),
                              layers_of=partial(_sample, tuple(used), H, ())))
        if len(H) == 0:
            return Chain("empty", f"no catalog triangle matches the first triangle {used[0]}-{used[1]}-{used[2]}",
                          used, H, suspects=used[::-1], culprit=used.copy(), candidates=candidates, hypotheses=hyps)
        prev = tuple(used)
        pivots = 0
        checked = None  # the hypotheses `consistent` returned last (it would return them as they are)
        while not self._settled(V, used, triangles, H, n_sets, sigma, t["tol"], checked=H is checked, t=t):
            if self.max_pivots is not None and pivots >= self.max_pivots:
                steps.append(Step("stop", f"pivot limit {self.max_pivots} reached with {n_sets} candidate "
                                          f"star sets", observed=used.copy(), catalog=_distinct(H),
                                  numbers={"hypotheses": len(H), "sets": n_sets}))
                return Chain("ambiguous", f"{n_sets} star sets left after {pivots} pivots (the limit)", used, H,
                              pivots=pivots, candidates=candidates, hypotheses=hyps)
            in_used = np.zeros(m, dtype=bool)
            in_used[used] = True
            in_prev = np.zeros(m, dtype=bool)
            in_prev[list(prev)] = True
            n_prev = in_prev[ti].astype(int) + in_prev[tj] + in_prev[tk]
            n_used = in_used[ti].astype(int) + in_used[tj] + in_used[tk]
            k = pick_next(~done & (n_used == 3)) if self.close_triangles else -1
            if k < 0:
                k = pick_next(~done & (n_prev == 2))
            if k < 0:  # nothing shares two stars with the previous triangle: two with any used star
                k = pick_next(~done & (n_used >= 2))
            if k < 0:
                steps.append(Step("stop", f"no triangle left to pivot to; {n_sets} candidate star sets",
                                  observed=used.copy(), catalog=_distinct(H),
                                  numbers={"hypotheses": len(H), "sets": n_sets}))
                return Chain("ambiguous", f"{n_sets} star sets left and no triangle to pivot to", used, H,
                              pivots=pivots, candidates=candidates, hypotheses=hyps)
            done[k] = True
            if self.count_of(t, k) > self.max_candidates:
                self._skip(t, k, steps)
                continue
            obs3 = [int(ti[k]), int(tj[k]), int(tk[k])]
            O, groups_of = self.oriented_candidates(t, k, sigma)
            before, sets_before = len(H), n_sets
            shared = [s for s in obs3 if s in used]
            H, used, new = join(H, used, obs3, O)
            triangles.append(obs3)
            if self.vertex_order == "sides":  # every pair of stars, also across triangles
                H = checked = self.consistent(V, used, triangles, H, sigma, t)
            pivots += 1
            n_sets = _n_sets(H)
            candidates.append(int(counts[k]))
            hyps.append(n_sets)
            row, shared = self._row(t, k), tuple(shared)
            steps.append(LazyStep("pivot", note_of=partial(_pivot_note, row, shared, sets_before, n_sets),
                                  observed=obs3, catalog_of=partial(_distinct, H), groups_of=groups_of,
                                  numbers_of=partial(_row_numbers, row, {
                                      "oriented": len(O), "hypotheses_before": before, "hypotheses_after": len(H),
                                      "sets_before": sets_before, "sets_after": n_sets, "pivot": pivots,
                                      "shared": len(shared), "new_star": -1 if new is None else new}),
                                  layers_of=partial(_sample, tuple(used), H, shared)))
            if len(H) == 0:
                if new is not None:
                    first_suspect = new
                else:  # a closed triangle: the newest of its stars first
                    first_suspect = max(obs3, key=used.index)
                rest = [s for s in used[::-1] if s != first_suspect]
                return Chain("empty", f"no hypothesis survives triangle {'-'.join(map(str, obs3))}", used, H,
                              suspects=[first_suspect] + rest, culprit=obs3, pivots=pivots, candidates=candidates,
                              hypotheses=hyps)
            prev = tuple(obs3)
        # one set of catalog stars (or a few that differ by unresolved close pairs): its vertex order
        if H is checked:
            Hc = H
        elif len(triangles) == 1 and H is t.get("oriented", {}).get(first) and first in t.get("consistent_rows", {}):
            kept = t["consistent_rows"][first]  # what `consistent` returns, from the join
            Hc = H if all(kept) else H[np.array(kept, dtype=bool)]
        else:
            Hc = self.consistent(V, used, triangles, H, sigma, t)
        if len(Hc) == 0:  # the paper would report this set; it fits in no vertex order, so it is wrong
            steps.append(Step("stop", "the one star set left fits the observed stars in no vertex order (sides or "
                                      "handedness)", observed=used.copy(), catalog=_distinct(H),
                              numbers={"hypotheses": len(H), "sets": n_sets}))
            return Chain("empty", "the remaining catalog stars fit the observed stars in no vertex order "
                                   "(sides or handedness)", used, Hc, suspects=used[::-1], culprit=used.copy(),
                          pivots=pivots, candidates=candidates, hypotheses=hyps,
                          answer=self._best(V, used, H, sigma) if n_sets == 1 else None)
        n_final = _n_sets(Hc)
        return Chain("unique", "one star set left" if n_final == 1 else
                      f"{n_final} star sets left that differ only by unresolved close pairs",
                      used, Hc, pivots=pivots, candidates=candidates, hypotheses=hyps)

    def _chain_lists(self, V: np.ndarray, excluded: frozenset, t: dict, steps: list[Step]) -> Chain:
        """The paper's pivoting: candidate lists of consecutive triangles pruned against each other.

        "Any solution in each list that does not have two stars in common with at least one solution in
        the other lists is discarded"; the next triangle shares two observed stars with the current one
        and meets its pruned list only. Ends when a list holds one star set; its vertex order is then
        taken from the sides and the handedness, as in the join.
        """
        ti, tj, tk, counts, priority = t["ti"], t["tj"], t["tk"], t["counts"], t["priority"]
        sigma, m = t["sigma"], t["stars"]
        oriented = self.pivoting == "shared-star"
        done = uses_any(excluded, m, ti, tj, tk)
        candidates: list[int] = []
        hyps: list[int] = []

        def next_triangle(mask):
            return take_pattern(done, priority, lambda k: self.count_of(t, k) > self.max_candidates,
                                lambda k: self._skip(t, k, steps), among=mask)

        def listed(k):
            rows = self.candidates(t, k)
            if oriented:  # rows over the observed stars (ti, tj, tk)[k], every vertex order that may fit
                return rows, self.orient(t, k, rows, sigma)[0]
            return rows, self.tri[rows].astype(np.int64)

        k = next_triangle(np.ones(len(ti), dtype=bool))
        if k < 0:
            return Chain("ambiguous", "no triangle with at most max_candidates candidates to start from", [],
                          np.zeros((0, 0), dtype=np.int64))
        cur_obs = [int(ti[k]), int(tj[k]), int(tk[k])]
        rows, cur = listed(k)
        used = cur_obs.copy()
        candidates.append(int(counts[k]))
        hyps.append(_n_sets(cur))
        steps.append(Step("pick", f"picked {self._label(t, k)}: {counts[k]} candidates", observed=cur_obs.copy(),
                          catalog=_distinct(cur), groups=_groups(self.tri, rows, rows),
                          numbers=self._numbers(t, k) | {"sets": _n_sets(cur)},
                          layers=(Hypotheses.sample(cur_obs, cur),)))
        if len(cur) == 0:
            return Chain("empty", f"no catalog triangle matches the first triangle {'-'.join(map(str, cur_obs))}",
                          used, cur, suspects=used[::-1], culprit=used.copy(), candidates=candidates, hypotheses=hyps)
        prev, prev_obs = None, None
        pivots = 0
        while _n_sets(cur) != 1 and (prev is None or _n_sets(prev) != 1):
            if self.max_pivots is not None and pivots >= self.max_pivots:
                steps.append(Step("stop", f"pivot limit {self.max_pivots} reached with {_n_sets(cur)} candidate "
                                          "star sets", observed=cur_obs.copy(), numbers={"sets": _n_sets(cur)}))
                return Chain("ambiguous", f"{_n_sets(cur)} star sets left after {pivots} pivots (the limit)", used,
                              cur, pivots=pivots, candidates=candidates, hypotheses=hyps)
            in_cur = np.zeros(m, dtype=bool)
            in_cur[cur_obs] = True
            k = next_triangle(in_cur[ti].astype(int) + in_cur[tj] + in_cur[tk] == 2)
            if k < 0:
                steps.append(Step("stop", f"no triangle sharing two stars with triangle {'-'.join(map(str, cur_obs))} "
                                          f"is left; {_n_sets(cur)} candidate star sets", observed=cur_obs.copy(),
                                  numbers={"sets": _n_sets(cur)}))
                return Chain("ambiguous", f"{_n_sets(cur)} star sets left and no triangle to pivot to", used, cur,
                              pivots=pivots, candidates=candidates, hypotheses=hyps)
            new_obs = [int(ti[k]), int(tj[k]), int(tk[k])]
            rows, new = listed(k)
            before = _n_sets(cur)
            M = int(max(cur.max(initial=0), new.max(initial=0))) + 1
            if oriented:  # the two common catalog stars sit on the two observed stars the triangles share
                s1, s2 = [s for s in new_obs if s in cur_obs]
                kc = cur[:, cur_obs.index(s1)] * M + cur[:, cur_obs.index(s2)]
                kn = new[:, new_obs.index(s1)] * M + new[:, new_obs.index(s2)]
                keep_cur, keep_new = np.isin(kc, kn), np.isin(kn, kc)
            else:
                pc, pn = _pair_keys(cur, M), _pair_keys(new, M)
                keep_cur = np.isin(pc, pn).any(axis=1)
                keep_new = np.isin(pn, pc).any(axis=1)
            prev, prev_obs = cur[keep_cur], cur_obs
            cur, cur_obs = new[keep_new], new_obs
            added = [s for s in new_obs if s not in used]
            used += added
            pivots += 1
            candidates.append(int(counts[k]))
            hyps.append(_n_sets(cur))
            steps.append(Step("pivot", f"pivoted to {self._label(t, k)}: {counts[k]} candidates, {_n_sets(cur)} share "
                                       f"two stars with the previous list ({before} -> {_n_sets(prev)})",
                              observed=new_obs.copy(), catalog=_distinct(cur), groups=_groups(self.tri, rows, rows),
                              numbers=self._numbers(t, k) | {"sets": _n_sets(cur), "previous_before": before,
                                                             "previous_after": _n_sets(prev), "pivot": pivots},
                              layers=(Hypotheses.sample(new_obs, cur, shared=[s for s in new_obs if s in prev_obs]),)))
            if len(cur) == 0:
                rest = [s for s in used[::-1] if s not in added]
                return Chain("empty", f"no candidate of triangle {'-'.join(map(str, new_obs))} shares two stars "
                                       "with the previous list", used, cur, suspects=added + rest,
                              culprit=new_obs.copy(), pivots=pivots, candidates=candidates, hypotheses=hyps)
        one, one_obs = (cur, cur_obs) if _n_sets(cur) == 1 else (prev, prev_obs)
        H = one if oriented else one[:1][:, _PERMS].reshape(-1, 3)
        Hc = self.consistent(V, one_obs, [one_obs], H, sigma, t)
        if len(Hc) == 0:  # the paper would report this set; it fits in no vertex order, so it is wrong
            steps.append(Step("stop", "the one star set left fits the observed stars in no vertex order (sides or "
                                      "handedness)", observed=one_obs.copy(), catalog=_distinct(H)))
            return Chain("empty", "the remaining catalog stars fit the observed stars in no vertex order "
                                   "(sides or handedness)", one_obs, Hc, suspects=used[::-1], culprit=one_obs.copy(),
                          pivots=pivots, candidates=candidates, hypotheses=hyps,
                          answer=self._best(V, one_obs, H, sigma))
        return Chain("unique", f"one star set left for triangle {'-'.join(map(str, one_obs))}", one_obs, Hc,
                      pivots=pivots, candidates=candidates, hypotheses=hyps)

    def _settled(self, V: np.ndarray, used: list[int], triangles: list[list[int]], H: np.ndarray, n_sets: int,
                 sigma: float, tol: float, checked: bool = False, t: dict | None = None) -> bool:
        """One set of catalog stars left, or a few that differ only by unresolved close pairs (checked: H
        is what `consistent` returned for these stars and triangles; t: the frame's triangles, for
        `consistent`)."""
        if n_sets <= 1:
            return True
        if n_sets > MAX_EQUIVALENT:
            return False
        if self.vertex_order == "paper" and not _has_close_pair(self.catalog.xyz[np.unique(H)], tol):
            return False  # different sets can only be one pattern through catalog stars closer than tol
        Hc = H if checked else self.consistent(V, used, triangles, H, sigma, t)
        if self.vertex_order == "paper" and _n_sets(Hc) < n_sets:
            return False  # the paper tells sets apart by pivoting only, never by their sides
        return len(Hc) > 0 and (_n_sets(Hc) == 1 or self._equivalent(Hc, tol))


# ---------------------------------------------------------------------- helpers

def join(H: np.ndarray, used: list[int], obs3: list[int], O: np.ndarray) -> tuple[np.ndarray, list[int], int | None]:
    """Join hypotheses H (columns: observed stars `used`) with the oriented candidates O of the observed
    triangle obs3 (columns in obs3's order) on the shared observed stars.

    Two shared stars: a hypothesis survives with every candidate that has its catalog stars on the
    two shared observed stars, and the candidate's third star is appended (never a catalog star the
    hypothesis already uses). Three shared stars (a closed triangle): the hypothesis' three stars must
    be a candidate as they are. Returns (H', used', new): new is the observed star added, or None.
    """
    pos = [used.index(s) if s in used else -1 for s in obs3]
    shared = [c for c in range(3) if pos[c] >= 0]
    if len(shared) < 2:
        raise ValueError("a pivot triangle must share at least two stars with the hypotheses")
    if len(H) == 0 or len(O) == 0:
        new = None if len(shared) == 3 else obs3[[c for c in range(3) if pos[c] < 0][0]]
        width = len(used) + (0 if new is None else 1)
        return np.zeros((0, width), dtype=np.int64), used + ([] if new is None else [new]), new
    M = int(max(H.max(), O.max())) + 1
    if len(shared) == 3:
        hk = (H[:, pos[0]] * M + H[:, pos[1]]) * M + H[:, pos[2]]
        ok_ = (O[:, 0] * M + O[:, 1]) * M + O[:, 2]
        return H[np.isin(hk, ok_)], used, None
    c1, c2 = shared
    c3 = 3 - c1 - c2
    okey = O[:, c1] * M + O[:, c2]
    o = okey.argsort(kind="stable")
    okey_s, third = okey[o], O[o, c3]
    hkey = H[:, pos[c1]] * M + H[:, pos[c2]]
    lo = np.searchsorted(okey_s, hkey, side="left")
    hi = np.searchsorted(okey_s, hkey, side="right")
    cnt = hi - lo
    total = int(cnt.sum())
    rows = np.repeat(np.arange(len(H)), cnt)
    offs = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    newc = third[np.repeat(lo, cnt) + offs]
    Hn = H[rows]
    ok = ~np.any(Hn == newc[:, None], axis=1)
    new = obs3[c3]
    return np.concatenate([Hn[ok], newc[ok, None]], axis=1), used + [new], new


def _triangle_index(i: int, j: int, k: int, m: int) -> int:
    """The position of the triangle (i < j < k) among itertools.combinations(range(m), 3) (`triangle_bounds`'
    order): the triangles before i, then those of i before j, then those of (i, j) before k."""
    return comb(m, 3) - comb(m - i, 3) + comb(m - i - 1, 2) - comb(m - j, 2) + k - j - 1


def _pair_keys(S: np.ndarray, M: int) -> np.ndarray:
    """(n, 3) keys of the three unordered star pairs of each star set."""
    a = np.sort(S, axis=1)
    return np.stack([a[:, 0] * M + a[:, 1], a[:, 0] * M + a[:, 2], a[:, 1] * M + a[:, 2]], axis=1)


def _has_close_pair(xyz: np.ndarray, tol: float) -> bool:
    """Whether two of these (distinct) catalog stars lie within tol of each other."""
    if len(xyz) < 2:
        return False
    d = angular_distance(xyz[:, None, :], xyz[None, :, :])
    return bool(np.any(d[np.triu_indices(len(xyz), 1)] <= tol))


def _row_label(row: tuple) -> str:
    i, j, k, area, area_bound, moment, moment_bound = row[:7]
    return (f"triangle {i}-{j}-{k} (area {area * DEG2_PER_SR:.4f} +- {area_bound * DEG2_PER_SR:.4f} deg2, "
            f"polar moment {moment:.3e} +- {moment_bound:.1e})")


def _row_numbers(row: tuple, more: dict | None = None) -> dict[str, float]:
    """A step's numbers from a `TriangleMethod._row` (then `more`)."""
    area, area_bound, moment, moment_bound, count, sides, spans = row[3:]
    out = {"area_sr": float(area), "area_bound_sr": float(area_bound), "moment": float(moment),
           "moment_bound": float(moment_bound)}
    if sides is not None:
        out |= {"pairs_side1": sides[0], "pairs_side2": sides[1], "candidates": int(count)}
    else:
        out |= {"candidates_area": int(spans[0]), "candidates_moment": int(spans[1]), "candidates": int(count)}
    return out if more is None else out | more


def _pick_note(row: tuple, oriented: int | None) -> str:
    return (f"picked {_row_label(row)}: {row[7]} candidates"
            + (f", {oriented} in a vertex order that fits the sides and handedness" if oriented is not None else ""))


def _pivot_note(row: tuple, shared: tuple, sets_before: int, n_sets: int) -> str:
    return (f"pivoted to {_row_label(row)} sharing stars {'-'.join(map(str, shared))}: {row[7]} candidates, "
            f"{sets_before} -> {n_sets} candidate star sets")


def _sample(used: tuple, H: np.ndarray, shared: tuple) -> tuple:
    return (Hypotheses.sample(used, H, shared=shared),)


def _distinct(H: np.ndarray) -> list[int]:
    """Distinct catalog rows of the first hypotheses, capped."""
    if H.size <= SMALL:  # the usual one or few hypotheses: a set, not np.unique's calls
        return sorted(set(H.ravel().tolist()))[:CAP]
    return np.unique(H[:4 * CAP]).astype(int)[:CAP].tolist()
