"""OpenAPI of `POST /v1/evaluate`: its body is read raw (two encodings), so its schema is declared here."""

from __future__ import annotations

import copy
from typing import Any

from pydantic.json_schema import models_json_schema

from jointlimits.schemas import EvaluateRequest, ErrorResponse
from jointlimits.service.http import openapi_text as text

_REF = "#/components/schemas/{model}"


def request_body() -> dict[str, Any]:
    """The `requestBody` of the route: the JSON schema of `EvaluateRequest`, or the binary document."""
    return {
        "required": True,
        "content": {
            "application/json": {
                "schema": {"$ref": _REF.format(model="EvaluateRequest")},
                "example": text.EXAMPLE_REQUEST,
            },
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
            "description": "type busy: the worker's memory budgets were full and nothing was evaluated (retry after "
            "Retry-After); type timeout: the evaluation passed the request timeout and was stopped",
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
    return _document(openapi)


def _document(openapi: dict[str, Any]) -> dict[str, Any]:
    """Field descriptions and UID values, the example answer, bearer auth and its 401, X-Request-ID."""
    schemas = openapi["components"]["schemas"]
    uid_words, uid_values = text.registered()
    for model, fields in [*text.FIELDS.items(), *uid_words.items()]:
        props = schemas.get(model, {}).get("properties", {})
        for name, words in fields.items():
            if name in props:
                props[name]["description"] = words
    for (model, name), values in uid_values.items():
        prop = schemas.get(model, {}).get("properties", {}).get(name)
        if prop is not None:
            prop["enum"] = values
    openapi["components"]["securitySchemes"] = {"bearer": text.BEARER}
    for path, ops in openapi.get("paths", {}).items():
        for op in ops.values():
            if path.startswith("/v1/"):
                op["security"] = [{"bearer": []}, {}]  # the bearer token, or none when the API is open
                op["responses"]["401"] = copy.deepcopy(text.UNAUTHORIZED)
            op.setdefault("parameters", []).append(text.REQUEST_ID)
            for answer in op.get("responses", {}).values():
                answer.setdefault("headers", {}).update(text.REQUEST_ID_HEADER)
    ok = openapi["paths"]["/v1/evaluate"]["post"]["responses"]["200"]["content"]
    ok.setdefault("application/json", {})["example"] = text.EXAMPLE_RESPONSE
    return openapi
