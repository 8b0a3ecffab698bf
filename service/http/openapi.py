"""OpenAPI of `POST /v1/evaluate`: its body is read raw (two encodings), so its schema is declared here."""

from __future__ import annotations

from typing import Any

from pydantic.json_schema import models_json_schema

from schemas import EvaluateRequest, ErrorResponse

_REF = "#/components/schemas/{model}"


def request_body() -> dict[str, Any]:
    """The `requestBody` of the route: the JSON schema of `EvaluateRequest`, or the binary document."""
    return {
        "required": True,
        "content": {
            "application/json": {"schema": {"$ref": _REF.format(model="EvaluateRequest")}},
            "application/msgpack": {
                "schema": {"type": "string", "format": "binary"},
                "description": "EvaluateRequest in the binary encoding (README, Binary transport)",
            },
        },
    }


def error_responses() -> dict[int | str, dict[str, Any]]:
    schema = {"$ref": _REF.format(model="ErrorResponse")}
    content = {"application/json": {"schema": schema}}
    return {
        406: {"description": "Accept names no supported encoding", "content": content},
        413: {
            "description": "Over a configured limit, before any work: body bytes, joints, batches, "
            "the answer's size bound, or a JSON body's values",
            "content": content,
        },
        415: {"description": "Content-Type is neither JSON nor msgpack", "content": content},
        422: {"description": "Malformed or physically meaningless input; loc names the field", "content": content},
        503: {
            "description": "The evaluation passed the request timeout and was stopped; see Retry-After",
            "content": content,
            "headers": {"Retry-After": {"schema": {"type": "integer"}, "description": "seconds"}},
        },
    }


def add_components(openapi: dict[str, Any]) -> dict[str, Any]:
    """Add the request and error models (and what they refer to) to `components.schemas`."""
    _, top = models_json_schema(
        [(EvaluateRequest, "validation"), (ErrorResponse, "serialization")], ref_template=_REF
    )
    schemas = openapi.setdefault("components", {}).setdefault("schemas", {})
    for name, schema in top.get("$defs", {}).items():
        schemas.setdefault(name, schema)
    return openapi
