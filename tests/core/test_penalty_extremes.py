"""The penalty at the float64 extremes (issue 19): `u - l` and `x - u` overflow, the ratio does not.

Each answer is checked against exact rational arithmetic (`fractions.Fraction`): the energy and its
first derivative within a few ulps, never the silent 0 of `5e307 / inf`. A true answer beyond float64
is a 422 naming the batch, field and joint, never a wrong 200.
"""

from __future__ import annotations

import copy
from fractions import Fraction

import numpy as np
import pytest
from fastapi.testclient import TestClient

from jointlimits.service.app import app
from jointlimits.service.core import penalty
from tests.http.test_state_inputs import REVOLUTE

# (x, lower, upper, strength): every one overflows `u - l` or `x - u` in float64.
EXTREMES = [
    (1.5e308, -1e308, 1e308, 100.0),  # exact energy 1.5625
    (-1.5e308, -1e308, 1e308, 100.0),
    (1.7e308, -9e307, 9e307, 100.0),
    (-1.7e308, -9e307, 9e307, 100.0),
    (1e308, -1.5e308, -1e308, 1.0),  # x - u overflows, u - l does not: ratio 4
    (-1e308, 1e308, 1.5e308, 3.0),
    (np.finfo(np.float64).max, -np.finfo(np.float64).max, np.finfo(np.float64).max * 0.5, 1e-300),
]


def _exact(x: float, lower: float, upper: float, strength: float) -> tuple[Fraction, Fraction, Fraction]:
    """E, dE/dx, d2E/dx2 in exact rationals (the penalty's definition, module docstring)."""
    X, L, U, S = map(Fraction, (x, lower, upper, strength))
    g, side = (X - U, 1) if X > U else ((L - X, -1) if X < L else (Fraction(0), 0))
    w = U - L if U > L else Fraction(1)
    r = g / w
    return S * r**3, side * 3 * S * r**2 / w, 6 * S * r / w**2


def _close(got: float, want: Fraction, ulps: int = 4) -> bool:
    """`got` within `ulps` ulps of the exact `want` (below the smallest normal: within as many subnormal steps)."""
    w = float(want)
    return abs(got - w) <= ulps * max(np.spacing(abs(w)), np.finfo(np.float64).smallest_subnormal)


@pytest.mark.parametrize("x,lower,upper,strength", EXTREMES)
def test_overflowing_differences_give_the_exact_ratio(x, lower, upper, strength):
    a = lambda v: np.array([v, 0.5])  # a second, ordinary joint alongside
    with np.errstate(over="ignore"):
        E, dE, d2E = penalty.derivatives(a(x), np.array([lower, 0.0]), np.array([upper, 1.0]), a(strength))
        e = penalty.energy(a(x), np.array([lower, 0.0]), np.array([upper, 1.0]), a(strength))
    want = _exact(x, lower, upper, strength)
    assert want[0] > 0 and E[0] > 0  # the silent answer was 0
    assert e[0] == E[0]
    for got, exact in zip((E[0], dE[0], d2E[0]), want):
        assert np.isfinite(got) and _close(got, exact), (got, float(exact))
    assert (E[1], dE[1], d2E[1]) == (0.0, 0.0, 0.0)  # inside its range


def test_the_issue_case_is_exactly_1_5625():
    with np.errstate(over="ignore"):
        e = penalty.energy(np.array([1.5e308]), np.array([-1e308]), np.array([1e308]), np.array([100.0]))
    assert e[0] == 1.5625 == float(_exact(1.5e308, -1e308, 1e308, 100.0)[0])


def test_ordinary_inputs_keep_the_plain_quotient_bitwise():
    rng = np.random.default_rng(19)
    n = 4000
    lower = rng.normal(size=n) * 10.0 ** rng.integers(-300, 300, n)
    upper = lower + np.abs(rng.normal(size=n)) * 10.0 ** rng.integers(-300, 300, n)
    x = rng.normal(size=n) * 10.0 ** rng.integers(-300, 300, n)
    s = np.abs(rng.normal(size=n)) * 10.0 ** rng.integers(-300, 3, n)
    with np.errstate(all="ignore"):
        g = np.where(x > upper, x - upper, np.where(x < lower, lower - x, 0.0))
        w = np.where(upper > lower, upper - lower, 1.0)
        r, sw = g / w, s / w
        plain = (s * (r * r * r), ((x > upper) * 1.0 - (x < lower)) * 3.0 * sw * (r * r), 6.0 * (sw / w) * r)
        got = penalty.derivatives(x, lower, upper, s)
    assert np.isfinite(w).all()
    for a, b in zip(got, plain):
        assert a.tobytes() == b.tobytes()


def _revolute(prev: float, lower: float, upper: float, strength: float) -> dict:
    doc = copy.deepcopy(REVOLUTE)
    b = doc["batches"][0]
    b.pop("offset", None)
    b.update(prev_coordinate=[prev], lower=[lower], upper=[upper], strength=[strength])
    doc["outputs"] = ["energy", "gradient", "hessian"]
    return doc


@pytest.mark.parametrize("prev,lower,upper", [(1.5e308, -1e308, 1e308), (-1.5e308, -1e308, 1e308), (1.7e308, -9e307, 9e307)])
def test_http_answers_the_exact_energy_at_the_extremes(prev, lower, upper):
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=_revolute(prev, lower, upper, 100.0))
    assert r.status_code == 200, r.text
    b = r.json()["batches"][0]
    want = _exact(b["x"][0], lower, upper, 100.0)[0]
    assert b["energy"][0] > 0 and _close(b["energy"][0], want), (b["energy"][0], float(want))
    if prev == 1.5e308:
        assert b["energy"][0] == 1.5625


def test_http_an_energy_beyond_float64_is_a_422_naming_the_joint():
    # x - u overflows, the ratio is 2.7e7 (finite): strength 1e300 takes the exact energy to ~2e322.
    assert _exact(1.7e308, -1.0000001e308, -1e308, 1e300)[0] > Fraction(np.finfo(np.float64).max)
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=_revolute(1.7e308, -1.0000001e308, -1e308, 1e300))
    assert r.status_code == 422, r.text
    assert [d["loc"] for d in r.json()["detail"]] == [["body", "batches", 0, "strength", 0]]



@pytest.mark.parametrize("uid", [670, 669])
def test_strength_zero_pays_nothing_however_far_out(uid):
    """`s = 0` (a limit switched off) is E = 0 and zero derivatives even where `(g / w)^3` overflows (a width of
    1e-200, a gap of 0.5): before, `0 * inf` was NaN and the request a 422 naming a joint whose energy is exactly 0."""
    from jointlimits.service.core import Bodies, Joints, evaluate
    from tests.scenes import pack, rotation_about

    eye = pack(np.zeros(3), np.eye(3))
    moved = pack(np.array([0.0, 0.0, 0.5]), rotation_about(np.array([0.0, 0.0, 1.0]), 0.5))  # x = 0.5 either way
    joints = Joints(uid, 18 if uid == 670 else 20, np.array([[0, 1]]), np.array([[[0.0, 0, 0], [0, 0, 1]]]),
                    np.array([-1e-200]), np.array([0.0]), np.array([0.0]))
    ev = evaluate(Bodies(np.stack([eye, moved]), np.stack([eye, eye]), np.stack([eye, eye])), [joints])
    r = ev.batches[0]
    assert abs(r.x[0] - 0.5) < 1e-15 and r.energy.tolist() == [0.0] and ev.total_energy == 0.0
    assert not r.gradient.any() and not r.hessian.any()
