"""Independent pieces of one evaluation on a few threads: NumPy releases the GIL inside its loops."""

from __future__ import annotations

import contextvars
import threading
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, TypeVar

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
    """Each task's result, in order; the first task's exception (in order) is raised, once every task has
    ended (a caller that retries or reports then never races a task still reading its arrays).

    Every task runs in a copy of the caller's context, so `np.errstate` (a context
    variable) holds in the workers as it does in the caller.
    """
    if threads <= 1 or len(tasks) <= 1:
        return [task() for task in tasks]
    pool = _pool(threads)
    futures = [pool.submit(contextvars.copy_context().run, task) for task in tasks]
    wait(futures)
    return [f.result() for f in futures]


@dataclass
class _Chunks:
    """One `Sharing.run` call's chunks: those not yet taken, and what each taken one gave."""

    chunks: Sequence[Callable[[], Any]]
    waiting: deque[int]  # positions not yet taken
    results: list[Any]
    errors: list[BaseException | None]
    running: int  # taken and not yet ended


class Sharing:
    """The chunks of work of the tasks of one `run_all`, shared between those tasks' threads.

    A task hands its chunks to `run`, takes them in order while it has any, then takes the other
    tasks' (from their ends), and returns once its own have all ended, whoever ran them. A task
    that ends (`task`) takes the others' chunks, and while every task has a thread, waits for those
    still going to hand theirs over: a large batch beside a small one (or two of unequal work) keeps
    both threads busy to the end. With a task still waiting for a thread, an ended task's thread goes
    back to the pool instead, to start it. Nobody waits for a chunk no thread has taken, nor for a task
    that has no thread: every wait ends.
    """

    def __init__(self, tasks: int) -> None:
        self._cond = threading.Condition()
        self._open: list[_Chunks] = []  # the `run` calls still going
        self._unstarted = tasks  # the tasks (`task`) not started yet
        self._going = 0  # started, not ended

    def task(self, fn: Callable[[], T]) -> Callable[[], T]:
        """`fn`, then on the same thread the chunks of the other tasks, as long as some may come."""

        def run() -> T:
            with self._cond:
                self._unstarted -= 1
                self._going += 1
            try:
                return fn()
            finally:
                with self._cond:
                    self._going -= 1
                    self._cond.notify_all()
                self._help(None)

        return run

    def run(self, chunks: Sequence[Callable[[], T]]) -> list[T]:
        """Each chunk's result, in order; the first chunk's exception (in order) once every chunk has ended."""
        mine = _Chunks(chunks, deque(range(len(chunks))), [None] * len(chunks), [None] * len(chunks), 0)
        with self._cond:
            self._open.append(mine)
            self._cond.notify_all()
        self._help(mine)
        with self._cond:
            self._open.remove(mine)
        error = next((e for e in mine.errors if e is not None), None)
        if error is not None:
            raise error
        return mine.results

    def _help(self, mine: _Chunks | None) -> None:
        """Run waiting chunks, `mine`'s first, then the others' (last first). With `mine`: until all of
        its chunks have ended (waiting for those other threads run); without: until no task is going, or
        none is waiting while a task has no thread yet."""
        while True:
            with self._cond:
                while True:
                    owner = mine if mine is not None and mine.waiting else next((c for c in self._open if c.waiting), None)
                    if owner is not None:
                        i = owner.waiting.popleft() if owner is mine else owner.waiting.pop()
                        owner.running += 1
                        break
                    if mine is not None and mine.running == 0:
                        return
                    if mine is None and (self._going == 0 or self._unstarted > 0):
                        return
                    self._cond.wait()  # the last of `mine` run on other threads, or chunks to come
            try:
                owner.results[i] = owner.chunks[i]()
            except BaseException as e:  # noqa: BLE001 (re-raised by the owner, in order)
                owner.errors[i] = e
            with self._cond:
                owner.running -= 1
                if owner.running == 0 and not owner.waiting:
                    self._cond.notify_all()
