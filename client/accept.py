"""What `evaluate` takes: a `Request`, the wire JSON as a dict, or a `schemas.EvaluateRequest`; one conversion."""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import orjson

from jointlimits.client.model import JointBatch, Request, in_body
from jointlimits.schemas import EvaluateRequest

ACCEPTED = ("a client.Request (Scene().request(), request_from_arrays(...)), a dict in the wire JSON's shape, "
            "or a schemas.EvaluateRequest")


def as_request(request: Any) -> Request:
    """`request` as a `Request`.

    A dict (or an `EvaluateRequest`, as its dict) is read exactly as the service reads a JSON body (NumPy
    arrays in it are fine): its faults raise `InvalidInput` with the server's `loc`s and words. Anything
    else: `TypeError`.
    """
    if isinstance(request, Request):
        return request
    if isinstance(request, EvaluateRequest):
        request = request.model_dump(exclude_none=True)  # an absent optional field, as the wire has it
    if not isinstance(request, dict):
        raise TypeError(f"evaluate() takes {ACCEPTED}; got {type(request).__module__}.{type(request).__qualname__}")
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
        raise in_body(e.faults) from None
    b = kw["bodies"]
    # The core's `Joints` has the SDK's `JointBatch` fields, by the same names.
    batches = [JointBatch(**{f.name: getattr(j, f.name) for f in fields(JointBatch)}) for j in kw["batches"]]
    return Request(b.q, b.q_prev, b.q_ref, batches, tuple(kw["outputs"]), kw["hessian_mode"], kw["active_only"],
                   kw["layout"])
