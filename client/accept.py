"""What `evaluate` takes: a `Request`, the wire JSON as a dict, or a `schemas.EvaluateRequest`; one conversion."""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson

from jointlimits.client.errors import Fault, InvalidInput
from jointlimits.client.model import JointBatch, Request
from jointlimits.schemas import EvaluateRequest
from jointlimits.schemas.constitutions import STRENGTH_DEFAULT

ACCEPTED = "a client.Request (Scene().request(), request_from_arrays(...)), a dict in the wire JSON's shape, or a schemas.EvaluateRequest"


def as_request(request: Any) -> Request:
    """`request` as a `Request`.

    A dict is read exactly as the service reads a JSON body (NumPy arrays in it are fine): its
    faults raise `InvalidInput` with the server's `loc`s and words. Anything else: `TypeError`.
    """
    if isinstance(request, Request):
        return request
    if isinstance(request, EvaluateRequest):
        return _from_wire(request)
    if isinstance(request, dict):
        try:
            body = orjson.dumps(request, option=orjson.OPT_SERIALIZE_NUMPY)
        except TypeError as e:
            raise TypeError(f"evaluate(): the dict is not wire JSON ({e})") from None
        # The service's own JSON reader (imported here: HTTP alone never loads it): the same faults, in the same words.
        from jointlimits.service.core import InputError
        from jointlimits.service.http.convert import read

        try:
            kw = read(body)
        except InputError as e:
            raise InvalidInput(422, [Fault(("body", *f.loc), f.msg, f.type) for f in e.faults], where="invalid input") from None
        b = kw["bodies"]
        batches = [JointBatch(**{f: getattr(j, f) for f in _JOINT_FIELDS}) for j in kw["batches"]]
        return Request(b.q, b.q_prev, b.q_ref, batches, tuple(kw["outputs"]), kw["hessian_mode"], kw["active_only"], kw["layout"])
    raise TypeError(f"evaluate() takes {ACCEPTED}; got {type(request).__module__}.{type(request).__qualname__}")


_JOINT_FIELDS = ("constitution_uid", "body_ids", "edges", "local_edges", "origin", "lower", "upper", "strength", "base_uid",
                 "offset", "prev_coordinate")


def _from_wire(req: EvaluateRequest) -> Request:
    f64 = lambda rows, *tail: np.asarray(rows, dtype=np.float64).reshape(len(rows), *tail)  # noqa: E731
    batches = [
        JointBatch(
            constitution_uid=j.constitution_uid,
            body_ids=np.asarray(j.body_ids, dtype=np.int64).reshape(len(j.body_ids), 2),
            edges=None if j.edges is None else f64(j.edges, 2, 3),
            local_edges=None if j.local_edges is None else f64(j.local_edges, 2, 2, 3),
            origin=j.origin,
            lower=f64(j.lower),
            upper=f64(j.upper),
            strength=np.full(len(j.body_ids), STRENGTH_DEFAULT) if j.strength is None else f64(j.strength),
            base_uid=j.base_uid,
            offset=None if j.offset is None else f64(j.offset),
            prev_coordinate=None if j.prev_coordinate is None else f64(j.prev_coordinate),
        )
        for j in req.batches
    ]
    b = req.bodies
    return Request(f64(b.q, 12), f64(b.q_prev, 12), f64(b.q_ref, 12), batches, tuple(req.outputs),
                   req.hessian_mode, req.active_only, req.layout)
