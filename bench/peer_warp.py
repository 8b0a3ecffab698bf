"""Peer (d): the energy written as an NVIDIA Warp kernel, float64, on the CPU device, derivatives by `wp.Tape`.

What a simulation engineer who does not use this service would write: one thread per joint,
written from the specs (/work/shared/spec, CONTRACT.md) like the JAX peer (bench/peer_jax.py),
on the same inputs: each joint's two bodies gathered once per scene outside the timing
(q, q_prev, q_ref as (N, 24)), the world edge, the limits. Every call derives the joint's
frames from `q_ref` in the kernel (polar rotation of `A_ref` by Newton's iteration, the local
vectors, the anchors), as a stateless service must. Energy alone is one launch; energy +
gradient is that launch recorded on a `wp.Tape` and its adjoint (`tape.backward`), which
leaves the gradient (N, 24) per joint in `q24.grad`.

Threads: Warp's CPU device runs a launch on one thread (it has no CPU thread pool), so this
peer is single-threaded. Compile time is not counted: the constructor compiles (or loads from
Warp's kernel cache) and runs each kernel once.
"""

from __future__ import annotations

from typing import Any

import numpy as np

import warp as wp

from jointlimits.service.core import Bodies, Joints

wp.config.log_level = 30  # logging.WARNING: no banner or module-load lines on stdout (the bench's last line is its own)
wp.init()

DEVICE = "cpu"
THREADS = 1
NAME = "Warp CPU kernel, same inputs"
f64 = wp.float64


@wp.func
def _polar(A: wp.mat33d) -> wp.mat33d:
    """Orthogonal polar factor by Newton's iteration `X <- (X + X^-T) / 2` (as the JAX peer: 6 steps
    converge to rounding for the bench's near-rotations)."""
    X = A
    for _ in range(6):
        X = f64(0.5) * (X + wp.transpose(wp.inverse(X)))
    return X


@wp.func
def _rows(q: wp.array2d(dtype=f64), j: int, body: int) -> wp.mat33d:
    """`A` (3 x 3, row-major in the DOFs) of body `body` (0: i, 1: j) of joint `j` in `q` (N, 24)."""
    o = 12 * body + 3
    return wp.mat33d(q[j, o + 0], q[j, o + 1], q[j, o + 2],
                     q[j, o + 3], q[j, o + 4], q[j, o + 5],
                     q[j, o + 6], q[j, o + 7], q[j, o + 8])


@wp.func
def _pos(q: wp.array2d(dtype=f64), j: int, body: int) -> wp.vec3d:
    o = 12 * body
    return wp.vec3d(q[j, o + 0], q[j, o + 1], q[j, o + 2])


@wp.func
def _penalty(x: f64, lo: f64, up: f64, s: f64) -> f64:
    """The contract's cubic penalty `s (gap / width)^3` (width 1 for a degenerate range)."""
    w = f64(1.0)
    if up > lo:
        w = up - lo
    g = f64(0.0)
    if x > up:
        g = x - up
    elif x < lo:
        g = lo - x
    r = g / w
    return s * r * r * r


@wp.func
def _cos_sin(q: wp.array2d(dtype=f64), j: int, bi: wp.vec3d, ni: wp.vec3d, bj: wp.vec3d, nj: wp.vec3d) -> wp.vec2d:
    """(cos, sin) of the #670 angle in state `q`: frames B_k = A_k b_k, N_k = A_k n_k."""
    Ai = _rows(q, j, 0)
    Aj = _rows(q, j, 1)
    Bi = Ai * bi
    Ni = Ai * ni
    Bj = Aj * bj
    Nj = Aj * nj
    return wp.vec2d(f64(0.5) * (wp.dot(Bi, Bj) + wp.dot(Ni, Nj)), f64(0.5) * (wp.dot(Bi, Nj) - wp.dot(Ni, Bj)))


@wp.func
def _delta(a: wp.vec2d, b: wp.vec2d) -> f64:
    """The angle from (cos, sin) `b` to `a`, in (-pi, pi]."""
    return wp.atan2(a[1] * b[0] - a[0] * b[1], a[0] * b[0] + a[1] * b[1])


@wp.func
def _theta(q: wp.array2d(dtype=f64), j: int, ci: wp.vec3d, ti: wp.vec3d, cj: wp.vec3d, tj: wp.vec3d) -> f64:
    """The #669 slide `(C_j - C_i) . (T_i + T_j) / 2` in state `q`, C_k = p_k + A_k c_k (body i's p first
    subtracted), T_k = A_k t_k."""
    Ai = _rows(q, j, 0)
    Aj = _rows(q, j, 1)
    dp = _pos(q, j, 1) - _pos(q, j, 0)
    D = dp + Aj * cj - Ai * ci
    return f64(0.5) * wp.dot(D, Ai * ti + Aj * tj)


@wp.func
def _revolute_local(q_ref: wp.array2d(dtype=f64), edges: wp.array2d(dtype=wp.vec3d), j: int) -> wp.mat44d:
    """Body-local b_i, n_i, b_j, n_j of #670 joint `j` (rows 0-3, first 3 columns): `b_k = R_k^T b`."""
    Ri = _polar(_rows(q_ref, j, 0))
    Rj = _polar(_rows(q_ref, j, 1))
    t = wp.normalize(edges[j, 1] - edges[j, 0])
    test = wp.vec3d(f64(1.0), f64(0.0), f64(0.0))
    if wp.abs(t[0]) > f64(0.9):
        test = wp.vec3d(f64(0.0), f64(1.0), f64(0.0))
    n = wp.normalize(wp.cross(t, test))
    b = wp.normalize(wp.cross(t, n))
    return _pack(wp.transpose(Ri) * b, wp.transpose(Ri) * n, wp.transpose(Rj) * b, wp.transpose(Rj) * n)


@wp.func
def _prismatic_local(q_ref: wp.array2d(dtype=f64), edges: wp.array2d(dtype=wp.vec3d), j: int) -> wp.mat44d:
    """Body-local c_i, t_i, c_j, t_j of #669 joint `j`: anchors `c_k = A_k^-1 (p0 - p_k)`, axes `t_k = R_k^T t`."""
    Ai = _rows(q_ref, j, 0)
    Aj = _rows(q_ref, j, 1)
    p0 = edges[j, 0]
    t = wp.normalize(edges[j, 1] - p0)
    ci = wp.inverse(Ai) * (p0 - _pos(q_ref, j, 0))
    cj = wp.inverse(Aj) * (p0 - _pos(q_ref, j, 1))
    return _pack(ci, wp.transpose(_polar(Ai)) * t, cj, wp.transpose(_polar(Aj)) * t)


@wp.func
def _pack(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, d: wp.vec3d) -> wp.mat44d:
    return wp.mat44d(a[0], a[1], a[2], f64(0.0), b[0], b[1], b[2], f64(0.0),
                     c[0], c[1], c[2], f64(0.0), d[0], d[1], d[2], f64(0.0))


@wp.func
def _vec(v: wp.mat44d, k: int) -> wp.vec3d:
    return wp.vec3d(v[k, 0], v[k, 1], v[k, 2])


@wp.func
def _revolute_x(q: wp.array2d(dtype=f64), q_prev: wp.array2d(dtype=f64), q_ref: wp.array2d(dtype=f64), j: int,
                v: wp.mat44d) -> f64:
    """#670: x = DeltaTheta(q_prev, q_ref) + DeltaTheta(q, q_prev)."""
    cs_ref = _cos_sin(q_ref, j, _vec(v, 0), _vec(v, 1), _vec(v, 2), _vec(v, 3))
    cs_prev = _cos_sin(q_prev, j, _vec(v, 0), _vec(v, 1), _vec(v, 2), _vec(v, 3))
    cs = _cos_sin(q, j, _vec(v, 0), _vec(v, 1), _vec(v, 2), _vec(v, 3))
    return _delta(cs_prev, cs_ref) + _delta(cs, cs_prev)


@wp.func
def _prismatic_x(q: wp.array2d(dtype=f64), q_prev: wp.array2d(dtype=f64), q_ref: wp.array2d(dtype=f64), j: int,
                 v: wp.mat44d) -> f64:
    """#669: x = theta(q) - theta(q_ref) (the incremental form telescopes; q_prev is not read)."""
    return (_theta(q, j, _vec(v, 0), _vec(v, 1), _vec(v, 2), _vec(v, 3))
            - _theta(q_ref, j, _vec(v, 0), _vec(v, 1), _vec(v, 2), _vec(v, 3)))


@wp.kernel
def revolute_energy(q: wp.array2d(dtype=f64), q_prev: wp.array2d(dtype=f64), q_ref: wp.array2d(dtype=f64),
                    edges: wp.array2d(dtype=wp.vec3d), lower: wp.array(dtype=f64), upper: wp.array(dtype=f64),
                    strength: wp.array(dtype=f64), energy: wp.array(dtype=f64)):
    """Energy alone, one kernel: the joint's frames from q_ref, then x and the penalty."""
    j = wp.tid()
    x = _revolute_x(q, q_prev, q_ref, j, _revolute_local(q_ref, edges, j))
    energy[j] = _penalty(x, lower[j], upper[j], strength[j])


@wp.kernel
def prismatic_energy(q: wp.array2d(dtype=f64), q_prev: wp.array2d(dtype=f64), q_ref: wp.array2d(dtype=f64),
                     edges: wp.array2d(dtype=wp.vec3d), lower: wp.array(dtype=f64), upper: wp.array(dtype=f64),
                     strength: wp.array(dtype=f64), energy: wp.array(dtype=f64)):
    j = wp.tid()
    x = _prismatic_x(q, q_prev, q_ref, j, _prismatic_local(q_ref, edges, j))
    energy[j] = _penalty(x, lower[j], upper[j], strength[j])


# Energy + gradient: the frames kernel runs before the tape (nothing differentiates through q_ref, and
# its adjoint, the polar iteration's, would only cost), the energy kernel of the frames on the tape.
@wp.kernel
def revolute_frames(q_ref: wp.array2d(dtype=f64), edges: wp.array2d(dtype=wp.vec3d), local: wp.array(dtype=wp.mat44d)):
    j = wp.tid()
    local[j] = _revolute_local(q_ref, edges, j)


@wp.kernel
def prismatic_frames(q_ref: wp.array2d(dtype=f64), edges: wp.array2d(dtype=wp.vec3d), local: wp.array(dtype=wp.mat44d)):
    j = wp.tid()
    local[j] = _prismatic_local(q_ref, edges, j)


@wp.kernel
def revolute_energy_of_frames(q: wp.array2d(dtype=f64), q_prev: wp.array2d(dtype=f64), q_ref: wp.array2d(dtype=f64),
                              local: wp.array(dtype=wp.mat44d), lower: wp.array(dtype=f64), upper: wp.array(dtype=f64),
                              strength: wp.array(dtype=f64), energy: wp.array(dtype=f64)):
    j = wp.tid()
    energy[j] = _penalty(_revolute_x(q, q_prev, q_ref, j, local[j]), lower[j], upper[j], strength[j])


@wp.kernel
def prismatic_energy_of_frames(q: wp.array2d(dtype=f64), q_prev: wp.array2d(dtype=f64), q_ref: wp.array2d(dtype=f64),
                               local: wp.array(dtype=wp.mat44d), lower: wp.array(dtype=f64), upper: wp.array(dtype=f64),
                               strength: wp.array(dtype=f64), energy: wp.array(dtype=f64)):
    j = wp.tid()
    energy[j] = _penalty(_prismatic_x(q, q_prev, q_ref, j, local[j]), lower[j], upper[j], strength[j])


KERNELS = {670: (revolute_energy, revolute_frames, revolute_energy_of_frames),
           669: (prismatic_energy, prismatic_frames, prismatic_energy_of_frames)}


class _Batch:
    """One batch's device arrays (gathered per joint once, outside the timing) and its kernel."""

    def __init__(self, bodies: Bodies, joints: Joints) -> None:
        ids = joints.body_ids
        q24 = [np.ascontiguousarray(np.asarray(a, dtype=np.float64)[ids].reshape(-1, 24))
               for a in (bodies.q, bodies.q_prev, bodies.q_ref)]
        self.n = ids.shape[0]
        self.kernel, self.frames, self.of_frames = KERNELS[joints.constitution_uid]
        self.q = wp.array(q24[0], dtype=f64, device=DEVICE, requires_grad=True)
        self.rest = [wp.array(a, dtype=f64, device=DEVICE) for a in q24[1:]]
        self.rest.append(wp.array(np.ascontiguousarray(joints.edges, dtype=np.float64), dtype=wp.vec3d, device=DEVICE))
        self.rest += [wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=f64, device=DEVICE)
                      for a in (joints.lower, joints.upper, joints.strength)]
        self.energy = wp.zeros(self.n, dtype=f64, device=DEVICE, requires_grad=True)
        self.ones = wp.array(np.ones(self.n), dtype=f64, device=DEVICE)
        self.local = wp.zeros(self.n, dtype=wp.mat44d, device=DEVICE)

    def launch(self) -> None:
        wp.launch(self.kernel, dim=self.n, inputs=[self.q, *self.rest], outputs=[self.energy], device=DEVICE)

    def energy_and_gradient(self) -> tuple[wp.array, wp.array]:
        """The launch recorded on a tape, then its adjoint: energy (N,) and its gradient in q (N, 24)."""
        q_ref, edges = self.rest[1], self.rest[2]
        wp.launch(self.frames, dim=self.n, inputs=[q_ref, edges], outputs=[self.local], device=DEVICE)
        tape = wp.Tape()
        with tape:
            wp.launch(self.of_frames, dim=self.n, inputs=[self.q, self.rest[0], q_ref, self.local, *self.rest[3:]],
                      outputs=[self.energy], device=DEVICE)
        self.q.grad.zero_()  # the adjoint accumulates: each call starts from zero
        tape.backward(grads={self.energy: self.ones})
        return self.energy, self.q.grad


class WarpPeer:
    """Evaluate a scene (list of batches) with the Warp kernels: "e" energy, "eg" energy + gradient (Tape)."""

    def __init__(self, bodies: Bodies, batches: list[Joints]) -> None:
        self.batches = [_Batch(bodies, j) for j in batches]
        for mode in ("e", "eg"):  # compile (or load from Warp's cache) and run once: not timed
            self(mode)

    def __call__(self, mode: str) -> list[Any]:
        """Per batch: energy (N,) for "e"; (energy (N,), gradient (N, 24)) for "eg" (Warp arrays, on the CPU)."""
        if mode == "e":
            for b in self.batches:
                b.launch()
            wp.synchronize_device(DEVICE)
            return [b.energy for b in self.batches]
        if mode != "eg":
            raise ValueError(f"the Warp peer has no mode {mode!r} (energy 'e' and energy + gradient 'eg')")
        out = [b.energy_and_gradient() for b in self.batches]
        wp.synchronize_device(DEVICE)
        return out

    def results(self) -> list[dict[str, np.ndarray]]:
        """Energy and gradient per batch as NumPy arrays, keyed like the core's results."""
        return [{"energy": e.numpy().copy(), "gradient": g.numpy().copy()} for e, g in self("eg")]
