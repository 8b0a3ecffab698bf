"""Split a large request into several that each fit the server's limits, and merge their answers.

Each part carries only the bodies its joints use (renumbered), so parts stay small
however many bodies the scene has. Results and error locations are mapped back to
the original batch, joint and body indices.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace

import numpy as np

from jointlimits.client.errors import Fault, ServiceError
from jointlimits.client.model import NEEDED, OPTIONAL, Assembled, BatchResult, Evaluation, JointBatch, Request, in_body
from jointlimits.service.core.assembled import raise_overflow, reduce_pairs
from jointlimits.service.core.errors import InputError


@dataclass(frozen=True)
class Part:
    """One request of a split: rows `[start, stop)` of original batch `batches[k]` for each k."""

    request: Request
    batches: list[int]
    starts: list[int]
    bodies: np.ndarray | None
    """Original body row of each of the part's bodies (M,), or None when they are all kept."""


def plan(request: Request, max_joints: int) -> list[Part]:
    """Parts of at most `max_joints` joints (at least one part, empty batches included)."""
    if request.n_joints <= max_joints:
        return [Part(request, list(range(len(request.batches))), [0] * len(request.batches), None)]
    parts, pieces, room = [], [], max_joints
    for k, b in enumerate(request.batches):
        start, n = 0, len(b)
        while True:
            take = min(room, n - start)
            pieces.append((k, start, start + take))
            start, room = start + take, room - take
            if room == 0:
                parts.append(_part(request, pieces))
                pieces, room = [], max_joints
            if start >= n:
                break
    if pieces:
        parts.append(_part(request, pieces))
    return parts


def _part(request: Request, pieces: list[tuple[int, int, int]]) -> Part:
    batches = [_rows(request.batches[k], a, b) for k, a, b in pieces]
    ids = np.concatenate([b.body_ids.reshape(-1) for b in batches]) if batches else np.zeros(0, np.int64)
    n_bodies = np.shape(request.q)[0]
    keep = None
    if ids.size and ids.min() >= 0 and ids.max() < n_bodies and not (ids[0::2] == ids[1::2]).any():
        # Only in-range pairs of two bodies are renumbered; else the server names the bad index as the user wrote it.
        keep = np.unique(ids)
        batches = [replace(b, body_ids=np.searchsorted(keep, b.body_ids)) for b in batches]
    pick = (lambda a: np.asarray(a)[keep]) if keep is not None else (lambda a: a)
    sub = replace(request, q=pick(request.q), q_prev=pick(request.q_prev), q_ref=pick(request.q_ref), batches=batches)
    return Part(sub, [k for k, _, _ in pieces], [a for _, a, _ in pieces], keep)


def _rows(b: JointBatch, start: int, stop: int) -> JointBatch:
    return replace(b, **{k: np.asarray(a)[start:stop] for k in NEEDED + OPTIONAL if (a := getattr(b, k)) is not None})


def merge(request: Request, parts: list[Part], results: list[Evaluation]) -> Evaluation:
    """One `Evaluation` as if the request had been sent whole (total energy summed part by part)."""
    assembled = _merge_assembled(request, parts, results)
    if len(parts) == 1 and parts[0].bodies is None:
        return replace(results[0], assembled=assembled)
    pieces: list[list[BatchResult]] = [[] for _ in request.batches]
    for part, ev in zip(parts, results):
        for k, start, r in zip(part.batches, part.starts, ev.batches):
            pieces[k].append(replace(r, index=r.index + start))
    merged = []
    for b, rs in zip(request.batches, pieces):
        cat = {k: None if getattr(rs[0], k) is None else np.concatenate([getattr(r, k) for r in rs])
               for k in ("index", "x", "energy", "gradient", "hessian", "coordinate")}
        merged.append(BatchResult(b.constitution_uid, **cat))
    total = sum(float(ev.total_energy) for ev in results)  # Python floats: an overflow is inf, no warning
    if not math.isfinite(total):  # finite parts whose sum is not: the whole request's fault, as the core words it
        raise in_body([Fault(("batches",), "the total energy overflows float64")])
    return Evaluation(total_energy=total, batches=merged, assembled=assembled)


def _merge_assembled(request: Request, parts: list[Part], results: list[Evaluation]) -> Assembled | None:
    """`layout="bodies"`: the parts' per-body answers in the original body rows, summed."""
    if not results or results[0].assembled is None:
        return None
    n_bodies = int(np.shape(request.q)[0])
    each = [(p.bodies if p.bodies is not None else np.arange(n_bodies), ev.assembled) for p, ev in zip(parts, results)]
    out = Assembled(n_bodies)
    with np.errstate(over="ignore", invalid="ignore"):  # parts' finite sums may overflow once added: refused below
        if each[0][1].gradient is not None:
            out.gradient = np.zeros((n_bodies, 12))
            for keep, a in each:
                np.add.at(out.gradient, keep, a.gradient)
        if each[0][1].blocks is not None:
            # keep is sorted: renumbering keeps rows <= cols.
            out.rows, out.cols, out.blocks = reduce_pairs(
                np.concatenate([keep[a.rows] for keep, a in each]), np.concatenate([keep[a.cols] for keep, a in each]),
                np.concatenate([a.blocks for _, a in each]))
    try:
        raise_overflow(out)  # the whole request's fault (422, the bodies named), never an infinity
    except InputError as e:
        raise in_body(e.faults) from None
    return out


def relocate(part: Part, e: ServiceError) -> ServiceError:
    """The error of one part with `loc`s in the original request's batch, joint and body indices."""
    whole = part.bodies is None and not any(part.starts) and part.batches == list(range(len(part.batches)))
    if whole:
        return e
    faults = [Fault(_relocate(part, f.loc), _renumber(part, f), f.type) for f in e.faults]
    return type(e)(e.status, faults, e.where)


_BODY_ROWS = re.compile(r"(?<=body )\d+|(?<=block \()\d+|(?<=, )\d+(?=\) overflows)")  # assembled.raise_overflow's


def _renumber(part: Part, f: Fault) -> str:
    """A per-body sum's fault names the part's body rows: the caller's instead."""
    if part.bodies is None or tuple(f.loc) != ("body", "layout"):
        return f.msg
    return _BODY_ROWS.sub(lambda m: str(int(part.bodies[int(m.group())])), f.msg)


def _relocate(part: Part, loc: tuple) -> tuple:
    loc = list(loc)
    # loc = ["body", "batches", b, field, j, ...] or ["body", "bodies", name, i, ...]
    if len(loc) >= 3 and loc[:2] == ["body", "batches"] and isinstance(loc[2], int) and loc[2] < len(part.batches):
        b = loc[2]
        loc[2] = part.batches[b]
        if len(loc) >= 5 and isinstance(loc[4], int) and loc[3] != "constitution_uid":
            loc[4] += part.starts[b]
    elif len(loc) >= 4 and loc[:2] == ["body", "bodies"] and isinstance(loc[3], int) and part.bodies is not None:
        if 0 <= loc[3] < len(part.bodies):
            loc[3] = int(part.bodies[loc[3]])
    return tuple(loc)
