"""#669 at the scales of issue 27, against the independent reference (bench/reference.py: 50 digits, or 700
where theta(q_ref) ~ 1e300 must cancel to leave theta(q)).

- `origin: "absolute"`: x is theta(q) itself, from the frames at q (`prepared.PreparedScene._step`), not
  theta(q_ref) plus the slide since, which keeps theta(q) only to the rounding of theta(q_ref); the frames
  at q keep body j's position at q whole, whatever the origin.

u = 2^-53 throughout.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench import reference
from jointlimits.service.core import Bodies, Joints, evaluate
from jointlimits.service.core.prepared import prepare
from tests import engine_ref
from tests.conftest import relerr
from tests.scenes import rotation_about

U = 2.0**-53
T = np.array([0.6, 0.0, 0.8])  # the axis in body i's coordinates (|T| = 1 up to its rounding)


def _dof(p: np.ndarray, A: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(p, dtype=np.float64), np.asarray(A, dtype=np.float64).reshape(9)])


def _joints(L: np.ndarray, lower: np.ndarray, upper: np.ndarray, origin: str) -> Joints:
    n = L.shape[0]
    ids = np.arange(2 * n).reshape(n, 2)
    return Joints(669, 20, ids, None, np.asarray(lower, float), np.asarray(upper, float), np.ones(n), local_edges=L, origin=origin)


def _reference(q: np.ndarray, q_ref: np.ndarray, L: np.ndarray, k: int, lower: float, upper: float, origin: str,
               derivatives: bool = True) -> dict:
    """Joint k (bodies 2k, 2k + 1, q_prev = q_ref) at `reference.DPS` digits, rounded to float64."""
    i, j = 2 * k, 2 * k + 1
    ref = reference.JointRef(669, q_ref[i], q_ref[j], local_edge=L[k])
    return ref.evaluate((q[i], q[j]), (q_ref[i], q_ref[j]), (q_ref[i], q_ref[j]), lower, upper, 1.0, derivatives,
                        origin=origin).as_float()


def _sizes(q: np.ndarray, q_ref: np.ndarray, L: np.ndarray, k: int) -> dict[str, float]:
    """Joint k's term sizes (float64, for bounds): M (|A_i c_i| + |A_j c_j| + |r|) and N (|A_i t_i| + |A_j t_j|)
    at q_ref and at q, dM and dN of A's and r's increments, and |r| at both."""
    i, j = 2 * k, 2 * k + 1
    A = {s: [Q[b, 3:].reshape(3, 3) for b in (i, j)] for s, Q in (("ref", q_ref), ("q", q))}
    r = {s: Q[j, :3] - Q[i, :3] for s, Q in (("ref", q_ref), ("q", q))}
    t = A["ref"][0] @ (L[k, 0, 1] - L[k, 0, 0])
    t /= np.linalg.norm(t)
    t_k = [(U_ @ Vt).T @ t for U_, _, Vt in (np.linalg.svd(a) for a in A["ref"])]  # R_k^T t
    c = [L[k, 0, 0], L[k, 1, 0]]
    size = lambda M, v: sum(np.linalg.norm(m @ w) for m, w in zip(M, v))  # noqa: E731
    dA = [a - b for a, b in zip(A["q"], A["ref"])]
    return dict(M_ref=size(A["ref"], c) + np.linalg.norm(r["ref"]), M_q=size(A["q"], c) + np.linalg.norm(r["q"]),
                N_ref=size(A["ref"], t_k), N_q=size(A["q"], t_k), dM=size(dA, c) + np.linalg.norm(r["q"] - r["ref"]),
                dN=size(dA, t_k), r=np.linalg.norm(r["q"]) + np.linalg.norm(r["ref"]))


def _bound(z: dict[str, float], x: float, origin: str) -> float:
    """x's error bound, first order (`PreparedScene._step`).

    The frames' terms round: D (A c: 3 products, 2 sums; + r, then C_j - C_i) by 5u of their sizes M,
    S (A t_k: 3u, and t_k itself ~8u: normalised, turned by R_k^T, both sides) by 12u of N. x = D.S / 2:
    absolute, theta(q): (5 + 12 + 3 for the dot) u M N / 2 = 10u M_q N_q, and u|x| for the last sum (2u|x|).
    Norms stand for sums of |products| (first order).
    """
    assert origin == "absolute"
    return 10 * U * z["M_q"] * z["N_q"] + 2 * U * abs(x)


# ---------------------------------------------------------------- 1. the absolute slide of distant bodies


def _far_apart(apart: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two unrotated bodies built `apart` along the axis, then body j slid back to 0.4 from body i; the
    anchors at the bodies' origins. Returns q, q_ref (2, 12) and the local edges (1, 2, 2, 3)."""
    q_ref = np.array([_dof([0, 0, 0], np.eye(3)), _dof(apart * T, np.eye(3))])
    q = np.array([_dof([0, 0, 0], np.eye(3)), _dof(0.4 * T, np.eye(3))])
    L = np.array([[[[0.0, 0, 0], T], [[0.0, 0, 0], [1.0, 0, 0]]]])
    return q, q_ref, L


@pytest.mark.parametrize("apart", [1e12, 1e17])
@pytest.mark.parametrize("mode", ["exact", "psd"])
def test_absolute_slide_of_bodies_built_far_apart(apart: float, mode: str) -> None:
    """x = 0.4 above the range [-0.1, 0] (E = 64), whatever theta(q_ref) (measured before: x = 0.39990234
    at 1e12 apart, x = 0 and E = 0 in a 200 at 1e17).

    Tolerance 64u = 7.1e-15 normwise. The inputs are exact here (D = r(q) = 0.4 T as given, A = I, R = I
    exactly) but for the axis, whose normalisation rounds 3 times: x = D.t to 6u, E ~ x^3 to 3 (6u) + 3u,
    the derivatives to 2 (6u) plus E', E'' (4) and the chain rule's products and sums (~10): ~25u, on terms
    of one sign. Measured <= 2u.
    """
    q, q_ref, L = _far_apart(apart)
    ev = evaluate(Bodies(q, q_ref, q_ref), [_joints(L, [-0.1], [0.0], "absolute")], hessian_mode=mode).batches[0]
    want = _reference(q, q_ref, L, 0, -0.1, 0.0, "absolute")
    for field, got in (("x", ev.x[0]), ("energy", ev.energy[0]), ("gradient", ev.gradient[0])):
        assert relerr(got, want[field]) <= 64 * U, field
    assert relerr(ev.hessian[0], want[f"hessian_{mode}"]) <= 64 * U


@pytest.mark.parametrize("apart", [1e12, 1e17])
def test_a_session_commits_the_absolute_slide(apart: float) -> None:
    """A prepared scene's evaluation and its commit (`PreparedScene._from_ref`) take the same theta(q)."""
    q, q_ref, L = _far_apart(apart)
    scene = prepare(Bodies(q_ref, q_ref, q_ref), [_joints(L, [-0.1], [0.0], "absolute")])
    assert relerr(scene.evaluate(q).batches[0].x, [0.4]) <= 8 * U  # the axis' 3 roundings and the dot's 3
    assert relerr(scene.commit(q)[0], [0.4]) <= 8 * U
    assert relerr(scene.coordinates()[0], [0.4]) <= 8 * U


@pytest.mark.parametrize("apart", [1e12, 1e17])
def test_q_ref_slide_of_bodies_built_far_apart_keeps_its_derivatives(apart: float) -> None:
    """Origin q_ref, the same bodies: x = theta(q) - theta(q_ref) ~ -apart rounds at apart's scale (as it
    must), but the derivatives read D at q, 0.4 T, which the frames at q keep whole (body j's position at q
    its own: `PreparedScene._step`; measured before: D 2.4e-4 off at 1e12 and 0 at 1e17, the gradient
    2.7e-5 and 0.16 off normwise). The range [0, 1] lies `apart` above x: E' and E'' read x only through
    g ~ apart, to its rounding. Tolerance 64u as above; measured <= 5.7u."""
    q, q_ref, L = _far_apart(apart)
    for mode in ("exact", "psd"):
        ev = evaluate(Bodies(q, q_ref, q_ref), [_joints(L, [0.0], [1.0], "q_ref")], hessian_mode=mode).batches[0]
        want = _reference(q, q_ref, L, 0, 0.0, 1.0, "q_ref")
        assert relerr(ev.x[0], want["x"]) <= 64 * U
        assert relerr(ev.gradient[0], want["gradient"]) <= 64 * U
        assert relerr(ev.hessian[0], want[f"hessian_{mode}"]) <= 64 * U


def _huge_reference() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four joints whose bodies' A_ref are 1e150 times a stretched rotation (theta(q_ref) ~ 1e300), and
    whose A at q are of order 1: q, q_ref (8, 12), local edges (4, 2, 2, 3)."""
    rng = np.random.default_rng(27)
    n = 4
    q_ref, q = np.empty((2 * n, 12)), np.empty((2 * n, 12))
    L = rng.normal(size=(n, 2, 2, 3))
    for b in range(2 * n):
        A = rotation_about(rng.normal(size=3), rng.uniform(-3, 3)) @ (np.eye(3) + 0.2 * rng.normal(size=(3, 3)))
        p = rng.normal(size=3)
        q_ref[b] = _dof(p, 1e150 * A)
        q[b] = _dof(p + 0.3 * rng.normal(size=3), rotation_about(rng.normal(size=3), 0.5) @ A)
    return q, q_ref, L


def test_absolute_slide_after_a_huge_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    """A_ref 1e150 times a stretched rotation (the careful frames), A at q of order 1: x = theta(q), of order
    1, against 700 digits (measured before: x = 0, E = 0 in a 200). x within `_bound`, E within 3 |x - x_ref| / g
    plus the penalty's 8u, the gradient (E' ~ g^2) within 2 |x - x_ref| / g plus 16u. Measured: x within 0.3
    of its bound."""
    monkeypatch.setattr(reference, "DPS", 700)
    q, q_ref, L = _huge_reference()
    pair = lambda Q: (Q[0::2], Q[1::2])  # noqa: E731
    x_est = engine_ref.prismatic(pair(q), pair(q_ref), pair(q_ref), -1.0, 1.0, 1.0, local_edges=L, origin="absolute").x
    upper = x_est - 0.5 * np.abs(x_est)  # only placed from x: every answer is checked against the reference
    lower = upper - 0.25 * np.abs(x_est)
    ev = evaluate(Bodies(q, q_ref, q_ref), [_joints(L, lower, upper, "absolute")]).batches[0]
    for k in range(L.shape[0]):
        want = _reference(q, q_ref, L, k, lower[k], upper[k], "absolute")
        bound = _bound(_sizes(q, q_ref, L, k), want["x"], "absolute")
        assert abs(ev.x[k] - want["x"]) <= bound, k
        g = want["x"] - upper[k]
        assert relerr(ev.energy[k], want["energy"]) <= 3 * bound / g + 8 * U, k
        assert relerr(ev.gradient[k], want["gradient"]) <= 2 * bound / g + 16 * U, k
