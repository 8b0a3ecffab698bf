"""Evaluate joint-limit energies, gradients and Hessians for a scene: the one entry point of the core."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from functools import partial

import numpy as np

from service.core import assembly, penalty
from service.core.constitution import Array, Constitution, Curvature
from service.core.errors import Fault, InputError
from service.core.kinematics import (
    PREV_STEP,
    REF,
    STEP,
    STEPS,
    TOTAL_STEP,
    BodyTable,
    frame_quantities,
    relative_position,
)
from service.core.parallel import run_all
from service.core.registry import CONSTITUTIONS
from service.core.scene import OUTPUTS, BatchResult, Bodies, Evaluation, Joints
from service.core.validate import (
    MAX_FAULTS,
    check_bodies,
    check_joints,
    check_options,
    check_rotations,
    nonfinite_rows,
    raise_if,
)

CHUNK = 1024
"""Active joints differentiated at once: bounds temporaries to a few MB whatever the batch size."""


def evaluate(
    bodies: Bodies,
    batches: Sequence[Joints],
    outputs: Iterable[str] = OUTPUTS,
    hessian_mode: str = "exact",
    active_only: bool = False,
    dtype: type = np.float64,
    threads: int = 1,
) -> Evaluation:
    """Energy, gradient and Hessian of every joint, as CONTRACT.md v1 defines them.

    Raises `InputError` naming every fault found. Only the outputs asked for are
    computed, and only joints outside their range are differentiated. `dtype`
    np.float32 runs everything after validation and the polar factors in single
    precision (a benchmark variant: ~1e-5 relative error; the wire is float64).
    `threads` > 1 evaluates the polar factors, the batches (or, for one batch, its
    derivative chunks) on that many threads, with bitwise the same results; the HTTP
    service keeps 1, its worker processes already fill the cores.
    """
    outputs = tuple(outputs)
    bodies = Bodies(*(np.asarray(a, dtype=np.float64) for a in (bodies.q, bodies.q_prev, bodies.q_ref)))
    faults = check_options(outputs, hessian_mode) + check_bodies(bodies)
    raise_if(faults)
    batches = [_as_arrays(j) for j in batches]
    # Only the increments of A (and the states they span) that the batches' constitutions read.
    used = [CONSTITUTIONS[j.constitution_uid] for j in batches if j.constitution_uid in CONSTITUTIONS]
    table = BodyTable(bodies, dtype, threads, rows={row for c in used for row in _increments(c)})
    n_bodies = bodies.q.shape[0]
    faults = check_rotations(table.ratio)
    for b, joints in enumerate(batches):
        faults += check_joints(b, joints, n_bodies)
    raise_if(faults)

    want_g, want_h = "gradient" in outputs, "hessian" in outputs
    inner = threads if len(batches) == 1 else 1  # one level of threads: a pool never waits on itself
    results = run_all(
        [
            partial(_evaluate_batch, b, j, table, want_g, want_h, hessian_mode == "psd", active_only, inner)
            for b, j in enumerate(batches)
        ],
        threads,
    )
    total = float(sum(np.sum(e) for e in (r.pop("all_energy") for r in results)))
    if not np.isfinite(total):
        raise InputError([Fault(("batches",), "the total energy overflows float64")])
    return Evaluation(total_energy=total, batches=[BatchResult(**r) for r in results])


def _increments(c: Constitution) -> tuple[int, ...]:
    """The body table's rows of `A` increments that `c.coordinate` takes, in its order."""
    return (TOTAL_STEP,) if c.telescopes else (PREV_STEP, STEP)


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
    table: BodyTable,
    want_g: bool,
    want_h: bool,
    psd: bool,
    active_only: bool,
    threads: int,
) -> dict:
    c = CONSTITUTIONS[joints.constitution_uid]
    pairs = np.ascontiguousarray(joints.body_ids.T)  # (2, N): contiguous indices gather 30% faster
    dtype = table.linear.dtype
    points = bool(c.alpha.any())
    rows = _increments(c)
    A_ref = table.linear_of(pairs, REF)
    p = {state: table.positions_of(pairs, state) for row in rows for state in STEPS[row]} if points else {}
    v = c.local_vectors(joints.edges.astype(dtype, copy=False), p.get(0), A_ref, table.rotations(pairs))
    # Body j from body i in each state (points only), then frames at q_ref and their increments.
    r = {state: relative_position(ps) for state, ps in p.items()}
    F_ref = frame_quantities(r.get(0), A_ref, c.alpha, v)

    def step(row: int) -> Array:
        s0, s1 = STEPS[row]
        return frame_quantities(r[s1] - r[s0] if points else None, table.linear_of(pairs, row), c.alpha, v)

    steps = [step(row) for row in rows]
    # F at q_prev (if used) and at q: where each step starts, the collapse check, the derivatives.
    states = [F_ref]
    for dF in steps:
        states.append(states[-1] + dF)
    x = c.coordinate(states[:-1], steps)
    _raise_collapsed(b, c, dict(zip(("q_ref", "q_prev", "q") if len(states) == 3 else ("q_ref", "q"), states)))
    F = states[-1]
    lo, up, s = (a.astype(dtype, copy=False) for a in (joints.lower, joints.upper, joints.strength))
    energy = penalty.energy(x, lo, up, s)

    active = np.flatnonzero((penalty.gap(x, lo, up)[0] > 0) & (s > 0))
    n = active.shape[0] if active_only else x.shape[0]
    # Inactive rows are exact zeros that were never differentiated (calloc: untouched pages stay free);
    # when every row is differentiated each is written once, with no zero-fill before.
    alloc = np.empty if active.shape[0] == n else np.zeros
    gradient = alloc((n, 24), dtype=dtype) if want_g else None
    hessian = alloc((n, 24, 24), dtype=dtype) if want_h else None
    out_pos = np.arange(n) if active_only else active

    def chunk(start: int) -> list[int]:
        """Differentiate active joints `start : start + CHUNK`; the rows among them that overflow."""
        sel = active[start : start + CHUNK]
        pos = out_pos[start : start + CHUNK]
        # Contiguous rows (active_only, or a fully active stretch) are written in place.
        contiguous = pos[-1] - pos[0] + 1 == pos.shape[0]
        h_out = None
        if want_h:
            h_out = hessian[pos[0] : pos[-1] + 1] if contiguous else np.empty((sel.shape[0], 24, 24), dtype)
        g, h_finite = _derivatives(c, F[sel], v[sel], x[sel], lo[sel], up[sel], s[sel], h_out, psd)
        # Only active rows can overflow: checked while they are still in cache (the Hessian only
        # when its factors do not already bound it).
        bad = nonfinite_rows(g) if want_g else []
        if want_h and not h_finite:
            bad += nonfinite_rows(h_out)
        if want_g and contiguous:
            gradient[pos[0] : pos[-1] + 1] = g
        elif want_g:
            gradient[pos] = g
        if want_h and not contiguous:
            hessian[pos] = h_out
        return [int(sel[i]) for i in bad]

    overflow = nonfinite_rows(energy)
    if want_g or want_h:
        for bad in run_all([partial(chunk, start) for start in range(0, active.shape[0], CHUNK)], threads):
            overflow += bad
    raise_if(
        [
            Fault(
                ("batches", b, "strength", j),
                "the energy or its derivatives overflow float64 at this configuration and strength",
            )
            for j in sorted(set(overflow))[:MAX_FAULTS]
        ]
    )
    return dict(
        constitution_uid=c.uid,
        index=active if active_only else np.arange(n),
        x=x[active] if active_only else x,
        energy=energy[active] if active_only else energy,
        gradient=gradient,
        hessian=hessian,
        all_energy=energy,
    )


def _derivatives(
    c: Constitution, F: Array, v: Array, x: Array, lo: Array, up: Array, s: Array, h_out: Array | None, psd: bool
) -> tuple[Array, bool]:
    """Gradient (M, 24) of active joints; their Hessian (M, 24, 24) into `h_out` if given, and whether it
    is finite for sure (False: check it)."""
    _, dE, d2E = penalty.derivatives(x, lo, up, s)
    dx, curvature = c.derivatives(F, second=h_out is not None)
    if h_out is None:
        return dE[:, None] * assembly.gradient(c.alpha, v, dx), True
    if psd:
        projected = c.projected_curvature(dE, curvature)
        if projected is None:  # the generic route: a 12 x 12 eigensolver per joint
            basis, lam = assembly.psd_projection(dE[:, None, None] * curvature.dense())
            m = lam.shape[0]
            projected = Curvature(kron=np.zeros((m, 4, 4), lam.dtype), basis=basis, coef=lam[:, :, None] * np.eye(12, dtype=lam.dtype),
                                  kron_factors=(np.zeros((m, 0), lam.dtype), np.zeros((m, 0, 4), lam.dtype)), diagonal=True)
        # The projection already carries E': the chain rule sees E' = 1 (E'' dx dx^T beside it, PSD as it is).
        Jdx, finite = assembly.hessian(c.alpha, v, projected, np.ones_like(dE), d2E, h_out, dx=dx)
    else:
        Jdx, finite = assembly.hessian(c.alpha, v, curvature, dE, d2E, h_out)
    return dE[:, None] * Jdx, finite  # J^T dx comes with the Hessian's factors


def _raise_collapsed(b: int, c: Constitution, F: dict[str, Array]) -> None:
    """Joints whose frame collapses in any state of `F` ((N, 4, 3) by state name)."""
    faults = [
        Fault(
            ("batches", b, "body_ids", int(j)),
            f"the joint frame collapses at {state} (cos = sin = 0): the angle and its derivatives do not exist",
        )
        for state, Fs in F.items()
        for j in np.flatnonzero(c.collapsed(Fs))[:MAX_FAULTS]
    ]
    raise_if(faults)
