"""#670 AffineBodyRevoluteJointLimit: the angle of a revolute joint (base UID 18).

F = [B_i, N_i, B_j, N_j], with B_k = A_k b_k, N_k = A_k n_k, and

    cos = (B_i.B_j + N_i.N_j) / 2,   sin = (B_i.N_j - N_i.B_j) / 2,

so that turning body j by +phi about +t relative to body i gives x = +phi.
x is atan2(sin, cos) measured incrementally: its derivatives in (cos, sin) are
those of the polar angle, d(x) = (cos d(sin) - sin d(cos)) / r^2.
"""

from __future__ import annotations

import numpy as np

from service.core.constitution import Array
from service.core.kinematics import unit

E_X = np.array([1.0, 0.0, 0.0])
E_Y = np.array([0.0, 1.0, 0.0])

# Constant second derivatives of the bilinear cos and sin in the (4 x 4) block
# layout of F; each block is a multiple of the 3 x 3 identity.
_COS_PAIRS = np.zeros((4, 4))
_COS_PAIRS[0, 2] = _COS_PAIRS[2, 0] = _COS_PAIRS[1, 3] = _COS_PAIRS[3, 1] = 0.5
_SIN_PAIRS = np.zeros((4, 4))
_SIN_PAIRS[0, 3] = _SIN_PAIRS[3, 0] = 0.5
_SIN_PAIRS[1, 2] = _SIN_PAIRS[2, 1] = -0.5


def _cos_sin(F: Array) -> tuple[Array, Array]:
    B_i, N_i, B_j, N_j = F[:, 0], F[:, 1], F[:, 2], F[:, 3]
    dot = lambda a, b: np.einsum("nr,nr->n", a, b)  # noqa: E731
    return 0.5 * (dot(B_i, B_j) + dot(N_i, N_j)), 0.5 * (dot(B_i, N_j) - dot(N_i, B_j))


def _delta(cs_a: tuple[Array, Array], cs_b: tuple[Array, Array]) -> Array:
    """DeltaTheta(a, b): the angle from state b to state a, in (-pi, pi]."""
    (c_a, s_a), (c_b, s_b) = cs_a, cs_b
    return np.arctan2(s_a * c_b - c_a * s_b, c_a * c_b + s_a * s_b)


class Revolute:
    uid = 670
    base_uid = 18
    name = "AffineBodyRevoluteJointLimit"
    alpha = np.zeros(4)

    def local_vectors(self, edges: Array, p_ref: Array, A_ref: Array, R_ref: Array) -> Array:
        t = unit(edges[:, 1] - edges[:, 0])
        test = np.where((np.abs(t[:, :1]) > 0.9), E_Y, E_X)
        n = unit(np.cross(t, test))
        b = unit(np.cross(t, n))
        # Body-local b_k = R_k^T b: the row-vector product b R_k.
        to_local = lambda w, k: np.einsum("nr,nrc->nc", w, R_ref[:, k])  # noqa: E731
        return np.stack([to_local(b, 0), to_local(n, 0), to_local(b, 1), to_local(n, 1)], axis=1)

    def coordinate(self, F: Array, F_prev: Array, F_ref: Array) -> Array:
        cs_prev = _cos_sin(F_prev)
        return _delta(cs_prev, _cos_sin(F_ref)) + _delta(_cos_sin(F), cs_prev)

    def collapsed(self, F: Array) -> np.ndarray:
        c, s = _cos_sin(F)
        return (c == 0.0) & (s == 0.0)

    def derivatives(self, F: Array, second: bool) -> tuple[Array, Array | None]:
        n = F.shape[0]
        c, s = _cos_sin(F)
        r2 = c * c + s * s
        x_c, x_s = -s / r2, c / r2
        # d cos/dF and d sin/dF, (N, 4, 3).
        g_c = np.einsum("kl,nlr->nkr", _COS_PAIRS, F)
        g_s = np.einsum("kl,nlr->nkr", _SIN_PAIRS, F)
        dx = x_c[:, None, None] * g_c + x_s[:, None, None] * g_s
        if not second:
            return dx, None
        r4 = r2 * r2
        x_cc, x_ss, x_cs = 2.0 * c * s / r4, -2.0 * c * s / r4, (s * s - c * c) / r4
        gc, gs = g_c.reshape(n, 12), g_s.reshape(n, 12)
        outer = lambda a, b: np.einsum("ni,nj->nij", a, b)  # noqa: E731
        cross = outer(gc, gs)
        d2x = (
            x_cc[:, None, None] * outer(gc, gc)
            + x_ss[:, None, None] * outer(gs, gs)
            + x_cs[:, None, None] * (cross + cross.transpose(0, 2, 1))
        ).reshape(n, 4, 3, 4, 3)
        pairs = x_c[:, None, None] * _COS_PAIRS + x_s[:, None, None] * _SIN_PAIRS  # (N, 4, 4)
        d2x += pairs[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
        return dx, d2x


REVOLUTE = Revolute()
