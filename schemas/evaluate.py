"""Pydantic models of `POST /v1/evaluate` (CONTRACT.md, wire contract v1 and v1.1).

Shapes are checked here (row lengths, pairs, triples); everything that needs
arithmetic (finiteness, ranges, singular frames) is checked by the core so that
the in-process SDK gets the same errors as HTTP callers.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

Output = Literal["energy", "gradient", "hessian"]
HessianMode = Literal["exact", "psd"]
OUTPUTS: tuple[Output, ...] = ("energy", "gradient", "hessian")

# allow_inf_nan=False: a 200 never carries NaN or Infinity, so none may come in (nor 1e400).
# strict: a number is a JSON number (integers included), never a string such as "0.5".
Real = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Dof = Annotated[list[Real], Field(min_length=12, max_length=12)]
Vec3 = Annotated[list[Real], Field(min_length=3, max_length=3)]
Edge = Annotated[list[Vec3], Field(min_length=2, max_length=2)]
# Integers are JSON integers (no 1.0, no "1", no true) that fit int64, as the binary encoding carries them.
Int64 = Annotated[int, Field(strict=True, ge=-(2**63), le=2**63 - 1)]
BodyPair = Annotated[list[Int64], Field(min_length=2, max_length=2)]


class _Wire(BaseModel):
    # A misspelt field is an error, not a silently ignored default.
    model_config = ConfigDict(extra="forbid")


class Bodies(_Wire):
    """Every body once; joints refer to rows by index. Each row is 12 DOFs `[p, A row 0, A row 1, A row 2]`."""

    q: list[Dof]
    q_prev: list[Dof]
    q_ref: list[Dof]


def _no_default(schema: dict) -> None:
    schema.pop("default", None)  # absent means "follows" (see the description), not null


class JointBatch(_Wire):
    """Joints of one constitution; all per-joint lists have one entry per joint."""

    constitution_uid: Int64
    # Optional on the wire (absent, never null): the core fills them in (service/http/convert.py: defaults).
    base_uid: Int64 = Field(None, json_schema_extra=_no_default)
    body_ids: list[BodyPair]
    edges: list[Edge]
    lower: list[Real]
    upper: list[Real]
    strength: list[Real] = Field(None, json_schema_extra=_no_default)
    offset: list[Real] | None = None
    """v1.1 (both constitutions, default 0): the spec's `init_angle` / `init_distance`; coordinate =
    x + offset, and `lower` / `upper` bound the coordinate."""
    prev_coordinate: list[Real] | None = None
    """v1.1 (670 only): the committed, unwrapped coordinate at `q_prev` (the spec's `angle`); then
    x = (prev_coordinate - offset) + DeltaTheta(q, q_prev)."""


class EvaluateRequest(_Wire):
    bodies: Bodies
    batches: list[JointBatch]
    outputs: Annotated[list[Output], Field(min_length=1)] = list(OUTPUTS)
    hessian_mode: HessianMode = "exact"
    active_only: Annotated[bool, Field(strict=True)] = False


class BatchResult(_Wire):
    constitution_uid: int
    index: list[int]
    x: list[float]
    coordinate: list[float]
    """v1.1: x + offset, per reported joint."""
    energy: list[float]
    gradient: list[list[float]] | None = None
    hessian: list[list[list[float]]] | None = None


class EvaluateResponse(_Wire):
    total_energy: float
    batches: list[BatchResult]
