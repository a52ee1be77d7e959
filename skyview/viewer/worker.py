"""A background thread per viewer session: slow work off the GUI callbacks, the latest request wins."""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Callable


class Worker:
    """One background thread; a new request replaces a pending one (the latest wins)."""

    def __init__(self, on_error: Callable[[Exception], None]):
        self._cv = threading.Condition()
        self._job: tuple[str, Callable[[], None]] | None = None
        self._on_error = on_error
        self._closed = False
        self.busy: tuple[str, float] | None = None  # (label, start time)
        self.progress: float | None = None  # 0..100 when the job knows, else None
        # the progress line: written under this lock, by the ticker while a job runs and by the worker
        # when it ends (so that no late tick writes over the result, and wait_idle sees the line restored)
        self._report = threading.Lock()
        self._shown = False  # the ticker showed the running job
        self._on_idle: Callable[[], None] | None = None
        self._thread = threading.Thread(target=self._loop, name="skyview-viewer-worker", daemon=True)
        self._thread.start()

    def submit(self, label: str, fn: Callable[[], None]) -> None:
        with self._cv:
            self._job = (label, fn)
            self._cv.notify_all()

    def relabel(self, text: str) -> None:
        """Say what the running job is doing now (the panel's progress line)."""
        busy = self.busy
        if busy is not None:
            self.busy = (text, busy[1])

    def watch(self, on_busy: Callable[[str, float, float | None], None], on_idle: Callable[[], None],
              after_s: float = 0.3, every_s: float = 0.2) -> None:
        """Until closed, report a job that runs longer than after_s every every_s, as on_busy(label,
        seconds so far, progress 0..100 or None; from a thread of its own), and the end of a job so
        reported as on_idle() (from the worker, before wait_idle returns)."""
        self._on_idle = on_idle

        def loop() -> None:
            while not self._closed:
                with self._report:
                    busy = self.busy
                    if busy is not None and time.monotonic() - busy[1] > after_s:
                        with contextlib.suppress(Exception):
                            on_busy(busy[0], time.monotonic() - busy[1], self.progress)
                        self._shown = True
                time.sleep(every_s)

        threading.Thread(target=loop, name="skyview-viewer-ticker", daemon=True).start()

    @property
    def superseded(self) -> bool:
        """A newer request is waiting: the running job's result would be stale."""
        with self._cv:
            return self._job is not None or self._closed

    def idle(self) -> bool:
        with self._cv:
            return self._job is None and self.busy is None

    def wait_idle(self, timeout: float) -> bool:
        end = time.monotonic() + timeout
        with self._cv:
            while self._job is not None or self.busy is not None:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._job = None
            self._cv.notify_all()

    def _loop(self) -> None:
        while True:
            with self._cv:
                while self._job is None and not self._closed:
                    self._cv.wait()
                if self._closed:
                    return
                label, fn = self._job
                self._job = None
                self.busy, self.progress = (label, time.monotonic()), None
            try:
                fn()
            except Exception as exc:  # noqa: BLE001 - shown in the panel, the thread lives on
                self._on_error(exc)
            finally:
                with self._report:
                    shown, self._shown = self._shown, False
                    if shown and self._on_idle is not None and not self._closed:  # a closed tab's panel is gone
                        with contextlib.suppress(Exception):
                            self._on_idle()
                    with self._cv:
                        self.busy = None
                        self._cv.notify_all()
