"""Typed, NumPy-backed requests and results of the SDK (the wire's structure, arrays instead of lists)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from schemas import OUTPUTS

Array = NDArray[np.float64]
REVOLUTE_LIMIT, PRISMATIC_LIMIT = 670, 669
BASE_UID = {REVOLUTE_LIMIT: 18, PRISMATIC_LIMIT: 20}


@dataclass
class JointBatch:
    """N joints of one constitution. `body_ids` (N, 2), `edges` (N, 2, 3) world space at q_ref,
    `lower`, `upper`, `strength` (N,); v1.1, optional: `offset` (N,) (coordinate = x + offset; the
    limits bound the coordinate) and, for 670, `prev_coordinate` (N,) (the committed coordinate at q_prev)."""

    constitution_uid: int
    body_ids: NDArray[np.int64]
    edges: Array
    lower: Array
    upper: Array
    strength: Array
    base_uid: int | None = None
    """Defaults to the constitution's base joint (18 for 670, 20 for 669)."""
    offset: Array | None = None
    prev_coordinate: Array | None = None

    def __post_init__(self) -> None:
        if self.base_uid is None:
            self.base_uid = BASE_UID.get(self.constitution_uid, -1)

    @classmethod
    def of(
        cls,
        constitution_uid: int,
        body_ids: ArrayLike,
        edges: ArrayLike,
        lower: ArrayLike,
        upper: ArrayLike,
        strength: ArrayLike = 1.0,
        *,
        offset: ArrayLike | None = None,
        prev_coordinate: ArrayLike | None = None,
    ) -> JointBatch:
        """From array-likes; scalar `lower`, `upper`, `strength`, `offset`, `prev_coordinate` apply to every joint.

        A solver that keeps its own state commits a time step by passing the `coordinate` it got at
        the accepted `q` as the next step's `prev_coordinate` (with `q_prev` := that `q`).
        """
        ids = np.asarray(body_ids, dtype=np.int64).reshape(-1, 2)
        n = ids.shape[0]
        per_joint = lambda v: np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy()  # noqa: E731
        return cls(
            constitution_uid=constitution_uid,
            body_ids=ids,
            edges=np.asarray(edges, dtype=np.float64).reshape(n, 2, 3),
            lower=per_joint(lower),
            upper=per_joint(upper),
            strength=per_joint(strength),
            offset=None if offset is None else per_joint(offset),
            prev_coordinate=None if prev_coordinate is None else per_joint(prev_coordinate),
        )

    def __len__(self) -> int:
        return int(np.shape(self.body_ids)[0])


@dataclass
class Request:
    """Bodies `q`, `q_prev`, `q_ref` (B, 12) and the joint batches that refer to them by row."""

    q: Array
    q_prev: Array
    q_ref: Array
    batches: list[JointBatch]
    outputs: tuple[str, ...] = OUTPUTS
    hessian_mode: str = "exact"
    active_only: bool = False

    @property
    def n_joints(self) -> int:
        return sum(len(b) for b in self.batches)


@dataclass
class BatchResult:
    """Rows `index` (M,) of a request batch: `x`, `energy` (M,), `gradient` (M, 24), `hessian` (M, 24, 24),
    and `coordinate` (M,) = x + offset (v1.1; None from a v1 server).

    Gradients and Hessians are in the DOFs `[q_i, q_j]` of the joint's two bodies.
    """

    constitution_uid: int
    index: NDArray[np.int64]
    x: Array
    energy: Array
    gradient: Array | None = None
    hessian: Array | None = None
    coordinate: Array | None = None


@dataclass
class Evaluation:
    total_energy: float
    batches: list[BatchResult] = field(default_factory=list)

    def batch(self, constitution_uid: int) -> BatchResult:
        """The first batch of a constitution (a `Scene` makes one per constitution)."""
        for b in self.batches:
            if b.constitution_uid == constitution_uid:
                return b
        raise KeyError(f"no batch of constitution {constitution_uid}")
