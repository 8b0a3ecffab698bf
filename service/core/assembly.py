"""Chain rule from the frame quantities F to the 24 DOFs of a joint, written in the contract's order.

Each F_k depends on its body's DOFs only through `alpha_k p + A v_k`, so
`dF_k / dq` is `I_3 (x) w_k` with `w_k = [alpha_k, v_k]` (4,): row r of F_k sees
`p_r` (weight alpha_k) and row r of A (weights v_k). `J` is never formed.

The Hessian `E'' g g^T + J^T (E' d2x/dF2) J` is assembled from the structured
curvature (`constitution.Curvature`) in two parts, each bitwise symmetric by
construction, straight into the output in DOF order:

- low rank: `J^T U^T S U J` with `S = E' C + E'' t t^T` (k x k, k <= 2) becomes
  `sum_a sign_a z_a z_a^T` from S's closed-form eigenpairs; `sigma z_i z_j` with
  `sigma = +-1` is exactly symmetric;
- Kronecker: `J^T (K (x) I_3) J` touches only the entries that share a row r of
  `[p | A]`: per r an 8 x 8 (or, with no points, 6 x 6) block `W = w^T K w`.

A revolute joint has no points (alpha = 0): its translation rows and columns
are never written beyond the zeros of the low-rank part.
"""

from __future__ import annotations

import numpy as np

from service.core.constitution import Array, Curvature


def _dof_index() -> np.ndarray:
    """(3, 2, 4): contract DOF of (row r, body b, m), m = 0 for p_r, 1 + c for A[r, c]."""
    idx = np.empty((3, 2, 4), dtype=np.intp)
    for r in range(3):
        for b in range(2):
            idx[r, b, 0] = 12 * b + r
            idx[r, b, 1:] = 12 * b + 3 + 3 * r + np.arange(3)
    return idx


DOF = _dof_index()


def gradient(alpha: Array, v: Array, dF: Array) -> Array:
    """`J^T dF`: (N, ..., 24) in DOF order from vectors `dF` (N, ..., 4, 3) in F; `v` (N, 4, 3)."""
    n = dF.shape[0]
    lead = dF.shape[1:-2]
    vb = v.reshape((n,) + (1,) * len(lead) + (2, 2, 1, 3))  # (N, .., body, k, ., c)
    db = dF.reshape(dF.shape[:-2] + (2, 2, 3, 1))  # (N, .., body, k, r, .)
    out = np.empty(dF.shape[:-2] + (2, 12), dtype=dF.dtype)
    A_part = out[..., 3:].reshape(dF.shape[:-2] + (2, 3, 3))
    np.multiply(db[..., 0, :, :], vb[..., 0, :, :], out=A_part)
    A_part += db[..., 1, :, :] * vb[..., 1, :, :]
    if alpha.any():
        a = alpha.reshape(2, 2)  # (body, k)
        out[..., :3] = a[:, 0, None] * db[..., :, 0, :, 0] + a[:, 1, None] * db[..., :, 1, :, 0]
    else:
        out[..., :3] = 0.0
    return out.reshape(dF.shape[:-2] + (24,))


def _eig2(S: Array) -> tuple[Array, Array]:
    """Eigenpairs of symmetric 2 x 2 `S` (N, 2, 2) by one Jacobi rotation: values (N, 2), vectors (N, 2, 2) as rows."""
    a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = (c - a) / (2.0 * b)
        t = np.where(tau >= 0, 1.0, -1.0) / (np.abs(tau) + np.hypot(1.0, tau))
    t = np.where(b == 0, 0.0, t)
    cs = 1.0 / np.sqrt(1.0 + t * t)
    sn = t * cs
    lam = np.stack([a - t * b, c + t * b], axis=1)
    vec = np.stack([np.stack([cs, -sn], axis=1), np.stack([sn, cs], axis=1)], axis=1)
    return lam, vec


def _low_rank_factors(Y: Array, S: Array) -> tuple[Array, Array]:
    """`Y^T S Y` as `sum_a sign_a z_a z_a^T`: `Y` (N, k, 24), `S` (N, k, k) -> signs (N, k), `z` (N, k, 24)."""
    k = Y.shape[1]
    if k == 1:
        lam, vec = S[:, :, 0], np.ones((S.shape[0], 1, 1), dtype=S.dtype)
    elif k == 2:
        lam, vec = _eig2(S)
    elif not np.any(S - S * np.eye(k, dtype=S.dtype)):
        lam, vec = np.diagonal(S, axis1=1, axis2=2), np.broadcast_to(np.eye(k, dtype=S.dtype), S.shape)
    else:
        lam, V = np.linalg.eigh(S)
        vec = V.transpose(0, 2, 1)
    z = np.einsum("nab,nbi->nai", vec * np.sqrt(np.abs(lam))[:, :, None], Y)
    return np.sign(lam), z


def hessian(
    alpha: Array, v: Array, curvature: Curvature, dE: Array, d2E: Array, out: Array, dx: Array | None = None
) -> Array:
    """`E'' g g^T + J^T (E' d2x/dF2) J` (N, 24, 24) into `out`, bitwise symmetric.

    `curvature` is `d2x/dF2` (already times E' when `dE` is None-like ones, as after a
    PSD projection: pass `dE = 1`). `dx` (N, 4, 3) only when `curvature.dx_coef` is None.
    """
    n = v.shape[0]
    # Low rank: S = E' C + E'' t t^T over the basis (plus dx as a factor if outside it).
    basis, S = curvature.basis, dE[:, None, None] * curvature.coef
    if curvature.dx_coef is not None:
        t = curvature.dx_coef
        S = S + d2E[:, None, None] * (t[:, :, None] * t[:, None, :])
    else:
        k = basis.shape[1]
        basis = np.concatenate([basis, dx[:, None]], axis=1)
        S = np.pad(S, ((0, 0), (0, 1), (0, 1)))
        S[:, k, k] = d2E
    sign, z = _low_rank_factors(gradient(alpha, v, basis), S)
    sz = sign[:, :, None] * z  # sign is +-1 or 0: exact
    np.multiply(sz[:, 0, :, None], z[:, 0, None, :], out=out)
    for a in range(1, z.shape[1]):
        out += sz[:, a, :, None] * z[:, a, None, :]
    # Kronecker part: W[b, m, b', m'] = sum w[b,k,m] (E' K)[b,k,b',l] w[b',l,m'].
    m0 = 0 if alpha.any() else 1
    w = np.empty((n, 2, 2, 4), dtype=v.dtype)
    w[..., 0] = alpha.reshape(2, 2)
    w[..., 1:] = v.reshape(n, 2, 2, 3)
    w = w[..., m0:]
    K = (dE[:, None, None] * curvature.kron).reshape(n, 2, 2, 2, 2)
    W = np.einsum("nbkm,nbkcl,nclo->nbmco", w, K, w).reshape(n, 8 - 2 * m0, 8 - 2 * m0)
    W = 0.5 * (W + W.transpose(0, 2, 1))  # bitwise symmetric before it is added twice
    for r in range(3):
        idx = DOF[r, :, m0:].reshape(-1)
        out[:, idx[:, None], idx[None, :]] += W
    return out


def psd_projection(M: Array) -> Array:
    """Each symmetric (12 x 12) `M` (N, 12, 12) with negative eigenvalues clamped to 0, as a Curvature's parts.

    Returns the eigen-factors `V^T` (N, 12, 4, 3) and clamped eigenvalues (N, 12).
    """
    n = M.shape[0]
    lam, V = np.linalg.eigh(M)
    return V.transpose(0, 2, 1).reshape(n, 12, 4, 3), np.maximum(lam, 0.0)
