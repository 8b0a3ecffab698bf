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

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from jointlimits.service.core.polar import polar_rotation
from jointlimits.service.core.scene import Bodies

Array = NDArray[np.float64]

# Which body each frame quantity belongs to (0: body i, 1: body j).
BLOCK_BODY = np.array([0, 0, 1, 1])
SMALL = 256
"""Joints up to which a kernel takes whole (N, 4, 3) blocks per pass: each pass's call overhead, not its
N numbers, is the cost there (`frame_quantities`: 36 passes of N, or 3 of 12 N; measured equal near 500)."""

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
    which read `A` in place, whatever its layout. Where `det` (~|A|^3) or a product leaves
    float64's comfortable range (|A| beyond ~1e+-100), those rows are solved again with
    `A` scaled by a power of two (exact): `A^-1 b = 2^-e (2^-e A)^-1 b`.
    """
    # Overflow is expected on the first pass (redone below) and legitimate on the second (an
    # anchor beyond float64: the coordinate overflows and `validate` names the joint).
    with np.errstate(all="ignore"):
        x, det = _solve3_cofactors(A, b)
        bad = ~((np.abs(det) >= _DET_MIN) & (np.abs(det) <= _DET_MAX) & np.isfinite(x[0] + x[1] + x[2]))
        if bad.any():
            idx = np.nonzero(bad)
            A_bad = A[idx]  # (M, 3, 3)
            _, e = np.frexp(np.abs(A_bad).max(axis=(-2, -1)))
            scaled, _ = _solve3_cofactors(np.ldexp(A_bad, -e[:, None, None]), b[idx])
            for k in range(3):
                x[k][idx] = np.ldexp(scaled[k], -e)
    return x


_DET_MIN, _DET_MAX = 2.0**-900, 2.0**900
"""`det` of a 3 x 3 `A` inside this range keeps its cofactors (~det^(2/3)) normal numbers."""


# Cofactor (3 i' + k') of A (flat, row-major) = A[_CP] A[_CQ] - A[_CS] A[_CT], in `_solve3_cofactors`' order.
_CP, _CQ, _CS, _CT = (np.array(e) for e in zip(*(
    (3 * i + k, 3 * j + l, 3 * i + l, 3 * j + k) for i, j in ((1, 2), (2, 0), (0, 1)) for k, l in ((1, 2), (2, 0), (0, 1))
)))


def _solve3_cofactors(A: Array, b: Array) -> tuple[list[Array], Array]:
    if b[..., 0].size <= SMALL:  # a few systems: the nine cofactors and three components in whole passes (the
        # same products and sums, in the same order, as the entry-by-entry form below)
        A9 = A.reshape(*A.shape[:-2], 9)
        C9 = A9[..., _CP] * A9[..., _CQ] - A9[..., _CS] * A9[..., _CT]
        det = A9[..., 0] * C9[..., 0] + A9[..., 1] * C9[..., 1] + A9[..., 2] * C9[..., 2]
        x = (C9[..., 0:3] * b[..., 0, None] + C9[..., 3:6] * b[..., 1, None] + C9[..., 6:9] * b[..., 2, None]) / det[..., None]
        return [x[..., 0], x[..., 1], x[..., 2]], det
    C = [
        [A[..., i, k] * A[..., j, l] - A[..., i, l] * A[..., j, k] for k, l in ((1, 2), (2, 0), (0, 1))]
        for i, j in ((1, 2), (2, 0), (0, 1))
    ]
    det = A[..., 0, 0] * C[0][0] + A[..., 0, 1] * C[0][1] + A[..., 0, 2] * C[0][2]
    return [(C[0][c] * b[..., 0] + C[1][c] * b[..., 1] + C[2][c] * b[..., 2]) / det for c in range(3)], det


def component_major(n: int, shape: tuple[int, ...], dtype: type = np.float64) -> Array:
    """An empty (N, *shape) array stored component-major: every `a[:, i, ..]` is a contiguous (N,) row.

    The kernels here work on whole columns of N numbers: NumPy's broadcasting over
    trailing 3-vectors (or a batched 3 x 3 matmul) spends its time in per-row loop
    overhead, 5x slower. Elementwise ufuncs keep this layout (order K).
    """
    k = len(shape)
    return np.empty(shape + (n,), dtype=dtype).transpose((k, *range(k)))  # moveaxis, less its checks (~3 us)


GATHER = "wrap"
"""`np.take`'s mode for the gathers of bodies and joints, whose indices are in range (`validate.check_joints`
refuses the others before any gather; joint positions come from `nonzero`): for such indices "wrap"
reads the very same elements, without the default mode's per-index bounds check and error path, which
made each gather about twice as slow (NumPy 2.x)."""


def take_joints(a: NDArray, sel: NDArray[np.intp]) -> NDArray:
    """Rows `sel` (M,) of `a` (N, ...) in `a`'s layout: a contiguous range is a view, other rows one
    `take` along the joints' axis (fancy indexing would give C order: a component-major array's
    kernels would then run along its short trailing axes)."""
    if sel.shape[0] and sel[-1] - sel[0] + 1 == sel.shape[0]:
        return a[sel[0] : sel[-1] + 1]
    return np.moveaxis(np.take(np.moveaxis(a, 0, -1), sel, axis=-1, mode=GATHER), -1, 0)


TRANSPOSE_BLOCK = 1024
"""Bodies `transpose_into` moves at once: a block's rows stay in cache while its columns are written."""


def transpose_into(out: Array, a: Array) -> None:
    """`out[...] = a.T` for `a` (B, K), `out` (K, B), a block of bodies at a time (a fifth faster at 5e4 x 12)."""
    for s in range(0, a.shape[0], TRANSPOSE_BLOCK):
        out[:, s : s + TRANSPOSE_BLOCK] = a[s : s + TRANSPOSE_BLOCK].T


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
        rows: Iterable[int] = STEPS,
        used: NDArray[np.bool_] | None = None,
        rotate: bool = True,
    ) -> None:
        """Only the increment `rows` of `A`, and the states they span, are filled (the others are garbage);
        `plain` is taken over `rows`. `used` (B,): the bodies some joint reads; only theirs are sure to have
        a polar factor, every body has its conditioning ratio (`polar_rotation`). `rotate` False: the polar
        factors wait for `rotate`."""
        n = bodies.q.shape[0]
        filled = tuple(sorted(set(rows)))
        q = (bodies.q_ref, bodies.q_prev, bodies.q)
        dofs = np.empty((3, 12, n), dtype=dtype)  # (q_ref, q_prev, q; DOF; body): one transposed copy per state
        self.dofs = dofs  # (state; DOF; body), the unfilled states garbage
        self.positions = dofs[:, :3]  # (state; xyz; body)
        self.states = dofs[:, 3:]  # (state; A[r, c]; body): A itself in each spanned state
        # (REF..TOTAL_STEP)[A[r, c]; body]: A_ref is the state's own rows (no copy), then the increments.
        self.linear = [dofs[0, 3:], *np.empty((3, 9, n), dtype=dtype)]
        spanned = sorted({0, *(s for row in filled for s in STEPS[row])})
        for s in spanned:
            transpose_into(dofs[s], q[s])
        self._subtract(filled)
        # `_plain_bodies`' squared norms, kept until their rows change: taken here with the rows, while in cache.
        self._norms: dict[tuple[str, int], Array] = {
            **{("state", s): squared_norms(self.states[s]) for s in spanned},
            **{("row", row): squared_norms(self.linear[row]) for row in filled},
        }
        self._plains: dict[frozenset[int], NDArray[np.bool_]] = {}  # `plain_over`'s, until the rows change
        self.dtype = np.dtype(dtype)
        self.plain = self.plain_over(filled)
        # The polar factors in float64 whatever `dtype`: they decide which A_ref is singular.
        self._A_ref = self.linear[REF] if self.dtype == np.float64 else np.ascontiguousarray(bodies.q_ref[:, 3:].T)
        if rotate:
            self.rotate(used)

    def rotate(self, used: NDArray[np.bool_] | None = None) -> None:
        """The polar factors `rotation` (9, B) and conditioning `ratio` (B,) (see `__init__`)."""
        R, self.ratio = polar_rotation(self._A_ref, used)
        self.rotation = R.astype(self.dtype, copy=False)  # (9, B)

    def load(self, state: int, q: Array) -> None:
        """Bodies' DOFs `q` (B, 12) into `state` (the rows of A's increments from or to it keep their old values)."""
        self._plains = {}
        transpose_into(self.dofs[state], q)
        self._norms.pop(("state", state), None)

    def increments(self, rows: Iterable[int]) -> None:
        """The increment `rows` of `A` from the states they span, as loaded."""
        rows = tuple(rows)
        self._plains = {}
        self._subtract(rows)
        for row in rows:
            self._norms.pop(("row", row), None)

    def _subtract(self, rows: tuple[int, ...]) -> None:
        for row in rows:
            a, b = STEPS[row]
            np.subtract(self.dofs[b, 3:], self.dofs[a, 3:], out=self.linear[row])

    def plain_over(self, rows: Iterable[int]) -> NDArray[np.bool_]:
        """`_plain_bodies` over the increment `rows` (the norms of states and rows that did not change since are kept)."""
        rows = frozenset(rows)
        if rows not in self._plains:
            self._plains[rows] = _plain_bodies(self.states, self.linear, rows, self._norms)
        return self._plains[rows]

    def size_bound(self, pairs: NDArray[np.intp], state: int) -> Array:
        """`4 |A_i|_F^2 |A_j|_F^2` (N,) of joints `pairs` (2, N) in `state` (`Constitution.collapsed`), from
        the bodies' squared norms that `plain_over` took (or takes now)."""
        key = ("state", state)
        if key not in self._norms:
            self._norms[key] = squared_norms(self.states[state])
        n2 = self._norms[key].take(pairs, mode=GATHER)
        out = np.multiply(4.0, n2[0])
        out *= n2[1]
        return out

    def positions_of(self, pairs: NDArray[np.intp], state: int) -> Array:
        """`p` (N, 2, 3) of joints `pairs` in `state` (0: q_ref, 1: q_prev, 2: q).

        `pairs` (2, N) contiguous: each joint's bodies i and j (the transpose of `body_ids`).
        """
        return self.positions[state].take(pairs, axis=1, mode=GATHER).transpose(2, 1, 0)

    def plain_joints(self, pairs: NDArray[np.intp], plain: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
        """(N,) True where both bodies of joints `pairs` (2, N) are `plain` (B,) (default `self.plain`, see `_plain_bodies`)."""
        plain = self.plain if plain is None else plain
        if plain.all():  # the common case: no gather
            return np.ones(pairs.shape[1], dtype=bool)
        return plain.take(pairs, mode=GATHER).all(axis=0)

    def linear_at(self, pairs: NDArray[np.intp], state: int) -> Array:
        """`A` (N, 2, 3, 3) of joints `pairs` (2, N) in `state` (0: q_ref, 1: q_prev, 2: q; spanned states only)."""
        return self._matrices(self.states[state], pairs)

    def linear_of(self, pairs: NDArray[np.intp], row: int) -> Array:
        """`A` (N, 2, 3, 3) of joints `pairs` (2, N) at `q_ref` (`REF`) or its increment `row`."""
        return self._matrices(self.linear[row], pairs)

    def rotations(self, pairs: NDArray[np.intp]) -> Array:
        """`R_ref` (N, 2, 3, 3) of joints `pairs` (2, N)."""
        return self._matrices(self.rotation, pairs)

    @staticmethod
    def _matrices(rows: Array, pairs: NDArray[np.intp]) -> Array:
        g = rows.take(pairs, axis=1, mode=GATHER)  # (9, 2, N); the method: no Python wrapper
        return g.reshape(3, 3, *g.shape[1:]).transpose(3, 2, 0, 1)


def squared_norms(a: Array, out: Array | None = None) -> Array:
    """Squared Frobenius norms (B,) of bodies' rows `a` (K, B) (or into `out`): one fused pass."""
    return np.einsum("ij,ij->j", a, a, out=out)


@cache  # per call it was a `finfo` lookup at every use
def plain_range(dtype: type) -> tuple[float, float]:
    """`|A|` (Frobenius) of a body in every state inside this range keeps every product the joint
    coordinates and their collapse test form (up to ~|A|^4, with margin) a normal number:
    `2^+-200` in float64 (`2^+-25` in the float32 bench variant)."""
    e = np.finfo(dtype).maxexp // 5
    return 2.0**-e, 2.0**e


PLAIN_STEP = 2.0
"""A step `dA` up to this times `A` (Frobenius) keeps the common path: any turn of a body of steady
scale (`|R - I| <= sqrt(8) < 2 |R|`), not a body shrunk or grown by orders of magnitude in one step."""


def _plain_bodies(
    states: Array, linear: Sequence[Array], rows: Iterable[int], norms: dict[tuple[str, int], Array] | None = None
) -> NDArray[np.bool_]:
    """(B,) True for a body whose frames the common path forms well: `F_a + dF` at each state.

    That needs each step's increment at most `PLAIN_STEP` times `A` where it ends (Frobenius norms):
    then `F_a + dF` and the increment forms of the coordinates round within a small factor (~16)
    of the direct `F(A_b)`, whatever the turn; and `A` inside `plain_range` in every state.
    Every other body's joints take `careful_frames` (rare: the passes here read B bodies once,
    not N joints). `norms`: squared norms already taken (("state", s) and ("row", row)), and
    where the new ones are kept.
    """
    rows = tuple(rows)
    norms = {} if norms is None else norms
    spanned = sorted({s for row in rows for s in STEPS[row]} | {0})

    def norm(key: tuple[str, int], a: Array) -> Array:
        if key not in norms:
            norms[key] = squared_norms(a)
        return norms[key]

    # Compared squared.
    size = {s: norm(("state", s), states[s]) for s in spanned}
    smallest, largest = size[spanned[0]].copy(), size[spanned[0]].copy()
    for s in spanned[1:]:
        np.minimum(smallest, size[s], out=smallest)
        np.maximum(largest, size[s], out=largest)
    lo, hi = plain_range(states.dtype)
    plain = (smallest >= lo * lo) & (largest <= hi * hi)
    for row in rows:
        plain &= norm(("row", row), linear[row]) <= (PLAIN_STEP * PLAIN_STEP) * size[STEPS[row][1]]
    return plain


@dataclass
class CarefulFrames:
    """Frames of joints `idx` (M,) from `A` scaled by powers of two (exact), for configurations at the
    edge of float64 or with steps larger than the frames (`_plain_bodies` says which).

    A joint coordinate that only depends on the directions of each body's frame vectors (the
    revolute angle) reads them scaled; `unscaled` gives the frames themselves. Frames with
    points (`alpha` nonzero) are not scaled (every exponent 0).
    `exponents[s]` (M, 2): body i's and j's frames in state `s` are scaled by `2^-e` in `states[s]`
    (direct, `F(A_s)`, largest |2^-e A_s| entry in [0.5, 1)). `starts[k]`, `steps[k]`: step `k`'s
    starting frames and increment in one scaling common to its two states.
    """

    idx: NDArray[np.intp]
    exponents: list[NDArray[np.int_]]
    states: list[Array]
    starts: list[Array]
    steps: list[Array]

    def unscaled(self, state: int) -> Array:
        """`F(A_s)` (M, 4, 3) unscaled (exact unless it under- or overflows)."""
        e = self.exponents[state][:, BLOCK_BODY, None]  # (M, 4, 1)
        return np.ldexp(self.states[state], e)


def exponents(A: Array) -> NDArray[np.int_]:
    """(M, 2): `e` with the largest entry of each `2^-e A` (M, 2, 3, 3) in [0.5, 1) (0 for A = 0)."""
    return np.frexp(np.abs(A).max(axis=(-2, -1)))[1]


def scaled_frames(r: Array | None, A: Array, e: NDArray[np.int_], alpha: Array, v: Array) -> Array:
    """`frame_quantities` of bodies `A` (M, 2, 3, 3), body j at `r` (M, 3), each body scaled by `2^-e` (M, 2)."""
    rs = None if r is None else np.ldexp(r, -e[:, 1, None])
    return frame_quantities(rs, np.ldexp(A, -e[:, :, None, None]), alpha, v)


def careful_frames(
    table: BodyTable, pairs: NDArray[np.intp], rows: tuple[int, ...], alpha: Array, v: Array, idx: NDArray[np.intp]
) -> CarefulFrames:
    """`CarefulFrames` of joints `idx` (M,) of `pairs` (2, N) with local vectors `v` (N, 4, 3), over the steps `rows`."""
    sub = np.ascontiguousarray(pairs[:, idx])
    v = v[idx]
    states = sorted({s for row in rows for s in STEPS[row]})
    A = {s: table.linear_at(sub, s) for s in states}
    r = {s: relative_position(table.positions_of(sub, s)) for s in states} if alpha.any() else {}
    # Frames with points (the anchors: r + A c) stay unscaled: a power of two common to r and A
    # could push r to 0 next to a large A, and their coordinate is not scale-invariant anyway.
    e = {s: np.zeros((idx.shape[0], 2), dtype=np.int32) if r else exponents(A[s]) for s in states}
    starts, steps = [], []
    for row in rows:
        a, b = STEPS[row]
        common = np.maximum(e[a], e[b])  # both states' A (and so the step) at most ~1 once scaled
        starts.append(scaled_frames(r.get(a), A[a], common, alpha, v))
        steps.append(scaled_frames(r[b] - r[a] if r else None, table.linear_of(sub, row), common, alpha, v))
    direct = [scaled_frames(r.get(s), A[s], e[s], alpha, v) for s in states]
    return CarefulFrames(idx, [e[s] for s in states], direct, starts, steps)


def state_frames(
    table: BodyTable,
    pairs: NDArray[np.intp],
    rows: tuple[int, ...],
    alpha: Array,
    v: Array,
    F_ref: Array,
    steps: list[Array],
) -> tuple[list[Array], CarefulFrames | None]:
    """Each state's frames (N, 4, 3) (`q_ref`, then the end of each step in `rows`), and the careful frames.

    A state's frames are `F_a + dF` (the previous state's plus the step: no extra gather) where
    that rounds within a small factor of the direct `F(A_s)`, i.e. for joints of `plain` bodies;
    every other joint's are the direct ones, formed from `A_s` scaled by a power of two (a step
    as large as the frame, e.g. `A_ref = 1e300 I` and `q_prev = I`, leaves nothing of `F_a + dF`).
    """
    states = [F_ref]
    with np.errstate(over="ignore", invalid="ignore"):  # only where `careful` replaces them below
        for dF in steps:
            states.append(states[-1] + dF)
    idx = (~table.plain_joints(pairs)).nonzero()[0]
    if idx.shape[0] == 0:
        return states, None
    careful = careful_frames(table, pairs, rows, alpha, v, idx)
    for s, F in enumerate(states):
        F[idx] = careful.unscaled(s)
    return states, careful


def frame_quantities(r: Array | None, A: Array, alpha: Array, v: Array) -> Array:
    """`F` (N, 4, 3), component-major, of joints whose bodies have `A` (N, 2, 3, 3), body j at `r` (N, 3) from body i.

    `alpha` (4,) and `v` (N, 4, 3) as in the module docstring; `r` None: `A v` alone (no positions,
    whatever `alpha`). `F` is linear in `(r, A)`: their increments give the increment of `F`.
    """
    n = A.shape[0]
    F = component_major(n, (4, 3), A.dtype)
    if n <= SMALL:  # a few joints: three passes over all 12 quantities (the same sums, in the same order)
        As = A[:, BLOCK_BODY]  # (N, 4, 3, 3): each quantity's body
        np.multiply(As[..., 0], v[:, :, None, 0], out=F)
        F += As[..., 1] * v[:, :, None, 1]
        F += As[..., 2] * v[:, :, None, 2]
        return F if r is None else add_positions(F, r, alpha)
    tmp = np.empty(n, dtype=A.dtype)
    for k in range(4):
        side = BLOCK_BODY[k]
        for row in range(3):
            out = F[:, k, row]
            np.multiply(A[:, side, row, 0], v[:, k, 0], out=out)
            out += np.multiply(A[:, side, row, 1], v[:, k, 1], out=tmp)
            out += np.multiply(A[:, side, row, 2], v[:, k, 2], out=tmp)
    return F if r is None else add_positions(F, r, alpha)


def add_positions(F: Array, r: Array, alpha: Array) -> Array:
    """`F` (N, 4, 3) plus body j's position `r` (N, 3) from body i in its points (`alpha_k r`), in place."""
    for k in (2, 3):  # body i is the origin: F_0, F_1 see no position
        if alpha[k]:
            F[:, k] += r if alpha[k] == 1.0 else alpha[k] * r  # 1.0 * r is r: no pass for it
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


def to_local(R: Array, w: Array, out: Array | None = None) -> Array:
    """`R^T w` (N, 3), component-major (or into `out`, columns contiguous), for rotations `R` (N, 3, 3)
    and world vectors `w` (N, 3)."""
    out = component_major(w.shape[0], (3,), w.dtype) if out is None else out
    if w.shape[0] <= SMALL:  # a few joints: the three columns at once (the same sums, in the same order)
        np.add(R[:, 0] * w[:, 0, None] + R[:, 1] * w[:, 1, None], R[:, 2] * w[:, 2, None], out=out)
        return out
    for c in range(3):
        np.add(R[:, 0, c] * w[:, 0] + R[:, 1, c] * w[:, 1], R[:, 2, c] * w[:, 2], out=out[:, c])
    return out


def edge_axis(edges: Array) -> Array:
    """Unit joint axis `t` (N, 3), component-major, of edges `p0 -> p1` (N, 2, 3).

    The difference is scaled by a power of two (exact) to a largest component in [0.5, 1)
    before its length is taken: `dot(d, d)` of an edge of 1e-160 would be subnormal (and lose
    digits) and of 1e160 infinite. Every edge with a nonzero, finite `p1 - p0` has an axis
    (`validate.check_joints` refuses the others); for ordinary edges the result is bitwise
    that of `d / |d|`.
    """
    return axis(edge_vector(edges))


def axis(d: Array) -> Array:
    """`d / |d|` (N, 3), component-major, of nonzero, finite vectors `d` (N, 3) (see `edge_axis`)."""
    lo, hi = plain_range(d.dtype)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # the odd rows are redone below
        dd = dot(d, d)
        t = d / np.sqrt(dd)[:, None]
        odd = (~((dd >= lo) & (dd <= hi))).nonzero()[0]  # rare: their dot(d, d) lost digits or overflowed
    if odd.shape[0]:
        _, e = np.frexp(max_abs(d[odd]))
        t[odd] = unit(np.ldexp(d[odd], -e[:, None]))
    return t


def from_local(M: Array, w: Array) -> Array:
    """`M w` (N, 3), component-major, for matrices `M` (N, 3, 3) and vectors `w` (N, 3)."""
    out = component_major(w.shape[0], (3,), w.dtype)
    if w.shape[0] <= SMALL:  # a few joints: the three rows at once (the same sums, in the same order)
        np.add(M[..., 0] * w[:, 0, None] + M[..., 1] * w[:, 1, None], M[..., 2] * w[:, 2, None], out=out)
        return out
    for r in range(3):
        np.add(M[:, r, 0] * w[:, 0] + M[:, r, 1] * w[:, 1], M[:, r, 2] * w[:, 2], out=out[:, r])
    return out


def edge_vector(edges: Array) -> Array:
    """`p1 - p0` (N, 3), component-major, of edges (N, 2, 3).

    One pass per component: a single (N, 3) subtraction into the transposed layout walks the
    C-order edges against their strides (4x slower)."""
    d = component_major(edges.shape[0], (3,), edges.dtype)
    if edges.shape[0] <= SMALL:  # a few joints: one pass
        return np.subtract(edges[:, 1], edges[:, 0], out=d)
    for c in range(3):
        np.subtract(edges[:, 1, c], edges[:, 0, c], out=d[:, c])
    return d


def max_abs(v: Array) -> Array:
    """Largest component magnitude (N,) of each row of `v` (N, 3)."""
    return np.maximum(np.maximum(np.abs(v[:, 0]), np.abs(v[:, 1])), np.abs(v[:, 2]))


def unit(v: Array) -> Array:
    """Each row of `v` (N, 3) over its length, in `v`'s layout (rows of moderate length: see `edge_axis`)."""
    return v / np.sqrt(dot(v, v))[:, None]
