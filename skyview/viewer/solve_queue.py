"""The viewer's solves, first come first served on a bounded number of slots (one viewer, many tabs).

Every tab has its own worker thread (`skyview.viewer.worker.Worker`), but a classroom of tabs must not
start thirty solves at once on two cores: each would take thirty times as long, the newest tab's panel
would wait behind all of them, and none would say why. `SolveQueue.turn` hands out `slots` turns in the
order they were asked for; a tab waiting for its turn is told its place ("2 ahead of you"), and one
whose request is stale (a newer one replaced it, or the tab was closed) leaves the queue at once
(`Superseded`), so a closed tab frees its place without running. Drawing the result is not queued:
each tab draws its own scene.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections import deque
from typing import Callable, Iterator

WAIT_TICK_S = 0.1  # how often a waiting tab rechecks whether its request is still wanted


class Superseded(Exception):
    """The request left the queue before its turn: a newer request replaced it or its tab was closed."""


class SolveQueue:
    def __init__(self, slots: int | None = None):
        self.slots = max(1, int(slots or os.cpu_count() or 1))
        self._cv = threading.Condition()
        self._waiting: deque[object] = deque()
        self.running = 0
        self.served = 0  # turns given (for the load benchmark and the tests)

    def waiting(self) -> int:
        with self._cv:
            return len(self._waiting)

    @contextlib.contextmanager
    def turn(self, say: Callable[[str], None] | None = None,
             stale: Callable[[], bool] | None = None) -> Iterator[None]:
        """Wait for a turn (first asked, first served), then hold it for the block. say(text): told the
        place in the queue while waiting; stale(): True when the request is no longer wanted (it then
        leaves the queue: Superseded)."""
        ticket = object()
        with self._cv:
            self._waiting.append(ticket)
            told = None
            try:
                while not (self._waiting[0] is ticket and self.running < self.slots):
                    if stale is not None and stale():
                        raise Superseded
                    ahead = self._waiting.index(ticket)
                    if say is not None and ahead != told:
                        say(f"waiting for a free core: {ahead} ahead of you" if ahead else
                            "waiting for a free core: next")
                        told = ahead
                    self._cv.wait(WAIT_TICK_S)
            except BaseException:
                self._waiting.remove(ticket)
                self._cv.notify_all()
                raise
            self._waiting.popleft()
            self.running += 1
            self.served += 1
        try:
            yield
        finally:
            with self._cv:
                self.running -= 1
                self._cv.notify_all()
