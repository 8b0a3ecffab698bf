"""What a joint-limit constitution contributes: its facts (`Facts`) and its coordinate `x` through the frame
quantities `F` (`Constitution`).

Everything else (the penalty, the chain rule to DOFs, Hessian modes, validation, the wire, discovery, the SDK)
is shared and reads the facts from the registry, so a new joint type is one module: its `Facts`, an object
implementing `Constitution`, and `jointlimits.service.core.registry.register` (docs/maintainers.md,
"Adding a constitution").
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
    """A second derivative in `F` (12 x 12 per joint) kept in its structured form

        d2x/dF2 = kron(K, I_3) + U^T C U,

    `K` (N, 4, 4) symmetric block coefficients, `U` (N, k, 4, 3) a few vectors in F,
    `C` (N, k, k) symmetric. `dx_coef` (N, k) says `dx/dF = dx_coef . U` when the
    gradient lies in span(U) (None otherwise): the chain rule then needs no extra
    factor for the `E'' dx dx^T` term. Never formed as 12 x 12 on the fast paths.

    `kron_factors` = (weights (N, m), vectors (N or 1, m, 4)) with `K = sum_e w_e f_e f_e^T`, when the
    constitution knows them (else the assembly takes K's eigen-decomposition); `diagonal` says `C` is
    diagonal. The Hessian is assembled from such signed rank-1 factors in one product.
    """

    kron: Array | None
    """None where `kron_factors` are given and no path needs K itself (formed by `dense` if asked)."""
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
            w, f = self.kron_factors
            K = np.einsum("nm,nma,nmb->nab", w, np.broadcast_to(f, (n, *f.shape[1:])), np.broadcast_to(f, (n, *f.shape[1:])))
        D.reshape(n, 4, 3, 4, 3)[...] += K[:, :, None, :, None] * np.eye(3, dtype=D.dtype)[None, None, :, None, :]
        return D


@dataclass
class Progress:
    """A joint coordinate summed over its first steps, to be continued (`Constitution.advance`).

    `x` (N,) so far, None before any step; `state` what the next step starts from (the constitution's
    own: the revolute (cos, sin), the prismatic D and S); `known` per state passed, in order, what
    `Constitution.collapsed` may take instead of forming it again (None: nothing). A prepared scene
    keeps the progress over its fixed steps (q_ref -> q_prev): each evaluation then takes the last step only.
    """

    x: Array | None
    state: tuple
    known: list


@dataclass(frozen=True, eq=False)
class Facts:
    """A constitution's facts, declared once next to its numerics; validation, discovery and OpenAPI, the
    SDK's `Scene` and the libuipc adapter read them through the registry."""

    uid: int
    """The limit's UID, the wire's `constitution_uid`."""
    base_uid: int
    """The UID of the base joint it limits, the wire's `base_uid` (an absent one is this)."""
    name: str
    base_name: str
    """The specs' names of the limit and of its base joint."""
    kind: str
    """The joint in one word ("revolute"): the SDK's `Scene.add_<kind>_limit`, the faults' words."""
    unit: str
    coordinate: str
    """The unit of the coordinate `x` and what it measures."""
    origin: str
    """Where `x = 0` for each value of a batch's `origin` (discovery)."""
    offset_name: str
    state_name: str
    """The spec's (and the engine's edge attribute) names of the offset (`init_angle`) and of the committed
    coordinate (`angle`), which a `stateful` constitution takes as `prev_coordinate`."""
    alpha: Array
    """(4,): 1 where `F_k` is a point that follows the body's translation, 0 for a direction."""
    telescopes: bool
    """True when the incremental `x` telescopes to a function of `q` and `q_ref`: `q_prev` is not needed, and
    the coordinate carries no state over time steps."""
    axis_by_rotation: bool
    """How a body-local edge (`local_edges`) gives the world axis: by body i's rotation `R_i` (True) or
    its `A_ref_i` (False), as the reference engine does for this constitution (`jointlimits.service.core.geometry`)."""
    unit_frames: bool
    """Every body-local vector `v_k` is a unit vector (directions only): then `|F_k| <= |A|_F` of its body,
    and `collapsed` may take a bound on the frames' sizes from the bodies' norms (`size_bound`)."""
    engine_zero_axis: float = 0.0
    """The reference engine refuses an edge whose `|p1 - p0|^2` is at most this (the libuipc adapter checks it)."""

    @property
    def stateful(self) -> bool:
        """The coordinate carries a state over time steps (the committed coordinate, `prev_coordinate`; a commit
        unwraps it): it does not telescope."""
        return not self.telescopes

    @property
    def points(self) -> bool:
        """Some `F_k` is a point (the coordinate depends on the bodies' positions)."""
        return bool(self.alpha.any())


class Constitution(Protocol):
    facts: Facts

    def local_vectors(self, t: Array, anchors: Array | None, R_ref: Array) -> Array:
        """Body-local `v` (N, 4, 3) from the unit world axis `t` (N, 3) at `q_ref`, the body-local
        anchors (N, 2, 3) of bodies i, j (None when `alpha` is zero) and their rotations `R_ref` (N, 2, 3, 3)."""
        ...

    def value(self, F: Array) -> Array:
        """The coordinate (N,) of frames `F` (N, 4, 3) measured from the constitution's own zero (the
        reference engine's): `origin: "absolute"` adds it at `q_ref` to `x`."""
        ...

    def begin(self, F: Array) -> Progress:
        """No step taken yet, from frames `F` (N, 4, 3)."""
        ...

    def advance(self, progress: Progress, F: Array, dF: Array) -> Progress:
        """`progress` one step further: from the frames `F` by their increment `dF` (N, 4, 3).

        The steps are the increments `F(q_prev - q_ref), F(q - q_prev)`, or `F(q - q_ref)` alone when
        `telescopes`, each from the frames where it starts (`F` at `q_ref`, then at `q_prev`). Taking `x` as
        increments of bilinear forms keeps its error relative to the step, not to the size of the scene."""
        ...

    def careful_coordinate(self, careful: CarefulFrames) -> Array:
        """x (M,) of the joints `careful.idx` (steps as large as the frames, or frames at the edge of float64),
        from their careful frames, in whichever form rounds better there (instead of `advance`'s)."""
        ...

    def collapsed(self, F: Array, known: object = None, size_bound: Array | None = None) -> NDArray[np.bool_]:
        """(N,) True where `x` has no derivatives at this `F` (or is decided by rounding alone).

        Must not depend on the scale of `F`'s frame vectors where `x` does not. `known`: what
        `begin` / `advance` recorded for this state (`Progress.known`), or None. `size_bound` (N,)
        (`unit_frames` only): `4 |A_i|_F^2 |A_j|_F^2`, an upper bound of the frames' sizes that the
        test may use to pass most joints without forming them (the same answer).
        """
        ...

    def derivatives(self, F: Array, second: bool) -> tuple[Array, Curvature | None]:
        """`dx/dF` (N, 4, 3) and, if `second`, `d2x/dF2` in structured form."""
        ...

    def projected_curvature(self, dE: Array, curvature: Curvature) -> Curvature | None:
        """`dE d2x/dF2` projected onto the PSD cone in closed form, or None to use the eigensolver."""
        ...
