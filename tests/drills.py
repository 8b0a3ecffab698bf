"""Load and fault drills against a running service (loopback only, bounded in time and count).

    python -m tests.drills --spawn --workers 2 --clients 16 --duration 30 --scenario all

from the repository's root: a test module (the tests run the drills and import their helpers), not part of the
installed package. `--spawn` starts `jointlimits serve` on a free loopback port for the run (and stops it);
without it, `--port` names a service already running on 127.0.0.1. Scenarios:

- `mixed`: N clients on keep-alive connections, valid and invalid requests mixed, for
  `--duration` seconds: throughput, p50/p99 latency per kind, 5xx count, dropped
  connections, and the RSS of each worker before and after (growth).
- `flood`: oversized requests (declared too long, streamed too long, too many joints) from
  half the clients while the other half send valid requests: the server stays up, the
  flood gets 413, the valid clients keep their latency.
- `kill`: SIGKILL one worker in the middle of a load run; clients retry a request whose
  connection broke (POST /v1/evaluate is a pure function, so retrying is safe) and must
  see no error; the supervisor replaces the worker.
- `sigterm`: SIGTERM the server while every client has a slow request in flight: each of
  those requests completes with 200 and the server exits 0.
- `slowloris`: `--slow` connections that send nothing, or trickle their headers or their
  body at one byte a second, while the clients send valid requests: each slow connection
  is closed within its read timeout (`--header-timeout`, `--body-timeout` of the spawned
  server), the valid clients keep their 200s.
- `peak`: the largest request each limit admits (answer bound in both encodings, JSON values,
  joints, body bytes, batches), each sent alone to a fresh 1-worker server: its time and the
  worker's peak RSS (`VmHWM`), the figures behind docs/deployment.md's sizing rule. Builds its bodies
  with NumPy and the SDK's codec (installed with the service).
- `stalled`: `--clients` connections (at most 32) each send the costliest answer the limits admit
  and read nothing (4 KiB receive buffers): when each was dropped (`--write-timeout` of the
  spawned server), the worker's peak RSS against the sizing rule.
- `stalled-sessions`: HTTP evaluates alone, then beside `--clients` sessions (4000 joints) that
  sent two evaluates each and read nothing: statuses, p50/p99, the budget the sessions hold.
- `pingflood`: 125-byte pings for `--duration` seconds (at most 30) on a connection that reads
  nothing: the worker's RSS before and after, when it was dropped.
- `connections`: one client opens `--held` connections as fast as it can and sends nothing, against a fresh
  1-worker server (under `prlimit --nofile=<--nofile>` if given): the worker's file descriptors and RSS, what a
  normal client's /healthz and /readyz get meanwhile, what the flood's connections got (held, or 503 `busy` past
  `JOINTLIMITS_MAX_CONNECTIONS`), /healthz after.
- `answer`: while valid clients run, one request whose answer would exceed
  `JOINTLIMITS_MAX_ANSWER_BYTES` (413 before any work) and one at that bound (200): the valid
  clients keep getting 200s and no worker is restarted (its pids are compared). Needs a server
  with the default limits (`--spawn` starts one).
- `lb`: HAProxy (installed: Debian's `haproxy`) with docs/load-balancers.md's configuration in front of
  three `jointlimits serve --workers 1` replicas it starts on loopback: steady load (`--duration`, at most
  60 s), a rolling restart (SIGTERM one at a time, with a 1 s drain) with session loops (evaluate, commit),
  a SIGKILL; an SDK client on keep-alive and one opening a connection per request (retrying nothing) at 2 and
  1000 joints: the failed requests per scenario and client, and inexact committed coordinates.

Plain exchanges (a GET, one request and its answer) go through httpx. The load loop (`Connection`, `run_load`)
is a minimal HTTP/1.1 client on asyncio streams with pre-encoded requests, so that on a 2-core machine it takes
as little CPU from the server as it can, and because the flood's requests misbehave on purpose; so are the
connections that misbehave (slowloris, stalled readers, raw WebSocket frames): see their comments.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

LOOPBACK = "127.0.0.1"
MAX_REQUESTS_PER_CLIENT = 200_000  # a hard bound on every loop, whatever the duration
CONNECTION_ERRORS = (ConnectionError, asyncio.IncompleteReadError, BrokenPipeError, OSError)


# --------------------------------------------------------------------------- payloads


def scene(n_joints: int, seed: int = 0, outside: float = 0.5) -> dict[str, Any]:
    """A request body: `n_joints` joints (alternately #670 and #669), about `outside` of them past a limit.

    Joint k couples bodies 2k and 2k+1 along +z; body 2k+1 is turned (revolute) or slid
    (prismatic) by a seeded amount in [-1, 1], the limits are [-w, w] with w chosen so
    that the wanted fraction is outside.
    """
    rng = random.Random(seed)
    w = 1.0 - outside
    ident = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    q, q_ref = [], []
    rev: dict[str, list] = {"body_ids": [], "edges": [], "lower": [], "upper": [], "strength": []}
    pri: dict[str, list] = {"body_ids": [], "edges": [], "lower": [], "upper": [], "strength": []}
    for k in range(n_joints):
        base = [float(2 * k), 0.0, 0.0]
        a = rng.uniform(-1.0, 1.0)
        q_ref += [base + ident, base + ident]
        if k % 2 == 0:
            c, s = math.cos(a), math.sin(a)
            q += [base + ident, base + [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0]]
            batch = rev
        else:
            q += [base + ident, [base[0], base[1], base[2] + a] + ident]
            batch = pri
        batch["body_ids"].append([2 * k, 2 * k + 1])
        batch["edges"].append([base, [base[0], base[1], base[2] + 1.0]])
        batch["lower"].append(-w)
        batch["upper"].append(w)
        batch["strength"].append(100.0)
    batches = []
    if rev["body_ids"]:
        batches.append({"constitution_uid": 670, "base_uid": 18, **rev})
    if pri["body_ids"]:
        batches.append({"constitution_uid": 669, "base_uid": 20, **pri})
    return {"bodies": {"q": q, "q_prev": q_ref, "q_ref": q_ref}, "batches": batches}


@dataclass(frozen=True)
class Kind:
    """One kind of request in a mix: its bytes on the wire and the statuses it may get."""

    name: str
    raw: bytes
    ok: frozenset[int]
    weight: float = 1.0


# Requests as bytes on the wire, written by hand: the load loop sends them pre-encoded (`Connection`), and the
# flood's are oversized on purpose (a declared length over the limit, a chunked stream past it).
def http_request(method: str, path: str, body: bytes | None = None, headers: dict[str, str] | None = None) -> bytes:
    lines = [f"{method} {path} HTTP/1.1", f"Host: {LOOPBACK}"]
    for k, v in (headers or {}).items():
        lines.append(f"{k}: {v}")
    if body is not None:
        lines.append("Content-Type: application/json")
        lines.append(f"Content-Length: {len(body)}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode() + (body or b"")


def _post(body: Any, token: str | None, **extra: str) -> Callable[[], bytes]:
    data = body if isinstance(body, bytes) else json.dumps(body).encode()
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    headers.update(extra)
    return lambda: http_request("POST", "/v1/evaluate", data, headers)


def mixed_kinds(token: str | None = None) -> list[Kind]:
    """What a solver farm sends, plus what a broken client sends (~1 request in 4 is invalid)."""
    small = scene(2, seed=1)
    medium = scene(200, seed=2) | {"outputs": ["energy", "gradient"]}
    hess = scene(100, seed=3) | {"hessian_mode": "psd"}
    bad_range = scene(4, seed=4)
    bad_range["batches"][0]["lower"][0] = 2.0  # lower > upper: 422 naming the joint
    bad_shape = scene(2, seed=5)
    bad_shape["bodies"]["q"][0] = bad_shape["bodies"]["q"][0][:11]  # an 11-DOF row: 422
    kinds = [
        Kind("valid_2_joints", _post(small, token)(), frozenset({200}), 4),
        Kind("valid_200_joints_grad", _post(medium, token)(), frozenset({200}), 3),
        Kind("valid_100_joints_hessian", _post(hess, token)(), frozenset({200}), 1),
        Kind("invalid_json", _post(b'{"bodies": [1, 2', token)(), frozenset({422}), 1),
        Kind("invalid_lower_gt_upper", _post(bad_range, token)(), frozenset({422}), 1),
        Kind("invalid_shape", _post(bad_shape, token)(), frozenset({422}), 1),
        Kind("healthz", http_request("GET", "/healthz"), frozenset({200}), 0.5),
        Kind("not_found", http_request("GET", "/nope"), frozenset({404}), 0.5),
    ]
    if token:
        kinds.append(Kind("unauthorized", _post(small, None)(), frozenset({401}), 0.5))
    return kinds


def flood_kinds(max_body_bytes: int, max_joints: int, token: str | None = None) -> list[Kind]:
    """Requests over the size limits: each should be refused (413) without being parsed."""
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    over = max_body_bytes + 1
    # Declares a body over the limit and sends it all (a client that does not wait for the answer).
    declared = (
        f"POST /v1/evaluate HTTP/1.1\r\nHost: {LOOPBACK}\r\n{auth}Content-Type: application/json\r\n"
        f"Content-Length: {over}\r\n\r\n"
    ).encode() + b" " * over
    # No length declared: chunks until past the limit.
    chunk = b" " * 65536
    n_chunks = over // len(chunk) + 2
    streamed = (
        f"POST /v1/evaluate HTTP/1.1\r\nHost: {LOOPBACK}\r\n{auth}Content-Type: application/json\r\n"
        "Transfer-Encoding: chunked\r\n\r\n"
    ).encode() + (f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n") * n_chunks + b"0\r\n\r\n"
    joints = _post(scene(max_joints + 1, seed=6), token)()
    kinds = [
        Kind("oversized_declared", declared, frozenset({413})),
        Kind("oversized_chunked", streamed, frozenset({413})),
    ]
    if len(joints) <= max_body_bytes:  # else it would be a body-size 413, not a joint-count one
        kinds.append(Kind("too_many_joints", joints, frozenset({413})))
    return kinds


# --------------------------------------------------------------------------- client


@dataclass
class Stats:
    started: float = 0.0
    elapsed: float = 0.0
    latencies: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    statuses: Counter = field(default_factory=Counter)
    unexpected: Counter = field(default_factory=Counter)  # (kind, status) not in kind.ok
    connection_errors: int = 0  # a connection broke before a complete answer (each retry counts)
    failed: int = 0  # requests that got no answer, retries included (dropped)
    retried_ok: int = 0  # requests that broke and then succeeded on a retry
    connects: int = 0
    evaluate_answered: int = 0  # answers to POST /v1/evaluate (to compare with /metrics)

    def record(self, kind: Kind, status: int, latency: float) -> None:
        self.statuses[status] += 1
        if kind.raw.startswith(b"POST /v1/evaluate "):
            self.evaluate_answered += 1
        self.latencies[kind.name].append(latency)
        if status not in kind.ok:
            self.unexpected[f"{kind.name}:{status}"] += 1

    @property
    def requests(self) -> int:
        return sum(self.statuses.values())

    def server_errors(self) -> int:
        return sum(n for s, n in self.statuses.items() if s >= 500)

    def summary(self) -> dict[str, Any]:
        every = sorted(x for v in self.latencies.values() for x in v)
        per_kind = {
            k: {"n": len(v), "p50_ms": _ms(_pct(sorted(v), 50)), "p99_ms": _ms(_pct(sorted(v), 99))}
            for k, v in sorted(self.latencies.items())
        }
        return {
            "seconds": round(self.elapsed, 2),
            "requests": self.requests,
            "throughput_rps": round(self.requests / self.elapsed, 1) if self.elapsed else 0.0,
            "p50_ms": _ms(_pct(every, 50)),
            "p99_ms": _ms(_pct(every, 99)),
            "max_ms": _ms(every[-1] if every else None),
            "statuses": {str(k): v for k, v in sorted(self.statuses.items())},
            "server_errors_5xx": self.server_errors(),
            "unexpected": dict(self.unexpected),
            "connection_errors": self.connection_errors,
            "dropped": self.failed,
            "retried_ok": self.retried_ok,
            "connects": self.connects,
            "evaluate_answered": self.evaluate_answered,
            "by_kind": per_kind,
        }


def _pct(xs: Sequence[float], p: float) -> float | None:
    if not xs:
        return None
    return xs[min(len(xs) - 1, max(0, math.ceil(p / 100 * len(xs)) - 1))]


def _ms(x: float | None) -> float | None:
    return None if x is None else round(x * 1e3, 2)


class Connection:
    """One keep-alive connection of the load loop, hand-written on asyncio streams rather than a library client:
    the load drills measure the server on a 2-core machine where the clients share its cores, so each request
    costs the client a write and a header parse, no more (~0.2 ms of CPU a GET /healthz on keep-alive, against
    ~2 ms for httpx.AsyncClient: as much as the server's own work on a small request); and the flood's requests misbehave on purpose (raw
    bytes over the limits, whose 413 is read even when the server closes before taking the body)."""

    def __init__(self, port: int, stats: Stats) -> None:
        self.port = port
        self.stats = stats
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def _open(self) -> None:
        self.reader, self.writer = await asyncio.open_connection(LOOPBACK, self.port, limit=2**24)
        self.stats.connects += 1

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None

    async def exchange(self, raw: bytes, timeout: float) -> int:
        """Send one request, read its whole answer; the status. Raises on a broken connection."""
        if self.writer is None:
            await self._open()
        assert self.reader is not None and self.writer is not None
        try:
            return await asyncio.wait_for(self._exchange(raw), timeout)
        except BaseException:
            self.close()
            raise

    async def _exchange(self, raw: bytes) -> int:
        assert self.reader is not None and self.writer is not None
        self.writer.write(raw)
        try:
            await self.writer.drain()
        except CONNECTION_ERRORS:
            # The server may answer (413) and close before reading a body it refuses: the
            # answer can still be in our receive buffer.
            pass
        head = await self.reader.readuntil(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split(" ", 2)[1])
        headers = {}
        for line in lines[1:]:
            if ":" in line:
                k, v = line.split(":", 1)
                headers[k.strip().lower()] = v.strip()
        if "content-length" in headers:
            await self.reader.readexactly(int(headers["content-length"]))
        elif headers.get("transfer-encoding", "").lower() == "chunked":
            while True:
                size = int((await self.reader.readuntil(b"\r\n")).split(b";")[0], 16)
                await self.reader.readexactly(size + 2)
                if size == 0:
                    break
        if headers.get("connection", "").lower() == "close":
            self.close()
        return status


async def client_loop(
    port: int,
    kinds: Sequence[Kind],
    stats: Stats,
    deadline: float,
    seed: int,
    retries: int = 0,
    timeout: float = 30.0,
    max_requests: int = MAX_REQUESTS_PER_CLIENT,
) -> None:
    """Requests drawn from `kinds` (by weight) until `deadline` or `max_requests`."""
    rng = random.Random(seed)
    weights = [k.weight for k in kinds]
    conn = Connection(port, stats)
    try:
        for _ in range(max_requests):
            if time.monotonic() >= deadline:
                break
            kind = rng.choices(kinds, weights)[0]
            t0 = time.perf_counter()
            for attempt in range(retries + 1):
                try:
                    status = await conn.exchange(kind.raw, timeout)
                except (asyncio.TimeoutError, *CONNECTION_ERRORS):
                    stats.connection_errors += 1
                    if attempt == retries:
                        stats.failed += 1
                        break
                    await asyncio.sleep(0.05 * (attempt + 1))
                    continue
                stats.record(kind, status, time.perf_counter() - t0)
                stats.retried_ok += attempt > 0
                break
    finally:
        conn.close()


async def run_load(
    port: int,
    kinds: Sequence[Kind],
    clients: int,
    duration: float,
    retries: int = 0,
    seed: int = 0,
    during: Callable[[], Any] | None = None,
) -> Stats:
    """`clients` concurrent clients for `duration` s; `during` (a coroutine function) runs alongside."""
    stats = Stats(started=time.monotonic())
    deadline = stats.started + duration
    tasks = [
        asyncio.create_task(client_loop(port, kinds, stats, deadline, seed * 1000 + i, retries)) for i in range(clients)
    ]
    side = asyncio.create_task(during()) if during else None
    await asyncio.gather(*tasks)
    stats.elapsed = time.monotonic() - stats.started
    if side:
        await side
    return stats


# --------------------------------------------------------------------------- server process


def free_port() -> int:
    with socket.socket() as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


def _status_kib(pid: int, field: str) -> int | None:
    """One `kB` field of a process's /proc status (None if it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def rss_kib(pid: int) -> int | None:
    """A process's resident set (`VmRSS`), KiB."""
    return _status_kib(pid, "VmRSS")


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process so far."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def worker_pids(supervisor: int) -> list[int]:
    """uvicorn's worker processes under `supervisor` (spawned children; not the resource tracker)."""
    pids = []
    for task in Path(f"/proc/{supervisor}/task").glob("*/children"):
        try:
            pids += [int(p) for p in task.read_text().split()]
        except OSError:
            continue
    out = []
    for pid in sorted(set(pids)):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmd and b"resource_tracker" not in cmd:
            out.append(pid)
    return out


class Server:
    """`jointlimits serve` in its own process group on a free loopback port."""

    def __init__(
        self,
        workers: int = 2,
        extra_args: Sequence[str] = (),
        env: dict[str, str] | None = None,
        command: Sequence[str] = (sys.executable, "-m", "jointlimits.service.cli"),
        port: int | None = None,
    ) -> None:
        self.port = port or free_port()
        self.workers = workers
        self.log_path = Path(os.environ.get("TMPDIR", "/tmp")) / f"jointlimits-serve-{self.port}.log"
        args = [
            *command, "serve",
            "--host", LOOPBACK, "--port", str(self.port), "--workers", str(workers), *extra_args,
        ]  # fmt: skip
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(
            args,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            # No drain phase unless a drill asks for one (the default 5 s would add 5 s to every stop).
            env={**os.environ, "JOINTLIMITS_SHUTDOWN_DELAY": "0", **(env or {})},
            start_new_session=True,
        )

    def wait_ready(self, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}:\n{self.log()[-3000:]}")
            if self.workers == 1 or len(worker_pids(self.proc.pid)) >= self.workers:
                if get(self.port, "/healthz", timeout=1.0)[0] == 200 and self._all_started():
                    # Every worker up: ask a few times so each has imported and served once.
                    for _ in range(4 * self.workers):
                        get(self.port, "/healthz", timeout=5.0)
                    return
            time.sleep(0.1)
        raise RuntimeError(f"server not ready in {timeout} s:\n{self.log()[-3000:]}")

    def _all_started(self) -> bool:
        """Every worker past its lifespan's start (uvicorn logs it once per worker, at info level). One worker's
        answer is not enough: the others may still be importing, and a SIGTERM before a worker's lifespan stops it
        without the drain (nothing to drain there, but a test of every worker's drain would see one missing)."""
        if self.workers == 1:
            return True
        log = self.log()
        return "Started server process" not in log or log.count("Application startup complete") >= self.workers

    def worker_pids(self) -> list[int]:
        return worker_pids(self.proc.pid) if self.workers > 1 else [self.proc.pid]

    def log(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def stop(self, timeout: float = 30.0) -> int | None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        try:  # stray workers of a supervisor that was killed
            os.killpg(self.proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        self._log.close()
        return self.proc.returncode

    def __enter__(self) -> Server:
        try:
            self.wait_ready()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.stop()
        if exc_type is None:  # kept for a post-mortem otherwise
            self.log_path.unlink(missing_ok=True)


def http_options(port: int, timeout: float) -> dict[str, Any]:
    """httpx's options for plain exchanges with the server on loopback. Plain HTTP, never TLS: `verify=False` only
    spares loading a CA bundle (~40 ms a client); no proxy or .netrc from the environment."""
    return {"base_url": f"http://{LOOPBACK}:{port}", "timeout": timeout, "verify": False, "trust_env": False}


def http_client(port: int, timeout: float) -> httpx.Client:
    """A library client for plain exchanges, over its own connections."""
    return httpx.Client(**http_options(port, timeout))


def get(port: int, path: str, timeout: float = 5.0, headers: dict[str, str] | None = None) -> tuple[int, bytes]:
    """A blocking GET on loopback; (0, b"") when nothing answers."""
    try:
        with http_client(port, timeout) as c:
            r = c.get(path, headers=headers)
            return r.status_code, r.content
    except httpx.TransportError:
        return 0, b""


def metric_total(text: str, name: str, **labels: str) -> float:
    """Sum of the samples of `name` whose labels include `labels` in a Prometheus exposition."""
    total = 0.0
    for line in text.splitlines():
        if not line.startswith(name + "{") and not line.startswith(name + " "):
            continue
        head, _, value = line.rpartition(" ")
        if all(f'{k}="{v}"' in head for k, v in labels.items()):
            total += float(value)
    return total


def metrics_text(port: int) -> str | None:
    """The server's own /metrics (all workers), or None when it does not answer."""
    status, text = get(port, "/metrics", timeout=10)
    return text.decode() if status == 200 else None


def scraped(port: int, name: str, **labels: str) -> float:
    """`metric_total` of one scrape of the server's /metrics; NaN when it does not answer."""
    text = metrics_text(port)
    return float("nan") if text is None else metric_total(text, name, **labels)


def budget_given_back(port: int, within: float = 5.0) -> float:
    """The worker's in-flight budget once it has settled: polled until 0, at most `within` seconds (a dropped
    session's task may still be ending when its client's socket is seen closed); what it holds then."""
    deadline = time.monotonic() + within
    while (held := scraped(port, "jointlimits_inflight_budget_bytes")) != 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    return held


def evaluate_requests_counted(port: int) -> float:
    """POST /v1/evaluate requests answered, according to the server's own /metrics (all workers)."""
    return scraped(port, "jointlimits_http_requests_total", route="/v1/evaluate")


# --------------------------------------------------------------------------- scenarios


def scenario_mixed(server: Server, clients: int, duration: float, token: str | None = None) -> dict[str, Any]:
    kinds = mixed_kinds(token)
    # Warm-up: every worker has seen every kind of request before memory is first measured.
    asyncio.run(run_load(server.port, kinds, clients, min(3.0, duration / 5), seed=99))
    before = {pid: rss_kib(pid) for pid in server.worker_pids()}
    cpu0 = {pid: cpu_seconds(pid) for pid in before}
    m0 = evaluate_requests_counted(server.port)
    stats = asyncio.run(run_load(server.port, kinds, clients, duration))
    m1 = evaluate_requests_counted(server.port)
    after = {pid: rss_kib(pid) for pid in server.worker_pids()}
    cpu1 = {pid: cpu_seconds(pid) for pid in before}
    out = stats.summary()
    out["workers_rss_kib"] = {
        str(pid): {"before": before[pid], "after": after.get(pid), "growth": _sub(after.get(pid), before[pid])}
        for pid in before
    }
    out["workers_cpu_s"] = {
        str(pid): None if cpu0[pid] is None or cpu1[pid] is None else round(cpu1[pid] - cpu0[pid], 2) for pid in before
    }
    out["workers_replaced"] = sorted(before) != sorted(after)
    out["metrics_evaluate_delta"] = m1 - m0
    return out


def _sub(a: int | None, b: int | None) -> int | None:
    return None if a is None or b is None else a - b


def scenario_flood(
    server: Server, clients: int, duration: float, max_body_bytes: int, max_joints: int, token: str | None = None
) -> dict[str, Any]:
    valid = [k for k in mixed_kinds(token) if k.name.startswith("valid")]
    baseline = asyncio.run(run_load(server.port, valid, max(1, clients // 2), duration / 2, seed=1))
    flood = flood_kinds(max_body_bytes, max_joints, token)
    flood_stats: list[Stats] = []

    async def both() -> Stats:
        async def flooders() -> None:
            flood_stats.append(await run_load(server.port, flood, max(1, clients // 2), duration, seed=2))

        valid_stats = await run_load(server.port, valid, max(1, clients // 2), duration, seed=3, during=flooders)
        return valid_stats

    under = asyncio.run(both())
    return {
        "valid_alone": baseline.summary(),
        "valid_under_flood": under.summary(),
        "flood": flood_stats[0].summary(),
        "healthz_after": get(server.port, "/healthz")[0],
    }


def scenario_kill(server: Server, clients: int, duration: float, token: str | None = None) -> dict[str, Any]:
    kinds = mixed_kinds(token)
    before = server.worker_pids()
    events: dict[str, Any] = {"workers_before": before}

    async def kill_one() -> None:
        cpu0 = {pid: cpu_seconds(pid) or 0.0 for pid in before}
        await asyncio.sleep(duration / 3)
        # The busiest worker: the one holding (most of) the clients' keep-alive connections.
        victim = max(before, key=lambda pid: (cpu_seconds(pid) or 0.0) - cpu0[pid])
        os.kill(victim, signal.SIGKILL)
        t_kill = time.monotonic()
        events["killed"] = victim
        for _ in range(int(duration * 20)):  # bounded: the supervisor checks every 0.5 s
            now = server.worker_pids()
            if victim not in now and len(now) == len(before):
                events["replaced_by"] = sorted(set(now) - set(before))
                events["replaced_after_s"] = round(time.monotonic() - t_kill, 2)
                break
            await asyncio.sleep(0.05)

    m0 = evaluate_requests_counted(server.port)
    stats = asyncio.run(run_load(server.port, kinds, clients, duration, retries=3, during=kill_one))
    out = stats.summary()
    # Scraped from a worker that did not serve most of these (the busiest one was killed):
    # the counts of the dead worker are still in the sum.
    out["metrics_evaluate_delta"] = evaluate_requests_counted(server.port) - m0
    out.update(events)
    out["workers_after"] = server.worker_pids()
    out["healthz_after"] = get(server.port, "/healthz")[0]
    return out


def scenario_sigterm(server: Server, clients: int, slow_joints: int = 1000, token: str | None = None) -> dict[str, Any]:
    """Every client sends one slow request; SIGTERM arrives while all of them are being computed."""
    body = json.dumps(scene(slow_joints, seed=7)).encode()  # ~0.5 MB in, ~6 MB of Hessians out
    headers = {"Content-Type": "application/json"} | ({"Authorization": f"Bearer {token}"} if token else {})

    async def post() -> int:
        """The slow request over its own connection, a plain request and its answer (httpx); its status."""
        async with httpx.AsyncClient(**http_options(server.port, 120.0)) as c:
            r = await asyncio.wait_for(c.post("/v1/evaluate", content=body, headers=headers), 120)
            return r.status_code

    # How long one takes alone, to send the signal well inside the in-flight window.
    async def alone() -> float:
        t0 = time.perf_counter()
        status = await post()
        assert status == 200, status
        return time.perf_counter() - t0

    one = asyncio.run(alone())
    results: list[tuple[float, float, int | str]] = []

    async def one_request(i: int) -> None:
        sent = time.monotonic()
        try:
            status: int | str = await post()
        except (asyncio.TimeoutError, httpx.TransportError, *CONNECTION_ERRORS) as e:
            status = type(e).__name__
        results.append((sent, time.monotonic(), status))

    async def drill() -> dict[str, Any]:
        tasks = [asyncio.create_task(one_request(i)) for i in range(clients)]
        await asyncio.sleep(min(0.5, one / 2))  # all sent and being computed (16 in 2 workers: ~8 x one)
        t_sig = time.monotonic()
        server.proc.send_signal(signal.SIGTERM)
        await asyncio.gather(*tasks)
        loop = asyncio.get_running_loop()
        code = await loop.run_in_executor(None, server.proc.wait, 120)
        return {"t_sig": t_sig, "exit_code": code, "exited_after_s": round(time.monotonic() - t_sig, 2)}

    info = asyncio.run(drill())
    statuses = Counter(str(s) for _, _, s in results)
    last_done = max(done for _, done, _ in results)
    return {
        "in_flight_at_sigterm": len(results),
        "one_request_alone_s": round(one, 3),
        "statuses": dict(statuses),
        "completed_200": statuses.get("200", 0),
        "last_completion_after_sigterm_s": round(last_done - info["t_sig"], 2),
        "exit_code": info["exit_code"],
        "server_exited_after_s": info["exited_after_s"],
    }


SLOW_KINDS = ("silent", "headers", "body")


async def slow_connection(port: int, kind: str, give_up: float) -> dict[str, Any]:
    """One slowloris connection: sends nothing, or its headers, or its body, one byte a second (raw bytes on asyncio
    streams on purpose: a library client sends a request whole and at once).

    Returns when the server closes it (`closed_after_s`, and the status it answered, if any)
    or after `give_up` seconds (`closed_after_s` None: the server never closed it).
    """
    t0 = time.monotonic()
    reader, writer = await asyncio.open_connection(LOOPBACK, port)
    head = f"POST /v1/evaluate HTTP/1.1\r\nHost: {LOOPBACK}\r\nContent-Type: application/json\r\n"
    if kind == "headers":
        writer.write(head.encode())  # and then one header byte a second, never the blank line
        trickle = b"X-Slow: " + b"a" * 10_000
    elif kind == "body":
        writer.write(f"{head}Content-Length: 100000\r\n\r\n".encode())  # and then one body byte a second
        trickle = b" " * 100_000
    else:
        trickle = b""

    async def drip() -> None:
        for i in range(len(trickle)):
            await asyncio.sleep(1.0)
            writer.write(trickle[i : i + 1])
            await writer.drain()

    dripping = asyncio.create_task(drip())
    answer = b""
    closed_after: float | None = None
    try:
        async with asyncio.timeout(give_up):
            try:
                while chunk := await reader.read(4096):
                    answer += chunk
            except CONNECTION_ERRORS:
                pass  # reset by the server: closed too
            closed_after = time.monotonic() - t0
    except TimeoutError:
        pass  # still open after give_up seconds
    finally:
        dripping.cancel()
        writer.close()
    status = answer.split(b" ", 2)[1].decode() if answer.startswith(b"HTTP/1.1 ") else None
    return {"kind": kind, "closed_after_s": None if closed_after is None else round(closed_after, 2), "status": status}


def scenario_slowloris(
    server: Server, clients: int, slow: int, header_timeout: float, body_timeout: float, token: str | None = None
) -> dict[str, Any]:
    """`slow` slowloris connections (silent, trickling headers, trickling a body) while `clients` valid clients run.

    The slow ones must be closed within their timeout (plus scheduling slack); the valid
    clients must keep their 200s. Bounded: the drill lasts `max(timeouts) + 5` seconds.
    """
    valid = [k for k in mixed_kinds(token) if k.name.startswith("valid")]
    span = max(header_timeout, body_timeout) + 5.0
    # The baseline only sets the p99 reference of the clients under the slowloris (the test bounds that p99 by
    # max(2 s, 5 x this one)): 2 s of `clients` clients is hundreds of requests, as many as the 4.5 s it was gave.
    baseline = asyncio.run(run_load(server.port, valid, clients, min(span / 2, 2.0), seed=1))
    closed: list[dict[str, Any]] = []
    counted_before = connections_closed_counted(server.port)

    async def drill() -> Stats:
        async def slowloris() -> None:
            closed.extend(
                await asyncio.gather(*(slow_connection(server.port, SLOW_KINDS[i % 3], span) for i in range(slow)))
            )

        return await run_load(server.port, valid, clients, span, seed=3, during=slowloris)

    under = asyncio.run(drill())
    by_kind: dict[str, dict[str, Any]] = {}
    for kind in SLOW_KINDS:
        rows = [c for c in closed if c["kind"] == kind]
        times = [c["closed_after_s"] for c in rows if c["closed_after_s"] is not None]
        by_kind[kind] = {
            "connections": len(rows),
            "closed": len(times),
            "max_closed_after_s": max(times, default=None),
            "statuses": dict(Counter(str(c["status"]) for c in rows)),
        }
    counted = connections_closed_counted(server.port)
    return {
        "valid_alone": baseline.summary(),
        "valid_under_slowloris": under.summary(),
        "slow": by_kind,
        # What /metrics says the connection layer closed meanwhile (all workers).
        "metrics_closed_delta": {reason: counted[reason] - counted_before[reason] for reason in counted},
        "healthz_after": get(server.port, "/healthz")[0],
    }


def scenario_connections(held: int, extra_args: Sequence[str] = (), nofile: str | None = None) -> dict[str, Any]:
    """One client opens `held` connections as fast as it can and sends nothing, against a fresh 1-worker server (run
    under `prlimit --nofile=<nofile>` if given: the open-file limit a container may set): what the worker holds then
    (file descriptors, RSS), what a normal client's /healthz and /readyz get meanwhile, how many of the flood's were
    answered (503 `busy` past `JOINTLIMITS_MAX_CONNECTIONS`), and /healthz once the flood has left."""
    prefix = ["prlimit", f"--nofile={nofile}"] if nofile else []
    with Server(1, extra_args, command=[*prefix, sys.executable, "-m", "jointlimits.service.cli"]) as server:
        pid, before = server.proc.pid, rss_kib(server.proc.pid)
        flood: list[socket.socket] = []
        t0 = time.monotonic()
        try:
            for _ in range(held):
                try:
                    flood.append(socket.create_connection((LOOPBACK, server.port), timeout=5))
                except OSError:
                    break  # the client's own limit, or the backlog full
            opened_s = time.monotonic() - t0
            time.sleep(0.5)  # the worker's loop takes what the kernel queued
            fds, rss = len(os.listdir(f"/proc/{pid}/fd")), rss_kib(pid)

            def probe(path: str) -> str:
                try:
                    with socket.create_connection((LOOPBACK, server.port), timeout=5) as s:
                        s.sendall(f"GET {path} HTTP/1.1\r\nHost: {LOOPBACK}\r\n\r\n".encode())
                        return _status_line(s)
                except OSError as e:
                    return type(e).__name__

            probes = {path: probe(path) for path in ("/healthz", "/readyz")}
            answered = Counter(_now(s) for s in flood)
        finally:
            for s in flood:
                s.close()
        time.sleep(0.5)
        return {
            "opened": len(flood), "opened_in_s": round(opened_s, 2), "worker_fds": fds,
            "worker_rss_mib": [round((before or 0) / 1024, 1), round((rss or 0) / 1024, 1)], "probes": probes,
            "flood_answered": dict(answered), "healthz_after": get(server.port, "/healthz")[0],
            "closed_counted": connections_closed_counted(server.port, ("connections_full", "silent")),
        }  # fmt: skip


def _now(s: socket.socket) -> str:
    """What the server did with a connection that sent nothing, read without waiting: its answer's status, `held`
    (open, nothing sent), `closed` (no answer) or the error."""
    s.setblocking(False)
    try:
        head = s.recv(64)
    except BlockingIOError:
        return "held"
    except OSError as e:
        return type(e).__name__
    return head.split(b" ", 2)[1].decode() if head.startswith(b"HTTP/1.1 ") else "closed"


def connections_closed_counted(port: int, reasons: Sequence[str] = ("silent", "slow_head")) -> dict[str, float]:
    """`jointlimits_connections_closed_total` by reason (silent, slow_head; slow_read, slow_message: the write
    timeout and a session message's deadline), summed over the workers."""
    text = metrics_text(port)  # one scrape for all
    if text is None:
        return {r: float("nan") for r in reasons}
    return {r: metric_total(text, "jointlimits_connections_closed_total", reason=r) for r in reasons}


EGH = ("energy", "gradient", "hessian")


def array_scene(n: int, batches: int = 1, outputs: Sequence[str] = EGH, active_only: bool = False, pairs: int = 1) -> Any:
    """A `client.Request` of `n` revolute joints on `pairs` body pairs, every one past its upper limit (active).

    Body 2k+1 is turned by 0.7 about +z against body 2k, the range is [-0.5, 0.5]; joints go
    round-robin over the pairs and are cut into `batches` consecutive batches. Vectorised (NumPy).
    """
    import numpy as np

    from jointlimits.client import JointBatch, request_from_arrays

    eye = np.eye(3).reshape(9)
    q_ref = np.zeros((2 * pairs, 12))
    q_ref[:, 0] = 2.0 * np.arange(2 * pairs)
    q_ref[:, 3:] = eye
    q = q_ref.copy()
    c, s = math.cos(0.7), math.sin(0.7)
    q[1::2, 3:] = [c, -s, 0, s, c, 0, 0, 0, 1]
    ids = np.arange(2 * pairs).reshape(pairs, 2)[np.arange(n) % pairs]
    edges = np.zeros((n, 2, 3))
    edges[:, :, 0] = q_ref[ids[:, :1], 0]
    edges[:, 1, 2] = 1.0
    joints = [
        JointBatch.of(670, ids[p], edges[p], np.full(len(p), -0.5), np.full(len(p), 0.5), np.full(len(p), 100.0))
        for p in np.array_split(np.arange(n), batches)
    ]
    return request_from_arrays(q, joints, q_ref=q_ref, outputs=outputs, active_only=active_only)


def short_values_json(n_bodies: int) -> bytes:
    """A legal JSON body whose cost is its values: `n_bodies` identity rows of short integers, one joint."""
    rows = b",".join([b"[0,0,0,1,0,0,0,1,0,0,0,1]"] * n_bodies)
    return (
        b'{"bodies":{"q":[' + rows + b'],"q_prev":[' + rows + b'],"q_ref":[' + rows + b']},"batches":[{"constitution_uid":670,'
        b'"base_uid":18,"body_ids":[[0,1]],"edges":[[[0,0,0],[0,0,1]]],"lower":[-0.5],"upper":[0.5],"strength":[1]}],'
        b'"outputs":["energy"]}'
    )


def peak_kib(pid: int) -> int | None:
    """A process's peak resident set (`VmHWM`), KiB."""
    return _status_kib(pid, "VmHWM")


def _one(port: int, body: bytes, content_type: str, accept: str, timeout: float = 300.0) -> tuple[int, float, int]:
    """POST a body over its own connection: status, seconds, answer bytes (counted as they arrive, not kept)."""
    t = time.monotonic()
    with http_client(port, timeout) as c, c.stream(
        "POST", "/v1/evaluate", content=body, headers={"Content-Type": content_type, "Accept": accept}
    ) as r:
        size = sum(len(chunk) for chunk in r.iter_raw())
        return r.status_code, round(time.monotonic() - t, 2), size


def peak_cases() -> dict[str, Callable[[], tuple[bytes, str, str, int]]]:
    """The largest request each limit of this environment's settings admits: (body, type, accept, joints)."""
    from jointlimits.client import codec
    from jointlimits.schemas.answer import joints_within
    from jointlimits.service.settings import Settings

    s = Settings()
    J, B = "application/json", "application/msgpack"

    def enc(req: Any, binary: bool) -> bytes:
        return codec.encode(req, binary=binary)[0]

    def at_answer(binary_request: bool, binary_answer: bool) -> tuple[bytes, str, str, int]:
        n = joints_within(s.max_answer_bytes, EGH, binary_answer)
        if not binary_request:  # a JSON body is bounded by its values too: 11 per joint, 72 per body pair
            n = min(n, (s.max_json_values - 64) // 84)
        return enc(array_scene(n, pairs=n), binary_request), B if binary_request else J, B if binary_answer else J, n

    def at_body() -> tuple[bytes, str, str, int]:
        n = min(s.max_joints, s.max_body_bytes // 88)
        pairs = max(1, (s.max_body_bytes - 88 * n - 4096) // 576)
        return enc(array_scene(n, outputs=("energy",), pairs=pairs), True), B, B, n

    return {
        "answer_bound_msgpack": lambda: at_answer(True, True),
        "answer_bound_json": lambda: at_answer(False, False),
        "answer_bound_json_request_msgpack_answer": lambda: at_answer(False, True),
        "json_values_bound": lambda: (short_values_json(s.max_json_values // 36 - 1), J, J, 1),
        "json_values_bound_joints": lambda: (
            enc(array_scene(s.max_json_values // 12, outputs=("energy",)), False), J, J, s.max_json_values // 12
        ),
        "joints_bound_energy": lambda: (enc(array_scene(s.max_joints, outputs=("energy",)), True), B, B, s.max_joints),
        "body_bound_energy": at_body,
        "batches_bound": lambda: (enc(array_scene(s.max_batches, batches=s.max_batches), True), B, B, s.max_batches),
    }


def scenario_peak(env: dict[str, str] | None = None, cases: Sequence[str] | None = None) -> dict[str, Any]:
    """Each case alone on a fresh 1-worker server: status, seconds, worker peak RSS before and after."""
    out: dict[str, Any] = {}
    for name, build in peak_cases().items():
        if cases and name not in cases:
            continue
        body, content_type, accept, joints = build()
        with Server(workers=1, env=env) as server:
            pid = server.worker_pids()[0]
            before = peak_kib(pid)
            status, seconds, answer = _one(server.port, body, content_type, accept)
            after = peak_kib(pid)
        out[name] = {
            "joints": joints, "body_bytes": len(body), "status": status, "seconds": seconds, "answer_bytes": answer,
            "peak_rss_before_mib": round((before or 0) / 1024), "peak_rss_after_mib": round((after or 0) / 1024),
        }  # fmt: skip
        del body
    return out


BURST_CASES = ("answer_bound_msgpack", "body_bound_energy")


def scenario_burst(
    copies: int, env: dict[str, str] | None = None, cases: Sequence[str] = BURST_CASES
) -> dict[str, Any]:
    """`copies` concurrent copies of the costliest request of each of `cases` (`peak_cases`, this environment's
    limits), each on its own connection, on a fresh 1-worker server: the answers (status, or the name of the
    error of a connection that broke), the worker's peak RSS against the sizing rule (`sizing.worker_bytes`),
    whether the worker survived, and a request alone afterwards."""
    from jointlimits.service import sizing
    from jointlimits.service.settings import Settings

    rule_mib = round(sizing.worker_bytes(Settings()) / 2**20)
    out: dict[str, Any] = {}
    for name in cases:
        body, content_type, accept, joints = peak_cases()[name]()
        answers: list[Any] = []

        def one(port: int, body: bytes) -> None:
            try:
                answers.append(_one(port, body, content_type, accept)[0])
            except (OSError, httpx.TransportError) as e:  # a broken connection is an answer too (the server should never cause one)
                answers.append(type(e).__name__)

        with Server(workers=1, env=env) as server:
            pid = server.worker_pids()[0]
            threads = [threading.Thread(target=one, args=(server.port, body)) for _ in range(copies)]
            t = time.monotonic()
            for th in threads:
                th.start()
            for th in threads:
                th.join()
            seconds = round(time.monotonic() - t, 2)
            peak = peak_kib(pid)
            survived = server.worker_pids() == [pid]
            after = _one(server.port, body, content_type, accept)[0]
        out[name] = {
            "joints": joints, "body_bytes": len(body), "copies": copies, "seconds": seconds,
            "answers": sorted(answers, key=str), "peak_rss_mib": round((peak or 0) / 1024), "rule_mib": rule_mib,
            "same_worker": survived, "alone_after": after,
        }  # fmt: skip
        del body
    return out


def answer_joints(max_answer_bytes: int = 256 * 2**20) -> tuple[int, int]:
    """Joints of a `scene` with E+G+H whose JSON answer bound is just within / just over `max_answer_bytes`."""
    from jointlimits.service.http.limits import answer_bytes

    outputs = ("energy", "gradient", "hessian")
    bound = lambda n: answer_bytes([(n + 1) // 2, n // 2], outputs, binary_answer=False)  # noqa: E731 (scene's two batches)
    lo, hi = 1, 10**7
    while lo < hi:  # the largest admitted count
        m = (lo + hi + 1) // 2
        lo, hi = (m, hi) if bound(m) <= max_answer_bytes else (lo, m - 1)
    return lo, lo + 1


def scenario_answer(
    server: Server, clients: int, duration: float, max_answer_bytes: int = 256 * 2**20, token: str | None = None
) -> dict[str, Any]:
    """Valid clients run while one over-the-answer-bound request (413) and one at the bound (200) are sent."""
    valid = [k for k in mixed_kinds(token) if k.name.startswith("valid")]
    # The baseline is the report's reference only (no bound reads it): 2 s of `clients` clients, not duration / 2.
    baseline = asyncio.run(run_load(server.port, valid, clients, min(duration / 2, 2.0), seed=1))
    at, over = answer_joints(max_answer_bytes)
    big = {name: json.dumps(scene(n, seed=8, outside=1.0)).encode() for name, n in (("over_bound", over), ("at_bound", at))}
    pids = server.worker_pids()
    heavy: dict[str, Any] = {}

    async def heavy_requests() -> None:
        await asyncio.sleep(duration / 4)
        for name, body in big.items():
            status, seconds, size = await asyncio.to_thread(_one, server.port, body, "application/json", "application/json", 120.0)
            heavy[name] = {"joints": at if name == "at_bound" else over, "body_bytes": len(body), "status": status, "seconds": seconds, "answer_bytes": size}

    under = asyncio.run(run_load(server.port, valid, clients, duration, seed=3, during=heavy_requests))
    time.sleep(1.0)  # the supervisor checks its workers every 0.5 s
    return {
        "valid_alone": baseline.summary(),
        "valid_during": under.summary(),
        "heavy": heavy,
        "workers_before": pids,
        "workers_after": server.worker_pids(),
        "healthz_after": get(server.port, "/healthz")[0],
    }


# --------------------------------------------------------------------------- clients that stop reading (issue 19)
# Raw sockets and hand-written HTTP and WebSocket bytes on purpose: these clients misbehave. They read nothing
# through a 4 KiB receive buffer, flood pings without reading a pong, or send frames a library would refuse to
# write (unfinished, reserved bits), where a library client (httpx, websockets) reads what arrives, answers pings,
# and writes only valid frames.

WRITE_REASONS = ("slow_read", "slow_message")


def stalled_socket(port: int, rcvbuf: int = 4096) -> socket.socket:
    """A loopback connection with a small receive buffer (set before connecting: the window is negotiated then),
    which the drills never read: what the server sends piles up on its side."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.settimeout(30)
    s.connect((LOOPBACK, port))
    return s


def post_bytes(body: bytes, content_type: str, accept: str) -> bytes:
    head = (
        f"POST /v1/evaluate HTTP/1.1\r\nHost: {LOOPBACK}\r\nContent-Type: {content_type}\r\nAccept: {accept}\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    )
    return head.encode() + body


def dropped(s: socket.socket) -> bool:
    """Whether the server reset the connection (it aborts a stalled writer: RST), read without reading data."""
    return s.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) != 0


def watch_dropped(
    socks: Sequence[socket.socket], t0: float, give_up: float, done: Callable[[int], bool] | None = None
) -> list[float | None]:
    """Seconds from `t0` until each socket saw the server drop it (None: still open after `give_up` seconds, or
    once `done(number dropped)` says the rest were answered otherwise; asked every half second)."""
    out: list[float | None] = [None] * len(socks)
    asked = time.monotonic()
    while time.monotonic() - t0 < give_up and any(t is None for t in out):
        for i, s in enumerate(socks):
            if out[i] is None and dropped(s):
                out[i] = round(time.monotonic() - t0, 2)
        if done is not None and time.monotonic() - asked > 0.5:
            asked = time.monotonic()
            if done(sum(t is not None for t in out)):
                break
        time.sleep(0.05)
    return out


def ws_upgrade(port: int, rcvbuf: int | None = None, headers: dict[str, str] | None = None) -> tuple[socket.socket, bytes]:
    """A raw connection upgraded to a session (or refused): the socket and the server's response head. By hand: the
    socket is then the caller's to misbehave on (read nothing, raw frames); websockets would own and read it."""
    import base64

    s = stalled_socket(port, rcvbuf) if rcvbuf else socket.create_connection((LOOPBACK, port), timeout=30)
    extra = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(
        f"GET /v1/sessions HTTP/1.1\r\nHost: {LOOPBACK}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n{extra}\r\n".encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = s.recv(1)
        if not chunk:
            break
        head += chunk
    return s, head


def ws_frame(opcode: int, payload: bytes, fin: bool = True, rsv: int = 0) -> bytes:
    """A client frame, masked with the key 0 (valid, and the payload goes out as it is: no CPU for masking)."""
    n = len(payload)
    head = bytes([(0x80 if fin else 0) | rsv << 4 | opcode])
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 2**16:
        head += bytes([0x80 | 126]) + n.to_bytes(2, "big")
    else:
        head += bytes([0x80 | 127]) + n.to_bytes(8, "big")
    return head + b"\0\0\0\0" + payload


def scenario_stalled(copies: int, env: dict[str, str] | None = None, extra_args: Sequence[str] = (),
                     give_up: float = 120.0, stagger: float = 0.0) -> dict[str, Any]:
    """`copies` clients each send the costliest answer this environment's limits admit (`answer_bound_msgpack`)
    from a socket with a 4 KiB receive buffer and read nothing (one every `stagger` seconds), on a fresh 1-worker
    server: how each ended (reset: dropped by JOINTLIMITS_WRITE_TIMEOUT; else the status it got) and when, the
    worker's peak RSS against the sizing rule, what /metrics counted, and a request alone afterwards."""
    from jointlimits.service import sizing
    from jointlimits.service.settings import Settings

    rule_mib = round(sizing.worker_bytes(_with_env(env, Settings)) / 2**20)
    body, content_type, accept, joints = _with_env(env, lambda: peak_cases()["answer_bound_msgpack"]())
    with Server(workers=1, env=env, extra_args=extra_args) as server:
        pid = server.worker_pids()[0]
        rss_before = rss_kib(pid)
        busy_before = scraped(server.port, "jointlimits_http_requests_total", route="/v1/evaluate", status="503")
        socks: list[socket.socket] = []
        sent_at: list[float] = []

        def send_all() -> None:
            for i in range(copies):
                time.sleep(stagger if i else 0.0)
                s = stalled_socket(server.port)  # connected now: an idle one would meet the head timeout
                s.sendall(post_bytes(body, content_type, accept))
                socks.append(s)
                sent_at.append(time.monotonic())

        sender = threading.Thread(target=send_all, daemon=True)
        sender.start()
        # Seconds from each request to its reset (None: not reset; it was answered, see `outcomes`).
        closed: list[float | None] = [None] * copies
        t0, asked = time.monotonic(), 0.0
        while time.monotonic() - t0 < give_up + copies * stagger:
            for i, s in enumerate(list(socks)):
                if closed[i] is None and dropped(s):
                    closed[i] = round(time.monotonic() - sent_at[i], 2)
            if len(socks) == copies and time.monotonic() - asked > 0.5:  # the rest refused 503 busy (not stalled)?
                asked = time.monotonic()
                busy = scraped(server.port, "jointlimits_http_requests_total", route="/v1/evaluate", status="503")
                if sum(t is not None for t in closed) + busy - busy_before >= copies:
                    break
            time.sleep(0.05)
        sender.join()
        peak = peak_kib(pid)
        outcomes = Counter("reset" if t is not None else _status_line(s) for s, t in zip(socks, closed))
        for s in socks:
            s.close()
        counted = connections_closed_counted(server.port, WRITE_REASONS)
        held = scraped(server.port, "jointlimits_inflight_budget_bytes")
        after = _one(server.port, body, content_type, accept)[0]
    return {
        "joints": joints, "body_bytes": len(body), "copies": copies, "outcomes": dict(outcomes),
        "closed_after_s": closed,
        "rss_before_mib": round((rss_before or 0) / 1024), "peak_rss_mib": round((peak or 0) / 1024),
        "rule_mib": rule_mib, "metrics_closed": counted, "budget_held_after": held, "alone_after": after,
    }  # fmt: skip


def _status_line(s: socket.socket) -> str:
    """The status of what the server answered on a connection it did not drop (read now), or why there is none."""
    s.settimeout(2.0)
    try:
        head = s.recv(64)
    except OSError as e:
        return type(e).__name__
    return head.split(b" ", 2)[1].decode() if head.startswith(b"HTTP/1.1 ") else "nothing"


def _with_env(env: dict[str, str] | None, fn: Callable[[], Any]) -> Any:
    """`fn()` with the variables of `env` set in this process's environment, then put back as they were."""
    saved = {k: os.environ.get(k) for k in (env or {})}
    try:
        os.environ.update(env or {})
        return fn()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def stalled_session(port: int, opening: bytes, evaluate: bytes, messages: int = 2) -> socket.socket:
    """A session opened with `opening` (msgpack), then `messages` evaluates sent, nothing read."""
    s, head = ws_upgrade(port, rcvbuf=4096)
    if not head.startswith(b"HTTP/1.1 101"):
        raise RuntimeError(f"no session: {head!r}")
    s.sendall(ws_frame(0x2, opening) + ws_frame(0x2, evaluate) * messages)
    return s


def session_frames(joints: int) -> tuple[bytes, bytes]:
    """A msgpack opening of `joints` active revolute joints (E+G+H) and an evaluate at its `q`."""
    from jointlimits.client import codec
    from jointlimits.schemas import binary as wire

    req = array_scene(joints, pairs=max(1, joints // 4))  # a body per two joints
    opening = codec.encode(req, binary=True)[0]
    import numpy as np

    q = wire.pack_array(np.asarray(req.q, dtype=np.float64), wire.FLOAT64)
    return opening, wire.dumps({"kind": "evaluate", "q": q})


def scenario_stalled_sessions(
    sessions: int = 4, joints: int = 4000, http_joints: int = 1000, requests: int = 20,
    env: dict[str, str] | None = None, extra_args: Sequence[str] = (), give_up: float = 120.0,
) -> dict[str, Any]:
    """HTTP beside stalled sessions, on a fresh 1-worker server: `requests` HTTP evaluates of `http_joints`
    (E+G+H, msgpack) alone, then while `sessions` sessions of `joints` joints have each sent two evaluates and
    read nothing: statuses and p50/p99 both times, the budget the sessions hold, when they were dropped."""
    opening, evaluate = session_frames(joints)
    from jointlimits.client import codec

    body = codec.encode(array_scene(http_joints, pairs=http_joints), binary=True)[0]
    B = "application/msgpack"

    def timed() -> dict[str, Any]:
        runs = [_one(server.port, body, B, B, timeout=60.0) for _ in range(requests)]
        secs = sorted(r[1] for r in runs)
        return {"statuses": dict(Counter(str(r[0]) for r in runs)), "p50_s": _pct(secs, 50), "p99_s": _pct(secs, 99)}

    with Server(workers=1, env=env, extra_args=extra_args) as server:
        pid = server.worker_pids()[0]
        alone = timed()
        rss_before = rss_kib(pid)
        t0 = time.monotonic()
        socks = [stalled_session(server.port, opening, evaluate) for _ in range(sessions)]
        time.sleep(1.0)  # each has opened and answered what it will before its write buffer fills
        held = scraped(server.port, "jointlimits_inflight_budget_bytes")
        opened = scraped(server.port, "jointlimits_session_messages_total", kind="open", outcome="ok")
        beside = timed()
        beside["seconds_after_stall"] = round(time.monotonic() - t0, 2)
        rss_stalled = rss_kib(pid)
        closed = watch_dropped(socks, t0, give_up)
        for s in socks:
            s.close()
        held_after = budget_given_back(server.port)
        counted = connections_closed_counted(server.port, WRITE_REASONS)
    return {
        "sessions": sessions, "sessions_opened": opened, "session_joints": joints, "http_joints": http_joints,
        "http_alone": alone,
        "http_beside_stalled": beside, "budget_held_by_stalled_bytes": held, "budget_held_after": held_after,
        "rss_before_mib": round((rss_before or 0) / 1024), "rss_stalled_mib": round((rss_stalled or 0) / 1024),
        "closed_after_s": closed, "metrics_closed": counted,
    }  # fmt: skip


def scenario_pingflood(
    seconds: float = 5.0, env: dict[str, str] | None = None, extra_args: Sequence[str] = (), max_bytes: int | None = None
) -> dict[str, Any]:
    """125-byte pings sent for up to `seconds` (and up to `max_bytes`, if given) on one upgraded connection that
    reads nothing, on a fresh 1-worker server: the bytes sent, the worker's RSS before and after, when the
    server dropped it."""
    ping = ws_frame(0x9, b"p" * 125) * 512  # 67 KB per send
    with Server(workers=1, env=env, extra_args=extra_args) as server:
        pid = server.worker_pids()[0]
        before = rss_kib(pid)
        s, head = ws_upgrade(server.port, rcvbuf=4096)
        if not head.startswith(b"HTTP/1.1 101"):
            raise RuntimeError(f"no session: {head!r}")
        s.settimeout(0.5)
        sent, t0, closed = 0, time.monotonic(), None
        while time.monotonic() - t0 < seconds and (max_bytes is None or sent < max_bytes):
            try:
                sent += s.send(ping)
            except TimeoutError:
                continue
            except OSError:
                closed = round(time.monotonic() - t0, 2)
                break
        if closed is None and dropped(s):
            closed = round(time.monotonic() - t0, 2)
        time.sleep(0.5)
        after, peak = rss_kib(pid), peak_kib(pid)
        s.close()
        counted = connections_closed_counted(server.port, WRITE_REASONS)
    return {
        "seconds": seconds, "ping_bytes_sent": sent, "dropped_after_s": closed, "rss_before_mib": round((before or 0) / 1024),
        "rss_after_mib": round((after or 0) / 1024), "peak_rss_mib": round((peak or 0) / 1024), "metrics_closed": counted,
    }  # fmt: skip


# --------------------------------------------------------------------------- command line


# --------------------------------------------------------------------------- behind a load balancer (HAProxy)

LB_PAGE = Path(__file__).resolve().parent.parent / "docs" / "load-balancers.md"
LB_CHECK_MS = 100
"""HAProxy's check interval in the drill (the docs' 1 s); with `fall 2` a draining replica is out within ~0.2 s."""
LB_DELAY = 1.0
"""The replicas' `--shutdown-delay` in the drill (the docs' 5 s): above check interval x fall, as the docs ask."""


def docs_block(lang: str, page: Path = LB_PAGE) -> str:
    """The first block of `lang` of a docs page, as it is."""
    return page.read_text().split(f"```{lang}\n", 1)[1].split("```", 1)[0]


def _rewrite(text: str, pattern: str, new: Callable[[re.Match[str]], str], count: int) -> str:
    text, n = re.subn(pattern, new, text, flags=re.MULTILINE)
    if n != count:
        raise ValueError(f"the docs' configuration changed: {n} matches of {pattern!r}, expected {count}")
    return text


def haproxy_config(front: int, backends: Sequence[int], check_ms: int = LB_CHECK_MS) -> str:
    """docs/load-balancers.md's HAProxy configuration as it is, but for its addresses (the frontend and the
    replicas on loopback ports) and its check interval."""
    ports = iter(backends)
    text = _rewrite(docs_block("haproxy"), r"^(\s*bind )\S+", lambda m: f"{m[1]}{LOOPBACK}:{front}", 1)
    text = _rewrite(text, r"^(\s*server \S+ )\S+", lambda m: f"{m[1]}{LOOPBACK}:{next(ports)}", len(backends))
    return _rewrite(text, r"\binter 1s\b", lambda m: f"inter {check_ms}ms", 1)


def nginx_config(front: int, backends: Sequence[int]) -> str:
    """docs/load-balancers.md's nginx configuration as it is, but for its addresses (loopback ports)."""
    ports = iter(backends)
    text = _rewrite(docs_block("nginx"), r"^(\s*listen )\d+", lambda m: f"{m[1]}{LOOPBACK}:{front}", 1)
    return _rewrite(text, r"^(\s*server )[0-9.]+:\d+", lambda m: f"{m[1]}{LOOPBACK}:{next(ports)}", len(backends))


class Proxy:
    """A proxy (`haproxy`, `nginx`) in the foreground in its own process group, in front on `front`."""

    def __init__(self, args: Sequence[str], front: int, check: Sequence[str]) -> None:
        done = subprocess.run(list(check), capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(check)}: {done.stdout}{done.stderr}")
        self.front = front
        self.proc = subprocess.Popen(list(args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
        deadline = time.monotonic() + 10
        while get(front, "/readyz", timeout=1.0)[0] != 200:
            if time.monotonic() > deadline or self.proc.poll() is not None:
                self.stop()
                raise RuntimeError(f"{args[0]} did not answer on {front}")
            time.sleep(0.05)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)


def haproxy(config: str, front: int) -> Proxy:
    path = Path(os.environ.get("TMPDIR", "/tmp")) / f"jointlimits-haproxy-{front}.cfg"
    path.write_text(config)
    return Proxy(["haproxy", "-db", "-f", str(path)], front, ["haproxy", "-c", "-q", "-f", str(path)])


@dataclass
class Tally:
    """One client kind's count: answered, and what failed (its kind -> times)."""

    ok: int = 0
    failed: Counter[str] = field(default_factory=Counter)
    inexact: int = 0  # sessions: committed coordinates not the same bits as an uninterrupted session's
    resumed: int = 0  # sessions: new connections the SDK opened by itself

    def report(self) -> dict[str, Any]:
        out: dict[str, Any] = {"ok": self.ok, "failed": sum(self.failed.values())}
        if self.failed:
            out["what"] = dict(self.failed)
        return out


def _failure(e: Exception) -> str:
    return f"{type(e).__name__}: {str(e)[:100]}"


def fresh_post(port: int, raw: bytes) -> str | None:
    """`raw` (asking `Connection: close`) on a connection of its own, read to its end: None for a whole 200,
    else what failed (the status, or the connection's error); nothing is retried."""
    try:
        with socket.create_connection((LOOPBACK, port), timeout=60) as s:
            s.sendall(raw)
            data = b"".join(iter(lambda: s.recv(1 << 16), b""))
    except OSError as e:
        return type(e).__name__
    head, _, body = data.partition(b"\r\n\r\n")
    status = head[9:12].decode(errors="replace") or "no answer"
    length = re.search(rb"(?im)^content-length: *(\d+)", head)
    if status == "200" and length is not None and int(length[1]) != len(body):
        return "truncated"
    return None if status == "200" else status


def lb_body(n: int) -> dict[str, Any]:
    """`scene(n)` asking energy and gradient: at 1000 joints a 0.4 MB JSON body (over HAProxy's 16 KiB buffer)."""
    return {**scene(n), "outputs": ["energy", "gradient"]}


def session_request(n: int) -> tuple[Any, Callable[[int], Any]]:
    """`n` revolute joints about z between consecutive bodies, limits +-0.5; `q_at(step)` turns every odd body
    0.2 rad per step, so each joint passes pi after 16 steps (its committed angle is the unwrapped one)."""
    import numpy as np

    from jointlimits.client import JointBatch, request_from_arrays

    def q_at(step: int) -> Any:
        a = 0.2 * step * (np.arange(n + 1) % 2)
        q = np.zeros((n + 1, 12))
        q[:, 3], q[:, 4], q[:, 6], q[:, 7], q[:, 11] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a), 1.0
        return q

    ids = [[k, k + 1] for k in range(n)]
    batch = JointBatch.of(670, ids, [[[0, 0, 0], [0, 0, 1]]] * n, -0.5, 0.5, 10.0)
    return request_from_arrays(q_at(0), [batch], q_prev=q_at(0), q_ref=q_at(0)), q_at


def _sdk_loop(front: int, n: int, stop: threading.Event, tally: Tally) -> None:
    from jointlimits.client import Client
    from jointlimits.client.model import as_request

    request = as_request(lb_body(n))
    with Client(f"http://{LOOPBACK}:{front}") as client:
        for _ in range(MAX_REQUESTS_PER_CLIENT):
            if stop.is_set():
                return
            try:
                client.evaluate(request)
                tally.ok += 1
            except Exception as e:
                tally.failed[_failure(e)] += 1


def _fresh_loop(front: int, n: int, stop: threading.Event, tally: Tally) -> None:
    raw = http_request("POST", "/v1/evaluate", json.dumps(lb_body(n)).encode(), {"Connection": "close"})
    for _ in range(MAX_REQUESTS_PER_CLIENT):
        if stop.is_set():
            return
        what = fresh_post(front, raw)
        if what is None:
            tally.ok += 1
        else:
            tally.failed[what] += 1


def _session_loop(front: int, n: int, stop: threading.Event, tally: Tally) -> None:
    """evaluate, commit, step after step through the SDK's session (resuming by itself); then every committed
    coordinate against an in-process session that never lost its connection, bitwise."""
    from jointlimits.client import Client, LocalClient

    request, q_at = session_request(n)
    committed = []
    try:
        with Client(f"http://{LOOPBACK}:{front}") as client, client.session(request) as s:
            connection = s._ws
            # Until the scenario's end (`stop`), not a count of steps: a session that stops stepping before its
            # replica restarts sees no resume. A cap of 2,000 steps was ~14 s of rolling restart at 58 steps/s here
            # (2 joints, loaded): a machine ~2.5x faster could reach it first (a cap of 400 here: 2 runs of 3 failed).
            for step in range(1, MAX_REQUESTS_PER_CLIENT):
                if stop.is_set():
                    break
                s.evaluate(q_at(step))
                committed.append(s.commit(q_at(step))[0].tobytes())
                tally.ok += 1
                tally.resumed += s._ws is not connection
                connection = s._ws
    except Exception as e:  # the loop stops at its first error: the state after it is not the solver's
        tally.failed[_failure(e)] += 1
    with LocalClient().session(request) as ref:
        tally.inexact = sum(ref.commit(q_at(step))[0].tobytes() != got for step, got in enumerate(committed, 1))


def under_load(front: int, joints: Sequence[int], action: Callable[[], Any], sessions: bool = False,
               warmup: float = 0.5, settle: float = 0.5) -> dict[str, Any]:
    """One SDK client (keep-alive) and one fresh-connection client per size in `joints` (and a session loop per
    size) while `action` runs: each kind's answered and failed requests, and what `action` returned."""
    stop = threading.Event()
    kinds: dict[str, Callable[[int, int, threading.Event, Tally], None]] = {"sdk": _sdk_loop, "fresh": _fresh_loop}
    if sessions:
        kinds["session"] = _session_loop
    tallies = {(kind, n): Tally() for kind in kinds for n in joints}
    threads = [threading.Thread(target=kinds[kind], args=(front, n, stop, t), daemon=True) for (kind, n), t in tallies.items()]
    for t in threads:
        t.start()
    time.sleep(warmup)
    try:
        done = action()
        time.sleep(settle)
    finally:
        stop.set()
        for t in threads:
            t.join(60)
    out: dict[str, Any] = {f"{kind} {n} joints": t.report() for (kind, n), t in tallies.items()}
    for (kind, n), t in tallies.items():
        if kind == "session":
            out[f"{kind} {n} joints"].update(inexact=t.inexact, resumed=t.resumed)
    out["action"] = done
    return out


def _restart(replicas: list[Server], k: int, args: Sequence[str]) -> None:
    old = replicas[k]
    old.stop()  # already exited: its process group and log closed
    replicas[k] = Server(workers=1, extra_args=args, port=old.port)
    replicas[k].wait_ready()
    time.sleep(3 * LB_CHECK_MS / 1000)  # `rise 2`: HAProxy takes it back


def rolling_restart(replicas: list[Server], args: Sequence[str]) -> dict[str, Any]:
    """SIGTERM each replica in turn, wait for its exit, start it again on its port: exit codes, seconds to exit."""
    codes, seconds = [], []
    for k in range(len(replicas)):
        t0 = time.monotonic()
        replicas[k].proc.send_signal(signal.SIGTERM)
        codes.append(replicas[k].proc.wait(LB_DELAY + 30))
        seconds.append(round(time.monotonic() - t0, 2))
        _restart(replicas, k, args)
    return {"exit_codes": codes, "seconds_to_exit": seconds}


def kill_one(replicas: list[Server], args: Sequence[str], down: float = 1.0) -> dict[str, Any]:
    """SIGKILL the first replica (its process group), `down` seconds under load, start it again."""
    os.killpg(replicas[0].proc.pid, signal.SIGKILL)
    code = replicas[0].proc.wait(10)
    time.sleep(down)
    _restart(replicas, 0, args)
    return {"exit_code": code}


def scenario_lb(joints: Sequence[int] = (2, 1000), steady: float = 3.0) -> dict[str, Any]:
    """HAProxy (docs/load-balancers.md's configuration) in front of three `jointlimits serve --workers 1` replicas
    on loopback: steady load, a rolling restart with session loops, a SIGKILL; per scenario and client kind
    (SDK on keep-alive, a new connection per request retrying nothing, sessions) the answered and failed
    requests. Bounded: each loop by MAX_REQUESTS_PER_CLIENT, each scenario by its action."""
    if shutil.which("haproxy") is None:
        raise RuntimeError("haproxy is not installed (Debian: apt-get install haproxy)")
    args = ["--shutdown-delay", str(LB_DELAY), "--access-log", "false"]
    replicas = [Server(workers=1, extra_args=args) for _ in range(3)]
    lb = None
    try:
        for r in replicas:
            r.wait_ready()
        front = free_port()
        lb = haproxy(haproxy_config(front, [r.port for r in replicas]), front)
        return {
            "steady": under_load(front, joints, lambda: time.sleep(steady)),
            "rolling restart": under_load(front, joints, lambda: rolling_restart(replicas, args), sessions=True),
            "SIGKILL": under_load(front, joints, lambda: kill_one(replicas, args)),
        }
    finally:
        if lb is not None:
            lb.stop()
        for r in replicas:
            r.stop()
            r.log_path.unlink(missing_ok=True)


def print_lb(report: dict[str, Any]) -> None:
    """Failed requests per scenario and client kind, one line each."""
    for scenario, kinds in report.items():
        for kind, t in kinds.items():
            if kind != "action":
                what = f"  {t['what']}" if t.get("what") else ""
                exact = f", {t['inexact']} inexact, {t['resumed']} resumed" if "inexact" in t else ""
                print(f"{scenario:16} {kind:22} {t['ok']:6} ok {t['failed']:4} failed{exact}{what}")


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.drills", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--scenario",
        choices=["mixed", "flood", "kill", "sigterm", "slowloris", "answer", "peak", "burst", "stalled", "stalled-sessions",
                 "pingflood", "connections", "lb", "all"],
        default="mixed",
    )
    p.add_argument("--spawn", action="store_true", help="start `jointlimits serve` on a free loopback port")
    p.add_argument("--port", type=int, default=8000, help="port of a running service on 127.0.0.1 (without --spawn)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--clients", type=int, default=16)
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--max-body-bytes", type=int, default=1_000_000, help="the spawned server's limit (flood)")
    p.add_argument("--max-joints", type=int, default=1_000, help="the spawned server's limit (flood)")
    p.add_argument("--token", default=os.environ.get("JOINTLIMITS_TOKEN") or None)
    p.add_argument("--slow", type=int, default=50, help="slowloris connections (slowloris)")
    p.add_argument("--header-timeout", type=float, default=3.0, help="the spawned server's header timeout (slowloris)")
    p.add_argument("--body-timeout", type=float, default=4.0, help="the spawned server's body timeout (slowloris)")
    p.add_argument("--write-timeout", type=float, default=5.0,
                   help="the spawned server's write timeout (stalled, stalled-sessions, pingflood)")
    p.add_argument("--held", type=int, default=3000, help="connections the flood opens (connections)")
    p.add_argument("--nofile", help="the spawned server's open-file limit, soft:hard, through prlimit (connections)")
    p.add_argument("--stagger", type=float, default=0.0, help="seconds between the stalled clients' requests (stalled)")
    a = p.parse_args(argv)
    if a.duration > 600 or a.clients > 256 or a.slow > 512 or a.held > 20000 or max(a.header_timeout, a.body_timeout, a.write_timeout) > 120:
        p.error("bounded: --duration <= 600, --clients <= 256, --slow <= 512, --held <= 20000, timeouts <= 120")
    limits = ["--max-body-bytes", str(a.max_body_bytes), "--max-joints", str(a.max_joints)]
    limits += ["--header-timeout", str(a.header_timeout), "--body-timeout", str(a.body_timeout)]
    env: dict[str, str] = {}  # the production defaults: JSON access log on (to a file)

    def spawned() -> Server:
        return Server(a.workers, limits, env)

    report: dict[str, Any] = {"workers": a.workers, "clients": a.clients, "duration_s": a.duration}
    if a.scenario == "lb":  # its own three replicas and HAProxy
        result = scenario_lb(steady=min(a.duration, 60.0))
        print_lb(result)
        print(json.dumps({"lb": result}, indent=2))
        return 0
    scenarios = ["mixed", "flood", "kill", "sigterm", "slowloris", "answer"] if a.scenario == "all" else [a.scenario]
    if a.scenario in ("peak", "burst", "stalled", "stalled-sessions", "pingflood", "connections"):
        # each on its own fresh 1-worker server, at this environment's limits
        if not a.spawn:
            p.error(f"--scenario {a.scenario} needs --spawn (it reads the worker's memory)")
        write = ["--write-timeout", str(a.write_timeout)]
        if a.scenario == "peak":
            result = scenario_peak(env)
        elif a.scenario == "burst":
            result = scenario_burst(min(a.clients, 32), env)
        elif a.scenario == "stalled":
            result = scenario_stalled(min(a.clients, 32), env, write, give_up=min(a.duration, 120.0), stagger=min(a.stagger, 10.0))
        elif a.scenario == "stalled-sessions":
            result = scenario_stalled_sessions(min(a.clients, 16), env=env, extra_args=write, give_up=min(a.duration, 120.0))
        elif a.scenario == "connections":
            result = scenario_connections(a.held, nofile=a.nofile)
        else:
            result = scenario_pingflood(min(a.duration, 30.0), env, write)
        print(json.dumps({a.scenario: result}, indent=2))
        return 0
    for name in scenarios:
        if not a.spawn:
            if name in ("kill", "sigterm"):
                p.error(f"--scenario {name} needs --spawn (it signals the server)")

            class _Running:
                port = a.port

                def worker_pids(self) -> list[int]:
                    return []

            target: Any = _Running()
            report[name] = _run(name, target, a)
            continue
        # The answer drill needs the default limits (its heavy requests are over the flood's 1 MB bodies).
        with Server(a.workers, [], env) if name == "answer" else spawned() as server:
            report[name] = _run(name, server, a)
    print(json.dumps(report, indent=2))
    return 0


def _run(name: str, server: Any, a: argparse.Namespace) -> dict[str, Any]:
    if name == "mixed":
        return scenario_mixed(server, a.clients, a.duration, a.token)
    if name == "flood":
        return scenario_flood(server, a.clients, min(a.duration, 10.0), a.max_body_bytes, a.max_joints, a.token)
    if name == "kill":
        return scenario_kill(server, a.clients, min(a.duration, 10.0), a.token)
    if name == "slowloris":
        return scenario_slowloris(server, a.clients, a.slow, a.header_timeout, a.body_timeout, a.token)
    if name == "answer":
        return scenario_answer(server, a.clients, min(a.duration, 10.0), token=a.token)
    return scenario_sigterm(server, a.clients, token=a.token)


if __name__ == "__main__":
    sys.exit(main())
