"""The ASGI application `jointlimits.service.app:app`."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, MutableMapping
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from fastapi_offline import FastAPIOffline
from starlette.datastructures import State

from jointlimits.service.core import registry
from jointlimits.service.core.heap import keep_heap
from jointlimits.service.http import sessions
from jointlimits.service.http.routes import install
from jointlimits.service.http.timeouts import OPENED
from jointlimits.service.http import middleware as ops
from jointlimits.service.observability import LIFESPAN_METRICS
from jointlimits.service.settings import Settings


log = logging.getLogger("jointlimits.drain")


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[dict[str, Any]]:
    """The lifespan state: the metrics, for the connection layer (`jointlimits.service.http.timeouts`);
    the drain on SIGTERM, when uvicorn serves the app (`drain_on_sigterm`)."""
    drain_on_sigterm(app)
    yield {LIFESPAN_METRICS: app.state.metrics}


def drain_on_sigterm(app: FastAPI) -> bool:
    """Under uvicorn, in the process's main thread (every worker of `jointlimits serve`), with a positive
    `shutdown_delay`: SIGTERM first marks the app draining (`/readyz` answers 503 "draining", every answer
    says `Connection: close`) while the worker keeps accepting and answering, and reaches uvicorn's own
    handler `shutdown_delay` seconds later: then the listener closes and what is in flight finishes (within
    `--graceful-timeout`), as without a delay. A second SIGTERM changes nothing (a supervisor and a process
    manager may each send one); SIGINT (Ctrl-C) still stops at once. True when installed.

    Installed from the lifespan: uvicorn has set its handler by then (`Server.capture_signals`, which
    puts it back, and the original, when the server ends), in a single process as in each worker of its
    supervisor, which passes its SIGTERM on to every worker."""
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


Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
ASGIApp = Callable[[Scope, Callable[[], Awaitable[Message]], Callable[[Message], Awaitable[None]]], Awaitable[None]]


class CloseConnections:
    """`Connection: close` on every HTTP answer while the app drains, and on the first answer of a connection older
    than `max_connection_age` (its age from `jointlimits serve`'s protocol, `timeouts.OPENED`): a client on a
    keep-alive connection (a proxy's pool, the SDK) opens its next one anew, which the load balancer sends to a
    pod that stays, or after a rollout to any pod, the restarted ones too."""

    def __init__(self, app: ASGIApp, state: State) -> None:
        self.app, self.state = app, state

    def closing(self, scope: Scope) -> bool:
        if scope["type"] != "http":
            return False
        opened, most = scope.get("extensions", {}).get(OPENED), self.state.settings.max_connection_age
        return self.state.draining or (opened is not None and 0 < most <= time.monotonic() - opened)

    async def __call__(self, scope: Scope, receive: Callable[[], Awaitable[Message]],
                       send: Callable[[Message], Awaitable[None]]) -> None:
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
    ops.install(app, settings)  # bearer auth, CORS, request ids, JSON access log, /metrics
    app.add_middleware(CloseConnections, state=app.state)  # outermost: every answer while draining, or aged
    return app


app = create_app()
