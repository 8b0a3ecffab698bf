"""Chain rule from the frame quantities F to the 24 DOFs of a joint, written in the contract's order.

Each F_k depends on its body's DOFs only through `alpha_k p + A v_k`, so
`dF_k / dq` is `I_3 (x) w_k` with `w_k = [alpha_k, v_k]` (4,): row r of F_k sees
`p_r` (weight alpha_k) and row r of A (weights v_k). `J` is never formed.

The Hessian `E'' g g^T + J^T (E' d2x/dF2) J` is assembled from the structured
curvature (`constitution.Curvature`), bitwise symmetric by construction, straight into
the output in DOF order, as signed rank-1 factors `X^T diag(s) X` in one small GEMM per
joint (the signs are exact, so `(s_e X_ei) X_ej == (s_e X_ej) X_ei`):

- low rank: `Y^T S Y` with `Y = U J` (k x 24) and `S = E' C + E'' t t^T` (k x k) as its
  eigen-factors;
- Kronecker: `J^T (K (x) I_3) J` touches only the entries that share a row r of
  `[p | A]`: per r an 8 x 8 (or, with no points, 6 x 6) block `W = w^T K w`. With points
  (the prismatic joint) it enters the GEMM as 3 m more factors; without (the revolute
  joint, whose translation rows and columns are then zero) its 3 x 3 blocks are added after
  a GEMM of the k low-rank factors alone: 12 factors of 24 entries cost the GEMM more
  than the 6 block additions (`python -m bench`, "Every joint active").

Every pass before the GEMM runs along the joints (component-major arrays, as the frames):
a per-joint 2 x 3 product or a broadcast over a trailing axis of 3 costs a call or a loop
per joint.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import as_strided

from service.core.constitution import Array, Curvature
from service.core.kinematics import component_major

MAX_FACTORS = 64
"""At most this many factors per joint (7 for the prismatic joint): `finite_factor` relies on it."""


def finite_factor(dtype: type) -> float:
    """Below this bound on |X|, the sum of `MAX_FACTORS` products of two factors stays finite in `dtype`."""
    return float(np.sqrt(np.finfo(dtype).max / MAX_FACTORS))


def chain(alpha: Array, v: Array, dF: Array) -> Array:
    """`J^T dF` (N, e, 24) component-major of vectors `dF` (N, e, 4, 3) in F; `v` (N, 4, 3)."""
    n, e = dF.shape[:2]
    out = component_major(n, (e, 2, 12), dF.dtype)
    chain_directions(v, dF, out=out[..., 3:].reshape(n, e, 2, 3, 3))  # a view: written in place
    a = alpha.reshape(2, 2)
    db = dF.reshape(n, e, 2, 2, 3)  # (joint, e, body, frame, r)
    for b in range(2):  # the positions see the points' rows: sum over the body's frames of alpha_k dF_k
        np.multiply(db[:, :, b, 0], a[b, 0], out=out[:, :, b, :3])
        out[:, :, b, :3] += db[:, :, b, 1] * a[b, 1]
    return out.reshape(n, e, 24)


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
    if not alpha.any():
        return _hessian_directions(v, curvature, dE, d2E, out, dx)
    X, SX, Jdx, bound = factors(alpha, v, curvature, dE, d2E, dx)
    # (s_e X_ei) X_ej == (s_e X_ej) X_ei bitwise (s_e is a sign) and a GEMM sums each entry over e
    # in the same order: the product is bitwise symmetric without a symmetrising pass.
    np.matmul(SX.transpose(0, 2, 1), X, out=out)
    return Jdx, bool(bound < finite_factor(X.dtype)) and X.shape[1] <= MAX_FACTORS


def _hessian_directions(
    v: Array, curvature: Curvature, dE: Array, d2E: Array, out: Array, dx: Array | None
) -> tuple[Array, bool]:
    """`hessian` for frames without points (the revolute joint): the low-rank part as one GEMM of its
    few factors, the Kronecker part added block by block.

    `J^T (K (x) I_3) J` only touches the entries where a row r of body b's `A` meets the same row r
    of body b''s: per r the 3 x 3 blocks `W_bb' = sum_kk' K_kk' v_k v_k'^T` over the two bodies' frames,
    added entry by entry after a GEMM of the k low-rank factors (12 more factors of 24 entries each
    cost the GEMM more; a revolute joint's exact K has no same-body blocks: only W_ij and its
    transpose). Bitwise symmetric: the GEMM as in `hessian`, `W_ji` is `W_ij` transposed, and each
    same-body `W_bb` is summed symmetrically.
    """
    n = v.shape[0]
    dtype = v.dtype
    basis, k0 = _with_dx(curvature, dx)
    Y = chain_directions(v, basis)  # (N, k, 18), component-major
    lam, Xl, Jdx_A = _low_rank(curvature, Y, k0, dE, d2E)
    k = Xl.shape[1]
    # The GEMM reads each joint's factors as a contiguous k x 24 matrix: one transposed copy of the few
    # factors, translation columns zero, and S X from it in the same layout.
    X = np.zeros((n, k, 2, 12), dtype=dtype)
    X[..., 3:] = Xl.reshape(n, k, 2, 9)
    X = X.reshape(n, k, 24)
    SX = np.multiply(X, np.sign(lam)[:, :, None])
    np.matmul(SX.transpose(0, 2, 1), X, out=out)
    W = _kron_blocks(v, curvature.kron, dE)
    # Along the joints, a row of W at a time: a 3 x 3 block of 3-element rows costs NumPy's iterator a
    # loop per row, and one call per entry 3x the calls (the Python overhead the threads share).
    for (b, b2), block in W.items():
        w = block.transpose(1, 2, 0)  # (a, c, N): rows of N contiguous
        for view in (_kron_view(out, b, b2), _kron_view(out, b2, b, transpose=True))[: 1 + (b != b2)]:
            for r in range(3):
                for a in range(3):
                    np.add(view[r, a], w[a], out=view[r, a])
    Jdx = np.zeros((n, 2, 12), dtype=dtype)
    Jdx[..., 3:] = Jdx_A.reshape(n, 2, 9)
    # |LR| <= k finite_factor^2 <= max / 4 and |W| < max / 4: no sum overflows (NaN fails both tests).
    big = float(np.finfo(dtype).max) / 4
    finite = bool(np.abs(Xl).max(initial=0.0) < finite_factor(dtype)) and k <= MAX_FACTORS
    finite = finite and all(bool(np.abs(block).max(initial=0.0) < big) for block in W.values())
    return Jdx.reshape(n, 24), finite


def _with_dx(curvature: Curvature, dx: Array | None) -> tuple[Array, int]:
    """The vectors in F (N, k, 4, 3) whose chained factors the low-rank part needs: the curvature's
    basis, then `dx` when the gradient is not in its span (E'' dx dx^T beside it); and the basis' size."""
    basis = curvature.basis
    n, k0 = basis.shape[:2]
    if curvature.dx_coef is not None:
        return basis, k0
    both = component_major(n, (k0 + 1, 4, 3), basis.dtype)  # every pass after it runs along the joints
    both[:, :k0], both[:, k0] = basis, dx
    return both, k0


def _kron_view(H: Array, b: int, b2: int, transpose: bool = False) -> Array:
    """The entries of `H` (N, 24, 24) where row r of body b's `A` (column a) meets row r of body b2's
    (column c), as a view (r, a, c, N); with `transpose`, indexed (r, c, a, N) (H's transposed block)."""
    s0, s1, s2 = H.strides
    inner = (s2, s1) if transpose else (s1, s2)
    return as_strided(H[:, 12 * b + 3, 12 * b2 + 3 :], shape=(3, 3, 3, H.shape[0]), strides=(3 * (s1 + s2), *inner, s0))


def chain_directions(v: Array, dF: Array, out: Array | None = None) -> Array:
    """`J^T dF` restricted to the `A` entries, for frames without points: (N, e, 18) component-major
    ((N,) contiguous per entry), entry `(b, r, c)` = sum over body b's frames k of `dF[k, r] v_k[c]`;
    or into `out` (N, e, 2, 3, 3), returned as given.

    `v` (N, 4, 3), `dF` (N, e, 4, 3), any layouts: every pass runs along the joints.
    """
    n, e = dF.shape[:2]
    given = out is not None
    out = component_major(n, (e, 2, 3, 3), dF.dtype) if out is None else out
    vb = v.reshape(n, 1, 2, 2, 1, 3)  # (joint, 1, body, frame, 1, c)
    db = dF.reshape(n, e, 2, 2, 3, 1)  # (joint, e, body, frame, r, 1)
    np.multiply(db[:, :, :, 0], vb[:, :, :, 0], out=out)
    out += db[:, :, :, 1] * vb[:, :, :, 1]
    return out if given else out.reshape(n, e, 18)


def _kron_blocks(v: Array, kron: Array, dE: Array) -> dict[tuple[int, int], Array]:
    """The nonzero blocks `W_bb'` (N, 3, 3) = `sum_kk' dE K_kk' v_k v_k'^T` over body b's frames k and
    b''s k', by (b, b'): (0, 1) always (`W_10` is its transpose), (0, 0) and (1, 1) where K has
    same-body entries. Component-major."""
    n = v.shape[0]
    dtype = v.dtype
    vc = [v[:, k, :, None] for k in range(4)]  # (N, 3, 1): v_k as a column
    vr = [v[:, k, None, :] for k in range(4)]  # (N, 1, 3): v_k as a row

    def Kab(a: int, b: int) -> Array:
        """`dE K_ab` (N, 1, 1), formed where used (8 of the 16 entries for an exact revolute K)."""
        return (dE * kron[:, a, b])[:, None, None]

    W = {(0, 1): component_major(n, (3, 3), dtype)}
    np.multiply(Kab(0, 2) * vc[0] + Kab(1, 2) * vc[1], vr[2], out=W[0, 1])
    W[0, 1] += (Kab(0, 3) * vc[0] + Kab(1, 3) * vc[1]) * vr[3]
    if kron[:, :2, :2].any() or kron[:, 2:, 2:].any():
        for b in range(2):
            p, q = 2 * b, 2 * b + 1
            # (v_p v_p^T) K_pp + (v_q v_q^T) K_qq + (v_p v_q^T + v_q v_p^T) K_pq: each term symmetric bitwise.
            W[b, b] = component_major(n, (3, 3), dtype)
            np.multiply(vc[p] * vr[p], Kab(p, p), out=W[b, b])
            W[b, b] += (vc[q] * vr[q]) * Kab(q, q)
            W[b, b] += (vc[p] * vr[q] + vc[q] * vr[p]) * Kab(p, q)
    return W


def factors(
    alpha: Array, v: Array, curvature: Curvature, dE: Array, d2E: Array, dx: Array | None = None
) -> tuple[Array, Array, Array, float]:
    """Factors `X` (N, p, 24) and `S X` (N, p, 24), `S` the diagonal of their signs, with `X^T S X` the
    Hessian of `hessian`; `J^T dx` (N, 24); max |X| (NaN if any entry is NaN).

    Low rank: `S = E' C + E'' t t^T` (or `E'' dx dx^T` beside it) as `sum_e lam_e z_e z_e^T` over
    combinations `z_e` of the chained basis. Kronecker: `E' K = sum_e w_e f_e f_e^T`, so
    `J^T (E' K (x) I_3) J = sum_{e, r} w_e (J^T (f_e (x) e_r)) (J^T (f_e (x) e_r))^T`, and
    `J^T (f (x) e_r)` is nonzero only in row r of `[p | A]` of each body.
    """
    n = v.shape[0]
    dtype = v.dtype
    basis, k0 = _with_dx(curvature, dx)
    Y = chain(alpha, v, basis)  # (N, k, 24): the basis chained to DOFs, component-major
    lam, Xl, Jdx = _low_rank(curvature, Y, k0, dE, d2E)
    if curvature.kron_factors is None:  # generic: K's own eigen-decomposition
        w, f = np.linalg.eigh(curvature.kron)
        w, f = dE[:, None] * w, f.transpose(0, 2, 1)
    else:
        w, f = curvature.kron_factors
        w = dE[:, None] * w
    m, k = w.shape[1], lam.shape[1]
    # t[e, body, :] = sum over the body's blocks of f_e[block] [alpha, v][block], times sqrt|w_e|:
    # elementwise along the joints (a 2 x 4 product per joint and body is a BLAS call each).
    wv = component_major(n, (2, 2, 4), dtype)  # (joint, body, block, [alpha, v])
    wv[..., 0] = alpha.reshape(2, 2)
    wv[..., 1:] = v.reshape(n, 2, 2, 3)
    fs = component_major(n, (m, 2, 2, 1), dtype)
    np.multiply(np.broadcast_to(f, (n, m, 4)), np.sqrt(np.abs(w))[:, :, None], out=fs.reshape(n, m, 4))
    t = component_major(n, (m, 2, 4), dtype)
    np.multiply(fs[:, :, :, 0], wv[:, None, :, 0], out=t)
    t += fs[:, :, :, 1] * wv[:, None, :, 1]
    t = np.ascontiguousarray(t)  # C order, as X: the placements below copy rows of 3
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
    X = X.reshape(n, k + 3 * m, 24)
    return X, X * sign[:, :, None], Jdx, bound


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
