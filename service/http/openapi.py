"""What `/openapi.json` says: the schema of `POST /v1/evaluate`, whose raw body (two encodings) FastAPI cannot
describe alone; each wire field's words (the UID fields' from the registry) and the example, enough for a C++ or
Julia author alone. `tests/docs/test_openapi_docs.py` checks that every field of every model is described and
that the example answers what it shows."""

from __future__ import annotations

import copy
from typing import Any

from pydantic.json_schema import models_json_schema

from jointlimits.schemas import EvaluateRequest, ErrorResponse
from jointlimits.service.core import registry
from jointlimits.service.core.revolute import FACTS as HINGE

_REF = "#/components/schemas/{model}"


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
    uid_words, uid_values = registered()
    for model, fields in [*FIELDS.items(), *uid_words.items()]:
        props = schemas.get(model, {}).get("properties", {})
        for name, words in fields.items():
            if name in props:
                props[name]["description"] = words
    for (model, name), values in uid_values.items():
        prop = schemas.get(model, {}).get("properties", {}).get(name)
        if prop is not None:
            prop["enum"] = values
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


DOFS = (
    "12 DOFs of an affine body, [p (3), A row 0 (3), A row 1 (3), A row 2 (3)]: a body-local point X "
    "sits at p + A X in the world"
)
JOINT_DOFS = "the joint's 24 DOFs [q_i (12), q_j (12)], i = body_ids[k][0], j = body_ids[k][1]"
ROWS = "One entry per joint of the batch (N = len(body_ids))."

FIELDS: dict[str, dict[str, str]] = {
    "EvaluateRequest": {
        "bodies": "Every body once, as three (B, 12) arrays; joints refer to bodies by row (0-based).",
        "batches": "Groups of joints, one constitution each; several batches may share a constitution.",
        "layout": "'joints' (default): gradient and Hessian per joint, in each batch. 'bodies': summed per body "
        "over the whole request, in `assembled` (the batches then carry index, x, coordinate, energy only).",
        "outputs": "What to compute, at least one of energy, gradient, hessian (default: all three). x and "
        "energy are always answered.",
        "hessian_mode": "exact: the true Hessian (not positive semi-definite in general); psd: the 12 x 12 "
        "curvature in the frame quantities projected onto the PSD cone before the chain rule (what the "
        "reference engine does). Default exact.",
        "active_only": "If true, answer only the joints outside their range (the others have zero energy, "
        "gradient and Hessian); each answer row's `index` then names its joint. Default false.",
    },
    "Bodies": {
        "q": f"Current DOFs (the Newton iterate), one row per body, (B, 12); {DOFS}.",
        "q_prev": "DOFs at the previous time step, (B, 12), same rows as q. The revolute angle is "
        "accumulated incrementally q_ref -> q_prev -> q.",
        "q_ref": "DOFs when the joints were built (the scene's initial transform), (B, 12), same rows as q. "
        "Edges are given in world space at q_ref; A_ref must not be singular.",
    },
    "JointBatch": {
        "body_ids": f"(N, 2) body rows [i, j] of each joint, i != j, 0 <= i, j < B. {ROWS}",
        "edges": "(N, 2, 3) each joint's edge [p0, p1] in world space at q_ref: the axis t = (p1 - p0) / "
        "|p1 - p0| is the revolute axis (670) or the sliding direction (669), p0 the prismatic anchor. "
        f"Exactly one of edges and local_edges per batch. {ROWS}",
        "local_edges": "(N, 2, 2, 3) v1.2, instead of edges: each joint's edge [[l0, l1], [r0, r1]] in body i's and "
        "body j's own coordinates (a body-local point X sits at p + A X; the reference engine's l_position0/1, "
        "r_position0/1). The axis is l1 - l0 carried to the world by body i at q_ref (its rotation R_i for 670, "
        f"A_ref_i for 669); the prismatic anchors are l0 and r0; r1 is unused but must be finite. {ROWS}",
        "origin": "v1.2, optional: where x = 0. 'q_ref' (default, the specs): at q_ref. 'absolute' (the reference "
        "engine): x is the frames' own coordinate, atan2(sin, cos) at q_ref plus the turn since (670), or the "
        "signed distance between the anchors along the axis (669). A constant in q: derivatives are unchanged.",
        "lower": "(N,) lower bound of the coordinate x + offset: radians for 670, the DOFs' length unit for "
        f"669; lower <= upper. The penalty's l is lower - offset (lower itself without offset). {ROWS}",
        "upper": f"(N,) upper bound of the coordinate x + offset, same units as lower (u = upper - offset). {ROWS}",
        "strength": "(N,) penalty strength s >= 0 (energy unit) of E = s ((x - u)/(u - l))^3 above, "
        "s ((l - x)/(u - l))^3 below, s |x - l|^3 when u == l. Optional: absent, every joint gets 1.0 "
        f"(the reference engine's default; never null). {ROWS}",
        "offset": "(N,) v1.1, optional (default 0): the spec's init_angle (670, radians) or init_distance (669). "
        "The reported coordinate is x + offset, and lower / upper bound that coordinate (the penalty uses "
        f"lower - offset, upper - offset). {ROWS}",
        "prev_coordinate": "(N,) v1.1, 670 only, optional: the joint's committed, continuously unwrapped "
        "coordinate at q_prev (the spec's angle; any real, several turns allowed). Then x = "
        "(prev_coordinate - offset) + DeltaTheta(q, q_prev); commit a step by sending the coordinate "
        f"answered at the accepted q as the next step's prev_coordinate. {ROWS}",
    },
    "EvaluateResponse": {
        "total_energy": "Sum of every joint's energy, all batches (including the joints active_only leaves out, "
        "which are 0).",
        "batches": "One entry per request batch, in request order.",
        "assembled": "With layout 'bodies' only: the gradient and Hessian summed per body over every joint.",
    },
    "AssembledResult": {
        "gradient": "(B, 12) dE/dq_b per body b (all joints summed), in the DOF order [p, A row 0, A row 1, A row 2]. "
        "Present when outputs has gradient.",
        "rows": "(K,) body index of each Hessian block's rows; rows <= cols, sorted by (row, col); one entry per "
        "pair of bodies coupled by a joint outside its range. Present when outputs has hessian.",
        "cols": "(K,) body index of each Hessian block's columns (see rows).",
        "blocks": "(K, 12, 12) d2E/dq_row dq_col summed over joints; the full (12B, 12B) matrix is these blocks "
        "plus the transposes of the off-diagonal ones (rows != cols).",
    },
    "BatchResult": {
        "index": "(M,) which joints of the request batch the rows describe: 0..N-1 in order, or with "
        "active_only only the joints outside their range (ascending).",
        "x": "(M,) joint coordinate: 670 the relative angle of body j about +t (radians, right-hand rule, "
        "incremental, may leave (-pi, pi] by one step's turn); 669 the relative slide along +t.",
        "coordinate": "(M,) v1.1: the reported coordinate x + offset (equal to x without offset).",
        "energy": "(M,) penalty energy of each joint (0 inside its range, bounds included).",
        "gradient": f"(M, 24) dE/d[q_i, q_j] per joint, in {JOINT_DOFS}. Present when outputs has gradient.",
        "hessian": f"(M, 24, 24) d2E/d[q_i, q_j]^2 per joint, row-major, symmetric, in {JOINT_DOFS}. "
        "Present when outputs has hessian.",
    },
    "ErrorResponse": {"detail": "Every fault found (up to 20 per check)."},
    "ConstitutionsResponse": {
        "constitutions": "Each constitution this service evaluates.",
        "limits": "This deployment's request limits (larger requests answer 413; the Python SDK splits by them).",
    },
    "ConstitutionInfo": {
        "uid": "The constitution's UID, the wire's constitution_uid.",
        "name": "Its name in the specs.",
        "base_uid": "The base joint's UID it pairs with (the wire's base_uid).",
        "base_name": "The base joint's name.",
        "coordinate": "What the joint coordinate x measures, and its unit.",
        "origin": "v1.2: where x = 0 for each value of a batch's origin ('q_ref', 'absolute': the reference engine's zero).",
        "attributes": "Its per-joint inputs, by their spec names (the edges by the reference engine's attribute names).",
    },
    "Attribute": {
        "name": "The spec's attribute name (limit/lower, limit/upper, limit/strength).",
        "field": "The wire field (a per-joint list of JointBatch).",
        "unit": "Its unit (rad, the DOFs' length unit, energy unit).",
        "default": "The default an absent field takes (null: required).",
        "description": "What it means.",
    },
    "Limits": {
        "max_body_bytes": "Largest request body accepted, in bytes (JOINTLIMITS_MAX_BODY_BYTES).",
        "max_joints": "Most joints, over all batches, in one request (JOINTLIMITS_MAX_JOINTS).",
        "max_batches": "Most batches in one request (JOINTLIMITS_MAX_BATCHES).",
        "max_answer_bytes": "Largest answer, bounded from joints x outputs x encoding before any work "
        "(JOINTLIMITS_MAX_ANSWER_BYTES; schemas/answer.py computes the bound).",
        "max_json_values": "Most values (commas + 1) in a JSON body, counted before parsing (JOINTLIMITS_MAX_JSON_VALUES).",
    },
    "ErrorItem": {
        "loc": "Where: starts with body (or header), then field, batch, joint, element, e.g. "
        '["body", "batches", 1, "lower", 2].',
        "msg": "What is wrong, in words.",
        "type": "A stable machine-readable kind, e.g. finite_number, too_short, missing, value_error, too_large.",
    },
}



def registered() -> tuple[dict[str, dict[str, str]], dict[tuple[str, str], list[int]]]:
    """The descriptions and values of the UID fields, from the constitutions registered now."""
    facts = registry.CONSTITUTIONS.values()
    names = " or ".join(f"{f.uid} ({f.name})" for f in facts)
    pairs = ", ".join(f"{f.base_uid} ({f.base_name}) with {f.uid}" for f in facts)
    uids = [f.uid for f in facts]
    words = {
        "JointBatch": {
            "constitution_uid": f"{names}.",
            "base_uid": f"The base joint the limit applies to: {pairs}; any other pairing is refused. Optional: "
            "absent, it follows from constitution_uid (never null).",
        },
        "BatchResult": {"constitution_uid": f"The request batch's constitution ({' or '.join(map(str, uids))})."},
    }
    enums = {
        ("JointBatch", "constitution_uid"): uids,
        ("JointBatch", "base_uid"): [f.base_uid for f in facts],
        ("BatchResult", "constitution_uid"): uids,
    }
    return words, enums


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
    "description": "Only when the deployment sets JOINTLIMITS_TOKEN (otherwise the API is open); /healthz, "
    "/metrics and /openapi.json are always open.",
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
