"""What `Client` and `AsyncClient` share: their settings, the requests they send, what they make of the answers.

As in httpx's own `BaseClient`, everything here is free of I/O; the subclasses only send
(blocking or awaited), sleep between retries (as long as `transport.Retry` says), and run the
parts of a split in turn or concurrently.
"""

from __future__ import annotations

from typing import TypedDict

import httpx

from jointlimits.client import codec, split, transport
from jointlimits.client.errors import Fault, InvalidInput, ServiceError
from jointlimits.client.model import Evaluation, Request, null_arrays
from jointlimits.client.progress import ProgressCallback, resolve_progress
from jointlimits.schemas import ConstitutionsResponse

DEFAULT_URL = "http://127.0.0.1:8000"


class HttpOptions(TypedDict):
    """What a subclass builds its httpx client from (with its own, sync or async, transport)."""

    base_url: str
    timeout: float | httpx.Timeout
    headers: dict[str, str]


class BaseClient:
    """Settings and request logic of the HTTP clients; a subclass sets `_http` and does the I/O."""

    _http: httpx.Client | httpx.AsyncClient

    def __init__(
        self,
        base_url: str,
        *,
        binary: bool,
        timeout: float | httpx.Timeout,
        connect_timeout: float,
        retries: int,
        backoff: float,
        token: str | None,
        max_joints_per_request: int | None,
        progress: bool | ProgressCallback,
        max_retry_after: float,
    ) -> None:
        self.binary = binary
        self.retries, self.backoff = retries, backoff
        self.max_retry_after = max_retry_after
        self.max_joints_per_request = max_joints_per_request
        self.progress = progress
        self._limits: ConstitutionsResponse | None = None
        self._http_options = HttpOptions(
            base_url=base_url,
            timeout=transport.timeouts(timeout, connect_timeout),
            headers=transport.headers(token, binary),
        )

    def _constitutions_request(self) -> httpx.Request:
        return self._http.build_request("GET", "/v1/constitutions")

    def _evaluate_request(self, part: split.Part) -> httpx.Request:
        content, content_type = codec.encode(part.request, self.binary)
        return self._http.build_request("POST", "/v1/evaluate", content=content, headers={"Content-Type": content_type})

    def _retry(self, request: httpx.Request) -> transport.Retry:
        return transport.Retry(self.retries, self.backoff, f"{request.method} {request.url}", self.max_retry_after)

    def _job(self, request: Request, progress: bool | ProgressCallback | None) -> Job:
        """`request` in parts that fit `self._limits` (fetched by the caller: that is I/O); a None array
        is refused here, as the service would (it cannot be counted, split or encoded)."""
        if missing := null_arrays(request):
            raise InvalidInput(422, [Fault(("body", *f.loc), f.msg, f.type) for f in missing], where="invalid input")
        n = transport.part_joints(
            self._limits, self.binary, self.max_joints_per_request, request.outputs, len(request.batches)
        )
        parts = split.plan(request, n)
        report = resolve_progress(self.progress if progress is None else progress, len(parts))
        return Job(request, parts, report)


class Job:
    """One `evaluate` call: its parts, their answers in whatever order they arrive, the progress so far."""

    def __init__(self, request: Request, parts: list[split.Part], report: ProgressCallback | None) -> None:
        self.request, self.parts = request, parts
        self._report = report
        self._done = 0

    def receive(self, part: split.Part, response: httpx.Response) -> Evaluation:
        """The part's evaluation; a server error is raised with `loc`s in the numbering of the whole request."""
        try:
            result = transport.result(response)
        except ServiceError as e:
            raise split.relocate(part, e) from None
        self._done += part.n_joints
        if self._report:
            self._report(self._done, self.request.n_joints)
        return result

    def merge(self, results: list[Evaluation]) -> Evaluation:
        """The parts' evaluations, in the order of `parts`, as one."""
        return split.merge(self.request, self.parts, results).sized(self.request)
