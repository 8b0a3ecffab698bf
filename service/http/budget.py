"""A worker's two memory budgets (sizes from the limits, `service/sizing.py`; docs/deployment.md, "Limits"):
what its requests hold together, whatever arrives at once, each request being admitted on its own cost (`limits`).

- uploads: the bodies being received (and a session's messages, `timeouts`), counted as their bytes arrive.
  Nothing waits for it: a chunk that does not fit makes the answer 503 `busy`, the rest read and dropped, so a
  slow sender holds only what it sent.
- in flight: a request's cost, bounded from its body's size, cut to what it holds once parsed (`routes`), then to
  its encoded answer, released once that has left the process (`ReleaseMiddleware`). Requests (and a session's
  opening and evaluates) wait in arrival order; past `queue_timeout` they are 503 `busy`, nothing evaluated.

Neither waits on the other (a body's upload bytes are given back once it is in flight): no deadlock.
"""

from __future__ import annotations

import asyncio
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from starlette.requests import Request
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from jointlimits.service import sizing
from jointlimits.service.http import limits
from jointlimits.service.http.errors import busy
from jointlimits.service.http.timeouts import DRAIN
from jointlimits.service.settings import Settings

SMALL_SHARE = 16
"""A request of at most this fraction of the budget (~160 MB at the defaults, ~50 MB at the manifest's
limits: every request of a few thousand joints) passes the waiters when it fits."""


@dataclass(eq=False)
class _Waiter:
    size: int
    future: asyncio.Future[None]
    loop: asyncio.AbstractEventLoop
    granted: bool = False


def _resolve(future: asyncio.Future[None]) -> None:
    if not future.done():  # a waiter that timed out meanwhile is done (cancelled)
        future.set_result(None)


@dataclass(eq=False)
class Reservation:
    """Bytes held in a `Budget` by one request; `shrink` and `release` may be called from any thread."""

    budget: Budget
    size: int
    _released: bool = False

    def try_grow(self, size: int) -> bool:
        """Hold `size` more bytes if they fit now and nobody waits (no waiting: for the uploads budget)."""
        b = self.budget
        with b._lock:
            fits = not self._released and not b._waiters and b.held + size <= b.capacity
            if fits:
                b.held += size
                self.size += size
        if fits:
            b._changed()
        return fits

    def shrink(self, size: int) -> None:
        """Hold `size` bytes from now on, if less than now (it never waits to grow: no request waits holding)."""
        self._give_back(max(0, self.size - max(size, 0)))

    def release(self) -> None:
        """Give every byte back (idempotent)."""
        self._give_back(self.size, final=True)

    def _give_back(self, size: int, final: bool = False) -> None:
        b = self.budget
        with b._lock:
            if self._released:
                return
            size = min(size, self.size)
            self.size -= size
            self._released = final
            b.held -= size
            b._wake()
        b._changed()


class Budget:
    """`capacity` bytes shared by the requests in flight; waiters served in arrival order (a small arrival,
    at most `capacity / SMALL_SHARE`, that fits starts at once). Thread-safe: the event loop acquires, worker
    threads may shrink and release (waking the waiters through their loop)."""

    def __init__(self, capacity: int, on_change: Callable[[Budget], None] | None = None) -> None:
        self.capacity, self.held = capacity, 0
        self._lock = threading.Lock()
        self._waiters: deque[_Waiter] = deque()
        self._on_change = on_change  # metrics: held bytes and queue length, after each change

    @property
    def queued(self) -> int:
        return len(self._waiters)

    async def acquire(self, size: int, timeout: float) -> Reservation:
        """Reserve `size` bytes (at most `capacity`: every request fits alone): at once if they fit and nobody
        waits (or they are small), else once every earlier waiter has been served and they fit; 503 busy after
        `timeout` seconds (JOINTLIMITS_QUEUE_TIMEOUT) of waiting (the waiter leaves the queue)."""
        size = min(max(size, 0), self.capacity)
        loop = asyncio.get_running_loop()
        with self._lock:
            # A small request that fits starts at once, even past waiters: it does not queue behind a large
            # one for the seconds that one may wait (which may then wait as long as smalls keep its room).
            passes = not self._waiters or size <= self.capacity // SMALL_SHARE
            granted = passes and self.held + size <= self.capacity
            if granted:
                self.held += size
            else:
                waiter = _Waiter(size, loop.create_future(), loop)
                self._waiters.append(waiter)
        self._changed()
        if granted:
            return Reservation(self, size)
        try:
            await asyncio.wait_for(waiter.future, timeout)
        except BaseException as e:  # timed out, or the request was cancelled (its client left)
            with self._lock:
                if waiter.granted:  # granted in the same instant: hand the bytes on
                    self.held -= size
                else:
                    self._waiters.remove(waiter)
                self._wake()  # a large waiter leaving the head may let the next ones in
            self._changed()
            if isinstance(e, TimeoutError):
                raise busy(f"this worker's requests in flight hold its memory budget ({self.capacity} bytes, "
                           f"docs/deployment.md, 'Limits and sizing a pod') and this request waited {timeout:g} s "
                           "(JOINTLIMITS_QUEUE_TIMEOUT) without starting") from None
            raise
        return Reservation(self, size)

    def reserve_now(self) -> Reservation:
        """An empty reservation, grown by `Reservation.try_grow` as bytes arrive."""
        return Reservation(self, 0)

    def _changed(self) -> None:
        if self._on_change is not None:
            self._on_change(self)

    def _wake(self) -> None:
        """Grant waiters from the head while they fit (lock held)."""
        while self._waiters and self.held + self._waiters[0].size <= self.capacity:
            waiter = self._waiters.popleft()
            self.held += waiter.size
            waiter.granted = True
            waiter.loop.call_soon_threadsafe(_resolve, waiter.future)


async def receive(request: Request, settings: Settings, binary_request: bool, binary_answer: bool) -> bytes:
    """The request's body, received within the worker's upload budget (once a chunk does not fit, the rest is
    read and dropped, then 503 busy); then its turn in the in-flight budget (bounded from the body's size until
    parsed), which counts the body, so its upload bytes are given back. Both are given back once the
    answer has been sent (`ReleaseMiddleware`)."""
    reservations = request.state.reservations  # given back by `ReleaseMiddleware`
    uploads = request.app.state.uploads
    upload = uploads.reserve_now()
    reservations.append(upload)

    def take(n: int) -> bool:
        if upload.try_grow(sizing.UPLOAD_FACTOR * n):
            return True
        upload.release()  # the chunks kept so far are dropped with it
        return False

    try:
        body = await limits.read_body(request, settings.max_body_bytes, settings.body_timeout, take)
        if body is None:  # refused as it arrived, then drained
            raise busy(f"this worker is receiving as many request bodies as its upload budget holds "
                       f"({uploads.capacity} bytes, docs/deployment.md, 'Limits and sizing a pod')")
        cost = sizing.cost_before_body(len(body), binary_request, binary_answer, settings)
        reservation = await request.app.state.in_flight.acquire(cost, settings.queue_timeout)
    finally:
        upload.release()
    reservations.append(reservation)
    request.state.in_flight = reservation
    return body


class ReleaseMiddleware:
    """Gives back every reservation a request took (`receive` appends them to `state.reservations`) once its answer has
    left the process, or it failed, or its client left (`hold_until_drained`)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":  # every HTTP request, whatever its path (a proxy's prefix included)
            return await self.app(scope, receive, send)
        reservations: list[Reservation] = []
        scope.setdefault("state", {})["reservations"] = reservations
        sent = 0

        async def counting_send(message: Message) -> None:
            nonlocal sent
            sent += len(message.get("body", b""))
            await send(message)

        try:
            await self.app(scope, receive, counting_send)
        finally:
            hold_until_drained(scope, reservations, sent)


def hold_until_drained(scope: Scope, reservations: list[Reservation], written: int) -> None:
    """Keep `written` bytes of `reservations` (what was just written to the connection) until its write buffer
    has drained (`timeouts.Drain`: a client that does not read is dropped after JOINTLIMITS_WRITE_TIMEOUT), give
    back the rest now; all of them at once without a `Drain` (in-process, no transport)."""
    drain = scope.get("extensions", {}).get(DRAIN)
    kept = list(reservations)
    reservations.clear()
    if drain is None or not drain.paused or not kept:
        for r in kept:
            r.release()
        return
    largest = max(kept, key=lambda r: r.size)  # the in-flight one (an upload reservation is given back by now)
    for r in kept:
        if r is not largest:
            r.release()
    largest.shrink(written)  # the encoded answer alone is held now (its arrays are gone)
    drain.after(largest.release)
