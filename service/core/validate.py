"""Checks that need arithmetic, vectorised over joints; each fault names batch, field and joint.

Shapes of wire requests are already enforced by `schemas`; they are checked
again here because the in-process API takes arbitrary arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from service.core.errors import MAX_FAULTS, Fault, InputError
from service.core.kinematics import dot
from service.core.polar import SINGULAR_RATIO
from service.core.registry import CONSTITUTIONS
from service.core.scene import OUTPUTS, Bodies, Evaluation, Joints

HESSIAN_MODES = ("exact", "psd")


def _where(mask: np.ndarray) -> list[int]:
    return [int(i) for i in np.flatnonzero(mask)[:MAX_FAULTS]]


def nonfinite_rows(a: np.ndarray) -> list[int]:
    """The first `MAX_FAULTS` rows of `a` (N, ...) holding a NaN or an infinity; N may be 0."""
    finite = np.isfinite(a)
    if finite.all():  # the common case: a flat reduction, much cheaper than one per row
        return []
    return _where(~finite.all(axis=tuple(range(1, a.ndim))))


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


def check_bodies(bodies: Bodies) -> list[Fault]:
    faults: list[Fault] = []
    n = np.shape(bodies.q)[0] if np.ndim(bodies.q) else 0
    for name in ("q", "q_prev", "q_ref"):
        a = getattr(bodies, name)
        if a.ndim != 2 or a.shape[1] != 12 or a.shape[0] != n:
            faults.append(Fault(("bodies", name), f"must be {n} rows of 12 numbers, got shape {a.shape}"))
            continue
        faults += [Fault(("bodies", name, i), "contains a non-finite number") for i in nonfinite_rows(a)]
    return faults


def check_rotations(rotation_ratio: np.ndarray) -> list[Fault]:
    """Bodies whose `A_ref` is too close to singular for a polar factor (`rotation_ratio` (B,) = s_min / s_max)."""
    return [
        Fault(("bodies", "q_ref", i), f"A_ref is singular (smallest/largest singular value < {SINGULAR_RATIO:g})")
        for i in _where(~(rotation_ratio >= SINGULAR_RATIO))
    ]


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
        faults += [Fault(at(name, j), "is not a finite number") for j in nonfinite_rows(getattr(joints, name))]
    ids = joints.body_ids
    faults += [
        Fault(at("body_ids", j), f"body index {ids[j].tolist()} out of range [0, {n_bodies}) (there are {n_bodies} bodies)")
        for j in _where(((ids < 0) | (ids >= n_bodies)).any(axis=1))
    ]
    faults += [
        Fault(at("body_ids", j), f"joint couples body {ids[j, 0]} to itself")
        for j in _where(ids[:, 0] == ids[:, 1])
    ]
    if faults:
        return faults
    lo, up, s = joints.lower, joints.upper, joints.strength
    faults += [
        Fault(at("lower", j), f"lower {float(lo[j])!r} > upper {float(up[j])!r}: the range is empty")
        for j in _where(lo > up)
    ]
    faults += [Fault(at("strength", j), f"strength {float(s[j])!r} < 0: must be >= 0") for j in _where(s < 0)]
    with np.errstate(over="ignore", invalid="ignore"):
        # The same arithmetic as the constitutions' unit axis, so exactly the edges it cannot normalise.
        d = joints.edges[:, 1] - joints.edges[:, 0]
        length = np.sqrt(dot(d, d))
    faults += [
        Fault(at("edges", j), "zero-length edge: p0 == p1 (or too close to normalise) gives no joint axis")
        for j in _where(length == 0)
    ]
    faults += [
        Fault(at("edges", j), "edge too long: |p1 - p0| overflows float64") for j in _where(~np.isfinite(length))
    ]
    return faults


def check_evaluation(ev: Evaluation) -> list[Fault]:
    """Faults of a finished evaluation that would put NaN or Infinity in an answer.

    The core names overflowing energies and derivatives itself; this also catches a
    joint coordinate `x` that overflowed in an otherwise inactive joint (x = NaN has
    no gap, so zero energy), so that no answer ever carries a non-finite number.
    """
    faults = [
        Fault(
            ("batches", b, "body_ids", int(r.index[i])),
            "the joint coordinate x overflows float64 at this configuration (positions or edge too large)",
        )
        for b, r in enumerate(ev.batches)
        for i in _where(~np.isfinite(r.x))
    ]
    if not faults and not np.isfinite(ev.total_energy):
        faults.append(Fault(("batches",), "the total energy overflows float64"))
    return faults[:MAX_FAULTS]


def raise_if(faults: list[Fault]) -> None:
    if faults:
        raise InputError(faults)


def checked_evaluate(
    bodies: Bodies, batches: Sequence[Joints], deadline: float | None = None, **options: Any
) -> Evaluation:
    """`service.core.evaluate` that never returns a non-finite number nor fails with a non-input error.

    What the HTTP shell and the SDK's local mode call. Overflow is expected with
    hostile numbers: warnings are silenced and every overflow becomes an
    `InputError` naming the joint. The PSD projection (an eigensolver) fails
    outright on a non-finite curvature; the exact mode then locates the joints.
    `deadline` (a `time.monotonic()` value): past it, `DeadlineExceeded` (see `evaluate`).
    """
    from service.core.evaluate import evaluate  # evaluate imports this module

    with np.errstate(all="ignore"):
        try:
            ev = evaluate(bodies, batches, deadline=deadline, **options)
        except np.linalg.LinAlgError:
            evaluate(bodies, batches, deadline=deadline, **{**options, "hessian_mode": "exact"})  # names the joints
            raise InputError([Fault(("hessian_mode",), "the PSD projection failed: the Hessian overflows float64")])
    raise_if(check_evaluation(ev))
    return ev
