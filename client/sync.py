"""The synchronous HTTP client."""

from __future__ import annotations

import time
from types import TracebackType
from typing import TYPE_CHECKING

import httpx

from jointlimits.client import transport
from jointlimits.client.accept import as_request
from jointlimits.client.model import Evaluation, Request
from jointlimits.client.transport import BaseClient, ProgressCallback
from jointlimits.schemas import ConstitutionsResponse, EvaluateRequest


if TYPE_CHECKING:  # sessions are imported when opened: HTTP alone never loads websockets
    from jointlimits.client.session_sync import Session


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

        >>> scene = Scene()
        >>> a, b = scene.add_body(np.eye(4)), scene.add_body(turned, ref=np.eye(4))
        >>> j = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5, strength=100.0)
        >>> r = client.evaluate(scene.request()).joint(j)
        >>> r.x, r.energy
        (0.7, 0.7999999999999995)
        """
        request = as_request(request)
        if self._limits is None:
            self._limits = self.constitutions()
        job = self._job(request, progress)
        return job.merge([job.receive(part, self._send(self._evaluate_request(part))) for part in job.parts])

    def session(self, request: Request | dict | EvaluateRequest, *, resume: bool = True) -> Session:
        """A session on the server's prepared scene of `request` (what `evaluate` takes; docs/sessions.md,
        "Sessions"): `with client.session(r) as s:`. `resume`: a session closed by a server that stops (1012,
        1001) or is full for now (1013, 4429), or dropped, is reopened in its committed state and the message
        in flight sent again, and an open that reaches no server, or one that drains, is tried again: `retries`
        times with `backoff`."""
        from jointlimits.client.session_sync import Session  # imported here: HTTP alone never loads websockets

        return Session(request=request, resume=resume, **self._session_options())

    def _send(self, request: httpx.Request) -> httpx.Response:
        retry = self._retry(request)
        while True:
            try:
                response = self._http.send(request)
            except transport.RETRYABLE as e:
                time.sleep(retry.pause(e))
                continue
            pause = retry.again(response)  # None: the answer; else a busy 503 or a proxy's 502/503/504 to retry
            if pause is None:
                return response
            time.sleep(pause)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        self.close()
