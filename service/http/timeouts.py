"""The connection layer: a worker's connections capped, deadlines on reads and writes, a WebSocket close always read.

uvicorn times out only idle keep-alive connections: a client that sends nothing, half its headers, or its body at
one byte a second (slowloris) holds a connection for ever. Each bound is a total, not an idle time: the request
head and the requests pipelined behind an answer (`ReadTimeoutProtocol`), the body (`limits.read_body`), a
session message, and in both protocols the write side (`_WriteBound`: a client that stops reading is reset, freeing
what it held; the application sees it as `Drain`). uvicorn's own WebSocket close on a protocol fault was a reset the
client read as 1006: ours sends a close frame and a FIN, then drains (`WriteTimeoutWebSocketProtocol`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import socket
import struct
import sys
import time
from collections import deque
from collections.abc import Callable
from typing import Any, TypeVar

from starlette.websockets import WebSocket
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.exceptions import PayloadTooBig
from websockets.frames import Close, Frame, Opcode

from jointlimits.schemas.session import TRY_AGAIN_LATER
from jointlimits.service.observability import LIFESPAN_METRICS, peer
from jointlimits.service.settings import from_env
from jointlimits.service.sizing import UPLOAD_FACTOR

RETRY_AFTER_SECONDS = 5
"""`Retry-After` of every 503 (busy, past the request deadline): the worker is free again at once, a busy pod soon."""
DRAIN = "jointlimits.drain"
"""Key in a connection's ASGI scope `extensions` of its `Drain` (absent in-process: TestClient, no transport)."""
OPENED = "jointlimits.opened"
"""Key in an HTTP request's scope `extensions` of its connection's `time.monotonic()` at accept (service/app.py:
the connection's age)."""
MESSAGE_TOO_SLOW = 1008  # policy violation: a session message not received within body_timeout
DRAIN_SECONDS = 30.0
"""Longest time the rest of a refused message is read and dropped before the socket is closed anyway."""
DRAIN_MESSAGES = 4
"""Most bytes read and dropped after the close, in messages at the limit: the rest of the refused one and those a
client sent behind it before it read the close (tests/http/test_session_closes.py sends two more)."""
SHUTDOWN_REASON = "the server is shutting down: reopen the session (another worker or pod answers)"
_PONG = b"\x8a"  # the first byte of a server's pong frame (FIN, opcode 0xA; no extensions are negotiated)
MAX_HEAD_BYTES = 64 * 1024
"""Bytes a request line and its headers may take (the deadline bounds their time only), from the head's first byte
(not a body or a request ahead of it in the same read): past it, 431 and closed.
httptools joins a header's or a URL's pieces by copying them, so an unbounded head costs memory and quadratic time:
one connection streaming a header for the 10 s deadline took a worker from 69 to 533 MiB and stalled it 5.5 s."""
MAX_HEADS_HELD = 16 * 2**20
"""Bytes of unfinished request heads one worker holds over all its connections (a head that arrives whole in one read
holds none): past it, 503 `busy` and closed. One client opens ~11 000 connections within the head deadline: 3000
holding 60 kB each took a worker from 93 to 266 MiB."""
REFUSED_LINGER, MAX_LINGERING = 1.0, 32
"""Seconds a refused connection (431, 408, 503 `busy`) stays half-closed after its answer, reading nothing, so that
the client reads the answer rather than a reset; it closes as soon as the client does. At most `MAX_LINGERING` of a
worker's at once (within `cli.FD_RESERVE`): past them, a flood's are closed at once."""
MIN_CHUNKS, CHUNK_BYTES = 1024, 256
"""A body may arrive in `MIN_CHUNKS` pieces (chunks; without chunking, reads), then one per `CHUNK_BYTES` bytes; past
it, nothing more is read, 413 (`limits.read_body`) and closed. Each piece is Python calls in uvicorn: 1-byte chunks
took 0.39 us of CPU a byte (16 x Content-Length's) and the worker's other clients waited 0.4 s a request (6 ms alone)
for the body deadline; 1-byte writes (TCP_NODELAY) 2.2 us a byte. An honest body is never refused: a TCP segment
carries 536 bytes or more (IPv4's smallest MSS; 1460 on Ethernet) but the last of a write, and a read takes all that
arrived, so reads are under 256 bytes only from a client writing less than that at a time with Nagle's algorithm off."""
CHUNKS = "jointlimits.chunks"
"""Key in an HTTP request's scope `extensions` of its body's pieces and bytes so far (a two-item list)."""
MAX_PIPELINED = 16
"""Requests one connection may send ahead of the one being answered (HTTP/1.1 pipelining): the next one is not read,
and the connection is closed after the answers owed (RFC 9112 9.3.2: the client resends what was not answered).
Unbounded, uvicorn read on after each answer: one connection pipelining `GET /healthz` took a worker from 68 to
640 MiB and 10 s of CPU in 10 s, answering 41 of them."""


def too_many_pieces(pieces: int, size: int) -> bool:
    """A body in `pieces` chunks, or a message in `pieces` frames, of `size` bytes in all: past `MIN_CHUNKS`, then one
    per `CHUNK_BYTES`."""
    return pieces > MIN_CHUNKS + size // CHUNK_BYTES


def _answer(status: bytes, msg: str, type: str, *headers: bytes) -> bytes:
    """An HTTP/1.1 answer with a one-fault list at the header, closing the connection. Written here, not by
    `errors.render`: `jointlimits serve`'s supervisor imports this module and never the core (nor NumPy)."""
    body = json.dumps({"detail": [{"loc": ["header"], "msg": msg, "type": type}]}).encode()
    return (b"HTTP/1.1 %s\r\ncontent-type: application/json\r\ncontent-length: %d\r\n%sconnection: close\r\n\r\n%s"
            % (status, len(body), b"".join(h + b"\r\n" for h in headers), body))


def _busy(what: str) -> bytes:
    """503 `busy` with `Retry-After`, as the worker's other budgets answer (`errors.busy`)."""
    retry = b"retry-after: %d" % RETRY_AFTER_SECONDS
    return _answer(b"503 Service Unavailable", f"{what}: retry after Retry-After seconds", "busy", retry)


_HEAD_START = re.compile(rb"[^\r\n]")  # a request's first byte: llhttp skips CR and LF between requests
log = logging.getLogger("jointlimits.timeouts")


class Drain:
    """A connection's write side as the application sees it: whether the transport's buffer is full
    (`paused`), callbacks to run once it is not (`after`), a wait for that (`wait`). Event loop only."""

    def __init__(self) -> None:
        self.paused = self.closed = False
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


class _Timer:
    """One deadline at a time on the loop: `start` replaces the one armed, `fn` runs when it passes."""

    def __init__(self, loop: asyncio.AbstractEventLoop, fn: Callable[[], None]) -> None:
        self.loop, self.fn, self.handle = loop, fn, None

    def start(self, seconds: float) -> None:
        self.stop()
        self.handle = self.loop.call_later(seconds, self._fire)  # type: ignore[assignment]

    def stop(self) -> None:
        if self.handle is not None:
            self.handle.cancel()
            self.handle = None

    def _fire(self) -> None:
        self.handle = None
        self.fn()


class _WriteBound:
    """The write deadline of both protocols: `write_timeout` seconds of paused writing, then a reset. Mixed in
    before uvicorn's protocol class (its `pause_writing`, `resume_writing`, `connection_lost` run after ours)."""

    write_timeout: float | None = None  # None: JOINTLIMITS_WRITE_TIMEOUT, read per connection
    transport: asyncio.Transport
    loop: asyncio.AbstractEventLoop
    app_state: dict[str, Any]
    client: tuple[str, int] | None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.write_timeout is None:
            self.write_timeout = from_env("write_timeout")
        self.drain = Drain()
        self._write_timer = _Timer(self.loop, self._write_expired)

    def pause_writing(self) -> None:
        super().pause_writing()  # type: ignore[misc]
        self.drain.pause()
        self._write_timer.start(self.write_timeout)  # type: ignore[arg-type]

    def resume_writing(self) -> None:
        self._write_timer.stop()
        super().resume_writing()  # type: ignore[misc]
        self.drain.resume()

    def connection_lost(self, exc: Exception | None) -> None:
        self._write_timer.stop()
        super().connection_lost(exc)  # type: ignore[misc]
        self.drain.close()  # what waited for the buffer (reservations) is freed with it

    def _linger(self) -> None:
        """After a last write (an answer complete, a session over): bytes still buffered below the high-water
        mark get the same bound, else `close()` would wait for them for ever."""
        if self._write_timer.handle is None and self.transport.get_write_buffer_size() > 0:
            self._write_timer.start(self.write_timeout)  # type: ignore[arg-type]

    def _closed(self, reason: str) -> None:
        """Count a connection the server closed (absent when uvicorn runs without the lifespan)."""
        metrics = self.app_state.get(LIFESPAN_METRICS)
        if metrics is not None:
            metrics.connections_closed.labels(reason=reason).inc()

    def _write_expired(self) -> None:
        buffered = self.transport.get_write_buffer_size()
        if buffered == 0:  # drained meanwhile (a lingering write), nothing is held
            return
        # One line, no traceback: a client that stops reading is expected, not a server fault.
        self._reset(logging.WARNING, "client %s left its write buffer full for %s s (%d bytes waiting): connection "
                    "reset (JOINTLIMITS_WRITE_TIMEOUT)", peer(self.client), self.write_timeout, buffered)

    def _reset(self, level: int, msg: str, *args: Any) -> None:
        """Log, count as `slow_read` and drop the connection now, with what the process and the kernel hold for it:
        `close()` would wait for the buffer to drain (what never happens), and a plain socket close leaves the
        kernel's send buffer queued before its FIN. A zero linger makes the close a reset: the client sees it, the
        kernel frees its buffer."""
        log.log(level, msg, *args)
        self._closed("slow_read")
        sock = self.transport.get_extra_info("socket")
        if sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            except OSError:  # already closed meanwhile
                pass
        self.transport.abort()


class _Cut(Exception):
    """Raised in httptools' callback to stop parsing (a pipelined request past `MAX_PIPELINED`, a body in tiny chunks)."""


class ReadTimeoutProtocol(_WriteBound, HttpToolsProtocol):
    """uvicorn's httptools protocol with a deadline on each request head (`header_timeout` seconds) and on
    a full write buffer (`write_timeout` seconds); each request's scope carries the connection's `Drain`."""

    header_timeout: float | None = None  # None: JOINTLIMITS_HEADER_TIMEOUT, read per connection
    max_connections: int | None = None  # None: JOINTLIMITS_MAX_CONNECTIONS, read per connection
    heads_held = 0  # bytes of every connection's unfinished and queued heads in this worker (MAX_HEADS_HELD)
    _cut = False  # a pipelined head or a body refused: the answers owed are sent, nothing more is read
    _lingers = False  # refused and half-closed (`REFUSED_LINGER`), counted in `lingering`
    _running: Any = None  # the request being answered (`_start_asgi_task`)
    lingering = 0  # this worker's connections that do

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.header_timeout is None or self.max_connections is None:
            self.header_timeout = self.header_timeout or from_env("header_timeout")
            self.max_connections = self.max_connections or from_env("max_connections")
        self._head_timer = _Timer(self.loop, self._head_expired)
        self._head_bytes, self._head_size = False, 0  # bytes of the current head have arrived (any; how many)
        self._in_head = False  # the parser is inside a request's head (not in the rest of an answered one's body)
        self._read, self._at, self._tail = b"", 0, b""  # the read being parsed; where in it the head began (or the
        # parser is: never past it); the last 3 bytes read before it (a head's blank line may straddle two reads)
        self._queued: deque[int] = deque()  # bytes of the heads pipelined behind an unanswered request, oldest first

    def on_message_begin(self) -> None:
        if len(self.pipeline) >= MAX_PIPELINED or (self.pipeline and self.heads_held > MAX_HEADS_HELD):
            self._refuse("pipelined" if len(self.pipeline) >= MAX_PIPELINED else "heads_full", b"")
            raise _Cut  # httptools stops here: the rest of this read is dropped (`send_400_response`)
        super().on_message_begin()
        self._in_head = True
        self._at = _HEAD_START.search(self._read, self._at).start()
        if self._head_timer.handle is None:  # a pipelined head: its deadline too
            self._head_timer.start(self.header_timeout)  # type: ignore[arg-type]
        self._chunks, self._chunked = [0, 0], False
        extensions = {**self.scope.get("extensions", {}), DRAIN: self.drain, OPENED: self.opened, CHUNKS: self._chunks}
        self.scope["extensions"] = extensions  # type: ignore[typeddict-item]

    def on_body(self, body: bytes) -> None:
        super().on_body(body)
        self._chunks[1] += len(body)
        self._at += len(body)  # exact for a Content-Length body; a chunked one's sizes and CRLFs are not counted
        if not self._chunked:  # each read of a Content-Length body is a piece
            self._piece()

    def on_chunk_header(self) -> None:
        self._chunked = True  # the chunks are the pieces, not the reads
        self._piece()

    def _piece(self) -> None:
        """One more piece of the body: a chunk, or a read of a Content-Length body."""
        chunks = self._chunks
        chunks[0] += 1
        if too_many_pieces(*chunks):
            self.cycle.message_event.set()  # the application wakes to refuse the body (`limits.read_body`)
            self._refuse("body_chunks", b"")
            raise _Cut  # the rest is not parsed

    def on_response_complete(self) -> None:
        queued = len(self.pipeline)
        super().on_response_complete()
        if len(self.pipeline) < queued:  # the oldest queued request started: its head is no longer held here
            ReadTimeoutProtocol.heads_held -= self._queued.popleft()
        self._linger()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.opened = time.monotonic()
        if len(self.connections) > self.max_connections:  # type: ignore[operator]
            # uvicorn's set of this worker's connections, HTTP and WebSocket: an upgrade replaces its HTTP one.
            self.connections.discard(self)  # a refused connection is not counted
            return self._refuse("connections_full", _busy(f"this worker holds {self.max_connections} connections, "
                                                          "its most (JOINTLIMITS_MAX_CONNECTIONS)"))
        self._arm()  # a connection that never sends a byte is closed too

    def data_received(self, data: bytes) -> None:
        if self._cut:  # what follows a refused pipelined head: dropped unread
            return
        if self._head_timer.handle is None and (self.cycle is None or self.cycle.response_complete):
            self._arm()  # the first bytes of the next request on a keep-alive connection
        self._head_bytes = True
        self._read, self._at = data, 0
        super().data_received(data)
        self._read, self._tail = b"", (self._tail + data[-3:])[-3:]
        # Still in a head: the rest of a body answered early (a 413 on its declared size) is no head, though
        # the timer is armed for the next request once the answer is complete. Of this read, only the bytes from
        # where the head began count (`_at`: 0 if it began in an earlier read), not the requests before it.
        if self._in_head and not self.transport.is_closing():
            self._head_size += len(data) - self._at  # counted after the parse: at most one read past the bound is held
            ReadTimeoutProtocol.heads_held += len(data) - self._at
            if self._head_size > MAX_HEAD_BYTES:
                msg = f"request line and headers exceed {MAX_HEAD_BYTES} bytes, the most this service reads"
                self._refuse("head_too_large", _answer(b"431 Request Header Fields Too Large", msg, "too_large"))
            elif ReadTimeoutProtocol.heads_held > MAX_HEADS_HELD:
                self._refuse("heads_full", _busy(f"this worker holds {MAX_HEADS_HELD} bytes of unfinished request "
                                                 "heads, its most"))

    def on_headers_complete(self) -> None:
        self._in_head = False
        # Past its first CRLF CRLF (llhttp is strict), which straddles two reads if the head began in the one before
        # (`_at` 0): never past the true end while `_at` is not past the head's start (short after a chunked body).
        i = (self._tail + self._read[:3]).find(b"\r\n\r\n") if self._at == 0 else -1
        if i >= 0:
            self._at = i + 4 - len(self._tail)
        elif (end := self._read.find(b"\r\n\r\n", self._at)) >= 0:
            self._at = end + 4
        self._head_timer.stop()
        self._drop_head()
        cycle = self.cycle
        super().on_headers_complete()
        if self.cycle is not cycle and self.pipeline and self.pipeline[0][0] is self.cycle:  # queued behind another
            # Held until it starts: its URL and headers, as uvicorn keeps them (MAX_PIPELINED heads of up to
            # MAX_HEAD_BYTES each, 1 MiB a connection behind a stalled request, were counted nowhere).
            size = len(self.url) + sum(len(n) + len(v) for n, v in self.cycle.scope["headers"])
            self._queued.append(size)
            ReadTimeoutProtocol.heads_held += size

    def _start_asgi_task(self, cycle: Any, app: Any) -> None:
        self._running = cycle  # the request being answered; with requests pipelined, `self.cycle` is the last read
        super()._start_asgi_task(cycle, app)

    def connection_lost(self, exc: Exception | None) -> None:
        self._head_timer.stop()
        self._drop_head()
        ReadTimeoutProtocol.heads_held -= sum(self._queued)
        self._queued.clear()
        ReadTimeoutProtocol.lingering -= self._lingers
        super().connection_lost(exc)
        # uvicorn tells only `self.cycle`, the last request read, that the client is gone: with requests pipelined, the
        # one answered ahead of it wrote to the closed transport (uvloop raises), logged as an application's error.
        if self._running is not None and not self._running.response_complete:
            self._running.disconnected = True
            self._running.message_event.set()

    def _arm(self) -> None:
        self._head_bytes = False
        self._drop_head()
        self._head_timer.start(self.header_timeout)  # type: ignore[arg-type]

    def _drop_head(self) -> None:
        ReadTimeoutProtocol.heads_held -= self._head_size
        self._head_size = 0

    def send_400_response(self, msg: str) -> None:
        if not self._cut:  # a parser error, not our `_Cut`
            super().send_400_response(msg)

    def _refuse(self, reason: str, answer: bytes) -> None:
        """Answer `answer` and close; behind answers still owed (pipelining), it would answer an earlier request:
        those are sent, then the connection is closed, and nothing more is read."""
        self._head_timer.stop()
        self._drop_head()
        self._closed(reason)
        if self.cycle is not None and not self.cycle.response_complete:
            self._cut, self.cycle.keep_alive = True, False  # the last request read is the last answered
            return
        self.transport.write(answer)
        if not answer or ReadTimeoutProtocol.lingering >= MAX_LINGERING or not self.transport.can_write_eof():
            return self.transport.close()
        # A close with the client's bytes unread is a reset, which can destroy the answer before the client reads
        # it (1 in 7 refused session openings did): end our side, drop what it sends, close when it does or soon.
        self._cut = self._lingers = True
        ReadTimeoutProtocol.lingering += 1
        self.transport.write_eof()
        self.loop.call_later(REFUSED_LINGER, self.transport.close)

    def _head_expired(self) -> None:
        if not self.transport.is_closing():
            log.debug("request head not complete within %s s: closing %s", self.header_timeout, self.client)
            msg = f"request headers not received within {self.header_timeout:g} s (JOINTLIMITS_HEADER_TIMEOUT)"
            timed_out = _answer(b"408 Request Timeout", msg, "timeout")  # as the body's 408 (`limits.read_body`)
            reason, answer = ("slow_head", timed_out) if self._head_bytes else ("silent", b"")
            self._refuse(reason, answer)


class _Queue(asyncio.Queue):  # type: ignore[type-arg]
    """uvicorn's queue of ASGI events, with the bytes of the messages it holds (`held`)."""

    held = 0

    def _put(self, item: Any) -> None:
        self.held += _size(item)
        super()._put(item)

    def _get(self) -> Any:
        item = super()._get()
        self.held -= _size(item)
        return item


def _size(event: dict[str, Any]) -> int:
    """Memory of a received message's payload (a text message's `str`: at most its UTF-8 bytes)."""
    data = event.get("bytes", event.get("text"))
    return sys.getsizeof(data) if data else 0


NOT_UTF8 = 1007, "a text message must be valid UTF-8 (send msgpack as a binary message)"


class WriteTimeoutWebSocketProtocol(_WriteBound, WebSocketsSansIOProtocol):
    """uvicorn's websockets (sans-I/O) protocol: a message over the limit (1009) or not UTF-8 (1007) closed with a
    reason and a FIN, the rest drained; 1012 on shutdown; a message's bytes in the worker's upload budget from its
    first byte (1013 past it); the latest ping alone answered; a client's protocol fault one WARNING line."""

    message_timeout: float | None = None  # None: JOINTLIMITS_BODY_TIMEOUT, read per connection
    draining = False  # closed under the application (1009, 1007, 1013): the rest is read and dropped
    _drained = 0  # bytes read and dropped since the close
    _upload: Any = None  # this connection's `budget.Reservation` in the worker's upload budget
    _in_app = 0  # bytes of the message the application took last (held until it asks for the next one)
    _fragments = 0  # bytes of `frames`, the fragments of the message arriving (a running sum: there may be millions)
    _frames_in = (0, 0)  # frames and payload bytes of the message arriving (MIN_CHUNKS, CHUNK_BYTES)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.queue = _Queue()
        if self.message_timeout is None:
            self.message_timeout = from_env("body_timeout")
        self._message_timer = _Timer(self.loop, self._message_expired)
        self._owed_pong = b""  # the answer to the latest ping, held while writes are paused (one at most)

    def handle_connect(self, event: Any) -> None:
        super().handle_connect(event)
        scope = getattr(self, "scope", None)
        if scope is not None:  # a refused handshake has none
            scope["extensions"] = {**scope.get("extensions", {}), DRAIN: self.drain}  # type: ignore[typeddict-unknown-key]

    def data_received(self, data: bytes) -> None:
        if self.draining:  # the rest of a refused message: dropped unread, up to DRAIN_MESSAGES at the limit
            self._drained += len(data)
            if self._drained > DRAIN_MESSAGES * (self.config.ws_max_size or 0):
                self.transport.close()  # cut off (a reset): the client has had its close frame for that long
        else:
            super().data_received(data)
            self._count_upload()
        self._watch_message()

    async def receive(self) -> Any:
        message = await super().receive()
        self._in_app = _size(message)  # the one before is done with: the application asks for the next
        self._count_upload()
        self._watch_message()  # reading may have resumed with part of a message buffered
        return message

    def handle_text(self, event: Frame) -> None:
        self._fragment(event, first=True)
        super().handle_text(event)

    def handle_bytes(self, event: Frame) -> None:
        self._fragment(event, first=True)
        super().handle_bytes(event)

    def handle_cont(self, event: Frame) -> None:
        self._fragment(event)
        super().handle_cont(event)

    def _fragment(self, event: Frame, first: bool = False) -> None:
        # A fragment is a bytes object in uvicorn's list: ~40 bytes besides its data, which a flood of tiny ones costs.
        self._fragments = 0 if event.fin else (0 if first else self._fragments) + sys.getsizeof(event.data) + 8
        # And ~6 us of websockets' parse: frames are bounded as a chunked body's chunks are (the rest is drained).
        n, size = (0, 0) if first else self._frames_in
        self._frames_in = n + 1, size + len(event.data)
        if too_many_pieces(*self._frames_in) and not self.draining:
            self._close_and_drain(1009, f"message in more than {n} frames for {size} bytes; this service reads "
                                        f"{MIN_CHUNKS} frames, then one per {CHUNK_BYTES} bytes: send larger frames")

    def _count_upload(self) -> None:
        """Hold what this connection's messages take in the worker's upload budget: the message arriving twice,
        those received once; past the budget, close with 1013 and drain."""
        if self.close_sent or self.disconnected:  # given back already (`_close_and_drain`, `connection_lost`)
            return
        if self._upload is None:
            uploads = getattr(getattr(getattr(self, "scope", {}).get("app"), "state", None), "uploads", None)
            if uploads is None:  # not the service's application, or not yet running
                return
            self._upload = uploads.reserve_now()
        want = UPLOAD_FACTOR * (len(self.conn.reader.buffer) + self._fragments) + self.queue.held + self._in_app
        if want <= self._upload.size:
            self._upload.shrink(want)
        elif not self._upload.try_grow(want - self._upload.size):
            capacity = self._upload.budget.capacity
            self._close_and_drain(TRY_AGAIN_LATER, f"this worker's upload budget ({capacity} bytes) is full: retry later")

    def eof_received(self) -> bool | None:
        return None  # the client closed its side: the transport closes (nothing is left unread)

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
        """A message too big or not UTF-8: our close frame and a FIN, then read and drop until the client closes."""
        close, exc = self.conn.close_sent, self.conn.parser_exc
        if close is not None:
            log.warning("client %s broke the WebSocket protocol: closing with %s (%s)", peer(self.client), close.code,
                        close.reason or "no reason")
        if not isinstance(exc, (PayloadTooBig, UnicodeDecodeError)):
            return super().handle_parser_exception()
        self.conn.data_to_send()  # websockets' own close frame and EOF: replaced by ours
        self._close_and_drain(*((1009, _too_big(exc, self.config.ws_max_size)) if isinstance(exc, PayloadTooBig)
                                else NOT_UTF8))

    def send_receive_event_to_app(self) -> None:
        if self.curr_msg_data_type != "text" or self.close_sent:
            return super().send_receive_event_to_app()
        # uvicorn's text path, with its traceback at ERROR for invalid UTF-8 replaced by one line and a drained close.
        data = self.frames[0] if len(self.frames) == 1 else b"".join(self.frames)
        self.frames = []
        try:
            text = data.decode()
        except UnicodeDecodeError:
            code, reason = NOT_UTF8
            log.warning("client %s broke the WebSocket protocol: closing with %s (%s)", peer(self.client), code, reason)
            return self._close_and_drain(code, reason)  # tells the application, sends the close, drains the rest
        self.queue.put_nowait({"type": "websocket.receive", "text": text})
        if not self.read_paused:
            self.read_paused = True
            self.transport.pause_reading()

    def _close_and_drain(self, code: int, reason: str) -> None:
        self.frames, self._fragments = [], 0  # freed now, not when the connection ends
        self.conn.reader.buffer.clear()
        if self._upload is not None:
            self._upload.release()
        self.queue.put_nowait({"type": "websocket.disconnect", "code": code, "reason": reason})
        self.transport.write(Frame(Opcode.CLOSE, Close(code, reason).serialize()).serialize(mask=False))
        if self.transport.can_write_eof():
            self.transport.write_eof()  # the client reads the close frame, then EOF: no reset
        self.close_sent = self.draining = True
        if self.read_paused:
            self.read_paused = False
            self.transport.resume_reading()
        self.close_timer = self.loop.call_later(DRAIN_SECONDS, self.transport.close)

    async def run_asgi(self) -> None:
        await super().run_asgi()
        self._linger()  # a close frame (or last reply) still buffered is bounded too

    async def send(self, message: Any) -> None:
        if self.draining:  # closed under the application: it hears so on its next receive
            return
        await super().send(message)
        if message["type"] == "websocket.http.response.body" and not message.get("more_body", False):
            # A denial (401, 503 draining) answers the upgrade as a close before accept does, but uvicorn marks only
            # the latter complete and logs an ERROR for every refused upgrade; the response is sent (`close_sent`).
            self.handshake_complete = True
        if message["type"] == "websocket.close" and self.close_timer is not None and not self.draining:
            # uvicorn waits 10 s for the client's answer to our close frame, then closes gracefully (the kernel
            # keeps what the client did not read): the client gets the write timeout, then a reset.
            self.close_timer.cancel()
            self.close_timer = self.loop.call_later(self.write_timeout, self._close_unanswered)  # type: ignore[arg-type]

    def _close_unanswered(self) -> None:
        self.close_timer = None
        if self.transport.is_closing() and self.transport.get_write_buffer_size() == 0:
            return
        self._reset(logging.INFO, "client %s did not answer the close frame within %s s: connection reset",
                    peer(self.client), self.write_timeout)

    def connection_lost(self, exc: Exception | None) -> None:
        self._message_timer.stop()
        super().connection_lost(exc)
        if self._upload is not None:
            self._upload.release()

    def shutdown(self) -> None:
        if not self.handshake_complete or self.close_sent:
            return super().shutdown()
        self.stop_keepalive()
        self.queue.put_nowait({"type": "websocket.disconnect", "code": 1012, "reason": SHUTDOWN_REASON})
        self.conn.send_close(1012, SHUTDOWN_REASON)
        self.transport.write(b"".join(self.conn.data_to_send()))
        self.transport.close()

    def _watch_message(self) -> None:
        """Arm the message deadline while part of a message is buffered and the server is reading; else disarm."""
        partial = bool(self.conn.reader.buffer) or bool(self.frames)
        if partial and not self.read_paused and not self.close_sent and self.handshake_complete:
            if self._message_timer.handle is None:
                self._message_timer.start(self.message_timeout)  # type: ignore[arg-type]
        else:
            self._message_timer.stop()

    def _message_expired(self) -> None:
        if self.close_sent or self.transport.is_closing():
            return
        buffered = len(self.conn.reader.buffer) + sum(len(f) for f in self.frames)
        log.warning("client %s sent %d bytes of a message, not all of it within %s s: closing with %d",
                    peer(self.client), buffered, self.message_timeout, MESSAGE_TOO_SLOW)
        self._closed("slow_message")
        self.frames = []
        self.conn.reader.buffer.clear()  # freed now, not when the connection ends (reading stops with the close)
        self.conn.send_close(MESSAGE_TOO_SLOW, f"message not received within {self.message_timeout:g} s")
        # uvicorn's close on a protocol fault (tell the application, send the frame, close), without our log line.
        WebSocketsSansIOProtocol.handle_parser_exception(self)
        self._linger()


def _too_big(exc: PayloadTooBig, limit: int | None) -> str:
    size = getattr(exc, "size", None)  # the frame's size; None for a message of several frames
    what = f"message of {size + (exc.current_size or 0)} bytes" if size is not None else "message"
    return f"{what} over the limit; this service accepts at most {limit} (JOINTLIMITS_MAX_FRAME_BYTES)"


P = TypeVar("P")


def bounded(protocol: type[P], **bounds: float | None) -> type[P]:
    """`protocol` (`ReadTimeoutProtocol`, `WriteTimeoutWebSocketProtocol`) with its own `header_timeout`,
    `write_timeout`, `message_timeout` (for an in-process uvicorn.Config; None: from the environment)."""
    return type(protocol.__name__, (protocol,), bounds)


def server_options(max_frame_bytes: int) -> dict[str, Any]:
    """uvicorn's WebSocket options for the service: this protocol, the message limit it enforces (the
    application's, so the two agree), no permessage-deflate (float64 arrays barely compress: it would only cost
    CPU; docs/sessions.md, "The protocol, byte by byte")."""
    return {"ws": "jointlimits.service.http.timeouts:WriteTimeoutWebSocketProtocol", "ws_max_size": max_frame_bytes,
            "ws_per_message_deflate": False}


def frame_limit(websocket: WebSocket, configured: int) -> int:
    """The message limit in force on this connection: `configured` (JOINTLIMITS_MAX_FRAME_BYTES), or the server's
    own where lower (plain `uvicorn jointlimits.service.app:app` keeps uvicorn's 16 MiB `ws_max_size`). Under
    another server (or Starlette's TestClient) it is not known, and the configured one is reported and enforced."""
    config = getattr(getattr(websocket._receive, "__self__", None), "config", None)
    server = getattr(config, "ws_max_size", None)
    return min(configured, server) if isinstance(server, int) and server > 0 else configured
