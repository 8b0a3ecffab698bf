"""`python -m bench.psd_vs_exact`: E+G+H psd against exact in this tree, every joint active (both constitutions,
then each alone), calls alternated (`bench.ab.pairs`), on 1 and 2 threads: the ratio issue 18 bounds (<= 1.3 at 1e5)."""

from __future__ import annotations

import argparse

from bench.ab import medians, pairs
from bench.scenes import make_scene
from jointlimits.service.core import evaluate
from jointlimits.service.core.heap import keep_heap


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.psd_vs_exact", description=__doc__.split("\n\n")[0])
    ap.add_argument("--joints", type=int, default=100_000, help="joints of the bench scene (default 1e5)")
    ap.add_argument("--pairs", type=int, default=11, help="alternated pairs per line (default 11)")
    args = ap.parse_args(argv)
    keep_heap()
    bodies, batches = make_scene(args.joints, 1.0, seed=args.joints % 89)
    for uids in ((670, 669), (669,), (670,)):
        scene = (bodies, [b for b in batches if b.constitution_uid in uids])
        for threads in (1, 2):
            t_psd, t_exact = pairs(lambda: evaluate(*scene, hessian_mode="psd", threads=threads),  # noqa: B023
                                   lambda: evaluate(*scene, hessian_mode="exact", threads=threads),  # noqa: B023
                                   args.pairs)
            a, b, _ = medians(t_psd, t_exact)
            print(f"{', '.join(map(str, uids))} threads {threads}: psd {a * 1e3:.1f} ms, exact {b * 1e3:.1f} ms, "
                  f"psd/exact {a / b:.3f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
