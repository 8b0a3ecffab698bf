"""Observability: JSON logs, one JSON access-log line per request, Prometheus metrics.

`ObservabilityMiddleware` is a pure ASGI middleware (`BaseHTTPMiddleware` would buffer bodies and cost a task per
request). The joint counts come from `state.joints` and `state.joints_by_constitution`, set by the evaluate route
once the body is parsed; a request refused before that logs `joints: null`.

Several workers: `prometheus_client` sums over processes only in its multiprocess mode, entered when
`PROMETHEUS_MULTIPROC_DIR` is set before it is imported; `jointlimits serve --workers N` sets it, so `/metrics` on
any worker reports all of them, including workers that died and were replaced.
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client import multiprocess
from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

ACCESS_LOGGER = "jointlimits.access"
_REQUEST_ID = re.compile(r"^[A-Za-z0-9._:\-]{1,128}$")

# Seconds. The evaluate route spans ~1 ms (one joint) to seconds (10^5 joints with Hessians).
LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class JsonFormatter(logging.Formatter):
    """One JSON object per line: `ts`, `level`, `logger`, `msg`, plus a record's `fields`."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        fields = getattr(record, "fields", None)
        if isinstance(fields, Mapping):
            out.update(fields)
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, separators=(",", ":"), default=str)


def log_config(level: str = "info", access_log: bool = True) -> dict[str, Any]:
    """uvicorn's `logging.config.dictConfig`: JSON lines on stdout; uvicorn's access log replaced by ours."""
    level = level.upper()
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"json": {"()": "jointlimits.service.observability.JsonFormatter"}},
        "handlers": {"stdout": {"class": "logging.StreamHandler", "formatter": "json", "stream": "ext://sys.stdout"}},
        "loggers": {
            "uvicorn": {"handlers": ["stdout"], "level": level, "propagate": False},
            "uvicorn.error": {"level": level},
            "uvicorn.access": {"handlers": [], "level": "CRITICAL", "propagate": False},
            "jointlimits": {"handlers": ["stdout"], "level": level, "propagate": False},
            ACCESS_LOGGER: {"level": "INFO" if access_log else "CRITICAL"},
        },
    }


def peer(client: Any) -> str | None:
    """`host:port` of a scope's `client` (a tuple or Starlette's `Address`)."""
    return f"{client[0]}:{client[1]}" if client else None


LIFESPAN_METRICS = "jointlimits_metrics"
"""The application's `Metrics` in its lifespan state: what uvicorn hands its protocols (`app_state`),
so the connection layer counts what happens before any request exists."""

_LIVE = {"multiprocess_mode": "livesum"}  # gauges: summed over the live workers
_METRICS: tuple[tuple[str, Any, str, str, tuple[str, ...], dict[str, Any]], ...] = (
    ("requests", Counter, "jointlimits_http_requests_total",
     "HTTP requests answered, by method, route template and status code.", ("method", "route", "status"), {}),
    ("latency", Histogram, "jointlimits_http_request_duration_seconds",
     "Time from the request's arrival to the end of its response, by method and route template.",
     ("method", "route"), {"buckets": LATENCY_BUCKETS}),
    ("joints", Counter, "jointlimits_joints_evaluated_total",
     "Joints evaluated in successful requests, by constitution UID.", ("constitution",), {}),
    ("in_flight", Gauge, "jointlimits_http_requests_in_flight",
     "HTTP requests being handled now (summed over live workers).", (), _LIVE),
    # The memory budgets (service/http/budget.py).
    ("budget_held", Gauge, "jointlimits_inflight_budget_bytes",
     "Bytes of the workers' memory budgets held by requests in flight (summed over live workers).", (), _LIVE),
    ("uploads_held", Gauge, "jointlimits_upload_budget_bytes",
     "Bytes of the workers' upload budgets held by request bodies being received (summed over live workers).",
     (), _LIVE),
    ("budget_queued", Gauge, "jointlimits_inflight_budget_queued",
     "Requests waiting for their worker's memory budget (summed over live workers).", (), _LIVE),
    # Connections closed by service/http/timeouts.py: most before any request exists.
    ("connections_closed", Counter, "jointlimits_connections_closed_total",
     "Connections the server closed, by reason: for want of a complete request head within "
     "JOINTLIMITS_HEADER_TIMEOUT (silent: not a byte, closed without an answer; slow_head: part of a head, "
     "answered 408); head_too_large: a head past 64 KiB (431); heads_full: the worker's unfinished and queued heads "
     "past 16 MiB (503); connections_full: one past JOINTLIMITS_MAX_CONNECTIONS (503); pipelined: a request pipelined "
     "past 16 queued (the answers owed are sent, then closed); body_chunks: a body in chunks or reads of under 256 "
     "bytes (413, closed); slow_read: a full write buffer for "
     "JOINTLIMITS_WRITE_TIMEOUT (dropped); slow_message: a session message not received within "
     "JOINTLIMITS_BODY_TIMEOUT (close 1008).", ("reason",), {}),
    # WebSocket sessions (service/http/sessions.py).
    ("sessions_open", Gauge, "jointlimits_sessions_open", "WebSocket sessions open now (summed over live workers).",
     (), _LIVE),
    ("sessions", Counter, "jointlimits_sessions_total",
     "WebSocket sessions ended, by reason (client, disconnect, idle, frame_too_large, invalid_utf8, protocol_error, "
     "slow_message, uploads_full, scene_too_large, too_many_sessions, shutdown, error).", ("reason",), {}),
    ("session_messages", Counter, "jointlimits_session_messages_total",
     "Session messages handled, by kind (open, evaluate, commit, update, close, invalid) and outcome (ok, fault).",
     ("kind", "outcome"), {}),
    ("session_latency", Histogram, "jointlimits_session_message_duration_seconds",
     "Time from a session message's arrival to its reply being sent, by kind.", ("kind",),
     {"buckets": (0.0001, 0.00025, 0.0005, *LATENCY_BUCKETS)}),
)


def multiprocess_dir() -> str | None:
    return os.environ.get("PROMETHEUS_MULTIPROC_DIR") or os.environ.get("prometheus_multiproc_dir")


class Metrics:
    """The service's metrics (attributes named as in `_METRICS`), one set per application: a registry of its own in
    one process (two apps in a test process do not share counts); in multiprocess mode, unregistered metrics whose
    values live in the shared directory, collected per scrape."""

    def __init__(self) -> None:
        self.multiprocess = multiprocess_dir() is not None
        self.registry = None if self.multiprocess else CollectorRegistry()
        for attr, kind, name, doc, labels, extra in _METRICS:
            setattr(self, attr, kind(name, doc, labels, registry=self.registry, **extra))
        if self.multiprocess:
            _forget_dead_workers()

    def exposition(self) -> bytes:
        registry = self.registry
        if registry is None:
            registry = CollectorRegistry()
            multiprocess.MultiProcessCollector(registry)
        return generate_latest(registry)


def _forget_dead_workers() -> None:
    """Drop the live-gauge files of workers gone (a killed worker cannot); their counters stay: their requests
    did happen."""
    path = multiprocess_dir()
    for f in Path(path).glob("gauge_live*_*.db") if path else ():
        try:
            pid = int(f.stem.rsplit("_", 1)[1])
            os.kill(pid, 0)
        except ProcessLookupError:
            multiprocess.mark_process_dead(pid, path)
        except (ValueError, PermissionError):
            continue


class ObservabilityMiddleware:
    """Request id (the caller's `X-Request-ID` when short and printable, else a new one, echoed in the answer),
    JSON access log and metrics for every HTTP request; serves `GET /metrics`."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app, self.metrics = app, metrics
        self._known: frozenset[str] | None = None  # the app's route paths without parameters, once read
        self.log = logging.getLogger(ACCESS_LOGGER)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        start = time.perf_counter()
        request_id = _request_id(scope)
        state = scope.setdefault("state", {})
        state["request_id"] = request_id
        status, bytes_in = 500, 0

        async def receive_counting() -> Message:
            nonlocal bytes_in
            message = await receive()
            bytes_in += len(message.get("body", b""))
            return message

        async def send_tagged(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                message["headers"] = [*message.get("headers", []), (b"x-request-id", request_id.encode())]
            await send(message)

        self.metrics.in_flight.inc()
        try:
            if scope["path"] == "/metrics" and scope["method"] in ("GET", "HEAD"):
                scope["route"] = _MetricsRoute
                body = self.metrics.exposition()
                headers = [(b"content-type", CONTENT_TYPE_LATEST.encode()), (b"content-length", b"%d" % len(body))]
                await send_tagged({"type": "http.response.start", "status": 200, "headers": headers})
                await send_tagged({"type": "http.response.body", "body": body})
            else:
                await self.app(scope, receive_counting, send_tagged)
        finally:
            self.metrics.in_flight.dec()
            self._record(scope, state, request_id, status, time.perf_counter() - start, bytes_in)

    def _record(self, scope: Scope, state: dict[str, Any], request_id: str, status: int, elapsed: float,
                bytes_in: int) -> None:
        route = getattr(scope.get("route"), "path", None)
        if route is None:  # refused before routing (401, 413 from a middleware): labelled with its route too;
            # any other path is "unmatched" (bounded labels)
            if self._known is None:  # the app's own routes, and its routers' (its OpenAPI paths)
                app = scope["app"]
                paths = [*(getattr(r, "path", None) for r in app.routes), *app.openapi().get("paths", {})]
                self._known = frozenset(p for p in paths if isinstance(p, str) and "{" not in p)
            route = scope["path"] if scope["path"] in self._known else "unmatched"
        method = scope["method"]
        self.metrics.requests.labels(method, route, str(status)).inc()
        self.metrics.latency.labels(method, route).observe(elapsed)
        by_uid = state.get("joints_by_constitution")
        if status == 200 and isinstance(by_uid, Mapping):
            for uid, n in by_uid.items():
                if n:
                    self.metrics.joints.labels(str(uid)).inc(n)
        if self.log.isEnabledFor(logging.INFO):
            fields = {"request_id": request_id, "method": method, "path": scope["path"], "route": route,
                      "status": status, "latency_ms": round(elapsed * 1e3, 3), "bytes_in": bytes_in,
                      "joints": state.get("joints"), "client": peer(scope.get("client")), "pid": os.getpid()}
            self.log.info("request", extra={"fields": fields})


class _MetricsRoute:
    path = "/metrics"


def _request_id(scope: Scope) -> str:
    rid = Headers(scope=scope).get("x-request-id", "")
    return rid if _REQUEST_ID.match(rid) else uuid.uuid4().hex
