"""The settings table (`Settings`) is the one source of the flags, the environment names and the defaults:
the CLI's flags, the workers' environment and docs/deployment.md's table all agree with it."""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path

import pytest

from jointlimits.service import cli
from jointlimits.service.settings import TABLE, Settings

ROOT = Path(__file__).resolve().parents[2]
COMMAND_LINE = (ROOT / "docs" / "deployment.md").read_text().split("## The command line", 1)[1].split("\n## ", 1)[0]
FLAGS = [s for s in TABLE if s.flag]


@pytest.fixture(autouse=True)
def no_settings_in_the_environment(monkeypatch):
    for name in [n for n in os.environ if n.startswith("JOINTLIMITS_")]:
        monkeypatch.delenv(name)


def _shown(default: object) -> str:
    """A default as the docs' table writes it."""
    if default is None:
        return "unset"
    if default == "":
        return "empty"
    if isinstance(default, bool):
        return f"`{str(default).lower()}`"
    return f"`{default:g}`" if isinstance(default, float) else f"`{default}`"


def test_the_docs_table_has_every_setting_with_its_default():
    rows = {}
    for line in COMMAND_LINE.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        for name in re.findall(r"`(JOINTLIMITS_[A-Z_]+)`", cells[0]) if len(cells) == 3 else []:
            rows[name] = cells[1]
    for s in TABLE:
        assert s.env in rows, s.env
        assert rows[s.env].startswith(_shown(s.default)), (s.env, rows[s.env])


def test_the_docs_usage_lists_every_flag():
    usage = COMMAND_LINE.split("```text", 1)[1].split("```", 1)[0]
    assert [s.name for s in FLAGS if f"[--{s.name.replace('_', '-')} " not in usage] == []


def test_each_setting_is_a_flag_then_a_variable_then_its_default(monkeypatch):
    defaults = cli.build_parser().parse_args(["serve"])
    assert all(getattr(defaults, s.name) == s.default for s in FLAGS)
    assert Settings() == Settings(**{s.name: s.default for s in TABLE})
    texts = {"keep_heap": ("off", "on")}  # (variable, flag); a number for the others
    expected = {"keep_heap": (False, True, False), "cors_origins": ("5", "1", ("5",))}  # (variable, flag, Settings())
    for s in FLAGS:
        monkeypatch.setenv(s.env, texts.get(s.name, ("5", "1"))[0])
    from_env = cli.build_parser().parse_args(["serve"])
    argv = [t for s in FLAGS for t in (f"--{s.name.replace('_', '-')}", texts.get(s.name, ("5", "1"))[1])]
    from_flags = cli.build_parser().parse_args(["serve", *argv])
    for s in FLAGS:
        seen = (getattr(from_env, s.name), getattr(from_flags, s.name), getattr(Settings(), s.name))
        assert seen == expected.get(s.name, (5, 1, 5)), s.name


def test_the_workers_read_back_what_the_cli_hands_them(monkeypatch):
    given = Settings(max_joints=7, request_timeout=2.5, cors_origins=("https://a.example", "https://b.example"),
                     token="s3cret", keep_heap=False)
    for name, text in given.environ().items():
        monkeypatch.setenv(name, text)
    assert Settings() == given


def test_a_bad_variable_names_itself_outside_the_cli(monkeypatch):
    monkeypatch.setenv("JOINTLIMITS_MAX_JOINTS", "-1")
    with pytest.raises(ValueError, match="JOINTLIMITS_MAX_JOINTS: must be a positive integer, got '-1'"):
        Settings()


def test_every_duration_of_the_settings_table_is_a_number_of_seconds():
    """docs/deployment.md's table gives each timeout and delay in seconds: a negative or NaN one, by flag or by
    variable, is refused at start (`jointlimits serve: error: ...`), never taken (NaN crashed the CLI with a
    traceback; a negative idle time closed every session at once)."""
    rows = [r for r in (*cli.FIRST, *TABLE, *cli.LAST) if isinstance(r.default, float)]
    assert {"session_idle_seconds", "graceful_timeout", "keepalive_timeout", "request_timeout"} <= {r.name for r in rows}
    for row in rows:
        for text in ("-1", "nan"):
            with pytest.raises((ValueError, argparse.ArgumentTypeError)):
                row.parse(text)
