"""Seeded random and adversarial scenes in the CONTRACT v1 shape, for the project's own tests.

A `Scene` holds NumPy arrays (bodies `q`, `q_prev`, `q_ref` (B, 12) and one `Batch` per
constitution batch) and turns itself into a request dict (`Scene.request`) or the core's
keyword arguments (`Scene.core_args`). Generators take a `numpy.random.Generator`, so every
scene is reproducible from its seed.

Limits are placed from the joint coordinate the core computes (`place_limits`), so that a
joint is inside, above, below, on a bound (exactly, in float64) or in a degenerate range by
construction.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from jointlimits.service.core import Bodies, Joints, evaluate

BASE_UID = {670: 18, 669: 20}
E_X = np.array([1.0, 0.0, 0.0])


# ---------------------------------------------------------------- geometry helpers


def pack(p: np.ndarray, A: np.ndarray) -> np.ndarray:
    """12 DOFs `[p, A row 0, A row 1, A row 2]` from `p` (3,) and `A` (3, 3)."""
    return np.concatenate([np.asarray(p, dtype=np.float64), np.asarray(A, dtype=np.float64).reshape(9)])


def unpack(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return q[:3].copy(), q[3:].reshape(3, 3).copy()


def unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=np.float64) / np.linalg.norm(v)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Right-handed rotation by `angle` about `axis` (Rodrigues)."""
    k = unit(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def random_unit(rng: np.random.Generator) -> np.ndarray:
    return unit(rng.normal(size=3))


def random_rotation(rng: np.random.Generator, max_angle: float = np.pi) -> np.ndarray:
    return rotation_about(random_unit(rng), rng.uniform(-max_angle, max_angle))


def random_affine(rng: np.random.Generator, strain: float = 0.2, max_cond: float = 3.0) -> np.ndarray:
    """A rotation times `I + strain * G` (det > 0, condition number <= max_cond): non-rigid, well conditioned."""
    R = random_rotation(rng)
    while True:
        S = np.eye(3) + strain * rng.uniform(-1.0, 1.0, size=(3, 3))
        if np.linalg.det(S) > 0 and np.linalg.cond(S) <= max_cond:
            return R @ S


def rigid_motion(q: np.ndarray, R: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Every body of `q` (B, 12) moved by the world motion `X -> R X + d`: p -> R p + d, A -> R A."""
    out = np.empty_like(q)
    for b, row in enumerate(q):
        p, A = unpack(row)
        out[b] = pack(R @ p + d, R @ A)
    return out


def dof_transform(R: np.ndarray) -> np.ndarray:
    """T (12, 12) with q' = T q + [d, 0] for the motion above; gradients map as T g, Hessians as T H T^T."""
    T = np.zeros((12, 12))
    T[:3, :3] = R
    T[3:, 3:] = np.kron(R, np.eye(3))  # row-major vec(R A) = (R (x) I) vec(A)
    return T


# ---------------------------------------------------------------- scene containers


@dataclass
class Batch:
    uid: int
    body_ids: np.ndarray  # (N, 2) int
    edges: np.ndarray  # (N, 2, 3)
    lower: np.ndarray  # (N,)
    upper: np.ndarray  # (N,)
    strength: np.ndarray  # (N,)

    def wire(self) -> dict[str, Any]:
        return dict(
            constitution_uid=self.uid,
            base_uid=BASE_UID[self.uid],
            body_ids=self.body_ids.tolist(),
            edges=self.edges.tolist(),
            lower=self.lower.tolist(),
            upper=self.upper.tolist(),
            strength=self.strength.tolist(),
        )

    def joints(self) -> Joints:
        return Joints(self.uid, BASE_UID[self.uid], self.body_ids, self.edges, self.lower, self.upper, self.strength)


@dataclass
class Scene:
    q: np.ndarray
    q_prev: np.ndarray
    q_ref: np.ndarray
    batches: list[Batch] = field(default_factory=list)
    name: str = ""

    def bodies(self) -> Bodies:
        return Bodies(self.q, self.q_prev, self.q_ref)

    def request(
        self, outputs: Sequence[str] = ("energy", "gradient", "hessian"), hessian_mode: str = "exact", active_only: bool = False
    ) -> dict[str, Any]:
        """The CONTRACT v1 request body (plain lists: JSON-ready, exact float64 round trip)."""
        return dict(
            bodies=dict(q=self.q.tolist(), q_prev=self.q_prev.tolist(), q_ref=self.q_ref.tolist()),
            batches=[b.wire() for b in self.batches],
            outputs=list(outputs),
            hessian_mode=hessian_mode,
            active_only=active_only,
        )

    def core_args(self, **options: Any) -> dict[str, Any]:
        """Keyword arguments of `jointlimits.service.core.evaluate`."""
        return dict(bodies=self.bodies(), batches=[b.joints() for b in self.batches], **options)

    def moved(self, R: np.ndarray, d: np.ndarray) -> Scene:
        """The whole scene (three states and every edge) under the world motion X -> R X + d."""
        return replace(
            self,
            q=rigid_motion(self.q, R, d),
            q_prev=rigid_motion(self.q_prev, R, d),
            q_ref=rigid_motion(self.q_ref, R, d),
            batches=[replace(b, edges=b.edges @ R.T + d) for b in self.batches],
        )

    def x(self) -> list[np.ndarray]:
        """The core's joint coordinates, per batch (the limits do not matter for x)."""
        ev = evaluate(**self.core_args(outputs=("energy",)))
        return [r.x for r in ev.batches]


# ---------------------------------------------------------------- limits

KINDS = ("inside", "above", "below", "degenerate", "on_lower", "on_upper", "degenerate_on")


def place_limits(
    scene: Scene,
    rng: np.random.Generator,
    kinds: Sequence[str] | None = None,
    gap: tuple[float, float] = (0.05, 0.5),
    width: tuple[float, float] = (0.2, 1.5),
    strength: tuple[float, float] = (1.0, 1e3),
) -> Scene:
    """Limits around each joint's current x: `kinds` cycles over the joints (random choice when None).

    `above` / `below`: x is `gap` (relative to max(1, |x|)) past the bound, so x - u is well conditioned.
    `on_lower` / `on_upper`: the bound is the core's float64 x itself; `degenerate_on`: l == u == x.
    `degenerate`: u == l, `gap` away from x.
    """
    xs = scene.x()
    batches = []
    count = 0
    for b, x in zip(scene.batches, xs):
        n = x.shape[0]
        lo, up = np.empty(n), np.empty(n)
        for j in range(n):
            kind = kinds[count % len(kinds)] if kinds else KINDS[rng.integers(len(KINDS))]
            count += 1
            w = rng.uniform(*width)
            g = rng.uniform(*gap) * max(1.0, abs(x[j]))
            if kind == "inside":
                lo[j] = x[j] - rng.uniform(0.1, 0.9) * w
                up[j] = lo[j] + w
            elif kind == "above":
                up[j] = x[j] - g
                lo[j] = up[j] - w
            elif kind == "below":
                lo[j] = x[j] + g
                up[j] = lo[j] + w
            elif kind == "degenerate":
                lo[j] = up[j] = x[j] + rng.choice([-1.0, 1.0]) * g
            elif kind == "on_lower":
                lo[j], up[j] = x[j], x[j] + w
            elif kind == "on_upper":
                lo[j], up[j] = x[j] - w, x[j]
            elif kind == "degenerate_on":
                lo[j] = up[j] = x[j]
            else:
                raise ValueError(kind)
        s = np.exp(rng.uniform(np.log(strength[0]), np.log(strength[1]), size=n))
        batches.append(replace(b, lower=lo, upper=up, strength=s))
    return replace(scene, batches=batches)


# ---------------------------------------------------------------- generators


def _blank(uid: int, body_ids: np.ndarray, edges: np.ndarray) -> Batch:
    n = body_ids.shape[0]
    return Batch(uid, np.asarray(body_ids, dtype=np.int64).reshape(n, 2), np.asarray(edges, dtype=np.float64), np.zeros(n), np.ones(n), np.ones(n))


def random_edge(rng: np.random.Generator, near: np.ndarray, length: float = 1.0, spread: float = 0.5) -> np.ndarray:
    p0 = near + rng.uniform(-spread, spread, size=3)
    return np.stack([p0, p0 + length * random_unit(rng)])


def random_chain_scene(
    rng: np.random.Generator,
    n_bodies: int = 4,
    strain: float = 0.2,
    prev_angle: float = 0.3,
    step_angle: float = 0.2,
    step: float = 0.1,
    batch_uids: Sequence[int] = (670, 669, 670),
    extra_joints: int = 1,
) -> Scene:
    """Affine bodies in a chain (joint k couples bodies k, k+1) plus random extra pairs, spread over
    several batches mixing #670 and #669; every body moves generically between the three states.

    Rotations stay moderate so that no revolute frame comes near collapse (well conditioned).
    """
    p_ref = rng.uniform(-2.0, 2.0, size=(n_bodies, 3))
    A_ref = np.stack([random_affine(rng, strain) for _ in range(n_bodies)])
    A_prev = np.stack([random_rotation(rng, prev_angle) @ A @ (np.eye(3) + 0.05 * strain * rng.normal(size=(3, 3))) for A in A_ref])
    A = np.stack([random_rotation(rng, step_angle) @ Ap @ (np.eye(3) + 0.05 * strain * rng.normal(size=(3, 3))) for Ap in A_prev])
    p_prev = p_ref + step * rng.normal(size=(n_bodies, 3))
    p = p_prev + step * rng.normal(size=(n_bodies, 3))
    pairs = [(k, k + 1) for k in range(n_bodies - 1)]
    for _ in range(extra_joints):
        i, j = rng.choice(n_bodies, size=2, replace=False)
        pairs.append((int(i), int(j)))
    rng.shuffle(pairs)
    groups = [pairs[k :: len(batch_uids)] for k in range(len(batch_uids))]
    batches = []
    for uid, group in zip(batch_uids, groups):
        if not group:
            continue
        ids = np.array(group)
        edges = np.stack([random_edge(rng, 0.5 * (p_ref[i] + p_ref[j])) for i, j in group])
        batches.append(_blank(uid, ids, edges))
    sc = Scene(
        q=np.stack([pack(p[k], A[k]) for k in range(n_bodies)]),
        q_prev=np.stack([pack(p_prev[k], A_prev[k]) for k in range(n_bodies)]),
        q_ref=np.stack([pack(p_ref[k], A_ref[k]) for k in range(n_bodies)]),
        batches=batches,
        name="chain",
    )
    return sc


def axis_pair_scene(
    rng: np.random.Generator,
    uid: int,
    axis: np.ndarray,
    motion_prev: float,
    motion: float,
    strain: float = 0.0,
    jitter: float = 0.0,
    origin: np.ndarray | None = None,
    edge_length: float = 1.0,
    A_scale: np.ndarray | float = 1.0,
    common_rotation: bool = True,
) -> Scene:
    """Two bodies and one joint along `axis`: body j turns (670) or slides (669) relative to body i by
    `motion_prev` at q_prev and by `motion` in total at q, about / along +axis.

    With `strain == jitter == 0` and rotation A_ref, x == motion exactly (analytically).
    `A_scale` multiplies both A_ref (a scalar, or a (3,) anisotropic stretch in body space).
    `jitter` adds a small generic affine perturbation (relative to |A|) to q, so the frames are not exactly rigid.
    """
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    t = unit(axis)
    stretch = np.diag(np.broadcast_to(np.asarray(A_scale, dtype=np.float64), (3,)))
    A_ref = [random_affine(rng, strain) @ stretch if strain else random_rotation(rng) @ stretch for _ in range(2)]
    p_ref = [origin + rng.uniform(-1.0, 1.0, size=3) for _ in range(2)]
    p0 = origin + rng.uniform(-0.5, 0.5, size=3)
    edge = np.stack([p0, p0 + edge_length * t])
    Q = random_rotation(rng) if common_rotation else np.eye(3)  # both bodies also turn together (x unchanged)
    Qp = random_rotation(rng, 0.5) if common_rotation else np.eye(3)
    d, dp = rng.normal(size=3), rng.normal(size=3)

    def state(amount: float, W: np.ndarray, shift: np.ndarray) -> list[np.ndarray]:
        # World motion X -> W X + shift applied to both bodies, body j additionally moved about/along the edge.
        out = []
        for k in range(2):
            A, p = A_ref[k], p_ref[k]
            if k == 1:
                if uid == 670:
                    G = rotation_about(t, amount)
                    A, p = G @ A, p0 + G @ (p - p0)
                else:
                    p = p + amount * t
            out.append(pack(W @ p + shift, W @ A))
        return out

    q_ref = np.stack([pack(p_ref[k], A_ref[k]) for k in range(2)])
    q_prev = np.stack(state(motion_prev, Qp, dp))
    q = np.stack(state(motion, Q, d))
    if jitter:  # relative to the size of each body's A, so scaled bodies get the same relative noise
        q[:, 3:] += jitter * np.abs(q[:, 3:]).max(axis=1, keepdims=True) * rng.normal(size=(2, 9))
    return Scene(q, q_prev, q_ref, [_blank(uid, np.array([[0, 1]]), edge[None])], name=f"axis_pair_{uid}")


def planar_chain_scene(
    rng: np.random.Generator, n_bodies: int = 4, max_angle: float = 1.2, strain: float = 0.15, jitter: float = 0.02
) -> Scene:
    """A chain whose revolute axes are all parallel: bodies turn by large angles about that axis
    (x up to several radians relative to each other), plus prismatic joints on the same bodies."""
    axis = random_unit(rng)
    p_ref = rng.uniform(-2.0, 2.0, size=(n_bodies, 3))
    A_ref = np.stack([random_affine(rng, strain) for _ in range(n_bodies)])
    ang_prev = rng.uniform(-max_angle, max_angle, size=n_bodies)
    ang = ang_prev + rng.uniform(-0.5, 0.5, size=n_bodies)
    A_prev = np.stack([rotation_about(axis, a) @ A for a, A in zip(ang_prev, A_ref)])
    A = np.stack([rotation_about(axis, a) @ Ap for a, Ap in zip(ang - ang_prev, A_prev)])
    A += jitter * rng.normal(size=A.shape)
    p_prev = p_ref + 0.2 * rng.normal(size=(n_bodies, 3))
    p = p_prev + 0.2 * rng.normal(size=(n_bodies, 3))
    pairs = np.array([(k, k + 1) for k in range(n_bodies - 1)])
    rev_edges = np.stack([np.stack([c, c + axis]) for c in 0.5 * (p_ref[:-1] + p_ref[1:])])
    pri_edges = np.stack([random_edge(rng, c) for c in 0.5 * (p_ref[:-1] + p_ref[1:])])
    return Scene(
        q=np.stack([pack(p[k], A[k]) for k in range(n_bodies)]),
        q_prev=np.stack([pack(p_prev[k], A_prev[k]) for k in range(n_bodies)]),
        q_ref=np.stack([pack(p_ref[k], A_ref[k]) for k in range(n_bodies)]),
        batches=[_blank(670, pairs, rev_edges), _blank(669, pairs[::-1].copy(), pri_edges[::-1].copy())],
        name="planar_chain",
    )


def random_scene(rng: np.random.Generator, kinds: Sequence[str] | None = None) -> Scene:
    """One of the generic families above, with limits placed (the well-conditioned random family)."""
    if rng.uniform() < 0.6:
        sc = random_chain_scene(rng, n_bodies=int(rng.integers(2, 6)))
    else:
        sc = planar_chain_scene(rng, n_bodies=int(rng.integers(2, 5)))
    return place_limits(sc, rng, kinds)
