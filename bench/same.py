"""`python -m bench.same REV`: is this tree's core bitwise the core of git revision REV?

A refactor of the core that claims "the same numbers" is held to this: both trees' cores are
imported side by side (as `bench.ab` does) and called on the same scenes, and every array of
every answer is compared bit for bit (NaN-safe), every `InputError` by its faults. The scenes:
`bench.scenes.make_scene` from 1 to 5000 joints, none / half / all active; each also with
offsets, a revolute `prev_coordinate`, `local_edges` with `origin="absolute"`, scaled by 1e-150 and
1e150 and moved 1e8 away; the tests' seeded adversarial scenes (`tests.scenes.random_scene`). The
calls: stateless (every output set, exact and psd, `active_only`, both layouts, 1 and 2 threads),
prepared at a moved `q`, a commit then an evaluation, `coordinates`, `update`. Prints the count of
comparisons and each difference; exits 1 on any.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from bench.ab import import_revision
from bench.scenes import make_scene

Scene = tuple[Any, list[Any]]


def _variants(bodies: Any, batches: list[Any], rng: np.random.Generator) -> Iterator[tuple[str, Scene]]:
    yield "plain", (bodies, batches)
    n = [len(b.lower) for b in batches]
    yield "offset", (bodies, [dataclasses.replace(b, offset=rng.normal(size=k)) for b, k in zip(batches, n)])
    yield "prev", (bodies, [dataclasses.replace(b, prev_coordinate=rng.normal(size=k) * 4)
                            if b.constitution_uid == 670 else b for b, k in zip(batches, n)])
    local = []
    for b, k in zip(batches, n):
        le = np.stack([b.edges, b.edges], axis=1) + rng.normal(size=(k, 2, 2, 3)) * 0.1
        local.append(dataclasses.replace(b, edges=None, local_edges=le, origin="absolute"))
    yield "local", (bodies, local)
    for s in (1e-150, 1e150):
        sc = np.ones(12)
        sc[:3] = s
        scaled = type(bodies)(*(a * sc for a in (bodies.q, bodies.q_prev, bodies.q_ref)))
        yield f"scale{s:g}", (scaled, [dataclasses.replace(b, edges=b.edges * s) for b in batches])
    off = np.zeros(12)
    off[:3] = 1e8
    moved = type(bodies)(*(a + off for a in (bodies.q, bodies.q_prev, bodies.q_ref)))
    yield "far", (moved, [dataclasses.replace(b, edges=b.edges + 1e8) for b in batches])


def scenes() -> Iterator[tuple[str, Scene]]:
    rng = np.random.default_rng(7)
    for n in (1, 2, 10, 100, 1000, 5000):
        for outside in (0.0, 0.5, 1.0):
            bodies, batches = make_scene(n, outside, seed=n + int(outside * 10))
            for name, scene in _variants(bodies, batches, rng):
                yield f"{n}/{outside}/{name}", scene
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.scenes import random_scene

    for seed in range(40):
        s = random_scene(np.random.default_rng(seed))
        args = s.core_args()
        yield f"random{seed}", (args["bodies"], list(args["batches"]))


def _flat(x: Any, out: dict[str, Any], key: str = "") -> None:
    """Every array and number of an answer (dataclasses, lists, tuples, dicts) by a path."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        for f in dataclasses.fields(x):
            _flat(getattr(x, f.name), out, f"{key}.{f.name}")
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            _flat(v, out, f"{key}[{i}]")
    elif isinstance(x, dict):
        for k, v in x.items():
            _flat(v, out, f"{key}[{k}]")
    elif hasattr(x, "__dict__") and not isinstance(x, (np.ndarray, np.generic)) and type(x).__module__ != "builtins":
        for k, v in sorted(vars(x).items()):
            if not k.startswith("_"):
                _flat(v, out, f"{key}.{k}")
    else:
        out[key] = x


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (np.ndarray, np.generic)) or isinstance(b, (np.ndarray, np.generic)):
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()
    if isinstance(a, float) and isinstance(b, float):
        return np.float64(a).tobytes() == np.float64(b).tobytes()
    return bool(a == b)


def _outcome(fn: Callable[[], Any]) -> dict[str, Any]:
    try:
        value = fn()
    except Exception as e:  # noqa: BLE001 - the fault itself is compared
        faults = getattr(e, "faults", None)
        return {"raised": type(e).__name__, "faults": [(tuple(f.loc), f.msg, f.type) for f in faults or []]}
    out: dict[str, Any] = {}
    _flat(value, out)
    return out


def calls(core: Any, scene: Scene) -> Iterator[tuple[str, Callable[[], Any]]]:
    bodies, batches = scene
    for outputs in (("energy",), ("energy", "gradient"), ("energy", "gradient", "hessian")):
        for mode in ("exact", "psd"):
            for active_only in (False, True):
                for layout in ("joints", "bodies"):
                    kw = dict(outputs=outputs, hessian_mode=mode, active_only=active_only, layout=layout)
                    yield f"stateless{kw}", lambda kw=kw: core.evaluate(bodies, batches, **kw)
    yield "threads2", lambda: core.evaluate(bodies, batches, threads=2)
    q2 = bodies.q.copy()
    q2[:, 3:] += 0.05 * np.sin(np.arange(q2[:, 3:].size)).reshape(q2[:, 3:].shape)

    def prepared() -> Any:
        s = core.prepare(bodies, batches)
        out = [s.evaluate(q2, hessian_mode=m) for m in ("exact", "psd")]
        out.append(s.commit(q2))
        out.append(s.coordinates())
        out.append(s.evaluate(bodies.q, layout="bodies"))
        k = min(3, len(batches[0].lower))
        s.update(0, np.arange(k), lower=batches[0].lower[:k] - 0.1, offset=np.full(k, 0.25))
        out.append(s.evaluate(q2))
        out.append(s.coordinates())
        return out

    yield "prepared", prepared


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.same", description=__doc__.split("\n\n")[0])
    ap.add_argument("rev", help="the git revision to compare against (e.g. main)")
    ap.add_argument("--quick", action="store_true", help="scenes up to 100 joints only")
    args = ap.parse_args(argv)
    from jointlimits.service import core as new

    compared, differ = 0, 0
    with tempfile.TemporaryDirectory() as tmp:
        old = import_revision(args.rev, Path(tmp))
        for name, scene in scenes():
            if args.quick and name.split("/")[0].isdigit() and int(name.split("/")[0]) > 100:
                continue
            for (call, f_new), (_, f_old) in zip(calls(new, scene), calls(old, scene)):
                a, b = _outcome(f_new), _outcome(f_old)
                compared += 1
                keys = sorted(set(a) | set(b))
                bad = [k for k in keys if k not in a or k not in b or not _same(a[k], b[k])]
                if bad:
                    differ += 1
                    print(f"DIFFER {name} {call}: {bad[:6]}")
    print(f"{compared} calls compared, {differ} differ")
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
