"""Chain rule from the frame quantities F to the 24 DOFs of a joint, written in the contract's order.

`dF_k / dq` is `I_3 (x) w_k` with `w_k = [alpha_k, v_k]` (4,) (`F_k = alpha_k p + A v_k`): row r of F_k
sees `p_r` (weight alpha_k) and row r of A (weights v_k). `J` is never formed.

The Hessian `E'' g g^T + J^T (E' d2x/dF2) J` of a structured curvature (`constitution.Curvature`) is
written straight into the output as signed rank-1 factors `X^T diag(s) X`, one small GEMM per joint,
bitwise symmetric (the signs are exact, so `(s_e X_ei) X_ej == (s_e X_ej) X_ei`): the low-rank part
`Y^T S Y` (`Y = U J`, `S = E' C + E'' t t^T`) as S's eigen-factors; the Kronecker part `J^T (K (x) I_3) J`,
which only pairs entries of the same row r of `[p | A]`, as 3 m more factors with points (the prismatic
joint), or without (the revolute joint) as 3 x 3 blocks added after the GEMM (12 more factors of 24
entries cost the GEMM more). Every pass before the GEMM runs along the joints (component-major arrays).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from jointlimits.service.core.constitution import Array, Curvature
from jointlimits.service.core.kinematics import GATHER, SMALL, component_major, finfo

BLOCK = 1024
"""Joints whose factors are formed and multiplied at once: their factors and the Hessian rows just written stay
in cache (per-joint scalars are taken for all joints at once: per block they would cost a call each)."""

MAX_FACTORS = 64
"""At most this many factors per joint (7 for the prismatic joint): `finite_factor` relies on it."""


@cache
def finite_factor(dtype: type) -> float:
    """Below this bound on |X|, the sum of `MAX_FACTORS` products of two factors stays finite in `dtype`."""
    return float(np.sqrt(np.finfo(dtype).max / MAX_FACTORS))


def chain(alpha: Array, v: Array, dF: Array) -> Array:
    """`J^T dF` (N, e, 24) component-major of vectors `dF` (N, e, 4, 3) in F; `v` (N, 4, 3)."""
    n, e = dF.shape[:2]
    if n <= SMALL:
        w = component_major(n, (4, 4), v.dtype)  # [alpha_k, v_k] per frame k
        w[..., 0], w[..., 1:] = alpha, v
        return _chained(w, dF)
    out = component_major(n, (e, 2, 12), dF.dtype)
    chain_directions(v, dF, out=out[..., 3:].reshape(n, e, 2, 3, 3))  # a view: written in place
    a = alpha.reshape(2, 2, 1)  # (body, frame, 1)
    db = dF.reshape(n, e, 2, 2, 3)  # (joint, e, body, frame, r)
    # the positions see the points' rows: sum over the body's frames of alpha_k dF_k
    np.multiply(db[:, :, :, 0], a[:, 0], out=out[..., :3])
    out[..., :3] += db[:, :, :, 1] * a[:, 1]
    return out.reshape(n, e, 24)


def chain_directions(v: Array, dF: Array, out: Array | None = None) -> Array:
    """`J^T dF` on the `A` entries, for frames without points: (N, e, 18) component-major, entry `(b, r, c)` =
    sum over body b's frames k of `dF[k, r] v_k[c]`; or into `out` (N, e, 2, 3, 3). `v` (N, 4, 3), `dF` (N, e, 4, 3)."""
    n, e = dF.shape[:2]
    if n <= SMALL and out is None:
        return _chained(v, dF)
    given = out is not None
    out = component_major(n, (e, 2, 3, 3), dF.dtype) if out is None else out
    vb = v.reshape(n, 1, 2, 2, 1, 3)  # (joint, 1, body, frame, 1, c)
    db = dF.reshape(n, e, 2, 2, 3, 1)  # (joint, e, body, frame, r, 1)
    np.multiply(db[:, :, :, 0], vb[:, :, :, 0], out=out)
    out += db[:, :, :, 1] * vb[:, :, :, 1]
    return out if given else out.reshape(n, e, 18)


def _chained(w: Array, dF: Array) -> Array:
    """`chain` of a few joints, (N, e, 2 c): entry (b, r, j) = sum over body b's frames k of `dF[k, r] w_k[j]`, `w`
    (N, 4, c) `[alpha_k, v_k]` (j = 0 the positions, else the A entries (r, j - 1)) or `v_k` (the A entries)."""
    n, e, cols = dF.shape[0], dF.shape[1], w.shape[2]
    left, right = _chain_rows(e, cols)  # every product in one pass over (rows, N) views, frame 2b's first
    p = dF.transpose(1, 2, 3, 0).reshape(12 * e, n).take(left, axis=0, mode=GATHER)
    p *= w.transpose(1, 2, 0).reshape(4 * cols, n).take(right, axis=0, mode=GATHER)
    h = p.shape[0] // 2
    return (p[:h] + p[h:]).reshape(e, -1, n).transpose(2, 0, 1)


@cache
def _chain_rows(e: int, cols: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """`_chained`'s rows of dF (12 e' + 3 k + r) and of w (cols k + j) of each product, frame 2b's, then 2b + 1's."""
    r, j = np.divmod(np.arange(9), 3)  # the A entries (r, c), then with w = [alpha, v] the positions' rows first
    r, j = (np.r_[0:3, r], np.r_[0, 0, 0, j + 1]) if cols == 4 else (r, j)
    k, f, b = np.arange(2)[:, None, None, None], np.arange(e)[:, None, None], np.arange(2)[:, None]
    return (12 * f + 3 * (2 * b + k) + r).ravel(), (cols * (2 * b + k) + j + 0 * f).ravel()


def hessian(alpha: Array, v: Array, curvature: Curvature, dE: Array, d2E: Array, out: Array, dx: Array | None = None,
            balance: Array | None = None) -> tuple[Array, bool]:
    """`E'' g g^T + J^T (E' d2x/dF2) J` (N, 24, 24) into `out`, bitwise symmetric, each entry written once.

    `curvature` is `d2x/dF2` (after a PSD projection it carries E': pass `dE = 1`); `dx` (N, 4, 3) only
    when `curvature.dx_coef` is None; `balance` (N, 4) `balance(alpha, v)` if already taken (a prepared scene's).
    `X` (N, p, 24) `BLOCK` joints at a time, the per-joint scalars once.
    Returns `J^T dx` (N, 24) (the gradient over E'), and whether `out` is finite for sure (|X| below
    `finite_factor`: no sum of products overflows; else the caller checks it).
    """
    # The vectors in F (N, k, 4, 3) whose chained factors the low-rank part needs: the basis, then `dx`
    # when the gradient is not in its span (E'' dx dx^T beside it).
    basis = curvature.basis
    n, k0 = basis.shape[:2]
    if curvature.dx_coef is None:
        basis = component_major(n, (k0 + 1, 4, 3), basis.dtype)  # every pass after it runs along the joints
        basis[:, :k0], basis[:, k0] = curvature.basis, dx
    mix = _Mix.of(curvature, k0, dE, d2E)
    blocks = [slice(s, s + BLOCK) for s in range(0, n, BLOCK)] if n > BLOCK else [slice(None)]
    if not alpha.any():
        return _hessian_directions(v, basis, mix, curvature.kron, dE, out, blocks)
    return _hessian_points(alpha, v, basis, mix, curvature, dE, out, blocks, balance)


def _hessian_points(alpha: Array, v: Array, basis: Array, mix: _Mix, curvature: Curvature, dE: Array, out: Array,
                    blocks: list[slice], scales: Array | None) -> tuple[Array, bool]:
    """`hessian` for frames with points (the prismatic joint): low-rank and Kronecker factors in one GEMM.

    `E' K = sum_e w_e f_e f_e^T`, so `J^T (E' K (x) I_3) J = sum_{e, r} w_e (J^T (f_e (x) e_r)) (J^T (f_e (x) e_r))^T`,
    and `J^T (f (x) e_r)` is nonzero only in row r of `[p | A]` of each body.
    """
    n, dtype = v.shape[0], v.dtype
    if curvature.kron_factors is None:  # generic: K's own eigen-decomposition
        w, f = np.linalg.eigh(curvature.kron)
        w, f = dE[:, None] * w, f.transpose(0, 2, 1)
    else:
        w, f = curvature.kron_factors
        w = dE[:, None] * w
    K = curvature.kron
    if K is not None and not K[:, alpha[:, None] == alpha].any():  # K pairs only points with directions
        f = f * (balance(alpha, v) if scales is None else scales)[:, None, :]
    m, k = w.shape[1], mix.lam.shape[1]
    fs = component_major(n, (m, 2, 2, 1), dtype)  # sqrt|w_e| f_e, by body and block
    np.multiply(f, np.sqrt(np.abs(w))[:, :, None], out=fs.reshape(n, m, 4))
    sign = np.empty((n, k + 3 * m), dtype=dtype)
    np.sign(mix.lam, out=sign[:, :k])
    sign[:, k:].reshape(n, m, 3)[...] = np.sign(w)[:, :, None]
    Jdx = component_major(n, (24,), dtype)
    finite = k + 3 * m <= MAX_FACTORS
    wv = component_major(n, (2, 2, 4), dtype)  # (joint, body, block, [alpha, v])
    wv[..., 0] = alpha.reshape(2, 2)
    wv[..., 1:] = v.reshape(n, 2, 2, 3)
    for q in blocks:
        Y = chain(alpha, v[q], basis[q])  # (M, k, 24): the basis chained to DOFs, component-major
        mq = mix.rows(q)
        Xl = mq.factors(Y)
        mq.jdx(Y, out=Jdx[q])
        M = Xl.shape[0]
        # t[e, body, :] = sum over the body's blocks of f_e[block] [alpha, v][block], times sqrt|w_e|:
        # elementwise along the joints (a 2 x 4 product per joint and body is a BLAS call each).
        t = component_major(M, (m, 2, 4), dtype)
        np.multiply(fs[q][:, :, :, 0], wv[q][:, None, :, 0], out=t)
        t += fs[q][:, :, :, 1] * wv[q][:, None, :, 1]
        t = np.ascontiguousarray(t)  # C order, as X: the placements below copy rows of 3
        X = np.zeros((M, k + 3 * m, 2, 12), dtype=dtype)
        X[:, :k] = Xl.reshape(M, k, 2, 12)
        Xk = X[:, k:].reshape(M, m, 3, 2, 12)  # (joint, e, row r, body, DOF)
        for r in range(3):
            Xk[:, :, r, :, 3 + 3 * r : 6 + 3 * r] = t[..., 1:]
            Xk[:, :, r, :, r] = t[..., 0]
        X = X.reshape(M, k + 3 * m, 24)
        # (s_e X_ei) X_ej == (s_e X_ej) X_ei bitwise (s_e is a sign) and a GEMM sums each entry over e
        # in the same order: the product is bitwise symmetric without a symmetrising pass.
        np.matmul((X * sign[q, :, None]).transpose(0, 2, 1), X, out=out[q])
        # X holds the values of Xl and t, and zeros (NaN fails the test).
        finite = finite and bool(max(np.abs(Xl).max(initial=0.0), np.abs(t).max(initial=0.0)) < finite_factor(dtype))
    return Jdx, finite


def balance(alpha: Array, v: Array) -> Array:
    """(N, 4) powers of two, g on the points' blocks and 1/g on the directions' (g^2 ~ |v_dir| / |[1, v_point]|):
    factors of a K pairing only points with directions still sum to K, and a point's row [1, c_k] far larger
    than a direction's [0, t_k] (an anchor 1/s body units away) cancels no digits in their difference of squares."""
    pts = alpha.astype(bool)
    size = np.abs(v).max(axis=2)  # (N, 4)
    ratio = size[:, ~pts].max(axis=1) / np.maximum(size[:, pts].max(axis=1), 1.0)
    bound = np.finfo(v.dtype).maxexp // 4  # g and 1/g far inside the range
    e = np.rint(0.5 * np.log2(ratio, where=ratio > 0, out=np.zeros(ratio.shape, ratio.dtype)))
    e = np.minimum(np.maximum(e, -bound), bound)  # np.clip's own checks cost more than both passes
    g = np.ldexp(ratio.dtype.type(1.0), e.astype(np.int32))[:, None]
    return np.where(pts, g, 1.0 / g)


def _hessian_directions(
    v: Array, basis: Array, mix: _Mix, kron: Array, dE: Array, out: Array, blocks: list[slice]
) -> tuple[Array, bool]:
    """`hessian` for frames without points (the revolute joint): the low-rank part as one GEMM of its
    few factors, the Kronecker part added after it.

    `J^T (K (x) I_3) J` only touches the entries where a row r of body b's `A` meets the same row r
    of body b''s: per r the 3 x 3 blocks `W_bb'` (`_kron_blocks`), added entry by entry after a GEMM
    of the k low-rank factors (12 more factors of 24 entries each cost the GEMM more). Bitwise
    symmetric: the GEMM as in `hessian`, `W_ji` is `W_ij` transposed, each `W_bb` symmetric.
    """
    n, dtype, k = v.shape[0], v.dtype, mix.lam.shape[1]
    sign = np.sign(mix.lam)
    K = kron.transpose(1, 2, 0).reshape(4, 4, -1)  # joints last (a view of the constitutions' component-major K)
    same = bool(K[:2, :2].any() or K[2:, 2:].any())  # only after a PSD projection
    dK = K.reshape(16, -1) * dE  # E' K, row 4 k + k'
    at, src = _KRON_SCATTER[same]
    Jdx = np.zeros((n, 2, 12), dtype=dtype)  # the translations stay 0: no points
    # |LR| <= k finite_factor^2 <= max / 4 and |W| < max / 4: no sum overflows (NaN fails both tests).
    big = float(finfo(dtype).max) / 4
    finite = k <= MAX_FACTORS
    for q in blocks:
        Y = chain_directions(v[q], basis[q])  # (M, k, 18), component-major
        mq = mix.rows(q)
        Xl = mq.factors(Y)
        Jdx[q, :, 3:] = mq.jdx(Y, out=np.empty_like(Y[:, 0])).reshape(-1, 2, 9)
        m = Xl.shape[0]
        # The GEMM reads each joint's factors as a contiguous k x 24 matrix: one transposed copy of the
        # few factors, translation columns zero, and S X from it in the same layout.
        X = np.zeros((m, k, 2, 12), dtype=dtype)
        X[..., 3:] = Xl.reshape(m, k, 2, 9)
        X = X.reshape(m, k, 24)
        np.matmul((X * sign[q, :, None]).transpose(0, 2, 1), X, out=out[q])
        W = _kron_blocks(v[q], dK[:, q], same)
        H = out[q].reshape(m, 576)
        # Each entry of H takes at most one entry of W: any order. A few joints: one scatter; more, column
        # by column (the scatter's (M, P) gather costs more than P strided passes there).
        if m <= SMALL:
            H[:, at] += W.take(src, axis=0, mode=GATHER).T
        else:
            for p, w in zip(at.tolist(), src.tolist()):
                H[:, p] += W[w]
        finite = finite and bool(np.abs(Xl).max(initial=0.0) < finite_factor(dtype))
        finite = finite and bool(np.abs(W).max(initial=0.0) < big)
    return Jdx.reshape(n, 24), finite


def _kron_scatter(same: bool) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Where `_kron_blocks`' entries go in a flat 24 x 24 Hessian: the positions (P,) and the flat entry of
    the blocks (nb, 3, 3) each takes. Entry (a, c) of `W_bb'` sits at (row r of body b's A, column a) x
    (row r of body b''s A, column c) for r = 0, 1, 2, and (b != b') at the transposed position too."""
    at, src = [], []
    for t, (b, b2) in enumerate([(0, 1), (0, 0), (1, 1)][: 3 if same else 1]):
        for a in range(3):
            for c in range(3):
                i, j = 12 * b + 3 + 3 * np.arange(3) + a, 12 * b2 + 3 + 3 * np.arange(3) + c
                spots = [*(24 * i + j)] + ([*(24 * j + i)] if b != b2 else [])
                at += spots
                src += [9 * t + 3 * a + c] * len(spots)
    return np.array(at), np.array(src)


_KRON_SCATTER = {same: _kron_scatter(same) for same in (False, True)}


def _kron_blocks(v: Array, dK: Array, same: bool) -> Array:
    """The nonzero blocks `W_bb'` (9 nb, N), entry (b, b', a, c) = `sum_kk' dK_kk' v_k[a] v_k'[c]` over body b's
    frames k and b''s k': (0, 1) (`W_10` is its transpose), then (0, 0) and (1, 1) when `same` (K has same-body
    entries). `dK` (16, N) is `E' K` (row 4 k + k'), `v` (N, 4, 3); every pass runs along the joints."""
    n = v.shape[0]
    if n <= SMALL:  # a few joints: each product's rows taken at once, the passes over whole (rows, N) arrays
        vv = v.transpose(1, 2, 0).reshape(12, n).take(_KB_V, axis=0, mode=GATHER)  # the v rows of every product
        W = np.empty((27 if same else 9, n), dtype=v.dtype)
        p = dK.take(_KB_U, axis=0, mode=GATHER) * vv[:12]  # K_kk' v_k[a], k = 0 then 1, k' = 2, 3
        u = p[:6] + p[6:]
        p = u.take(_KB_W, axis=0, mode=GATHER) * vv[12:30]  # u_k'[a] v_k'[c]
        W[:9] = p[:9]  # each partial sum rounded to W's dtype, as below (a float32 W of float64 E' K)
        W[:9] += p[9:]
        if same:  # both bodies at once, p = 2b, q = 2b + 1, as below
            o = vv[30:102] * vv[102:]  # (pp, qq, pq, qp; b; a; c)
            kd = dK.take(_KB_K, axis=0, mode=GATHER)  # K_pp, K_qq (b = 0, 1), then K_pq
            t, Ws = o[:36].reshape(2, 2, 9, n) * kd[:4].reshape(2, 2, 1, n), W[9:].reshape(2, 9, n)
            Ws[...] = t[0]
            Ws += t[1]
            Ws += (o[36:54] + o[54:]).reshape(2, 9, n) * kd[4:, None]
        return W
    dK = dK.reshape(4, 4, n).transpose(2, 0, 1)
    W = component_major(n, (3 if same else 1, 3, 3), v.dtype)
    u = dK[:, 0, 2:, None] * v[:, 0, None, :]  # (N, 2, 3): sum over body i's k of K_kk' v_k, for k' = 2, 3
    u += dK[:, 1, 2:, None] * v[:, 1, None, :]
    np.multiply(u[:, 0, :, None], v[:, 2, None, :], out=W[:, 0])
    W[:, 0] += u[:, 1, :, None] * v[:, 3, None, :]
    if same:  # both bodies at once: p = 2b, q = 2b + 1
        Kb = dK.reshape(n, 2, 2, 2, 2).diagonal(axis1=1, axis2=3)[..., None, None]  # [:, i, j, b] = K_(2b+i)(2b+j)
        vb = v.reshape(n, 2, 2, 3)
        o = vb[:, :, :, None, :, None] * vb[:, :, None, :, None, :]  # [:, b, i, j] = v_(2b+i) v_(2b+j)^T, in one pass
        # (v_p v_p^T) K_pp + (v_q v_q^T) K_qq + (v_p v_q^T + v_q v_p^T) K_pq: each term symmetric bitwise.
        np.multiply(o[:, :, 0, 0], Kb[:, 0, 0], out=W[:, 1:])
        W[:, 1:] += o[:, :, 1, 1] * Kb[:, 1, 1]
        W[:, 1:] += (o[:, :, 0, 1] + o[:, :, 1, 0]) * Kb[:, 0, 1]
    return W.transpose(1, 2, 3, 0).reshape(-1, n)


def _kron_block_rows() -> tuple[NDArray[np.intp], ...]:
    """`_kron_blocks`' rows: of v (3 k + a) for its products in order (u, W_01, then body b's terms pp, qq, pq, qp),
    of K (4 k + k'), of u, of K again."""
    c, a, b = np.arange(3), np.arange(3)[:, None], np.arange(2)[:, None, None]
    i, j = (np.array(x)[:, None, None, None] for x in ([0, 1, 0, 1], [0, 1, 1, 0]))
    o_l, o_r = (3 * (2 * b + i) + a + 0 * c).ravel(), (3 * (2 * b + j) + c + 0 * a).ravel()
    v = np.concatenate([np.repeat([0, 3], 6) + np.tile(c, 4), np.repeat([6, 9], 9) + np.tile(c, 6), o_l, o_r])
    return v, np.repeat([2, 3, 6, 7], 3), np.repeat(np.arange(6), 3), np.array([0, 10, 5, 15, 1, 11])


_KB_V, _KB_U, _KB_W, _KB_K = _kron_block_rows()


@dataclass
class _Mix:
    """The low-rank part `S` (k x k per joint) over the chained basis `Y` (N, k, 24), as factors
    `Xl_e = sqrt|lam_e| (V^T Y)_e` with eigenvalues `lam` (N, k), and `J^T dx` from `Y`.

    `S = E' C + E'' t t^T` (`t` = `dx_coef`), or `E'' dx dx^T` beside it when dx is outside the
    basis (its row `k0` of Y). Per-joint scalars, taken once per call: `scale` (N, k) when S is
    diagonal, `rot` (4 x (N,)) for k = 2 in closed form, else `VT` (N, k, k) (V^T, rows scaled).
    """

    lam: Array
    k0: int
    t: Array | None = None
    scale: Array | None = None
    rot: tuple[Array, Array, Array, Array] | None = None
    VT: Array | None = None

    @classmethod
    def of(cls, curvature: Curvature, k0: int, dE: Array, d2E: Array) -> _Mix:
        n, t, C = dE.shape[0], curvature.dx_coef, curvature.coef
        k = k0 + (t is None)
        if t is None:
            if curvature.diagonal:
                lam = np.empty((n, k), dtype=dE.dtype)
                lam[:, :k0] = dE[:, None] * C.diagonal(axis1=1, axis2=2)
                lam[:, k0] = d2E
                return cls(lam, k0, scale=np.sqrt(np.abs(lam)))
            S = np.zeros((n, k, k), dtype=dE.dtype)
            S[:, :k0, :k0] = dE[:, None, None] * C
            S[:, k0, k0] = d2E
        else:
            if k == 1:
                lam = dE[:, None] * C[:, 0] + d2E[:, None] * (t * t)
                return cls(lam, k0, t, scale=np.sqrt(np.abs(lam)))
            if k == 2:  # per-joint scalars (N,): a batched 2 x 2 is slower than these few passes
                p, q, u = (dE * C[:, a, b] + d2E * (t[:, a] * t[:, b]) for a, b in ((0, 0), (0, 1), (1, 1)))
                return cls._eig2(p, q, u, k0, t)
            S = dE[:, None, None] * C + d2E[:, None, None] * (t[:, :, None] * t[:, None, :])
        if k == 2:
            return cls._eig2(S[:, 0, 0], S[:, 0, 1], S[:, 1, 1], k0, t)
        lam, V = np.linalg.eigh(S)
        V *= np.sqrt(np.abs(lam))[:, None, :]
        return cls(lam, k0, t, VT=V.transpose(0, 2, 1))

    @classmethod
    def _eig2(cls, p: Array, q: Array, u: Array, k0: int, t: Array | None) -> _Mix:
        """`[[p, q], [q, u]]` (each (N,)) in closed form."""
        mean, h = 0.5 * (p + u), np.hypot(0.5 * (p - u), q)
        phi = 0.5 * np.arctan2(q, 0.5 * (p - u))  # rotation taking e_1 to the eigenvector of mean + h
        c, s = np.cos(phi), np.sin(phi)
        lam = np.stack([mean + h, mean - h], axis=1)
        r = np.sqrt(np.abs(lam))
        return cls(lam, k0, t, rot=(r[:, 0] * c, r[:, 0] * s, r[:, 1] * c, r[:, 1] * s))

    def rows(self, q: slice) -> _Mix:
        """Joints `q` (views)."""
        if q == slice(None):
            return self
        cut = lambda a: None if a is None else a[q]  # noqa: E731
        rot = None if self.rot is None else tuple(a[q] for a in self.rot)
        return _Mix(self.lam[q], self.k0, cut(self.t), cut(self.scale), rot, cut(self.VT))  # type: ignore[arg-type]

    def factors(self, Y: Array) -> Array:
        """`Xl` (N, k, 24), in Y's layout."""
        if self.scale is not None:
            return Y * self.scale[:, :, None]
        if self.rot is None:
            return np.matmul(self.VT, Y)
        rc0, rs0, rc1, rs1 = self.rot
        Xl = np.empty_like(Y)
        # Eigenvectors (c, s) and (-s, c).
        np.multiply(rc0[:, None], Y[:, 0], out=Xl[:, 0])
        Xl[:, 0] += rs0[:, None] * Y[:, 1]
        np.multiply(rc1[:, None], Y[:, 1], out=Xl[:, 1])
        Xl[:, 1] -= rs1[:, None] * Y[:, 0]
        return Xl

    def jdx(self, Y: Array, out: Array) -> Array:
        """`J^T dx` (N, 24) into `out`: `t . Y`, or Y's row `k0`."""
        if self.t is None:
            out[...] = Y[:, self.k0]
            return out
        t = self.t
        np.multiply(t[:, 0, None], Y[:, 0], out=out)
        for b in range(1, t.shape[1]):
            out += t[:, b, None] * Y[:, b]
        return out


def psd_projection(M: Array) -> Array:
    """Each symmetric `M` (N, 12, 12) with negative eigenvalues clamped to 0, as a Curvature's parts: the
    eigen-factors `V^T` (N, 12, 4, 3) and the clamped eigenvalues (N, 12)."""
    n = M.shape[0]
    lam, V = np.linalg.eigh(M)
    return V.transpose(0, 2, 1).reshape(n, 12, 4, 3), np.maximum(lam, 0.0)
