"""The blocking clients: HTTP (`Client`) and its WebSocket sessions (`Client(url).session(request)`,
on `websockets.sync.client`), each step of `client/transport.py` and `client/session.py` run with blocking I/O."""

from __future__ import annotations

import functools
import sys
import time
from contextlib import ExitStack
from types import TracebackType
from typing import Any

import httpx
from numpy.typing import ArrayLike

from jointlimits.client import transport
from jointlimits.client.model import Array, Evaluation, Request, as_request
from jointlimits.client.session import CONNECT_OPTIONS, Exchange, closed_error, handshake_error
from jointlimits.client.transport import BaseClient, ProgressCallback, Steps, T, run
from jointlimits.schemas import ConstitutionsResponse, EvaluateRequest


class Client(BaseClient):
    """`POST /v1/evaluate` from NumPy arrays to NumPy arrays.

    `binary` (default) speaks msgpack with raw float64 buffers; `False` speaks JSON. Both
    return bit-identical numbers. Requests larger than the server's limits (or
    `max_joints_per_request`) are split and their answers merged; `progress=True` shows
    a stderr bar while they run, or pass a callback `(done, total)`.
    Connection failures (refused, reset, dropped) are retried `retries` times with exponential
    `backoff` (seconds); so is a busy 503 (the server had no room and computed nothing), after its
    `Retry-After` (at least the backoff step; a server asking more than `max_retry_after` seconds
    raises `Busy` at once), and a proxy's 502/503/504 (not the service's JSON error: no upstream
    answered), all from the one `retries` budget. No other status is retried (not the deadline's
    503 either); a 4xx/5xx raises `ServiceError` (`InvalidInput` for 422) carrying the server's
    `loc`s, `Busy` for a 503 still busy when the retries are spent, `Unreachable` (the proxy's
    `status`) for a proxy still answering for the service.
    `token` goes as `Authorization: Bearer <token>` (sessions too); none given, `$JOINTLIMITS_TOKEN` (the
    server's setting of that name) when set and not empty; `token=""` sends none.
    """

    _HTTP = httpx.Client
    _http: httpx.Client

    def constitutions(self) -> ConstitutionsResponse:
        """The supported constitutions (UIDs, attribute names, defaults, units) and the server's limits."""
        return transport.constitutions(self._send(self._constitutions_request()))

    def evaluate(self, request: Request | dict | EvaluateRequest, *, progress: bool | ProgressCallback | None = None) -> Evaluation:
        """Energy, gradient and Hessian of every joint of `request`, as NumPy arrays.

        `request` is one of:

        - a `client.Request`: `Scene().request(outputs=..., hessian_mode="psd", active_only=True)`
          (the options belong to the request, not to this call), or
          `request_from_arrays(q, [JointBatch.of(670, body_ids, edges, lower, upper, strength)])`;
        - a dict shaped like the wire JSON (`{"bodies": {"q": ..., "q_prev": ..., "q_ref": ...},
          "batches": [...], ...}`; lists or NumPy arrays), read exactly as the service reads JSON;
        - a `schemas.EvaluateRequest`.

        Returns an `Evaluation`: `total_energy`, and per request batch a `BatchResult` with rows
        `index` (M,), `x`, `energy` (M,), `gradient` (M, 24), `hessian` (M, 24, 24) (the last two
        when asked for), in the DOFs `[q_i, q_j]` of the joint's two bodies. `result.joint(j)` picks
        one joint by the handle `Scene` returned, with or without `active_only`.

        Raises `InvalidInput` (422: `e.loc` like `("body", "batches", 1, "lower", 2)`, `e.faults`),
        `TooLarge` (413), `Busy` (503 "busy" after the retries, or a `Retry-After` over
        `max_retry_after`), `ServiceError` (any other 4xx/5xx), `Unreachable` (no connection, or only
        a proxy's 502/503/504, after the retries), `WrongURL` (`base_url` is not the service), `TypeError` (not a request).
        Requests over the server's limits are split and merged; `progress` overrides the client's.

        >>> import numpy as np
        >>> from jointlimits import LocalClient, Scene
        >>> c, s, scene = np.cos(0.7), np.sin(0.7), Scene()
        >>> turned = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])  # 0.7 rad about +z
        >>> a, b = scene.add_body(np.eye(4)), scene.add_body(turned, ref=np.eye(4))
        >>> j = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5, strength=100.0)
        >>> client = LocalClient()  # in-process: a `Client(url)` answers the same, bit for bit
        >>> r = client.evaluate(scene.request()).joint(j)
        >>> round(r.x, 12), round(r.energy, 12)  # 0.2 rad past the upper limit
        (0.7, 0.8)
        """
        request = as_request(request)
        if self._limits is None:
            self._limits = self.constitutions()
        job = self._job(request, progress)
        return job.merge([job.receive(part, self._send(self._evaluate_request(part))) for part in job.parts])

    def session(self, request: Request | dict | EvaluateRequest, *, resume: bool = True) -> Session:
        """A session on the server's prepared scene of `request` (what `evaluate` takes; docs/sessions.md,
        "Sessions"): `with client.session(r) as s:`; `resume` as `Session` says."""
        return Session(request=request, resume=resume, **self._session_options())

    def _send(self, request: httpx.Request) -> httpx.Response:
        return run(self._sending(request), lambda op, arg: time.sleep(arg) if op == "sleep" else self._http.send(arg))

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        self.close()


class Session(Exchange):
    """A prepared scene on the server, held by one WebSocket connection (see `jointlimits.client.session`).

    `evaluate(q, ...)` answers as `Client.evaluate` does; `commit(q)` ends a time step and
    returns the committed coordinates (one (N,) array per batch); `update(batch, index, lower=...)`
    changes limits, strengths or offsets of some joints. A fault raises `InvalidInput` and the
    session stays open. With `resume` (the default), a connection closed by a server that stops
    (1012, 1001), full for now (1013, 4429) or dropped is reopened in the committed state and the message in flight sent
    again, `retries` times at most with `backoff` (behind a load balancer, on another server), as is an opening
    that reaches no server or one that drains (a busy 503, the worker's connection cap: after its `Retry-After`,
    as `evaluate`); else, or past them, a lost connection raises `SessionClosed`, and `reopen()` continues.
    """

    def _begin(self) -> None:
        self._stack = ExitStack()
        self._run(self._opening())

    def _run(self, steps: Steps[T]) -> T:
        return run(steps, self._io)

    def _io(self, op: str, arg: Any) -> Any:
        if op == "sleep":
            time.sleep(arg)
        elif op == "drop":
            if self._ws is not None:
                self._ws = None
                self._stack.close()
        elif op == "connect":
            from websockets.sync.client import connect  # here: HTTP alone never loads websockets

            try:
                # websockets 17 wants its connection used as a context manager: entered here, exited by "drop".
                self._stack = ExitStack()
                self._ws = self._stack.enter_context(connect(self.url, additional_headers=self.headers,
                                                             open_timeout=self.timeout, create_connection=_connection(),
                                                             **CONNECT_OPTIONS))
            except Exception as e:
                raise handshake_error(self.url, e) from None
        else:  # "send": the reply
            try:
                self._ws.send(arg)
                return self._ws.recv(timeout=self.timeout)
            except sys.modules["websockets.exceptions"].ConnectionClosed as e:  # loaded by "connect"
                self._io("drop", None)
                raise closed_error(self.url, e) from None
            except BaseException as e:  # no reply in time, or Ctrl-C before it (it would answer the next call)
                self._ws.close_timeout = 0  # given up: closed without waiting for a close handshake
                self._io("drop", None)
                if isinstance(e, TimeoutError):
                    raise self._no_reply() from None
                raise
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


@functools.cache
def _connection() -> type:
    """websockets' blocking connection, raising the server's answer to the upgrade once read, whatever else failed,
    and sending nothing after it: a worker at its connection cap answers 503 at accept, before the request is sent,
    and websockets' two threads raced (`ConnectionClosed`, or its own `AssertionError`: 1 opening in 5 here), its
    `Retry-After` unread, then wrote the upgrade to the closed socket (its "unexpected internal error" logged)."""
    from websockets.sync.client import ClientConnection

    class Connection(ClientConnection):
        def handshake(self, *args: Any, **kwargs: Any) -> None:
            try:
                super().handshake(*args, **kwargs)
            except Exception:
                if self.protocol.handshake_exc is None:
                    raise
                raise self.protocol.handshake_exc  # with its cause (an `EOFError`: `handshake_error` reads it)

        def send_data(self) -> None:  # the reader thread's last write, outside any `try`: EBADF, EPIPE, logged
            if self.protocol.handshake_exc is None:
                super().send_data()
            else:
                self.protocol.data_to_send()  # dropped (the caller holds the protocol's lock)

    return Connection
