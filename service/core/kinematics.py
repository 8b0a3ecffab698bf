"""Affine-body kinematics shared by all constitutions.

A body's 12 DOFs are `q = [p (3), A row 0, A row 1, A row 2]`. Every joint
exposes four frame quantities `F_k` (k = 0, 1 on body i; k = 2, 3 on body j),
each an affine function of its body's DOFs:

    F_k = alpha_k (p - o) + A v_k,

with `v_k` a body-local vector fixed at `q_ref` and `alpha_k` 1 for points
(that follow translation) and 0 for directions. `o` is a per-joint origin
(body i's position in the same state): every joint coordinate is invariant
under a translation of the scene, and subtracting `o` first keeps a scene far
from the origin from losing digits to its translation.
"""

from __future__ import annotations

from collections.abc import Iterable
from functools import partial

import numpy as np
from numpy.typing import NDArray

from service.core.parallel import run_all
from service.core.polar import polar_rotation
from service.core.scene import Bodies

Array = NDArray[np.float64]

# Which body each frame quantity belongs to (0: body i, 1: body j).
BLOCK_BODY = np.array([0, 0, 1, 1])

# The body table holds `A` at the reference state and its increments, each taken once per
# body; a joint coordinate is then an increment of a bilinear form in the increments of F
# (no cancellation between two large values of two states), see the constitutions.
REF, PREV_STEP, STEP, TOTAL_STEP = range(4)
"""Rows of `A` in the body table: at `q_ref`, then `q_prev - q_ref`, `q - q_prev`, `q - q_ref`."""
STEPS = {PREV_STEP: (0, 1), STEP: (1, 2), TOTAL_STEP: (0, 2)}
"""Each increment row of `A` as (from, to) states: 0 q_ref, 1 q_prev, 2 q."""


def solve3(A: Array, b: Array) -> list[Array]:
    """Components of `A^-1 b` (each (...,)) for `A` (..., 3, 3), `b` (..., 3), by cofactors.

    `A^-1 = C^T / det`: a 3 x 3 LAPACK call per joint costs more than these passes,
    which read `A` in place, whatever its layout.
    """
    C = [
        [A[..., i, k] * A[..., j, l] - A[..., i, l] * A[..., j, k] for k, l in ((1, 2), (2, 0), (0, 1))]
        for i, j in ((1, 2), (2, 0), (0, 1))
    ]
    det = A[..., 0, 0] * C[0][0] + A[..., 0, 1] * C[0][1] + A[..., 0, 2] * C[0][2]
    return [(C[0][c] * b[..., 0] + C[1][c] * b[..., 1] + C[2][c] * b[..., 2]) / det for c in range(3)]


def component_major(n: int, shape: tuple[int, ...], dtype: type = np.float64) -> Array:
    """An empty (N, *shape) array stored component-major: every `a[:, i, ..]` is a contiguous (N,) row.

    The kernels here work on whole columns of N numbers: NumPy's broadcasting over
    trailing 3-vectors (or a batched 3 x 3 matmul) spends its time in per-row loop
    overhead, 5x slower. Elementwise ufuncs keep this layout (order K).
    """
    return np.moveaxis(np.empty(shape + (n,), dtype=dtype), -1, 0)


class BodyTable:
    """Every body's positions, its `A` at `q_ref` and `A`'s increments, and its reference rotation, component-major.

    Built once per evaluation (B bodies, whatever the number of joints); each batch
    then gathers its joints' two bodies with one `take` per row. Positions stay
    absolute: a joint differences its two bodies' positions within one state first
    (small), then across states. `ratio` (B,) is each `A_ref`'s conditioning (`polar_rotation`).
    """

    def __init__(
        self,
        bodies: Bodies,
        dtype: type = np.float64,
        threads: int = 1,
        rows: Iterable[int] = STEPS,
    ) -> None:
        """Only the increment `rows` of `A`, and the states they span, are filled (the others are garbage)."""
        n = bodies.q.shape[0]
        rows = tuple(rows)
        q = (bodies.q_ref, bodies.q_prev, bodies.q)
        dofs = np.empty((3, 12, n), dtype=dtype)  # (q_ref, q_prev, q; DOF; body): one transposed copy per state
        for s in {0, *(s for row in rows for s in STEPS[row])}:
            dofs[s] = q[s].T
        self.dofs = dofs  # (state; DOF; body), the unfilled states garbage
        self.positions = dofs[:, :3]  # (state; xyz; body)
        self.linear = np.empty((4, 9, n), dtype=dtype)  # (REF..TOTAL_STEP; A[r, c]; body)
        self.linear[REF] = dofs[0, 3:]
        for row in rows:
            a, b = STEPS[row]
            np.subtract(dofs[b, 3:], dofs[a, 3:], out=self.linear[row])
        # The polar factors in float64 whatever `dtype`: they decide which A_ref is singular.
        A_ref = self.linear[REF] if self.linear.dtype == np.float64 else np.ascontiguousarray(bodies.q_ref[:, 3:].T)
        parts = np.array_split(A_ref, threads, axis=1) if threads > 1 else [A_ref]
        parts = run_all([partial(polar_rotation, a) for a in parts], threads)
        R, self.ratio = parts[0] if len(parts) == 1 else (np.concatenate(a, axis=-1) for a in zip(*parts))
        self.rotation = R.astype(dtype, copy=False)  # (9, B)

    def positions_of(self, pairs: NDArray[np.intp], state: int) -> Array:
        """`p` (N, 2, 3) of joints `pairs` in `state` (0: q_ref, 1: q_prev, 2: q).

        `pairs` (2, N) contiguous: each joint's bodies i and j (the transpose of `body_ids`).
        """
        return np.take(self.positions[state], pairs, axis=1).transpose(2, 1, 0)

    def linear_of(self, pairs: NDArray[np.intp], row: int) -> Array:
        """`A` (N, 2, 3, 3) of joints `pairs` (2, N) at `q_ref` (`REF`) or its increment `row`."""
        return self._matrices(self.linear[row], pairs)

    def rotations(self, pairs: NDArray[np.intp]) -> Array:
        """`R_ref` (N, 2, 3, 3) of joints `pairs` (2, N)."""
        return self._matrices(self.rotation, pairs)

    @staticmethod
    def _matrices(rows: Array, pairs: NDArray[np.intp]) -> Array:
        g = np.take(rows, pairs, axis=1)  # (9, 2, N)
        return g.reshape(3, 3, *g.shape[1:]).transpose(3, 2, 0, 1)


def frame_quantities(r: Array | None, A: Array, alpha: Array, v: Array) -> Array:
    """`F` (N, 4, 3), component-major, of joints whose bodies have `A` (N, 2, 3, 3), body j at `r` (N, 3) from body i.

    `alpha` (4,) and `v` (N, 4, 3) as in the module docstring; `r` may be None when
    `alpha` is zero. `F` is linear in `(r, A)`: their increments give the increment of `F`.
    """
    n = A.shape[0]
    F = component_major(n, (4, 3), A.dtype)
    tmp = np.empty(n, dtype=A.dtype)
    for k in range(4):
        side = BLOCK_BODY[k]
        for row in range(3):
            out = F[:, k, row]
            np.multiply(A[:, side, row, 0], v[:, k, 0], out=out)
            out += np.multiply(A[:, side, row, 1], v[:, k, 1], out=tmp)
            out += np.multiply(A[:, side, row, 2], v[:, k, 2], out=tmp)
    for k in (2, 3):  # body i is the origin: F_0, F_1 see no position
        if alpha[k]:
            F[:, k] += alpha[k] * r
    return F


def relative_position(p: Array) -> Array:
    """Body j's position from body i's, `r` (N, 3), of positions `p` (N, 2, 3) in one state.

    Nearby positions are differenced before anything large is added: a scene far from
    the origin, or moved far between states, loses no digits to its translation.
    """
    r = component_major(p.shape[0], (3,), p.dtype)
    np.subtract(p[:, 1], p[:, 0], out=r)
    return r


def dot(a: Array, b: Array) -> Array:
    """Row-wise dot (N,) of (N, 3) arrays, column by column."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def cross(a: Array, b: Array) -> Array:
    """Row-wise cross product of (N, 3) arrays, component-major."""
    out = component_major(a.shape[0], (3,), a.dtype)
    for r in range(3):
        i, j = (r + 1) % 3, (r + 2) % 3
        np.subtract(a[:, i] * b[:, j], a[:, j] * b[:, i], out=out[:, r])
    return out


def to_local(R: Array, w: Array) -> Array:
    """`R^T w` (N, 3), component-major, for rotations `R` (N, 3, 3) and world vectors `w` (N, 3)."""
    out = component_major(w.shape[0], (3,), w.dtype)
    for c in range(3):
        np.add(R[:, 0, c] * w[:, 0] + R[:, 1, c] * w[:, 1], R[:, 2, c] * w[:, 2], out=out[:, c])
    return out


def edge_axis(edges: Array) -> Array:
    """Unit joint axis `t` (N, 3), component-major, of edges `p0 -> p1` (N, 2, 3)."""
    d = component_major(edges.shape[0], (3,), edges.dtype)
    np.subtract(edges[:, 1], edges[:, 0], out=d)
    return unit(d)


def unit(v: Array) -> Array:
    """Each row of `v` (N, 3) over its length, in `v`'s layout."""
    return v / np.sqrt(dot(v, v))[:, None]
