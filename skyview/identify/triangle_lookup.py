"""The triangle method's look-up (Cole & Crassidis 2006, section III-D; the method is
`skyview.identify.triangle`, the databases `skyview.identify.triangle_database`).

Every observed triangle of the pattern stars: its sides, area (L'Huilier), polar moment, their bounds
and the triple product's sigma, measured as the search needs them (`triangle_bounds`, `_measure`);
its candidates from the stored triangle database (the area and polar-moment k-vector ranges, counted
exactly by the block counter `_count`, listed by `_scan` with the camera's cap rule) or, with
database="pairs", joined from the angle database's pairs (`join_pairs`; the few joined triangles tested
in plain floats, `_close_few`); and the vertex orders in which a candidate fits the observed triangle
(`orient`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from functools import lru_cache, partial

import numpy as np

from skyview.core.catalog import einsum_c
from skyview.identify import spherical as sph
from skyview.identify.pivot import by_star
from skyview.identify.triangle_database import BLOCK, _block_search
from skyview.identify.verify import angular_distance

CAP = 200  # catalog rows / groups kept in one step
MEASURE_BATCH = 4  # observed triangles measured at once when the search reaches an unmeasured one
# (a chain visits 1-3 triangles in most frames; a call costs mostly its fixed overhead; database="pairs"
# with area_sigma="stars" measures one at a time in plain floats, ~15 us: `_measure_one`)
SCAN_LIMIT = 65536  # a triangle looked up alone is counted by listing its candidates up to this range
SQ2 = float(np.sqrt(2.0))
JOIN_DENSE = 16384  # up to this many (pq, qr) pairs of pairs, the join compares all of them at once
SMALL = 64  # up to this many catalog rows, distinct stars / sets are taken in plain Python (numpy's calls cost more)
_PERMS = np.array([[0, 1, 2], [1, 2, 0], [2, 0, 1], [0, 2, 1], [2, 1, 0], [1, 0, 2]])
_PARITY = np.array([1, 1, 1, -1, -1, -1])
_SIDE = np.array([[-1, 0, 2], [0, -1, 1], [2, 1, -1]])  # side index of vertex pair (x, y): ij=0, jk=1, ki=2


class TriangleLookup:
    """The look-up half of `TriangleMethod` (a mixin: it reads the method's parameters and databases)."""

    def moment_sigma(self, moment: np.ndarray, sigma: float) -> np.ndarray:
        """The simulated polar-moment sigma bound for a measured polar moment (section III-D)."""
        c0, c1 = self.moment_sigma_coef
        return float(sigma) * (c0 + c1 * np.asarray(moment, dtype=np.float64))

    def triangle_bounds(self, V: np.ndarray, sigma: float, lookup: bool = True) -> dict[str, np.ndarray]:
        """Every observed triangle of the stars V: stars, area, polar moment, bounds, and the k-vector
        ranges (s1, e1: area order; s2, e2: polar-moment order) and candidate counts.

        lookup=False leaves the ranges and counts at -1, to be filled for the triangles actually visited
        (`count_of`): the largest-area order needs only those.
        """
        ti, tj, tk = _combinations(len(V))
        pairs, side_of = _side_pairs(len(V))
        # the sides a = AB, b = BC, c = CA of every triangle (as sph.sides) are angles between two stars:
        # each pair's once (the arc of C, A is that of A, C: the difference only changes sign)
        ends = V.take(pairs, axis=0)  # both stars of every pair, in one gather (take: no index parsing)
        arcs = np.zeros(pairs.shape[1] + 1)
        sph.arc(ends[0], ends[1], out=arcs[:-1])
        S4 = arcs.take(side_of)  # (4, n): 0, a, b, c
        S = S4[1:]
        area = sph.lhuilier_zero_first(S4)  # = sph.lhuilier(*S)
        n = len(area)
        # the rest are measured as the search visits them (`_measure`); the triple product with them
        nan = np.empty((5, n))
        nan.fill(np.nan)
        out = dict(ti=ti, tj=tj, tk=tk, sides=S.T, area=area, triple=nan[0], sigma=sigma, V=V, area_bound=nan[1],
                   moment=nan[2], moment_bound=nan[3], triple_sigma=nan[4])
        if lookup or self.order == "fewest":
            self._measure(out, np.arange(n))
        if self.database == "pairs":  # no ranges: each triangle's candidates are joined when it is visited
            out.update(zip(("s1", "e1", "s2", "e2", "counts"), np.full((5, n), -1, dtype=np.int64)))
            if lookup:
                for k in range(len(area)):
                    self.count_of(out, k)
        elif lookup:
            with np.errstate(invalid="ignore"):
                da, moment, dm = out["area_bound"], out["moment"], out["moment_bound"]
                out["s1"], out["e1"] = self.kv_area.ranges(area - da, area + da)
                out["s2"], out["e2"] = self.kv_moment.ranges(moment - dm, moment + dm)
            out["counts"] = self._count(out)
            # the counter sees the whole database; list the candidates to keep those that fit this camera
            for k in np.flatnonzero(out["counts"] > 0).tolist():
                if min(out["e1"][k] - out["s1"][k], out["e2"][k] - out["s2"][k]) <= SCAN_LIMIT:
                    out.setdefault("rows", {})[k] = rows = self._scan(out, k)
                    out["counts"][k] = len(rows)
        else:
            out.update(zip(("s1", "e1", "s2", "e2", "counts"), np.full((5, n), -1, dtype=np.int64)))
        return out

    def _measure(self, t: dict, idx: np.ndarray, moment: bool = True) -> None:
        """Fill the area bound, polar moment, its bound and the triple product's sigma of the observed
        triangles idx (the largest-area order measures only the triangles it visits, MEASURE_BATCH at a
        time: the polar moments of all 220 triangles of 12 stars would cost more than the search).
        moment=False leaves the polar moments to `join_pairs`, which computes them in one call with its
        candidates' (t["moment_pending"] holds idx until then)."""
        V, sigma = t["V"], t["sigma"]
        A, B, C = V[t["ti"][idx]], V[t["tj"][idx]], V[t["tk"][idx]]
        if self.area_sigma == "paper":  # eq. 24 with each side's own sigma, sqrt(2) sigma (eq. 13)
            a, b, c = t["sides"][idx].T
            s_area = sph.area_sigma_paper(a, b, c, SQ2 * sigma)
        elif self.area_sigma == "star-sigma":
            a, b, c = t["sides"][idx].T
            s_area = sph.area_sigma_paper(a, b, c, sigma)
        else:
            s_area = sph.area_sigma_stars(A, B, C, sigma)
        t["area_bound"][idx] = self.beta * s_area
        if moment:
            self._set_moment(t, idx, sph.polar_moment(A, B, C, self.depth))
        else:
            t["moment_pending"] = idx
        t["triple_sigma"][idx] = sph.triple_sigma(A, B, C, sigma)
        t["triple"][idx] = sph.triple(A, B, C)

    def _measure_one(self, t: dict, k: int) -> bool:
        """database="pairs", area_sigma="stars": `_measure` of observed triangle k alone, in plain floats
        (`sph.triangle_sigmas`: the same numbers as the batch; its polar moment is left to `join_pairs`,
        which computes it with the candidates' in a batch of two or more, as `_moments` explains). False
        when the triangle is degenerate (then `_measure` does it)."""
        if "V_list" not in t:
            t["V_list"] = t["V"].tolist()  # the frame's stars as lists, once
        Vl = t["V_list"]
        A, B, C = Vl[t["ti"][k]], Vl[t["tj"][k]], Vl[t["tk"][k]]
        a, b, c = t["sides"][k].tolist()
        sig = sph.triangle_sigmas([A], [B], [C], [a], [b], [c], t["sigma"])
        if sig is None:
            return False
        t["area_bound"][k] = self.beta * sig[0][0]
        t["triple_sigma"][k] = sig[1][0]
        t["triple"][k] = sph.dot3(A, sph.cross3(B, C))  # = sph.triple
        t["moment_pending"] = pend = np.array([k])
        t["moment_pending_corners"] = (pend, ([A], [B], [C]))  # for `_moments`, as lists
        t.setdefault("corners", {})[k] = (A, B, C)  # for `_close_few`
        return True

    def _set_moment(self, t: dict, idx: np.ndarray, moment: np.ndarray) -> None:
        t["moment"][idx] = moment
        if len(moment) <= SMALL:  # `moment_sigma` in plain floats: the same operations, the same numbers
            (c0, c1), sigma, beta = self.moment_sigma_coef.tolist(), float(t["sigma"]), self.beta
            t["moment_bound"][idx] = [beta * (sigma * (c0 + c1 * m)) for m in moment.tolist()]
        else:
            t["moment_bound"][idx] = self.beta * self.moment_sigma(moment, t["sigma"])

    def _ensure(self, t: dict, k: int) -> None:
        """Observed triangle k measured (`_measure`), with the next unmeasured ones in the search order
        (database="pairs": but for the polar moments, which `join_pairs` computes next; with
        area_sigma="stars" too, k alone, in plain floats: `_measure_one`)."""
        done = t["area_bound"][k]
        if done == done:  # not NaN: measured (a NaN is unequal to itself; np.isnan costs a ufunc call)
            return
        if self.database == "pairs" and self.area_sigma == "stars" and self._measure_one(t, k):
            return
        todo = np.isnan(t["area_bound"]).nonzero()[0]
        pr = t.get("priority")
        if pr is not None and len(todo) > MEASURE_BATCH:
            # never one triangle left over: measured alone, its polar moment would differ in the last bit
            # (np.einsum sums one column another way) from the same triangle measured in a batch
            take = MEASURE_BATCH + 1 if len(todo) == MEASURE_BATCH + 1 else MEASURE_BATCH
            todo = todo[pr[todo].argsort(kind="stable")[:take]]
            if k not in todo:
                todo = np.append(todo[:-1], k)
        elif pr is None:
            todo = np.array([k])
        self._measure(t, np.sort(todo), moment=self.database != "pairs")

    def _count(self, t: dict) -> np.ndarray:
        """|area range ∩ polar-moment range| of each observed triangle, exact and vectorised.

        A catalog triangle is a candidate when its position in area order is in [s1, e1) and its
        position in polar-moment order (its rank) in [s2, e2) (and it fits the camera: `_scan` applies
        that, this counter counts the whole database's range). The area order is cut into blocks of
        BLOCK triangles whose ranks are stored sorted (`block_rank`): a block wholly
        inside [s1, e1) is counted with two binary searches, the at most 2 BLOCK triangles of the two
        partial blocks at the ends one by one.
        """
        s1, e1, s2, e2 = t["s1"], t["e1"], t["s2"], t["e2"]
        b = BLOCK
        q = np.arange(len(s1))
        live = (e1 > s1) & (e2 > s2)
        first = -(-s1 // b)  # first block starting at or after s1
        last = e1 // b  # blocks [first, last) lie inside [s1, e1)
        full = live & (last > first)
        counts = np.zeros(len(s1), dtype=np.int64)
        # whole blocks: two bisections inside each (triangle, block)'s sorted ranks
        nb = np.where(full, last - first, 0)
        if nb.sum():
            owner = np.repeat(q, nb)
            blk = np.repeat(first, nb) + (np.arange(int(nb.sum())) - np.repeat(np.cumsum(nb) - nb, nb))
            c = (_block_search(self.block_rank, blk, e2[owner], b) - _block_search(self.block_rank, blk, s2[owner], b))
            counts += np.bincount(owner, weights=c, minlength=len(s1)).astype(np.int64)
        # the ends: [s1, first * b) and [last * b, e1) (or all of [s1, e1) when no block fits inside)
        ends = ((s1, np.where(full, first * b, e1)), (np.where(full, last * b, e1), e1))
        for lo, hi in ends:
            ln = np.where(live, np.maximum(hi - lo, 0), 0)
            total = int(ln.sum())
            if total == 0:
                continue
            owner = np.repeat(q, ln)
            pos = np.repeat(lo - np.cumsum(ln) + ln, ln) + np.arange(total)
            r = self.moment_rank[pos]
            ok = (r >= s2[owner]) & (r < e2[owner])
            counts += np.bincount(owner, weights=ok, minlength=len(s1)).astype(np.int64)
        return counts

    def count_of(self, t: dict, k: int) -> int:
        """The candidate count of observed triangle k, looked up and counted now if it was left out
        (database="pairs": the catalog star sets that the pair join leaves)."""
        self._ensure(t, k)
        if t["counts"][k] < 0 and self.database == "pairs":
            t.setdefault("oriented", {})[k] = H = self.join_pairs(t, k)
            t["counts"][k] = _n_sets(H)
        elif t["counts"][k] < 0:
            a, da, i, di = t["area"][k], t["area_bound"][k], t["moment"][k], t["moment_bound"][k]
            t["s1"][k], t["e1"][k] = self.kv_area.range(a - da, a + da)
            t["s2"][k], t["e2"][k] = self.kv_moment.range(i - di, i + di)
            if min(t["e1"][k] - t["s1"][k], t["e2"][k] - t["s2"][k]) <= SCAN_LIMIT:  # list them at once
                t.setdefault("rows", {})[k] = rows = self._scan(t, k)
                t["counts"][k] = len(rows)
            else:
                one = {key: t[key][k:k + 1] for key in ("s1", "e1", "s2", "e2")}
                t["counts"][k] = self._count(one)[0]
        return int(t["counts"][k])

    def join_pairs(self, t: dict, k: int) -> np.ndarray:
        """database="pairs": the oriented candidates of observed triangle k ((p, q, r) = (ti, tj, tk)[k]),
        without a triangle database.

        The catalog pairs whose angle matches side pq within beta sigma_p (sigma_p = sqrt(2) sigma, the
        tolerance `orient` gives each side) are joined on the shared star q with the pairs matching
        side qr, in both orientations (first pruned to the pairs whose stars also end a pair of their
        other side: most of them do not); a third side rp within the same tolerance closes the triangle
        (its angle computed from the two stars, as the database computes its pairs'). Then, as the
        triangle database's candidates: the handedness where the observed sign is certain, the area
        within its bound and the polar moment within its bound. Returns (h, 3) catalog rows in the
        order (p, q, r): what `orient` returns from the stored candidates, up to the stored database's
        cap rule (a triangle that matches a sensor's triangle within the noise fits the sensor).
        """
        self._ensure(t, k)
        sig = float(t["sigma"])
        tol = self.beta * SQ2 * sig
        sides = t["sides"][k]
        lo, hi = sides - tol, sides + tol
        # the pairs of each side: kv_pairs.ranges (its two binary searches; lo <= hi, as tol > 0)
        values = self.kv_pairs.sorted_values
        st, sp = values.searchsorted(lo, "left").tolist(), values.searchsorted(hi, "right").tolist()
        E, xyz = self.pair_ends, self.catalog.xyz
        # each star of a candidate ends a pair of both its sides (p: pq and rp, q: pq and qr, r: qr and rp):
        # a pair with a star that does not is dropped before the join (a few dozen of ~1,000 are left). Side
        # rp's pairs are the database's, whose stored angles are to the bit those computed below; but near
        # the database's largest angle (where the catalog's pair search might round a pair out) rp is left
        # to the test below alone. Then the same triangles, in the same order, as joining every pair.
        rp = float(hi[2]) < (1.0 - 1e-9) * self.pair_max_sep_rad
        on1, on2, on3 = _ends(E, st, sp, len(xyz), 3 if rp else 2)
        p_ok, q_ok, r_ok = on1 & on3, on1 & on2, on2 & on3
        # (catalog p, catalog q) of side pq's pairs in both orientations, (i, j) then (j, i): [pair_i, pair_j]
        # and [pair_j, pair_i] of its block, each one copy; the same for side qr's (q, r)
        block = E[st[0]:sp[0]]
        cp, cq = block.T.ravel(), block[:, ::-1].T.ravel()
        keep = p_ok[cp] & q_ok[cq]
        cp, cq = cp[keep], cq[keep]
        block = E[st[1]:sp[1]]
        q2, r2 = block.T.ravel(), block[:, ::-1].T.ravel()
        keep = q_ok[q2] & r_ok[r2]
        q2, r2 = q2[keep], r2[keep]
        if len(cp) * len(q2) <= JOIN_DENSE:
            # every (pq, qr) pair with the same star on q: row-major, so in pq's order and then qr's (by_star's)
            rows, cols = divmod((cq[:, None] == q2).ravel().nonzero()[0], len(q2))  # (1-D nonzero: faster)
            a, b, c = cp.take(rows), cq.take(rows), r2.take(cols)
        else:
            r2s, start, size = by_star(q2, r2, len(xyz))  # side qr's pairs in blocks by their star on q
            cnt = size[cq]
            rows = np.repeat(np.arange(len(cp)), cnt)
            c = r2s[np.repeat(start[cq] - np.cumsum(cnt) + cnt, cnt) + np.arange(int(cnt.sum()))]
            a, b = cp[rows], cq[rows]
        t.setdefault("side_counts", {})[k] = (sp[0] - st[0], sp[1] - st[1])
        if len(a) <= SMALL:  # the usual few: the tests in plain floats, the same numbers
            return self._close_few(t, k, a, b, c, float(lo[2]), float(hi[2]))
        ok = c != a
        a, b, c = a[ok], b[ok], c[ok]
        # side rp: the angle exactly as the database computes its pairs' (for many, first a cheap test on
        # the dot product, a little wider than the bounds: the same triangles as computing every angle)
        if len(a) > SMALL:
            hi_rp = min(float(hi[2]), self.pair_max_sep_rad)
            near = einsum_c("ij,ij->i", xyz[c], xyz[a]) >= np.cos(min(hi_rp + 1e-6, np.pi))
            a, b, c = a[near], b[near], c[near]
        d = angular_distance(xyz[c], xyz[a])
        ok = (d >= lo[2]) & (d <= hi[2]) & (d <= self.pair_max_sep_rad)
        a, b, c = a[ok], b[ok], c[ok]
        if len(a) <= SMALL:  # now few: the rest of the tests in plain floats (the same numbers, side rp again)
            return self._close_few(t, k, a, b, c, float(lo[2]), float(hi[2]))
        tr, trs = float(t["triple"][k]), float(t["triple_sigma"][k])
        ar, da = float(t["area"][k]), float(t["area_bound"][k])
        A, B, C = xyz[a], xyz[b], xyz[c]
        if abs(tr) > self.beta * trs:
            ok = np.sign(sph.triple(A, B, C)) == np.sign(tr)
            a, b, c, A, B, C = a[ok], b[ok], c[ok], A[ok], B[ok], C[ok]
        area = sph.area(A, B, C)
        ok = (area >= ar - da) & (area <= ar + da)
        a, b, c, A, B, C = a[ok], b[ok], c[ok], A[ok], B[ok], C[ok]
        moment = self._moments(t, A, B, C)  # also the observed triangles' left pending by `_ensure`
        if len(a):
            mo, dm = float(t["moment"][k]), float(t["moment_bound"][k])
            ok = (moment >= mo - dm) & (moment <= mo + dm)
            a, b, c = a[ok], b[ok], c[ok]
        return np.stack([a, b, c], axis=1)

    def _close_few(self, t: dict, k: int, a: np.ndarray, b: np.ndarray, c: np.ndarray, lo: float, hi: float
                   ) -> np.ndarray:
        """`join_pairs`' tests of a few joined triangles (catalog stars a, b, c on p, q, r) in plain floats,
        the same numbers as its arrays: r is not p; side rp within [lo, hi] and the database's largest angle
        (the third of `sph.sides_few`, = angular_distance(C, A) as the database computes its pairs'); the
        handedness where the observed sign is certain; the area within its bound (`sph.lhuilier_few` of the
        same sides, = sph.area); the polar moment within its bound (`_moments`). Returns (h, 3) rows."""
        xyz = self.catalog.xyz
        # side rp first by its squared chord, which the angle grows with: outside the bounds' own squared
        # chords, widened far beyond any rounding, no angle can pass (most of the joined triangles; on the
        # arrays, as the joined triangles are a dozen or so and the few left are one or two)
        c_lo = (2.0 * math.sin(lo / 2.0)) ** 2 * (1.0 - 1e-9) if lo > 0.0 else 0.0
        c_hi = (2.0 * math.sin(hi / 2.0)) ** 2 * (1.0 + 1e-9) if hi < math.pi else math.inf
        d = xyz.take(c, axis=0) - xyz.take(a, axis=0)
        chord2 = einsum_c("ij,ij->i", d, d)
        ok = (chord2 >= c_lo) & (chord2 <= c_hi)
        if not c_lo > 0.0:  # r on p has a zero chord: only a zero lower bound keeps it
            ok &= c != a
        near = ok.nonzero()[0]
        abc = np.array((a, b, c)).take(near, axis=1)
        a, b, c = abc.tolist()
        A, B, C = xyz.take(abc, axis=0).tolist()
        # the observed triangle's sides first, in the same call (for `consistent_rows`)
        P, Q, R = t.get("corners", {}).get(k) or t["V"][[t["ti"][k], t["tj"][k], t["tk"][k]]].tolist()
        obs, *sides = sph.sides_few([P] + A, [Q] + B, [R] + C)
        top = self.pair_max_sep_rad
        tr, trs = float(t["triple"][k]), float(t["triple_sigma"][k])
        hand = sph.sign(tr) if abs(tr) > self.beta * trs else None
        keep = [i for i in range(len(a)) if lo <= sides[i][2] <= hi and sides[i][2] <= top
                and (hand is None or sph.sign(sph.dot3(A[i], sph.cross3(B[i], C[i]))) == hand)]
        ar, da = float(t["area"][k]), float(t["area_bound"][k])
        area = sph.lhuilier_few([sides[i] for i in keep])
        keep = [i for i, v in zip(keep, area) if ar - da <= v <= ar + da]
        # also the observed triangles' left pending; lists of vertices make one array in one call
        moment = self._moments(t, [A[i] for i in keep], [B[i] for i in keep], [C[i] for i in keep])
        if keep:
            mo, dm = float(t["moment"][k]), float(t["moment_bound"][k])
            keep = [i for i, v in zip(keep, moment.tolist()) if mo - dm <= v <= mo + dm]
        # which rows `TriangleMethod.consistent` keeps as a chain of this one triangle: its handedness test is
        # the one above, and each side within tol of the observed angle (the same angles: it sums the same
        # chords, or their negatives, and takes numpy's arcsin)
        tol = self.beta * SQ2 * float(t["sigma"])
        t.setdefault("consistent_rows", {})[k] = [all(abs(sides[i][j] - obs[j]) <= tol for j in range(3))
                                                  for i in keep]
        return np.array([(a[i], b[i], c[i]) for i in keep], dtype=np.int64).reshape(-1, 3)

    def _moments(self, t: dict, A, B, C) -> np.ndarray | None:
        """The polar moments of the catalog triangles (A, B, C: (h, 3) arrays, or lists of h 3-vectors)
        (None when there are none), and those of the observed triangles `_measure` / `_measure_one` left
        pending, in one call (np.einsum sums a single column another way, to the last bit, so an observed
        triangle is always computed in a call of two or more triangles, as a batch of `_measure` computes
        it; but the frame's only triangle, which was always computed alone. A lone candidate's moment may
        differ from its own call's in the last bit, far inside the moment bound it is tested against)."""
        pend = t.pop("moment_pending", None)
        corners = t.pop("moment_pending_corners", None)
        if pend is None or len(pend) == 0:
            return sph.polar_moment_few(A, B, C, self.depth) if len(A) else None
        if isinstance(A, list) and corners is not None and corners[0] is pend:
            P, Q, R = corners[1]  # `_measure_one`'s lists of the observed vertices
        else:
            V = t["V"]
            P, Q, R = V[t["ti"][pend]], V[t["tj"][pend]], V[t["tk"][pend]]
            if isinstance(A, list):
                P, Q, R = P.tolist(), Q.tolist(), R.tolist()
        if len(t["area"]) == 1:  # the frame's one triangle: computed alone, as it always was
            self._set_moment(t, pend, sph.polar_moment_few(P, Q, R, self.depth))
            return sph.polar_moment_few(A, B, C, self.depth) if len(A) else None
        # the observed first, then the candidates, in one call of two or more triangles: a column's sum
        # is then the same whatever the others (a lone observed triangle is doubled to make two)
        n = len(pend)
        if isinstance(A, list):
            if A or n == 1:
                P, Q, R = (X + (Y if A else X) for X, Y in ((P, A), (Q, B), (R, C)))
        elif len(A) or n == 1:
            P, Q, R = (np.concatenate([X, Y if len(A) else X]) for X, Y in ((P, A), (Q, B), (R, C)))
        both = sph.polar_moment_few(P, Q, R, self.depth)
        self._set_moment(t, pend, both[:n])
        return both[n:] if len(A) else None

    def oriented_candidates(self, t: dict, k: int, sigma: float
                            ) -> tuple[np.ndarray, Callable[[], list[tuple[int, ...]]]]:
        """The oriented candidates of observed triangle k (rows over (ti, tj, tk)[k]) and a function giving
        the catalog triangles a step draws for them (capped; `LazyStep` calls it if the step is read)."""
        if self.database == "pairs":
            self.count_of(t, k)
            H = t["oriented"][k]
            return H, partial(_distinct_sets, H[:64 * CAP])
        rows = self.candidates(t, k)
        H, src = self.orient(t, k, rows, sigma)
        return H, partial(_groups, self.tri, rows, src)

    def candidates(self, t: dict, m: int) -> np.ndarray:
        """Rows (into self.tri, area order) of the catalog triangles matching observed triangle m:
        the shorter of its two ranges, filtered by the other."""
        self.count_of(t, m)
        rows = t.get("rows", {}).get(m)
        return rows if rows is not None else self._scan(t, m)

    def _scan(self, t: dict, m: int) -> np.ndarray:
        """The candidate rows of observed triangle m: its two ranges intersected, then the triangles
        that fit this camera (enclosing cap <= its half-diagonal)."""
        s1, e1, s2, e2 = int(t["s1"][m]), int(t["e1"][m]), int(t["s2"][m]), int(t["e2"][m])
        if e1 - s1 <= e2 - s2:
            r = self.moment_rank[s1:e1]
            rows = s1 + np.flatnonzero((r >= s2) & (r < e2))
        else:
            p = self.moment_order[s2:e2].astype(np.int64)
            rows = np.sort(p[(p >= s1) & (p < e1)])
        return rows[self.cap[rows] <= self.cap_limit]

    def orient(self, t: dict, m: int, rows: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
        """Hypotheses of observed triangle m from candidate rows: (h, 3) catalog stars for the observed
        stars (ti, tj, tk)[m], and the candidate row each came from.

        vertex_order="sides": the vertex orders whose sides match the observed sides within
        beta sigma_p and whose handedness (sign of the triple product) is the observed one when that
        sign is certain. vertex_order="paper": every one of the 6 orders (the paper matches triangles
        by area and polar moment only; the join and the final resolution sort the orders out).
        """
        self._ensure(t, m)
        if len(rows) == 0:
            return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
        cat = self.tri[rows].astype(np.int64)  # (r, 3)
        if self.vertex_order == "paper":
            H = cat[:, _PERMS].reshape(-1, 3)
            return H, np.repeat(rows, len(_PERMS))
        P = self.catalog.xyz[cat]  # (r, 3, 3)
        S = np.stack(sph.sides(P[:, 0], P[:, 1], P[:, 2]), axis=1)  # ij, jk, ki
        sgn = np.sign(sph.triple(P[:, 0], P[:, 1], P[:, 2]))
        obs_sides = t["sides"][m]  # pq, qr, rp
        tol = self.beta * SQ2 * sigma
        tr, trs = float(t["triple"][m]), float(t["triple_sigma"][m])
        check_hand = abs(tr) > self.beta * trs
        keep_rows, keep_perm = [], []
        for k, perm in enumerate(_PERMS):
            sp_ = S[:, [_SIDE[perm[0], perm[1]], _SIDE[perm[1], perm[2]], _SIDE[perm[2], perm[0]]]]
            ok = np.all(np.abs(sp_ - obs_sides[None, :]) <= tol, axis=1)
            if check_hand:
                ok &= sgn * _PARITY[k] == np.sign(tr)
            idx = np.flatnonzero(ok)
            keep_rows.append(idx)
            keep_perm.append(np.full(len(idx), k))
        idx = np.concatenate(keep_rows)
        perm = _PERMS[np.concatenate(keep_perm)]
        H = np.take_along_axis(cat[idx], perm, axis=1)
        return H, rows[idx]


# ---------------------------------------------------------------------- helpers

@lru_cache(maxsize=64)
def _combinations(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (i < j < k) of n stars, as three index arrays (read-only, cached)."""
    c = np.fromiter(itertools.chain.from_iterable(itertools.combinations(range(n), 3)), dtype=np.int64)
    c = c.reshape(-1, 3)
    out = tuple(np.ascontiguousarray(c[:, s]) for s in range(3))
    for a in out:
        a.flags.writeable = False
    return out


def _ends(E: np.ndarray, st: list[int], sp: list[int], n: int, sides: int) -> np.ndarray:
    """Which of n catalog stars end one of the pairs E[st[s]:sp[s]] ((pairs, 2): both stars of each) of
    each of the first `sides` sides s, as (3, n) booleans (a side left out: every star)."""
    on = np.zeros((3, n), dtype=bool)
    for s in range(sides):
        row = on[s]  # (a 1-D scatter is faster than on[s, index])
        row[E[st[s]:sp[s]]] = True  # both stars of each pair: one contiguous block of the database
    if sides < 3:
        on[sides:] = True
    return on


@lru_cache(maxsize=64)
def _side_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of n stars ((2, n_pairs): np.triu_indices(n, 1)) and, for every triangle of
    `_combinations(n)`, a (4, n_triangles) index into their angles with one more, zero entry appended:
    that zero, then the pairs of the sides ij, jk and ik (read-only, cached)."""
    ii, jj = np.triu_indices(n, 1)
    pair = np.full((n, n), -1, dtype=np.intp)
    pair[ii, jj] = np.arange(len(ii))
    ti, tj, tk = _combinations(n)
    out = (np.stack([ii, jj]), np.stack([np.full(len(ti), len(ii)), pair[ti, tj], pair[tj, tk], pair[ti, tk]]))
    for a in out:
        a.flags.writeable = False
    return out


def _n_sets(H: np.ndarray) -> int:
    """How many distinct sets of catalog stars the hypotheses hold (vertex orders of one set count once).

    A set is keyed by the wrapping sum of a fixed random 64-bit word per catalog star: independent
    of the order, and two different sets collide with probability 2^-64.
    """
    if len(H) <= 1:
        return len(H)
    words = _star_words(int(H.max()) + 1)
    key = np.sort(words[H].sum(axis=1, dtype=np.uint64))
    return 1 + int(np.count_nonzero(key[1:] != key[:-1]))


def _distinct_sets(H: np.ndarray) -> list[tuple[int, ...]]:
    """The first CAP distinct star sets of the (h, 3) rows H, each sorted, in sorted order
    (= np.unique(np.sort(H, axis=1), axis=0)[:CAP], by one integer key per set)."""
    if not len(H):
        return []
    if H.size <= SMALL:  # the usual one or few: tuples (ints below m sort as their keys do)
        return sorted({tuple(sorted(r)) for r in H.tolist()})[:CAP]
    S = np.sort(H, axis=1).astype(np.int64)
    m = int(S[:, 2].max()) + 1
    key = np.sort((S[:, 0] * m + S[:, 1]) * m + S[:, 2])
    keep = np.empty(len(key), dtype=bool)
    keep[0] = True
    np.not_equal(key[1:], key[:-1], out=keep[1:])
    key = key[keep][:CAP]
    return list(zip(*(x.tolist() for x in (key // (m * m), key // m % m, key % m))))


_WORDS = np.zeros(0, dtype=np.uint64)


def _star_words(n: int) -> np.ndarray:
    """The first n of a fixed sequence of random 64-bit words (grown on demand, same for every run)."""
    global _WORDS
    if len(_WORDS) < n:
        size = max(n, 2 * len(_WORDS), 8192)
        _WORDS = np.random.default_rng(0x5E75).integers(0, np.iinfo(np.uint64).max, size=size, dtype=np.uint64,
                                                        endpoint=True)
    return _WORDS


def _groups(tri: np.ndarray, rows: np.ndarray, oriented_rows: np.ndarray) -> list[tuple[int, ...]]:
    """Candidate catalog triangles to draw, those that fit in some vertex order first, capped."""
    if len(oriented_rows) == len(_PERMS) * len(rows):  # vertex_order="paper": every candidate
        return list(map(tuple, tri[rows[:CAP]].astype(int).tolist()))
    first = np.unique(oriented_rows[:64 * CAP])[:CAP]
    if len(first) < CAP and len(rows) > len(first):
        rest = rows[~np.isin(rows, first)][:CAP - len(first)]
        first = np.concatenate([first, rest])
    return list(map(tuple, tri[first].astype(int).tolist()))
