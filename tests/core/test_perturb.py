"""The harness of `--perturb-ulps` (tests/perturb.py) does what it says: it reaches the core's calls, it moves
results by at most what it promises, and the same inputs give the same outputs (as a real kernel's would)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.perturb import perturbed, plain, ulp_steps


def test_the_perturbation_reaches_the_core(request: pytest.FixtureRequest) -> None:
    """Under `--perturb-ulps N`: the core's `np.arctan2` is not glibc's (math.atan2, < 1 ulp) on most values."""
    n = request.config.getoption("--perturb-ulps")
    if n == 0:
        pytest.skip("runs under --perturb-ulps only")
    from jointlimits.service.core import revolute

    y, x = np.random.default_rng(1).standard_normal((2, 1000))
    got = revolute.np.arctan2(y, x)
    glibc = np.array([math.atan2(a, b) for a, b in zip(y, x, strict=True)])
    off = np.abs(got - glibc) / np.spacing(np.abs(glibc))
    assert (off > 0).mean() > 0.5 and off.max() <= n + 1  # +1: glibc's own last bit


def test_moves_are_bounded_deterministic_and_odd() -> None:
    rng = np.random.default_rng(2)
    a = rng.standard_normal(10_000) * 10.0 ** rng.integers(-300, 300, 10_000)
    a[:3] = (0.0, np.inf, np.nan)
    b = a.copy()
    ulp_steps(b, 4, seed=5)
    finite = np.isfinite(a) & (a != 0)
    steps = np.abs(b[finite] - a[finite]) / np.spacing(np.abs(a[finite]))
    assert steps.max() <= 4 * 2 + 1e-9 and (steps > 0).mean() > 0.8  # a step below a power of 2 is half an ulp
    assert b[0] == 0 and b[1] == np.inf and np.isnan(b[2])
    c = -a
    ulp_steps(c, 4, seed=5)
    np.testing.assert_array_equal(c[finite], -b[finite])


def test_blas_moves_keep_equal_inputs_equal() -> None:
    """matmul: the same product twice is bitwise the same, X^T X stays symmetric, and it moved within 2 K u."""
    rng = np.random.default_rng(3)
    X = rng.standard_normal((50, 7, 24))
    with plain():
        base = np.matmul(X.transpose(0, 2, 1), X)
        bound = np.matmul(np.abs(X.transpose(0, 2, 1)), np.abs(X))
    with perturbed(4):
        one = np.matmul(X.transpose(0, 2, 1), X)
        two = np.matmul(X.transpose(0, 2, 1), X)
        w1, w2 = np.linalg.eigh(base)[0], np.linalg.eigh(base.copy())[0]
    np.testing.assert_array_equal(one, two)
    np.testing.assert_array_equal(one, one.transpose(0, 2, 1))
    np.testing.assert_array_equal(w1, w2)
    # both sums' errors, each within 7 u sum|a_k b_k|
    assert np.any(one != base) and np.all(np.abs(one - base) <= 2 * 7 * 2.0**-53 * bound)


def test_lapack_stand_ins_give_the_same_answers_in_another_order() -> None:
    """eigh, svd, solve of the reversed problem, mapped back: right to rounding, exact where any order is."""
    rng = np.random.default_rng(4)
    S = rng.standard_normal((30, 12, 12))
    S = S + S.transpose(0, 2, 1)
    G = rng.standard_normal((30, 3, 3))
    b = rng.standard_normal((30, 3, 2))
    with plain():
        base = np.linalg.eigh(S)[1]
    with perturbed(4):
        w, V = np.linalg.eigh(S)
        U, s, Vt = np.linalg.svd(G)
        x = np.linalg.solve(G, b)
        moved = np.linalg.eigh(S)[1]
        exact = np.linalg.solve(np.diag([2.0, 4.0, 8.0]), np.array([1.0, 3.0, 5.0])), np.linalg.norm(np.array([0, 0, 1.0]))
    assert np.abs(np.einsum("nij,nj,nkj->nik", V, w, V) - S).max() <= 1e-13 * np.abs(S).max()
    assert np.all(np.diff(w, axis=1) >= 0) and np.any(np.abs(moved) != np.abs(base))
    assert np.abs(np.einsum("nij,nj,njk->nik", U, s, Vt) - G).max() <= 1e-13 * np.abs(G).max()
    assert np.abs(np.einsum("nij,njk->nik", G, x) - b).max() <= 1e-12 * np.abs(b).max()
    assert exact[0].tolist() == [0.5, 0.75, 0.625] and exact[1] == 1.0


def test_a_started_python_computes_with_the_same_kernels(request: pytest.FixtureRequest) -> None:
    """Under `--perturb-ulps N`: a Python process started by a test (a live server, the console script) gets the
    same arctan2 as the test process (tests/perturb_site/sitecustomize.py)."""
    if request.config.getoption("--perturb-ulps") == 0:
        pytest.skip("runs under --perturb-ulps only")
    import subprocess
    import sys

    code = "import numpy as np; print(repr(float(np.arctan2(np.float64(0.3), np.float64(0.4)))))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    here = float(np.arctan2(np.float64(0.3), np.float64(0.4)))
    assert float(done.stdout) == here and here != math.atan2(0.3, 0.4)


def test_a_second_installation_replaces_the_first() -> None:
    """pytest's installation in a process whose sitecustomize already installed one (an xdist worker, a pytest
    subprocess) moves results by N ulps, not 2N."""
    y, x = np.random.default_rng(5).standard_normal((2, 1000))
    glibc = np.array([math.atan2(a, b) for a, b in zip(y, x, strict=True)])
    before = np.arctan2
    with perturbed(40, 1), perturbed(4, 0):
        off = np.abs(np.arctan2(y, x) - glibc) / np.spacing(np.abs(glibc))
    assert 0 < off.max() <= 5  # +1: glibc's own last bit
    assert np.arctan2 is before  # restored
