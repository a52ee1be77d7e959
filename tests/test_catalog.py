"""The guide catalog against known stars, the shipped file against a rebuild, and the filters."""

import numpy as np
import pytest

from skyview.core.catalog import (
    ASSET_PATH,
    FLAG_DOUBLE,
    build_guide_catalog,
    chord,
    close_pairs,
    load_guide_catalog,
    radec_to_vec,
    save_guide_catalog,
    vec_to_radec,
)
from skyview.core.errors import BadInput

ARCSEC = np.radians(1 / 3600)


@pytest.fixture(scope="module")
def cat():
    return load_guide_catalog()


def _sep(v, w):
    return np.arctan2(np.linalg.norm(np.cross(v, w)), np.dot(v, w))


# SIMBAD ICRS J2000 positions (epoch 2000) and Hipparcos-2 Hp magnitudes
KNOWN = {
    32349: ("Sirius", 101.28715533, -16.71611586, -1.0876),
    27989: ("Betelgeuse", 88.79293899, 7.40706399, 0.4997),
    24436: ("Rigel", 78.63446707, -8.20163836, 0.1930),
}


@pytest.mark.parametrize("hip", sorted(KNOWN))
def test_known_stars_at_j2000(cat, hip):
    name, ra, dec, hp = KNOWN[hip]
    c2000 = cat.at_epoch(2000.0)
    i = c2000.index_of(hip)
    assert _sep(c2000.xyz[i], radec_to_vec(np.radians(ra), np.radians(dec))) < 0.5 * ARCSEC, name
    assert cat.mag[i] == pytest.approx(hp, abs=0.02), name


def test_sirius_moves_with_its_proper_motion(cat):
    # Sirius: pmRA* = -546.01 mas/yr, pmDE = -1223.07 mas/yr (hip2). At 2025.0, by hand from J2000:
    dec = -16.71611586 - 25 * 1.22307 / 3600
    ra = 101.28715533 - 25 * 0.54601 / 3600 / np.cos(np.radians(-16.7204))
    assert cat.epoch == 2025.0
    i = cat.index_of(32349)
    assert _sep(cat.xyz[i], radec_to_vec(np.radians(ra), np.radians(dec))) < 0.05 * ARCSEC
    assert _sep(cat.xyz[i], cat.at_epoch(2000.0).xyz[i]) == pytest.approx(33.5 * ARCSEC, rel=0.01)


def test_shipped_file_is_reproduced_by_a_rebuild(tmp_path, cat):
    rebuilt = build_guide_catalog()
    save_guide_catalog(rebuilt, tmp_path / "g.npz")
    again = load_guide_catalog(tmp_path / "g.npz")
    for name in ("hip", "mag", "pm", "flags"):
        np.testing.assert_array_equal(getattr(again, name), getattr(cat, name), err_msg=name)
    # the unit vectors to the last bit where this machine's numpy computes sin and cos as the one that built
    # the file did; its SIMD trigonometry differs by an ulp between instruction sets (AVX2 / AVX-512)
    np.testing.assert_allclose(again.xyz, cat.xyz, rtol=0, atol=4e-16)
    np.testing.assert_array_equal(np.isnan(again.bv), np.isnan(cat.bv))
    assert again.fingerprint == cat.fingerprint or not np.array_equal(again.xyz, cat.xyz)
    assert ASSET_PATH.exists()


def test_counts_and_sorting(cat):
    assert np.all(np.diff(cat.hip) > 0)
    np.testing.assert_allclose(np.linalg.norm(cat.xyz, axis=1), 1.0, atol=1e-12)
    assert len(cat.brighter_than(6.0)) == 4559  # Hipparcos-2 stars with Hp <= 6.0
    assert cat.mag.max() <= 9.0


def test_neighbour_query_equals_brute_force(cat):
    bright = cat.brighter_than(6.5)
    rng = np.random.default_rng(3)
    for _ in range(5):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        got = bright.within(d, np.radians(6.0))
        want = np.flatnonzero(bright.xyz @ d >= np.cos(np.radians(6.0)))
        np.testing.assert_array_equal(got, want)


def test_pairs_within_equals_brute_force(cat):
    sub = cat.brighter_than(4.0)
    pairs = sub.pairs_within(np.radians(10))
    cosang = sub.xyz @ sub.xyz.T
    i, j = np.nonzero(np.triu(cosang >= np.cos(np.radians(10)), 1))
    assert set(map(tuple, pairs)) == set(zip(i.tolist(), j.tolist()))


def test_close_pair_filter_removes_every_close_pair(cat):
    sub = cat.brighter_than(6.0)
    sep = np.radians(0.2)
    both = sub.without_close_pairs(sep)
    assert len(both.pairs_within(sep)) == 0
    n_close = len(np.unique(sub.pairs_within(sep)))
    assert len(both) == len(sub) - n_close
    bright = sub.without_close_pairs(sep, keep="brighter")
    assert len(both) < len(bright) < len(sub)
    assert len(sub.without_flags(FLAG_DOUBLE)) < len(sub)


@pytest.mark.parametrize("mag, deg", [(6.0, 0.01), (6.0, 0.2), (6.0, 3.0), (7.5, 0.2), (9.0, 1.0)])
def test_close_pairs_are_the_kd_trees_pairs(cat, mag, deg, monkeypatch):
    """close_pairs (a sweep along z, no scipy.spatial) gives cKDTree.query_pairs's pairs, in its sorted
    order: measured a bounded number at a time, and through the tree itself beyond SWEEP_PAIRS_MAX."""
    from scipy.spatial import cKDTree

    import skyview.core.catalog as catalog_module

    sub = cat.brighter_than(mag)
    ch = float(chord(np.radians(deg)))
    want = cKDTree(sub.xyz).query_pairs(ch, output_type="ndarray").astype(np.int64)
    want.sort(axis=1)
    want = want[np.lexsort((want[:, 1], want[:, 0]))]
    got = close_pairs(sub.xyz, ch)
    np.testing.assert_array_equal(got, want)
    assert got.dtype == np.int64 and len(got) > 0
    monkeypatch.setattr(catalog_module, "PAIRS_AT_ONCE", 997)  # many small pieces, one star's run at least
    np.testing.assert_array_equal(close_pairs(sub.xyz, ch), want)
    assert close_pairs(sub.xyz[:1], ch).shape == (0, 2) and close_pairs(sub.xyz, 0.0).shape == (0, 2)


def test_close_pairs_at_the_limit_are_the_trees_answer():
    """Two stars exactly one chord apart (to rounding) are decided by the tree, as query_pairs decides."""
    from scipy.spatial import cKDTree

    a = np.radians(0.2)
    xyz = np.array([[0.0, 0.0, 1.0], [np.sin(a), 0.0, np.cos(a)], [0.0, np.sin(2 * a), np.cos(2 * a)]])
    for ch in (float(np.linalg.norm(xyz[0] - xyz[1])), float(np.linalg.norm(xyz[0] - xyz[2]))):
        want = sorted(cKDTree(xyz).query_pairs(ch))
        assert [tuple(p) for p in close_pairs(xyz, ch).tolist()] == want


def test_chord_matches_angle():
    a = np.radians(7.0)
    v, w = radec_to_vec(0, 0), radec_to_vec(a, 0)
    assert np.linalg.norm(v - w) == pytest.approx(chord(a))


def test_missing_or_corrupt_catalog_is_bad_input(tmp_path):
    with pytest.raises(BadInput):
        load_guide_catalog(tmp_path / "nope.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(BadInput):
        load_guide_catalog(bad)


def _caps(rng, n):
    """Directions anywhere, near the poles and on RA 0 / 2 pi, with radii from arcseconds to most of the sky."""
    for k in range(n):
        if k % 3:
            dec = rng.choice([-1, 1]) * (np.pi / 2 - rng.exponential(0.1))
        else:
            dec = rng.uniform(-np.pi / 2, np.pi / 2)
        ra = rng.uniform(0, 2 * np.pi) if k % 5 else float(rng.choice([0.0, 2 * np.pi - 1e-12, 1e-9]))
        yield radec_to_vec(ra, dec), float(rng.choice([rng.uniform(0, 0.02), rng.uniform(0, 0.4), rng.uniform(0, 3.5)]))


@pytest.mark.parametrize("run", [True, False], ids=["z-run", "cells"])
def test_sky_index_gives_the_kd_tree_sets(catalog, monkeypatch, run):
    """within / ball_rows from the sky index (both of its ways of reading a cap) are the k-d tree's sets."""
    import skyview.core.catalog as C

    monkeypatch.setattr(C, "CAP_RUN", 10 ** 9 if run else -1)
    rng = np.random.default_rng(7)
    for sub in (catalog, catalog.brighter_than(6.0)):
        for d, r in _caps(rng, 300):
            want = np.sort(np.asarray(sub.tree.query_ball_point(d, float(chord(r))), dtype=np.int64))
            np.testing.assert_array_equal(sub.within(d, r), want)
        # a superset of every cap from the cells alone, ascending within a cell
        for d, r in _caps(rng, 100):
            got = set(sub.sky.cap(d, r).tolist())
            assert set(sub.tree.query_ball_point(d, float(chord(r)))) <= got


def test_sky_index_counts_and_nearest_are_the_kd_tree_answers(catalog):
    """ball_counts (with and without rows known to hold the stars) answers as the tree, chords exactly at a
    neighbour's distance and a hair either side included."""
    rng = np.random.default_rng(11)
    sub = catalog.brighter_than(7.0)
    for spread in (0.01, 0.3, 3.0):
        c0 = radec_to_vec(rng.uniform(0, 2 * np.pi), rng.uniform(-np.pi / 2, np.pi / 2))
        c = c0 + rng.normal(0, spread, (300, 3))
        c /= np.linalg.norm(c, axis=1)[:, None]
        ch = chord(rng.uniform(0, 0.05, 300))
        want = sub.tree.query_ball_point(c, ch, return_length=True)
        np.testing.assert_array_equal(sub.ball_counts(c, ch), want)
        np.testing.assert_array_equal(sub.ball_counts(c, float(ch[0])),
                                      sub.tree.query_ball_point(c, float(ch[0]), return_length=True))
    rows = rng.choice(len(sub), 400, replace=False)
    nn = sub.tree.query(sub.xyz[rows], k=2)[0][:, 1]
    for chords in (nn, nn * (1 + 1e-15), nn * (1 - 1e-15)):  # on the limit: the tree's own count
        want = sub.tree.query_ball_point(sub.xyz[rows], chords, return_length=True)
        np.testing.assert_array_equal(sub.ball_counts(sub.xyz[rows], chords), want)
        among = np.unique(np.concatenate([sub.within(x, 0.05) for x in sub.xyz[rows]]))
        np.testing.assert_array_equal(sub.ball_counts(sub.xyz[rows], chords, among), want)
        one = float(chords[0])  # one chord for all (the local density's)
        np.testing.assert_array_equal(sub.ball_counts(sub.xyz[rows], one, among),
                                      sub.tree.query_ball_point(sub.xyz[rows], one, return_length=True))


@pytest.mark.parametrize("run", [True, False], ids=["z-run", "cells"])
def test_sky_index_cap_cosines(catalog, monkeypatch, run):
    """cap_cosines: every star within the angle, ascending, each with its cosine to the centre; nothing
    a dot product puts beyond the angle."""
    import skyview.core.catalog as C

    monkeypatch.setattr(C, "CAP_RUN", 10 ** 9 if run else -1)
    rng = np.random.default_rng(9)
    for d, r in _caps(rng, 200):
        rows, cos = catalog.sky.cap_cosines(d, r)
        with_xyz = catalog.sky.cap_cosines(d, r, with_xyz=True)
        assert np.array_equal(with_xyz[0], rows) and np.array_equal(with_xyz[1], cos)
        assert np.array_equal(with_xyz[2], catalog.xyz[rows])  # the same numbers, read from the run
        want = np.sort(np.asarray(catalog.tree.query_ball_point(d, float(chord(r))), dtype=np.int64))
        assert np.all(np.diff(rows) > 0) and set(want.tolist()) <= set(rows.tolist())
        np.testing.assert_allclose(cos, catalog.xyz[rows] @ (d / np.linalg.norm(d)), rtol=0, atol=1e-15)
        assert np.all(cos >= np.cos(min(r, np.pi)) - 1e-9)


def test_radec_table_is_each_rows_own_conversion(catalog):
    """GuideCatalog.radec_deg, row for row, is np.degrees(vec_to_radec(xyz[rows])) of any subset to the bit
    (what a solve's matched stars report)."""
    rng = np.random.default_rng(12)
    ra, dec = catalog.radec_deg
    for k in range(300):
        rows = rng.choice(len(catalog), int(rng.integers(1, 70)), replace=False)
        want_ra, want_dec = np.degrees(vec_to_radec(catalog.xyz[rows]))
        assert np.array_equal(ra[rows], want_ra) and np.array_equal(dec[rows], want_dec)


def test_sky_index_is_small_and_lazy(catalog):
    fresh = load_guide_catalog()
    assert "sky" not in fresh.__dict__ and "tree" not in fresh.__dict__
    fresh.within(radec_to_vec(1.0, 0.5), np.radians(10))
    assert "sky" in fresh.__dict__ and "tree" not in fresh.__dict__  # no k-d tree built for it
    assert fresh.sky.nbytes <= 50 * len(fresh) + 56 * 6 * 16 * 16


def test_a_subset_reads_its_sky_index_off_its_parents_and_gets_the_sorted_one():
    """A catalog cut by magnitude (the verification's depth) takes its parent's sky index with the other
    stars left out: the arrays a fresh sort gives, and the same cone queries."""
    from skyview.core.catalog import SkyIndex

    full = load_guide_catalog()
    full.within(radec_to_vec(1.0, 0.5), np.radians(10))  # the parent's index made
    rng = np.random.default_rng(4)
    for m in (4.0, 6.25, 7.5):
        sub = full.brighter_than(m)
        assert "sky" in sub.__dict__  # read off the parent's
        fresh = SkyIndex(sub.xyz)
        for name in ("by_z", "xyz_z", "z"):
            assert np.array_equal(getattr(sub.sky, name), getattr(fresh, name)), (m, name)
        for _ in range(5):
            c = radec_to_vec(rng.uniform(0, 2 * np.pi), rng.uniform(-1.5, 1.5))
            assert np.array_equal(sub.within(c, np.radians(8)), np.sort(sub.tree.query_ball_point(c, chord(
                np.radians(8)))))
    # a few rows' RA / Dec are the whole table's numbers
    rows = rng.choice(len(full), 37, replace=False)
    ra, dec = full.radec_deg_of(rows)
    assert "radec_deg" not in full.__dict__
    assert np.array_equal(ra, full.radec_deg[0][rows]) and np.array_equal(dec, full.radec_deg[1][rows])


def test_a_large_catalogs_sky_index_is_built_once_and_read_from_the_cache(tmp_path, monkeypatch):
    """The guide catalog's sky index (its z order and cells) is sorted once per catalog and read from the
    cache after that (into memory): the same arrays and the same answers as sorting it in the process."""
    from skyview.core.catalog import SkyIndex
    from skyview.identify import database

    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    first = database.with_cached_sky_index(load_guide_catalog())
    files = list((tmp_path / "databases").glob("sky_index-*.npz"))
    assert len(files) == 1 and "sky" in first.__dict__
    again = database.with_cached_sky_index(load_guide_catalog())
    # read from the file, not sorted again (in memory: the map's pages would make its gathers slower)
    assert not isinstance(again.sky.by_z, np.memmap) and again.sky.by_z.flags.owndata
    with monkeypatch.context() as m:
        m.setattr(SkyIndex, "__init__", lambda *a: pytest.fail("sorted again"))
        again = database.with_cached_sky_index(load_guide_catalog())
    fresh = SkyIndex(again.xyz)
    for name in ("by_z", "xyz_z", "z"):
        assert np.array_equal(getattr(again.sky, name), getattr(fresh, name)), name
    for a, b in zip(again.sky.cells, fresh.cells):
        assert np.array_equal(a, b)
    rng = np.random.default_rng(9)
    for angle in (3.0, 20.0, 70.0):  # a run of declinations, and the cells (a wide cap on the deep end)
        c = radec_to_vec(rng.uniform(0, 2 * np.pi), rng.uniform(-1.5, 1.5))
        assert np.array_equal(again.within(c, np.radians(angle)), np.sort(again.tree.query_ball_point(
            c, chord(np.radians(angle)))))
    # a catalog at another epoch has its own index; a small catalog is sorted in the process (a millisecond)
    other = database.with_cached_sky_index(load_guide_catalog(epoch=2050.0))
    assert len(list((tmp_path / "databases").glob("sky_index-*.npz"))) == 2 and "sky" in other.__dict__
    small = database.with_cached_sky_index(load_guide_catalog().brighter_than(5.0))
    assert "sky" not in small.__dict__


def test_a_magnitude_cut_is_made_once_and_the_cuts_kept_are_bounded(cat):
    from skyview.core.catalog import MAX_KEPT_CUTS

    a = cat.brighter_than(5.5)
    assert cat.brighter_than(5.5) is a  # the same cut, not a copy hashed again for the database keys
    assert len(a) == int(np.count_nonzero(cat.mag <= 5.5)) and np.all(a.mag <= 5.5)
    assert a.fingerprint == cat.select(cat.mag <= 5.5, "again").fingerprint
    for k in range(MAX_KEPT_CUTS):
        cat.brighter_than(4.0 + 0.1 * k)
    assert len(cat.__dict__["_cuts"]) == MAX_KEPT_CUTS
    assert cat.brighter_than(5.5) is not a  # the oldest cut went; made again, the same stars
    assert np.array_equal(cat.brighter_than(5.5).hip, a.hip)
    # a numpy float64 limit compares in float64, a Python float in float32 (the magnitudes' type): at 6.3 the
    # two cuts differ, and each keeps its own
    wide, narrow = cat.brighter_than(6.3), cat.brighter_than(np.float64(6.3))
    assert len(wide) == int(np.count_nonzero(cat.mag <= 6.3))
    assert len(narrow) == int(np.count_nonzero(cat.mag <= np.float64(6.3))) < len(wide)
