"""docs/maintainers.md stays true of the code (issue 28).

- Every path it names exists, and every module of `service/`, `service/http/`, `service/core/`, `schemas/` and
  `client/` is named on it: a module added or removed without the page changing fails here.
- Every `path.py:name` it names (the request's walk, the map) is defined in that module: a top-level function,
  class or constant, or `Class.member`.
- What it says of the structure: who imports whom, the members of the `Constitution` protocol and the fields of
  `Facts`, a UID written in its constitution's module alone, and every module that names a constitution is in
  "Adding a constitution".
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "maintainers.md"
FOLDERS = ("service", "service/http", "service/core", "schemas", "client")
TOP = ("service", "schemas", "client", "tests", "bench", "docs", "jointlimits")


def _text() -> str:
    return PAGE.read_text()


def _spans(text: str) -> list[str]:
    """The inline code spans of the page (outside fenced blocks)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)
    return re.findall(r"`([^`\n]+)`", text)


def _paths(text: str) -> dict[str, list[str]]:
    """Every repository path the page names in a code span (`path` or `path.py:name`), with the names after it."""
    found: dict[str, list[str]] = {}
    for span in _spans(text):
        m = re.fullmatch(r"((?:%s)/[\w./<>-]*)(?::([\w.]+))?" % "|".join(TOP), span)
        if m:
            found.setdefault(m.group(1), [])
            if m.group(2):
                found[m.group(1)].append(m.group(2))
    return found


def _modules() -> list[str]:
    return [f"{d}/{p.name}" for d in FOLDERS for p in sorted((ROOT / d).glob("*.py"))]


def _section(text: str, title: str) -> str:
    start = text.index(f"## {title}")
    end = text.find("\n## ", start + 1)
    return text[start : end if end >= 0 else len(text)]


def test_the_page_is_in_the_nav_and_linked():
    assert "maintainers.md" in (ROOT / "mkdocs.yml").read_text()
    assert "(maintainers.md)" in (ROOT / "docs" / "index.md").read_text()
    assert "(docs/maintainers.md)" in (ROOT / "README.md").read_text()


def test_every_path_named_exists():
    paths = _paths(_text())
    assert len(paths) > 60
    missing = [p for p in paths if "<" not in p and not (ROOT / p).exists()]
    assert missing == []


def test_every_module_is_named():
    """Each module of the five folders is on the page (its map has a row for it), and each folder too."""
    text = _text()
    named = set(_paths(text))
    assert [m for m in _modules() if m not in named] == []
    assert [d for d in FOLDERS if f"`{d}/`" not in text] == []


def _defined(tree: ast.Module) -> dict[str, set[str]]:
    """Top-level names of a module (functions, classes, assignments), each class with its members."""
    out: dict[str, set[str]] = {}

    def targets(node: ast.stmt) -> list[str]:
        if isinstance(node, ast.Assign):
            return [n.id for t in node.targets for n in ast.walk(t) if isinstance(n, ast.Name)]
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            return [node.target.id]
        return []

    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            out[node.name] = set()
        elif isinstance(node, ast.ClassDef):
            members: set[str] = set()
            for sub in node.body:
                if isinstance(sub, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    members.add(sub.name)
                members.update(targets(sub))
            out[node.name] = members
        else:
            for name in targets(node):
                out[name] = set()
    return out


def test_every_function_named_is_in_its_module():
    refs = {p: names for p, names in _paths(_text()).items() if names}
    assert sum(len(v) for v in refs.values()) > 80  # the walk names the functions it goes through
    wrong = []
    for path, names in refs.items():
        defined = _defined(ast.parse((ROOT / path).read_text()))
        for name in names:
            head, _, member = name.partition(".")
            if head not in defined or (member and member not in defined[head]):
                wrong.append(f"{path}:{name}")
    assert wrong == []


def _imports(path: Path) -> set[str]:
    """The `jointlimits.*` modules a file imports, anywhere in it (also inside functions)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return {m for m in out if m.startswith("jointlimits")}


@pytest.mark.parametrize("folder, may_not, except_", [
    ("schemas", ("jointlimits.service", "jointlimits.client"), ()),
    ("service/core", ("jointlimits.service.http", "jointlimits.client", "jointlimits.schemas"), ("jointlimits.schemas.errors",)),
    ("service/http", ("jointlimits.client",), ()),
    ("service", ("jointlimits.client",), ()),
])
def test_who_imports_whom(folder, may_not, except_):
    """The page's "One namespace, three folders": the wire imports neither side, the core not its shell (of the
    wire only the words for a non-finite number, `schemas/errors.py`), the service never the SDK."""
    assert "service/core/errors.py" in _section(_text(), "One namespace")
    bad = {
        f"{folder}/{p.name}": sorted(m for m in _imports(p) if m.startswith(may_not) and m not in except_)
        for p in (ROOT / folder).glob("*.py")
    }
    assert {k: v for k, v in bad.items() if v} == {}


def test_the_protocol_members_and_the_facts_are_listed():
    """"Adding a constitution" lists every member of `Constitution` a new joint type implements, and every fact."""
    defined = _defined(ast.parse((ROOT / "service" / "core" / "constitution.py").read_text()))
    members, facts = defined["Constitution"], defined["Facts"]
    section = _section(_text(), "Adding a constitution")
    assert {"facts", "derivatives", "advance"} <= members and {"uid", "base_uid", "alpha", "telescopes"} <= facts
    assert sorted(m for m in members | facts if f"`{m}`" not in section) == []


UID_NAMES = {"REVOLUTE_LIMIT", "PRISMATIC_LIMIT", "REVOLUTE", "PRISMATIC"}


def _holds_a_uid(path: Path) -> bool:
    """The module's code (not its docstrings) holds the UID 670 or 669."""
    return any(isinstance(n, ast.Constant) and type(n.value) is int and n.value in (669, 670)
               for n in ast.walk(ast.parse(path.read_text())))


def _names_a_constitution(path: Path) -> bool:
    """The module's code holds the UID 670 or 669, or a name standing for one."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Name) and node.id in UID_NAMES:
            return True
        if isinstance(node, ast.alias) and (node.asname or node.name) in UID_NAMES:
            return True
    return _holds_a_uid(path)


def test_a_uid_is_written_in_its_constitution_module_alone():
    """Each constitution in one place: its UIDs appear in the code of its own module only; every other module
    reads the registry, or the SDK's names for the two (read from their facts), and is listed in the how-to."""
    assert [m for m in _modules() if _holds_a_uid(ROOT / m)] == ["service/core/prismatic.py", "service/core/revolute.py"]
    section = _section(_text(), "Adding a constitution")
    knowing = [m for m in _modules() if _names_a_constitution(ROOT / m)]
    assert "client/model.py" in knowing
    assert [m for m in knowing if f"`{m}" not in section] == []


def test_the_middleware_is_named_in_its_order():
    """"Before the route" names the middleware outermost first, as `create_app` stacks it (CORS by its word)."""
    from jointlimits.service.app import create_app
    from jointlimits.service.settings import Settings

    walk = _text().split("**Before the route.**", 1)[1].split("**The route**", 1)[0].split("outermost first", 1)[1]
    named = re.findall(r"`service/[\w/]+\.py:(\w+)`|\b(CORS)\b", walk)
    named = [("CORSMiddleware" if cors else n) for n, cors in named if n != "create_app"]
    app = create_app(Settings(token="t", cors_origins=("https://a.example",)))  # every optional layer on
    assert named == [m.cls.__name__ for m in app.user_middleware]
