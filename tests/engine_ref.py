"""An independent transcription of the reference engine's two joint limits, in plain NumPy (float64).

It reads nothing of the project (no `service`, no `client`): it is what the pyuipc adapter's
answers are checked against. Transcribed from libuipc (spiriMirror/libuipc, the snapshot at commit
619a5412cf958eb59cf3c9cebc9a8e8e9625ebd3):

- `src/backends/cuda/affine_body/constitutions/affine_body_revolute_joint.cu`:
  `AffineBodyRevoluteJoint::do_init` (frames from world or local edges: `t = P1 - P0`, or
  `t = LT.rotation() * (l_position1 - l_position0)`; `orthonormal_basis(t, n, b)`; body-local
  `[n, b]` = `LT.rotation().inverse() * [n, b]`), `compute_current_angles` (the committed angle is
  seeded with `init_angle` and unwrapped against it, so at `world.init()` it is
  `theta(q_ref) + init_angle`), and `AffineBodyRevoluteJointLimit::do_compute_gradient_hessian`
  (`x = (current_angle - init_angle) + DeltaTheta(q, q_prev)`, bounds `limit/* - init_angle`,
  `H = E'' g g^T + J^T make_spd(E' d2x/dF2) J` in the 12 frame quantities).
- `.../affine_body_revolute_joint_function.h` (`unwrap_angle`, `compute_relative_angle`) and
  `.../sym/affine_body_revolute_joint_limit.inl` (`F`, `DeltaTheta`, `dDeltaTheta_dF`,
  `ddDeltaTheta_ddF`, `JT_H_J`; F = `[A_i n_i, A_i b_i, A_j n_j, A_j b_j]`).
- `.../affine_body_prismatic_joint.cu`: `AffineBodyPrismaticJoint::do_init` (world: `t = P1 - P0`,
  anchors `LT.inverse() * P0`, `RT.inverse() * P0`; local: `t = LT * l1 - LT * l0`, anchors
  `l_position0`, `r_position0`; axis `LT.rotation().inverse() * t`, `RT.rotation().inverse() * t`)
  and `AffineBodyPrismaticJointLimit` (`x = compute_absolute_distance(q)`, bounds
  `limit/* - init_distance`, no state).
- `.../affine_body_prismatic_joint_function.h` and `.../sym/affine_body_driving_prismatic_joint.inl`
  (`F01_q = [C_j - C_i, T_i, -T_j]`, `Distance`, `dxdF01`, `ddxdF01`, `J01T_H01_J01`: the psd
  Hessian projects `E' d2x/dF01^2` in those 9 quantities).
- `.../joint_limit_penalty.h` (the cubic penalty) and `src/backends/cuda/utils/make_spd.h`
  (eigenvalues clamped at 0; here `numpy.linalg.eigh`).
- `Eigen::Transform::rotation()` is the SVD-based `computeRotationScaling`:
  `R = U diag(1, 1, det(U V^T)) V^T`.

The generated (SymEigen) expressions are transcribed as the closed forms they expand: `dx/dF` and
`d2x/dF2` of `atan2(s, c)` with `c, s` bilinear in F (identical functions; the engine writes them
through `atan2(s c_t - c s_t, c c_t + s s_t)`, whose F-derivatives are the same). Checked once
against the generated code itself, evaluated literally (its C++ turned into Python by regex): over
200 random frames `DeltaTheta`, `dDeltaTheta_dF`, `ddDeltaTheta_ddF`, `dDeltaTheta_dQ` agree to 5e-15,
and `F01_q`, `J01T_G01`, `J01T_H01_J01` of the prismatic joint to 4e-16 (normwise). Everything is
vectorised over N joints. Shapes: `q*` (N, 12) per side; results `x`, `energy` (N,),
`gradient` (N, 24), `hessian` (N, 24, 24) in the DOFs `[q_i, q_j]`.

`origin="absolute"` is the engine's own zero; `origin="q_ref"` (the specs' zero) subtracts the
value at `q_ref`, which lets the same code check the contract's golden cases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

TWO_PI = 2.0 * np.pi


# ---------------------------------------------------------------------------------------- helpers


def q_to_A(q: Array) -> Array:
    """(N, 12) -> (N, 3, 3): the rows of A are q[3:6], q[6:9], q[9:12] (`q = [p, A row 0..2]`)."""
    return np.asarray(q, dtype=np.float64)[:, 3:].reshape(-1, 3, 3)


def transform_to_q(T: Array) -> Array:
    """(N, 4, 4) transforms -> (N, 12): the engine's `transform_to_q` (`[T[0:3, 3], T[0, 0:3], T[1, 0:3], T[2, 0:3]]`)."""
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    return np.concatenate([T[:, :3, 3], T[:, :3, :3].reshape(-1, 9)], axis=1)


def eigen_rotation(A: Array) -> Array:
    """(N, 3, 3) -> (N, 3, 3): `Eigen::Transform::rotation()` (SVD; the polar factor when det A > 0)."""
    U, _, Vt = np.linalg.svd(A)
    x = np.linalg.det(U @ Vt)  # +-1
    U = U.copy()
    U[:, :, 2] *= x[:, None]
    return U @ Vt


def orthonormal_basis(t: Array) -> tuple[Array, Array, Array]:
    """(N, 3) -> t, n, b (N, 3) each: `affine_body/utils.cu: orthonormal_basis` (test e_x, e_y when |t.e_x| > 0.9)."""
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    test = np.zeros_like(t)
    use_y = np.abs(t[:, 0]) > 0.9
    test[~use_y, 0] = 1.0
    test[use_y, 1] = 1.0
    n = np.cross(t, test)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    b = np.cross(t, n)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    return t, n, b


def jac_vec(v: Array) -> Array:
    """(N, 3) body-local vector -> (N, 3, 12): d(A v)/dq (`(A v)[r] = q[3 + 3 r : 6 + 3 r] . v`)."""
    N = v.shape[0]
    J = np.zeros((N, 3, 12))
    for r in range(3):
        J[:, r, 3 + 3 * r: 6 + 3 * r] = v
    return J


def jac_point(c: Array) -> Array:
    """(N, 3) body-local point -> (N, 3, 12): d(p + A c)/dq."""
    J = jac_vec(c)
    J[:, :, :3] += np.eye(3)
    return J


def apply_vec(q: Array, v: Array) -> Array:
    """(N, 12), (N, 3) -> (N, 3): A v."""
    return np.einsum("nrc,nc->nr", q_to_A(q), v)


def make_spd(H: Array) -> Array:
    """(N, K, K) symmetric -> (N, K, K): eigenvalues clamped at 0 (`utils/make_spd.h`)."""
    H = 0.5 * (H + H.transpose(0, 2, 1))
    w, V = np.linalg.eigh(H)
    w = np.where(w < 0.0, 0.0, w)
    return np.einsum("nik,nk,njk->nij", V, w, V)


def penalty(x: Array, lower: Array, upper: Array, strength: Array) -> tuple[Array, Array, Array]:
    """`joint_limit::eval_penalty`, elementwise (N,): E, dE/dx, d2E/dx2 (zero in range, bounds included)."""
    x, lower, upper, s = (np.asarray(a, dtype=np.float64) for a in (x, lower, upper, strength))
    E, d1, d2 = np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
    w = upper - lower
    above, below = x > upper, x < lower
    deg = w == 0.0
    # u == l: s |x - l|^3
    d = np.where(above, x - upper, lower - x)
    sgn = np.where(above, 1.0, -1.0)
    m = deg & (above | below)
    E[m] = (s * d * d * d)[m]
    d1[m] = (sgn * 3.0 * s * d * d)[m]
    d2[m] = (6.0 * s * d)[m]
    # u > l: s ((x - u) / (u - l))^3 above, s ((l - x) / (u - l))^3 below
    m = ~deg & (above | below)
    inv_w = np.divide(1.0, w, out=np.zeros_like(w), where=~deg)
    r = d * inv_w
    E[m] = (s * r * r * r)[m]
    d1[m] = (sgn * 3.0 * s * r * r * inv_w)[m]
    d2[m] = (6.0 * s * r * inv_w * inv_w)[m]
    return E, d1, d2


@dataclass
class Result:
    """Per joint: `x`, `coordinate` = x + offset, `energy` (N,), `gradient` (N, 24), `hessian` (N, 24, 24) (psd)."""

    x: Array
    coordinate: Array
    energy: Array
    gradient: Array
    hessian: Array


def _assemble(x: Array, offset: Array, lower: Array, upper: Array, strength: Array,
              g_F: Array, J: Array, H_F: Array) -> Result:
    """Energy and the engine's psd derivatives from x, dx/dF (N, K), J = dF/dq (N, K, 24), d2x/dF2 (N, K, K)."""
    E, d1, d2 = penalty(x, lower - offset, upper - offset, strength)
    dx_dq = np.einsum("nk,nkq->nq", g_F, J)
    G = d1[:, None] * dx_dq
    H = d2[:, None, None] * np.einsum("ni,nj->nij", dx_dq, dx_dq)
    active = d1 != 0.0  # the engine adds the curvature term only where E' != 0
    if np.any(active):
        P = make_spd(d1[active, None, None] * H_F[active])
        H[active] += np.einsum("nki,nkl,nlj->nij", J[active], P, J[active])
    return Result(x, x + offset, E, G, H)


# --------------------------------------------------------------------------------- #670 revolute


def revolute_frames(
    A_ref_i: Array, A_ref_j: Array, *, edges: Array | None = None, local_edges: Array | None = None
) -> tuple[Array, Array, Array, Array]:
    """Body-local `n_i, b_i, n_j, b_j` (N, 3) as `AffineBodyRevoluteJoint::do_init` builds them.

    `edges` (N, 2, 3): world `P0, P1` at q_ref; `local_edges` (N, 2, 2, 3): `[[l0, l1], [r0, r1]]`.
    `A_ref_*` (N, 3, 3): the bodies' `A` at q_ref (the rest transforms' linear parts).
    """
    R_i, R_j = eigen_rotation(A_ref_i), eigen_rotation(A_ref_j)
    if local_edges is not None:
        le = np.asarray(local_edges, dtype=np.float64)
        t = np.einsum("nrc,nc->nr", R_i, le[:, 0, 1] - le[:, 0, 0])  # LT.rotation() * (l1 - l0)
    else:
        e = np.asarray(edges, dtype=np.float64)
        t = e[:, 1] - e[:, 0]
    _, n, b = orthonormal_basis(t)
    to_local = lambda R, v: np.einsum("nrc,nr->nc", R, v)  # R^{-1} v = R^T v  # noqa: E731
    return to_local(R_i, n), to_local(R_i, b), to_local(R_j, n), to_local(R_j, b)


def revolute_F(frames: tuple[Array, Array, Array, Array], q_i: Array, q_j: Array) -> Array:
    """(N, 12): `sym::affine_body_revolute_joint_limit::F` = `[A_i n_i, A_i b_i, A_j n_j, A_j b_j]`."""
    n_i, b_i, n_j, b_j = frames
    return np.concatenate([apply_vec(q_i, n_i), apply_vec(q_i, b_i), apply_vec(q_j, n_j), apply_vec(q_j, b_j)], axis=1)


def _cos_sin(F: Array) -> tuple[Array, Array]:
    """cos = (N_i.N_j + B_i.B_j)/2, sin = (B_i.N_j - N_i.B_j)/2 (the generated `theta` / `DeltaTheta`)."""
    Ni, Bi, Nj, Bj = F[:, 0:3], F[:, 3:6], F[:, 6:9], F[:, 9:12]
    dot = lambda a, b: np.einsum("nk,nk->n", a, b)  # noqa: E731
    return 0.5 * (dot(Ni, Nj) + dot(Bi, Bj)), 0.5 * (dot(Bi, Nj) - dot(Ni, Bj))


def revolute_theta(F: Array) -> Array:
    """The wrapped angle `atan2(sin, cos)` in (-pi, pi] (`compute_relative_angle`)."""
    c, s = _cos_sin(F)
    return np.arctan2(s, c)


def revolute_delta(F: Array, F_t: Array) -> Array:
    """`DeltaTheta(F, F_t) = atan2(s c_t - c s_t, c c_t + s s_t)`."""
    c, s = _cos_sin(F)
    ct, st = _cos_sin(F_t)
    return np.arctan2(s * ct - c * st, c * ct + s * st)


def unwrap_angle(wrapped: Array, ref: Array) -> Array:
    """`unwrap_angle`: `ref + remainder(wrapped - ref, 2 pi)` (the 2 pi representative nearest `ref`;
    C's `remainder` rounds the quotient half to even, as `math.remainder` does)."""
    return ref + _remainder(np.asarray(wrapped, dtype=np.float64) - ref, TWO_PI)


_remainder = np.vectorize(math.remainder, otypes=[np.float64])


def _revolute_derivatives(F: Array) -> tuple[Array, Array]:
    """dx/dF (N, 12) and d2x/dF2 (N, 12, 12) of x = atan2(s, c) + const (what `dDeltaTheta_dF` /
    `ddDeltaTheta_ddF` expand to). With u = grad c, v = grad s (constant Hessians Hc, Hs):
    g = (c v - s u) / r2, w = (c u + s v) / r2, H = (c Hs - s Hc) / r2 - (g w^T + w g^T)."""
    Ni, Bi, Nj, Bj = F[:, 0:3], F[:, 3:6], F[:, 6:9], F[:, 9:12]
    c, s = _cos_sin(F)
    u = 0.5 * np.concatenate([Nj, Bj, Ni, Bi], axis=1)
    v = 0.5 * np.concatenate([-Bj, Nj, Bi, -Ni], axis=1)
    r2 = c * c + s * s
    g = (c[:, None] * v - s[:, None] * u) / r2[:, None]
    w = (c[:, None] * u + s[:, None] * v) / r2[:, None]
    I3, Z = 0.5 * np.eye(3), np.zeros((3, 3))
    Hc = np.block([[Z, Z, I3, Z], [Z, Z, Z, I3], [I3, Z, Z, Z], [Z, I3, Z, Z]])
    Hs = np.block([[Z, Z, Z, -I3], [Z, Z, I3, Z], [Z, I3, Z, Z], [-I3, Z, Z, Z]])
    H = (c[:, None, None] * Hs - s[:, None, None] * Hc) / r2[:, None, None]
    H -= np.einsum("ni,nj->nij", g, w) + np.einsum("ni,nj->nij", w, g)
    return g, H


def revolute(
    q: tuple[Array, Array],
    q_prev: tuple[Array, Array],
    q_ref: tuple[Array, Array],
    lower: Array,
    upper: Array,
    strength: Array,
    *,
    edges: Array | None = None,
    local_edges: Array | None = None,
    offset: Array | None = None,
    prev_coordinate: Array | None = None,
    origin: str = "absolute",
) -> Result:
    """#670 as the engine evaluates it. `q*` are `(q_i, q_j)` pairs of (N, 12); `lower`, `upper`,
    `strength`, `offset` (= `init_angle`), `prev_coordinate` (= the committed `angle`) (N,).

    Without `prev_coordinate` the committed angle is what the engine would hold after committing
    `q_prev` from `world.init()` at `q_ref`: `theta_ref + remainder(theta(q_prev) - theta_ref)`
    (`compute_current_angles`), minus `theta_ref` when `origin="q_ref"`.
    """
    n = np.shape(q[0])[0]
    per = lambda a, d=0.0: np.broadcast_to(np.asarray(d if a is None else a, dtype=np.float64), (n,))  # noqa: E731
    offset_ = per(offset)
    frames = revolute_frames(q_to_A(q_ref[0]), q_to_A(q_ref[1]), edges=edges, local_edges=local_edges)
    F = revolute_F(frames, *q)
    F_prev = revolute_F(frames, *q_prev)
    if prev_coordinate is not None:
        theta_t = per(prev_coordinate) - offset_  # current_angles(I) - init_angles(I)
    else:
        theta_ref = revolute_theta(revolute_F(frames, *q_ref))  # seeded: unwrap(theta_ref, 0)
        theta_t = unwrap_angle(revolute_theta(F_prev), theta_ref)
        if origin == "q_ref":
            theta_t = theta_t - theta_ref
    x = theta_t + revolute_delta(F, F_prev)
    g_F, H_F = _revolute_derivatives(F)
    n_i, b_i, n_j, b_j = frames
    J = np.zeros((n, 12, 24))
    J[:, 0:3, 0:12], J[:, 3:6, 0:12] = jac_vec(n_i), jac_vec(b_i)
    J[:, 6:9, 12:24], J[:, 9:12, 12:24] = jac_vec(n_j), jac_vec(b_j)
    return _assemble(x, offset_, per(lower), per(upper), per(strength, 1.0), g_F, J, H_F)


# -------------------------------------------------------------------------------- #669 prismatic


def prismatic_frames(
    q_ref_i: Array, q_ref_j: Array, *, edges: Array | None = None, local_edges: Array | None = None
) -> tuple[Array, Array, Array, Array]:
    """Body-local anchors and axes `c_i, t_i, c_j, t_j` (N, 3) as `AffineBodyPrismaticJoint::do_init` builds them."""
    A_i, A_j = q_to_A(q_ref_i), q_to_A(q_ref_j)
    p_i, p_j = q_ref_i[:, :3], q_ref_j[:, :3]
    if local_edges is not None:
        le = np.asarray(local_edges, dtype=np.float64)
        lp0 = p_i + np.einsum("nrc,nc->nr", A_i, le[:, 0, 0])  # LT * l_position0
        lp1 = p_i + np.einsum("nrc,nc->nr", A_i, le[:, 0, 1])
        t = lp1 - lp0
        c_i, c_j = le[:, 0, 0], le[:, 1, 0]
    else:
        e = np.asarray(edges, dtype=np.float64)
        t = e[:, 1] - e[:, 0]
        c_i = np.linalg.solve(A_i, (e[:, 0] - p_i)[:, :, None])[:, :, 0]  # LT.inverse() * P0
        c_j = np.linalg.solve(A_j, (e[:, 0] - p_j)[:, :, None])[:, :, 0]
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    to_local = lambda A, v: np.einsum("nrc,nr->nc", eigen_rotation(A), v)  # noqa: E731
    return c_i, to_local(A_i, t), c_j, to_local(A_j, t)


def prismatic_F01(frames: tuple[Array, Array, Array, Array], q_i: Array, q_j: Array) -> Array:
    """(N, 9): `F01_q = [C_j - C_i, T_i, -T_j]`."""
    c_i, t_i, c_j, t_j = frames
    D = (q_j[:, :3] + apply_vec(q_j, c_j)) - (q_i[:, :3] + apply_vec(q_i, c_i))
    return np.concatenate([D, apply_vec(q_i, t_i), -apply_vec(q_j, t_j)], axis=1)


def prismatic_distance(F01: Array) -> Array:
    """`Distance`: x = D . (T_i - (-T_j)) / 2."""
    return 0.5 * np.einsum("nk,nk->n", F01[:, 0:3], F01[:, 3:6] - F01[:, 6:9])


def prismatic(
    q: tuple[Array, Array],
    q_prev: tuple[Array, Array],
    q_ref: tuple[Array, Array],
    lower: Array,
    upper: Array,
    strength: Array,
    *,
    edges: Array | None = None,
    local_edges: Array | None = None,
    offset: Array | None = None,
    origin: str = "absolute",
) -> Result:
    """#669 as the engine evaluates it: `x = theta(q)` (absolute, no state; `q_prev` is unused by
    the engine), minus `theta(q_ref)` when `origin="q_ref"`. `offset` = `init_distance`."""
    n = np.shape(q[0])[0]
    per = lambda a, d=0.0: np.broadcast_to(np.asarray(d if a is None else a, dtype=np.float64), (n,))  # noqa: E731
    frames = prismatic_frames(q_ref[0], q_ref[1], edges=edges, local_edges=local_edges)
    F = prismatic_F01(frames, *q)
    x = prismatic_distance(F)
    if origin == "q_ref":
        x = x - prismatic_distance(prismatic_F01(frames, *q_ref))
    g_F = 0.5 * np.concatenate([F[:, 3:6] - F[:, 6:9], F[:, 0:3], -F[:, 0:3]], axis=1)  # dxdF01
    h = np.array([[0.0, 0.5, -0.5], [0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]])
    H_F = np.broadcast_to(np.kron(h, np.eye(3)), (n, 9, 9))  # ddxdF01, blocks [D, T_i, -T_j]
    c_i, t_i, c_j, t_j = frames
    J = np.zeros((n, 9, 24))
    J[:, 0:3, 0:12], J[:, 0:3, 12:24] = -jac_point(c_i), jac_point(c_j)
    J[:, 3:6, 0:12], J[:, 6:9, 12:24] = jac_vec(t_i), -jac_vec(t_j)
    return _assemble(x, per(offset), per(lower), per(upper), per(strength, 1.0), g_F, J, H_F)


def evaluate_batch(batch: dict, q: Array, q_prev: Array, q_ref: Array) -> Result:
    """One wire batch (a dict of the JSON request) over bodies (B, 12): the engine's numbers with
    the batch's `origin` (default "q_ref", as the wire's)."""
    ids = np.asarray(batch["body_ids"], dtype=np.int64).reshape(-1, 2)
    pair = lambda Q: (np.asarray(Q, dtype=np.float64)[ids[:, 0]], np.asarray(Q, dtype=np.float64)[ids[:, 1]])  # noqa: E731
    kw = dict(
        edges=None if batch.get("edges") is None else np.asarray(batch["edges"], dtype=np.float64),
        local_edges=None if batch.get("local_edges") is None else np.asarray(batch["local_edges"], dtype=np.float64),
        offset=batch.get("offset"),
        origin=batch.get("origin", "q_ref"),
    )
    args = (pair(q), pair(q_prev), pair(q_ref), batch["lower"], batch["upper"], batch.get("strength", 1.0))
    if batch["constitution_uid"] == 670:
        return revolute(*args, prev_coordinate=batch.get("prev_coordinate"), **kw)
    return prismatic(*args, **kw)
