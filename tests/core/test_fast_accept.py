"""A batch's fast accept (`validate._clean`: a few flat reductions over what is usually clean) vouches only for what
the detailed pass (`validate._check_rows`) finds clean: on hostile and edge values (widths and strengths of 0, edges
whose `dot(e, e)` under- or overflows, sums that overflow) the faults are the detailed pass's, one for one."""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.service.core import Joints
from jointlimits.service.core.kinematics import edge_vector
from jointlimits.service.core.validate import _check_rows, check_joints

ODD = [0.0, -0.0, 1.0, -1.0, 1e-170, 5e-324, 1e200, 1e308, -1e308, np.inf, -np.inf, np.nan]
"""Values the fast accept must decline (or take as the detailed pass does)."""


def _detailed(b: int, joints: Joints, n_bodies: int) -> list:
    """`check_joints` of a well-formed batch with no fast accept: `_check_rows` alone."""
    with np.errstate(all="ignore"):
        geometry = "edges" if joints.edges is not None else "local_edges"
        ends = joints.edges if geometry == "edges" else joints.local_edges[:, 0]
        shaped = {"body_ids", "lower", "upper", "strength", geometry}
        shaped |= {k for k in ("offset", "prev_coordinate") if getattr(joints, k) is not None}
        return _check_rows(b, joints, n_bodies, geometry, shaped, edge_vector(ends))[:20]


def _batch(rng: np.random.Generator, n: int, local: bool) -> Joints:
    ids = np.stack([np.zeros(n, np.int64), np.ones(n, np.int64)], axis=1)
    edges = rng.normal(size=(n, 2, 2, 3) if local else (n, 2, 3))
    lower = -rng.random(n)
    return Joints(670, 18, ids, None if local else edges, lower, lower + 1.0, rng.random(n) + 0.5,
                  offset=rng.normal(size=n), local_edges=edges if local else None)


@pytest.mark.parametrize("local", [False, True])
@pytest.mark.parametrize("field", ["lower", "upper", "strength", "offset", "edge", "far end"])
def test_each_odd_value_named_as_the_detailed_pass_names_it(field: str, local: bool) -> None:
    rng = np.random.default_rng(len(field) + local)
    joints = _batch(rng, len(ODD), local)
    for j, value in enumerate(ODD):
        if field == "edge":  # the edge vector itself: p1 = p0 + value (or l1 = l0 + value)
            ends = joints.local_edges[:, 0] if local else joints.edges
            ends[j, 1] = ends[j, 0] + value
        elif field == "far end":  # r1 of a body-local edge (not in the edge vector), else p0 and p1 together
            (joints.local_edges[j, 1, 1] if local else joints.edges[j])[...] = value
        elif field in ("lower", "upper"):
            getattr(joints, field)[j] = value
            if field == "lower":
                joints.upper[j] = max(value, 0.0) if np.isfinite(value) else 1.0  # in order where finite
        else:
            getattr(joints, field)[j] = value
    assert check_joints(0, joints, 2) == _detailed(0, joints, 2)
    for j in range(len(ODD)):  # one odd joint among clean ones: fast accept declined or right
        one = _batch(rng, 3, local)
        for name in ("lower", "upper", "strength", "offset", "edges", "local_edges", "body_ids"):
            a = getattr(joints, name)
            if a is not None:
                getattr(one, name)[1] = a[j]
        assert check_joints(0, one, 2) == _detailed(0, one, 2)


def test_ranges_at_the_edge_of_float64_and_zero_widths_are_clean() -> None:
    """Valid batches at the fast accept's edges (`upper - lower` overflows, widths and strengths of 0, an edge of
    1e-170 whose `dot` underflows, one of 1e200 whose `dot` overflows): no fault."""
    n = 5
    ids = np.array([[0, 1]] * n)
    p0 = np.zeros((n, 3))
    t = np.array([[1e-170, 0, 0], [1e200, 1e200, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    joints = Joints(669, 20, ids, np.stack([p0, p0 + t], axis=1), np.array([-1e308, 0, 1, -1, 2]),
                    np.array([1e308, 0, 1, 1, 2]), np.array([1.0, 0.0, 1, 0, 2]))
    assert check_joints(0, joints, 2) == []
