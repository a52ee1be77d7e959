"""Scale-free four-star patterns of the sky: the database of the blind solver.

A pattern is four catalog stars. Its six separations, sorted and divided by the largest, give five
edge ratios that do not change with the camera's scale, rotation or position in the image, so one
database serves every camera whose field of view lies in the range it was built for (tetra3 and
cedar-solve use the same invariant). The largest separation then gives the plate scale.

The database belongs to the sky: it is keyed by the catalog, the depth of each scale level and the
range of pattern sizes, never by one camera.

Levels. Pattern sizes are split into levels by their largest separation: level l holds the patterns
whose largest edge lies in [D_l / step, D_l), with D_0 = max_edge_deg and D_l = D_0 / step^l down to
min_edge_deg. Each pattern belongs to exactly one level, so nothing is stored twice.

Pattern stars of a level. The stars that a camera sees as the brightest around a pattern of size D:
a catalog star is a pattern star of level l when fewer than `stars_per_circle` brighter stars lie
within D_l / 2 of it (vectorised from the pairs within that radius). Stars of an unresolved close
pair (closer than `min_separation` of the pattern size) are merged into the brighter one. The level's
stars are taken no fainter than the magnitude where the sky holds `depth_factor` times the stars
needed, and never fainter than the catalog.

Patterns of a level: every four pattern stars of the level whose largest separation is in the
level's band, enumerated by the largest edge (a pair i < j), then the pairs of stars inside the lens
of points within that separation of both ends. Each is stored as its four catalog rows and a key:
the five ratios quantised in bins of `bin_width` and packed into one int64; the table is sorted by
key, so a look-up is a `searchsorted`. The arrays are plain and uncompressed: the file is
memory-mapped on load.

Size. The pattern count grows as stars_per_circle^3 per level and the levels are alike in count, so
`estimate_size` predicts the bytes from a sample of the sky before the build starts; `build`
refuses a database over the memory budget with one line that says how to raise it.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from skyview.core.catalog import GuideCatalog, chord
from skyview.core.errors import BadInput

FORMAT_VERSION = 2
N_RATIOS = 5
RATIO_BITS = 8  # each quantised ratio in 0..255 (bin_width >= 1/256)
PAIRS_OF_FOUR = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
BYTES_PER_PATTERN = 8 + 4 * 4 + 1 + 8  # key, four int32 rows, level, about one bucket entry
DEFAULT_BUDGET_MB = 1024


@dataclass(frozen=True)
class PatternParams:
    """What a pattern database depends on besides the catalog (all angles in degrees)."""

    max_edge_deg: float = 67.5  # the largest pattern: fits a field of about 80 deg
    min_edge_deg: float = 1.7  # the smallest: fits a field of about 2.5-3 deg
    step: float = 1.5  # ratio of consecutive levels' largest edges
    stars_per_circle: int = 7  # pattern stars: fewer than this many brighter within D_l / 2
    depth_factor: float = 4.0  # take stars to the magnitude with this many times the needed density
    mag_limit: float = 8.0  # never fainter than this (Hipparcos is complete to about Hp 8)
    min_separation: float = 0.02  # merge stars closer than this fraction of the level's size
    bin_width: float = 0.01  # quantisation of the edge ratios

    def levels(self) -> list[float]:
        """Largest edge D_l of each level, degrees, from the largest down."""
        out, d = [], float(self.max_edge_deg)
        while d / self.step >= self.min_edge_deg * (1 - 1e-9) or not out:
            out.append(d)
            d /= self.step
        return out

    def check(self) -> None:
        if not (0.1 <= self.min_edge_deg < self.max_edge_deg <= 90.0):
            raise BadInput("pattern sizes must satisfy 0.1 <= min_edge_deg < max_edge_deg <= 90")
        if not (1.1 <= self.step <= 4.0):
            raise BadInput("the level step must be in [1.1, 4]")
        if not (4 <= self.stars_per_circle <= 30):
            raise BadInput("stars_per_circle must be in [4, 30]")
        if not (1.0 / (1 << RATIO_BITS) <= self.bin_width <= 0.1):
            raise BadInput(f"bin_width must be in [{1 / (1 << RATIO_BITS):.4f}, 0.1]")


# The narrow fields' database, built on the deep catalog (Hipparcos-2 + Gaia DR3 to G 10,
# skyview.core.deep_catalog): patterns of 0.51-2.6 deg for fields of ~0.7-3.1 deg, where the guide
# catalog's database (PatternParams()) reaches down to ~1.6 deg only with the few stars Hipparcos holds
# there. Four pattern stars per circle, not seven: the deep catalog holds every star a narrow field
# shows, so each level takes nearly the whole catalog and the count grows as the cube of this number
# (seven: 92 million patterns, 2.9 GB; four: 10.4 million, 395 MB on disk, built in ~45 s with ~1.3 GB
# at its peak on this 2-core machine). Measured on 1024 x 768 simulated fields to G 10: 1.5 deg, 30 of
# 30 solved; 1.0 deg, 22 of 30 (the rest show 2-8 stars), none wrong.
NARROW_FIELD_PARAMS = PatternParams(max_edge_deg=2.6, min_edge_deg=0.5, stars_per_circle=4, mag_limit=10.0)


# ============================================================================ invariants

def separations(v: np.ndarray) -> np.ndarray:
    """(..., 4, 3) unit vectors -> (..., 6) angles (radians) in PAIRS_OF_FOUR order."""
    d = v[..., PAIRS_OF_FOUR[:, 0], :] - v[..., PAIRS_OF_FOUR[:, 1], :]
    # = 2 arcsin(clip(np.linalg.norm(d, axis=-1) / 2, 0, 1)): the norm is sqrt(add.reduce(d * d)) as numpy
    # computes it for real rows, and it is >= 0 (NaN stays NaN): the same numbers without the wrappers
    return 2.0 * np.arcsin(np.minimum(np.sqrt(np.add.reduce(d * d, axis=-1)) / 2.0, 1.0))


def edge_ratios(edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 6) edges -> ((..., 5) sorted edges / largest, (...,) largest edge)."""
    s = np.sort(edges, axis=-1)
    largest = s[..., -1]
    return s[..., :-1] / largest[..., None], largest


def pack_key(q: np.ndarray) -> np.ndarray:
    """(..., 5) quantised ratios (0..255) -> (...,) int64 keys."""
    q = q.astype(np.int64)
    key = np.zeros(q.shape[:-1], dtype=np.int64)
    for k in range(N_RATIOS):
        key = (key << RATIO_BITS) | q[..., k]
    return key


def quantise(ratios: np.ndarray, bin_width: float) -> np.ndarray:
    return np.clip(np.floor(ratios / bin_width), 0, (1 << RATIO_BITS) - 1).astype(np.int64)


# ============================================================================ selection

def level_stars(catalog: GuideCatalog, edge_deg: float, params: PatternParams) -> np.ndarray:
    """Catalog rows of the pattern stars of the level whose largest edge is edge_deg."""
    rho = math.radians(edge_deg) / 2.0
    circle_sr = 2.0 * math.pi * (1.0 - math.cos(rho))
    needed = params.stars_per_circle / circle_sr * 4.0 * math.pi  # on the whole sky
    order = np.argsort(catalog.mag, kind="stable")
    n_take = int(min(len(order), math.ceil(params.depth_factor * needed)))
    mag_cut = min(float(catalog.mag[order[n_take - 1]]), params.mag_limit)
    rows = order[catalog.mag[order] <= mag_cut]  # brightest first
    xyz = catalog.xyz[rows]
    # merge unresolved pairs into the brighter star
    from scipy.spatial import cKDTree

    tree = cKDTree(xyz)
    close = tree.query_pairs(float(chord(params.min_separation * math.radians(edge_deg))), output_type="ndarray")
    keep = np.ones(len(rows), dtype=bool)
    if len(close):
        keep[close.max(axis=1)] = False  # rows are brightest first: the larger index is fainter
    rows, xyz = rows[keep], xyz[keep]
    tree = cKDTree(xyz)
    pairs = tree.query_pairs(float(chord(rho)), output_type="ndarray")
    brighter = np.bincount(pairs.max(axis=1), minlength=len(rows)) if len(pairs) else np.zeros(len(rows), int)
    return np.sort(rows[brighter < params.stars_per_circle])


def level_patterns(xyz: np.ndarray, lo_rad: float, hi_rad: float, chunk_rows: int = 4_000_000
                   ) -> np.ndarray:
    """Every four stars (indices into xyz) whose largest separation is in [lo_rad, hi_rad).

    Enumerated by the largest edge: for each pair (i, j) in the band, the stars k within that
    separation of both i and j, then the pairs (k, l) of them within it of each other.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(xyz)
    pairs = tree.query_pairs(float(chord(hi_rad)), output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 4), dtype=np.int64)
    n = len(xyz)
    # neighbour lists (CSR, both directions) within hi_rad
    a = np.r_[pairs[:, 0], pairs[:, 1]]
    b = np.r_[pairs[:, 1], pairs[:, 0]]
    o = np.lexsort((b, a))
    a, b = a[o], b[o]
    start = np.searchsorted(a, np.arange(n + 1))
    out = []
    for i in range(n):
        nb = b[start[i]:start[i + 1]]
        if len(nb) < 3:
            continue
        loc = np.r_[i, nb]
        dots = np.clip(xyz[loc] @ xyz[loc].T, -1.0, 1.0)
        ang = np.arccos(dots)
        d0 = ang[0, 1:]
        js = np.flatnonzero((nb > i) & (d0 >= lo_rad) & (d0 < hi_rad)) + 1  # local index of j
        if len(js) == 0:
            continue
        dij = ang[0, js]  # (J,)
        m = len(loc)
        inside = (ang[0][None, :] < dij[:, None]) & (ang[js] < dij[:, None])  # (J, m): k in the lens
        inside[:, 0] = False
        inside[np.arange(len(js)), js] = False
        cand = inside[:, :, None] & inside[:, None, :] & (ang[None, :, :] < dij[:, None, None])
        cand &= np.triu(np.ones((m, m), dtype=bool), 1)[None]
        jj, kk, ll = np.nonzero(cand)
        if len(jj):
            out.append(np.stack([np.full(len(jj), i), loc[js[jj]], loc[kk], loc[ll]], axis=1))
    if not out:
        return np.zeros((0, 4), dtype=np.int64)
    return np.concatenate(out).astype(np.int64)


# ============================================================================ size and build

def pattern_keys(xyz: np.ndarray, quads: np.ndarray, bin_width: float, chunk: int = 250_000) -> np.ndarray:
    """Keys of patterns given as (P, 4) rows into xyz, in chunks (bounded temporary memory)."""
    out = np.empty(len(quads), dtype=np.int64)
    for s in range(0, len(quads), chunk):
        ratios, _ = edge_ratios(separations(xyz[quads[s:s + chunk]]))
        out[s:s + chunk] = pack_key(quantise(ratios, bin_width))
    return out


def estimate_size(catalog: GuideCatalog, params: PatternParams, sample: int = 300, seed: int = 0) -> dict:
    """Predicted pattern count and bytes, from the patterns around a random sample of level stars."""
    rng = np.random.default_rng(seed)
    per_level = []
    total = 0.0
    for d in params.levels():
        rows = level_stars(catalog, d, params)
        hi, lo = math.radians(d), math.radians(d / params.step)
        if len(rows) <= sample:
            n = len(level_patterns(catalog.xyz[rows], lo, hi))
        else:
            # patterns are counted once, at their largest edge's first star: the mean count per star
            # over a random subset of first stars, times the stars
            pick = rng.choice(len(rows), sample, replace=False)
            n = _count_from(catalog.xyz[rows], pick, lo, hi) * len(rows) / sample
        per_level.append({"edge_deg": d, "stars": int(len(rows)), "patterns": int(round(n))})
        total += n
    return {"levels": per_level, "patterns": int(round(total)),
            "bytes": int(round(total * BYTES_PER_PATTERN))}


def _count_from(xyz: np.ndarray, firsts: np.ndarray, lo: float, hi: float) -> float:
    """Patterns whose first star (the smaller index of the largest edge) is in `firsts`."""
    from scipy.spatial import cKDTree

    tree = cKDTree(xyz)
    count = 0
    for i in firsts.tolist():
        nb = np.asarray(tree.query_ball_point(xyz[i], float(chord(hi))), dtype=np.int64)
        nb = nb[nb != i]
        loc = np.r_[i, nb]
        ang = np.arccos(np.clip(xyz[loc] @ xyz[loc].T, -1.0, 1.0))
        d0 = ang[0, 1:]
        js = np.flatnonzero((nb > i) & (d0 >= lo) & (d0 < hi)) + 1
        if len(js) == 0:
            continue
        dij = ang[0, js]
        m = len(loc)
        inside = (ang[0][None, :] < dij[:, None]) & (ang[js] < dij[:, None])
        inside[:, 0] = False
        inside[np.arange(len(js)), js] = False
        cand = inside[:, :, None] & inside[:, None, :] & (ang[None, :, :] < dij[:, None, None])
        count += int(np.count_nonzero(cand & np.triu(np.ones((m, m), dtype=bool), 1)[None]))
    return float(count)


def build(catalog: GuideCatalog, params: PatternParams, *, budget_mb: float = DEFAULT_BUDGET_MB,
          progress=None) -> dict[str, np.ndarray]:
    """The pattern database as plain arrays (see the module docstring).

    progress: None, or a callable taking one line of text (what is built, how far, how long left).
    Raises BadInput before any work when the estimated size exceeds budget_mb.
    """
    params.check()
    est = estimate_size(catalog, params)
    mb = est["bytes"] / 2 ** 20
    # the build holds the patterns twice (enumeration + sorted copy)
    if 2.2 * mb > budget_mb:
        raise BadInput(f"the pattern database would take about {mb:.0f} MB ({est['patterns']:,} patterns) and "
                       f"about {2.2 * mb:.0f} MB while it is built, over the memory budget of {budget_mb:.0f} MB: "
                       f"raise it with --memory-mb or narrow the range of pattern sizes")
    say = progress or (lambda line: None)
    say(f"building the blind pattern database once: ~{est['patterns']:,} patterns of four stars, "
        f"~{mb:.0f} MB, {len(est['levels'])} levels of {params.min_edge_deg:g}-{params.max_edge_deg:g} deg")
    rows_all, keys_all, level_of = [], [], []
    t0 = time.perf_counter()
    done = 0.0
    for li, d in enumerate(params.levels()):
        rows = level_stars(catalog, d, params)
        quads = level_patterns(catalog.xyz[rows], math.radians(d / params.step), math.radians(d))
        quads = rows[quads].astype(np.int32)
        keys_all.append(pattern_keys(catalog.xyz, quads, params.bin_width))
        rows_all.append(quads)
        level_of.append(np.full(len(quads), li, dtype=np.int8))
        done += len(quads)
        el = time.perf_counter() - t0
        left = el / max(done, 1) * max(est["patterns"] - done, 0)
        say(f"  level {li + 1}/{len(params.levels())} ({d / params.step:.2f}-{d:.2f} deg): {len(rows):,} stars, "
            f"{len(quads):,} patterns; {el:.0f} s so far, ~{left:.0f} s left")
    keys = np.concatenate(keys_all)
    del keys_all
    bits = table_bits(len(keys))
    bucket = bucket_of(keys, bits)
    order = np.lexsort((keys, bucket))
    start = np.searchsorted(bucket[order], np.arange((1 << bits) + 1)).astype(np.int64)
    return {"keys": keys[order], "rows": np.concatenate(rows_all)[order],
            "level": np.concatenate(level_of)[order], "bucket_start": start,
            "edges_deg": np.array(params.levels(), dtype=np.float64)}


def table_bits(n_patterns: int) -> int:
    """Hash-table size: the power of two at or above the pattern count (at least 2^10)."""
    return max(10, int(math.ceil(math.log2(max(n_patterns, 1)))))


_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def bucket_of(keys: np.ndarray, bits: int) -> np.ndarray:
    """Fibonacci hashing of the keys into 2^bits buckets."""
    with np.errstate(over="ignore"):
        h = keys.astype(np.uint64) * _GOLDEN
    return (h >> np.uint64(64 - bits)).astype(np.int64)


def lookup(keys: np.ndarray, bucket_start: np.ndarray, needles: np.ndarray,
           prefetch: Callable[[str, np.ndarray], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(needle index, table index) of every stored pattern whose key equals a needle: two reads of
    the bucket table per needle, then the bucket's entries compared. prefetch(name, indices): told
    before each table ("bucket_start", "keys") is read at those indices (a memory map asks for its pages)."""
    bits = int(round(math.log2(len(bucket_start) - 1)))
    b = bucket_of(needles, bits)
    if prefetch is not None:
        prefetch("bucket_start", np.concatenate([b, b + 1]))
    a = bucket_start[b]
    n = bucket_start[b + 1] - a
    if prefetch is not None:
        prefetch("keys", np.concatenate([a, a + np.maximum(n - 1, 0)]))
    total = int(n.sum())
    if total == 0:
        e = np.zeros(0, dtype=np.int64)
        return e, e
    ni = np.repeat(np.arange(len(needles)), n)
    ti = np.repeat(a - np.cumsum(np.r_[0, n[:-1]]), n) + np.arange(total)
    hit = keys[ti] == needles[ni]
    return ni[hit], ti[hit]


def key_dict(catalog: GuideCatalog, params: PatternParams) -> dict:
    """The database key: the catalog and the pattern parameters (never a camera)."""
    return {"method": "patterns", "format": FORMAT_VERSION, "params": asdict(params),
            "catalog": {"fingerprint": catalog.fingerprint, "stars": len(catalog), "epoch": float(catalog.epoch),
                        "filters": list(catalog.history)}}


def print_progress(line: str) -> None:
    print(line, file=sys.stderr, flush=True)
