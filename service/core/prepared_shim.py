"""TEMPORARY stand-in for `service.core.prepared` (branch i10-core), deleted once that is merged.

Same interface; built on `checked_evaluate`, so it re-derives everything per call and does not
carry multi-turn angles into `evaluate` (the real prepared scene does).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import replace

import numpy as np

from service.core.errors import Fault, InputError
from service.core.scene import OUTPUTS, Array, Bodies, Evaluation, Joints
from service.core.validate import checked_evaluate


def _rem(y: Array) -> Array:
    return y - 2 * np.pi * np.round(y / (2 * np.pi))


class PreparedScene:
    def __init__(self, bodies: Bodies, batches: Sequence[Joints], threads: int = 1) -> None:
        checked_evaluate(bodies, batches, outputs=("energy",), threads=threads)
        f = lambda a: np.array(a, dtype=np.float64)  # noqa: E731
        self.q_prev, self.q_ref = f(bodies.q_prev), f(bodies.q_ref)
        self.batches = [
            replace(j, body_ids=np.array(j.body_ids, dtype=np.int64), edges=f(j.edges), lower=f(j.lower),
                    upper=f(j.upper), strength=f(j.strength))
            for j in batches
        ]
        self.offsets = [np.zeros(len(j.lower)) for j in self.batches]
        self.threads = threads
        self.n_bodies = self.q_ref.shape[0]
        self.batch_sizes = [len(j.lower) for j in self.batches]
        self._r = self._x(self.q_prev, self.q_prev)

    def _x(self, q: Array, q_prev: Array) -> list[Array]:
        ev = checked_evaluate(Bodies(q, q_prev, self.q_ref), self.batches, outputs=("energy",), threads=self.threads)
        return [np.array(b.x) for b in ev.batches]

    def _q(self, q: object) -> Array:
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.n_bodies, 12):
            raise InputError([Fault(("q",), f"must be {self.n_bodies} rows of 12 numbers, got shape {q.shape}")])
        return q

    def evaluate(self, q: object, outputs: Iterable[str] = OUTPUTS, hessian_mode: str = "exact",
                 active_only: bool = False) -> Evaluation:
        return checked_evaluate(Bodies(self._q(q), self.q_prev, self.q_ref), self.batches, outputs=tuple(outputs),
                                hessian_mode=hessian_mode, active_only=active_only, threads=self.threads)

    def commit(self, q: object) -> list[Array]:
        q = self._q(q)
        theta = self._x(q, self.q_ref)
        self._r = [r + _rem(t - r) if j.constitution_uid == 670 else t for r, t, j in zip(self._r, theta, self.batches)]
        self.q_prev = q.copy()
        return self.coordinates()

    def coordinates(self) -> list[Array]:
        return [r + o for r, o in zip(self._r, self.offsets)]

    def update(self, batch: int, index: object, lower: object = None, upper: object = None, strength: object = None,
               offset: object = None) -> None:
        if not 0 <= batch < len(self.batches):
            raise InputError([Fault(("batch",), f"batch {batch} out of range [0, {len(self.batches)})")])
        idx = np.asarray(index, dtype=np.int64).reshape(-1)
        n = self.batch_sizes[batch]
        bad = np.flatnonzero((idx < 0) | (idx >= n))
        if bad.size:
            raise InputError([Fault(("index", int(k)), f"joint {int(idx[k])} out of range [0, {n})") for k in bad[:20]])
        j = self.batches[batch]
        new = {"lower": j.lower.copy(), "upper": j.upper.copy(), "strength": j.strength.copy(),
               "offset": self.offsets[batch].copy()}
        faults = []
        for name, v in (("lower", lower), ("upper", upper), ("strength", strength), ("offset", offset)):
            if v is None:
                continue
            v = np.asarray(v, dtype=np.float64).reshape(-1)
            if v.shape != idx.shape:
                faults.append(Fault((name,), f"must have {idx.shape[0]} entries (one per index), got {v.shape[0]}"))
                continue
            faults += [Fault((name, int(k)), "is not a finite number") for k in np.flatnonzero(~np.isfinite(v))[:20]]
            new[name][idx] = v
        if faults:
            raise InputError(faults)
        faults += [Fault(("batches", batch, "lower", int(k)), f"lower {new['lower'][k]!r} > upper {new['upper'][k]!r}")
                   for k in np.flatnonzero(new["lower"] > new["upper"])[:20]]
        faults += [Fault(("batches", batch, "strength", int(k)), "strength < 0") for k in np.flatnonzero(new["strength"] < 0)[:20]]
        if faults:
            raise InputError(faults)
        self.batches[batch] = replace(j, lower=new["lower"], upper=new["upper"], strength=new["strength"])
        self.offsets[batch] = new["offset"]


def prepare(bodies: Bodies, batches: Sequence[Joints], *, threads: int = 1) -> PreparedScene:
    return PreparedScene(bodies, batches, threads)
