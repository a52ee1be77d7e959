"""`skyview view --coverage DIR`: the sweep's map is a layer of every tab, switched in the View tab."""

import contextlib
import dataclasses
import io

import pytest

from skyview.coverage import CoverageConfig, run_coverage
from skyview.errors import BadInput
from skyview.viewer.coverage_layer import CoverageLayer

viser = pytest.importorskip("viser")


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("cov-view")
    cfg = CoverageConfig("angle", "improved", fov_deg=20.0, mag_limit=5.0, nside=1, rolls=1, chunk=6)
    run_coverage(cfg, out, scheduler="inline", progress=False)
    return out


def test_a_tab_shows_the_map_and_its_checkbox_switches_it(sweep):
    from skyview.viewer.app import ViewerApp
    from skyview.viewer.session import Session

    with contextlib.redirect_stdout(io.StringIO()):
        app = ViewerApp("127.0.0.1", 0, coverage=CoverageLayer.from_folder(sweep))
    try:
        # a tab as the app makes it (one CoverageLayer copy per tab)
        layer = dataclasses.replace(app.coverage, handles=[])
        session = Session(app.server, app.solvers, coverage=layer)
        assert session.wait_idle(120)
        box = session.panel.checks["coverage"]
        assert "angle" in box.label and box.value
        assert layer.visible and "20 deg FOV" in layer.caption
        assert not app.coverage.visible  # the app's own copy is never drawn: each tab draws its own
        session._toggle("coverage", False)
        assert not layer.visible
        session._toggle("coverage", True)
        assert layer.visible
        session.close()
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            app.stop()


def test_a_folder_that_is_not_a_sweep_is_bad_input(tmp_path):
    from skyview.viewer.app import serve

    with pytest.raises(BadInput, match="not a coverage folder"):
        serve(port=0, coverage=tmp_path, say=lambda line: None)
