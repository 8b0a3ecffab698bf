"""`layout="bodies"` in the core: the assembled answer equals the scatter-add of the per-joint answer.

The bitwise references are plain Python loops over joints adding each joint's blocks in request
order (batch, joint, then (i, i), (j, j), (i, j)): the core sums each key's terms in that order.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from jointlimits.service.core import InputError, evaluate
from jointlimits.service.core import assembled as core_assembled
from jointlimits.service.core.assembled import Assembled, assemble_active, reduce_pairs
from jointlimits.service.core.prepared import prepare
from tests import scenes
from tests.assembled_ref import apply, assemble
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
    for out in (apply(ev, bodies.q.shape[0], batches, False), evaluate(bodies, batches, layout="bodies")):
        assert all(r.gradient is None and r.hessian is None for r in out.batches)
        assert all(np.array_equal(a.x, b.x) and np.array_equal(a.energy, b.energy) for a, b in zip(out.batches, ev.batches))
        assert out.assembled is not None and out.total_energy == ev.total_energy
    assert ev.assembled is None  # layout "joints": the per-joint answer as it is


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
    assert isinstance(M, sparse.csr_array)  # the array API (`M @ v` a product), not the legacy csr_matrix
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
    # In order: (a + b) + c differs from a + (b + c) here, and reduce_pairs gives the former.
    a, b, c = 1.0, 2.0**-53, 2.0**-53
    terms = np.array([a, b, c])[:, None, None] * np.ones((3, 12, 12))
    _, _, bb = reduce_pairs(np.zeros(3, np.int64), np.ones(3, np.int64), terms)
    assert bb[0, 0, 0] == (a + b) + c != a + (b + c)
    r = np.array([2, 0, 2, 0])
    c = np.array([3, 1, 3, 0])
    b = np.arange(4, dtype=float)[:, None, None] * np.ones((4, 12, 12))
    rr, cc, bb = reduce_pairs(r, c, b)
    assert rr.tolist() == [0, 0, 2] and cc.tolist() == [0, 1, 3]
    assert bb[:, 0, 0].tolist() == [3.0, 1.0, 2.0]
    rr, cc, bb = reduce_pairs(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 12, 12)))
    assert rr.shape == (0,) and bb.shape == (0, 12, 12)


# ---------------------------------------------------------------- bitwise against a loop in request order


def loop_assembly(body_ids: list[np.ndarray], per_joint: list, n_bodies: int) -> tuple[np.ndarray, dict]:
    """Gradient (B, 12) and {(r, c): block} (r <= c) by a plain loop over every joint of `per_joint`
    (core `BatchResult`s of layout "joints", all rows), adding joints outside their range only."""
    G = np.zeros((n_bodies, 12))
    blocks: dict[tuple[int, int], np.ndarray] = {}

    def add(key, block):
        blocks[key] = blocks[key] + block if key in blocks else block.copy()

    for ids, r in zip(body_ids, per_joint):
        for m, k in enumerate(r.index):
            if r.energy[m] == 0.0:  # inside its range (bounds included): never differentiated
                continue
            i, j = (int(v) for v in ids[k])
            G[i] = G[i] + r.gradient[m, :12]
            G[j] = G[j] + r.gradient[m, 12:]
            H = r.hessian[m]
            add((i, i), H[:12, :12])
            add((j, j), H[12:, 12:])
            add((min(i, j), max(i, j)), H[:12, 12:] if i < j else H[12:, :12])
    return G, blocks


def shared_scene(seed: int, n_bodies: int = 5, extra: int = 20, uids: tuple = (670, 669, 670)) -> scenes.Scene:
    """Bodies shared by many joints (a chain plus `extra` random pairs, both orders), batches of `uids`."""
    rng = np.random.default_rng(seed)
    sc = scenes.random_chain_scene(rng, n_bodies=n_bodies, extra_joints=extra, batch_uids=uids)
    return scenes.place_limits(sc, rng, ("above", "below", "inside", "on_upper"))


ARRAYS = ("gradient", "rows", "cols", "blocks")


def assert_bitwise(a, b) -> None:
    assert a.n_bodies == b.n_bodies
    for k in ARRAYS:
        x, y = getattr(a, k), getattr(b, k)
        assert (x is None) == (y is None), k
        if x is not None:
            assert x.dtype == y.dtype and x.shape == y.shape, k
            assert np.array_equal(np.ascontiguousarray(x).view(np.uint8), np.ascontiguousarray(y).view(np.uint8)), k


@pytest.mark.parametrize("mode", ["exact", "psd"])
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("size", [(5, 20), (40, 120), (40, 120, (669,))], ids=["small", "rank-passes", "one-batch"])
def test_core_equals_the_loop_scatter_add_bitwise(seed, mode, size):
    # 40 bodies: more than _FEW groups of several terms, so the vectorised rank passes run too.
    sc = shared_scene(seed, *size)
    ids = [b.body_ids for b in sc.batches]
    pairs = np.concatenate(ids)
    assert (pairs[:, 0] < pairs[:, 1]).any() and (pairs[:, 0] > pairs[:, 1]).any()  # both orientations
    per_joint = evaluate(**sc.core_args(hessian_mode=mode))
    ev = evaluate(**sc.core_args(hessian_mode=mode, layout="bodies"))
    G, blocks = loop_assembly(ids, per_joint.batches, sc.q.shape[0])
    a = ev.assembled
    keys = sorted(blocks)
    assert len(keys) > sc.q.shape[0]  # off-diagonal blocks present
    assert list(zip(a.rows.tolist(), a.cols.tolist())) == keys  # rows <= cols, lexicographic, one per pair
    assert a.rows.dtype == a.cols.dtype == np.int64 and a.blocks.shape == (len(keys), 12, 12)
    assert np.array_equal(a.gradient, G)
    assert np.array_equal(a.blocks, np.stack([blocks[k] for k in keys]))
    assert ev.total_energy == per_joint.total_energy
    # The same bits from a per-joint answer (apply), with or without active_only.
    for active_only in (False, True):
        rows = evaluate(**sc.core_args(hessian_mode=mode, active_only=active_only))
        assert_bitwise(apply(rows, sc.q.shape[0], [b.joints() for b in sc.batches], active_only).assembled, a)
    if size[0] == 40:
        terms = np.concatenate([b.body_ids[r.energy > 0] for b, r in zip(sc.batches, per_joint.batches)])
        assert (np.bincount(terms.reshape(-1)) > 1).sum() > core_assembled._FEW


@pytest.mark.parametrize("mode", ["exact", "psd"])
def test_a_hub_body_with_many_joints_on_few_pairs(mode):
    # 4 bodies, ~100 joints: each pair's group is longer than the rank passes handle (the tail path).
    sc = shared_scene(7, n_bodies=4, extra=100)
    ids = [b.body_ids for b in sc.batches]
    per_joint = evaluate(**sc.core_args(hessian_mode=mode))
    a = evaluate(**sc.core_args(hessian_mode=mode, layout="bodies")).assembled
    G, blocks = loop_assembly(ids, per_joint.batches, 4)
    keys = sorted(blocks)
    assert list(zip(a.rows.tolist(), a.cols.tolist())) == keys
    assert np.array_equal(a.gradient, G)
    assert np.array_equal(a.blocks, np.stack([blocks[k] for k in keys]))


def test_offsets_move_the_range_and_the_assembly_follows():
    # v1.1 offsets: the active joints are those outside [lower - offset, upper - offset] in x;
    # `apply` on the per-joint answer finds the same ones as the core (bitwise the same sums).
    sc = shared_scene(11)
    rng = np.random.default_rng(11)
    batches = [replace(b.joints(), offset=rng.uniform(-0.3, 0.3, len(b.lower))) for b in sc.batches]
    ev = evaluate(sc.bodies(), batches, layout="bodies")
    per_joint = evaluate(sc.bodies(), batches)
    assert_bitwise(apply(per_joint, sc.q.shape[0], batches, False).assembled, ev.assembled)
    G, blocks = loop_assembly([b.body_ids for b in batches], per_joint.batches, sc.q.shape[0])
    assert np.array_equal(ev.assembled.gradient, G)
    assert np.array_equal(ev.assembled.blocks, np.stack([blocks[k] for k in sorted(blocks)]))


def test_batches_keep_rows_x_energy_only():
    sc = shared_scene(1)
    for active_only in (False, True):
        per_joint = evaluate(**sc.core_args(active_only=active_only))
        ev = evaluate(**sc.core_args(active_only=active_only, layout="bodies"))
        assert ev.total_energy == per_joint.total_energy
        for r, p in zip(ev.batches, per_joint.batches):
            assert r.gradient is None and r.hessian is None
            for k in ("index", "x", "coordinate", "energy"):
                assert np.array_equal(getattr(r, k), getattr(p, k)), k
    assert per_joint.assembled is None


def test_only_the_outputs_asked_for_are_assembled():
    sc = shared_scene(2)
    all_ = evaluate(**sc.core_args(layout="bodies")).assembled
    g = evaluate(**sc.core_args(outputs=("energy", "gradient"), layout="bodies")).assembled
    h = evaluate(**sc.core_args(outputs=("hessian",), layout="bodies")).assembled
    e = evaluate(**sc.core_args(outputs=("energy",), layout="bodies")).assembled
    # The per-joint gradient alone is formed on another route than beside the Hessian (J^T dx from the
    # Hessian's factors): rounding apart. Bitwise, it is the sum of the gradient-only per-joint rows.
    per_joint = evaluate(**sc.core_args(outputs=("energy", "gradient")))
    G, _ = loop_assembly([b.body_ids for b in sc.batches],
                         [replace(r, hessian=np.zeros((len(r.index), 24, 24))) for r in per_joint.batches], sc.q.shape[0])
    assert g.blocks is None and g.rows is None and np.array_equal(g.gradient, G)
    np.testing.assert_allclose(g.gradient, all_.gradient, rtol=0, atol=1e-14 * np.abs(all_.gradient).max())
    assert h.gradient is None and np.array_equal(h.blocks, all_.blocks) and np.array_equal(h.cols, all_.cols)
    assert e.gradient is None and e.blocks is None and e.n_bodies == sc.q.shape[0]


def test_no_joint_outside_its_range_gives_k_0():
    sc = shared_scene(3)
    inside = replace(sc, batches=[replace(b, lower=b.lower - 10, upper=b.upper + 10) for b in sc.batches])
    a = evaluate(**inside.core_args(layout="bodies")).assembled
    assert a.rows.shape == a.cols.shape == (0,) and a.blocks.shape == (0, 12, 12)
    assert a.rows.dtype == a.cols.dtype == np.int64
    assert a.gradient.shape == (sc.q.shape[0], 12) and not a.gradient.any()
    none = evaluate(**replace(sc, batches=[]).core_args(layout="bodies")).assembled
    assert none.blocks.shape == (0, 12, 12) and none.gradient.shape == (sc.q.shape[0], 12)


def test_assemble_orients_blocks_by_body_order():
    # Synthetic rows (random symmetric H) in two batches: the assembled matrix is sum_m P_m^T H_m P_m,
    # P_m picking the joint's DOFs [q_i, q_j] in whatever order body_ids gives them.
    rng = np.random.default_rng(0)
    n_bodies, n = 6, 40
    ids = np.stack([rng.choice(n_bodies, size=2, replace=False) for _ in range(n)])
    g = rng.normal(size=(n, 24))
    H = rng.normal(size=(n, 24, 24))
    H = H + H.transpose(0, 2, 1)
    a = assemble_active(n_bodies, [(ids[:20], g[:20], H[:20]), (ids[20:], g[20:], H[20:])], True, True)
    D, G = np.zeros((12 * n_bodies,) * 2), np.zeros(12 * n_bodies)
    for m in range(n):
        dofs = np.concatenate([np.arange(12 * b, 12 * b + 12) for b in ids[m]])
        D[np.ix_(dofs, dofs)] += H[m]
        G[dofs] += g[m]
    np.testing.assert_allclose(full(a), D, rtol=1e-14, atol=1e-13)
    np.testing.assert_allclose(a.gradient.reshape(-1), G, rtol=1e-14, atol=1e-13)
    assert (a.rows <= a.cols).all() and (np.diff(a.rows * n_bodies + a.cols) > 0).all()


def test_an_overflowing_sum_is_an_input_error_at_layout():
    ids = np.array([[0, 1], [1, 0]])
    g = np.full((2, 24), 1e308)
    with pytest.raises(InputError) as e, np.errstate(over="ignore"):
        assemble_active(2, [(ids, g, None)], True, False)
    assert e.value.faults[0].loc == ("layout",) and "body 0" in e.value.faults[0].msg
    H = np.full((2, 24, 24), 1e308)
    with pytest.raises(InputError) as e, np.errstate(over="ignore"):
        assemble_active(2, [(ids, None, H)], False, True)
    assert e.value.faults[0].loc == ("layout",) and "block (0, 0)" in e.value.faults[0].msg


def test_an_unknown_layout_names_the_field():
    sc = shared_scene(0)
    with pytest.raises(InputError) as e:
        evaluate(**sc.core_args(layout="body"))
    assert e.value.faults[0].loc == ("layout",)


def test_a_prepared_scene_assembles_too():
    sc = shared_scene(9)
    scene = prepare(sc.bodies(), [b.joints() for b in sc.batches])
    a = scene.evaluate(sc.q, layout="bodies").assembled
    assert_bitwise(a, evaluate(**sc.core_args(layout="bodies")).assembled)
    assert scene.evaluate(sc.q).assembled is None
    with pytest.raises(InputError) as e:
        scene.evaluate(sc.q, layout="rows")
    assert e.value.faults[0].loc == ("layout",)
