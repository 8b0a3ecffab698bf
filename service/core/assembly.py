"""Chain rule from the frame quantities F to the 24 DOFs of a joint, written in the contract's order.

Each F_k depends on its body's DOFs only through `alpha_k p + A v_k`, so
`dF_k / dq` is `I_3 (x) w_k` with `w_k = [alpha_k, v_k]` (4,): row r of F_k sees
`p_r` (weight alpha_k) and row r of A (weights v_k). `J` is never formed.

The Hessian `E'' g g^T + J^T (E' d2x/dF2) J` is assembled from the structured
curvature (`constitution.Curvature`) in two parts, each bitwise symmetric by
construction, straight into the output in DOF order:

- low rank: `Y^T S Y` with `Y = U J` (k x 24) and `S = E' C + E'' t t^T` (k x k): one
  small GEMM per joint, then averaged with its transpose (for k = 1, `s (y_i y_j)`);
- Kronecker: `J^T (K (x) I_3) J` touches only the entries that share a row r of
  `[p | A]`: per r an 8 x 8 (or, with no points, 6 x 6) block `W = w^T K w`.

A revolute joint has no points (alpha = 0): its translation rows and columns
are never written beyond the zeros of the low-rank part.
"""

from __future__ import annotations

import numpy as np

from service.core.constitution import Array, Curvature


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
    Y = gradient(alpha, v, basis)  # (N, k, 24)
    if Y.shape[1] == 1:
        # s (y_i y_j) == s (y_j y_i): bitwise symmetric as it stands.
        np.multiply(Y[:, 0, :, None], Y[:, 0, None, :], out=out)
        out *= S[:, 0, 0, None, None]
    else:
        np.matmul(Y.transpose(0, 2, 1), S @ Y, out=out)  # one small GEMM per joint: k passes fused into one
        scratch = np.empty_like(out)
        np.copyto(scratch, out.transpose(0, 2, 1))
        out += scratch
        out *= 0.5  # (H + H^T) / 2: bitwise symmetric whatever order the GEMM summed in
    # Kronecker part: W[b, m, b', m'] = sum w[b,k,m] (E' K)[b,k,b',l] w[b',l,m'].
    m0 = 0 if alpha.any() else 1
    w = np.empty((n, 2, 2, 4), dtype=v.dtype)  # (joint, body, k, m)
    w[..., 0] = alpha.reshape(2, 2)
    w[..., 1:] = v.reshape(n, 2, 2, 3)
    w = w[..., m0:]
    K = (dE[:, None, None] * curvature.kron).reshape(n, 2, 2, 2, 2)  # (joint, body, k, body', l)
    Kw = (K[..., None] * w[:, None, None]).sum(axis=4)  # sum over l: (joint, body, k, body', m')
    W = (w[:, :, :, :, None, None] * Kw[:, :, :, None]).sum(axis=2)  # sum over k: (joint, body, m, body', m')
    W += W.transpose(0, 3, 4, 1, 2)
    W *= 0.5  # bitwise symmetric before it is added to both triangles
    # Each row r of [p | A] gets the same W: basic-slice views of `out`, no fancy indexing.
    H = out.reshape(n, 2, 12, 2, 12)
    A = W[:, :, -3:, :, -3:]
    for r in range(3):
        a = slice(3 + 3 * r, 6 + 3 * r)
        H[:, :, a, :, a] += A
        if m0 == 0:
            H[:, :, r, :, a] += W[:, :, 0, :, 1:]
            H[:, :, a, :, r] += W[:, :, 1:, :, 0]
            H[:, :, r, :, r] += W[:, :, 0, :, 0]
    return out


def psd_projection(M: Array) -> Array:
    """Each symmetric (12 x 12) `M` (N, 12, 12) with negative eigenvalues clamped to 0, as a Curvature's parts.

    Returns the eigen-factors `V^T` (N, 12, 4, 3) and clamped eigenvalues (N, 12).
    """
    n = M.shape[0]
    lam, V = np.linalg.eigh(M)
    return V.transpose(0, 2, 1).reshape(n, 12, 4, 3), np.maximum(lam, 0.0)
