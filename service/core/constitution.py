"""What a joint-limit constitution contributes: its facts (`Facts`) and its coordinate `x` through the frame
quantities `F` (`Constitution`). Everything else (penalty, chain rule, Hessian modes, validation, the wire,
discovery, the SDK) is shared and reads the registry, so a new joint type is one module: its `Facts`, an object
implementing `Constitution`, and `registry.register` (docs/maintainers.md, "Adding a constitution").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from jointlimits.service.core.kinematics import CarefulFrames

Array = NDArray[np.float64]


@dataclass
class Curvature:
    """`d2x/dF2 = kron(K, I_3) + U^T C U` (12 x 12 per joint, never formed on the fast paths): `kron` K (N or 1, 4,
    4) symmetric, `basis` U (N, k, 4, 3), `coef` C (N, k, k) symmetric (`diagonal`: diagonal); `dx_coef` (N, k):
    `dx/dF = dx_coef . U` if the gradient lies in span(U) (else None). `kron_factors` = (w (N or 1, m), f (N or 1,
    m, 4)) with `K = sum_e w_e f_e f_e^T` when known (else the assembly takes K's eigen-decomposition; `kron`
    may then be None)."""

    kron: Array | None
    basis: Array
    coef: Array
    dx_coef: Array | None = None
    kron_factors: tuple[Array, Array] | None = None
    diagonal: bool = False

    def dense(self) -> Array:
        """(N, 12, 12): the generic form, for the eigensolver of the PSD projection."""
        n, k = self.basis.shape[:2]
        U = self.basis.reshape(n, k, 12)
        D = np.einsum("nab,nai,nbj->nij", self.coef, U, U)
        K = self.kron
        if K is None:
            w, f = (np.broadcast_to(a, (n, *a.shape[1:])) for a in self.kron_factors)
            K = np.einsum("nm,nma,nmb->nab", w, f, f)
        D.reshape(n, 4, 3, 4, 3)[...] += K[:, :, None, :, None] * np.eye(3, dtype=D.dtype)[None, None, :, None, :]
        return D


@dataclass
class Progress:
    """A joint coordinate summed over its first steps, to be continued (`Constitution.advance`): `x` (N,) so far
    (None before any step); `state` what the next step starts from (the constitution's own); `known` per state
    passed, what `Constitution.collapsed` may take instead of forming it again (None: nothing). A prepared scene
    keeps the progress over its fixed steps (q_ref -> q_prev): each evaluation takes the last step only."""

    x: Array | None
    state: tuple
    known: list


@dataclass(frozen=True, eq=False)
class Facts:
    """A constitution's facts, declared once next to its numerics; validation, discovery and OpenAPI, the
    SDK's `Scene` and the libuipc adapter read them through the registry."""

    uid: int  # the limit's UID, the wire's `constitution_uid`
    base_uid: int  # the UID of the base joint it limits (an absent `base_uid` is this)
    name: str  # the specs' names of the limit and of its base joint
    base_name: str
    kind: str  # the joint in one word ("revolute"): `Scene.add_<kind>_limit`, the faults' words
    unit: str  # the unit of `x`, and what it measures
    coordinate: str
    origin: str  # where `x = 0` for each value of a batch's `origin` (discovery)
    offset_name: str  # the spec's (and the engine's) names of the offset and of the committed coordinate
    state_name: str
    alpha: Array  # (4,): 1 where `F_k` is a point that follows the body's translation, 0 for a direction
    telescopes: bool
    """The incremental `x` telescopes to a function of `q` and `q_ref`: `q_prev` is not needed, no state."""
    axis_by_rotation: bool
    """A body-local edge's world axis is carried by body i's rotation `R_i` (True) or its `A_ref_i` (False),
    as the reference engine does for this constitution (`geometry.axis_and_anchors`)."""
    unit_frames: bool
    """Every `v_k` is a unit direction: `|F_k| <= |A|_F`, so `collapsed` may take `size_bound`."""
    engine_zero_axis: float = 0.0  # the engine refuses an edge with `|p1 - p0|^2` at most this (the uipc adapter)

    @property
    def stateful(self) -> bool:
        """The coordinate carries a state over time steps (`prev_coordinate`; a commit unwraps it)."""
        return not self.telescopes

    @property
    def points(self) -> bool:
        """Some `F_k` is a point (the coordinate depends on the bodies' positions)."""
        return bool(self.alpha.any())


class Constitution(Protocol):
    facts: Facts

    def local_vectors(self, t: Array, anchors: Array | None, R_ref: Array) -> Array:
        """Body-local `v` (N, 4, 3) from the unit world axis `t` (N, 3) at `q_ref`, the body-local anchors
        (N, 2, 3) of bodies i, j (None without points) and their rotations `R_ref` (N, 2, 3, 3)."""

    def value(self, F: Array) -> Array:
        """The coordinate (N,) of frames `F` (N, 4, 3) from the constitution's own (the engine's) zero."""

    def begin(self, F: Array) -> Progress:
        """No step taken yet, from frames `F` (N, 4, 3)."""

    def advance(self, progress: Progress, F: Array, dF: Array) -> Progress:
        """`progress` one step further, from the frames `F` by their increment `dF` (N, 4, 3): the steps are
        `F(q_prev - q_ref), F(q - q_prev)`, or `F(q - q_ref)` alone when `telescopes`. Increments of bilinear
        forms keep the error relative to the step, not to the size of the scene."""

    def careful_coordinate(self, careful: CarefulFrames) -> Array:
        """x (M,) of the joints `careful.idx` (steps as large as the frames, or frames at the edge of float64),
        from their careful frames, in whichever form rounds better there."""

    def collapsed(self, F: Array, known: object = None, size_bound: Array | None = None) -> NDArray[np.bool_]:
        """(N,) True where `x` has no derivatives at `F` (or is decided by rounding alone), whatever the scale
        of `F`'s frame vectors. `known`: what `begin` / `advance` recorded for this state, or None.
        `size_bound` (N,) (`unit_frames` only): `4 |A_i|_F^2 |A_j|_F^2`, to pass most joints unformed. By default
        (a constitution that subclasses this one) no frame collapses."""
        return np.zeros(F.shape[0], dtype=bool)

    def derivatives(self, F: Array, second: bool) -> tuple[Array, Curvature | None]:
        """`dx/dF` (N, 4, 3) and, if `second`, `d2x/dF2` in structured form."""

    def projected_curvature(self, dE: Array, curvature: Curvature) -> Curvature | None:
        """`dE d2x/dF2` projected onto the PSD cone in closed form, or None to use the eigensolver."""
