"""Service configuration, from the environment (`JOINTLIMITS_*`) or explicit arguments."""

from __future__ import annotations

import os
from dataclasses import dataclass, field


def _env(name: str, default: str) -> str:
    return os.environ.get(f"JOINTLIMITS_{name}", default)


@dataclass(frozen=True)
class Settings:
    max_body_bytes: int = field(default_factory=lambda: int(_env("MAX_BODY_BYTES", str(256 * 2**20))))
    """Largest request body accepted; larger answers 413 before it is parsed."""
    max_joints: int = field(default_factory=lambda: int(_env("MAX_JOINTS", "1000000")))
    """Most joints (over all batches) in one request; more answers 413."""
    # WebSocket sessions (/v1/sessions, service/http/sessions.py); a scene's joints are bounded by max_joints.
    max_sessions: int = field(default_factory=lambda: int(_env("MAX_SESSIONS", "64")))
    """Open sessions per worker process; one more is closed at once with code 4429."""
    max_frame_bytes: int = field(default_factory=lambda: int(_env("MAX_FRAME_BYTES", str(64 * 2**20))))
    """Largest WebSocket message a session accepts; larger closes the session with code 1009."""
    max_session_joints: int = field(default_factory=lambda: int(_env("MAX_SESSION_JOINTS", "1000000")))
    """Joints all open sessions of a worker may hold together (a prepared scene keeps ~0.7 KiB per joint);
    a scene that would pass it is refused (413, then close 4413)."""
    session_idle_seconds: float = field(default_factory=lambda: float(_env("SESSION_IDLE_SECONDS", "300")))
    """A session with no message from its client for this long is closed with code 4408."""
    token: str | None = field(default_factory=lambda: _env("TOKEN", "") or None)
    """Bearer token required on /v1/evaluate when set; the API is open when unset."""
    cors_origins: tuple[str, ...] = field(
        default_factory=lambda: tuple(o for o in _env("CORS_ORIGINS", "").split(",") if o)
    )
    """Origins allowed by CORS; CORS is off when empty."""
    keep_heap: bool = field(default_factory=lambda: _env("KEEP_HEAP", "true").strip().lower() not in ("0", "false", "no", "off"))
    """Keep freed memory in the worker's heap (`jointlimits.service.core.heap`): no page faults per request, at the
    price of holding the largest request's memory."""
    header_timeout: float = field(default_factory=lambda: float(_env("HEADER_TIMEOUT", "10")))
    """Seconds a connection has to send a request's head (line and headers); then 408 and closed
    (enforced by `jointlimits.service.http.timeouts.ReadTimeoutProtocol`, which `jointlimits serve` runs)."""
    body_timeout: float = field(default_factory=lambda: float(_env("BODY_TIMEOUT", "30")))
    """Seconds from a request's head to the end of its body; then 408 and the connection closed. Also the
    bound on a WebSocket session message from its first byte to its last (then close 1008)."""
    write_timeout: float = field(default_factory=lambda: float(_env("WRITE_TIMEOUT", "30")))
    """Seconds a connection's write buffer may stay full (the client not reading what it was sent: an answer,
    session replies, a close frame, pongs); then the connection is dropped and what it held freed
    (`jointlimits.service.http.timeouts`)."""
    # Admission by cost (service/http/limits.py, docs/deployment.md, "Limits"): checked before any evaluation.
    max_batches: int = field(default_factory=lambda: int(_env("MAX_BATCHES", "4096")))
    """Most batches in one request (each costs ~0.5 ms of fixed work); more answers 413."""
    max_answer_bytes: int = field(default_factory=lambda: int(_env("MAX_ANSWER_BYTES", str(256 * 2**20))))
    """Largest answer, bounded from joints x outputs x encoding before any work; larger answers 413."""
    request_timeout: float = field(default_factory=lambda: float(_env("REQUEST_TIMEOUT", "60")))
    """Seconds one evaluation may take (parse, core, encode); past it 503 with Retry-After."""
    queue_timeout: float = field(default_factory=lambda: float(_env("QUEUE_TIMEOUT", "30")))
    """Seconds a request may wait for the worker's memory budget of requests in flight
    (`service/http/budget.py`) before it starts; past it 503 `busy` with Retry-After, its body unread."""
    max_json_values: int = field(default_factory=lambda: int(_env("MAX_JSON_VALUES", "2000000")))
    """Most values (numbers and list items, counted as commas + 1) in a JSON body: parsing costs ~90 bytes
    and 0.2-2.5 us each (more under load), whatever their length; more answers 413 before parsing."""
