"""A session over WebSocket, blocking (`Client(url).session(request)`), on `websockets.sync.client`."""

from __future__ import annotations

import sys
import time
from contextlib import ExitStack
from types import TracebackType
from typing import Any, TypeVar

from numpy.typing import ArrayLike
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidMessage, InvalidStatus
from websockets.sync.client import connect

from jointlimits.client import codec
from jointlimits.client.errors import Unreachable
from jointlimits.client.model import Array, Evaluation
from jointlimits.client.session import RESUMED_CLOSES, Exchange, SessionClosed, Steps
from jointlimits.client.transport import PROXY_STATUSES, is_fault_list, proxy_page, wrong_url

T = TypeVar("T")


def handshake_error(url: str, e: Exception) -> Exception:
    """Why a session did not open, as `evaluate` says it: `Unreachable` (nothing answered), `WrongURL` (a 404,
    or a server that is not this service), else the service's refusal (401, ...) as the `ServiceError` HTTP raises."""
    if isinstance(e, InvalidStatus):
        status, body = e.response.status_code, bytes(e.response.body or b"")
        if status in PROXY_STATUSES and not is_fault_list(body):  # a proxy with no upstream: as `evaluate` says it
            return Unreachable(url, 1, status=status, proxy=proxy_page(body))
        if status == 404 or not is_fault_list(body):
            return wrong_url(url, f"answered HTTP {status} to the WebSocket upgrade", 404)
        return codec.error(status, body)
    if isinstance(e, (InvalidHandshake, InvalidMessage)):  # a server that speaks something else (HTTP/1.0, TLS, ...)
        return wrong_url(url, f"did not answer as a WebSocket server ({type(e).__name__}: {e})", 404)
    if isinstance(e, (OSError, TimeoutError)):  # refused, unresolvable host, no answer within the open timeout
        return Unreachable(url, 1, e)
    return SessionClosed(url, None, "", f"{type(e).__name__}: {e}")


def closed_error(url: str, e: ConnectionClosed) -> SessionClosed:
    frame = e.rcvd
    if frame is None:  # dropped (no close frame): resumable
        return SessionClosed(url, None, "", "no close frame", resumable=True)
    return SessionClosed(url, frame.code, frame.reason, resumable=frame.code in RESUMED_CLOSES)


CONNECT_OPTIONS: dict[str, Any] = dict(
    max_size=None,  # answers with Hessians are large; the server bounds what it sends by its scene limit
    compression=None,  # float64 arrays barely compress: deflate would only cost time on both sides
)


class Session(Exchange):
    """A prepared scene on the server, held by one WebSocket connection (see `jointlimits.client.session`).

    `evaluate(q, ...)` answers as `Client.evaluate` does; `commit(q)` ends a time step and
    returns the committed coordinates (one (N,) array per batch); `update(batch, index, lower=...)`
    changes limits, strengths or offsets of some joints. A fault raises `InvalidInput` and the
    session stays open. With `resume` (the default), a connection closed by a server that stops
    (1012, 1001), full for now (1013, 4429) or dropped is reopened in the committed state and the message in flight sent
    again, `retries` times at most with `backoff` (behind a load balancer, on another server);
    else, or past them, a lost connection raises `SessionClosed`, and `reopen()` continues.
    """

    def _begin(self) -> None:
        self._stack = ExitStack()
        self._run(self._opening())

    def _run(self, steps: Steps[T]) -> T:
        """`steps` run to the end, each I/O it asks for done here, blocking, and its result (or failure) sent back."""
        reply: Any = None
        error: BaseException | None = None
        while True:
            try:
                op, arg = steps.throw(error) if error is not None else steps.send(reply)
            except StopIteration as done:
                return done.value
            reply, error = None, None
            try:
                reply = self._io(op, arg)
            except BaseException as e:  # thrown into `steps`, where it is handled or raised on
                error = e

    def _io(self, op: str, arg: Any) -> Any:
        if op == "sleep":
            time.sleep(arg)
        elif op == "drop":
            if self._ws is not None:
                self._ws = None
                self._stack.close()
        elif op == "connect":
            try:
                # websockets 17 wants its connection used as a context manager: entered here, exited by "drop".
                self._stack = ExitStack()
                self._ws = self._stack.enter_context(
                    connect(self.url, additional_headers=self.headers, open_timeout=self.timeout, **CONNECT_OPTIONS))
            except Exception as e:
                raise handshake_error(self.url, e) from None
        else:  # "send": the reply
            try:
                self._ws.send(arg)
                return self._ws.recv(timeout=self.timeout)
            except ConnectionClosed as e:
                self._io("drop", None)
                raise closed_error(self.url, e) from None
            except TimeoutError:
                self._io("drop", None)
                raise self._no_reply() from None
        return None

    def evaluate(self, q: ArrayLike, *, outputs: Any = None, hessian_mode: str | None = None,
                 active_only: bool | None = None) -> Evaluation:
        """Energy, gradient, Hessian at `q` (B, 12); options default to the opening request's."""
        return self._run(self._evaluate(q, outputs, hessian_mode, active_only))

    def commit(self, q: ArrayLike) -> list[Array]:
        """End the time step at the accepted `q`: the committed coordinates; `q` becomes `q_prev`."""
        return self._run(self._commit(q))

    def update(self, batch: int, index: ArrayLike, *, lower: ArrayLike | None = None, upper: ArrayLike | None = None,
               strength: ArrayLike | None = None, offset: ArrayLike | None = None) -> None:
        """Change per-joint values of joints `index` of `batch` (each given array: one entry per index)."""
        self._run(self._update(batch, index, {"lower": lower, "upper": upper, "strength": strength, "offset": offset}))

    def reopen(self) -> None:
        """A new connection in the committed state (after a drop, or to move to another server)."""
        self._run(self._resuming(self._reopen))

    def close(self) -> None:
        """Ask the server to close (code 1000); closing a closed session does nothing."""
        self._run(self._close())

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        self.close()

    def __del__(self) -> None:
        # Dropped without close() (a notebook cell run again): free the socket, its two threads and the server's
        # session slot now, waiting a second at most for the server's close frame. Not at exit: websockets' threads
        # are stopped by then, and closing would wait on them for ever (the server sees the socket end instead).
        if getattr(self, "_ws", None) is not None and not sys.is_finalizing():
            self._ws.close_timeout = min(self._ws.close_timeout or 1.0, 1.0)
            self._stack.close()
