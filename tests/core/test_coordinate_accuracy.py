"""x is an increment, not a difference of two large values: its error follows the step, not the scene.

Bodies 30 apart, anchors far from body j, steps of ~0.02 between q_ref, q_prev and q. Taking x
as the difference of two states' thetas (or of two O(1) sin-cos products) lost digits here
(measured when x was computed that way: prismatic 1.3e-13, revolute 1.8e-14 relative); the
increments keep 3.2e-14 and 1.3e-15 (the prismatic residue is the rounding of F ~ 30 itself).
"""

from __future__ import annotations

import numpy as np

from jointlimits.service.core import Bodies, Joints, evaluate
from bench.reference import reference_request
from tests.scenes import rotation_about


def _dof(p: np.ndarray, A: np.ndarray) -> np.ndarray:
    return np.r_[p, A.ravel()]


def _worst_relative_x_error(uid: int, base: int, trials: int = 20, floor: float = 0.0) -> float:
    rng = np.random.default_rng(7)
    worst = 0.0
    for _ in range(trials):
        R = [rotation_about(rng.normal(size=3), rng.uniform(-3, 3)) for _ in range(2)]
        pos = [np.zeros(3), 30 * rng.normal(size=3)]
        q_ref = np.array([_dof(p, A) for p, A in zip(pos, R)])
        turn = [rotation_about(rng.normal(size=3), 0.02) for _ in range(4)]
        q_prev = np.array([_dof(pos[k] + 0.01 * rng.normal(size=3), turn[k] @ R[k]) for k in range(2)])
        q = np.array([_dof(q_prev[k, :3] + 0.01 * rng.normal(size=3), turn[2 + k] @ q_prev[k, 3:].reshape(3, 3)) for k in range(2)])
        edge = np.array([[0.5, 0.2, 0.1], [0.5, 0.2, 0.1] + rng.normal(size=3)])
        joints = Joints(uid, base, np.array([[0, 1]]), edge[None], np.array([-10.0]), np.array([10.0]), np.array([1.0]))
        x = evaluate(Bodies(q, q_prev, q_ref), [joints], outputs=("energy",)).batches[0].x[0]
        request = {
            "bodies": {"q": q.tolist(), "q_prev": q_prev.tolist(), "q_ref": q_ref.tolist()},
            "batches": [{"constitution_uid": uid, "base_uid": base, "body_ids": [[0, 1]], "edges": edge[None].tolist(),
                         "lower": [-10.0], "upper": [10.0], "strength": [1.0]}],
        }  # fmt: skip
        exact = float(reference_request(request, derivatives=False)[0]["x"][0])
        worst = max(worst, abs(x - exact) / max(abs(exact), floor))
    return worst


def test_prismatic_slide_of_distant_bodies_keeps_its_digits() -> None:
    assert _worst_relative_x_error(669, 20) <= 6e-14  # measured 3.2e-14


def test_revolute_small_turns_of_distant_bodies_keep_their_digits() -> None:
    """Relative to the steps' size: each body turns 0.02 rad a step, and x, the sum of the steps' relative turns
    (one atan2 each), cancels to |x| = 0.002 in some trials; there x's own relative error is the steps' (a few ulps
    of 0.02 each) times |steps| / |x| ~ 10, and a kernel's ulps more in atan2 show there first (relative to |x|: 2.1e-15
    here, up to 9.9e-15 under `--perturb-ulps 4`, tests/perturb.py). Against max(|x|, 0.02): 3.9e-16 measured here,
    <= 1.2e-15 under `--perturb-ulps 4`; x taken as the difference of two O(1) angles errs by ulps of 1 (~2e-16
    absolute), 1e-14 of 0.02, which 4e-15 still fails."""
    assert _worst_relative_x_error(670, 18, floor=0.02) <= 4e-15


def test_prismatic_slide_after_the_body_shrank_keeps_its_digits() -> None:
    """World-edge anchors meet at q_ref (`C_i = C_j = p0`), so theta(q_ref) is exactly 0 and x = theta(q).
    Bodies 2^k times larger at q_ref than at q (a step as large as the frames: the careful path) took x as
    theta(q) - theta(q_ref), and theta(q_ref) is the rounding of `D_ref ~ 0` times `S_ref ~ 2^k`: measured
    relative errors 4.7e-10 at 2^20, 5.6e-7 at 2^30, 1.9e-3 at 2^40, 0.1 at 2^50 on x ~ 1.

    Exact reference: `A_ref = 2^k I` (so `R = I`, `c_k = 2^-k (p0 - p_ref_k)` exactly) and an axis along e_z
    (t exact), so `x = (D . S) / 2` at q in rationals. Bound: theta(q) from q's own frames rounds by a few u
    (|D| |S| + |x|), D, S ~ 1 here: 1e-14 relative (measured after the fix: <= 6e-16).
    """
    from fractions import Fraction

    rng = np.random.default_rng(27)
    for k in (10, 20, 30, 40, 50, 60):
        for _ in range(4):
            p_ref = rng.normal(size=(2, 3))
            q_ref = np.array([_dof(p, 2.0**k * np.eye(3)) for p in p_ref])
            q = np.array([_dof(rng.normal(size=3), rotation_about(rng.normal(size=3), rng.uniform(-3, 3))) for _ in range(2)])
            p0 = rng.normal(size=3)
            edge = np.array([p0, p0 + [0.0, 0.0, 0.75]])
            joints = Joints(669, 20, np.array([[0, 1]]), edge[None], np.array([-10.0]), np.array([10.0]), np.array([1.0]))
            x = evaluate(Bodies(q, q, q_ref), [joints], outputs=("energy",)).batches[0].x[0]
            F = lambda a: [Fraction(float(v)) for v in a]  # noqa: E731
            A = [[F(q[b, 3 + 3 * r : 6 + 3 * r]) for r in range(3)] for b in range(2)]
            c = [[(Fraction(float(p0[r])) - Fraction(float(p_ref[b, r]))) / 2**k for r in range(3)] for b in range(2)]
            C = [[Fraction(float(q[b, r])) + sum(A[b][r][m] * c[b][m] for m in range(3)) for r in range(3)] for b in range(2)]
            S = [A[0][r][2] + A[1][r][2] for r in range(3)]  # A_i e_z + A_j e_z
            exact = sum((C[1][r] - C[0][r]) * S[r] for r in range(3)) / 2
            assert abs(Fraction(float(x)) - exact) <= Fraction(1e-14) * abs(exact), (k, x, float(exact))
