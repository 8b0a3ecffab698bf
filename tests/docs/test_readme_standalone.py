"""The README and docs/ stand alone (their links and quoted paths resolve inside the repository) and the CLI speaks
the user's words."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from jointlimits.service import cli

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
DOCS = {p.name: p.read_text() for p in sorted((ROOT / "docs").glob("*.md"))}
DEPLOYMENT = DOCS["deployment.md"]  # the command line's table, moved from the README


def test_no_pointer_outside_the_repository():
    assert "shared/" not in README
    assert [name for name, text in DOCS.items() if "shared/" in text] == []


def test_every_linked_or_quoted_repository_path_exists():
    linked = re.findall(r"\]\(([\w./-]+)\)", README)
    quoted = re.findall(r"`((?:schemas|service|client|bench|tests|deploy)/[\w./-]+\.(?:md|py|json|yaml|png))`", README)
    assert "schemas/CONTRACT.md" in linked and "service/core/CONSTITUTIONS.md" in linked
    missing = [p for p in {*linked, *quoted} if not (ROOT / p).exists()]
    assert missing == []


def test_every_path_the_docs_quote_exists():
    """(Links between pages are mkdocs' to check: tests/docs/test_docs_site.py builds with --strict.)"""
    quoted = {p for text in DOCS.values()
              for p in re.findall(r"`((?:schemas|service|client|bench|tests|deploy)/[\w./-]+\.(?:md|py|json|yaml|png))`", text)}
    pending = {"client/uipc.py"}  # docs/uipc.md's placeholder: the module lands from another branch
    assert len(quoted) > 20
    assert sorted(p for p in quoted - pending if not (ROOT / p).exists()) == []


def test_the_constitutions_summary_covers_both():
    text = (ROOT / "service" / "core" / "CONSTITUTIONS.md").read_text()
    for words in ("#670 AffineBodyRevoluteJointLimit", "#669 AffineBodyPrismaticJointLimit", "#18", "#20",
                  "limit/strength", "(default 1)", "s |x - l|^3", "schemas/CONTRACT.md", "psd", "q_ref"):
        assert words in text, words
    assert "v1.1" in (ROOT / "schemas" / "CONTRACT.md").read_text()


def _error(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as e:
        cli.build_parser().parse_args(["serve", *argv])
    assert e.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("flag", ["--workers", "--backlog", "--max-joints", "--max-body-bytes"])
def test_bad_numbers_name_the_option_not_a_function(flag, capsys):
    err = _error([flag, "foo"], capsys)
    assert f"argument {flag}: must be a positive integer" in err and "'foo'" in err
    assert "_workers" not in err and "_positive_int" not in err and "invalid" not in err


@pytest.mark.parametrize("flag", ["--keep-heap", "--access-log"])
def test_boolean_options_show_their_values(flag, capsys):
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["serve", "--help"])
    assert f"{flag} true|false" in capsys.readouterr().out
    err = _error([flag, "maybe"], capsys)
    assert "must be true or false" in err and "'maybe'" in err
    for word in ("1", "no", "ON", "False"):
        assert isinstance(getattr(cli.build_parser().parse_args(["serve", flag, word]), flag[2:].replace("-", "_")), bool)


def test_every_option_is_in_the_readme_table():
    """Each `--option` of `serve` has its `JOINTLIMITS_<OPTION>` row (the token file shares the token's)."""
    serve = cli.build_parser()._subparsers._group_actions[0].choices["serve"]  # noqa: SLF001
    options = [a.option_strings[0] for a in serve._actions if a.option_strings and a.option_strings[0] != "-h"]  # noqa: SLF001
    rows = set(re.findall(r"`(JOINTLIMITS_[A-Z_]+)`", DEPLOYMENT.split("## The command line", 1)[1].split("\n## ", 1)[0]))
    missing = [o for o in options if "JOINTLIMITS_" + o[2:].upper().replace("-", "_") not in rows]
    assert missing == []


def test_the_console_script_says_it_too():
    out = subprocess.run([sys.executable, "-m", "jointlimits.service.cli", "serve", "--workers", "foo"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "argument --workers: must be a positive integer or 'auto', got 'foo'" in out.stderr
