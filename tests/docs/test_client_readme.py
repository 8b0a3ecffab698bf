"""The SDK quick start (docs/sdk.md, moved from the README) runs as pasted and prints what its comments say."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import EXAMPLE_RTOL, same_numbers

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "docs" / "sdk.md").read_text()
HTTP_API = (ROOT / "docs" / "http-api.md").read_text()


def quick_start() -> str:
    return README.split("## Python SDK quick start", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]


def test_quick_start_runs_as_pasted():
    scope: dict = {}
    exec(compile(quick_start(), "README quick start", "exec"), scope)  # noqa: S102 (our own README)
    r = scope["r"]
    # This machine's last bits are 0.7 and 0.7999999999999995; another CPU's arctan2 may move them (EXAMPLE_RTOL).
    assert r.x == pytest.approx(0.7, rel=EXAMPLE_RTOL) and r.energy == pytest.approx(0.7999999999999995, rel=EXAMPLE_RTOL)
    H = r.hessian
    assert H.shape == (24, 24) and np.array_equal(H, H.T) and np.isfinite(H).all()


def test_quick_start_comments_show_the_values_printed():
    """Each bare expression line followed by `# <value>` prints that value (its repr, up to the colon; the floats
    up to another CPU's last bits, `same_numbers`)."""
    lines = quick_start().splitlines()
    scope: dict = {}
    checked = 0
    for k, line in enumerate(lines):
        exec(compile(line, "README quick start", "exec"), scope)  # noqa: S102
        m = re.fullmatch(r"(r\.[\w., ]+?)\s+# (.+)", line)
        if m:
            shown = m.group(2).split(":", 1)[0]
            printed = repr(eval(m.group(1), scope))  # noqa: S307
            assert same_numbers(printed, shown), (line, printed)
            checked += 1
    assert checked == 2


def test_quick_start_comment_points_at_the_request_options():
    """`outputs`, `hessian_mode`, `active_only` are `scene.request()` arguments, not `evaluate`'s."""
    call = next(line for line in quick_start().splitlines() if "client.evaluate(" in line)
    assert "scene.request(outputs=" in call and "evaluate(req, hessian_mode" not in call


def test_binary_example_bytes_are_documented():
    assert "81 a1 78  83 a5 \"dtype\" a3 \"<f8\"  a5 \"shape\" 91 02  a4 \"data\" c4 10" in HTTP_API
