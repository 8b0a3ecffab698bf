"""Timing, accuracy and memory measurements of the core and its peers (no JAX imported here)."""

from __future__ import annotations

import json
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jointlimits.service.core import Bodies, Joints, evaluate

# Bench mode -> the core's outputs; "psd" is E+G+H with hessian_mode="psd".
OUTPUTS = {
    "e": ("energy",),
    "eg": ("energy", "gradient"),
    "egh": ("energy", "gradient", "hessian"),
    "psd": ("energy", "gradient", "hessian"),
}
MODE_NAMES = {"e": "energy", "eg": "E+G", "egh": "E+G+H exact", "psd": "E+G+H psd"}
FIELDS = (("E", "energy"), ("G", "gradient"), ("H", "hessian"))  # error key, result field
Results = list[dict[str, np.ndarray]]  # per batch: energy (N,), gradient (N, 24), hessian (N, 24, 24)


def median_time(fn: Callable[[], Any], reps: int = 5, warmup: int = 1) -> float:
    """Median wall time (s) of `reps` calls after `warmup` calls."""
    return median_times({fn: fn}, reps, warmup)[fn]


def median_times(fns: dict[Any, Callable[[], Any]], reps: int = 5, warmup: int = 1) -> dict[Any, float]:
    """Median wall time (s) of each of `fns`, called in turn: `warmup` rounds, then `reps` timed rounds.

    Every median then spans the same stretch of the run: a machine that slows down or speeds up
    meanwhile (these are shared virtual machines: 10-30% between minutes) moves them alike, and the
    ratios between them (what the targets read) keep still where medians taken one after the other
    would each catch a different moment.
    """
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    ts: dict[Any, list[float]] = {k: [] for k in fns}
    for _ in range(reps):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            ts[k].append(time.perf_counter() - t)
    return {k: float(np.median(v)) for k, v in ts.items()}


def _hessian_mode(mode: str) -> str:
    return "psd" if mode == "psd" else "exact"


def core_call(bodies: Bodies, batches: list[Joints], mode: str, dtype: type = np.float64, **kw: Any) -> Callable:
    """The core on a whole scene in bench mode `mode` ("e", "eg", "egh", "psd"); `kw` goes to `evaluate`."""
    return lambda: evaluate(bodies, batches, outputs=OUTPUTS[mode], hessian_mode=_hessian_mode(mode), dtype=dtype, **kw)


def single_joints(batches: list[Joints]) -> list[list[Joints]]:
    """Per batch, its N joints as N one-joint batches (what a caller looping over joints would pass)."""
    return [
        [Joints(j.constitution_uid, j.base_uid, j.body_ids[k : k + 1], j.edges[k : k + 1], j.lower[k : k + 1],
                j.upper[k : k + 1], j.strength[k : k + 1]) for k in range(j.body_ids.shape[0])]
        for j in batches
    ]


def loop_results(bodies: Bodies, singles: list[list[Joints]], mode: str = "egh") -> Results:
    """Peer (b): the core called once per joint (`singles` from `single_joints`), rows stacked per batch."""
    outputs = OUTPUTS[mode]
    out = []
    for batch in singles:
        rows: dict[str, list] = {f: [] for f in outputs}
        for one in batch:
            r = evaluate(bodies, [one], outputs=outputs, hessian_mode=_hessian_mode(mode)).batches[0]
            for f in outputs:
                rows[f].append(getattr(r, f)[0])
        out.append({f: np.array(v) for f, v in rows.items()})
    return out


def loop_call(bodies: Bodies, batches: list[Joints], mode: str) -> Callable:
    """Peer (b) timed: the per-joint loop; splitting the batches is setup, outside the timing."""
    singles = single_joints(batches)
    return lambda: loop_results(bodies, singles, mode)


def _output_shapes(n: int, mode: str) -> list[tuple[int, ...]]:
    """Shapes the core returns for `n` joints: x and energy (n,), gradient (n, 24), Hessian (n, 24, 24)."""
    return [(n,), (n,)] + ([(n, 24)] if mode != "e" else []) + ([(n, 24, 24)] if mode in ("egh", "psd") else [])


def floor_call(n: int, mode: str) -> Callable:
    """Peer (c): the memory-write floor, allocating and filling the outputs of `n` joints once."""
    shapes = _output_shapes(n, mode)
    return lambda: [np.full(s, 1.0) for s in shapes]


def output_bytes(n: int, mode: str) -> int:
    """Bytes of the float64 outputs of `n` joints in `mode` (x, energy, then gradient, Hessian if asked)."""
    return 8 * sum(int(np.prod(s)) for s in _output_shapes(n, mode))


def peak_memory(fn: Callable[[], Any]) -> int:
    """Peak bytes allocated (NumPy reports its buffers to tracemalloc) during one call, its result included."""
    fn()  # warm-up: caches and lazily built tables are not part of the peak
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    out = fn()
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    del out
    return peak


# ------------------------------------------------------------------ accuracy


def relerr(got: Any, want: Any) -> float:
    """Normwise relative error `max|got - want| / max|want|` (absolute when want is all zero)."""
    got, want = np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64)
    scale = float(np.max(np.abs(want), initial=0.0))
    diff = float(np.max(np.abs(got - want), initial=0.0))
    return diff / scale if scale > 0 else diff


def document(bodies: Bodies, batches: list[Joints], f64: Callable, i64: Callable, hessian_mode: str = "exact",
             active_only: bool = False) -> dict:
    """A CONTRACT v1 request of every output, arrays converted by `f64` / `i64` (lists, NumPy, wire arrays)."""
    return {
        "bodies": {k: f64(getattr(bodies, k)) for k in ("q", "q_prev", "q_ref")},
        "batches": [
            {"constitution_uid": j.constitution_uid, "base_uid": j.base_uid, "body_ids": i64(j.body_ids),
             **{k: f64(getattr(j, k)) for k in ("edges", "lower", "upper", "strength")}}
            for j in batches
        ],
        "outputs": ["energy", "gradient", "hessian"],
        "hessian_mode": hessian_mode,
        "active_only": active_only,
    }


def to_request(bodies: Bodies, batches: list[Joints], hessian_mode: str = "exact") -> dict:
    """The scene as a JSON-ready request dict (nested lists)."""
    tolist = lambda a: np.asarray(a).tolist()  # noqa: E731
    return document(bodies, batches, tolist, tolist, hessian_mode)


def from_request(req: dict) -> tuple[Bodies, list[Joints]]:
    """The scene of a request dict, as the core's NumPy inputs."""
    b = req["bodies"]
    bodies = Bodies(*(np.asarray(b[k], dtype=np.float64) for k in ("q", "q_prev", "q_ref")))
    batches = [
        Joints(int(j["constitution_uid"]), int(j["base_uid"]), np.asarray(j["body_ids"], dtype=np.int64),
               np.asarray(j["edges"], dtype=np.float64), np.asarray(j["lower"], dtype=np.float64),
               np.asarray(j["upper"], dtype=np.float64), np.asarray(j["strength"], dtype=np.float64))
        for j in req["batches"]
    ]
    return bodies, batches


@dataclass
class CaseSet:
    """Cases merged into one scene (one batch per constitution), with the 50-digit reference per joint."""

    names: list[str]
    families: list[str]  # per case: "well" or "hard"
    bodies: Bodies
    batches: list[Joints]
    case_of: list[np.ndarray]  # per merged batch: the case index of each joint (N,)
    ref: dict[str, Results] = field(default_factory=dict)  # hessian mode -> per merged batch

    def errors(self, results: Results, mode: str = "exact", family: str | None = None) -> dict[str, float]:
        """Max over cases (of `family`, or all) of each case's normwise relative error of E, G, H.

        `results` is per merged batch, like `ref`; {} when no case is of `family`.
        """
        keep = [c for c, f in enumerate(self.families) if family in (None, f)]
        if not keep:
            return {}
        worst = {key: 0.0 for key, _ in FIELDS}
        for got, want, case in zip(results, self.ref[mode], self.case_of):
            for c in keep:
                rows = case == c
                if rows.any():
                    for key, f in FIELDS:
                        if f not in got:  # a peer without this output (Warp: no Hessian)
                            worst.pop(key, None)
                            continue
                        worst[key] = max(worst[key], relerr(np.asarray(got[f])[rows], want[f][rows]))
        return worst


def build_case_set(cases: list[tuple[str, str, dict]], modes: tuple[str, ...] = ("exact", "psd")) -> CaseSet:
    """Merge `(name, family, request)` cases; the reference (bench/reference.py, mpmath) per case and mode."""
    from bench.reference import reference_request  # the team's 50-digit reference of the contract

    qs: dict[str, list] = {"q": [], "q_prev": [], "q_ref": []}
    per_uid: dict[int, dict[str, list]] = {}
    offset = 0
    refs: dict[str, dict[int, dict[str, list]]] = {m: {} for m in modes}
    tails = {"energy": (), "gradient": (24,), "hessian": (24, 24)}
    for ci, (_, _, req) in enumerate(cases):
        bodies, batches = from_request(req)
        for k in qs:
            qs[k].append(getattr(bodies, k))
        ref_case = reference_request(req)  # per batch: energy, gradient, hessian_exact, hessian_psd
        for bi, j in enumerate(batches):
            d = per_uid.setdefault(j.constitution_uid, {"base": j.base_uid, "ids": [], "edges": [], "lower": [],
                                                        "upper": [], "strength": [], "case": []})
            d["ids"].append(j.body_ids + offset)  # body ids shift with the bodies of the cases before
            for f in ("edges", "lower", "upper", "strength"):
                d[f].append(getattr(j, f))
            d["case"].append(np.full(j.body_ids.shape[0], ci))
            for m in modes:
                r = refs[m].setdefault(j.constitution_uid, {f: [] for f in tails})
                for f, tail in tails.items():
                    key = f"hessian_{m}" if f == "hessian" else f
                    r[f].append(np.asarray(ref_case[bi][key], dtype=np.float64).reshape((-1,) + tail))
        offset += bodies.q.shape[0]
    bodies = Bodies(*(np.concatenate(qs[k]) for k in ("q", "q_prev", "q_ref")))
    uids = sorted(per_uid, reverse=True)
    batches = [
        Joints(u, per_uid[u]["base"], np.concatenate(per_uid[u]["ids"]),
               *(np.concatenate(per_uid[u][f]) for f in ("edges", "lower", "upper", "strength")))
        for u in uids
    ]
    ref = {m: [{f: np.concatenate(v) for f, v in refs[m][u].items()} for u in uids] for m in modes}
    return CaseSet([c[0] for c in cases], [c[1] for c in cases], bodies, batches,
                   [np.concatenate(per_uid[u]["case"]) for u in uids], ref)


def core_results(cs: CaseSet, mode: str, dtype: type = np.float64, **kw: Any) -> Results:
    """The core on the merged cases, hessian mode `mode` ("exact" or "psd"); `kw` goes to `evaluate`."""
    ev = evaluate(cs.bodies, cs.batches, hessian_mode=mode, dtype=dtype, **kw)
    return [{"energy": r.energy, "gradient": r.gradient, "hessian": r.hessian} for r in ev.batches]


def golden_cases(path: Path) -> list[tuple[str, str, dict]]:
    """`(name, family, request)` of tests/golden_cases.json ([] if absent)."""
    if not path.exists():
        return []
    return [(c["name"], c["family"], c["request"]) for c in json.loads(path.read_text())["cases"]]
