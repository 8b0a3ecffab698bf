"""A per-joint answer (`layout="joints"`) summed per body with the core's own scatter-add: the reference the
core's `layout="bodies"` answer (which differentiates and stores the active joints alone) is compared with."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from jointlimits.service.core import penalty
from jointlimits.service.core.prepared import _bounds
from jointlimits.service.core.assembled import Assembled, assemble_active
from jointlimits.service.core.scene import Evaluation, Joints


def assemble(n_bodies: int, batches: Sequence[Joints], ev: Evaluation, active_only: bool) -> Assembled:
    """The scatter-add over the bodies of `batches` of `ev`'s per-joint rows, its active joints' alone (the
    gap is the core's, bitwise its bounds: `x` against `lower - offset`, `upper - offset`, or the coordinate against
    `lower`, `upper` where the core takes those)."""
    per_joint = []
    for joints, r in zip(batches, ev.batches):
        rows = np.arange(r.index.shape[0])
        if not active_only:
            i = r.index
            # the core's bounds: on x where `prepared._bounds` keeps them there, else (and with committed
            # coordinates) on the coordinate
            lo, up, on_c = _bounds(joints.lower[i], joints.upper[i], None if joints.offset is None else joints.offset[i],
                                   np.float64)
            pen = r.x if on_c is None else np.where(on_c, r.coordinate, r.x)
            if joints.prev_coordinate is not None:
                pen, lo, up = r.coordinate, joints.lower[i], joints.upper[i]
            g, _ = penalty.gap(pen, lo, up)
            rows = np.flatnonzero((g > 0) & (joints.strength[i] > 0))
        ids = np.asarray(joints.body_ids, dtype=np.int64)[r.index[rows]]
        per_joint.append((ids, None if r.gradient is None else r.gradient[rows], None if r.hessian is None else r.hessian[rows]))
    want_g = bool(ev.batches) and ev.batches[0].gradient is not None
    want_h = bool(ev.batches) and ev.batches[0].hessian is not None
    return assemble_active(n_bodies, per_joint, want_g, want_h)


def apply(ev: Evaluation, n_bodies: int, batches: Sequence[Joints], active_only: bool) -> Evaluation:
    """A per-joint `ev` as the core answers `layout="bodies"`: the assembled answer, batches without derivatives."""
    out = assemble(n_bodies, batches, ev, active_only)
    return replace(ev, batches=[replace(r, gradient=None, hessian=None) for r in ev.batches], assembled=out)
