"""skyview.core.special against scipy.special (which the solve path no longer imports): the error function
the C library's (within 3 ulp of scipy's), the binomial tails to 1e-11 relative from 1 down to 1e-280."""

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.special import bdtr, bdtrc
from scipy.special import erf as scipy_erf

from skyview.core.special import binomial_cdf, binomial_sf, erf


def test_erf_is_the_c_librarys():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-7, 7, 200_000), rng.normal(0, 1, 200_000), rng.uniform(-1e-8, 1e-8, 1000),
                        [0.0, 0.84375, 1.25, 1 / 0.35, 6.0, -6.0, 1e-300, 27.0]])
    y = erf(x)
    ref = np.array([math.erf(v) for v in x])
    assert np.array_equal(y, ref)  # the C library's, bit for bit
    assert np.all(np.abs(y - scipy_erf(x)) <= 3 * np.spacing(np.abs(ref)))
    assert np.isnan(erf(np.array([np.nan]))[0]) and erf(np.array([np.inf, -np.inf])).tolist() == [1.0, -1.0]
    assert math.copysign(1, erf(np.array([-0.0]))[0]) == -1  # odd, to the sign of zero


def test_erf_writes_into_out_in_the_shape_given():
    x = np.linspace(-3, 3, 24).reshape(2, 3, 4)
    out = np.empty((2, 3, 4))
    assert erf(x, out=out) is out and np.array_equal(out, erf(x)) and out.shape == x.shape


def test_binomial_tails_are_scipys():
    rng = np.random.default_rng(1)
    for _ in range(5000):
        n = int(rng.integers(1, 500))
        k = int(rng.integers(0, n + 1))
        p = float(rng.choice([rng.uniform(0, 1), 10 ** rng.uniform(-8, 0), 1 - 10 ** rng.uniform(-8, 0)]))
        for ours, theirs in ((binomial_sf(k, n, p), float(bdtrc(k - 1, n, p))),
                             (binomial_cdf(k, n, p), float(bdtr(k, n, p)))):
            if theirs > 1e-280:
                assert ours == pytest.approx(theirs, rel=1e-11, abs=0), (n, k, p)
    assert binomial_sf(0, 10, 0.3) == 1.0 and binomial_sf(11, 10, 0.3) == 0.0
    assert binomial_sf(3, 10, 0.0) == 0.0 and binomial_sf(3, 10, 1.0) == 1.0
    assert binomial_cdf(-1, 10, 0.3) == 0.0 and binomial_cdf(10, 10, 0.3) == 1.0


def test_a_solve_imports_neither_scipy_special_nor_scipy_spatial(tmp_path):
    """What a process pays before it answers: `skyview solve PHOTO` (blind) loads no scipy.special and no
    scipy.spatial (0.15 s and 0.2 s of imports), nor numpy.ma (np.median's first call, ~10 ms)."""
    from pathlib import Path

    photos = [str(p) for p in sorted((Path(__file__).parent / "data" / "real-images").glob("*.png"))]
    code = ("import sys; from skyview.cli import main; rc = max(main(['solve', f, '--json']) for f in sys.argv[1:]); "
            "bad = sorted(m for m in sys.modules if m.startswith(('scipy.special', 'scipy.spatial', 'numpy.ma.')) or m == 'numpy.ma'); "
            "print('LOADED', bad, file=sys.stderr); sys.exit(rc)")
    for run in ("builds the databases the first time (a k-d tree may build them)", "answers from them"):
        p = subprocess.run([sys.executable, "-c", code, *photos], capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stderr[-500:]
    assert "LOADED []" in p.stderr
