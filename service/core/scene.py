"""In-process inputs and outputs of the core: NumPy arrays, no wire types."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
OUTPUTS = ("energy", "gradient", "hessian")


@dataclass(frozen=True)
class Bodies:
    """Every body once: `q`, `q_prev`, `q_ref` (B, 12)."""

    q: Array
    q_prev: Array
    q_ref: Array


@dataclass(frozen=True)
class Joints:
    """One batch of joints of one constitution (N joints)."""

    constitution_uid: int
    base_uid: int
    body_ids: NDArray[np.int64]  # (N, 2)
    edges: Array | None  # (N, 2, 3), world space at q_ref; None where `local_edges` are given
    lower: Array  # (N,)
    upper: Array  # (N,)
    strength: Array  # (N,)
    offset: Array | None = None  # (N,) v1.1: coordinate = x + offset; lower/upper bound the coordinate (None: 0)
    prev_coordinate: Array | None = None  # (N,) v1.1, 670 only: the committed coordinate at q_prev (None: from q_prev)
    local_edges: Array | None = None  # (N, 2, 2, 3) v1.2: [[l0, l1], [r0, r1]] in bodies i's and j's own coordinates
    origin: str = "q_ref"  # v1.2: where x = 0: "q_ref" (the specs) or "absolute" (the reference engine's zero)


@dataclass
class BatchResult:
    """Rows `index` (M,) of a request batch: `x`, `energy`, `coordinate` (M,), `gradient` (M, 24), `hessian` (M, 24, 24).

    `coordinate` (v1.1) is `x + offset`, the coordinate the limits bound.
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
    assembled: object | None = None
    """`jointlimits.service.core.assembled.Assembled` when asked for `layout="bodies"`."""
