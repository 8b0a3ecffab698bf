"""The documentation site builds with `mkdocs build --strict`: no broken link or anchor, no page outside the nav,
every mkdocstrings reference resolved (mkdocs.yml's `validation` turns each into a warning, --strict into a failure)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

pytest.importorskip("mkdocs", reason="the `test` extra installs mkdocs, mkdocs-material and mkdocstrings")


def test_mkdocs_build_strict(tmp_path):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-4000:]
    site = tmp_path / "site"
    # The API reference was generated from the docstrings, and the committed bench run is in the site.
    api = (site / "api" / "index.html").read_text()
    for name in ("jointlimits.client.sync.Client", "jointlimits.client.aio.AsyncClient", "jointlimits.client.local.LocalClient", "jointlimits.client.scene.Scene",
                 "jointlimits.client.model.Evaluation", "jointlimits.client.errors.ServiceError", "jointlimits.client.session.SessionClosed",
                 "jointlimits.client.session_sync.Session"):
        assert f'id="{name}"' in api, name
    assert (site / "bench" / "report.png").read_bytes() == (ROOT / "bench" / "results" / "report.png").read_bytes()
    # The report page is the committed report itself: its first target's measured ratio is on it.
    first = re.search(r"^\| 1\. [^|]*\| ([0-9.]+x) \|", (ROOT / "bench" / "results" / "report.md").read_text(), re.M)
    assert first is not None and first.group(1) in (site / "bench-report" / "index.html").read_text()


def test_every_page_is_in_the_nav():
    """Also what --strict checks (validation.omitted_files); said here in the test's words."""
    import yaml

    def pages(nav):
        for item in nav:
            for v in item.values():
                yield from (pages(v) if isinstance(v, list) else [v])

    conf = yaml.safe_load((ROOT / "mkdocs.yml").read_text().replace("!!python", "#"))
    listed = set(pages(conf["nav"]))
    on_disk = {p.name for p in (ROOT / "docs").glob("*.md")}
    assert listed == on_disk


def _rounds_to(quoted: str, figures: list[float]) -> bool:
    """`quoted` (as the docs print it) is one of `figures` rounded to the digits shown (units may differ: ms and s)."""
    mant = re.sub(r"e.*", "", quoted)
    sig = len(mant.replace(".", "").lstrip("0"))
    want = float(quoted)
    for f in figures:
        if f == 0:
            continue
        for scale in (1, 1e3, 1e-3, 100):
            if float(f"{f * scale:.{sig - 1}e}") == float(f"{want:.{sig - 1}e}"):
                return True
    return False


@pytest.mark.parametrize("table, report", [("| target | measured | status |", "report.md"),
                                           ("| session `evaluate`", "sessions.md")])
def test_the_performance_figures_are_the_committed_runs(table, report):
    """docs/performance.md's target tables quote bench/results/report.md and sessions.md (the committed runs)."""
    page = (ROOT / "docs" / "performance.md").read_text()
    figures = [float(n) for n in re.findall(r"\d+\.?\d*(?:e[-+]?\d+)?", (ROOT / "bench" / "results" / report).read_text())]
    start = page.index(table)
    rows = [line for line in page[start:].split("\n\n", 1)[0].splitlines() if line.startswith("| ") and "---" not in line]
    rows = [r for r in rows if not r.startswith("| target |")]
    assert rows
    for row in rows:
        measured = re.split(r" \| ", row.strip("| "))[1]
        quoted = re.findall(r"\d+\.?\d*(?:e[-+]?\d+)?", measured)
        assert quoted, row
        assert [q for q in quoted if not _rounds_to(q, figures)] == [], row
