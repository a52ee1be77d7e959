"""What one viewer tab shows, as typed data: which image, which sequence and frame, which step.

`ViewState` is the session's only record of what is on screen; the scene, the panel and the plots
are drawn from it. A sequence on screen is either a sequence method's (`SequenceRun`: the method
identifies over the frames) or a tracked one (`TrackedSequenceRun`: any single-frame method, frame 0
lost-in-space, then tracking); both show their frames the same way, and the text of each kind is
picked here, once. `Quiet` marks programmatic control changes that must not fire their callbacks.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from skyview.viewer import panel as P
from skyview.viewer.run import Run, Source
from skyview.viewer.sequence_run import SequenceRun, TrackedSequenceRun

Frames = SequenceRun | TrackedSequenceRun


@dataclass
class ViewState:
    """The state of one tab. run: the image on screen (with a sequence, the frame shown); sequence:
    the sequence on screen, if any; frame / step: the frame and the step shown (None: none chosen);
    upload: the user's image being solved instead of the simulation; compare_rows / compare_source:
    the comparison table and the image it is of; error: the error line in the panel."""

    run: Run | None = None
    sequence: Frames | None = None
    frame: int | None = None
    step: int | None = None
    upload: Source | None = None
    error: str = ""
    compare_rows: list[dict] = field(default_factory=list)
    compare_source: Source | None = None
    timings: dict[str, float] = field(default_factory=dict)  # ms of the last update, draw, step, frame

    @property
    def seq(self) -> SequenceRun | None:
        """The sequence method's sequence on screen (None for a tracked one)."""
        return self.sequence if isinstance(self.sequence, SequenceRun) else None

    @property
    def tracked(self) -> TrackedSequenceRun | None:
        """The tracked sequence on screen (None for a sequence method's)."""
        return self.sequence if isinstance(self.sequence, TrackedSequenceRun) else None

    def frame_text(self) -> str:
        """What the frame shown says (empty without a sequence)."""
        seq, k = self.sequence, self.frame
        if seq is None or k is None:
            return ""
        return P.frame_markdown(seq, k) if isinstance(seq, SequenceRun) else seq.frame_markdown(k)

    def status_text(self) -> str:
        """The status line: the sequence's (which frame was identified) or the image's."""
        if self.seq is not None and self.frame is not None:
            return P.sequence_status_markdown(self.seq, self.frame)
        return P.status_markdown(self.run) if self.run is not None else ""

    def result_text(self, viewer_ms: dict) -> str:
        """The Result tab: the image's result, under the whole sequence's when one is on screen."""
        text = P.result_markdown(self.run, viewer_ms)
        seq, k = self.sequence, self.frame
        if seq is None or k is None:
            return text
        whole = P.sequence_markdown(seq) if isinstance(seq, SequenceRun) else seq.markdown()
        return f"{whole}\n\n---\n\n**Frame {k}** (shown)  \n{text}"

    def forget_stale_comparison(self) -> bool:
        """A comparison is of one image: True (and forgotten) when another image is on screen."""
        if self.compare_source is not None and self.run is not None and self.run.source is not self.compare_source:
            self.compare_rows, self.compare_source = [], None
            return True
        return False


class Quiet:
    """`with quiet:` control values set by the program, not the user, fire no solve (`bool(quiet)`
    is True inside). Re-entrant and shared by the session's threads."""

    def __init__(self):
        self._depth = 0
        self._lock = threading.Lock()

    def __enter__(self) -> "Quiet":
        with self._lock:
            self._depth += 1
        return self

    def __exit__(self, *exc) -> None:
        with self._lock:
            self._depth -= 1

    def __bool__(self) -> bool:
        return self._depth > 0
