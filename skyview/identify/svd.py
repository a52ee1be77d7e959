"""The singular value method of Juang, Kim & Junkins (2003), NASA/TM-2003-212142.

Invariants. Let W = [w_1 ... w_N] be N measured unit vectors (camera frame) and V = [v_1 ... v_N]
the same stars in the catalog (ICRS), both in the same order, so that W = C V (eq. 1). Then W and V
have the same three singular values (eq. 11) and the same first three right singular vectors up to
sign, q_wi = +-q_vi (eq. 15), so Q_w(:, 1:3) = Q_v(:, 1:3) L with L = diag(sign(q_wi^T q_vi))
(eqs. 16-17), and the attitude follows without pairing the stars: P_w = C P_v L (eq. 23), so
C = P_w (P_v L)^T (eq. 24). Since W = C V with W in the camera frame and V in ICRS, C maps ICRS to
the camera: it IS skyview's R (v_cam = R v_icrs), no transpose (tests/test_svd.py checks it against
the truth). Exchanging columns (W K, eqs. 18-21) keeps the singular values and the left singular
vectors; the rows of the right singular vectors follow the stars, so both sides are ordered by
brightness, brightest first. sigma_1^2 + sigma_2^2 + sigma_3^2 = trace(W W^T) = N for unit vectors:
two of the three singular values are independent (sigma_2, sigma_3 ~ sqrt(N) x the principal
standard deviations of the pattern in the tangent plane).

Mission catalog (the paper's "Pattern Recognition and Mission Catalog Generation"), built once per
catalog and camera, vectorised, and cached (`skyview.identify.database`):

1. the reference catalog: the guide catalog passed in (Hp <= the scenario's limit; the paper: 7.3 Mv)
   without "too close stars and double stars": of every pair closer than min_separation_rad
   (default 3 pixels, below which the centroider cannot split two PSFs of sigma 1.1 px) the
   fainter star is removed (the paper gives no distance);
2. every reference star is a boresight direction; its neighbours are the reference stars within
   fov_radius_rad of it (the paper: 4 deg for its 8 x 8 deg camera; default: fov_radius_factor x
   half the horizontal FOV, factor 1), itself included, sorted by magnitude;
3. the N = 4 brightest are the set, brightest first. When the N-th and (N+1)-th brightest have the
   same magnitude ("possibly more than 2"; equal when quantised to mag_step = 0.01, the resolution of
   a visual-magnitude catalog), one set for each choice of the tied stars;
4. duplicate sets (Fig. 3: the set of the fainter boresight a equals that of d) are removed, keeping
   the brightest boresight: L sets remain, the L x N index matrix; the distinct stars in it are the
   M guide stars;
5. the L x 3 singular values of the sets, and a k-vector (`skyview.identify.kvector`) on sigma_2.

The ranking rule (the paper: "choose the stars in ascending order ... delete measured stars that are
not separated by at least a relative magnitude increment of 0.2 ... analogous steps must be taken in
creating the catalog"): walking from the brightest, a star within delta_m of the last star kept is
deleted (delta_m_rule="thin"), on the measured stars (delta_m = 0.2) and in every boresight's sorted
list of the catalog (delta_m_catalog = 0.2), so both sides make the same set. At Hp 7.3, 8 deg:
M = 7,246 guide stars, L = 10,379 sets, 494 KiB in Table 1's format, 7 of 18,950 boresights without
4 stars (Table 1: 5,761, 11,157, 484 KB; without the rule on the catalog, delta_m_catalog = 0:
5,699, 10,547, 463 KiB). Deleting both stars of a close pair (delta_m_rule="pairs") on the catalog
leaves 15,826 boresights with fewer than 4 stars; on the measured side only (the former reading) it
breaks the set in most fields: 25 % identified against 94.3 % (vector level, 300 attitudes, seed 1).

The paper's storage (Table 1) is M x 3 doubles + L x 4 two-byte integers + L x 3 doubles:
5,761 x 24 + 11,157 x 8 + 11,157 x 24 bytes = 484 KB (1 KB = 1024 bytes). `database_info` reports
M, L and that size ("paper_bytes") beside the arrays actually kept (int32 rows, the boresights, the
k-vector). At Hp <= 7.3, 8 deg (juang8): 18,950 reference stars, no holes, 426 extra sets from equal
magnitudes, 19,376 sets before and L = 10,547 after duplicate removal, M = 5,699 guide stars,
463 KiB in the paper's format (623 KiB cached), built in ~0.1-0.5 s, loaded in ~1.5 ms.

Recognition (the paper's "pattern recognition process"):

1. the measured stars are ranked by brightness (relative magnitudes -2.5 log10(brightness): a rank
   only); a measured star is the boresight, brightest first;
2. the measured stars within fov_radius_rad of it, brightest first; the ranking-ambiguity rule (above:
   a star within delta_m = 0.2 of the last star kept is deleted); the N brightest left are the set. Fewer than N stars
   in the circle: "too few stars"; fewer than N left after the deletion: "ranking";
3. the singular values of W; the catalog sets whose singular values all lie within z_s s_k of the
   measured ones. The bound: to first order a tangent-plane error dw_i moves sigma_k by
   d sigma_k = sum_i q_ki p_k^T dw_i (from W^T p_k = sigma_k q_k), so with sigma per axis and star its
   standard deviation is s_k = sigma sqrt(sum_i q_ki^2 (1 - (p_k^T w_i)^2)) <= sigma (about sigma for
   k = 2, 3; about 0.035 sigma for k = 1 in an 8 deg field); the catalog side has no error. beta = 3
   (as the angle method) sets the chance of losing the true set: P(|x| > 3) = 0.27 %, shared by the
   3 numbers compared, z_s = 3.32 (`bonferroni_bound`). The k-vector returns the sets with sigma_2 in
   range, then sigma_1 and sigma_3 are checked. None: "missing set" ("ranking" when the delta_m rule
   had taken a star out of the set);
4. the right singular vectors: L by the paper's sign rule ("compare the maximum value of q_wi and
   the maximum value of q_vi and take the sign of the resultant product": the signed components of
   largest magnitude; sign_rule="dot" uses eq. 17's sign(q_wi^T q_vi) instead), then
   |Q_w(:, 1:3) - Q_v(:, 1:3) L| <= z_q s_q element by element, s_q the first-order standard deviation
   of each element from the same noise model (eigenvector perturbation of W^T W, null space
   included), z_q = 3.69 for 3N = 12 elements; a candidate whose C (eq. 24) is a reflection (det < 0:
   inconsistent signs) is dropped. None left although the singular values matched: "ranking" (the
   order of the stars disagrees). Both first-order models match a Monte Carlo (tests/test_svd.py);
   on simulated images 0.07 % of true sets exceed z_q. The paper's sign rule fails when the two
   largest components of a q_i are about equal and of opposite sign (1.0 % of true sets here);
5. C = P_w (P_v L)^T for each surviving set (eq. 24; stats["attitude_eq24"] of the identified set),
   the stars paired in their common brightness order, and the shared verification
   (`skyview.identify.verify`; the number of sets verified is the Bonferroni factor); only a
   verified set is an identification (the paper instead re-identifies the next images and compares
   attitudes). Two verified sets with different attitudes: inconclusive ("ambiguous"). No star
   left to verify with: "too few stars"; refused: "rejected". Next boresight on failure; a set
   already tried (the same stars in the same order from another boresight) is not tried again.

Steps (kinds "boresight", "singular_values", "lookup", "filter", "attitude", "verify", "skip",
"stop") carry the observed stars, the catalog rows and the candidate sets (groups, capped at 200).
stats: "failure_causes" counts the outcome of every attempt, "cause" is the frame's (the furthest
any attempt got: ambiguous > rejected > ranking > missing_set > too_few_stars), "attempts" lists
them, "first_chain" the paper's answer before verification (the first boresight whose set survived
the singular-vector filter, when unique). Without the truth "missing set" cannot be told from a
ranking error; `diagnose` in tests/oracles/diagnose_svd.py does it with the truth of a simulated frame (truth never
enters the method), in the paper's words:
ranking error, missing boresight set (lack of boresight directions, Fig. 5: the boresight's catalog
set reaches off the sensor, or the boresight is no reference star), too few stars.

Magnitudes. The paper ranks with visual magnitudes; skyview's catalog and simulator use Hp, so the
instrument's ranks follow the catalog's up to photon noise (about 0.07 mag at Hp 7.3, 0.015 at 5),
saturation and blends. A real camera adds a colour term between catalog and instrument magnitudes
(tenths of a magnitude for red stars), the source of the paper's ranking errors; the benches here
see fewer of them. Hp <= 7.3 is also not the same sample as V <= 7.3.

Improvements (options, all off in the paper's method; IMPROVED_PARAMS turns them on):

- rank_swaps: no deletion by the delta_m rule; where two of the N + 1 brightest stars of the circle
  are closer than delta_m in magnitude, the sets and orders from swapping them are tried too (at
  most max_sets per boresight, the measured order first);
- boresight_order="inside": boresights whose FOV circle lies most on the sensor first (their catalog
  set is complete in the image), then by brightness;
- sign_rule="dot": eq. 17 instead of the comparison of the largest components;
- fov_radius_factor=0.75 (3 deg at 8 deg): the circle of a star fits on the sensor far more often
  (with the paper's 4 deg only the image centre has its whole circle inside an 8 x 8 deg sensor);
- N=3: sets of the 3 brightest: fewer stars per circle needed in sparse fields.

Measured: docs/methods.md and docs/benchmarks.md (`skyview bench --compare` and
`skyview bench --method svd`, with their seeds).

Length (~850 lines, 120 of them this description): the mission catalog, the first-order bounds on
singular values and vectors and the recognition are one paper's method; the failure causes against the
truth are in tests/oracles/diagnose_svd.py, the common path the template of `skyview.identify.base`.

Long (~850 lines, a docstring of 120) on purpose: by the identification template's contract
(`skyview.identify.base`) everything the method is lives in its one module: the paper's description, its
typed parameters, its search as a generator of hypotheses with its steps, and its improved variant; the
shared verification is not here.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import norm

from skyview.core.attitude import RAD_TO_ARCSEC
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, chord
from skyview.core.errors import BadInput
from skyview.identify import database
from skyview.identify.base import Hypothesis, Identifier, Observation, Search, Step
from skyview.identify.kvector import KVector
from skyview.identify.layers import Attitudes, StarSets
from skyview.identify.params import MethodParams, at_least, one_of, positive
from skyview.identify.verify import angular_distance, match_radius

SIGN_RULES = ("max", "dot")
BORESIGHT_ORDERS = ("brightness", "inside")
CAUSES = ("too_few_stars", "missing_set", "ranking", "rejected", "ambiguous")
# the delta_m rule: delete one of every close pair walking from the brightest ("thin", the paper's, on
# both sides) or both stars of a close pair ("pairs")
DELTA_M_RULES = ("thin", "pairs")
CAP = 200  # catalog rows / groups kept in one step
MAX_VERIFY = 8  # candidate sets verified per measured set
DATABASE_VERSION = 1
MIN_SEPARATION_PX = 3.0


# ---------------------------------------------------------------------- maths

def singular_values(W: np.ndarray) -> np.ndarray:
    """The three singular values, largest first, of (..., 3, N) column-vector matrices."""
    return np.linalg.svd(np.asarray(W, dtype=np.float64), compute_uv=False)


def relative_magnitudes(brightness: np.ndarray) -> np.ndarray:
    """-2.5 log10(b / b_max): 0 for the brightest; non-positive or non-finite brightness -> +inf."""
    b = np.asarray(brightness, dtype=np.float64)
    ok = np.isfinite(b) & (b > 0)
    m = np.full(b.shape, np.inf)
    if np.any(ok):
        m[ok] = -2.5 * np.log10(b[ok] / b[ok].max())
    return m


def thinned_ranks(mag_sorted: np.ndarray, delta_m: float) -> np.ndarray:
    """Stars of a magnitude-sorted list deleted by the paper's rule read as "choose the stars in ascending
    order ... delete measured stars that are not separated by at least delta_m": walking from the
    brightest, a star within delta_m of the last star kept is deleted (one of every close pair)."""
    m = np.asarray(mag_sorted, dtype=np.float64)
    out = np.zeros(len(m), dtype=bool)
    if delta_m <= 0 or len(m) < 2:
        return out
    last = m[0]
    for k in range(1, len(m)):
        if m[k] - last < delta_m:
            out[k] = True
        else:
            last = m[k]
    return out


def deleted_ranks(mag_sorted: np.ndarray, delta_m: float, rule: str) -> np.ndarray:
    """The stars the delta_m rule deletes: rule "thin" (`thinned_ranks`) or "pairs" (`ambiguous_ranks`)."""
    return thinned_ranks(mag_sorted, delta_m) if rule == "thin" else ambiguous_ranks(mag_sorted, delta_m)


def _thin_groups(group: np.ndarray, mag: np.ndarray, delta_m: float) -> np.ndarray:
    """`thinned_ranks` inside each group of a list sorted by (group, magnitude), vectorised over groups."""
    n = len(group)
    deleted = np.zeros(n, dtype=bool)
    if n == 0:
        return deleted
    first = np.r_[True, group[1:] != group[:-1]]
    starts = np.flatnonzero(first)
    counts = np.diff(np.r_[starts, n])
    last = mag[starts].copy()
    for d in range(1, int(counts.max())):
        live = counts > d
        e = starts[live] + d
        close = mag[e] - last[live] < delta_m
        deleted[e[close]] = True
        upd = np.flatnonzero(live)[~close]
        last[upd] = mag[e[~close]]
    return deleted


def ambiguous_ranks(mag_sorted: np.ndarray, delta_m: float) -> np.ndarray:
    """Stars of a magnitude-sorted list within delta_m of the star before or after them."""
    m = np.asarray(mag_sorted, dtype=np.float64)
    amb = np.zeros(len(m), dtype=bool)
    if delta_m <= 0 or len(m) < 2:
        return amb
    close = np.diff(m) < delta_m
    amb[:-1] |= close
    amb[1:] |= close
    return amb


def sign_matrix(Qw: np.ndarray, Qv: np.ndarray, rule: str = "max") -> np.ndarray:
    """The diagonal of L (eq. 17) for (..., N, 3) right singular vectors: +-1 per vector.

    rule "max": the paper's "compare the maximum value of q_wi and the maximum value of q_vi and take
    the sign of the resultant product" (the component of largest magnitude of each, with its sign);
    rule "dot": sign(q_wi^T q_vi).
    """
    Qw = np.asarray(Qw, dtype=np.float64)
    Qv = np.asarray(Qv, dtype=np.float64)
    if rule == "dot":
        s = np.sign(np.sum(Qw * Qv, axis=-2))
    elif rule == "max":
        iw = np.argmax(np.abs(Qw), axis=-2)[..., None, :]
        iv = np.argmax(np.abs(Qv), axis=-2)[..., None, :]
        s = np.sign(np.take_along_axis(Qw, iw, axis=-2)[..., 0, :] * np.take_along_axis(Qv, iv, axis=-2)[..., 0, :])
    else:
        raise ValueError(f"unknown sign rule {rule!r}: choose from {', '.join(SIGN_RULES)}")
    return np.where(s == 0, 1.0, s)


def bonferroni_bound(beta: float, n_tests: int) -> float:
    """The bound z for n_tests Gaussian numbers with the rejection chance of ONE beta-sigma bound:
    P(|x| > beta) = n_tests P(|x| > z) (3 sigma over 3 singular values: 3.32; over 12 elements: 3.69)."""
    p = 2.0 * norm.sf(beta)
    return float(norm.isf(p / (2.0 * max(int(n_tests), 1))))


def attitude_eq24(Pw: np.ndarray, Pv: np.ndarray, L: np.ndarray) -> np.ndarray:
    """C = P_w (P_v L)^T (eq. 24) for L given as its diagonal; C maps catalog to measured: W = C V."""
    return np.asarray(Pw) @ np.swapaxes(np.asarray(Pv) * np.asarray(L)[..., None, :], -1, -2)


@dataclass
class SVDecomposition:
    """W = P diag(s) Q(:, 1:3)^T of one (3, N) matrix, with what the bounds need."""

    W: np.ndarray  # (3, N)
    P: np.ndarray  # (3, 3) left singular vectors (columns)
    s: np.ndarray  # (3,) singular values, largest first
    Q: np.ndarray  # (N, N) right singular vectors (columns; 1:3 the ones paired with s)


def decompose(W: np.ndarray) -> SVDecomposition:
    W = np.asarray(W, dtype=np.float64)
    U, s, Vt = np.linalg.svd(W, full_matrices=True)
    return SVDecomposition(W=W, P=U, s=s, Q=Vt.T)


def _tangent_bases(W: np.ndarray) -> np.ndarray:
    """(N, 2, 3): two unit vectors perpendicular to each column of W."""
    w = np.asarray(W, dtype=np.float64).T
    a = np.where(np.abs(w[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(w, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(w, e1)
    return np.stack([e1, e2], axis=1)


def singular_value_sigma(d: SVDecomposition, sigma: float) -> np.ndarray:
    """First-order standard deviation of each singular value for a tangent-plane error sigma per axis.

    d sigma_k = sum_i q_ki p_k^T dw_i, dw_i perpendicular to w_i: var = sigma^2 sum_i q_ki^2 |p_k,perp_i|^2.
    """
    w = d.W.T  # (N, 3)
    q = d.Q[:, :3]  # (N, 3)
    pw = w @ d.P  # (N, 3): p_k . w_i
    return sigma * np.sqrt(np.sum(q * q * (1.0 - pw * pw), axis=0))


def right_vector_sigma(d: SVDecomposition, sigma: float) -> np.ndarray:
    """First-order standard deviation of each element of Q(:, 1:3), shape (N, 3).

    W^T W = sum_j sigma_j^2 q_j q_j^T; a change dW gives dq_k = sum_{j != k} q_j (q_j^T dM q_k) /
    (lambda_k - lambda_j) with dM = dW^T W + W^T dW and q_j^T dM q_k = sigma_k q_ji (e.p_k) +
    sigma_j q_ki (e.p_j) when dW moves star i by e (sigma_j = 0 beyond 3). Summed over two
    perpendicular directions e per star, each with variance sigma^2.
    """
    N = d.W.shape[1]
    s = np.zeros(N)
    s[:3] = d.s
    lam = s ** 2
    E = _tangent_bases(d.W)  # (N, 2, 3)
    Pfull = np.zeros((3, N))
    Pfull[:, :3] = d.P
    ep = np.einsum("iac,cj->iaj", E, Pfull)  # (N, 2, N): e . p_j (0 for j > 3)
    Q = d.Q
    var = np.zeros((N, 3))
    for k in range(3):
        # coefficient of q_j in dq_k for a move of star i along e
        num = (s[k] * Q[:, None, :] * ep[:, :, k][:, :, None]  # sigma_k q_ji (e.p_k)
               + s[None, None, :] * Q[:, k][:, None, None] * ep)  # sigma_j q_ki (e.p_j)
        den = lam[k] - lam
        with np.errstate(divide="ignore", invalid="ignore"):
            coef = np.where(np.arange(N) == k, 0.0, num / den)
        coef = np.where(np.isfinite(coef), coef, 1e6)  # a repeated singular value: no information
        dq = np.einsum("iaj,rj->iar", coef, Q)  # (N, 2, N rows)
        var[:, k] = sigma ** 2 * np.sum(dq ** 2, axis=(0, 1))
    return np.sqrt(var)


# ---------------------------------------------------------------------- mission catalog

def _tie_sets(mag_q: np.ndarray, members: np.ndarray, N: int) -> list[tuple[int, ...]]:
    """The sets of one boresight: its N brightest, one per choice of stars tied at the N/N+1 boundary.

    members: the boresight's remaining neighbours sorted by magnitude; mag_q their quantised magnitudes.
    """
    if len(members) <= N or mag_q[N - 1] != mag_q[N]:
        return [tuple(members[:N].tolist())]
    tied = np.flatnonzero(mag_q == mag_q[N - 1])
    first, last = int(tied[0]), int(tied[-1])
    base = members[:first].tolist()
    group = members[first:last + 1].tolist()
    return [tuple(base + list(c)) for c in itertools.combinations(group, N - first)]


def reference_mask(catalog: GuideCatalog, min_separation_rad: float) -> np.ndarray:
    """The reference catalog: without the fainter star of every pair closer than min_separation_rad."""
    n = len(catalog)
    keep = np.ones(n, dtype=bool)
    if min_separation_rad > 0 and n > 1:
        mag = catalog.mag.astype(np.float64)
        pairs = catalog.pairs_within(min_separation_rad)
        if len(pairs):
            a, b = pairs[:, 0], pairs[:, 1]
            a_fainter = (mag[a] > mag[b]) | ((mag[a] == mag[b]) & (a > b))
            keep[np.where(a_fainter, a, b)] = False
    return keep


def build_svd_database(catalog: GuideCatalog, fov_radius_rad: float, N: int = 4, delta_m: float = 0.0,
                       mag_step: float = 0.01, min_separation_rad: float = 0.0,
                       kvector_fit: str = "line", delta_m_rule: str = "thin") -> dict[str, np.ndarray]:
    """The paper's mission catalog: L sets of N catalog rows (brightest first), their singular values.

    delta_m > 0 deletes, in every boresight's sorted list, the stars within delta_m of their neighbour
    (the "analogous steps" of the ranking rule; not in the paper's Table 1 catalog). Returned arrays:
    sets (L, N) int32 catalog rows; sv (L, 3) singular values; boresight (L,) int32 the brightest
    boresight star whose set it is; n_* counts (0-d); the k-vector on sv[:, 1] (kv_*). Rows are in
    k-vector (sigma_2) order.
    """
    mag = catalog.mag.astype(np.float64)
    ref = np.flatnonzero(reference_mask(catalog, min_separation_rad))
    n_ref = len(ref)
    xyz = catalog.xyz[ref]
    m_ref = mag[ref]
    rank = np.empty(n_ref, dtype=np.int64)
    rank[np.lexsort((ref, m_ref))] = np.arange(n_ref)  # exact magnitude, then catalog row

    # neighbours within the FOV radius (the boresight itself included), sorted by magnitude
    tree = cKDTree(xyz)
    P = tree.query_pairs(float(chord(fov_radius_rad)), output_type="ndarray").astype(np.int64)
    selfs = np.arange(n_ref, dtype=np.int64)
    bo = np.concatenate([P[:, 0], P[:, 1], selfs])
    nb = np.concatenate([P[:, 1], P[:, 0], selfs])
    o = np.lexsort((rank[nb], bo))
    bo, nb = bo[o], nb[o]

    # the ranking-ambiguity rule inside each boresight's list
    if delta_m > 0 and len(bo) > 1 and delta_m_rule == "thin":
        keep = ~_thin_groups(bo, m_ref[nb], delta_m)
        bo, nb = bo[keep], nb[keep]
    elif delta_m > 0 and len(bo) > 1:
        same = bo[1:] == bo[:-1]
        close = same & (np.diff(m_ref[nb]) < delta_m)
        amb = np.zeros(len(bo), dtype=bool)
        amb[:-1] |= close
        amb[1:] |= close
        bo, nb = bo[~amb], nb[~amb]

    counts = np.bincount(bo, minlength=n_ref)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts >= N
    n_holes = int(np.sum(~has))
    bs = np.flatnonzero(has)
    pos = starts[bs][:, None] + np.arange(N)[None, :]
    sets = nb[pos]  # (B, N) reference indices
    set_bore = bs.copy()

    # equal magnitudes of the N-th and (N+1)-th star: one set per choice of the tied stars
    q = np.round(m_ref / mag_step) if mag_step > 0 else m_ref
    more = bs[counts[bs] > N]
    tie = more[q[nb[starts[more] + N - 1]] == q[nb[starts[more] + N]]]
    extra_sets, extra_bore = [], []
    for b in tie.tolist():
        members = nb[starts[b]:starts[b] + counts[b]]
        alts = _tie_sets(q[members], members, N)
        extra_sets += alts[1:]
        extra_bore += [b] * (len(alts) - 1)
        sets[np.searchsorted(bs, b)] = alts[0]
    n_tie_sets = len(extra_sets)
    if extra_sets:
        sets = np.concatenate([sets, np.array(extra_sets, dtype=np.int64)])
        set_bore = np.concatenate([set_bore, np.array(extra_bore, dtype=np.int64)])
    n_before = len(sets)

    # duplicate sets (Fig. 3): keep the brighter boresight
    o = np.argsort(rank[set_bore], kind="stable")
    sets, set_bore = sets[o], set_bore[o]
    if len(sets):
        _, first = np.unique(sets, axis=0, return_index=True)
        first = np.sort(first)
        sets, set_bore = sets[first], set_bore[first]

    W = np.swapaxes(xyz[sets], 1, 2) if len(sets) else np.zeros((0, 3, N))
    sv = singular_values(W) if len(sets) else np.zeros((0, 3))
    o = np.lexsort((np.arange(len(sv)), sv[:, 1])) if len(sv) else np.zeros(0, dtype=np.int64)
    sets, set_bore, sv = sets[o], set_bore[o], sv[o]
    kv = KVector(sv[:, 1], fit=kvector_fit, presorted=True)
    return {
        "sets": ref[sets].astype(np.int32).reshape(-1, N), "sv": sv, "boresight": ref[set_bore].astype(np.int32),
        "n_reference": np.array(n_ref), "n_holes": np.array(n_holes), "n_boresights": np.array(len(bs)),
        "n_tie_sets": np.array(n_tie_sets), "n_sets_before_dedupe": np.array(n_before),
        **kv.to_arrays(),
    }


def paper_storage_bytes(M: int, L: int, N: int = 4) -> int:
    """Table 1's storage: M x 3 doubles (guide stars), L x N 2-byte integers, L x 3 doubles."""
    return int(M * 3 * 8 + L * N * 2 + L * 3 * 8)


# ---------------------------------------------------------------------- the method

@dataclass(frozen=True)
class SVDParams(MethodParams):
    """The svd method's parameters (the paper's defaults; the module docstring explains each).

    fov_radius_rad None: fov_radius_factor x half the horizontal FOV; min_separation_rad None:
    MIN_SEPARATION_PX pixels of the camera."""

    N: int = 4
    fov_radius_rad: float | None = None
    fov_radius_factor: float = 1.0
    delta_m: float = 0.2
    delta_m_catalog: float = 0.2
    delta_m_rule: str = "thin"
    mag_step: float = 0.01
    min_separation_rad: float | None = None
    beta: float = 3.0
    sign_rule: str = "max"
    boresight_order: str = "brightness"
    max_boresights: int | None = None
    rank_swaps: bool = False
    max_sets: int = 8
    kvector_fit: str = "line"

    def __post_init__(self):
        super().__post_init__()
        at_least("N", self.N, 3, " (stars per set)")
        positive("fov_radius_factor", self.fov_radius_factor)
        if self.fov_radius_rad is not None and not (np.isfinite(self.fov_radius_rad)
                                                    and 0 < self.fov_radius_rad < np.pi / 2):
            raise BadInput(f"fov_radius_rad must be in (0, pi/2), not {self.fov_radius_rad!r}")
        for name in ("delta_m", "delta_m_catalog", "mag_step"):
            positive(name, getattr(self, name), allow_zero=True)
        one_of("delta_m_rule", self.delta_m_rule, DELTA_M_RULES)
        if self.min_separation_rad is not None:
            positive("min_separation_rad", self.min_separation_rad, allow_zero=True)
        positive("beta", self.beta)
        one_of("sign rule", self.sign_rule, SIGN_RULES)
        one_of("boresight order", self.boresight_order, BORESIGHT_ORDERS)
        if self.max_boresights is not None and not (isinstance(self.max_boresights, int) and self.max_boresights >= 1):
            raise BadInput("max_boresights must be >= 1 or None (all)")
        at_least("max_sets", self.max_sets, 1)
        one_of("kvector_fit", self.kvector_fit, ("line", "parabola"))


PAPER = SVDParams()
IMPROVED = replace(PAPER, rank_swaps=True, boresight_order="inside", sign_rule="dot", fov_radius_factor=0.75, N=3,
                   delta_m_catalog=0.0)
IMPROVED_PARAMS = IMPROVED.changed()


@dataclass
class _Attempt:
    boresight: int
    stars: list[int]  # the measured set, in the order compared
    within: int = 0  # measured stars within the FOV radius of the boresight (before the delta_m rule)
    changed: bool = False  # the delta_m rule deleted a star brighter than the set's faintest
    cause: str = ""  # CAUSES, or "" when identified
    candidates: int = 0
    survivors: int = 0
    verified: int = 0
    matches: dict[int, int] = field(default_factory=dict)  # the paper's answer (unique survivor)
    verification: dict = field(default_factory=dict)  # the figures of its last verification


class SVDMethod(Identifier):
    """Juang, Kim & Junkins' singular value method, ending in the shared verification."""

    name = "svd"
    paper_scenario = "juang8"
    title = "the SVD method"
    Params = SVDParams
    improved_params = IMPROVED_PARAMS

    def __init__(self, catalog: GuideCatalog, camera: Camera, sigma_rad: float, **params):
        p = self.configure(catalog, camera, sigma_rad, params)
        fov_radius_rad = p.fov_radius_rad
        if fov_radius_rad is None:
            fov_radius_rad = float(p.fov_radius_factor * np.radians(camera.fov_deg) / 2.0)
        if not (np.isfinite(fov_radius_rad) and 0 < fov_radius_rad < np.pi / 2):
            raise BadInput(f"fov_radius_rad must be in (0, pi/2), not {fov_radius_rad!r}")
        min_separation_rad = p.min_separation_rad
        if min_separation_rad is None:
            min_separation_rad = MIN_SEPARATION_PX * camera.pixel_scale_rad
        self.N = self.min_stars = int(p.N)
        self.fov_radius_rad = float(fov_radius_rad)
        self.delta_m = float(p.delta_m)
        self.delta_m_catalog = float(p.delta_m_catalog)
        self.mag_step = float(p.mag_step)
        self.min_separation_rad = float(min_separation_rad)
        self.beta = float(p.beta)
        # the same chance of rejecting the true set as one beta-sigma bound, shared by the numbers tested
        self.beta_s = bonferroni_bound(self.beta, 3)
        self.beta_q = bonferroni_bound(self.beta, 3 * self.N)
        self.radius_sigmas = float(p.radius_sigmas)
        kvector_fit, delta_m_rule = p.kvector_fit, p.delta_m_rule

        params = {"N": self.N, "fov_radius_rad": self.fov_radius_rad, "delta_m": self.delta_m_catalog,
                  "mag_step": self.mag_step, "min_separation_rad": self.min_separation_rad,
                  "kvector_fit": kvector_fit, "version": DATABASE_VERSION}
        if self.delta_m_catalog > 0:
            params["delta_m_rule"] = delta_m_rule
        self.database_key = database.make_key(self.name, params, catalog, camera)
        # the neighbours of every star within the FOV radius (~32 bytes each, both ways) while built
        arrays, info = database.load_or_build(
            self.database_key,
            lambda: build_svd_database(catalog, self.fov_radius_rad, self.N, self.delta_m_catalog, self.mag_step,
                                       self.min_separation_rad, kvector_fit, delta_m_rule),
            what=f"the svd database ({len(catalog):,} stars within {np.degrees(self.fov_radius_rad):.1f} deg)",
            estimate_bytes=64 * database.pairs_estimate(len(catalog), self.fov_radius_rad))
        self.reference = reference_mask(catalog, self.min_separation_rad)
        self.sets = arrays["sets"].astype(np.int64)
        self.sv = arrays["sv"]
        self.set_boresight = arrays["boresight"].astype(np.int64)
        self.kv = KVector.from_arrays(arrays)
        L = len(self.sets)
        M = int(len(np.unique(self.sets))) if L else 0
        info.update(M=M, L=L, paper_bytes=paper_storage_bytes(M, L, self.N),
                    paper_table1={"M": 5761, "L": 11157, "bytes": 484 * 1024},
                    reference_stars=int(arrays["n_reference"]), boresights=int(arrays["n_boresights"]),
                    holes=int(arrays["n_holes"]), tie_sets=int(arrays["n_tie_sets"]),
                    sets_before_dedupe=int(arrays["n_sets_before_dedupe"]),
                    fov_radius_deg=float(np.degrees(self.fov_radius_rad)), catalog_stars=len(catalog))
        self.database_info = info

    @property
    def n_patterns(self) -> int:
        return len(self.sets)

    def catalog_sets_of(self, row: int) -> list[tuple[int, ...]]:
        """The set(s) the mission catalog makes for catalog star `row` as boresight (before duplicate
        removal; more than one when magnitudes tie at the N/N+1 boundary); [] when the star is not a
        reference star or has fewer than N neighbours."""
        if not self.reference[row]:
            return []
        near = self.catalog.within(self.catalog.xyz[row], self.fov_radius_rad)
        near = near[self.reference[near]]
        m = self.catalog.mag[near].astype(np.float64)
        near = near[np.lexsort((near, m))]
        m = self.catalog.mag[near].astype(np.float64)
        near = near[~deleted_ranks(m, self.delta_m_catalog, self.delta_m_rule)]
        if len(near) < self.N:
            return []
        m = self.catalog.mag[near].astype(np.float64)
        q = np.round(m / self.mag_step) if self.mag_step > 0 else m
        return _tie_sets(q, near, self.N)

    # ------------------------------------------------------------------ identify (the template's parts)
    def too_few(self, search: Search) -> str:
        reason = super().too_few(search)
        if reason:
            reason = f"the SVD method needs at least N = {self.N} stars, the frame has {search.n}"
            search.stats = {"boresights_tried": 0,
                            "failure_causes": {c: int(c == "too_few_stars") for c in CAUSES},
                            "cause": "too_few_stars", "first_chain": {"outcome": "empty", "matches": {}}}
        return reason

    def hypotheses(self, search: Search):
        """Boresight by boresight, the measured set(s) -> catalog sets -> verification (`_attempt`); the
        first verified set (or an ambiguous one) ends the search."""
        obs, V, sigma, steps = search.obs, search.V, search.sigma, search.steps
        n = search.n
        N = self.N
        causes = {c: 0 for c in CAUSES}
        mag = relative_magnitudes(obs.brightness)
        by_brightness = np.lexsort((np.arange(n), mag))  # brightest first, ties by index
        cos_r = np.cos(self.fov_radius_rad)
        dots = V @ V.T
        boresights = by_brightness
        if self.boresight_order == "inside":
            inside = self._inside_fraction(obs)
            boresights = by_brightness[np.lexsort((np.arange(n), -inside[by_brightness]))]
        if self.max_boresights is not None:
            boresights = boresights[: self.max_boresights]

        attempts: list[_Attempt] = []
        tried: dict[tuple[int, ...], _Attempt] = {}
        done = False
        verified_any: list[tuple] = []
        for b in boresights.tolist():
            near = by_brightness[dots[b, by_brightness] > cos_r]  # within the FOV radius, brightest first
            m_near = mag[near]
            if self.rank_swaps:
                kept = near
            else:
                kept = near[~deleted_ranks(m_near, self.delta_m, self.delta_m_rule)]
            steps.append(Step("boresight", f"boresight star {b}: {len(near)} stars within "
                                           f"{np.degrees(self.fov_radius_rad):.2f} deg, {len(near) - len(kept)} "
                                           f"deleted by the {self.delta_m:g} mag rule, set {kept[:N].tolist()}",
                              observed=[b] + [i for i in kept[:N].tolist() if i != b],
                              numbers={"boresight": b, "stars_in_radius": len(near), "deleted": len(near) - len(kept),
                                       **{f"mag_{k + 1}": float(mag[s]) for k, s in enumerate(kept[:N + 1])}},
                              layers=(StarSets.of(within=near.tolist(),
                                                  deleted=sorted(set(near.tolist()) - set(kept.tolist()))),)))
            changed = bool(len(kept) < len(near) and (len(kept) < N or np.any(
                ~np.isin(near[mag[near] <= mag[kept[N - 1]]], kept))))
            if len(kept) < N:
                a = _Attempt(b, kept.tolist(), within=len(near), changed=changed,
                             cause="ranking" if len(near) >= N else "too_few_stars")
                attempts.append(a)
                causes[a.cause] += 1
                steps.append(Step("skip", f"boresight {b}: only {len(kept)} stars left, N = {N} needed",
                                  observed=kept.tolist(), numbers={"stars": len(kept)}))
                continue
            for S in self._measured_sets(kept, mag):
                a = _Attempt(b, list(S), within=len(near), changed=changed)
                attempts.append(a)
                if S in tried:  # the same stars in the same order: the same answer, nothing new to verify
                    prev = tried[S]
                    a.cause, a.candidates, a.survivors = prev.cause, prev.candidates, prev.survivors
                    causes[a.cause] += 1
                    steps.append(Step("skip", f"boresight {b}: set {list(S)} was tried already ({a.cause})",
                                      observed=list(S), numbers={"boresight": b}))
                    continue
                tried[S] = a
                passed = yield from self._attempt(V, np.array(S), a, sigma, steps)
                if a.cause == "missing_set" and changed:
                    a.cause = "ranking"  # the delta_m rule took a star out of the set
                if a.cause:
                    causes[a.cause] += 1
                if passed is not None:
                    verified_any.append(passed)
                if passed is not None or a.cause == "ambiguous":
                    done = True
                    break
            if done:
                break

        if not verified_any:
            reasons = [f"boresight {a.boresight} set {a.stars}: {a.cause}" for a in attempts]
            search.reasons = [("no boresight star gave a verified set (" + "; ".join(reasons[:6])
                               + ("; ..." if len(reasons) > 6 else "") + ")") if reasons else "no boresight to try"]
        first = next((a for a in attempts if a.survivors > 0), None)
        eq24 = {}
        if verified_any:
            ver, S_used, rows, C_eq24 = verified_any[0]
            eq24 = {"set_observed": [int(i) for i in S_used], "set_catalog": [int(r) for r in rows],
                    "C": C_eq24.tolist(),
                    "C_vs_verified_arcsec": _rotation_angle(C_eq24 @ ver.R.T) * RAD_TO_ARCSEC}
        search.stats = {
            "attitude_eq24": eq24,
            "boresights_tried": len({a.boresight for a in attempts}),
            "sets_tried": len(attempts),
            "candidates": [a.candidates for a in attempts],
            "survivors": [a.survivors for a in attempts],
            "verifications": search.verifications,
            "failure_causes": causes,
            "cause": "" if verified_any else _frame_cause(attempts),
            "attempts": [{"boresight": a.boresight, "stars": a.stars, "within": a.within, "changed": a.changed,
                          "cause": a.cause, "candidates": a.candidates, "survivors": a.survivors} for a in attempts],
            "first_chain": {"outcome": ("unique" if first is not None and first.survivors == 1 else
                                        "ambiguous" if first is not None else "empty"),
                            "matches": dict(first.matches) if first is not None and first.survivors == 1 else {}},
        }
        if verified_any:
            yield verified_any[0][0]  # the chosen set's verification: accepted

    # ------------------------------------------------------------------ one measured set
    def _measured_sets(self, kept: np.ndarray, mag: np.ndarray) -> list[tuple[int, ...]]:
        """The measured set(s) of one boresight, in the order to compare: the N brightest, brightest first.

        With rank_swaps, also the sets and orders from swapping stars of the N + 1 brightest whose
        magnitudes differ by less than delta_m (the rank order the catalog may have instead).
        """
        N = self.N
        base = tuple(kept[:N].tolist())
        if not self.rank_swaps:
            return [base]
        top = kept[: N + 1].tolist()
        m = mag[top]
        close = [k for k in range(len(top) - 1) if m[k + 1] - m[k] < self.delta_m]
        out = [base]
        seen = {base}
        # every subset of the close adjacent pairs, swapped (smallest subsets first)
        for r in range(1, len(close) + 1):
            for combo in itertools.combinations(close, r):
                order = list(top)
                for k in combo:
                    order[k], order[k + 1] = order[k + 1], order[k]
                S = tuple(order[:N])
                if S not in seen:
                    seen.add(S)
                    out.append(S)
                if len(out) >= self.max_sets:
                    return out
        return out

    def _attempt(self, V: np.ndarray, S: np.ndarray, a: _Attempt, sigma: float, steps: list[Step]):
        """Singular values -> catalog candidates -> right singular vectors -> eq. 24 -> verification (a
        generator: it yields the hypotheses of the surviving sets; the method chooses among the verified).

        Sets a.cause on failure; returns (verification, S, catalog rows, C) of the verified set, or None.
        """
        W = V[S].T
        d = decompose(W)
        s_sig = singular_value_sigma(d, sigma)
        tol = self.beta_s * s_sig + 1e-12
        steps.append(Step("singular_values", f"singular values of stars {S.tolist()}: "
                                             + ", ".join(f"{x:.6f}" for x in d.s)
                                             + f" (+- {tol[1]:.2e}, {tol[2]:.2e} on sigma_2, sigma_3)",
                          observed=S.tolist(),
                          numbers={"sigma_1": d.s[0], "sigma_2": d.s[1], "sigma_3": d.s[2],
                                   "bound_1": tol[0], "bound_2": tol[1], "bound_3": tol[2]}))
        start, stop = self.kv.range(d.s[1] - tol[1], d.s[1] + tol[1])
        idx = np.arange(start, stop)
        n_sigma2 = len(idx)
        if len(idx):
            ok = np.all(np.abs(self.sv[idx] - d.s[None, :]) <= tol[None, :], axis=1)
            idx = idx[ok]
        a.candidates = int(len(idx))
        steps.append(Step("lookup", f"{n_sigma2} catalog sets with sigma_2 in range, {len(idx)} with all three "
                                    "singular values in range",
                          observed=S.tolist(), catalog=_distinct(self.sets[idx]),
                          groups=[tuple(r) for r in self.sets[idx[:CAP]].tolist()],
                          numbers={"candidates_sigma_2": n_sigma2, "candidates": len(idx)}))
        if len(idx) == 0:
            a.cause = "missing_set"
            return None

        # right singular vectors (eqs. 15-17)
        Wc = np.swapaxes(self.catalog.xyz[self.sets[idx]], 1, 2)  # (k, 3, N)
        U, _, Vt = np.linalg.svd(Wc)
        Qv = np.swapaxes(Vt, 1, 2)[:, :, :3]  # (k, N, 3)
        Qw = d.Q[:, :3]
        Ls = sign_matrix(Qw[None], Qv, self.sign_rule)  # (k, 3)
        q_tol = self.beta_q * right_vector_sigma(d, sigma) + 1e-9
        diff = np.abs(Qw[None] - Qv * Ls[:, None, :])
        C = attitude_eq24(d.P[None], U, Ls)  # (k, 3, 3)
        det = np.linalg.det(C)
        keep = np.all(diff <= q_tol[None], axis=(1, 2)) & (det > 0)
        surv = idx[keep]
        a.survivors = int(len(surv))
        steps.append(Step("filter", f"right singular vectors: {len(surv)} of {len(idx)} candidate sets agree",
                          observed=S.tolist(), catalog=_distinct(self.sets[surv]),
                          groups=[tuple(r) for r in self.sets[surv[:CAP]].tolist()],
                          numbers={"before": len(idx), "after": len(surv),
                                   "worst_ratio_best": float(np.min(np.max(diff / q_tol[None], axis=(1, 2))))}))
        if len(surv) == 0:
            a.cause = "ranking"
            return None
        if len(surv) == 1:
            a.matches = {int(o): int(c) for o, c in zip(S.tolist(), self.sets[surv[0]].tolist())}

        passed = []
        untestable = 0
        for j, c in zip(np.flatnonzero(keep)[:MAX_VERIFY].tolist(), surv[:MAX_VERIFY].tolist()):
            rows = self.sets[c]
            Cj = C[j]
            pred = self.catalog.xyz[rows] @ Cj.T
            fit = angular_distance(V[S], pred)
            steps.append(Step("attitude", f"eq. 24 attitude from catalog set {rows.tolist()}: largest residual "
                                          f"{fit.max() * RAD_TO_ARCSEC:.1f}\"",
                              observed=S.tolist(), catalog=rows.tolist(), groups=[tuple(rows.tolist())],
                              numbers={"set": c, "max_residual_arcsec": float(fit.max() * RAD_TO_ARCSEC),
                                       "L1": Ls[j, 0], "L2": Ls[j, 1], "L3": Ls[j, 2]},
                              layers=(Attitudes.of(Cj, name="eq. 24 attitude"),)))
            hyp = {int(o): int(r) for o, r in zip(S.tolist(), rows.tolist())}
            ver = yield Hypothesis(hyp, accept=False)
            a.verification = ver.to_dict()
            a.verified += 1
            untestable += ver.n_tested == 0
            if ver.passed:
                passed.append((ver, S, rows, Cj))
        if not passed:
            a.cause = "too_few_stars" if untestable == a.verified else "rejected"
            return None
        if len(passed) > 1:
            R0 = passed[0][0].R
            if any(_rotation_angle(p[0].R @ R0.T) > 2.0 * match_radius(sigma, self.radius_sigmas) for p in passed[1:]):
                a.cause = "ambiguous"
                steps.append(Step("stop", f"{len(passed)} catalog sets verified with different attitudes: "
                                          "not identified", observed=S.tolist(), numbers={"verified": len(passed)}))
                return None
            passed.sort(key=lambda p: -len(p[0].matches))
        return passed[0]

    def _inside_fraction(self, obs: Observation) -> np.ndarray:
        """Fraction of each star's FOV circle that lies on the sensor (sampled on 3 rings x 24 points)."""
        V = np.asarray(obs.vectors, dtype=np.float64)
        n = len(V)
        ang = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
        radii = self.fov_radius_rad * np.array([1.0 / 3.0, 2.0 / 3.0, 1.0])
        E = _tangent_bases(V.T)  # (n, 2, 3)
        pts = (np.cos(radii)[None, :, None, None] * V[:, None, None, :]
               + np.sin(radii)[None, :, None, None]
               * (np.cos(ang)[None, None, :, None] * E[:, None, None, 0, :]
                  + np.sin(ang)[None, None, :, None] * E[:, None, None, 1, :]))
        uv, front = self.camera.project(pts.reshape(-1, 3))
        inside = (front & self.camera.in_image(uv)).reshape(n, -1)
        return inside.mean(axis=1)


# ---------------------------------------------------------------------- helpers

def _frame_cause(attempts: list[_Attempt]) -> str:
    """The cause of a failed frame: the furthest any attempt got (ambiguous > rejected > ranking > missing set)."""
    order = ["ambiguous", "rejected", "ranking", "missing_set", "too_few_stars"]
    got = {a.cause for a in attempts}
    for c in order:
        if c in got:
            return c
    return "too_few_stars"


def _rotation_angle(R: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def _distinct(H: np.ndarray) -> list[int]:
    return np.unique(H).astype(int)[:CAP].tolist() if H.size else []
