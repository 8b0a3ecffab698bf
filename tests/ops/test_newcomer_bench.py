"""docs/performance.md's bench commands, run the way a newcomer runs them: a fresh clone, a fresh venv, the `bench` extra only.

Slow for a test (a fresh virtual environment with JAX from pip's cache, ~40-60 s, then the quick bench:
88 s at 1e5 joints on a quiet machine before --quick measured at 1e4 and reused JAX's compiled functions,
57 s now with the machine's load at 4.4 on its 2 cores), but well under CI's few minutes, so the page's
command runs as written (`python -m bench --quick`, JAX and HTTP included) rather than trimmed:
the import path is exactly the one a newcomer hits. The bench must find its 50-digit reference
(mpmath) with the `bench` extra alone, not through `tests/` and the `test` extra.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "docs" / "performance.md").read_text()  # the bench commands, moved from the README


def bench_commands() -> list[str]:
    """The shell lines of docs/performance.md's first block, without their comments."""
    block = README.split("# Performance: speed against error", 1)[1].split("```bash\n", 1)[1].split("```", 1)[0]
    return [line.split("  #", 1)[0].strip() for line in block.splitlines() if line.strip()]


def fresh_clone(dest: Path) -> Path:
    """The repository's files as a clone has them (tracked and new, never .venv or caches)."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT, capture_output=True, check=True,
    ).stdout.decode().split("\0")
    for rel in filter(None, listed):
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


@pytest.mark.slow  # a fresh venv with JAX, then the quick bench (~30 s quiet)
@pytest.mark.skipif(shutil.which("git") is None, reason="needs git to list the repository's files")
def test_readme_quick_bench_runs_on_a_fresh_venv_with_the_bench_extra(tmp_path: Path):
    clone = fresh_clone(tmp_path / "clone")
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    install, quick = bench_commands()
    run = lambda cmd, timeout: subprocess.run(  # noqa: E731
        cmd, shell=True, cwd=clone, env=env, capture_output=True, text=True, timeout=timeout
    )
    made = run(f"{sys.executable} -m venv .venv && {install.split(' && ')[0]}", 900)
    assert made.returncode == 0, made.stderr[-3000:]
    # Nothing of the `test` extra: the bench must not need it.
    assert run(".venv/bin/python -c 'import pytest'", 60).returncode != 0
    out = run(quick, 1200)
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-4000:])
    last = out.stdout.strip().splitlines()[-1]
    assert re.fullmatch(r"speedup_vs_autodiff_egh=\d+\.\d\d speedup_vs_autodiff_e=\d+\.\d\d speedup_all_active_egh=\d+\.\d\d "
                        r"speedup_vs_autodiff_e_all_active=\d+\.\d\d speedup_vs_warp_e=\d+\.\d\d speedup_vs_warp_eg=\d+\.\d\d",
                        last), last
    assert (clone / "bench" / "results" / "quick.md").exists()
