"""Session-wide test setup: every database goes to a temporary cache, never the user's ~/.cache.

Set before any test module is imported, so the subprocesses the tests start inherit it too. Modules
that want a cache of their own still point SKYVIEW_CACHE elsewhere with monkeypatch.
"""

import os
import shutil
import tempfile

_CACHE = tempfile.mkdtemp(prefix="skyview-test-cache-")
os.environ["SKYVIEW_CACHE"] = _CACHE


def pytest_sessionfinish(session, exitstatus):
    shutil.rmtree(_CACHE, ignore_errors=True)
