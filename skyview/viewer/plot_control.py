"""The panel's two plots: a number across the steps, and a sequence's posterior across its frames.

Each plot is one uPlot element made once with the panel (`add_step_plot`, `add_frame_plot`) and
updated in place: its data, its series' labels, its scales. Removing and re-adding an element on
every solve made the panel shrink for a moment, so a panel scrolled down jumped (and cut off the
sensor image); an element updated in place keeps its height.
"""

from __future__ import annotations

import math

import numpy as np
from viser import uplot

from skyview.present.drawables import default_plot_key, numeric_keys, series

PLOT_COLORS = ("#e848d2", "#ffd23c")
# The plot across frames: stars above the prior, the leading star's and the true star's posterior, now.
FRAME_PLOT_COLORS = ("#e848d2", "#ffb830", "#46d7ff", "#ffffff")
NO_PLOT = "-"  # the dropdown's choice when a run has no number to plot


def _empty(n_series: int) -> tuple[np.ndarray, ...]:
    return (np.arange(2, dtype=np.float64),) + tuple(np.full(2, np.nan) for _ in range(n_series))


def _step_series(key: str) -> tuple:
    return (uplot.Series(label="step"),
            uplot.Series(label=key, stroke=PLOT_COLORS[0], width=2,
                         points={"show": True, "size": 5, "fill": PLOT_COLORS[0]}),
            uplot.Series(label="now", stroke="transparent", points={"show": True, "size": 11, "fill": PLOT_COLORS[1]}))


def _step_scales(log: bool) -> dict:
    return {"x": {"time": False}, "y": {"distr": 3 if log else 1}}


def add_step_plot(gui):
    """The plot across steps (hidden until a run with numbers is on screen)."""
    return gui.add_uplot(data=_empty(2), series=_step_series(NO_PLOT), scales=_step_scales(False),
                         legend={"show": True, "live": False}, aspect=1.8, visible=False)


def _frame_line(label, color, scale, width=2.0, dash=None):
    s = uplot.Series(label=label, scale=scale, stroke=color, width=width,
                     points={"show": True, "size": 6, "fill": color})
    if dash:
        s["dash"] = dash
    return s


def _frame_axes_scales(n: int, above: np.ndarray) -> tuple[tuple, dict]:
    """x: the frames; left: stars above 1/N on a log axis labelled by decades; right: posteriors 0-1."""
    top = max(1, math.ceil(math.log10(max(float(np.nanmax(above)) if np.isfinite(above).any() else 1.0, 2.0))))
    decades = tuple(float(10 ** i) for i in range(top + 1))
    scales = {"x": {"time": False, "range": (-0.3, max(n - 1, 0) + 0.3)},
              "n": {"distr": 3, "log": 10, "range": (1.0, decades[-1])}, "p": {"range": (0.0, 1.0)}}
    axes = (uplot.Axis(scale="x", label="frame", incrs=(1, 2, 5, 10), space=18, size=28, labelSize=16),
            uplot.Axis(scale="n", side=3, label="stars above 1/N", splits=decades,
                       values=tuple(f"{int(v):d}" for v in decades), size=42, labelSize=16),
            uplot.Axis(scale="p", side=1, label="posterior", splits=(0.0, 0.25, 0.5, 0.75, 1.0),
                       values=("0", ".25", ".5", ".75", "1"), size=36, labelSize=16, grid={"show": False}))
    return axes, scales


def add_frame_plot(gui):
    """The plot across a sequence's frames (hidden until a sequence method's sequence is on screen)."""
    c = FRAME_PLOT_COLORS
    axes, scales = _frame_axes_scales(2, np.array([1.0]))
    return gui.add_uplot(
        data=_empty(4),
        series=(uplot.Series(label="frame"),
                _frame_line("stars above 1/N", c[0], "n"),
                _frame_line("P(leading star)", c[1], "p", 2.5),
                _frame_line("P(true star)", c[2], "p", 1.5, (4, 5)),
                uplot.Series(label="frame shown", scale="p", stroke=c[3], width=0,
                             points={"show": True, "size": 14, "fill": "transparent", "stroke": c[3], "width": 2})),
        scales=scales, axes=axes, legend={"show": True, "live": False}, aspect=1.6, padding=(10, 8, 0, 0),
        visible=False)


class StepPlot:
    """The number chosen in the panel's dropdown across the steps of the run on screen, the step shown
    marked. key: the dropdown (its options follow the run's numbers); handle: `add_step_plot`'s."""

    def __init__(self, key, handle):
        self.key = key
        self.handle = handle
        self._drawables: list = []
        self._log: bool | None = None

    def options(self, drawables: list) -> None:
        """The numbers of a new run in the dropdown, its default chosen (call quietly: no redraw)."""
        keys = numeric_keys(drawables)
        default = default_plot_key(drawables)
        self.key.options = tuple(keys) if default is not None else (NO_PLOT, *keys)
        self.key.value = default or NO_PLOT

    def draw(self, drawables: list, step: int | None) -> None:
        """Plot the chosen number of `drawables` (hidden when there is none), with `step` marked."""
        self._drawables = drawables
        key = self.key.value
        if not drawables or key == NO_PLOT:
            self.handle.visible = False
            return
        y = series(drawables, key)
        positive = np.isfinite(y) & (y > 0)
        log = bool(positive.sum() >= 2 and np.nanmax(y[positive]) / np.nanmin(y[positive]) > 50
                   and not np.any(np.isfinite(y) & (y < 0)))
        if self.handle.series[1]["label"] != key:
            self.handle.series = _step_series(key)
        if log != self._log:
            self.handle.scales = _step_scales(log)
            self._log = log
        self.handle.data = self.data(step)
        self.handle.visible = True

    def data(self, step: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x = step number (from 1), y = the chosen number, and y at the step shown only."""
        n = len(self._drawables)
        x = np.arange(1, n + 1, dtype=np.float64)
        key = self.key.value
        y = series(self._drawables, key) if n and key != NO_PLOT else np.full(n, np.nan)
        now = np.full(n, np.nan)
        if step is not None and 0 <= step < n:
            now[step] = y[step]
        return (x, y, now)

    def mark(self, step: int | None) -> None:
        if self.handle.visible and self._drawables:
            self.handle.data = self.data(step)


class FramePlot:
    """A sequence method's sequence across its frames: stars above the prior, the leading star's and
    the true star's posterior, the frame shown marked. handle: `add_frame_plot`'s."""

    def __init__(self, handle):
        self.handle = handle
        self._series: dict[str, np.ndarray] | None = None

    def draw(self, seq, frame: int | None) -> None:
        """Plot `seq` (a `SequenceRun`; None hides the plot)."""
        if seq is None:
            self._series = None
            self.handle.visible = False
            return
        self._series = seq.series()
        axes, scales = _frame_axes_scales(len(seq), self._series["above_prior"])
        self.handle.axes, self.handle.scales = axes, scales
        self.handle.data = self.data(frame)
        self.handle.visible = True

    def data(self, frame: int | None) -> tuple[np.ndarray, ...]:
        """x = frame; stars above the prior, the leading star's and the true star's posterior, and the
        frame shown (marked on the leading star's posterior)."""
        ser = self._series
        n = len(ser["top_posterior"])
        now = np.full(n, np.nan)
        if frame is not None and 0 <= frame < n:
            now[frame] = ser["top_posterior"][frame]
        return (np.arange(n, dtype=np.float64), ser["above_prior"], ser["top_posterior"], ser["true_posterior"], now)

    def mark(self, frame: int | None) -> None:
        if self._series is not None:
            self.handle.data = self.data(frame)
