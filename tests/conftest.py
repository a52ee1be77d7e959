"""Session-wide test setup: nothing the tests run writes into the user's home.

Every database goes to a temporary cache (SKYVIEW_CACHE), and the programs the tests start (the Rerun
viewer, Chromium) find their XDG config, data, cache and state folders there too instead of
~/.config, ~/.local/share and ~/.cache. Set before any test module is imported, so the subprocesses
the tests start inherit it. Modules that want a cache of their own still point SKYVIEW_CACHE
elsewhere with monkeypatch.
"""

import os
import shutil
import tempfile

_CACHE = tempfile.mkdtemp(prefix="skyview-test-cache-")
os.environ["SKYVIEW_CACHE"] = _CACHE
for _var, _sub in (("XDG_CONFIG_HOME", "config"), ("XDG_DATA_HOME", "data"), ("XDG_CACHE_HOME", "xdg-cache"),
                   ("XDG_STATE_HOME", "state")):
    os.environ[_var] = os.path.join(_CACHE, "home", _sub)
    os.makedirs(os.environ[_var], exist_ok=True)  # astropy ignores (and warns about) a missing one


def pytest_sessionfinish(session, exitstatus):
    shutil.rmtree(_CACHE, ignore_errors=True)
