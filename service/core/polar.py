"""Orthogonal polar factors of many 3 x 3 matrices at once, component-major (the joint frames' R_k)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

SINGULAR_RATIO = 1e-12
"""`A_ref` is singular when its smallest singular value is below this times its largest."""

_NEWTON_RATIO = 1e-4  # below this estimated conditioning ratio: an SVD, not Newton's iteration
_SUBSET_FRACTION = 0.5  # `polar_rotation(a, used)` iterates on the used bodies alone below this fraction
_NEWTON_STEPS = 12
_NEWTON_TOL = 1e-8
"""Stop once a step changes no entry by more than this: near the factor, X = U (I + E) steps to
U (I + E^2 / 2 + O(E^3)), so the step just taken left an error of about half its square (< 1e-16)."""
SMALL = 256  # matrices up to which `cofactors` takes its nine entries in whole (9, M) passes (`kinematics.SMALL`)
# Cofactor (3 r + k) = a[_P] a[_Q] - a[_S] a[_T]: row r of the cofactors is row r+1 x row r+2.
_P, _Q, _S, _T = (np.array(i) for i in zip(*(
    (u + (k + 1) % 3, w + (k + 2) % 3, u + (k + 2) % 3, w + (k + 1) % 3)
    for u, w in ((3 * ((r + 1) % 3), 3 * ((r + 2) % 3)) for r in range(3)) for k in range(3)
)))
_PQST = np.concatenate([_P, _Q, _S, _T])  # the four at once: one gather (`take`: faster than fancy indexing)


def cofactors(a: Array, out: Array | None = None) -> tuple[Array, Array]:
    """Cofactors and determinant, component-major: `a` (9, M) -> `C` (9, M) (into `out` if given), det (M,).
    Row i of the cofactor matrix is row (i+1) x row (i+2); contiguous (M,) rows make every product a SIMD pass."""
    if a.shape[1] <= SMALL:  # a few bodies: all nine entries in two passes (the same products, the same order)
        g = a.take(_PQST, axis=0)
        C = np.multiply(g[:9], g[9:18], out=out)
        C -= g[18:27] * g[27:]
        p = a[:3] * C[:3]  # det = a0 C0 + a1 C1 + a2 C2 (below), its products in one pass
        return C, p[0] + p[1] + p[2]
    C = np.empty_like(a) if out is None else out  # a pass per entry, in place: no (9, M) gathers
    tmp = np.empty_like(a[0])
    for i in range(9):
        np.multiply(a[_P[i]], a[_Q[i]], out=C[i])
        C[i] -= np.multiply(a[_S[i]], a[_T[i]], out=tmp)
    det = np.multiply(a[0], C[0])
    det += a[1] * C[1]
    det += a[2] * C[2]
    return C, det


def squared_norms(a: Array) -> Array:
    """Squared norms (M,) of the columns of `a` (K, M), summed in one fixed order whatever M and layout (einsum's
    is not: a lone column is one contiguous dot, so a joint's answer would depend on its request's other joints)."""
    sq = a * a  # every product in one pass, then the sums in order
    if sq.shape[1] > 1 and sq.flags.c_contiguous:  # one call: NumPy sums pairwise only along the fast axis, not this one
        return np.add.reduce(sq, axis=0)
    s = sq[0] + sq[1]
    for row in sq[2:]:
        s += row
    return s


def polar_rotation(a: Array, used: NDArray[np.bool_] | None = None) -> tuple[Array, Array]:
    """Orthogonal polar factor `R` (9, M) of each `A` and its conditioning ratio `s_min / s_max` (M,).

    Component-major in and out: `a[3 r + c]` is `A[r, c]`. `used` (M,): where fewer than half the bodies are
    used, Newton's iteration only for these (the others' columns of `R` are 0 unless the SVD took them); the
    ratio of every one (a singular `A_ref` is refused whether a joint reads it or not).

    An SVD for every body was 95% of an energy-only evaluation. Newton's iteration `X <- (g X + X^-T / g) / 2`
    (`X^-T = C / det`) converges quadratically to the same factor, with the determinant's scaling
    `g = |det X|^(-1/3)` (Byers; Higham, Functions of Matrices 8.9), free once `det` is known. Bodies with an
    estimated ratio below 1e-4, or not converged in 12 steps, take the SVD. The ratio is exact from the SVD
    where it decides anything; elsewhere the bound `1 / (|A|_F |A^-1|_F)` in `[ratio / 3, ratio]`.
    """
    m = a.shape[1]
    ratio = np.zeros(m)
    C, det = cofactors(a)
    nA = np.sqrt(squared_norms(a))
    nC = np.sqrt(squared_norms(C))
    est = np.abs(det) / (nA * nC)
    good = est >= _NEWTON_RATIO
    # A subset costs a gather and scatters (the common case hands a step over as R whole): worth it
    # only where most bodies are not read.
    subset = used is not None and np.count_nonzero(used) < _SUBSET_FRACTION * m
    newton = (good & used if subset else good).nonzero()[0]
    R = np.zeros_like(a) if subset else None  # filled as bodies converge; None: `going` is every body, in order
    if subset or newton.shape[0] < m:
        ratio[good] = est[good]  # a Newton body's ratio is its estimate, read or not
        X, C, det = a[:, newton], C[:, newton], det[newton]
    else:
        ratio, X = est, a  # `a` itself is only read
    # Each body stops on its own test: its factor never depends on which others it was batched with.
    going = newton
    for _ in range(_NEWTON_STEPS):
        # In place where a value is not needed again (C, the step in X): the same operations.
        g = np.cbrt(np.abs(det))  # 1 / the scaling |det X|^(-1/3)
        X_new = X * np.divide(0.5, g)
        h = np.divide(g, det, out=g)
        h *= 0.5
        X_new += np.multiply(C, h, out=C)
        step = np.subtract(X, X_new, out=None if X is a else X)
        done = np.maximum.reduce(np.abs(step, out=step), axis=0) <= _NEWTON_TOL
        if done.any():
            if R is None and going.shape[0] == m:
                # Every body still going, column j body j: this step is R (the common case: all at once, no
                # scatter). Columns not done yet are overwritten as they converge (or by the SVD below).
                R = X_new
            else:
                R = np.empty_like(a) if R is None else R
                R[:, going[done]] = X_new[:, done]
            going, X_new = going[~done], X_new[:, ~done]
        if going.shape[0] == 0:
            break
        X = X_new
        C, det = cofactors(X, out=C if C.shape == X.shape else None)
    R = np.empty_like(a) if R is None else R
    svd = np.concatenate([(~good).nonzero()[0], going])
    if svd.shape[0]:
        U, s, Vt = np.linalg.svd(a[:, svd].T.reshape(-1, 3, 3))
        R[:, svd] = (U @ Vt).reshape(-1, 9).T
        ratio[svd] = np.nan_to_num(s[:, -1] / s[:, 0], nan=0.0)
    return R, ratio
