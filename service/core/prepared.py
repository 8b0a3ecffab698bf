"""A prepared scene: what does not depend on `q`, computed once, then any `q` evaluated (CONTRACT.md v1.1).

`prepare` validates the static data (`q_prev`, `q_ref`, the joints), takes the polar
factors, the body-local vectors, the frames at `q_ref` (and at `q_prev`), and the state:
`q_prev` and the committed coordinates. `PreparedScene.evaluate(q)` then forms only the
frames' step to `q`. The stateless `evaluate` is "prepare, evaluate once": one code path.

Hostile numbers overflow by design, and every overflow becomes an `InputError` naming the joint: each public
call here runs the numerics under one `np.errstate(all="ignore")` (its helpers set none of their own).

The state of a revolute joint is its committed coordinate at `q_prev` as the wire carries it (a `prev_coordinate`,
a commit's), its angle `theta` always that minus the offset: a reopened scene, a stateless call and the scene
itself take the same bits. Without a `prev_coordinate` and before any commit it is not stored: `x` is then summed
over the steps `q_ref -> q_prev -> q` exactly as contract v1 computes it, so a v1 request gets bit-identical
numbers. A telescoping coordinate (the prismatic slide) depends on `q` and `q_ref` alone and has no state.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import accumulate

import numpy as np
from numpy.typing import ArrayLike, NDArray

from jointlimits.service.core import assembled, assembly, penalty
from jointlimits.service.core.constitution import Array, Constitution, Progress
from jointlimits.service.core.errors import MAX_FAULTS, Fault, FaultLog, InputError, check_deadline
from jointlimits.service.core.evaluate import collapsed_faults, differentiate, penalize
from jointlimits.service.core.kinematics import (PREV_STEP, REF, STEP, STEPS, TOTAL_STEP, BodyTable, CarefulFrames,
                                                 add_positions, careful_frames, exponents, frame_quantities,
                                                 relative_position, scaled_frames, state_frames)
from jointlimits.service.core.geometry import axis_and_anchors
from jointlimits.service.core.registry import CONSTITUTIONS, numerics
from jointlimits.service.core.scene import OUTPUTS, BatchResult, Bodies, Evaluation, Joints
from jointlimits.service.core.validate import (check_bodies, check_coordinates, check_dofs, check_evaluation, check_moved,
                                               check_options, check_rotations, check_update_index, check_update_ranges,
                                               check_update_values, joint_faults, raise_if)

# 2 pi in two parts (Cody-Waite): `k * _TWO_PI_HI` is exact for |k| < 2**24 turns (24 trailing zero
# bits), so `rem` of a many-turn angle loses nothing to the rounding of 2 pi.
_TWO_PI_HI = float.fromhex("0x1.921fb54000000p+2")
_TWO_PI_LO = (2 * np.pi - _TWO_PI_HI) + 2.4492935982947064e-16  # 2 pi - fl(2 pi), to double precision


def rem(y: Array) -> Array:
    """The representative of `y` (N,) modulo 2 pi closest to 0 (ties either way), always within [-pi, pi]."""
    k = np.rint(y / (2 * np.pi))
    # Past 2^24 turns `k * _TWO_PI_HI` rounds by up to ulps of y: an ulp of y is past 1e-8 rad there, and `fmod`
    # (exact) keeps the result in range, where y of 1e89 rad gave 1e73.
    return np.where(np.abs(k) < 2**24, (y - k * _TWO_PI_HI) - k * _TWO_PI_LO, np.remainder(y + np.pi, 2 * np.pi) - np.pi)


@dataclass
class _Batch:
    """One batch's static data and state; arrays (N,) unless said."""

    c: Constitution
    pairs: NDArray[np.intp]  # (2, N) bodies i and j of each joint
    v: Array  # (N, 4, 3) body-local vectors
    F_ref: Array  # (N, 4, 3) frames at q_ref
    starts: list[Array]  # frames where each step of `x` starts (F_ref, then F at q_prev if used)
    fixed: list[Array]  # the steps before the last one (which goes to q): they do not depend on q
    rows: tuple[int, ...]  # the body table's increment rows of those steps and the last one (STEP or TOTAL_STEP, to q)
    prev_careful: CarefulFrames | None  # the fixed steps' careful frames (kinematics.state_frames)
    r_start: Array | None  # (N, 3) body j from body i where the last step starts (points only)
    held: Array | None  # (N, 4, 3) the frames in that state without body j's position, `A v` (points, origin q_ref: `_step`)
    lower: Array  # the request's bounds on the coordinate, float64 (`update` writes them: copies in `prepare`)
    upper: Array
    strength: Array
    offset: Array | None  # None: 0 (only in the stateless call, which saves the arrays)
    lo: Array  # the penalty's bounds (`_bounds`: on x, or on the coordinate at `on_c`) and strength, in the scene's dtype
    up: Array
    s: Array
    committed: Array | None  # the committed coordinate at q_prev, float64 (the wire's), None: x summed over the steps
    theta: Array | None  # `committed - offset` in the scene's dtype (`_angle_of`): the angle x's last step starts from
    absolute: bool  # origin "absolute": x from the constitution's own zero (False: from q_ref, the specs' origin)
    x0: Array | None  # absolute and not telescoping: x's value at q_ref, added to x (a telescoping x is its value at q)
    faults: list[Fault]  # the stateless call's collapsed frames at q_ref, q_prev: reported with those at q
    progress: dict[str, Progress]  # the coordinate's progress over the steps that do not depend on q ("whole":
    # from starts[0] over `fixed`; "last": from starts[-1]; "ref": from F_ref), kept until `starts` change
    index: NDArray[np.int64]  # (N,) 0 ... N - 1, read-only: every answer of the scene's batch shares it
    meets: bool = False  # world edges, points, telescoping: the anchors meet at q_ref, so x = theta(q) (`_to_q`)
    balance: Array | None = None  # (N, 4) `assembly.balance` of `v` (points, a prepared scene): not taken per Hessian
    w: Array | None = None  # (N,) the penalty's widths `upper - lower` (`penalty.width`): not taken per evaluation
    on_c: NDArray[np.bool_] | None = None  # (N,) where `lo`, `up` bound the coordinate, not x (`_bounds`); None: nowhere


class PreparedScene:
    """A scene prepared once (`prepare`): evaluate any `q`, commit time steps, update limits.

    Not thread-safe: one scene serves one caller at a time (a session, a solver loop).
    """

    def __init__(self, table: BodyTable, batches: list[_Batch], threads: int) -> None:
        self._table = table
        self._batches = batches
        self._threads = threads  # each batch's derivative chunks on that many threads
        self._plain, self._all_plain = table.plain, False  # the bodies on the frames' common path to q (`_load`)
        self.n_bodies: int = table.dofs.shape[2]
        self.batch_sizes: list[int] = [jb.v.shape[0] for jb in batches]
        self._ends = [0, *accumulate(self.batch_sizes)]  # batch b's joints: [ends[b], ends[b + 1]) of all
        self._kept: tuple | None = None  # `_limits`

    def evaluate(self, q: ArrayLike, outputs: Iterable[str] = OUTPUTS, hessian_mode: str = "exact",
                 active_only: bool = False, deadline: float | None = None, layout: str = "joints") -> Evaluation:
        """Energy, gradient and Hessian of every joint at `q` (B, 12), as CONTRACT.md defines them
        (`layout` "bodies": summed per body, `Evaluation.assembled`, service/core/assembled.py).

        Raises `InputError` naming every fault (bad `q`: loc ("bodies", "q", i, k); a configuration
        without derivatives or that overflows: the joint); never returns NaN or Infinity.
        `deadline` (a `time.monotonic()` value) is checked between batches and derivative chunks:
        past it, `DeadlineExceeded`.
        """
        q = np.asarray(q, dtype=np.float64)
        outputs = tuple(outputs)
        FaultLog(check_options(outputs, hessian_mode), assembled.check_layout(layout),
                 check_dofs("q", q, self.n_bodies)).raise_if_any()
        with np.errstate(all="ignore"):
            return self._evaluate(q, outputs, hessian_mode, active_only, deadline, layout)

    def _evaluate(self, q: Array, outputs: tuple[str, ...], hessian_mode: str, active_only: bool,
                  deadline: float | None, layout: str) -> Evaluation:
        """`evaluate` of checked arguments, under `np.errstate(all="ignore")` (module docstring)."""
        # The PSD projection (an eigensolver) fails outright on a non-finite curvature; the exact mode then
        # locates the joints.
        try:
            ev = self._run(q, outputs, hessian_mode == "psd", active_only, deadline, layout)
        except np.linalg.LinAlgError:
            self._run(q, outputs, False, active_only, deadline, "joints")
            raise InputError([Fault(("hessian_mode",), "the PSD projection failed: the Hessian overflows float64")])
        raise_if(check_evaluation(ev))
        return ev

    def _run(self, q: Array, outputs: tuple[str, ...], psd: bool, active_only: bool, deadline: float | None,
             layout: str) -> Evaluation:
        batches = self._batches
        # v1's coordinate takes every step at q; once the angle is a state (a prev_coordinate, a commit), the last.
        steps = {r for jb in batches for r in (jb.rows if jb.theta is None else jb.rows[-1:])}
        self._load(q, {jb.rows[-1] for jb in batches}, steps)
        want_g, want_h, compact = "gradient" in outputs, "hessian" in outputs, layout == "bodies"
        at_q = [self._at_q(b, jb, deadline) for b, jb in enumerate(batches)]  # (F, x, coordinate, pen, faults)
        # The penalty of every batch at once; then each batch's faults and derivatives in batch order.
        # layout "bodies" sums the active joints' rows alone: only those are stored (compact)
        pen = np.concatenate([p for _, _, _, p, _ in at_q]) if batches else np.zeros(0)
        energy, finite, active, slopes = penalize(pen, *self._limits(), want_g or want_h, compact or active_only)
        ends = self._ends
        cuts = ends if active is None else active.searchsorted(ends).tolist()
        results = []
        for b, (jb, (F, x, coordinate, _, faults)) in enumerate(zip(batches, at_q)):
            raise_if(faults)
            e, own = energy[ends[b] : ends[b + 1]], slice(cuts[b], cuts[b + 1])
            a = None if active is None else active[own] - ends[b]
            gradient, hessian = differentiate(b, jb.c, F, jb.v, e, finite, a, slopes, cuts[b], want_g, want_h, psd,
                                              compact or active_only, self._threads, deadline, jb.balance)
            index, xs, es, cs = (a, x[a], e[a], coordinate[a]) if active_only else (jb.index, x, e, coordinate)
            results.append((BatchResult(jb.c.facts.uid, index, xs, es, gradient, hessian, cs), e, a))
        total = float(sum(e.sum() for _, e, _ in results))
        if not np.isfinite(total):
            raise InputError([Fault(("batches",), "the total energy overflows float64")])
        ev = Evaluation(total_energy=total, batches=[r for r, _, _ in results])
        if compact:  # summed per body; the batches keep index, x, energy and coordinate
            per_joint = [(jb.pairs.T[a], r.gradient, r.hessian) for jb, (r, _, a) in zip(batches, results)]
            ev.assembled = assembled.assemble_active(self.n_bodies, per_joint, want_g, want_h)
            for r in ev.batches:
                r.gradient = r.hessian = None
        return ev

    def _load(self, q: Array, rows: Iterable[int], steps: Iterable[int]) -> None:
        """`q` (B, 12) into the body table's state 2 (scratch: states 0, 1 are `q_ref`, `q_prev`), the increments
        `rows` of `A` to it, and whether the common frame path serves every body over the increments `steps`."""
        t = self._table
        t.load(2, q)
        t.increments(rows)
        self._plain = t.plain_over(steps)
        self._all_plain = bool(self._plain.all())

    def _to_q(self, jb: _Batch, starts: list[Array], fixed: list[Array], rows: tuple[int, ...], path: str,
              dF: Array | None, F_q: Array | None) -> tuple[Array, CarefulFrames | None, Array, object]:
        """Frames (N, 4, 3) at the loaded `q` (the end of the steps `rows`), the careful frames there
        (`_last_state`), x (N,) summed over the steps `fixed + [dF]` from `starts`, and what the coordinate formed at
        q for the collapse test (`Progress.known`). As `kinematics.state_frames`: each state is the previous
        one plus its step (or `F_q`, `_step`), but for joints of bodies off the common path (`_plain`),
        formed directly (scaled). The `fixed` steps' progress is kept per scene (`_progress`, as `path`).
        """
        states = [*starts, starts[-1] + dF if F_q is None else F_q]  # dF None: F_q, and x its value (`_step`)
        careful = None
        if not self._all_plain:
            idx = (~self._table.plain_joints(jb.pairs, self._plain)).nonzero()[0]
            if idx.shape[0]:
                careful = careful_frames(self._table, jb.pairs, rows, jb.c.facts.alpha, jb.v, idx)
                states = [F.copy() for F in states[:-1]] + states[-1:]  # the cached starts stay as they are
                for k, F in enumerate(states):
                    F[idx] = careful.unscaled(k)
        if dF is None:
            return states[-1], _last_state(careful), jb.c.value(states[-1]), None
        p = jb.c.advance(_progress(jb.c, jb.progress, path, starts, fixed), states[-2], dF)
        x = p.x
        if careful is not None:  # `meets`: theta(q_ref) is 0, its rounding (D_ref ~ 0 times a large S_ref) is not
            # (the frames at q of those joints are already `careful.unscaled`, above)
            x[careful.idx] = jb.c.value(states[-1][careful.idx]) if jb.meets else jb.c.careful_coordinate(careful)
        return states[-1], _last_state(careful), x, p.known[-1]

    def _step(self, jb: _Batch, row: int, r_start: Array | None) -> tuple[Array | None, Array | None]:
        """The frames' increment (N, 4, 3) over the table's increment `row` to the loaded `q`, from the state
        where body j sits at `r_start` (N, 3) from body i; with points, also the frames at q (else None).
        With the absolute origin (points telescope) x is the value at q alone: those frames from q's own A
        and positions, as the engine forms them, and no increment (None).

        The start's frames plus the step would keep body j's position at q only to the rounding of its
        position at the start (nothing of a 0.4 apart at q after 1e17 apart there). So the frames at q are
        `A v` at the start (`held`) plus A's increment, then body j's position at q.
        """
        t, alpha = self._table, jb.c.facts.alpha
        if r_start is not None and jb.absolute:
            r_q = relative_position(t.positions_of(jb.pairs, 2))
            return None, frame_quantities(r_q, t.linear_at(jb.pairs, 2), alpha, jb.v)
        dF = frame_quantities(None, t.linear_of(jb.pairs, row), alpha, jb.v)  # A's increment times v
        if r_start is None:
            return dF, None
        r_q = relative_position(t.positions_of(jb.pairs, 2))
        F_q = add_positions(jb.held + dF, r_q, alpha)
        return add_positions(dF, r_q - r_start, alpha), F_q

    def _collapsed(self, b: int, jb: _Batch, F: Array, careful: CarefulFrames | None, known: object) -> list[Fault]:
        """Batch `b`'s joints whose frame `F` (N, 4, 3) collapses at the loaded `q`."""
        bound = [self._table.size_bound(jb.pairs, 2)] if jb.c.facts.unit_frames else None
        return collapsed_faults(b, jb.c, ("q",), [F], careful, [known], bound)

    def _at_q(self, b: int, jb: _Batch, deadline: float | None) -> tuple[Array, Array, Array, Array, list[Fault]]:
        """Batch `b`'s frames (N, 4, 3), x, coordinate and the penalty's argument (N,) at the loaded `q`, and its faults
        there (raised in batch order, with its derivatives')."""
        check_deadline(deadline)
        dF, F_q = self._step(jb, jb.rows[-1], jb.r_start)
        if jb.theta is None:  # v1: x summed over every step from q_ref
            F, careful, x, known = self._to_q(jb, jb.starts, jb.fixed, jb.rows, "whole", dF, F_q)
            x = _from_origin(x, jb)
            coordinate = _plus_offset(x, jb.offset)
            pen = x if jb.on_c is None else np.where(jb.on_c, coordinate, x)
        else:
            F, careful, dx, known = self._to_q(jb, jb.starts[-1:], [], jb.rows[-1:], "last", dF, F_q)
            # the committed coordinate plus the turn: `(committed - offset) + dx + offset` kept `committed` only to
            # ulps of the offset (0.8 answered 0 under an offset of 1e17)
            x, coordinate = jb.theta + dx, jb.committed + dx
            pen = coordinate  # on the coordinate (`_limits`)
        faults = (jb.faults + self._collapsed(b, jb, F, careful, known))[:MAX_FAULTS]
        return F, x, coordinate, pen.astype(x.dtype, copy=False), faults

    def _limits(self) -> list[Array]:
        """Every batch's penalty bounds, strengths and widths (`penalize`), one after the other (a committed batch's
        bound its coordinate: `lower`, `upper`), kept until `update` or a commit changes them."""
        key = [jb.theta is None for jb in self._batches]
        if self._kept is None or self._kept[0] != key:
            dt = self._table.dtype
            parts = [((jb.lo, jb.up) if free else (jb.lower.astype(dt), jb.upper.astype(dt))) + (jb.s, jb.w)
                     for jb, free in zip(self._batches, key)]
            self._kept = key, [np.concatenate(a) for a in zip(*parts)] if parts else [np.zeros(0)] * 4
        return self._kept[1]

    # ---------------------------------------------------------------- state

    def commit(self, q: ArrayLike) -> list[Array]:
        """End a time step at the accepted `q` (B, 12); the committed coordinates, one (N,) per batch.

        Per revolute joint, as the contract: `r := r + rem(DeltaTheta(q, q_ref) - r)`, coordinate
        `r + offset`; a telescoping coordinate (prismatic) commits `x(q) + offset`. Then `q_prev := q`.
        All or nothing: a bad `q` or a collapsed frame raises `InputError` and changes nothing.
        """
        q = np.asarray(q, dtype=np.float64)
        raise_if(check_dofs("q", q, self.n_bodies))
        with np.errstate(all="ignore"):
            self._load(q, (TOTAL_STEP,), (TOTAL_STEP,))
            log, new = FaultLog(), []
            for b, jb in enumerate(self._batches):
                F_q, x, careful, known = self._from_ref(jb)
                log.add(self._collapsed(b, jb, F_q, careful, known))
                coordinate = None
                if jb.c.facts.stateful:
                    r = self._angle(jb)
                    turn = rem(x - r)
                    x = r + turn
                    if jb.committed is not None:  # the committed coordinate moves by the turn (as in `_at_q`)
                        coordinate = jb.committed + turn
                new.append((F_q, x, _plus_offset(x, jb.offset) if coordinate is None else coordinate))
            log.raise_if_any()
            coordinates = [c for _, _, c in new]
            raise_if(check_coordinates([(b, jb.index, x, c) for b, (jb, (_, x, c)) in enumerate(zip(self._batches, new))]))
            for jb, (F_q, x, c) in zip(self._batches, new):
                if jb.c.facts.stateful:  # its steps start at q_prev (state 1)
                    jb.starts, jb.fixed, jb.committed = [F_q], [], c.copy()
                    jb.theta = _angle_of(jb.committed, jb.offset, jb.lo.dtype)
                    jb.progress = {"ref": jb.progress["ref"]} if "ref" in jb.progress else {}
            self._table.load(1, self._table.dofs[2].T)
            return coordinates

    def _from_ref(self, jb: _Batch) -> tuple[Array, Array, CarefulFrames | None, object]:
        """Frames (N, 4, 3) at `q` (loaded with `TOTAL_STEP`), the coordinate from `q_ref` in one
        step (DeltaTheta(q, q_ref), or the slide), the careful frames at `q` and what the coordinate
        formed there."""
        r_ref = None
        if jb.c.facts.points:
            r_ref = jb.r_start if STEPS[jb.rows[-1]][0] == 0 else relative_position(self._table.positions_of(jb.pairs, 0))
        F_q, careful, x, known = self._to_q(jb, [jb.F_ref], [], (TOTAL_STEP,), "ref",
                                            *self._step(jb, TOTAL_STEP, r_ref))
        return F_q, _from_origin(x, jb), careful, known

    def _angle(self, jb: _Batch) -> Array:
        """The committed angle at q_prev: `theta`, or DeltaTheta(q_prev, q_ref) (from the batch's origin) before any commit."""
        if jb.theta is not None:
            return jb.theta
        x = _progress(jb.c, {}, "", jb.starts[:1], jb.fixed[:1]).x  # fresh: the kept progress stays as it is
        if jb.prev_careful is not None:
            x[jb.prev_careful.idx] = jb.c.careful_coordinate(jb.prev_careful)
        return _from_origin(x, jb)

    def coordinates(self, batches: Sequence[int] | None = None) -> list[Array]:
        """The committed coordinates at `q_prev` of `batches` (default every batch), one (N,) each (`x(q_prev) +
        offset`); `InputError` naming the joints where they overflow."""
        chosen = [(b, self._batches[b]) for b in (range(len(self._batches)) if batches is None else batches)]
        with np.errstate(all="ignore"):  # as a prev_coordinate carried it or the last commit answered it, else x + offset
            xs = [jb.committed if jb.committed is not None else self._x_prev(jb) for _, jb in chosen]
            out = [x.copy() if jb.committed is not None else _plus_offset(x, jb.offset) for (_, jb), x in zip(chosen, xs)]
        raise_if(check_coordinates([(b, jb.index, x, c) for (b, jb), x, c in zip(chosen, xs, out)]))
        return out

    def _x_prev(self, jb: _Batch) -> Array:
        """x (N,) at `q_prev` of a batch with no committed coordinate."""
        if jb.c.facts.stateful:
            return self._angle(jb)
        self._load(self._table.dofs[1].T, (TOTAL_STEP,), (TOTAL_STEP,))
        return self._from_ref(jb)[1]

    def update(self, batch: int, index: ArrayLike, lower: ArrayLike | None = None, upper: ArrayLike | None = None,
               strength: ArrayLike | None = None, offset: ArrayLike | None = None) -> None:
        """Set the limits, strengths or offsets of joints `index` (M,) of `batch`, each (M,) if given.

        Validated as a request is (`InputError`, loc ("batches", batch, "lower", j)); all or
        nothing. A new offset moves the coordinate with it (the angle `coordinate - offset` stays, to a rounding).
        """
        index = np.asarray(index)
        if index.dtype == object or index.size == 0:
            index = index.astype(np.int64)
        given = dict(lower=lower, upper=upper, strength=strength, offset=offset)
        values = {k: np.asarray(v, dtype=np.float64) for k, v in given.items() if v is not None}
        n = self.batch_sizes[batch] if 0 <= batch < len(self._batches) else 0
        raise_if(check_update_index(batch, len(self._batches), n, index))
        raise_if(check_update_values(batch, index, values))
        jb = self._batches[batch]
        after = {k: values[k] if k in values else getattr(jb, k)[index] for k in ("lower", "upper", "strength", "offset")}
        with np.errstate(all="ignore"):
            raise_if(check_update_ranges(batch, index, after["lower"], after["upper"], after["strength"]))
            if offset is not None:  # the committed coordinates it moves stay finite
                x = (jb.theta if jb.committed is not None else self._x_prev(jb))[index]  # this batch's alone
                raise_if(check_moved(batch, x, after["offset"], index))
            lo, up, on_c = _bounds(after["lower"], after["upper"], after["offset"], jb.lo.dtype)
            w = penalty.width(after["lower"], after["upper"])
        for k, a in after.items():
            getattr(jb, k)[index] = a
        if jb.committed is not None and offset is not None:  # the same angle, in the words of the new offset
            jb.committed[index] = jb.theta[index] + after["offset"]
            jb.theta = _angle_of(jb.committed, jb.offset, jb.lo.dtype)
        jb.lo[index], jb.up[index], jb.s[index], jb.w[index] = lo, up, after["strength"], w
        self._kept = None
        if on_c is not None or jb.on_c is not None:
            jb.on_c = np.zeros(jb.lo.shape[0], dtype=bool) if jb.on_c is None else jb.on_c
            jb.on_c[index] = False if on_c is None else on_c


def prepare(bodies: Bodies, batches: Sequence[Joints], *, threads: int = 1, dtype: type = np.float64) -> PreparedScene:
    """A scene prepared for evaluating many `q`: `bodies.q_prev`, `bodies.q_ref` (B, 12) and the joints.

    Raises `InputError` naming every fault of the static data. `bodies.q` is not used.
    `threads` > 1 takes each evaluation's derivative chunks on that many threads (bitwise the same numbers).
    `dtype` np.float32 is the benchmark's single-precision variant.
    """
    q_prev, q_ref = (np.array(a, dtype=np.float64) for a in (bodies.q_prev, bodies.q_ref))
    raise_if(check_bodies(Bodies(q_prev, q_prev, q_ref), names=("q_ref", "q_prev"))[:MAX_FAULTS])
    with np.errstate(all="ignore"):
        return _prepare(Bodies(q_prev, q_prev, q_ref), [_as_arrays(j, copy=True) for j in batches], threads, dtype,
                        own=True)


def evaluate(bodies: Bodies, batches: Sequence[Joints], outputs: Iterable[str] = OUTPUTS, hessian_mode: str = "exact",
             active_only: bool = False, dtype: type = np.float64, threads: int = 1, deadline: float | None = None,
             layout: str = "joints") -> Evaluation:
    """Energy, gradient and Hessian of every joint, as CONTRACT.md (v1, v1.1) defines them: the
    stateless call, `prepare(bodies, batches).evaluate(bodies.q, ...)`.

    Raises `InputError` naming every fault found (at most `MAX_FAULTS`); never returns NaN or
    Infinity. Only the outputs asked for are computed, and only joints outside their range are
    differentiated. `dtype` np.float32 runs everything after validation and the polar factors in
    single precision (a benchmark variant: ~1e-5 relative error; the wire is float64). `threads`
    > 1 runs each batch's derivative chunks on that many threads, with bitwise the same results; the HTTP
    service keeps 1, its worker processes already fill the cores. `deadline` (a `time.monotonic()` value): past it,
    `DeadlineExceeded` (checked between batches and derivative chunks). `layout` "bodies" answers
    the gradient and Hessian summed per body (`jointlimits.service.core.assembled`) instead of per joint: only
    the joints outside their range are differentiated and stored, then summed.
    """
    outputs = tuple(outputs)
    bodies = Bodies(*(np.asarray(a, dtype=np.float64) for a in (bodies.q, bodies.q_prev, bodies.q_ref)))
    FaultLog(check_options(outputs, hessian_mode), assembled.check_layout(layout), check_bodies(bodies)).raise_if_any()
    with np.errstate(all="ignore"):
        scene = _prepare(bodies, [_as_arrays(j) for j in batches], threads, dtype, own=False)
        return scene._evaluate(bodies.q, outputs, hessian_mode, active_only, deadline, layout)


def _as_arrays(j: Joints, copy: bool = False) -> Joints:
    f64 = lambda a: None if a is None else np.array(a, dtype=np.float64, copy=copy or None)  # noqa: E731
    return Joints(int(j.constitution_uid), int(j.base_uid), np.array(j.body_ids, dtype=np.int64, copy=copy or None),
                  f64(j.edges), f64(j.lower), f64(j.upper), f64(j.strength), f64(j.offset), f64(j.prev_coordinate),
                  f64(j.local_edges), j.origin)


def _increments(c: Constitution) -> tuple[int, ...]:
    """The body table's rows of `A` increments that `c`'s coordinate takes, in its order."""
    return (TOTAL_STEP,) if c.facts.telescopes else (PREV_STEP, STEP)


def _prepare(bodies: Bodies, batches: list[Joints], threads: int, dtype: type, own: bool) -> PreparedScene:
    """`prepare` of bodies whose states are already checked, and joints as arrays. `own`: the scene's
    limits are its own arrays (`update` writes them); else the stateless call's, which allocates
    nothing it does not need (every fresh array here is page faults of its own), and whose collapsed
    frames at q_ref and q_prev are named with those at q."""
    # q_prev is always in the table: the state a commit replaces. The stateless call's q too, and its last steps.
    steps = [_increments(numerics(j.constitution_uid)) for j in batches if j.constitution_uid in CONSTITUTIONS]
    rows = {PREV_STEP} | {row for s in steps for row in s[:-1]}
    n_bodies = bodies.q_ref.shape[0]
    checks = [joint_faults(b, joints, n_bodies) for b, joints in enumerate(batches)]
    # The polar factors of the bodies some joint reads, of batches without faults (their indices are in range; with
    # a fault the call is refused after `check_rotations`, which reads every body's ratio, used or not).
    used = np.zeros(n_bodies, dtype=bool)
    for j, (faults, _) in zip(batches, checks):
        if not faults:
            used[j.body_ids] = True
    # A singular A_ref is named by check_rotations, hostile numbers by the checks after (in batch order).
    table = BodyTable(bodies, dtype, rows=rows if own else rows | {s[-1] for s in steps}, used=used, plain=rows)
    FaultLog(check_rotations(table.ratio), *(faults for faults, _ in checks)).raise_if_any()
    # (2, N) pairs: contiguous indices gather 30% faster; the edge vectors as the checks took them (float64)
    prepared = [_prepare_batch(b, j, table, own, np.ascontiguousarray(j.body_ids.T), d if dtype == np.float64 else None)
                for b, (j, (_, d)) in enumerate(zip(batches, checks))]
    if own:  # a prepared scene with a collapsed frame evaluates nothing: refused at once
        FaultLog(*(jb.faults for jb in prepared)).raise_if_any()
        for jb in prepared:
            jb.faults = []
    return PreparedScene(table, prepared, threads)


def _prepare_batch(b: int, joints: Joints, table: BodyTable, own: bool, pairs: NDArray[np.intp],
                   edge: Array | None) -> _Batch:
    """Batch `b`'s frames at its states, from `table`; `pairs` (2, N) its bodies i and j, contiguous; `edge` (N, 3)
    its edge vectors, if taken."""
    c = numerics(joints.constitution_uid)
    alpha, points, dtype = c.facts.alpha, c.facts.points, table.dtype
    rows = _increments(c)
    A_ref = table.linear_of(pairs, REF)
    start = STEPS[rows[-1]][0]
    # The states read here: q_ref, where the last step starts, and those the fixed steps span.
    states = {0, start} | {s for row in rows[:-1] for s in STEPS[row]}
    p = {s: table.positions_of(pairs, s) for s in states} if points else {}
    r = {s: relative_position(ps) for s, ps in p.items()}
    cast = lambda a: None if a is None else a.astype(dtype, copy=False)  # noqa: E731
    R_ref = table.rotations(pairs)
    t, anchors = axis_and_anchors(c, cast(joints.edges), cast(joints.local_edges), p.get(0), A_ref, R_ref, edge)
    v = c.local_vectors(t, anchors, R_ref)
    F_ref = frame_quantities(None, A_ref, alpha, v)
    absolute = joints.origin == "absolute"
    held = None
    if points and not absolute:  # x's last step starts at q_ref (points telescope): `_step` forms the frames at q from `A_ref v`
        held = F_ref.copy(order="K")  # component-major, as F_ref
    if points:
        add_positions(F_ref, r[0], alpha)
    # x at q_ref from the constitution's own zero, for a coordinate of directions alone (one with points
    # telescopes: its absolute value is taken at q, `_step`), from `A_ref` scaled per body by a power of
    # two (exact): frames at the edge of float64 keep every digit of their angle.
    x0 = None
    if absolute and not c.facts.telescopes:
        x0 = c.value(scaled_frames(None, A_ref, exponents(A_ref), alpha, v))
    # The steps before the last one (q_ref -> q_prev) and where each starts.
    fixed = []
    for row in rows[:-1]:
        s0, s1 = STEPS[row]
        fixed.append(frame_quantities(r[s1] - r[s0] if points else None, table.linear_of(pairs, row), alpha, v))
    starts, prev_careful = state_frames(table, pairs, rows[:-1], alpha, v, F_ref, fixed) if fixed else ([F_ref], None)
    progress: dict[str, Progress] = {}
    # The fixed steps' progress now: the collapse tests at q_ref and q_prev read what it formed there.
    known = _progress(c, progress, "whole", starts, fixed).known
    bounds = [table.size_bound(pairs, s) for s in range(len(starts))] if c.facts.unit_frames else None
    faults = collapsed_faults(b, c, ("q_ref", "q_prev")[: len(starts)], starts, prev_careful, known, bounds)
    offset = joints.offset if joints.offset is not None or not own else np.zeros(pairs.shape[1])
    committed = joints.prev_coordinate
    theta = None if committed is None else _angle_of(committed, offset, dtype)
    lower, upper, strength = joints.lower, joints.upper, joints.strength
    lo, up, on_c = _bounds(lower, upper, offset, dtype)
    index = np.arange(pairs.shape[1])
    index.flags.writeable = False
    return _Batch(c, pairs, v, F_ref, starts, fixed, rows, prev_careful, r.get(start), held, lower, upper, strength,
                  offset, lo, up, strength.astype(dtype, copy=own), committed, theta, absolute, x0, faults, progress,
                  index, meets=points and c.facts.telescopes and joints.edges is not None,
                  balance=assembly.balance(alpha, v) if own and points else None, w=penalty.width(lower, upper), on_c=on_c)


def _bounds(lower: Array, upper: Array, offset: Array | None, dtype: type) -> tuple[Array, Array, NDArray[np.bool_] | None]:
    """The penalty's bounds (N,) in `dtype` and where they bound the coordinate (N,) (None: nowhere) of a batch without
    committed coordinates (with them: `lower`, `upper` on the coordinate). The contract's l = lower - offset, u = upper
    - offset on x (the engine's arithmetic) where their width is `upper - lower`'s; else lower, upper on the coordinate
    x + offset: `(upper - offset) - (lower - offset)` rounds at the offset's scale (a range [-5, 5] under an offset of
    1e17 read as degenerate, 1000x the energy) or overflows, `upper - lower` does not."""
    if offset is None:
        return lower.astype(dtype, copy=False), upper.astype(dtype, copy=False), None
    lo, up = (lower - offset).astype(dtype, copy=False), (upper - offset).astype(dtype, copy=False)
    on_c = (penalty.width(lo, up) != penalty.width(lower, upper)) | ~np.isfinite(lo) | ~np.isfinite(up)
    lo[on_c], up[on_c] = lower[on_c], upper[on_c]
    return lo, up, on_c if on_c.any() else None


def _progress(c: Constitution, kept: dict[str, Progress], path: str, starts: list[Array], fixed: list[Array]) -> Progress:
    """The coordinate's progress from `starts[0]` over the steps `fixed` (from `starts`), kept in
    `kept` as `path` (they do not depend on q)."""
    p = kept.get(path)
    if p is None:
        p = c.begin(starts[0])
        for F, dF in zip(starts, fixed):
            p = c.advance(p, F, dF)
        kept[path] = p
    return p


def _last_state(careful: CarefulFrames | None) -> CarefulFrames | None:
    """`careful` reduced to its last state (the frames at q), for the collapse test there."""
    return None if careful is None else CarefulFrames(careful.idx, careful.exponents[-1:], careful.states[-1:], [], [])


def _angle_of(committed: Array, offset: Array | None, dtype: type) -> Array:
    """The angle (N,) of committed coordinates (N,), on every path (`lower - offset` is rounded at that scale too)."""
    return (committed - (0.0 if offset is None else offset)).astype(dtype, copy=False)


def _from_origin(x: Array, jb: _Batch) -> Array:
    """`x` (N,) measured from the batch's origin: plus its value at q_ref where that is "absolute" (a telescoping
    coordinate is already: its value at q, `_step`; x(q_ref) plus the difference from there would keep x
    only to the rounding of x(q_ref), nothing of a slide of 0.4 after one of 1e17)."""
    return x if jb.x0 is None else x + jb.x0


def _plus_offset(x: Array, offset: Array | None, index: NDArray[np.int64] | None = None) -> Array:
    """The coordinate `x + offset` (M,) of `x` (M,), at joints `index` (M,) of `offset` if given."""
    if offset is None:
        return x.copy()
    return x + (offset if index is None else offset[index])
