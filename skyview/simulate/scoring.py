"""Scoring against the truth: the one module the bench and the sinks call.

A method never sees the truth. What the simulator drew (its truth sidecar: the attitude, the stars and
false stars it rendered) is compared with what a solve found here, after the fact:

    score_trial         correct / incorrect / inconclusive, and the wrong matches
    centroid_outcomes   per centroid: identified / unidentified / false star / wrong match / not used
    truth_rows          the catalog row of each centroid (-1: a false star or nothing drawn there)
    true_posterior      per step, the probability a method's posterior (a `Posterior` layer) gives the
                        true star, and its rank among the stars
    sequence_truth      per frame of a sequence: the designated star's true row, its posterior and rank,
                        and the posterior of the true sequence (the hypothesis that started on the true
                        star), read from the frames' Posterior layers

The geometry of the match (which centroid lies on which rendered star) is `skyview.simulate.truth`'s.
"""

from __future__ import annotations

import numpy as np

from skyview.identify.layers import Posterior, posterior_figures
from skyview.simulate.truth import centroid_truth, wrong_matches


def score_trial(result, truth: dict) -> tuple[str, list[int]]:
    """Outcome of one solve against the truth sidecar, and the wrong match indices."""
    if not result.solved:
        return "inconclusive", []
    wrong = wrong_matches([(m["index"], m["u"], m["v"], m["hip"]) for m in result.matches], truth)
    return ("incorrect" if wrong else "correct"), wrong


def truth_rows(uv: np.ndarray, truth: dict, catalog) -> np.ndarray:
    """The catalog row of each centroid at `uv` (-1: nothing rendered there, a false star, or a star not in
    `catalog`), from a simulator truth sidecar."""
    rows = []
    for hip in centroid_truth(np.asarray(uv, dtype=np.float64).reshape(-1, 2), truth):
        try:
            rows.append(catalog.index_of(hip) if hip is not None and hip >= 0 else -1)
        except KeyError:
            rows.append(-1)
    return np.array(rows, dtype=np.int64)


def centroid_outcomes(n_centroids: int, n_used: int, matches: dict[int, int], uv: np.ndarray,
                      catalog_hip: np.ndarray, truth: dict | None) -> list[str]:
    """Per centroid: identified / unidentified / false star / wrong match / not used.

    With truth, a match that is not the star the simulator drew there is a 'wrong match', and an
    unmatched centroid on a false star a 'false star'. 'not used': fainter than the brightest stars the
    identifier was given.
    """
    rendered = centroid_truth(np.asarray(uv, dtype=np.float64).reshape(-1, 2), truth) if truth else [None] * n_centroids
    out = []
    for i in range(n_centroids):
        if i in matches:
            out.append("wrong match" if truth and rendered[i] != int(catalog_hip[matches[i]]) else "identified")
        elif truth and rendered[i] == -1:
            out.append("false star")
        elif i >= n_used:
            out.append("not used")
        else:
            out.append("unidentified")
    return out


def true_posterior(steps, true_row: int) -> list[tuple[float, int] | None]:
    """Per step: (the probability the step's posterior gives catalog row `true_row`, its rank among the
    stars, 0 = leading; -1 when outside the stars it ranks), or None for a step without a posterior.

    The posterior of a star is the sum over the hypotheses that designate it (`Posterior.per_star`)."""
    out: list[tuple[float, int] | None] = []
    for st in steps:
        post = st.layer(Posterior)
        if post is None or true_row < 0:
            out.append(None)
            continue
        rows = np.asarray(post.rows, dtype=np.int64)
        w = np.nan_to_num(np.asarray(post.weights, dtype=np.float64))
        mass = float(w[rows == true_row].sum())
        star = np.bincount(rows, weights=w)
        rank = int(np.sum(star > mass)) if mass > 0 else -1
        out.append((mass, rank))
    return out


def last_true_posterior(steps, true_row: int) -> float | None:
    """The true star's probability under the last posterior of `steps` (None: no posterior)."""
    vals = [v for v in true_posterior(steps, true_row) if v is not None]
    return vals[-1][0] if vals else None


def frame_truth(steps, rows: np.ndarray | None) -> dict:
    """The truth of one frame of a sequence, scored here (never by the method): the catalog row of the
    designated star (the observed star its posterior step updates on; `rows` the true row of every
    observed star, `truth_rows`) and the probability the frame's posterior gives it."""
    fig = posterior_figures(steps)
    if fig is None or rows is None or fig["designated"] is None or fig["designated"] >= len(rows):
        return {"true_row": None, "true_posterior": None}
    true_row = int(rows[fig["designated"]])
    return {"true_row": true_row if true_row >= 0 else None,
            "true_posterior": last_true_posterior(steps, true_row) if true_row >= 0 else None}


def sequence_truth(identifications, rows) -> list[dict]:
    """Per frame of a sequence method's result, scored against the truth here (the method never sees it):
    true_row (the true catalog row of the frame's designated star, `frame_truth`), true_posterior and
    true_rank (its probability under the frame's posterior and its rank among the stars, 0 = leading),
    true_sequence_posterior (the weight of the hypothesis that started on the true star of the first
    frame with a posterior: hypothesis h starts on catalog row h, the paper's Table 1).

    rows: per frame, the true catalog row of every observed star (-1: a false star), or None (then
    every figure is None). A frame without a posterior (nothing to designate) keeps the last weights."""
    out = []
    start = None  # the true row of the first designated star: the true sequence's hypothesis
    weights = None
    for k, r in enumerate(identifications):
        steps = r.steps
        f = frame_truth(steps, None if rows is None else rows[k])
        post = next((s.layer(Posterior) for s in reversed(list(steps)) if s.layer(Posterior) is not None), None)
        f["true_rank"] = None
        if f["true_row"] is not None:
            f["true_rank"] = [v for v in true_posterior(steps, f["true_row"]) if v is not None][-1][1]
        if post is not None:
            weights = np.asarray(post.weights, dtype=np.float64)
            if start is None and rows is not None:
                start = f["true_row"] if f["true_row"] is not None else -1
        f["true_sequence_posterior"] = (float(weights[start]) if weights is not None and start is not None
                                        and 0 <= start < len(weights) else None)
        out.append(f)
    return out
