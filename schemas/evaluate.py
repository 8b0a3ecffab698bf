"""Pydantic models of `POST /v1/evaluate` (CONTRACT.md, wire contract v1, v1.1 and v1.2).

The models describe the document (fields, literals, shapes: row lengths, pairs, triples) for OpenAPI and
for a request built from them directly (the SDK takes one). The service does not validate with them: its one
validator (`service/http/document.py`) reads their fields' names and which are required, checks a decoded
document in their words, and hands the numeric arrays to the core (`service/core/validate.py`), which checks
shapes and everything that needs arithmetic (finiteness, ranges, singular frames), so that every path, the
in-process SDK included, gets the same faults.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, FailFast, Field, WithJsonSchema

Output = Literal["energy", "gradient", "hessian"]
HessianMode = Literal["exact", "psd"]
Layout = Literal["joints", "bodies"]
Origin = Literal["q_ref", "absolute"]
OUTPUTS: tuple[Output, ...] = ("energy", "gradient", "hessian")

# Non-finite numbers (NaN, Infinity, 1e400, and `null`, which is what most JSON writers make of a
# NaN: it arrives as NaN) pass here and are refused by the core's one check
# (service/core/validate.py), which names every one to the element with the same words on every
# path (JSON, msgpack, in-process); FailFast below would otherwise hide all but a list's first.
# strict: a number is a JSON number (integers included), never a string such as "0.5".
# FailFast: a list's first bad item ends its checks, so a body of a million bad rows gets a
# handful of errors, not a million (the service lists at most MAX_FAULTS anyway).
Real = Annotated[float | None, Field(strict=True, allow_inf_nan=True), WithJsonSchema({"type": "number"})]
Dof = Annotated[list[Real], Field(min_length=12, max_length=12), FailFast()]
Vec3 = Annotated[list[Real], Field(min_length=3, max_length=3), FailFast()]
Edge = Annotated[list[Vec3], Field(min_length=2, max_length=2), FailFast()]
LocalEdge = Annotated[list[Edge], Field(min_length=2, max_length=2), FailFast()]  # [[l0, l1], [r0, r1]]
# Integers are JSON integers (no 1.0, no "1", no true) that fit int64, as the binary encoding carries them.
Int64 = Annotated[int, Field(strict=True, ge=-(2**63), le=2**63 - 1)]
BodyPair = Annotated[list[Int64], Field(min_length=2, max_length=2), FailFast()]


class _Wire(BaseModel):
    # A misspelt field is an error, not a silently ignored default.
    model_config = ConfigDict(extra="forbid")


# The words of /openapi.json, enough for a C++ or Julia author alone (tests/docs/test_openapi_docs.py); the UID
# fields' words and values are the registry's, written when the document is made (service/http/openapi.py).
_DOFS = (
    "12 DOFs of an affine body, [p (3), A row 0 (3), A row 1 (3), A row 2 (3)]: a body-local point X "
    "sits at p + A X in the world"
)
_JOINT_DOFS = "the joint's 24 DOFs [q_i (12), q_j (12)], i = body_ids[k][0], j = body_ids[k][1]"
_ROWS = "One entry per joint of the batch (N = len(body_ids))."


class Bodies(_Wire):
    """Every body once; joints refer to rows by index. Each row is 12 DOFs `[p, A row 0, A row 1, A row 2]`."""

    q: Annotated[list[Dof], FailFast()] = Field(
        description=f"Current DOFs (the Newton iterate), one row per body, (B, 12); {_DOFS}."
    )
    q_prev: Annotated[list[Dof], FailFast()] = Field(
        description="DOFs at the previous time step, (B, 12), same rows as q. The revolute angle is "
        "accumulated incrementally q_ref -> q_prev -> q."
    )
    q_ref: Annotated[list[Dof], FailFast()] = Field(
        description="DOFs when the joints were built (the scene's initial transform), (B, 12), same rows as q. "
        "Edges are given in world space at q_ref; A_ref must not be singular."
    )


def _no_default(schema: dict) -> None:
    schema.pop("default", None)  # absent means "follows" (see the description), not null


def _absent(description: str | None = None) -> Any:
    """An optional field, absent on the wire (never null)."""
    return Field(None, description=description, json_schema_extra=_no_default)


class JointBatch(_Wire):
    """Joints of one constitution; all per-joint lists have one entry per joint."""

    constitution_uid: Int64
    # The optional fields are filled in by the validator (service/http/document.py: base_uid_of and the defaults).
    base_uid: Int64 = _absent()
    body_ids: Annotated[list[BodyPair], FailFast()] = Field(
        description=f"(N, 2) body rows [i, j] of each joint, i != j, 0 <= i, j < B. {_ROWS}"
    )
    # Exactly one of `edges` and `local_edges` (the core names the batch otherwise, on every path).
    edges: Annotated[list[Edge], FailFast()] = _absent(
        "(N, 2, 3) each joint's edge [p0, p1] in world space at q_ref: the axis t = (p1 - p0) / "
        "|p1 - p0| is the revolute axis (670) or the sliding direction (669), p0 the prismatic anchor. "
        f"Exactly one of edges and local_edges per batch. {_ROWS}"
    )
    local_edges: Annotated[list[LocalEdge], FailFast()] = _absent(
        "(N, 2, 2, 3) v1.2, instead of edges: each joint's edge [[l0, l1], [r0, r1]] in body i's and "
        "body j's own coordinates (a body-local point X sits at p + A X; the reference engine's l_position0/1, "
        "r_position0/1). The axis is l1 - l0 carried to the world by body i at q_ref (its rotation R_i for 670, "
        f"A_ref_i for 669); the prismatic anchors are l0 and r0; r1 is unused but must be finite. {_ROWS}"
    )
    origin: Origin = Field(
        "q_ref",
        description="v1.2, optional: where x = 0. 'q_ref' (default, the specs): at q_ref. 'absolute' (the reference "
        "engine): x is the frames' own coordinate, atan2(sin, cos) at q_ref plus the turn since (670), or the "
        "signed distance between the anchors along the axis (669). A constant in q: derivatives are unchanged.",
    )
    lower: Annotated[list[Real], FailFast()] = Field(
        description="(N,) lower bound of the coordinate x + offset: radians for 670, the DOFs' length unit for "
        f"669; lower <= upper. The penalty's l is lower - offset (lower itself without offset). {_ROWS}"
    )
    upper: Annotated[list[Real], FailFast()] = Field(
        description=f"(N,) upper bound of the coordinate x + offset, same units as lower (u = upper - offset). {_ROWS}"
    )
    strength: Annotated[list[Real], FailFast()] = _absent(
        "(N,) penalty strength s >= 0 (energy unit) of E = s ((x - u)/(u - l))^3 above, "
        "s ((l - x)/(u - l))^3 below, s |x - l|^3 when u == l. Optional: absent, every joint gets 1.0 "
        f"(the reference engine's default; never null). {_ROWS}"
    )
    offset: Annotated[list[Real], FailFast()] = _absent(
        "(N,) v1.1, optional (default 0): the spec's init_angle (670, radians) or init_distance (669). "
        "The reported coordinate is x + offset, and lower / upper bound that coordinate (the penalty uses "
        f"lower - offset, upper - offset). {_ROWS}"
    )
    prev_coordinate: Annotated[list[Real], FailFast()] = _absent(
        "(N,) v1.1, 670 only, optional: the joint's committed, continuously unwrapped "
        "coordinate at q_prev (the spec's angle; any real, several turns allowed). Then x = "
        "(prev_coordinate - offset) + DeltaTheta(q, q_prev); commit a step by sending the coordinate "
        f"answered at the accepted q as the next step's prev_coordinate. {_ROWS}"
    )


class EvaluateRequest(_Wire):
    bodies: Bodies = Field(
        description="Every body once, as three (B, 12) arrays; joints refer to bodies by row (0-based)."
    )
    batches: Annotated[list[JointBatch], FailFast()] = Field(
        description="Groups of joints, one constitution each; several batches may share a constitution."
    )
    outputs: Annotated[list[Output], Field(min_length=1), FailFast()] = Field(
        list(OUTPUTS),
        description="What to compute, at least one of energy, gradient, hessian (default: all three). x and "
        "energy are always answered.",
    )
    hessian_mode: HessianMode = Field(
        "exact",
        description="exact: the true Hessian (not positive semi-definite in general); psd: the 12 x 12 "
        "curvature in the frame quantities projected onto the PSD cone before the chain rule (what the "
        "reference engine does). Default exact.",
    )
    active_only: Annotated[bool, Field(strict=True)] = Field(
        False,
        description="If true, answer only the joints outside their range (the others have zero energy, "
        "gradient and Hessian); each answer row's `index` then names its joint. Default false.",
    )
    layout: Layout = Field(
        "joints",
        description="'joints' (default): gradient and Hessian per joint, in each batch. 'bodies': summed per body "
        "over the whole request, in `assembled` (the batches then carry index, x, coordinate, energy only).",
    )


class BatchResult(_Wire):
    constitution_uid: int
    index: list[int] = Field(
        description="(M,) which joints of the request batch the rows describe: 0..N-1 in order, or with "
        "active_only only the joints outside their range (ascending)."
    )
    x: list[float] = Field(
        description="(M,) joint coordinate: 670 the relative angle of body j about +t (radians, right-hand rule, "
        "incremental, may leave (-pi, pi] by one step's turn); 669 the relative slide along +t."
    )
    coordinate: list[float] = Field(
        description="(M,) v1.1: the reported coordinate x + offset (equal to x without offset)."
    )
    energy: list[float] = Field(description="(M,) penalty energy of each joint (0 inside its range, bounds included).")
    gradient: list[list[float]] | None = Field(
        None, description=f"(M, 24) dE/d[q_i, q_j] per joint, in {_JOINT_DOFS}. Present when outputs has gradient."
    )
    hessian: list[list[list[float]]] | None = Field(
        None,
        description=f"(M, 24, 24) d2E/d[q_i, q_j]^2 per joint, row-major, symmetric, in {_JOINT_DOFS}. "
        "Present when outputs has hessian.",
    )


class AssembledResult(_Wire):
    """`layout="bodies"`: gradient per body (B, 12); Hessian blocks (K, 12, 12) at body pairs rows <= cols."""

    gradient: list[list[float]] | None = Field(
        None,
        description="(B, 12) dE/dq_b per body b (all joints summed), in the DOF order [p, A row 0, A row 1, "
        "A row 2]. Present when outputs has gradient.",
    )
    rows: list[int] | None = Field(
        None,
        description="(K,) body index of each Hessian block's rows; rows <= cols, sorted by (row, col); one entry "
        "per pair of bodies coupled by a joint outside its range. Present when outputs has hessian.",
    )
    cols: list[int] | None = Field(None, description="(K,) body index of each Hessian block's columns (see rows).")
    blocks: list[list[list[float]]] | None = Field(
        None,
        description="(K, 12, 12) d2E/dq_row dq_col summed over joints; the full (12B, 12B) matrix is these blocks "
        "plus the transposes of the off-diagonal ones (rows != cols).",
    )


class EvaluateResponse(_Wire):
    total_energy: float = Field(
        description="Sum of every joint's energy, all batches (including the joints active_only leaves out, "
        "which are 0)."
    )
    batches: list[BatchResult] = Field(description="One entry per request batch, in request order.")
    assembled: AssembledResult | None = Field(
        None, description="With layout 'bodies' only: the gradient and Hessian summed per body over every joint."
    )
