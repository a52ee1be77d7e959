"""The k-vector returns exactly the brute-force range, on random data and on real pair angles."""

import numpy as np
import pytest

from skyview.core.catalog import load_guide_catalog
from skyview.identify.kvector import KVector
from skyview.identify.verify import angular_distance


def brute(values, lo, hi):
    return np.flatnonzero((values >= lo) & (values <= hi))


def check(kv, values, lo, hi):
    got = np.sort(kv.query(lo, hi))
    np.testing.assert_array_equal(got, brute(values, lo, hi))
    start, stop = kv.ranges([lo], [hi])
    assert stop[0] - start[0] == len(got)
    assert kv.range(lo, hi) == (int(start[0]), int(stop[0]))


@pytest.mark.parametrize("fit", ["line", "parabola"])
def test_random_data_matches_brute_force(fit):
    rng = np.random.default_rng(7)
    makers = [
        lambda n: rng.normal(size=n),
        lambda n: rng.exponential(size=n) ** 3,  # far from linear when sorted
        lambda n: np.round(rng.normal(size=n), 1),  # many duplicates
        lambda n: rng.integers(0, 3, size=n).astype(float),  # almost all duplicates
    ]
    for trial in range(60):
        n = int(rng.integers(0, 400))
        values = makers[trial % len(makers)](n)
        kv = KVector(values, fit=fit)
        for _ in range(25):
            lo, hi = np.sort(rng.normal(size=2) * 2.5)
            check(kv, values, lo, hi)
        for v in values[:10]:  # bounds exactly on stored values (duplicates included)
            check(kv, values, v, v)
            check(kv, values, v, v + 0.1)
            check(kv, values, v - 0.1, v)


@pytest.mark.parametrize("fit", ["line", "parabola"])
def test_vectorised_ranges_equal_scalar_queries(fit):
    rng = np.random.default_rng(3)
    values = rng.random(5000) ** 0.5
    kv = KVector(values, fit=fit)
    lo = rng.uniform(-0.1, 1.1, size=2000)
    hi = lo + rng.uniform(-0.01, 0.05, size=2000)  # some inverted ranges
    start, stop = kv.ranges(lo, hi)
    s = np.sort(values)
    expected = np.where(lo <= hi, np.searchsorted(s, hi, "right") - np.searchsorted(s, lo, "left"), 0)
    np.testing.assert_array_equal(stop - start, np.maximum(expected, 0))
    np.testing.assert_array_equal(kv.count(lo, hi), stop - start)
    for k in range(0, 2000, 97):
        assert kv.range(lo[k], hi[k]) == (start[k], stop[k])
    # the k-vector walk (Mortari's superset + bisection) gives the very same slices as the binary searches
    ks, ke = kv.ranges_kvector(lo, hi)
    np.testing.assert_array_equal(ks, start)
    np.testing.assert_array_equal(ke, stop)


def test_edge_cases():
    values = np.array([1.0, 2.0, 2.0, 2.0, 3.0, 5.0])
    kv = KVector(values)
    assert len(kv.query(-10, 0.5)) == 0  # entirely below the data
    assert len(kv.query(6.0, 9.0)) == 0  # entirely above
    assert len(kv.query(3.5, 4.5)) == 0  # a gap inside the data
    assert len(kv.query(4.0, 3.0)) == 0  # inverted range
    assert len(kv.query(np.nan, 3.0)) == 0
    np.testing.assert_array_equal(np.sort(kv.query(2.0, 2.0)), [1, 2, 3])  # duplicates, closed range
    np.testing.assert_array_equal(np.sort(kv.query(-np.inf, np.inf)), np.arange(6))
    np.testing.assert_array_equal(np.sort(kv.query(0.0, 100.0)), np.arange(6))
    # the line passes below the first and above the last value: k[0] = 0 and k[-1] = n
    assert kv.k[0] == 0 and kv.k[-1] == len(values)

    empty = KVector(np.array([]))
    assert len(empty.query(0, 1)) == 0 and empty.range(0, 1) == (0, 0)
    one = KVector(np.array([0.5]))
    np.testing.assert_array_equal(one.query(0, 1), [0])
    assert len(one.query(0.6, 1)) == 0
    same = KVector(np.full(50, 4.2))
    assert len(same.query(4.2, 4.2)) == 50 and len(same.query(4.3, 5)) == 0
    negative = KVector(-np.arange(10.0))
    np.testing.assert_array_equal(np.sort(negative.query(-3.5, -1.0)), [1, 2, 3])

    with pytest.raises(ValueError):
        KVector(np.array([1.0, np.nan]))
    with pytest.raises(ValueError):
        KVector(np.array([2.0, 1.0]), presorted=True)
    with pytest.raises(ValueError):
        KVector(values, fit="cubic")


def test_query_returns_original_indices():
    values = np.array([0.3, 0.1, 0.2, 0.9, 0.5])
    kv = KVector(values)
    idx = kv.query(0.15, 0.6)
    assert sorted(idx.tolist()) == [0, 2, 4]
    assert np.all(np.diff(values[idx]) >= 0)  # in sorted-value order


def test_real_pair_angles_and_persistence():
    cat = load_guide_catalog().brighter_than(6.0)
    pairs = cat.pairs_within(np.radians(8.0))
    ang = angular_distance(cat.xyz[pairs[:, 0]], cat.xyz[pairs[:, 1]])
    rng = np.random.default_rng(11)
    for fit in ("line", "parabola"):
        kv = KVector(ang, fit=fit)
        kv2 = KVector.from_arrays(kv.to_arrays(prefix="x_"), prefix="x_")
        bound = 3 * np.sqrt(2) * 87e-6
        for theta in rng.uniform(-0.001, np.radians(8.2), size=150):
            expected = brute(ang, theta - bound, theta + bound)
            np.testing.assert_array_equal(np.sort(kv.query(theta - bound, theta + bound)), expected)
            np.testing.assert_array_equal(np.sort(kv2.query(theta - bound, theta + bound)), expected)
        # the extreme values themselves
        check(kv, ang, ang.min(), ang.min())
        check(kv, ang, ang.max(), ang.max())
