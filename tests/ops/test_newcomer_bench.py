"""The README's bench commands, run the way a newcomer runs them: a fresh clone, a fresh venv, the `bench` extra only.

Slow for a test (a fresh virtual environment with JAX from pip's cache, ~65 s, then the quick bench,
~95 s), but the README's command runs as written (`python -m bench --quick`, JAX and HTTP included)
rather than trimmed: the import path is exactly the one a newcomer hits. The bench must find its
50-digit reference (mpmath) with the `bench` extra alone, not through `tests/` and the `test` extra.

Two tests, one clone and venv: the install measures nothing, so it runs among the parallel tests of CI's
first pytest run (`-n 2 -m "not serial"`); the quick bench times its peers, so it runs in the second, `serial`
one, in the venv the first left (or builds it, when run alone). They share it through a folder named by this
tree's files, so a changed tree gets a fresh clone and venv; the bench's test removes it when done.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "docs" / "performance.md").read_text()  # the bench commands, moved from the README


def bench_commands() -> list[str]:
    """The shell lines of docs/performance.md's first block, without their comments."""
    block = README.split("# Performance: speed against error", 1)[1].split("```bash\n", 1)[1].split("```", 1)[0]
    return [line.split("  #", 1)[0].strip() for line in block.splitlines() if line.strip()]


def listed_files() -> list[str]:
    """The repository's files as a clone has them (tracked and new, never .venv or caches), relative to ROOT."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT, capture_output=True, check=True,
    ).stdout.decode().split("\0")
    return [rel for rel in listed if rel and ((ROOT / rel).is_symlink() or (ROOT / rel).is_file())]


def fresh_clone(dest: Path) -> Path:
    """A copy of `listed_files()` at `dest`."""
    for rel in listed_files():
        src = ROOT / rel
        if src.is_symlink():  # as git checks it out: a link (jointlimits/service -> ../service)
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            (dest / rel).symlink_to(os.readlink(src))
        elif src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    return dest


def test_readme_bench_block_is_install_then_quick():
    install, quick = bench_commands()
    assert install.startswith(".venv/bin/pip install -e '.[bench]' && ")
    assert quick == ".venv/bin/python -m bench --quick"


def tree_key() -> str:
    """A digest of this tree's files (names, link targets, contents)."""
    h = hashlib.sha256()
    for rel in listed_files():
        src = ROOT / rel
        h.update(rel.encode() + b"\0" + (os.readlink(src).encode() if src.is_symlink() else src.read_bytes()) + b"\0")
    return h.hexdigest()[:16]


def clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}


def run_in(clone: Path, cmd: str, timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, shell=True, cwd=clone, env=clean_env(), capture_output=True, text=True, timeout=timeout)


def bench_clone() -> Path:
    """This tree's clone with the docs' install done in its `.venv` (the first install command alone): built once,
    under a lock (two pytest workers may ask at once), reused while the tree's files are unchanged."""
    prefix = f"jointlimits-newcomer-bench-{hashlib.sha256(str(ROOT).encode()).hexdigest()[:8]}-"
    folder = Path(tempfile.gettempdir()) / (prefix + tree_key())
    for old in folder.parent.glob(prefix + "*"):  # this checkout's earlier trees' (a run that left before the bench)
        if old != folder:
            shutil.rmtree(old, ignore_errors=True)
    folder.mkdir(exist_ok=True)
    clone, ready = folder / "clone", folder / "ready"
    with open(folder / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not ready.exists():
            shutil.rmtree(clone, ignore_errors=True)
            fresh_clone(clone)
            install = bench_commands()[0].split(" && ")[0]
            made = run_in(clone, f"{sys.executable} -m venv .venv && {install}", 900)
            assert made.returncode == 0, made.stderr[-3000:]
            ready.touch()
    return clone


@pytest.mark.slow  # a fresh venv with JAX from pip's cache (~65 s)
@pytest.mark.skipif(shutil.which("git") is None, reason="needs git to list the repository's files")
def test_readme_bench_install_makes_a_fresh_venv_with_the_bench_extra_alone():
    clone = bench_clone()
    # Nothing of the `test` extra: the bench must not need it.
    assert run_in(clone, ".venv/bin/python -c 'import pytest'", 60).returncode != 0
    assert run_in(clone, ".venv/bin/python -c 'import jax, jaxlib, warp, matplotlib, mpmath, jointlimits'", 120).returncode == 0


@pytest.mark.slow  # the quick bench (~95 s), in the venv above
@pytest.mark.serial  # it times the core against its peers
@pytest.mark.skipif(shutil.which("git") is None, reason="needs git to list the repository's files")
def test_readme_quick_bench_runs_on_a_fresh_venv_with_the_bench_extra():
    clone = bench_clone()
    try:
        assert run_in(clone, ".venv/bin/python -c 'import pytest'", 60).returncode != 0
        out = run_in(clone, bench_commands()[1], 1200)
        assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-4000:])
        last = out.stdout.strip().splitlines()[-1]
        assert re.fullmatch(r"speedup_vs_autodiff_egh=\d+\.\d\d speedup_vs_autodiff_e=\d+\.\d\d speedup_all_active_egh=\d+\.\d\d "
                            r"speedup_vs_autodiff_e_all_active=\d+\.\d\d speedup_vs_warp_e=\d+\.\d\d speedup_vs_warp_eg=\d+\.\d\d",
                            last), last
        assert (clone / "bench" / "results" / "quick.md").exists()
    finally:
        shutil.rmtree(clone.parent, ignore_errors=True)
