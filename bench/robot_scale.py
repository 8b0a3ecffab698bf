"""`python -m bench.robot_scale`: the fixed cost per call, where robots live.

1, 10, 100, 1000 joints, every joint active (`make_scene(n, outside=1.0)`: half #670, half #669):
the core's stateless energy, E+G+H exact and E+G+H psd, and a prepared scene's (`prepare(...)`,
`.evaluate(q)`, a session's evaluation in-process) E+G+H psd; beside them the JAX `jit(vmap)` peer
(same inputs, bench/peer_jax.py) and the Warp CPU peer's energy (bench/peer_warp.py) when importable,
else "not installed". Medians of `--reps` calls, every column's calls alternated (`measure.median_times`:
drift moves them alike), one thread. The last columns are the targets' ratios (issue 28).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

import numpy as np

from bench.measure import median_times
from bench.scenes import make_scene
from jointlimits.service.core import evaluate, prepare

SIZES = (1, 10, 100, 1000)
CORE = (("core E", "e"), ("core EGH", "egh"), ("core EGH psd", "psd"), ("prepared EGH psd", "prep"))
PEERS = (("JAX E", "jax_e"), ("JAX EGH", "jax_egh"), ("Warp E", "warp_e"))


def _peers() -> dict[str, Any]:
    """The importable peers' modules ("jax", "warp"); a missing one is absent."""
    found: dict[str, Any] = {}
    try:
        from bench import peer_jax

        found["jax"] = peer_jax
    except ImportError:
        pass
    try:
        from bench import peer_warp

        found["warp"] = peer_warp
    except ImportError:
        pass
    return found


def calls(n: int, peers: dict[str, Any]) -> dict[str, Callable[[], Any]]:
    """The timed calls on the robot scene of `n` joints, by column key."""
    bodies, batches = make_scene(n, outside=1.0, seed=n % 89)
    batches = [b for b in batches if b.body_ids.shape[0]]  # 1 joint: the #669 batch is empty
    egh = ("energy", "gradient", "hessian")
    scene = prepare(bodies, batches)
    fns: dict[str, Callable[[], Any]] = {
        "e": lambda: evaluate(bodies, batches, outputs=("energy",)),
        "egh": lambda: evaluate(bodies, batches, outputs=egh),
        "psd": lambda: evaluate(bodies, batches, outputs=egh, hessian_mode="psd"),
        "prep": lambda: scene.evaluate(bodies.q, outputs=egh, hessian_mode="psd"),
    }
    if "jax" in peers:
        jp = peers["jax"].JaxPeer(bodies, batches, same_work=True)
        jp("e"), jp("egh")  # compiled outside the timing
        fns["jax_e"] = lambda: jp("e")
        fns["jax_egh"] = lambda: jp("egh")
    if "warp" in peers:
        wpeer = peers["warp"].WarpPeer(bodies, batches)
        fns["warp_e"] = lambda: wpeer("e")
    return fns


def table(sizes: tuple[int, ...] = SIZES, reps: int = 301) -> list[dict[str, Any]]:
    """One row per size: its medians (s) by column key (absent: the peer is not installed)."""
    peers = _peers()
    rows = []
    for n in sizes:
        fns = calls(n, peers)
        times = median_times(fns, reps=reps, warmup=max(1, reps // 20))
        rows.append({"joints": n, **times})
    return rows


def render(rows: list[dict[str, Any]]) -> str:
    """The table: medians in ms, then the targets' ratios (JAX EGH / core EGH, Warp E / core E, prepared / 0.35 ms)."""
    cols = [*CORE, *PEERS]
    head = ["joints", *(name for name, _ in cols), "JAX EGH/core", "Warp E/core", "prepared/0.35ms"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [str(r["joints"])]
        for _, key in cols:
            cells.append(f"{r[key] * 1e3:.3f}" if key in r else "not installed")
        ratio = lambda a, b: f"{r[a] / r[b]:.2f}x" if a in r and b in r else "not installed"  # noqa: E731
        cells += [ratio("jax_egh", "egh"), ratio("warp_e", "e"), f"{r['prep'] / 0.35e-3:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.robot_scale", description=__doc__.split("\n\n")[0])
    ap.add_argument("--joints", type=int, nargs="+", default=list(SIZES), help="scene sizes (default 1 10 100 1000)")
    ap.add_argument("--reps", type=int, default=301, help="timed calls per column (default 301)")
    args = ap.parse_args(argv)
    from jointlimits.service.core.heap import keep_heap

    keep_heap()  # as the service and the bench run
    print(f"robot scale: every joint active, half #670 half #669, one thread, medians of {args.reps} calls (ms)")
    print(render(table(tuple(args.joints), args.reps)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
