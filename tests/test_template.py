"""The identifier template: a seventh method is one module and one registry line.

`ToyMethod` below is the whole of a method (the worked example of docs/architecture.md): its parameters
(a frozen dataclass with its checks), its database (every catalog pair closer than the sensor's
diagonal, sorted by separation, cached by `skyview.identify.database`) and its hypotheses (the two
brightest stars looked up as a pair, the third brightest confirming it). The template
(`Identifier.identify`) does the rest: sigma, input checks, the too-few-stars exit, verification with
the running hypothesis count, acceptance, the failure reason, timing. Registered at run time, it
shows up in make_identifier, the CLI, the bench and the step drawables with no other edit.
"""

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from skyview.core.errors import BadInput
from skyview.identify import (
    FAILED,
    IDENTIFIED,
    INCONCLUSIVE,
    METHODS,
    Hypothesis,
    Identifier,
    Search,
    Status,
    Step,
    database,
    make_identifier,
    register,
)
from skyview.identify.layers import Hypotheses
from skyview.identify.params import MethodParams, at_least, parameter_table, positive
from skyview.identify.steps import LazyStep
from skyview.identify.verify import angular_distance

DOCS = Path(__file__).resolve().parents[1] / "docs"


# ---------------------------------------------------------------------- the toy method (one module's worth)

@dataclasses.dataclass(frozen=True)
class ToyParams(MethodParams):
    """beta: the pair's separation bound in sigmas of a separation (sqrt(2) sigma); max_candidates:
    the catalog pairs tried."""

    beta: float = 3.0
    max_candidates: int = 2000

    def __post_init__(self):
        super().__post_init__()
        positive("beta", self.beta)
        at_least("max_candidates", self.max_candidates, 1)


class ToyMethod(Identifier):
    """Pair lookup by separation, the third brightest star confirming: a seventh method in ~40 lines."""

    name = "toy"
    title = "the toy method"
    paper_scenario = "cole8"  # the conditions it is meant for: the bench's, the comparison's, the recordings' default
    Params = ToyParams
    improved_params = dataclasses.replace(ToyParams(), beta=4.0).changed()

    def __init__(self, catalog, camera, sigma_rad, **params):
        self.configure(catalog, camera, sigma_rad, params)  # ToyParams checked, set as attributes
        max_sep = 2.0 * camera.half_diagonal_rad
        self.database_key = database.make_key(self.name, {"max_sep_rad": max_sep}, catalog, camera)

        def build():
            pairs = catalog.pairs_within(max_sep)
            sep = angular_distance(catalog.xyz[pairs[:, 0]], catalog.xyz[pairs[:, 1]])
            o = np.argsort(sep)
            return {"pairs": pairs[o], "sep": sep[o]}

        arrays, self.database_info = database.load_or_build(self.database_key, build)
        self.pairs, self.sep = arrays["pairs"], arrays["sep"]

    @property
    def n_patterns(self) -> int:
        return len(self.sep)

    def hypotheses(self, search: Search):
        V, tol = search.V, self.beta * np.sqrt(2.0) * search.sigma
        d01, d02, d12 = (float(angular_distance(V[i], V[j])) for i, j in ((0, 1), (0, 2), (1, 2)))
        lo, hi = np.searchsorted(self.sep, [d01 - tol, d01 + tol])
        cand = self.pairs[lo:hi][:self.max_candidates]
        both = np.concatenate([cand, cand[:, ::-1]])  # either star may be the brighter one
        xyz = self.catalog.xyz
        keep = []
        for a, b in both.tolist():  # the third star: a catalog star at d02 from a and d12 from b
            near = self.catalog.within(xyz[a], d02 + tol)
            ok = near[(np.abs(angular_distance(xyz[near], xyz[a]) - d02) <= tol)
                      & (np.abs(angular_distance(xyz[near], xyz[b]) - d12) <= tol)]
            keep += [(a, b, int(c)) for c in ok.tolist()]
        search.steps.append(Step("lookup", f"pair 0-1 ({np.degrees(d01):.3f} deg): {len(both)} oriented catalog "
                                           f"pairs, {len(keep)} confirmed by star 2",
                                 observed=[0, 1, 2], numbers={"pairs": len(both), "confirmed": len(keep)},
                                 layers=(Hypotheses.sample((0, 1, 2), np.array(keep).reshape(-1, 3)),)))
        search.stats["confirmed"] = len(keep)
        for a, b, c in keep:
            ver = yield Hypothesis({0: a, 1: b, 2: c})
            search.reasons.append(f"{a}-{b}-{c}: {ver.reason}")


@pytest.fixture
def toy():
    """The one registry line (at run time here; a module of the package adds its line to METHODS)."""
    register("toy", ToyMethod)
    yield ToyMethod
    METHODS.unregister("toy")


@pytest.fixture(scope="module")
def frame(cat, cam):
    from skyview.core.attitude import random_attitudes
    from skyview.identify.synthetic import synthetic_frame

    rng = np.random.default_rng(3)
    return synthetic_frame(cat, cam, random_attitudes(1, rng)[0], 87e-6, rng)


# ---------------------------------------------------------------------- through make_identifier

def test_the_toy_method_identifies_through_the_template(toy, cat, cam, frame):
    ident = make_identifier("toy", cat, cam, 87e-6)
    r = ident.identify(frame.obs)
    assert r.status == IDENTIFIED == "identified" and isinstance(r.status, Status)
    assert all(frame.truth[o] == c for o, c in r.matches.items()) and len(r.matches) >= 4
    # the template's part: timing, the hypothesis count (Bonferroni), the verify step, the database key
    assert r.stats["time_s"] > 0 and r.stats["stars"] == len(frame.obs) and r.stats["confirmed"] >= 1
    assert r.verification["n_hypotheses"] >= 1 and r.verification["passed"]
    assert [s.kind for s in r.steps][0] == "lookup" and r.steps[-1].kind == "verify"
    assert r.database_key == database.key_string(ident.database_key)
    json.dumps(r.to_dict())


def test_the_template_counts_every_hypothesis_and_gives_the_reason(toy, cat, cam, frame):
    ident = make_identifier("toy", cat, cam, 87e-6, threshold=1e-300)  # nothing can pass
    r = ident.identify(frame.obs)
    n = len([s for s in r.steps if s.kind == "verify"])
    assert r.status == INCONCLUSIVE and n == r.stats["confirmed"] >= 1
    assert r.verification["n_hypotheses"] == n  # one per hypothesis, counted as they come
    assert r.reason.count(":") >= n and not r.matches


def test_too_few_stars_and_bad_input(toy, cat, cam, frame):
    ident = make_identifier("toy", cat, cam, 87e-6)
    few = dataclasses.replace(frame.obs, vectors=frame.obs.vectors[:2], uv=frame.obs.uv[:2],
                              brightness=frame.obs.brightness[:2])
    r = ident.identify(few)
    assert r.status == FAILED and r.reason == "the toy method needs at least 3 stars, the frame has 2"
    assert set(r.stats) == {"stars", "time_s"}
    bad = dataclasses.replace(frame.obs, vectors=np.full((4, 3), np.nan))
    with pytest.raises(BadInput, match="finite"):
        ident.identify(bad)
    for params, words in (({"beta": -1}, "beta must be a positive number"),
                          ({"max_candidates": 0}, "max_candidates must be an integer >= 1"),
                          ({"statistic": "x"}, "unknown verification statistic"),
                          ({"betta": 1}, "no parameter 'betta'")):
        with pytest.raises(BadInput, match=words):
            make_identifier("toy", cat, cam, 87e-6, **params)


def test_parameters_are_declared_once(toy, cat, cam):
    assert list(ToyMethod.parameters())[:2] == ["beta", "max_candidates"]  # its own first, then verification's
    assert make_identifier("toy", cat, cam, 87e-6, variant="improved").beta == 4.0
    assert make_identifier("toy", cat, cam, 87e-6, variant="improved", beta=2.5).beta == 2.5
    # the six methods' improved variants are replaces of their paper defaults
    for name in ("svd", "ellipticity", "genetic", "stochastic"):
        cls = METHODS[name]
        imp = dataclasses.replace(cls.Params(), **cls.improved_params)
        assert imp.changed() == cls.improved_params and cls.Params().changed() == {}


def test_the_parameter_table_in_the_docs_is_current():
    text = (DOCS / "methods.md").read_text()
    block = re.search(r"<!-- parameters:begin -->\n(.*?)\n<!-- parameters:end -->", text, re.S)
    assert block, "docs/methods.md lost its generated parameter table"
    builtin = {k: METHODS[k] for k in METHODS if k != "toy"}
    assert block.group(1) == parameter_table(builtin), "regenerate with: python -m skyview.identify.params"


def test_status_keeps_its_strings():
    assert json.dumps({"s": IDENTIFIED}) == '{"s": "identified"}' and f"{FAILED}" == "failed"
    assert Status("inconclusive") is INCONCLUSIVE


def test_a_lazy_step_is_the_step_it_stands_for():
    """A LazyStep computes its catalog rows and groups when first read, once, and reads, compares,
    copies, replaces and pickles as the Step with those contents."""
    import copy
    import pickle

    made = []
    lazy = LazyStep("pivot", "pivoted", observed=[1, 2], catalog_of=lambda: made.append("c") or [5, 7],
                    groups_of=lambda: made.append("g") or [(5, 7)], numbers={"hypotheses": 3.0})
    assert made == []
    plain = Step("pivot", "pivoted", [1, 2], [5, 7], [(5, 7)], {"hypotheses": 3.0})
    assert lazy.catalog == [5, 7] and made == ["c"]
    assert lazy == plain and plain == lazy and lazy.to_dict() == plain.to_dict()
    assert made == ["c", "g"] and lazy.groups == [(5, 7)] and made == ["c", "g"]
    back = pickle.loads(pickle.dumps(lazy))
    assert type(back) is Step and back == plain and copy.deepcopy(lazy) == plain
    assert dataclasses.asdict(lazy) == dataclasses.asdict(plain)
    assert dataclasses.replace(lazy, note="other").note == "other"
    lazy.catalog = [9]
    assert lazy.catalog == [9] and lazy != plain
    assert LazyStep("x", "y") == Step("x", "y")
    # the note, the figures and the layers may be made when read, too
    layer = Hypotheses.single({1: 5, 2: 7})
    lazier = LazyStep("pivot", note_of=lambda: made.append("n") or "pivoted", observed=[1, 2],
                      catalog_of=lambda: [5, 7], groups_of=lambda: [(5, 7)],
                      numbers_of=lambda: made.append("f") or {"hypotheses": 3.0},
                      layers_of=lambda: made.append("l") or (layer,))
    made.clear()
    assert lazier.numbers == {"hypotheses": 3.0} and made == ["f"]
    full = dataclasses.replace(plain, layers=(layer,))
    assert lazier == full and made == ["f", "n", "l"] and lazier.layer(Hypotheses) is layer
    back = pickle.loads(pickle.dumps(lazier))  # (its layer a copy: compared by its contents)
    assert dataclasses.replace(back, layers=()) == dataclasses.replace(plain, layers=())
    assert back.layers[0].used == (1, 2) and back.layers[0].rows.tolist() == [[5, 7]]
    assert lazier.to_dict() == full.to_dict()
    assert made == ["f", "n", "l"]  # each made once
    lazier.note = "other"
    assert lazier.note == "other" and lazier != full


# ---------------------------------------------------------------------- the sinks: CLI, bench, drawables

def test_the_toy_method_in_the_cli_the_bench_and_the_drawables(toy, cat, cam, frame, tmp_path, capsys):
    from skyview.bench.runner import run_bench
    from skyview.cli import main
    from skyview.present.drawables import step_views
    from skyview.simulate.scenarios import get_scenario

    png = tmp_path / "orion.png"
    assert main(["simulate", "--ra", "83.8", "--dec", "-5.4", "--roll", "30", "--fov-deg", "8", "--seed", "1",
                 "--out", str(png)]) == 0
    capsys.readouterr()
    rrd = tmp_path / "toy.rrd"
    assert main(["solve", str(png), "--fov-deg", "8", "--method", "toy", "--json", "--record", str(rrd)]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["status"] == "solved" and res["method"] == "toy"
    # the recording: the toy's steps on the step timeline, the identification drawn
    from rerun.chunk import RrdReader

    timelines: dict[str, set] = {}
    for ch in RrdReader(rrd).stream():
        timelines.setdefault(ch.entity_path, set()).update(ch.timeline_names)
    assert "step" in timelines["/steps/log"] and {"/sky/matches", "/camera/image/matches"} <= set(timelines)

    # the viewer: the toy in its method list, and solved there with its steps drawn
    from skyview.viewer.run import SceneConfig, Solvers, check_method, simulate, solve, viewer_methods

    assert "toy" in viewer_methods() and check_method("toy", "improved") == ("toy", "improved")
    scene = SceneConfig(ra_deg=83.8, dec_deg=-5.4, roll_deg=30.0, fov_deg=8.0)
    solvers = Solvers()
    run = solve(simulate(scene, solvers.base_catalog), "toy", "paper", scene.mag_limit, solvers)
    assert run.result.solved and run.result.method == "toy" and run.result.identification.steps

    b = run_bench("toy", get_scenario("cole8"), 4, seed=0, progress=False)
    assert b["counts"]["correct"] >= 2 and b["counts"]["incorrect"] == 0  # weak (no false-star handling), never wrong

    # the comparison and the example recordings find it in the registry, with its own scenario: no list
    # outside its module names it
    from skyview.bench.compare import method_order, run_simulated, slow_methods
    from skyview.present.text import paper_scenario

    assert "toy" in method_order() and "toy" not in slow_methods() and "genetic" in slow_methods()
    assert paper_scenario("toy") == "cole8" and paper_scenario("angle") == "cole8" and paper_scenario("blind") is None
    sim = run_simulated(get_scenario("cole8"), 2, 0, n_slow=1, methods=("toy",))
    assert {row["method"] for row in sim["rows"]} == {"toy"} and all(row["incorrect"] == 0 for row in sim["rows"])

    r = make_identifier("toy", cat, cam, 87e-6).identify(frame.obs)
    views = step_views(r.steps, cat.xyz, len(frame.obs), camera=cam, hip=cat.hip)
    assert len(views) == len(r.steps) and views[0].drawables and views[0].surviving == r.stats["confirmed"]
