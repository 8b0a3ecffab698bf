"""The libuipc page's example (docs/uipc.md) runs as pasted and prints what its comments say."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import pytest

pytest.importorskip("uipc")  # the `test` extra installs pyuipc

PAGE = (Path(__file__).resolve().parents[2] / "docs" / "uipc.md").read_text()


def example() -> str:
    return PAGE.split("```python\n", 1)[1].split("```", 1)[0]


def test_the_door_hinge_example_prints_its_comments():
    code = example()
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, "docs/uipc.md example", "exec"), {})  # noqa: S102 (our own README)
    said = [m.group(1).strip() for m in re.finditer(r"^print\(.*#\s*(.+?)(?::.*)?$", code, re.M)]
    got = out.getvalue().strip().split("\n")
    assert len(got) == len(said) == 2
    for line, comment in zip(got, said):
        assert comment.startswith(line), (line, comment)
