"""Shared fixtures: the golden cases and normwise error measures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

GOLDEN = json.loads((Path(__file__).parent / "golden_cases.json").read_text())["cases"]


def relerr(got, want, floor: float = 0.0) -> float:
    """Normwise relative error `max|got - want| / max(max|want|, floor)` (0 when both are zero)."""
    got, want = np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape, (got.shape, want.shape)
    scale = max(float(np.max(np.abs(want), initial=0.0)), floor)
    diff = float(np.max(np.abs(got - want), initial=0.0))
    return diff / scale if scale > 0 else diff


@pytest.fixture(params=GOLDEN, ids=[c["name"] for c in GOLDEN])
def golden_case(request):
    return request.param


# ---------------------------------------------------------------- the fast subset
# `pytest -m "not slow"` leaves out the tests marked `slow` where they are: `pytestmark = pytest.mark.slow` at the top
# of a wholly slow module, `@pytest.mark.slow` on a test, each with its reason (live servers in subprocesses, the load
# and fault drills, the Dockerfile's replay, the bench, fuzzers, timers that wait on purpose, property tests over random
# scenes). tests/test_slow_marks.py checks that the tests known slow stay marked and that a test starting a process is.
