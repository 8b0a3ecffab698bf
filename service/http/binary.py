"""The binary encoding (schemas/binary.py): msgpack bytes <-> core arrays, no Python lists of numbers.

Numeric payloads bypass pydantic: each array is one `np.frombuffer` view. Structure
faults get the same `loc` a JSON request would get (`("batches", 1, "lower")`);
per-row faults (non-finite, ranges) come from the core, as for JSON.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from schemas import OUTPUTS
from schemas import binary as wire
from service.core import Bodies, Evaluation, Fault, InputError, Joints
from service.core.errors import Loc
from service.http import limits
from service.http.convert import base_uid_of, strength_of

MEDIA_TYPE = wire.MEDIA_TYPE

_REQUEST_KEYS = {"bodies": True, "batches": True, "outputs": False, "hessian_mode": False, "active_only": False}
_BODY_KEYS = {"q": True, "q_prev": True, "q_ref": True}
_JOINT_ARRAYS = {"body_ids": (wire.INT64, 2), "edges": (wire.FLOAT64, 3)} | {
    k: (wire.FLOAT64, 1) for k in ("lower", "upper", "strength", "offset", "prev_coordinate")
}
_OPTIONAL = {"strength", "offset", "prev_coordinate"}  # strength defaults to 1; offset, prev_coordinate: v1.1
_BATCH_KEYS = {"constitution_uid": True, "base_uid": False} | {k: k not in _OPTIONAL for k in _JOINT_ARRAYS}
_INT64_RANGE = range(-(2**63), 2**63)
_EMPTY = {"f": np.zeros((0, 12)), "i": np.zeros((0, 2), dtype=np.int64)}


class _Reader:
    """Walks the document's few structural levels (never its joints), collecting faults."""

    def __init__(self) -> None:
        self.faults: list[Fault] = []

    def fault(self, loc: Loc, msg: str, type: str = "value_error") -> None:
        self.faults.append(Fault(loc, msg, type))

    def fields(self, obj: Any, loc: Loc, keys: dict[str, bool]) -> dict[str, Any]:
        if not isinstance(obj, dict):
            self.fault(loc, "Input should be a map (a msgpack map, as a JSON object)", "model_type")
            return {}
        for k in obj:
            if k not in keys:
                self.fault((*loc, k), "Extra inputs are not permitted", "extra_forbidden")
        for k, required in keys.items():
            if required and k not in obj:
                self.fault((*loc, k), "Field required", "missing")
        return {k: v for k, v in obj.items() if k in keys}

    def array(self, obj: Any, loc: Loc, dtype: str, ndim: int, empty: np.ndarray) -> np.ndarray:
        try:
            return wire.unpack_array(obj, dtype, ndim)
        except ValueError as e:
            self.fault(loc, str(e))
            return empty

    def int64(self, obj: Any, loc: Loc) -> int:
        if isinstance(obj, bool) or not isinstance(obj, int) or obj not in _INT64_RANGE:
            self.fault(loc, "Input should be a valid integer in int64 range", "int_type")
            return 0
        return obj


def decode(body: bytes, max_joints: int) -> dict[str, Any]:
    """Keyword arguments of `service.core.evaluate` for a msgpack body; `InputError` / 413 `HttpError`."""
    try:
        doc = wire.loads(body)
    except ValueError as e:
        raise InputError([Fault((), str(e), "msgpack_invalid")]) from None
    r = _Reader()
    top = r.fields(doc, (), _REQUEST_KEYS)
    raw_bodies = r.fields(top.get("bodies", {}), ("bodies",), _BODY_KEYS)
    f = {k: r.array(raw_bodies.get(k), ("bodies", k), wire.FLOAT64, 2, _EMPTY["f"]) for k in _BODY_KEYS}
    raw_batches = top.get("batches", [])
    if not isinstance(raw_batches, list):
        r.fault(("batches",), "Input should be a valid list", "list_type")
        raw_batches = []
    batches = [_batch(r, b, raw) for b, raw in enumerate(raw_batches)]
    outputs, hessian_mode, active_only = _options(r, top)
    if r.faults:
        raise InputError(r.faults)
    limits.check_joints(sum(j.body_ids.shape[0] for j in batches), max_joints)
    return dict(
        bodies=Bodies(q=f["q"], q_prev=f["q_prev"], q_ref=f["q_ref"]),
        batches=batches,
        outputs=outputs,
        hessian_mode=hessian_mode,
        active_only=active_only,
    )


def _batch(r: _Reader, b: int, raw: Any) -> Joints:
    loc = ("batches", b)
    fields = r.fields(raw, loc, _BATCH_KEYS)
    arrays = {
        k: r.array(fields.get(k), (*loc, k), dtype, ndim, np.zeros((0,) * ndim))
        for k, (dtype, ndim) in _JOINT_ARRAYS.items()
        if k in fields
    }
    uid = r.int64(fields.get("constitution_uid", 0), (*loc, "constitution_uid"))
    ids = arrays.get("body_ids", _EMPTY["i"])
    return Joints(
        constitution_uid=uid,
        base_uid=r.int64(fields["base_uid"], (*loc, "base_uid")) if "base_uid" in fields else base_uid_of(uid),
        body_ids=ids,
        edges=arrays.get("edges", np.zeros((0, 2, 3))),
        lower=arrays.get("lower", np.zeros(0)),
        upper=arrays.get("upper", np.zeros(0)),
        strength=arrays["strength"] if "strength" in fields else strength_of(None, ids.shape[0]),
        offset=arrays.get("offset"),
        prev_coordinate=arrays.get("prev_coordinate"),
    )


def _options(r: _Reader, top: dict[str, Any]) -> tuple[list[str], str, bool]:
    outputs = top.get("outputs", list(OUTPUTS))
    if not isinstance(outputs, list) or not all(isinstance(o, str) for o in outputs):
        r.fault(("outputs",), "Input should be a list of strings", "list_type")
        outputs = list(OUTPUTS)
    hessian_mode = top.get("hessian_mode", "exact")
    if not isinstance(hessian_mode, str):
        r.fault(("hessian_mode",), "Input should be 'exact' or 'psd'", "literal_error")
        hessian_mode = "exact"
    active_only = top.get("active_only", False)
    if not isinstance(active_only, bool):
        r.fault(("active_only",), "Input should be a valid boolean", "bool_type")
        active_only = False
    return outputs, hessian_mode, active_only


def encode(ev: Evaluation) -> bytes:
    """The response document: arrays as raw little-endian buffers (one copy each, into the message)."""
    batches = []
    for res in ev.batches:
        out: dict[str, Any] = {
            "constitution_uid": res.constitution_uid,
            "index": wire.pack_array(res.index, wire.INT64),
            "x": wire.pack_array(res.x, wire.FLOAT64),
            **({} if res.coordinate is None else {"coordinate": wire.pack_array(res.coordinate, wire.FLOAT64)}),
            "energy": wire.pack_array(res.energy, wire.FLOAT64),
        }
        for k in ("gradient", "hessian"):
            a = getattr(res, k)
            if a is not None:
                out[k] = wire.pack_array(a, wire.FLOAT64)
        batches.append(out)
    return wire.dumps({"total_energy": float(ev.total_energy), "batches": batches})
