"""Synthetic scenes for the bench: half revolute, half prismatic, a chosen fraction outside its range.

Bodies are rigid-ish affine bodies (a rotation times `I + small strain`) scattered in a
box; every joint couples two random distinct bodies. `q_prev` and `q` are small steps
from `q_ref`, so each joint moves by a few hundredths of a radian or length unit. The
limits are then placed around each joint's current coordinate so that exactly the
requested fraction is outside (by a random amount up to 20% of the range width).
"""

from __future__ import annotations

import numpy as np

from service.core import Bodies, Joints, evaluate


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
    """A scene of `n_joints` joints (half #670, half #669), `outside` of them past a limit."""
    rng = np.random.default_rng(seed)
    n_bodies = max(2, n_joints // 2 + 2)
    bodies = _bodies(rng, n_bodies, step, strain)
    batches = []
    counts = {670: (n_joints + 1) // 2, 669: n_joints // 2}
    for uid, base in ((670, 18), (669, 20)):
        n = counts[uid]
        i = rng.integers(0, n_bodies, size=n)
        j = (i + rng.integers(1, n_bodies, size=n)) % n_bodies
        p0 = bodies.q_ref[i, :3] + rng.uniform(-0.5, 0.5, size=(n, 3))
        t = rng.normal(size=(n, 3))
        edges = np.stack([p0, p0 + t / np.linalg.norm(t, axis=1, keepdims=True)], axis=1)
        wide = np.full(n, 1e3)
        probe = Joints(uid, base, np.stack([i, j], axis=1), edges, -wide, wide, np.ones(n))
        x = evaluate(bodies, [probe], outputs=("energy",)).batches[0].x
        width = rng.uniform(0.2, 1.0, size=n)
        out = rng.random(n) < outside
        above = rng.random(n) < 0.5
        past = rng.uniform(0.01, 0.2, size=n) * width
        # Inside: x sits somewhere strictly within [lower, upper].
        lower = x - rng.uniform(0.05, 0.95, size=n) * width
        # Outside: the whole range lies below (above) x by `past`.
        lower = np.where(out & above, x - past - width, lower)
        lower = np.where(out & ~above, x + past, lower)
        upper = lower + width
        strength = rng.uniform(10.0, 1e3, size=n)
        batches.append(Joints(uid, base, probe.body_ids, edges, lower, upper, strength))
    return bodies, batches
