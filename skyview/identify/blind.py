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

import copy
import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import bdtrc

from skyview.core.camera import Camera
from skyview.core.camera_fit import CameraFit, fit_camera
from skyview.core.catalog import GuideCatalog, chord
from skyview.identify import database
from skyview.identify import patterns as pdb
from skyview.identify.base import FAILED, INCONCLUSIVE, Identification, Step
from skyview.identify.verify import BLEND_RADIUS_PX, verification_step, verify

PERMUTATIONS = np.array(list(itertools.permutations(range(4))))
# the pair index (in PAIRS_OF_FOUR order) of each ordered pair of the four stars
_PAIR_INDEX = {(int(a), int(b)): k for k, (a, b) in enumerate(pdb.PAIRS_OF_FOUR)}
_PAIR_INDEX.update({(b, a): k for (a, b), k in list(_PAIR_INDEX.items())})
# for each permutation p, the catalog edge that lands on each image edge
PERM_EDGES = np.array([[_PAIR_INDEX[(int(p[a]), int(p[b]))] for a, b in pdb.PAIRS_OF_FOUR] for p in PERMUTATIONS])
CAP = 200
WIDE_FROM_DEG = 54.0  # FOVs above this are searched after the narrower ones (see BlindIdentifier.identify)
BLEND_DELTA_MAG = 2.5  # a companion this much fainter moves a blended centroid by < 10 % of the separation


@dataclass(frozen=True)
class BlindParams:
    """The blind search (angles in degrees)."""

    fov_min_deg: float = 5.0  # horizontal FOV searched when none is given
    fov_max_deg: float = 40.0
    pattern_stars: int = 16  # brightest centroids combined four at a time (in batches, brightest first)
    verify_stars: int = 40  # brightest centroids the frame is checked with
    ratio_tolerance: float = 0.006  # edge ratios agree within this
    ladder_deg2: float = 60.0  # an assumed FOV F covers the FOVs within a factor 1 + ladder_deg2 / F^2
    depth_factor: float = 2.0  # catalog stars projected per centroid used
    quick_radius_px: float = 4.0
    quick_threshold: float = 1e-3
    max_checks: int = 400  # quick checks at most
    time_budget_s: float = 5.0


@dataclass
class BlindResult:
    identification: Identification
    camera: Camera | None = None  # the fitted camera when identified
    fit: CameraFit | None = None
    mag_limit: float | None = None  # the depth the verification used
    sigma_rad: float | None = None
    info: dict = field(default_factory=dict)


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
class _Search:
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

    def __post_init__(self):
        self.tree = cKDTree(self.uv[: self.n_obs])


class BlindIdentifier:
    """Blind identification against the sky's pattern database; one instance serves every camera."""

    name = "blind"

    def __init__(self, catalog: GuideCatalog, *, pattern_params: pdb.PatternParams | None = None,
                 params: BlindParams | None = None, memory_mb: float = pdb.DEFAULT_BUDGET_MB, progress=None):
        self.catalog = catalog
        self.pattern_params = pattern_params or pdb.PatternParams()
        self.params = params or BlindParams()
        self.database_key = pdb.key_dict(catalog, self.pattern_params)
        arrays, info = database.load_or_build(
            self.database_key, lambda: pdb.build(catalog, self.pattern_params, budget_mb=memory_mb, progress=progress),
            mmap=True)
        self.keys = np.asarray(arrays["keys"])  # plain views of the memory map
        self.rows = np.asarray(arrays["rows"])
        self.bucket_start = np.asarray(arrays["bucket_start"])
        self.level = np.asarray(arrays["level"])
        # each level's band of largest edges, radians, [lo, hi) (patterns.py), widened by 1e-6 for
        # rounding: the look-up drops the patterns whose size cannot give an FOV it searches
        band_hi = np.radians(np.asarray(arrays["edges_deg"], dtype=np.float64))
        self._band = (band_hi / self.pattern_params.step * (1.0 - 1e-6), band_hi * (1.0 + 1e-6))
        self.database_info = {**info, "patterns": int(len(self.keys))}
        edges = self.pattern_params.levels()
        # a field shows patterns up to about its diagonal and down to a quarter of its width
        self.fov_range_deg = (max(edges[-1] / self.pattern_params.step * 1.4, 1.0), min(edges[0] * 1.2, 90.0))
        self._depth_catalogs: dict[float, GuideCatalog] = {}

    # ------------------------------------------------------------------ depth
    def catalog_to(self, mag: float) -> GuideCatalog:
        """The catalog to `mag` (rounded up to a quarter magnitude), cached with its tree."""
        m = min(math.ceil(mag * 4.0) / 4.0, float(self.catalog.mag.max()))
        cat = self._depth_catalogs.get(m)
        if cat is None:
            cat = self._depth_catalogs[m] = self.catalog.brighter_than(m)
        return cat

    # ------------------------------------------------------------------ main
    def identify(self, uv: np.ndarray, width: int, height: int, *, fov_deg: float | None = None,
                 fov_error: float = 0.1) -> BlindResult:
        """Identify centroids uv (N, 2), brightest first, of a width x height image."""
        t0 = time.perf_counter()
        p = self.params
        uv = np.asarray(uv, dtype=np.float64)
        steps: list[Step] = []
        lo, hi = self.fov_range_deg
        if fov_deg is not None:
            lo, hi = fov_deg * (1.0 - fov_error), fov_deg * (1.0 + fov_error)
            if hi < self.fov_range_deg[0] or lo > self.fov_range_deg[1]:
                return self._fail(FAILED, f"the blind database covers FOVs of {self.fov_range_deg[0]:.1f}-"
                                          f"{self.fov_range_deg[1]:.1f} deg, not {lo:.2f}-{hi:.2f} deg", steps)
            lo, hi = max(lo, self.fov_range_deg[0]), min(hi, self.fov_range_deg[1])
        n_pat = min(len(uv), p.pattern_stars)
        if n_pat < 4:
            return self._fail(FAILED, f"{len(uv)} stars found: a pattern needs four", steps)
        quads = np.array(list(itertools.combinations(range(n_pat), 4)), dtype=np.int64)
        # brightest first: by the faintest star of the quad, then by the sum of ranks
        quads = quads[np.lexsort((quads.sum(axis=1), quads.max(axis=1)))]
        # in batches: the quads of the brightest 8 stars, then those that add the next stars. Fields
        # wider than WIDE_FROM_DEG (a ladder twice as long, for a few cameras) are a section of their
        # own, searched after the narrower one at each batch, each section with its own count of checks
        state = _Search(uv, min(len(uv), p.verify_stars), width, height)
        n_cands = 0
        res = None
        sections = [(a, b) for a, b in ((lo, min(hi, WIDE_FROM_DEG)), (max(lo, WIDE_FROM_DEG), hi)) if a < b]
        spent = [0] * len(sections)
        exhausted: set[int] = set()
        for upto in sorted({min(n_pat, k) for k in (8, 10, 12, 14, 16, n_pat) if k <= n_pat} | {n_pat}):
            batch = np.flatnonzero((quads.max(axis=1) < upto) & (quads.max(axis=1) >= state.done_upto))
            state.done_upto = upto
            if len(batch) == 0:
                continue
            for k, (s_lo, s_hi) in enumerate(sections):
                if k in exhausted:
                    continue
                cands = self._lookup(uv[:n_pat], quads, batch, width, height, s_lo, s_hi)
                n_cands += len(cands["pattern"])
                shown = self.rows[cands["pattern"][:CAP]]
                steps.append(Step("lookup", f"patterns of four among the {upto} brightest stars ({len(batch)} new), "
                                            f"FOV {s_lo:.2f}-{s_hi:.2f} deg: {len(cands['pattern'])} catalog patterns "
                                            "agree",
                                  observed=list(range(upto)),
                                  catalog=sorted({int(r) for r in shown.ravel()}),
                                  groups=[tuple(int(r) for r in g) for g in shown],
                                  numbers={"stars": upto, "quads": len(batch), "candidates": len(cands["pattern"]),
                                           "fov_min_deg": s_lo, "fov_max_deg": s_hi}))
                before = state.checks
                res = self._check(uv, quads, cands, state, steps, t0, max_checks=p.max_checks - spent[k])
                spent[k] += state.checks - before
                if res is not None or state.timed_out:
                    break
                if state.out_of_budget:
                    exhausted.add(k)
                    state.out_of_budget = False
            if res is not None or state.timed_out or len(exhausted) == len(sections):
                break
        if res is not None:
            return res
        reason = ": ".join(x for x in (state.gave_up, state.reason) if x) if state.checks else (
            "no catalog pattern matches the brightest stars (not a star field, or its FOV is outside "
            f"{lo:.1f}-{hi:.1f} deg)")
        return self._fail(INCONCLUSIVE if state.checks else FAILED, reason, steps,
                          stats={"checks": state.checks, "candidates": n_cands})

    # ------------------------------------------------------------------ look-up
    def _lookup(self, uv: np.ndarray, quads_all: np.ndarray, batch: np.ndarray, width: int, height: int,
                lo: float, hi: float) -> dict:
        """Catalog patterns that agree with quads_all[batch]: (quad index, table row, FOV, ratio error)."""
        quads = quads_all[batch]
        p, pp = self.params, self.pattern_params
        w, tol = pp.bin_width, p.ratio_tolerance
        # a ratio +- tol spans up to three bins (tol < w)
        offsets = np.array(list(itertools.product((0, 1, 2), repeat=pdb.N_RATIOS)), dtype=np.int64)
        found_q, found_p, found_f, found_err = [], [], [], []
        for fa, cover in fov_ladder(lo, hi, p.ladder_deg2):
            cam = Camera.from_fov(float(fa), width, height)
            vec = cam.unproject(uv)
            ratios, largest = pdb.edge_ratios(pdb.separations(vec[quads]))
            qlo = pdb.quantise(ratios - tol, w)
            qhi = pdb.quantise(ratios + tol, w)
            span = qhi - qlo
            ok = np.all(offsets[None, :, :] <= span[:, None, :], axis=2)  # (Q, 3^5)
            qi, oi = np.nonzero(ok)
            ni, prow = pdb.lookup(self.keys, self.bucket_start, pdb.pack_key(qlo[qi] + offsets[oi]))
            if len(prow) == 0:
                continue
            qrep = qi[ni]
            # the FOV a pattern implies is fa * (its largest edge) / (the quad's): a pattern whose level's
            # band of largest edges cannot put it in this rung's range is dropped before its stars are read
            f_lo, f_hi = max(lo, fa / cover), min(hi, fa * cover)  # the FOVs this rung accepts
            fits = self._sizes_fit(prow, largest[qrep] / fa, f_lo, f_hi)
            if not fits.all():
                prow, qrep = prow[fits], qrep[fits]
                if len(prow) == 0:
                    continue
            cat_v = self.catalog.xyz[self.rows[prow]]
            c_ratios, c_largest = pdb.edge_ratios(pdb.separations(cat_v))
            err = np.abs(c_ratios - ratios[qrep]).max(axis=1)
            fov = fa * c_largest / largest[qrep]  # small-angle: the scale that maps image onto sky
            keep = (err <= tol) & (fov >= f_lo) & (fov <= f_hi)
            found_q.append(batch[qrep[keep]])
            found_p.append(prow[keep])
            found_f.append(fov[keep])
            found_err.append(err[keep])
        if sum(len(x) for x in found_q) == 0:
            e = np.zeros(0, dtype=np.int64)
            return {"quad": e, "pattern": e, "fov": np.zeros(0), "err": np.zeros(0)}
        q, pr, f, er = (np.concatenate(x) for x in (found_q, found_p, found_f, found_err))
        # one entry per (quad, pattern): the one whose assumed FOV was closest
        order = np.lexsort((er, pr, q))
        q, pr, f, er = q[order], pr[order], f[order], er[order]
        first = np.r_[True, (q[1:] != q[:-1]) | (pr[1:] != pr[:-1])]
        q, pr, f, er = q[first], pr[first], f[first], er[first]
        order = np.lexsort((er, q))  # quads in their brightness order, best agreement first
        return {"quad": q[order], "pattern": pr[order], "fov": f[order], "err": er[order]}

    def _sizes_fit(self, prow: np.ndarray, size: np.ndarray, f_lo: float, f_hi: float) -> np.ndarray:
        """Which table patterns prow can imply an FOV in [f_lo, f_hi] degrees for quads whose largest
        edge is `size` times the assumed FOV (the FOV is the pattern's largest edge over size): those
        whose level's band of largest edges reaches [f_lo * size, f_hi * size]."""
        lvl = self.level[prow]
        return (self._band[1][lvl] >= f_lo * size) & (self._band[0][lvl] <= f_hi * size)

    # ------------------------------------------------------------------ hypotheses
    def _check(self, uv, quads, cands, state: "_Search", steps, t0, max_checks: int) -> BlindResult | None:
        """Check candidates in order, at most max_checks of them; the first verified one is the result,
        None if none is."""
        first = state.checks
        p = self.params
        width, height, n_obs = state.width, state.height, state.n_obs
        for q, pr, fov in zip(cands["quad"], cands["pattern"], cands["fov"]):
            state.timed_out = time.perf_counter() - t0 > p.time_budget_s
            if state.checks - first >= max_checks or state.timed_out:
                state.out_of_budget = True
                state.gave_up = f"gave up after {state.checks} hypotheses ({time.perf_counter() - t0:.1f} s)"
                return None
            obs4 = quads[q]
            rows4 = self.rows[pr].astype(np.int64)
            cam = Camera.from_fov(float(fov), width, height)
            b = cam.unproject(uv[obs4])
            r = self.catalog.xyz[rows4]
            # correspondence: the permutation of the catalog stars whose separations agree best
            cost = np.abs(pdb.separations(r)[PERM_EDGES] - pdb.separations(b)[None, :]).sum(axis=1)
            perm = PERMUTATIONS[int(np.argmin(cost))]
            rows4 = rows4[perm]
            r = r[perm]
            U, _, Vt = np.linalg.svd(b.T @ r)
            R = U @ np.diag([1.0, 1.0, np.linalg.det(U) * np.linalg.det(Vt)]) @ Vt
            fit_px = np.hypot(*(cam.project(r @ R.T)[0] - uv[obs4]).T)
            if fit_px.max() > max(3.0 * p.quick_radius_px, 0.01 * width):
                continue  # a mirror image, or a pattern that only shares its ratios
            state.checks += 1
            outcome = self._quick(uv, n_obs, state.tree, obs4, rows4, cam, R, state.checks)
            if state.shown < CAP:
                state.shown += 1
                steps.append(Step("hypothesis", f"stars {list(map(int, obs4))} as HIP "
                                                f"{[int(self.catalog.hip[k]) for k in rows4]} at FOV {fov:.2f} deg: "
                                                f"{outcome['note']}",
                                  observed=[int(i) for i in obs4], catalog=[int(k) for k in rows4],
                                  groups=[tuple(int(k) for k in rows4)],
                                  numbers={"fov_deg": float(fov), "agree": outcome["n_agree"],
                                           "tested": outcome["n_tested"], "p_chance": outcome["p"]}))
            if not outcome["passed"]:
                state.reason = f"the best hypothesis was not confirmed by the other stars ({outcome['note']})" \
                    if not state.reason else state.reason
                continue
            res = self._finish(uv, n_obs, obs4, rows4, outcome, state.checks, width, height, steps, t0)
            if res.identification.identified:
                return res
            state.reason = res.identification.reason
        return None

    def _frame_rows(self, cam: Camera, R: np.ndarray, n_obs: int) -> np.ndarray:
        """Catalog rows on the sensor for (cam, R), the brightest depth_factor * n_obs of them."""
        near = self.catalog.within(R[2], cam.half_diagonal_rad * 1.02)
        if len(near) == 0:
            return near
        uv, front = cam.project(self.catalog.xyz[near] @ R.T)
        near = near[front & cam.in_image(uv)]
        keep = max(int(self.params.depth_factor * n_obs), 8)
        return near[np.argsort(self.catalog.mag[near], kind="stable")[:keep]]

    def _match(self, uv, n_obs, obs_tree, cam, R, radius_px):
        rows = self._frame_rows(cam, R, n_obs)
        if len(rows) == 0:
            return {}, rows
        puv, _ = cam.project(self.catalog.xyz[rows] @ R.T)
        d, j = obs_tree.query(puv, k=1, distance_upper_bound=radius_px)
        ok = np.isfinite(d)
        pairs = {}
        for ci in np.argsort(d)[: int(ok.sum())]:  # nearest first, each observed star once
            o = int(j[ci])
            if o not in pairs:
                pairs[o] = int(rows[ci])
        return pairs, rows

    def _quick(self, uv, n_obs, obs_tree, obs4, rows4, cam, R, checks) -> dict:
        p = self.params
        pairs, rows = self._match(uv, n_obs, obs_tree, cam, R, p.quick_radius_px)
        hyp = set(int(i) for i in obs4)
        agree = {o: c for o, c in pairs.items() if o not in hyp and c not in set(rows4.tolist())}
        n_tested = n_obs - 4
        density = len(rows) / (cam.width * cam.height)  # catalog stars per pixel
        p1 = min(1.0, density * math.pi * p.quick_radius_px ** 2)
        prob = float(min(1.0, checks * bdtrc(len(agree) - 1, n_tested, p1))) if agree else 1.0
        passed = prob < p.quick_threshold
        note = f"{len(agree)} of {n_tested} other stars land on the {len(rows)} brightest catalog stars, " \
               f"chance {prob:.1e}"
        return {"passed": passed, "n_agree": len(agree), "n_tested": n_tested, "p": prob, "note": note,
                "agree": agree, "camera": cam, "R": R}

    def _finish(self, uv, n_obs, obs4, rows4, quick, checks, width, height, steps, t0) -> BlindResult:
        p = self.params
        obs_tree = cKDTree(uv[:n_obs])
        matches = {**{int(o): int(c) for o, c in zip(obs4, rows4)}, **quick["agree"]}
        cam, R = quick["camera"], quick["R"]
        fit, fitted_on = None, None
        # the attitude and the scale first, then the distortion too, each followed by matching again
        for radius, distortion in ((p.quick_radius_px, False), (max(1.5, 0.5 * p.quick_radius_px), None)):
            idx = np.array(sorted(matches))
            fit = fit_camera(uv[idx], self.catalog.xyz[[matches[i] for i in idx]], cam, R,
                             fit_k1=distortion, fit_k2=distortion)
            cam, R, fitted_on = fit.camera, fit.R, dict(matches)
            pairs, _ = self._match(uv, n_obs, obs_tree, cam, R, max(radius, 3.0 * fit.rms_px))
            matches = {**{int(o): int(c) for o, c in zip(obs4, rows4)}, **pairs}
        idx = np.array(sorted(matches))
        if matches != fitted_on:  # the last matching changed the stars: fit once more
            fit = fit_camera(uv[idx], self.catalog.xyz[[matches[i] for i in idx]], cam, R)
            cam, R = fit.camera, fit.R
        steps.append(Step("fit", f"camera fitted to {len(idx)} stars: FOV {cam.fov_deg:.3f} deg, "
                                 f"k1 {cam.k1:+.4f}, k2 {cam.k2:+.4f}, residual {fit.rms_px:.2f} px per axis",
                          observed=[int(i) for i in idx], catalog=[int(matches[i]) for i in idx][:CAP],
                          numbers={"fov_deg": cam.fov_deg, "k1": cam.k1, "k2": cam.k2, "rms_px": fit.rms_px,
                                   "stars": len(idx)}))
        # the shared verification: the fitted camera, the catalog to the frame's depth, measured noise
        frame = self._frame_rows(cam, R, n_obs)
        mag_limit = float(self.catalog.mag[frame].max()) if len(frame) else float(self.catalog.mag.max())
        cat = self.catalog_to(mag_limit)
        sigma_px = max(fit.rms_px if np.isfinite(fit.rms_px) else 0.5, 0.25)
        sigma_rad = sigma_px * cam.pixel_scale_rad
        vectors = cam.unproject(uv[:n_obs])
        hyp = {int(o): int(cat.index_of(self.catalog.hip[c])) for o, c in zip(obs4, rows4)
               if self.catalog.mag[c] <= cat.mag.max()}
        ver = verify(vectors, hyp, cat, cam, sigma_rad, n_hypotheses=checks)
        # the steps and the result refer to rows of the full catalog, the verification to the depth's
        to_full = {int(c): int(self.catalog.index_of(cat.hip[c])) for c in set(hyp.values()) | set(ver.matches.values())}
        shown = copy.copy(ver)
        shown.matches = {o: to_full[c] for o, c in ver.matches.items()}
        steps.append(verification_step(shown, {o: to_full[c] for o, c in hyp.items()},
                                       numbers={"fov_deg": cam.fov_deg, "mag_limit": mag_limit}))
        ident = Identification(method=self.name, status=INCONCLUSIVE, matches={}, steps=steps,
                               reason=ver.reason, verification=ver.to_dict(),
                               stats={"checks": checks, "fov_deg": cam.fov_deg, "k1": cam.k1, "k2": cam.k2,
                                      "mag_limit": mag_limit, "fit_rms_px": fit.rms_px},
                               database_key=database.key_string(self.database_key))
        if ver.passed:
            ident.accept(ver)
            ident.matches = self._resolved(dict(shown.matches), cam)
            ident.stats["unresolved_pairs_left_out"] = len(shown.matches) - len(ident.matches)
        ident.stats["time_ms"] = (time.perf_counter() - t0) * 1e3
        return BlindResult(ident, camera=cam if ver.passed else None, fit=fit, mag_limit=mag_limit,
                           sigma_rad=sigma_rad, info={"checks": checks})

    def _resolved(self, matches: dict[int, int], cam: Camera) -> dict[int, int]:
        """Matches without the stars that have a companion in the FULL catalog close enough to blend
        (within BLEND_RADIUS_PX pixels) and bright enough to move the centroid (at most BLEND_DELTA_MAG
        fainter): the verification only sees its depth catalog, whose faint companions are left out."""
        if not matches:
            return matches
        obs = np.array(sorted(matches))
        rows = np.array([matches[o] for o in obs])
        radius = BLEND_RADIUS_PX * cam.pixel_scale_rad
        near = self.catalog.tree.query_ball_point(self.catalog.xyz[rows], float(chord(radius)))
        keep = {}
        for o, c, nb in zip(obs.tolist(), rows.tolist(), near):
            rivals = [k for k in nb if k != c and self.catalog.mag[k] <= self.catalog.mag[c] + BLEND_DELTA_MAG]
            if not rivals:
                keep[o] = c
        return keep if len(keep) >= 2 else matches

    def _fail(self, status, reason, steps, stats=None) -> BlindResult:
        ident = Identification(method=self.name, status=status, matches={}, steps=steps, reason=reason,
                               stats=stats or {}, database_key=database.key_string(self.database_key))
        return BlindResult(ident)
