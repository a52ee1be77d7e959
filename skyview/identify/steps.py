"""A method's record of what it did: one `Step` per thing it did, in its own vocabulary, with the typed
layers of what it knows after it (`skyview.identify.layers`); `LazyStep` computes what a hot path
would rarely read only when it is read."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

from skyview.identify.layers import Layer

L = TypeVar("L")


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
    `skyview.present.drawables` turns them into drawables for every sink.
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


class LazyStep(Step):
    """A `Step` whose `catalog` rows and `groups` (and, where given as functions, its `note`, `numbers`
    and `layers`) are computed when first read (then kept): a method's hot path records a step per
    pick / pivot and most are never read. catalog_of / groups_of / note_of / numbers_of / layers_of:
    functions of no argument giving the field (they must read only values the method no longer
    changes). It reads, compares, copies and pickles as the `Step` it stands for."""

    def __init__(self, kind: str, note: str = "", observed: list[int] | None = None, catalog: list[int] | None = None,
                 groups: list[tuple[int, ...]] | None = None, numbers: dict[str, float] | None = None,
                 layers: tuple[Layer, ...] = (), *, catalog_of: Callable[[], list[int]] | None = None,
                 groups_of: Callable[[], list[tuple[int, ...]]] | None = None,
                 note_of: Callable[[], str] | None = None, numbers_of: Callable[[], dict[str, float]] | None = None,
                 layers_of: Callable[[], tuple[Layer, ...]] | None = None):
        self.kind = kind
        self.observed = [] if observed is None else observed
        d = self.__dict__
        d["_catalog"], d["_catalog_of"] = ([] if catalog is None else catalog), catalog_of
        d["_groups"], d["_groups_of"] = ([] if groups is None else groups), groups_of
        d["_note"], d["_note_of"] = note, note_of
        d["_numbers"], d["_numbers_of"] = ({} if numbers is None else numbers), numbers_of
        d["_layers"], d["_layers_of"] = layers, layers_of

    def _lazy(self, name: str):
        d = self.__dict__
        make = d[f"_{name}_of"]
        if make is not None:
            d[f"_{name}"], d[f"_{name}_of"] = make(), None
        return d[f"_{name}"]

    def _set(self, name: str, value) -> None:
        self.__dict__[f"_{name}"], self.__dict__[f"_{name}_of"] = value, None

    catalog = property(lambda self: self._lazy("catalog"), lambda self, v: self._set("catalog", v))
    groups = property(lambda self: self._lazy("groups"), lambda self, v: self._set("groups", v))
    note = property(lambda self: self._lazy("note"), lambda self, v: self._set("note", v))
    numbers = property(lambda self: self._lazy("numbers"), lambda self, v: self._set("numbers", v))
    layers = property(lambda self: self._lazy("layers"), lambda self, v: self._set("layers", v))

    def __eq__(self, other):
        if not isinstance(other, Step):
            return NotImplemented
        return all(getattr(self, f.name) == getattr(other, f.name) for f in dataclasses.fields(Step))

    __hash__ = None

    def __reduce__(self):
        return Step, tuple(getattr(self, f.name) for f in dataclasses.fields(Step))
