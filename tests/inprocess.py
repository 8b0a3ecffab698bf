"""An in-process uvicorn on 127.0.0.1 with the project's own protocol classes (HTTP and WebSocket), as
`jointlimits serve` runs them, with bounds short enough for tests; and raw WebSocket frames for clients
that misbehave on purpose."""

from __future__ import annotations

import base64
import os
import socket
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import uvicorn

from schemas import session as proto
from service.app import create_app
from service.http import timeouts
from service.settings import Settings


@dataclass
class Live:
    port: int
    server: uvicorn.Server

    def connections(self) -> int:
        """Open connections of the server (HTTP and WebSocket) right now."""
        return len(self.server.server_state.connections)


@contextmanager
def serve(settings: Settings, header_timeout: float = 5.0, write_timeout: float = 1.0,
          message_timeout: float | None = None) -> Iterator[Live]:
    """uvicorn in a thread; `log_config=None` leaves logging to the test (caplog sees uvicorn's records)."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    config = uvicorn.Config(
        create_app(settings), log_config=None, log_level="info", lifespan="on",
        http=timeouts.http_protocol(header_timeout, write_timeout),
        ws=timeouts.ws_protocol(write_timeout, message_timeout if message_timeout is not None else settings.body_timeout),
        ws_max_size=settings.max_frame_bytes, ws_per_message_deflate=False,
    )  # fmt: skip
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "uvicorn did not start"
        time.sleep(0.01)
    try:
        yield Live(sock.getsockname()[1], server)
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        sock.close()


def upgrade(port: int, headers: dict[str, str] | None = None, rcvbuf: int | None = None) -> tuple[socket.socket, bytes]:
    """A raw socket upgraded to a session (or refused): the socket and the server's response head."""
    s = socket.socket()
    if rcvbuf is not None:  # before connecting: the window is negotiated then
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.settimeout(10)
    s.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    extra = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
    s.sendall(
        f"GET {proto.PATH} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n{extra}\r\n".encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = s.recv(1)
        if not chunk:
            break
        head += chunk
    return s, head


def frame(opcode: int, payload: bytes, fin: bool = True, rsv: int = 0) -> bytes:
    """A masked client frame."""
    mask = os.urandom(4)
    n = len(payload)
    head = bytes([(0x80 if fin else 0) | rsv << 4 | opcode])
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 2**16:
        head += bytes([0x80 | 126]) + struct.pack("!H", n)
    else:
        head += bytes([0x80 | 127]) + struct.pack("!Q", n)
    keys = np.resize(np.frombuffer(mask, np.uint8), n)
    return head + mask + (np.frombuffer(payload, np.uint8) ^ keys).tobytes()


def read_close(s: socket.socket, give_up: float = 10.0) -> int | None:
    """Read frames until a close frame (its code) or the end of the connection (None)."""
    s.settimeout(give_up)
    buf = b""
    try:
        while True:
            chunk = s.recv(65536)
            if not chunk:
                return None
            buf += chunk
            while len(buf) >= 2:
                op, n = buf[0] & 0x0F, buf[1] & 0x7F
                at = 2
                if n == 126:
                    n, at = struct.unpack("!H", buf[2:4])[0], 4
                elif n == 127:
                    n, at = struct.unpack("!Q", buf[2:10])[0], 10
                if len(buf) < at + n:
                    break
                payload, buf = buf[at : at + n], buf[at + n :]
                if op == 0x8:
                    return struct.unpack("!H", payload[:2])[0] if len(payload) >= 2 else 1005
    except (TimeoutError, ConnectionResetError):
        return None
