"""The asyncio clients, `Client`'s API awaitable: `AsyncClient` (parts of a split request sent concurrently) and its
sessions (`async with AsyncClient(url).session(request) as s:`, on `websockets.asyncio.client`): each step of
`client/transport.py` and `client/session.py` run with awaited I/O."""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Generator
from types import TracebackType
from typing import Any

import httpx
from numpy.typing import ArrayLike

from jointlimits.client import split, transport
from jointlimits.client.model import Array, Evaluation, Request, as_request
from jointlimits.client.session import CONNECT_OPTIONS, Exchange, closed_error, handshake_error
from jointlimits.client.transport import DEFAULT_URL, BaseClient, ProgressCallback, Steps, T, arun
from jointlimits.schemas import ConstitutionsResponse, EvaluateRequest

_CLOSING: set[asyncio.Task] = set()  # the close handshakes of dropped sessions (a loop keeps only weak references)


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

        tasks = [asyncio.ensure_future(run(part)) for part in job.parts]
        try:
            return job.merge(await asyncio.gather(*tasks))
        except BaseException:  # a part failed (or `progress` raised): the others are not sent on, as `Client`'s
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            raise

    def session(self, request: Request | dict | EvaluateRequest, *, resume: bool = True) -> AsyncSession:
        """`async with client.session(r) as s:` (or `s = await client.session(r)`): `Client.session`, awaitable."""
        return AsyncSession(request=request, resume=resume, **self._session_options())

    async def _send(self, request: httpx.Request) -> httpx.Response:
        return await arun(self._sending(request), self._io)

    async def _io(self, op: str, arg: Any) -> Any:
        return await (asyncio.sleep(arg) if op == "sleep" else self._http.send(arg))

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        await self.aclose()


class AsyncSession(Exchange):
    """The asyncio twin of `jointlimits.client.sync.Session` (same arguments, results and errors)."""

    async def open(self) -> AsyncSession:
        await self._run(self._opening())
        return self

    def __await__(self) -> Generator[Any, None, AsyncSession]:
        return self.open().__await__()

    async def _run(self, steps: Steps[T]) -> T:
        return await arun(steps, self._io)

    async def _io(self, op: str, arg: Any) -> Any:
        if op == "sleep":
            await asyncio.sleep(arg)
        elif op == "drop":
            if self._ws is not None:
                await self._ws.close()
                self._ws = None
        elif op == "connect":
            from websockets.asyncio.client import connect  # here: HTTP alone never loads websockets

            try:
                self._ws = await connect(self.url, additional_headers=self.headers, open_timeout=self.timeout,
                                         **CONNECT_OPTIONS)
            except Exception as e:
                raise handshake_error(self.url, e) from None
        else:  # "send": the reply
            try:
                await self._ws.send(arg)
                return await asyncio.wait_for(self._ws.recv(), self.timeout)
            except sys.modules["websockets.exceptions"].ConnectionClosed as e:  # loaded by "connect"
                self._ws = None
                raise closed_error(self.url, e) from None
            except BaseException as e:  # no reply in time, or cancelled before it (it would answer the next call)
                ws, self._ws = self._ws, None
                ws.close_timeout = 0  # given up: closed without waiting for a close handshake
                if isinstance(e, asyncio.TimeoutError):
                    await ws.close()
                    raise self._no_reply() from None
                _close_soon(ws)  # not awaited: a cancelled task awaits nothing more
                raise
        return None

    async def evaluate(self, q: ArrayLike, *, outputs: Any = None, hessian_mode: str | None = None,
                       active_only: bool | None = None) -> Evaluation:
        return await self._run(self._evaluate(q, outputs, hessian_mode, active_only))

    async def commit(self, q: ArrayLike) -> list[Array]:
        return await self._run(self._commit(q))

    async def update(self, batch: int, index: ArrayLike, *, lower: ArrayLike | None = None,
                     upper: ArrayLike | None = None, strength: ArrayLike | None = None,
                     offset: ArrayLike | None = None) -> None:
        values = {"lower": lower, "upper": upper, "strength": strength, "offset": offset}
        await self._run(self._update(batch, index, values))

    async def reopen(self) -> None:
        await self._run(self._resuming(self._reopen))

    async def close(self) -> None:
        await self._run(self._close())

    async def __aenter__(self) -> AsyncSession:
        return await self.open() if self._ws is None else self

    async def __aexit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        await self.close()

    def __del__(self) -> None:
        # Dropped without close() (a notebook cell run again): close the connection now, on its own loop (a task:
        # `__del__` cannot await), and free the server's session slot, not when the loop ends. A loop already
        # closed has dropped the socket itself.
        ws = getattr(self, "_ws", None)
        if ws is not None and not sys.is_finalizing():
            _close_soon(ws)


def _close_soon(ws: Any) -> None:
    """Close `ws` in a task of its own loop (from any thread), kept in `_CLOSING` until done."""
    def close() -> None:
        task = ws.loop.create_task(ws.close())
        _CLOSING.add(task)
        task.add_done_callback(_CLOSING.discard)

    try:
        ws.loop.call_soon_threadsafe(close)
    except RuntimeError:  # the loop is closed: it has dropped the socket itself
        pass
