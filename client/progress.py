"""A tiny stderr progress bar (no dependency): `done / total` joints of a split request."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

ProgressCallback = Callable[[int, int], None]
"""Called with `(joints_done, joints_total)` after each part of a split request."""


class Bar:
    def __init__(self, width: int = 30) -> None:
        self.width = width
        self.t0 = time.perf_counter()

    def __call__(self, done: int, total: int) -> None:
        frac = done / total if total else 1.0
        filled = int(self.width * frac)
        elapsed = time.perf_counter() - self.t0
        sys.stderr.write(f"\r[{'#' * filled}{'.' * (self.width - filled)}] {done}/{total} joints {elapsed:5.1f}s")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def resolve_progress(progress: bool | ProgressCallback | None, n_parts: int) -> ProgressCallback | None:
    """`True`: a stderr bar when the work is split; a callable: itself; else none."""
    if callable(progress):
        return progress
    return Bar() if progress and n_parts > 1 else None
