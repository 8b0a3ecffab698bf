"""Pydantic models of `POST /v1/evaluate` (CONTRACT.md, wire contract v1, v1.1 and v1.2).

The models describe the document (fields, literals, shapes: row lengths, pairs, triples) for OpenAPI and
for a request built from them directly (the SDK takes one). The service does not validate with them: its one
validator (`service/http/document.py`) reads their fields' names and which are required, checks a decoded
document in their words, and hands the numeric arrays to the core (`service/core/validate.py`), which checks
shapes and everything that needs arithmetic (finiteness, ranges, singular frames), so that every path, the
in-process SDK included, gets the same faults.
"""

from __future__ import annotations

from typing import Annotated, Literal

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


class Bodies(_Wire):
    """Every body once; joints refer to rows by index. Each row is 12 DOFs `[p, A row 0, A row 1, A row 2]`."""

    q: Annotated[list[Dof], FailFast()]
    q_prev: Annotated[list[Dof], FailFast()]
    q_ref: Annotated[list[Dof], FailFast()]


def _no_default(schema: dict) -> None:
    schema.pop("default", None)  # absent means "follows" (see the description), not null


class JointBatch(_Wire):
    """Joints of one constitution; all per-joint lists have one entry per joint."""

    constitution_uid: Int64
    # Optional on the wire (absent, never null): the validator fills them in (service/http/document.py: base_uid_of and the defaults).
    base_uid: Int64 = Field(None, json_schema_extra=_no_default)
    body_ids: Annotated[list[BodyPair], FailFast()]
    # Exactly one of `edges` and `local_edges` (the core names the batch otherwise, on every path).
    edges: Annotated[list[Edge], FailFast()] = Field(None, json_schema_extra=_no_default)
    local_edges: Annotated[list[LocalEdge], FailFast()] = Field(None, json_schema_extra=_no_default)
    """v1.2: per joint [[l0, l1], [r0, r1]], the edge in body i's and body j's own coordinates."""
    origin: Origin = "q_ref"
    """v1.2: "q_ref" (x = 0 at q_ref, the specs) or "absolute" (the reference engine's zero)."""
    lower: Annotated[list[Real], FailFast()]
    upper: Annotated[list[Real], FailFast()]
    strength: Annotated[list[Real], FailFast()] = Field(None, json_schema_extra=_no_default)
    offset: Annotated[list[Real], FailFast()] = Field(None, json_schema_extra=_no_default)
    """v1.1 (both constitutions, default 0): the spec's `init_angle` / `init_distance`; coordinate =
    x + offset, and `lower` / `upper` bound the coordinate."""
    prev_coordinate: Annotated[list[Real], FailFast()] = Field(None, json_schema_extra=_no_default)
    """v1.1 (670 only): the committed, unwrapped coordinate at `q_prev` (the spec's `angle`); then
    x = (prev_coordinate - offset) + DeltaTheta(q, q_prev)."""


class EvaluateRequest(_Wire):
    bodies: Bodies
    batches: Annotated[list[JointBatch], FailFast()]
    outputs: Annotated[list[Output], Field(min_length=1), FailFast()] = list(OUTPUTS)
    hessian_mode: HessianMode = "exact"
    active_only: Annotated[bool, Field(strict=True)] = False
    layout: Layout = "joints"
    """"bodies": the gradient and Hessian summed per body (`assembled`), batches without them."""


class BatchResult(_Wire):
    constitution_uid: int
    index: list[int]
    x: list[float]
    coordinate: list[float]
    """v1.1: x + offset, per reported joint."""
    energy: list[float]
    gradient: list[list[float]] | None = None
    hessian: list[list[list[float]]] | None = None


class AssembledResult(_Wire):
    """`layout="bodies"`: gradient per body (B, 12); Hessian blocks (K, 12, 12) at body pairs rows <= cols."""

    gradient: list[list[float]] | None = None
    rows: list[int] | None = None
    cols: list[int] | None = None
    blocks: list[list[list[float]]] | None = None


class EvaluateResponse(_Wire):
    total_energy: float
    batches: list[BatchResult]
    assembled: AssembledResult | None = None
