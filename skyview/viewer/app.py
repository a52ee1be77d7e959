"""The viewer server: one `Session` (panel + scene + worker) per browser tab, and `skyview view`.

`ViewerApp` starts a viser server (on 127.0.0.1 unless told otherwise) and gives each connecting tab
its own session, so tabs do not fight over controls; solvers are shared.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import importlib
import io
import os
import signal
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Callable

import viser

from skyview.core.camera import Camera
from skyview.core.errors import BadInput
from skyview.detect.centroids import load_image
from skyview.viewer.picture import MAX_UPLOAD_BYTES
from skyview.viewer.run import SceneConfig, Solvers, Source, check_fov
from skyview.viewer.session import Session

UNKNOWN_FOV_GUESS_DEG = 10.0  # an image given without its FOV: the camera is fitted blind; this is only the
# starting value shown (and used if the blind search fails)


def load_initial_image(path: str | Path, fov_deg: float | None) -> Source:
    """The `--image` / `--fov-deg` pair of `skyview view`, checked (BadInput with one line). The FOV
    may be left out: the viewer fits the camera to the image's stars (blind)."""
    fov = check_fov(UNKNOWN_FOV_GUESS_DEG if fov_deg is None else fov_deg)
    image = load_image(path)
    Camera.from_fov(fov, image.shape[1], image.shape[0])
    return Source(image=image, fov_deg=fov, name=Path(path).name)


def check_host(host: str) -> None:
    """A host the server can listen on: resolvable and bindable on this machine (one line otherwise)."""
    import socket

    try:
        infos = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise BadInput(f"--host {host!r} cannot be resolved: {exc}") from None
    err = None
    for family, stype, proto, _, addr in infos:
        try:
            with socket.socket(family, stype, proto) as sock:
                sock.bind(addr[:2] if family == socket.AF_INET else addr)
            return
        except OSError as exc:
            err = exc
    raise BadInput(f"cannot listen on --host {host}: {err.strerror if err else 'no address'} (it must be an "
                   f"address of this machine, e.g. 127.0.0.1 or 0.0.0.0)")


RELEASE_AFTER_S = 0.5  # a closed tab's session is collected this long after its client left
NO_AUTH_WARNING = ("warning: the viewer has no authentication: anyone who can reach {host} can use it. Put it "
                   "behind a reverse proxy with authentication (nginx, Caddy) or an SSH tunnel to 127.0.0.1 instead")


class ViewerApp:
    """The viser server and its sessions (one per connected tab)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, *, initial: Source | None = None,
                 config: SceneConfig | None = None, method: str | None = None, variant: str | None = None,
                 coverage=None, bench_report: dict | None = None):
        self.solvers = Solvers()
        self.bench_report = bench_report  # a `skyview bench --compare` report shown in every tab's Result
        self.coverage = coverage  # a CoverageLayer read once; each tab draws its own copy
        self.method, self.variant = method, variant
        self.initial = initial
        self.config = (config or SceneConfig()).checked()
        self.sessions: dict[int, Session] = {}
        self._building: set[int] = set()  # clients whose session is being built
        self._left: set[int] = set()  # ... of which the tab has already closed
        self._lock = threading.Lock()
        check_host(host)
        # a tab may close at any moment, its session's last panel and scene updates then go nowhere: viser
        # warns of each; for a server of many tabs that is the normal course, not a fault to print
        warnings.filterwarnings("ignore", message=r"Queued a \w+ on a closed connection", category=UserWarning)
        self.solvers.base_catalog  # load once before the first tab arrives
        # astropy (the constellation names of a solved photograph, 0.3 s to import) while nobody waits
        threading.Thread(target=importlib.import_module, args=("astropy.coordinates",), daemon=True).start()
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints its own banner
            self.server = viser.ViserServer(host=host, port=port, label="skyview", verbose=False)
        self.host = host
        self._refuse_oversized_uploads()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.port}"

    def _refuse_oversized_uploads(self) -> None:
        """Refuse an upload larger than MAX_UPLOAD_BYTES when it starts (the browser announces its size),
        so the server never buffers it: viser's own handler has just created the transfer's state; it is
        dropped here, and the parts that follow are ignored. (viser internals, pinned to viser 1.1.1.)"""
        from viser import _messages

        gui = self.server.gui

        def check(client_id, message) -> None:
            if message.size_bytes <= MAX_UPLOAD_BYTES:
                return
            gui._current_file_upload_states.pop(message.transfer_uuid, None)
            with self._lock:
                session = self.sessions.get(client_id)
            if session is not None:
                session.show_error(f"{message.filename} is {message.size_bytes / 1e6:.0f} MB: the viewer takes "
                                   f"images up to {MAX_UPLOAD_BYTES // 2 ** 20} MB")

        gui._websock_interface.register_handler(_messages.FileTransferStartUpload, check)

    def _connect(self, client: viser.ClientHandle) -> None:
        key = client.client_id
        with self._lock:
            self._building.add(key)
        layer = None if self.coverage is None else dataclasses.replace(self.coverage, handles=[])
        session = Session(client, self.solvers, initial=self.initial, config=self.config, method=self.method,
                          variant=self.variant, coverage=layer, bench_report=self.bench_report)
        with self._lock:
            self._building.discard(key)
            left = key in self._left  # the tab closed while its session was being built
            self._left.discard(key)
            if not left:
                self.sessions[key] = session
        if left:
            self._release(session)

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            session = self.sessions.pop(client.client_id, None)
            if session is None and client.client_id in self._building:
                self._left.add(client.client_id)  # released by _connect once built
        if session is not None:
            self._release(session)

    @staticmethod
    def _release(session: Session) -> None:
        session.close()
        del session
        # a session and its panel's callbacks hold each other (a reference cycle), and viser holds the
        # client until this callback returns: collected a moment later, not at the next full collection,
        # which a server of numpy arrays may not reach for a long time (~9 MB a closed tab)
        timer = threading.Timer(RELEASE_AFTER_S, gc.collect)
        timer.daemon = True
        timer.start()

    def stop(self) -> None:
        with self._lock:
            sessions = list(self.sessions.values())
            self.sessions.clear()
        for s in sessions:
            s.close()
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()


def serve(host: str = "127.0.0.1", port: int = 8080, image: str | None = None, fov_deg: float | None = None,
          say: Callable[[str], None] = print, *, config: SceneConfig | None = None, method: str | None = None,
          variant: str | None = None, coverage: str | Path | None = None,
          compare: str | Path | None = None) -> int:
    """`skyview view` (and the end of `skyview demo`): run the viewer until Ctrl-C (or SIGTERM).

    config / method / variant: the simulated scene and the method every tab starts on. coverage: the
    folder of a `skyview coverage` sweep, drawn on the sphere as a layer ("Sky coverage" in View).
    compare: a `skyview bench --compare` JSON, its tables shown in every tab's Result tab."""
    initial = load_initial_image(image, fov_deg) if image is not None else None
    layer = None
    if coverage is not None:
        from skyview.viewer.coverage_layer import CoverageLayer

        layer = CoverageLayer.from_folder(coverage)
    report = None
    if compare is not None:
        from skyview.bench.compare import load_compare

        report = load_compare(compare)
    if config is None:
        config = SceneConfig(fov_deg=check_fov(fov_deg)) if fov_deg is not None and image is None else None

    stopping = []

    def _terminate(_signum, _frame):
        if stopping:  # a second Ctrl-C (or a `kill` and its wrapper's) while stopping: the stop is under way
            return
        stopping.append(True)
        raise KeyboardInterrupt

    # Ctrl-C (SIGINT) and a plain `kill` (SIGTERM) both stop it cleanly. SIGINT is set explicitly: a
    # process started from a background job inherits it ignored, and would then never stop on Ctrl-C.
    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {sig: signal.signal(sig, _terminate) for sig in (signal.SIGINT, signal.SIGTERM)}
    app = None
    try:
        app = ViewerApp(host, port, initial=initial, config=config, method=method, variant=variant, coverage=layer,
                        bench_report=report)
        # the address is announced inside the try: a Ctrl-C right after it still stops the server
        say(f"skyview viewer: {app.url}  (Ctrl-C stops it)")
        if host not in ("127.0.0.1", "localhost", "::1"):
            say(f"listening on {host}: other machines can reach it")
            say(NO_AUTH_WARNING.format(host=host))
        while True:
            # short naps: a signal the kernel hands to another thread (viser's event loop) only marks itself
            # pending, and the main thread runs its handler when its nap ends (a 3600 s sleep once left a
            # `kill` unanswered for an hour)
            time.sleep(WAKE_S)
    except KeyboardInterrupt:
        pass
    finally:
        clean = True
        if app is not None:
            clean = _stop_within(app, STOP_TIMEOUT_S)
        if not stopping:  # stopped by a signal, the process is on its way out: later ones stay ignored
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    say("skyview viewer stopped" if clean else
        f"skyview viewer stopped (the server did not shut down within {STOP_TIMEOUT_S:g} s; exiting anyway)")
    if not clean:  # a server thread that will not end must not keep the process alive
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0


STOP_TIMEOUT_S = 10.0
WAKE_S = 0.25  # the main thread's longest nap while serving: a stop signal is answered within this


def _stop_within(app: ViewerApp, timeout_s: float) -> bool:
    """Stop the app (sessions, then the viser server) in a helper thread; False if it took longer."""
    t = threading.Thread(target=app.stop, name="skyview-viewer-stop", daemon=True)
    t.start()
    t.join(timeout_s)
    return not t.is_alive()
