"""Identification steps and results -> drawable geometry, without a viewer.

Everything here is plain numpy on the objects the CLI uses (`SolveResult`, `Identification`, `Step`)
and the guide catalog the solver used (step rows index it). The viewer draws what this module
returns; it knows no method. A method shows up in the viewer through what its steps record:

- `observed`: observed-star indices it used (highlighted on the image; 2 to 4 of them are joined
  into the pattern: a pair, a triangle, a quad);
- `catalog`: candidate catalog rows (lit on the sphere);
- `groups`: candidate catalog tuples (pairs, triangles, ...), drawn as great-circle arcs;
- `numbers`: shown as a table, and any of them can be plotted across the steps;
- `extra` (the same conventions as the Rerun recorder):
  - an (N, 3) float array of unit vectors (or one 3-vector) is drawn as points on the sphere (a GA
    population, a boresight); a 1-D float array of the same length tints them, high values bright,
    except a cost (a name with "cost"), whose lowest is brightest (+inf: an invalid individual);
  - a 3x3 rotation is an attitude: its sensor footprint is drawn;
  - a dict that outlines a region of the sky (`skyview.sky_geometry.outline_polyline`) is drawn as a
    closed line on the sphere: with "corners" ((K, 3) unit vectors, K >= 3) a polygon whose edges are
    great-circle arcs; else with "center" (a unit 3-vector) and "radius_rad" the small circle at that
    angular radius (a GA's search box: a square, or the circle of its roll chromosomes); its other
    entries go to the step's text, and a dict with neither is text only;
  - a 1-D float array as long as `catalog` is a weight per candidate (a posterior) and tints the
    candidates; one as long as the whole guide catalog lights its highest-weighted stars, tinted on
    a log scale (summed per star first when an integer array of the same length maps each weight
    to a catalog row: hypotheses that have moved to other stars, as after a known turn);
  - everything else is summarised in the step's text.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import Delaunay, QhullError

from skyview.sky_geometry import arcs_as_segments, group_edges, outline_polyline, polylines_as_segments
from skyview.truth import centroid_truth

# Numbers plotted across the steps by default, first found wins (with a `_after` variant first).
DEFAULT_PLOT_KEYS = ("hypotheses", "candidates")
ARC_POINTS = 3  # points per candidate arc: seen from the sphere's centre a chord already is the arc
OUTCOMES = ("identified", "unidentified", "false star", "wrong match", "not used")
SKY_WEIGHT_TOP = 300  # stars lit from a whole-catalog weight (a posterior over the catalog)
SKY_WEIGHT_FLOOR = 1e-3  # ... down to this fraction of the highest weight


@dataclass
class StepDrawable:
    """What to draw for one step."""

    index: int
    kind: str
    note: str
    observed: np.ndarray  # observed-star indices (ints), valid ones only
    pattern: np.ndarray  # (E, 2) edges between observed stars (the pair / triangle the step measured)
    candidates: np.ndarray  # catalog rows to light up
    segments: np.ndarray  # (S, 2, 3) float32 arcs on the unit sphere for the candidate groups
    n_groups: int
    numbers: dict[str, float]
    weights: np.ndarray | None = None  # per candidate, in [0, 1], when the step carries one
    weight_name: str = ""
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # extra directions
    point_weights: np.ndarray | None = None  # per point, in [0, 1]
    points_name: str = ""
    attitudes: list[np.ndarray] = field(default_factory=list)  # 3x3 rotations whose footprint is drawn
    outlines: list[np.ndarray] = field(default_factory=list)  # closed polylines (M, 3) on the sphere
    outline_segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3), np.float32))  # the same
    outline_names: str = ""
    extras: list[str] = field(default_factory=list)  # one line per extra not drawn


def _valid_rows(rows, n_catalog: int) -> np.ndarray:
    a = np.asarray(list(rows), dtype=np.int64).reshape(-1)
    return a[(a >= 0) & (a < n_catalog)]


def pattern_edges(observed: np.ndarray) -> np.ndarray:
    """Edges joining 2 to 4 observed stars in the order given (a pair, a closed triangle or quad)."""
    obs = [int(i) for i in observed]
    if len(obs) == 2:
        return np.array([[obs[0], obs[1]]], dtype=np.int64)
    if 3 <= len(obs) <= 4:
        return np.array([[obs[k], obs[(k + 1) % len(obs)]] for k in range(len(obs))], dtype=np.int64)
    return np.zeros((0, 2), dtype=np.int64)


def _normalised(a: np.ndarray) -> np.ndarray:
    """To [0, 1] over the finite values' range; +inf at the top (an invalid individual's cost), -inf and
    NaN at the bottom."""
    a = np.asarray(a, dtype=np.float64)
    fin = np.isfinite(a)
    if not fin.any():
        return np.ones_like(a)
    lo, hi = float(a[fin].min()), float(a[fin].max())
    a = np.where(a == np.inf, hi, np.where(fin, a, lo))
    return (a - lo) / (hi - lo) if hi > lo else np.ones_like(a)


def _float_array(val, finite: bool = True) -> np.ndarray | None:
    """`val` as a float array (all finite, or with finite=False at least one finite value), else None."""
    if isinstance(val, (list, tuple, np.ndarray)):
        try:
            a = np.asarray(val)
        except (ValueError, TypeError):
            return None
        if a.dtype.kind == "f" and a.size and (np.all(np.isfinite(a)) if finite else np.any(np.isfinite(a))):
            return a
    return None


def _is_rotation(a: np.ndarray) -> bool:
    return a.shape == (3, 3) and np.abs(a @ a.T - np.eye(3)).max() < 1e-6 and np.linalg.det(a) > 0


def _unit_rows(a: np.ndarray) -> np.ndarray | None:
    rows = a.reshape(1, 3) if a.shape == (3,) else a
    if rows.ndim == 2 and rows.shape[1] == 3 and len(rows) and np.abs(np.linalg.norm(rows, axis=1) - 1).max() < 1e-3:
        return rows.astype(np.float64)
    return None


def classify_extras(step, n_candidates: int, catalog_xyz: np.ndarray, hip: np.ndarray | None = None,
                    dict_cache: dict | None = None) -> dict:
    """Sort a step's extras into what the viewer draws (see the module docstring) and text.

    dict_cache: (key, id) -> (dict, outline, text) of the dict extras already seen (a GA stage's steps
    share one box dict), kept by the caller for one list of live steps."""
    out = {"weights": None, "weight_name": "", "points": [], "point_keys": [], "attitudes": [], "text": [],
           "outlines": [], "outline_keys": []}
    series: dict[str, np.ndarray] = {}
    labels: dict[str, str] = {}
    for key, val in step.extra.items():
        if isinstance(val, dict):
            seen = dict_cache.get((key, id(val))) if dict_cache is not None else None
            if seen is None or seen[0] is not val:
                seen = (val, outline_polyline(val), summarise_extra(key, val, hip))
                if dict_cache is not None:
                    dict_cache[(key, id(val))] = seen
            if seen[1] is not None:
                out["outlines"].append(seen[1])
                out["outline_keys"].append(key)
            out["text"].append(seen[2])
            continue
        a = _float_array(val)
        if a is not None and _is_rotation(a):
            out["attitudes"].append(a.astype(np.float64))
            continue
        rows = _unit_rows(a) if a is not None else None
        if rows is not None:
            out["points"].append(rows)
            out["point_keys"].append(key)
            continue
        if a is not None and a.ndim == 1:
            if out["weights"] is None and n_candidates > 0 and len(a) == n_candidates == len(step.catalog):
                out["weights"], out["weight_name"] = _normalised(a), key
                continue
            if len(a) == len(catalog_xyz) and len(a) > SKY_WEIGHT_TOP:
                stars, w, by = sky_weights(a, step.extra, len(catalog_xyz))
                out["points"].append(np.asarray(catalog_xyz, dtype=np.float64)[stars])
                out["point_keys"].append(key)
                series[key] = w
                out["log_tint"] = key
                labels[key] = f"{key} (summed per star by {by})" if by else key
                continue
            series[key] = a
        elif a is None:  # a series with some non-finite values (costs of invalid individuals) still tints
            loose = _float_array(val, finite=False)
            if loose is not None and loose.ndim == 1:
                series[key] = loose
        out["text"].append(summarise_extra(key, val, hip))
    # a series as long as a set of points tints them (the population's costs)
    out["point_weights"] = None
    if len(out["points"]) == 1:
        n = len(out["points"][0])
        key = out["point_keys"][0]
        same = [k for k, v in series.items() if len(v) == n]
        pick = key if key in series else (same[0] if same else None)
        if pick is not None:
            w = series[pick]
            if out.get("log_tint") == pick:
                out["point_weights"] = _log_normalised(w)
            elif "cost" in pick.lower():  # a cost: the lowest (the best individual) brightest
                out["point_weights"] = 1.0 - _normalised(w)
            else:
                out["point_weights"] = _normalised(w)
            out["point_keys"] = [f"{key} (tinted by {pick})" if pick != key else key]
    out["point_keys"] = [labels.get(k, k) for k in out["point_keys"]]
    return out


def sky_weights(a: np.ndarray, extra: dict, n_catalog: int) -> tuple[np.ndarray, np.ndarray, str]:
    """The stars to light for a weight over the whole catalog: (rows, weights, name of the row map).

    When the step also carries a 1-D integer array of the same length whose values are catalog rows
    (the star each hypothesis designates now, e.g. the stochastic method's `rows` after a turn), the
    weights are hypotheses' and are summed per star first; otherwise weight i is catalog row i. The
    SKY_WEIGHT_TOP highest are kept, down to SKY_WEIGHT_FLOOR of the highest when the weights are
    positive (a converged posterior lights its few leading stars, not 300).
    """
    w = np.nan_to_num(np.asarray(a, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    by = ""
    for key, val in extra.items():
        r = np.asarray(val) if isinstance(val, (list, tuple, np.ndarray)) else None
        if r is not None and r.dtype.kind in "iu" and r.shape == w.shape and r.size \
                and r.min() >= 0 and r.max() < n_catalog:
            w = np.bincount(r.astype(np.int64), weights=w, minlength=n_catalog)
            by = str(key)
            break
    top = np.argsort(-w, kind="stable")[:SKY_WEIGHT_TOP]
    if np.all(w >= 0) and w[top[0]] > 0:
        top = top[w[top] >= SKY_WEIGHT_FLOOR * w[top[0]]]
    return top, w[top], by


def _log_normalised(w: np.ndarray) -> np.ndarray:
    """Positive weights to [0, 1] on a log scale over SKY_WEIGHT_FLOOR (3 decades) below the highest."""
    w = np.asarray(w, dtype=np.float64)
    if len(w) == 0 or not np.all(w > 0):
        return _normalised(w)
    lo = math.log10(SKY_WEIGHT_FLOOR)
    return np.clip((np.log10(w / w.max()) - lo) / -lo, 0.0, 1.0)


def _short(key: str, val) -> str:
    """A dict entry in a few characters: numbers by value (an angle named *_rad in degrees too), a unit
    3-vector as RA/Dec, other arrays by shape, None as '-'."""
    if val is None:
        return "-"
    if isinstance(val, (bool, np.bool_)):
        return str(bool(val))
    if isinstance(val, (int, float, np.integer, np.floating)):
        v = float(val)
        deg = f" ({math.degrees(v):.3g}°)" if str(key).endswith("_rad") and math.isfinite(v) else ""
        return format_number(v) + deg
    if isinstance(val, (list, tuple, np.ndarray)):
        try:
            a = np.asarray(val)
        except (ValueError, TypeError):
            return f"{len(val)} items"
        if a.shape == (3,) and a.dtype.kind == "f" and np.all(np.isfinite(a)) and abs(np.linalg.norm(a) - 1) < 1e-3:
            ra = math.degrees(math.atan2(a[1], a[0])) % 360.0
            dec = math.degrees(math.asin(max(-1.0, min(1.0, float(a[2])))))
            return f"RA {ra:.2f}° Dec {dec:+.2f}°"
        return "[" + " x ".join(str(n) for n in a.shape) + "]"
    text = str(val)
    return text[:24] + ("..." if len(text) > 24 else "")


def summarise_extra(key: str, val, hip: np.ndarray | None = None) -> str:
    """One line for an extra (arrays by shape, scalars by value, a dict by its entries)."""
    if isinstance(val, dict):
        text = ", ".join(f"{k} {_short(k, v)}" for k, v in val.items())
        return f"{key}: {text[:120]}" + ("..." if len(text) > 120 else "")
    if isinstance(val, (list, tuple, np.ndarray)):
        try:
            a = np.asarray(val)
        except (ValueError, TypeError):
            return f"{key}: {len(val)} items"
        if a.dtype.kind in "iu" and a.ndim == 2 and a.size and hip is not None and a.min() >= 0 \
                and a.max() < len(hip):
            first = ", ".join(f"HIP {int(hip[r])}" for r in a[0][:6])
            return f"{key}: {a.shape[0]} x {a.shape[1]} catalog rows; first: {first}"
        if a.dtype.kind in "iu" and a.ndim == 1 and 0 < a.size <= 12:
            return f"{key}: {', '.join(str(int(x)) for x in a)}"
        if a.dtype.kind in "iuf" and a.size:
            return (f"{key}: shape {tuple(a.shape)}, min {format_number(float(np.nanmin(a)))}, "
                    f"max {format_number(float(np.nanmax(a)))}")
        return f"{key}: shape {tuple(a.shape)}"
    if isinstance(val, (int, float, np.integer, np.floating)):
        return f"{key}: {format_number(float(val))}"
    text = str(val)
    return f"{key}: {text[:80]}" + ("..." if len(text) > 80 else "")


def step_drawables(steps, catalog_xyz: np.ndarray, n_observed: int, hip: np.ndarray | None = None) -> list[StepDrawable]:
    """Every step of an identification as drawables; catalog rows index `catalog_xyz`."""
    xyz = np.asarray(catalog_xyz, dtype=np.float64)
    out = []
    dict_cache: dict = {}
    for k, st in enumerate(steps):
        obs = np.array([int(i) for i in st.observed if 0 <= int(i) < n_observed], dtype=np.int64)
        cand = _valid_rows(st.catalog, len(xyz))
        groups = [tuple(int(r) for r in g) for g in st.groups
                  if len(g) >= 2 and all(0 <= int(r) < len(xyz) for r in g)]
        edges = group_edges(groups)
        if len(edges):
            segs = arcs_as_segments(xyz[edges[:, 0]], xyz[edges[:, 1]], ARC_POINTS).astype(np.float32)
        else:
            segs = np.zeros((0, 2, 3), dtype=np.float32)
        if len(cand) == 0 and groups:  # a step with groups only: light their stars
            cand = np.unique(np.concatenate([np.asarray(g) for g in groups]))
        ex = classify_extras(st, len(cand), xyz, hip, dict_cache)
        pts = np.concatenate(ex["points"]).astype(np.float32) if ex["points"] else np.zeros((0, 3), np.float32)
        pw = ex["point_weights"] if len(ex["points"]) == 1 else None
        numbers = {str(key): (float(v) if v is not None else float("nan")) for key, v in st.numbers.items()
                   if isinstance(v, (int, float, np.integer, np.floating, type(None)))}
        out.append(StepDrawable(index=k, kind=str(st.kind), note=str(st.note), observed=obs,
                                pattern=pattern_edges(obs), candidates=cand, segments=segs,
                                n_groups=len(groups), numbers=numbers,
                                weights=ex["weights"], weight_name=ex["weight_name"], points=pts,
                                point_weights=pw, points_name=", ".join(ex["point_keys"]),
                                attitudes=ex["attitudes"], extras=ex["text"], outlines=ex["outlines"],
                                outline_segments=polylines_as_segments(ex["outlines"]).astype(np.float32),
                                outline_names=", ".join(ex["outline_keys"])))
    return out


def numeric_keys(drawables: list[StepDrawable]) -> list[str]:
    """Every number recorded by some step, the default plot keys first."""
    keys: list[str] = []
    for d in drawables:
        for key in d.numbers:
            if key not in keys:
                keys.append(key)
    first = [k for k in keys if any(k == p or k == p + "_after" for p in DEFAULT_PLOT_KEYS)]
    return first + [k for k in keys if k not in first]


def series(drawables: list[StepDrawable], key: str) -> np.ndarray:
    """Values of one number across the steps (NaN where a step does not record it).

    For `hypotheses` / `candidates` a step's `<key>_after` counts when present (what is left after
    the step), so the plot shows the candidates shrinking pivot by pivot.
    """
    vals = []
    for d in drawables:
        v = d.numbers.get(key + "_after", d.numbers.get(key)) if key in DEFAULT_PLOT_KEYS else d.numbers.get(key)
        vals.append(float("nan") if v is None else float(v))
    return np.array(vals, dtype=np.float64)


def default_plot_key(drawables: list[StepDrawable]) -> str | None:
    """hypotheses / candidates when recorded, else the first number that changes from step to step, else
    None (nothing worth a plot: e.g. one frame of a sequence, each number recorded by one step only)."""
    keys = numeric_keys(drawables)
    for p in DEFAULT_PLOT_KEYS:
        if p in keys or p + "_after" in keys:
            return p
    for k in keys:
        v = series(drawables, k)
        if len(np.unique(v[np.isfinite(v)])) >= 2:
            return k
    return None


def match_groups(matches: dict[int, int], uv: np.ndarray) -> list[tuple[int, ...]]:
    """Triangles between matched catalog stars: a Delaunay mesh of the matched centroids in the image.

    matches: observed index -> catalog row; uv: (N, 2) pixels of the observed stars. Two matches give
    one pair; collinear ones a chain.
    """
    idx = sorted(int(i) for i in matches if 0 <= int(i) < len(uv))
    if len(idx) < 2:
        return []
    if len(idx) == 2:
        return [(matches[idx[0]], matches[idx[1]])]
    pts = np.asarray(uv, dtype=np.float64)[idx]
    try:
        tri = Delaunay(pts)
        simplices = tri.simplices
    except QhullError:
        order = np.argsort(pts[:, 0] + 1e-3 * pts[:, 1])
        return [(matches[idx[order[k]]], matches[idx[order[k + 1]]]) for k in range(len(order) - 1)]
    return [tuple(int(matches[idx[v]]) for v in s) for s in simplices]


def centroid_outcomes(n_centroids: int, n_used: int, matches: dict[int, int], uv: np.ndarray,
                      catalog_hip: np.ndarray, truth: dict | None) -> list[str]:
    """Per centroid: identified / unidentified / false star / wrong match / not used.

    With truth (a simulator sidecar, scored by `skyview.truth`), a match that is not the star the
    simulator drew there is a 'wrong match', and an unmatched centroid on a false star a 'false star'.
    'not used': fainter than the brightest stars the identifier was given.
    """
    rendered = centroid_truth(np.asarray(uv, dtype=np.float64).reshape(-1, 2), truth) if truth else [None] * n_centroids
    out = []
    for i in range(n_centroids):
        if i in matches:
            if truth and rendered[i] != int(catalog_hip[matches[i]]):
                out.append("wrong match")
            else:
                out.append("identified")
        elif truth and rendered[i] == -1:
            out.append("false star")
        elif i >= n_used:
            out.append("not used")
        else:
            out.append("unidentified")
    return out


def format_number(v: float) -> str:
    """Compact, readable figure: integers as such, small probabilities in scientific notation."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if float(v).is_integer() and abs(v) < 1e9:
        return f"{int(v):d}"
    a = abs(v)
    if a != 0 and (a < 1e-3 or a >= 1e6):
        return f"{v:.3g}"
    if a < 1:
        return f"{v:.4f}"
    if a < 100:
        return f"{v:.3f}"
    return f"{v:.1f}"
