"""What every session (WebSocket sync and async, in-process) shares, free of I/O (docs/sessions.md, "Sessions").

A session keeps, client-side, what reopening needs: the scene as last updated, the last committed `q` (the
server's `q_prev`) and the committed coordinates; `reopen()` opens a new session in exactly that state.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import orjson
from numpy.typing import ArrayLike

from jointlimits.client import codec
from jointlimits.client.errors import Busy, Fault, ServiceError, Unreachable
from jointlimits.client.model import Array, Evaluation, Request, as_flag, as_outputs, as_request, in_body
from jointlimits.client.transport import (MAX_RETRY_AFTER, PROXY_STATUSES, Retry, Steps, T, is_fault_list, refusal,
                                         wrong_url)
from jointlimits.schemas import binary as wire
from jointlimits.schemas import session as proto
from jointlimits.service.core import registry
from jointlimits.service.core.validate import NOT_AN_INTEGER, as_array

Frame = bytes | str
_BINARY_ERROR = b"\xa4kind\xa5error"
_JSON_ERROR = '{"kind":"error"'


class SessionClosed(ServiceError):
    """The session's connection is gone: closed by the server (a bound: `code`, `reason`), dropped, or never made.

    `status` is the WebSocket close code (None when there was none). The session object still
    holds the committed state: `reopen()` continues where the last commit left off. `resumable`: the
    server went away (1001, 1012), was full for now (1013, 4429) or the connection dropped, so another server
    (or this one, later) can take the session over: a session with `resume` on (the default) has tried to already.
    """

    def __init__(self, url: str, code: int | None, reason: str, cause: str = "", resumable: bool = False) -> None:
        self.url, self.code, self.reason, self.resumable = url, code, reason, resumable
        self.status, self.faults = code or 0, [Fault((), reason or cause, "session_closed")]
        what = f"closed with code {code}" + (f" ({reason})" if reason else "") if code else cause
        Exception.__init__(self, f"session at {url} {what}; reopen() continues from the last commit")


CLOSED = "closed by close()"
DROPPED = "dropped (a lost connection, or a call interrupted before its reply) with resume off"
RESUMED_CLOSES = (proto.GOING_AWAY, proto.SERVICE_RESTART, proto.TRY_AGAIN_LATER, proto.TOO_MANY_SESSIONS)
"""Close codes after which the session goes on, after a pause, on a new connection: a server that stops (a rollout,
a scale-down), a worker whose upload budget (1013) or session slots (4429) are full for now."""


def resumable(e: Exception) -> bool:
    """A failure another server can take over from (`resume`): a session closed by a server that stops or
    dropped, no server reached, or a 502/503/504 to the upgrade (a proxy with no upstream, a worker that
    drains after SIGTERM and refuses new sessions)."""
    if isinstance(e, SessionClosed):
        return e.resumable
    return isinstance(e, Unreachable) or (isinstance(e, ServiceError) and e.status in (502, 503, 504))


class Resume(Retry):
    """The retries of one step of a session (an open, a message and its reply), by the HTTP clients' rule
    (`transport.Retry`), of a failure another server can take over from (`resumable`); one no server would mend
    (a fault, 401, 4408, ...) is raised at once. Past the retries a lost session's `SessionClosed` (the first
    failure) stays the one raised, the last as its cause, unless the last was busy."""

    def __init__(self, retries: int, backoff: float, on: bool, max_retry_after: float = MAX_RETRY_AFTER) -> None:
        super().__init__(retries if on else 0, backoff, max_retry_after)
        self._first: ServiceError | None = None

    def pause(self, e: ServiceError) -> float:
        self._first = first = self._first or e
        if not resumable(e):
            raise e
        try:
            return super().pause(e)
        except ServiceError as last:
            if isinstance(first, SessionClosed) and first is not e and not isinstance(last, Busy):
                raise first from last
            raise


class SessionState:
    """What every session keeps, client-side, for reopening: where (`url`), the scene as last updated (`request`),
    the last committed `q` (`q_prev`, the server's) and the committed `coordinates`; `request_for_reopen()`."""

    def __init__(self, request: Request | dict[str, Any], url: str) -> None:
        """`request`: a `Request`, or what `Client.evaluate` also takes (wire JSON as a dict, a `schemas.EvaluateRequest`)."""
        request = as_request(request)
        self.url = url
        # A private copy: later updates change it, the caller's request stays as it was.
        self.request = replace(request, batches=[copy.deepcopy(b) for b in request.batches])
        self.q_prev: Array = owned(request.q_prev)
        """The last committed `q` (the opening request's `q_prev` before any commit)."""
        self._coordinates: list[Array] = []
        self._committed_once = False  # before, a revolute's x is summed from q_ref: a reopen sends no prev_coordinate

    @property
    def coordinates(self) -> list[Array]:
        """The committed coordinates, one (N,) array per batch (as opened, before any commit)."""
        return list(self._coordinates)

    def _keep(self, coordinates: list[ArrayLike], q: ArrayLike) -> list[Array]:
        """A commit's state, kept for reopening; returns copies of `coordinates` (the caller's to change)."""
        self._coordinates, self.q_prev, self._committed_once = [owned(c) for c in coordinates], owned(q), True
        return [c.copy() for c in self._coordinates]

    def _apply_update(self, batch: int, index: ArrayLike, values: dict[str, ArrayLike | None]) -> None:
        """The server accepted the update: the local copy of the scene follows it."""
        b, idx = self.request.batches[batch], np.asarray(index, dtype=np.int64).reshape(-1)
        for k, v in values.items():
            if v is None:
                continue
            if getattr(b, k) is None:  # an offset given for the first time: the others stay 0
                setattr(b, k, np.zeros(len(b)))
            getattr(b, k)[idx] = np.asarray(v, dtype=np.float64).reshape(-1)

    def request_for_reopen(self) -> Request:
        """A request that opens a session in this one's committed state: `q_prev` and `q` the last committed
        `q`, the scene as updated, the committed coordinates of stateful joints (the revolute's angles) as
        `prev_coordinate` (contract v1.1), once they are the state (a commit, or a `prev_coordinate` opened with):
        the server then takes them back bit for bit."""
        batches = [copy.deepcopy(b) for b in self.request.batches]
        for b, coords in zip(batches, self._coordinates):  # none before the opening's reply
            facts = registry.CONSTITUTIONS.get(b.constitution_uid)  # a slide is absolute: no state
            if facts is not None and facts.stateful and (self._committed_once or b.prev_coordinate is not None):
                b.prev_coordinate = coords.copy()
        q = self.q_prev.copy()
        return replace(self.request, q=q, q_prev=q.copy(), batches=batches)


def owned(a: ArrayLike) -> Array:
    """A read-only float64 copy: the committed state a reopen starts from, which no caller's array aliases."""
    a = np.array(a, dtype=np.float64)
    a.flags.writeable = False
    return a


def message_array(value: Any, name: str, integer: bool = False) -> np.ndarray:
    """An array of a session message as the service reads it (`validate.as_array`, its JSON decoder's reading):
    no cast (an index of 0.5 is not joint 0); else `InvalidInput`, the service's fault, before anything is sent."""
    a, faults = as_array(value, (name,), integer)
    if faults:
        raise in_body(faults)
    return a


def evaluate_message(q: ArrayLike, outputs: Any, hessian_mode: str | None, active_only: bool | None) -> dict[str, Any]:
    """An `evaluate` message's fields as the service reads them: `q`, and the options given (None: the opening's)."""
    given = {"outputs": None if outputs is None else list(as_outputs(outputs)), "hessian_mode": hessian_mode,
             "active_only": None if active_only is None else as_flag(active_only)}
    return {"q": message_array(q, "q"), **{k: v for k, v in given.items() if v is not None}}


def update_message(batch: Any, index: ArrayLike, values: dict[str, ArrayLike | None]) -> dict[str, Any]:
    """An `update` message's fields as the service reads them: `batch` an int64 (0.5 is not batch 0, in pydantic's
    words), `index` and the values given (None: left out), neither cast nor reshaped."""
    listed = isinstance(batch, (list, tuple)) or (isinstance(batch, np.ndarray) and batch.ndim > 0)
    a, faults = (None, [Fault(("batch",), *NOT_AN_INTEGER)]) if listed else as_array([batch], ("batch",), integer=True)
    if faults:
        raise in_body([replace(faults[0], loc=("batch",))])  # the field, not its element
    return {"batch": int(a[0]), "index": message_array(index, "index", integer=True),
            **{k: message_array(v, k) for k, v in values.items() if v is not None}}


__all__ = ["Resume", "SessionClosed", "SessionState", "evaluate_message", "message_array", "resumable", "update_message"]


class Exchange(SessionState):
    """A WebSocket session's steps, free of I/O (the sans-I/O pattern): each a generator of the I/O it needs,
    `("connect", None)`, `("send", frame)` (sent the reply), `("sleep", seconds)`, `("drop", None)`, which
    `sync.Session` runs blocking and `aio.AsyncSession` awaited (their `_run`: `transport.run`, `transport.arun`)."""

    _ws: Any

    def __init__(self, url: str, request: Request, *, binary: bool = True, timeout: float | None = 60.0,
                 headers: dict[str, str] | None = None, retries: int = 3, backoff: float = 0.2,
                 resume: bool = True, max_retry_after: float = MAX_RETRY_AFTER) -> None:
        super().__init__(request, url)
        self.binary = binary
        self.bytes_sent = self.bytes_received = 0
        self.timeout, self.headers = timeout, dict(headers or {})
        self.retries, self.backoff, self.resume, self.max_retry_after = retries, backoff, resume, max_retry_after
        self._ws = None
        self._closed = False  # by `close()`: no more resuming
        self._begin()

    def _encode(self, doc: dict[str, Any]) -> Frame:
        return self._out(codec.dumps({k: np.ascontiguousarray(v) if isinstance(v, np.ndarray) else v
                                      for k, v in doc.items()}, self.binary))

    def _out(self, content: bytes) -> Frame:
        frame = content if self.binary else content.decode()
        self.bytes_sent += len(frame)
        return frame

    def _read(self, frame: Frame, kind: str) -> dict[str, Any]:
        """The reply document of `kind`; a fault reply raises `InvalidInput` / `TooLarge` (the session stays open)."""
        self.bytes_received += len(frame)
        doc = wire.loads(frame) if isinstance(frame, bytes) else orjson.loads(frame)
        if doc.get("kind") == proto.ERROR:
            raise ServiceError.from_body(int(doc.get("status", 422)), doc)
        if doc.get("kind") != kind:
            raise ServiceError(502, [Fault((), f"expected a {kind!r} reply, got {doc.get('kind')!r}", "protocol")])
        return doc

    def _array(self, v: Any) -> Array:
        return owned(wire.unpack_array(v, wire.FLOAT64, 1) if isinstance(v, dict) else v)

    def _begin(self) -> None:
        """The constructor's last step: the blocking session opens here, the asyncio one when awaited."""

    def _resuming(self, step: Callable[[], Steps[T]]) -> Steps[T]:
        """`step()`, tried again after a failure another server can take over (`Resume`)."""
        resume = Resume(self.retries, self.backoff, self.resume, self.max_retry_after)
        while True:
            try:
                return (yield from step())
            except ServiceError as e:  # SessionClosed, Unreachable, a refused upgrade, a fault
                yield "sleep", resume.pause(e)

    def _opening(self) -> Steps[None]:
        try:
            yield from self._resuming(self._open)
        except BaseException:
            # A refused opening (a fault, 4429, ...): close the connection before raising, so that the server has
            # let go of it (its session slot, its budget) by the time the caller tries again.
            yield "drop", None
            raise

    def _open(self) -> Steps[None]:
        yield "drop", None  # a connection whose opening was refused (a busy 503 reply) before trying again
        yield "connect", None
        doc = self._read((yield "send", self._out(codec.encode(self.request, self.binary)[0])), proto.OPENED)
        self._coordinates = [self._array(c) for c in doc["coordinates"]]
        self.limits: dict[str, Any] = dict(doc.get("limits", {}))  # the server's bounds in force: max_frame_bytes, idle_seconds

    def _reopen(self) -> Steps[None]:
        self._closed = False
        self.request = self.request_for_reopen()
        yield from self._open()

    def _exchange(self, doc: dict[str, Any]) -> Steps[Frame]:
        """`doc`'s reply; with `resume`, on a new connection in the committed state where the last one was lost."""
        frame = self._encode(doc)

        def attempt() -> Steps[Frame]:
            if self._ws is None and self.resume and not self._closed:
                yield from self._reopen()
            if self._ws is None:
                raise SessionClosed(self.url, None, "", CLOSED if self._closed else DROPPED)
            return (yield "send", frame)

        return (yield from self._resuming(attempt))

    def _evaluate(self, q: ArrayLike, outputs: Any, hessian_mode: str | None,
                  active_only: bool | None) -> Steps[Evaluation]:
        frame = yield from self._exchange({"kind": proto.EVALUATE, **evaluate_message(q, outputs, hessian_mode, active_only)})
        # Every reply starts with its kind (fixmap header, "kind", then the kind; or '{"kind":"...'): a fault is
        # read as such, an evaluation is HTTP's answer document (plus kind), which HTTP's decoder reads.
        if frame[1:12] == _BINARY_ERROR or frame[:15] == _JSON_ERROR:
            self._read(frame, proto.EVALUATION)  # raises the fault
        self.bytes_received += len(frame)
        ev = codec.decode(frame, codec.BINARY if isinstance(frame, bytes) else codec.JSON)  # type: ignore[arg-type]
        return ev.sized(self.request)  # each batch knows its size: `joint(k)` works under active_only

    def _commit(self, q: ArrayLike) -> Steps[list[Array]]:
        doc = self._read((yield from self._exchange({"kind": proto.COMMIT, "q": message_array(q, "q")})), proto.COMMITTED)
        return self._keep([self._array(c) for c in doc["coordinates"]], q)

    def _update(self, batch: int, index: ArrayLike, values: dict[str, ArrayLike | None]) -> Steps[None]:
        reply = yield from self._exchange({"kind": proto.UPDATE, **update_message(batch, index, values)})
        doc = self._read(reply, proto.UPDATED)
        self._apply_update(batch, index, values)
        if "coordinates" in doc:  # the batch's committed coordinates after a change of offsets
            self._coordinates[batch] = self._array(doc["coordinates"])

    def _close(self) -> Steps[None]:
        self._closed = True
        if self._ws is not None:
            try:
                yield "send", self._encode({"kind": proto.CLOSE})  # the server answers by closing (code 1000)
            except SessionClosed:
                pass
            yield "drop", None

    def _no_reply(self) -> SessionClosed:
        return SessionClosed(self.url, None, "", f"dropped (no reply within {self.timeout} s)")


def handshake_error(url: str, e: Exception) -> Exception:
    """Why a session did not open, as `evaluate` says it: `Unreachable` (nothing answered), `WrongURL` (a 404,
    or a server that is not this service), else the service's refusal (401, ...) as the `ServiceError` HTTP raises."""
    from websockets.exceptions import InvalidHandshake, InvalidMessage, InvalidStatus  # HTTP never loads websockets

    if isinstance(e, InvalidStatus):
        status, body = e.response.status_code, bytes(e.response.body or b"")
        proxy = status in PROXY_STATUSES and not is_fault_list(body)  # a proxy with no upstream: as `evaluate` says it
        if not proxy and (status == 404 or not is_fault_list(body)):  # the status read, not 404 (a FastAPI app with no route: 403)
            return wrong_url(url, f"answered HTTP {status} {e.response.reason_phrase} to the WebSocket upgrade", status)
        # A worker at its connection cap: `Busy`, waited as it asks (`Resume`); else the service's refusal (401, ...).
        return refusal(url, e.response, status, body, proxy) or codec.error(status, body)
    # Refused, unresolvable, no answer within the open timeout, or closed before any answer (`evaluate` retries it);
    # `InvalidMessage` says only "did not receive a valid HTTP response": its cause says what was read instead.
    why = e.__cause__ if isinstance(e, InvalidMessage) and e.__cause__ is not None else e
    if isinstance(e, (OSError, TimeoutError)) or isinstance(why, EOFError):
        return Unreachable(url, 1, why)
    if isinstance(e, (InvalidHandshake, InvalidMessage)):  # a server that speaks something else (HTTP/1.0, TLS, ...)
        return wrong_url(url, f"did not answer as a WebSocket server ({why})", 0)  # no status was read
    # The connection lost during the handshake (websockets' ConnectionClosed, or its reader's race with a refusal's
    # close): nothing was opened, so the opening is tried again, as after a drop.
    return SessionClosed(url, None, "", f"not opened ({type(e).__name__}: {e})", resumable=True)


def closed_error(url: str, e: Any) -> SessionClosed:
    frame = e.rcvd  # of websockets' ConnectionClosed
    if frame is None:  # dropped (no close frame): resumable
        return SessionClosed(url, None, "", "dropped (no close frame)", resumable=True)
    return SessionClosed(url, frame.code, frame.reason, resumable=frame.code in RESUMED_CLOSES)


CONNECT_OPTIONS: dict[str, Any] = dict(
    max_size=None,  # answers with Hessians are large; the server bounds what it sends by its scene limit
    compression=None,  # float64 arrays barely compress: deflate would only cost time on both sides
)
