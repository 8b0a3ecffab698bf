"""`jointlimits serve`: run the service under uvicorn with production defaults.

Every option can also come from the environment (`JOINTLIMITS_<OPTION>`); a command-line
flag wins over the environment, which wins over the default. The request limits and CORS
are handed to the application through the same `JOINTLIMITS_*` variables that
`jointlimits.service.settings.Settings` reads, so each worker process sees them. The bearer token is
read from `JOINTLIMITS_TOKEN` or `--token-file` only, never from a flag (flags show in `ps`).

Several workers (`--workers N`, N > 1, or `auto`) run under uvicorn's supervisor, which
shares one listening socket and respawns a worker that dies. Prometheus needs its
multiprocess mode for `/metrics` to sum over them: unless `PROMETHEUS_MULTIPROC_DIR` is
already set, a fresh directory is made for the run and removed afterwards.

The supervisor kills a worker whose health ping goes unanswered for `--healthcheck-timeout`
seconds; the answer needs the GIL, so the timeout must exceed the longest step that holds it
(a JSON parse at `--max-json-values`, docs/deployment.md, "Limits and sizing a pod").

SIGTERM / SIGINT shut down gracefully: stop accepting, finish in-flight requests (for at most
`--graceful-timeout` seconds), exit 0.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

ENV_PREFIX = "JOINTLIMITS_"


def _env(name: str, default: str) -> str:
    return os.environ.get(ENV_PREFIX + name, default)


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
    return _positive_int(value, "a positive integer or 'auto'")


def _positive_int(value: str, what: str = "a positive integer") -> int:
    # argparse would name a bare ValueError by this function's name ("invalid _workers value").
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be {what}, got {value!r}")
    return n


BOOL = "true|false"
"""What boolean options show; 1/0, yes/no, on/off are accepted too."""


def _positive_float(value: str) -> float:
    x = float(value)
    if not (0 < x < float("inf")):
        raise argparse.ArgumentTypeError("must be a positive number of seconds")
    return x


def _bool(value: str) -> bool:
    v = value.strip().lower()
    if v in ("1", "true", "yes", "on"):
        return True
    if v in ("0", "false", "no", "off", ""):
        return False
    raise argparse.ArgumentTypeError(f"must be true or false (or 1/0, yes/no, on/off), got {value!r}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jointlimits", description="The joint-limit constitution service.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser(
        "serve",
        help="serve the HTTP API",
        description="Serve the HTTP API. Each option defaults to its JOINTLIMITS_* environment variable.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    s.add_argument("--host", default=_env("HOST", "127.0.0.1"), help="bind address (JOINTLIMITS_HOST); 0.0.0.0 in the container")
    s.add_argument("--port", type=int, default=int(_env("PORT", "8000")), help="TCP port (JOINTLIMITS_PORT)")
    s.add_argument(
        "--workers",
        type=_workers,
        default=_env("WORKERS", "auto"),
        help="worker processes, or 'auto' = usable CPUs, cgroup quota included (JOINTLIMITS_WORKERS)",
    )
    s.add_argument(
        "--max-body-bytes",
        type=_positive_int,
        default=int(_env("MAX_BODY_BYTES", str(256 * 2**20))),
        help="largest request body; larger answers 413 (JOINTLIMITS_MAX_BODY_BYTES)",
    )
    s.add_argument(
        "--max-joints",
        type=_positive_int,
        default=int(_env("MAX_JOINTS", "1000000")),
        help="most joints in one request; more answers 413 (JOINTLIMITS_MAX_JOINTS)",
    )
    # Admission by cost and the per-request deadline (docs/deployment.md, "Limits").
    s.add_argument(
        "--max-batches",
        type=_positive_int,
        default=_env("MAX_BATCHES", "4096"),  # a string: argparse applies `type`, so a bad variable is refused too
        help="most batches in one request; more answers 413 (JOINTLIMITS_MAX_BATCHES)",
    )
    s.add_argument(
        "--max-answer-bytes",
        type=_positive_int,
        default=_env("MAX_ANSWER_BYTES", str(256 * 2**20)),
        help="largest answer, bounded before any work from joints x outputs x encoding; larger answers 413 "
        "(JOINTLIMITS_MAX_ANSWER_BYTES)",
    )
    s.add_argument(
        "--max-json-values",
        type=_positive_int,
        default=_env("MAX_JSON_VALUES", "2000000"),
        help="most values (commas + 1) in a JSON body; more answers 413 before parsing (JOINTLIMITS_MAX_JSON_VALUES)",
    )
    s.add_argument(
        "--request-timeout",
        type=_positive_float,
        default=_env("REQUEST_TIMEOUT", "60"),
        help="seconds an evaluation may take (parse, core, encode); past it 503 with Retry-After "
        "(JOINTLIMITS_REQUEST_TIMEOUT)",
    )
    s.add_argument(
        "--queue-timeout",
        type=_positive_float,
        default=_env("QUEUE_TIMEOUT", "30"),
        help="seconds a request may wait for the worker's memory budget of requests in flight before it starts; "
        "past it 503 busy with Retry-After, nothing evaluated (JOINTLIMITS_QUEUE_TIMEOUT)",
    )
    s.add_argument(
        "--healthcheck-timeout",
        type=_positive_int,
        default=_env("HEALTHCHECK_TIMEOUT", "30"),
        help="seconds uvicorn's supervisor waits for a worker's health ping before killing it; above the "
        "longest step that holds the GIL (a JSON parse at --max-json-values) (JOINTLIMITS_HEALTHCHECK_TIMEOUT)",
    )
    s.add_argument(
        "--cors-origins",
        default=_env("CORS_ORIGINS", ""),
        help="comma-separated origins allowed by CORS; empty = CORS off (JOINTLIMITS_CORS_ORIGINS)",
    )
    s.add_argument(
        "--max-sessions",
        type=_positive_int,
        default=int(_env("MAX_SESSIONS", "64")),
        help="open WebSocket sessions per worker; one more is closed with code 4429 (JOINTLIMITS_MAX_SESSIONS)",
    )
    s.add_argument(
        "--max-session-joints",
        type=_positive_int,
        default=int(_env("MAX_SESSION_JOINTS", "1000000")),
        help="joints all open sessions of a worker hold together; a scene past it is refused with 413, then "
        "code 4413 (JOINTLIMITS_MAX_SESSION_JOINTS)",
    )
    s.add_argument(
        "--max-frame-bytes",
        type=_positive_int,
        default=int(_env("MAX_FRAME_BYTES", str(64 * 2**20))),
        help="largest session message; larger closes the session with code 1009 (JOINTLIMITS_MAX_FRAME_BYTES)",
    )
    s.add_argument(
        "--session-idle-seconds",
        type=float,
        default=float(_env("SESSION_IDLE_SECONDS", "300")),
        help="a session without a message for this long is closed with code 4408 (JOINTLIMITS_SESSION_IDLE_SECONDS)",
    )
    s.add_argument(
        "--token-file",
        default=_env("TOKEN_FILE", "") or None,
        help="file holding the bearer token required on /v1/* (JOINTLIMITS_TOKEN_FILE; or JOINTLIMITS_TOKEN itself)",
    )
    s.add_argument(
        "--graceful-timeout",
        type=float,
        default=float(_env("GRACEFUL_TIMEOUT", "30")),
        help="seconds in-flight requests get to finish after SIGTERM (JOINTLIMITS_GRACEFUL_TIMEOUT)",
    )
    s.add_argument(
        "--keepalive-timeout",
        type=float,
        default=float(_env("KEEPALIVE_TIMEOUT", "75")),
        help="seconds an idle keep-alive connection stays open; keep it above your load balancer's "
        "idle timeout (JOINTLIMITS_KEEPALIVE_TIMEOUT)",
    )
    s.add_argument(
        "--header-timeout",
        type=_positive_float,
        default=_positive_float(_env("HEADER_TIMEOUT", "10")),
        help="seconds a connection has to send a request's headers, from its first byte (or from connecting); "
        "then 408 and closed: slowloris (JOINTLIMITS_HEADER_TIMEOUT)",
    )
    s.add_argument(
        "--body-timeout",
        type=_positive_float,
        default=_positive_float(_env("BODY_TIMEOUT", "30")),
        help="seconds from a request's headers to the end of its body; then 408 and closed (JOINTLIMITS_BODY_TIMEOUT)",
    )
    s.add_argument(
        "--write-timeout",
        type=_positive_float,
        default=_positive_float(_env("WRITE_TIMEOUT", "30")),
        help="seconds a connection's write buffer may stay full (the client not reading its answer, session "
        "replies or pongs); then the connection is dropped and what it held freed (JOINTLIMITS_WRITE_TIMEOUT)",
    )
    s.add_argument("--backlog", type=_positive_int, default=int(_env("BACKLOG", "2048")), help="listen backlog (JOINTLIMITS_BACKLOG)")
    s.add_argument(
        "--log-level",
        default=_env("LOG_LEVEL", "info"),
        choices=["critical", "error", "warning", "info", "debug"],
        help="log level (JOINTLIMITS_LOG_LEVEL)",
    )
    s.add_argument(
        "--keep-heap",
        type=_bool,
        metavar=BOOL,
        default=_bool(_env("KEEP_HEAP", "true")),
        help="keep freed memory in each worker's heap: no page faults per request, holds the largest request's "
        "memory (JOINTLIMITS_KEEP_HEAP)",
    )
    s.add_argument(
        "--access-log",
        type=_bool,
        metavar=BOOL,
        default=_bool(_env("ACCESS_LOG", "true")),
        help="one JSON line per request on stdout (JOINTLIMITS_ACCESS_LOG)",
    )
    return parser


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("jointlimits")
    except Exception:  # pragma: no cover
        return "unknown"


def serve(args: argparse.Namespace) -> int:
    import uvicorn

    from jointlimits.service.observability import log_config
    from jointlimits.service.http.ws_protocol import server_options

    # Hand the application settings to every worker through the environment Settings reads.
    os.environ[ENV_PREFIX + "MAX_BODY_BYTES"] = str(args.max_body_bytes)
    os.environ[ENV_PREFIX + "MAX_JOINTS"] = str(args.max_joints)
    os.environ[ENV_PREFIX + "CORS_ORIGINS"] = args.cors_origins
    for name in ("max_batches", "max_answer_bytes", "max_json_values", "request_timeout", "queue_timeout"):
        os.environ[ENV_PREFIX + name.upper()] = str(getattr(args, name))
    os.environ[ENV_PREFIX + "KEEP_HEAP"] = "true" if args.keep_heap else "false"
    os.environ[ENV_PREFIX + "HEADER_TIMEOUT"] = str(args.header_timeout)  # read by ReadTimeoutProtocol
    os.environ[ENV_PREFIX + "BODY_TIMEOUT"] = str(args.body_timeout)
    os.environ[ENV_PREFIX + "WRITE_TIMEOUT"] = str(args.write_timeout)  # read by both protocols below
    if args.token_file:
        token = Path(args.token_file).read_text().strip()
        if not token:
            print(f"jointlimits: token file {args.token_file} is empty", file=sys.stderr)
            return 2
        os.environ[ENV_PREFIX + "TOKEN"] = token

    for name in ("max_sessions", "max_session_joints", "max_frame_bytes", "session_idle_seconds"):  # WebSocket sessions
        os.environ[ENV_PREFIX + name.upper()] = str(getattr(args, name))

    from jointlimits.service.settings import Settings

    Settings()  # fail here, once, on a malformed variable rather than in every worker
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
        signal.signal(sig, _exit_cleanly)
    try:
        uvicorn.run(
            "jointlimits.service.app:app",
            host=args.host,
            port=args.port,
            workers=args.workers,
            log_config=log_config(args.log_level, args.access_log),
            log_level=args.log_level,
            # uvicorn refuses a larger message itself (1009, drained: the client reads it) before buffering it;
            # no permessage-deflate: float64 arrays barely compress, deflate would only cost CPU.
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


def _exit_cleanly(signum: int, frame: object) -> None:
    raise SystemExit(0)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "serve":
        return serve(args)
    return 2  # pragma: no cover (argparse requires a command)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
