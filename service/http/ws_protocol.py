"""uvicorn's WebSocket protocol (websockets, sans-I/O) with a close the client always reads, and a reason.

`jointlimits serve` runs it as the base of `timeouts.WriteTimeoutWebSocketProtocol` (the write-side bounds on
top: `server_options`). Four changes:

- A message over the limit (`ws_max_size`, set to `JOINTLIMITS_MAX_FRAME_BYTES`) or a text message that is
  not UTF-8: uvicorn wrote the close frame and closed the socket at once; with the client's message still
  arriving, the kernel answered it with a reset, and the client saw 1006 instead of 1009 (issue 20: 1009
  in 0-2 of 6 tries at 64 MiB). Here the close frame (1009 / 1007, with a reason) and a FIN go out, then
  the rest of what the client sends is read and dropped until it closes, at most `DRAIN_SECONDS` and
  `DRAIN_MESSAGES` times the limit. A reply the application sends meanwhile is dropped (it hears the close
  on its next receive).
- The application hears the same code and reason (`websocket.disconnect`), so the session's log line and
  `jointlimits_sessions_total{reason}` name the cause.
- A shutdown closes sessions with 1012 and a reason (uvicorn sends none).
- A message's bytes count in the worker's upload budget (`app.state.uploads`, service/http/budget.py) from
  its first byte: twice while it arrives (the buffer, then the joined copy), once from its arrival until the
  application asks for the next message. Bytes that do not fit close the session with 1013 (try again later)
  and a reason, drained as 1009 is: unfinished messages are bounded as request bodies are.
"""

from __future__ import annotations

import asyncio
import sys
from typing import Any

from starlette.websockets import WebSocket
from websockets.exceptions import PayloadTooBig
from websockets.frames import Close, Frame, Opcode
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from jointlimits.schemas.session import TRY_AGAIN_LATER
from jointlimits.service.sizing import UPLOAD_FACTOR

DRAIN_SECONDS = 30.0
"""Longest time the rest of a refused message is read and dropped before the socket is closed anyway."""
DRAIN_MESSAGES = 4
"""Most bytes read and dropped after the close, in messages at the limit: the rest of the refused one and those a
client sent behind it before it read the close (tests/http/test_session_closes.py sends two more)."""

SHUTDOWN_REASON = "the server is shutting down: reopen the session (another worker or pod answers)"


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


class SessionProtocol(WebSocketsSansIOProtocol):
    draining = False
    _drained = 0  # bytes read and dropped since the close
    _upload: Any = None  # this connection's `budget.Reservation` in the worker's upload budget
    _in_app = 0  # bytes of the message the application took last (held until it asks for the next one)
    _fragments = 0  # bytes of `frames`, the fragments of the message arriving (a running sum: there may be millions)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.queue = _Queue()

    def data_received(self, data: bytes) -> None:
        if self.draining:  # the rest of a refused message: dropped unread, up to DRAIN_MESSAGES at the limit
            self._drained += len(data)
            if self._drained > DRAIN_MESSAGES * (self.config.ws_max_size or 0):
                self.transport.close()  # cut off (a reset): the client has had its close frame for that long
            return
        super().data_received(data)
        self._count_upload()

    def handle_text(self, event: Frame) -> None:
        self._fragments = 0  # a new message
        self._fragment(event)
        super().handle_text(event)

    def handle_bytes(self, event: Frame) -> None:
        self._fragments = 0
        self._fragment(event)
        super().handle_bytes(event)

    def handle_cont(self, event: Frame) -> None:
        self._fragment(event)
        super().handle_cont(event)

    def _fragment(self, event: Frame) -> None:
        # A fragment is a bytes object in uvicorn's list: ~40 bytes besides its data, which a flood of tiny ones costs.
        self._fragments = 0 if event.fin else self._fragments + sys.getsizeof(event.data) + 8

    async def receive(self) -> Any:
        message = await super().receive()
        self._in_app = _size(message)  # the one before is done with: the application asks for the next
        self._count_upload()
        return message

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
        partial = len(self.conn.reader.buffer) + self._fragments
        want = UPLOAD_FACTOR * partial + self.queue.held + self._in_app
        if want <= self._upload.size:
            self._upload.shrink(want)
        elif not self._upload.try_grow(want - self._upload.size):
            capacity = self._upload.budget.capacity
            self._close_and_drain(TRY_AGAIN_LATER, f"this worker's upload budget ({capacity} bytes) is full: retry later")

    def eof_received(self) -> bool | None:
        return None  # the client closed its side: the transport closes (nothing is left unread)

    def handle_parser_exception(self) -> None:
        """Send the close frame and a FIN, keep reading (dropping) until the client closes."""
        exc = self.conn.parser_exc
        if not isinstance(exc, (PayloadTooBig, UnicodeDecodeError)):
            super().handle_parser_exception()
            return
        self.conn.data_to_send()  # websockets' own close frame and EOF: replaced by ours
        code, reason = (1009, _too_big(exc, self.config.ws_max_size)) if isinstance(exc, PayloadTooBig) else not_utf8()
        self._close_and_drain(code, reason)

    def send_receive_event_to_app(self) -> None:
        """As uvicorn's, with a reason and a drained close for a text message that is not UTF-8."""
        if self.curr_msg_data_type == "text" and not self.close_sent:
            data = self.frames[0] if len(self.frames) == 1 else b"".join(self.frames)
            try:
                data.decode()
            except UnicodeDecodeError:
                self.frames = []
                self._close_and_drain(*not_utf8())
                return
        super().send_receive_event_to_app()

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

    async def send(self, message: Any) -> None:
        if self.draining:  # closed under the application (1009, 1007, 1013): it hears so on its next receive
            return
        await super().send(message)
        if message["type"] == "websocket.http.response.body" and not message.get("more_body", False):
            # A denial (401, 503 draining) answers the upgrade as a close before accept does, but uvicorn marks only
            # the latter complete and logs an ERROR for every refused upgrade; the response is sent (`close_sent`).
            self.handshake_complete = True

    def connection_lost(self, exc: Exception | None) -> None:
        super().connection_lost(exc)
        if self._upload is not None:
            self._upload.release()

    def shutdown(self) -> None:
        if self.handshake_complete and not self.close_sent:
            self.stop_keepalive()
            self.queue.put_nowait({"type": "websocket.disconnect", "code": 1012, "reason": SHUTDOWN_REASON})
            self.conn.send_close(1012, SHUTDOWN_REASON)
            self.transport.write(b"".join(self.conn.data_to_send()))
            self.transport.close()
            return
        super().shutdown()


def _too_big(exc: PayloadTooBig, limit: int | None) -> str:
    size = getattr(exc, "size", None)  # the frame's size; None for a message of several frames
    what = f"message of {size + (exc.current_size or 0)} bytes" if size is not None else "message"
    return f"{what} over the limit; this service accepts at most {limit} (JOINTLIMITS_MAX_FRAME_BYTES)"


def not_utf8() -> tuple[int, str]:
    return 1007, "a text message must be valid UTF-8 (send msgpack as a binary message)"


def server_options(max_frame_bytes: int) -> dict[str, Any]:
    """uvicorn's WebSocket options for the service: this protocol, the message limit it enforces (the
    application's, so the two agree), no permessage-deflate (docs/sessions.md, "The protocol, byte by byte")."""
    return {"ws": "jointlimits.service.http.timeouts:WriteTimeoutWebSocketProtocol", "ws_max_size": max_frame_bytes,
            "ws_per_message_deflate": False}


def frame_limit(websocket: WebSocket, configured: int) -> int:
    """The message limit in force on this connection: `configured` (JOINTLIMITS_MAX_FRAME_BYTES), or the server's
    own limit where it is lower (plain `uvicorn jointlimits.service.app:app` keeps uvicorn's 16 MiB `ws_max_size`).

    uvicorn's `receive` is a method of its protocol, whose config holds the limit; under another server
    (or Starlette's TestClient) it is not known, and the configured one is reported and enforced."""
    config = getattr(getattr(websocket._receive, "__self__", None), "config", None)
    server = getattr(config, "ws_max_size", None)
    return min(configured, server) if isinstance(server, int) and server > 0 else configured
