"""`parallel.run_all`: results in order, the first exception in order, raised once every task has ended."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from jointlimits.service.core.parallel import run_all


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
