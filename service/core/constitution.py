"""What a joint-limit constitution contributes: its coordinate `x` through the frame quantities `F`.

Everything else (the penalty, the chain rule to DOFs, Hessian modes, validation)
is shared, so a new joint type is one small module implementing this protocol
and one line in `service.core.registry`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


class Constitution(Protocol):
    uid: int
    base_uid: int
    name: str
    alpha: Array
    """(4,): 1 where `F_k` is a point that follows the body's translation, 0 for a direction."""

    def local_vectors(self, edges: Array, p_ref: Array, A_ref: Array, R_ref: Array) -> Array:
        """Body-local `v` (N, 4, 3) from the joint edges (N, 2, 3) and the bodies at `q_ref`.

        `p_ref` (N, 2, 3), `A_ref` (N, 2, 3, 3) and its rotation `R_ref` (N, 2, 3, 3) of bodies i, j.
        """
        ...

    def coordinate(self, F: Array, F_prev: Array, F_ref: Array) -> Array:
        """Joint coordinate `x` (N,) in incremental form from `F` (N, 4, 3) at `q`, `q_prev`, `q_ref`."""
        ...

    def collapsed(self, F: Array) -> NDArray[np.bool_]:
        """(N,) True where `x` has no derivatives at this `F`."""
        ...

    def derivatives(self, F: Array, second: bool) -> tuple[Array, Array | None]:
        """`dx/dF` (N, 4, 3) and, if `second`, `d2x/dF2` (N, 4, 3, 4, 3)."""
        ...
