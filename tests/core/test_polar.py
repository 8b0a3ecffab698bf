"""Polar factors (jointlimits.service.core.polar) and the body table's kept norms (kinematics.BodyTable)."""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.service.core.kinematics import PREV_STEP, STEP, TOTAL_STEP, BodyTable, _plain_bodies
from jointlimits.service.core.polar import polar_rotation, squared_norms
from jointlimits.service.core.scene import Bodies


def _mixed(rng: np.random.Generator, m: int, svd: bool) -> np.ndarray:
    """(9, m) component-major: strained rotations (Newton, converging after 2 to 5 steps), if `svd`
    near-singular and singular matrices (the SVD's), and extreme scales, shuffled."""
    R = np.linalg.qr(rng.normal(size=(m, 3, 3)))[0]
    strain = rng.choice([0.0, 1e-6, 1e-2, 0.3, 0.9], size=m)[:, None, None] * rng.normal(size=(m, 3, 3))
    A = R @ (np.eye(3) + strain)
    if svd:
        A[rng.random(m) < 0.1] = np.diag([1.0, 1.0, 1e-9])  # estimated ratio below 1e-4: the SVD
        A[rng.random(m) < 0.05] = 0.0
    # Beyond ~1e+-100 the estimate's |A|^3 leaves float64 and those bodies take the SVD too.
    A *= rng.choice([1e-200, 1.0, 1e150] if svd else [1e-60, 1.0, 1e60], size=m)[:, None, None]
    return np.ascontiguousarray(A.reshape(m, 9).T)


@pytest.mark.parametrize("svd", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_each_factor_is_the_one_of_its_body_alone_and_the_input_is_not_written(seed, svd):
    # With every body Newton's, the loop reads `a` in place and hands the step where the first bodies
    # converge over as R itself, iterating on the rest: every column must still be exactly that body's
    # own factor, and `a` untouched.
    rng = np.random.default_rng(seed)
    a = _mixed(rng, 300, svd)
    before = a.copy()
    with np.errstate(all="ignore"):
        R, ratio = polar_rotation(a)
        alone = [polar_rotation(a[:, [j]].copy()) for j in range(a.shape[1])]
    assert np.array_equal(a, before)
    assert R.tobytes() == np.concatenate([r for r, _ in alone], axis=1).tobytes()
    assert ratio.tobytes() == np.concatenate([s for _, s in alone]).tobytes()


def test_factors_are_rotations_whose_stretch_is_symmetric():
    rng = np.random.default_rng(7)
    m = 500
    Q = np.linalg.qr(rng.normal(size=(m, 3, 3)))[0]
    Q[np.linalg.det(Q) < 0] *= -1.0
    S = rng.normal(size=(m, 3, 3))
    S = np.eye(3) + 0.3 * (S @ S.transpose(0, 2, 1))  # a symmetric positive definite stretch
    A = Q @ S
    R, ratio = polar_rotation(np.ascontiguousarray(A.reshape(m, 9).T))
    R = R.T.reshape(m, 3, 3)
    np.testing.assert_allclose(R, Q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), (m, 3, 3)), rtol=0, atol=1e-14)
    s = np.linalg.svd(A, compute_uv=False)
    exact = s[:, -1] / s[:, 0]
    assert np.all(ratio <= exact * (1 + 1e-12)) and np.all(ratio >= exact / 3)


def test_kept_norms_follow_each_load():
    # `plain_over` keeps the squared norms of states and increments until they are rewritten: after
    # loading a state with a body scaled out of the plain range, and after a commit-like copy, the
    # flags must be those of a fresh computation.
    rng = np.random.default_rng(3)
    n = 64
    q_ref = np.concatenate([rng.normal(size=(n, 3)), np.tile(np.eye(3).ravel(), (n, 1))], axis=1)
    bodies = Bodies(q_ref.copy(), q_ref.copy(), q_ref.copy())
    rows = (PREV_STEP, STEP, TOTAL_STEP)
    table = BodyTable(bodies, rows=rows)
    assert table.plain_over(rows).all()
    q = q_ref.copy()
    q[5, 3:] *= 2.0**300  # out of the plain range
    q[9, 3:] = -q[9, 3:]  # a step of 2 |A|: still plain (at the bound)
    q[11, 3:] *= -0.2  # a step of 6 times the A it ends at: not plain
    table.load(2, q)
    table.increments((STEP, TOTAL_STEP))
    got = table.plain_over(rows)
    want = _plain_bodies(table.states, table.linear, rows)
    assert np.array_equal(got, want)
    assert not got[5] and got[9] and not got[11] and got.sum() == n - 2
    table.load(1, table.dofs[2].T)  # q_prev := q
    table.increments(rows)
    assert np.array_equal(table.plain_over(rows), _plain_bodies(table.states, table.linear, rows))


@pytest.mark.parametrize("svd", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_factors_of_the_used_bodies_only_and_every_ratio(seed, svd):
    """`used`: the read bodies' factors bit for bit as without it, 0 for the others, and every ratio
    as without it (a singular A_ref is refused whether a joint reads it or not)."""
    rng = np.random.default_rng(10 + seed)
    a = _mixed(rng, 400, svd)
    used = rng.random(400) < 0.3
    with np.errstate(all="ignore"):
        R, ratio = polar_rotation(a)
        R_used, ratio_used = polar_rotation(a, used)
    assert ratio_used.tobytes() == ratio.tobytes()
    assert R_used[:, used].tobytes() == R[:, used].tobytes()
    # Not taken (0) where Newton's iteration would have; the few the SVD takes for their ratio keep it.
    unused = R_used[:, ~used]
    zero, same = ~unused.any(axis=0), (unused == R[:, ~used]).all(axis=0)
    assert (zero | same).all() and zero.any()


def test_unused_bodies_change_no_bit_and_a_singular_one_is_still_refused():
    """A scene padded with bodies no joint reads answers every bit as without them; one of them
    with a singular A_ref is a 422 naming it, as before."""
    from bench.scenes import make_scene
    from jointlimits.service.core import InputError, evaluate

    bodies, batches = make_scene(400, 0.5, seed=3)
    B = bodies.q.shape[0]
    rng = np.random.default_rng(3)
    extra = np.concatenate([rng.normal(size=(5 * B, 3)), np.tile(np.eye(3).ravel(), (5 * B, 1))], axis=1)
    padded = Bodies(*(np.concatenate([a, extra]) for a in (bodies.q, bodies.q_prev, bodies.q_ref)))
    for mode in ("exact", "psd"):
        want, got = evaluate(bodies, batches, hessian_mode=mode), evaluate(padded, batches, hessian_mode=mode)
        assert got.total_energy == want.total_energy
        for g, w in zip(got.batches, want.batches):
            for f in ("x", "energy", "gradient", "hessian"):
                assert getattr(g, f).tobytes() == getattr(w, f).tobytes()
    q_ref = padded.q_ref.copy()
    q_ref[B + 7, 3:] = np.diag([1.0, 1.0, 0.0]).ravel()  # an unused body, singular
    with pytest.raises(InputError) as e:
        evaluate(Bodies(padded.q, padded.q_prev, q_ref), batches)
    assert [f.loc for f in e.value.faults] == [("bodies", "q_ref", B + 7)]


def test_mostly_used_bodies_take_the_whole_table():
    """With most bodies read the subset would cost more (a gather and scatters) than it saves: every
    factor is taken, bit for bit as without `used`."""
    rng = np.random.default_rng(20)
    a = _mixed(rng, 400, False)
    used = rng.random(400) < 0.9
    R, ratio = polar_rotation(a)
    R_used, ratio_used = polar_rotation(a, used)
    assert R_used.tobytes() == R.tobytes() and ratio_used.tobytes() == ratio.tobytes()


@pytest.mark.parametrize("m", [1, 2, 3, 257])
@pytest.mark.parametrize("order", ["C", "F"])
def test_squared_norms_add_the_rows_in_order(m, order):
    """`polar.squared_norms` in one call where NumPy's sum is row after row: bitwise the rows added in order, for
    any count of columns (a lone one is summed pairwise by NumPy) and layout, with magnitudes far apart."""
    rng = np.random.default_rng(m)
    for k in (9, 12):
        a = np.array(rng.normal(size=(k, m)) * 10.0 ** rng.integers(-8, 9, size=(k, m)), order=order)
        sq = a * a
        want = sq[0] + sq[1]
        for row in sq[2:]:
            want = want + row
        assert squared_norms(a).tobytes() == want.tobytes()
