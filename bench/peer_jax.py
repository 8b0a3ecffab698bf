"""Peer (a): the energy written in JAX, derivatives by autodiff, `jit(vmap(...))`, float64.

This is what a user would write instead of calling the service: one scalar function per
joint of its 24 DOFs, with `jax.grad` and `jax.hessian` doing the rest. It follows
CONTRACT.md exactly (same frames, same incremental coordinate, same penalty). Two flavours:

- `same_work=True`: every call starts from the same inputs the core gets (bodies at
  q, q_prev, q_ref, edges, limits) and derives the joint frames itself (polar rotation by
  SVD of A_ref, local vectors), as the stateless service must.
- `same_work=False`: the frames (body-local vectors) are precomputed once per scene, outside
  the timing, and only the per-step function of (q, q_prev, q_ref) is timed: the strongest
  peer a JAX user could write.

The psd mode differentiates `x(F)` twice in `F`, clamps the 12 x 12 curvature's eigenvalues
with `eigh`, and applies the chain rule with `jacfwd` of `F(q)`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_platforms", "cpu")
import jax.numpy as jnp  # noqa: E402

from jointlimits.service.core import Bodies, Joints  # noqa: E402

# (name in the report, same_work): the fair peer first, the strongest second.
FLAVOURS = [("JAX jit(vmap), same inputs", True), ("JAX jit(vmap), frames precomputed", False)]
E_X = jnp.array([1.0, 0.0, 0.0])
E_Y = jnp.array([0.0, 1.0, 0.0])


def _unit(v: jax.Array) -> jax.Array:
    return v / jnp.linalg.norm(v)


def _split2(q2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Positions (2, 3) and affine matrices (2, 3, 3) of the two bodies `q2` (2, 12)."""
    return q2[:, :3], q2[:, 3:].reshape(2, 3, 3)


def _inv(A: jax.Array) -> jax.Array:
    """3 x 3 inverse by cofactors: batched LAPACK calls (`inv`, `solve`) stall under `vmap` at 5e4."""
    C = jnp.stack([jnp.cross(A[1], A[2]), jnp.cross(A[2], A[0]), jnp.cross(A[0], A[1])])  # rows: cofactors^T
    return C.T / (A[0] @ C[0])


def _polar(A: jax.Array) -> jax.Array:
    """Orthogonal polar factor by Newton's iteration `X <- (X + X^-T) / 2`.

    `jnp.linalg.svd` under `vmap` stalls for 5e4 matrices on CPU (minutes), so the peer uses
    the iteration a careful JAX user would: 6 steps converge to rounding for the bench's
    near-rotations (quadratic from a strain of 1e-2).
    """
    X = A
    for _ in range(6):
        X = 0.5 * (X + _inv(X).T)
    return X


def _local_vectors(uid: int, q_ref2: jax.Array, edge: jax.Array) -> jax.Array:
    """(4, 3) body-local vectors of one joint; `q_ref2` (2, 12), `edge` (2, 3)."""
    p, A = _split2(q_ref2)
    R = jax.vmap(_polar)(A)
    t = _unit(edge[1] - edge[0])
    if uid == 670:
        test = jnp.where(jnp.abs(t[0]) > 0.9, E_Y, E_X)
        n = _unit(jnp.cross(t, test))
        b = _unit(jnp.cross(t, n))
        return jnp.stack([R[0].T @ b, R[0].T @ n, R[1].T @ b, R[1].T @ n])
    c0 = _inv(A[0]) @ (edge[0] - p[0])
    c1 = _inv(A[1]) @ (edge[0] - p[1])
    return jnp.stack([c0, R[0].T @ t, c1, R[1].T @ t])


def _frames(uid: int, q2: jax.Array, v: jax.Array) -> jax.Array:
    """F (4, 3) from one state of the two bodies `q2` (2, 12) and the local vectors `v` (4, 3)."""
    p, A = _split2(q2)
    if uid == 670:
        return jnp.stack([A[0] @ v[0], A[0] @ v[1], A[1] @ v[2], A[1] @ v[3]])
    dp = p[1] - p[0]
    return jnp.stack([A[0] @ v[0], A[0] @ v[1], dp + A[1] @ v[2], A[1] @ v[3]])


def _cos_sin(F: jax.Array) -> tuple[jax.Array, jax.Array]:
    """cos and sin of the #670 angle between the two bodies' frames, F (4, 3)."""
    return 0.5 * (F[0] @ F[2] + F[1] @ F[3]), 0.5 * (F[0] @ F[3] - F[1] @ F[2])


def _delta(a: tuple[jax.Array, jax.Array], b: tuple[jax.Array, jax.Array]) -> jax.Array:
    """The angle from (cos, sin) `b` to `a`, in (-pi, pi]."""
    (ca, sa), (cb, sb) = a, b
    return jnp.arctan2(sa * cb - ca * sb, ca * cb + sa * sb)


def _theta(F: jax.Array) -> jax.Array:
    """The #669 slide along the axis, F (4, 3)."""
    return 0.5 * (F[2] - F[0]) @ (F[1] + F[3])


def _coordinate_of_F(uid: int, F: jax.Array, F_prev: jax.Array, F_ref: jax.Array) -> jax.Array:
    """The joint coordinate x: incremental for #670 (through q_prev), relative to q_ref for #669."""
    if uid == 670:
        cs_prev = _cos_sin(F_prev)
        return _delta(cs_prev, _cos_sin(F_ref)) + _delta(_cos_sin(F), cs_prev)
    return _theta(F) - _theta(F_ref)


def _penalty(x: jax.Array, lo: jax.Array, up: jax.Array, s: jax.Array) -> jax.Array:
    """The contract's cubic penalty `s (gap / width)^3` of one joint."""
    w = jnp.where(up > lo, up - lo, 1.0)
    g = jnp.where(x > up, x - up, jnp.where(x < lo, lo - x, 0.0))
    r = g / w
    return s * r * r * r


@functools.cache  # one set per flavour: a jitted function compiles once per shape, and the all-active scene has the
# typical scene's shapes (10-15 s of XLA compiling per E+G+H function here, never timed but waited for)
def make_functions(uid: int, same_work: bool, psd: bool = False) -> dict[str, Callable]:
    """Jitted, vmapped `e`, `eg`, `egh` (exact, or psd) over joints of one constitution.

    Arguments of each: q24 (N, 24), q24_prev (N, 24), q24_ref (N, 24), then either
    edges (N, 2, 3) (`same_work`) or local vectors (N, 4, 3), then lower, upper, strength (N,).
    """

    def setup(q_ref24: jax.Array, geo: jax.Array) -> jax.Array:
        return _local_vectors(uid, q_ref24.reshape(2, 12), geo) if same_work else geo

    def energy(q24: jax.Array, q_prev24: jax.Array, q_ref24: jax.Array, geo: jax.Array,
               lo: jax.Array, up: jax.Array, s: jax.Array) -> jax.Array:
        v = setup(q_ref24, geo)
        F = [_frames(uid, a.reshape(2, 12), v) for a in (q24, q_prev24, q_ref24)]
        return _penalty(_coordinate_of_F(uid, *F), lo, up, s)

    def egh(q24: jax.Array, *rest: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        e, g = jax.value_and_grad(energy)(q24, *rest)
        return e, g, jax.hessian(energy)(q24, *rest)

    def egh_psd(q24: jax.Array, q_prev24: jax.Array, q_ref24: jax.Array, geo: jax.Array,
                lo: jax.Array, up: jax.Array, s: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        v = setup(q_ref24, geo)
        Fq = lambda q: _frames(uid, q.reshape(2, 12), v).reshape(12)  # noqa: E731
        F_prev, F_ref = (_frames(uid, a.reshape(2, 12), v) for a in (q_prev24, q_ref24))
        xF = lambda F: _coordinate_of_F(uid, F.reshape(4, 3), F_prev, F_ref)  # noqa: E731
        F = Fq(q24)
        x, dx = jax.value_and_grad(xF)(F)
        d2x = jax.hessian(xF)(F)
        pen = lambda x: _penalty(x, lo, up, s)  # noqa: E731
        e, dE = jax.value_and_grad(pen)(x)
        d2E = jax.grad(jax.grad(pen))(x)
        lam, V = jnp.linalg.eigh(dE * d2x)
        curv = (V * jnp.maximum(lam, 0.0)) @ V.T
        J = jax.jacfwd(Fq)(q24)  # (12, 24)
        dxq = dx @ J
        return e, dE * dxq, d2E * jnp.outer(dxq, dxq) + J.T @ curv @ J

    return {
        "e": jax.jit(jax.vmap(energy)),
        "eg": jax.jit(jax.vmap(jax.value_and_grad(energy))),
        "egh": jax.jit(jax.vmap(egh_psd if psd else egh)),
    }


def pack_inputs(bodies: Bodies, joints: Joints, same_work: bool) -> tuple:
    """Device arrays for one batch (gathered per joint, outside the timing)."""
    ids = joints.body_ids
    q24 = [np.asarray(a)[ids].reshape(-1, 24) for a in (bodies.q, bodies.q_prev, bodies.q_ref)]
    if same_work:
        geo = joints.edges
    else:
        geo = np.asarray(
            jax.jit(jax.vmap(lambda q, e: _local_vectors(joints.constitution_uid, q.reshape(2, 12), e)))(
                q24[2], joints.edges
            )
        )  # precomputed once per scene, outside the timing
    return tuple(jnp.asarray(a) for a in (*q24, geo, joints.lower, joints.upper, joints.strength))


class JaxPeer:
    """Evaluate a scene (list of batches) with the JAX functions (psd: the projected Hessian for "egh")."""

    def __init__(self, bodies: Bodies, batches: list[Joints], same_work: bool = True, psd: bool = False) -> None:
        self.inputs = [pack_inputs(bodies, j, same_work) for j in batches]
        self.fns = [make_functions(j.constitution_uid, same_work, psd) for j in batches]
        self.uids = [j.constitution_uid for j in batches]

    def __call__(self, mode: str) -> list[Any]:
        """Per batch, device arrays: energy (N,) for "e", (E, G (N, 24)) for "eg", (E, G, H (N, 24, 24)) for "egh"."""
        return jax.block_until_ready([fn[mode](*args) for fn, args in zip(self.fns, self.inputs)])

    def results(self, pad_to: dict[int, int] | None = None) -> list[dict[str, np.ndarray]]:
        """E+G+H per batch as NumPy arrays, keyed like the core's results (energy, gradient, hessian).

        `pad_to` (uid -> joints): a batch with fewer joints is evaluated padded to that many with copies of its
        last joint and its rows cut back, so the executable already compiled for the timing scene's shape (the
        one timed) gives the accuracy too, instead of a compile for this shape (vmap: each row is its own joint).
        XLA vectorizes per shape, so rows can differ in their last bits from a compile for the cases' own shape
        (measured: relative 4e-15 at most, the hard cases' worst E error 1.18e-13 against 1.43e-13): the error
        reported is the one of the executable that was timed.
        """
        out = []
        for fn, args, uid in zip(self.fns, self.inputs, self.uids):
            m, n = args[0].shape[0], (pad_to or {}).get(uid, 0)
            if n > m:
                args = tuple(jnp.concatenate([a, jnp.repeat(a[-1:], n - m, axis=0)]) for a in args)
            e, g, h = jax.block_until_ready(fn["egh"](*args))
            out.append({"energy": np.asarray(e)[:m], "gradient": np.asarray(g)[:m], "hessian": np.asarray(h)[:m]})
        return out
