"""The documentation site builds from the repository with no warnings (`mkdocs build --strict`).

Skipped where mkdocs is not installed; the `test` extra installs it (mkdocs, mkdocs-material,
mkdocstrings with the python handler), so CI runs it. The build is local: ~2 s, no network.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # the whole site is built once (mkdocs, a few seconds)

pytest.importorskip("mkdocs")
pytest.importorskip("mkdocstrings")
pytest.importorskip("mkdocstrings_handlers.python")
pytest.importorskip("material")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def built_site(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")  # mkdocs-material's banner about its successor
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                           "-d", str(out)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    return out, proc


def test_build_is_strict_and_clean(built_site):
    out, proc = built_site
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log
    assert "WARNING" not in log, log
    assert "ERROR" not in log, log


def test_key_pages_exist(built_site):
    out, _ = built_site
    for page in ("index.html", "getting-started.html", "howto/photograph.html", "howto/camera.html",
                 "howto/catalog.html", "howto/many-frames.html", "howto/record-replay.html",
                 "howto/viewer.html", "howto/benchmarks.html", "reference/api.html",
                 "reference/pipeline.html", "reference/camera-attitude.html", "blind.html", "methods.html",
                 "conventions.html", "stochastic.html", "genetic.html", "tracking.html", "recordings.html",
                 "viewer.html", "benchmarks.html", "peers.html", "search/search_index.json"):
        assert (out / page).is_file(), page


def test_api_reference_is_generated_from_the_docstrings(built_site):
    out, _ = built_site
    api = (out / "reference" / "api.html").read_text(encoding="utf-8")
    for text in ('id="skyview.solver.api.solve"', 'id="skyview.solver.api.Solution"', 'id="skyview.solver.api.Solver"',
                 "Solution", "ra_deg", "dec_deg", "roll_deg", "fov_deg",
                 "Solve one star-field image"):  # the first line of skyview.solve's docstring
        assert text in api, text
    pipeline = (out / "reference" / "pipeline.html").read_text(encoding="utf-8")
    assert 'id="skyview.solver.pipeline.solve_image"' in pipeline and 'id="skyview.solver.pipeline.SolveResult"' in pipeline
    cam = (out / "reference" / "camera-attitude.html").read_text(encoding="utf-8")
    assert 'id="skyview.core.camera.Camera.from_fov"' in cam and 'id="skyview.core.attitude.R_from_radec_roll"' in cam


def test_peer_comparison_includes_the_benchmarks_readme(built_site):
    out, _ = built_site
    peers = (out / "peers.html").read_text(encoding="utf-8")
    assert "cedar-solve" in peers and "tetra3rs" in peers


def test_the_site_loads_nothing_from_the_internet(built_site):
    out, _ = built_site
    for page in out.rglob("*.html"):
        html = page.read_text(encoding="utf-8")
        assert "fonts.googleapis.com" not in html, page
        assert '<script src="http' not in html, page
