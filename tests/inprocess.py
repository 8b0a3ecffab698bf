"""An in-process uvicorn on 127.0.0.1 with the project's own protocol classes (HTTP and WebSocket), as
`jointlimits serve` runs them, with bounds short enough for tests; and raw WebSocket frames for clients
that misbehave on purpose."""

from __future__ import annotations

import socket
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import uvicorn

from jointlimits.service.app import create_app
from jointlimits.service.http import timeouts
from jointlimits.service.settings import Settings
from tests.drills import ws_frame, ws_upgrade
from tests.http.test_contract_live import running


@dataclass
class Live:
    port: int
    server: uvicorn.Server
    app: Any

    def held(self) -> int:
        """Bytes of the worker's in-flight budget held right now."""
        return int(self.app.state.in_flight.held)

    def buffered(self) -> list[int]:
        """Bytes waiting in each open connection's write buffer (in the process, not yet taken by the kernel)."""
        return [c.transport.get_write_buffer_size() for c in list(self.server.server_state.connections)
                if getattr(c, "transport", None) is not None and not c.transport.is_closing()]

    def connections(self) -> int:
        """Open connections of the server (HTTP and WebSocket) right now."""
        return len(self.server.server_state.connections)


@contextmanager
def serve(settings: Settings, header_timeout: float = 5.0, write_timeout: float = 1.0,
          message_timeout: float | None = None, max_connections: int | None = None, app: Any = None) -> Iterator[Live]:
    """uvicorn in a thread; `log_config=None` leaves logging to the test (caplog sees uvicorn's records).
    `max_connections` None: JOINTLIMITS_MAX_CONNECTIONS (its default); `app`: `create_app(settings)` unless given."""
    app = app or create_app(settings)
    message_timeout = settings.body_timeout if message_timeout is None else message_timeout
    config = uvicorn.Config(
        app, log_config=None, log_level="info", lifespan="on",
        http=timeouts.bounded(timeouts.ReadTimeoutProtocol, header_timeout=header_timeout, write_timeout=write_timeout,
                              max_connections=max_connections),
        ws=timeouts.bounded(timeouts.WriteTimeoutWebSocketProtocol, write_timeout=write_timeout,
                            message_timeout=message_timeout),
        ws_max_size=settings.max_frame_bytes, ws_per_message_deflate=False,
    )  # fmt: skip
    with running(config) as (server, port):
        yield Live(port, server, app)


def upgrade(port: int, headers: dict[str, str] | None = None, rcvbuf: int | None = None) -> tuple[socket.socket, bytes]:
    """A raw socket upgraded to a session (or refused): the socket and the server's response head."""
    return ws_upgrade(port, rcvbuf=rcvbuf, headers=headers)


def frame(opcode: int, payload: bytes, fin: bool = True, rsv: int = 0) -> bytes:
    """A client frame (masked with the key 0)."""
    return ws_frame(opcode, payload, fin, rsv)


def close_frame(s: socket.socket, give_up: float = 20.0) -> tuple[int | None, str]:
    """Read (and drop) frames until the server's close frame: its code (1005 if it has none) and reason;
    (None, why) if the connection ended without one (a reset, EOF, or nothing within `give_up`)."""
    s.settimeout(give_up)
    buf = b""
    try:
        while True:
            while len(buf) >= 2:
                op, n, at = buf[0] & 0x0F, buf[1] & 0x7F, 2
                if n == 126:
                    n, at = struct.unpack("!H", buf[2:4])[0], 4
                elif n == 127:
                    n, at = struct.unpack("!Q", buf[2:10])[0], 10
                if len(buf) < at + n:
                    break
                payload, buf = buf[at : at + n], buf[at + n :]
                if op == 0x8:
                    return (struct.unpack("!H", payload[:2])[0], payload[2:].decode()) if len(payload) >= 2 else (1005, "")
            chunk = s.recv(1 << 16)
            if not chunk:
                return None, "EOF without a close frame"
            buf += chunk
    except OSError as e:  # a reset (1006 to a WebSocket client), or nothing within give_up
        return None, repr(e)


def read_close(s: socket.socket, give_up: float = 10.0) -> int | None:
    """The code of the server's close frame; None if the connection ended without one."""
    return close_frame(s, give_up)[0]


def read_frame(s: socket.socket, give_up: float = 5.0) -> tuple[int, bytes]:
    """The next server frame (opcode, payload); small frames only."""
    s.settimeout(give_up)
    head = _exactly(s, 2)
    n = head[1] & 0x7F
    if n == 126:
        n = struct.unpack("!H", _exactly(s, 2))[0]
    elif n == 127:
        n = struct.unpack("!Q", _exactly(s, 8))[0]
    return head[0] & 0x0F, _exactly(s, n)


def _exactly(s: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = s.recv(n - len(out))
        if not chunk:
            raise ConnectionError("closed")
        out += chunk
    return out
