"""The asyncio HTTP client: the same API as `Client`, with parts of a split request sent concurrently."""

from __future__ import annotations

import asyncio
from types import TracebackType

import httpx

from client import codec, split, transport
from client.errors import ServiceError
from client.model import Evaluation, Request
from client.progress import ProgressCallback, resolve_progress
from schemas import ConstitutionsResponse


class AsyncClient:
    """Async twin of `client.Client` (same arguments, same results and errors); `concurrency`
    bounds how many parts of a split request are in flight at once."""

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
        concurrency: int = 4,
        http_transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        self.binary = binary
        self.retries, self.backoff = retries, backoff
        self.max_joints_per_request = max_joints_per_request
        self.progress = progress
        self.concurrency = concurrency
        self._limits: ConstitutionsResponse | None = None
        self._http = httpx.AsyncClient(
            base_url=base_url, timeout=timeout, headers=transport.headers(token, binary), transport=http_transport
        )

    async def constitutions(self) -> ConstitutionsResponse:
        return transport.constitutions(await self._send("GET", "/v1/constitutions"))

    async def evaluate(self, request: Request, *, progress: bool | ProgressCallback | None = None) -> Evaluation:
        if self._limits is None:
            self._limits = await self.constitutions()
        parts = split.plan(request, transport.part_joints(self._limits, self.binary, self.max_joints_per_request))
        report = resolve_progress(self.progress if progress is None else progress, len(parts))
        gate = asyncio.Semaphore(self.concurrency)
        done = 0

        async def run(part: split.Part) -> Evaluation:
            nonlocal done
            content, content_type = codec.encode(part.request, self.binary)
            async with gate:
                response = await self._send(
                    "POST", "/v1/evaluate", content=content, headers={"Content-Type": content_type}
                )
            try:
                ev = transport.result(response)
            except ServiceError as e:
                raise split.relocate(part, e) from None
            done += part.n_joints
            if report:
                report(done, request.n_joints)
            return ev

        results = await asyncio.gather(*(run(p) for p in parts))
        return split.merge(request, parts, list(results))

    async def _send(self, method: str, url: str, **kw: object) -> httpx.Response:
        for pause in [*transport.delays(self.retries, self.backoff), None]:
            try:
                return await self._http.request(method, url, **kw)  # type: ignore[arg-type]
            except transport.RETRYABLE:
                if pause is None:
                    raise
                await asyncio.sleep(pause)
        raise AssertionError("unreachable")

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        await self.aclose()
