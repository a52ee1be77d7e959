"""Blind identification: no field of view needed, any camera, lens distortion fitted.

The front end that real photographs need (tetra3 and cedar-solve solve the same way; the database
is `skyview.identify.patterns`):

1. Patterns in the image. The `pattern_stars` brightest centroids, every four of them (brightest
   first: the quads whose faintest star is brightest come first). Their six separations are taken
   as angles through a pinhole of an assumed FOV; because the gnomonic projection is not quite
   scale-free, this is done for a ladder of assumed FOVs across the searched range (a factor
   `fov_ladder` apart), and a candidate is kept only where the FOV it implies is close to the one
   assumed.
2. Look-up. The five edge ratios of each quad, widened by +-`ratio_tolerance`, give the bins to look
   up in the sorted key table; the candidates' own ratios (from the catalog) must agree within the
   tolerance, and the FOV they imply (the catalog's largest separation over the image's) must lie
   in the searched range (a candidate whose level's band of sizes cannot give such an FOV is dropped
   on its level alone, before its stars are read).
3. Hypothesis. The four stars are put in correspondence by the permutation whose separations agree
   best; the attitude is the SVD solution of the four pairs with the implied FOV.
4. Quick check. The catalog stars in that frame, the brightest `depth_factor` times as many as the
   centroids used (so the depth follows the image: a narrow deep field and a wide shallow one both
   get the stars they show), are projected; centroids within `quick_radius_px` of one count. The
   chance of that many by accident (catalog density x pi r^2, binomial, times the hypotheses
   checked so far) must be below 1e-3; then the camera is fitted (`skyview.core.camera_fit`: attitude,
   focal length, k1 and k2 where the stars support them) and the stars re-matched, twice.
5. The shared verification (`skyview.identify.verify`) with the fitted camera, the catalog to the
   magnitude of the frame's depth and the measured residual noise; only a verified hypothesis is
   reported. The number of quick checks made is its Bonferroni factor.
"""

from __future__ import annotations

import functools
import itertools
import time
from dataclasses import dataclass
from functools import partial

import numpy as np

from skyview.core.attitude import proper_rotation
from skyview.core.camera import FISHEYE_FOV_RANGE_DEG, PINHOLE, Camera, pinhole_rays, rows_turned_over
from skyview.core.catalog import GuideCatalog
from skyview.identify import database
from skyview.identify import patterns as pdb
from skyview.identify.base import FAILED, Identification, PixelStars, Search, Step
from skyview.identify.camera_refit import CAP, BlindParams, CameraRefit, NearestPixels
from skyview.identify.layers import SkyPlaces, even_sample
from skyview.identify.steps import LazyStep

PERMUTATIONS = np.array(list(itertools.permutations(range(4))))
_TURN_ROWS = np.array([1.0, -1.0, 1.0])  # a ray in the image with its rows turned over: its y changes sign
# the pair index (in PAIRS_OF_FOUR order) of each ordered pair of the four stars
_PAIR_INDEX = {(int(a), int(b)): k for k, (a, b) in enumerate(pdb.PAIRS_OF_FOUR)}
_PAIR_INDEX.update({(b, a): k for (a, b), k in list(_PAIR_INDEX.items())})
# for each permutation p, the catalog edge that lands on each image edge
PERM_EDGES = np.array([[_PAIR_INDEX[(int(p[a]), int(p[b]))] for a, b in pdb.PAIRS_OF_FOUR] for p in PERMUTATIONS])
# a ratio +- the tolerance spans up to three bins (tolerance < bin width): every bin offset of the five ratios
BIN_OFFSETS = np.array(list(itertools.product((0, 1, 2), repeat=pdb.N_RATIOS)), dtype=np.int64)
# the bins a quad's ratios touch, by the span of each ratio (0, 1 or 2 bins past its lowest): the span's
# code (base 3, the first ratio most significant) indexes the offsets that fit in it, packed as keys (a
# key is linear in its quantised ratios, and the lowest bin plus an offset never passes the highest)
_SPAN_WEIGHTS = 3 ** np.arange(pdb.N_RATIOS - 1, -1, -1)
_CODE_OFFSETS = [np.flatnonzero(np.all(BIN_OFFSETS <= BIN_OFFSETS[c], axis=1)) for c in range(len(BIN_OFFSETS))]
CODE_COUNT = np.array([len(o) for o in _CODE_OFFSETS], dtype=np.int64)
CODE_START = np.r_[0, np.cumsum(CODE_COUNT)]
CODE_KEYS = pdb.pack_key(BIN_OFFSETS[np.concatenate(_CODE_OFFSETS)])
WIDE_FROM_DEG = 54.0  # FOVs above this are searched after the narrower ones (see BlindIdentifier.identify)
PATTERN_SLIDE = 8  # when the brightest stars' patterns do not verify, the window of pattern stars moves this far
MAX_SLIDE_DEPTH = 40  # down to this many stars (the verification's own depth)
BATCH_STARS = (5, 6, 8, 10, 12, 14, 16)  # the quads are looked up in batches: those among the 5 brightest, then 6, ...
PLACES_CAP = 20_000  # a look-up step draws at most this many of its hit patterns (an even sample)


def _ranges(start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The indices start[k], ..., start[k] + count[k] - 1 of every k, one after the other."""
    total = int(count.sum())
    return np.repeat(start - np.cumsum(count) + count, count) + np.arange(total)


def _candidate_rows(table_rows: np.ndarray, patterns: np.ndarray) -> list[int]:
    """The catalog rows of the first CAP candidate patterns, each once."""
    return sorted({int(r) for r in table_rows[patterns[:CAP]].ravel()})


def _candidate_groups(table_rows: np.ndarray, patterns: np.ndarray) -> list[tuple[int, ...]]:
    """The first CAP candidate patterns as groups of four catalog rows."""
    return [tuple(int(r) for r in g) for g in table_rows[patterns[:CAP]]]


def _through_rungs(uv: np.ndarray, fovs: np.ndarray, width: int, height: int, model: str) -> np.ndarray:
    """(rungs, N, 3): the pixels uv unprojected through each assumed FOV's camera, `Camera.unproject`'s
    numbers; a pinhole's rungs all at once (`pinhole_rays`)."""
    if model != PINHOLE:
        return np.stack([Camera.from_fov(float(f), width, height, model=model).unproject(uv) for f in fovs])
    # the rungs' focal lengths as Camera.from_fov makes them (the same operations on an array: the same numbers)
    focal = (width / (2.0 * np.tan(np.radians(np.asarray(fovs, dtype=np.float64)) / 2.0)))[:, None, None]
    return pinhole_rays(uv - np.array([(width - 1) / 2.0, (height - 1) / 2.0]), focal)


@functools.lru_cache(maxsize=64)
def quads_in_order(n: int) -> np.ndarray:
    """Every four of n stars (ranks), brightest first: by the faintest star of the quad, then by the sum of
    ranks (made once per n, read-only)."""
    quads = np.array(list(itertools.combinations(range(n), 4)), dtype=np.int64).reshape(-1, 4)
    quads = quads[np.lexsort((quads.sum(axis=1), quads.max(axis=1)))]
    quads.flags.writeable = False
    return quads


@functools.lru_cache(maxsize=64)
def _faintest_of_quads(n: int) -> np.ndarray:
    """The faintest star (highest rank) of each of `quads_in_order(n)`: non-decreasing (read-only)."""
    faintest = quads_in_order(n).max(axis=1)
    faintest.flags.writeable = False
    return faintest


def fov_ladder(lo: float, hi: float, ladder_deg2: float) -> list[tuple[float, float]]:
    """Assumed FOVs (deg) and the factor each covers, from lo to hi.

    The edge ratios measured through a pinhole of the wrong FOV err by about F^2 |s - 1| (F in
    radians, s the ratio of assumed to true FOV): one assumption serves a factor 2 at 5 deg but only
    5 % at 40 deg, so the ladder is dense where fields are wide.
    """
    out = []
    edge = lo
    while edge < hi * (1 - 1e-9):
        s = 1.0 + min(0.7, ladder_deg2 / edge ** 2)
        centre = min(edge * s, hi)
        s_c = 1.0 + min(0.7, ladder_deg2 / centre ** 2)
        out.append((centre, max(s, s_c)))
        edge = centre * s_c
    return out or [(lo, 1.0)]


@dataclass
class _Progress:
    """What one blind search carries between its batches of quads."""

    uv: np.ndarray
    n_obs: int
    width: int
    height: int
    done_upto: int = 0
    checks: int = 0
    shown: int = 0
    out_of_budget: bool = False
    timed_out: bool = False
    gave_up: str = ""  # how many checks and how long, when the budget ran out
    reason: str = ""
    model: str = PINHOLE  # the lens searched through
    mirror: bool = True  # also search the image as a mirror image of the sky (its rows turned over)
    mirror_budget: int = 0  # the mirror image's checks at most, in the whole search (its max_checks)
    normal_checks: int = 0  # the checks of the image as it is (its budget's) ...
    mirror_checks: int = 0  # ... and of its mirror image; `checks` counts both (Bonferroni)

    def __post_init__(self):
        self.tree = NearestPixels(self.uv[: self.n_obs])
        self._mirror = None

    def mirrored(self) -> tuple[np.ndarray, NearestPixels]:
        """The centroids with the image's rows turned over (v -> height - 1 - v), and their nearest-star table."""
        if self._mirror is None:
            uv = rows_turned_over(self.uv, self.height)
            self._mirror = (uv, NearestPixels(uv[: self.n_obs]))
        return self._mirror


class BlindIdentifier(CameraRefit):
    """Blind identification against the sky's pattern database; one instance serves every camera."""

    name = "blind"

    def __init__(self, catalog: GuideCatalog, *, pattern_params: pdb.PatternParams | None = None,
                 params: BlindParams | None = None, memory_mb: float = pdb.DEFAULT_BUDGET_MB, progress=None):
        self.pattern_params = pattern_params or pdb.PatternParams()
        super().__init__(catalog, params, database_key=pdb.key_dict(catalog, self.pattern_params))
        arrays, info = database.load_or_build(
            self.database_key, lambda: pdb.build(catalog, self.pattern_params, budget_mb=memory_mb, progress=progress),
            mmap=True)
        self.keys = np.asarray(arrays["keys"])  # plain views of the memory map
        self.rows = np.asarray(arrays["rows"])
        self.bucket_start = np.asarray(arrays["bucket_start"])
        self.level = np.asarray(arrays["level"])
        # the table is read at random places: no read-ahead; and the first search after the database is
        # opened, when its pages are likely not in memory yet (a process's first solve: ~1,400 of them on a
        # photograph), asks for the pages each look-up will read all at once (~250 -> ~60 ms on a cold page
        # cache); after it, asking costs more than it saves (~2 ms a solve), so it stops
        self._maps = arrays
        database.random_access(arrays)
        self._cold = True
        # each level's band of largest edges, radians, [lo, hi) (patterns.py), widened by 1e-6 for
        # rounding: the look-up drops the patterns whose size cannot give an FOV it searches
        band_hi = np.radians(np.asarray(arrays["edges_deg"], dtype=np.float64))
        self._band = (band_hi / self.pattern_params.step * (1.0 - 1e-6), band_hi * (1.0 + 1e-6))
        self.database_info = {**info, "patterns": int(len(self.keys))}
        edges = self.pattern_params.levels()
        # a field shows patterns up to about its diagonal and down to a quarter of its width
        self.fov_range_deg = (max(edges[-1] / self.pattern_params.step * 1.4, 0.5), min(edges[0] * 1.2, 90.0))

    # ------------------------------------------------------------------ main
    def identify(self, uv: np.ndarray, width: int, height: int, *, fov_deg: float | None = None,
                 fov_error: float = 0.1, max_checks: int | None = None,
                 slide: bool = True, model: str = PINHOLE,
                 checks_before: int = 0, mirror: bool = True) -> Identification:
        """Identify centroids uv (N, 2), brightest first, of a width x height image; max_checks: the quick
        checks allowed (None: params.max_checks); slide: when no pattern of the brightest
        params.pattern_stars verifies, search the next ones after them too; every centroid verifies. model:
        the lens the image is searched through
        (`skyview.core.camera`: a fisheye over FISHEYE_FOV_RANGE_DEG, its k1 and k2 fitted like a
        pinhole's). checks_before: hypotheses already checked on this image by earlier searches (another
        database, another lens): the verification counts them with its own (Bonferroni). The template's
        `Identification`; when identified, with the fitted `camera`, the verification's `mag_limit` and
        the measured `sigma_rad`. mirror: a pattern that fits the catalog's only as a mirror image (the sky
        seen through an odd number of mirrors, a star diagonal's; an export flipped) is checked too, as one
        of the image with its rows turned over (`rows_turned_over`), within a budget of its own (max_checks for
        the whole search), every check counted in the verification; identified
        so, `stats["rows_reversed"]` is True and the matches, camera and attitude are that image's."""
        search = self.begin(PixelStars(np.asarray(uv, dtype=np.float64).reshape(-1, 2), int(width), int(height)))
        search.data.update(fov_deg=fov_deg, fov_error=fov_error, max_checks=max_checks, slide=slide, model=model,
                           checks_before=int(checks_before), mirror=bool(mirror))
        try:
            return self.run(search)
        finally:
            self._cold = False

    def _prefetch(self, name: str, rows: np.ndarray) -> None:
        database.prefetch(self._maps[name], rows)

    def hypotheses(self, search: Search):
        """The search (the module docstring): the quads' look-ups and quick checks; each hypothesis that
        passes its quick check is fitted (`CameraRefit._fitted`) and yielded for the shared verification."""
        p, d = self.params, search.data
        uv, width, height, model = search.obs.uv, search.obs.width, search.obs.height, d["model"]
        span = self.fov_range_deg if model == PINHOLE else FISHEYE_FOV_RANGE_DEG
        lo, hi = span
        fov_deg, fov_error = d["fov_deg"], d["fov_error"]
        if fov_deg is not None:
            lo, hi = fov_deg * (1.0 - fov_error), fov_deg * (1.0 + fov_error)
            if hi < span[0] or lo > span[1]:
                what = "the blind database covers" if model == PINHOLE else f"the {model} search covers"
                return self._cannot(search, f"{what} FOVs of {span[0]:.1f}-{span[1]:.1f} deg, not {lo:.2f}-{hi:.2f} deg")
            lo, hi = max(lo, span[0]), min(hi, span[1])
        budget = p.max_checks if d["max_checks"] is None else int(d["max_checks"])
        state = _Progress(uv, min(len(uv), p.verify_stars), width, height, model=model, mirror=d["mirror"],
                          mirror_budget=budget)
        state.checks = d["checks_before"]
        # the brightest pattern_stars first; when no pattern of them verifies, the window slides down the
        # brightness order (a lit roof, street lights or a planet can take the brightest places), each
        # window with its own budget of checks, every check counted in the verification (Bonferroni)
        # and one time budget for all
        starts = [0] + [s for s in range(PATTERN_SLIDE, MAX_SLIDE_DEPTH, PATTERN_SLIDE)
                        if d["slide"] and len(uv) - s >= 8]
        windows = [np.arange(s, min(len(uv), s + p.pattern_stars)) for s in starts]
        if len(windows[0]) < 4:
            return self._cannot(search, f"{len(windows[0])} stars found: a pattern needs four")
        n_cands = 0
        for pat in windows:
            n_cands += yield from self._search(search, pat, lo, hi, state, budget)
            if state.timed_out:
                break
        # none verified
        # (checks_normal: what `checks` would be without the mirror image's, the image's own budget spent)
        search.stats.update(checks=state.checks, candidates=n_cands,
                            checks_normal=d["checks_before"] + state.normal_checks)
        if state.checks > d["checks_before"]:
            search.reasons.append(": ".join(x for x in (state.gave_up, state.reason) if x))
        else:
            self._cannot(search, "no catalog pattern matches the brightest stars (not a star field, or its FOV is "
                                 f"outside {lo:.1f}-{hi:.1f} deg)")

    @staticmethod
    def _cannot(search: Search, reason: str) -> None:
        """The search could not run on this image (FAILED), and why; the hypotheses checked before it are
        still counted (a later search's Bonferroni factor reads them)."""
        search.result.status = FAILED
        search.reasons.append(reason)
        search.stats.setdefault("checks", search.data["checks_before"])

    def _search(self, search: Search, pat, lo, hi, state: "_Progress", budget: int):
        """The quads of the pattern stars `pat` (indices of uv, brightest first), looked up and checked in
        batches (BATCH_STARS): the quads of the 5 brightest, then those that add the next stars, each batch
        checked before the next is looked up (the candidates are checked quad by quad in brightness order
        either way: a field whose brightest stars are stars costs one small look-up). Fields wider than
        WIDE_FROM_DEG (a ladder twice as long, for a few cameras) are a section of their own, searched
        after the narrower one at each batch, each section with `budget` checks. Yields the hypotheses (the
        search ends at an accepted one); returns the number of candidates."""
        n_pat = len(pat)
        if n_pat < 4:
            return 0
        uv, width, height = search.obs.uv, search.obs.width, search.obs.height
        quads = quads_in_order(n_pat)
        quads_uv = pat[quads]  # the quads as indices of uv
        state.done_upto = 0
        n_cands = 0
        sections = [(a, b) for a, b in ((lo, min(hi, WIDE_FROM_DEG)), (max(lo, WIDE_FROM_DEG), hi)) if a < b]
        spent = [0] * len(sections)
        exhausted: set[int] = set()
        for upto in sorted({min(n_pat, k) for k in BATCH_STARS if k <= n_pat} | {n_pat}):
            # the quads whose faintest star is below `upto` and not below the last batch's: a run of them, the
            # quads being in the order of their faintest star
            faintest = _faintest_of_quads(n_pat)
            batch = np.arange(int(np.searchsorted(faintest, state.done_upto)), int(np.searchsorted(faintest, upto)))
            state.done_upto = upto
            if len(batch) == 0:
                continue
            for k, (s_lo, s_hi) in enumerate(sections):
                if k in exhausted:
                    continue
                cands = self._lookup(uv[pat], quads, batch, width, height, s_lo, s_hi, state.model)
                n_cands += len(cands["pattern"])
                self._record_lookup(search.steps, cands, pat[:upto].tolist(), upto, len(batch), s_lo, s_hi)
                before = state.normal_checks
                yield from self._check(search, quads_uv, cands, state, max_checks=budget - spent[k])
                spent[k] += state.normal_checks - before
                if state.timed_out:
                    return n_cands
                if state.out_of_budget:
                    exhausted.add(k)
                    state.out_of_budget = False
            if len(exhausted) == len(sections):
                break
        return n_cands

    # ------------------------------------------------------------------ look-up
    def _record_lookup(self, steps, cands: dict, observed: list[int], upto: int, n_quads: int,
                       s_lo: float, s_hi: float) -> None:
        """Three steps per look-up, the hits thinning: the pattern table's hits across the sky ("lookup"),
        those of a size that can give an FOV in the range, those whose ratios agree and whose FOV lies in it,
        one per quad and pattern ("prune" twice). What a step draws (the hit patterns' centres, an even
        sample; the first CAP candidates, in the order they are checked) is made when it is first read:
        a solve reads none."""
        n = cands["counts"]
        fov = f"FOV {s_lo:.2f}-{s_hi:.2f} deg"
        where = {"stars": upto, "quads": n_quads, "fov_min_deg": s_lo, "fov_max_deg": s_hi}
        steps.append(LazyStep("lookup", f"patterns of four among the {upto} brightest stars ({n_quads} new), {fov}: "
                                        f"{n['hits']} hits in the pattern table, from {n['needles']} bins looked up",
                              observed=observed,
                              layers_of=partial(self._places, cands["hit_rows"], "patterns the look-up hit"),
                              numbers={**where, "bins": n["needles"], "hits": n["hits"], "candidates": n["hits"]}))
        steps.append(LazyStep("prune", f"of the {n['hits']} hits, {n['sized']} are of a size that can give an FOV "
                                       f"of {s_lo:.2f}-{s_hi:.2f} deg",
                              observed=observed,
                              layers_of=partial(self._places, cands["sized_rows"], "patterns of a size that fits"),
                              numbers={**where, "hits": n["hits"], "candidates": n["sized"]}))
        steps.append(LazyStep("prune", f"of those {n['sized']}, {n['agree']} have ratios that agree within the "
                                       f"tolerance and an FOV in the range: {len(cands['pattern'])} candidates, "
                                       f"one per quad and catalog pattern, to check best first",
                              observed=observed,
                              catalog_of=partial(_candidate_rows, self.rows, cands["pattern"]),
                              groups_of=partial(_candidate_groups, self.rows, cands["pattern"]),
                              numbers={**where, "agree": n["agree"], "candidates": len(cands["pattern"])}))

    def _places(self, patterns: np.ndarray, name: str) -> tuple[SkyPlaces]:
        """The distinct table patterns as a `SkyPlaces` layer: their centres, an even sample of PLACES_CAP."""
        distinct = np.unique(patterns)
        drawn = distinct[even_sample(len(distinct), PLACES_CAP)]
        centre = self.catalog.xyz[self.rows[drawn]].sum(axis=1)
        centre /= np.linalg.norm(centre, axis=1, keepdims=True)
        return (SkyPlaces(centre.astype(np.float32), len(distinct), name),)

    def _lookup(self, uv: np.ndarray, quads_all: np.ndarray, batch: np.ndarray, width: int, height: int,
                lo: float, hi: float, model: str = PINHOLE) -> dict:
        """Catalog patterns that agree with quads_all[batch]: (quad index, table row, FOV, ratio error).

        Every rung of the FOV ladder at once: the quads' ratios through each rung's pinhole, the bins a
        ratio +- tolerance touches, one hash look-up of the distinct keys of all rungs (neighbouring rungs
        share most of theirs), each stored pattern's ratios computed once however many rungs hit it."""
        quads = quads_all[batch]
        p, pp = self.params, self.pattern_params
        w, tol = pp.bin_width, p.ratio_tolerance
        ladder = fov_ladder(lo, hi, p.ladder_deg2 if model == PINHOLE else p.fisheye_ladder_deg2)
        fa = np.array([f for f, _ in ladder])
        cover = np.array([c for _, c in ladder])
        f_lo, f_hi = np.maximum(lo, fa / cover), np.minimum(hi, fa * cover)  # the FOVs each rung accepts
        vec = _through_rungs(uv, fa, width, height, model)
        ratios, largest = pdb.edge_ratios(pdb.separations(vec[:, quads]))  # (rungs, Q, 5), (rungs, Q)
        # a quad with a star a lens cannot see at a rung (beyond a fisheye's image circle) has no ratios there
        seen = np.isfinite(ratios).all(axis=2) & np.isfinite(largest) & (largest > 0)
        ratios = np.where(seen[:, :, None], ratios, 0.0)
        qlo = pdb.quantise(ratios - tol, w)
        span = np.minimum(pdb.quantise(ratios + tol, w) - qlo, 2)
        ri, qi = np.nonzero(seen)  # the (rung, quad) pairs, in rung then quad order
        # the pairs whose lowest bins and spans agree (neighbouring rungs, mostly) share their needles
        combo = pdb.pack_key(qlo[ri, qi]) * len(BIN_OFFSETS) + span[ri, qi] @ _SPAN_WEIGHTS
        combos, member_combo = np.unique(combo, return_inverse=True)
        base, code = np.divmod(combos, len(BIN_OFFSETS))
        needles = np.repeat(base, CODE_COUNT[code]) + CODE_KEYS[_ranges(CODE_START[code], CODE_COUNT[code])]
        distinct, which = np.unique(needles, return_inverse=True)
        cold = self._prefetch if self._cold else None
        hit_needle, hit_row = pdb.lookup(self.keys, self.bucket_start, distinct, cold)  # by distinct key, ascending
        if cold is not None:  # the hits' levels and stars are read next
            cold("level", hit_row)
            cold("rows", hit_row)
        per_key = np.bincount(hit_needle, minlength=len(distinct))
        first_hit = np.cumsum(per_key) - per_key
        # each combination's hits (its needles' in offset order), then each pair's: its combination's
        combo_rows = hit_row[_ranges(first_hit[which], per_key[which])]
        per_combo = np.bincount(np.repeat(np.arange(len(combos)), CODE_COUNT[code]), weights=per_key[which],
                                minlength=len(combos)).astype(np.int64)
        n_hits = per_combo[member_combo]
        total = int(n_hits.sum())
        counts = {"needles": len(distinct), "hits": total, "sized": 0, "agree": 0}
        if total == 0:
            return self._no_candidates(counts)
        prow = combo_rows[_ranges((np.cumsum(per_combo) - per_combo)[member_combo], n_hits)]
        j = np.repeat(np.arange(len(ri)), n_hits)
        r, q = ri[j], qi[j]
        # the FOV a pattern implies is fa * (its largest edge) / (the quad's): a pattern whose level's band of
        # largest edges cannot put it in its rung's range is dropped before its stars are read
        fits = self._sizes_fit(prow, largest[r, q] / fa[r], f_lo[r], f_hi[r])
        hit_rows = prow
        prow, r, q = prow[fits], r[fits], q[fits]
        counts["sized"] = len(prow)
        sized_rows = prow
        rows, at = np.unique(prow, return_inverse=True)
        c_ratios, c_largest = pdb.edge_ratios(pdb.separations(self.catalog.xyz[self.rows[rows]]))
        err = np.abs(c_ratios[at] - ratios[r, q]).max(axis=1)
        fov = fa[r] * c_largest[at] / largest[r, q]  # small-angle: the scale that maps image onto sky
        keep = (err <= tol) & (fov >= f_lo[r]) & (fov <= f_hi[r])
        counts["agree"] = int(keep.sum())
        if not keep.any():
            return self._no_candidates(counts, hit_rows, sized_rows)
        q, pr, f, er = batch[q[keep]], prow[keep], fov[keep], err[keep]
        # one entry per (quad, pattern): the one whose assumed FOV was closest
        order = np.lexsort((er, pr, q))
        q, pr, f, er = q[order], pr[order], f[order], er[order]
        first = np.r_[True, (q[1:] != q[:-1]) | (pr[1:] != pr[:-1])]
        q, pr, f, er = q[first], pr[first], f[first], er[first]
        order = np.lexsort((er, q))  # quads in their brightness order, best agreement first
        return {"quad": q[order], "pattern": pr[order], "fov": f[order], "err": er[order], "counts": counts,
                "hit_rows": hit_rows, "sized_rows": sized_rows}

    @staticmethod
    def _no_candidates(counts: dict, hit_rows: np.ndarray | None = None, sized_rows: np.ndarray | None = None) -> dict:
        """No candidate; counts: how many each stage of the look-up kept; hit_rows, sized_rows: the table
        patterns the look-up hit, and those of them whose size fits."""
        e = np.zeros(0, dtype=np.int64)
        return {"quad": e, "pattern": e, "fov": np.zeros(0), "err": np.zeros(0), "counts": counts,
                "hit_rows": e if hit_rows is None else hit_rows, "sized_rows": e if sized_rows is None else sized_rows}

    def _sizes_fit(self, prow: np.ndarray, size: np.ndarray, f_lo: float, f_hi: float) -> np.ndarray:
        """Which table patterns prow can imply an FOV in [f_lo, f_hi] degrees for quads whose largest
        edge is `size` times the assumed FOV (the FOV is the pattern's largest edge over size): those
        whose level's band of largest edges reaches [f_lo * size, f_hi * size]."""
        lvl = self.level[prow]
        return (self._band[1][lvl] >= f_lo * size) & (self._band[0][lvl] <= f_hi * size)

    # ------------------------------------------------------------------ hypotheses
    def _check(self, search: Search, quads, cands, state: "_Progress", max_checks: int):
        """Check candidates in order, at most max_checks of them (and as many of the mirror image's, up to the
        search's `mirror_budget`); each that passes its quick check is fitted and yielded (the search ends at an
        accepted one)."""
        first = state.normal_checks
        p = self.params
        uv, steps, t0, cpu0 = search.obs.uv, search.steps, search.t0, search.cpu0
        width, height, n_obs = state.width, state.height, state.n_obs
        for q, pr, fov in zip(cands["quad"], cands["pattern"], cands["fov"]):
            state.timed_out = time.thread_time() - cpu0 > p.time_budget_s  # (the search's CPU time: `Search.cpu0`)
            if state.normal_checks - first >= max_checks or state.timed_out:
                state.out_of_budget = True
                state.gave_up = (f"gave up after {state.checks} hypotheses ({time.thread_time() - cpu0:.1f} s of CPU time, "
                                 f"{time.perf_counter() - t0:.1f} s wall)")
                return
            obs4 = quads[q]
            rows4 = self.rows[pr].astype(np.int64)
            cam = Camera.from_fov(float(fov), width, height, model=state.model)
            b = cam.unproject(uv[obs4])
            if not np.isfinite(b).all():  # a star beyond what the lens can see at this FOV (a fisheye's corner
                continue  # past its 180 deg from the axis): no ray, no hypothesis
            r = self.catalog.xyz[rows4]
            # correspondence: the permutation of the catalog stars whose separations agree best
            cost = np.abs(pdb.separations(r)[PERM_EDGES] - pdb.separations(b)[None, :]).sum(axis=1)
            perm = PERMUTATIONS[int(np.argmin(cost))]
            rows4 = rows4[perm]
            r = r[perm]
            R = proper_rotation(b.T @ r)
            fit_px = np.hypot(*(cam.project(r @ R.T)[0] - uv[obs4]).T)
            tolerance = max(3.0 * p.quick_radius_px, 0.01 * width)
            here, tree, turned = uv, state.tree, False
            if fit_px.max() > tolerance:
                # the catalog's pattern as a mirror image of the quad: a fit with the image's rows turned over
                # (a ray's y changes sign), or a pattern that only shares its ratios
                if not state.mirror or state.mirror_checks >= state.mirror_budget:
                    continue
                here, tree = state.mirrored()
                R = proper_rotation((b * _TURN_ROWS).T @ r)
                if np.hypot(*(cam.project(r @ R.T)[0] - here[obs4]).T).max() > tolerance:
                    continue
                turned = True
            state.checks += 1
            if turned:
                state.mirror_checks += 1
            else:
                state.normal_checks += 1
            outcome = self._quick(here, n_obs, tree, obs4, rows4, cam, R)
            if state.shown < CAP:
                state.shown += 1
                steps.append(Step("hypothesis", f"stars {list(map(int, obs4))} as HIP "
                                                f"{[int(self.catalog.hip[k]) for k in rows4]} at FOV {fov:.2f} deg"
                                                f"{' (a mirror image: rows turned over)' if turned else ''}: "
                                                f"{outcome['note']}",
                                  observed=[int(i) for i in obs4], catalog=[int(k) for k in rows4],
                                  groups=[tuple(int(k) for k in rows4)],
                                  numbers={"fov_deg": float(fov), "agree": outcome["n_agree"],
                                           "tested": outcome["n_tested"], "p_chance": outcome["p"]}))
            if not outcome["passed"]:
                state.reason = f"the best hypothesis was not confirmed by the other stars ({outcome['note']})" \
                    if not state.reason else state.reason
                continue
            ver = yield from self._fitted(search, here, n_obs, obs4, rows4, outcome, state.checks,
                                          rows_reversed=turned)
            state.reason = ver.reason
