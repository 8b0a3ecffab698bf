"""A session over WebSocket for asyncio (`AsyncClient(url).session(request)`), on `websockets.asyncio.client`.

`async with client.session(request) as s:` or `s = await client.session(request)`; the same
methods as the blocking `Session`, awaitable.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Generator
from types import TracebackType
from typing import Any, TypeVar

from numpy.typing import ArrayLike
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from jointlimits.client.errors import ServiceError
from jointlimits.client.model import Array, Evaluation, Request
from jointlimits.client.session import Frame, Resume, SessionClosed, SessionState, StateView
from jointlimits.client.session_sync import CONNECT_OPTIONS, closed_error, handshake_error

T = TypeVar("T")


class AsyncSession(StateView):
    """The asyncio twin of `jointlimits.client.session_sync.Session` (same arguments, results and errors)."""

    def __init__(self, url: str, request: Request, *, binary: bool = True, timeout: float | None = 60.0,
                 headers: dict[str, str] | None = None, retries: int = 3, backoff: float = 0.2,
                 resume: bool = True) -> None:
        self.state = SessionState(request, url, binary)
        self.timeout, self.headers = timeout, dict(headers or {})
        self.retries, self.backoff, self.resume = retries, backoff, resume
        self._ws: ClientConnection | None = None
        self._closed = False  # by `close()`: no more resuming

    async def open(self) -> AsyncSession:
        try:
            await self._resuming(self._open)
        except BaseException:
            await self._drop()  # a refused opening: the server lets go of it before the caller tries again
            raise
        return self

    async def _open(self) -> None:
        await self._drop()  # a connection whose opening was refused (a busy 503 reply) before trying again
        try:
            self._ws = await connect(self.url, additional_headers=self.headers, open_timeout=self.timeout,
                                     **CONNECT_OPTIONS)
        except Exception as e:
            raise handshake_error(self.url, e) from None
        self.state.opened(await self._send(self.state.open_frame()))

    def __await__(self) -> Generator[Any, None, AsyncSession]:
        return self.open().__await__()

    async def _resuming(self, step: Callable[[], Awaitable[T]]) -> T:
        """`Session._resuming`, awaited."""
        resume = Resume(self.retries, self.backoff, self.resume)
        while True:
            try:
                return await step()
            except ServiceError as e:
                await asyncio.sleep(resume.pause(e))

    async def _exchange(self, frame: Frame) -> Frame:
        async def attempt() -> Frame:
            if self._ws is None and self.resume and not self._closed:
                await self._reopen()
            return await self._send(frame)

        return await self._resuming(attempt)

    async def _send(self, frame: Frame) -> Frame:
        if self._ws is None:
            raise SessionClosed(self.url, None, "", "the session is closed")
        try:
            await self._ws.send(frame)
            return await asyncio.wait_for(self._ws.recv(), self.timeout)
        except ConnectionClosed as e:
            self._ws = None
            raise closed_error(self.url, e) from None
        except asyncio.TimeoutError:
            await self._drop()
            raise SessionClosed(self.url, None, "", f"no reply within {self.timeout} s") from None

    async def evaluate(self, q: ArrayLike, *, outputs: Any = None, hessian_mode: str | None = None,
                       active_only: bool | None = None) -> Evaluation:
        frame = self.state.evaluate_frame(q, outputs, hessian_mode, active_only)
        return self.state.evaluation(await self._exchange(frame))

    async def commit(self, q: ArrayLike) -> list[Array]:
        return self.state.committed(await self._exchange(self.state.commit_frame(q)), q)

    async def update(self, batch: int, index: ArrayLike, *, lower: ArrayLike | None = None,
                     upper: ArrayLike | None = None, strength: ArrayLike | None = None,
                     offset: ArrayLike | None = None) -> None:
        values = {"lower": lower, "upper": upper, "strength": strength, "offset": offset}
        self.state.updated(await self._exchange(self.state.update_frame(batch, index, values)), batch, index, values)

    def request_for_reopen(self) -> Request:
        return self.state.request_for_reopen()

    async def reopen(self) -> None:
        await self._resuming(self._reopen)

    async def _reopen(self) -> None:
        self._closed = False
        self.state.request = self.state.request_for_reopen()
        await self._open()

    async def _drop(self) -> None:
        if self._ws is not None:
            await self._ws.close()
            self._ws = None

    async def close(self) -> None:
        self._closed = True
        if self._ws is None:
            return
        try:
            await self._ws.send(self.state.close_frame())
            await asyncio.wait_for(self._ws.recv(), self.timeout)
        except (ConnectionClosed, asyncio.TimeoutError):
            pass
        await self._drop()

    async def __aenter__(self) -> AsyncSession:
        return await self.open() if self._ws is None else self

    async def __aexit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        await self.close()
