"""The asyncio HTTP client: the same API as `Client`, with parts of a split request sent concurrently."""

from __future__ import annotations

import asyncio
from types import TracebackType
from typing import TYPE_CHECKING

import httpx

from jointlimits.client import split, transport
from jointlimits.client.accept import as_request
from jointlimits.client.model import Evaluation, Request
from jointlimits.client.transport import DEFAULT_URL, BaseClient, ProgressCallback
from jointlimits.schemas import ConstitutionsResponse, EvaluateRequest


if TYPE_CHECKING:  # sessions are imported when opened: HTTP alone never loads websockets
    from jointlimits.client.session_aio import AsyncSession


class AsyncClient(BaseClient):
    """Async twin of `client.Client` (same arguments, same results and errors); `concurrency`
    bounds how many parts of a split request are in flight at once."""

    _HTTP = httpx.AsyncClient
    _http: httpx.AsyncClient

    # Spelled out, as `Client`'s (tests/sdk/test_client_sdk.py holds them to the same), plus `concurrency`.
    def __init__(self, base_url: str = DEFAULT_URL, *, binary: bool = True, timeout: float | httpx.Timeout = 60.0,
                 connect_timeout: float = transport.CONNECT_TIMEOUT, retries: int = 3, backoff: float = 0.2,
                 token: str | None = None, max_joints_per_request: int | None = None,
                 progress: bool | ProgressCallback = False, max_retry_after: float = transport.MAX_RETRY_AFTER,
                 concurrency: int = 4, http_transport: httpx.AsyncBaseTransport | None = None) -> None:
        options = {k: v for k, v in locals().items() if k not in ("self", "concurrency", "__class__")}
        super().__init__(**options)
        self.concurrency = concurrency

    async def constitutions(self) -> ConstitutionsResponse:
        return transport.constitutions(await self._send(self._constitutions_request()))

    async def evaluate(
        self, request: Request | dict | EvaluateRequest, *, progress: bool | ProgressCallback | None = None
    ) -> Evaluation:
        """`Client.evaluate`, awaited: the same arguments, results and errors; the parts of a split
        request are in flight `concurrency` at a time."""
        request = as_request(request)
        if self._limits is None:
            self._limits = await self.constitutions()
        job = self._job(request, progress)
        gate = asyncio.Semaphore(self.concurrency)

        async def run(part: split.Part) -> Evaluation:
            outgoing = self._evaluate_request(part)  # only sending is gated: parts encode while others are in flight
            async with gate:
                response = await self._send(outgoing)
            return job.receive(part, response)

        return job.merge(await asyncio.gather(*(run(part) for part in job.parts)))

    def session(self, request: Request | dict | EvaluateRequest, *, resume: bool = True) -> AsyncSession:
        """`async with client.session(r) as s:` (or `s = await client.session(r)`): `Client.session`, awaitable."""
        from jointlimits.client.session_aio import AsyncSession  # imported here: HTTP alone never loads websockets

        return AsyncSession(request=request, resume=resume, **self._session_options())

    async def _send(self, request: httpx.Request) -> httpx.Response:
        retry = self._retry(request)
        while True:
            try:
                response = await self._http.send(request)
            except transport.RETRYABLE as e:
                await asyncio.sleep(retry.pause(e))
                continue
            pause = retry.again(response)  # None: the answer; else a busy 503 or a proxy's 502/503/504 to retry
            if pause is None:
                return response
            await asyncio.sleep(pause)

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        await self.aclose()
