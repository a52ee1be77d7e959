"""The ellipticity method's first hypothesis for many frames at once (a coverage sweep's hot path).

`EllipticityMethod.hypotheses` walks one frame: the pivot nearest the boresight, its adjacent stars,
the patterns of their 3-subsets in order, each pattern's eps window and angle test, the candidates
of a pattern best first. On a sweep almost every frame is decided by the first hypothesis that walk
yields (on Sun's grid: every orientation makes one verification), and the walk up to it costs more
than the verification. `first_hypotheses` takes the same walk for a list of frames as arrays: every
frame's pivot and adjacent stars in one pass, then the first pattern of every frame, then the rest
of the patterns of the frames whose first pattern found no candidate. Each number is computed by the
same operations as the walk's (an SVD of each 3 x 4 matrix, the same searchsorted windows, the same
cost and the same first-minimum), so each frame's first hypothesis is the one `hypotheses` yields
first. The rounds go on to the next pivot (passing over a pivot with fewer than 3 adjacent stars, up to
max_pivots, the paper's variant stopping after its first) for the frames whose pivot found no candidate. A
frame whose walk would find none at all gets `NoHypothesis`, with the reason the walk gives; a frame with
fewer stars than the method needs gets None (the caller identifies it with `identify`).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations, permutations

import numpy as np

from skyview.identify.verify import angular_distance

BORESIGHT = np.array([0.0, 0.0, 1.0])
PERMUTATIONS = np.array(list(permutations(range(3))), dtype=np.int64)  # (`_assign`'s order, the identity first)


@dataclass(frozen=True)
class NoHypothesis:
    """A frame whose walk yields no hypothesis at all (no pattern of any pivot it takes has a database
    candidate): the reason `identify` gives it (`EllipticityMethod.failure_reason` of the walk's reasons)."""

    reason: str


def first_hypotheses(method, V_list: list[np.ndarray], sigmas: np.ndarray
                     ) -> list[dict[int, int] | NoHypothesis | None]:
    """For each frame (V_list[f]: (n_f, 3) camera-frame unit vectors, brightest first; sigmas[f]: its sigma)
    the first hypothesis (observed index -> catalog row) `method.hypotheses` would yield; `NoHypothesis`
    where it would yield none; None where the batch leaves the frame to `identify` (fewer stars than the
    method needs)."""
    F = len(V_list)
    out: list[dict[int, int] | NoHypothesis | None] = [None] * F
    counts = np.array([len(v) for v in V_list], dtype=np.int64)
    live = np.flatnonzero(counts >= method.min_stars)
    if len(live) == 0:
        return out
    n_max = int(counts[live].max())
    Vp = np.full((len(live), n_max, 3), np.nan)
    for a, f in enumerate(live.tolist()):
        Vp[a, :counts[f]] = V_list[f]
    sig = np.asarray(sigmas, dtype=np.float64)[live]

    # the pivots: observed stars by angle from the boresight (argsort, stable), within the critical value
    offset = angular_distance(Vp, BORESIGHT)
    order = np.argsort(np.where(np.isnan(offset), np.inf, offset), axis=1, kind="stable")
    rows = np.arange(len(live))
    within = offset[rows[:, None], order] <= method.pivot_radius  # (NaN: a padded star, never within)
    tol_theta = (method.beta * np.sqrt(2.0) * sig if method.adaptive_thresholds
                 else np.full(len(live), method.angle_threshold))
    theta_lo = method.theta_min - (tol_theta if method.theta_min_slack else np.zeros(len(live)))
    k_adj = method.n_adjacent
    subsets = np.array(list(combinations(range(k_adj), 3)), dtype=np.int64)  # (the walk's order)
    tried = np.zeros(len(live), dtype=np.int64)
    # the walk's failure reasons of a frame that finds no candidate: how many, and the last
    n_reasons = np.zeros(len(live), dtype=np.int64)
    last: list[str] = [""] * len(live)
    todo = rows
    for rank in range(n_max):
        todo = todo[within[todo, rank] & (tried[todo] < method.max_pivots)]
        if len(todo) == 0:
            break
        pivot = order[todo, rank]
        # its adjacent stars: the n_adjacent nearest no closer than theta_lo, in order of angle (stable)
        ang = angular_distance(Vp[todo], Vp[todo, pivot][:, None, :])
        near = ang >= theta_lo[todo, None]  # (NaN: a padded star, never near)
        adj = np.argsort(np.where(near, ang, np.inf), axis=1, kind="stable")[:, :k_adj]
        n_adj = np.minimum(near.sum(axis=1), k_adj)
        enough = n_adj >= 3  # (a pivot with fewer is passed over: the walk takes the next)
        tried[todo[enough]] += 1
        gone = enough.copy() if not method.next_pivot else np.zeros(len(todo), dtype=bool)
        decided = _decide(method, out, live, Vp, sig, tol_theta, todo[enough], pivot[enough], adj[enough],
                          n_adj[enough], subsets)
        gone[enough] |= decided
        for i in np.flatnonzero(~enough).tolist():
            a = int(todo[i])
            n_reasons[a] += 1
            last[a] = f"pivot {int(pivot[i])} has {int(n_adj[i])} adjacent star(s) in the image"
        for i in np.flatnonzero(enough)[~decided].tolist():  # every pattern of the pivot without a candidate
            a, k = int(todo[i]), int(n_adj[i])
            n_reasons[a] += k * (k - 1) * (k - 2) // 6
            last[a] = f"no pattern matches pivot {int(pivot[i])} with adjacent {adj[i, k - 3:k].tolist()}"
        # a frame whose pivot found no candidate: the next pivot (the paper's method stops there)
        todo = todo[~gone]
    radius_deg = np.degrees(method.pivot_radius)
    for a, f in enumerate(live.tolist()):
        if out[f] is not None:
            continue
        if not within[a, 0]:
            out[f] = NoHypothesis(f"no observed star within {radius_deg:g} deg of the boresight")
            continue
        n, reason = int(n_reasons[a]), last[a]
        if tried[a] == 0:
            n, reason = n + 1, f"no pivot within {radius_deg:g} deg of the boresight has 3 adjacent stars in the image"
        out[f] = NoHypothesis(reason if n == 1 else f"{n} failures, the last: {reason}")
    return out


def _decide(method, out, live, Vp, sig, tol_theta, frames, pivot, adj, n_adj, subsets) -> np.ndarray:
    """The first hypothesis of each of `frames` (rows of Vp) from the patterns of its pivot and adjacent
    stars, written to out[live[frame]]: the first pattern (in the walk's order) with a candidate, its best
    candidate. Returns the mask of the frames decided."""
    done = np.zeros(len(frames), dtype=bool)
    todo = np.arange(len(frames))
    # the first pattern of every frame, then the next patterns in growing runs for the frames still undecided
    # (most frames are decided by their first pattern; an SVD is ~3 us a pattern)
    for a, b in ((0, 1), (1, 4), (4, 16), (16, len(subsets))):
        chunk = subsets[a:b]
        if len(todo) == 0 or len(chunk) == 0:
            break
        t_idx = np.repeat(todo, len(chunk))
        s_idx = np.tile(np.arange(len(chunk)), len(todo))
        fits = chunk.max(axis=1)[s_idx] < n_adj[t_idx]  # the subsets of the adjacent stars the frame has
        t_idx, s_idx = t_idx[fits], s_idx[fits]
        a_idx = frames[t_idx]
        obs_idx = np.concatenate([pivot[t_idx, None], adj[t_idx[:, None], chunk[s_idx]]], axis=1)  # (m, 4)
        m, k, th = _first_candidates(method, Vp[a_idx[:, None], obs_idx], sig[a_idx], tol_theta[a_idx])
        # a frame's first pattern with a candidate (patterns ascend within a frame, frames within the run)
        first = np.unique(t_idx[m], return_index=True)[1]
        m, k, th = m[first], k[first], th[first]
        t, a = t_idx[m], a_idx[m]
        done[t] = True
        rows = method.stars[k]
        if method.resolve_ties:  # (`_assign`: only where another order of the adjacent stars fits too)
            cat = method.theta[k][:, PERMUTATIONS]  # (n, 6, 3), the identity first
            fits = np.all(np.abs(th[:, None, :] - cat) <= tol_theta[a, None, None], axis=2).sum(axis=1)
            for i in np.flatnonzero(fits > 1).tolist():
                rows[i] = method._assign(Vp[a[i], obs_idx[m[i]]], int(k[i]), th[i], float(tol_theta[a[i]]),
                                         float(sig[a[i]]))
        for i, o, r in zip(live[a].tolist(), obs_idx[m].tolist(), rows.tolist()):
            out[i] = dict(zip(o, r))
        todo = todo[~done[todo]]
    return done


def _first_candidates(method, W: np.ndarray, sigma: np.ndarray, tol_theta: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The patterns (W: (m, 4, 3) observed vectors, the pivot first) with a database candidate within the
    thresholds, ascending; each one's best candidate (a database row) and its pivot-adjacent angles.
    The numbers of `_pivot`."""
    eps, theta, _, tol_eps, _, _, pos, seg = pattern_lookup(method, W, sigma, tol_theta)
    # the first of the smallest cost in each pattern (np.argsort(cost, kind="stable")[0] of its hits)
    cost = ((method.eps[pos] - eps[seg]) / tol_eps[seg]) ** 2 + np.sum(
        ((method.theta[pos] - theta[seg]) / tol_theta[seg, None]) ** 2, axis=1)
    order = np.lexsort((np.arange(len(pos)), cost, seg))
    first = order[np.r_[True, seg[order][1:] != seg[order][:-1]]] if len(pos) else order
    return seg[first], pos[first], theta[seg[first]]


def pattern_lookup(method, W: np.ndarray, sigma, tol_theta: np.ndarray) -> tuple[np.ndarray, ...]:
    """The method's look-up of observed patterns W ((m, 4, 3) unit vectors, the pivot first; sigma: one, or
    one per pattern; tol_theta (m,): each one's angle threshold): (eps, theta (m, 3), the singular values
    (m, 3), the eps thresholds, the eps windows' first and end rows lo and hi, and the database rows
    within every threshold with their patterns (pos, seg, seg ascending)). One SVD of each 3 x 4 matrix,
    a binary search of the eps column, the angle test on every window at once (a ragged gather)."""
    A = np.swapaxes(W, 1, 2)
    U, s, Vt = _svd_3x4(A)
    eps = s[:, 2] / s[:, 1]
    theta = angular_distance(W[:, 1:, :], W[:, :1, :])
    if method.adaptive_thresholds:
        tol_eps = method.beta * eps_sigma_stacked(A, U, s, Vt, sigma)
    else:
        tol_eps = np.full(len(eps), method.eps_threshold)
    lo = np.searchsorted(method.eps, eps - tol_eps, side="left")
    hi = np.searchsorted(method.eps, eps + tol_eps, side="right")
    cnt = hi - lo
    seg = np.repeat(np.arange(len(W)), cnt)
    pos = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(lo, cnt)
    hit = np.all(np.abs(method.theta[pos] - theta[seg]) <= tol_theta[seg, None], axis=1)
    return eps, theta, s, tol_eps, lo, hi, pos[hit], seg[hit]


def _svd_3x4(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The thin SVD (U, s, Vt) of a stack of (m, 3, 4) matrices from the eigen-decomposition of A A^T
    (m, 3, 3): s the square roots of its eigenvalues, largest first, U its eigenvectors, Vt = U^T A / s.
    LAPACK's batched 3 x 3 symmetric eigensolver takes about half the time of its 3 x 4 SVD (a coverage
    sweep looks up ~350 patterns at a time). The smallest singular value (a pattern's departure from a
    plane, ~0.005 for 20 deg patterns) comes from its square, to ~1e-16 of the largest (~4): 1e-11 of it
    relative at 20 deg, ~1e-7 at 1 deg, where eps's own threshold (beta sigma_eps) is ~1e-3 of it. A
    zero singular value (a degenerate pattern) gives a row of Vt of NaN, as a zero eps gives its threshold."""
    lam, Ue = np.linalg.eigh(A @ np.swapaxes(A, 1, 2))  # ascending eigenvalues
    s = np.sqrt(np.maximum(lam[:, ::-1], 0.0))
    U = Ue[:, :, ::-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        Vt = (np.swapaxes(U, 1, 2) @ A) / s[:, :, None]
    return U, s, Vt


def eps_sigma_stacked(A: np.ndarray, U: np.ndarray, s: np.ndarray, Vt: np.ndarray, sigma_rad: float) -> np.ndarray:
    """`ellipticity.eps_sigma` for a stack of (m, 3, 4) pattern matrices, from their SVD (sigma_rad: one, or
    one per pattern)."""
    eps = s[:, 2] / s[:, 1]
    g = U[:, :, 2, None] * Vt[:, 2, None, :] - eps[:, None, None] * U[:, :, 1, None] * Vt[:, 1, None, :]
    gt = g - A * np.sum(g * A, axis=1, keepdims=True)
    return sigma_rad * np.sqrt(np.sum(gt * gt, axis=(1, 2))) / s[:, 1]
