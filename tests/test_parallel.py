"""`parallel.run_all`: results in order, the first exception in order, raised once every task has ended."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from jointlimits.service.core.parallel import Sharing, run_all


def test_results_in_task_order() -> None:
    assert run_all([lambda k=k: k * k for k in range(7)], 2) == [k * k for k in range(7)]


def test_first_exception_in_order_after_every_task_ended() -> None:
    """Task 0 fails at once while task 1 still reads: the caller (a retry, a report) must not run beside it."""
    ended = threading.Event()

    def slow() -> None:
        time.sleep(0.2)
        ended.set()
        raise KeyError("second")

    def fail() -> None:
        raise ValueError("first")

    with pytest.raises(ValueError, match="first"):
        run_all([fail, slow], 2)
    assert ended.is_set()


def test_tasks_keep_the_callers_error_state() -> None:
    with np.errstate(divide="raise"):
        with pytest.raises(FloatingPointError):
            run_all([lambda: None, lambda: np.divide(1.0, np.zeros(1))], 2)


def _shared(work: list[tuple[float, list[float]]], threads: int) -> tuple[list, dict[int, set[int]], dict[int, tuple[float, float]]]:
    """Tasks (one per entry of `work`: a delay, then chunks sleeping the given seconds) through one
    `Sharing`: each task's results, the threads that ran each task's chunks, each task's start and end."""
    share = Sharing(len(work))
    ran: dict[int, set[int]] = {t: set() for t in range(len(work))}
    spans: dict[int, tuple[float, float]] = {}

    def chunk(t: int, s: float) -> float:
        time.sleep(s)
        ran[t].add(threading.get_ident())
        return s

    def task(t: int, delay: float, chunks: list[float]) -> list[float]:
        start = time.monotonic()
        time.sleep(delay)
        out = share.run([lambda s=s: chunk(t, s) for s in chunks])
        spans[t] = (start, time.monotonic())
        return out

    results = run_all([share.task(lambda t=t, w=w: task(t, *w)) for t, w in enumerate(work)], threads)
    return results, ran, spans


def test_shared_chunks_keep_both_threads_busy() -> None:
    """Task 1 ends before task 0 hands its chunks over; its thread waits for them and takes its share."""
    results, ran, _ = _shared([(0.05, [0.02] * 10), (0.0, [])], 2)
    assert results == [[0.02] * 10, []]
    assert len(ran[0]) == 2  # task 0's chunks ran on both threads


def test_shared_chunks_leave_a_thread_to_a_waiting_task() -> None:
    """Three tasks on two threads: the thread whose task ends first starts the third task rather than
    waiting for the first one's chunks; every task ends."""
    done: list = []
    runner = threading.Thread(target=lambda: done.append(_shared([(0.05, [0.02] * 5), (0.0, []), (0.0, [0.01] * 2)], 2)), daemon=True)
    runner.start()
    runner.join(10.0)
    assert done, "the tasks did not end"
    results, _, spans = done[0]
    assert results == [[0.02] * 5, [], [0.01] * 2]
    assert spans[2][0] < spans[0][1]  # the third task started before the first ended


def test_shared_chunks_raise_the_first_error_in_order() -> None:
    share = Sharing(1)
    order: list[int] = []

    def chunk(k: int) -> int:
        order.append(k)
        if k in (1, 3):
            raise ValueError(f"chunk {k}")
        return k

    with pytest.raises(ValueError, match="chunk 1"):
        run_all([share.task(lambda: share.run([lambda k=k: chunk(k) for k in range(5)])), lambda: None], 2)
    assert sorted(order) == list(range(5))  # every chunk ran before the error was raised
