"""The README's SDK quick start runs as pasted and gives the documented numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np

README = (Path(__file__).resolve().parent.parent / "README.md").read_text()


def test_quick_start_runs_as_pasted():
    block = README.split("## Python SDK quick start", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    scope: dict = {}
    exec(compile(block, "README quick start", "exec"), scope)  # noqa: S102 (our own README)
    r, j = scope["r"], scope["j"]
    assert abs(r.x[j] - 0.7) < 1e-15 and r.energy[j] == 0.7999999999999995
    H = r.hessian[j]
    assert H.shape == (24, 24) and np.array_equal(H, H.T) and np.isfinite(H).all()


def test_binary_example_bytes_are_documented():
    assert "81 a1 78  83 a5 \"dtype\" a3 \"<f8\"  a5 \"shape\" 91 02  a4 \"data\" c4 10" in README
