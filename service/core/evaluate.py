"""Evaluate joint-limit energies, gradients and Hessians for a scene: the one entry point of the core."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from service.core import assembly, penalty
from service.core.constitution import Array, Constitution
from service.core.errors import Fault, InputError
from service.core.kinematics import frame_quantities, polar_rotation, split
from service.core.registry import CONSTITUTIONS
from service.core.scene import OUTPUTS, BatchResult, Bodies, Evaluation, Joints
from service.core.validate import MAX_FAULTS, check_bodies, check_joints, check_options, raise_if

CHUNK = 4096
"""Active joints differentiated at once: bounds temporaries to a few MB whatever the batch size."""


def evaluate(
    bodies: Bodies,
    batches: Sequence[Joints],
    outputs: Iterable[str] = OUTPUTS,
    hessian_mode: str = "exact",
    active_only: bool = False,
) -> Evaluation:
    """Energy, gradient and Hessian of every joint, as CONTRACT.md v1 defines them.

    Raises `InputError` naming every fault found. Only the outputs asked for are
    computed, and only joints outside their range are differentiated.
    """
    outputs = tuple(outputs)
    bodies = Bodies(*(np.asarray(a, dtype=np.float64) for a in (bodies.q, bodies.q_prev, bodies.q_ref)))
    faults = check_options(outputs, hessian_mode) + check_bodies(bodies, None)
    raise_if(faults)
    _, A_ref = split(bodies.q_ref)
    R_ref, ratio = polar_rotation(A_ref)
    n_bodies = bodies.q.shape[0]
    batches = [_as_arrays(j) for j in batches]
    faults = check_bodies(bodies, ratio)
    for b, joints in enumerate(batches):
        faults += check_joints(b, joints, n_bodies)
    raise_if(faults)

    want_g, want_h = "gradient" in outputs, "hessian" in outputs
    results = [
        _evaluate_batch(b, j, bodies, R_ref, want_g, want_h, hessian_mode == "psd", active_only)
        for b, j in enumerate(batches)
    ]
    total = float(sum(np.sum(e) for e in (r.pop("all_energy") for r in results)))
    if not np.isfinite(total):
        raise InputError([Fault(("batches",), "the total energy overflows float64")])
    return Evaluation(total_energy=total, batches=[BatchResult(**r) for r in results])


def _as_arrays(j: Joints) -> Joints:
    return Joints(
        constitution_uid=int(j.constitution_uid),
        base_uid=int(j.base_uid),
        body_ids=np.asarray(j.body_ids, dtype=np.int64),
        edges=np.asarray(j.edges, dtype=np.float64),
        lower=np.asarray(j.lower, dtype=np.float64),
        upper=np.asarray(j.upper, dtype=np.float64),
        strength=np.asarray(j.strength, dtype=np.float64),
    )


def _evaluate_batch(
    b: int,
    joints: Joints,
    bodies: Bodies,
    R_ref: Array,
    want_g: bool,
    want_h: bool,
    psd: bool,
    active_only: bool,
) -> dict:
    c = CONSTITUTIONS[joints.constitution_uid]
    ids = joints.body_ids
    p_ref, A_ref = split(bodies.q_ref[ids])
    v = c.local_vectors(joints.edges, p_ref, A_ref, R_ref[ids])
    F = [frame_quantities(q[ids], c.alpha, v) for q in (bodies.q, bodies.q_prev, bodies.q_ref)]
    _raise_collapsed(b, c, F)
    x = c.coordinate(*F)
    lo, up, s = joints.lower, joints.upper, joints.strength
    energy = penalty.energy(x, lo, up, s)

    outside = (penalty.gap(x, lo, up)[0] > 0) & (s > 0)
    active = np.flatnonzero(outside)
    rows = active if active_only else np.arange(x.shape[0])
    n = rows.shape[0]
    # Inactive rows are exact zeros that were never differentiated.
    gradient = np.zeros((n, 24)) if want_g else None
    hessian = np.zeros((n, 24, 24)) if want_h else None
    out_pos = np.arange(active.shape[0]) if active_only else active
    if want_g or want_h:
        for start in range(0, active.shape[0], CHUNK):
            sel = active[start : start + CHUNK]
            pos = out_pos[start : start + CHUNK]
            g, h = _derivatives(c, F[0][sel], v[sel], x[sel], lo[sel], up[sel], s[sel], want_h, psd)
            if want_g:
                gradient[pos] = g
            if want_h:
                hessian[pos] = h
    _raise_nonfinite(b, rows, energy[rows], gradient, hessian)
    return dict(
        constitution_uid=c.uid,
        index=rows,
        x=x[rows],
        energy=energy[rows],
        gradient=gradient,
        hessian=hessian,
        all_energy=energy,
    )


def _derivatives(
    c: Constitution, F: Array, v: Array, x: Array, lo: Array, up: Array, s: Array, want_h: bool, psd: bool
) -> tuple[Array, Array | None]:
    """Gradient (M, 24) and Hessian (M, 24, 24) of active joints."""
    _, dE, d2E = penalty.derivatives(x, lo, up, s)
    dx, d2x = c.derivatives(F, second=want_h)
    w = assembly.weights(c.alpha, v)
    grad = dE[:, None] * assembly.gradient(w, dx)
    if not want_h:
        return grad, None
    m = dx.shape[0]
    curvature = dE[:, None, None, None, None] * d2x
    if psd:
        curvature = assembly.psd_projection(curvature)
    dx12 = dx.reshape(m, 12)
    M = curvature + (d2E[:, None, None] * dx12[:, :, None] * dx12[:, None, :]).reshape(m, 4, 3, 4, 3)
    return grad, assembly.hessian(w, M)


def _raise_collapsed(b: int, c: Constitution, F: list[Array]) -> None:
    faults = []
    for state, Fs in zip(("q", "q_prev", "q_ref"), F):
        faults += [
            Fault(
                ("batches", b, "body_ids", int(j)),
                f"the joint frame collapses at {state} (cos = sin = 0): the angle and its derivatives do not exist",
            )
            for j in np.flatnonzero(c.collapsed(Fs))[:MAX_FAULTS]
        ]
    raise_if(faults)


def _raise_nonfinite(b: int, rows: np.ndarray, *arrays: Array | None) -> None:
    bad = np.zeros(rows.shape[0], dtype=bool)
    for a in arrays:
        if a is not None:
            bad |= ~np.isfinite(a).all(axis=tuple(range(1, a.ndim)))
    raise_if(
        [
            Fault(
                ("batches", b, "strength", int(rows[i])),
                "the energy or its derivatives overflow float64 at this configuration and strength",
            )
            for i in np.flatnonzero(bad)[:MAX_FAULTS]
        ]
    )
