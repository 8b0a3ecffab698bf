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


def split(q: Array) -> tuple[Array, Array]:
    """`q` (..., 12) -> `p` (..., 3), `A` (..., 3, 3) as views."""
    return q[..., :3], q[..., 3:].reshape(*q.shape[:-1], 3, 3)


def polar_rotation(A: Array) -> tuple[Array, Array]:
    """Orthogonal polar factor of each `A` (M, 3, 3) and its conditioning ratio `s_min / s_max` (M,)."""
    U, s, Vt = np.linalg.svd(A)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = s[:, -1] / s[:, 0]
    return U @ Vt, np.nan_to_num(ratio, nan=0.0)


def frame_quantities(q_pair: Array, alpha: Array, v: Array) -> Array:
    """`F` (N, 4, 3) of joints whose bodies are in state `q_pair` (N, 2, 12).

    `alpha` (4,) and `v` (N, 4, 3) as in the module docstring.
    """
    p, A = split(q_pair)
    A_k = A[:, BLOCK_BODY]  # (N, 4, 3, 3)
    F = np.einsum("nkrc,nkc->nkr", A_k, v)
    if alpha.any():
        # Nearby positions are differenced before anything large is added.
        dp = p - p[:, :1]  # (N, 2, 3)
        F += alpha[None, :, None] * dp[:, BLOCK_BODY]
    return F


def unit(v: Array) -> Array:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
