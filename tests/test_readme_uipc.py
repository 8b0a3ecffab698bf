"""The README's libuipc example runs as pasted and prints what its comments say."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import pytest

pytest.importorskip("uipc")  # the `test` extra installs pyuipc

README = (Path(__file__).resolve().parent.parent / "README.md").read_text()


def example() -> str:
    return README.split("## From a libuipc scene", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]


def test_the_door_hinge_example_prints_its_comments():
    code = example()
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, "README libuipc example", "exec"), {})  # noqa: S102 (our own README)
    said = [m.group(1).strip() for m in re.finditer(r"^print\(.*#\s*(.+?)(?::.*)?$", code, re.M)]
    got = out.getvalue().strip().split("\n")
    assert len(got) == len(said) == 2
    for line, comment in zip(got, said):
        assert comment.startswith(line), (line, comment)
