"""Every fenced python and bash example of the README and docs/ runs (tests/docs_blocks.py says how).

A block that cannot run is marked `<!-- docs-test: skip (why) -->`; those are listed, each with its
reason, by `test_every_skipped_block_says_why`.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections import defaultdict

import pytest

from tests.docs_blocks import PAGES, ROOT, RUN, Block, blocks, examples, live_text
from tests.http.test_contract_live import live  # noqa: F401 (fixture)

BY_PAGE: dict[str, list[Block]] = defaultdict(list)
for _b in examples():
    BY_PAGE[_b.page].append(_b)
PYTHON_PAGES = sorted(p for p, bs in BY_PAGE.items() if any(b.lang == "python" and not b.skip for b in bs))
BASH = [b for b in examples() if b.lang == "bash" and not b.skip]


def test_the_pages_have_examples_and_the_readme_one_runs():
    assert "README.md" in PYTHON_PAGES and "docs/sessions.md" in PYTHON_PAGES
    assert len(BASH) >= 3


def test_every_skipped_block_says_why():
    skipped = [b for b in examples() if b.skip]
    assert all(len(b.skip) > 20 for b in skipped), [b.id for b in skipped if len(b.skip) <= 20]
    # A marker must sit right above a runnable block: one above anything else would silence nothing.
    for page in PAGES:
        lines = page.read_text().splitlines()
        marked = {k + 2 for k, line in enumerate(lines) if line.strip().startswith("<!-- docs-test: skip (")}
        fences = {b.line for b in blocks(page) if b.lang in RUN}
        assert marked <= fences, (page.name, sorted(marked - fences))


@pytest.mark.parametrize("page", PYTHON_PAGES)
def test_python_blocks_run(page, live, capsys):
    scope: dict = {"__name__": "__docs__"}
    for b in BY_PAGE[page]:
        if b.lang != "python" or b.skip:
            continue
        code = compile(live_text(b.code, live, sys.executable), b.id, "exec")
        exec(code, scope)  # noqa: S102 (our own documentation)


@pytest.mark.parametrize("block", BASH, ids=[b.id for b in BASH])
def test_bash_blocks_run(block, live):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    out = subprocess.run(["bash", "-euo", "pipefail", "-c", live_text(block.code, live, sys.executable)],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, (block.id, out.stdout[-2000:], out.stderr[-2000:])
    assert out.stdout.strip(), f"{block.id} printed nothing"


def test_the_sdks_docstring_examples_run_as_written(monkeypatch):
    """Every `>>>` example of the SDK's docstrings (`help()` and the API reference show them) runs in a namespace of
    its own, as a reader pastes it, from the repository's root. Before, `Client.evaluate`'s and `Scene`'s used
    `turned` and `client`, `Robot`'s `q`, and `Scene`'s `l0, l1, r0, r1`, none of them defined."""
    import doctest
    import importlib
    import warnings

    monkeypatch.chdir(ROOT)
    ran, failed = [], []
    for path in sorted((ROOT / "client").glob("*.py")):
        module = importlib.import_module(f"jointlimits.client.{path.stem}")
        for test in doctest.DocTestFinder().find(module, globs={}):  # globs={}: none of the module's names
            if test.examples and test.name.startswith(module.__name__):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)  # the test robot's mimic joint, as documented
                    result = doctest.DocTestRunner().run(test, out=lambda text: failed.append(text))
                ran.append((test.name, result.attempted))
    assert not failed, "\n".join(failed)
    assert {name for name, _ in ran} >= {"jointlimits.client.sync.Client.evaluate", "jointlimits.client.scene.Scene",
                                         "jointlimits.client.robot.Robot"}, ran
