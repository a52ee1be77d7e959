"""Session-wide test setup: nothing the tests run writes into the user's home.

Every database goes to a temporary cache (SKYVIEW_CACHE), and the programs the tests start (the Rerun
viewer, Chromium) find their XDG config, data, cache and state folders there too instead of
~/.config, ~/.local/share and ~/.cache. Set before any test module is imported, so the subprocesses
the tests start inherit it. Tests that want a cache of their own (to see a database built) still point
SKYVIEW_CACHE elsewhere with monkeypatch.

Session-scoped fixtures shared by the test files: `cache` (that folder: every file reuses the databases
another built), `catalog` (the whole guide catalog), `cat` (it to Hp 6, the papers' depth) and `cam`
(8 deg, 1024 x 1024, the cole8 camera). A file whose tests need another depth or camera defines its own.
"""

import os
import shutil
import tempfile
from pathlib import Path

import pytest

# SKYVIEW_TEST_CACHE=DIR keeps the databases between runs (the quick loop: pytest -m "not slow and not browser");
# by default every run builds them afresh in a temporary folder, removed at the end
_KEEP = os.environ.get("SKYVIEW_TEST_CACHE")
_CACHE = os.path.abspath(_KEEP) if _KEEP else tempfile.mkdtemp(prefix="skyview-test-cache-")
os.makedirs(_CACHE, exist_ok=True)
os.environ["SKYVIEW_CACHE"] = _CACHE
for _var, _sub in (("XDG_CONFIG_HOME", "config"), ("XDG_DATA_HOME", "data"), ("XDG_CACHE_HOME", "xdg-cache"),
                   ("XDG_STATE_HOME", "state")):
    os.environ[_var] = os.path.join(_CACHE, "home", _sub)
    os.makedirs(os.environ[_var], exist_ok=True)  # astropy ignores (and warns about) a missing one


def pytest_sessionfinish(session, exitstatus):
    if not _KEEP:
        shutil.rmtree(_CACHE, ignore_errors=True)


@pytest.fixture(scope="session")
def cache() -> Path:
    """The session's database cache (SKYVIEW_CACHE)."""
    return Path(_CACHE)


@pytest.fixture(scope="session")
def catalog():
    """The whole guide catalog, at the default epoch."""
    from skyview.core.catalog import load_guide_catalog

    return load_guide_catalog()


@pytest.fixture(scope="session")
def cat(catalog):
    """The guide catalog to Hp 6."""
    return catalog.brighter_than(6.0)


@pytest.fixture(scope="session")
def cam():
    """An 8 deg (horizontal), 1024 x 1024 pinhole camera."""
    from skyview.core.camera import Camera

    return Camera.from_fov(8.0, 1024)
