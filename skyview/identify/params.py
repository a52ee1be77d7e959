"""Method parameters, declared once per method as a frozen dataclass with its checks.

Each method module declares `XParams(MethodParams)`: its fields are the paper's names with the paper's
defaults, `__post_init__` refuses a bad value with a one-line `BadInput`, and the improved variant is a
`dataclasses.replace` of the paper defaults (`IMPROVED = replace(PAPER, ...)`). `make_identifier`,
the CLI's `--param NAME=VALUE` (and its listing) and the parameter table of docs/methods.md
(`parameter_table`) read these classes; the method's constructor takes the same names.

The three parameters of the shared verification (statistic, threshold, radius_sigmas) are in
`MethodParams`, so every method has them and checks them the same way.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from skyview.core.errors import BadInput
from skyview.identify.verify import CALIBRATED, RADIUS_SIGMAS, STATISTICS


def positive(name: str, value, *, allow_zero: bool = False) -> None:
    """BadInput unless value is a finite number > 0 (>= 0 with allow_zero)."""
    try:
        ok = bool(np.isfinite(value) and (value >= 0 if allow_zero else value > 0))
    except TypeError:
        ok = False
    if not ok:
        raise BadInput(f"{name} must be {'>= 0' if allow_zero else 'a positive number'}, not {value!r}")


def at_least(name: str, value, low: int, what: str = "") -> None:
    """BadInput unless value is an integer >= low."""
    try:
        ok = int(value) == value and int(value) >= low
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise BadInput(f"{name}{what} must be an integer >= {low}, not {value!r}")


def one_of(name: str, value, choices) -> None:
    """BadInput unless value is one of choices."""
    if value not in choices:
        raise BadInput(f"unknown {name} {value!r}: choose from {', '.join(map(str, choices))}")


@dataclass(frozen=True)
class MethodParams:
    """What every method has: the shared verification's statistic, threshold and match radius in sigmas."""

    statistic: str = CALIBRATED
    threshold: float | None = None
    radius_sigmas: float = RADIUS_SIGMAS

    def __post_init__(self):
        if self.statistic not in STATISTICS:
            raise BadInput(f"unknown verification statistic {self.statistic!r}: choose from {', '.join(STATISTICS)}")
        if self.threshold is not None and not (isinstance(self.threshold, (int, float))
                                               and 0 < float(self.threshold) <= 1):
            raise BadInput("threshold must be in (0, 1]")
        positive("radius_sigmas", self.radius_sigmas)

    def changed(self, base: MethodParams | None = None) -> dict[str, Any]:
        """The fields that differ from `base` (default: the paper defaults of this class)."""
        base = type(self)() if base is None else base
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) != getattr(base, f.name)}


def check_sigma(sigma_rad) -> float:
    """The method's default measurement sigma: a positive number (BadInput otherwise)."""
    if not (np.isfinite(sigma_rad) and sigma_rad > 0):
        raise BadInput(f"the measurement sigma must be a positive number, not {sigma_rad!r}")
    return float(sigma_rad)


def bind(method, params: MethodParams) -> None:
    """Set every parameter as an attribute of the method (its code reads self.<name>), and keep the
    dataclass as method.params."""
    method.params = params
    for f in dataclasses.fields(params):
        setattr(method, f.name, getattr(params, f.name))


def parameter_table(methods) -> str:
    """Markdown: per method, each parameter with its paper default and its improved value (the
    generated part of docs/methods.md; tests/test_template.py checks the two agree)."""
    lines = ["| method | parameter | paper | improved |", "|---|---|---|---|"]
    for name, cls in methods.items():
        defaults = cls.parameters()
        improved = dict(cls.improved_params)
        for key, value in defaults.items():
            imp = f"`{_shown(improved[key])}`" if key in improved else ""
            lines.append(f"| {name} | `{key}` | `{_shown(value)}` | {imp} |")
    return "\n".join(lines)


def _shown(value) -> str:
    """A parameter value as the table shows it (floats to 6 significant digits)."""
    if isinstance(value, (float, np.floating)):
        return f"{float(value):g}"
    if isinstance(value, (tuple, list)):
        return "(" + ", ".join(_shown(v) for v in value) + ")"
    return repr(value)


if __name__ == "__main__":  # `python -m skyview.identify.params`: the table to paste into docs/methods.md
    from skyview.identify import METHODS

    print(parameter_table(METHODS))
