"""Typed layers of a step: what a method knows after one step, in data the sinks can draw.

A `Step` (skyview.identify.base) carries a tuple of these frozen records instead of a free-form dict.
Each says one kind of thing in the method's own terms; `skyview.present.drawables` is the one module that turns
them into drawables, so the viewer and the recorder show a new layer in the same way or not at all.

    Hypotheses      the correspondence hypotheses that survive: observed stars used and, per
                    hypothesis, the catalog rows assigned to them (a sample, with the total)
    Population      directions on the sky with a cost each (a GA population; lower is better)
    Posterior       a probability over catalog stars (hypothesis weights and the star each designates)
    Attitudes       candidate attitudes (3x3 rotations, v_cam = R @ v_icrs)
    SearchRegion    a region of the sky being searched (a GA's box: a square, a roll circle, the sky)
    StarSets        named sets of observed stars (the stars within a radius, the ones a rule deleted)
    SkyPlaces       the places on the sky a step's candidates lie (a look-up's hits: their patterns' centres)

Nothing here imports a viewer or a recorder; arrays are numpy, angles in radians.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

HYPOTHESES_SAMPLE = 500  # hypotheses kept in a step: an even sample of the survivors when there are more


def even_sample(n: int, cap: int) -> np.ndarray:
    """Indices of at most `cap` of `n` items spread evenly over them (first and last included)."""
    if n <= cap:
        return np.arange(n)
    idx = np.linspace(0, n - 1, cap).round().astype(np.int64)  # non-decreasing: drop the repeats
    return idx[np.r_[True, idx[1:] != idx[:-1]]]


@dataclass(frozen=True)
class Hypotheses:
    """Surviving correspondence hypotheses.

    used: the observed stars the hypotheses assign (brightness ranks), in order; rows: (H, len(used))
    catalog rows, rows[h, j] is the catalog star of observed star used[j] under hypothesis h (an even
    sample of the survivors); total: how many survive in all (>= len(rows)); shared: the observed stars
    the step's pattern shares with the one before (a triangle pivot).
    """

    used: tuple[int, ...]
    rows: np.ndarray
    total: int
    shared: tuple[int, ...] = ()

    @classmethod
    def sample(cls, used, H, cap: int = HYPOTHESES_SAMPLE, shared=()) -> Hypotheses:
        """The survivors H ((n, len(used)) catalog rows) as a layer: an even sample of `cap`, the total.

        The sample is taken when a sink first reads `rows` (the methods' hot paths record a layer per
        step and most are never drawn); H must not be changed in place afterwards (the methods make a
        new array at every step)."""
        used = tuple(map(int, used))
        if not isinstance(H, np.ndarray):  # a list the caller may go on changing: sample it now
            return cls(used, _sample_rows(used, H, cap), _n_rows(used, H), tuple(map(int, shared)))
        return _SampledHypotheses(used, H, cap, tuple(map(int, shared)))

    @classmethod
    def single(cls, hypothesis: dict[int, int]) -> Hypotheses:
        """One hypothesis (observed index -> catalog row) as a layer."""
        used = sorted(int(k) for k in hypothesis)
        return cls(tuple(used), np.array([[int(hypothesis[u]) for u in used]], dtype=np.int64).reshape(1, -1), 1)


def _n_rows(used: tuple[int, ...], H) -> int:
    if not used:
        return 0
    return H.size // len(used) if isinstance(H, np.ndarray) else int(np.size(H) // len(used))


def _sample_rows(used: tuple[int, ...], H, cap: int) -> np.ndarray:
    """`Hypotheses.sample`'s rows: an even sample of at most cap of the (n, len(used)) rows of H, int64."""
    H = np.asarray(H, dtype=np.int64).reshape(-1, len(used)) if len(used) else np.zeros((0, 0), np.int64)
    return H[even_sample(len(H), cap)]


class _SampledHypotheses(Hypotheses):
    """A `Hypotheses` whose rows are sampled from the survivors when first read (then kept); it pickles
    and copies as a plain `Hypotheses`."""

    def __init__(self, used: tuple[int, ...], H: np.ndarray, cap: int, shared: tuple[int, ...]):
        object.__setattr__(self, "used", used)
        object.__setattr__(self, "total", _n_rows(used, H))
        object.__setattr__(self, "shared", shared)
        object.__setattr__(self, "_source", (H, cap))

    @property
    def rows(self) -> np.ndarray:
        src = self.__dict__.get("_source")
        if src is not None:
            object.__setattr__(self, "_rows", _sample_rows(self.used, *src))
            object.__setattr__(self, "_source", None)
        return self.__dict__["_rows"]

    def __reduce__(self):
        return Hypotheses, (self.used, self.rows, self.total, self.shared)


@dataclass(frozen=True)
class Population:
    """Directions on the sky with a cost each, lower is better (a GA population, best first).

    xyz: (P, 3) ICRS unit vectors (float32); costs: (P,) (+inf: an invalid individual); roll_rad: for a
    roll population the roll of each chromosome (skyview's convention), else None.
    """

    xyz: np.ndarray
    costs: np.ndarray
    roll_rad: np.ndarray | None = None
    name: str = "population"


@dataclass(frozen=True)
class Posterior:
    """A probability over catalog stars.

    weights: (H,) the posterior of each hypothesis; rows: (H,) the catalog row each hypothesis designates
    now (several may designate one star: the star's probability is their sum); top_rows / top_mass: the
    leading stars and their summed probability, best first; top_xi: the catalog statistics of those
    stars (the method's own figures, (T, k)) or None.
    """

    weights: np.ndarray
    rows: np.ndarray
    top_rows: np.ndarray
    top_mass: np.ndarray
    top_xi: np.ndarray | None = None

    def per_star(self, n_catalog: int) -> np.ndarray:
        """(n_catalog,) the probability of each catalog star: the hypotheses' weights summed per star."""
        w = np.nan_to_num(np.asarray(self.weights, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        return np.bincount(np.asarray(self.rows, dtype=np.int64), weights=w, minlength=n_catalog)


@dataclass(frozen=True)
class Attitudes:
    """Candidate attitudes: 3x3 rotations with v_cam = R @ v_icrs (their sensor footprints are drawn)."""

    R: tuple[np.ndarray, ...]
    name: str = "attitude"

    @classmethod
    def of(cls, *R: np.ndarray, name: str = "attitude") -> Attitudes:
        return cls(tuple(np.array(r, dtype=np.float64) for r in R), name)


@dataclass(frozen=True)
class SearchRegion:
    """A region of the sky being searched.

    kind: "sky" (everywhere: no outline), "square" (corners: (4, 3) ICRS unit vectors in order around
    it, edges along great circles) or "roll" (the small circle of radius_rad around center: the image-up
    directions of roll chromosomes); center: unit 3-vector or None; half_width_rad: the box half width.
    """

    kind: str
    center: np.ndarray | None
    half_width_rad: float
    corners: np.ndarray | None = None
    radius_rad: float | None = None

    @classmethod
    def from_box(cls, box: dict) -> SearchRegion:
        """From a GA box dict {"kind", "center", "half_width_rad", "corners"?, "radius_rad"?}."""
        c = box.get("center")
        corners = box.get("corners")
        return cls(str(box["kind"]), None if c is None else np.array(c, dtype=np.float64),
                   float(box["half_width_rad"]),
                   None if corners is None else np.array(corners, dtype=np.float64),
                   None if box.get("radius_rad") is None else float(box["radius_rad"]))


@dataclass(frozen=True)
class StarSets:
    """Named sets of observed stars (brightness ranks): e.g. {"within": (...), "deleted": (...)}."""

    sets: dict[str, tuple[int, ...]] = field(default_factory=dict)

    @classmethod
    def of(cls, **sets) -> StarSets:
        return cls({k: tuple(int(i) for i in v) for k, v in sets.items()})


@dataclass(frozen=True)
class SkyPlaces:
    """Where on the sky a step's candidates lie, one ICRS unit vector each (float32): e.g. the centres of the
    catalog patterns a look-up hit. total: how many candidates in all (>= len(xyz): an even sample is drawn);
    name: what they are, in words."""

    xyz: np.ndarray
    total: int
    name: str


def posterior_figures(steps, n_hypotheses_floor: int = 1) -> dict | None:
    """What a posterior step says, read from its layer (no method's own figures): the designated star
    (the observed star the step updates on), the leading stars and their probability, how many stars
    are above the prior 1/H (H hypotheses). None when no step carries a `Posterior`."""
    st = next((s for s in reversed(list(steps)) if s.layer(Posterior) is not None), None)
    if st is None:
        return None
    p = st.layer(Posterior)
    H = max(len(p.weights), n_hypotheses_floor)
    star = np.bincount(np.asarray(p.rows, dtype=np.int64),
                       weights=np.nan_to_num(np.asarray(p.weights, dtype=np.float64)))
    return {"designated": int(st.observed[0]) if st.observed else None,
            "top_rows": np.asarray(p.top_rows, dtype=np.int64), "top_mass": np.asarray(p.top_mass, dtype=np.float64),
            "top_posterior": float(p.top_mass[0]) if len(p.top_mass) else None,
            "above_prior": int(np.sum(star > 1.0 / H))}


Layer = Hypotheses | Population | Posterior | Attitudes | SearchRegion | StarSets
