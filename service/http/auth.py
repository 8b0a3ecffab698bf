"""Optional bearer-token auth on `/v1/...`, checked before the body is read; the sessions' `Origin` check.

With no token (`JOINTLIMITS_TOKEN` unset or empty) the API is open. With one, every request under `/v1/` must carry
`Authorization: Bearer <token>`, else 401 with `WWW-Authenticate: Bearer` before its body is read (a flood costs
no parsing). `/healthz`, `/metrics` and the OpenAPI document stay open for probes and scrapers; CORS preflights
are answered by the CORS middleware, outside this one.
"""

from __future__ import annotations

import hmac

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

from jointlimits.service.core import Fault
from jointlimits.service.http.errors import refuse

PROTECTED_PREFIX = "/v1/"
_UNAUTHORIZED = "missing or invalid bearer token"


class BearerAuthMiddleware:
    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app, self.expected = app, token.encode()  # installed only with a token (service/app.py)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        protected = scope["type"] in ("http", "websocket") and scope["path"].startswith(PROTECTED_PREFIX)
        if not protected or self._authorized(scope):
            return await self.app(scope, receive, send)
        # A session is refused on its upgrade request, before it is accepted: the same 401.
        fault = Fault(("header", "authorization"), _UNAUTHORIZED, "unauthorized")
        challenge = {"WWW-Authenticate": 'Bearer realm="jointlimits"'}
        await refuse(scope, receive, send, 401, fault, _UNAUTHORIZED, challenge)

    def _authorized(self, scope: Scope) -> bool:
        scheme, _, credentials = Headers(scope=scope).get("authorization", "").strip().partition(" ")
        # The scheme is case-insensitive (RFC 9110); the token comparison is constant-time,
        # so it leaks nothing about how much of the token matched.
        return scheme.lower() == "bearer" and hmac.compare_digest(credentials.strip().encode("latin-1"), self.expected)


class SessionOriginMiddleware:
    """Sessions honour the CORS allow-list (`*` allows every origin): a WebSocket upgrade whose `Origin` is not in
    it is refused (403) before auth, token or not. A browser sends `Origin` on an upgrade and does not apply CORS to
    it: without this check any page could open a session (cross-site WebSocket hijacking). No `Origin` (the SDK, a
    solver) is allowed."""

    def __init__(self, app: ASGIApp, origins: tuple[str, ...]) -> None:
        self.app = app
        self.origins = {o.rstrip("/") for o in origins}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        origin = Headers(scope=scope).get("origin") if scope["type"] == "websocket" else None
        if origin is None or "*" in self.origins or origin.rstrip("/") in self.origins:
            return await self.app(scope, receive, send)
        msg = f"origin {origin[:200]!r} is not allowed (JOINTLIMITS_CORS_ORIGINS): no session from this site"
        fault = Fault(("header", "origin"), msg, "origin_not_allowed")
        await refuse(scope, receive, send, 403, fault, "origin not allowed")
