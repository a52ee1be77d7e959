"""`skyview replay FILE.rrd`: open a recording in the Rerun viewer.

With a desktop (DISPLAY or WAYLAND_DISPLAY set) the native viewer opens a window; without one, or with
`web=True`, Rerun serves its web viewer over HTTP and the recording over gRPC, both on `host`
(127.0.0.1 by default), and the URL to open is printed. Either way the viewer runs until it is closed or
interrupted (Ctrl-C / SIGTERM), and then the Rerun binary itself is stopped by its process id: the
`rerun` Python launcher is not used, because killing it leaves the real viewer running.

This module does not import the rerun SDK: it starts the binary that ships with rerun-sdk (rerun_cli).
"""

from __future__ import annotations

import importlib.util
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from skyview.core.errors import BadInput, SkyviewError

RRD_MAGIC = b"RRF"  # first bytes of a Rerun recording file (RRF2 in rerun 0.41)
START_TIMEOUT_S = 30.0


def rerun_binary() -> Path:
    """The Rerun viewer binary installed with rerun-sdk (the `rerun_cli` package)."""
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin:
        exe = Path(spec.origin).parent / ("rerun.exe" if os.name == "nt" else "rerun")
        if exe.is_file() and os.access(exe, os.X_OK):
            return exe
    raise BadInput("the Rerun viewer binary is missing: install rerun-sdk (pip install rerun-sdk==0.41.0)")


def check_recording(path: str | os.PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p} does not exist")
    if not p.is_file():
        raise BadInput(f"{p} is not a file")
    try:
        with open(p, "rb") as f:
            head = f.read(4)
    except OSError as exc:
        raise BadInput(f"cannot read {p}: {exc.strerror}") from None
    if not head.startswith(RRD_MAGIC):
        raise BadInput(f"{p} is not a Rerun recording (.rrd)")
    # read every chunk once (~10 ms for a 1 MB recording): a truncated or damaged file is refused here,
    # not served to a viewer that shows half of it or nothing
    import warnings

    from rerun.chunk import RrdReader

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            n = sum(1 for _ in RrdReader(str(p)).stream())
    except Exception as exc:  # the reader raises RuntimeError / ValueError on damaged frames
        raise BadInput(f"{p} is a damaged or truncated Rerun recording: {str(exc)[:200]}") from None
    if n == 0:
        raise BadInput(f"{p} is an empty Rerun recording (no data)")
    return p


def web_renderer() -> str:
    """The web viewer's renderer: WebGL, which renders everywhere, software rendering included (the
    default WebGPU crashes in a browser without a GPU); SKYVIEW_RERUN_RENDERER=webgpu chooses WebGPU."""
    r = os.environ.get("SKYVIEW_RERUN_RENDERER", "webgl").strip().lower()
    if r not in ("webgl", "webgpu"):
        raise BadInput(f"SKYVIEW_RERUN_RENDERER={r!r}: choose webgl or webgpu")
    return r


def has_desktop() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _check_port(host: str, port: int, what: str) -> None:
    if not 0 < port < 65536:
        raise BadInput(f"{what} port {port} is not a valid port (1-65535, or 0 for any free port)")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise BadInput(f"cannot listen on {host}:{port} for the {what}: {exc.strerror}; "
                           f"pick another port") from None


def _url_host(host: str) -> str:
    if host in ("0.0.0.0", "::"):
        return "127.0.0.1"
    return f"[{host}]" if ":" in host else host


@dataclass
class Viewer:
    """A started Rerun viewer process."""

    proc: subprocess.Popen
    url: str  # what to open (web) or the gRPC address of the native viewer
    web: bool
    log_path: Path

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stop(self, timeout_s: float = 10.0) -> int:
        """Stop the viewer by its process id (SIGTERM, then SIGKILL); returns its exit code."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=timeout_s)
        self.log_path.unlink(missing_ok=True)
        return int(self.proc.returncode)


def start_viewer(path: str | os.PathLike, *, web: bool | None = None, host: str = "127.0.0.1", port: int = 9090,
                 grpc_port: int = 0, wait: bool = True) -> Viewer:
    """Start the Rerun viewer on a recording; returns once it serves (web) or has started (native).

    web=None: the web viewer when there is no desktop. port: the web viewer's HTTP port; grpc_port: the
    port that serves the recording to the viewer. 0 picks a free port.
    """
    p = check_recording(path)
    exe = rerun_binary()
    web = (not has_desktop()) if web is None else bool(web)
    try:
        port = free_port(host) if port == 0 else int(port)
        grpc_port = free_port(host) if grpc_port == 0 else int(grpc_port)
    except OSError as exc:
        raise BadInput(f"cannot listen on {host}: {exc.strerror}") from None
    _check_port(host, grpc_port, "recording server (gRPC)")
    cmd = [str(exe), str(p), "--bind", host, "--port", str(grpc_port)]
    if web:
        _check_port(host, port, "web viewer")
        cmd += ["--web-viewer", "--web-viewer-port", str(port)]
    fd, log_name = tempfile.mkstemp(prefix="skyview-replay-", suffix=".log")
    log_path = Path(log_name)
    with os.fdopen(fd, "wb") as log:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)  # our Ctrl-C is handled here, not by the viewer
    grpc = f"rerun+http://{_url_host(host)}:{grpc_port}/proxy"
    if web:
        url = (f"http://{_url_host(host)}:{port}/?url={urllib.parse.quote(grpc, safe='')}"
               f"&renderer={web_renderer()}")
    else:
        url = grpc
    viewer = Viewer(proc, url, web, log_path)
    if wait:
        try:
            _wait_until_serving(viewer, host, port if web else grpc_port)
        except BaseException:
            viewer.stop()
            raise
    return viewer


def _wait_until_serving(viewer: Viewer, host: str, port: int) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    probe = f"http://{_url_host(host)}:{port}/"
    while time.monotonic() < deadline:
        if viewer.proc.poll() is not None:
            tail = [ln.strip() for ln in viewer.log_path.read_text(errors="replace").splitlines() if ln.strip()]
            last = tail[-1] if tail else f"exit code {viewer.proc.returncode}"
            hint = "" if viewer.web else " (no usable desktop? --web serves the web viewer instead)"
            raise BadInput(f"the Rerun viewer stopped at once: {last[-300:]}{hint}")
        if viewer.web:
            try:
                with urllib.request.urlopen(probe, timeout=1.0) as r:
                    if r.status == 200:
                        return
            except (urllib.error.URLError, OSError):
                pass
        else:
            with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
                s.settimeout(1.0)
                if s.connect_ex((_url_host(host).strip("[]"), port)) == 0:
                    return
        time.sleep(0.1)
    raise BadInput(f"the Rerun viewer did not start serving on {host}:{port} within {START_TIMEOUT_S:.0f} s")


def replay(path: str | os.PathLike, *, web: bool | None = None, host: str = "127.0.0.1", port: int = 9090,
           grpc_port: int = 0, out=sys.stdout) -> int:
    """Open `path` in the Rerun viewer and run until the viewer exits or we are interrupted."""
    viewer = start_viewer(path, web=web, host=host, port=port, grpc_port=grpc_port)
    # Ctrl-C (SIGINT) and SIGTERM both stop the viewer; SIGINT is set explicitly because a shell starts
    # background jobs with it ignored.
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def _on_signal(signum, frame):
        raise KeyboardInterrupt

    interrupted = False
    failure = ""
    try:
        for sig in previous:
            signal.signal(sig, _on_signal)
        if viewer.web:
            print(f"Rerun web viewer for {path}: {viewer.url}", file=out)
            print(f"(open it in a browser; renderer {web_renderer()}: it works without a GPU, "
                  f"SKYVIEW_RERUN_RENDERER=webgpu for the faster one; Ctrl-C stops the viewer)", file=out, flush=True)
        else:
            print(f"Rerun viewer opened on {path} (pid {viewer.pid}); close its window or press Ctrl-C to stop",
                  file=out, flush=True)
        if host not in ("127.0.0.1", "localhost", "::1"):
            print(f"warning: listening on {host}: the recording server and the web viewer are reachable from "
                  f"other machines, without authentication", file=sys.stderr, flush=True)
        viewer.proc.wait()
        if viewer.proc.returncode not in (0, None):  # the viewer ended by itself, with an error
            tail = [ln.strip() for ln in viewer.log_path.read_text(errors="replace").splitlines() if ln.strip()]
            failure = (f"the Rerun viewer failed on {path} (exit code {viewer.proc.returncode})"
                       + (f": {tail[-1][-200:]}" if tail else ""))
    except KeyboardInterrupt:
        interrupted = True
    finally:
        code = viewer.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if failure and not interrupted:
        raise SkyviewError(failure)
    print(f"viewer stopped (exit code {code})", file=out, flush=True)
    return 0
