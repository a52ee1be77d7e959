"""Helpers shared by the test files (importable: pytest puts tests/ on the path)."""

from __future__ import annotations

import contextlib
import io


@contextlib.contextmanager
def viewer_session():
    """A viewer Session on its own viser server (127.0.0.1, a free port), idle after its first solve:
    (server, session); closed and stopped afterwards."""
    import viser

    from skyview.viewer.run import Solvers
    from skyview.viewer.session import Session

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    s = Session(server, Solvers())
    try:
        assert s.wait_idle(60)
        yield server, s
    finally:
        s.close()
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
