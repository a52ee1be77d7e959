"""The angle method (Cole & Crassidis) end to end on vector-level frames with known truth."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from skyview.core.attitude import attitude_error_arcsec, random_attitudes
from skyview.core.camera import Camera
from skyview.core.errors import BadInput
from skyview.core.lru import LRU
from skyview.identify import FAILED, IDENTIFIED, METHODS, database, make_identifier
from skyview.identify.angle import AngleMethod, _close, _join, _Ranges
from skyview.identify.base import Observation
from skyview.identify.pivot import Restarts
from skyview.identify.synthetic import add_noise, synthetic_frame
from skyview.identify.verify import angular_distance

SIGMA = 87e-6


@pytest.fixture(scope="module")
def ident(cache, cat, cam):
    return make_identifier("angle", cat, cam, SIGMA)


def frames(cat, cam, n, seed, n_min=6, false_stars=0):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        R = random_attitudes(1, rng)[0]
        if len(cam.visible(R, cat.xyz)[0]) < n_min:
            continue
        out.append(synthetic_frame(cat, cam, R, SIGMA, rng, false_stars=false_stars))
    return out


def assert_correct(result, frame):
    assert result.status == IDENTIFIED, result.reason
    assert len(result.matches) >= 3
    for o, c in result.matches.items():
        assert frame.truth[o] == c
    err = attitude_error_arcsec(result.R, frame.R)
    assert err["boresight"] < 60.0  # pointing within 1 arcmin
    # roll about the boresight is ~2 arcmin (1 sigma) at 8 deg and 87 microradians: check it
    # against the reported covariance instead
    assert abs(err["roll"]) < 5.0 * np.sqrt(result.attitude_covariance[2, 2]) * 206264.8


# ---------------------------------------------------------------------- database

def test_database_built_once_then_loaded(tmp_path, monkeypatch, cat, cam):
    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    a = AngleMethod(cat, cam, SIGMA)
    assert a.database_info["source"] == "built"
    path = tmp_path / "databases" / f"{a.database_key_string}.npz"
    assert path.exists() and a.database_info["path"] == str(path)
    import skyview.identify.angle as angle_module

    monkeypatch.setattr(angle_module, "_LOADED", LRU(angle_module.MAX_LOADED))  # a new process: the file
    b = AngleMethod(cat, cam, SIGMA, beta=2.0, max_pivots=None)  # search parameters: same database
    assert b.database_info["source"] == "cache"
    assert b.database_key == a.database_key
    np.testing.assert_array_equal(a.pair_i, b.pair_i)
    np.testing.assert_array_equal(a.kv.sorted_values, b.kv.sorted_values)
    # the cached file is mapped, not read (a process reads the pages its look-ups touch), and the
    # candidates a look-up gives are the built database's, widened to int64
    assert isinstance(b.pair_i, np.memmap) and b.kv.sorted_values.flags.owndata  # (the searched angles: copied)
    ctx = {"counts": type("Span", (), {"span": lambda self, k: (100, 160)})()}
    for x, y in zip(a._candidates(ctx, 0), b._candidates(ctx, 0)):
        assert x.dtype == y.dtype == np.int64 and np.array_equal(x, y)
    # another solver of a camera of the same range shares the process's map and its copy of the angles
    b2 = AngleMethod(cat, Camera.from_fov(cam.fov_deg * 0.999, 1024), SIGMA)
    assert b2.pair_i is b.pair_i and b2.kv.sorted_values is b.kv.sorted_values
    assert b2.database_info["source"] == "cache" and b2.database_info["fov_deg"] != b.database_info["fov_deg"]
    # keys differ when what the database depends on differs
    c = AngleMethod(cat, cam, SIGMA, kvector_fit="parabola")
    d = AngleMethod(cat, Camera.from_fov(10.0, 1024), SIGMA)
    e = AngleMethod(cat.brighter_than(5.5), cam, SIGMA)
    keys = {x.database_key_string for x in (a, c, d, e)}
    assert len(keys) == 4
    assert all(x.database_info["source"] == "built" for x in (c, d, e))
    assert len(list((tmp_path / "databases").glob("*.npz"))) == 4
    assert not list((tmp_path / "databases").glob("*.tmp"))  # atomic writes leave nothing behind


def test_load_or_build_generic(tmp_path, monkeypatch, cat, cam):
    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    calls = []

    def build():
        calls.append(1)
        return {"x": np.arange(5)}

    key = database.make_key("toy", {"a": 1}, cat, cam)
    arr, info = database.load_or_build(key, build)
    arr2, info2 = database.load_or_build(key, build)
    assert len(calls) == 1 and info["source"] == "built" and info2["source"] == "cache"
    np.testing.assert_array_equal(arr2["x"], np.arange(5))
    assert info2["key"] == key and info2["file_bytes"] > 0
    assert database.key_hash(database.make_key("toy", {"a": 2}, cat, cam)) != database.key_hash(key)
    # a corrupt file is rebuilt, not trusted
    database.database_path(key).write_bytes(b"not an npz")
    _, info3 = database.load_or_build(key, build)
    assert len(calls) == 2 and info3["source"] == "built"


def test_database_content(ident, cat, cam):
    info = ident.database_info
    diag = 2 * cam.half_diagonal_rad
    assert info["pairs"] == len(ident.pair_i) and info["pairs_within_fov"] < info["pairs"]
    assert info["nbytes"] > 0 and (info["build_s"] is not None or info["load_s"] is not None)
    ang = angular_distance(cat.xyz[ident.pair_i], cat.xyz[ident.pair_j])
    np.testing.assert_allclose(ang, ident.kv.sorted_values, atol=1e-15)
    assert np.all(np.diff(ident.kv.sorted_values) >= 0) and ang.max() <= ident.max_sep_rad
    # the database belongs to the sky: its range is the diagonal rounded up by at most 5 %
    assert diag <= ident.max_sep_rad <= 1.05 * diag
    # every pair that fits in the image diagonal is present (brute force on a bright subset)
    bright = np.flatnonzero(cat.mag <= 3.5)
    d = angular_distance(cat.xyz[bright][:, None], cat.xyz[bright][None, :])
    iu = np.triu_indices(len(bright), 1)
    expected = {(int(bright[a]), int(bright[b])) for a, b in zip(*iu) if d[a, b] <= ident.max_sep_rad}
    in_bright = np.isin(ident.pair_i, bright) & np.isin(ident.pair_j, bright)
    got = {tuple(sorted((int(a), int(b)))) for a, b in zip(ident.pair_i[in_bright], ident.pair_j[in_bright])}
    assert got == expected
    assert info["pairs_within_fov"] == int(np.sum(ang <= np.radians(cam.fov_deg)))


# ---------------------------------------------------------------------- identification

def test_identifies_fields_with_known_truth(ident, cat, cam):
    n_identified = 0
    for f in frames(cat, cam, 6, seed=2024):
        r = ident.identify(f.obs)
        if r.status != IDENTIFIED:  # the paper's method can run out of stars to verify with
            assert any(w in r.reason for w in ("verification failed: no observed star", "candidate pairs left"))
            continue
        n_identified += 1
        assert_correct(r, f)
        kinds = [s.kind for s in r.steps]
        assert kinds[0] == "pick" and kinds[-1] == "verify" and set(kinds) <= {"pick", "pivot", "skip", "verify"}
        assert r.stats["pivots"] == kinds.count("pivot") and r.stats["stars_used"] >= 2
        assert r.verification["passed"] and r.database_key == ident.database_key_string
    assert n_identified >= 4
    # with joins, loop closing and backtracking every one of these fields is identified
    better = AngleMethod(cat, cam, SIGMA, pivoting="join", close_loops=True, backtrack=True)
    for f in frames(cat, cam, 6, seed=2024):
        assert_correct(better.identify(f.obs), f)


def test_steps_record_the_chain(ident, cat, cam):
    f = frames(cat, cam, 1, seed=5, n_min=8)[0]
    r = ident.identify(f.obs)
    pick = r.steps[0]
    assert pick.kind == "pick" and len(pick.observed) == 2
    a, b = pick.observed
    theta = angular_distance(f.obs.vectors[a], f.obs.vectors[b])
    n = len(f.obs)
    all_theta = [angular_distance(f.obs.vectors[i], f.obs.vectors[j]) for i in range(n) for j in range(i + 1, n)]
    assert theta == pytest.approx(max(all_theta))  # the paper starts with the largest angle
    assert pick.numbers["bound_arcsec"] == pytest.approx(3 * np.sqrt(2) * SIGMA * 206264.806, rel=1e-6)
    true_pair = tuple(sorted((int(f.truth[a]), int(f.truth[b]))))
    start, stop = ident.kv.range(theta - 3 * np.sqrt(2) * SIGMA, theta + 3 * np.sqrt(2) * SIGMA)
    assert pick.numbers["candidates"] == pick.numbers["pairs"] == 2 * (stop - start)  # both orientations
    assert len(pick.groups) == min(200, stop - start)
    cands = {tuple(sorted(p)) for p in zip(ident.pair_i[start:stop].tolist(), ident.pair_j[start:stop].tolist())}
    assert true_pair in cands
    for s in r.steps:
        if s.kind == "pivot":
            # the paper's pruning: each list keeps only pairs with the shared star in the other list
            assert s.numbers["pairs"] <= s.numbers["candidates"]
            assert s.numbers["previous_after"] <= s.numbers["previous_before"]
            assert len(s.catalog) <= 200 and len(s.groups) <= 200
            d = s.to_dict()
            assert d["kind"] == "pivot" and isinstance(d["numbers"]["candidates"], float)


def test_rotation_invariance(ident, cat, cam):
    """The same star pattern, rotated, is identified the same way."""
    rng = np.random.default_rng(77)
    # a field whose stars all lie inside the inscribed circle, so that any roll keeps them on the sensor
    while True:
        R0 = random_attitudes(1, rng)[0]
        idx, _ = cam.visible(R0, cat.xyz)
        v = cat.xyz[idx] @ R0.T
        inside = np.arccos(np.clip(v[:, 2], -1, 1)) < np.radians(3.9)
        if inside.sum() >= 7:
            break
    rows = idx[inside][np.argsort(cat.mag[idx[inside]])]
    v_cam = add_noise(cat.xyz[rows] @ R0.T, SIGMA, rng)
    better = AngleMethod(cat, cam, SIGMA, pivoting="join", close_loops=True, backtrack=True)

    def obs(vectors):
        uv, _ = cam.project(vectors)
        return Observation(vectors=vectors, uv=uv, brightness=10 ** (-0.4 * cat.mag[rows]), sigma_rad=SIGMA)

    base = better.identify(obs(v_cam))
    assert base.status == IDENTIFIED
    assert base.matches == {i: int(r) for i, r in enumerate(rows)}
    for psi in rng.uniform(0, 2 * np.pi, size=4):  # rolls about the boresight: the full identification
        Q = Rotation.from_rotvec([0, 0, psi]).as_matrix()
        r = better.identify(obs(v_cam @ Q.T))
        assert r.matches == base.matches
        assert attitude_error_arcsec(r.R, Q @ R0)["boresight"] < 60.0
    first = ident.identify(obs(v_cam)).stats["first_chain"]
    assert first["outcome"] == "unique"
    assert first["matches"] == {i: int(rows[i]) for i in first["matches"]}
    for Q in random_attitudes(4, rng):  # any rotation: the pattern match (before verification)
        r = ident.identify(Observation(vectors=v_cam @ Q.T, uv=np.zeros((len(rows), 2)),
                                       brightness=np.ones(len(rows)), sigma_rad=SIGMA))
        assert r.stats["first_chain"] == first


@pytest.mark.parametrize("params", [{}, {"backtrack": True}, {"order": "fewest"},
                                    {"pivoting": "join", "close_loops": True, "backtrack": True}])
def test_false_star_never_gives_a_wrong_identification(cache, cat, cam, params):
    method = AngleMethod(cat, cam, SIGMA, **params)
    n_ok = 0
    for f in frames(cat, cam, 25, seed=99, n_min=4, false_stars=1):
        assert f.n_true == len(f.obs) - 1
        r = method.identify(f.obs)
        if r.status == IDENTIFIED:
            assert all(f.truth[o] == c for o, c in r.matches.items()), (f.truth, r.matches)
            n_ok += 1
    assert n_ok >= 5


def test_backtracking_drops_the_false_star(cache, cat, cam):
    method = AngleMethod(cat, cam, SIGMA, backtrack=True)
    seen_backtrack = False
    for f in frames(cat, cam, 25, seed=123, n_min=6, false_stars=1):
        r = method.identify(f.obs)
        kinds = [s.kind for s in r.steps]
        if "backtrack" in kinds and r.status == IDENTIFIED:
            seen_backtrack = True
            assert_correct(r, f)
            assert r.stats["chains"] > 1 and r.verification["n_hypotheses"] == r.stats["verifications"]
    assert seen_backtrack


def test_restarts_drop_each_suspect_once_within_the_limits():
    """The shared backtracking driver: the full set first, then one restart per new suspect (queue order,
    or the method's pick), each set of dropped stars once, at most max_dropped out, 3 stars left."""
    steps = []
    r = Restarts(steps, 5, backtrack=True, max_restarts=3, max_dropped=1)
    got = []
    for excluded in r:
        got.append(sorted(excluded))
        r.failed(excluded, [4, 2, 4] if not excluded else [0])  # a restart's suspects are not queued
    assert got == [[], [4], [2]]  # the queue ran dry before the budget (1 + 3 chains)
    assert [(s.kind, s.observed, s.numbers["restart"]) for s in steps] == [("backtrack", [4], 1), ("backtrack", [2], 2)]
    r = Restarts([], 4, backtrack=True, max_restarts=10, max_dropped=2, pick=lambda q: len(q) - 1)  # newest first
    got = []
    for excluded in r:
        got.append(sorted(excluded))
        r.failed(excluded, [0, 1])
    assert got == [[], [1], [0]]  # 4 stars: never fewer than 3 left, so never two dropped
    r = Restarts([], 9, backtrack=True, max_restarts=2, max_dropped=2)
    got = []
    for excluded in r:
        got.append(sorted(excluded))
        r.failed(excluded, [5, 6, 7])
    assert got == [[], [5], [6]]  # the budget: 1 + max_restarts chains
    r = Restarts([], 9, backtrack=False, max_restarts=10, max_dropped=1)
    assert [sorted(e) for e in r if r.failed(e, [1, 2]) is None] == [[]]  # no backtracking: one chain


def test_failure_reason_numbers_the_chains(cache, cat, cam):
    method = AngleMethod(cat, cam, SIGMA, backtrack=True, max_candidates=10)  # every angle has more
    f = frames(cat, cam, 1, seed=8, n_min=8)[0]
    r = method.identify(f.obs)
    assert r.status != IDENTIFIED and r.stats["chains"] == 1 and r.stats["verifications"] == 0
    assert r.reason == "no angle with at most max_candidates candidates to start from"
    rng = np.random.default_rng(4)  # eight stars scattered at random: no chain holds
    v = np.column_stack([rng.uniform(-0.05, 0.05, (8, 2)), np.ones(8)])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = AngleMethod(cat, cam, SIGMA, backtrack=True).identify(Observation(v, np.zeros((8, 2)), np.ones(8), SIGMA))
    assert r.status != IDENTIFIED and r.stats["chains"] > 1
    assert r.reason.startswith("chain 1: ") and f"; chain {r.stats['chains']}: " in r.reason


def test_limits_and_small_inputs(ident, cat, cam):
    f = frames(cat, cam, 1, seed=8, n_min=8)[0]
    r = AngleMethod(cat, cam, SIGMA, max_pivots=0).identify(f.obs)
    assert r.status != IDENTIFIED and [s.kind for s in r.steps][:1] == ["pick"]
    assert "pivot" not in [s.kind for s in r.steps]
    r = AngleMethod(cat, cam, SIGMA, max_candidates=10).identify(f.obs)  # every angle has more
    assert r.status != IDENTIFIED and all(s.kind == "skip" for s in r.steps)
    few = Observation(vectors=f.obs.vectors[:2], uv=f.obs.uv[:2], brightness=f.obs.brightness[:2], sigma_rad=SIGMA)
    r = ident.identify(few)
    assert r.status == FAILED and "at least 3" in r.reason
    none = Observation(vectors=np.zeros((0, 3)), uv=np.zeros((0, 2)), brightness=np.zeros(0), sigma_rad=SIGMA)
    assert ident.identify(none).status == FAILED


def test_pattern_stars_are_the_brightest_and_every_star_verifies(cache, cat, cam):
    """max_stars (12 in the improved variant): only the brightest stars form angles, all of them verify."""
    f = frames(cat, cam, 1, seed=12, n_min=9)[0]
    capped = AngleMethod(cat, cam, SIGMA, pivoting="join", close_loops=True, max_stars=5)
    r = capped.identify(f.obs)
    assert r.stats["pattern_stars"] == 5 and r.stats["stars"] == len(f.obs) >= 9
    for s in r.steps:
        if s.kind in ("pick", "pivot", "skip"):
            assert max(s.observed) < 5
    assert_correct(r, f)
    assert max(r.matches) >= 5  # stars outside the pattern search are matched by the verification
    full = AngleMethod(cat, cam, SIGMA, pivoting="join", close_loops=True)
    assert full.identify(f.obs).stats["pattern_stars"] == len(f.obs)
    assert make_identifier("angle", cat, cam, SIGMA, variant="improved").max_stars == 12
    with pytest.raises(BadInput):
        make_identifier("angle", cat, cam, SIGMA, max_stars=2)


@pytest.mark.parametrize("n_candidates", [3000, 100])  # few hypotheses per candidate, and many
def test_join_against_a_loop(n_candidates):
    """The vectorised join (blocks by catalog star) gives the rows of a plain double loop, in its order."""
    rng = np.random.default_rng(5)
    ci, cj = rng.integers(0, 300, n_candidates), rng.integers(0, 300, n_candidates)
    H = np.stack([rng.integers(0, 300, 40), rng.integers(300, 600, 40)], axis=1)
    H[:10, 1] = ci[:10]  # some closed loops that hold
    H[:10, 0] = cj[:10]
    cand = list(zip(np.concatenate([ci, cj]).tolist(), np.concatenate([cj, ci]).tolist()))  # (on p, on q)
    for n in (0, 1, 3, 40):
        for p, q in ((1, 2), (2, 1), (0, 2), (0, 1), (1, 0)):  # a new star on either side, closed loops
            got, used, new = _join(H[:n], [0, 1], p, q, ci, cj)
            pairs = cand if p in (0, 1) else [(b, a) for a, b in cand]  # (on the shared star, on the other)
            s, o = (p, q) if p in (0, 1) else (q, p)
            if o in (0, 1):
                ref = [h for h in H[:n].tolist() if (h[s], h[o]) in set(pairs)]
                assert new is None
            else:
                ref = [h + [b] for h in H[:n].tolist() for a, b in sorted(pairs, key=lambda x: x[0])
                       if a == h[s] and b not in h]
                assert new == o and used == [0, 1, o]
            assert got.tolist() == ref
    assert len(_join(H, [0, 1], 0, 1, ci, cj)[0]) == 10


def test_a_closed_loop_tested_by_its_angle_is_the_join(ident, cat):
    """`_close` (the angle between the two catalog stars within the bounds) keeps the rows the join
    with the database's candidates keeps, in their order: the database holds every pair in range."""
    rng = np.random.default_rng(11)
    bound = 3.0 * np.sqrt(2.0) * SIGMA
    for theta in rng.uniform(0.005, 0.12, 20):
        lo, hi = theta - bound, theta + bound
        s, e = (int(x[0]) for x in ident.kv.ranges(lo, hi))
        ci, cj = ident.pair_i[s:e], ident.pair_j[s:e]
        near = np.stack([ci, cj], axis=1)[:30]  # candidates, both orientations, and pairs that are not
        H = np.concatenate([near, near[:, ::-1], rng.integers(0, len(cat), (60, 2)),
                            np.stack([ident.pair_i[e:e + 20], ident.pair_j[e:e + 20]], axis=1)])
        H = np.concatenate([H, rng.integers(0, len(cat), (len(H), 1))], axis=1)  # a third star, unused
        H = H[rng.permutation(len(H))]
        for ip, iq in ((0, 1), (1, 0)):
            ref, used, new = _join(H, [7, 8, 9], [7, 8, 9][ip], [7, 8, 9][iq], ci, cj, len(cat))
            assert new is None and used == [7, 8, 9]
            got = _close(H, ip, iq, cat.xyz, lo, hi)
            assert got.tolist() == ref.tolist() and len(ref) >= 60 and got.dtype == ref.dtype


def test_candidate_ranges_looked_up_when_read(ident):
    """An angle's range, looked up alone when a chain reads it, is the batch look-up's."""
    rng = np.random.default_rng(2)
    theta = rng.uniform(0.0, 0.2, 50)
    bound = 3.0 * np.sqrt(2.0) * SIGMA
    start, stop = ident.kv.ranges(theta - bound, theta + bound)
    lazy = _Ranges(ident.kv.sorted_values, theta, bound)
    for k in rng.permutation(50):
        assert lazy.span(int(k)) == (start[k], stop[k]) and lazy[k] == 2 * (stop[k] - start[k])
    assert lazy.all().tolist() == (2 * (stop - start)).tolist()


def test_join_is_a_join_on_the_shared_star():
    H = np.array([[10, 20], [11, 21], [12, 22]])  # observed stars [0, 1]
    # angle (1, 2): candidates (20, 30), (21, 31), (40, 41) in both orientations
    H2, used, new = _join(H, [0, 1], 1, 2, np.array([20, 31, 40]), np.array([30, 21, 41]))
    assert used == [0, 1, 2] and new == 2
    assert sorted(map(tuple, H2.tolist())) == [(10, 20, 30), (11, 21, 31)]
    # closed loop (0, 2): only (10, 30) is a candidate
    H3, used3, new3 = _join(H2, used, 2, 0, np.array([30]), np.array([10]))
    assert new3 is None and H3.tolist() == [[10, 20, 30]]
    # a catalog star is never assigned to two observed stars
    H4, _, _ = _join(H, [0, 1], 0, 2, np.array([10]), np.array([20]))
    assert len(H4) == 0


def test_registry_and_bad_input(cache, cat, cam):
    assert "angle" in METHODS
    with pytest.raises(BadInput, match="unknown method 'x': choose from angle"):
        make_identifier("x", cat, cam, SIGMA)
    with pytest.raises(BadInput, match="no parameter"):
        make_identifier("angle", cat, cam, SIGMA, bogus=1)
    with pytest.raises(BadInput):
        make_identifier("angle", cat, cam, SIGMA, order="random")
    with pytest.raises(BadInput):
        make_identifier("angle", cat, cam, -1.0)
    with pytest.raises(BadInput):
        make_identifier("angle", cat, cam, SIGMA, beta=0)


def test_cameras_of_nearly_the_same_field_share_one_database(cat, tmp_path, monkeypatch):
    monkeypatch.setenv("SKYVIEW_CACHE", str(tmp_path))
    a = AngleMethod(cat, Camera.from_fov(8.0, 1024), 1e-4)
    b = AngleMethod(cat, Camera.from_fov(8.03, 1024, 1000), 1e-4)
    assert a.database_key == b.database_key and b.database_info["source"] == "cache"
    c = AngleMethod(cat, Camera.from_fov(12.0, 1024), 1e-4)
    assert c.database_key != a.database_key
