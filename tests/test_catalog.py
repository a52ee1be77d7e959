"""The guide catalog against known stars, the shipped file against a rebuild, and the filters."""

import numpy as np
import pytest

from skyview.catalog import (ASSET_PATH, FLAG_DOUBLE, build_guide_catalog, chord, load_guide_catalog,
                             radec_to_vec, save_guide_catalog)
from skyview.errors import BadInput

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
    for name in ("hip", "xyz", "mag", "pm", "flags"):
        np.testing.assert_array_equal(getattr(again, name), getattr(cat, name), err_msg=name)
    np.testing.assert_array_equal(np.isnan(again.bv), np.isnan(cat.bv))
    assert again.fingerprint == cat.fingerprint
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
