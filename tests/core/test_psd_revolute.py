"""The revolute joint's closed-form PSD projection (`Revolute.projected_curvature`) against `numpy.linalg.eigh`.

For frames F (N, 4, 3) and penalty slopes E' (N,): the exact `E' d2x/dF2` (12 x 12) is projected by
eigh (negative eigenvalues clamped to 0) and compared with the closed form: its eigenvalues, the
matrix itself (normwise relative), PSD-ness and symmetry; on random frames, frames scaled from
1e-8 to 1e8, and degenerate ones (parallel and antiparallel vectors, zero vectors, identical
frames of the two bodies (a zero-length step), frames of rank 1 and 2).
"""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.service.core import assembly, evaluate
from jointlimits.service.core.constitution import Curvature
from jointlimits.service.core.revolute import REVOLUTE
from tests.scenes import random_scene

# eigh's own backward error is a few eps times ||M||: 1e-13 leaves room for it and for the
# closed form's few roundings, with nothing to spare for a wrong formula (errors O(1)).
TOL = 1e-13


def by_eigh(dE: np.ndarray, curvature: Curvature) -> tuple[np.ndarray, np.ndarray]:
    """The projected matrix (N, 12, 12) and its eigenvalues (N, 12) by the generic route."""
    n = dE.shape[0]
    V, lam = assembly.psd_projection(dE[:, None, None] * curvature.dense())
    V = V.reshape(n, 12, 12)
    return np.einsum("nk,nki,nkj->nij", lam, V, V), np.sort(lam, axis=1)


def closed(F: np.ndarray, dE: np.ndarray) -> np.ndarray:
    _, curvature = REVOLUTE.derivatives(F, second=True)
    return REVOLUTE.projected_curvature(dE, curvature).dense()


def check(F: np.ndarray, dE: np.ndarray) -> None:
    _, curvature = REVOLUTE.derivatives(F, second=True)
    want, lam_want = by_eigh(dE, curvature)
    got = REVOLUTE.projected_curvature(dE, curvature).dense()
    scale = np.abs(want).max(axis=(1, 2))
    assert (scale > 0).all()
    err = np.abs(got - want).max(axis=(1, 2)) / scale
    assert err.max() <= TOL, (err.max(), int(err.argmax()))
    lam_got = np.linalg.eigvalsh(0.5 * (got + got.transpose(0, 2, 1)))
    lam_scale = lam_want[:, -1:]
    np.testing.assert_array_less(np.abs(lam_got - lam_want) / lam_scale, TOL)
    assert (lam_got >= -TOL * lam_scale).all()  # PSD up to rounding
    np.testing.assert_array_less(np.abs(got - got.transpose(0, 2, 1)).max(axis=(1, 2)) / scale, TOL)


def slopes(rng: np.random.Generator, n: int) -> np.ndarray:
    """E' of both signs (above and below the range), over six decades."""
    return rng.choice([-1.0, 1.0], size=n) * 10.0 ** rng.uniform(-3, 3, size=n)


@pytest.mark.parametrize("seed", range(4))
def test_random_frames(seed: int):
    rng = np.random.default_rng(seed)
    n = 500
    check(rng.normal(size=(n, 4, 3)), slopes(rng, n))


@pytest.mark.parametrize("scale", [1e-8, 1e-4, 1.0, 1e4, 1e8])
def test_scaled_frames(scale: float):
    rng = np.random.default_rng(7)
    n = 200
    # Each joint's frame at its own scale around `scale`, and the four vectors at different lengths.
    F = rng.normal(size=(n, 4, 3)) * scale * 10.0 ** rng.uniform(-1, 1, size=(n, 4, 1))
    check(F, slopes(rng, n))


def rigid_frames(rng: np.random.Generator, n: int, turn: np.ndarray) -> np.ndarray:
    """Orthonormal (b, n) per body, body j's turned by `turn` (N,) about t = b x n: the service's frames."""
    Q, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    b, nn = Q[:, :, 0], Q[:, :, 1]
    c, s = np.cos(turn)[:, None], np.sin(turn)[:, None]
    return np.stack([b, nn, c * b + s * nn, c * nn - s * b], axis=1)


def test_rigid_frames_and_zero_turn():
    """The service's own frames: complex-parallel z_i, z_j (rho^2 = r, the reduced case), any turn, zero included."""
    rng = np.random.default_rng(3)
    n = 400
    turn = rng.uniform(-np.pi, np.pi, size=n)
    turn[:50] = 0.0  # zero-length step: the two bodies' frames coincide
    turn[50:60] = np.pi  # antiparallel
    check(rigid_frames(rng, n, turn), slopes(rng, n))


def test_degenerate_frames():
    rng = np.random.default_rng(5)
    n = 60
    cases = []
    v = rng.normal(size=(n, 3))
    w = rng.normal(size=(n, 3))
    # B_i parallel to N_i, body j general.
    cases.append(np.stack([v, 2.0 * v, rng.normal(size=(n, 3)), rng.normal(size=(n, 3))], axis=1))
    # Every vector on one line (rank 1), signs mixed: parallel and antiparallel.
    k = rng.normal(size=(n, 4, 1))
    cases.append(k * v[:, None, :])
    # Every vector in one plane (rank 2).
    a, b = rng.normal(size=(n, 4, 1)), rng.normal(size=(n, 4, 1))
    cases.append(a * v[:, None, :] + b * w[:, None, :])
    # A zero vector on each body (N_i = N_j = 0): r from B_i . B_j alone.
    F = rng.normal(size=(n, 4, 3))
    F[:, 1] = F[:, 3] = 0.0
    cases.append(F)
    # Body j's frame equal to body i's (sin = 0, zero turn) and its negative (a half turn).
    F = rng.normal(size=(n, 4, 3))
    F[:, 2:] = F[:, :2]
    cases.append(F)
    cases.append(np.concatenate([F[:, :2], -F[:, :2]], axis=1))
    # Nearly collapsed: r ~ 1e-6 |F|^2 (B_j, N_j nearly orthogonal to B_i, N_i).
    F = rigid_frames(rng, n, np.zeros(n))
    t = np.cross(F[:, 0], F[:, 1])
    F[:, 2] = t + 1e-6 * F[:, 0]
    F[:, 3] = np.cross(t, F[:, 0]) * 0.0 + 1e-6 * F[:, 1]
    cases.append(F)
    for F in cases:
        _, c = REVOLUTE.derivatives(F, second=True)
        assert np.isfinite(c.kron).all()
        check(F, slopes(rng, n))


def test_zero_slope_gives_zero():
    rng = np.random.default_rng(9)
    F = rng.normal(size=(5, 4, 3))
    assert not closed(F, np.zeros(5)).any()


@pytest.mark.parametrize("seed", range(6))
def test_evaluate_psd_hessian_is_symmetric_and_psd(seed: int):
    """Through the whole chain rule: bitwise symmetric, PSD up to rounding, per revolute joint."""
    sc = random_scene(np.random.default_rng(60_000 + seed), ("above", "below"))
    ev = evaluate(sc.bodies(), [b.joints() for b in sc.batches], hessian_mode="psd")
    for batch in ev.batches:
        H = batch.hessian
        assert np.array_equal(H, H.transpose(0, 2, 1))
        lam = np.linalg.eigvalsh(H)
        top = np.abs(lam).max(axis=1, keepdims=True)
        assert (lam >= -1e-13 * np.maximum(top, 1e-300)).all()
