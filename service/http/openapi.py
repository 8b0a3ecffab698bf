"""What `/openapi.json` says: the schema of `POST /v1/evaluate`, whose raw body (two encodings) FastAPI cannot
describe alone; the UID fields' words and values, from the registry (every other field's words are the wire
models' own), and the example. `tests/docs/test_openapi_docs.py` checks that every field of every model is
described and that the example answers what it shows."""

from __future__ import annotations

import copy
from typing import Any

from pydantic.json_schema import models_json_schema

from jointlimits.schemas import EvaluateRequest, ErrorResponse
from jointlimits.service.core import registry
from jointlimits.service.core.revolute import FACTS as HINGE

_REF = "#/components/schemas/{model}"


def add_components(openapi: dict[str, Any]) -> dict[str, Any]:
    """Add the request and error models (and what they refer to) to `components.schemas`; the UID fields' words and
    values, the example answer, bearer auth and its 401, X-Request-ID."""
    _, top = models_json_schema(
        [(EvaluateRequest, "validation"), (ErrorResponse, "serialization")], ref_template=_REF
    )
    schemas = openapi.setdefault("components", {}).setdefault("schemas", {})
    for name, schema in top.get("$defs", {}).items():
        schemas.setdefault(name, schema)
    for (model, name), words in registered().items():
        schemas[model]["properties"][name].update(words)
    openapi["components"]["securitySchemes"] = {"bearer": BEARER}
    for path, ops in openapi.get("paths", {}).items():
        for op in ops.values():
            if path.startswith("/v1/"):
                op["security"] = [{"bearer": []}, {}]  # the bearer token, or none when the API is open
                op["responses"]["401"] = copy.deepcopy(UNAUTHORIZED)
            op.setdefault("parameters", []).append(REQUEST_ID)
            for answer in op.get("responses", {}).values():
                answer.setdefault("headers", {}).update(REQUEST_ID_HEADER)
    ok = openapi["paths"]["/v1/evaluate"]["post"]["responses"]["200"]["content"]
    ok.setdefault("application/json", {})["example"] = EXAMPLE_RESPONSE
    return openapi


def registered() -> dict[tuple[str, str], dict[str, Any]]:
    """The UID fields' description and values, from the constitutions registered now."""
    facts = registry.CONSTITUTIONS.values()
    names = " or ".join(f"{f.uid} ({f.name})" for f in facts)
    pairs = ", ".join(f"{f.base_uid} ({f.base_name}) with {f.uid}" for f in facts)
    uids = [f.uid for f in facts]
    return {
        ("JointBatch", "constitution_uid"): {"description": f"{names}.", "enum": uids},
        ("JointBatch", "base_uid"): {
            "description": f"The base joint the limit applies to: {pairs}; any other pairing is refused. Optional: "
            "absent, it follows from constitution_uid (never null).",
            "enum": [f.base_uid for f in facts],
        },
        ("BatchResult", "constitution_uid"): {
            "description": f"The request batch's constitution ({' or '.join(map(str, uids))}).",
            "enum": uids,
        },
    }


# The README's example: body 1 turned 0.7 rad about +z, 0.2 rad past the upper limit of 0.5.
_C, _S = 0.7648421872844885, 0.644217687237691
_I = [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]
EXAMPLE_REQUEST: dict[str, Any] = {
    "bodies": {
        "q": [_I, [0, 0, 0, _C, -_S, 0, _S, _C, 0, 0, 0, 1]],
        "q_prev": [_I, _I],
        "q_ref": [_I, _I],
    },
    "batches": [
        {"constitution_uid": HINGE.uid, "base_uid": HINGE.base_uid, "body_ids": [[0, 1]], "edges": [[[0, 0, 0], [0, 0, 1]]],
         "lower": [-0.5], "upper": [0.5], "strength": [100.0]}
    ],
    "outputs": ["energy", "gradient"],
}
EXAMPLE_RESPONSE: dict[str, Any] = {
    "total_energy": 0.7999999999999995,
    "batches": [
        {
            "constitution_uid": HINGE.uid,
            "index": [0],
            "x": [0.7],
            "coordinate": [0.7],
            "energy": [0.7999999999999995],
            "gradient": [[
                0.0, 0.0, 0.0, 0.0, 5.999999999999997, 0.0, -5.999999999999997, 0.0,
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -3.8653061234261443,
                -4.589053123706929, 0.0, 4.589053123706929, -3.8653061234261443, 0.0, 0.0, 0.0, 0.0,
            ]],
        }
    ],
}

REQUEST_ID = {
    "name": "X-Request-ID",
    "in": "header",
    "required": False,
    "description": "Your id for this request (up to 128 characters of [A-Za-z0-9._:-]); echoed in the "
    "answer's X-Request-ID and the access log. Absent or invalid, the service makes one.",
    "schema": {"type": "string", "maxLength": 128, "pattern": "^[A-Za-z0-9._:-]{1,128}$"},
}
REQUEST_ID_HEADER = {
    "X-Request-ID": {"description": "The caller's X-Request-ID, or the one the service made.", "schema": {"type": "string"}}
}
UNAUTHORIZED = {
    "description": "A token is configured (JOINTLIMITS_TOKEN) and the request has no valid "
    "`Authorization: Bearer <token>`; answered before the body is read.",
    "headers": {"WWW-Authenticate": {"description": 'Bearer realm="jointlimits"', "schema": {"type": "string"}}},
    "content": {"application/json": {
        "schema": {"$ref": "#/components/schemas/ErrorResponse"},  # the fault list, as every refusal
        "example": {"detail": [{"loc": ["header", "authorization"], "msg": "missing or invalid bearer token", "type": "unauthorized"}]},
    }},
}
BEARER = {
    "type": "http",
    "scheme": "bearer",
    "description": "Only when the deployment sets JOINTLIMITS_TOKEN (otherwise the API is open); only /v1/ needs it "
    "(/healthz, /readyz, /metrics, /openapi.json and /docs do not).",
}

REQUEST_BODY: dict[str, Any] = {  # the route's body: the JSON schema of `EvaluateRequest`, or the binary document
    "required": True,
    "content": {
        "application/json": {"schema": {"$ref": _REF.format(model="EvaluateRequest")}, "example": EXAMPLE_REQUEST},
        # A Media Type Object has no `description` (OpenAPI 3.1 forbids unknown keys there): it goes in the schema.
        "application/msgpack": {
            "schema": {
                "type": "string",
                "format": "binary",
                "description": "EvaluateRequest in the binary encoding (docs/http-api.md, Binary transport)",
            },
        },
    },
}
_FAULTS = {"application/json": {"schema": {"$ref": _REF.format(model="ErrorResponse")}}}
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    406: {"description": "Accept names no supported encoding", "content": _FAULTS},
    413: {
        "description": "Over a configured limit, before any work: body bytes, joints, batches, "
        "the answer's size bound, or a JSON body's values",
        "content": _FAULTS,
    },
    415: {"description": "Content-Type is neither JSON nor msgpack", "content": _FAULTS},
    422: {"description": "Malformed or physically meaningless input; loc names the field", "content": _FAULTS},
    503: {
        "description": "type busy: the worker's memory budgets were full and nothing was evaluated (retry after "
        "Retry-After); type timeout: the evaluation passed the request timeout and was stopped",
        "content": _FAULTS,
        "headers": {"Retry-After": {"schema": {"type": "integer"}, "description": "seconds"}},
    },
}
