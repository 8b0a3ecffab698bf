"""Independent pieces of one evaluation on a few threads: NumPy releases the GIL inside its loops."""

from __future__ import annotations

import contextvars
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")


def run_all(tasks: Sequence[Callable[[], T]], threads: int) -> list[T]:
    """Each task's result, in order; the first task's exception (in order) is raised.

    Every task runs in a copy of the caller's context, so `np.errstate` (a context
    variable) holds in the workers as it does in the caller.
    """
    if threads <= 1 or len(tasks) <= 1:
        return [task() for task in tasks]
    with ThreadPoolExecutor(min(threads, len(tasks))) as pool:
        futures = [pool.submit(contextvars.copy_context().run, task) for task in tasks]
        return [f.result() for f in futures]
