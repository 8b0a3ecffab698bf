"""`GET /v1/constitutions`: what the service evaluates, in the specs' own names."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field


class Attribute(BaseModel):
    """A per-joint input: `field` on the wire (a list in `JointBatch`), `name` in the spec."""

    name: str = Field(description="The spec's attribute name (limit/lower, limit/upper, limit/strength).")
    field: str = Field(description="The wire field (a per-joint list of JointBatch).")
    unit: str = Field(description="Its unit (rad, the DOFs' length unit, energy unit).")
    # The reference engine's default (the SDK's scene builder applies it); None: required, except
    # `prev_coordinate` (v1.1, optional), whose default is derived from `q_prev` as contract v1 does.
    default: float | None = Field(description="The default an absent field takes (null: required).")
    description: str = Field(description="What it means.")


class ConstitutionInfo(BaseModel):
    uid: int = Field(description="The constitution's UID, the wire's constitution_uid.")
    name: str = Field(description="Its name in the specs.")
    base_uid: int = Field(description="The base joint's UID it pairs with (the wire's base_uid).")
    base_name: str = Field(description="The base joint's name.")
    coordinate: str = Field(description="What the joint coordinate x measures, and its unit.")
    origin: str = Field(
        "",
        description="v1.2: where x = 0 for each value of a batch's origin ('q_ref', 'absolute': the reference "
        "engine's zero).",
    )
    attributes: list[Attribute] = Field(
        description="Its per-joint inputs, by their spec names (the edges by the reference engine's attribute names)."
    )


class Limits(BaseModel):
    """This deployment's request limits; larger requests answer 413 (the SDK splits by them)."""

    max_body_bytes: int = Field(description="Largest request body accepted, in bytes (JOINTLIMITS_MAX_BODY_BYTES).")
    max_joints: int = Field(description="Most joints, over all batches, in one request (JOINTLIMITS_MAX_JOINTS).")
    # Admission by cost (docs/deployment.md, "Limits"); None from a server that predates them.
    max_batches: int | None = Field(None, description="Most batches in one request (JOINTLIMITS_MAX_BATCHES).")
    max_answer_bytes: int | None = Field(
        None,
        description="Largest answer, bounded from joints x outputs x encoding before any work "
        "(JOINTLIMITS_MAX_ANSWER_BYTES; schemas/answer.py computes the bound).",
    )
    max_json_values: int | None = Field(
        None,
        description="Most values (commas + 1, or twice its lists and objects, or 8 times its keys, where more) in a JSON "
        "body, counted before parsing (JOINTLIMITS_MAX_JSON_VALUES).",
    )


class ConstitutionsResponse(BaseModel):
    constitutions: list[ConstitutionInfo] = Field(description="Each constitution this service evaluates.")
    limits: Limits = Field(
        description="This deployment's request limits (larger requests answer 413; the Python SDK splits by them)."
    )


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
