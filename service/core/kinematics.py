"""Affine-body kinematics shared by all constitutions.

A body's 12 DOFs are `q = [p (3), A row 0, A row 1, A row 2]`. Every joint exposes four frame quantities
`F_k` (k = 0, 1 on body i; k = 2, 3 on body j), `F_k = alpha_k (p - o) + A v_k`, with `v_k` body-local
(fixed at `q_ref`), `alpha_k` 1 for a point and 0 for a direction, and `o` body i's position in the same
state: subtracting it first keeps a scene far from the origin from losing digits to its translation.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from jointlimits.service.core.polar import cofactors, polar_rotation
from jointlimits.service.core.scene import Bodies

Array = NDArray[np.float64]

BLOCK_BODY = np.array([0, 0, 1, 1])  # the body of each frame quantity (0: i, 1: j)
SMALL = 256
"""Joints up to which a kernel takes whole (N, 4, 3) blocks per pass (its call overhead is the cost there); above,
a pass per contiguous (N,) column, which streams through memory (2-4x faster at 1e5 joints)."""
REF, PREV_STEP, STEP, TOTAL_STEP = range(4)
"""Rows of `A` in the body table: at `q_ref`, then `q_prev - q_ref`, `q - q_prev`, `q - q_ref` (a coordinate is an
increment of a bilinear form in F's increments: no cancellation of two large values of two states)."""
STEPS = {PREV_STEP: (0, 1), STEP: (1, 2), TOTAL_STEP: (0, 2)}
"""Each increment row of `A` as (from, to) states: 0 q_ref, 1 q_prev, 2 q."""
_SPANNING = [{row for row, spans in STEPS.items() if s in spans} for s in range(3)]  # the rows each state ends or starts


def solve3(A: Array, b: Array) -> Array:
    """`A^-1 b` (..., 3), component-major, for `A` (..., 3, 3), `b` (..., 3), by cofactors (`polar.cofactors`:
    a LAPACK call per system costs more). Where `det` or a product leaves float64's comfortable range
    (|A| beyond ~1e+-100), those systems are solved again with `A` scaled by a power of two (exact)."""
    lead = b.shape[:-1]
    a = A.transpose(A.ndim - 2, A.ndim - 1, *range(A.ndim - 3, -1, -1)).reshape(9, -1)  # (9, M): the table's A, a view
    y = b.transpose(b.ndim - 1, *range(b.ndim - 2, -1, -1)).reshape(3, -1)
    # Overflow is expected on the first pass (redone below) and legitimate on the second (an
    # anchor beyond float64: the coordinate overflows and `validate` names the joint).
    x, det = _solve3(a, y)
    size = np.abs(det)  # the common case: every det inside, every x finite, in three flat reductions
    if size.min(initial=1.0) >= 2.0**-900 and size.max(initial=1.0) <= 2.0**900 and math.isfinite(np.add.reduce(x, None)):
        return x.reshape(3, *lead[::-1]).T
    bad = (~((size >= 2.0**-900) & (size <= 2.0**900) & np.isfinite(x[0] + x[1] + x[2]))).nonzero()[0]
    if bad.shape[0]:  # det ~|A|^3 inside 2^+-900 keeps the cofactors (~det^(2/3)) normal numbers
        e = np.frexp(np.abs(a[:, bad]).max(axis=0))[1]
        x[:, bad] = np.ldexp(_solve3(np.ldexp(a[:, bad], -e), y[:, bad])[0], -e)
    return x.reshape(3, *lead[::-1]).T


def _solve3(a: Array, y: Array) -> tuple[Array, Array]:
    C, det = cofactors(a)
    return (C[0:3] * y[0] + C[3:6] * y[1] + C[6:9] * y[2]) / det, det


def component_major(n: int, shape: tuple[int, ...], dtype: type = np.float64) -> Array:
    """An empty (N, *shape) array in which every `a[:, i, ..]` is a contiguous (N,) row: the kernels run along
    the joints (broadcasting over trailing 3-vectors is 5x slower). Elementwise ufuncs keep it (order K)."""
    return np.empty(shape + (n,), dtype=dtype).transpose(_LAST_FIRST[len(shape)])  # moveaxis, less its checks (~3 us)


_LAST_FIRST = [(k, *range(k)) for k in range(6)]


GATHER = "wrap"
"""`np.take`'s mode for indices known in range (`validate.check_joints` refuses the others, `nonzero` makes the
rest): the very same elements, without the default mode's bounds check (twice as slow, NumPy 2.x)."""


def take_joints(a: NDArray, sel: NDArray[np.intp]) -> NDArray:
    """Rows `sel` (M,) of `a` (N, ...) in `a`'s layout (fancy indexing would give C order): a view where contiguous."""
    if sel.shape[0] and sel[-1] - sel[0] + 1 == sel.shape[0]:
        return a[sel[0] : sel[-1] + 1]
    return np.moveaxis(np.take(np.moveaxis(a, 0, -1), sel, axis=-1, mode=GATHER), -1, 0)


def transpose_into(out: Array, a: Array) -> None:
    """`out[...] = a.T` for `a` (B, K), 1024 bodies at a time (in cache: a fifth faster at 5e4 x 12)."""
    for s in range(0, a.shape[0], 1024):
        out[:, s : s + 1024] = a[s : s + 1024].T


class BodyTable:
    """Every body's positions, `A` at `q_ref` and its increments, and its reference rotation, component-major.

    Built once per evaluation; each batch gathers its joints' two bodies with one `take` per row. Positions stay
    absolute: a joint differences its two bodies' positions within one state first, then across states.
    """

    def __init__(self, bodies: Bodies, dtype: type = np.float64, rows: Iterable[int] = STEPS,
                 used: NDArray[np.bool_] | None = None, plain: Iterable[int] | None = None) -> None:
        """Only the increment `rows` of `A`, and the states they span, are filled (the others are garbage);
        `plain` is taken over the rows `plain` (default `rows`). The polar factors `rotation` (9, B) and the
        conditioning `ratio` (B,) of each `A_ref`; `used` (B,): the bodies sure to get one (`polar_rotation`)."""
        n = bodies.q.shape[0]
        filled = tuple(sorted(set(rows)))
        q = (bodies.q_ref, bodies.q_prev, bodies.q)
        self.dofs = dofs = np.empty((3, 12, n), dtype=dtype)  # (state; DOF; body)
        self.positions = dofs[:, :3]  # (state; xyz; body)
        self.states = dofs[:, 3:]  # (state; A[r, c]; body)
        self.linear = [dofs[0, 3:], *np.empty((3, 9, n), dtype=dtype)]  # (REF..TOTAL_STEP)[A[r, c]; body]
        spanned = sorted({0, *(s for row in filled for s in STEPS[row])})
        for s in spanned:
            transpose_into(dofs[s], q[s])
        self._subtract(filled)
        self._current = set(filled)  # the increment rows that are those of the states as loaded (`increments`)
        self._fresh = bodies.q if 2 in spanned else None  # `load` of this `q` once: already there (the stateless call)
        # Squared norms (`_plain_bodies`), kept until their rows change: taken now, while in cache.
        self._norms = {("state", s): squared_norms(self.states[s]) for s in spanned}
        self._norms |= {("row", row): squared_norms(self.linear[row]) for row in filled}
        self._plains: dict[frozenset[int], NDArray[np.bool_]] = {}  # `plain_over`'s, until the rows change
        self.dtype = np.dtype(dtype)
        self.plain = self.plain_over(filled)  # first over every row: over fewer it may be that one (`plain_over`)
        if plain is not None:
            self.plain = self.plain_over(plain)
        # The polar factors in float64 whatever `dtype`: they decide which A_ref is singular.
        A_ref = self.linear[REF] if self.dtype == np.float64 else np.ascontiguousarray(bodies.q_ref[:, 3:].T)
        R, self.ratio = polar_rotation(A_ref, used)
        self.rotation = R.astype(self.dtype, copy=False)

    def load(self, state: int, q: Array) -> None:
        """Bodies' DOFs `q` (B, 12) into `state` (the increment rows keep their old values)."""
        fresh, self._fresh = self._fresh, None
        if state == 2 and q is fresh:  # the q this table was built with, not loaded since: there already
            return
        self._plains = {}
        transpose_into(self.dofs[state], q)
        self._norms.pop(("state", state), None)
        self._current -= _SPANNING[state]

    def increments(self, rows: Iterable[int]) -> None:
        """The increment `rows` of `A` from the states they span, as loaded (the rows already so: as they are)."""
        rows = tuple(row for row in rows if row not in self._current)
        if not rows:
            return
        self._plains = {}
        self._subtract(rows)
        self._current.update(rows)
        for row in rows:
            self._norms.pop(("row", row), None)

    def _subtract(self, rows: tuple[int, ...]) -> None:
        for row in rows:
            a, b = STEPS[row]
            np.subtract(self.dofs[b, 3:], self.dofs[a, 3:], out=self.linear[row])

    def plain_over(self, rows: Iterable[int]) -> NDArray[np.bool_]:
        """`_plain_bodies` over the increment `rows` (with the kept norms)."""
        rows = frozenset(rows)
        if rows not in self._plains:
            # Over more rows a body meets more conditions: where every body is plain over more, so over these.
            every = next((p for wider, p in self._plains.items() if wider > rows and p.all()), None)
            self._plains[rows] = _plain_bodies(self.states, self.linear, rows, self._norms) if every is None else every
        return self._plains[rows]

    def size_bound(self, pairs: NDArray[np.intp], state: int) -> Array:
        """`4 |A_i|_F^2 |A_j|_F^2` (N,) of joints `pairs` (2, N) in `state` (`Constitution.collapsed`)."""
        n2 = _norm(self._norms, ("state", state), self.states[state]).take(pairs, mode=GATHER)
        out = np.multiply(4.0, n2[0])
        out *= n2[1]
        return out

    def positions_of(self, pairs: NDArray[np.intp], state: int) -> Array:
        """`p` (N, 2, 3) of joints `pairs` (2, N), each joint's bodies i and j, in `state` (0 q_ref, 1 q_prev, 2 q)."""
        return self.positions[state].take(pairs, axis=1, mode=GATHER).transpose(2, 1, 0)

    def plain_joints(self, pairs: NDArray[np.intp], plain: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
        """(N,) True where both bodies of joints `pairs` (2, N) are `plain` (B,) (default `self.plain`)."""
        plain = self.plain if plain is None else plain
        if plain.all():  # the common case: no gather
            return np.ones(pairs.shape[1], dtype=bool)
        return plain.take(pairs, mode=GATHER).all(axis=0)

    def linear_at(self, pairs: NDArray[np.intp], state: int) -> Array:
        """`A` (N, 2, 3, 3) of joints `pairs` (2, N) in `state` (a spanned one)."""
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


def squared_norms(a: Array) -> Array:
    """Squared Frobenius norms (B,) of bodies' rows `a` (K, B): one fused pass. (einsum sums a column in another
    order when B == 1, one contiguous dot; a table with joints has two bodies at least. `polar.squared_norms`
    fixes the order for arrays of joints, which may be one: 2-3% of a 10-joint call here.)"""
    return np.einsum("ij,ij->j", a, a)


def _norm(norms: dict[tuple[str, int], Array], key: tuple[str, int], a: Array) -> Array:
    """`squared_norms(a)`, kept in `norms` as `key`."""
    if key not in norms:
        norms[key] = squared_norms(a)
    return norms[key]


finfo = cache(np.finfo)  # `np.finfo` itself costs microseconds per call, a few times per evaluation


@cache  # per call it was a `finfo` lookup at every use
def plain_range(dtype: type) -> tuple[float, float]:
    """`|A|` (Frobenius) in every state inside this range keeps every product the coordinates and their collapse
    test form (up to ~|A|^4, with margin) a normal number: `2^+-200` in float64 (`2^+-25` in float32)."""
    e = np.finfo(dtype).maxexp // 5
    return 2.0**-e, 2.0**e


PLAIN_STEP = 2.0
"""A step `dA` up to this times `A` (Frobenius) keeps the common path: any turn of a body of steady
scale (`|R - I| <= sqrt(8) < 2 |R|`), not a body shrunk or grown by orders of magnitude in one step."""


def _plain_bodies(states: Array, linear: Sequence[Array], rows: Iterable[int],
                  norms: dict[tuple[str, int], Array] | None = None) -> NDArray[np.bool_]:
    """(B,) True for a body whose frames the common path (`F_a + dF` at each state) forms well: each step's
    increment at most `PLAIN_STEP` times `A` where it ends, and `A` inside `plain_range` in every state. Then
    `F_a + dF` and the increment forms round within a small factor (~16) of the direct `F(A_b)`; every other
    body's joints take `careful_frames`. `norms`: the squared norms already taken, and where new ones are kept.
    """
    rows = tuple(rows)
    norms = {} if norms is None else norms
    spanned = sorted({s for row in rows for s in STEPS[row]} | {0})
    size = {s: _norm(norms, ("state", s), states[s]) for s in spanned}  # compared squared
    smallest, largest = size[spanned[0]].copy(), size[spanned[0]].copy()
    for s in spanned[1:]:
        np.minimum(smallest, size[s], out=smallest)
        np.maximum(largest, size[s], out=largest)
    lo, hi = plain_range(states.dtype)
    plain = (smallest >= lo * lo) & (largest <= hi * hi)
    for row in rows:
        plain &= _norm(norms, ("row", row), linear[row]) <= (PLAIN_STEP * PLAIN_STEP) * size[STEPS[row][1]]
    return plain


@dataclass
class CarefulFrames:
    """Frames of joints `idx` (M,) from `A` scaled by powers of two (exact), for configurations at the edge of
    float64 or with steps as large as the frames (`_plain_bodies` says which).

    `states[s]` (M, 4, 3): the frames in state `s`, body i's and j's scaled by `2^-exponents[s]` (M, 2) (largest
    |2^-e A_s| entry in [0.5, 1); with points, unscaled). `starts[k]`, `steps[k]`: step `k`'s starting frames
    and increment, in one scaling common to its two states."""

    idx: NDArray[np.intp]
    exponents: list[NDArray[np.int_]]
    states: list[Array]
    starts: list[Array]
    steps: list[Array]

    def unscaled(self, state: int) -> Array:
        """`F(A_s)` (M, 4, 3) unscaled (exact unless it under- or overflows)."""
        return np.ldexp(self.states[state], self.exponents[state][:, BLOCK_BODY, None])


def exponents(A: Array) -> NDArray[np.int_]:
    """(M, 2): `e` with the largest entry of each `2^-e A` (M, 2, 3, 3) in [0.5, 1) (0 for A = 0)."""
    return np.frexp(np.abs(A).max(axis=(-2, -1)))[1]


def scaled_frames(r: Array | None, A: Array, e: NDArray[np.int_], alpha: Array, v: Array) -> Array:
    """`frame_quantities` of bodies `A` (M, 2, 3, 3), body j at `r` (M, 3), each body scaled by `2^-e` (M, 2)."""
    rs = None if r is None else np.ldexp(r, -e[:, 1, None])
    return frame_quantities(rs, np.ldexp(A, -e[:, :, None, None]), alpha, v)


def careful_frames(table: BodyTable, pairs: NDArray[np.intp], rows: tuple[int, ...], alpha: Array, v: Array,
                   idx: NDArray[np.intp]) -> CarefulFrames:
    """`CarefulFrames` of joints `idx` (M,) of `pairs` (2, N), local vectors `v` (N, 4, 3), over the steps `rows`."""
    sub = np.ascontiguousarray(pairs[:, idx])
    v = v[idx]
    states = sorted({s for row in rows for s in STEPS[row]})
    A = {s: table.linear_at(sub, s) for s in states}
    r = {s: relative_position(table.positions_of(sub, s)) for s in states} if alpha.any() else {}
    # Frames with points (r + A c) stay unscaled: a power of two common to r and A could push r to 0 next to
    # a large A, and their coordinate is not scale-invariant anyway.
    e = {s: np.zeros((idx.shape[0], 2), dtype=np.int32) if r else exponents(A[s]) for s in states}
    starts, steps = [], []
    for row in rows:
        a, b = STEPS[row]
        common = np.maximum(e[a], e[b])  # both states' A (and so the step) at most ~1 once scaled
        starts.append(scaled_frames(r.get(a), A[a], common, alpha, v))
        steps.append(scaled_frames(r[b] - r[a] if r else None, table.linear_of(sub, row), common, alpha, v))
    direct = [scaled_frames(r.get(s), A[s], e[s], alpha, v) for s in states]
    return CarefulFrames(idx, [e[s] for s in states], direct, starts, steps)


def state_frames(table: BodyTable, pairs: NDArray[np.intp], rows: tuple[int, ...], alpha: Array, v: Array,
                 F_ref: Array, steps: list[Array]) -> tuple[list[Array], CarefulFrames | None]:
    """Each state's frames (N, 4, 3) (`q_ref`, then the end of each step in `rows`), and the careful frames: the
    previous state's plus the step, except for joints of bodies not `plain`, whose are the direct ones from `A_s`
    scaled (a step as large as the frame, `A_ref = 1e300 I` to `q_prev = I`, leaves nothing of `F_a + dF`)."""
    states = [F_ref]
    # (overflows only where `careful` replaces them below)
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
    """`F` (N, 4, 3), component-major, of joints whose bodies have `A` (N, 2, 3, 3), body j at `r` (N, 3) from
    body i (None: `A v` alone, whatever `alpha`); `alpha` (4,), `v` (N, 4, 3). `F` is linear in `(r, A)`."""
    n = A.shape[0]
    if n <= SMALL:  # a few joints: every product in one pass over (rows, N) views, then the sums over c in order
        p = A.transpose(2, 3, 1, 0).reshape(18, n).take(_FQ_A, axis=0, mode=GATHER)
        p *= v.transpose(1, 2, 0).reshape(12, n).take(_FQ_V, axis=0, mode=GATHER)
        F = (p[:12] + p[12:24] + p[24:]).reshape(4, 3, n).transpose(2, 0, 1)
        return F if r is None else add_positions(F, r, alpha)
    F = component_major(n, (4, 3), A.dtype)
    tmp = np.empty(n, dtype=A.dtype)
    for k in range(4):
        for row in range(3):
            out, a = F[:, k, row], A[:, BLOCK_BODY[k], row]
            np.multiply(a[:, 0], v[:, k, 0], out=out)
            out += np.multiply(a[:, 1], v[:, k, 1], out=tmp)
            out += np.multiply(a[:, 2], v[:, k, 2], out=tmp)
    return F if r is None else add_positions(F, r, alpha)


_FQ_A = np.array([(3 * r + c) * 2 + b for c in range(3) for b in BLOCK_BODY for r in range(3)])  # A[b, r, c] of F_k[r]
_FQ_V = np.array([3 * k + c for c in range(3) for k in range(4) for _ in range(3)])  # v_k[c]


def add_positions(F: Array, r: Array, alpha: Array) -> Array:
    """`F` (N, 4, 3) plus body j's position `r` (N, 3) from body i in its points (`alpha_k r`), in place."""
    for k in (2, 3):  # body i is the origin: F_0, F_1 see no position
        if alpha[k]:
            F[:, k] += r if alpha[k] == 1.0 else alpha[k] * r  # 1.0 * r is r: no pass for it
    return F


def relative_position(p: Array) -> Array:
    """Body j's position from body i's, `r` (N, 3), of positions `p` (N, 2, 3) in one state: nearby positions are
    differenced before anything large is added (a scene far from the origin loses no digits)."""
    r = component_major(p.shape[0], (3,), p.dtype)
    np.subtract(p[:, 1], p[:, 0], out=r)
    return r


def dot(a: Array, b: Array) -> Array:
    """Row-wise dot (N,) of (N, 3) arrays: the products in one pass, summed column by column."""
    p = a * b
    return p[:, 0] + p[:, 1] + p[:, 2]


def cross(a: Array, b: Array) -> Array:
    """Row-wise cross product of (N, 3) arrays, component-major."""
    out = component_major(a.shape[0], (3,), a.dtype)
    for r in range(3):
        i, j = (r + 1) % 3, (r + 2) % 3
        np.subtract(a[:, i] * b[:, j], a[:, j] * b[:, i], out=out[:, r])
    return out


def from_local(M: Array, w: Array) -> Array:
    """`M w` (N, 3), component-major, for matrices `M` (N, 3, 3) and vectors `w` (N, 3)."""
    out = component_major(w.shape[0], (3,), w.dtype)
    if w.shape[0] <= SMALL:  # a few joints: the three rows at once (the same sums, in the same order)
        return np.add(M[..., 0] * w[:, 0, None] + M[..., 1] * w[:, 1, None], M[..., 2] * w[:, 2, None], out=out)
    for r in range(3):
        np.add(M[:, r, 0] * w[:, 0] + M[:, r, 1] * w[:, 1], M[:, r, 2] * w[:, 2], out=out[:, r])
    return out


def axis(d: Array) -> Array:
    """`d / |d|` (N, 3), component-major, of nonzero, finite vectors `d` (N, 3) (`validate.check_joints` refuses
    the others). Where `dot(d, d)` leaves float64's comfortable range (an edge of 1e-160 or 1e160), `d` is scaled
    by a power of two first (exact); elsewhere the result is bitwise `d / |d|`."""
    lo, hi = plain_range(d.dtype)
    # (overflows only in the odd rows, redone below)
    dd = dot(d, d)
    t = d / np.sqrt(dd)[:, None]
    if dd.min(initial=lo) >= lo and dd.max(initial=hi) <= hi:  # the common case (NaN: below)
        return t
    odd = (~((dd >= lo) & (dd <= hi))).nonzero()[0]
    if odd.shape[0]:
        _, e = np.frexp(max_abs(d[odd]))
        t[odd] = unit(np.ldexp(d[odd], -e[:, None]))
    return t


def edge_vector(edges: Array) -> Array:
    """`p1 - p0` (N, 3), component-major, of edges (N, 2, 3): above `SMALL`, a pass per component (one (N, 3)
    subtraction into this layout walks the C-order edges against their strides, 4x slower)."""
    d = component_major(edges.shape[0], (3,), edges.dtype)
    if edges.shape[0] <= SMALL:
        return np.subtract(edges[:, 1], edges[:, 0], out=d)
    for c in range(3):
        np.subtract(edges[:, 1, c], edges[:, 0, c], out=d[:, c])
    return d


def max_abs(v: Array) -> Array:
    """Largest component magnitude (N,) of each row of `v` (N, 3)."""
    return np.maximum(np.maximum(np.abs(v[:, 0]), np.abs(v[:, 1])), np.abs(v[:, 2]))


def unit(v: Array) -> Array:
    """Each row of `v` (N, 3) over its length, in `v`'s layout (rows of moderate length: see `axis`)."""
    return v / np.sqrt(dot(v, v))[:, None]
