"""`jointlimits.service.core.heap.keep_heap`: freed arrays stay in the heap, so a repeated evaluation page-faults nothing."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # counts page faults of repeated evaluations: a performance measurement

SCRIPT = """
import resource, sys
import numpy as np
sys.path.insert(0, {root!r})
from jointlimits.service.core import Bodies, Joints, evaluate
from jointlimits.service.core.heap import keep_heap
applied = keep_heap() if sys.argv[1] == "keep" else None
rng = np.random.default_rng(0)
n, b = 20000, 10002
eye = np.tile(np.r_[0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1.0], (b, 1))
q = eye + 0.01 * rng.normal(size=(b, 12))
ids = np.stack([np.arange(n) % b, (np.arange(n) + 1) % b], axis=1)
edges = np.stack([np.zeros((n, 3)), rng.normal(size=(n, 3))], axis=1)
joints = [Joints(uid, base, ids, edges, -0.01 * np.ones(n), 0.01 * np.ones(n), np.ones(n)) for uid, base in ((670, 18), (669, 20))]
bodies = Bodies(q, eye, eye)
evaluate(bodies, joints, outputs=("energy",))
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(3):
    evaluate(bodies, joints, outputs=("energy",))
print(applied, (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 3)
"""


def _faults(mode: str) -> tuple[str, float]:
    from pathlib import Path

    root = str(Path(__file__).resolve().parents[2])
    out = subprocess.run([sys.executable, "-c", SCRIPT.format(root=root), mode], capture_output=True, text=True, check=True)
    applied, faults = out.stdout.split()
    return applied, float(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_keep_heap_removes_the_page_faults_of_a_repeated_evaluation() -> None:
    applied, kept = _faults("keep")
    _, default = _faults("default")
    assert applied == "True"
    # 2e4 joints allocate a few MB per array: with glibc's defaults each is a fresh mapping, faulted in again.
    assert default > 500, default
    assert kept < 0.05 * default, (kept, default)
