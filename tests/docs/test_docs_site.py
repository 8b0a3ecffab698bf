"""The documentation site builds with `mkdocs build --strict`: no broken link or anchor, no page outside the nav,
every mkdocstrings reference resolved (mkdocs.yml's `validation` turns each into a warning, --strict into a failure);
and the built pages render as a reader expects: one <h1> each, no list run into a paragraph, the API reference's
docstring examples as code blocks (issue 27)."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

pytest.importorskip("mkdocs", reason="the `test` extra installs mkdocs, mkdocs-material and mkdocstrings")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The site, built once for this module's tests: (mkdocs' exit status and stderr, the site's directory)."""
    site = tmp_path_factory.mktemp("docs") / "site"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    return out, site


@pytest.fixture(scope="module")
def site(built):
    out, site = built
    assert out.returncode == 0, out.stderr[-4000:]
    return site


def test_mkdocs_build_strict(built):
    out, site = built
    assert out.returncode == 0, out.stderr[-4000:]
    # The API reference was generated from the docstrings, and the committed bench run is in the site.
    api = (site / "api" / "index.html").read_text()
    for name in ("jointlimits.client.sync.Client", "jointlimits.client.aio.AsyncClient", "jointlimits.client.local.LocalClient", "jointlimits.client.scene.Scene",
                 "jointlimits.client.model.Evaluation", "jointlimits.client.errors.ServiceError", "jointlimits.client.session.SessionClosed",
                 "jointlimits.client.sync.Session"):
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


class _Page(HTMLParser):
    """What a reader sees of a built page's structure: its <h1> headings, the class of every heading, the text
    of every <p> (its inline code masked) and <pre>, the deepest nesting of <blockquote>, and any text with a
    doctest prompt (`>>>`) outside a <pre>."""

    def __init__(self, html: str):
        super().__init__(convert_charrefs=True)
        self.h1: list[str] = []
        self.headings: list[tuple[str, str]] = []  # (tag, class)
        self.pres: list[str] = []
        self.paragraphs: list[str] = []
        self.quote_depth = self.deepest_quote = 0
        self.prompts_outside_pre: list[str] = []
        self._in_h1 = self._in_pre = self._in_p = self._in_code = 0
        self.feed(html)
        self.close()

    def handle_starttag(self, tag, attrs):
        if re.fullmatch(r"h[1-6]", tag):
            self.headings.append((tag, dict(attrs).get("class") or ""))
        if tag == "h1":
            self._in_h1 += 1
            self.h1.append("")
        elif tag == "pre":
            self._in_pre += 1
            self.pres.append("")
        elif tag == "p":
            self._in_p += 1
            self.paragraphs.append("")
        elif tag == "code":
            self._in_code += 1
        elif tag == "blockquote":
            self.quote_depth += 1
            self.deepest_quote = max(self.deepest_quote, self.quote_depth)

    def handle_endtag(self, tag):
        if tag == "h1":
            self._in_h1 -= 1
        elif tag == "pre":
            self._in_pre -= 1
        elif tag == "p":
            self._in_p -= 1
        elif tag == "code":
            self._in_code -= 1
        elif tag == "blockquote":
            self.quote_depth -= 1

    def handle_data(self, data):
        if self._in_h1:
            self.h1[-1] += data
        if self._in_p:
            self.paragraphs[-1] += re.sub(r"\S", "c", data) if self._in_code else data
        if self._in_pre:
            self.pres[-1] += data
        elif ">>>" in data:
            self.prompts_outside_pre.append(data.strip()[:120])


def _pages(site: Path) -> dict[str, Path]:
    """Every page of the built site, by its directory ("." the home page)."""
    return {str(p.parent.relative_to(site)): p for p in site.rglob("index.html")}


def test_every_page_has_one_h1(site):
    """A page's title is its only <h1>. Python-Markdown reads any line starting with `#` as a heading (no space
    needed), so a wrapped line such as "half\n#670 half #669" became a second title on the performance page."""
    pages = _pages(site)
    assert len(pages) >= 10 and "performance" in pages and "api" in pages
    many = {name: _Page(p.read_text()).h1 for name, p in pages.items()}
    assert {name: h1 for name, h1 in many.items() if len(h1) != 1} == {}


def test_no_list_item_runs_into_a_paragraph(site):
    """Python-Markdown nests a list by 4 spaces, and a list item right below a paragraph's last line (no blank
    line) continues that paragraph: the performance page's "What changed" items ran into one paragraph as
    "... of bare GEMMs). - A revolute joint ... - Every pass ...". No paragraph of a page has a line starting
    with a list marker (outside inline code, where `x = (a - b)\n+ c` is a formula)."""
    run_in = {}
    for name, path in _pages(site).items():
        found = [line.strip()[:60] for par in _Page(path.read_text()).paragraphs for line in par.splitlines()[1:]
                 if re.match(r"\s*[-*+] \S", line)]
        if found:
            run_in[name] = found
    assert run_in == {}


def _markdown_sources() -> list[Path]:
    """The pages and the committed reports they include (docs/bench-*.md: `--8<-- "bench/results/...md"`)."""
    pages = sorted((ROOT / "docs").glob("*.md"))
    included = [ROOT / inc for page in pages for inc in re.findall(r'^--8<-- "([^"]+)"$', page.read_text(), re.M)]
    return [*pages, *included]


def test_no_line_of_prose_starts_with_a_hash():
    """The same trap at its source: outside fenced code, a line starting with `#` is a heading (`# Title`, one to
    six `#` then a space); a wrapped line starting with `#670` is one too, or a heading in waiting inside a list."""
    bad = []
    for path in _markdown_sources():
        fence = None
        for n, line in enumerate(path.read_text().splitlines(), 1):
            m = re.match(r"\s*(```+|~~~+)", line)
            if m and (fence is None or m.group(1).startswith(fence)):
                fence = None if fence else m.group(1)
                continue
            if fence is None and line.lstrip().startswith("#") and not re.match(r"#{1,6} \S", line):
                bad.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:60]}")
    assert bad == []


def _docstring_examples() -> dict[str, list[str]]:
    """The `>>>` lines of every docstring of the SDK (client/*.py), by module."""
    found: dict[str, list[str]] = {}
    for path in sorted((ROOT / "client").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                doc = ast.get_docstring(node) or ""
                lines = [line.strip() for line in doc.splitlines() if line.strip().startswith(">>>")]
                if lines:
                    found.setdefault(path.name, []).extend(lines)
    return found


def test_the_api_reference_shows_docstring_examples_as_code(site):
    """The docstrings' `>>>` examples are code blocks on the API reference, one line each, prompts kept: not
    paragraphs three blockquotes deep (Markdown reads `>>>` as three nested quotes) with their lines run together."""
    examples = _docstring_examples()
    assert sum(len(v) for v in examples.values()) >= 5, examples
    page = _Page((site / "api" / "index.html").read_text())
    assert page.deepest_quote <= 1
    assert page.prompts_outside_pre == []
    shown = {line.strip() for pre in page.pres for line in pre.splitlines()}
    missing = {name: [x for x in lines if x not in shown] for name, lines in examples.items()}
    assert {name: lines for name, lines in missing.items() if lines} == {}


def test_the_api_reference_has_no_heading_from_docstring_text(site):
    """Its headings are the page's own (docs/api.md) and mkdocstrings' one per object: a docstring whose line starts
    with `#670` (`Scene.add_revolute_limit`'s first) read as a heading in the table of contents before."""
    page = _Page((site / "api" / "index.html").read_text())
    own = [h for h in page.headings if "doc-heading" not in h[1].split()]
    written = re.findall(r"^#{1,6} ", (ROOT / "docs" / "api.md").read_text(), re.M)
    assert len(own) == len(written), own
