"""Wire models <-> core arrays. No numerics beyond `np.asarray`."""

from __future__ import annotations

from typing import Any

import numpy as np

from schemas import EvaluateRequest
from service.core import Bodies, Evaluation, Joints


def to_core(req: EvaluateRequest) -> dict[str, Any]:
    """Keyword arguments of `service.core.evaluate` for a parsed request."""
    b = req.bodies
    dof = lambda rows: np.asarray(rows, dtype=np.float64).reshape(len(rows), 12)  # noqa: E731
    return dict(
        bodies=Bodies(q=dof(b.q), q_prev=dof(b.q_prev), q_ref=dof(b.q_ref)),
        batches=[
            Joints(
                constitution_uid=j.constitution_uid,
                base_uid=j.base_uid,
                body_ids=np.asarray(j.body_ids, dtype=np.int64).reshape(len(j.body_ids), 2),
                edges=np.asarray(j.edges, dtype=np.float64).reshape(len(j.edges), 2, 3),
                lower=np.asarray(j.lower, dtype=np.float64),
                upper=np.asarray(j.upper, dtype=np.float64),
                strength=np.asarray(j.strength, dtype=np.float64),
            )
            for j in req.batches
        ],
        outputs=req.outputs,
        hessian_mode=req.hessian_mode,
        active_only=req.active_only,
    )


def to_wire(ev: Evaluation) -> dict[str, Any]:
    """The response body of contract v1; `gradient`/`hessian` only when computed."""
    batches = []
    for r in ev.batches:
        out: dict[str, Any] = dict(
            constitution_uid=r.constitution_uid, index=r.index.tolist(), x=r.x.tolist(), energy=r.energy.tolist()
        )
        if r.gradient is not None:
            out["gradient"] = r.gradient.tolist()
        if r.hessian is not None:
            out["hessian"] = r.hessian.tolist()
        batches.append(out)
    return dict(total_energy=ev.total_energy, batches=batches)
