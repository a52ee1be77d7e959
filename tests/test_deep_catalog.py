"""The deep catalog (Hipparcos-2 + Gaia DR3 to G 10) and the narrow fields it solves (issue 27, item 2).

The truth here is the simulator's: frames of 1-1.5 deg rendered from the deep catalog at known attitudes.
The database of narrow fields is built once per session (~45 s, ~1.3 GB at its peak): those tests are slow.
"""

import numpy as np
import pytest

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.camera import Camera
from skyview.core.catalog import GAIA_ID_MIN, designation
from skyview.core.deep_catalog import GAIA_EPOCH, MATCH_ARCSEC, build_deep_catalog, load_deep_catalog, read_gaia
from skyview.simulate.render import SensorModel, simulate_image
from skyview.simulate.scenarios import get_scenario


@pytest.fixture(scope="module")
def deep(catalog):
    return load_deep_catalog(catalog.epoch)


def test_deep_catalog_keeps_every_hipparcos_star_and_adds_gaia_to_g10(catalog, deep):
    hip = deep.hip < GAIA_ID_MIN
    assert hip.sum() == len(catalog)  # every Hipparcos star, once
    rows = catalog.rows_of(deep.hip[hip])
    np.testing.assert_array_equal(deep.xyz[hip], catalog.xyz[rows])  # its own position at the epoch
    np.testing.assert_array_equal(deep.mag[hip], catalog.mag[rows])
    gaia = ~hip
    assert 350_000 < gaia.sum() < 482_176  # Gaia's stars to G 10 that Hipparcos does not hold
    assert deep.mag[gaia].max() <= 10.0 and np.all(deep.pm[gaia] == 0.0)
    assert np.all(np.diff(deep.mag) >= 0)  # brightest first
    # no Gaia star is a Hipparcos star counted twice: none where Gaia saw a Hipparcos star (J2016.0) unless
    # fainter than it by more than 1.5 mag (a companion)
    from scipy.spatial import cKDTree

    from skyview.core.catalog import propagate

    at_gaia = propagate(deep.xyz[hip], deep.pm[hip].astype(np.float64), GAIA_EPOCH - deep.epoch)
    d, k = cKDTree(at_gaia).query(deep.xyz[gaia], distance_upper_bound=np.radians(MATCH_ARCSEC / 3600.0))
    close = np.isfinite(d)
    assert 0 < close.sum() < 2000
    assert np.all(deep.mag[gaia][close] - deep.mag[hip][k[close]] > 1.5)


def test_deep_catalog_reads_the_gaia_file_as_it_is_written():
    g = read_gaia()
    assert len(g) == 482_176 and g["g"].max() <= 10.0
    # Barnard's star (Gaia DR3 4472832130942575872): G 8.19 at its J2016.0 place; the two columns after the
    # magnitude are BP and RP (9.7, 7.0), not its proper motion (-802, +10362 mas/yr): none is taken from them
    b = g[g["source_id"] == 4472832130942575872][0]
    assert abs(b["ra"] - 269.4485) < 1e-3 and abs(b["dec"] - 4.7394) < 1e-3 and abs(b["g"] - 8.19) < 0.01
    assert 9.5 < b["bp"] < 10.0 and 6.8 < b["rp"] < 7.1


def test_a_hipparcos_star_matched_in_gaia_is_found_at_gaias_epoch(catalog):
    # a small Gaia file made of three guide-catalog stars put where Gaia saw them, and one star of its own
    from skyview.core.catalog import propagate, vec_to_radec
    from skyview.core.deep_catalog import _RECORD

    fastest = int(np.argmax(np.hypot(*catalog.pm.T)))  # it moves arcseconds a year: found only where Gaia saw it
    rows = np.array([catalog.index_of(32349), fastest, catalog.index_of(11767)])
    at_gaia = propagate(catalog.xyz[rows], catalog.pm[rows].astype(np.float64), GAIA_EPOCH - catalog.epoch)
    ra, dec = np.degrees(vec_to_radec(at_gaia))
    g = np.zeros(4, dtype=_RECORD)
    g["source_id"] = [2947050466531873024, 4472832130942575872, 576465654691848192, 5_000_000_000]
    g["ra"], g["dec"] = np.r_[ra, 10.0], np.r_[dec, 20.0]
    g["g"] = np.r_[catalog.mag[rows] + 0.2, 9.5]
    merged = build_deep_catalog(catalog.epoch, hipparcos=catalog, gaia=g)
    assert len(merged) == len(catalog) + 1  # the three found, the fourth added
    assert np.degrees(np.hypot(*catalog.pm[fastest])) * 3600 * (catalog.epoch - GAIA_EPOCH) > 3 * MATCH_ARCSEC
    assert designation(merged.hip[merged.hip >= GAIA_ID_MIN][0]) == "Gaia DR3 5000000000"
    assert designation(32349) == "HIP 32349"


def test_the_simulator_renders_the_deep_catalogs_faint_stars(deep):
    sc = get_scenario("narrow1.5")
    R = random_attitudes(1, np.random.default_rng(3))[0]
    fr = simulate_image(deep, sc.camera(), R, sc.sensor(), seed=1, **sc.render_kwargs())
    mags = np.array([s["mag"] for s in fr.truth["stars"]])
    assert len(mags) >= 5 and mags.max() > 9.0  # stars beyond Hipparcos's Hp 9


def _narrow_frame(deep, fov: float, seed: int):
    R = random_attitudes(seed + 1, np.random.default_rng(seed))[-1]
    fr = simulate_image(deep, Camera.from_fov(fov, 1024, 768), R, SensorModel(exposure_s=2.0), seed=seed,
                        mag_limit=10.0)
    return fr, R


@pytest.mark.slow
def test_a_narrow_field_is_solved_blind_in_the_deep_catalog(deep):
    from skyview.solver.pipeline import solve_image

    solved = 0
    for seed in range(4):
        fr, R = _narrow_frame(deep, 1.5, seed)
        res = solve_image(fr.image)
        if not res.solved:
            continue
        solved += 1
        err = attitude_error_arcsec(res.R, R)
        assert err["boresight"] < 2.0, err  # 5.3 arcsec pixels
        assert abs(res.camera.fov_deg / 1.5 - 1.0) < 1e-3
        assert any("deep catalog" in n for n in res.notes)
        names = {m["hip"]: m["name"] for m in res.matches}
        assert any(n.startswith("Gaia DR3 ") for n in names.values())
        truth = {(round(s["u"]), round(s["v"])): s["hip"] for s in fr.truth["stars"]}
        for m in res.matches:  # every match names the star rendered there
            near = [h for (u, v), h in truth.items() if abs(u - m["u"]) <= 2 and abs(v - m["v"]) <= 2]
            assert m["hip"] in near
    assert solved >= 3
    # told not to, the guide catalog alone does not reach it: no answer rather than a wrong one
    fr, _ = _narrow_frame(deep, 1.5, 0)
    assert not solve_image(fr.image, deep=False).solved


@pytest.mark.slow
def test_the_narrow_field_bench_scores_against_the_deep_catalogs_truth():
    from skyview.bench.runner import run_blind_bench

    s = run_blind_bench(get_scenario("narrow1.5"), 4, progress=False)
    assert s["counts"]["incorrect"] == 0 and s["counts"]["correct"] >= 3
