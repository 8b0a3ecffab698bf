"""`GET /v1/constitutions`: what the service evaluates, in the specs' own names."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel


class Attribute(BaseModel):
    """A per-joint input: `field` on the wire (a list in `JointBatch`), `name` in the spec."""

    name: str
    field: str
    unit: str
    default: float | None
    """The reference engine's default (the SDK's scene builder applies it); `None`: required, except
    `prev_coordinate` (v1.1, optional), whose default is derived from `q_prev` as contract v1 does."""
    description: str


class ConstitutionInfo(BaseModel):
    uid: int
    name: str
    base_uid: int
    base_name: str
    coordinate: str
    """What the joint coordinate `x` measures, and its unit."""
    origin: str = ""
    """v1.2: where `x = 0` for each value of a batch's `origin` ("q_ref", "absolute": the reference engine's)."""
    attributes: list[Attribute]


class Limits(BaseModel):
    """This deployment's request limits; larger requests answer 413 (the SDK splits by them)."""

    max_body_bytes: int
    max_joints: int
    # Admission by cost (docs/deployment.md, "Limits"); None from a server that predates them.
    max_batches: int | None = None
    max_answer_bytes: int | None = None
    """Bound of the answer from joints x outputs x encoding (`jointlimits.schemas.answer.answer_bytes`)."""
    max_json_values: int | None = None
    """Values (commas + 1) of a JSON body."""


class ConstitutionsResponse(BaseModel):
    constitutions: list[ConstitutionInfo]
    limits: Limits


STRENGTH_DEFAULT = 1.0
"""The reference engine's default `limit/strength` (`apply_to(sc, lower, upper, strength = 1)`)."""


def _attribute(name: str, field: str, unit: str, default: float | None, description: str) -> Attribute:
    return Attribute(name=name, field=field, unit=unit, default=default, description=description)


def describe(facts: Any) -> ConstitutionInfo:
    """The discovery entry of one constitution, in the specs' attribute names and units, from its facts (the
    core's `Facts`, read here by attribute: the wire imports nothing of the service)."""
    unit, length = facts.unit, "length unit of the DOFs"
    attributes = [
        # The joint's edge, in either of the engine's two variants (exactly one per batch, v1.2).
        _attribute("position", "edges", length, None, "(N, 2, 3) the edge p0 -> p1 in world space at q_ref (the "
                   "engine's world create_geometry); or local_edges"),
        _attribute("l_position0, l_position1, r_position0, r_position1", "local_edges", length, None,
                   "(N, 2, 2, 3) [[l0, l1], [r0, r1]]: the edge in body i's and body j's own coordinates (the "
                   "engine's local create_geometry); or edges (v1.2)"),
        _attribute("limit/lower", "lower", unit, None,
                   "lower bound of the coordinate x + offset (absolute); lower <= upper"),
        _attribute("limit/upper", "upper", unit, None, "upper bound of the coordinate x + offset"),
        _attribute("limit/strength", "strength", "energy unit", STRENGTH_DEFAULT,
                   "penalty strength s >= 0 of E = s (gap / (u - l))^3 (s |x - l|^3 when u == l), "
                   "l = lower - offset, u = upper - offset"),
        # v1.1: the offset (`init_angle` / `init_distance`) and a stateful joint's committed coordinate (`angle`).
        _attribute(facts.offset_name, "offset", unit, 0.0,
                   "the coordinate at q_ref: the reported coordinate is x + offset (v1.1)"),
    ]
    if facts.stateful:
        attributes.append(_attribute(
            facts.state_name, "prev_coordinate", unit, None,
            "optional: the committed, continuously unwrapped coordinate at q_prev (any number of turns); "
            "x = (prev_coordinate - offset) + DeltaTheta(q, q_prev). Without it x starts from "
            "DeltaTheta(q_prev, q_ref) (v1.1)"))
    return ConstitutionInfo(uid=facts.uid, name=facts.name, base_uid=facts.base_uid, base_name=facts.base_name,
                            coordinate=f"{facts.coordinate} [{unit}]", origin=facts.origin, attributes=attributes)
