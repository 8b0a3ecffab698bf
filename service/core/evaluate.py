"""The energies of every batch's joints at once (`penalize`), then a batch's derivatives of its active joints
(`differentiate`), from its frames and coordinates.

The pipeline that validates and forms frames and coordinates is `jointlimits.service.core.prepared`.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from numpy.typing import NDArray

from jointlimits.service.core import assembly, penalty
from jointlimits.service.core.constitution import Array, Constitution, Curvature
from jointlimits.service.core.errors import MAX_FAULTS, Fault, check_deadline
from jointlimits.service.core.kinematics import CarefulFrames, take_joints
from jointlimits.service.core.parallel import run_all
from jointlimits.service.core.validate import nonfinite_rows, raise_if

CHUNK = 8192
"""Active joints whose coordinate derivatives are taken at once: per-joint scalars cost a call each per
chunk (its overhead, and on threads a GIL hand-off), so chunks are long; temporaries stay a few MB."""
SCATTER_CHUNK = 2048
"""The chunk when Hessian rows are scattered (some joints inside their range): its scratch rows, 9 MB."""


def penalize(x: Array, lo: Array, up: Array, s: Array, w: Array, want_d: bool,
             want_active: bool) -> tuple[Array, bool, NDArray[np.intp] | None, tuple | None]:
    """The energy (N,) at `x` (N,) of every batch's joints at once (each joint's arithmetic is its own: the bits of
    a batch alone), whether it is finite, the positions `active` (A,) of the joints outside their range (None
    without `want_d` or `want_active`), and with `want_d` their slopes `(E', E'', shift, plain)` (`_in_band`).
    `lo`, `up` (N,) the bounds on `x`, `w` (N,) their `penalty.width`, `s` (N,) the strengths."""
    # one gap for the energy, the active joints and their slopes (the side only for these)
    g, side = penalty.gap(x, lo, up) if want_d else (penalty.distance(x, lo, up), None)
    energy, r, w, careful = penalty.energy_and_relative(g, x, lo, up, s, w)
    finite = bool(np.isfinite(energy).all())  # the common case: one flat test (`differentiate` names the rows)
    if not finite:  # s = 0 pays nothing however far out: 0 * inf is no overflow (nor active, below)
        energy[s == 0] = 0.0
    active = slopes = None
    if want_d or want_active:
        active = ((g > 0) & (s > 0)).nonzero()[0]
    if want_d:
        # Per-joint scalars for every active joint at once: per chunk they would be a dozen short calls each.
        at_active = (x, lo, up, s, r, w, side)
        if active.shape[0] != x.shape[0]:
            at_active = tuple(take_joints(q, active) for q in at_active)
        if careful:  # a gap or width overflowed, or r^3 left the normal range: from halves and exponents
            _, dE, d2E = penalty.derivatives(*at_active[:4])
        else:  # from the energy's own relative gaps and widths (the same bits as `derivatives`)
            dE, d2E = penalty.slopes(*at_active[4:], at_active[3])
        slopes = (dE, d2E, *_in_band(dE, d2E, penalty.scale_up(dE, d2E, *at_active[:4])))
    return energy, finite, active, slopes


def differentiate(b: int, c: Constitution, F: Array, v: Array, energy: Array, finite: bool, active: NDArray[np.intp],
                  slopes: tuple | None, first: int, want_g: bool, want_h: bool, psd: bool, compact: bool,
                  threads: int = 1, deadline: float | None = None,
                  balance: Array | None = None) -> tuple[Array | None, Array | None]:
    """Batch `b`'s asked-for gradient (R, 24) and Hessian (R, 24, 24), else None, at its frames `F` (N, 4, 3):
    R = A rows of the `active` (A,) joints if `compact`, else N (the inactive rows exact zeros, never
    differentiated). `energy` (N,), `finite` and `active` are `penalize`'s for these joints, their `slopes` its rows
    `first : first + A`.

    `v` (N, 4, 3) the body-local vectors (`balance` (N, 4): their `assembly.balance`, if already taken).
    Raises `InputError` naming the joints whose energy or derivatives overflow; `DeadlineExceeded`
    past `deadline` (a `time.monotonic()` value), checked before each derivative chunk, which run on `threads`.
    """
    overflow = [] if finite else nonfinite_rows(energy)
    gradient = hessian = None
    if want_g or want_h:
        a, dtype, n_all = active.shape[0], F.dtype, F.shape[0]
        n = a if compact else n_all
        # Inactive rows are exact zeros (calloc: untouched pages stay free); when every row is
        # differentiated each is written once, with no zero-fill before.
        alloc = np.empty if a == n else np.zeros
        gradient = alloc((n, 24), dtype=dtype) if want_g else None
        hessian = alloc((n, 24, 24), dtype=dtype) if want_h else None
        every = a == n_all  # every joint active: no gathers, every chunk's rows in place
        dE, d2E, shift, plain = slopes
        # Rows written in place when every row is differentiated; else a chunk's go through scratch rows
        # first, kept to a few MB. On threads, at least two chunks per thread (a batch alone keeps them busy).
        size = CHUNK if a == n or not want_h else SCATTER_CHUNK
        if threads > 1:
            size = min(size, assembly.BLOCK * max(1, -(-a // (2 * threads * assembly.BLOCK))))

        def chunk(start: int) -> list[int]:
            """Differentiate active joints `start : start + size`; the rows among them that overflow."""
            check_deadline(deadline)
            part, rows_s = slice(start, start + size), slice(first + start, first + min(start + size, a))  # of `slopes`
            sel = active[part]
            rows, contiguous = part, True  # compact or every joint active: the chunk's own rows, in place
            if not (compact or every):  # in place too where a stretch of joints is active
                rows, contiguous = slice(sel[0], sel[-1] + 1), sel[-1] - sel[0] + 1 == sel.shape[0]
            h_out = (hessian[rows] if contiguous else np.empty((sel.shape[0], 24, 24), dtype)) if want_h else None
            g_out = gradient[rows] if want_g and contiguous else np.empty((sel.shape[0], 24), dtype)
            at = (lambda a: a[part]) if every else (lambda a: take_joints(a, sel))  # noqa: E731
            bc = None if balance is None else at(balance)

            def formed(dE: Array, d2E: Array, shift: NDArray[np.int_] | None, g_out: Array, h_out: Array | None) -> bool:
                h_finite = _derivatives(c, at(F), at(v), dE[rows_s], d2E[rows_s], g_out, h_out, psd, bc)
                if shift is not None:  # rows of E' and E'' formed scaled by 2^k (`penalty.scale_up`, `_in_band`): back
                    k = shift[rows_s]
                    lifted = k.nonzero()[0]
                    for out in (g_out, h_out):
                        if out is not None and lifted.shape[0]:
                            out[lifted] = np.ldexp(out[lifted], -k[lifted].reshape(-1, *(1,) * (out.ndim - 1)))
                    h_finite = h_finite and not (k < 0).any()  # scaled up: its bound held before
                return h_finite

            h_finite = formed(dE, d2E, shift, g_out, h_out)
            redo = [] if plain is None else sorted(set(nonfinite_rows(g_out) + (nonfinite_rows(h_out) if want_h else [])))
            if redo:  # rows `_in_band` moved that overflowed from there: as they were (they may not)
                g2, h2 = np.empty_like(g_out), None if h_out is None else np.empty_like(h_out)
                formed(*plain, g2, h2)
                g_out[redo] = g2[redo]
                if h_out is not None:
                    h_out[redo], h_finite = h2[redo], False
            # Only active rows can overflow: checked while in cache (the Hessian only when its factors
            # do not already bound it).
            bad = nonfinite_rows(g_out) if want_g else []
            if want_h and not h_finite:
                bad += nonfinite_rows(h_out)
            for whole, out in ((gradient, g_out), (hessian, h_out)):
                if whole is not None and not contiguous:  # the scratch rows into place
                    whole[sel] = out
            return [int(sel[i]) for i in bad]

        for bad in run_all([partial(chunk, start) for start in range(0, a, size)], threads):
            overflow += bad
    raise_if([
        Fault(("batches", b, "strength", j),
              "the energy or its derivatives overflow float64 at this configuration and strength")
        for j in sorted(set(overflow))[:MAX_FAULTS]
    ])
    return gradient, hessian


def _in_band(dE: Array, d2E: Array, shift: NDArray[np.int_] | None) -> tuple[NDArray[np.int_] | None, tuple | None]:
    """`shift` (A,) (`penalty.scale_up`'s exponents, or None) plus `k`, with `dE`, `d2E` (A,) replaced in place by
    `2^k E'`, `2^k E''` (k even: square roots scale exactly) where the larger lies beyond 2^+-500, so that it lies at
    that edge; and `(E', E'', shift)` as they were (None if no row moved), for rows whose answer overflows from the
    edge. The chain rule splits the Hessian into factors of E', E'' and of the frames: a tiny E'' times a factor of
    frames far from 1 underflowed where their product does not (E'' 2.4e-240, frames 1e-65 and 1e133: a Hessian of
    6e-111 answered 2e-309), a huge one overflowed (E'' 1.3e182, frames 3e-61: 1.2e302 refused). Other rows keep
    their bits."""
    m = np.abs(dE)
    np.maximum(m, d2E, out=m)  # E'' >= 0
    if m.shape[0] == 0 or (m.min() >= 2.0**-500 and m.max() <= 2.0**500):  # the usual case: two reductions
        return shift, None
    far = (m < 2.0**-500) | (m > 2.0**500)
    if shift is not None:  # rows `penalty.scale_up` placed are left where it put them: moving both again to the
        far &= shift == 0  # edge put the smaller's product below float64 (E' 3e550 on frames of 1e-300: gradient 0)
    far = far.nonzero()[0]
    if far.shape[0] == 0:
        return shift, None
    plain = (dE.copy(), d2E.copy(), None if shift is None else shift.copy())
    e = np.frexp(m[far])[1]  # m = f 2^e, f in [1/2, 1): to f 2^500 from above, f 2^-499 from below
    k = np.where(m[far] > 1.0, 2 * ((500 - e) // 2), -2 * ((499 + e) // 2))
    dE[far], d2E[far] = np.ldexp(dE[far], k), np.ldexp(d2E[far], k)
    shift = np.zeros(dE.shape[0], dtype=np.int32) if shift is None else shift
    shift[far] += k.astype(shift.dtype)
    return shift, plain


def _derivatives(c: Constitution, F: Array, v: Array, dE: Array, d2E: Array, g_out: Array, h_out: Array | None,
                 psd: bool, balance: Array | None) -> bool:
    """Gradient (M, 24) of active joints into `g_out`; their Hessian (M, 24, 24) into `h_out` if given;
    whether the Hessian is finite for sure (False: check it). `dE`, `d2E` (M,) the penalty's
    derivatives in x."""
    dx, curvature = c.derivatives(F, second=h_out is not None)
    if h_out is None:
        _gradient(dE, assembly.chain(c.facts.alpha, v, dx[:, None])[:, 0], g_out)
        return True
    dE_h, dx_h = dE, None
    if psd:
        projected = c.projected_curvature(dE, curvature)
        if projected is None:  # the generic route: a 12 x 12 eigensolver per joint
            basis, lam = assembly.psd_projection(dE[:, None, None] * curvature.dense())
            m = lam.shape[0]
            projected = Curvature(kron=np.zeros((m, 4, 4), lam.dtype), basis=basis,
                                  coef=lam[:, :, None] * np.eye(12, dtype=lam.dtype), diagonal=True,
                                  kron_factors=(np.zeros((m, 0), lam.dtype), np.zeros((m, 0, 4), lam.dtype)))
        # The projection already carries E': the chain rule sees E' = 1 (E'' dx dx^T beside it, PSD as it is).
        curvature, dE_h, dx_h = projected, np.ones_like(dE), dx
    Jdx, finite = assembly.hessian(c.facts.alpha, v, curvature, dE_h, d2E, h_out, dx=dx_h, balance=balance)
    _gradient(dE, Jdx, g_out)  # J^T dx comes with the Hessian's factors
    return finite


def _gradient(dE: Array, Jdx: Array, out: Array) -> None:
    """`E' J^T dx` (M, 24) into `out`, its zeros +0.0: a negative E' times a zero of `J^T dx` (a
    revolute joint's translation entries, an axis-aligned edge's) would answer -0.0."""
    # Transposed views: NumPy then runs along the joints of each of the 24 entries (`Jdx` is
    # component-major), where `dE[:, None] * Jdx` into the rows ran along each row's 24 (2x slower).
    np.multiply(Jdx.T, dE, out=out.T)
    out += 0.0  # -0.0 + 0.0 == +0.0, every other value unchanged


def collapsed_faults(b: int, c: Constitution, names: tuple[str, ...], states: list[Array],
                     careful: CarefulFrames | None = None, known: list | None = None,
                     size_bounds: list | None = None) -> list[Fault]:
    """Joints of batch `b` whose frame collapses in any state (`states` (N, 4, 3) named by `names`);
    `careful` joints judged on their scaled frames (`careful.states`, in the same order). `known`: per
    state, what the coordinate already formed there (`Progress.known`), or None; `size_bounds` per
    state (`Constitution.collapsed`), or None."""
    faults = []
    for s, (name, F) in enumerate(zip(names, states)):
        bad = c.collapsed(F, None if known is None else known[s], None if size_bounds is None else size_bounds[s])
        if careful is not None:
            bad[careful.idx] = c.collapsed(careful.states[s])
        faults += [
            Fault(
                ("batches", b, "body_ids", int(j)),
                f"the joint frame collapses at {name} (cos and sin within rounding of 0): the angle and its derivatives do not exist",
            )
            for j in bad.nonzero()[0][:MAX_FAULTS]
        ]
    return faults[:MAX_FAULTS]
