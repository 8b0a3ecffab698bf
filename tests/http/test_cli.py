"""`jointlimits serve`: options from flags and the environment, limits passed through, JSON logs, SIGTERM."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from jointlimits.service import cli
from tests.drills import LOOPBACK, Server, get, scene

ROOT = Path(__file__).resolve().parents[2]


def console_script() -> list[str]:
    """The `jointlimits` script pip made from pyproject.toml's [project.scripts]."""
    beside = Path(sys.executable).parent / "jointlimits"
    found = str(beside) if beside.exists() else shutil.which("jointlimits")
    assert found, "the jointlimits console script is not installed (pip install -e .)"
    return [found]


def post(port: int, body: dict | bytes, headers: dict[str, str] | None = None) -> tuple[int, dict]:
    data = body if isinstance(body, bytes) else json.dumps(body).encode()
    req = urllib.request.Request(
        f"http://{LOOPBACK}:{port}/v1/evaluate", data, {"Content-Type": "application/json", **(headers or {})}
    )
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"{}")


# --------------------------------------------------------------------------- options


def test_pyproject_declares_the_console_script():
    import tomllib

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["jointlimits"] == "jointlimits.cli:main"


def parse(argv: list[str]):
    return cli.build_parser().parse_args(["serve", *argv])


def test_defaults(monkeypatch):
    for k in list(os.environ):
        if k.startswith("JOINTLIMITS_"):
            monkeypatch.delenv(k)
    a = parse([])
    assert (a.host, a.port, a.workers) == ("127.0.0.1", 8000, cli.available_cpus())
    assert a.max_body_bytes == 256 * 2**20 and a.max_joints == 1_000_000
    assert a.graceful_timeout == 30 and a.access_log is True and a.cors_origins == ""


def test_environment_then_flags(monkeypatch):
    monkeypatch.setenv("JOINTLIMITS_HOST", "0.0.0.0")
    monkeypatch.setenv("JOINTLIMITS_PORT", "9000")
    monkeypatch.setenv("JOINTLIMITS_WORKERS", "3")
    monkeypatch.setenv("JOINTLIMITS_MAX_BODY_BYTES", "12345")
    monkeypatch.setenv("JOINTLIMITS_MAX_JOINTS", "77")
    monkeypatch.setenv("JOINTLIMITS_ACCESS_LOG", "off")
    a = parse([])
    assert (a.host, a.port, a.workers, a.max_body_bytes, a.max_joints, a.access_log) == ("0.0.0.0", 9000, 3, 12345, 77, False)
    a = parse(["--port", "9001", "--workers", "1", "--max-joints", "5", "--access-log", "true"])
    assert (a.port, a.workers, a.max_joints, a.access_log) == (9001, 1, 5, True)


def test_auto_workers_follow_the_cpu_quota(monkeypatch):
    monkeypatch.setattr(cli, "_cgroup_cpu_quota", lambda: 1.5)
    assert cli.available_cpus() == min(2, len(os.sched_getaffinity(0)))
    monkeypatch.setattr(cli, "_cgroup_cpu_quota", lambda: 0.25)
    assert cli.available_cpus() == 1
    monkeypatch.setattr(cli, "_cgroup_cpu_quota", lambda: None)
    assert cli.available_cpus() == len(os.sched_getaffinity(0))


@pytest.mark.parametrize("argv", [["--workers", "0"], ["--max-joints", "-1"], ["--access-log", "maybe"],
                                  ["--port", "70000"], ["--port", "-5"], ["--port", "http"]])  # 70000 bound 4464
def test_bad_options_are_refused(argv, capsys):
    with pytest.raises(SystemExit) as e:
        parse(argv)
    assert e.value.code == 2


@pytest.mark.parametrize("argv", [["--token", "s3cret"], ["--max-joint", "5"], ["--graceful", "5"]])
def test_a_flag_is_read_whole_not_by_its_prefix(argv, capsys):
    """Before: argparse took a prefix for the flag it starts, so `--token s3cret` (a newcomer's guess: the token is
    JOINTLIMITS_TOKEN, no flag) was read as `--token-file s3cret`, "token file s3cret: No such file or directory"."""
    with pytest.raises(SystemExit) as e:
        parse(argv)
    assert e.value.code == 2 and f"unrecognized arguments: {' '.join(argv)}" in capsys.readouterr().err


@pytest.mark.parametrize("flag", ["--request-timeout", "--header-timeout", "--shutdown-delay"])
def test_a_duration_that_is_no_number_is_refused_in_the_settings_words(flag, capsys):
    """`float('foo')` raised ValueError inside the reader, which argparse worded "invalid positive_float value"."""
    with pytest.raises(SystemExit):
        parse([flag, "foo"])
    err = capsys.readouterr().err
    assert f"argument {flag}: must be " in err and "positive number of seconds, got 'foo'" in err
    assert "invalid" not in err and "positive_float" not in err


@pytest.mark.parametrize(("env", "text"), [("JOINTLIMITS_HEADER_TIMEOUT", "abc"), ("JOINTLIMITS_MAX_JOINTS", "-3")])
def test_a_bad_variable_is_named_by_the_cli(env, text, monkeypatch, capsys):
    """A container sets variables, not flags: the refusal names the variable and its text beside the flag."""
    monkeypatch.setenv(env, text)
    with pytest.raises(SystemExit) as e:
        parse([])
    assert e.value.code == 2 and f"({env}={text!r})" in capsys.readouterr().err
    flag = "--" + env.removeprefix("JOINTLIMITS_").lower().replace("_", "-")
    assert getattr(parse([flag, "7"]), flag[2:].replace("-", "_")) == 7  # the flag given wins over a bad variable



def test_a_token_file_that_does_not_read_is_said_in_one_line(tmp_path, monkeypatch, capsys):
    """Before: a mistyped --token-file (or a secret not mounted at JOINTLIMITS_TOKEN_FILE) was a traceback."""
    missing = tmp_path / "no-such-token"
    assert cli.main(["serve", "--token-file", str(missing)]) == 2
    assert capsys.readouterr().err == f"jointlimits: token file {missing}: No such file or directory\n"
    monkeypatch.setenv("JOINTLIMITS_TOKEN_FILE", str(tmp_path))
    assert cli.main(["serve"]) == 2 and f"token file {tmp_path}: Is a directory" in capsys.readouterr().err

def test_version():
    out = subprocess.run([*console_script(), "--version"], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0 and out.stdout.startswith("jointlimits ")


def test_the_soft_limit_on_file_descriptors_is_raised_for_the_connections(monkeypatch, capsys):
    """A worker holds `--max-connections` sockets and a burst of up to `--backlog` accepted before they are refused:
    past the soft limit (1024 is common) accept fails and every client is reset, so `serve` raises it to the hard
    one, and says so when the hard one is too low."""
    limits, set_to = [(1024, 524288)], []
    monkeypatch.setattr(cli.resource, "getrlimit", lambda _: limits[0])
    monkeypatch.setattr(cli.resource, "setrlimit", lambda _, new: set_to.append(new))
    cli.fd_room(1024 + 2048 + cli.FD_RESERVE)
    assert set_to == [(524288, 524288)] and capsys.readouterr().err == ""
    limits[0] = (4096, 4096)  # enough already: left alone
    cli.fd_room(4000)
    assert set_to == [(524288, 524288)] and capsys.readouterr().err == ""
    limits[0] = (1024, 2048)  # the hard limit is below: raised as far as it goes, and said
    cli.fd_room(3136)
    assert set_to[-1] == (2048, 2048)
    err = capsys.readouterr().err
    assert "3136 file descriptors" in err and "2048 (ulimit -Hn)" in err
    limits[0] = (256, cli.resource.RLIM_INFINITY)  # macOS: a soft limit of "unlimited" is refused for files
    cli.fd_room(3136)
    assert set_to[-1] == (3136, cli.resource.RLIM_INFINITY) and capsys.readouterr().err == ""


# --------------------------------------------------------------------------- a real server


@pytest.mark.slow  # `jointlimits serve` subprocesses
def test_serve_passes_limits_logs_json_and_stops_gracefully(tmp_path):
    """Limits from a flag and from the environment reach the app; one JSON line per request; SIGTERM exits 0."""
    server = Server(
        workers=1,
        extra_args=["--max-joints", "6"],
        env={"JOINTLIMITS_MAX_BODY_BYTES": "5000"},
        command=console_script(),
    )
    with server:
        assert post(server.port, scene(4))[0] == 200
        assert post(server.port, scene(8))[0] == 413  # 8 joints > --max-joints 6, 4.2 kB < 5000 B
        assert post(server.port, scene(20))[0] == 413  # 10 kB > JOINTLIMITS_MAX_BODY_BYTES
        assert post(server.port, scene(4), {"X-Request-ID": "cli-test-1"})[0] == 200
        assert get(server.port, "/metrics")[0] == 200
        server.proc.send_signal(signal.SIGTERM)
        assert server.proc.wait(30) == 0
        log = server.log()
    lines = [json.loads(line) for line in log.splitlines() if line.strip()]  # every line is JSON
    access = [line for line in lines if line["logger"] == "jointlimits.access" and line["path"] != "/healthz"]
    assert [a["status"] for a in access] == [200, 413, 413, 200, 200]
    mine = next(a for a in access if a["request_id"] == "cli-test-1")
    assert mine["joints"] == 4 and mine["route"] == "/v1/evaluate" and mine["latency_ms"] > 0
    assert any("Shutting down" in line["msg"] for line in lines)


@pytest.mark.slow  # `jointlimits serve` subprocesses
def test_token_file_and_cors(tmp_path):
    token = tmp_path / "token"
    token.write_text("file-secret\n")
    server = Server(workers=1, extra_args=["--token-file", str(token), "--cors-origins", "https://a.example"])
    with server:
        assert post(server.port, scene(2))[0] == 401
        assert post(server.port, scene(2), {"Authorization": "Bearer file-secret"})[0] == 200
        assert get(server.port, "/healthz")[0] == 200
        req = urllib.request.Request(
            f"http://{LOOPBACK}:{server.port}/v1/evaluate",
            method="OPTIONS",
            headers={"Origin": "https://a.example", "Access-Control-Request-Method": "POST"},
        )
        with urllib.request.urlopen(req, timeout=10) as r:
            assert r.headers["access-control-allow-origin"] == "https://a.example"


@pytest.mark.slow  # `jointlimits serve` subprocesses
def test_an_app_that_does_not_import_fails_fast(tmp_path):
    """With several workers, uvicorn's supervisor would respawn them forever: the CLI refuses to start."""
    (tmp_path / "msgpack.py").write_text("raise ImportError('broken on purpose')\n")
    (tmp_path / "numpy.py").write_text("raise ImportError('broken on purpose')\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-m", "jointlimits.service.cli", "serve", "--workers", "2", "--port", "0"],
        capture_output=True, text=True, env=env, timeout=60, cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 3 and "broken on purpose" in out.stderr


def test_readme_serves_with_the_cli():  # the README's first command
    text = (ROOT / "README.md").read_text()
    first = text.split("```bash\n", 1)[1].split("```", 1)[0].splitlines()[0]
    assert "jointlimits serve" in first


@pytest.mark.slow  # a `jointlimits serve` subprocess
def test_serve_caps_a_workers_connections_and_raises_its_fd_limit():
    """`--max-connections` reaches the worker's connection layer; the soft fd limit it started with (1024) is raised."""
    hard = int(subprocess.run(["sh", "-c", "ulimit -Hn"], capture_output=True, text=True).stdout.strip() or 0)
    if not shutil.which("prlimit") or hard <= 1024:
        pytest.skip("needs prlimit and a hard fd limit above 1024")
    server = Server(workers=1, extra_args=["--max-connections", "3"],
                    command=["prlimit", f"--nofile=1024:{hard}", *console_script()])
    with server:
        limits = Path(f"/proc/{server.proc.pid}/limits").read_text().split("Max open files")[1].split()[:2]
        assert limits == [str(hard), str(hard)]
        held = [socket.create_connection((LOOPBACK, server.port)) for _ in range(3)]
        try:
            deadline = time.monotonic() + 10
            while (status := get(server.port, "/healthz")[0]) != 503 and time.monotonic() < deadline:
                time.sleep(0.05)  # until the worker has accepted the three
            assert status == 503
        finally:
            for s in held:
                s.close()


@pytest.mark.parametrize("token", ["a\nb", " lead", "caf\u00e9"])
def test_a_token_no_header_can_carry_is_refused_at_start(token, monkeypatch, capsys):
    """Before, the server started and answered every client 401: no client could send such a token (the SDK refuses
    it at construction, httpx in its own words)."""
    monkeypatch.setattr("uvicorn.run", never_started)
    monkeypatch.setenv("JOINTLIMITS_TOKEN", token)
    assert cli.main(["serve"]) == 2
    assert capsys.readouterr().err == f"jointlimits: JOINTLIMITS_TOKEN: {BAD_TOKEN}\n"


@pytest.mark.parametrize("token", ["a\nb", "caf\u00e9"])
def test_a_token_file_whose_token_no_header_can_carry_is_refused(token, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr("uvicorn.run", never_started)
    secret = tmp_path / "token"
    secret.write_text(f"{token}\n", encoding="utf-8")  # stripped: the line break inside stays
    assert cli.main(["serve", "--token-file", str(secret)]) == 2
    assert capsys.readouterr().err == f"jointlimits: token file {secret}: {BAD_TOKEN}\n"


BAD_TOKEN = "a bearer token is printable ASCII, without line breaks or spaces around it"


def never_started(*args, **kwargs):
    raise AssertionError("the server started")
