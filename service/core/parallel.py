"""Independent pieces of one evaluation on a few threads: NumPy releases the GIL inside its loops."""

from __future__ import annotations

import contextvars
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from typing import TypeVar

T = TypeVar("T")

_POOLS: dict[int, ThreadPoolExecutor] = {}
_LOCK = threading.Lock()


def _pool(threads: int) -> ThreadPoolExecutor:
    """One long-lived pool per size: starting threads per call costs more than small evaluations."""
    with _LOCK:
        if threads not in _POOLS:
            _POOLS[threads] = ThreadPoolExecutor(threads, thread_name_prefix="jointlimits-core")
        return _POOLS[threads]


def run_all(tasks: Sequence[Callable[[], T]], threads: int) -> list[T]:
    """Each task's result, in order; the first task's exception (in order) is raised once every task has ended
    (a caller never races a task still reading its arrays). Each task runs in a copy of the caller's context,
    so `np.errstate` (a context variable) holds in the workers too."""
    if threads <= 1 or len(tasks) <= 1:
        return [task() for task in tasks]
    pool = _pool(threads)
    futures = [pool.submit(contextvars.copy_context().run, task) for task in tasks]
    wait(futures)
    return [f.result() for f in futures]
