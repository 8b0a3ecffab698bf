"""Read timeouts: a connection gets `header_timeout` seconds for its request head, `body_timeout` for its body.

uvicorn times out only idle keep-alive connections: a client that connects and sends
nothing, or half its headers, or its body at one byte a second (slowloris), holds a
connection (and a file descriptor) for ever. Two bounds, at the two layers that see them:

- the request head, in the HTTP protocol (`ReadTimeoutProtocol`, passed to uvicorn as
  `http=`): a timer from the connection's first moment (or, on a keep-alive connection,
  the next request's first byte) until its headers are complete; when it fires the
  connection is answered 408 (if it sent anything) and closed;
- the body, in the ASGI receive path (`BodyTimeoutMiddleware`): each wait for body bytes
  is bounded by the request's deadline, `body_timeout` after the request began; past it
  the app sees a disconnect, and `client_gone` (routes' handler of `ClientDisconnect`)
  answers 408 with `Connection: close`.

Both deadlines are totals, not idle times between reads: a trickle of one byte a second
is closed as surely as silence.

The write side (issue 19): a client that stops reading leaves what it was sent in the
process (the transport's write buffer), uncounted and for ever: `transport.close()` waits
for the buffer to drain. So both protocols here (HTTP, `ReadTimeoutProtocol`, and WebSocket,
`WriteTimeoutWebSocketProtocol`, passed to uvicorn as `ws=`) arm a timer when the transport
pauses writing (its buffer is past the high-water mark) and abort the connection if it has
not resumed within `write_timeout` seconds: answers, session replies, close frames and pongs
alike are freed with it. The application sees the write side through `Drain`
(`scope["extensions"][DRAIN]`): budget reservations are given back once what they paid for
has left the process (`Drain.after`), and a session waits for its last reply to drain before
it reads the next message (`Drain.wait`). Only the latest ping of what was read is answered,
and only while writes are not paused (RFC 6455 5.5.3 lets an endpoint answer only the latest
ping): a connection owes one pong at most, so a ping flood queues nothing.
A session message still arriving is bounded by `body_timeout` from its first byte, as a
request body is (close 1008).
"""

from __future__ import annotations

import asyncio
import logging
import socket
import struct
import time
from collections.abc import Callable
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from jointlimits.service.http.ws_protocol import SessionProtocol, not_utf8
from jointlimits.service.observability import LIFESPAN_METRICS
from jointlimits.service.settings import Settings

BODY_TIMED_OUT = "body_timed_out"  # key in the request's scope state, read by `client_gone`
DRAIN = "jointlimits.drain"
"""Key in a connection's ASGI scope `extensions` of its `Drain` (absent in-process: TestClient, no transport)."""
OPENED = "jointlimits.opened"
"""Key in an HTTP request's scope `extensions` of its connection's `time.monotonic()` at accept (service/app.py:
the connection's age)."""
MESSAGE_TOO_SLOW = 1008  # policy violation: a session message not received within body_timeout
_PONG = b"\x8a"  # the first byte of a server's pong frame (FIN, opcode 0xA; no extensions are negotiated)
_408 = b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain\r\ncontent-length: 33\r\nconnection: close\r\n\r\nrequest headers not sent in time\n"
log = logging.getLogger("jointlimits.timeouts")


def header_timeout_from_env() -> float:
    """`Settings().header_timeout`: JOINTLIMITS_HEADER_TIMEOUT, which `jointlimits serve` sets for its workers."""
    return Settings().header_timeout


def write_timeout_from_env() -> float:
    """`Settings().write_timeout`: JOINTLIMITS_WRITE_TIMEOUT, which `jointlimits serve` sets for its workers."""
    return Settings().write_timeout


class Drain:
    """A connection's write side as the application sees it: whether the transport's buffer is full
    (`paused`), callbacks to run once it is not (`after`), a wait for that (`wait`). Event loop only."""

    def __init__(self) -> None:
        self.paused = False
        self.closed = False
        self._after: list[Callable[[], None]] = []
        self._writable = asyncio.Event()
        self._writable.set()

    def after(self, fn: Callable[[], None]) -> None:
        """Run `fn` once what was written so far has left the process (below the low-water mark, a few KiB),
        or the connection is gone: at once if the buffer is not full."""
        if self.paused and not self.closed:
            self._after.append(fn)
        else:
            fn()

    async def wait(self) -> None:
        """Return once the buffer is below the low-water mark or the connection is gone."""
        await self._writable.wait()

    def pause(self) -> None:
        self.paused = True
        self._writable.clear()

    def resume(self) -> None:
        self.paused = False
        self._writable.set()
        pending, self._after = self._after, []
        for fn in pending:
            fn()

    def close(self) -> None:
        self.closed = True
        self.resume()


class _WriteBound:
    """The write deadline shared by both protocols: `write_timeout` seconds of paused writing, then abort.

    Mixed in before uvicorn's protocol class (its `pause_writing`, `resume_writing`, `connection_lost`
    run after ours); the subclass calls `_init_write_bound` in its `__init__`."""

    write_timeout: float | None = None  # None: JOINTLIMITS_WRITE_TIMEOUT, read per connection
    transport: asyncio.Transport
    loop: asyncio.AbstractEventLoop
    app_state: dict[str, Any]
    client: tuple[str, int] | None

    def _init_write_bound(self) -> None:
        if self.write_timeout is None:
            self.write_timeout = write_timeout_from_env()
        self.drain = Drain()
        self._write_timer: asyncio.TimerHandle | None = None

    def pause_writing(self) -> None:
        super().pause_writing()  # type: ignore[misc]
        self.drain.pause()
        self._start_write_timer()

    def _linger(self) -> None:
        """After a last write (an answer complete, a session over): bytes still buffered below the high-water
        mark get the same bound, else `close()` would wait for them for ever."""
        if self._write_timer is None and self.transport.get_write_buffer_size() > 0:
            self._start_write_timer()

    def _start_write_timer(self) -> None:
        self._stop_write_timer()
        self._write_timer = self.loop.call_later(self.write_timeout, self._write_expired)  # type: ignore[arg-type]

    def resume_writing(self) -> None:
        self._stop_write_timer()
        super().resume_writing()  # type: ignore[misc]
        self.drain.resume()

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_write_timer()
        super().connection_lost(exc)  # type: ignore[misc]
        self.drain.close()  # what waited for the buffer (reservations) is freed with it

    def _stop_write_timer(self) -> None:
        if self._write_timer is not None:
            self._write_timer.cancel()
            self._write_timer = None

    def _write_expired(self) -> None:
        self._write_timer = None
        buffered = self.transport.get_write_buffer_size()
        if buffered == 0:  # drained meanwhile (a lingering write), nothing is held
            return
        # One line, no traceback: a client that stops reading is expected, not a server fault.
        log.warning(
            "client %s left its write buffer full for %s s (%d bytes waiting): connection reset (JOINTLIMITS_WRITE_TIMEOUT)",
            _peer(self.client), self.write_timeout, buffered,
        )
        metrics = self.app_state.get(LIFESPAN_METRICS)
        if metrics is not None:
            metrics.connections_closed.labels(reason="slow_read").inc()
        _reset(self.transport)


def _reset(transport: asyncio.Transport) -> None:
    """Drop the connection now, with what the process and the kernel hold for it: `close()` would wait for the
    buffer to drain (what never happens), and a plain socket close leaves the kernel's send buffer queued
    before its FIN. A zero linger makes the close a reset: the client sees it, the kernel frees its buffer."""
    sock = transport.get_extra_info("socket")
    if sock is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        except OSError:  # already closed meanwhile
            pass
    transport.abort()


def _peer(client: tuple[str, int] | None) -> str:
    return f"{client[0]}:{client[1]}" if client else "?"


class ReadTimeoutProtocol(_WriteBound, HttpToolsProtocol):
    """uvicorn's httptools protocol with a deadline on each request head (`header_timeout` seconds) and on
    a full write buffer (`write_timeout` seconds); each request's scope carries the connection's `Drain`."""

    header_timeout: float | None = None  # None: JOINTLIMITS_HEADER_TIMEOUT, read per connection

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.header_timeout is None:
            self.header_timeout = header_timeout_from_env()
        self._head_timer: asyncio.TimerHandle | None = None
        self._head_bytes = False  # bytes of the current head have arrived
        self._init_write_bound()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        extensions = {**self.scope.get("extensions", {}), DRAIN: self.drain, OPENED: self.opened}
        self.scope["extensions"] = extensions  # type: ignore[typeddict-item]

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._linger()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.opened = time.monotonic()
        self._arm()  # a connection that never sends a byte is closed too

    def data_received(self, data: bytes) -> None:
        if self._head_timer is None and (self.cycle is None or self.cycle.response_complete):
            self._arm()  # the first bytes of the next request on a keep-alive connection
        self._head_bytes = True
        super().data_received(data)

    def on_headers_complete(self) -> None:
        self._disarm()
        super().on_headers_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._disarm()
        self._head_bytes = False
        self._head_timer = self.loop.call_later(self.header_timeout, self._head_expired)

    def _disarm(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_expired(self) -> None:
        self._head_timer = None
        if self.transport.is_closing():
            return
        log.debug("request head not complete within %s s: closing %s", self.header_timeout, self.client)
        metrics = self.app_state.get(LIFESPAN_METRICS)  # absent when uvicorn runs without the lifespan
        if metrics is not None:
            metrics.connections_closed.labels(reason="slow_head" if self._head_bytes else "silent").inc()
        if self._head_bytes:
            self.transport.write(_408)
        self.transport.close()


def http_protocol(header_timeout: float, write_timeout: float | None = None) -> type[ReadTimeoutProtocol]:
    """A `ReadTimeoutProtocol` with its own `header_timeout` and `write_timeout` (for an in-process
    uvicorn.Config; None: JOINTLIMITS_WRITE_TIMEOUT)."""
    return type("ReadTimeoutProtocol", (ReadTimeoutProtocol,), {"header_timeout": header_timeout, "write_timeout": write_timeout})


class WriteTimeoutWebSocketProtocol(_WriteBound, SessionProtocol):
    """uvicorn's websockets (sans-I/O) protocol with a close the client always reads (`ws_protocol.SessionProtocol`:
    1009 / 1007 drained, reasons), bounded on the write side like `ReadTimeoutProtocol`, with:

    - no pong queued while writes are paused (a ping flood then costs nothing but CPU);
    - a deadline of `message_timeout` seconds (JOINTLIMITS_BODY_TIMEOUT) on a message still arriving,
      counted while the server reads (not while it holds a received message for the application);
    - a client's protocol faults (invalid UTF-8: 1007; bad frames: 1002) logged as one WARNING line,
      never a traceback: they are the client's, and a traceback per frame is a log flood for free.
    """

    message_timeout: float | None = None  # None: JOINTLIMITS_BODY_TIMEOUT, read per connection

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.message_timeout is None:
            self.message_timeout = Settings().body_timeout
        self._message_timer: asyncio.TimerHandle | None = None
        self._owed_pong = b""  # the answer to the latest ping, held while writes are paused (one at most)
        self._init_write_bound()

    def handle_connect(self, event: Any) -> None:
        super().handle_connect(event)
        scope = getattr(self, "scope", None)
        if scope is not None:  # a refused handshake has none
            scope["extensions"] = {**scope.get("extensions", {}), DRAIN: self.drain}  # type: ignore[typeddict-unknown-key]

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._watch_message()

    async def receive(self) -> Any:
        message = await super().receive()
        self._watch_message()  # reading may have resumed with part of a message buffered
        return message

    def handle_ping(self) -> None:
        # websockets queues a pong for every ping of the bytes just read (up to 256 KiB of them: ~2000): the
        # latest one alone is answered (RFC 6455 5.5.3 allows it), and only once the write buffer has room.
        frames = self.conn.data_to_send()
        pongs = [f for f in frames if f[:1] == _PONG]
        others = b"".join(f for f in frames if f[:1] != _PONG)
        if others:
            self.transport.write(others)
        if pongs:
            self._owed_pong = pongs[-1]
            self._pay_pong()

    def resume_writing(self) -> None:
        super().resume_writing()
        self._pay_pong()

    def _pay_pong(self) -> None:
        if self._owed_pong and not self.drain.paused and not self.transport.is_closing():
            pong, self._owed_pong = self._owed_pong, b""
            self.transport.write(pong)

    def handle_parser_exception(self) -> None:
        close = self.conn.close_sent
        if close is not None:
            log.warning("client %s broke the WebSocket protocol: closing with %s (%s)", _peer(self.client), close.code,
                        close.reason or "no reason")
        super().handle_parser_exception()

    def send_receive_event_to_app(self) -> None:
        if self.curr_msg_data_type != "text" or self.close_sent:
            super().send_receive_event_to_app()
            return
        # uvicorn's text path, with its traceback at ERROR for invalid UTF-8 replaced by one line.
        data = self.frames[0] if len(self.frames) == 1 else b"".join(self.frames)
        self.frames = []
        try:
            text = data.decode()
        except UnicodeDecodeError:
            code, reason = not_utf8()
            log.warning("client %s broke the WebSocket protocol: closing with %s (%s)", _peer(self.client), code, reason)
            self._close_and_drain(code, reason)  # tells the application, sends the close, drains the rest
            return
        self.queue.put_nowait({"type": "websocket.receive", "text": text})
        if not self.read_paused:
            self.read_paused = True
            self.transport.pause_reading()

    async def run_asgi(self) -> None:
        await super().run_asgi()
        self._linger()  # a close frame (or last reply) still buffered is bounded too

    async def send(self, message: Any) -> None:
        await super().send(message)
        if message.get("type") == "websocket.close" and self.close_timer is not None and not self.draining:
            # uvicorn waits 10 s for the client's answer to our close frame, then closes gracefully (the kernel
            # keeps what the client did not read): the client gets the write timeout, then a reset.
            self.close_timer.cancel()
            self.close_timer = self.loop.call_later(self.write_timeout, self._close_unanswered)  # type: ignore[arg-type]

    def _close_unanswered(self) -> None:
        self.close_timer = None
        if self.transport.is_closing() and self.transport.get_write_buffer_size() == 0:
            return
        log.info("client %s did not answer the close frame within %s s: connection reset", _peer(self.client),
                 self.write_timeout)
        metrics = self.app_state.get(LIFESPAN_METRICS)
        if metrics is not None:
            metrics.connections_closed.labels(reason="slow_read").inc()
        _reset(self.transport)

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_message_timer()
        super().connection_lost(exc)

    def _watch_message(self) -> None:
        """Arm the message deadline while part of a message is buffered and the server is reading; else disarm."""
        partial = bool(self.conn.reader.buffer) or bool(self.frames)
        if partial and not self.read_paused and not self.close_sent and self.handshake_complete:
            if self._message_timer is None:
                self._message_timer = self.loop.call_later(self.message_timeout, self._message_expired)  # type: ignore[arg-type]
        else:
            self._stop_message_timer()

    def _stop_message_timer(self) -> None:
        if self._message_timer is not None:
            self._message_timer.cancel()
            self._message_timer = None

    def _message_expired(self) -> None:
        self._message_timer = None
        if self.close_sent or self.transport.is_closing():
            return
        buffered = len(self.conn.reader.buffer) + sum(len(f) for f in self.frames)
        log.warning("client %s sent %d bytes of a message, not all of it within %s s: closing with %d",
                    _peer(self.client), buffered, self.message_timeout, MESSAGE_TOO_SLOW)
        metrics = self.app_state.get(LIFESPAN_METRICS)
        if metrics is not None:
            metrics.connections_closed.labels(reason="slow_message").inc()
        self.frames = []
        self.conn.reader.buffer.clear()  # freed now, not when the connection ends (reading stops with the close)
        self.conn.send_close(MESSAGE_TOO_SLOW, f"message not received within {self.message_timeout:g} s")
        # uvicorn's close on a protocol fault (tell the application, send the frame, close), without our log line.
        WebSocketsSansIOProtocol.handle_parser_exception(self)
        self._linger()


def ws_protocol(write_timeout: float | None = None, message_timeout: float | None = None) -> type[WriteTimeoutWebSocketProtocol]:
    """A `WriteTimeoutWebSocketProtocol` with its own bounds (for an in-process uvicorn.Config; None: from the
    environment)."""
    return type(
        "WriteTimeoutWebSocketProtocol", (WriteTimeoutWebSocketProtocol,),
        {"write_timeout": write_timeout, "message_timeout": message_timeout},
    )


class BodyTimeoutMiddleware:
    """Bounds each wait for body bytes by the request's deadline; past it the app sees a disconnect."""

    def __init__(self, app: ASGIApp, timeout: float) -> None:
        self.app = app
        self.timeout = timeout

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.timeout
        body_done = False

        async def receive_bounded() -> Message:
            nonlocal body_done
            if body_done:  # after the body, a receive waits for a disconnect: no deadline on that
                return await receive()
            try:
                async with asyncio.timeout_at(deadline):
                    message = await receive()
            except TimeoutError:
                scope.setdefault("state", {})[BODY_TIMED_OUT] = self.timeout
                return {"type": "http.disconnect"}
            if message["type"] != "http.request" or not message.get("more_body", False):
                body_done = True
            return message

        await self.app(scope, receive_bounded, send)
