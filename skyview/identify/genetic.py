"""Genetic-algorithm star pattern recognition (Paladugu, Williams & Schoen), taken to the real sky.

The paper. A chromosome is a candidate bore-sight position on the star map. Its fitness is the cost
of eq. 3: the distances R_k from the candidate position to the m stars nearest to it (m = 15-20;
only the m closest when the FOV holds more, zeros added at the BEGINNING of the vector when it holds
fewer), sorted nearest first into D_i, against the same vector D_a of the image (distances from the
image centre): C_i = sum_k |D_a[k] - D_i[k]|. A first GA (300 random chromosomes, 150 kept as the
steady-state population, 80 survive each generation, the rest are offspring of rank-weighted pairs,
6 % of the genes mutate) runs until its best cost is <= delta_1 = 3.0; a second, "spiral" GA (100 /
50 / 30) searches a square of +-Delta around the best chromosome until its best cost is <= delta_2
(the paper's example: delta_2 = 1.0 with Delta = 2.40075 = 1.1 x the first GA's best cost 2.1825,
so Delta = box_factor x previous best cost, box_factor = 1.1); the statistics of the paper use
0.001882, taken here as a third spiral level: deltas = (3.0, 1.0, 0.001882). A last GA (120 / 60 /
30) finds the roll phi: the angles theta_k of the same stars (counter-clockwise from the x axis)
must differ from the image's by one constant, eq. 4: C_i = sum_k |theta_a[k] + phi - theta_i[k]|
(differences wrapped to (-pi, pi]). A stage that does not converge within max_generations = 600
generations restarts the whole search with new chromosomes. The GA is Haupt & Haupt's continuous GA
(the paper's reference 3): rank-weighted pairing, one crossover gene blended with a random beta and
the genes after it swapped, mutation replacing random genes of all but the best chromosome with
random values. `skyview.experiments.genetic_map` reproduces the paper on its own synthetic map.

The real sky (the paper's future work). Stage 1 chromosomes are (RA, Dec) boresights over the whole
sphere (Dec sampled uniformly in sin Dec, so the population is uniform on the sky). The image side
of eq. 3 is the observed stars within the circle inscribed in the sensor (radius r_c, roll-free, as
the paper's distance vector must be), at most m of them, nearest first: their angles from the
camera axis +z. The catalog side is, for every chromosome, the same number n of catalog stars
nearest to it within r_c grown by 3 sigma sqrt(2) (a star on the edge may fall on either side with
noise), found for the whole population at once with one cKDTree query (the catalog's tree on unit
vectors: chord distances, converted to angles on the sphere); the paper's zero padding applies when
the catalog has fewer. Two adaptations keep the two sides comparable on real images. (1) Stars
closer than merge_px = 3 pixels are one blob for the centroider: the GA's catalog makes each such
group one star (flux-weighted position, summed flux; the verification uses the full catalog).
(2) The pipeline passes only the brightest centroids (40 by default) and a real sensor sees stars
below the catalog's limit, so an image with complete_below = 40 stars or more is taken as cut at
some brightness: the GA then uses the stars brighter than the widest gap in instrument magnitude
among the fainter half, and the catalog side the stars brighter than the same cut (a cut in a gap
survives magnitude errors; magnitudes are relative to the median star by brightness rank on each
side, which saturation of the brightest stars does not move). The spiral stages search a square of +-Delta in the gnomonic plane
around the previous best position (genes xi, eta: a true square on the sky, even at the poles). The
roll GA compares position angles in the tangent plane: theta_a = atan2(y, x) of the camera-frame
direction, theta_i = atan2(north, east) of the catalog star at the found boresight, and
theta_i = theta_a + phi gives the attitude (x = cos phi east + sin phi north, y = boresight x x).
Stars are paired in distance order as in eq. 4; two stars whose distances agree within the noise
may be in either order, so a star's term is the smaller of the two pairings.

Thresholds on the sky. The paper's deltas are for m = 20 stars in a 25-unit FOV (delta_fov); on the
sky they scale per star and with the FOV (delta x n / 20 x fov / 25: 3.0 -> 0.96 deg for 20 stars
in an 8 deg FOV) and never go below the noise floor, the sum of n half-normal distance errors:
sigma (n sqrt(2/pi) + 4 sqrt(n (1 - 2/pi))). The roll GA converges when its cost is below
sum_k min(pi, (3 sqrt(2) sigma + eps_b) / R_k) with eps_b = 3 C / n from the final position cost C
(the angle error of a star at R_k from a position error eps_b and noise).

Magnitude pre-filter (proposed by the paper as "another option", not part of the method it tested,
so off in the paper variant and on in `IMPROVED_PARAMS`): a chromosome whose nearest catalog star is
not within mag_tolerance = 1 magnitude of the observed star nearest the boresight gets no cost
(infinite). Instrument brightness is used as relative magnitude only: both sides are taken relative
to the median star (by brightness rank) of the stars they use. mag_tolerance=None switches it off.

Verification (the identifier contract). The GA's answer (boresight + roll) is refined with the
paired stars (SVD, outliers dropped), every observed star is matched to the catalog within the
match radius, and the two brightest matched stars form the hypothesis sent to the shared
verification, which tests every other observed star. The number of hypotheses of the verification
statistic is the number of oriented catalog pairs whose separation agrees with that pair's within
2 r (r the match radius): whatever way the GA chose its answer, it is one of those, so the union
bound over them covers the selection. It accumulates over restarts. A restart also follows a
rejected answer; after max_restarts the frame is inconclusive: a failure is better than a mismatch.
The database of the method is those catalog pair separations, sorted (cached on disk).

Speed. A generation evaluates only its new chromosomes (offspring and mutated ones), all at once:
one cKDTree query for the population, numpy for the rest. workers=2 runs two restarts at a time in
forked processes; attempts are verified in restart order with per-restart seeds, so the answer is
the same as with workers=1.

Step record. One step per generation (kind "generation"): numbers best_cost, threshold, stage,
generation, evaluations, attempt, box_half_width_deg; layers (skyview.identify.layers): the search box
as a SearchRegion (kind "sky" | "square" | "roll", center, half_width_rad, corners ((4, 3) ICRS, square
only), radius_rad (roll only: the circle of the image-up directions, = half_width_rad)), drawn by every
sink through skyview.present.drawables; the population as a Population: (P, 3) ICRS unit vectors (float32, best
first) with their costs — for the roll GA the direction of image-up at half the circle radius from the
boresight, one per roll chromosome, with roll_rad the rolls (skyview's convention). To keep
a failing 600-generation stage small, the population is attached to generations 0-20, every 10th,
those that improve the best cost or converge, and the last of each stage (the generations in
between show none). Steps "converged", "restart", "answer" and "verify" mark the stages.

Length (~1,050 lines, a third of them this description): the paper's encoding and fitness on the sky
(eqs. 3 and 4, the sky field with its brightness cut and outliers, the merged catalog) and its staged
search are one method; the GA engine itself is `skyview.identify.genetic_engine`, the common path
(verification, acceptance, timing) the template of `skyview.identify.base`.

Long (~1,000 lines, a docstring of 90) on purpose: by the identification template's contract
(`skyview.identify.base`) everything the method is lives in its one module: the paper's description, its
typed parameters, its search as a generator of hypotheses with its steps, and its improved variant; the
shared verification is not here.
"""

from __future__ import annotations

import math
import multiprocessing
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from skyview.core.attitude import east_north, radec_roll_from_R, svd_attitude
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, chord, radec_to_vec, vec_to_radec
from skyview.core.errors import BadInput
from skyview.identify import database
from skyview.identify.base import Hypothesis, Identifier, Search, Step
from skyview.identify.genetic_engine import GAResult, GeneSpace, Sizes, run_ga
from skyview.identify.layers import Attitudes, Hypotheses, Population, SearchRegion
from skyview.identify.params import MethodParams, one_of
from skyview.identify.verify import RADIUS_SIGMAS, angular_distance, match_one_to_one, match_radius

# ------------------------------------------------------------------ the paper's parameters
PAPER_M = 20  # stars in the distance vector (the paper: m = 15 to 20; its example uses 20)
PAPER_FIRST = (300, 150, 80)  # first GA: initial, steady-state population, survivors
PAPER_SPIRAL = (100, 50, 30)  # second ("spiral") GA
PAPER_ROLL = (120, 60, 30)  # roll-angle GA
PAPER_MUTATION_RATE = 0.06
PAPER_MAX_GENERATIONS = 600
PAPER_DELTAS = (3.0, 1.0, 0.001882)  # convergence costs, map units
PAPER_FOV = 25.0  # the map FOV the deltas are given for (units)
PAPER_BOX_FACTOR = 1.1  # Delta = 1.1 x previous best cost (2.40075 = 1.1 x 2.1825 in the paper)
PAPER_MAG_TOLERANCE = 1.0  # the pre-filter's +-1 magnitude

# Options beyond the paper (variant "improved"): the first GA starts from 60,000 chromosomes placed at
# the observed nearest-star distance from random catalog stars ("rings") instead of 300 uniform ones;
# a stage whose best cost has not improved for 60 generations restarts at once instead of waiting
# for generation 600; with 10 stars or more in the distance vector, eq. 3 forgives one false or
# missing star (outliers=1); the magnitude pre-filter the paper only proposes (mag_tolerance=1).
SEEDINGS = ("uniform", "rings")
# step record: the population is kept for generations 0-20, every 10th, those that improve the best
# cost or converge, and the last of each stage (a failing 600-generation stage keeps ~100, not 600)
RECORD_FIRST_GENERATIONS = 20
RECORD_EVERY = 10
DATABASE_VERSION = 1
HALF_NORMAL_MEAN = math.sqrt(2.0 / math.pi)
HALF_NORMAL_SD = math.sqrt(1.0 - 2.0 / math.pi)


# ================================================================== the costs (eq. 3 and eq. 4)

def distance_vector(R: np.ndarray, m: int) -> np.ndarray:
    """The paper's distance vector(s): the m smallest distances, sorted, zeros added at the beginning.

    R: (..., k) distances with inf (or nan) for "no star". Returns (..., m).
    """
    R = np.asarray(R, dtype=np.float64)
    R = np.where(np.isfinite(R), R, np.inf)
    k = R.shape[-1]
    if k > m:
        R = np.sort(R, axis=-1)[..., :m]
    elif k < m:
        R = np.concatenate([R, np.full(R.shape[:-1] + (m - k,), np.inf)], axis=-1)
    return np.sort(np.where(np.isinf(R), 0.0, R), axis=-1)


def distance_cost(D_a: np.ndarray, D_i: np.ndarray) -> np.ndarray:
    """Eq. 3: sum_k |D_a[k] - D_i[k]| for each candidate row of D_i."""
    return np.sum(np.abs(np.asarray(D_i) - np.asarray(D_a)), axis=-1)


def wrap_angle(x: np.ndarray) -> np.ndarray:
    """Angles wrapped into (-pi, pi]."""
    return np.pi - (np.pi - np.asarray(x)) % (2.0 * np.pi)


def angle_partners(D_a: np.ndarray, D_i: np.ndarray, tol: float = 0.0) -> np.ndarray:
    """Which candidate stars each image star may pair with in eq. 4, (m, J) indices (-1 = none).

    D_a, D_i: distance vectors (zero-padded at the beginning). Star k of the image pairs with star k
    of the candidate (the paper's order); when tol > 0 also with every candidate star whose distance
    agrees within tol (two stars at nearly the same distance may swap places with noise). Padded
    (zero) entries have no partner.
    """
    D_a, D_i = np.asarray(D_a, dtype=np.float64), np.asarray(D_i, dtype=np.float64)
    m = len(D_a)
    real_a, real_i = D_a > 0, D_i > 0
    cols = []
    for k in range(m):
        if not real_a[k]:
            cols.append([])
            continue
        js = {k} if real_i[k] else set()
        if tol > 0:
            js |= set(np.flatnonzero(real_i & (np.abs(D_i - D_a[k]) <= tol)).tolist())
        cols.append(sorted(js))
    J = max(1, max(len(c) for c in cols))
    out = -np.ones((m, J), dtype=np.int64)
    for k, js in enumerate(cols):
        out[k, :len(js)] = js
    return out


def angle_cost(theta_a: np.ndarray, theta_i: np.ndarray, phi: np.ndarray, partners: np.ndarray | None = None
               ) -> np.ndarray:
    """Eq. 4 for each roll phi: sum_k |theta_a[k] + phi - theta_i[k]| (differences wrapped).

    theta_a, theta_i: (m,) angles in distance order. With partners (angle_partners) a star's term is
    its best pairing; a star with no partner (padding) adds nothing.
    """
    theta_a = np.asarray(theta_a, dtype=np.float64)
    theta_i = np.asarray(theta_i, dtype=np.float64)
    phi = np.atleast_1d(np.asarray(phi, dtype=np.float64))
    if partners is None:
        partners = np.arange(len(theta_a))[:, None]
    has = partners >= 0
    ti = theta_i[np.clip(partners, 0, None)]  # (m, J)
    diff = np.abs(wrap_angle(theta_a[None, :, None] + phi[:, None, None] - ti[None]))  # (P, m, J)
    diff = np.where(has[None], diff, np.inf)
    term = diff.min(axis=2)
    used = has.any(axis=1)
    term = np.where(used[None], term, 0.0)
    return term.sum(axis=1)


def noise_floor(n: int, sigma: float) -> float:
    """Mean + 4 sd of the eq. 3 cost at the truth: n half-normal distance errors of sigma."""
    return float(sigma * (n * HALF_NORMAL_MEAN + 4.0 * math.sqrt(n) * HALF_NORMAL_SD))


def roll_threshold(R_a: np.ndarray, sigma: float, position_cost: float) -> float:
    """Convergence cost of the roll GA: sum_k min(pi, (3 sqrt(2) sigma + eps_b) / R_k), eps_b = 3 C / n."""
    R_a = np.asarray(R_a, dtype=np.float64)
    R_a = R_a[R_a > 0]
    if len(R_a) == 0:
        return 0.0
    eps_b = 3.0 * position_cost / len(R_a)
    return float(np.sum(np.minimum(np.pi, (RADIUS_SIGMAS * sigma + eps_b) / R_a)))


# ================================================================== geometry on the sky

def tangent_basis(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(east, north) at unit vector b (skyview's convention)."""
    return east_north(b)


def box_vectors(center: np.ndarray, xi: np.ndarray, eta: np.ndarray,
                basis: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Unit vectors at gnomonic offsets (xi east, eta north) around `center`."""
    e, n = tangent_basis(center) if basis is None else basis
    v = center[None, :] + np.asarray(xi)[:, None] * e[None, :] + np.asarray(eta)[:, None] * n[None, :]
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def attitude_from_phi(b: np.ndarray, phi: float) -> np.ndarray:
    """R (v_cam = R v_icrs) with boresight b and theta_catalog = theta_image + phi."""
    e, n = tangent_basis(b)
    x = np.cos(phi) * e + np.sin(phi) * n
    y = np.cross(b, x)
    return np.stack([x, y, b])


def position_angles(vectors: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Position angles atan2(north, east) of ICRS vectors around b."""
    e, n = tangent_basis(b)
    return np.arctan2(vectors @ n, vectors @ e)


def ring_seeds(catalog_xyz: np.ndarray, radius: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """n directions, each at `radius` from a random catalog star in a random direction."""
    c = catalog_xyz[rng.integers(0, len(catalog_xyz), size=n)]
    e = np.stack([-c[:, 1], c[:, 0], np.zeros(n)], axis=1)
    norm = np.linalg.norm(e, axis=1, keepdims=True)
    e = np.where(norm > 1e-9, e / np.maximum(norm, 1e-300), np.array([1.0, 0.0, 0.0]))
    nn = np.cross(c, e)
    psi = rng.uniform(0.0, 2.0 * np.pi, size=n)
    v = np.cos(radius) * c + np.sin(radius) * (np.cos(psi)[:, None] * e + np.sin(psi)[:, None] * nn)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _corners(center: np.ndarray, half: float) -> np.ndarray:
    s = np.array([-1.0, 1.0, 1.0, -1.0]) * half
    t = np.array([-1.0, -1.0, 1.0, 1.0]) * half
    return box_vectors(center, s, t)


def inscribed_radius(camera: Camera) -> float:
    """Angle from the boresight to the nearest sensor edge (the circle inside the image)."""
    mid = np.array([[-0.5, camera.cy], [camera.width - 0.5, camera.cy], [camera.cx, -0.5],
                    [camera.cx, camera.height - 0.5]])
    return float(np.min(np.arccos(np.clip(camera.unproject(mid)[:, 2], -1.0, 1.0))))


# ================================================================== the sky problem of one frame

def brightness_cut(stars: np.ndarray, m_inst: np.ndarray, min_stars: int) -> tuple[np.ndarray, float]:
    """Of observed `stars` (a brightness-limited set: the pipeline passes the brightest centroids), the
    ones brighter than the widest gap in instrument magnitude among the fainter half (at least
    min_stars kept), and the cut (the middle of that gap, instrument magnitude)."""
    o = stars[np.argsort(m_inst[stars], kind="stable")]
    mags = m_inst[o]
    lo = max(min_stars, (len(o) + 1) // 2)
    gaps = np.diff(mags)[lo - 1:]  # gap after the k-th brightest, k = lo .. len - 1
    k = lo + int(np.argmax(gaps))
    return np.sort(o[:k]), float(0.5 * (mags[k - 1] + mags[k]))


def reference_magnitude(mags: np.ndarray, k: int) -> np.ndarray:
    """Per row, the k-th brightest finite magnitude (the faintest finite one when a row has fewer): the
    zero of the relative magnitudes. With k half the stars used it is the median star: saturation
    compresses only the brightest few (in the simulator from Hp ~3.3 on), and a star entering or
    leaving the circle moves it by one rank only."""
    mags = np.atleast_2d(np.asarray(mags, dtype=np.float64))
    if mags.shape[1] == 0:
        return np.full(len(mags), np.inf)
    k = int(min(max(k, 1), mags.shape[1]))
    part = np.sort(mags, axis=1)[:, :k] if mags.shape[1] <= 64 else np.sort(
        np.partition(mags, k - 1, axis=1)[:, :k], axis=1)
    fin = np.isfinite(part)
    last = np.maximum(fin.sum(axis=1) - 1, 0)
    out = part[np.arange(len(part)), last]
    return np.where(fin.any(axis=1), out, np.inf)


class SkyField:
    """What eq. 3 and 4 need from one frame, and the population cost on the sphere.

    Image side: the N observed stars within r_circle of the camera axis. When the observation may
    have been cut at some brightness (complete=False: the pipeline passes the brightest centroids
    only; a real sensor also sees stars below the catalog's limit), only the stars brighter than the
    widest magnitude gap of the fainter half are used (brightness_cut), and the catalog side applies
    the same cut: a cut in a gap survives magnitude errors. Their m nearest (n = min(m, N)) give the
    distances D_a, nearest first, and the position angles theta_a. Catalog side, for every
    chromosome: the n nearest catalog stars within r_catalog of it (after the cut), zero-padded at
    the beginning when fewer. Magnitudes are relative on both sides, to the median star by rank
    (reference_magnitude) of the stars used (complete image: the n; cut image: those above the cut).
    The pre-filter compares the relative magnitude of the nearest star. k_max: the most catalog stars
    any circle of r_catalog holds (rows that reach it are completed one by one).
    """

    def __init__(self, catalog: GuideCatalog, V: np.ndarray, brightness: np.ndarray, r_circle: float,
                 r_catalog: float, m: int, mag_tolerance: float | None, k_max: int, complete: bool = True,
                 min_stars: int = 3, outliers: int = 0, outlier_min_stars: int = 10):
        self.catalog = catalog
        self.r_circle, self.r_catalog = float(r_circle), float(r_catalog)
        ang = np.arccos(np.clip(V[:, 2], -1.0, 1.0)) if len(V) else np.zeros(0)
        inside = np.flatnonzero(ang <= r_circle)
        b = np.asarray(brightness, dtype=np.float64)
        m_inst = -2.5 * np.log10(np.where(np.isfinite(b) & (b > 0), b, np.nan)) if len(b) else b
        self.cut_rel_mag = None
        cut = None
        if not complete and len(inside) > min_stars and np.all(np.isfinite(m_inst[inside])):
            inside, cut = brightness_cut(inside, m_inst, min_stars)
            self.ref_rank = (len(inside) + 1) // 2
            self.cut_rel_mag = float(cut - reference_magnitude(m_inst[inside][None, :], self.ref_rank)[0])
        self.n_circle = len(inside)
        order = inside[np.argsort(ang[inside], kind="stable")][:m]
        if cut is None:  # complete: the median star of the n used
            self.ref_rank = (len(order) + 1) // 2
        self.obs_index = order  # observed star of each entry, nearest first
        self.n = len(order)
        self.R_a = ang[order]
        self.D_a = self.R_a.copy()  # the image's own n entries (no padding needed)
        self.theta_a = np.arctan2(V[order, 1], V[order, 0]) if self.n else np.zeros(0)
        self.chord_catalog = float(chord(r_catalog))
        self.complete = self.cut_rel_mag is None
        self.outliers = int(outliers) if self.n >= max(3, int(outlier_min_stars)) else 0
        self.n_query = self.n + self.outliers  # catalog stars per chromosome (one more to drop one)
        if self.outliers:  # D_a with each image star left out in turn; index of n + 1 less one
            self.D_a_drop = np.stack([np.delete(self.D_a, j) for j in range(self.n)])
            self.drop_one = np.stack([np.delete(np.arange(self.n + 1), j) for j in range(self.n + 1)])
        if self.complete:  # the paper's rule: the n nearest
            self.k_max = self.k_first = max(self.n_query, 1)
        else:  # every star of the circle is needed to apply the cut
            expected = len(catalog) / (4.0 * np.pi) * 2.0 * np.pi * (1.0 - np.cos(r_catalog))
            self.k_max = max(int(k_max), self.n_circle + 1)
            self.k_first = min(self.k_max, max(self.n_circle + 8, int(np.ceil(1.5 * expected)) + 10))
        self.mag_tolerance = mag_tolerance
        self.rel_mag_a = None
        used = order if self.complete else inside
        if mag_tolerance is not None and self.n and np.all(np.isfinite(m_inst[used])):
            self.rel_mag_a = float(m_inst[order[0]] - reference_magnitude(m_inst[used][None, :], self.ref_rank)[0])
        self.cat_mag = catalog.mag.astype(np.float64)

    def _query(self, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tree = self.catalog.tree
        d, idx = tree.query(B, k=self.k_first, distance_upper_bound=self.chord_catalog)
        d, idx = d.reshape(len(B), -1), idx.reshape(len(B), -1)
        if self.complete:
            return d, idx
        full = np.flatnonzero(np.isfinite(d[:, -1]))
        if len(full) and self.k_first < self.k_max:
            d2, i2 = tree.query(B[full], k=self.k_max, distance_upper_bound=self.chord_catalog)
            d2, i2 = d2.reshape(len(full), -1), i2.reshape(len(full), -1)
            pad = self.k_max - self.k_first
            d = np.concatenate([d, np.full((len(B), pad), np.inf)], axis=1)
            idx = np.concatenate([idx, np.full((len(B), pad), len(self.catalog))], axis=1)
            d[full], idx[full] = d2, i2
            full = full[np.isfinite(d2[:, -1])]
        for r in full:  # more stars than k_max: take them all
            near = np.asarray(tree.query_ball_point(B[r], self.chord_catalog), dtype=np.int64)
            dd = np.linalg.norm(self.catalog.xyz[near] - B[r], axis=1)
            o = np.argsort(dd)
            if len(o) > d.shape[1]:
                pad = len(o) - d.shape[1]
                d = np.concatenate([d, np.full((len(B), pad), np.inf)], axis=1)
                idx = np.concatenate([idx, np.full((len(B), pad), len(self.catalog))], axis=1)
            d[r, :len(o)], idx[r, :len(o)] = dd[o], near[o]
        return d, idx

    def neighbours(self, B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For chromosomes B (P, 3): (P, n + outliers) angles (inf: none) and catalog rows (-1) of the
        stars that make D_i, nearest first, and the reference magnitude of the relative magnitudes.

        Complete image: the n nearest catalog stars (the paper's rule). Cut image: the n nearest of
        the catalog stars within r_catalog brighter than the image's cut (relative magnitudes)."""
        B = np.atleast_2d(B)
        d, idx = self._query(B)
        found = np.isfinite(d)
        mags = np.where(found, self.cat_mag[np.where(found, idx, 0)], np.inf)
        ref = reference_magnitude(mags if not self.complete else mags[:, :self.n], self.ref_rank)
        if not self.complete:
            keep = found & (mags <= ref[:, None] + self.cut_rel_mag)
            d = np.where(keep, d, np.inf)
            o = np.argsort(d, axis=1, kind="stable")[:, :self.n_query]
            d, idx = np.take_along_axis(d, o, axis=1), np.take_along_axis(idx, o, axis=1)
            found = np.isfinite(d)
        ang = np.where(found, 2.0 * np.arcsin(np.clip(np.where(found, d, 0.0) / 2.0, 0.0, 1.0)), np.inf)
        return ang, np.where(found, idx, -1), ref

    def cost(self, B: np.ndarray) -> np.ndarray:
        """Eq. 3 for chromosomes B (P, 3): sum |D_a - D_i| over the n entries (+ the pre-filter).

        With outliers=1 the cost is the smallest of eq. 3, eq. 3 with one image star left out (against
        the n - 1 nearest catalog stars: a false star) and eq. 3 with one of the n + 1 nearest catalog
        stars left out (a star the image lacks)."""
        ang, idx, ref = self.neighbours(B)
        n = self.n
        c = distance_cost(self.D_a, distance_vector(ang[:, :n], n))
        if self.outliers:
            D1 = distance_vector(ang[:, :n - 1], n - 1)
            c = np.minimum(c, np.abs(self.D_a_drop[None, :, :] - D1[:, None, :]).sum(axis=2).min(axis=1))
            D2 = distance_vector(ang[:, :n + 1], n + 1)
            c = np.minimum(c, np.abs(D2[:, self.drop_one] - self.D_a[None, None, :]).sum(axis=2).min(axis=1))
        if self.rel_mag_a is not None:
            near = (idx[:, 0] >= 0) & np.isfinite(ref)
            rel = np.where(near, self.cat_mag[np.clip(idx[:, 0], 0, None)] - np.where(near, ref, 0.0), np.inf)
            c = np.where(np.abs(rel - self.rel_mag_a) <= self.mag_tolerance, c, np.inf)
        return c

    def alignment(self, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At position b, the entries of the image that eq. 3 compares (indices into D_a), the catalog
        distance vector they are compared with and its catalog rows (-1 for padding): the full
        vectors, or with one star left out on either side when that costs less (outliers=1)."""
        ang, idx, _ = self.neighbours(np.asarray(b)[None, :])
        a, i = ang[0], idx[0]
        n = self.n

        def catalog_side(k):
            ii = i[:k]
            real = ii[ii >= 0]
            return distance_vector(a[None, :k], k)[0], np.concatenate([-np.ones(k - len(real), np.int64), real])

        keep = np.arange(n)
        D_i, rows = catalog_side(n)
        best = float(np.sum(np.abs(self.D_a - D_i)))
        if self.outliers:
            D1, rows1 = catalog_side(n - 1)
            for j in range(n):
                cj = float(np.sum(np.abs(self.D_a_drop[j] - D1)))
                if cj < best:
                    best, keep, D_i, rows = cj, np.delete(np.arange(n), j), D1, rows1
            D2, rows2 = catalog_side(n + 1)
            for j in range(n + 1):
                kj = np.delete(np.arange(n + 1), j)
                cj = float(np.sum(np.abs(self.D_a - D2[kj])))
                if cj < best:
                    best, keep, D_i, rows = cj, np.arange(n), D2[kj], rows2[kj]
        return keep, D_i, rows


def merged_catalog(catalog: GuideCatalog, sep_rad: float) -> tuple[GuideCatalog, np.ndarray]:
    """The catalog as a centroider sees it: every group of stars closer than sep_rad becomes one star
    at the flux-weighted mean position with the summed flux (row of its brightest star). Returns the
    catalog and, for each of its rows, the row of the original catalog."""
    n = len(catalog)
    if sep_rad <= 0 or n < 2:
        return catalog, np.arange(n)
    pairs = catalog.tree.query_pairs(float(chord(sep_rad)), output_type="ndarray")
    if len(pairs) == 0:
        return catalog, np.arange(n)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    flux = 10.0 ** (-0.4 * catalog.mag.astype(np.float64))
    order = np.lexsort((catalog.mag, label))  # by group, brightest first
    first = np.ones(n, dtype=bool)
    first[1:] = label[order][1:] != label[order][:-1]
    rows = np.sort(order[first])  # the brightest star of each group
    total = np.bincount(label, weights=flux)
    xyz = np.zeros((label.max() + 1, 3))
    np.add.at(xyz, label, flux[:, None] * catalog.xyz)
    xyz = xyz[label[rows]]
    xyz /= np.linalg.norm(xyz, axis=1, keepdims=True)
    mag = (-2.5 * np.log10(total[label[rows]])).astype(catalog.mag.dtype)
    out = GuideCatalog(hip=catalog.hip[rows], xyz=xyz, mag=mag, pm=catalog.pm[rows], bv=catalog.bv[rows],
                       flags=catalog.flags[rows], epoch=catalog.epoch,
                       history=catalog.history + (f"merged<{np.degrees(sep_rad) * 3600:.1f}arcsec",))
    return out, rows


# ================================================================== the database: pair separations

def build_pair_separations(catalog: GuideCatalog, max_sep_rad: float) -> dict[str, np.ndarray]:
    pairs = catalog.pairs_within(max_sep_rad)
    sep = angular_distance(catalog.xyz[pairs[:, 0]], catalog.xyz[pairs[:, 1]])
    return {"separations": np.sort(sep[sep <= max_sep_rad])}


# ================================================================== the identifier

@dataclass
class _Attempt:
    """One run of the search (stage 1, spiral stages, roll) and its answer."""

    index: int
    steps: list[Step] = field(default_factory=list)
    outcome: str = ""  # "answer" or the stage that did not converge
    reason: str = ""
    b: np.ndarray | None = None
    phi: float | None = None
    R: np.ndarray | None = None
    matches: dict[int, int] = field(default_factory=dict)  # the GA's answer (observed -> catalog row)
    generations: list[int] = field(default_factory=list)
    evaluations: int = 0
    costs: list[float] = field(default_factory=list)
    time_s: float = 0.0


@dataclass(frozen=True)
class GeneticParams(MethodParams):
    """The genetic method's parameters: the paper's GA sizes, rates and convergence costs, and the options
    beyond it (the module docstring explains each)."""

    m: int = PAPER_M
    initial: int = PAPER_FIRST[0]
    population: int = PAPER_FIRST[1]
    survivors: int = PAPER_FIRST[2]
    spiral_initial: int = PAPER_SPIRAL[0]
    spiral_population: int = PAPER_SPIRAL[1]
    spiral_survivors: int = PAPER_SPIRAL[2]
    roll_initial: int = PAPER_ROLL[0]
    roll_population: int = PAPER_ROLL[1]
    roll_survivors: int = PAPER_ROLL[2]
    mutation_rate: float = PAPER_MUTATION_RATE
    max_generations: int = PAPER_MAX_GENERATIONS
    deltas: tuple[float, ...] = PAPER_DELTAS
    delta_fov: float = PAPER_FOV
    box_factor: float = PAPER_BOX_FACTOR
    mag_tolerance: float | None = None
    max_restarts: int = 20
    stall_generations: int | None = None
    seeding: str = "uniform"
    outliers: int = 0
    outlier_min_stars: int = 10
    min_stars: int = 3
    complete_below: int = 40
    merge_px: float = 3.0
    seed: int = 0
    workers: int = 1

    def __post_init__(self):
        if int(self.m) < 2:
            raise BadInput("m (stars in the distance vector) must be at least 2")
        if not (0.0 <= float(self.mutation_rate) <= 1.0):
            raise BadInput("mutation_rate must be in [0, 1]")
        if int(self.max_generations) < 1:
            raise BadInput("max_generations must be at least 1")
        deltas = tuple(float(x) for x in np.atleast_1d(self.deltas))
        if not deltas or any(not (np.isfinite(x) and x > 0) for x in deltas):
            raise BadInput("deltas must be one or more positive convergence costs")
        object.__setattr__(self, "deltas", deltas)
        if not (np.isfinite(self.delta_fov) and self.delta_fov > 0):
            raise BadInput("delta_fov must be positive")
        if not (np.isfinite(self.box_factor) and self.box_factor > 0):
            raise BadInput("box_factor must be positive")
        if self.mag_tolerance is not None and not (np.isfinite(self.mag_tolerance) and self.mag_tolerance > 0):
            raise BadInput("mag_tolerance must be positive or None (no magnitude pre-filter)")
        if int(self.max_restarts) < 0:
            raise BadInput("max_restarts must be >= 0")
        if self.stall_generations is not None and int(self.stall_generations) < 1:
            raise BadInput("stall_generations must be >= 1 or None")
        one_of("seeding", self.seeding, SEEDINGS)
        if int(self.outliers) not in (0, 1):
            raise BadInput("outliers must be 0 or 1")
        if int(self.outlier_min_stars) < 3:
            raise BadInput("outlier_min_stars must be at least 3")
        if not (np.isfinite(self.merge_px) and self.merge_px >= 0):
            raise BadInput("merge_px must be >= 0")
        if int(self.complete_below) < 1:
            raise BadInput("complete_below must be at least 1")
        if int(self.min_stars) < 2:
            raise BadInput("min_stars must be at least 2")
        if int(self.workers) not in (1, 2):
            raise BadInput("workers must be 1 or 2")
        super().__post_init__()
        self.sizes()  # Sizes checks itself

    def sizes(self) -> tuple[Sizes, Sizes, Sizes]:
        """The population sizes of the first, spiral and roll GAs (each checked)."""
        return (Sizes(int(self.initial), int(self.population), int(self.survivors)),
                Sizes(int(self.spiral_initial), int(self.spiral_population), int(self.spiral_survivors)),
                Sizes(int(self.roll_initial), int(self.roll_population), int(self.roll_survivors)))


PAPER = GeneticParams()
IMPROVED = replace(PAPER, seeding="rings", initial=60_000, stall_generations=60, max_restarts=30, outliers=1,
                   mag_tolerance=PAPER_MAG_TOLERANCE)
IMPROVED_PARAMS = IMPROVED.changed()


class GeneticMethod(Identifier):
    """Paladugu, Williams & Schoen's spiral GA on the celestial sphere, ending in the shared verification."""

    name = "genetic"
    paper_scenario = "sun20"
    slow = True  # a generational search: seconds a frame
    title = "the genetic method"
    Params = GeneticParams
    improved_params = IMPROVED_PARAMS

    def __init__(self, catalog: GuideCatalog, camera: Camera, sigma_rad: float, **params):
        p = self.configure(catalog, camera, sigma_rad, params)
        self.first, self.spiral, self.roll = p.sizes()
        self.m = int(p.m)
        self.mutation_rate = float(p.mutation_rate)
        self.max_generations = int(p.max_generations)
        self.delta_fov = float(p.delta_fov)
        self.box_factor = float(p.box_factor)
        self.mag_tolerance = None if p.mag_tolerance is None else float(p.mag_tolerance)
        self.max_restarts = int(p.max_restarts)
        self.stall_generations = None if p.stall_generations is None else int(p.stall_generations)
        self.outliers = int(p.outliers)
        self.outlier_min_stars = int(p.outlier_min_stars)
        self.min_stars = int(p.min_stars)
        self.complete_below = int(p.complete_below)
        self.seed = int(p.seed)
        self.workers = int(p.workers)
        self.radius_sigmas = float(p.radius_sigmas)
        self.r_circle = inscribed_radius(camera)
        self.fov_rad = float(np.radians(camera.fov_deg))
        self.max_sep_rad = 2.0 * camera.half_diagonal_rad
        # the GA's catalog: stars closer than merge_px are one blob for the centroider
        self.merge_px = float(p.merge_px)
        self.ga_catalog, self.ga_rows = merged_catalog(catalog, self.merge_px * camera.pixel_scale_rad)
        # the most catalog stars a circle around a chromosome may hold (a little wider than r_circle)
        gx = self.ga_catalog
        self.k_max = int(gx.tree.query_ball_point(gx.xyz, float(chord(1.1 * self.r_circle + 0.005)),
                                                  return_length=True).max()) + 1 if len(gx) else 1
        self._pool: tuple[ProcessPoolExecutor, object] | None = None
        self._stop: Callable[[], bool] | None = None  # set in worker processes

        params = {"max_sep_rad": self.max_sep_rad, "version": DATABASE_VERSION}
        self.database_key = database.make_key(self.name, params, catalog, camera)
        n_pairs = database.pairs_estimate(len(catalog), self.max_sep_rad)
        what = (f"the genetic method's pair database ({len(catalog):,} stars, pairs up to "
                f"{np.degrees(self.max_sep_rad):.1f} deg, ~{n_pairs / 1e6:.1f} M pairs)")
        arrays, info = database.load_or_build(self.database_key,
                                              lambda: build_pair_separations(catalog, self.max_sep_rad),
                                              what=what, estimate_s=0.5e-6 * n_pairs, estimate_bytes=40 * n_pairs)
        self.separations = arrays["separations"]
        info.update(pairs=len(self.separations), catalog_stars=len(catalog),
                    max_sep_deg=float(np.degrees(self.max_sep_rad)),
                    circle_radius_deg=float(np.degrees(self.r_circle)))
        self.database_info = info

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_pool"] = None
        return state

    def close(self) -> None:
        """Stop the worker processes (workers=2)."""
        if self._pool is not None:
            self._pool[0].shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown
            pass

    # ------------------------------------------------------------------ helpers
    def pair_hypotheses(self, sep_rad: float, radius_rad: float) -> int:
        """Oriented catalog pairs whose separation is within 2 r of sep_rad (the hypotheses a pair stands for)."""
        lo = np.searchsorted(self.separations, sep_rad - 2.0 * radius_rad, side="left")
        hi = np.searchsorted(self.separations, sep_rad + 2.0 * radius_rad, side="right")
        return int(2 * max(hi - lo, 1))

    def thresholds(self, n: int, sigma: float) -> list[float]:
        """The position GA's convergence costs on the sky for n stars: the paper's deltas (for m = 20 stars
        in a 25-unit FOV) per star and per FOV, never below the noise floor."""
        floor = noise_floor(n, sigma)
        return [max(d * (n / PAPER_M) * self.fov_rad / self.delta_fov, floor) for d in self.deltas]

    @property
    def n_patterns(self) -> int:
        return len(self.separations)

    # ------------------------------------------------------------------ identify (the template's parts)
    def too_few(self, search: Search) -> str:
        sky = search.data["sky"] = self._field(search.V, search.obs.brightness, search.sigma)
        search.stats = {"stars_in_circle": sky.n_circle, "stars_in_vector": sky.n}
        if search.n < 3 or sky.n < self.min_stars:
            return (f"the genetic method needs at least {self.min_stars} stars within "
                    f"{np.degrees(self.r_circle):.2f} deg of the centre and 3 in the image; the frame has "
                    f"{sky.n} and {search.n}")
        return ""

    def failure_reason(self, search: Search) -> str:
        reasons = search.reasons
        return (f"no verified answer in {search.data['attempts']} attempt(s): "
                + "; ".join(sorted(set(reasons), key=reasons.index)))

    def hypotheses(self, search: Search):
        """The attempts' answers in restart order, each as the hypothesis of its two brightest matched
        stars (counted as every catalog pair of that separation), until one verifies."""
        V, sigma, steps, reasons, sky = search.V, search.sigma, search.steps, search.reasons, search.data["sky"]
        frame_key = zlib.crc32(np.ascontiguousarray(V).tobytes())
        attempts: list[_Attempt] = []
        runs = self._attempts(V, search.obs.brightness, sigma, frame_key)
        try:
            for att in runs:
                attempts.append(att)
                steps.extend(att.steps)
                if att.outcome != "answer":
                    reasons.append(att.reason)
                    continue
                hyp, n_pair = self._hypothesis(V, att.matches, search.radius)
                if hyp is None:
                    reasons.append("an answer matched fewer than two observed stars")
                    steps.append(Step("restart", f"attempt {att.index + 1}: the answer matched fewer than two stars",
                                      numbers={"attempt": att.index}))
                    continue
                ver = yield Hypothesis(hyp, count=n_pair, numbers={"attempt": att.index, "pair_hypotheses": n_pair},
                                       layers=(Hypotheses.single(hyp),))
                reasons.append(f"verification failed: {ver.reason}")
        finally:  # also when the search ends at an accepted answer (the generator is closed)
            runs.close()
            first_answer = next((a for a in attempts if a.outcome == "answer"), None)
            search.data["attempts"] = len(attempts)
            search.stats.update({
                "brightness_cut_mag": sky.cut_rel_mag,
                "attempts": len(attempts),
                "restarts": max(0, len(attempts) - 1),
                "generations": int(sum(sum(a.generations) for a in attempts)),
                "evaluations": int(sum(a.evaluations for a in attempts)),
                "verifications": search.verifications,
                "n_hypotheses": search.n_hypotheses,
                "thresholds_rad": self.thresholds(sky.n, sigma),
                "first_chain": {"outcome": "answer" if first_answer is not None else "none",
                                "matches": dict(first_answer.matches) if first_answer is not None else {}},
            })

    def _field(self, V: np.ndarray, brightness: np.ndarray, sigma: float) -> SkyField:
        margin = RADIUS_SIGMAS * sigma
        return SkyField(self.ga_catalog, V if len(V) else np.zeros((0, 3)), np.asarray(brightness), self.r_circle,
                        self.r_circle + margin, self.m, self.mag_tolerance, self.k_max,
                        complete=len(V) < self.complete_below, min_stars=self.min_stars, outliers=self.outliers,
                        outlier_min_stars=self.outlier_min_stars)

    def _attempts(self, V, brightness, sigma, frame_key):
        """The attempts in restart order (with workers=2 two are computed at a time in forked processes;
        closing the generator stops the one still running)."""
        total = self.max_restarts + 1
        if self.workers == 1:
            for k in range(total):
                yield self._attempt(V, brightness, sigma, frame_key, k)
            return
        pool, stop_event = self._get_pool()
        stop_event.clear()
        futures = {}
        nxt = 0
        try:
            for k in range(total):
                while nxt < total and nxt < k + self.workers:
                    futures[nxt] = pool.submit(_attempt_in_worker, V, brightness, sigma, frame_key, nxt)
                    nxt += 1
                yield futures.pop(k).result()
        finally:
            if futures:
                stop_event.set()
                for f in futures.values():
                    if not f.cancel():
                        f.exception()  # wait for the abandoned attempt to stop
                stop_event.clear()

    def _get_pool(self):
        if self._pool is None:
            ctx = multiprocessing.get_context("fork")
            event = ctx.Event()
            self._pool = (ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx,
                                              initializer=_set_worker_method, initargs=(self, event)), event)
        return self._pool

    # ------------------------------------------------------------------ one attempt
    def _attempt(self, V: np.ndarray, brightness: np.ndarray, sigma: float, frame_key: int, k: int) -> _Attempt:
        t0 = time.perf_counter()
        rng = np.random.default_rng([self.seed, frame_key, k])
        sky = self._field(V, brightness, sigma)
        att = _Attempt(index=k)
        ths = self.thresholds(sky.n, sigma)
        # stage 1: the whole sky, genes (RA, Dec)
        space = GeneSpace(lo=(0.0, -np.pi / 2), hi=(2 * np.pi, np.pi / 2), periodic=(True, False),
                          sine=(False, True))
        box = {"kind": "sky", "center": None, "half_width_rad": float(np.pi), "corners": None}

        def sky_cost(genes):
            return sky.cost(radec_to_vec(genes[:, 0], genes[:, 1]))

        initial = None
        if self.seeding == "rings":
            seeds = ring_seeds(self.ga_catalog.xyz, float(sky.R_a[0]), self.first.initial, rng)
            initial = np.stack(vec_to_radec(seeds), axis=1)
        res = self._run(att, 1, sky_cost, space, self.first, ths[0], rng, box,
                        lambda g: radec_to_vec(g[:, 0], g[:, 1]), initial=initial)
        if not res.converged:
            return self._fail(att, 1, res, ths[0], t0)
        best = radec_to_vec(res.genes[0], res.genes[1])
        cost = res.cost
        # spiral stages: a square of +-Delta (gnomonic) around the best so far
        for stage, th in enumerate(ths[1:], start=2):
            half = self.box_factor * cost
            center = best

            basis = tangent_basis(center)

            def box_cost(genes, center=center, basis=basis):
                return sky.cost(box_vectors(center, genes[:, 0], genes[:, 1], basis))

            space = GeneSpace(lo=(-half, -half), hi=(half, half))
            box = {"kind": "square", "center": center.copy(), "half_width_rad": float(half),
                   "corners": _corners(center, half)}
            res = self._run(att, stage, box_cost, space, self.spiral, th, rng, box,
                            lambda g, center=center, basis=basis: box_vectors(center, g[:, 0], g[:, 1], basis))
            if not res.converged:
                return self._fail(att, stage, res, th, t0)
            best = box_vectors(center, res.genes[:1], res.genes[1:2])[0]
            cost = res.cost
        att.b = best
        # roll: eq. 4 at the found position, on the stars eq. 3 compared there
        keep, D_i, rows = sky.alignment(best)
        D_a, theta_a, R_a, obs_index = sky.D_a[keep], sky.theta_a[keep], sky.R_a[keep], sky.obs_index[keep]
        theta_i = np.zeros(len(rows))
        real = rows >= 0
        theta_i[real] = position_angles(self.ga_catalog.xyz[rows[real]], best)
        tie = 2.0 * RADIUS_SIGMAS * sigma
        partners = angle_partners(D_a, D_i, tie)
        th_roll = roll_threshold(R_a, sigma, cost)
        ring = 0.5 * self.r_circle

        def roll_vectors(g):
            return _up_directions(best, g[:, 0], ring)

        box = {"kind": "roll", "center": best.copy(), "half_width_rad": float(ring), "corners": None,
               "radius_rad": float(ring)}  # the circle the roll chromosomes' image-up directions sit on
        res = self._run(att, len(ths) + 1, lambda g: angle_cost(theta_a, theta_i, g[:, 0], partners),
                        GeneSpace(lo=(0.0,), hi=(2 * np.pi,), periodic=(True,)), self.roll, th_roll, rng, box,
                        roll_vectors, roll=True)
        if not res.converged:
            return self._fail(att, len(ths) + 1, res, th_roll, t0, "roll")
        att.phi = float(res.genes[0])
        att.R = attitude_from_phi(best, att.phi)
        # the GA's answer: the paired stars, refined, then every observed star within r
        dphi = np.abs(wrap_angle(theta_a[:, None] + att.phi - theta_i[np.clip(partners, 0, None)]))
        dphi = np.where(partners >= 0, dphi, np.inf)
        pick = partners[np.arange(len(keep)), np.argmin(dphi, axis=1)]
        pairs = {int(obs_index[j]): int(self.ga_rows[rows[pick[j]]]) for j in range(len(keep))
                 if pick[j] >= 0 and rows[pick[j]] >= 0}
        att.matches, att.R = self._answer(V, pairs, att.R, sigma)
        att.outcome = "answer"
        ra, dec, roll = radec_roll_from_R(att.R)
        att.steps.append(Step("answer", f"attempt {att.index + 1}: the GA points at RA {np.degrees(ra):.3f}, "
                                        f"Dec {np.degrees(dec):.3f}, roll {np.degrees(roll):.2f} deg with "
                                        f"{len(att.matches)} matched stars",
                              observed=sorted(att.matches), catalog=[c for _, c in sorted(att.matches.items())],
                              numbers={"ra_deg": float(np.degrees(ra)), "dec_deg": float(np.degrees(dec)),
                                       "roll_deg": float(np.degrees(roll)), "matched": len(att.matches),
                                       "attempt": att.index},
                              layers=(Attitudes.of(att.R, name="GA answer"),)))
        att.time_s = time.perf_counter() - t0
        return att

    def _run(self, att: _Attempt, stage: int, cost, space, sizes, threshold, rng, box, to_vectors,
             roll: bool = False, initial: np.ndarray | None = None) -> GAResult:
        name = "roll" if roll else ("first" if stage == 1 else "spiral")
        half_deg = float(np.degrees(box["half_width_rad"]))

        best_so_far = [np.inf]

        region = SearchRegion.from_box(box)  # one record for every step of the stage

        def population_layer(pop, c):
            return Population(to_vectors(pop).astype(np.float32), c.astype(np.float32),
                              _phi_to_roll(box["center"], pop[:, 0]) if roll else None)

        def record(gen, pop, c, evals):
            best = float(c[0])
            layers = (region,)
            if (gen <= RECORD_FIRST_GENERATIONS or gen % RECORD_EVERY == 0 or best < best_so_far[0]
                    or best <= threshold):
                layers += (population_layer(pop, c),)
            best_so_far[0] = min(best_so_far[0], best)
            att.steps.append(Step("generation", f"attempt {att.index + 1}, {name} GA (stage {stage}), generation "
                                                f"{gen}: best cost {_deg(best)}",
                                  numbers={"best_cost": best, "threshold": float(threshold), "stage": stage,
                                           "generation": gen, "evaluations": evals, "attempt": att.index,
                                           "box_half_width_deg": half_deg},
                                  layers=layers))

        res = run_ga(cost, space, sizes, rng, mutation_rate=self.mutation_rate, threshold=threshold,
                     max_generations=self.max_generations, stall_generations=self.stall_generations,
                     initial=initial, stop=self._stop, on_generation=record)
        if att.steps[-1].layer(Population) is None:  # the last generation of a stage always has it
            att.steps[-1].layers += (population_layer(res.population, res.costs),)
        att.generations.append(res.generations)
        att.evaluations += res.evaluations
        att.costs.append(res.cost)
        if res.converged:
            att.steps.append(Step("converged", f"attempt {att.index + 1}: {name} GA (stage {stage}) converged in "
                                               f"{res.generations} generations, cost {_deg(res.cost)} "
                                               f"<= {_deg(threshold)}",
                                  numbers={"best_cost": res.cost, "threshold": float(threshold), "stage": stage,
                                           "generations": res.generations, "attempt": att.index}))
        return res

    def _fail(self, att: _Attempt, stage: int, res: GAResult, threshold: float, t0: float,
              what: str = "position") -> _Attempt:
        why = "stalled" if res.stalled else f"reached {self.max_generations} generations"
        att.outcome = f"stage {stage}"
        att.reason = f"the {what} GA (stage {stage}) did not converge"
        att.steps.append(Step("restart", f"attempt {att.index + 1}: stage {stage} {why} with best cost "
                                         f"{_deg(res.cost)} > {_deg(threshold)}"
                                         f": new chromosomes",
                              numbers={"best_cost": res.cost, "threshold": float(threshold), "stage": stage,
                                       "generations": res.generations, "attempt": att.index}))
        att.time_s = time.perf_counter() - t0
        return att

    def _answer(self, V: np.ndarray, pairs: dict[int, int], R: np.ndarray, sigma: float
                ) -> tuple[dict[int, int], np.ndarray]:
        """Refine the GA attitude with its paired stars (dropping the worst while any misfits), then
        match every observed star within the match radius, one to one."""
        r = match_radius(sigma, self.radius_sigmas)
        cur = dict(pairs)
        while len(cur) >= 2:
            o = np.array(sorted(cur))
            c = np.array([cur[i] for i in o])
            R = svd_attitude(V[o], self.catalog.xyz[c], sigma).R
            res = angular_distance(V[o], self.catalog.xyz[c] @ R.T)
            if res.max() <= r or len(cur) == 2:
                break
            cur.pop(int(o[np.argmax(res)]))
        near = self.catalog.within(R[2], self.camera.half_diagonal_rad + r)
        qi, rj, _, amb = match_one_to_one(V @ R, self.catalog.xyz[near], r)
        matches = {int(q): int(near[j]) for q, j in zip(qi, rj) if q not in set(amb.tolist())}
        return matches, R

    def _hypothesis(self, V: np.ndarray, matches: dict[int, int], r: float) -> tuple[dict[int, int] | None, int]:
        """The two brightest matched stars (observed indices are brightest first) and the number of
        oriented catalog pairs they stand for."""
        if len(matches) < 2:
            return None, 0
        o1, o2 = sorted(matches)[:2]
        sep = float(angular_distance(V[o1], V[o2]))
        return {o1: matches[o1], o2: matches[o2]}, self.pair_hypotheses(sep, r)


# ---------------------------------------------------------------------- helpers

def _deg(c: float) -> str:
    return f"{np.degrees(c):.4g} deg"


def _up_directions(b: np.ndarray, phi: np.ndarray, ring: float) -> np.ndarray:
    """For roll chromosomes phi: the sky direction of image-up at `ring` from the boresight b."""
    e, n = tangent_basis(b)
    phi = np.asarray(phi, dtype=np.float64)
    # x = cos phi e + sin phi n, y = b x x = cos phi n - sin phi e; up = -y
    up = np.sin(phi)[:, None] * e[None, :] - np.cos(phi)[:, None] * n[None, :]
    v = np.cos(ring) * b[None, :] + np.sin(ring) * up
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _phi_to_roll(b: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """skyview roll (image-up from north towards east) of roll chromosomes phi: roll = pi - phi."""
    return wrap_angle(np.pi - np.asarray(phi, dtype=np.float64)).astype(np.float32)


_WORKER_METHOD: GeneticMethod | None = None


def _set_worker_method(method: GeneticMethod, stop_event) -> None:
    global _WORKER_METHOD
    _WORKER_METHOD = method
    method._pool = None
    method._stop = stop_event.is_set


def _attempt_in_worker(V, brightness, sigma, frame_key, k) -> _Attempt:
    return _WORKER_METHOD._attempt(V, brightness, sigma, frame_key, k)
