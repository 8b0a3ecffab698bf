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


def test_the_batches_derivative_chunks_take_the_threads() -> None:
    """A batch of 3000 beside one of 2: one batch after another, each's derivative chunks on both threads;
    bitwise the answers of one thread, both modes."""
    from bench.scenes import make_scene
    from jointlimits.service.core import evaluate, prepare

    bodies, batches = make_scene(3000, outside=1.0, seed=5)
    _, few = make_scene(4, outside=1.0, seed=5)  # bodies 0..3 exist in the large scene too
    scene = [batches[0], few[1]]
    for mode in ("exact", "psd"):
        one = evaluate(bodies, scene, hessian_mode=mode)
        for two in (evaluate(bodies, scene, hessian_mode=mode, threads=2),
                    prepare(bodies, scene, threads=2).evaluate(bodies.q, hessian_mode=mode)):
            for a, b in zip(one.batches, two.batches):
                for f in ("x", "energy", "gradient", "hessian"):
                    assert getattr(a, f).tobytes() == getattr(b, f).tobytes()
