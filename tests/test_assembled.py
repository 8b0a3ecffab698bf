"""`layout="bodies"` in the core: the assembled answer equals the scatter-add of the per-joint answer."""

from __future__ import annotations

import numpy as np
import pytest

from service.core import evaluate
from service.core.assembled import Assembled, apply, assemble, reduce_pairs
from tests.scenes import random_scene


def scene(seed: int):
    sc = random_scene(np.random.default_rng(70_000 + seed), None)
    return sc.bodies(), [b.joints() for b in sc.batches]


def dense(bodies, batches, ev) -> tuple[np.ndarray, np.ndarray]:
    """Scene gradient (12B) and Hessian (12B, 12B) by a plain loop over every joint's rows."""
    n = bodies.q.shape[0]
    g, H = np.zeros(12 * n), np.zeros((12 * n, 12 * n))
    for joints, r in zip(batches, ev.batches):
        for row, j in enumerate(r.index):
            dofs = np.concatenate([np.arange(12 * b, 12 * b + 12) for b in joints.body_ids[j]])
            g[dofs] += r.gradient[row]
            H[np.ix_(dofs, dofs)] += r.hessian[row]
    return g, H


def full(a: Assembled) -> np.ndarray:
    n = 12 * a.n_bodies
    H = np.zeros((n, n))
    for r, c, blk in zip(a.rows, a.cols, a.blocks):
        H[12 * r : 12 * r + 12, 12 * c : 12 * c + 12] += blk
        if r != c:
            H[12 * c : 12 * c + 12, 12 * r : 12 * r + 12] += blk.T
    return H


@pytest.mark.parametrize("mode", ["exact", "psd"])
@pytest.mark.parametrize("active_only", [False, True])
@pytest.mark.parametrize("seed", range(6))
def test_assembled_is_the_scatter_add_of_the_per_joint_answer(seed: int, mode: str, active_only: bool):
    bodies, batches = scene(seed)
    ev = evaluate(bodies, batches, hessian_mode=mode, active_only=active_only)
    a = assemble(bodies.q.shape[0], batches, ev, active_only)
    g, H = dense(bodies, batches, ev)
    scale = max(np.abs(H).max(), 1e-300)
    np.testing.assert_allclose(a.gradient.reshape(-1), g, rtol=0, atol=1e-14 * max(np.abs(g).max(), 1e-300))
    np.testing.assert_allclose(full(a), H, rtol=0, atol=1e-14 * scale)
    assert (a.rows <= a.cols).all()
    key = a.rows * bodies.q.shape[0] + a.cols
    assert (np.diff(key) > 0).all()  # sorted, one entry per pair
    for r, c, blk in zip(a.rows, a.cols, a.blocks):
        if r == c:
            assert np.array_equal(blk, blk.T)  # bitwise, as the per-joint blocks it sums
    # Exactly the pairs of joints outside their range.
    pairs = set()
    for joints, res in zip(batches, ev.batches):
        for row, j in enumerate(res.index):
            if res.energy[row] > 0:
                i, k = sorted(int(b) for b in joints.body_ids[j])
                pairs |= {(i, i), (k, k), (i, k)}
    assert set(zip(a.rows.tolist(), a.cols.tolist())) == pairs


def test_apply_strips_the_batches_and_keeps_x_and_energy():
    bodies, batches = scene(1)
    ev = evaluate(bodies, batches)
    out = apply(ev, bodies.q.shape[0], batches, "bodies", False)
    assert all(r.gradient is None and r.hessian is None for r in out.batches)
    assert all(np.array_equal(a.x, b.x) and np.array_equal(a.energy, b.energy) for a, b in zip(out.batches, ev.batches))
    assert out.assembled is not None and out.total_energy == ev.total_energy
    assert apply(ev, bodies.q.shape[0], batches, "joints", False) is ev


def test_only_the_outputs_asked_for():
    bodies, batches = scene(2)
    a = assemble(bodies.q.shape[0], batches, evaluate(bodies, batches, outputs=("energy", "gradient")), False)
    assert a.gradient is not None and a.blocks is None and a.rows is None
    a = assemble(bodies.q.shape[0], batches, evaluate(bodies, batches, outputs=("energy",)), False)
    assert a.gradient is None and a.blocks is None


def test_matrix_is_the_symmetric_sparse_hessian():
    sparse = pytest.importorskip("scipy.sparse")
    bodies, batches = scene(3)
    ev = evaluate(bodies, batches)
    a = assemble(bodies.q.shape[0], batches, ev, False)
    M = a.matrix()
    assert sparse.issparse(M) and M.shape == (12 * bodies.q.shape[0],) * 2
    _, H = dense(bodies, batches, ev)
    np.testing.assert_allclose(M.toarray(), H, rtol=0, atol=1e-14 * np.abs(H).max())
    assert (abs(M - M.T) > 0).nnz == 0


def test_matrix_without_scipy_says_how_to_get_it(monkeypatch: pytest.MonkeyPatch):
    import builtins

    real = builtins.__import__

    def no_scipy(name, *args, **kw):
        if name == "scipy" or name.startswith("scipy."):
            raise ImportError(name)
        return real(name, *args, **kw)

    monkeypatch.setattr(builtins, "__import__", no_scipy)
    with pytest.raises(ImportError, match=r"pip install"):
        Assembled(1, rows=np.zeros(0, np.int64), cols=np.zeros(0, np.int64), blocks=np.zeros((0, 12, 12))).matrix()


def test_reduce_pairs_sums_in_order_and_sorts():
    r = np.array([2, 0, 2, 0])
    c = np.array([3, 1, 3, 0])
    b = np.arange(4, dtype=float)[:, None, None] * np.ones((4, 12, 12))
    rr, cc, bb = reduce_pairs(r, c, b)
    assert rr.tolist() == [0, 0, 2] and cc.tolist() == [0, 1, 3]
    assert bb[:, 0, 0].tolist() == [3.0, 1.0, 2.0]
    rr, cc, bb = reduce_pairs(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 12, 12)))
    assert rr.shape == (0,) and bb.shape == (0, 12, 12)
