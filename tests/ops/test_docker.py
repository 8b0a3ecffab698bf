"""The Dockerfile, kept honest without a Docker engine.

The build stage's COPY steps are replayed from a build context filtered by `.dockerignore`,
its RUN steps run in a shell with `/opt/venv` mapped to a fresh temporary directory (one
virtual environment for the whole module), and the image's ENTRYPOINT + CMD start with
the runtime stage's ENV (host and port moved to a free loopback port). Then the result is
asked for `/healthz`, an evaluation and `/metrics`, the HEALTHCHECK command runs against
it, and SIGTERM stops it cleanly.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.drills import LOOPBACK, free_port, get

pytestmark = pytest.mark.slow  # replays the Dockerfile into a fresh venv and serves from it (~20 s)

ROOT = Path(__file__).resolve().parents[2]
VENV_IN_IMAGE = "/opt/venv"


# --------------------------------------------------------------------------- parsing


@dataclass
class Stage:
    base: str
    name: str | None
    steps: list[tuple[str, str]] = field(default_factory=list)  # (INSTRUCTION, arguments)

    def all(self, instruction: str) -> list[str]:
        return [args for ins, args in self.steps if ins == instruction]

    def last(self, instruction: str) -> str | None:
        found = self.all(instruction)
        return found[-1] if found else None


def parse_dockerfile(text: str) -> list[Stage]:
    logical, buf = [], ""
    for line in text.splitlines():
        stripped = line.strip()
        if not buf and (not stripped or stripped.startswith("#")):
            continue
        if buf and stripped.startswith("#"):
            continue
        if stripped.endswith("\\"):
            buf += stripped[:-1] + " "
            continue
        logical.append(buf + stripped)
        buf = ""
    stages: list[Stage] = []
    for line in logical:
        instruction, _, args = line.partition(" ")
        instruction = instruction.upper()
        if instruction == "FROM":
            m = re.match(r"(\S+)(?:\s+AS\s+(\S+))?", args.strip(), re.IGNORECASE)
            assert m, line
            stages.append(Stage(m.group(1), m.group(2)))
        else:
            assert stages, f"{line!r} before FROM"
            stages[-1].steps.append((instruction, args.strip()))
    return stages


def parse_env(args: str) -> dict[str, str]:
    """`ENV a=1 b="2 3"` (the key=value form; the legacy `ENV a 1` too)."""
    parts = shlex.split(args)
    if parts and "=" not in parts[0]:
        return {parts[0]: " ".join(parts[1:])}
    return dict(p.split("=", 1) for p in parts)


def exec_form(args: str) -> list[str]:
    value = json.loads(args)
    assert isinstance(value, list) and all(isinstance(v, str) for v in value), f"not exec form: {args}"
    return value


def expand(value: str, env: dict[str, str]) -> str:
    return re.sub(r"\$\{?([A-Za-z_][A-Za-z0-9_]*)\}?", lambda m: env.get(m.group(1), ""), value)


def _pattern(pat: str) -> re.Pattern[str]:
    out, i = "", 0
    while i < len(pat):
        if pat.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif pat.startswith("**", i):
            out, i = out + ".*", i + 2
        elif pat[i] == "*":
            out, i = out + "[^/]*", i + 1
        elif pat[i] == "?":
            out, i = out + "[^/]", i + 1
        else:
            out, i = out + re.escape(pat[i]), i + 1
    return re.compile(out)


def dockerignored(rel: str, patterns: list[str]) -> bool:
    """`.dockerignore` semantics, enough for ours: the last matching pattern wins, `!` re-includes,
    and a pattern that matches a directory matches everything under it."""
    parts = rel.split("/")
    prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    ignored = False
    for pat in patterns:
        negate = pat.startswith("!")
        rx = _pattern(pat.lstrip("!").strip("/"))
        if any(rx.fullmatch(p) for p in prefixes):
            ignored = not negate
    return ignored


def build_context(dest: Path) -> Path:
    patterns = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.strip().startswith("#")
    ]
    # Top-level names a `!` pattern could bring back; other ignored top-level folders (.git, .venv)
    # are not walked at all.
    reincluded = [_pattern(p[1:].strip("/").split("/")[0]) for p in patterns if p.startswith("!")]
    for dirpath, dirnames, filenames in os.walk(ROOT):
        base = Path(dirpath)
        if base == ROOT:
            dirnames[:] = [d for d in dirnames if not dockerignored(d, patterns) or any(r.fullmatch(d) for r in reincluded)]
        links = [d for d in dirnames if (base / d).is_symlink()]  # os.walk lists links to folders, never enters them
        for name in [*filenames, *links]:
            rel = (base / name).relative_to(ROOT).as_posix()
            if dockerignored(rel, patterns):
                continue
            target = dest / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            if (base / name).is_symlink():  # the context holds the link itself, as Docker's does
                target.symlink_to(os.readlink(base / name))
            else:
                shutil.copy2(base / name, target)
    return dest


# --------------------------------------------------------------------------- fixtures


STAGES = parse_dockerfile((ROOT / "Dockerfile").read_text())
FINAL = STAGES[-1]


@dataclass
class Built:
    venv: Path
    runtime_env: dict[str, str]
    command: list[str]
    healthcheck: list[str]
    workdir: Path


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Built:
    tmp = tmp_path_factory.mktemp("docker")
    venv = tmp / "venv"
    context = build_context(tmp / "context")
    shim = tmp / "shim"  # `python` in RUN steps is the image's Python: here, the one running the tests
    shim.mkdir()
    (shim / "python").symlink_to(sys.executable)
    (shim / "python3").symlink_to(sys.executable)
    base_env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    base_env["PATH"] = f"{shim}:{base_env.get('PATH', '')}"

    def map_path(p: str) -> str:
        return p.replace(VENV_IN_IMAGE, str(venv))

    def stage_root(stage: Stage) -> Path:
        return tmp / f"stage-{stage.name or 'final'}"

    env: dict[str, str] = {}
    for stage in STAGES:
        env = dict(base_env)
        root = stage_root(stage)
        workdir = root
        workdir.mkdir(parents=True, exist_ok=True)
        for ins, args in stage.steps:
            if ins == "ENV":
                for k, v in parse_env(args).items():
                    env[k] = map_path(expand(v, env))
            elif ins == "WORKDIR":
                workdir = root / args.lstrip("/")
                workdir.mkdir(parents=True, exist_ok=True)
            elif ins == "COPY":
                parts = shlex.split(args)
                if parts[0].startswith("--from="):
                    src, dst = parts[1], parts[2]
                    assert map_path(src) == map_path(dst) == str(venv), "only the venv crosses stages"
                    continue
                *srcs, dst = parts
                target = workdir / dst if not dst.startswith("/") else root / dst.lstrip("/")
                for src in srcs:
                    s = context / src
                    assert s.exists(), f"COPY {src}: not in the build context (.dockerignore?)"
                    if s.is_dir():
                        # As Docker does: a link inside a copied folder stays a link (jointlimits/ -> ../service).
                        shutil.copytree(s, target if not dst.endswith("/") else target / s.name, dirs_exist_ok=True, symlinks=True)
                    else:
                        target.mkdir(parents=True, exist_ok=True) if dst.endswith("/") else None
                        shutil.copy2(s, target / s.name if dst.endswith("/") else target)
            elif ins == "RUN":
                if stage is FINAL and args.startswith("useradd"):
                    continue  # needs root; the USER it makes is checked in test_image_shape
                cmd = args if not args.startswith("[") else shlex.join(exec_form(args))
                subprocess.run(["bash", "-euo", "pipefail", "-c", map_path(cmd)], cwd=workdir, env=env, check=True, timeout=600)
    runtime_env = {k: v for k, v in env.items()}
    runtime_env["PATH"] = expand(runtime_env["PATH"], {"PATH": os.environ.get("PATH", "")})
    command = exec_form(FINAL.last("ENTRYPOINT") or "[]") + exec_form(FINAL.last("CMD") or "[]")
    health = FINAL.last("HEALTHCHECK") or ""
    health_cmd = exec_form(health.split("CMD", 1)[1].strip())
    return Built(venv, runtime_env, command, health_cmd, tmp)


# --------------------------------------------------------------------------- tests


def test_image_shape():
    """Slim bases, non-root, health check on /healthz, `jointlimits serve`, workers and port from ENV."""
    assert all(re.fullmatch(r"python:3\.\d+-slim(-\w+)?", s.base) for s in STAGES), [s.base for s in STAGES]
    user = FINAL.last("USER")
    assert user and user.split(":")[0] not in ("root", "0")
    health = FINAL.last("HEALTHCHECK")
    assert health and "/healthz" in health
    assert exec_form(FINAL.last("ENTRYPOINT")) + exec_form(FINAL.last("CMD")) == ["jointlimits", "serve"]
    final_env = {k: v for args in FINAL.all("ENV") for k, v in parse_env(args).items()}
    assert {"JOINTLIMITS_WORKERS", "JOINTLIMITS_PORT", "JOINTLIMITS_HOST"} <= final_env.keys()
    assert final_env["JOINTLIMITS_HOST"] == "0.0.0.0"  # reachable from outside the container
    assert FINAL.last("EXPOSE") == final_env["JOINTLIMITS_PORT"]
    runs = " ".join(r for s in STAGES for r in s.all("RUN"))
    assert "[test]" not in runs and "pytest" not in runs  # runtime dependencies only
    assert re.search(r"-m compileall [^&]*-j 0\b", runs), runs  # the venv's bytecode on every core (default: one)
    assert any(f"useradd" in r and user.split(":")[0] in r for r in FINAL.all("RUN"))


def test_dockerignore_keeps_the_context_small(tmp_path: Path):
    ctx = build_context(tmp_path / "ctx")
    top = {p.name for p in ctx.iterdir()}
    assert top <= {"pyproject.toml", "README.md", "service", "schemas", "client", "jointlimits"}, top
    assert (ctx / "jointlimits" / "service").is_symlink()  # the namespace's links, as Docker copies them
    assert not list(ctx.rglob("__pycache__"))


def test_the_image_installs_only_runtime_dependencies(built: Built):
    py = built.venv / "bin" / "python"
    where = subprocess.run([py, "-c", "import jointlimits.service as s; print(s.__file__)"], capture_output=True, text=True,
                           cwd=built.workdir)
    assert where.returncode == 0, where.stderr
    assert str(built.venv) in where.stdout  # installed into the venv, not run from the source tree
    assert subprocess.run([py, "-c", "import pytest"], capture_output=True, cwd=built.workdir).returncode != 0
    assert (built.venv / "bin" / "jointlimits").exists()


def test_the_image_serves_checks_health_and_stops_on_sigterm(built: Built):
    port = free_port()
    env = dict(built.runtime_env, JOINTLIMITS_HOST=LOOPBACK, JOINTLIMITS_PORT=str(port), JOINTLIMITS_WORKERS="2")
    exe = shutil.which(built.command[0], path=env["PATH"])
    assert exe and exe.startswith(str(built.venv)), exe
    log = built.workdir / "serve.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([exe, *built.command[1:]], env=env, cwd=built.workdir, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while get(port, "/healthz", timeout=1)[0] != 200:
            assert proc.poll() is None, log.read_text()
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        # The HEALTHCHECK command, as Docker would run it inside the container.
        hc = subprocess.run(built.healthcheck, env=env, cwd=built.workdir, capture_output=True, timeout=10)
        assert hc.returncode == 0, hc.stderr
        body = json.dumps(_example()).encode()
        req = urllib.request.Request(f"http://{LOOPBACK}:{port}/v1/evaluate", body, {"Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=10) as r:
            answer = json.loads(r.read())
        assert abs(answer["total_energy"] - 0.8) < 1e-9
        # A request is counted once its answer has gone out: the scrape may come first (on the other worker).
        deadline = time.monotonic() + 10
        while (got := get(port, "/metrics"))[0] == 200 and b"jointlimits_joints_evaluated_total" not in got[1]:
            assert time.monotonic() < deadline, got
            time.sleep(0.1)
        status, metrics = got
        assert status == 200 and b"jointlimits_joints_evaluated_total" in metrics
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0, log.read_text()
        # And with nothing serving, the health check fails.
        hc = subprocess.run(built.healthcheck, env=env, cwd=built.workdir, capture_output=True, timeout=10)
        assert hc.returncode != 0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    lines = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    assert any(line.get("route") == "/v1/evaluate" and line.get("joints") == 1 for line in lines)


def _example() -> dict:
    c, s = 0.7648421872844885, 0.644217687237691
    ident = [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]
    return {
        "bodies": {"q": [ident, [0, 0, 0, c, -s, 0, s, c, 0, 0, 0, 1]], "q_prev": [ident, ident], "q_ref": [ident, ident]},
        "batches": [
            {
                "constitution_uid": 670,
                "base_uid": 18,
                "body_ids": [[0, 1]],
                "edges": [[[0, 0, 0], [0, 0, 1]]],
                "lower": [-0.5],
                "upper": [0.5],
                "strength": [100.0],
            }
        ],
        "outputs": ["energy", "gradient"],
    }
