"""What `layout="bodies"` costs beside the per-joint answer: median time and peak memory, in-process.

    python -m bench.layout_cost [N] [REPS]        (defaults: 100000 joints, 3 repetitions)

The bench's scene (`bench.scenes.make_scene`: half #670, half #669) with 10% and then 100% of the
joints outside their range; E+G+H exact per joint, per joint with `active_only`, and per body.
Peak memory is `bench.measure.peak_memory` (tracemalloc: NumPy's buffers, the result included).
The heap is kept (`keep_heap`), as the service runs.
"""

from __future__ import annotations

import sys

from bench.measure import median_time, peak_memory
from bench.scenes import make_scene
from jointlimits.service.core import evaluate
from jointlimits.service.core.heap import keep_heap


def main(argv: list[str]) -> None:
    n = int(argv[0]) if argv else 100_000
    reps = int(argv[1]) if len(argv) > 1 else 3
    keep_heap()
    for outside in (0.1, 1.0):
        bodies, batches = make_scene(n, outside=outside)
        for name, options in (("joints", {}), ("joints+active_only", {"active_only": True}), ("bodies", {"layout": "bodies"})):
            run = lambda: evaluate(bodies, batches, **options)  # noqa: E731
            t = median_time(run, reps)
            mib = peak_memory(run) / 2**20
            print(f"n={n} outside={outside} {name:20s} {t:.3f} s  {mib:.0f} MiB peak", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
