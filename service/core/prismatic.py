"""#669 AffineBodyPrismaticJointLimit: the slide of a prismatic joint (base UID 20).

F = [C_i, T_i, C_j, T_j], with C_k = p_k + A_k c_k (the anchor) and T_k = A_k t_k
(the axis), and

    theta = (C_j - C_i) . (T_i + T_j) / 2,   x = theta(q) - theta(q_ref).

The incremental form of the spec telescopes exactly to this difference.
theta is bilinear in F, so d2x/dF2 is a constant.
"""

from __future__ import annotations

import numpy as np

from service.core.constitution import Array
from service.core.kinematics import unit

# theta = D.S / 2 with D = C_j - C_i, S = T_i + T_j: coefficients of D and S per block.
_D = np.array([-1.0, 0.0, 1.0, 0.0])
_S = np.array([0.0, 1.0, 0.0, 1.0])
_PAIRS = 0.5 * (np.outer(_D, _S) + np.outer(_S, _D))  # (4, 4) block coefficients of d2theta/dF2
_D2X = np.einsum("kl,rs->krls", _PAIRS, np.eye(3))  # (4, 3, 4, 3)


def _theta(F: Array) -> Array:
    D = F[:, 2] - F[:, 0]
    S = F[:, 1] + F[:, 3]
    return 0.5 * np.einsum("nr,nr->n", D, S)


class Prismatic:
    uid = 669
    base_uid = 20
    name = "AffineBodyPrismaticJointLimit"
    alpha = np.array([1.0, 0.0, 1.0, 0.0])

    def local_vectors(self, edges: Array, p_ref: Array, A_ref: Array, R_ref: Array) -> Array:
        t = unit(edges[:, 1] - edges[:, 0])
        # c_k = A_ref_k^{-1} (p0 - p_ref_k): the difference first, then the solve.
        c = np.linalg.solve(A_ref, (edges[:, :1] - p_ref)[..., None])[..., 0]  # (N, 2, 3)
        t_local = np.einsum("nr,nkrc->nkc", t, R_ref)  # R_k^T t
        return np.stack([c[:, 0], t_local[:, 0], c[:, 1], t_local[:, 1]], axis=1)

    def coordinate(self, F: Array, F_prev: Array, F_ref: Array) -> Array:
        return _theta(F) - _theta(F_ref)

    def collapsed(self, F: Array) -> np.ndarray:
        return np.zeros(F.shape[0], dtype=bool)

    def derivatives(self, F: Array, second: bool) -> tuple[Array, Array | None]:
        D = F[:, 2] - F[:, 0]
        S = F[:, 1] + F[:, 3]
        dx = 0.5 * (_D[None, :, None] * S[:, None, :] + _S[None, :, None] * D[:, None, :])
        if not second:
            return dx, None
        return dx, np.broadcast_to(_D2X, (F.shape[0], 4, 3, 4, 3))


PRISMATIC = Prismatic()
