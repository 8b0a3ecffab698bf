"""Optional bearer-token auth for the API (`/v1/...`).

With no token configured (`JOINTLIMITS_TOKEN` unset or empty) the API is open. With one,
every request under `/v1/` must carry `Authorization: Bearer <token>`, or it answers 401
with `WWW-Authenticate: Bearer` before its body is read (an unauthenticated flood costs
no parsing). `/healthz`, `/metrics` and the OpenAPI document stay open, so probes and
scrapers need no secret. CORS preflights (`OPTIONS`) are answered by the CORS middleware,
which sits outside this one.
"""

from __future__ import annotations

import hmac
import json

from starlette.types import ASGIApp, Receive, Scope, Send

from jointlimits.service.http.refusals import FAULT_LIST

PROTECTED_PREFIX = "/v1/"


class BearerAuthMiddleware:
    def __init__(self, app: ASGIApp, token: str, prefix: str = PROTECTED_PREFIX) -> None:
        if not token:
            raise ValueError("BearerAuthMiddleware needs a non-empty token")
        self.app = app
        self.expected = token.encode()
        self.prefix = prefix

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or not scope["path"].startswith(self.prefix) or self._authorized(scope):
            await self.app(scope, receive, send)
            return
        fault = {"loc": ["header", "authorization"], "msg": "missing or invalid bearer token", "type": "unauthorized"}
        body = json.dumps({"detail": [fault]}).encode()
        prefix = "http"
        if scope["type"] == "websocket":
            # A session is refused on its upgrade request, before it is accepted: the same 401 where the
            # server can answer the handshake with a response (uvicorn can), else a close (HTTP 403).
            if "websocket.http.response" not in (scope.get("extensions") or {}):
                await send({"type": "websocket.close", "code": 1008, "reason": "missing or invalid bearer token"})
                return
            prefix = "websocket.http"
        await send(
            {
                "type": f"{prefix}.response.start",
                "status": 401,
                FAULT_LIST: True,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"www-authenticate", b'Bearer realm="jointlimits"'),
                ],
            }
        )
        await send({"type": f"{prefix}.response.body", "body": body})

    def _authorized(self, scope: Scope) -> bool:
        for name, value in scope.get("headers", ()):
            if name == b"authorization":
                scheme, _, credentials = value.strip().partition(b" ")
                # The scheme is case-insensitive (RFC 9110); the token comparison is constant-time,
                # so it leaks nothing about how much of the token matched.
                return scheme.lower() == b"bearer" and hmac.compare_digest(credentials.strip(), self.expected)
        return False


class SessionOriginMiddleware:
    """Sessions honour the CORS allow-list: a WebSocket upgrade whose `Origin` is not in it is refused (403 with a
    fault list) before auth, so a browser on a foreign site gets no session, token or not.

    A browser always sends `Origin` on a WebSocket upgrade and does not apply CORS to it: without this check
    any page could open a session (cross-site WebSocket hijacking). No `Origin` (a non-browser client: the
    SDK, a solver) is allowed. Installed only when JOINTLIMITS_CORS_ORIGINS is set; `*` allows every origin."""

    def __init__(self, app: ASGIApp, origins: tuple[str, ...]) -> None:
        self.app = app
        self.origins = {o.rstrip("/") for o in origins}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        origin = self._origin(scope) if scope["type"] == "websocket" else None
        if origin is None or "*" in self.origins or origin.rstrip("/") in self.origins:
            await self.app(scope, receive, send)
            return
        msg = f"origin {origin[:200]!r} is not allowed (JOINTLIMITS_CORS_ORIGINS): no session from this site"
        body = json.dumps({"detail": [{"loc": ["header", "origin"], "msg": msg, "type": "origin_not_allowed"}]}).encode()
        if "websocket.http.response" not in (scope.get("extensions") or {}):
            await send({"type": "websocket.close", "code": 1008, "reason": "origin not allowed"})  # 403 with no body
            return
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
        await send({"type": "websocket.http.response.start", "status": 403, "headers": headers, FAULT_LIST: True})
        await send({"type": "websocket.http.response.body", "body": body})

    @staticmethod
    def _origin(scope: Scope) -> str | None:
        for name, value in scope.get("headers", ()):
            if name == b"origin":
                return value.decode("latin-1")
        return None
