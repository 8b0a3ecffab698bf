"""A session over WebSocket for asyncio (`AsyncClient(url).session(request)`), on `websockets.asyncio.client`.

`async with client.session(request) as s:` or `s = await client.session(request)`; the same
methods as the blocking `Session`, awaitable.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Generator
from types import TracebackType
from typing import Any, TypeVar

from numpy.typing import ArrayLike
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from jointlimits.client.model import Array, Evaluation
from jointlimits.client.session import Exchange, Steps
from jointlimits.client.session_sync import CONNECT_OPTIONS, closed_error, handshake_error

T = TypeVar("T")
_CLOSING: set[asyncio.Task] = set()  # the close handshakes of dropped sessions (a loop keeps only weak references)


class AsyncSession(Exchange):
    """The asyncio twin of `jointlimits.client.session_sync.Session` (same arguments, results and errors)."""

    async def open(self) -> AsyncSession:
        await self._run(self._opening())
        return self

    def __await__(self) -> Generator[Any, None, AsyncSession]:
        return self.open().__await__()

    async def _run(self, steps: Steps[T]) -> T:
        """`Session._run`, each I/O awaited."""
        reply: Any = None
        error: BaseException | None = None
        while True:
            try:
                op, arg = steps.throw(error) if error is not None else steps.send(reply)
            except StopIteration as done:
                return done.value
            reply, error = None, None
            try:
                reply = await self._io(op, arg)
            except BaseException as e:
                error = e

    async def _io(self, op: str, arg: Any) -> Any:
        if op == "sleep":
            await asyncio.sleep(arg)
        elif op == "drop":
            if self._ws is not None:
                await self._ws.close()
                self._ws = None
        elif op == "connect":
            try:
                self._ws = await connect(self.url, additional_headers=self.headers, open_timeout=self.timeout,
                                         **CONNECT_OPTIONS)
            except Exception as e:
                raise handshake_error(self.url, e) from None
        else:  # "send": the reply
            try:
                await self._ws.send(arg)
                return await asyncio.wait_for(self._ws.recv(), self.timeout)
            except ConnectionClosed as e:
                self._ws = None
                raise closed_error(self.url, e) from None
            except asyncio.TimeoutError:
                await self._io("drop", None)
                raise self._no_reply() from None
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
        if ws is None or sys.is_finalizing():
            return

        def close() -> None:
            task = ws.loop.create_task(ws.close())
            _CLOSING.add(task)
            task.add_done_callback(_CLOSING.discard)

        try:
            ws.loop.call_soon_threadsafe(close)
        except RuntimeError:  # the loop is closed
            pass
