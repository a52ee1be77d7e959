"""Star identification methods and what they share.

`make_identifier("angle", catalog, camera, sigma_rad, **params)` builds (or loads from the cache) the
method's database and returns an identifier with `name`, `database_key`, `database_info` and
`identify(obs) -> Identification`. To add a method, write its module (its `Params` dataclass, its
database, its `hypotheses`) and add one line to METHODS (or `register` it at run time); the CLI, the
bench, the viewer and the recorder find it here. docs/architecture.md has a worked example.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping

from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog
from skyview.core.errors import BadInput
from skyview.identify.base import (
    FAILED,
    IDENTIFIED,
    INCONCLUSIVE,
    Hypothesis,
    Identification,
    Identifier,
    Observation,
    Search,
    SequenceIdentifier,
    Status,
    Step,
    is_sequence_method,
)


class _Registry(Mapping):
    """Method name -> identifier class, each module imported on first use (a `skyview solve` that
    runs one method does not pay for importing the other five)."""

    def __init__(self, paths: dict[str, str]):
        self._paths = dict(paths)
        self._classes: dict[str, type[Identifier]] = {}

    def __getitem__(self, name: str) -> type[Identifier]:
        cls = self._classes.get(name)
        if cls is None:
            module, _, attr = self._paths[name].rpartition(".")
            cls = self._classes[name] = getattr(importlib.import_module(module), attr)
        return cls

    def __iter__(self):
        return iter(self._paths)

    def __len__(self) -> int:
        return len(self._paths)

    def register(self, name: str, cls: type[Identifier] | str) -> None:
        """Add a method at run time: its class, or its "module.Class" path (imported on first use)."""
        if isinstance(cls, str):
            self._paths[name] = cls
            self._classes.pop(name, None)
        else:
            self._paths[name] = f"{cls.__module__}.{cls.__qualname__}"
            self._classes[name] = cls

    def unregister(self, name: str) -> None:
        """Remove a method registered at run time."""
        self._paths.pop(name, None)
        self._classes.pop(name, None)


METHODS: Mapping[str, type[Identifier]] = _Registry({  # the order every listing and comparison shows
    "angle": "skyview.identify.angle.AngleMethod",
    "triangle": "skyview.identify.triangle.TriangleMethod",
    "svd": "skyview.identify.svd.SVDMethod",
    "ellipticity": "skyview.identify.ellipticity.EllipticityMethod",
    "stochastic": "skyview.identify.stochastic.StochasticMethod",
    "genetic": "skyview.identify.genetic.GeneticMethod",
})


VARIANTS = ("paper", "improved")


def make_identifier(method: str, catalog: GuideCatalog, camera: Camera, sigma_rad: float, /, *,
                    variant: str = "paper", **params) -> Identifier:
    """An identifier for `method`; params are the method's keyword parameters (paper names).

    variant="paper" keeps the paper's defaults; "improved" applies the method's `improved_params`
    first (explicit params still win).
    """
    cls = METHODS.get(method)
    if cls is None:
        raise BadInput(f"unknown method {method!r}: choose from {', '.join(METHODS)}")
    if variant not in VARIANTS:
        raise BadInput(f"unknown variant {variant!r}: choose from {', '.join(VARIANTS)}")
    reserved = sorted({"catalog", "camera", "sigma_rad", "variant"} & set(params))
    if reserved:
        raise BadInput(f"{', '.join(reserved)} cannot be set with --param: use the command's own options "
                       f"(--sigma-arcsec, --variant, --fov-deg, --mag-limit)")
    if variant == "improved":
        params = {**cls.improved_params, **params}
    allowed = cls.parameters()
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        raise BadInput(f"method {method!r} has no parameter {', '.join(map(repr, unknown))}: its parameters "
                       f"(paper defaults) are {', '.join(f'{k}={v!r}' for k, v in allowed.items())}")
    try:
        return cls(catalog, camera, sigma_rad, **params)
    except (TypeError, ValueError) as exc:
        if not params:
            raise
        shown = ", ".join(f"{k}={v!r}" for k, v in params.items())
        raise BadInput(f"method {method!r} cannot take {shown}: {exc}") from None


def register(name: str, cls: type[Identifier] | str) -> None:
    """Register a method under `name` (a class or its "module.Class" path): the one line a new method
    needs when it is not in METHODS' literal (tests, plug-ins)."""
    METHODS.register(name, cls)


__all__ = ["METHODS", "VARIANTS", "make_identifier", "register", "Identifier", "SequenceIdentifier",
           "Identification", "Observation", "Step", "Hypothesis", "Search", "Status", "is_sequence_method",
           "IDENTIFIED", "INCONCLUSIVE", "FAILED"]
