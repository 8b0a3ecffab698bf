"""The JSON encoding: wire bytes <-> core arrays. No numerics beyond `np.asarray`."""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson
from pydantic import ValidationError

from schemas import EvaluateRequest
from service.core import Bodies, Evaluation, Joints
from service.http import limits
from service.http.errors import from_validation

MEDIA_TYPE = "application/json"


def decode(body: bytes, max_joints: int) -> dict[str, Any]:
    """Keyword arguments of `service.core.evaluate` for a JSON body.

    Raises `HttpError` (413) for too many joints, `InputError` (422) for a malformed body.
    """
    limits.check_joints(limits.json_joints_upper_bound(body), max_joints)
    try:
        # Rust-side parse and validation straight from bytes; rejects NaN, Infinity and 1e400.
        req = EvaluateRequest.model_validate_json(body)
    except ValidationError as e:
        raise from_validation(e) from None
    limits.check_joints(sum(len(j.body_ids) for j in req.batches), max_joints)
    return to_core(req)


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
    """The response body of contract v1 as NumPy arrays; `gradient`/`hessian` only when computed."""
    batches = []
    for r in ev.batches:
        out: dict[str, Any] = dict(constitution_uid=r.constitution_uid, index=r.index, x=r.x, energy=r.energy)
        if r.gradient is not None:
            out["gradient"] = r.gradient
        if r.hessian is not None:
            out["hessian"] = r.hessian
        batches.append(out)
    return dict(total_energy=ev.total_energy, batches=batches)


FLOATS_PER_PIECE = 2**18
"""Numbers orjson writes in one call (~5 ms): between calls the GIL passes to other threads, so a
worker's event loop and uvicorn's health-check thread keep answering while a large answer is written."""


def encode(ev: Evaluation) -> bytes:
    """JSON bytes with each float in its shortest round-trip form, written in pieces.

    The bytes are those of `orjson.dumps(to_wire(ev))`; each array is written
    `FLOATS_PER_PIECE` numbers at a time and the pieces are joined once (`bytes.join`
    releases the GIL while it copies). The core guarantees finite numbers; orjson
    would write a stray NaN as `null`, never as `NaN`.
    """
    doc = to_wire(ev)
    out: list[bytes | memoryview] = [b'{"total_energy":', orjson.dumps(doc["total_energy"]), b',"batches":[']
    for i, b in enumerate(doc["batches"]):
        out.append(b"," if i else b"")
        for j, (k, v) in enumerate(b.items()):
            out += [b'{"' if j == 0 else b',"', k.encode(), b'":']
            out += _array_pieces(v) if isinstance(v, np.ndarray) else [orjson.dumps(v)]
        out.append(b"}")
    out.append(b"]}")
    return b"".join(out)


def _array_pieces(a: np.ndarray) -> list[bytes | memoryview]:
    """`a` (N, ...) as JSON: one orjson call per block of rows, the blocks' brackets dropped and rejoined."""
    a = np.ascontiguousarray(a)  # orjson serialises C-ordered arrays only
    rows = max(1, FLOATS_PER_PIECE // max(1, a[0].size if a.ndim > 1 and a.shape[0] else 1))
    if a.shape[0] <= rows:
        return [orjson.dumps(a, option=orjson.OPT_SERIALIZE_NUMPY)]
    out: list[bytes | memoryview] = [b"["]
    for start in range(0, a.shape[0], rows):
        out += [memoryview(orjson.dumps(a[start : start + rows], option=orjson.OPT_SERIALIZE_NUMPY))[1:-1], b","]
    out[-1] = b"]"
    return out
