"""What every identification method shares: its input, its step record and its result.

Nothing in `skyview.identify` imports viser or rerun: the viewer and the recorder draw the steps.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from skyview.identify.layers import Layer

L = TypeVar("L")

IDENTIFIED = "identified"
INCONCLUSIVE = "inconclusive"
FAILED = "failed"


@dataclass(frozen=True)
class Observation:
    """Observed stars of one frame, brightest first.

    vectors: (N, 3) camera-frame unit vectors; uv: (N, 2) pixels; brightness: (N,) summed
    background-subtracted intensity (used as rank / relative magnitude only); sigma_rad: the 1-sigma
    direction error of one star (the paper's sigma).
    """

    vectors: np.ndarray
    uv: np.ndarray
    brightness: np.ndarray
    sigma_rad: float

    def __len__(self) -> int:
        return int(self.vectors.shape[0])


@dataclass
class Step:
    """One thing a method did, in its own vocabulary.

    kind: short machine name ('pick', 'lookup', 'pivot', 'prune', 'verify', 'generation', ...).
    note: one sentence for people ("pivoted to angle 2-5 (6.21 deg): 812 candidates, 3 consistent").
    observed: observed-star indices involved. catalog: catalog rows involved (capped for size).
    groups: candidate catalog tuples (pairs, triangles, ...) to draw, capped; rows of the catalog.
    numbers: the figures behind the decision (candidates, bounds, costs, posteriors, ...).
    layers: typed records of what the method knows after the step (`skyview.identify.layers`: the
    surviving hypotheses, a GA population and its search region, a posterior, candidate attitudes);
    `skyview.present` turns them into drawables for every sink.
    """

    kind: str
    note: str
    observed: list[int] = field(default_factory=list)
    catalog: list[int] = field(default_factory=list)
    groups: list[tuple[int, ...]] = field(default_factory=list)
    numbers: dict[str, float] = field(default_factory=dict)
    layers: tuple[Layer, ...] = ()

    def layer(self, kind: type[L]) -> L | None:
        """The step's first layer of type `kind`, or None."""
        return next((la for la in self.layers if isinstance(la, kind)), None)

    def to_dict(self) -> dict:
        return {
            "kind": self.kind, "note": self.note,
            "observed": [int(i) for i in self.observed],
            "catalog": [int(i) for i in self.catalog],
            "groups": [[int(i) for i in g] for g in self.groups],
            "numbers": {k: (float(v) if v is not None else None) for k, v in self.numbers.items()},
        }


@dataclass
class Identification:
    """The outcome of one identification.

    status: IDENTIFIED (verified), INCONCLUSIVE (no unique verified hypothesis) or FAILED (could not
    run: too few stars, ...). matches: observed index -> catalog row, only when identified (after
    verification, extended to every observed star that agrees). R: attitude when identified.
    """

    method: str
    status: str
    matches: dict[int, int]
    steps: list[Step]
    reason: str = ""
    R: np.ndarray | None = None
    attitude_covariance: np.ndarray | None = None
    verification: dict[str, Any] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    database_key: str = ""

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
            "verification": _plain(self.verification), "stats": _plain(self.stats),
            "database_key": self.database_key, "steps": [s.to_dict() for s in self.steps],
        }


class Identifier(ABC):
    """An identification method bound to its database (catalog + camera configuration).

    Subclasses set `name`, fill `database_key` (the key dict the database was built for; see
    `skyview.identify.database`) and `database_info` (counts, bytes, build / load time), and
    implement `identify`. Every method ends in `skyview.identify.verify.verify`.
    """

    name: str = ""
    # Options beyond the paper that make the method better; `variant="improved"` applies them.
    improved_params: dict = {}
    database_key: dict
    database_info: dict

    @abstractmethod
    def identify(self, obs: Observation) -> Identification:
        """Identify the observed stars of one frame."""


class SequenceIdentifier(Identifier):
    """A method that identifies over a sequence of frames with known turns between them (one frame alone
    is only its first step). Sinks and runners ask `is_sequence_method`, never for an attribute."""

    @abstractmethod
    def identify_sequence(self, observations, turns=None, **kwargs) -> list[Identification]:
        """Identify frame by frame: observations (one `Observation` per frame) and the known turns
        between consecutive frames; one `Identification` per frame."""


def is_sequence_method(method_or_class) -> bool:
    """Whether a method (its class or an instance) identifies over sequences (`SequenceIdentifier`)."""
    cls = method_or_class if isinstance(method_or_class, type) else type(method_or_class)
    return issubclass(cls, SequenceIdentifier)


def _plain(x: Any) -> Any:
    """numpy scalars / arrays inside dicts and lists -> plain Python for JSON."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating):
        return float(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x
