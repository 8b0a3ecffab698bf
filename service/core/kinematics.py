"""Affine-body kinematics shared by all constitutions.

A body's 12 DOFs are `q = [p (3), A row 0, A row 1, A row 2]`. Every joint
exposes four frame quantities `F_k` (k = 0, 1 on body i; k = 2, 3 on body j),
each an affine function of its body's DOFs:

    F_k = alpha_k (p - o) + A v_k,

with `v_k` a body-local vector fixed at `q_ref` and `alpha_k` 1 for points
(that follow translation) and 0 for directions. `o` is a per-joint origin
(body i's position in the same state): every joint coordinate is invariant
under a translation of the scene, and subtracting `o` first keeps a scene far
from the origin from losing digits to its translation.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# Which body each frame quantity belongs to (0: body i, 1: body j).
BLOCK_BODY = np.array([0, 0, 1, 1])

SINGULAR_RATIO = 1e-12
"""`A_ref` is singular when its smallest singular value is below this times its largest."""

_NEWTON_RATIO = 1e-4
"""Below this estimated conditioning ratio the polar factor comes from an SVD, not Newton's iteration."""
_NEWTON_STEPS = 12
_NEWTON_TOL = 1e-13


def split(q: Array) -> tuple[Array, Array]:
    """`q` (..., 12) -> `p` (..., 3), `A` (..., 3, 3) as views."""
    return q[..., :3], q[..., 3:].reshape(*q.shape[:-1], 3, 3)


def _cofactors_t(a: Array) -> tuple[Array, Array]:
    """Cofactors and determinant in component-major layout: `a` (9, M) -> `C` (9, M), det (M,).

    Row i of the cofactor matrix is row (i+1) x row (i+2); contiguous (M,) components
    make every product a SIMD pass (strided views of (M, 3, 3) are 10x slower).
    """
    C = np.empty_like(a)
    for r in range(3):
        u0, u1, u2 = a[3 * ((r + 1) % 3) : 3 * ((r + 1) % 3) + 3]
        w0, w1, w2 = a[3 * ((r + 2) % 3) : 3 * ((r + 2) % 3) + 3]
        C[3 * r] = u1 * w2 - u2 * w1
        C[3 * r + 1] = u2 * w0 - u0 * w2
        C[3 * r + 2] = u0 * w1 - u1 * w0
    return C, a[0] * C[0] + a[1] * C[1] + a[2] * C[2]


def solve3(A: Array, b: Array) -> Array:
    """`A^-1 b` for `A` (M, 3, 3), `b` (M, 3) by cofactors (`A^-1 = C^T / det`): 3 x 3 LAPACK calls cost more."""
    m = A.shape[0]
    C, det = _cofactors_t(np.ascontiguousarray(A.reshape(m, 9).T))
    bt = b.T
    x = np.empty((3, m), dtype=A.dtype)
    for c in range(3):
        x[c] = (C[c] * bt[0] + C[3 + c] * bt[1] + C[6 + c] * bt[2]) / det
    return x.T


def polar_rotation(A: Array) -> tuple[Array, Array]:
    """Orthogonal polar factor of each `A` (M, 3, 3) and its conditioning ratio `s_min / s_max` (M,).

    Why not an SVD for every body: it was 95% of an energy-only evaluation. Newton's
    iteration `X <- (g X + X^-T / g) / 2` (Frobenius scaling `g`), with cofactor inverses
    (`X^-T = C / det`), converges quadratically to the same factor; bodies it is not good
    for (estimated ratio below 1e-4, or not converged in 12 steps) take the SVD. The
    returned ratio is exact from the SVD where it decides anything; elsewhere it is the
    bound `1 / (|A|_F |A^-1|_F)`, which lies in `[ratio / 3, ratio]`, far above `SINGULAR_RATIO`.
    """
    m = A.shape[0]
    a = np.ascontiguousarray(A.reshape(m, 9).T)  # (9, M)
    ratio = np.zeros(m)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        C, det = _cofactors_t(a)
        nA = np.sqrt(np.einsum("im,im->m", a, a))
        nC = np.sqrt(np.einsum("im,im->m", C, C))
        est = np.abs(det) / (nA * nC)
    good = est >= _NEWTON_RATIO
    newton = np.flatnonzero(good)
    ratio[newton] = est[newton]
    if newton.shape[0] < m:
        a, C, det, nA, nC = a[:, newton], C[:, newton], det[newton], nA[newton], nC[newton]
    X, done = a.copy() if newton.shape[0] == m else a, np.zeros(newton.shape[0], dtype=bool)
    for _ in range(_NEWTON_STEPS):
        g = np.sqrt(nC / (np.abs(det) * nA))  # sqrt(|X^-1|_F / |X|_F)
        X_new = X * (0.5 * g)
        X_new += C * (0.5 / (g * det))
        X -= X_new
        done = np.abs(X, out=X).max(axis=0) <= _NEWTON_TOL
        X = X_new
        if done.all():
            break
        C, det = _cofactors_t(X)
        nA = np.sqrt(np.einsum("im,im->m", X, X))
        nC = np.sqrt(np.einsum("im,im->m", C, C))
    if newton.shape[0] == m:
        R = np.ascontiguousarray(X.T).reshape(m, 3, 3)
    else:
        R = np.empty_like(A)
        R[newton] = X.T.reshape(-1, 3, 3)
    svd = np.concatenate([np.flatnonzero(~good), newton[~done]])
    if svd.shape[0]:
        U, s, Vt = np.linalg.svd(A[svd])
        R[svd] = U @ Vt
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio[svd] = np.nan_to_num(s[:, -1] / s[:, 0], nan=0.0)
    return R, ratio


def gather_pairs(q: Array, ids: NDArray[np.int64], dtype: type = np.float64) -> tuple[Array, Array]:
    """`p` (N, 2, 3) and `A` (N, 2, 3, 3) of each joint's two bodies in state `q` (B, 12)."""
    q2 = np.take(q, ids, axis=0)  # faster than q[ids] for (N, 2) index arrays
    if q2.dtype != dtype:
        q2 = q2.astype(dtype)
    return split(q2)


def frame_quantities(q: Array, ids: NDArray[np.int64], alpha: Array, v: Array, dtype: type = np.float64) -> Array:
    """`F` (N, 4, 3) of joints `ids` (N, 2) whose bodies are in state `q` (B, 12).

    `alpha` (4,) and `v` (N, 4, 3) as in the module docstring. Computed component by
    component on contiguous (N,) rows: NumPy's broadcasting over trailing 3-vectors (or a
    batched 3 x 3 matmul) spends its time in per-row loop overhead, 5x slower.
    """
    n = v.shape[0]
    qT = np.ascontiguousarray(q.T, dtype=dtype)  # (12, B)
    vT = np.ascontiguousarray(v.transpose(1, 2, 0))  # (4, 3, N)
    FT = np.empty((4, 3, n), dtype=dtype)
    tmp = np.empty(n, dtype=dtype)
    for b in range(2):
        body = np.take(qT, ids[:, b], axis=1)  # (12, N)
        for k in (2 * b, 2 * b + 1):
            for r in range(3):
                out = FT[k, r]
                np.multiply(body[3 + 3 * r], vT[k, 0], out=out)
                out += np.multiply(body[4 + 3 * r], vT[k, 1], out=tmp)
                out += np.multiply(body[5 + 3 * r], vT[k, 2], out=tmp)
        if b == 0:
            p_i = body[:3]
        elif alpha.any():
            # Nearby positions are differenced before anything large is added.
            dp = body[:3] - p_i
            for k in (2, 3):
                if alpha[k]:
                    FT[k] += alpha[k] * dp
    return np.ascontiguousarray(FT.transpose(2, 0, 1))


def unit(v: Array) -> Array:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
