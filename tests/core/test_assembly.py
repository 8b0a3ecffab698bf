"""The chain rule from F to DOFs (`jointlimits.service.core.assembly`) against a dense, independent one.

`J` (12 x 24 per joint) is formed explicitly here and `J^T M J` taken with einsum, `M` the dense
12 x 12 `E'' dx dx^T + E' d2x/dF2`; the core never forms either. Checked: the signed-factor
Hessian matches to ~1e-14 normwise, is bitwise symmetric (one GEMM, no symmetrising pass),
and `J^T dx` comes out as the gradient; for both joints, exact and PSD curvatures, random and
widely scaled inputs.
"""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.service.core import assembly
from jointlimits.service.core.prismatic import PRISMATIC
from jointlimits.service.core.revolute import REVOLUTE

TOL = 1e-13  # a few roundings per entry, relative to the largest entry of the joint's Hessian


def dense_J(alpha: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 12, 24): d F[k, r] / d q, q = [p_i, A_i rows, p_j, A_j rows]."""
    n = v.shape[0]
    J = np.zeros((n, 4, 3, 2, 12))
    for k in range(4):
        body = k // 2
        for r in range(3):
            J[:, k, r, body, r] = alpha[k]
            J[:, k, r, body, 3 + 3 * r : 6 + 3 * r] = v[:, k]
    return J.reshape(n, 12, 24)


def inputs(c, n: int, seed: int, spread: float = 2.0):
    rng = np.random.default_rng(seed)
    scale = 10.0 ** rng.uniform(-spread, spread, size=(n, 1, 1))
    F = rng.normal(size=(n, 4, 3)) * scale
    v = rng.normal(size=(n, 4, 3)) * 10.0 ** rng.uniform(-spread, spread, size=(n, 1, 1))
    dE = rng.choice([-1.0, 1.0], size=n) * 10.0 ** rng.uniform(-3, 3, size=n)
    d2E = 10.0 ** rng.uniform(-3, 3, size=n)
    dx, curvature = c.derivatives(F, second=True)
    return v, dx, curvature, dE, d2E


@pytest.mark.parametrize("c", [REVOLUTE, PRISMATIC], ids=["revolute", "prismatic"])
@pytest.mark.parametrize("psd", [False, True], ids=["exact", "psd"])
@pytest.mark.parametrize("seed", range(3))
def test_factors_match_the_dense_chain_rule(c, psd: bool, seed: int):
    n = 700
    v, dx, curvature, dE, d2E = inputs(c, n, seed)
    J = dense_J(c.facts.alpha, v)
    dxv = dx.reshape(n, 12)
    if psd:
        curvature = c.projected_curvature(dE, curvature)
        M = curvature.dense()
        dE_used = np.ones(n)
    else:
        M = dE[:, None, None] * curvature.dense()
        dE_used = dE
    M = M + d2E[:, None, None] * dxv[:, :, None] * dxv[:, None, :]
    want = np.einsum("nai,nab,nbj->nij", J, M, J)
    out = np.empty((n, 24, 24))
    Jdx, finite = assembly.hessian(c.facts.alpha, v, curvature, dE_used, d2E, out, dx=dx)
    assert finite
    assert np.array_equal(out, out.transpose(0, 2, 1))  # bitwise
    err = np.abs(out - want).max(axis=(1, 2)) / np.abs(want).max(axis=(1, 2))
    assert err.max() <= TOL, (err.max(), int(err.argmax()))
    g_want = np.einsum("nai,na->ni", J, dxv)
    g_err = np.abs(Jdx - g_want).max(axis=1) / np.abs(g_want).max(axis=1)
    assert g_err.max() <= TOL
    if c is REVOLUTE:  # no points: the translation rows and columns are exact zeros
        H = out.reshape(n, 2, 12, 2, 12)
        assert not H[:, :, :3].any() and not H[:, :, :, :, :3].any()


@pytest.mark.parametrize("psd", [False, True], ids=["exact", "psd"])
def test_prismatic_anchor_far_in_body_units(psd: bool):
    """A prismatic anchor far from its body's origin in body units (`A = s R` with s = 1e-6 .. 1e-150, so
    |c_k| ~ 1/s and |T_k| ~ s): the Kronecker part pairs c_k ~ 1/s with t_k ~ 1, and the gradient stays O(1).
    As a difference of squares of (D +- S)/2 it cancelled to ~u/s of the Hessian's norm (1e-10 at s = 1e-6,
    1e+134 at 1e-150, with `finite` still True: a silent wrong answer). Balanced factors lose nothing."""
    rng = np.random.default_rng(8)
    n = 200
    s = 10.0 ** rng.uniform(-150, 0, size=(n, 1))
    F = rng.normal(size=(n, 4, 3))
    F[:, 1::2] *= s[:, :, None]  # T_k = A t_k
    dx, curvature = PRISMATIC.derivatives(F, True)
    v = rng.normal(size=(n, 4, 3))
    v[:, 0::2] /= s[:, :, None]  # c_k = A_ref^-1 (p0 - p_ref)
    dE = rng.choice([-1.0, 1.0], size=n) * 10.0 ** rng.uniform(-3, 3, size=n)
    d2E = 10.0 ** rng.uniform(-3, 3, size=n)
    J = dense_J(PRISMATIC.facts.alpha, v)
    dxv = dx.reshape(n, 12)
    if psd:
        curvature = PRISMATIC.projected_curvature(dE, curvature)
        M, dE = curvature.dense(), np.ones(n)
    else:
        M = dE[:, None, None] * curvature.dense()
    want = np.einsum("nai,nab,nbj->nij", J, M + d2E[:, None, None] * dxv[:, :, None] * dxv[:, None, :], J)
    out = np.empty((n, 24, 24))
    _, finite = assembly.hessian(PRISMATIC.facts.alpha, v, curvature, dE, d2E, out, dx=dx)
    assert finite and np.array_equal(out, out.transpose(0, 2, 1))
    err = np.abs(out - want).max(axis=(1, 2)) / np.abs(want).max(axis=(1, 2))
    assert err.max() <= TOL, (err.max(), float(s[int(err.argmax()), 0]))


def test_symmetric_at_extreme_magnitudes():
    """Joints whose entries span ~1e-100 .. 1e100 still give a bitwise symmetric product."""
    rng = np.random.default_rng(4)
    n = 300
    for c in (REVOLUTE, PRISMATIC):
        v, dx, curvature, dE, d2E = inputs(c, n, 4)
        v = v * 10.0 ** rng.uniform(-25, 25, size=(n, 4, 1))  # blocks of one joint at very different scales
        out = np.empty((n, 24, 24))
        assembly.hessian(c.facts.alpha, v, curvature, dE * 10.0 ** rng.uniform(-40, 40, size=n), d2E, out)
        assert np.isfinite(out).all()
        assert np.array_equal(out, out.transpose(0, 2, 1))


def test_gradient_matches_the_dense_chain_rule():
    rng = np.random.default_rng(5)
    for c in (REVOLUTE, PRISMATIC):
        v = rng.normal(size=(50, 4, 3))
        dF = rng.normal(size=(50, 3, 4, 3))  # a leading axis of several vectors per joint
        want = np.einsum("nai,nka->nki", dense_J(c.facts.alpha, v), dF.reshape(50, 3, 12))
        np.testing.assert_allclose(assembly.chain(c.facts.alpha, v, dF), want, rtol=0, atol=1e-14 * np.abs(want).max())


def test_finite_flag_is_false_when_products_may_overflow():
    """Factors above sqrt(max / 64) may overflow in the product: the flag sends the caller to check `out`."""
    v, dx, curvature, dE, d2E = inputs(PRISMATIC, 20, 6)
    out = np.empty((20, 24, 24))
    with np.errstate(all="ignore"):  # the overflow this test provokes (the public calls set this state)
        _, finite = assembly.hessian(PRISMATIC.facts.alpha, v * 1e160, curvature, dE, d2E, out)
    assert not finite and not np.isfinite(out).all()
    _, finite = assembly.hessian(PRISMATIC.facts.alpha, v, curvature, dE, d2E, out)
    assert finite and np.isfinite(out).all()


def test_finite_bound_follows_the_dtype():
    assert assembly.finite_factor(np.float64) ** 2 * assembly.MAX_FACTORS <= np.finfo(np.float64).max
    assert 1e18 < assembly.finite_factor(np.float32) < 1e19


def test_finite_flag_of_the_revolute_route():
    """Without points the Kronecker blocks are added after the GEMM: their size enters the flag too."""
    v, dx, curvature, dE, d2E = inputs(REVOLUTE, 20, 7)
    out = np.empty((20, 24, 24))
    with np.errstate(all="ignore"):  # the overflow this test provokes
        _, finite = assembly.hessian(REVOLUTE.facts.alpha, v * 1e160, curvature, dE, d2E, out)
    assert not finite and not np.isfinite(out).all()
    _, finite = assembly.hessian(REVOLUTE.facts.alpha, v, curvature, dE, d2E, out)
    assert finite and np.isfinite(out).all()


@pytest.mark.parametrize("c", [REVOLUTE, PRISMATIC], ids=["revolute", "prismatic"])
def test_component_major_inputs_give_the_same_bits(c):
    """The core hands the assembly component-major chunks, the tests C-order arrays: same numbers."""
    from jointlimits.service.core.kinematics import component_major

    n = 300
    v, dx, curvature, dE, d2E = inputs(c, n, 8)
    F = np.random.default_rng(8).normal(size=(n, 4, 3))
    dx, curvature = c.derivatives(F, second=True)
    Fc = component_major(n, (4, 3))
    Fc[...] = F
    vc = component_major(n, (4, 3))
    vc[...] = v
    dxc, curvature_c = c.derivatives(Fc, second=True)
    a, b = np.empty((n, 24, 24)), np.empty((n, 24, 24))
    ga, _ = assembly.hessian(c.facts.alpha, v, curvature, dE, d2E, a, dx=dx)
    gb, _ = assembly.hessian(c.facts.alpha, vc, curvature_c, dE, d2E, b, dx=dxc)
    assert np.array_equal(a, b) and np.array_equal(ga, gb)


@pytest.mark.parametrize("mode", ["exact", "psd"])
@pytest.mark.parametrize("outputs", [("energy", "gradient"), ("energy", "gradient", "hessian")], ids=["EG", "EGH"])
def test_derivatives_carry_no_negative_zero(mode: str, outputs: tuple[str, ...]):
    """A negative E' times a zero entry (a revolute joint's translation) would answer -0.0; the answers
    (JSON text included) show +0.0 there, whatever the sign of E'."""
    from bench.scenes import make_scene
    from jointlimits.service.core import evaluate

    ev = evaluate(*make_scene(600, 1.0, seed=5), outputs=outputs, hessian_mode=mode)
    for b in ev.batches:
        for a in (b.gradient, b.hessian):
            if a is not None:
                assert (a == 0).any() or b.constitution_uid != 670  # the revolute rows have zeros to look at
                assert not np.signbit(a[a == 0]).any()
