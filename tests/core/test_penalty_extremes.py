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
    """Joints whose plain products all stay well inside the normal range (2^+-300) keep their bits, and so
    do joints inside their range; the others are formed from exponents (`test_sweep_against_exact_rationals`)."""
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
        steps = np.abs([r, r * r, r * r * r, sw, sw / w, *plain])
        keep = ((steps >= 2.0**-300) & (steps <= 2.0**300)).all(axis=0) | ((g == 0) & np.isfinite(sw / w))
    assert np.isfinite(w).all()
    assert 500 < keep.sum() < n
    for a, b in zip(got, plain):
        assert a[keep].tobytes() == b[keep].tobytes()


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


# ---------------------------------------------------------------- every scale (the integrator's cases, a sweep)

MAX = np.finfo(np.float64).max
ROUNDINGS = (6, 6, 5)
"""Roundings of E, E', E'' on either route with g and w exact: E = s r r r with r = g / w: 3 (r, cubed) + 3;
E' = 3 (s / w) (r r): s / w, 3 (s / w), r r, the product, and r twice (2); E'' = 6 (s / w / w) r: 3 + r's 2. From
exponents the same counts (mr = mg / mw for r, 3 ms, 6 ms and mw mw for the quotients), then one `ldexp`, exact
unless the result is subnormal (half a step more)."""


def _exact_nd(x: float, lower: float, upper: float, strength: float) -> list[tuple[int, int]]:
    """`_exact`'s E, E', E'' as (numerator, denominator > 0) integers, unreduced: no gcd (the sweep's 10^4 joints
    in about a second). E = s g^3 / w^3, E' = 3 side s g^2 / w^3, E'' = 6 s g / w^3."""
    (xn, xd), (ln, ld), (un, ud), (sn, sd) = (float(v).as_integer_ratio() for v in (x, lower, upper, strength))
    if x > upper:
        (gn, gd), side = (xn * ud - un * xd, xd * ud), 1
    elif x < lower:
        (gn, gd), side = (ln * xd - xn * ld, ld * xd), -1
    else:
        (gn, gd), side = (0, 1), 0
    wn, wd = (un * ld - ln * ud, ud * ld) if upper > lower else (1, 1)
    num, den = sn * wd**3, sd * wn**3
    return [(num * gn**3, den * gd**3), (3 * side * num * gn**2, den * gd**2), (6 * num * gn, den * gd)]


def _within(got: float, want: tuple[int, int], n: int) -> bool:
    """`got` within `n` roundings of `want` = N / D ((1 + u)^n - 1 <= n u / (1 - n u), relative), plus half a
    subnormal step (the last rounding below the normal range); inf only where `want` so widened passes float64."""
    N, D = want
    if np.isnan(got):
        return False
    if np.isinf(got):  # |N| / D (1 + n / (2^53 - n)) >= MAX
        return (got > 0) == (N > 0) and abs(N) * 2**53 >= int(MAX) * D * (2**53 - n)
    pn, pd = float(got).as_integer_ratio()  # |got - N / D| <= n |N| / ((2^53 - n) D) + 2^-1075
    return abs(pn * D - N * pd) * (2**53 - n) * 2**1075 <= n * abs(N) * pd * 2**1075 + pd * D * (2**53 - n)


# (x, lower, upper, strength): the integrator's five (a spurious 422 or a silent wrong number before), then
# s / w or s / w^2 subnormal or overflowing midway while E, E', E'' are normal.
BRIEF = [
    (1 + 1e110, 0.0, 1.0, 1e-300),  # r^3 overflows: E = 1e30 (inf before)
    (1 + 1e160, 0.0, 1.0, 1e-300),  # r^2 too: E' = 3e20
    (2.0, 0.0, 1e-200, 1e-300),  # r = 2e200
    (1e-110, -1.0, 0.0, 1e300),  # r^3 = 1e-330 underflows: E = 1e-30 (0 before, silently)
    (1e-103, -1.0, 0.0, 1e300),  # r^3 subnormal: E 2e-15 off before
]
MIDWAY = [
    (1e60, -1e10, 0.0, 1e-300),  # s / w^2 = 1e-320 (subnormal): E'' 1e-5 off before
    (-1e60, 0.0, 1e10, 1e-300),
    (5e-324, -1e-15, 0.0, 1e308),  # s / w overflows, r^2 underflows: E' NaN, E'' inf before
    (1e-110, -1e-10, 0.0, 1e308),  # s / w overflows: E' inf before (3e118)
]


@pytest.mark.parametrize("x,lower,upper,strength", BRIEF + MIDWAY)
def test_the_penalty_is_exact_where_its_products_leave_the_normal_range(x, lower, upper, strength):
    lo, up, s = np.array([lower, 0.0, 0.0]), np.array([upper, 1.0, 1.0]), np.array([strength, 1.0, 1.0])
    xs = np.array([x, 0.5, 2.0])  # an ordinary joint inside and one outside alongside
    with np.errstate(all="ignore"):
        got = penalty.derivatives(xs, lo, up, s)
        e = penalty.energy(xs, lo, up, s)
    for v, want, n in zip(got, _exact_nd(x, lower, upper, strength), ROUNDINGS):
        assert np.isfinite(v[0]) and _within(v[0], want, n), (v[0], float(Fraction(*want)))
    assert e.tobytes() == got[0].tobytes()
    assert [v[1:].tolist() for v in got] == [[0.0, 1.0], [0.0, 3.0], [0.0, 6.0]]


def _sweep() -> tuple[np.ndarray, ...]:
    """(x, lower, upper, strength) over a grid of exponents, each with a random 53-bit mantissa: s over
    2^[-1074, 1023] (subnormal too), g and w across the range, above (x = g, [-w, 0]), below (x = -g, [0, w]) and
    degenerate ([0, 0], w = 1), so that g and w are exact; and u - l or x - u overflowing, with exact halves."""
    rng = np.random.default_rng(20261129)
    es = np.r_[-1074, -1060, -1030, -1000:1001:250, 1023]
    ew = np.r_[-1074, -1000, -700, -400, -341, -200, -40, 0, 200, 341, 400, 700, 1023]
    m = lambda e: np.ldexp(1.0 + rng.random(np.shape(e)), e)  # noqa: E731
    S, G, W = np.meshgrid(es, ew, ew, indexing="ij")
    s, g, w = m(S.ravel()), m(G.ravel()), m(W.ravel())
    zero = np.zeros_like(g)
    big = np.ldexp(1.0, 1023)  # u - l or x - u overflows: 1.5, 1.75 or 2.5 * 2^1023, whose halves subtract exactly
    wide = [(1.75 * big, -big, 0.75 * big), (-1.75 * big, -0.75 * big, big), (1.5 * big, -big, -0.25 * big)]
    xw, lw, uw = (np.repeat(v, es.size) for v in zip(*wide))
    return (np.r_[g, -g, g, xw], np.r_[-w, zero, zero, lw], np.r_[zero, w, zero, uw],
            np.r_[s, s, s, np.tile(m(es), len(wide))])


def test_sweep_against_exact_rationals():
    """Every E, E', E'' of the sweep within its roundings of the exact value (`_within`): finite where the
    exact value is within float64, correctly subnormal or 0 below it, inf (the core's 422) beyond it; the
    energy alone the same bits; E', E'' formed times 2^k (`scale_up`) within their roundings of 2^k times
    the exact values, and at most 2^1000."""
    x, lower, upper, s = _sweep()
    with np.errstate(all="ignore"):
        E, dE, d2E = penalty.derivatives(x, lower, upper, s)
        e = penalty.energy(x, lower, upper, s)
        k = penalty.scale_up(dE2 := dE.copy(), d2E2 := d2E.copy(), x, lower, upper, s)
    assert e.tobytes() == E.tobytes()
    bad = []
    for j in range(x.size):
        (En, Ed), (dn, dd), (hn, hd) = exact = _exact_nd(x[j], lower[j], upper[j], s[j])
        up = 2 ** max(int(k[j]), 0), 2 ** max(-int(k[j]), 0)  # 2^k as a ratio
        lifted = (dn * up[0], dd * up[1]), (hn * up[0], hd * up[1])
        for got, want, n in zip((E[j], dE[j], d2E[j], dE2[j], d2E2[j]), (*exact, *lifted), ROUNDINGS + ROUNDINGS[1:]):
            if not _within(got, want, n):
                bad.append((j, x[j], lower[j], upper[j], s[j], got, Fraction(*want)))
    assert not bad, (len(bad), bad[:5])
    assert (np.abs(np.r_[dE2, d2E2]) <= 2.0**1000).all()  # inf too: k brings both into range (E''/E' = 2/g)


def _one_joint(uid: int, x: float, lower: float, upper: float, strength: float) -> dict:
    """A request of one joint at the coordinate `x` exactly: identity frames at q_ref, and body j slid by `x` along
    the axis (669), or `prev_coordinate` x with q = q_prev (670: DeltaTheta(q, q) is 0)."""
    eye = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    moved = [0.0, 0.0, x if uid == 669 else 0.0, *eye[3:]]
    batch = dict(constitution_uid=uid, base_uid=18 if uid == 670 else 20, body_ids=[[0, 1]],
                 edges=[[[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]], lower=[lower], upper=[upper], strength=[strength])
    if uid == 670:
        batch["prev_coordinate"] = [x]
    return dict(bodies=dict(q=[eye, moved], q_prev=[eye, moved], q_ref=[eye, eye]), batches=[batch],
                outputs=["energy", "gradient", "hessian"])


def _normwise(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.abs(np.asarray(got) - want).max() / np.abs(want).max())


@pytest.mark.parametrize("uid", [670, 669])
@pytest.mark.parametrize("x,lower,upper,strength", BRIEF)
def test_the_integrators_cases_are_answered_on_every_path(uid, x, lower, upper, strength):
    """HTTP (JSON), `LocalClient` (bitwise the service's) and an in-process session answer the exact energy
    (its roundings and 3 more: g = x - u rounded once, cubed) and the 50-digit reference's gradient and Hessian
    within 16u normwise (E', E'' to 6u; the identity frames' dx, d2x to a few roundings; sums of a few terms,
    measured 1.3u); before, a 422 or a wrong energy."""
    from bench.reference import reference_request
    from jointlimits.client import LocalClient

    doc = _one_joint(uid, x, lower, upper, strength)
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=doc)
    assert r.status_code == 200, r.text
    b = r.json()["batches"][0]
    assert b["x"] == [x]
    assert _within(b["energy"][0], _exact_nd(x, lower, upper, strength)[0], ROUNDINGS[0] + 3), b["energy"]
    ref = reference_request(doc)[0]
    assert _normwise(b["gradient"][0], ref["gradient"][0]) <= 16 * 2.0**-53
    assert _normwise(b["hessian"][0], ref["hessian_exact"][0]) <= 16 * 2.0**-53
    local = LocalClient().evaluate(doc).batches[0]
    for key in ("energy", "gradient", "hessian"):
        assert np.asarray(b[key]).tobytes() == getattr(local, key).tobytes(), key
    with LocalClient().session(doc) as s:
        sb = s.evaluate(doc["bodies"]["q"]).batches[0]
    assert _within(sb.energy[0], _exact_nd(x, lower, upper, strength)[0], ROUNDINGS[0] + 3), sb.energy
    assert _normwise(sb.gradient[0], ref["gradient"][0]) <= 16 * 2.0**-53
    assert _normwise(sb.hessian[0], ref["hessian_exact"][0]) <= 16 * 2.0**-53


def _shrunk(outputs: tuple[str, ...], mode: str = "exact") -> dict:
    """A prismatic joint whose bodies shrink to 1e-300 at q (dx/dq ~ 1e-300), 1e-250 above a range 1e-250 wide,
    strength 1e300: E = 1e300, E' = 3e550 beyond float64, the gradient E' dx/dq = 3e250 within it; the
    Hessian's E' d2x/dq2 (d2x ~ 1/2) beyond it."""
    eye, c = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], 1e-300
    tiny = [c * v for v in eye]
    q = [[0.0, 0.0, 0.0, *tiny], [0.0, 0.0, 0.5 * c, *tiny]]  # x = 0 (from q_ref's frames, where q = q_prev)
    batch = dict(constitution_uid=669, base_uid=20, body_ids=[[0, 1]], edges=[[[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]],
                 lower=[-2e-250], upper=[-1e-250], strength=[1e300])
    return dict(bodies=dict(q=q, q_prev=q, q_ref=[[0.0, 0.0, 0.0, *eye]] * 2), batches=[batch], outputs=list(outputs),
                hessian_mode=mode)


def test_a_gradient_within_float64_is_answered_where_E1_is_not():
    """E' is formed times 2^k with k < 0 there (`penalty.scale_up`) and the gradient scaled back: the 50-digit
    reference's within 16u (measured 0: E' rounds ~6 times, dx/dq exact at these frames); before, a 422."""
    from bench.reference import reference_request

    doc = _shrunk(("energy", "gradient"))
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=doc)
    assert r.status_code == 200, r.text
    b, ref = r.json()["batches"][0], reference_request(doc, hessians=False)[0]
    assert b["x"] == [0.0] and b["energy"] == [1e300] and 1e250 < np.abs(ref["gradient"]).max() < 1e251
    assert _normwise(b["gradient"][0], ref["gradient"][0]) <= 16 * 2.0**-53


@pytest.mark.parametrize("mode", ["exact", "psd"])
def test_a_hessian_beyond_float64_scaled_back_is_still_a_422(mode):
    """The Hessian of `_shrunk` formed with E' 2^k (k < 0) overflows when scaled back: checked then (a 200 carried
    inf before the check)."""
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=_shrunk(("energy", "gradient", "hessian"), mode))
    assert r.status_code == 422, r.text
    assert [d["loc"] for d in r.json()["detail"]] == [["body", "batches", 0, "strength", 0]]
