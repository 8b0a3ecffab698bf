"""The ASGI application `jointlimits.service.app:app`."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from fastapi_offline import FastAPIOffline

from jointlimits.service.core.heap import keep_heap
from jointlimits.service.http import sessions
from jointlimits.service.http.routes import install
from jointlimits.service.http import middleware as ops
from jointlimits.service.observability import LIFESPAN_METRICS
from jointlimits.service.settings import Settings


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[dict[str, Any]]:
    """The lifespan state: the metrics, for the connection layer (`jointlimits.service.http.timeouts`)."""
    yield {LIFESPAN_METRICS: app.state.metrics}


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
        description="Energy, gradient and Hessian of #670 AffineBodyRevoluteJointLimit "
        "and #669 AffineBodyPrismaticJointLimit (wire contract v1.2).",
    )
    app.state.settings = settings
    app.include_router(sessions.router)  # /v1/sessions (WebSocket)
    install(app)  # routes, 4xx handlers (422, 413, 415, 406), OpenAPI of the raw-bodied route
    ops.install(app, settings)  # bearer auth, CORS, request ids, JSON access log, /metrics
    return app


app = create_app()
