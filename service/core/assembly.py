"""Chain rule from the frame quantities F to the 24 DOFs of a joint.

Each F_k depends on its body's DOFs only through `alpha_k p + A v_k`, so
`dF_k / dq` is `I_3 (x) w_k` with `w_k = [alpha_k, v_k]` (4,) once the body's
DOFs are ordered `(r, m)`: row r of `[p | A]` (3 x 4). `J` is never formed.
`PERM` maps the contract's DOF order `[p, A row 0, A row 1, A row 2]` of
bodies i, j to that `(body, r, m)` order.
"""

from __future__ import annotations

import numpy as np

from service.core.constitution import Array


def _perm() -> np.ndarray:
    perm = []
    for body in range(2):
        perm += [body * 12 + r * 4 for r in range(3)]  # p[r]      -> (r, m=0)
        perm += [body * 12 + r * 4 + 1 + c for r in range(3) for c in range(3)]  # A[r, c] -> (r, 1 + c)
    return np.array(perm)


PERM = _perm()


def weights(alpha: Array, v: Array) -> Array:
    """`w` (N, 2, 2, 4): `[alpha_k, v_k]` per (body, block within body)."""
    n = v.shape[0]
    w = np.empty((n, 4, 4))
    w[:, :, 0] = alpha
    w[:, :, 1:] = v
    return w.reshape(n, 2, 2, 4)


def gradient(w: Array, dF: Array) -> Array:
    """`dX/dq` (N, 24) from `dX/dF` (N, 4, 3) for any scalar X."""
    n = dF.shape[0]
    G = np.einsum("nbkr,nbkm->nbrm", dF.reshape(n, 2, 2, 3), w)  # (N, 2, 3, 4)
    return G.reshape(n, 24)[:, PERM]


def hessian(w: Array, M: Array) -> Array:
    """`J^T M J` (N, 24, 24) from a second derivative `M` (N, 4, 3, 4, 3) in F."""
    n = M.shape[0]
    H = np.einsum(
        "nbkm,nbkrcls,nclo->nbrmcso", w, M.reshape(n, 2, 2, 3, 2, 2, 3), w, optimize=True
    ).reshape(n, 24, 24)
    H = H[:, PERM[:, None], PERM[None, :]]
    # Bitwise symmetric: a solver may read either triangle.
    H += H.transpose(0, 2, 1)
    H *= 0.5
    return H


def psd_projection(M: Array) -> Array:
    """Each symmetric (12 x 12) `M` (N, 4, 3, 4, 3) with negative eigenvalues clamped to 0."""
    n = M.shape[0]
    lam, V = np.linalg.eigh(M.reshape(n, 12, 12))
    P = np.einsum("nij,nj,nkj->nik", V, np.maximum(lam, 0.0), V)
    return P.reshape(n, 4, 3, 4, 3)
