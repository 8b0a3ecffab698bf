"""MkDocs hook, and a Griffe extension for the API reference (mkdocs.yml names both).

The hook: the committed bench plot (bench/results/report.png) joins the site as bench/report.png. The docs
show the committed run's figure itself rather than a copy in docs/ that could drift from it.

The extension (`DocstringMarkdown`): the SDK's docstrings are plain text written for `help()`, rendered by
mkdocstrings as Markdown (mkdocs.yml: `docstring_style: null`). Two of their habits mean something else
in Markdown, so the extension rewrites the docstrings as Griffe loads them, for the site only:

- a doctest example (`>>> ...` lines and their output, up to a blank line) would be a quote three deep,
  its lines run into one paragraph: it becomes a fenced `pycon` code block;
- a line starting with `#` but not `# Title` (`#670 on the revolute joint ...`) would be a heading: its
  `#` is escaped.

Fenced code already in a docstring is left as it is.
"""

from __future__ import annotations

import re
from pathlib import Path

import griffe
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
EXTRA = {"bench/report.png": ROOT / "bench" / "results" / "report.png"}


def on_files(files: Files, config) -> Files:
    for uri, src in EXTRA.items():
        files.append(File.generated(config, uri, abs_src_path=str(src)))
    return files


_FENCE = re.compile(r"(```+|~~~+)")
_HEADING = re.compile(r"#{1,6}(\s|$)")


def docstring_markdown(text: str) -> str:
    """`text` (a docstring) with its doctest examples fenced as `pycon` and its stray leading `#` escaped."""
    lines = text.splitlines()
    out: list[str] = []
    fence: str | None = None
    k = 0
    while k < len(lines):
        line = lines[k]
        body = line.lstrip()
        indent = line[: len(line) - len(body)]
        opening = _FENCE.match(body)
        if fence is not None:
            if opening and opening.group(1).startswith(fence) and not body[len(opening.group(1)):].strip():
                fence = None
        elif opening:
            fence = opening.group(1)
        elif body.startswith(">>>"):
            run = []
            while k < len(lines) and lines[k].strip():
                run.append(lines[k][len(indent):] if lines[k].startswith(indent) else lines[k].strip())
                k += 1
            if out and out[-1].strip():
                out.append("")
            out += [f"{indent}```pycon", *(indent + r for r in run), f"{indent}```"]
            continue
        elif body.startswith("#") and not _HEADING.match(body):
            line = f"{indent}\\{body}"
        out.append(line)
        k += 1
    return "\n".join(out)


class DocstringMarkdown(griffe.Extension):
    """Rewrites every docstring Griffe loads with `docstring_markdown` (for the API reference)."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = docstring_markdown(obj.docstring.value)
