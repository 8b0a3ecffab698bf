"""Answers assembled per body (`layout="bodies"`): the per-joint answer scattered and summed.

A solver wants the scene's gradient (B, 12) and its Hessian as a sparse matrix over bodies,
not one (24, 24) block per joint. The Hessian is kept as symmetric block-sparse: for each
pair of bodies `rows[k] <= cols[k]` touched by a joint outside its range, `blocks[k]`
(12, 12) = d2E / dq_rows dq_cols summed over those joints; the full matrix is the blocks plus
the transposes of the off-diagonal ones. Pairs are sorted (row, then column) and summed in
joint order (a stable sort, then `np.add.reduceat`), so the answer is reproducible and each
diagonal block is bitwise symmetric like the per-joint blocks it sums.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.core import penalty
from service.core.errors import Fault, InputError
from service.core.scene import Array, BatchResult, Evaluation, Joints

LAYOUTS = ("joints", "bodies")


@dataclass
class Assembled:
    """Per-body gradient `gradient` (B, 12) and block-sparse Hessian `rows`, `cols` (K,), `blocks` (K, 12, 12).

    Each part is None when its output was not asked for.
    """

    n_bodies: int
    gradient: Array | None = None
    rows: NDArray[np.int64] | None = None
    cols: NDArray[np.int64] | None = None
    blocks: Array | None = None

    def matrix(self) -> Any:
        """The Hessian as a `scipy.sparse` CSR matrix (12B, 12B), symmetric (needs scipy)."""
        try:
            from scipy import sparse
        except ImportError:
            raise ImportError(
                "Assembled.matrix() needs scipy: pip install 'jointlimits[sparse]' (or pip install scipy)"
            ) from None
        if self.blocks is None:
            raise ValueError("no Hessian: ask for the 'hessian' output")
        off = self.rows != self.cols
        r = np.concatenate([self.rows, self.cols[off]])
        c = np.concatenate([self.cols, self.rows[off]])
        data = np.concatenate([self.blocks, self.blocks[off].transpose(0, 2, 1)])
        a = np.arange(12)
        ii = (12 * r[:, None, None] + a[None, :, None]).repeat(12, axis=2)
        jj = (12 * c[:, None, None] + a[None, None, :]).repeat(12, axis=1)
        n = 12 * self.n_bodies
        return sparse.coo_matrix((data.ravel(), (ii.ravel(), jj.ravel())), shape=(n, n)).tocsr()


def active_rows(joints: Joints, result: BatchResult, active_only: bool) -> NDArray[np.intp]:
    """Positions in `result`'s rows of joints outside their range (the only rows with derivatives)."""
    if active_only:
        return np.arange(result.index.shape[0])
    i = result.index
    g, _ = penalty.gap(result.x, joints.lower[i], joints.upper[i])
    return np.flatnonzero((g > 0) & (joints.strength[i] > 0))


def assemble(n_bodies: int, batches: Sequence[Joints], ev: Evaluation, active_only: bool) -> Assembled:
    """The scatter-add of `ev`'s per-joint gradient and Hessian rows over the bodies of `batches`."""
    ids, grads, hesses = [], [], []
    for joints, r in zip(batches, ev.batches):
        rows = active_rows(joints, r, active_only)
        ids.append(np.asarray(joints.body_ids, dtype=np.int64)[r.index[rows]])
        grads.append(None if r.gradient is None else r.gradient[rows])
        hesses.append(None if r.hessian is None else r.hessian[rows])
    body_ids = np.concatenate(ids) if ids else np.zeros((0, 2), np.int64)
    out = Assembled(n_bodies)
    if ev.batches and grads[0] is not None:
        out.gradient = _gradient(n_bodies, body_ids, np.concatenate(grads))
    if ev.batches and hesses[0] is not None:
        out.rows, out.cols, out.blocks = _hessian(body_ids, np.concatenate(hesses))
    return out


def _gradient(n_bodies: int, body_ids: NDArray[np.int64], g: Array) -> Array:
    """(B, 12): each joint's `[g_i, g_j]` (M, 24) added to its bodies `body_ids` (M, 2), in joint order."""
    out = np.zeros((n_bodies, 12), dtype=np.float64)
    np.add.at(out, body_ids.reshape(-1), g.reshape(-1, 12))
    return out


def _hessian(body_ids: NDArray[np.int64], H: Array) -> tuple[NDArray[np.int64], NDArray[np.int64], Array]:
    """Block-sparse upper triangle of the sum of each joint's (24, 24) `H` (M, 24, 24) over its bodies."""
    m = H.shape[0]
    i, j = body_ids[:, 0], body_ids[:, 1]
    B = H.reshape(m, 2, 12, 2, 12)
    # Three blocks per joint: (i, i), (j, j) and the off-diagonal one oriented so that row <= col.
    swap = i > j
    off = np.where(swap[:, None, None], B[:, 1, :, 0, :], B[:, 0, :, 1, :])
    r = np.concatenate([i, j, np.minimum(i, j)])
    c = np.concatenate([i, j, np.maximum(i, j)])
    blocks = np.concatenate([B[:, 0, :, 0, :], B[:, 1, :, 1, :], off])  # i != j: validation rejects a joint on one body
    return reduce_pairs(r, c, blocks)


def reduce_pairs(
    r: NDArray[np.int64], c: NDArray[np.int64], blocks: Array
) -> tuple[NDArray[np.int64], NDArray[np.int64], Array]:
    """Blocks (L, 12, 12) at pairs (r, c) summed per pair: sorted unique pairs and their sums."""
    if r.shape[0] == 0:
        return r.astype(np.int64), c.astype(np.int64), np.zeros((0, 12, 12))
    order = np.lexsort((c, r))  # stable: equal pairs keep their order, so the sums are reproducible
    r, c = r[order], c[order]
    start = np.flatnonzero(np.concatenate([[True], (r[1:] != r[:-1]) | (c[1:] != c[:-1])]))
    return r[start].astype(np.int64), c[start].astype(np.int64), np.add.reduceat(blocks[order], start, axis=0)


def check_layout(layout: str) -> list[Fault]:
    return [] if layout in LAYOUTS else [Fault(("layout",), f"unknown layout {layout!r}; expected 'joints' or 'bodies'", "literal_error")]


def apply(ev: Evaluation, n_bodies: int, batches: Sequence[Joints], layout: str, active_only: bool) -> Evaluation:
    """`ev` in `layout`: unchanged for "joints"; for "bodies" the assembled answer, batches without derivatives."""
    if check_layout(layout):
        raise InputError(check_layout(layout))
    if layout == "joints":
        return ev
    assembled = assemble(n_bodies, batches, ev, active_only)
    out = replace(ev, batches=[replace(r, gradient=None, hessian=None) for r in ev.batches])
    out.assembled = assembled
    return out
