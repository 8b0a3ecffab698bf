"""#669 AffineBodyPrismaticJointLimit: the slide of a prismatic joint (base UID 20).

F = [C_i, T_i, C_j, T_j], with C_k = p_k + A_k c_k (the anchor) and T_k = A_k t_k (the axis), and

    theta = (C_j - C_i) . (T_i + T_j) / 2,   x = theta(q) - theta(q_ref)

(the spec's incremental form telescopes to it), from the frames at q_ref and their increment `F(q - q_ref)`;
`origin: "absolute"` takes theta(q) itself (the engine's formula). d2x/dF2 is constant, `kron(PAIRS, I_3)`.
"""

from __future__ import annotations

import numpy as np

from jointlimits.service.core.constitution import Array, Constitution, Curvature, Facts, Progress
from jointlimits.service.core.kinematics import CarefulFrames, component_major, dot, frame_quantities
from jointlimits.service.core.registry import register

FACTS = Facts(
    uid=669,
    base_uid=20,
    name="AffineBodyPrismaticJointLimit",
    base_name="AffineBodyPrismaticJoint",
    kind="prismatic",
    unit="length unit of the DOFs",
    coordinate="relative slide of body j along the edge axis +t",
    origin='batch field origin: "q_ref" (default): x = 0 at q_ref; "absolute" (the engine): x = theta(q), the signed '
    "distance between the anchors along the axis (not 0 at q_ref where the anchors do not meet) (v1.2)",
    offset_name="init_distance",
    state_name="distance",  # the engine's published slide: written back, never an input (the slide telescopes)
    alpha=np.array([1.0, 0.0, 1.0, 0.0]),
    telescopes=True,
    axis_by_rotation=False,
    unit_frames=False,
)

# theta = D.S / 2 with D = C_j - C_i, S = T_i + T_j: coefficients of D and S per block.
_D = np.array([-1.0, 0.0, 1.0, 0.0])
_S = np.array([0.0, 1.0, 0.0, 1.0])
_PAIRS = 0.5 * (np.outer(_D, _S) + np.outer(_S, _D))[None]  # (1, 4, 4) block coefficients of d2theta/dF2
_SIGNS = np.array([[1.0, -1.0]])
_UU = np.stack([0.5 * (_D + _S), 0.5 * (_D - _S)])[None]  # (1, 2, 4): PAIRS = u+ u+^T - u- u-^T, the chain rule's factors
for _a in (_PAIRS, _SIGNS, _UU):  # one joint's, handed to every joint's curvature (the assembly broadcasts them)
    _a.flags.writeable = False

# The engine's PSD projection (contract v1.2) is taken in the 9 quantities F01 = [D, T_i, -T_j], where
# x = D . (T_i - (-T_j)) / 2: per component d2x/dF01^2 = [[0, 1/2, -1/2], [1/2, 0, 0], [-1/2, 0, 0]],
# eigenvalues +-1/sqrt 2 and 0, so the PSD part of E' d2x/dF01^2 is (|E'| / sqrt 2) w w^T with
# w = (1/sqrt 2, s/2, -s/2), s = sign(E'). Back in F = [C_i, T_i, C_j, T_j] (D = C_j - C_i) that is
# (|E'| / sqrt 2) f f^T, f = (-1/sqrt 2, s/2, 1/sqrt 2, s/2): one rank-1 factor per joint, no eigensolver.
_F01_POS = np.array([-np.sqrt(0.5), 0.5, np.sqrt(0.5), 0.5])
_F01_NEG = np.array([-np.sqrt(0.5), -0.5, np.sqrt(0.5), -0.5])


def _theta2(F: Array) -> Array:
    """2 theta = (C_j - C_i) . (T_i + T_j) (N,)."""
    return dot(F[:, 2] - F[:, 0], F[:, 1] + F[:, 3])


class Prismatic(Constitution):  # its frames never collapse (`Constitution.collapsed`)
    facts = FACTS

    def local_vectors(self, t: Array, anchors: Array | None, R_ref: Array) -> Array:
        # t_k = R_k^T t (the frames of R^T with every v_k = t), then c_i, c_j in place of the points
        tt = np.broadcast_to(t[:, None], (t.shape[0], 4, 3))
        v = frame_quantities(None, R_ref.transpose(0, 1, 3, 2), FACTS.alpha, tt)
        v[:, 0::2] = anchors
        return v

    def value(self, F: Array) -> Array:
        return 0.5 * _theta2(F)

    def begin(self, F: Array) -> Progress:
        return Progress(None, (F[:, 2] - F[:, 0], F[:, 1] + F[:, 3]), [None])

    def advance(self, progress: Progress, F: Array, dF: Array) -> Progress:
        # The one step q_ref -> q (the slide telescopes) in increment form, D2.S2 - D.S = D2.dS + dD.S: it
        # rounds by 2u (|D2| |dS| + |dD| |S|) + u|x| (u = 2^-53, first order), relative to the step; the
        # difference of the two thetas (the engine's formula) by 1.5u (|D2| |S2| + |D| |S|) + u|x|, relative
        # to the frames: hundreds of times more for anchors 1e3 apart turned by 1e-3, within a small factor
        # for a step as large as the frames (the whole bound: tests/core/test_prismatic_scales.py, `_bound`).
        D, S = progress.state
        dD, dS = dF[:, 2] - dF[:, 0], dF[:, 1] + dF[:, 3]
        x = 0.5 * (dot(D + dD, dS) + dot(dD, S))
        return Progress(x if progress.x is None else progress.x + x, (), [*progress.known, None])

    def careful_coordinate(self, careful: CarefulFrames) -> Array:
        # A step as large as the frames (or frames at the edge of float64): theta at q from A(q) itself.
        return 0.5 * (_theta2(careful.unscaled(1)) - _theta2(careful.unscaled(0)))

    def derivatives(self, F: Array, second: bool) -> tuple[Array, Curvature | None]:
        n = F.shape[0]
        dx = np.empty_like(F)
        D = F[:, 2] - F[:, 0]
        S = F[:, 1] + F[:, 3]
        dx[:, 0] = -0.5 * S
        dx[:, 2] = 0.5 * S
        dx[:, 1] = dx[:, 3] = 0.5 * D
        if not second:
            return dx, None
        # Rank-1 factor for E'' dx dx^T is dx itself (coefficient 0 in d2x).
        dtype = F.dtype
        factors = (_SIGNS.astype(dtype, copy=False), _UU.astype(dtype, copy=False))
        return dx, Curvature(kron=_PAIRS.astype(dtype, copy=False), basis=dx[:, None], coef=np.zeros((n, 1, 1), dtype),
                             dx_coef=np.ones((n, 1), dtype), kron_factors=factors)

    def projected_curvature(self, dE: Array, curvature: Curvature) -> Curvature:
        """The engine's projection (contract v1.2, 9 quantities): `(|E'| / sqrt 2) f f^T` per joint (see `_F01_POS`)."""
        f = np.where((dE >= 0)[:, None], _F01_POS, _F01_NEG).astype(dE.dtype, copy=False)  # (N, 4)
        w = np.abs(dE) * np.sqrt(0.5)
        n = dE.shape[0]
        # K itself is not formed: the chain rule of frames with points takes the factors (assembly._hessian_points).
        return Curvature(kron=None, basis=curvature.basis, coef=np.zeros((n, 1, 1), dE.dtype), dx_coef=curvature.dx_coef,
                         kron_factors=(w[:, None], f[:, None]))


PRISMATIC = register(Prismatic())
