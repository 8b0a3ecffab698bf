"""A joint's geometry at `q_ref`: its world axis `t` and its anchors in the two bodies' own coordinates, from
which each constitution makes its body-local vectors (`Constitution.local_vectors`). CONTRACT.md v1.2:

- `edges` (N, 2, 3), `p0 -> p1` in world space at `q_ref`: `t = (p1 - p0) / |p1 - p0|`,
  anchors `c_k = A_ref_k^{-1} (p0 - p_ref_k)`;
- `local_edges` (N, 2, 2, 3), `[[l0, l1], [r0, r1]]` in body i's and body j's coordinates (the engine's local
  variant): `t` is `l1 - l0` carried to the world by body i's `R_i` or `A_ref_i` (`Facts.axis_by_rotation`),
  anchors `c_i = l0`, `c_j = r0`.
"""

from __future__ import annotations

import numpy as np

from jointlimits.service.core.constitution import Array, Constitution
from jointlimits.service.core.kinematics import SMALL, axis, component_major, edge_vector, from_local, solve3


def axis_and_anchors(c: Constitution, edges: Array | None, local_edges: Array | None, p_ref: Array | None,
                     A_ref: Array, R_ref: Array, d: Array | None = None) -> tuple[Array, Array | None]:
    """The unit world axis `t` (N, 3) and, with points, the body-local anchors (N, 2, 3) (else None), both
    component-major. `p_ref` (N, 2, 3), `A_ref` and `R_ref` (N, 2, 3, 3) of bodies i, j; `d` (N, 3) the edge
    vectors `p1 - p0` (or `l1 - l0`) if already taken (`validate.joint_faults`)."""
    points = c.facts.points
    if local_edges is None:
        return axis(edge_vector(edges) if d is None else d), (_world_anchors(edges, p_ref, A_ref) if points else None)
    d = edge_vector(local_edges[:, 0]) if d is None else d  # l1 - l0, in body i's coordinates
    # Both factors scaled by powers of two (exact; the direction is all that counts): `M d` then
    # neither overflows nor underflows for any finite, nonzero `d` and a nonsingular `A_ref`.
    M = R_ref[:, 0] if c.facts.axis_by_rotation else _unit_scaled(A_ref[:, 0])
    t = axis(from_local(M, _unit_scaled(d)))
    if not points:
        return t, None
    anchors = component_major(t.shape[0], (2, 3), t.dtype)
    anchors[...] = local_edges[:, :, 0]  # l0 on body i, r0 on body j
    return t, anchors


def _unit_scaled(a: Array) -> Array:
    """Each row of `a` (N, ...) times the power of two that puts its largest magnitude in [0.5, 1) (exact)."""
    _, e = np.frexp(np.abs(a).reshape(a.shape[0], int(np.prod(a.shape[1:]))).max(axis=1, initial=0.0))  # N may be 0
    return np.ldexp(a, -e.reshape(-1, *(1,) * (a.ndim - 1)))


def _world_anchors(edges: Array, p_ref: Array, A_ref: Array) -> Array:
    """`c_k = A_ref_k^{-1} (p0 - p_ref_k)` (N, 2, 3): the difference first, then the solve."""
    n = edges.shape[0]
    d = component_major(n, (2, 3), edges.dtype)
    if n <= SMALL:  # a few joints: one pass
        np.subtract(edges[:, 0, None], p_ref, out=d)
    else:
        for r in range(3):
            np.subtract(edges[:, 0, r, None], p_ref[:, :, r], out=d[:, :, r])
    return solve3(A_ref, d)
