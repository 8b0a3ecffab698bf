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


def _worst_relative_x_error(uid: int, base: int, trials: int = 20) -> float:
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
        worst = max(worst, abs(x - exact) / abs(exact))
    return worst


def test_prismatic_slide_of_distant_bodies_keeps_its_digits() -> None:
    assert _worst_relative_x_error(669, 20) <= 6e-14  # measured 3.2e-14


def test_revolute_small_turns_of_distant_bodies_keep_their_digits() -> None:
    assert _worst_relative_x_error(670, 18) <= 4e-15  # measured 1.3e-15
