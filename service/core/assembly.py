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

MAX_FACTORS = 64
"""At most this many factors per joint (14 for the revolute joint): `finite_factor` relies on it."""


def finite_factor(dtype: type) -> float:
    """Below this bound on |X|, the sum of `MAX_FACTORS` products of two factors stays finite in `dtype`."""
    return float(np.sqrt(np.finfo(dtype).max / MAX_FACTORS))


def gradient(alpha: Array, v: Array, dF: Array) -> Array:
    """`J^T dF`: (N, ..., 24) in DOF order from vectors `dF` (N, ..., 4, 3) in F; `v` (N, 4, 3)."""
    n = dF.shape[0]
    lead = dF.shape[:-2]
    vb = v.reshape((n,) + (1,) * (len(lead) - 1) + (2, 2, 3))  # (N, .., body, k, c)
    db = dF.reshape(lead + (2, 2, 3))  # (N, .., body, k, r)
    out = np.empty(lead + (2, 12), dtype=dF.dtype)
    # A[r, c] = sum over the body's two blocks k of dF_k[r] v_k[c]: (r x 2) @ (2 x c) per body.
    np.matmul(db.swapaxes(-1, -2), vb, out=out[..., 3:].reshape(lead + (2, 3, 3)))
    if alpha.any():
        a = alpha.reshape(2, 2)  # (body, k)
        out[..., :3] = a[:, 0, None] * db[..., :, 0, :] + a[:, 1, None] * db[..., :, 1, :]
    else:
        out[..., :3] = 0.0
    return out.reshape(lead + (24,))


def hessian(
    alpha: Array, v: Array, curvature: Curvature, dE: Array, d2E: Array, out: Array, dx: Array | None = None
) -> Array:
    """`E'' g g^T + J^T (E' d2x/dF2) J` (N, 24, 24) into `out`, bitwise symmetric, each entry written once.

    `curvature` is `d2x/dF2` (after a PSD projection it already carries E': pass `dE = 1`). `dx`
    (N, 4, 3) only when `curvature.dx_coef` is None. The Hessian is `X^T diag(s) X` with `X`
    (N, p, 24) signed rank-1 factors (`s` in {-1, 0, 1}): one small GEMM per joint.
    Returns `J^T dx` (N, 24), a by-product of the factors (the gradient over E'), and whether every
    entry of `out` is finite for sure (no check of `out` needed): |X| below `finite_factor`, so no sum of
    products overflows.
    """
    X, sign, Jdx, bound = factors(alpha, v, curvature, dE, d2E, dx)
    # (s_e X_ei) X_ej == (s_e X_ej) X_ei bitwise (s_e is a sign) and a GEMM sums each entry over e
    # in the same order: the product is bitwise symmetric without a symmetrising pass.
    np.matmul((X * sign[:, :, None]).transpose(0, 2, 1), X, out=out)
    return Jdx, bool(bound < finite_factor(X.dtype)) and X.shape[1] <= MAX_FACTORS


def factors(
    alpha: Array, v: Array, curvature: Curvature, dE: Array, d2E: Array, dx: Array | None = None
) -> tuple[Array, Array, Array, float]:
    """Factors `X` (N, p, 24) and signs (N, p) with `X^T diag(sign) X` the Hessian of `hessian`; `J^T dx`
    (N, 24); max |X| (NaN if any entry is NaN).

    Low rank: `S = E' C + E'' t t^T` (or `E'' dx dx^T` beside it) as `sum_e lam_e z_e z_e^T` over
    combinations `z_e` of the chained basis. Kronecker: `E' K = sum_e w_e f_e f_e^T`, so
    `J^T (E' K (x) I_3) J = sum_{e, r} w_e (J^T (f_e (x) e_r)) (J^T (f_e (x) e_r))^T`, and
    `J^T (f (x) e_r)` is nonzero only in row r of `[p | A]` of each body.
    """
    n = v.shape[0]
    dtype = v.dtype
    basis = curvature.basis
    k0 = basis.shape[1]
    if curvature.dx_coef is None:  # E'' dx dx^T beside the basis
        basis = np.concatenate([basis, dx[:, None]], axis=1)
    Y = gradient(alpha, v, basis)  # (N, k, 24): the basis chained to DOFs
    lam, Xl, Jdx = _low_rank(curvature, Y, k0, dE, d2E)
    if curvature.kron_factors is None:  # generic: K's own eigen-decomposition
        w, f = np.linalg.eigh(curvature.kron)
        w, f = dE[:, None] * w, f.transpose(0, 2, 1)
    else:
        w, f = curvature.kron_factors
        w = dE[:, None] * w
    m, k = w.shape[1], lam.shape[1]
    # t[e, body, :] = sum over the body's blocks of f_e[block] [alpha, v][block], times sqrt|w_e|.
    wv = np.empty((n, 2, 2, 4), dtype=dtype)  # (joint, body, block, [alpha, v])
    wv[..., 0] = alpha.reshape(2, 2)
    wv[..., 1:] = v.reshape(n, 2, 2, 3)
    f = np.broadcast_to(f, (n, m, 4)) * np.sqrt(np.abs(w))[:, :, None]
    # Per body one (m x 2) @ (2 x 4) product: (N, body, m, 4), seen as (N, m, body, 4).
    t = np.matmul(f.reshape(n, m, 2, 2).transpose(0, 2, 1, 3), wv).transpose(0, 2, 1, 3)
    X = np.zeros((n, k + 3 * m, 2, 12), dtype=dtype)
    X[:, :k] = Xl.reshape(n, k, 2, 12)
    Xk = X[:, k:].reshape(n, m, 3, 2, 12)  # (joint, e, row r, body, DOF)
    points = bool(alpha.any())
    for r in range(3):
        Xk[:, :, r, :, 3 + 3 * r : 6 + 3 * r] = t[..., 1:]
        if points:
            Xk[:, :, r, :, r] = t[..., 0]
    sign = np.empty((n, k + 3 * m), dtype=dtype)
    np.sign(lam, out=sign[:, :k])
    sign[:, k:].reshape(n, m, 3)[...] = np.sign(w)[:, :, None]
    bound = max(np.abs(Xl).max(initial=0.0), np.abs(t).max(initial=0.0))  # X holds these values and zeros
    return X.reshape(n, k + 3 * m, 24), sign, Jdx, bound


def _low_rank(curvature: Curvature, Y: Array, k0: int, dE: Array, d2E: Array) -> tuple[Array, Array, Array]:
    """`S` over the chained basis `Y` (N, k, 24) (its first `k0` rows the curvature's basis, then dx if
    outside it) as eigenvalues (N, k), factors `sqrt|lam_e| sum_b V_be Y_b` (N, k, 24), and `J^T dx`."""
    n, k = Y.shape[:2]
    if curvature.dx_coef is None:
        Jdx = Y[:, k0]
        if curvature.diagonal:
            lam = np.empty((n, k), dtype=Y.dtype)
            lam[:, :k0] = dE[:, None] * np.diagonal(curvature.coef, axis1=1, axis2=2)
            lam[:, k0] = d2E
            return lam, Y * np.sqrt(np.abs(lam))[:, :, None], Jdx
        S = np.zeros((n, k, k), dtype=Y.dtype)
        S[:, :k0, :k0] = dE[:, None, None] * curvature.coef
        S[:, k0, k0] = d2E
    else:
        t = curvature.dx_coef
        Jdx = t[:, 0, None] * Y[:, 0]
        for b in range(1, k):
            Jdx += t[:, b, None] * Y[:, b]
        if k == 1:
            lam = dE[:, None] * curvature.coef[:, 0] + d2E[:, None] * (t * t)
            return lam, Y * np.sqrt(np.abs(lam))[:, :, None], Jdx
        if k == 2:  # per-joint scalars (N,): a batched 2 x 2 is slower than these few passes
            C = curvature.coef
            p, q, u = (dE * C[:, a, b] + d2E * (t[:, a] * t[:, b]) for a, b in ((0, 0), (0, 1), (1, 1)))
            return _eig2_factors(p, q, u, Y, Jdx)
        S = dE[:, None, None] * curvature.coef + d2E[:, None, None] * (t[:, :, None] * t[:, None, :])
    if k == 2:
        return _eig2_factors(S[:, 0, 0], S[:, 0, 1], S[:, 1, 1], Y, Jdx)
    lam, V = np.linalg.eigh(S)
    V *= np.sqrt(np.abs(lam))[:, None, :]
    return lam, np.matmul(V.transpose(0, 2, 1), Y), Jdx


def _eig2_factors(p: Array, q: Array, u: Array, Y: Array, Jdx: Array) -> tuple[Array, Array, Array]:
    """`[[p, q], [q, u]]` (each (N,)) in closed form: eigenvalues (N, 2), `sqrt|lam_e| (V^T Y)_e` (N, 2, 24)."""
    mean, h = 0.5 * (p + u), np.hypot(0.5 * (p - u), q)
    phi = 0.5 * np.arctan2(q, 0.5 * (p - u))  # rotation taking e_1 to the eigenvector of mean + h
    c, s = np.cos(phi), np.sin(phi)
    lam = np.stack([mean + h, mean - h], axis=1)
    r = np.sqrt(np.abs(lam))
    Xl = np.empty_like(Y)
    # Eigenvectors (c, s) and (-s, c).
    np.multiply((r[:, 0] * c)[:, None], Y[:, 0], out=Xl[:, 0])
    Xl[:, 0] += (r[:, 0] * s)[:, None] * Y[:, 1]
    np.multiply((r[:, 1] * c)[:, None], Y[:, 1], out=Xl[:, 1])
    Xl[:, 1] -= (r[:, 1] * s)[:, None] * Y[:, 0]
    return lam, Xl, Jdx


def psd_projection(M: Array) -> Array:
    """Each symmetric (12 x 12) `M` (N, 12, 12) with negative eigenvalues clamped to 0, as a Curvature's parts.

    Returns the eigen-factors `V^T` (N, 12, 4, 3) and clamped eigenvalues (N, 12).
    """
    n = M.shape[0]
    lam, V = np.linalg.eigh(M)
    return V.transpose(0, 2, 1).reshape(n, 12, 4, 3), np.maximum(lam, 0.0)
