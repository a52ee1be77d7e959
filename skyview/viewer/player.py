"""One player for everything the viewer plays: the steps of an identification, the frames of a sequence.

A `Player` shows index 0, 1, … n-1 one after another on a thread, calling `show(k)` every
`interval_s` (the session's `show` sets the slider, as a user would), and keeps its button's label
("Play …" / "Pause") true. Pause, a new run on screen (`stop`) or the session closing end it; a
Pause then Play starts a new pass, and the old thread stops at its next tick.
"""

from __future__ import annotations

import threading
import time
from typing import Callable


class Player:
    """Plays 0..n-1 through `show(k)`; `button`: the viser button that toggles it (its label follows;
    None: no button)."""

    def __init__(self, button, show: Callable[[int], None], *, interval_s: float, label: str,
                 min_length: int = 1, on_error: Callable[[Exception], None] | None = None):
        self.button = button
        self.show = show
        self.interval_s = interval_s
        self.label = label  # the button's label while not playing
        self.min_length = min_length  # fewer items than this: nothing to play
        self.on_error = on_error
        self._lock = threading.Lock()
        self._pass = 0  # which pass is current: a thread whose pass is not current stops
        self._playing = False
        self._thread: threading.Thread | None = None

    @property
    def playing(self) -> bool:
        return self._playing

    def toggle(self, n: int, current: int | None, still: Callable[[], bool] = lambda: True) -> None:
        """Play (from `current` + 1, or from 0 at the end) or, while playing, pause.
        still(): False once what is played has left the screen (the player then stops quietly)."""
        if self._playing:
            self.stop()
            return
        if n < self.min_length:
            return
        start = 0 if current is None or current >= n - 1 else current + 1
        with self._lock:
            self._pass += 1
            me = self._pass
            self._playing = True
        self._label("Pause")

        def go_on() -> bool:
            return self._pass == me and still()

        def play() -> None:
            try:
                for k in range(start, n):
                    if not go_on():
                        break
                    self.show(k)
                    if k < n - 1:
                        time.sleep(self.interval_s)
            except Exception as exc:  # noqa: BLE001 - reported in the panel, the server keeps running
                if self.on_error is None:
                    raise
                self.on_error(exc)
            finally:
                with self._lock:
                    if self._pass == me:
                        self._playing = False
                        self._label(self.label)

        self._thread = threading.Thread(target=play, name="skyview-viewer-player", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Pause (or forget a pass in progress): the button says Play again."""
        with self._lock:
            self._pass += 1
            self._playing = False
        self._label(self.label)

    def reset(self, n: int) -> None:
        """A new run of n items on screen: stopped, the button enabled only if there is something to play."""
        self.stop()
        if self.button is not None:
            self.button.disabled = n < self.min_length

    def _label(self, text: str) -> None:
        if self.button is not None:
            self.button.label = text

    def wait(self, timeout: float = 30.0) -> bool:
        """Block until the pass in progress ends (tests and scripts); False on timeout."""
        end = time.monotonic() + timeout
        while self._playing and time.monotonic() < end:
            time.sleep(0.01)
        return not self._playing
