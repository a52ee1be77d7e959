"""Stochastic star identification (Udomkesmalee, Alexander & Tolivar 1994).

The paper identifies ONE star per frame, the designated star, and does it over a sequence of frames
whose relative rotation is known, with Bayes' rule. Its pieces, with the paper's names:

f (designated star). The catalog star nearest the boresight. In an observed frame it is the observed
star nearest the boresight (the +z camera axis).

g (statistics). x = [n, mu_m, sigma_m, mu_d, sigma_d, sigma_theta] (eq. 4) of the field around the
designated star: the number of stars in the field (the designated one included), the mean and the
spread (standard deviation, ddof 0) of their magnitudes, the mean and the spread of the angular
distances of the other stars to the designated star, and the spread of the neighbouring angles of
Fig. 1: the angles between consecutive lines radiating from the designated star to the others,
ordered by position angle (they sum to 2 pi). One neighbour gives one angle of 2 pi and a spread of
0; no neighbour gives 0 for the distance and angle statistics.

xi (catalog statistics). For every catalog star s, xi_s is x of the field a camera sees with its
boresight on s (the paper: "the star pattern surrounding each cataloged star for a given FOV").
skyview's sensor is a rectangle, so the field depends on the roll: xi_s is the mean of x over
N_ROLL rolls spread over half a turn (a rectangle repeats after half a turn). Built once per
catalog and camera and cached (`skyview.identify.database`).

Likelihood (eq. 5). p(x | s) = N(x; xi_s, Q) with the paper's diagonal Q (PAPER_Q): 4 star^2,
0.36 mag^2, 0.36 mag^2, 2 deg^2, 2 deg^2 and 0.01 for sigma_theta. The paper prints "deg^2" for the
last one too, but a spread of neighbouring angles known to 0.1 deg is impossible with its 1 deg
position noise; 0.01 rad^2 (0.1 rad = 5.7 deg, the angle error of a star 1 deg off at 10 deg) is what
fits, and what is used. The exponent has the usual 1/2 (the OCR of eq. 5 lost it; the paper calls
p a Gaussian). Equal priors 1/N (eq. 3).

Recursion (eq. 3, Table 1). Row r of the table is the hypothesis "the designated star of frame 0 is
catalog star r"; it carries its current designated star s_k(r), an attitude and its log-posterior.
At frame k the known turn moves every row to its next designated star and the posterior is carried
over: rho_k(r) = p(x_k | s_k(r)) rho_{k-1}(r) / sum. Everything is in logarithms. Rows that reach the
same star by different histories add up in the posterior of that star (`marginal`): that is "the
probability of the correct star" and "the stars with probability > 1/N" of Table 2, and what
p_identify is compared with.

The known turn and the roll (the paper leaves both open). The turn is what a spacecraft's gyros
measure: the rotation of the camera body between frames, given in the CAMERA frame as dR_cam with
v_cam_{k+1} = dR_cam @ v_cam_k (R_{k+1} = dR_cam @ R_k), exactly what `simulate.save_sequence`
records. A hypothesis "the designated star is catalog star s" fixes two of the three attitude
angles (the observed designated star's direction must be s); the roll about it is free, and without
a roll a turn given in body axes cannot be carried to the sky. So each row carries a full attitude
R(r):

- at frame 0 the roll comes from matching its field: every pair (observed neighbour i, catalog
  neighbour j of s) whose distances to the designated stars agree within 3 sqrt(2) sigma and whose
  magnitudes agree within 3 sqrt(2) sigma_mag votes for the roll phi_i - phi_j (position angles
  around the designated star); the votes are weighted by how well distance and magnitude agree,
  smoothed over the roll uncertainty sqrt(2) sigma / d, and the peak is refined by the weighted
  circular mean of the votes near it. R(r) then maps s onto the observed designated star exactly.
- after each frame the leading rows (posterior above REFINE_FLOOR of the prior, at most REFINE_TOP)
  fit their attitude to the whole field: the catalog stars the attitude predicts are matched one to
  one to the observed stars (within 3 sqrt(2) sigma) and Wahba's problem is solved, twice.
- at frame k+1 the row's attitude is propagated with the turn, R = dR_cam @ R(r), and its next
  designated star registered (the paper: "the newly designated star is registered"):
  registration="boresight" (default, the paper's f) takes the catalog star nearest the predicted
  boresight R[2]; registration="designated" reads it where the OBSERVED designated star points under
  the row (R^T v_d), weighing the 3 nearest catalog stars by position and magnitude (`_predict`).

Identification. When one star dominates (posterior >= p_identify, the paper's rho -> 1), the
attitude of its best row predicts where every catalog star falls; observed stars are matched to them one to one
(twice, re-estimating the attitude with Markley's SVD in between) and the designated star with the
farthest matched neighbour goes to the shared verification (`skyview.identify.verify`), which tests
the attitude of those two stars against all the other observed stars. Up to max_verify neighbours
are tried (each counts in the Bonferroni factor). Only a verified answer is reported as identified.

Magnitudes. The paper's mu_m is an absolute magnitude. Observed magnitudes are
m = mag_zero_point - 2.5 log10(brightness): the instrument's photometric zero point (for the
simulator it follows from its sensor model, see `skyview.solver.sequence.zero_point`). Without a zero point
(mag_zero_point=None) mu_m is used relative to the designated star (mean(m) - m_designated, against
xi_mu_m - mag(s) of each hypothesis): the zero point cancels, sigma_m needs none. mag_cut (needs a
zero point) leaves the observed stars fainter than the catalog out of the statistics.

Options beyond the paper (IMPROVED_PARAMS): verify_top verifies the leading stars each frame even
before one dominates (the shared verification keeps wrong answers out; every test counts in its
Bonferroni factor); prediction_likelihood adds the registration residual (how far the observed
designated star lands, under row r, from the nearest catalog star: Gaussian with the position noise
and half a degree of attitude error) to the likelihood, a geometric check the statistics alone lack;
registration="designated" (above). docs/stochastic.md has the reasons and the measurements.

The paper taken literally (hypothesis="boresight", for reproducing it): row r is "the boresight is on
star r", the turns are the inertial rotations of the boresight, no roll is carried and no field is
fitted; a row gets a roll (the vote) only when it goes to verification.

Length (~890 lines): the statistics, the roll vote, the prediction with the known turn, the
registration and the recursion are one method over a sequence; scoring against the truth (the true
star's posterior) is `skyview.simulate.scoring.sequence_truth`, never here.

Long (~900 lines, a docstring of 90) on purpose: by the identification template's contract
(`skyview.identify.base`) everything the method is lives in its one module: the paper's description, its
typed parameters, its search as a generator of hypotheses with its steps, and its improved variant; the
shared verification is not here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import logsumexp
from scipy.stats import chi2

from skyview.core.attitude import RAD_TO_ARCSEC, svd_attitude
from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, chord
from skyview.core.errors import BadInput
from skyview.identify import database
from skyview.identify.base import (
    INCONCLUSIVE,
    Hypothesis,
    Identification,
    Observation,
    Search,
    SequenceIdentifier,
    Step,
)
from skyview.identify.layers import Posterior
from skyview.identify.params import MethodParams, one_of
from skyview.identify.verify import angular_distance, frame_stars, match_one_to_one, match_radius

STAT_NAMES = ("n", "mu_m", "sigma_m", "mu_d", "sigma_d", "sigma_theta")
# The paper's Q (diagonal): star^2, mag^2, mag^2, deg^2, deg^2, rad^2 (see the module docstring)
PAPER_Q = (4.0, 0.36, 0.36, 2.0, 2.0, 0.01)
_DEG = np.pi / 180.0
_Q_TO_INTERNAL = np.array([1.0, 1.0, 1.0, _DEG ** 2, _DEG ** 2, 1.0])  # x is in radians inside
N_ROLL = 12  # rolls averaged in xi (over half a turn)
NEIGHBOUR_RADIUS_FACTOR = 1.5  # catalog neighbours kept for the roll vote: this x the half-diagonal
TOP_K = 10  # hypotheses listed in each step
REFINE_TOP = 256  # at most this many leading rows get their attitude fitted to each frame
REFINE_FLOOR = 0.1  # ... those with a posterior above this fraction of the prior 1/N
N_REGISTER = 3  # candidate catalog stars for a row's next designated star (registration="designated")
REGISTRATIONS = ("boresight", "designated")
# What a hypothesis is, and so in which frame the known turn is given (docs/stochastic.md):
# "attitude" (skyview's default): a full attitude per row, turns in the camera frame (dR_cam, gyros);
# "boresight" (the paper taken literally): "the boresight is on star s", turns inertial (T, the
# boresight moves b_{k+1} = T b_k, e.g. 10 deg along right ascension), no roll until verification.
HYPOTHESES = ("attitude", "boresight")
N_BINS = 360  # roll histogram bins
DATABASE_VERSION = 1
MAG_CONSISTENCY_P = 1e-4  # a verified match whose magnitudes disagree more than this is refused
MAG_CLIP = 4.0  # sigmas: one saturated or blended star cannot refuse a match on its own


# ---------------------------------------------------------------------------- statistics (g)

def neighbour_angles(phi: np.ndarray) -> np.ndarray:
    """The angles between consecutive position angles (Fig. 1), wrap-around included; sum 2 pi."""
    phi = np.sort(np.mod(np.asarray(phi, dtype=np.float64), 2.0 * np.pi))
    if len(phi) == 0:
        return np.zeros(0)
    gaps = np.diff(phi)
    return np.concatenate([gaps, [2.0 * np.pi - (phi[-1] - phi[0])]])


def field_statistics(m_designated: float, m_neighbours: np.ndarray, d_neighbours: np.ndarray,
                     phi_neighbours: np.ndarray) -> np.ndarray:
    """x = [n, mu_m, sigma_m, mu_d, sigma_d, sigma_theta] of a field (eq. 4); angles in radians.

    m_*: magnitudes; d_neighbours: angular distances of the other stars to the designated star;
    phi_neighbours: their position angles around it (any fixed origin and sense).
    """
    m = np.concatenate([[float(m_designated)], np.asarray(m_neighbours, dtype=np.float64)])
    d = np.asarray(d_neighbours, dtype=np.float64)
    x = np.zeros(6)
    x[0] = len(m)
    x[1] = m.mean()
    x[2] = m.std()
    if len(d):
        x[3] = d.mean()
        x[4] = d.std()
        x[5] = neighbour_angles(phi_neighbours).std()
    return x


def tangent_basis(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """East and north unit vectors at each ICRS direction (rows); east x north = v."""
    v = np.atleast_2d(np.asarray(v, dtype=np.float64))
    ra = np.arctan2(v[:, 1], v[:, 0])
    east = np.stack([-np.sin(ra), np.cos(ra), np.zeros_like(ra)], axis=1)
    north = np.cross(v, east)
    north /= np.linalg.norm(north, axis=1, keepdims=True)
    return east, north


def observed_basis(v_d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A fixed tangent basis (a1, a2) at a camera-frame direction; a1 x a2 = v_d."""
    v_d = np.asarray(v_d, dtype=np.float64)
    ref = np.array([1.0, 0.0, 0.0]) if abs(v_d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a1 = ref - (ref @ v_d) * v_d
    a1 /= np.linalg.norm(a1)
    return a1, np.cross(v_d, a1)


def position_angles(center: np.ndarray, others: np.ndarray, b1: np.ndarray, b2: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Angular distance and position angle atan2(w.b2, w.b1) of `others` around `center`."""
    others = np.atleast_2d(others)
    d = angular_distance(others, center[None, :])
    phi = np.arctan2(others @ b2, others @ b1)
    return d, phi


def build_stochastic_database(catalog: GuideCatalog, camera: Camera, n_roll: int = N_ROLL,
                              neighbour_radius_rad: float | None = None) -> dict[str, np.ndarray]:
    """xi for every catalog star (mean of x over n_roll rolls with the boresight on the star) and
    every star's neighbours within neighbour_radius_rad (CSR: distance, position angle from north
    towards east)."""
    xyz = catalog.xyz
    N = len(catalog)
    mag = catalog.mag.astype(np.float64)
    if neighbour_radius_rad is None:
        neighbour_radius_rad = NEIGHBOUR_RADIUS_FACTOR * camera.half_diagonal_rad
    east, north = tangent_basis(xyz)
    lists = catalog.tree.query_ball_point(xyz, float(chord(neighbour_radius_rad)))
    psi = np.arange(n_roll) * np.pi / n_roll
    cps, sps = np.cos(psi)[:, None], np.sin(psi)[:, None]
    xi = np.zeros((N, 6))
    offsets = np.zeros(N + 1, dtype=np.int64)
    nb_all, d_all, phi_all = [], [], []
    f_half = camera.half_diagonal_rad
    for s in range(N):
        J = np.asarray(lists[s], dtype=np.int64)
        J = np.sort(J[J != s])
        w = xyz[J]
        we, wn, wb = w @ east[s], w @ north[s], w @ xyz[s]
        d = 2.0 * np.arcsin(np.clip(np.linalg.norm(w - xyz[s], axis=1) / 2.0, 0.0, 1.0))
        phi = np.arctan2(wn, we)
        nb_all.append(J.astype(np.int32))
        d_all.append(d)
        phi_all.append(phi)
        offsets[s + 1] = offsets[s] + len(J)
        # camera axes for boresight s and roll psi (attitude.R_from_radec_roll): up = cos n + sin e,
        # y = -up, x = y x b = -cos e + sin n
        near = d <= f_half + 1e-9
        xc = -cps * we[near] + sps * wn[near]
        yc = -(cps * wn[near] + sps * we[near])
        zc = np.broadcast_to(wb[near], xc.shape)
        acc = np.zeros(6)
        for r in range(n_roll):
            v = np.stack([xc[r], yc[r], zc[r]], axis=1)
            if len(v):
                uv, front = camera.project(v)
                inside = front & camera.in_image(uv)
            else:
                inside = np.zeros(0, dtype=bool)
            sel = np.flatnonzero(near)[inside]
            acc += field_statistics(mag[s], mag[J[sel]], d[sel], phi[sel])
        xi[s] = acc / n_roll
    return {
        "xi": xi,
        "nb_offsets": offsets,
        "nb_index": np.concatenate(nb_all) if nb_all else np.zeros(0, np.int32),
        "nb_d": np.concatenate(d_all) if d_all else np.zeros(0),
        "nb_phi": np.concatenate(phi_all) if phi_all else np.zeros(0),
    }


# ---------------------------------------------------------------------------- rotations

def _wrap(a: np.ndarray) -> np.ndarray:
    return np.mod(np.asarray(a) + np.pi, 2.0 * np.pi) - np.pi


# ---------------------------------------------------------------------------- state

@dataclass
class StochasticState:
    """The posterior table of the paper's Table 1 after some frames.

    rows: the current designated star s_k(r) of every row; R: each row's attitude estimate;
    log_post: log rho_k(r); frames: frames absorbed; history: one summary dict per frame.
    """

    rows: np.ndarray
    R: np.ndarray
    log_post: np.ndarray
    frames: int = 0  # frames absorbed (with at least one star)
    seen: int = 0  # frames given
    verifications: int = 0
    history: list[dict] = field(default_factory=list)

    @property
    def posterior(self) -> np.ndarray:
        return np.exp(self.log_post)


@dataclass
class _Field:
    """The observed field of one frame, as the statistics see it."""

    designated: int  # observed index of the designated star
    used: np.ndarray  # observed indices that enter the statistics (designated first)
    v_d: np.ndarray
    a1: np.ndarray
    a2: np.ndarray
    d: np.ndarray  # neighbours (used[1:]): distance, position angle, magnitude
    phi: np.ndarray
    m: np.ndarray
    m_d: float
    x: np.ndarray


@dataclass(frozen=True)
class StochasticParams(MethodParams):
    """The stochastic method's parameters (the paper's Q and rho -> 1; the module docstring explains each)."""

    Q: tuple | None = None
    p_identify: float = 0.95
    mag_zero_point: float | None = None
    mag_cut: float | None = None
    sigma_mag: float = 0.6
    n_roll: int = N_ROLL
    max_verify: int = 3
    verify_top: int = 0
    prediction_likelihood: bool = False
    registration: str = "boresight"
    hypothesis: str = "attitude"

    def __post_init__(self):
        q = np.asarray(PAPER_Q if self.Q is None else self.Q, dtype=np.float64)
        if q.shape != (6,) or not np.all(np.isfinite(q)) or np.any(q <= 0):
            raise BadInput("Q must be six positive variances (star^2, mag^2, mag^2, deg^2, deg^2, rad^2)")
        if not (0.0 < float(self.p_identify) <= 1.0):
            raise BadInput("p_identify must be in (0, 1]")
        if self.mag_zero_point is not None and not np.isfinite(self.mag_zero_point):
            raise BadInput("mag_zero_point must be a finite number or None")
        if self.mag_cut is not None and (self.mag_zero_point is None or not np.isfinite(self.mag_cut)):
            raise BadInput("mag_cut needs a finite value and a mag_zero_point (magnitudes on the catalog's scale)")
        if not (np.isfinite(self.sigma_mag) and self.sigma_mag > 0):
            raise BadInput("sigma_mag must be positive")
        if int(self.n_roll) < 1:
            raise BadInput("n_roll must be at least 1")
        if int(self.max_verify) < 1 or int(self.verify_top) < 0:
            raise BadInput("max_verify must be >= 1 and verify_top >= 0")
        one_of("registration", self.registration, REGISTRATIONS)
        one_of("hypothesis", self.hypothesis, HYPOTHESES)
        if self.hypothesis == "boresight" and (self.registration != "boresight" or self.prediction_likelihood):
            raise BadInput("hypothesis='boresight' (the paper's literal model) goes with the paper variant only: "
                           "it registers by the boresight and has no prediction likelihood")
        super().__post_init__()


PAPER = StochasticParams()
IMPROVED = replace(PAPER, verify_top=3, prediction_likelihood=True, registration="designated")
IMPROVED_PARAMS = IMPROVED.changed()


class StochasticMethod(SequenceIdentifier):
    """Udomkesmalee et al.'s stochastic identification over a sequence of frames, ending in the
    shared verification. `identify(obs)` is one frame (the prior update only);
    `identify_sequence(observations, turns)` runs the recursion of eq. 3."""

    name = "stochastic"
    paper_scenario = "udomkesmalee30"
    Params = StochasticParams
    improved_params = IMPROVED_PARAMS

    def __init__(self, catalog: GuideCatalog, camera: Camera, sigma_rad: float, **params):
        p = self.configure(catalog, camera, sigma_rad, params)
        if len(catalog) < 2:
            raise BadInput("the stochastic method needs a catalog of at least two stars")
        n_roll = p.n_roll
        q = np.asarray(PAPER_Q if p.Q is None else p.Q, dtype=np.float64)
        self.Q = tuple(float(v) for v in q)
        self.q_inv = 1.0 / (q * _Q_TO_INTERNAL)
        self.p_identify = float(p.p_identify)
        self.mag_zero_point = None if p.mag_zero_point is None else float(p.mag_zero_point)
        self.mag_cut = None if p.mag_cut is None else float(p.mag_cut)
        self.sigma_mag = float(p.sigma_mag)
        self.max_verify = int(p.max_verify)
        self.verify_top = int(p.verify_top)
        self.prediction_likelihood = bool(p.prediction_likelihood)
        self.radius_sigmas = float(p.radius_sigmas)

        self.neighbour_radius_rad = NEIGHBOUR_RADIUS_FACTOR * camera.half_diagonal_rad
        params = {"n_roll": int(n_roll), "neighbour_radius_rad": self.neighbour_radius_rad,
                  "version": DATABASE_VERSION}
        self.database_key = database.make_key(self.name, params, catalog, camera)
        n_pairs = database.pairs_estimate(len(catalog), self.neighbour_radius_rad)
        what = (f"the stochastic method's database ({len(catalog):,} stars, neighbours within "
                f"{np.degrees(self.neighbour_radius_rad):.1f} deg, {int(n_roll)} rolls)")
        # neighbour lists (index, distance, angle: ~48 bytes a neighbour, both ways) and the statistics vector
        # of every star at every roll
        arrays, info = database.load_or_build(
            self.database_key, lambda: build_stochastic_database(catalog, camera, int(n_roll),
                                                                 self.neighbour_radius_rad),
            what=what, estimate_bytes=96 * n_pairs + 64 * len(catalog) * int(n_roll))
        self.xi = arrays["xi"]
        self.nb_offsets = arrays["nb_offsets"].astype(np.int64)
        self.nb_index = arrays["nb_index"].astype(np.int64)
        self.nb_d = arrays["nb_d"]
        self.nb_phi = arrays["nb_phi"]
        self.mag = catalog.mag.astype(np.float64)
        self.east, self.north = tangent_basis(catalog.xyz)
        info.update(catalog_stars=len(catalog), fov_deg=float(camera.fov_deg), n_roll=int(n_roll),
                    neighbours=int(len(self.nb_index)), mean_stars_in_field=float(self.xi[:, 0].mean()))
        self.database_info = info

    @property
    def n_catalog(self) -> int:
        return len(self.catalog)

    @property
    def n_patterns(self) -> int:
        return self.n_catalog

    # ------------------------------------------------------------------ public API
    def start(self) -> StochasticState:
        """Equal priors 1/N: row r starts at catalog star r (attitudes are set by the first frame)."""
        N = self.n_catalog
        return StochasticState(rows=np.arange(N), R=np.tile(np.eye(3), (N, 1, 1)),
                               log_post=np.full(N, -np.log(N)))

    def identify_sequence(self, observations: list[Observation], turns: list[np.ndarray] | None = None,
                          designated: list[int | None] | None = None) -> list[Identification]:
        """Frames k = 0..K-1 with turns[k] = dR_cam from frame k to k+1 (v_cam_{k+1} = dR_cam v_cam_k),
        or, with hypothesis="boresight", the inertial turn T of the boresight (b_{k+1} = T b_k, i.e.
        R_{k+1} = R_k T^T).

        designated (optional): per frame, the observed index to use as the designated star instead of
        the one nearest the boresight (None: the rule f). Returns one Identification per frame; frame
        k's steps cover that frame (its 'update' step carries the posterior as a `Posterior` layer:
        `skyview.simulate.scoring.sequence_truth` scores it against the truth), its stats hold the posterior
        summary.
        """
        observations = list(observations)
        turns = [] if turns is None else [np.asarray(t, dtype=np.float64) for t in turns]
        for t in turns:
            if t.shape != (3, 3) or not np.all(np.isfinite(t)) or np.abs(t @ t.T - np.eye(3)).max() > 1e-6 \
                    or np.linalg.det(t) < 0:
                raise BadInput("every turn must be a proper 3x3 rotation matrix (dR_cam)")
        if designated is not None and len(designated) != len(observations):
            raise BadInput("designated must have one entry per frame")
        return super().identify_sequence(observations, turns, designated=designated)

    # ------------------------------------------------------------------ one frame
    def update(self, state: StochasticState, obs: Observation, dR_cam: np.ndarray | None,
               designated: int | None = None) -> Identification:
        """Absorb one frame into `state` (in place): predict with the turn, update the posterior,
        and try to identify. dR_cam: the turn from the previous frame (None for the first frame);
        designated: the observed index of the designated star (default: the rule f, the observed star
        nearest the boresight)."""
        k = state.seen  # this frame's number
        first = state.frames == 0  # no star seen yet: the prior update (a turn before it is moot)
        if k > 0 and dR_cam is None:
            raise BadInput("a frame after the first needs the turn from the previous frame (dR_cam)")
        search = self.begin(obs)
        search.n_hypotheses = state.verifications  # the Bonferroni factor runs over the whole sequence
        V, sigma, steps, result = search.V, search.sigma, search.steps, search.result
        fld = self._field(obs, V, designated)
        state.seen += 1

        if fld is None:  # nothing to see: carry the rows with the turn only
            if not first:
                state.R = self._carry(state.R, np.asarray(dR_cam))
                _, rows = self.catalog.tree.query(state.R[:, 2, :])
                state.rows = rows.astype(np.int64)
            steps.append(Step("skip", f"frame {k}: no star to designate; the posterior is unchanged",
                              numbers={"frame": k}))
            result.reason = "no star in the frame"
            self._finish_stats(state, search, fld)
            return result

        steps.append(Step("statistics",
                          f"frame {k}: designated star {fld.designated}"
                          f"{' (nearest the boresight)' if designated is None else ''}, "
                          f"{int(fld.x[0])} stars: mu_m {fld.x[1]:.2f}, sigma_m {fld.x[2]:.2f}, "
                          f"mu_d {np.degrees(fld.x[3]):.2f} deg, sigma_d {np.degrees(fld.x[4]):.2f} deg, "
                          f"sigma_theta {fld.x[5]:.3f} rad",
                          observed=fld.used.tolist(),
                          numbers={"frame": k, "designated": fld.designated,
                                   **{f"x_{n}": float(v) for n, v in zip(STAT_NAMES, self._report_x(fld.x))}}))

        # likelihood (eq. 5) and the recursion (eq. 3)
        if first and self.hypothesis == "boresight":  # row r: the boresight is on catalog star r
            state.R = self._boresight_attitudes(state.rows)
            loglik = self._log_likelihood(fld, state.rows)
        elif first:  # row r: the designated star is catalog star r; its roll from its field
            psi, _ = self._vote(state.rows, fld, sigma)
            state.R = self._attitudes(state.rows, psi, fld)
            loglik = self._log_likelihood(fld, state.rows)
        else:
            loglik, resid = self._predict(state, fld, np.asarray(dR_cam), sigma, steps, k)
            if self.prediction_likelihood:
                loglik = loglik - 0.5 * (resid / self._prediction_sigma(sigma)) ** 2
        lp = loglik + state.log_post
        state.log_post = lp - logsumexp(lp)
        state.frames += 1
        self._posterior_step(state, fld, steps, k)
        self._refine(state, V, fld, sigma)

        # identification
        result.status = INCONCLUSIVE
        search.data.update(state=state, field=fld, frame=k)
        if not self.drive(search, self.hypotheses(search)):
            result.reason = self.failure_reason(search)
        state.verifications = search.n_hypotheses
        self._finish_stats(state, search, fld)
        return result

    def designated_star(self, R: np.ndarray) -> int:
        """The paper's f: the catalog row nearest the boresight of attitude R."""
        R = np.asarray(R, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise BadInput("an attitude must be a finite 3x3 matrix")
        return int(self.catalog.tree.query(R[2])[1])

    # ------------------------------------------------------------------ pieces
    def _magnitudes(self, obs: Observation) -> np.ndarray:
        b = np.asarray(obs.brightness, dtype=np.float64).reshape(-1)
        b = np.where(np.isfinite(b) & (b > 0), b, 1e-30)
        return (0.0 if self.mag_zero_point is None else self.mag_zero_point) - 2.5 * np.log10(b)

    def _field(self, obs: Observation, V: np.ndarray, designated: int | None = None) -> _Field | None:
        if len(V) == 0:
            return None
        m = self._magnitudes(obs)
        if len(m) != len(V):
            raise BadInput("brightness must have one value per observed star")
        use = np.arange(len(V))
        if self.mag_cut is not None:
            use = use[m <= self.mag_cut]
        if len(use) == 0:
            return None
        if designated is None:
            dsg = int(use[np.argmax(V[use, 2])])
        else:
            dsg = int(designated)
            if dsg not in set(use.tolist()):
                raise BadInput(f"designated star {designated} is not one of the observed stars in the statistics")
        others = use[use != dsg]
        v_d = V[dsg]
        a1, a2 = observed_basis(v_d)
        d, phi = position_angles(v_d, V[others], a1, a2)
        x = field_statistics(m[dsg], m[others], d, phi)
        if self.mag_zero_point is None:
            x[1] -= m[dsg]  # relative to the designated star: the unknown zero point cancels
        return _Field(designated=dsg, used=np.concatenate([[dsg], others]).astype(np.int64), v_d=v_d, a1=a1,
                      a2=a2, d=d, phi=phi, m=m[others], m_d=float(m[dsg]), x=x)

    def _report_x(self, x: np.ndarray) -> np.ndarray:
        """x in the paper's units (degrees for distances) for people."""
        y = x.copy()
        y[3:5] = np.degrees(y[3:5])
        return y

    def _xi(self, rows: np.ndarray) -> np.ndarray:
        xi = self.xi[rows].copy()
        if self.mag_zero_point is None:
            xi[:, 1] -= self.mag[rows]
        return xi

    def _log_likelihood(self, fld: _Field, rows: np.ndarray) -> np.ndarray:
        """log p(x | s) of eq. 5 up to the constant (which cancels in eq. 3)."""
        dx = fld.x[None, :] - self._xi(rows)
        return -0.5 * np.sum(dx * dx * self.q_inv[None, :], axis=1)

    def _prediction_sigma(self, sigma: float) -> float:
        """Spread of the registration residual: two stars' noise plus a few degrees of roll error."""
        return float(np.hypot(np.sqrt(2.0) * sigma, np.radians(0.5)))

    def _vote(self, rows: np.ndarray, fld: _Field, sigma: float) -> tuple[np.ndarray, np.ndarray]:
        """The roll psi of each row (phi_observed = phi_catalog + psi) from its field, and the vote
        weight behind it (0 and 0 where no pair of neighbours agrees)."""
        H = len(rows)
        psi = np.zeros(H)
        score = np.zeros(H)
        K = len(fld.d)
        if K == 0 or H == 0:
            return psi, score
        t_d = self.radius_sigmas * sigma
        t_m = self.radius_sigmas * self.sigma_mag
        m_rel = fld.m - (fld.m_d if self.mag_zero_point is None else 0.0)
        d_ref = max(float(np.median(fld.d)), 1e-6)
        s_psi = np.sqrt(2.0) * sigma / d_ref  # roll spread of one vote at the typical distance
        binw = 2.0 * np.pi / N_BINS
        starts, stops = self.nb_offsets[rows], self.nb_offsets[rows + 1]
        lens = stops - starts
        chunk_pairs = 2_000_000
        h0 = 0
        while h0 < H:
            # rows h0..h1 whose neighbour lists x K observed neighbours fit in one chunk
            cum = np.cumsum(lens[h0:]) * K
            h1 = h0 + max(1, int(np.searchsorted(cum, chunk_pairs, side="right")))
            h1 = min(h1, H)
            L = lens[h0:h1]
            hh = np.repeat(np.arange(h0, h1), L)
            pos = np.repeat(starts[h0:h1] - np.concatenate([[0], np.cumsum(L)[:-1]]), L) + np.arange(int(L.sum()))
            cd, cphi = self.nb_d[pos], self.nb_phi[pos]
            cm = self.mag[self.nb_index[pos]]
            if self.mag_zero_point is None:
                cm = cm - self.mag[rows[hh]]
            # pair every catalog neighbour with every observed neighbour
            dd = fld.d[None, :] - cd[:, None]
            dm = m_rel[None, :] - cm[:, None]
            ok = (np.abs(dd) <= t_d) & (np.abs(dm) <= t_m)
            ci, oi = np.nonzero(ok)
            h0_next = h1
            if len(ci):
                w = np.exp(-0.25 * (dd[ci, oi] / sigma) ** 2 - 0.25 * (dm[ci, oi] / self.sigma_mag) ** 2)
                vote = np.mod(fld.phi[oi] - cphi[ci], 2.0 * np.pi)
                hr = hh[ci] - h0
                n_rows = h1 - h0
                hist = np.zeros((n_rows, N_BINS))
                np.add.at(hist, (hr, np.minimum((vote / binw).astype(np.int64), N_BINS - 1)), w)
                ker_s = max(s_psi / binw, 0.5)
                half = int(min(N_BINS // 2, np.ceil(3 * ker_s)))
                offs = np.arange(-half, half + 1)
                ker = np.exp(-0.5 * (offs / ker_s) ** 2)
                kern = np.zeros(N_BINS)
                kern[np.mod(offs, N_BINS)] += ker
                sm = np.fft.irfft(np.fft.rfft(hist, axis=1) * np.fft.rfft(kern)[None, :], n=N_BINS, axis=1)
                centre = ((np.argmax(sm, axis=1) + 0.5) * binw)[hr]
                win = max(3.0 * s_psi, 2.0 * binw)
                near = np.abs(_wrap(vote - centre)) <= win
                sw = np.zeros(n_rows)
                ss = np.zeros(n_rows)
                sc = np.zeros(n_rows)
                np.add.at(sw, hr[near], w[near])
                np.add.at(ss, hr[near], w[near] * np.sin(vote[near]))
                np.add.at(sc, hr[near], w[near] * np.cos(vote[near]))
                have = sw > 0
                idx = np.arange(h0, h1)
                psi[idx[have]] = np.arctan2(ss[have], sc[have])
                score[idx] = sw
            h0 = h0_next
        return psi, score

    def _attitudes(self, rows: np.ndarray, psi: np.ndarray, fld: _Field) -> np.ndarray:
        """R for each row: catalog star rows[i] on the observed designated star, roll psi[i]."""
        c, s = np.cos(psi)[:, None], np.sin(psi)[:, None]
        col0 = c * fld.a1[None] + s * fld.a2[None]
        col1 = -s * fld.a1[None] + c * fld.a2[None]
        e, n, v = self.east[rows], self.north[rows], self.catalog.xyz[rows]
        return (col0[:, :, None] * e[:, None, :] + col1[:, :, None] * n[:, None, :]
                + fld.v_d[None, :, None] * v[:, None, :])

    def _boresight_attitudes(self, rows: np.ndarray) -> np.ndarray:
        """R for each row with catalog star rows[i] on the boresight (roll 0: x east, y north)."""
        return np.stack([self.east[rows], self.north[rows], self.catalog.xyz[rows]], axis=1)

    def _carry(self, R: np.ndarray, turn: np.ndarray) -> np.ndarray:
        """Attitudes after the known turn: dR_cam @ R (camera frame), or R @ T^T (inertial, boresight)."""
        return R @ turn.T[None] if self.hypothesis == "boresight" else turn[None] @ R

    def _predict(self, state: StochasticState, fld: _Field, dR_cam: np.ndarray, sigma: float,
                 steps: list[Step], k: int) -> tuple[np.ndarray, np.ndarray]:
        """Carry every row to this frame with the known turn, register its new designated star and
        return its log-likelihood log p(x_k | s_k) and its registration residual: the angle between
        the observed designated star, seen through the row's attitude, and the row's star.

        The row's attitude becomes dR_cam @ R. registration="boresight" (the paper): the new
        designated star is f of the row's predicted boresight, the catalog star nearest it.
        registration="designated": the candidates are the N_REGISTER catalog stars nearest the
        direction R^T v_d at which the OBSERVED designated star points under the row, weighted by
        how well they fit it in position (sqrt(2) sigma: the star's noise and the attitude's) and,
        with a zero point, in magnitude (sigma_mag); the row's likelihood is the weighted sum over
        them and its star the one that explains x best. With small noise one candidate takes all
        the weight and both rules agree; with the paper's 1 deg noise two stars 1-2 deg apart cannot
        be told apart by position."""
        before = state.rows.copy()
        Rp = self._carry(state.R, dR_cam)
        H = len(Rp)
        target = np.einsum("hji,j->hi", Rp, fld.v_d)  # R^T v_d
        state.R = Rp
        if self.registration == "boresight":
            _, rows = self.catalog.tree.query(Rp[:, 2, :])
            state.rows = rows.astype(np.int64)
            loglik = self._log_likelihood(fld, state.rows)
            # boresight hypotheses have no roll: their residual is the boresight's distance to its star
            resid = angular_distance(Rp[:, 2, :] if self.hypothesis == "boresight" else target,
                                     self.catalog.xyz[state.rows])
        else:
            kq = min(N_REGISTER, self.n_catalog)
            dist, idx = self.catalog.tree.query(target, k=kq)
            dist, idx = dist.reshape(H, kq), idx.reshape(H, kq).astype(np.int64)
            ang = 2.0 * np.arcsin(np.clip(dist / 2.0, 0.0, 1.0))
            score = -0.5 * (ang / (np.sqrt(2.0) * sigma)) ** 2
            if self.mag_zero_point is not None:
                score = score - 0.5 * ((fld.m_d - self.mag[idx]) / self.sigma_mag) ** 2
            joint = score - logsumexp(score, axis=1, keepdims=True) \
                + self._log_likelihood(fld, idx.ravel()).reshape(H, kq)
            pick = np.argmax(joint, axis=1)
            h = np.arange(H)
            state.rows = idx[h, pick]
            loglik = logsumexp(joint, axis=1)
            resid = ang[h, pick]
        top = int(np.argmax(state.log_post))
        steps.append(Step("predict",
                          f"frame {k}: the known turn carried the {H} hypotheses to their next "
                          f"designated stars ({len(np.unique(state.rows))} distinct); under the leading one the "
                          f"{'boresight' if self.hypothesis == 'boresight' else 'observed designated star'} lands "
                          f"{np.degrees(resid[top]):.2f} deg from its star",
                          observed=[fld.designated],
                          catalog=[int(r) for r in state.rows[np.argsort(-state.log_post)[:TOP_K]]],
                          numbers={"frame": k, "distinct": int(len(np.unique(state.rows))),
                                   "moved": int(np.sum(state.rows != before)),
                                   "turn_deg": float(np.degrees(np.arccos(np.clip((np.trace(dR_cam) - 1) / 2,
                                                                                  -1, 1)))),
                                   "residual_leading_deg": float(np.degrees(resid[top])),
                                   "residual_median_deg": float(np.degrees(np.median(resid)))}))
        return loglik, resid

    def _fit(self, R: np.ndarray, s: int, V: np.ndarray, tree: cKDTree | None, sigma: float,
             passes: int = 2) -> np.ndarray:
        """Fit a row's attitude to the whole field: the catalog star s and its neighbours, predicted
        with R, are matched one to one (nearest first, within 3 sqrt(2) sigma) to the observed
        stars V, and R is re-estimated from the matches (Wahba's problem, Markley's SVD), twice."""
        if tree is None:
            return R
        cand = np.concatenate([[s], self.nb_index[self.nb_offsets[s]:self.nb_offsets[s + 1]]])
        r = self.catalog.xyz[cand]
        c_rad = float(chord(match_radius(sigma, self.radius_sigmas)))
        for _ in range(passes):
            d, j = tree.query(r @ R.T, distance_upper_bound=c_rad)
            ok = np.flatnonzero(np.isfinite(d))
            if len(ok) < 2:
                break
            ok = ok[np.argsort(d[ok], kind="stable")]
            _, first = np.unique(j[ok], return_index=True)
            ok = ok[first]
            if len(ok) < 2:
                break
            B = V[j[ok]].T @ r[ok]
            U, _, Vt = np.linalg.svd(B)
            R = U @ np.diag([1.0, 1.0, np.linalg.det(U) * np.linalg.det(Vt)]) @ Vt
        return R

    def _refine(self, state: StochasticState, V: np.ndarray, fld: _Field, sigma: float) -> None:
        """Fit the attitude of the leading rows to this frame's field (all its stars, not just the
        designated one): the prediction of the next frame then rests on the whole field. Boresight
        hypotheses (the paper's literal model) are not refined."""
        if self.hypothesis == "boresight":
            return
        Vu = V[fld.used]
        tree = cKDTree(Vu) if len(Vu) >= 2 else None
        floor = np.log(REFINE_FLOOR / self.n_catalog)
        lead = np.argsort(-state.log_post)[:REFINE_TOP]
        for r in lead[state.log_post[lead] >= floor]:
            state.R[r] = self._fit(state.R[r], int(state.rows[r]), Vu, tree, sigma)

    def marginal(self, state: StochasticState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The posterior of each current designated star: rows that reached the same star (different
        histories, Table 1) add up. Returns (stars, mass, best row of each star), by mass, largest first."""
        post = state.posterior
        stars, inv = np.unique(state.rows, return_inverse=True)
        mass = np.bincount(inv, weights=post, minlength=len(stars))
        best = np.full(len(stars), -1, dtype=np.int64)
        order_rows = np.argsort(-state.log_post, kind="stable")
        first = np.full(len(stars), True)
        for r in order_rows:  # highest-posterior row of each star
            j = inv[r]
            if first[j]:
                best[j] = r
                first[j] = False
        o = np.argsort(-mass, kind="stable")
        return stars[o], mass[o], best[o]

    def _posterior_step(self, state: StochasticState, fld: _Field, steps: list[Step], k: int) -> None:
        N = self.n_catalog
        stars, mass, best = self.marginal(state)
        top = slice(0, TOP_K)
        above = int(np.sum(mass > 1.0 / N))
        numbers = {"frame": k, "above_prior": above, "top_posterior": float(mass[0]),
                   "top_row": int(stars[0]), "top_hip": int(self.catalog.hip[stars[0]])}
        note = (f"frame {k}: {above} of {N} stars above the prior 1/{N}; leading HIP "
                f"{numbers['top_hip']} at {numbers['top_posterior']:.3f}")
        steps.append(Step("update", note, observed=[fld.designated],
                          catalog=[int(c) for c in stars[top]],
                          numbers=numbers,
                          layers=(Posterior(state.posterior.astype(np.float64), state.rows.astype(np.int32),
                                            stars[top].copy(), mass[top].copy(), self._xi(stars[top])),)))
        state.history.append({kk: v for kk, v in numbers.items()} | {"designated": fld.designated})

    def hypotheses(self, search: Search):
        """The leading star when it dominates (and, with verify_top, the leading stars once a known turn
        has been survived): each one's hypotheses (`_match`), for the shared verification. The frame's
        state, field and number are in `search.data` (`update` puts them there)."""
        state, fld, k = search.data["state"], search.data["field"], search.data["frame"]
        stars, mass, best = self.marginal(state)
        cand = [0] if mass[0] >= self.p_identify else []
        if state.frames >= 2:  # verify_top: only hypotheses that have survived a known turn
            for j in range(min(self.verify_top, len(stars))):
                if j not in cand:
                    cand.append(j)
        if not cand:
            search.reasons.append(f"no star dominates yet: the leading one, HIP {int(self.catalog.hip[stars[0]])}, "
                                  f"has posterior {mass[0]:.3f} < p_identify {self.p_identify:g}")
            return
        m_obs = self._magnitudes(search.obs)
        for j in cand:
            why = yield from self._match(search, state, int(best[j]), m_obs, fld, k, float(mass[j]))
            search.reasons.append(why)

    def _pair_count(self, s: int, fld: _Field, sigma: float) -> int:
        """How many two-star hypotheses (the designated star on s, one observed neighbour on one of
        s's catalog neighbours) pass the distance and magnitude gates of the roll vote: the search
        behind a row's attitude, counted in the verification's Bonferroni factor."""
        a, b = self.nb_offsets[s], self.nb_offsets[s + 1]
        if b == a or len(fld.d) == 0:
            return 1
        cm = self.mag[self.nb_index[a:b]]
        m_rel = fld.m
        if self.mag_zero_point is None:
            cm = cm - self.mag[s]
            m_rel = fld.m - fld.m_d
        ok = ((np.abs(fld.d[None, :] - self.nb_d[a:b, None]) <= self.radius_sigmas * sigma)
              & (np.abs(m_rel[None, :] - cm[:, None]) <= self.radius_sigmas * self.sigma_mag))
        return max(1, int(ok.sum()))

    def magnitude_consistency(self, m_obs: np.ndarray, matches: dict[int, int]) -> float:
        """P(chi^2 >= observed) of the matched stars' magnitude differences (sigma_mag each, clipped at
        MAG_CLIP sigmas against saturation; relative to their mean without a zero point). A rotation
        that maps a near-symmetric group of stars onto itself passes a purely geometric check but puts
        stars on catalog stars of other magnitudes."""
        o = np.array(sorted(matches), dtype=np.int64)
        dm = m_obs[o] - self.mag[[matches[i] for i in o]]
        dof = len(dm)
        if self.mag_zero_point is None:
            dm = dm - dm.mean()
            dof -= 1
        if dof <= 0:
            return 1.0
        return float(chi2.sf(np.sum(np.minimum((dm / self.sigma_mag) ** 2, MAG_CLIP ** 2)), dof))

    def _match(self, search: Search, state: StochasticState, r: int, m_obs: np.ndarray, fld: _Field, k: int,
               p: float):
        """Match the neighbours with the attitude of row r and yield the hypotheses (the designated star
        and a matched neighbour, farthest first; the other stars test it). The Bonferroni factor grows
        by the row's two-star hypotheses (`_pair_count`), and a verified match must also agree in
        magnitude (`magnitude_consistency`). Returns why the row did not verify."""
        V, sigma, steps = search.V, search.sigma, search.steps
        s = int(state.rows[r])
        R = state.R[r]
        if self.hypothesis == "boresight":  # no roll yet: put s on the designated star, roll from the field
            psi, _ = self._vote(np.array([s]), fld, sigma)
            R = self._attitudes(np.array([s]), psi, fld)[0]
        rad = match_radius(sigma, self.radius_sigmas)
        matches = {fld.designated: s}
        for radius in (2.0 * rad, rad):
            cat_rows = frame_stars(self.catalog, self.camera, R, margin_rad=radius)
            if len(cat_rows) == 0:
                break
            qi, rj, _, amb = match_one_to_one(V, self.catalog.xyz[cat_rows] @ R.T, radius)
            ambiguous = set(amb.tolist())
            # the designated star is s under this hypothesis: no other observed star may take s
            matches = {int(o): int(cat_rows[j]) for o, j in zip(qi, rj) if o not in ambiguous and cat_rows[j] != s}
            matches[fld.designated] = s
            if len(matches) >= 2:
                idx = np.array(sorted(matches))
                R = svd_attitude(V[idx], self.catalog.xyz[[matches[i] for i in idx]], sigma).R
        others = [o for o in matches if o != fld.designated]
        steps.append(Step("match", f"frame {k}: hypothesis HIP {int(self.catalog.hip[s])} (posterior {p:.3f}) "
                                   f"matches {len(others)} neighbours within {rad * RAD_TO_ARCSEC:.0f}\"",
                          observed=sorted(matches), catalog=[matches[o] for o in sorted(matches)],
                          numbers={"frame": k, "row": r, "posterior": p, "matched": len(matches)}))
        if not others:
            return f"HIP {int(self.catalog.hip[s])}: no neighbour matches its attitude"
        dist = angular_distance(V[others], fld.v_d[None, :])
        count = max(self._pair_count(s, fld, sigma), self.max_verify)  # counted once for the row's pairs

        def magnitudes(ver):  # a verified match must also agree in magnitude
            if not ver.passed:
                return {"frame": k, "p_magnitudes": float("nan")}, {}
            p_mag = self.magnitude_consistency(m_obs, ver.matches)
            if p_mag < MAG_CONSISTENCY_P:
                ver.passed = False
                ver.reason = (f"the geometry agrees ({ver.reason}) but the magnitudes do not: "
                              f"P(chi^2) = {p_mag:.1e} < {MAG_CONSISTENCY_P:g}")
            return {"frame": k, "p_magnitudes": p_mag}, {"p_magnitudes": p_mag}

        def carry(ver):  # the verified attitude carries on to the next frame
            state.R[r] = ver.R

        why = ""
        for j in np.argsort(-dist)[:self.max_verify]:
            o2 = int(others[j])
            ver = yield Hypothesis({fld.designated: s, o2: matches[o2]}, count=count, judge=magnitudes, on_accept=carry)
            count = 0
            why = f"HIP {int(self.catalog.hip[s])}: verification failed: {ver.reason}"
        return why

    def _finish_stats(self, state: StochasticState, search: Search, fld: _Field | None) -> None:
        stars, mass, _ = self.marginal(state)
        top = slice(0, TOP_K)
        search.result.stats = {
            "frame": state.seen - 1,
            "stars": 0 if fld is None else int(len(fld.used)),
            "designated": None if fld is None else fld.designated,
            "x": None if fld is None else self._report_x(fld.x).tolist(),
            "above_prior": int(np.sum(mass > 1.0 / self.n_catalog)),
            "top_posterior": float(mass[0]),
            "top_rows": [int(c) for c in stars[top]],
            "top_hips": [int(self.catalog.hip[c]) for c in stars[top]],
            "posterior_top": [float(p) for p in mass[top]],
            "verifications": state.verifications,
            "sigma_rad": search.sigma,
            "time_s": time.perf_counter() - search.t0,
        }
