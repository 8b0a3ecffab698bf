"""The README's two set-up commands stay true: CI runs the second one verbatim."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = text.split("```bash\n", 1)[1].split("```", 1)[0]
    return [line for line in block.splitlines() if line.strip()]


def test_readme_starts_with_two_commands():
    assert len(readme_commands()) == 2


def test_ci_runs_the_readme_test_command():
    ci_lines = (ROOT / ".ci" / "run").read_text().splitlines()
    assert readme_commands()[1] in ci_lines


def test_readme_fits_on_a_few_screens_with_the_conventions_on_the_first():
    text = (ROOT / "README.md").read_text()
    lines = text.splitlines()
    assert len(lines) <= 200
    first_screen = "\n".join(lines[:60])
    for words in ("[p, A row 0, A row 1, A row 2]", "**world** coordinates at `q_ref`", "`local_edges`",
                  "sign of `x`", "`coordinate = x + offset`", "`exact` and `psd`"):
        assert words in first_screen, words


def test_readme_example_is_a_newton_solve_then_a_session_loop():
    """The one example (run by tests/docs/test_docs_examples.py): layout="bodies" with scipy.sparse, then a commit per step."""
    text = (ROOT / "README.md").read_text()
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    assert 30 <= len(code.splitlines()) <= 50
    for words in ("Scene()", 'layout="bodies"', "from scipy.sparse", ".assembled.matrix()", ".session(", ".commit("):
        assert words in code, words
