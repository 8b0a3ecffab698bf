"""Service configuration: one table, `Settings`, whose fields are also the flags of `jointlimits serve`.

A field `max_body_bytes` is the flag `--max-body-bytes` and the variable `JOINTLIMITS_MAX_BODY_BYTES`;
a flag wins over the variable, which wins over the default. `Settings()` reads each field not given
from the environment; `Settings.environ()` is what makes `Settings()` in a worker process equal to it.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, NamedTuple

ENV_PREFIX = "JOINTLIMITS_"
_FROM_ENV: Any = object()  # a field not given: its variable, else its default


# Readers of a flag's or a variable's text; argparse shows an ArgumentTypeError's message as it is.
def positive_int(text: str, what: str = "a positive integer") -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return n


def positive_float(text: str) -> float:
    return _seconds(text, False, "a positive number of seconds")


def seconds(text: str) -> float:
    """A duration that may be 0 (nothing to wait)."""
    return _seconds(text, True, "0 or a positive number of seconds")


def _seconds(text: str, zero: bool, what: str) -> float:
    """A finite duration, above 0 (or 0 too, with `zero`); text that is no number is refused in the same words."""
    try:
        x = float(text)
    except ValueError:
        x = float("nan")
    if not ((0 <= x if zero else 0 < x) and x < float("inf")):
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return x


def boolean(text: str) -> bool:
    v = text.strip().lower()
    if v in ("1", "true", "yes", "on"):
        return True
    if v in ("0", "false", "no", "off", ""):
        return False
    raise argparse.ArgumentTypeError(f"must be true or false (or 1/0, yes/no, on/off), got {text!r}")


def bearer_token(text: str) -> str | None:
    """A token the Authorization header can carry (none if empty): the server refuses another at start, the SDK's
    clients at construction (a client could send no other). ValueError: it has no flag for argparse to word."""
    if text != text.strip() or not all(" " <= c <= "~" for c in text):
        raise ValueError("a bearer token is printable ASCII, without line breaks or spaces around it")
    return text or None


def _setting(default: Any, parse: Callable[[str], Any], help: str, flag: bool = True) -> Any:
    """A row of the table: its default, how a flag's or a variable's text reads, the flag's help, whether
    there is a flag."""
    return field(default=_FROM_ENV, metadata={"row": (default, parse, help, flag)})


@dataclass(frozen=True, kw_only=True)
class Settings:
    """The table: each field's default, reader and flag help (`_setting`). A field not given is read from
    its variable, else its default."""

    max_body_bytes: int = _setting(256 * 2**20, positive_int, "largest request body; larger answers 413")
    max_joints: int = _setting(1_000_000, positive_int, "most joints in one request; more answers 413")
    # Admission by cost and the per-request deadline (service/http/limits.py; docs/deployment.md, "Limits").
    max_batches: int = _setting(4096, positive_int, "most batches in one request; more answers 413")
    max_answer_bytes: int = _setting(
        256 * 2**20, positive_int,
        "largest answer, bounded before any work from joints x outputs x encoding; larger answers 413",
    )
    max_json_values: int = _setting(
        2_000_000, positive_int,
        "most values in a JSON body (commas + 1, 2 x lists and objects, or 8 x keys: the most); more answers 413 unparsed",
    )
    request_timeout: float = _setting(
        60.0, positive_float, "seconds an evaluation may take (parse, core, encode); past it 503 with Retry-After"
    )
    queue_timeout: float = _setting(
        30.0, positive_float,
        "seconds a request may wait for the worker's memory budget of requests in flight before it starts; "
        "past it 503 busy with Retry-After, nothing evaluated",
    )
    # Text (a flag, a variable) is split at commas by __post_init__.
    cors_origins: tuple[str, ...] = _setting("", str, "comma-separated origins allowed by CORS; empty = CORS off")
    # No flag: a flag shows in `ps` (`jointlimits serve --token-file` reads it from a file instead).
    token: str | None = _setting(
        None, bearer_token, "bearer token required on /v1/*; the API is open when unset", flag=False
    )
    # WebSocket sessions (service/http/sessions.py); a scene's joints are bounded by max_joints too.
    max_sessions: int = _setting(64, positive_int, "open WebSocket sessions per worker; one more is closed with code 4429")
    max_session_joints: int = _setting(
        1_000_000, positive_int,
        "joints all open sessions of a worker hold together; a scene past it is refused with 413, then code 4413",
    )
    max_frame_bytes: int = _setting(
        64 * 2**20, positive_int, "largest session message; larger closes the session with code 1009"
    )
    session_idle_seconds: float = _setting(
        300.0, positive_float, "a session without a message for this long is closed with code 4408"
    )
    # Connection deadlines, enforced by the protocols of service/http/timeouts.py (`jointlimits serve` runs them).
    header_timeout: float = _setting(
        10.0, positive_float,
        "seconds a connection has to send a request's headers, from connecting (on a keep-alive connection, from "
        "the next request's first byte); then 408 and closed: slowloris",
    )
    body_timeout: float = _setting(  # also a session message's bound, from its first byte to its last (close 1008)
        30.0, positive_float, "seconds from a request's headers to the end of its body; then 408 and closed"
    )
    write_timeout: float = _setting(
        30.0, positive_float,
        "seconds a connection's write buffer may stay full (the client not reading its answer, session "
        "replies or pongs); then the connection is dropped and what it held freed",
    )
    # The connection layer's (service/http/timeouts.py); its default, measured: docs/deployment.md, "Limits".
    max_connections: int = _setting(
        1024, positive_int,
        "connections a worker holds at once, HTTP and sessions; one more is answered 503 busy and closed",
    )
    # The drain on SIGTERM (service/app.py:drain_on_sigterm); then the worker finishes what it holds.
    shutdown_delay: float = _setting(
        5.0, seconds,
        "seconds each worker keeps accepting and answering after SIGTERM, /readyz answering 503 draining, "
        "before it stops accepting (load balancers and Kubernetes endpoints stop sending meanwhile); 0: at once",
    )
    # Rebalancing after a rollout (service/app.py:CloseConnections; an L4 balancer: onto a restarted pod too).
    max_connection_age: float = _setting(
        60.0, seconds,
        "seconds a keep-alive connection serves requests; the first answer after it says Connection: close, "
        "so the client reconnects (through a balancer, to any replica); 0: no limit. Not sessions",
    )
    keep_heap: bool = _setting(  # service/core/heap.py
        True, boolean,
        "keep freed memory in each worker's heap: no page faults per request, holds the largest request's memory",
    )

    def __post_init__(self) -> None:
        for s in TABLE:
            if getattr(self, s.name) is _FROM_ENV:
                object.__setattr__(self, s.name, s.from_env())
        if isinstance(self.cors_origins, str):
            object.__setattr__(self, "cors_origins", tuple(o for o in self.cors_origins.split(",") if o))

    def environ(self) -> dict[str, str]:
        """The variables that make `Settings()` in another process (a worker) equal to this one."""
        return {s.env: _text(v) for s in TABLE if (v := getattr(self, s.name)) is not None}


class Setting(NamedTuple):
    name: str
    default: Any
    parse: Callable[[str], Any]
    help: str
    flag: bool

    @property
    def env(self) -> str:
        return ENV_PREFIX + self.name.upper()

    def from_env(self) -> Any:
        text = os.environ.get(self.env)
        if text is None:
            return self.default
        try:
            return self.parse(text)
        except (ValueError, argparse.ArgumentTypeError) as e:  # name the variable: no flag to name here
            raise ValueError(f"{self.env}: {e}") from None


TABLE: tuple[Setting, ...] = tuple(Setting(f.name, *f.metadata["row"]) for f in fields(Settings))
_ROWS = {s.name: s for s in TABLE}


def from_env(name: str) -> Any:
    """The field `name` as `Settings()` reads it, alone: a connection reads its bounds at accept, where the whole
    table (20 variables read and parsed, 35 us idle, 160 us under load) was read twice per HTTP connection."""
    return _ROWS[name].from_env()


def _text(value: Any) -> str:
    """A value as its variable holds it (what the field's `parse` reads back)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return ",".join(value)
    return str(value)
