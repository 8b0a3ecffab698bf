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
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.observability import LIFESPAN_METRICS

BODY_TIMED_OUT = "body_timed_out"  # key in the request's scope state, read by `client_gone`
_408 = b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain\r\ncontent-length: 33\r\nconnection: close\r\n\r\nrequest headers not sent in time\n"
log = logging.getLogger("jointlimits.timeouts")


def header_timeout_from_env() -> float:
    """`Settings().header_timeout`: JOINTLIMITS_HEADER_TIMEOUT, which `jointlimits serve` sets for its workers."""
    from service.settings import Settings

    return Settings().header_timeout


class ReadTimeoutProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with a deadline on each request head (`header_timeout` seconds)."""

    header_timeout: float | None = None  # None: JOINTLIMITS_HEADER_TIMEOUT, read per connection

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.header_timeout is None:
            self.header_timeout = header_timeout_from_env()
        self._head_timer: asyncio.TimerHandle | None = None
        self._head_bytes = False  # bytes of the current head have arrived

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
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


def http_protocol(header_timeout: float) -> type[ReadTimeoutProtocol]:
    """A `ReadTimeoutProtocol` with its own `header_timeout` (for an in-process uvicorn.Config)."""
    return type("ReadTimeoutProtocol", (ReadTimeoutProtocol,), {"header_timeout": header_timeout})


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
