"""`jointlimits serve`: the service under uvicorn with production defaults.

Each option is a flag, else its `JOINTLIMITS_<OPTION>` variable, else its default; the application's options are
the rows of `Settings` (service/settings.py), handed to every worker as those variables (`Settings.environ`). The
bearer token comes from `JOINTLIMITS_TOKEN` or `--token-file`, never a flag (flags show in `ps`).

Several workers (`--workers N`, or `auto`) run under uvicorn's supervisor; `/metrics` sums over them through
Prometheus' multiprocess mode (a fresh `PROMETHEUS_MULTIPROC_DIR` unless one is set). SIGTERM drains first
(`service/app.py:drain_on_sigterm`), then stops accepting, finishes in-flight requests and exits 0.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from jointlimits.service.settings import ENV_PREFIX, TABLE, Setting, Settings, bearer_token, boolean, positive_float
from jointlimits.service.settings import positive_int

BOOL = "true|false"
"""What boolean options show; 1/0, yes/no, on/off are accepted too."""


def available_cpus() -> int:
    """CPUs this process may use: its affinity mask, capped by a cgroup v2/v1 CPU quota (containers)."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover (not Linux)
        n = os.cpu_count() or 1
    quota = _cgroup_cpu_quota()
    if quota is not None:
        n = min(n, max(1, math.ceil(quota)))
    return max(1, n)


def _cgroup_cpu_quota() -> float | None:
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]  # cgroup v2
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota_us = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us").read_text())  # cgroup v1
        period_us = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us").read_text())
        return None if quota_us <= 0 else quota_us / period_us
    except (OSError, ValueError):
        return None


def _workers(value: str) -> int:
    if value.strip().lower() == "auto":
        return available_cpus()
    return positive_int(value, "a positive integer or 'auto'")


def _port(text: str) -> int:
    """A TCP port, 0 (the system picks one) to 65535: uvicorn would bind 70000 as 4464 and log "70000"."""
    n = int(text) if text.strip().lstrip("+-").isdigit() else -1
    if not 0 <= n <= 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port, 0 to 65535, got {text!r}")
    return n


# The process's own options (uvicorn's), rows of the settings' shape: in --help before and after the application's.
FIRST = (
    Setting("host", "127.0.0.1", str, "bind address; 0.0.0.0 in the container", True),
    Setting("port", 8000, _port, "TCP port", True),
    Setting("workers", "auto", _workers, "worker processes, or 'auto' = usable CPUs, cgroup quota included", True),
)
LAST = (
    Setting("healthcheck_timeout", 30, positive_int, "seconds uvicorn's supervisor waits for a worker's health ping "
            "before killing it; above the longest step that holds the GIL (a JSON parse at --max-json-values)", True),
    Setting("graceful_timeout", 30.0, positive_float, "seconds in-flight requests get after --shutdown-delay", True),
    Setting("keepalive_timeout", 75.0, positive_float, "seconds an idle keep-alive connection stays open; keep it "
            "above your load balancer's idle timeout", True),
    Setting("backlog", 2048, positive_int, "listen backlog", True),
    Setting("log_level", "info", str, "log level", True),
    Setting("access_log", True, boolean, "one JSON line per request on stdout", True),
)
LOG_LEVELS = ["critical", "error", "warning", "info", "debug"]
# A worker's descriptors besides its connections: 14 measured (listener, loop, logs, metrics) and up to 32 refused
# connections lingering after their answer (timeouts.MAX_LINGERING).
FD_RESERVE = 64


def _option(parser: argparse.ArgumentParser, row: Setting) -> None:
    """`--<name>` defaulting to its variable, else its default. A variable's text goes through `row.parse` as a
    flag's does, so a bad variable is refused like a bad flag."""
    def parse(text: str) -> Any:
        try:
            return row.parse(text)
        except (ValueError, argparse.ArgumentTypeError) as e:  # argparse names the flag; a container sets variables
            named = f" ({row.env}={text!r})" if os.environ.get(row.env) == text else ""
            raise argparse.ArgumentTypeError(f"{e}{named}") from None

    parser.add_argument("--" + row.name.replace("_", "-"), default=os.environ.get(row.env, row.default),
                        type=parse, help=f"{row.help} ({row.env})", metavar=BOOL if row.parse is boolean else None,
                        choices=LOG_LEVELS if row.name == "log_level" else None)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jointlimits", description="The joint-limit constitution service.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser(
        "serve",
        help="serve the HTTP API",
        description="Serve the HTTP API. Each option defaults to its JOINTLIMITS_* environment variable.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter, allow_abbrev=False,  # `--token x` is no --token-file
    )
    for row in (*FIRST, *(t for t in TABLE if t.flag)):  # the token has no flag
        _option(s, row)
    s.add_argument(
        "--token-file",
        default=os.environ.get(ENV_PREFIX + "TOKEN_FILE") or None,
        help="file holding the bearer token required on /v1/* (JOINTLIMITS_TOKEN_FILE; or JOINTLIMITS_TOKEN itself)",
    )
    for row in LAST:
        _option(s, row)
    # The SDK's command, run by the `jointlimits` entry point (jointlimits/cli.py): listed here for --help only.
    sub.add_parser("evaluate", help="a URDF robot's joints against their limits (jointlimits evaluate --help)")
    return parser


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("jointlimits")
    except Exception:  # pragma: no cover
        return "unknown"


def fd_room(need: int) -> None:
    """Let this process and its workers open `need` file descriptors: the soft limit raised to the hard one (1024 is a
    common soft limit; the service polls with epoll, not select). Past it, accept fails and every client is reset."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < need:
        # An unlimited hard limit (macOS): the soft one may not be "unlimited" for files, so `need`.
        resource.setrlimit(resource.RLIMIT_NOFILE, (need if hard == resource.RLIM_INFINITY else hard, hard))
    if hard != resource.RLIM_INFINITY and hard < need:
        print(f"jointlimits: warning: --max-connections and --backlog need {need} file descriptors per worker, this "
              f"process may open {hard} (ulimit -Hn): past it every new client is reset", file=sys.stderr)


def serve(args: argparse.Namespace) -> int:
    import uvicorn

    from jointlimits.service.observability import log_config
    from jointlimits.service.http.timeouts import server_options

    given = {t.name: getattr(args, t.name) for t in TABLE if t.flag}
    if args.token_file:  # else Settings reads JOINTLIMITS_TOKEN
        try:
            given["token"] = bearer_token(Path(args.token_file).read_text().strip())
        except (OSError, ValueError) as e:  # a mistyped path, a secret not mounted, a token no header carries
            print(f"jointlimits: token file {args.token_file}: {getattr(e, 'strerror', None) or e}", file=sys.stderr)
            return 2
        if not given["token"]:
            print(f"jointlimits: token file {args.token_file} is empty", file=sys.stderr)
            return 2
    try:
        settings = Settings(**given)
    except ValueError as e:  # a variable without a flag (JOINTLIMITS_TOKEN), named by `Setting.from_env`
        print(f"jointlimits: {e}", file=sys.stderr)
        return 2
    os.environ.update(settings.environ())  # what every worker's Settings() reads
    fd_room(args.max_connections + args.backlog + FD_RESERVE)  # + what one turn of the accept loop takes (<= backlog)

    if args.workers > 1:
        # uvicorn's supervisor would respawn workers that cannot import the app, forever: fail fast
        # instead, in a throw-away process (the supervisor itself stays small: it never imports it).
        check = subprocess.run([sys.executable, "-c", "import jointlimits.service.app"], capture_output=True, text=True)
        if check.returncode != 0:
            print(f"jointlimits: the application does not import:\n{check.stderr}", file=sys.stderr)
            return 3

    own_metrics_dir = None
    if args.workers > 1 and not os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        own_metrics_dir = tempfile.mkdtemp(prefix="jointlimits-metrics-")
        os.environ["PROMETHEUS_MULTIPROC_DIR"] = own_metrics_dir
    elif os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        # A directory kept from an earlier run would add its counts to this one's.
        directory = Path(os.environ["PROMETHEUS_MULTIPROC_DIR"])
        directory.mkdir(parents=True, exist_ok=True)
        for stale in directory.glob("*.db"):
            stale.unlink()
    # uvicorn re-raises SIGTERM/SIGINT once it has shut down gracefully, which would end the
    # process "killed by SIGTERM" (143). A graceful stop is a success: exit 0, like the
    # multi-worker supervisor does.
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: sys.exit(0))
    try:
        uvicorn.run(
            "jointlimits.service.app:app",
            host=args.host,
            port=args.port,
            workers=args.workers,
            log_config=log_config(args.log_level, args.access_log),
            log_level=args.log_level,
            # uvicorn refuses a larger message itself (1009, drained: the client reads it) before buffering it.
            **server_options(args.max_frame_bytes),
            access_log=False,  # ours (JSON, with request id and joints) replaces uvicorn's
            timeout_graceful_shutdown=max(1, math.ceil(args.graceful_timeout)),
            timeout_keep_alive=max(1, math.ceil(args.keepalive_timeout)),
            backlog=args.backlog,
            # The supervisor's ping is answered by a thread of the worker, which needs the GIL.
            timeout_worker_healthcheck=args.healthcheck_timeout,
            server_header=False,
            http="jointlimits.service.http.timeouts:ReadTimeoutProtocol",  # uvicorn's httptools + deadlines on heads and writes
        )
    finally:
        if own_metrics_dir:
            shutil.rmtree(own_metrics_dir, ignore_errors=True)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "serve":
        return serve(args)
    print("jointlimits evaluate: run it as the `jointlimits` command (jointlimits/cli.py)", file=sys.stderr)
    return 2  # pragma: no cover (argparse requires a command)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
