"""Properties of the core that need no reference: derivatives vs finite differences, symmetry,
PSD-ness, output subsets, active_only, invariance under a rigid motion, sign conventions.

NumPy only; scenes from tests/scenes.py, seeded. (hypothesis is not in the `test` extra that CI
installs, so the scene families are enumerated by seed instead.)
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from jointlimits.service.core import Evaluation, InputError, evaluate
from tests.conftest import relerr
from tests.scenes import (
    E_X,
    Batch,
    Scene,
    axis_pair_scene,
    dof_transform,
    place_limits,
    random_rotation,
    random_scene,
    random_unit,
    rotation_about,
    unit,
)

pytestmark = pytest.mark.slow  # derivatives by finite differences over random scenes (~8 s)

OFF_BOUND = ("inside", "above", "below", "degenerate")
SEEDS = range(14)


def scene(seed: int, kinds: tuple[str, ...] | None = OFF_BOUND) -> Scene:
    return random_scene(np.random.default_rng(50_000 + seed), kinds)


def assemble(sc: Scene, ev: Evaluation) -> tuple[np.ndarray, np.ndarray | None]:
    """Scene-level gradient (12B) and Hessian (12B, 12B): each joint's [q_i, q_j] blocks scattered and summed."""
    n = 12 * sc.q.shape[0]
    G = np.zeros(n)
    H = np.zeros((n, n)) if ev.batches and ev.batches[0].hessian is not None else None
    for b, r in zip(sc.batches, ev.batches):
        for row, k in enumerate(r.index):
            i, j = b.body_ids[k]
            dofs = np.r_[12 * i : 12 * i + 12, 12 * j : 12 * j + 12]
            G[dofs] += r.gradient[row]
            if H is not None:
                H[np.ix_(dofs, dofs)] += r.hessian[row]
    return G, H


def with_q(sc: Scene, q_flat: np.ndarray) -> Scene:
    return replace(sc, q=q_flat.reshape(sc.q.shape))


def richardson(f, q: np.ndarray, h: float) -> np.ndarray:
    """4-point central differences of f (scalar or array valued) in every coordinate of q: error O(h^4)."""
    cols = []
    for a in range(q.size):
        e = np.zeros(q.size)
        e[a] = h
        cols.append((-f(q + 2 * e) + 8 * f(q + e) - 8 * f(q - e) + f(q - 2 * e)) / (12 * h))
    return np.stack(cols, axis=-1)


# ---------------------------------------------------------------- derivatives


@pytest.mark.parametrize("seed", SEEDS)
def test_gradient_is_the_derivative_of_the_energy(seed: int) -> None:
    sc = scene(seed)
    G, _ = assemble(sc, evaluate(**sc.core_args(outputs=("gradient",))))
    energy = lambda q: evaluate(**with_q(sc, q).core_args(outputs=("energy",))).total_energy  # noqa: E731
    fd = richardson(energy, sc.q.ravel(), 1e-4)
    assert np.abs(G).max() > 0
    # Differences of float64 energies: rounding ~eps |E| / h ~ 1e-12 (h^4 truncation ~1e-16); measured 2.1e-12.
    assert relerr(G, fd) <= 1e-10


@pytest.mark.parametrize("seed", SEEDS)
def test_exact_hessian_is_the_derivative_of_the_gradient(seed: int) -> None:
    sc = scene(seed)
    _, H = assemble(sc, evaluate(**sc.core_args()))
    grad = lambda q: assemble(with_q(sc, q), evaluate(**with_q(sc, q).core_args(outputs=("gradient",))))[0]  # noqa: E731
    fd = richardson(grad, sc.q.ravel(), 1e-4)
    assert np.abs(H).max() > 0
    # Same error budget as for the gradient; measured 2.0e-12.
    assert relerr(H, fd) <= 1e-10


@pytest.mark.parametrize("mode", ["exact", "psd"])
@pytest.mark.parametrize("seed", SEEDS)
def test_hessians_are_bitwise_symmetric(seed: int, mode: str) -> None:
    ev = evaluate(**scene(seed).core_args(hessian_mode=mode))
    for r in ev.batches:
        np.testing.assert_array_equal(r.hessian, r.hessian.transpose(0, 2, 1))


@pytest.mark.parametrize("seed", SEEDS)
def test_psd_hessians_are_psd(seed: int) -> None:
    sc = scene(seed)
    ev = evaluate(**sc.core_args(hessian_mode="psd"))
    for r in ev.batches:
        for H in r.hessian:
            scale = max(np.abs(H).max(), 1e-300)
            assert np.linalg.eigvalsh(H).min() >= -1e-13 * scale
    _, H = assemble(sc, ev)  # a sum of PSD blocks stays PSD
    assert np.linalg.eigvalsh(H).min() >= -1e-13 * max(np.abs(H).max(), 1e-300)


def test_exact_hessians_are_indefinite_somewhere() -> None:
    """The two modes differ: exact is not PSD in general, and psd only adds curvature (psd - exact >= 0)."""
    worst = 0.0
    for seed in SEEDS:
        sc = scene(seed)
        exact, psd = (evaluate(**sc.core_args(hessian_mode=m)) for m in ("exact", "psd"))
        for re, rp in zip(exact.batches, psd.batches):
            for He, Hp in zip(re.hessian, rp.hessian):
                scale = max(np.abs(He).max(), 1e-300)
                worst = min(worst, np.linalg.eigvalsh(He).min() / scale)
                assert np.linalg.eigvalsh(Hp - He).min() >= -1e-13 * scale
    assert worst < -1e-3


# ---------------------------------------------------------------- what is reported


@pytest.mark.parametrize("seed", SEEDS)
def test_energy_only_request_matches_full_request_bitwise(seed: int) -> None:
    sc = scene(seed, kinds=None)
    full = evaluate(**sc.core_args())
    for outputs in (("energy",), ("energy", "gradient"), ("hessian",)):
        part = evaluate(**sc.core_args(outputs=outputs))
        assert part.total_energy == full.total_energy
        for p, f in zip(part.batches, full.batches):
            np.testing.assert_array_equal(p.x, f.x)
            np.testing.assert_array_equal(p.energy, f.energy)
            np.testing.assert_array_equal(p.index, f.index)
            assert (p.gradient is None) == ("gradient" not in outputs)
            assert (p.hessian is None) == ("hessian" not in outputs)
            if p.gradient is not None:
                assert relerr(p.gradient, f.gradient) <= 1e-15


@pytest.mark.parametrize("mode", ["exact", "psd"])
@pytest.mark.parametrize("seed", SEEDS)
def test_active_only_reports_exactly_the_joints_with_energy(seed: int, mode: str) -> None:
    rng = np.random.default_rng(60_000 + seed)
    sc = place_limits(scene(seed), rng)  # every kind, on-bound included
    batches = []
    for b, x in zip(sc.batches, sc.x()):
        # Some joints outside their range with zero strength: no energy, so not active.
        s = np.where(rng.uniform(size=b.strength.shape) < 0.2, 0.0, b.strength)
        # Joint 0 of each batch is active (an all-idle batch is test_active_only_with_an_idle_batch's).
        lo, up = b.lower.copy(), b.upper.copy()
        up[0], lo[0], s[0] = x[0] - 0.1, x[0] - 1.1, 1.0
        batches.append(replace(b, lower=lo, upper=up, strength=s))
    sc = replace(sc, batches=batches)
    full = evaluate(**sc.core_args(hessian_mode=mode))
    act = evaluate(**sc.core_args(hessian_mode=mode, active_only=True))
    assert act.total_energy == full.total_energy
    for a, f in zip(act.batches, full.batches):
        np.testing.assert_array_equal(f.index, np.arange(f.x.shape[0]))
        want = np.flatnonzero(f.energy != 0)
        np.testing.assert_array_equal(a.index, want)
        for name in ("x", "energy", "gradient", "hessian"):
            np.testing.assert_array_equal(getattr(a, name), getattr(f, name)[want])
        # Inactive rows of the full answer are exact zeros.
        idle = np.flatnonzero(f.energy == 0)
        assert not f.gradient[idle].any() and not f.hessian[idle].any()


@pytest.mark.parametrize("outputs", [("energy",), ("energy", "gradient", "hessian")])
def test_active_only_with_an_idle_batch(outputs: tuple[str, ...]) -> None:
    """A batch with no joint outside its range answers zero rows (CORE BUG: it raises ValueError
    "cannot reshape array of size 0" in the non-finite check, a 500 over HTTP)."""
    sc = scene(0)
    x = sc.x()
    idle = replace(sc.batches[0], lower=x[0] - 1.0, upper=x[0] + 1.0)  # every joint well inside
    busy = replace(sc.batches[-1], lower=x[-1] + 0.5, upper=x[-1] + 1.5)  # every joint below its range
    sc = replace(sc, batches=[idle, busy])
    ev = evaluate(**sc.core_args(outputs=outputs, active_only=True))
    assert ev.batches[0].index.shape == (0,) and ev.batches[0].x.shape == (0,) and ev.batches[0].energy.shape == (0,)
    if "gradient" in outputs:
        assert ev.batches[0].gradient.shape == (0, 24) and ev.batches[0].hessian.shape == (0, 24, 24)
    np.testing.assert_array_equal(ev.batches[1].index, np.arange(busy.lower.shape[0]))


def test_empty_batch_is_not_a_crash() -> None:
    """A batch with no joints is either an input error or zero rows, never an unhandled exception
    (CORE BUG: same ValueError as above)."""
    sc = scene(1)
    empty = replace(sc.batches[0], body_ids=np.zeros((0, 2), dtype=np.int64), edges=np.zeros((0, 2, 3)), lower=np.zeros(0), upper=np.zeros(0), strength=np.zeros(0))
    sc = replace(sc, batches=[empty, *sc.batches])
    try:
        ev = evaluate(**sc.core_args())
    except InputError:
        return
    assert ev.batches[0].x.shape == (0,) and ev.batches[0].gradient.shape == (0, 24)


@pytest.mark.parametrize("seed", SEEDS)
def test_energy_is_the_cubic_penalty_of_x(seed: int) -> None:
    """E from the reported x by the spec's formula, both for normal and degenerate (u == l) ranges."""
    sc = scene(seed)
    ev = evaluate(**sc.core_args(outputs=("energy",)))
    for b, r in zip(sc.batches, ev.batches):
        lo, up, s, x = b.lower, b.upper, b.strength, r.x
        w = np.where(up > lo, up - lo, 1.0)
        g = np.where(x > up, x - up, np.where(x < lo, lo - x, 0.0))
        np.testing.assert_allclose(r.energy, s * (g / w) ** 3, rtol=1e-14, atol=0)


@pytest.mark.parametrize("active_only", [False, True])
def test_rows_do_not_depend_on_the_batch_they_are_in(active_only: bool) -> None:
    """A batch of > 4096 active joints (the core differentiates in chunks) gives each joint the row it gets alone."""
    sc = scene(2)
    big = []
    for b in sc.batches:
        reps = 4100 // b.lower.shape[0] + 1
        tile = lambda a: np.concatenate([a] * reps)  # noqa: E731
        big.append(replace(b, body_ids=tile(b.body_ids), edges=tile(b.edges), lower=tile(b.lower), upper=tile(b.upper), strength=tile(b.strength)))
    small_ev = evaluate(**sc.core_args(active_only=active_only))
    big_ev = evaluate(**replace(sc, batches=big).core_args(active_only=active_only))
    for s, g, b in zip(small_ev.batches, big_ev.batches, sc.batches):
        n = b.lower.shape[0]
        assert g.x.shape[0] == s.x.shape[0] * (4100 // n + 1)
        reps = g.x.shape[0] // max(s.x.shape[0], 1)
        np.testing.assert_array_equal(g.index % n, np.tile(s.index, reps))
        for name in ("x", "energy", "gradient", "hessian"):
            assert relerr(getattr(g, name), np.concatenate([getattr(s, name)] * reps)) <= 1e-15


@pytest.mark.parametrize("seed", SEEDS)
def test_swapping_the_bodies_of_a_joint_negates_x(seed: int) -> None:
    """(j, i) instead of (i, j) with the same edge: x -> -x; with limits (-u, -l) the energy is the same
    and the gradient and Hessian are those of (i, j) with the two 12-DOF blocks swapped."""
    sc = scene(seed)
    swapped = replace(sc, batches=[replace(b, body_ids=b.body_ids[:, ::-1].copy(), lower=-b.upper, upper=-b.lower) for b in sc.batches])
    a, b = evaluate(**sc.core_args()), evaluate(**swapped.core_args())
    perm = np.r_[12:24, 0:12]
    for ra, rb in zip(a.batches, b.batches):
        # Measured over the seeds: x 2.1e-16, E 2.7e-15, gradient 1.7e-15, Hessian 8.1e-16.
        assert relerr(rb.x, -ra.x, floor=1.0) <= 1e-14
        assert relerr(rb.energy, ra.energy) <= 1e-12
        assert relerr(rb.gradient, ra.gradient[:, perm]) <= 1e-12
        assert relerr(rb.hessian, ra.hessian[:, perm][:, :, perm]) <= 1e-12


# ---------------------------------------------------------------- invariance under a rigid motion


@pytest.mark.parametrize("seed", SEEDS)
def test_rigid_motion_of_the_whole_scene(seed: int) -> None:
    """x and E are invariant; gradients map as T g and Hessians as T H T^T per body (T = dof_transform(R)).

    The revolute frame (b, n) is not equivariant (its test vector e_x stays put), but cos and sin are
    invariant under any turn of (b, n) about t, so x is still invariant.
    """
    rng = np.random.default_rng(70_000 + seed)
    sc = scene(seed)
    R, d = random_rotation(rng), rng.uniform(-5.0, 5.0, size=3)
    T2 = np.kron(np.eye(2), dof_transform(R))
    for mode in ("exact", "psd"):
        a = evaluate(**sc.core_args(hessian_mode=mode))
        b = evaluate(**sc.moved(R, d).core_args(hessian_mode=mode))
        # Measured over the seeds: total 2.3e-14, x 1.8e-15, E 2.4e-14, gradient 1.6e-14, Hessian 8.8e-15.
        assert relerr(b.total_energy, a.total_energy) <= 1e-12
        for ra, rb in zip(a.batches, b.batches):
            assert relerr(rb.x, ra.x, floor=1.0) <= 1e-13
            assert relerr(rb.energy, ra.energy) <= 1e-12
            assert relerr(rb.gradient, np.einsum("ab,nb->na", T2, ra.gradient)) <= 1e-12
            assert relerr(rb.hessian, T2 @ ra.hessian @ T2.T) <= 1e-12


# ---------------------------------------------------------------- sign conventions

AXES = {
    "e_x": E_X,
    "-e_x": -E_X,
    "e_y": np.array([0.0, 1.0, 0.0]),
    "e_z": np.array([0.0, 0.0, 1.0]),
    "switch-": np.array([0.9 - 1e-9, np.sqrt(1 - (0.9 - 1e-9) ** 2), 0.0]),
    "switch+": np.array([0.9 + 1e-9, 0.0, np.sqrt(1 - (0.9 + 1e-9) ** 2)]),
    "random": unit(np.array([0.3, -1.2, 0.7])),
}


@pytest.mark.parametrize("phi", [-3.1, -2.0, -0.4, 0.25, 1.0, 2.5, 3.1, 3.6, -4.5, 5.5])
@pytest.mark.parametrize("axis", list(AXES))
def test_turning_j_by_phi_about_t_gives_x_phi(axis: str, phi: float) -> None:
    """Body j turned by +phi about +t relative to i (half of it at q_prev, so |phi| > pi is reachable)."""
    rng = np.random.default_rng(abs(int(phi * 1000)) + 7 * len(axis))
    sc = axis_pair_scene(rng, 670, AXES[axis], phi / 2, phi)
    x = evaluate(**sc.core_args(outputs=("energy",))).batches[0].x[0]
    assert abs(x - phi) <= 1e-14 * max(1.0, abs(phi))  # measured 2.2e-16


@pytest.mark.parametrize("d", [-2.0, -0.3, 1e-3, 0.5, 4.0])
@pytest.mark.parametrize("axis", list(AXES))
def test_sliding_j_by_d_along_t_gives_x_d(axis: str, d: float) -> None:
    rng = np.random.default_rng(abs(int(d * 1000)) + 7 * len(axis))
    sc = axis_pair_scene(rng, 669, AXES[axis], d / 3, d)
    x = evaluate(**sc.core_args(outputs=("energy",))).batches[0].x[0]
    assert abs(x - d) <= 1e-14 * max(1.0, abs(d))  # measured 6.7e-16


@pytest.mark.parametrize("uid", [670, 669])
@pytest.mark.parametrize("seed", range(6))
def test_sign_survives_affine_bodies(uid: int, seed: int) -> None:
    """With strained bodies x is no longer exactly the motion, but it keeps its sign; the penalty
    then pushes back: past the upper limit the energy decreases when j moves back by -motion."""
    rng = np.random.default_rng(80_000 + seed)
    motion = rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 1.5)
    t = random_unit(rng)
    sc = axis_pair_scene(rng, uid, t, 0.0, motion, strain=0.2, common_rotation=False)  # t stays the world axis
    x = evaluate(**sc.core_args(outputs=("energy",))).batches[0].x[0]
    assert np.sign(x) == np.sign(motion)
    # Limits [-|x|/2, |x|/2]: the gradient along "turn / slide j further" is positive.
    half = abs(x) / 2
    sc = replace(sc, batches=[replace(sc.batches[0], lower=np.array([-half]), upper=np.array([half]), strength=np.array([10.0]))])
    g = evaluate(**sc.core_args(outputs=("gradient",))).batches[0].gradient[0]
    p_j, A_j = sc.q[1, :3], sc.q[1, 3:].reshape(3, 3)
    if uid == 670:
        K = np.cross(t, np.eye(3)).T  # [t]_x: column k is t x e_k, the rate of a turn about t
        dq_j = np.r_[np.cross(t, p_j), (K @ A_j).ravel()] * np.sign(motion)
    else:
        dq_j = np.r_[t, np.zeros(9)] * np.sign(motion)
    assert g[12:] @ dq_j > 0


# ---------------------------------------------------------------- a collapsed frame is an error


def test_collapsed_revolute_frame_is_an_input_error_naming_the_joint() -> None:
    """Body j flipped by pi about an axis normal to t: cos = sin = 0 exactly, x has no derivatives."""
    eye = np.r_[np.zeros(3), np.eye(3).ravel()]
    flip = np.r_[np.zeros(3), rotation_about(E_X, np.pi).round().ravel()]  # diag(1, -1, -1), exact
    q_ref = np.stack([eye, eye, eye])
    q = np.stack([eye, eye, flip])
    edges = np.array([[[0, 0, 0], [0, 0, 1.0]]] * 2)
    sc = Scene(q, q_ref.copy(), q_ref, [Batch(670, np.array([[0, 1], [0, 2]]), edges, np.array([-1.0] * 2), np.array([1.0] * 2), np.array([1.0] * 2))])
    with pytest.raises(InputError) as err:
        evaluate(**sc.core_args())
    assert [f.loc for f in err.value.faults] == [("batches", 0, "body_ids", 1)]


# ---------------------------------------------------------------- threads


def _same(a: Evaluation, b: Evaluation) -> None:
    assert a.total_energy == b.total_energy
    for p, q in zip(a.batches, b.batches, strict=True):
        for name in ("index", "x", "energy", "gradient", "hessian"):
            np.testing.assert_array_equal(getattr(p, name), getattr(q, name))


@pytest.mark.parametrize("mode", ["exact", "psd"])
@pytest.mark.parametrize("seed", range(4))
def test_threads_give_bitwise_the_same_answer(seed: int, mode: str) -> None:
    """threads=2: polar factors in halves and the batches side by side; one batch: its derivative chunks."""
    sc = scene(seed)
    _same(evaluate(**sc.core_args(hessian_mode=mode)), evaluate(**sc.core_args(hessian_mode=mode), threads=2))
    one = replace(sc, batches=sc.batches[:1])
    _same(evaluate(**one.core_args(hessian_mode=mode)), evaluate(**one.core_args(hessian_mode=mode), threads=3))


@pytest.mark.parametrize("active_only", [False, True])
def test_threads_over_derivative_chunks(active_only: bool) -> None:
    """One batch of ~8300 active joints: its derivative chunks run on two threads into the same output."""
    sc = scene(3)
    b = sc.batches[0]
    x = sc.x()[0]
    reps = 8300 // b.lower.shape[0] + 1
    tile = lambda a: np.concatenate([a] * reps)  # noqa: E731
    big = replace(b, body_ids=tile(b.body_ids), edges=tile(b.edges), lower=tile(x - 2.0), upper=tile(x - 1.0), strength=tile(b.strength))
    sc = replace(sc, batches=[big])
    _same(evaluate(**sc.core_args(active_only=active_only)), evaluate(**sc.core_args(active_only=active_only), threads=2))


def test_threads_keep_the_callers_error_state() -> None:
    """An overflow on a worker thread is an InputError naming the joint, under the caller's np.errstate
    (no RuntimeWarning escapes from the workers). Joint 0 is 1e-10 above a range 1e-10 wide at strength 1e300:
    E ~ 1e300, E' ~ 3e310 and the gradient ~ 1e310, beyond float64 (at 1e308 and a degenerate range a gap of 1,
    as before, the gradient is 1.3e308 and the Hessian 1.4e308: answered since E' is formed scaled)."""
    import warnings

    sc = scene(4)
    b = sc.batches[0]
    s = b.strength.copy()
    s[0] = 1e300
    lo, up = b.lower.copy(), b.upper.copy()
    x = sc.x()[0]
    lo[0], up[0] = x[0] - 2e-10, x[0] - 1e-10
    sc = replace(sc, batches=[replace(b, lower=lo, upper=up, strength=s), *sc.batches[1:]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError) as err:
            evaluate(**sc.core_args(), threads=2)
    assert err.value.faults[0].loc == ("batches", 0, "strength", 0)


@pytest.mark.parametrize("mode", ["exact", "psd"])
def test_blocks_and_chunks_change_no_bit(monkeypatch: pytest.MonkeyPatch, mode: str) -> None:
    """The Hessian's blocks (factors and GEMMs per block, scalars per call) and the derivative chunks
    (in place, or scattered through scratch rows) are a matter of cache: tiny ones, with partial last
    blocks and chunks, give bitwise the default's answer, every joint active and some."""
    import importlib

    assembly_module = importlib.import_module("jointlimits.service.core.assembly")
    evaluate_module = importlib.import_module("jointlimits.service.core.evaluate")  # the package's `evaluate` is the function

    sc = scene(5)
    tile = lambda a: np.concatenate([a] * 13)  # noqa: E731  (39 joints per batch)
    sc = replace(sc, batches=[replace(b, body_ids=tile(b.body_ids), edges=tile(b.edges), lower=tile(b.lower),
                                      upper=tile(b.upper), strength=tile(b.strength)) for b in sc.batches])
    x = sc.x()
    for fraction in (1.0, 0.5):
        batches = []
        for b, xb in zip(sc.batches, x):
            lo, up = b.lower.copy(), b.upper.copy()
            out = np.arange(xb.shape[0]) < fraction * xb.shape[0]
            lo[out], up[out] = xb[out] + 1.0, xb[out] + 2.0
            batches.append(replace(b, lower=lo, upper=up))
        args = replace(sc, batches=batches).core_args(hessian_mode=mode)
        want = evaluate(**args)
        assert sum(int(np.count_nonzero(b.gradient.any(axis=1))) for b in want.batches) >= 39  # several blocks and chunks
        with monkeypatch.context() as m:
            m.setattr(assembly_module, "BLOCK", 3)
            m.setattr(evaluate_module, "CHUNK", 7)
            m.setattr(evaluate_module, "SCATTER_CHUNK", 5)
            _same(want, evaluate(**args))
            _same(want, evaluate(**args, threads=2))
