"""The ASGI application `jointlimits.service.app:app`: settings, routes, sessions, middleware."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import threading
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from fastapi_offline import FastAPIOffline
from starlette.datastructures import State
from starlette.middleware.cors import CORSMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from jointlimits.service import sizing
from jointlimits.service.core import registry
from jointlimits.service.core.heap import keep_heap
from jointlimits.service.http import sessions
from jointlimits.service.http.auth import BearerAuthMiddleware, SessionOriginMiddleware
from jointlimits.service.http.budget import Budget, ReleaseMiddleware
from jointlimits.service.http.errors import FaultListMiddleware
from jointlimits.service.http.routes import install
from jointlimits.service.http.timeouts import OPENED
from jointlimits.service.observability import LIFESPAN_METRICS, Metrics, ObservabilityMiddleware
from jointlimits.service.settings import Settings

log = logging.getLogger("jointlimits.drain")


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[dict[str, Any]]:
    """The metrics in the lifespan state, for the connection layer (service/http/timeouts.py); the drain."""
    drain_on_sigterm(app)
    yield {LIFESPAN_METRICS: app.state.metrics}


def drain_on_sigterm(app: FastAPI) -> bool:
    """Under uvicorn, in the main thread, with a positive `shutdown_delay`: SIGTERM marks the app draining
    (`/readyz` answers 503, every answer says `Connection: close`) while it keeps answering, and reaches uvicorn's
    own handler (set by the lifespan's start, in each worker) `shutdown_delay` seconds later. A second SIGTERM
    changes nothing (a supervisor and a process manager may each send one); SIGINT still stops at once."""
    delay = app.state.settings.shutdown_delay
    if delay <= 0 or threading.current_thread() is not threading.main_thread():
        return False  # a test's app in a thread, or no delay: SIGTERM stays uvicorn's
    from uvicorn.server import Server

    stop = signal.getsignal(signal.SIGTERM)
    if not isinstance(getattr(stop, "__self__", None), Server):
        return False  # not served by uvicorn's Server (another server, or a handler of someone else's)
    loop = asyncio.get_running_loop()

    def begin() -> None:
        log.info("SIGTERM: draining for %g s (/readyz answers 503 draining), then shutting down", delay,
                 extra={"fields": {"pid": os.getpid(), "shutdown_delay": delay}})
        loop.call_later(delay, stop, signal.SIGTERM, None)

    def on_sigterm(signum: int, frame: object) -> None:
        if not app.state.draining:
            app.state.draining = True  # at once: the next /readyz says so
            loop.call_soon_threadsafe(begin)  # the rest in the loop, not in the signal handler

    signal.signal(signal.SIGTERM, on_sigterm)
    return True


class CloseConnections:
    """`Connection: close` on every HTTP answer while the app drains, and on the first answer of a connection older
    than `max_connection_age` (`timeouts.OPENED`): a keep-alive client (a proxy's pool, the SDK) opens its next
    connection anew, which the load balancer sends to a pod that stays, or after a rollout to any pod."""

    def __init__(self, app: ASGIApp, state: State) -> None:
        self.app, self.state = app, state

    def closing(self, scope: Scope) -> bool:
        if scope["type"] != "http":
            return False
        opened, most = scope.get("extensions", {}).get(OPENED), self.state.settings.max_connection_age
        return self.state.draining or (opened is not None and 0 < most <= time.monotonic() - opened)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not self.closing(scope):
            return await self.app(scope, receive, send)

        async def closing(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), (b"connection", b"close")]}
            await send(message)

        await self.app(scope, receive, closing)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    if settings.keep_heap:
        keep_heap()  # every worker imports the app: this process's allocator, once
    # /docs and /redoc from assets shipped in the package (clusters often have no internet); the
    # validator badge would fetch an image from outside, so it is off.
    app = FastAPIOffline(
        swagger_ui_parameters={"validatorUrl": None},
        lifespan=_lifespan,
        title="Joint-limit constitution service",
        version="1.0.0",
        description="Energy, gradient and Hessian of "
        + " and ".join(f"#{f.uid} {f.name}" for f in registry.CONSTITUTIONS.values()) + " (wire contract v1.2).",
    )
    app.state.settings = settings
    app.state.draining = False  # True from SIGTERM on (drain_on_sigterm): /readyz answers 503
    app.include_router(sessions.router)  # /v1/sessions (WebSocket)
    install(app)  # routes, 4xx handlers (422, 413, 415, 406), OpenAPI of the raw-bodied route
    metrics = app.state.metrics = Metrics()

    def show(b: Budget) -> None:
        metrics.budget_held.set(b.held)
        metrics.budget_queued.set(b.queued)

    # The worker's memory budgets (service/http/budget.py): taken by the routes, given back after the answer.
    app.state.uploads = Budget(sizing.upload_bytes(settings), on_change=lambda b: metrics.uploads_held.set(b.held))
    app.state.in_flight = Budget(sizing.inflight_bytes(settings), on_change=show)
    # The middleware, innermost first (Starlette wraps in reverse): the release of the budgets after the answer is
    # sent; bearer auth (before the body is read); CORS (answers preflights before auth could refuse them) and the
    # sessions' Origin check (a foreign Origin is refused, token or not); every refusal in the fault-list shape;
    # observability (sees every request, 401s and preflights too, serves /metrics); outermost, `Connection: close`
    # while draining or on an aged connection.
    app.add_middleware(ReleaseMiddleware)
    if settings.token:
        app.add_middleware(BearerAuthMiddleware, token=settings.token)
    if settings.cors_origins:
        app.add_middleware(SessionOriginMiddleware, origins=settings.cors_origins)
        app.add_middleware(CORSMiddleware, allow_origins=list(settings.cors_origins), allow_methods=["GET", "POST"],
                           allow_headers=["Authorization", "Content-Type", "Accept", "X-Request-ID"],
                           expose_headers=["X-Request-ID"], max_age=600)
    app.add_middleware(FaultListMiddleware)
    app.add_middleware(ObservabilityMiddleware, metrics=metrics)
    app.add_middleware(CloseConnections, state=app.state)
    return app


app = create_app()
