"""Every refusal in the fault-list shape `{"detail": [{"loc", "msg", "type"}]}`, whoever refuses.

The routes' own 4xx and 503 are written by `jointlimits.service.http.errors`. Others come from elsewhere:
Starlette's 404 and 405 (`{"detail": "Not Found"}`), the CORS middleware's plain-text 400, a
WebSocket upgrade closed before it is accepted (the server answers a bare 403). This outermost
wrapper (inside the access log, which sees the final status) rewrites any such body. The service's
own refusals (`errors.FaultList`, the auth middleware) are written in the shape once and say so in
their `response.start` message (`FAULT_LIST`): they pass untouched and unread, never parsed again.
"""

from __future__ import annotations

import json
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

FAULT_LIST = "jointlimits.fault_list"
"""Key of a `response.start` message whose body is already a fault list: passed on as is (the key dropped)."""

# For each status a client may meet before the routes: where the fault is and its type.
_FAULT = {
    400: (["header"], "bad_request"),
    401: (["header", "authorization"], "unauthorized"),
    403: (["header"], "forbidden"),
    404: (["path"], "not_found"),
    405: (["method"], "method_not_allowed"),
    406: (["header", "accept"], "not_acceptable"),
    408: (["body"], "timeout"),
    413: (["body"], "too_large"),
    415: (["header", "content-type"], "media_type"),
    429: (["header"], "too_many_requests"),
    503: (["body"], "busy"),
}


def fault_body(status: int, msg: str) -> bytes:
    """The one-fault body of a refusal with status `status` saying `msg`."""
    loc, type_ = _FAULT.get(status, (["body"], "http_error"))
    return json.dumps({"detail": [{"loc": loc, "msg": msg, "type": type_}]}).encode()


def is_fault_list(body: bytes) -> bool:
    try:
        doc = json.loads(body)
    except ValueError:
        return False
    detail = doc.get("detail") if isinstance(doc, dict) else None
    return isinstance(detail, list) and all(isinstance(d, dict) and {"loc", "msg", "type"} <= d.keys() for d in detail)


def _words(body: bytes, status: int) -> str:
    """What the original body said: its `detail` string, its text, or the status's reason."""
    try:
        doc = json.loads(body)
        if isinstance(doc, dict) and isinstance(doc.get("detail"), str):
            return doc["detail"]
    except ValueError:
        pass
    text = body.decode("utf-8", "replace").strip()
    return text[:1024] or f"refused with HTTP {status}"


class FaultListMiddleware:
    """Rewrites a refusal's body into the fault list; answers a WebSocket refused before its accept
    with a 403 (or the router's 404) that says why, where the server supports it."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            await self.app(scope, receive, _HttpRefusal(send))
        elif scope["type"] == "websocket" and "websocket.http.response" in (scope.get("extensions") or {}):
            await self.app(scope, receive, _WebSocketRefusal(scope, send))
        else:
            await self.app(scope, receive, send)


class _HttpRefusal:
    """`send` that holds a >= 400 response until its body is complete, then rewrites it if needed."""

    def __init__(self, send: Send, prefix: str = "http") -> None:
        self.send, self.prefix = send, prefix
        self.start: Message | None = None
        self.body: list[bytes] = []

    async def __call__(self, message: Message) -> None:
        kind = message["type"]
        if kind == f"{self.prefix}.response.start" and message["status"] >= 400:
            if FAULT_LIST in message:  # written in the shape by the service itself
                await self.send({k: v for k, v in message.items() if k != FAULT_LIST})
                return
            self.start = message
            return
        if self.start is None or kind != f"{self.prefix}.response.body":
            await self.send(message)
            return
        self.body.append(message.get("body", b""))
        if message.get("more_body", False):
            return
        await self.flush()

    async def flush(self) -> None:
        start, body = self.start, b"".join(self.body)
        assert start is not None
        self.start = None
        status = start["status"]
        headers: list[Any] = list(start.get("headers", []))
        if not is_fault_list(body):
            body = fault_body(status, _words(body, status))
            drop = {b"content-type", b"content-length"}
            headers = [(k, v) for k, v in headers if k.lower() not in drop]
            headers += [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
        await self.send({**start, "headers": headers})
        await self.send({"type": f"{self.prefix}.response.body", "body": body})


class _WebSocketRefusal(_HttpRefusal):
    """A `websocket.close` before `websocket.accept` becomes an HTTP answer to the upgrade with a fault list."""

    def __init__(self, scope: Scope, send: Send) -> None:
        super().__init__(send, "websocket.http")
        self.scope = scope
        self.accepted = False

    async def __call__(self, message: Message) -> None:
        kind = message["type"]
        if kind == "websocket.accept":
            self.accepted = True
        elif kind == "websocket.close" and not self.accepted:
            reason = message.get("reason") or ""
            # Starlette's router closes an upgrade to a path it has no WebSocket route for: that is a 404.
            if not reason and message.get("code", 1000) == 1000 and not _routed(self.scope):
                status, reason = 404, f"no WebSocket endpoint at {self.scope.get('path', '')}; sessions are at /v1/sessions"
            else:
                status = 403
            self.start = {"type": "websocket.http.response.start", "status": status, "headers": []}
            self.body = [reason.encode()]
            await self.flush()
            return
        await super().__call__(message)


def _routed(scope: Scope) -> bool:
    """The router matched a WebSocket route (it records the endpoint in the scope)."""
    return scope.get("endpoint") is not None
