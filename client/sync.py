"""The synchronous HTTP client."""

from __future__ import annotations

import time
from types import TracebackType

import httpx

from client import codec, split, transport
from client.progress import ProgressCallback, resolve_progress
from client.errors import ServiceError
from client.model import Evaluation, Request
from schemas import ConstitutionsResponse


class Client:
    """`POST /v1/evaluate` from NumPy arrays to NumPy arrays.

    `binary` (default) speaks msgpack with raw float64 buffers; `False` speaks JSON. Both
    return bit-identical numbers. Requests larger than the server's limits (or
    `max_joints_per_request`) are split and their answers merged; `progress=True` shows
    a stderr bar while they run, or pass a callback `(done, total)`.
    Connection failures are retried `retries` times with exponential `backoff` (seconds);
    a 4xx/5xx raises `ServiceError` (`InvalidInput` for 422) carrying the server's `loc`s.
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        binary: bool = True,
        timeout: float | httpx.Timeout = 60.0,
        retries: int = 3,
        backoff: float = 0.2,
        token: str | None = None,
        max_joints_per_request: int | None = None,
        progress: bool | ProgressCallback = False,
        http_transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.binary = binary
        self.retries, self.backoff = retries, backoff
        self.max_joints_per_request = max_joints_per_request
        self.progress = progress
        self._limits: ConstitutionsResponse | None = None
        self._http = httpx.Client(
            base_url=base_url, timeout=timeout, headers=transport.headers(token, binary), transport=http_transport
        )

    def constitutions(self) -> ConstitutionsResponse:
        """The supported constitutions (UIDs, attribute names, defaults, units) and the server's limits."""
        return transport.constitutions(self._send("GET", "/v1/constitutions"))

    def evaluate(self, request: Request, *, progress: bool | ProgressCallback | None = None) -> Evaluation:
        """Energy, gradient and Hessian of every joint of `request` (see `Evaluation`)."""
        if self._limits is None:
            self._limits = self.constitutions()
        parts = split.plan(request, transport.part_joints(self._limits, self.binary, self.max_joints_per_request))
        report = resolve_progress(self.progress if progress is None else progress, len(parts))
        results, done = [], 0
        for part in parts:
            content, content_type = codec.encode(part.request, self.binary)
            response = self._send("POST", "/v1/evaluate", content=content, headers={"Content-Type": content_type})
            try:
                results.append(transport.result(response))
            except ServiceError as e:
                raise split.relocate(part, e) from None
            done += part.n_joints
            if report:
                report(done, request.n_joints)
        return split.merge(request, parts, results)

    def _send(self, method: str, url: str, **kw: object) -> httpx.Response:
        for pause in [*transport.delays(self.retries, self.backoff), None]:
            try:
                return self._http.request(method, url, **kw)  # type: ignore[arg-type]
            except transport.RETRYABLE:
                if pause is None:
                    raise
                time.sleep(pause)
        raise AssertionError("unreachable")

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        self.close()

