"""The fenced examples of the README and of docs/: found, and run as a reader would run them.

A block's info string names its language; `python` and `bash` blocks are examples and run,
every other (`json`, `text`, none) is output or a transcript and does not. A block that cannot run
carries, on the line right above its fence, `<!-- docs-test: skip (why) -->`: an HTML comment,
so the rendered page does not show it, and the test reports the reason.

Python blocks of one page run in order in one namespace, as a reader pastes them into one
session; bash blocks run each in `bash -euo pipefail` from the repository's root. Both see a live
server where the page says `127.0.0.1:8000` or `localhost:8000` (the address is rewritten to the
test server's), and `.venv/bin/` is this interpreter's directory.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RUN = ("python", "bash")
SKIP = re.compile(r"^<!-- docs-test: skip \((?P<why>.+)\) -->$")
FENCE = re.compile(r"^(?P<indent> *)(?P<fence>```+|~~~+)(?P<info>[^`\n]*)$")

# Blocks that carry no marker because their place is fixed: the README opens with its two set-up commands
# (tests/docs/test_readme.py), and CI runs the second one verbatim through .ci/run.
COVERED_ELSEWHERE = {
    ("README.md", 0): "the set-up commands: the first serves until stopped; CI runs the second through .ci/run "
                      "(tests/docs/test_readme.py keeps them identical)",
}


@dataclass(frozen=True)
class Block:
    page: str
    line: int  # 1-based, the opening fence
    lang: str
    code: str
    skip: str | None  # why it does not run

    @property
    def id(self) -> str:
        return f"{self.page}:{self.line}"


def blocks(path: Path) -> list[Block]:
    """Every fenced block of a page, in order."""
    lines = path.read_text().splitlines()
    page = str(path.relative_to(ROOT))
    found: list[Block] = []
    k = 0
    while k < len(lines):
        m = FENCE.match(lines[k])
        if not m:
            k += 1
            continue
        fence, indent = m["fence"], len(m["indent"])
        end = k + 1
        while end < len(lines) and not lines[end].strip().startswith(fence):
            end += 1
        code = "\n".join(line[indent:] for line in lines[k + 1:end]) + "\n"
        lang = m["info"].strip().split(" ")[0] if m["info"].strip() else ""
        above = SKIP.match(lines[k - 1].strip()) if k else None
        skip = above["why"] if above else None
        if skip is None and lang in RUN:
            skip = COVERED_ELSEWHERE.get((page, sum(b.lang in RUN for b in found)))
        found.append(Block(page, k + 1, lang, code, skip))
        k = end + 1
    return found


def examples() -> list[Block]:
    return [b for p in PAGES for b in blocks(p) if b.lang in RUN]


def live_text(code: str, url: str, python: str) -> str:
    """The block as run: the documented address is the test server's, `.venv/bin/` this interpreter's directory."""
    host = url.removeprefix("http://")
    code = re.sub(r"(?:http://)?(?:127\.0\.0\.1|localhost):8000", lambda m: ("http://" if m[0].startswith("http") else "") + host, code)
    return code.replace(".venv/bin/", str(Path(python).parent) + "/")
