"""Requests to bytes and response bytes to results, in JSON or the binary encoding (schemas/binary.py)."""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson

from jointlimits.client.errors import ServiceError
from jointlimits.client.model import NEEDED, OPTIONAL, Assembled, BatchResult, Evaluation, Request
from jointlimits.schemas import binary as wire

JSON = "application/json"
BINARY = wire.MEDIA_TYPE


def encode(request: Request, binary: bool) -> tuple[bytes, str]:
    """The request body and its Content-Type."""
    f64, i64 = ((lambda a, t=t: None if a is None else np.ascontiguousarray(a, dtype=t)) for t in (np.float64, np.int64))
    doc = {  # a None array goes as null (nil), for the service to name (a session's opening)
        "bodies": {k: f64(getattr(request, k)) for k in ("q", "q_prev", "q_ref")},
        "batches": [
            {
                "constitution_uid": int(b.constitution_uid),
                "base_uid": int(b.base_uid if b.base_uid is not None else -1),
                "body_ids": i64(b.body_ids),
                **{k: f64(getattr(b, k)) for k in NEEDED[1:]},
                **{k: f64(a) for k in OPTIONAL if (a := getattr(b, k, None)) is not None},  # sent when given
                **({"origin": b.origin} if b.origin != "q_ref" else {}),  # the default stays off the wire
            }
            for b in request.batches
        ],
        "outputs": list(request.outputs),
        "hessian_mode": request.hessian_mode,
        "active_only": bool(request.active_only),
        **({"layout": request.layout} if request.layout != "joints" else {}),  # the default stays off the wire
    }
    return dumps(doc, binary), BINARY if binary else JSON


def dumps(doc: Any, binary: bool) -> bytes:
    """A document whose arrays are C-ordered float64 or int64 NumPy arrays: msgpack, each array a wire map (no
    copy), or JSON, where orjson writes every float64 in its shortest round-trip form (the server reads the same bits)."""
    if not binary:
        return orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY)

    def packed(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: packed(x) for k, x in v.items()}
        if isinstance(v, list):
            return [packed(x) for x in v]
        return wire.pack_array(v, wire.INT64 if v.dtype.kind == "i" else wire.FLOAT64) if isinstance(v, np.ndarray) else v

    return wire.dumps(packed(doc))


def decode(content: bytes, content_type: str) -> Evaluation:
    """An `Evaluation` from a 200 body of either encoding (binary arrays are read-only views, no copy)."""
    binary = content_type.split(";")[0].strip().lower() in wire.MEDIA_TYPES
    doc = wire.loads(content) if binary else orjson.loads(content)

    def arr(v: Any, tail: tuple[int, ...] = (), dtype: str = wire.FLOAT64) -> np.ndarray:
        if binary:
            return wire.unpack_array(v, dtype, 1 + len(tail))
        return np.asarray(v, dtype=np.dtype(dtype)).reshape((-1, *tail))

    def given(d: dict[str, Any], k: str, tail: tuple[int, ...] = (), dtype: str = wire.FLOAT64) -> np.ndarray | None:
        return arr(d[k], tail, dtype) if k in d else None

    batches = [BatchResult(int(b["constitution_uid"]), arr(b["index"], (), wire.INT64), arr(b["x"]), arr(b["energy"]),
                           given(b, "gradient", (24,)), given(b, "hessian", (24, 24)), given(b, "coordinate"))
               for b in doc["batches"]]
    # layout="bodies": the per-body answer; `n_bodies` is set by the caller (from its Request).
    a = doc.get("assembled")
    assembled = None if a is None else Assembled(-1, given(a, "gradient", (12,)), given(a, "rows", (), wire.INT64),
                                                 given(a, "cols", (), wire.INT64), given(a, "blocks", (12, 12)))
    return Evaluation(float(doc["total_energy"]), batches, assembled)


def error(status: int, content: bytes) -> ServiceError:
    """The server's error body (always JSON) as an exception."""
    try:
        body = orjson.loads(content)
    except orjson.JSONDecodeError:
        body = {"detail": content.decode("utf-8", "replace")[:500] or f"HTTP {status}"}
    return ServiceError.from_body(status, body)
