"""The penalty's distance: the bitwise blend selects exactly what nested `np.where`s select."""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.service.core import penalty

SPECIAL = np.array([0.0, -0.0, 1.0, -1.0, 0.5, np.nan, np.inf, -np.inf, 1e-300, 5e-324, 1e300, -1e308, 1e308])


def _reference(x, lower, upper):
    above, below = x > upper, x < lower
    return np.where(above, x - upper, np.where(below, lower - x, 0.0)), above.astype(np.float64) - below.astype(np.float64)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("seed", range(5))
def test_gap_is_bitwise_the_nested_where(dtype, seed):
    rng = np.random.default_rng(seed)
    n = 2000
    with np.errstate(all="ignore"):
        x = (rng.choice(SPECIAL, n) * rng.choice([1.0, 0.3, -2.0], n)).astype(dtype)
        lower = rng.choice(SPECIAL[[0, 1, 2, 3, 4, 8, 9, 10, 11]], n).astype(dtype)
        upper = (lower + rng.choice([0.0, -0.0, 0.5, 1.0, 1e-300, 1e308], n)).astype(dtype)
        x[: n // 2] = rng.normal(size=n // 2)  # random sides, as in a scene with every joint out of range
        upper[::7], lower[::7] = lower[::7].copy(), upper[::7].copy()  # an empty range too: above wins
        got = penalty.gap(x, lower, upper)
        want = _reference(x, lower, upper)
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and g.tobytes() == w.tobytes()
    assert not np.signbit(got[0]).any()  # never -0: inside the range (and NaN) is +0


def test_energy_is_the_cube_of_the_relative_gap():
    x = np.array([-2.0, 0.0, 0.25, 1.0, 1.5, np.nan])
    lower, upper, s = np.zeros(6), np.ones(6), np.full(6, 2.0)
    with np.errstate(invalid="ignore"):
        e = penalty.energy(x, lower, upper, s)
    np.testing.assert_array_equal(e, [16.0, 0.0, 0.0, 0.0, 0.25, 0.0])
    assert not np.signbit(e).any()
