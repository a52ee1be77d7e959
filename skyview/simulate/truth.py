"""Scoring a solve against a simulator truth sidecar (shared by the CLI, the bench and the viewer)."""

from __future__ import annotations

import numpy as np

MATCH_RADIUS_PX = 3.0


def truth_points(truth: dict) -> tuple[np.ndarray, list[int]]:
    """Where the simulator put light: rendered stars (noisy positions) and false stars (HIP -1)."""
    pts = ([(s["u_noisy"], s["v_noisy"]) if "u_noisy" in s else (s["u"], s["v"]) for s in truth.get("stars", [])]
           + [(f["u"], f["v"]) for f in truth.get("false_stars", [])])
    hips = [int(s["hip"]) for s in truth.get("stars", [])] + [-1] * len(truth.get("false_stars", []))
    return np.array(pts, dtype=np.float64).reshape(-1, 2), hips


def wrong_matches(matches: list[tuple[int, float, float, int]], truth: dict,
                  radius_px: float = MATCH_RADIUS_PX) -> list[int]:
    """Indices of (index, u, v, hip) matches that are not the star rendered at (u, v)."""
    from scipy.spatial import cKDTree  # here: scipy.spatial costs ~0.1 s to import, a solve without truth needs none

    pts, hips = truth_points(truth)
    tree = cKDTree(pts) if len(pts) else None
    wrong = []
    for index, u, v, hip in matches:
        if tree is None:
            wrong.append(index)
            continue
        d, j = tree.query([u, v])
        if d > radius_px or hips[j] != hip:
            wrong.append(index)
    return wrong


def centroid_truth(uv: np.ndarray, truth: dict, radius_px: float = MATCH_RADIUS_PX) -> list[int | None]:
    """For each centroid, the HIP rendered there (-1 for a false star), or None when nothing was."""
    pts, hips = truth_points(truth)
    if len(pts) == 0 or len(uv) == 0:
        return [None] * len(uv)
    from scipy.spatial import cKDTree

    d, j = cKDTree(pts).query(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    return [hips[k] if dist <= radius_px else None for dist, k in zip(d, j)]
