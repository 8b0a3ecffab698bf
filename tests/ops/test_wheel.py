"""The distribution: one top-level name, `jointlimits`, and the README's example running from the built wheel.

The wheel is built from this tree (`pip wheel --no-deps`), installed without its dependencies into a fresh
venv that borrows the dependencies from this environment's site-packages through a path entry (a `.pth`
line: a path added so is searched, its own `.pth` files, this tree's editable finder among them, are not
run). The example then runs from an empty directory: what it imports comes from the wheel or not at all.
"""

from __future__ import annotations

import re
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # builds the wheel (an isolated build environment), runs the README example from it

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    run = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out),
                          str(ROOT)], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    (whl,) = out.glob("jointlimits-*.whl")
    return whl


def test_the_wheel_installs_one_top_level_name(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top == {"jointlimits"}
    for sub in ("service/app.py", "service/core/prepared.py", "schemas/evaluate.py", "client/sync.py", "client/uipc.py"):
        assert f"jointlimits/{sub}" in names, sub
    # The load and fault drills are a test module (tests/drills.py, `python -m tests.drills`), not the product's.
    assert [n for n in names if "drills" in n or "loadtest" in n] == []
    entry = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("entry_points.txt"))).decode()
    assert "jointlimits = jointlimits.cli:main" in entry


def test_the_readme_example_runs_from_the_wheel(wheel: Path, tmp_path: Path) -> None:
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    with zipfile.ZipFile(wheel) as z:  # a wheel is a zip laid out as site-packages: pip would do this
        z.extractall(site)
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    readme = (ROOT / "README.md").read_text()
    example = readme.split("## Example", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    assert "from jointlimits import" in example
    probe = ("import jointlimits, jointlimits.service.app, jointlimits.schemas\n"
             "print('FROM', jointlimits.__file__)\n"
             "from jointlimits import Client, AsyncClient, LocalClient, Scene, Request, JointBatch\n")
    work = tmp_path / "empty"
    work.mkdir()
    run = subprocess.run([str(python), "-c", probe + example], cwd=work, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert re.search(rf"FROM {re.escape(str(site))}/jointlimits/__init__\.py", run.stdout), run.stdout
    for bare in ("service", "schemas", "client"):  # the wheel adds no generic top-level package
        gone = subprocess.run([str(python), "-c", f"import {bare}"], cwd=work, capture_output=True, text=True)
        assert gone.returncode != 0, bare


def test_no_module_imports_the_folders_by_their_bare_names() -> None:
    """Every import of the card's folders goes through `jointlimits` (a bare `service.x` beside
    `jointlimits.service.x` would be a second copy of the module, its classes and its state)."""
    bare = re.compile(r"^\s*(from|import) (service|schemas|client)(\.| |$)", re.M)
    offenders = [str(p.relative_to(ROOT)) for folder in ("service", "schemas", "client", "tests", "bench", "jointlimits")
                 for p in (ROOT / folder).rglob("*.py") if bare.search(p.read_text())]
    assert offenders == []
