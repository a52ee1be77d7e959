"""What every identification method shares: its input, its step record, its result and the template
every method runs in.

The template (`Identifier.identify`) owns the common path: the frame's sigma (the observation's, else
the method's), the input checks, the too-few-stars exit with the method's minimum, timing into
stats["time_s"], verifying each hypothesis the method proposes with the running hypothesis count (the
Bonferroni factor of `skyview.identify.verify`), accepting a verified one, and the failure reason. A
method writes `hypotheses(search)`: a generator that records its own steps in `search.steps` and
yields `Hypothesis` records; each yield is answered with the `Verification` of that hypothesis (so
the method can react: try the next orientation, blame a star, collect several); an accepted one ends
the search (the hypothesis' `on_accept` sees it). A method that must
choose among verified hypotheses itself yields the chosen `Verification` instead (it is accepted).
A hypothesis is verified on the search's terms (the observed vectors, the method's catalog, camera and
sigma) unless it brings its own `VerificationFrame`: the blind search's, for one, is a camera fitted to
the hypothesis' stars, the catalog to the frame's depth and the measured noise. Every source of
hypotheses (the six methods, the blind search, a calibrated answer refitted) ends in this one
verification and this one `Identification`.

Nothing in `skyview.identify` imports viser or rerun: the viewer and the recorder draw the steps.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from skyview.core.errors import BadInput
from skyview.core.jsonable import plain
from skyview.identify.layers import Layer
from skyview.identify.steps import Step


class Status(StrEnum):
    """The outcome of one identification (a `str`: JSON and comparisons see "identified", ...).

    IDENTIFIED: a hypothesis passed the shared verification. INCONCLUSIVE: the method ran and found
    no unique verified hypothesis. FAILED: the method could not run on this frame (too few stars,
    nothing to designate). A pipeline or sequence result that says "failed" means "not solved" (either
    of the last two): that word belongs to `skyview.solver.api.Solution`, not to this enum.
    """

    IDENTIFIED = "identified"
    INCONCLUSIVE = "inconclusive"
    FAILED = "failed"


IDENTIFIED = Status.IDENTIFIED
INCONCLUSIVE = Status.INCONCLUSIVE
FAILED = Status.FAILED


@dataclass(frozen=True)
class Observation:
    """Observed stars of one frame, brightest first.

    vectors: (N, 3) camera-frame unit vectors; uv: (N, 2) pixels; brightness: (N,) summed
    background-subtracted intensity (used as rank / relative magnitude only); sigma_rad: the 1-sigma
    direction error of one star (the paper's sigma). window_sr: (N,) the solid angle of the window each
    star was found in, for a frame measured in windows only (a tracker's: the verification then takes a
    star's chance of agreeing by accident within its window); None for a whole frame.
    """

    vectors: np.ndarray
    uv: np.ndarray
    brightness: np.ndarray
    sigma_rad: float
    window_sr: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.vectors.shape[0])


@dataclass(frozen=True)
class PixelStars:
    """Detected stars of a width x height image whose camera is not known (a blind search's input), brightest
    first: uv (N, 2) pixels. No vectors: the camera that would give them is what the search finds."""

    uv: np.ndarray
    width: int
    height: int
    vectors = None
    sigma_rad = None
    window_sr = None

    def __len__(self) -> int:
        return int(len(self.uv))


@dataclass(frozen=True)
class VerificationFrame:
    """What a hypothesis is verified on when not the search's own: the observed stars' `vectors` through
    `camera` (e.g. a camera fitted to the hypothesis' stars), `catalog` (e.g. the method's catalog to the
    frame's depth), `sigma_rad` (e.g. measured from the fit's residuals). `parent_rows[k]`: row k of that
    catalog as a row of the method's own catalog (the step and the result are told in those rows); None
    when it is the method's catalog."""

    vectors: np.ndarray
    catalog: Any
    camera: Any
    sigma_rad: float
    parent_rows: np.ndarray | None = None


@dataclass
class Identification:
    """The outcome of one identification.

    status: IDENTIFIED (verified), INCONCLUSIVE (no unique verified hypothesis) or FAILED (could not
    run: too few stars, ...). matches: observed index -> catalog row, only when identified (after
    verification, extended to every observed star that agrees). R: attitude when identified. When the
    method verified on a camera, a depth or a noise of its own finding (the blind search, a refit): the
    fitted `camera`, the catalog's `mag_limit` and the measured `sigma_rad` (None otherwise: the method's
    own camera and sigma hold).
    """

    method: str
    status: Status
    matches: dict[int, int]
    steps: list[Step]
    reason: str = ""
    R: np.ndarray | None = None
    attitude_covariance: np.ndarray | None = None
    verification: dict[str, Any] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    database_key: str = ""
    camera: Any = None
    mag_limit: float | None = None
    sigma_rad: float | None = None

    @property
    def identified(self) -> bool:
        return self.status == IDENTIFIED

    def accept(self, verification) -> None:
        """Take a verification that passed (`verify.Verification`): identified, with its matches
        (every observed star that agrees), its attitude and covariance; no failure reason."""
        self.status = IDENTIFIED
        self.matches = verification.matches
        self.R = verification.R
        self.attitude_covariance = verification.covariance
        self.reason = ""

    def to_dict(self) -> dict:
        """JSON-ready summary (steps included)."""
        return {
            "method": self.method, "status": self.status, "reason": self.reason,
            "matches": {str(int(k)): int(v) for k, v in sorted(self.matches.items())},
            "R": None if self.R is None else np.asarray(self.R).tolist(),
            "attitude_covariance": (None if self.attitude_covariance is None
                                    else np.asarray(self.attitude_covariance).tolist()),
            "verification": plain(self.verification), "stats": plain(self.stats),
            "database_key": self.database_key, "steps": [s.to_dict() for s in self.steps],
        }


@dataclass
class Hypothesis:
    """A correspondence a method proposes (observed index -> catalog row), for the shared verification.

    count: how many hypotheses this one stands for in the Bonferroni factor (1; a method that picked
    it among many pair hypotheses counts them all). frame: what it is verified on, when not the search's
    (`VerificationFrame`). prediction: a tracker's `skyview.identify.tracking.Prediction` when the
    hypothesis is a predicted attitude, not stars of this frame (`matches`: the stars on their predicted
    places; `verify.verify_prediction`: every observed star tests it). numbers / groups / layers: what the 'verify' step
    shows beside the verification's own figures. judge: an optional check run on the verification
    before it is recorded (it may refuse a verified hypothesis: set `ver.passed = False` and the
    reason), returning (extra numbers for the step, extra figures for the verification record). accept: False
    when the method decides among verified hypotheses itself (it then yields the chosen Verification).
    on_accept: called with the verification when this hypothesis is accepted (the search then ends).
    """

    matches: dict[int, int]
    count: int = 1
    numbers: dict[str, float] = field(default_factory=dict)
    groups: list[tuple[int, ...]] = field(default_factory=list)
    layers: tuple[Layer, ...] = ()
    judge: Callable[[Any], tuple[dict, dict]] | None = None
    accept: bool = True
    on_accept: Callable[[Any], None] | None = None
    frame: VerificationFrame | None = None
    prediction: Any = None


@dataclass
class Search:
    """One identification in progress: what the template gives a method's `hypotheses` and keeps.

    obs, V ((N, 3) float64 vectors), n, sigma (this frame's), radius (the match radius); steps (the
    method appends its own), stats (the method fills them; "time_s" is added), reasons (why
    hypotheses failed: the default failure reason), verifications (hypotheses verified) and
    n_hypotheses (the Bonferroni factor so far), result (the Identification being built), data (the
    method's own working values, e.g. what its `too_few` computed).
    """

    obs: Any
    V: np.ndarray
    sigma: float
    radius: float
    result: Identification
    t0: float
    # the thread's CPU clock at the start: what a method's time budget counts (`BlindParams.time_budget_s`), so
    # that a disk slow to page a database in, or another process on the cores, does not cut a search short
    cpu0: float = field(default_factory=time.thread_time)
    stats: dict[str, Any] = field(default_factory=dict)
    reasons: list[str] = field(default_factory=list)
    verifications: int = 0
    n_hypotheses: int = 0
    data: dict[str, Any] = field(default_factory=dict)  # the method's own working values
    # (matches, Verification): this search's first hypothesis verified already (`identify_batch`'s), taken
    # by the search's first verification when it is of those matches (a plain hypothesis: count 1, no frame
    # or prediction of its own) instead of verifying them again
    first_verified: tuple[dict[int, int], Any] | None = None

    @property
    def n(self) -> int:
        return int(len(self.obs))

    @property
    def steps(self) -> list[Step]:
        return self.result.steps


_SHARED_PARAMS = ("statistic", "threshold", "radius_sigmas")  # skyview.identify.params.MethodParams
HypothesisSource = Generator["Hypothesis | Any", Any, None]


class Identifier(ABC):
    """An identification method bound to its database (catalog + camera configuration).

    A method sets `name`, `Params` (its frozen parameter dataclass: `skyview.identify.params`),
    `min_stars`, fills `database_key` (the key dict its database was built for; see
    `skyview.identify.database`) and `database_info` (counts, bytes, build / load time), and writes
    `hypotheses(search)`; `identify` (the template, above) does the rest and ends every hypothesis in
    the shared verification (`skyview.identify.verify.verify`; a tracker's predicted attitude in
    `verify.verify_prediction`). Hooks with defaults: `too_few` (the too-few-stars exit),
    `failure_reason`, `n_patterns` (the database size the tetra3 statistic divides by).
    """

    name: str = ""
    Params: type | None = None  # the frozen dataclass of the method's parameters (paper defaults)
    min_stars: int = 3  # fewer observed stars than this: FAILED, "too few stars"
    title: str = ""  # the method in a sentence ("the angle method"), for the too-few-stars reason
    # the scenario of the method's paper (`skyview.simulate.scenarios`): the conditions it was published
    # under, the bench's and the example recording's default for it, what a result is compared with
    paper_scenario: str | None = None
    slow: bool = False  # an identification takes seconds: a comparison runs it on fewer images
    # Options beyond the paper that make the method better; `variant="improved"` applies them.
    improved_params: dict = {}
    database_key: dict
    database_info: dict
    catalog: Any
    camera: Any
    sigma_rad: float
    statistic: str
    threshold: float | None
    radius_sigmas: float

    @classmethod
    def parameters(cls) -> dict[str, Any]:
        """The method's parameters and their paper defaults: its `Params` fields (or, for a method not
        yet on a Params dataclass, its constructor's keyword-only arguments)."""
        if cls.Params is not None:  # the method's own first, then the verification's (MethodParams)
            fields = sorted(dataclasses.fields(cls.Params), key=lambda f: f.name in _SHARED_PARAMS)
            return {f.name: (f.default if f.default is not dataclasses.MISSING else f.default_factory())
                    for f in fields}
        sig = inspect.signature(cls.__init__)
        return {n: p.default for n, p in sig.parameters.items() if p.kind == inspect.Parameter.KEYWORD_ONLY}

    def configure(self, catalog, camera, sigma_rad: float, params: dict):
        """The common head of a constructor: `Params(**params)` (its checks: one-line BadInput), each
        parameter set as an attribute, the sigma checked, the catalog and camera kept. Returns the Params."""
        from skyview.identify.params import bind, check_sigma

        p = self.Params(**params)
        self.sigma_rad = check_sigma(sigma_rad)
        bind(self, p)
        self.catalog, self.camera = catalog, camera
        return p

    @property
    def database_key_string(self) -> str:
        """`database.key_string(database_key)`, computed once per key dict (a SHA-256, ~60 us: every
        identify records it)."""
        key = self.database_key
        if not key:  # no database of its own (a refit, a tracked frame)
            return ""
        cached = self.__dict__.get("_key_string_of")
        if cached is None or cached[0] is not key:
            from skyview.identify import database

            cached = self.__dict__["_key_string_of"] = (key, database.key_string(key))
        return cached[1]

    @property
    def n_patterns(self) -> int:
        """Patterns in the database (the tetra3 statistic divides its threshold by this)."""
        return 1

    # ------------------------------------------------------------------ the template
    def identify(self, obs: Observation) -> Identification:
        """Identify the observed stars of one frame (the template: see the module docstring)."""
        return self.run(self.begin(obs))

    def run(self, search: Search, source: HypothesisSource | None = None) -> Identification:
        """The too-few-stars exit, then every hypothesis of `source` (default: the method's `hypotheses`)
        verified until one is accepted, then the result."""
        reason = self.too_few(search)
        if reason:
            return self.finish(search, reason=reason)
        search.result.status = INCONCLUSIVE
        self.drive(search, self.hypotheses(search) if source is None else source)
        return self.finish(search)

    @abstractmethod
    def hypotheses(self, search: Search) -> HypothesisSource:
        """The method's search: record steps in `search.steps`, fill `search.stats`, yield `Hypothesis`
        records (each answered with its Verification) or a chosen passed Verification."""

    def begin(self, obs: Observation | PixelStars) -> Search:
        """The frame's sigma (the observation's when it is a positive number, else the method's), the
        checked vectors (none for `PixelStars`) and an empty result (FAILED until the search runs)."""
        match_radius = (_VERIFY or _verify_module()).match_radius
        t0 = time.perf_counter()
        s = obs.sigma_rad
        sigma = float(s) if (s is not None and math.isfinite(s) and s > 0) else self.sigma_rad
        V = np.zeros((0, 3)) if obs.vectors is None else np.asarray(obs.vectors, dtype=np.float64)
        if obs.vectors is not None and len(obs) and (V.ndim != 2 or V.shape[1] != 3 or not np.isfinite(V).all()):
            raise BadInput(f"observed vectors must be a finite (N, 3) array, not shape {V.shape}")
        result = Identification(method=self.name, status=FAILED, matches={}, steps=[],
                                database_key=self.database_key_string)
        return Search(obs=obs, V=V.reshape(-1, 3), sigma=sigma, radius=match_radius(sigma, self.radius_sigmas),
                      result=result, t0=t0)

    def too_few(self, search: Search) -> str:
        """Why the frame is too small to try (then FAILED), or ''."""
        if search.n < self.min_stars:
            return f"{self.title or f'the {self.name} method'} needs at least {self.min_stars} stars, " \
                   f"the frame has {search.n}"
        return ""

    def verify(self, search: Search, hyp: Hypothesis):
        """The shared verification of one hypothesis, counted in the Bonferroni factor, recorded as a
        'verify' step; `result.verification` keeps its figures. On the search's terms, or on the
        hypothesis' own `frame` (its matches then told in the method's catalog rows)."""
        mod = _VERIFY or _verify_module()
        ver = self.verification(search, hyp)
        on, hypothesis = hyp.frame, hyp.matches
        if on is not None and on.parent_rows is not None:
            hypothesis = {o: int(on.parent_rows[c]) for o, c in hyp.matches.items()}
        numbers, record = hyp.judge(ver) if hyp.judge is not None else ({}, {})
        vd = ver.to_dict()
        search.steps.append(mod.verification_step(ver, hypothesis, numbers={**hyp.numbers, **numbers}, vd=vd,
                                                  groups=list(hyp.groups), layers=tuple(hyp.layers)))
        if record:
            vd |= record
        search.result.verification = vd
        return ver

    def verification(self, search: Search, hyp: Hypothesis):
        """The shared verification of one hypothesis, counted in the Bonferroni factor (no step recorded;
        `verify` records it). On the search's terms, or on the hypothesis' own `frame`."""
        mod = _VERIFY or _verify_module()
        search.n_hypotheses += int(hyp.count)
        search.verifications += 1
        on, pred = hyp.frame, hyp.prediction
        made, search.first_verified = search.first_verified, None
        if (made is not None and search.verifications == 1 and made[0] == hyp.matches and hyp.count == 1
                and on is None and pred is None):
            return made[1]
        if pred is not None:
            ver = mod.verify_prediction(search.V, hyp.matches, self.catalog, search.sigma, pred.P, pred.density_sr,
                                        pred.min_stars, n_hypotheses=search.n_hypotheses, threshold=self.threshold,
                                        radius_rad=search.radius)
        else:
            if on is None:
                V, catalog, camera, sigma, radius = search.V, self.catalog, self.camera, search.sigma, search.radius
            else:
                V, catalog, camera, sigma = on.vectors, on.catalog, on.camera, on.sigma_rad
                radius = mod.match_radius(sigma, self.radius_sigmas)
            ver = mod.verify(V, hyp.matches, catalog, camera, sigma,
                             n_hypotheses=search.n_hypotheses, n_patterns=self.n_patterns, statistic=self.statistic,
                             threshold=self.threshold, radius_rad=radius,
                             window_sr=search.obs.window_sr if on is None else None)
        if on is not None and on.parent_rows is not None:
            ver = ver.in_rows(on.parent_rows)
        return ver

    def identify_batch(self, observations) -> Iterator[Identification]:
        """Identify many frames (a sweep's): yields, frame after frame, the same identifications as
        `identify`. A method may find them faster together (`EllipticityMethod` does: the frames its first
        hypothesis decides then carry no steps and only a few stats). Each result's stats["time_s"]: the
        time it took, its share of a batch included. (Yielded: a caller that uses each and lets it go
        holds one frame's steps at a time.)"""
        for obs in observations:
            t0 = time.perf_counter()
            result = self.identify(obs)
            result.stats["time_s"] = time.perf_counter() - t0
            yield result

    def drive(self, search: Search, source: HypothesisSource) -> bool:
        """Verify what `source` yields until a hypothesis is accepted (True) or the source ends."""
        from skyview.identify.verify import Verification

        try:
            item = next(source)
            while True:
                if isinstance(item, Verification):  # the method's choice among verified hypotheses
                    search.result.accept(item)
                    search.result.verification = item.to_dict()
                    return True
                ver = self.verify(search, item)
                if ver.passed and item.accept:
                    search.result.accept(ver)
                    if item.on_accept is not None:
                        item.on_accept(ver)
                    return True
                item = source.send(ver)
        except StopIteration:
            return False
        finally:
            source.close()

    def failure_reason(self, search: Search) -> str:
        """Why nothing was identified (default: the reasons the search gave, joined)."""
        r = search.reasons
        return r[0] if len(r) == 1 else "; ".join(r) if r else "no hypothesis to verify"

    def finish(self, search: Search, reason: str = "") -> Identification:
        """The failure reason (the too-few-stars one, or `failure_reason`) and stats["time_s"]."""
        result = search.result
        if reason:
            result.reason = reason
        elif result.status != IDENTIFIED:
            result.reason = self.failure_reason(search)
        result.stats = {"stars": search.n, **search.stats, "time_s": time.perf_counter() - search.t0}
        return result


_VERIFY = None  # skyview.identify.verify (it imports scipy: imported when first used, then kept here)


def _verify_module():
    global _VERIFY
    import skyview.identify.verify as verify

    _VERIFY = verify
    return verify


class SequenceIdentifier(Identifier):
    """A method that identifies over a sequence of frames with known turns between them (one frame alone
    is only its first step). Its interface: `start()` a state, `update(state, obs, turn)` one frame,
    `identify_sequence(observations, turns)` all of them. Sinks and runners ask `is_sequence_method`,
    never for an attribute."""

    @abstractmethod
    def start(self):
        """The state before the first frame."""

    @abstractmethod
    def update(self, state, obs: Observation, turn) -> Identification:
        """Absorb one frame into `state` (the turn from the previous frame, None for the first)."""

    def identify(self, obs: Observation) -> Identification:
        """One frame alone: the first step of a sequence."""
        return self.update(self.start(), obs, None)

    def identify_sequence(self, observations, turns=None, **kwargs) -> list[Identification]:
        """Identify frame by frame: observations (one `Observation` per frame) and the known turns
        between consecutive frames (turns[k]: frame k to k + 1); one `Identification` per frame."""
        observations = list(observations)
        turns = [] if turns is None else list(turns)
        if len(turns) != max(len(observations) - 1, 0):
            raise BadInput(f"{len(observations)} frames need {max(len(observations) - 1, 0)} turns, "
                           f"got {len(turns)}")
        state = self.start()
        return [self.update(state, obs, turns[k - 1] if k > 0 else None, **{key: v[k] for key, v in kwargs.items()
                                                                          if v is not None})
                for k, obs in enumerate(observations)]


def is_sequence_method(method_or_class) -> bool:
    """Whether a method (its class or an instance) identifies over sequences (`SequenceIdentifier`)."""
    cls = method_or_class if isinstance(method_or_class, type) else type(method_or_class)
    return issubclass(cls, SequenceIdentifier)
