"""Checks that need arithmetic, vectorised over joints; each fault names batch, field and joint.

Shapes of wire requests are already enforced by `schemas`; they are checked
again here because the in-process API takes arbitrary arrays.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from service.core.errors import Fault, InputError
from service.core.kinematics import SINGULAR_RATIO
from service.core.registry import CONSTITUTIONS
from service.core.scene import OUTPUTS, Bodies, Joints

MAX_FAULTS = 20
"""Faults listed per check; a request with a million bad joints gets a readable answer."""

HESSIAN_MODES = ("exact", "psd")


def _where(mask: np.ndarray) -> list[int]:
    return [int(i) for i in np.flatnonzero(mask)[:MAX_FAULTS]]


def _nonfinite_rows(a: np.ndarray) -> np.ndarray:
    return ~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)


def check_options(outputs: Sequence[str], hessian_mode: str) -> list[Fault]:
    faults = [
        Fault(("outputs", i), f"unknown output {o!r}; expected one of {', '.join(OUTPUTS)}")
        for i, o in enumerate(outputs)
        if o not in OUTPUTS
    ]
    if not outputs:
        faults.append(Fault(("outputs",), "must name at least one of energy, gradient, hessian"))
    if hessian_mode not in HESSIAN_MODES:
        faults.append(Fault(("hessian_mode",), f"unknown mode {hessian_mode!r}; expected 'exact' or 'psd'"))
    return faults


def check_bodies(bodies: Bodies, rotation_ratio: np.ndarray | None) -> list[Fault]:
    faults: list[Fault] = []
    n = np.shape(bodies.q)[0] if np.ndim(bodies.q) else 0
    for name in ("q", "q_prev", "q_ref"):
        a = getattr(bodies, name)
        if a.ndim != 2 or a.shape[1] != 12 or a.shape[0] != n:
            faults.append(Fault(("bodies", name), f"must be {n} rows of 12 numbers, got shape {a.shape}"))
            continue
        faults += [Fault(("bodies", name, i), "contains a non-finite number") for i in _where(_nonfinite_rows(a))]
    if not faults and rotation_ratio is not None:
        faults += [
            Fault(("bodies", "q_ref", i), f"A_ref is singular (smallest/largest singular value < {SINGULAR_RATIO:g})")
            for i in _where(~(rotation_ratio >= SINGULAR_RATIO))
        ]
    return faults


def check_joints(b: int, joints: Joints, n_bodies: int) -> list[Fault]:
    at = lambda *loc: ("batches", b, *loc)  # noqa: E731
    c = CONSTITUTIONS.get(joints.constitution_uid)
    if c is None:
        known = ", ".join(str(u) for u in CONSTITUTIONS)
        return [Fault(at("constitution_uid"), f"unknown constitution {joints.constitution_uid}; supported: {known}")]
    if joints.base_uid != c.base_uid:
        return [
            Fault(
                at("base_uid"),
                f"constitution {c.uid} ({c.name}) needs base_uid {c.base_uid}, got {joints.base_uid}",
            )
        ]
    n = joints.body_ids.shape[0] if joints.body_ids.ndim == 2 else -1
    shapes = {
        "body_ids": (joints.body_ids, (n, 2)),
        "edges": (joints.edges, (n, 2, 3)),
        "lower": (joints.lower, (n,)),
        "upper": (joints.upper, (n,)),
        "strength": (joints.strength, (n,)),
    }
    faults = [
        Fault(at(name), f"must have shape {want} (one row per joint of body_ids), got {a.shape}")
        for name, (a, want) in shapes.items()
        if a.shape != want
    ]
    if faults:
        return faults
    for name in ("edges", "lower", "upper", "strength"):
        faults += [Fault(at(name, j), "is not a finite number") for j in _where(_nonfinite_rows(getattr(joints, name)))]
    ids = joints.body_ids
    faults += [
        Fault(at("body_ids", j), f"body index {ids[j].tolist()} out of range [0, {n_bodies})")
        for j in _where(((ids < 0) | (ids >= n_bodies)).any(axis=1))
    ]
    faults += [
        Fault(at("body_ids", j), f"joint couples body {ids[j, 0]} to itself")
        for j in _where(ids[:, 0] == ids[:, 1])
    ]
    if faults:
        return faults
    lo, up, s = joints.lower, joints.upper, joints.strength
    faults += [Fault(at("lower", j), f"lower {lo[j]!r} > upper {up[j]!r}") for j in _where(lo > up)]
    faults += [Fault(at("strength", j), f"strength {s[j]!r} < 0") for j in _where(s < 0)]
    length = np.linalg.norm(joints.edges[:, 1] - joints.edges[:, 0], axis=-1)
    faults += [Fault(at("edges", j), "zero-length edge: p0 == p1 gives no joint axis") for j in _where(length == 0)]
    return faults


def raise_if(faults: list[Fault]) -> None:
    if faults:
        raise InputError(faults)
