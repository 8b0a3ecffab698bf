"""Operational wiring of the application: auth, CORS, request ids, access log, metrics.

Order, outermost first: observability (sees every request, including 401s and CORS
preflights, and serves `/metrics`), the fault-list shape of every refusal, CORS (answers preflights before
auth could refuse them; a session's upgrade from a foreign `Origin` is refused), bearer auth (refuses before the
body is read), the release of the memory budgets an
evaluation took (after its answer is sent), the body's read timeout, then the routes.
"""

from __future__ import annotations

from fastapi import FastAPI
from starlette.middleware.cors import CORSMiddleware

from jointlimits.service import sizing
from jointlimits.service.http.auth import BearerAuthMiddleware, SessionOriginMiddleware
from jointlimits.service.http.budget import Budget, ReleaseMiddleware
from jointlimits.service.http.refusals import FaultListMiddleware
from jointlimits.service.http.timeouts import BodyTimeoutMiddleware
from jointlimits.service.observability import Metrics, ObservabilityMiddleware
from jointlimits.service.settings import Settings


def install(app: FastAPI, settings: Settings) -> None:
    # Starlette wraps in reverse: the middleware added last is the outermost.
    app.add_middleware(BodyTimeoutMiddleware, timeout=settings.body_timeout)  # innermost: only the body's reads
    metrics = app.state.metrics = Metrics()

    def show(b: Budget) -> None:
        metrics.budget_held.set(b.held)
        metrics.budget_queued.set(b.queued)

    def show_uploads(b: Budget) -> None:
        metrics.uploads_held.set(b.held)

    # The worker's memory budgets (service/http/budget.py): taken by the routes, given back after the answer.
    app.state.uploads = Budget(sizing.upload_bytes(settings), on_change=show_uploads)
    app.state.in_flight = Budget(sizing.inflight_bytes(settings), on_change=show)
    app.add_middleware(ReleaseMiddleware)
    if settings.token:
        app.add_middleware(BearerAuthMiddleware, token=settings.token)
    if settings.cors_origins:
        # Outside auth: a foreign Origin is refused its session whether or not it carries the token.
        app.add_middleware(SessionOriginMiddleware, origins=settings.cors_origins)
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(settings.cors_origins),
            allow_methods=["GET", "POST"],
            allow_headers=["Authorization", "Content-Type", "Accept", "X-Request-ID"],
            expose_headers=["X-Request-ID"],
            max_age=600,
        )
    app.add_middleware(FaultListMiddleware)  # every refusal in the fault-list shape, whoever refused
    app.add_middleware(
        ObservabilityMiddleware,
        metrics=metrics,
        route_paths=lambda: _route_paths(app),
    )


def _route_paths(app: FastAPI) -> list[str]:
    """Paths of the app's routes without parameters (labels for requests refused before routing)."""
    paths = [r.path for r in app.routes if isinstance(getattr(r, "path", None), str)]
    try:
        paths += list(app.openapi().get("paths", {}))  # also the routes of included routers
    except Exception:  # pragma: no cover (a broken schema must not break metrics)
        pass
    return [p for p in paths if "{" not in p]
