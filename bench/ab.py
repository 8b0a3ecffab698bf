"""`python -m bench.ab REV`: the core of this tree against the core of git revision REV, in one process.

On a noisy machine two runs minutes apart differ by more than most changes (the same tree
measured 140 ms, then 200 ms, a minute later on the development VM). Here both trees' `service`
packages are imported side by side (REV's as `_ab_service`, from `git archive`) and their
`evaluate` calls alternate on the same scene and the same heap, so drift hits both alike. Each
pair's order alternates too. Prints, per thread count, the medians, their ratio and in how many
pairs this tree was faster. The packages REV's core imports besides `service` (`schemas`) come
from this tree. `--prepared`: each tree's scene prepared once (outside the timing), then its
`PreparedScene.evaluate(q)` timed, as a session evaluates.
"""

from __future__ import annotations

import argparse
import importlib
import re
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable
from io import BytesIO
from pathlib import Path
from typing import Any

from bench.scenes import make_scene

ALIAS = "_ab_service"
ROOT = Path(__file__).resolve().parents[1]


def import_revision(rev: str, into: Path) -> Any:
    """REV's `service` package, written under `into` and imported as `_ab_service`; its `core` package."""
    archive = subprocess.run(["git", "archive", rev, "service"], cwd=ROOT, capture_output=True, check=True).stdout
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        try:
            tar.extractall(into, filter="data")
        except TypeError:  # Python before 3.11.4: no filters (the archive is this repository's own)
            tar.extractall(into)
    (into / "service").rename(into / ALIAS)
    for path in (into / ALIAS).rglob("*.py"):
        text = path.read_text()
        # REV's own imports of its service package: `jointlimits.service` (since the one namespace) or `service`.
        text = re.sub(r"\bfrom (?:jointlimits\.)?service(\.| import)", rf"from {ALIAS}\1", text)
        text = re.sub(r"\bimport (?:jointlimits\.)?service\.", f"import {ALIAS}.", text)
        path.write_text(text)
    sys.path.insert(0, str(into))
    return importlib.import_module(f"{ALIAS}.core")


def pairs(
    new: Callable[[], Any], old: Callable[[], Any], n: int, clock: Callable[[], float] = time.perf_counter
) -> tuple[list[float], list[float]]:
    """Seconds of `n` alternated calls of each (after one warm-up each) by `clock`; the pair's order alternates."""
    new(), old()
    t_new: list[float] = []
    t_old: list[float] = []
    for i in range(n):
        order = [(new, t_new), (old, t_old)] if i % 2 == 0 else [(old, t_old), (new, t_new)]
        for fn, out in order:
            t = clock()
            fn()
            out.append(clock() - t)
    return t_new, t_old


def medians(t_new: list[float], t_old: list[float]) -> tuple[float, float, int]:
    """The two sides' medians (upper, for an even count) and in how many pairs the first was faster."""
    return sorted(t_new)[len(t_new) // 2], sorted(t_old)[len(t_old) // 2], sum(x < y for x, y in zip(t_new, t_old))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.ab", description=__doc__.split("\n\n")[0])
    ap.add_argument("rev", help="the git revision to compare against (e.g. main, HEAD~1, a commit)")
    ap.add_argument("--joints", type=int, default=100_000, help="joints of the bench scene (default 1e5)")
    ap.add_argument("--outside", type=float, default=1.0, help="fraction of joints outside their range (default 1: all active)")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="core threads, each measured (default 1 2)")
    ap.add_argument("--pairs", type=int, default=21, help="alternated pairs per thread count (default 21)")
    ap.add_argument("--outputs", default="energy,gradient,hessian", help="comma-separated outputs (default all)")
    ap.add_argument("--hessian-mode", default="exact", choices=("exact", "psd"), help="the Hessian's mode (default exact)")
    ap.add_argument("--uids", type=int, nargs="+", default=[670, 669], help="the constitutions' batches kept (default both)")
    ap.add_argument("--prepared", action="store_true",
                    help="time PreparedScene.evaluate(q) of a scene prepared once per tree (a session's evaluation)")
    ap.add_argument("--cpu", action="store_true",
                    help="the calling thread's CPU time (time.thread_time) instead of wall time: on a loaded machine the "
                         "time a call waits for a core does not count (one thread only)")
    args = ap.parse_args(argv)

    from jointlimits.service.core import evaluate, prepare
    from jointlimits.service.core.heap import keep_heap

    keep_heap()  # as the service and the bench run
    outputs = tuple(args.outputs.split(","))
    with tempfile.TemporaryDirectory() as tmp:
        old = import_revision(args.rev, Path(tmp))
        bodies, batches = make_scene(args.joints, args.outside, seed=args.joints % 89)
        scene = (bodies, [b for b in batches if b.constitution_uid in args.uids])
        kw = dict(outputs=outputs, hessian_mode=args.hessian_mode)
        n = sum(b.body_ids.shape[0] for b in scene[1])
        print(f"{n} joints ({', '.join(map(str, args.uids))}), {args.outside:.0%} outside, outputs {','.join(outputs)}, "
              f"{args.hessian_mode}{', prepared' if args.prepared else ''}: this tree against {args.rev}")
        for threads in args.threads:
            if args.prepared:
                new_scene, old_scene = prepare(*scene, threads=threads), old.prepare(*scene, threads=threads)
                new_call = lambda s=new_scene: s.evaluate(scene[0].q, **kw)  # noqa: E731
                old_call = lambda s=old_scene: s.evaluate(scene[0].q, **kw)  # noqa: E731
            else:
                new_call = lambda t=threads: evaluate(*scene, **kw, threads=t)  # noqa: E731
                old_call = lambda t=threads: old.evaluate(*scene, **kw, threads=t)  # noqa: E731
            t_new, t_old = pairs(new_call, old_call, args.pairs, time.thread_time if args.cpu else time.perf_counter)
            a, b, wins = medians(t_new, t_old)
            print(f"threads {threads}: this tree {a * 1e3:.3f} ms{' CPU' if args.cpu else ''}, {args.rev} {b * 1e3:.3f} ms, "
                  f"ratio {a / b:.3f}, this tree faster in {wins} of {args.pairs} pairs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
