"""Synthetic scenes for the bench: half revolute, half prismatic, a chosen fraction outside its range.

Bodies are rigid-ish affine bodies (a rotation times `I + small strain`) scattered in a
box; every joint couples two random distinct bodies. `q_prev` and `q` are small steps
from `q_ref`, so each joint moves by a few hundredths of a radian or length unit. The
limits are then placed around each joint's current coordinate so that exactly
`round(outside * n_joints)` joints are outside (by a random amount up to 20% of the range width).
"""

from __future__ import annotations

import numpy as np

from jointlimits.service.core import Bodies, Joints, evaluate

# (constitution uid, base uid): #670 revolute, #669 prismatic.
CONSTITUTIONS = ((670, 18), (669, 20))


def _rotations(rng: np.random.Generator, n: int, scale: float = np.pi) -> np.ndarray:
    """(n, 3, 3) rotations about random axes by angles up to `scale` (Rodrigues)."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = rng.uniform(-scale, scale, size=n)
    K = np.zeros((n, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K -= K.transpose(0, 2, 1)
    s, c = np.sin(ang)[:, None, None], np.cos(ang)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * K @ K


def _bodies(rng: np.random.Generator, n: int, step: float, strain: float) -> Bodies:
    """`n` bodies: q_ref (n, 12) a strained rotation, q_prev and q two random steps of size `step`."""
    p_ref = rng.uniform(-10, 10, size=(n, 3))
    A_ref = _rotations(rng, n) @ (np.eye(3) + strain * rng.normal(size=(n, 3, 3)))
    dR1, dR2 = _rotations(rng, n, step), _rotations(rng, n, step)
    A_prev = dR1 @ A_ref
    A = dR2 @ A_prev
    p_prev = p_ref + step * rng.normal(size=(n, 3))
    p = p_prev + step * rng.normal(size=(n, 3))
    pack = lambda p, A: np.concatenate([p, A.reshape(n, 9)], axis=1)  # noqa: E731
    return Bodies(q=pack(p, A), q_prev=pack(p_prev, A_prev), q_ref=pack(p_ref, A_ref))


def make_scene(
    n_joints: int,
    outside: float = 0.1,
    seed: int = 0,
    step: float = 0.05,
    strain: float = 0.01,
) -> tuple[Bodies, list[Joints]]:
    """A scene of `n_joints` joints: ceil(n/2) #670 then floor(n/2) #669, `round(outside * n)` past a limit."""
    rng = np.random.default_rng(seed)
    n_bodies = max(2, n_joints // 2 + 2)
    bodies = _bodies(rng, n_bodies, step, strain)
    # Exactly the requested count outside (a Bernoulli draw per joint would only be close): the
    # active-only measurement and the tests rely on it.
    out_all = np.zeros(n_joints, dtype=bool)
    out_all[rng.permutation(n_joints)[: round(outside * n_joints)]] = True
    counts = ((n_joints + 1) // 2, n_joints // 2)
    batches = []
    for (uid, base), n, out in zip(CONSTITUTIONS, counts, np.split(out_all, [counts[0]])):
        i = rng.integers(0, n_bodies, size=n)
        j = (i + rng.integers(1, n_bodies, size=n)) % n_bodies
        p0 = bodies.q_ref[i, :3] + rng.uniform(-0.5, 0.5, size=(n, 3))
        t = rng.normal(size=(n, 3))
        edges = np.stack([p0, p0 + t / np.linalg.norm(t, axis=1, keepdims=True)], axis=1)
        wide = np.full(n, 1e3)
        # The core itself gives each joint's coordinate x, around which the limits are placed.
        probe = Joints(uid, base, np.stack([i, j], axis=1), edges, -wide, wide, np.ones(n))
        x = evaluate(bodies, [probe], outputs=("energy",)).batches[0].x
        width = rng.uniform(0.2, 1.0, size=n)
        above = rng.random(n) < 0.5
        past = rng.uniform(0.01, 0.2, size=n) * width
        # Inside: x sits strictly within [lower, upper], at least 5% of the width from either end.
        lower = x - rng.uniform(0.05, 0.95, size=n) * width
        # Outside: the whole range lies below (above) x by `past`.
        lower = np.where(out & above, x - past - width, lower)
        lower = np.where(out & ~above, x + past, lower)
        upper = lower + width
        strength = rng.uniform(10.0, 1e3, size=n)
        batches.append(Joints(uid, base, probe.body_ids, edges, lower, upper, strength))
    return bodies, batches


def shifted(bodies: Bodies, batches: list[Joints], d: float) -> tuple[Bodies, list[Joints]]:
    """The same scene translated by `d` along (1, 1, 1): every joint coordinate x is unchanged (up to rounding)."""
    off = np.zeros(12)
    off[:3] = d
    moved = Bodies(*(a + off for a in (bodies.q, bodies.q_prev, bodies.q_ref)))
    return moved, [Joints(j.constitution_uid, j.base_uid, j.body_ids, j.edges + d, j.lower, j.upper, j.strength)
                   for j in batches]
