"""`skyview view --coverage DIR`: the sweep's map is a layer of every tab, switched in the View tab."""

import contextlib
import dataclasses
import io

import pytest

from skyview.bench.coverage import CoverageConfig
from skyview.bench.coverage_sweep import run_coverage
from skyview.core.errors import BadInput
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
        box.value = False  # as the checkbox does
        assert not layer.visible
        box.value = True
        assert layer.visible
        session.close()
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            app.stop()


def test_a_folder_that_is_not_a_sweep_is_bad_input(tmp_path):
    from skyview.viewer.app import serve

    with pytest.raises(BadInput, match="not a coverage folder"):
        serve(port=0, coverage=tmp_path, say=lambda line: None)


def test_a_bench_comparison_is_shown_in_every_tab(tmp_path):
    """`skyview view --compare FILE`: the six-method table of `skyview bench --compare` in the Result tab."""
    from skyview.bench.compare import load_compare, run_simulated, save_compare
    from skyview.simulate.scenarios import SCENARIOS
    from skyview.viewer.app import ViewerApp
    from skyview.viewer.session import Session

    sim = run_simulated(SCENARIOS["cole8"], 2, 3, n_slow=1, methods=("angle",), variants=("paper", "improved"))
    path, _ = save_compare({"kind": "compare", "version": 1, "simulated": sim, "machine": {}, "wall_s": 1.0},
                           tmp_path, "cmp")
    report = load_compare(path)
    with contextlib.redirect_stdout(io.StringIO()):
        app = ViewerApp("127.0.0.1", 0, bench_report=report)
    try:
        session = Session(app.server, app.solvers, bench_report=app.bench_report)
        assert session.wait_idle(120)
        table = session.panel.bench_table.content
        assert "skyview bench --compare" in table and "| angle | improved | 2 |" in table
        session.close()
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            app.stop()
    for bad in ('{"kind": "coverage"}', "not json"):
        (tmp_path / "bad.json").write_text(bad)
        with pytest.raises(BadInput, match="bench --compare"):
            load_compare(tmp_path / "bad.json")
