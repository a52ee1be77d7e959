"""Steps and results as drawables: the one presentation layer the viewer and the recorder render.

A step (`skyview.identify.base.Step`) is a state of knowledge: what the method knows after it. This
module turns a step, with its typed layers (`skyview.identify.layers`), into `StepView`: a fixed set
of roles, each a `SkyPoints`, `SkyLines`, `ImageMarks` or `ImageEdges` with its colour from the one
`PALETTE`. The viewer (`skyview.viewer.scene`) makes one viser node per role and the recorder
(`skyview.record.draw`) one Rerun entity per role, so a layer appears in both or in neither, in the
same colours. What a step shows:

    observed         the stars the step measured now (its pair, triangle, star set), highlighted
    pattern          the measured pattern's edges in the image
    known            stars measured by earlier steps, faded
    candidates       the hypotheses that survive, as great-circle arcs between their catalog stars
                     (an even sample when there are many: the text says how many survive in all)
    candidate_stars  the catalog stars of the surviving hypotheses (tinted by a posterior when known)
    points           a GA population (tinted by cost) or the stars a posterior weighs
    attitudes        sensor footprints of candidate attitudes
    outline          a region of the sky being searched (a GA's box or roll circle)

The identification (matched stars, their mesh) is not a step role: sinks draw it only at the last
step (`StepView.final`) or when no step is selected. Re-exported here from its two halves: the image
stretch and label placement without collisions (`skyview.present.image`: `stretch`, `layout_labels`)
and the result as text (`skyview.present.text`: `result_lines`, `why_not`). Pure numpy; nothing here
imports viser or rerun.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from skyview.core import sky_geometry as sg
from skyview.identify.layers import (
    Attitudes,
    Hypotheses,
    Population,
    Posterior,
    SearchRegion,
    SkyPlaces,
    StarSets,
    posterior_figures,
)
from skyview.present.image import TEXTURE_FLOOR_SIGMAS, LabelLayout, layout_labels, place_labels, stretch, stretch_note

# One palette for every sink (RGB).
PALETTE: dict[str, tuple[int, int, int]] = {
    "grid": (48, 66, 98),
    "grid_main": (78, 100, 140),
    "constellation": (150, 125, 200),  # constellation figures and names
    "estimated": (255, 184, 48),  # camera / footprint at the estimated attitude
    "true": (70, 215, 255),  # ... at the true attitude
    "observed": (255, 230, 60),  # the stars the step measured (and its pattern)
    "known": (150, 140, 90),  # stars measured by earlier steps
    "candidates": (236, 72, 210),  # surviving hypotheses
    "candidates_high": (255, 236, 120),  # ... with a high weight
    "points": (175, 80, 255),  # a population, a posterior's stars
    "points_high": (120, 255, 230),  # ... the best / most probable
    "attitudes": (175, 80, 255),
    "outline": (255, 92, 28),  # the region searched
    "identified": (90, 230, 130),  # the identification (matched stars, their mesh)
    "centroid": (255, 60, 60),
    "unidentified": (120, 170, 255),
    "false star": (255, 150, 40),
    "wrong match": (255, 40, 90),
    "not used": (110, 110, 120),
}
OUTCOME_RGB = {k: PALETTE[k] for k in ("identified", "unidentified", "false star", "wrong match", "not used")}
LEGEND = {  # what each colour on screen means (the viewer's and the recording's legend)
    "observed": "stars measured at this step",
    "known": "stars measured at earlier steps",
    "candidates": "surviving candidates (arcs between their catalog stars)",
    "points": "GA population / posterior stars (bright: best) / look-up hits",
    "attitudes": "candidate attitude (its sensor footprint)",
    "outline": "region searched",
    "identified": "identified stars (last step)",
    "estimated": "field of view, estimated attitude",
    "true": "field of view, true attitude",
}
SKY_ROLES = ("candidates", "candidate_stars", "points", "attitudes", "outline")
IMAGE_ROLES = ("observed", "pattern", "known")
ARC_POINTS = 5  # points per great-circle arc of a candidate (seen from the centre a chord is the arc)
SKY_WEIGHT_TOP = 300  # stars lit from a posterior over the catalog
SKY_WEIGHT_FLOOR = 1e-3  # ... down to this fraction of the highest
DEFAULT_PLOT_KEYS = ("hypotheses", "candidates")


# ============================================================================ drawables

@dataclass(frozen=True)
class SkyPoints:
    """Points on the unit sphere: xyz (N, 3) float32, colors (N, 3) uint8, size: radius on the sphere."""

    role: str
    xyz: np.ndarray
    colors: np.ndarray
    size: float


@dataclass(frozen=True)
class SkyLines:
    """Line segments on the unit sphere: (S, 2, 3) float32, one colour, width in screen points."""

    role: str
    segments: np.ndarray
    color: tuple[int, int, int]
    width: float


@dataclass(frozen=True)
class ImageMarks:
    """Observed stars marked in the image (indices into the centroids), one colour."""

    role: str
    observed: np.ndarray
    color: tuple[int, int, int]


@dataclass(frozen=True)
class ImageEdges:
    """Edges between observed stars in the image: (E, 2) centroid indices, one colour."""

    role: str
    edges: np.ndarray
    color: tuple[int, int, int]


@dataclass
class StepView:
    """What a sink draws for step `index` of `n_steps`: drawables per role (absent: nothing), text."""

    index: int
    n_steps: int
    kind: str
    note: str
    numbers: dict[str, float]
    drawables: dict[str, SkyPoints | SkyLines | ImageMarks | ImageEdges] = field(default_factory=dict)
    text: list[str] = field(default_factory=list)
    surviving: int | None = None  # hypotheses that survive (all of them, drawn or not)
    drawn: int = 0  # candidate hypotheses drawn

    @property
    def final(self) -> bool:
        """The last step: the identification is drawn from here on."""
        return self.index == self.n_steps - 1

    @property
    def observed(self) -> np.ndarray:
        d = self.drawables.get("observed")
        return d.observed if d is not None else np.zeros(0, np.int64)

    @property
    def pattern(self) -> np.ndarray:
        d = self.drawables.get("pattern")
        return d.edges if d is not None else np.zeros((0, 2), np.int64)

    def legend(self) -> list[tuple[str, tuple[int, int, int]]]:
        """(meaning, colour) of every colour this step puts on screen, plus the identification at the end."""
        roles = {"candidate_stars": "candidates", "pattern": "observed"}
        seen = []
        for role in self.drawables:
            key = roles.get(role, role)
            if key in LEGEND and key not in seen:
                seen.append(key)
        if self.final:
            seen.append("identified")
        return [(LEGEND[k], PALETTE[k]) for k in seen]


def _rgb(name: str) -> np.ndarray:
    return np.array(PALETTE[name], dtype=np.float64)


def _blend(low: str, high: str, w: np.ndarray) -> np.ndarray:
    w = np.clip(np.asarray(w, dtype=np.float64), 0.0, 1.0)[:, None]
    return ((1 - w) * _rgb(low) + w * _rgb(high)).astype(np.uint8)


def _flat(name: str, n: int) -> np.ndarray:
    return np.broadcast_to(np.array(PALETTE[name], np.uint8), (n, 3)).copy()


def normalised(a: np.ndarray) -> np.ndarray:
    """To [0, 1] over the finite values' range; +inf at the top, -inf and NaN at the bottom."""
    a = np.asarray(a, dtype=np.float64)
    fin = np.isfinite(a)
    if not fin.any():
        return np.ones_like(a)
    lo, hi = float(a[fin].min()), float(a[fin].max())
    a = np.where(a == np.inf, hi, np.where(fin, a, lo))
    return (a - lo) / (hi - lo) if hi > lo else np.ones_like(a)


def log_normalised(w: np.ndarray) -> np.ndarray:
    """Positive weights to [0, 1] on a log scale over SKY_WEIGHT_FLOOR below the highest."""
    w = np.asarray(w, dtype=np.float64)
    if len(w) == 0 or not np.all(w > 0):
        return normalised(w)
    lo = math.log10(SKY_WEIGHT_FLOOR)
    return np.clip((np.log10(w / w.max()) - lo) / -lo, 0.0, 1.0)


def pattern_edges(observed) -> np.ndarray:
    """Edges joining 2 to 4 stars in the order given (a pair, a closed triangle or quad); more: a chain."""
    obs = [int(i) for i in observed]
    if len(obs) == 2:
        return np.array([[obs[0], obs[1]]], dtype=np.int64)
    if 3 <= len(obs) <= 4:
        return np.array([[obs[k], obs[(k + 1) % len(obs)]] for k in range(len(obs))], dtype=np.int64)
    if len(obs) > 4:
        return np.array([[obs[k], obs[k + 1]] for k in range(len(obs) - 1)], dtype=np.int64)
    return np.zeros((0, 2), dtype=np.int64)


def _arcs(xyz: np.ndarray, edges: np.ndarray) -> np.ndarray:
    if len(edges) == 0:
        return np.zeros((0, 2, 3), np.float32)
    return sg.arcs_as_segments(xyz[edges[:, 0]], xyz[edges[:, 1]], ARC_POINTS).astype(np.float32)


def _hypothesis_edges(h: Hypotheses, n_catalog: int, observed=()) -> np.ndarray:
    """Distinct catalog-row edges of the sampled hypotheses along the pattern the step measured (its
    observed stars, when the hypotheses assign them; else along all the stars they assign): one arc per
    surviving candidate of the measured pair / triangle, so the arcs thin as the hypotheses do."""
    rows = np.asarray(h.rows, dtype=np.int64)
    if rows.size == 0 or rows.shape[1] < 2:
        return np.zeros((0, 2), np.int64)
    where = {u: j for j, u in enumerate(h.used)}
    now = [where[int(o)] for o in observed if int(o) in where]
    local = pattern_edges(now if len(now) >= 2 else range(rows.shape[1]))
    e = rows[:, local].reshape(-1, 2)
    e = e[((e >= 0) & (e < n_catalog)).all(axis=1)]
    return np.unique(np.sort(e, axis=1), axis=0)


def _posterior_stars(p: Posterior, n_catalog: int) -> tuple[np.ndarray, np.ndarray]:
    """The stars a posterior weighs most (at most SKY_WEIGHT_TOP, down to SKY_WEIGHT_FLOOR of the top)."""
    w = p.per_star(n_catalog)
    top = np.argsort(-w, kind="stable")[:SKY_WEIGHT_TOP]
    if len(top) and w[top[0]] > 0:
        top = top[w[top] >= SKY_WEIGHT_FLOOR * w[top[0]]]
    return top, w[top]


def _radec(v: np.ndarray) -> str:
    ra = math.degrees(math.atan2(v[1], v[0])) % 360.0
    dec = math.degrees(math.asin(max(-1.0, min(1.0, float(v[2])))))
    return f"RA {ra:.2f}° Dec {dec:+.2f}°"


def step_views(steps, catalog_xyz: np.ndarray, n_observed: int, *, camera=None,
               hip: np.ndarray | None = None) -> list[StepView]:
    """Every step of an identification as a `StepView`; catalog rows index `catalog_xyz`.

    camera: draws candidate attitudes as sensor footprints (without one they are left out)."""
    xyz = np.asarray(catalog_xyz, dtype=np.float64)
    n_cat = len(xyz)
    views: list[StepView] = []
    known: set[int] = set()
    region_cache: dict[int, np.ndarray | None] = {}
    for k, st in enumerate(steps):
        obs = np.array([int(i) for i in st.observed if 0 <= int(i) < n_observed], dtype=np.int64)
        numbers = {str(key): (float(v) if v is not None else float("nan")) for key, v in st.numbers.items()
                   if isinstance(v, (int, float, np.integer, np.floating, type(None)))}
        v = StepView(index=k, n_steps=len(steps), kind=str(st.kind), note=str(st.note), numbers=numbers)
        dr = v.drawables
        # --- the image: what is measured now, what was measured before
        if len(obs):
            dr["observed"] = ImageMarks("observed", obs, PALETTE["observed"])
            edges = pattern_edges(obs) if len(obs) <= 4 else np.zeros((0, 2), np.int64)
            if len(edges):
                dr["pattern"] = ImageEdges("pattern", edges, PALETTE["observed"])
        before = np.array(sorted(known - set(obs.tolist())), dtype=np.int64)
        if len(before):
            dr["known"] = ImageMarks("known", before, PALETTE["known"])
        known |= set(obs.tolist())
        # --- the sky: the candidates that survive
        hyp = st.layer(Hypotheses)
        post = st.layer(Posterior)
        cand = np.array([int(r) for r in st.catalog if 0 <= int(r) < n_cat], dtype=np.int64)
        if hyp is not None:
            e = _hypothesis_edges(hyp, n_cat, obs.tolist())
            v.surviving, v.drawn = hyp.total, len(hyp.rows)
            rows = np.asarray(hyp.rows, dtype=np.int64).reshape(-1)
            cand = np.unique(rows[(rows >= 0) & (rows < n_cat)])
            shown = f" ({len(hyp.rows)} drawn, an even sample)" if len(hyp.rows) < hyp.total else ""
            v.text.append(f"{hyp.total} hypothes{'i' if hyp.total == 1 else 'e'}s survive{shown}, over observed "
                          f"stars {', '.join(map(str, hyp.used))}"
                          + (f"; shares {', '.join(map(str, hyp.shared))} with the step before" if hyp.shared else ""))
        else:
            groups = [tuple(int(r) for r in g) for g in st.groups if len(g) >= 2 and all(0 <= int(r) < n_cat for r in g)]
            e = sg.group_edges(groups)
            if groups:
                v.drawn = len(groups)
            if len(cand) == 0 and groups:
                cand = np.unique(np.concatenate([np.asarray(g) for g in groups]))
        if len(e):
            dr["candidates"] = SkyLines("candidates", _arcs(xyz, e), PALETTE["candidates"], 1.4)
        if len(cand):
            if post is not None and len(post.top_rows) == len(cand) and np.array_equal(post.top_rows, cand):
                colors = _blend("candidates", "candidates_high", normalised(post.top_mass))
            else:
                colors = _flat("candidates", len(cand))
            dr["candidate_stars"] = SkyPoints("candidate_stars", xyz[cand].astype(np.float32), colors,
                                              float(sg.star_radius(3.0)))
        # --- a population or a posterior's stars
        pop = st.layer(Population)
        if pop is not None:
            w = 1.0 - normalised(pop.costs)  # the lowest cost brightest; +inf (invalid) darkest
            dr["points"] = SkyPoints("points", np.asarray(pop.xyz, np.float32), _blend("points", "points_high", w),
                                     float(sg.star_radius(0.5)))
            fin = np.isfinite(pop.costs)
            best = float(np.min(pop.costs[fin])) if fin.any() else float("inf")
            v.text.append(f"{pop.name}: {len(pop.xyz)} individuals, best cost {best:.4g}"
                          + (", roll chromosomes" if pop.roll_rad is not None else ""))
        elif post is not None:
            stars, w = _posterior_stars(post, n_cat)
            if len(stars):
                dr["points"] = SkyPoints("points", xyz[stars].astype(np.float32),
                                         _blend("points", "points_high", log_normalised(w)), float(sg.star_radius(0.5)))
            lead = ", ".join(f"HIP {int(hip[r])} {m:.3f}" if hip is not None else f"row {int(r)} {m:.3f}"
                             for r, m in zip(post.top_rows[:3], post.top_mass[:3]))
            v.text.append(f"posterior over {len(post.weights)} hypotheses; {len(stars)} stars lit; leading: {lead}")
        places = st.layer(SkyPlaces)
        if places is not None and "points" not in dr:
            n = len(places.xyz)
            dr["points"] = SkyPoints("points", np.asarray(places.xyz, np.float32), _flat("points", n),
                                     float(sg.star_radius(0.5)))
            v.text.append(f"{places.name}: {places.total} on the sky" + (f" ({n} drawn, an even sample)"
                                                                          if n < places.total else ""))
        # --- candidate attitudes, the region searched, star sets
        att = st.layer(Attitudes)
        if att is not None:
            if camera is not None:
                seg = sg.polylines_as_segments([sg.sensor_footprint(camera, R) for R in att.R]).astype(np.float32)
                dr["attitudes"] = SkyLines("attitudes", seg, PALETTE["attitudes"], 1.4)
            v.text.append(f"{att.name}: " + "; ".join(f"boresight {_radec(np.asarray(R)[2])}" for R in att.R[:3]))
        reg = st.layer(SearchRegion)
        if reg is not None:
            if id(reg) not in region_cache:
                region_cache[id(reg)] = region_polyline(reg)
            poly = region_cache[id(reg)]
            if poly is not None:
                dr["outline"] = SkyLines("outline", sg.polylines_as_segments([poly]).astype(np.float32),
                                         PALETTE["outline"], 2.5)
            centre = f", centre {_radec(reg.center)}" if reg.center is not None else ""
            v.text.append(f"search region: {reg.kind}, half width {math.degrees(reg.half_width_rad):.3g}°{centre}")
        sets = st.layer(StarSets)
        if sets is not None:
            v.text += [f"{name}: {', '.join(map(str, ids)) or '-'}" for name, ids in sets.sets.items()]
        views.append(v)
    return views


def region_polyline(reg: SearchRegion) -> np.ndarray | None:
    """The closed outline of a search region ((M, 3), first == last), None for the whole sky."""
    if reg.kind == "square" and reg.corners is not None:
        return sg.polygon_outline(reg.corners)
    if reg.kind == "roll" and reg.center is not None and reg.radius_rad is not None:
        return sg.small_circle(reg.center, reg.radius_rad)
    return None


# ============================================================================ numbers across steps

def numeric_keys(views: list[StepView]) -> list[str]:
    """Every number recorded by some step, the default plot keys first."""
    keys: list[str] = []
    for d in views:
        for key in d.numbers:
            if key not in keys:
                keys.append(key)
    first = [k for k in keys if any(k == p or k == p + "_after" for p in DEFAULT_PLOT_KEYS)]
    return first + [k for k in keys if k not in first]


def series(views: list[StepView], key: str) -> np.ndarray:
    """Values of one number across the steps (NaN where a step does not record it); for hypotheses /
    candidates a step's `<key>_after` counts when present (what is left after the step)."""
    vals = []
    for d in views:
        v = d.numbers.get(key + "_after", d.numbers.get(key)) if key in DEFAULT_PLOT_KEYS else d.numbers.get(key)
        vals.append(float("nan") if v is None else float(v))
    return np.array(vals, dtype=np.float64)


def default_plot_key(views: list[StepView]) -> str | None:
    """hypotheses / candidates when recorded, else the first number that changes, else None."""
    keys = numeric_keys(views)
    for p in DEFAULT_PLOT_KEYS:
        if p in keys or p + "_after" in keys:
            return p
    for k in keys:
        v = series(views, k)
        if len(np.unique(v[np.isfinite(v)])) >= 2:
            return k
    return None


def unit_of(key: str) -> str:
    """The unit a number is in, from its name (one plot per unit)."""
    k = key.lower()
    for suffix, unit in (("_deg", "deg"), ("_arcsec", "arcsec"), ("_rad", "rad"), ("_ms", "ms")):
        if k.endswith(suffix) or f"{suffix}_" in k:
            return unit
    if k.startswith("p_") or "posterior" in k or k in ("passed", "p"):
        return "probability"
    if "cost" in k:
        return "cost"
    if k.startswith("mag") or k.startswith("x_mu_m") or k.startswith("x_sigma_m"):
        return "mag"
    return "count"


def match_groups(matches: dict[int, int], uv: np.ndarray) -> list[tuple[int, ...]]:
    """The identification's mesh: triangles between matched catalog stars, a Delaunay mesh of the matched
    centroids in the image (observed index -> catalog row; uv (N, 2) pixels). Two matches give one pair;
    collinear ones a chain."""
    from scipy.spatial import Delaunay, QhullError

    idx = sorted(int(i) for i in matches if 0 <= int(i) < len(uv))
    if len(idx) < 2:
        return []
    if len(idx) == 2:
        return [(matches[idx[0]], matches[idx[1]])]
    pts = np.asarray(uv, dtype=np.float64)[idx]
    try:
        simplices = Delaunay(pts).simplices
    except QhullError:
        order = np.argsort(pts[:, 0] + 1e-3 * pts[:, 1])
        return [(matches[idx[order[k]]], matches[idx[order[k + 1]]]) for k in range(len(order) - 1)]
    return [tuple(int(matches[idx[v]]) for v in s) for s in simplices]


__all__ = ["PALETTE", "OUTCOME_RGB", "LEGEND", "SKY_ROLES", "IMAGE_ROLES", "ARC_POINTS", "SkyPoints", "SkyLines",
           "ImageMarks", "ImageEdges", "StepView", "step_views", "region_polyline", "pattern_edges", "normalised",
           "log_normalised", "numeric_keys", "series", "default_plot_key", "unit_of", "match_groups",
           "posterior_figures",
           # the image and text halves (skyview.present.image, skyview.present.text), re-exported
           "TEXTURE_FLOOR_SIGMAS", "LabelLayout", "layout_labels", "place_labels", "stretch", "stretch_note"]
