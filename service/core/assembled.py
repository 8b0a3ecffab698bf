"""Answers per body (`layout="bodies"`): every active joint's gradient and Hessian summed into its bodies' DOFs.

A joint on bodies `(i, j)` has a gradient `[g_i, g_j]` (24) and a Hessian of 12 x 12 blocks `H_ii, H_ij, H_ji, H_jj`.
Over B bodies: `gradient` (B, 12), row `k` the sum of every active joint's `g_k`; the Hessian (12B x 12B, symmetric)
as its upper block triangle, `rows <= cols` (K,) sorted (row, then column), one per body pair a joint outside its
range touches, and `blocks` (K, 12, 12) summed over those joints (the full matrix adds the off-diagonal transposes).

A scatter-add is one stable sort of integer keys and vectorised passes over the sorted terms (no loop over joints),
adding each key's terms one after the other in request order (batch, joint, then `(i, i)`, `(j, j)`, `(i, j)`): a
plain loop in that order gives the same bits (tests/core/test_assembled.py); diagonal blocks stay bitwise symmetric.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from jointlimits.service.core.errors import MAX_FAULTS, Fault, InputError
from jointlimits.service.core.scene import Array
from jointlimits.service.core.validate import literal_msg, nonfinite_rows

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
        """The Hessian as a `scipy.sparse.csr_array` (12B, 12B), symmetric (needs scipy)."""
        try:
            from scipy import sparse
        except ImportError:
            msg = "Assembled.matrix() needs scipy: pip install scipy (the sparse extra)"
            raise ImportError(msg) from None
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
        return sparse.coo_array((data.ravel(), (ii.ravel(), jj.ravel())), shape=(n, n)).tocsr()


def assemble_active(
    n_bodies: int, batches: Sequence[tuple[NDArray[np.int64], Array | None, Array | None]], want_g: bool, want_h: bool
) -> Assembled:
    """The request's gradient (B, 12) and block-sparse Hessian from each batch's active joints: their body
    ids (M, 2), gradient (M, 24) and Hessian (M, 24, 24) (None when not asked for), in request order.

    Raises `InputError` at ("layout",) when a sum overflows float64 (each term is finite; their sum need not be).
    """
    pairs = np.concatenate([ids.reshape(-1, 2) for ids, _, _ in batches] or [np.zeros((0, 2), np.int64)])
    out = Assembled(n_bodies)
    if want_g:
        # (M, 24) -> (2M, 12): row 2m is joint m's g_i, row 2m + 1 its g_j, i.e. body pairs.reshape(-1).
        g = np.concatenate([b[1].reshape(-1, 12) for b in batches] or [np.zeros((0, 12))])
        keys, sums = _sum_by_key(pairs.reshape(-1), g.__getitem__, (12,))
        out.gradient = np.zeros((n_bodies, 12))
        out.gradient[keys] = sums
    if want_h:
        keys, take = _hessian_terms(n_bodies, pairs, [b[2] for b in batches])
        keys, sums = _sum_by_key(keys, take, (12, 12))
        out.rows, out.cols, out.blocks = keys // max(n_bodies, 1), keys % max(n_bodies, 1), sums
    raise_overflow(out)
    return out


Take = Callable[[NDArray[np.int64]], Array]
"""The terms (n, ...) at the given term indices (n,): gathered when needed, never all at once."""


def _hessian_terms(n_bodies: int, pairs: NDArray[np.int64], hessians: list[Array]) -> tuple[NDArray[np.int64], Take]:
    """Each active joint's three upper-triangle blocks, `(i, i)`, `(j, j)`, `(min, max)`, in that order
    per joint: their keys `row * B + col` (3M,) and a gather of the blocks (n, 12, 12) by term index.

    When `i > j` the upper block `(j, i)` is d2E/dq_j dq_i, the Hessian's lower-left block
    `H[12:, :12]` (per-joint Hessians are bitwise symmetric, so that is `H_ij^T` exactly).
    """
    i, j = pairs[:, 0], pairs[:, 1]
    # B <= 2**31 bodies (far beyond any request's bytes), so row * B + col fits int64.
    keys = np.stack([i * n_bodies + i, j * n_bodies + j, np.minimum(i, j) * n_bodies + np.maximum(i, j)], axis=1)
    swap = (i > j).astype(np.int64)
    h5 = [h.reshape(-1, 2, 12, 2, 12) for h in hessians]
    bounds = np.cumsum([0] + [h.shape[0] for h in hessians])
    dtype = np.result_type(*hessians) if hessians else np.float64

    def take(terms: NDArray[np.int64]) -> Array:
        # Term 3m + t of active joint m: block (a, b) = H5[m, a, :, b, :], a = b = t for t = 0, 1;
        # (0, 1) for t = 2, or (1, 0) when the joint's bodies come in descending order.
        m, t = np.divmod(terms, 3)
        a = np.where(t == 2, swap[m], t)
        b = np.where(t == 2, 1 - swap[m], t)
        if len(h5) == 1:
            return h5[0][m, a, :, b, :]
        out = np.empty((terms.shape[0], 12, 12), dtype)
        batch = np.searchsorted(bounds, m, side="right") - 1
        for k, h in enumerate(h5):  # one gather per batch, not per joint
            sel = np.flatnonzero(batch == k)
            out[sel] = h[m[sel] - bounds[k], a[sel], :, b[sel], :]
        return out

    return keys.reshape(-1), take


def _sum_by_key(keys: NDArray[np.int64], take: Take, shape: tuple[int, ...]) -> tuple[NDArray[np.int64], Array]:
    """The distinct `keys` (K,) ascending and the sum per key (K, *shape) of the terms `take` gathers.

    Each key's terms are added one after the other in their order in `keys` (a stable sort groups
    them), as a plain loop would: one vectorised pass per rank within the groups (`np.add.reduceat`
    does not add in that order, and is slower on short groups), and a contiguous `sum(axis=0)`
    (sequential along the outer axis) for the few groups still longer than that.
    """
    if keys.shape[0] == 0:
        return keys.astype(np.int64), np.zeros((0, *shape))
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.concatenate([[True], sorted_keys[1:] != sorted_keys[:-1]]))
    lengths = np.diff(starts, append=keys.shape[0])
    sums = take(order[starts])
    longer = np.flatnonzero(lengths > 1)
    rank = 1
    while longer.shape[0] > _FEW:
        sums[longer] += take(order[starts[longer] + rank])
        rank += 1
        longer = longer[lengths[longer] > rank]
    for k in longer:  # at most _FEW groups (a hub body's many joints): each summed afresh, in order
        sums[k] = take(order[starts[k] : starts[k] + lengths[k]]).sum(axis=0)
    return sorted_keys[starts].astype(np.int64), sums


_FEW = 16
"""Groups left when the rank passes stop; each pass costs ~10 us of overhead whatever its size."""


def reduce_pairs(
    r: NDArray[np.int64], c: NDArray[np.int64], blocks: Array
) -> tuple[NDArray[np.int64], NDArray[np.int64], Array]:
    """Blocks (L, 12, 12) at pairs (r, c) summed per pair, in their order: sorted unique pairs and their sums."""
    n = int(max(r.max(initial=-1), c.max(initial=-1))) + 1
    keys, sums = _sum_by_key(np.asarray(r, np.int64) * n + c, blocks.__getitem__, (12, 12))
    return keys // max(n, 1), keys % max(n, 1), sums


def raise_overflow(out: Assembled) -> None:
    """`InputError` naming each body (gradient) and pair (Hessian block) whose sum is not finite."""
    faults = []
    if out.gradient is not None:
        faults += [
            Fault(("layout",), f"the assembled gradient of body {k} overflows float64 (its joints' sum)")
            for k in nonfinite_rows(out.gradient)
        ]
    if out.blocks is not None:
        faults += [
            Fault(("layout",), f"the assembled Hessian block ({int(out.rows[k])}, {int(out.cols[k])}) overflows "
                  "float64 (its joints' sum)")
            for k in nonfinite_rows(out.blocks)
        ]
    if faults:
        raise InputError(faults[:MAX_FAULTS])


def check_layout(layout: str) -> list[Fault]:
    return [] if layout in LAYOUTS else [Fault(("layout",), literal_msg(LAYOUTS), "literal_error")]
