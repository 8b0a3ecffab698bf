"""Every refusal in FastAPI's fault-list shape, `{"detail": [{"loc", "msg", "type"}]}`, whoever refuses.

`render` is the one place faults become JSON: whatever a decoder put in a fault (a msgpack `bin` key, a 2 MB
misspelt key, a million faults), the answer is JSON-safe and bounded: at most `MAX_FAULTS` faults, every `loc`
element an `int` or a `str` of at most `MAX_KEY_CHARS` characters (longer ones cut, marked `...`), every `msg` at
most `MAX_MSG_CHARS`. The service's own refusals (`FaultList`, `refuse`) say so in their `response.start`
(`FAULT_LIST`) and pass `FaultListMiddleware` unread; it rewrites the others (Starlette's 404 and 405, CORS's
plain-text 400, a WebSocket upgrade closed before its accept: a bare 403).
"""

from __future__ import annotations

import json
import numbers
from collections.abc import Sequence
from typing import Any

from fastapi import Request
from fastapi.responses import JSONResponse, Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from jointlimits.service.core import Fault, InputError
from jointlimits.service.core.errors import MAX_FAULTS, DeadlineExceeded
from jointlimits.service.http.timeouts import RETRY_AFTER_SECONDS
MAX_KEY_CHARS = 64
"""A `loc` element echoed back (an unknown key) is cut to this many characters plus `...`."""
MAX_MSG_CHARS = 1024
"""A message quoting the input (a dtype string, a shape) is cut to this many characters plus `...`."""
FAULT_LIST = "jointlimits.fault_list"
"""Key of a `response.start` message whose body is already a fault list: passed on as is (the key dropped)."""
CLIENT_CLOSED = 499
"""Status recorded (metrics, access log) for a request whose client left before its body was read (nginx's 499)."""


class HttpError(Exception):
    """A request refused before the core sees it: 413 too large, 408 its body too slow, 415 / 406 unknown media type,
    503 busy."""

    def __init__(self, status: int, faults: list[Fault], headers: dict[str, str] | None = None) -> None:
        self.status, self.faults, self.headers = status, faults, headers  # headers: a 503's Retry-After
        super().__init__("; ".join(f.msg for f in faults))


def too_large(loc: tuple[str, ...], msg: str) -> HttpError:
    return HttpError(413, [Fault(loc, msg, "too_large")])


def busy(what: str) -> HttpError:
    """503 `busy`: refused before any evaluation, for `what` reason; a client may retry after Retry-After."""
    msg = f"{what}; nothing was evaluated: retry after Retry-After seconds (the Python SDK does), or send smaller requests"
    return HttpError(503, [Fault(("body",), msg, "busy")], headers={"Retry-After": str(RETRY_AFTER_SECONDS)})


def _cut(s: str, n: int) -> str:
    return s if len(s) <= n else s[:n] + "..."


def loc_element(x: object) -> int | str:
    """`x` as a JSON-safe `loc` element: ints stay ints, `bytes` keys show as `b'...'`, all cut to size."""
    if isinstance(x, numbers.Integral) and not isinstance(x, bool):
        return int(x)  # NumPy's integers too
    if isinstance(x, str):
        return _cut(x, MAX_KEY_CHARS)
    return _cut(repr(x[: MAX_KEY_CHARS + 1] if isinstance(x, (bytes, bytearray)) else x), MAX_KEY_CHARS)


def render(faults: Sequence[Fault], prefix: Sequence[str] = ()) -> dict:
    """The `{"detail": [...]}` answer of `faults` (the first `MAX_FAULTS`), each `loc` after `prefix`."""
    return {
        "detail": [
            {"loc": [*prefix, *map(loc_element, f.loc)], "msg": _cut(str(f.msg), MAX_MSG_CHARS), "type": str(f.type)}
            for f in faults[:MAX_FAULTS]
        ]
    }


class FaultList(JSONResponse):
    """A refusal rendered here, marked so that `FaultListMiddleware` passes it on without reading it."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def marked(message: Message) -> None:
            await send({**message, FAULT_LIST: True} if message["type"].endswith("response.start") else message)

        await super().__call__(scope, receive, marked)


def one_fault(status: int, loc: Sequence[Any], msg: str, type: str, headers: dict[str, str] | None = None) -> FaultList:
    return FaultList(render([Fault(tuple(loc), msg, type)]), status_code=status, headers=headers)


async def refuse(scope: Scope, receive: Receive, send: Send, status: int, fault: Fault, close_reason: str,
                 headers: dict[str, str] | None = None) -> None:
    """Answer a request, or a WebSocket upgrade where the server can answer one (uvicorn can), with `status` and
    the one `fault`, before the application; an upgrade elsewhere is closed with 1008 (HTTP 403, no body)."""
    if scope["type"] == "websocket" and "websocket.http.response" not in (scope.get("extensions") or {}):
        return await send({"type": "websocket.close", "code": 1008, "reason": close_reason})
    await one_fault(status, fault.loc, fault.msg, fault.type, headers)(scope, receive, send)


async def fault_handler(request: Request, exc: Exception) -> FaultList:
    """An `InputError`: 422, every `loc` after "body"; an `HttpError`: its status, its faults' whole `loc`."""
    if isinstance(exc, InputError):
        return FaultList(render(exc.faults, ("body",)), status_code=422)
    assert isinstance(exc, HttpError)
    return FaultList(render(exc.faults), status_code=exc.status, headers=exc.headers)


async def client_gone(request: Request, exc: Exception) -> Response:
    """`ClientDisconnect` while reading the body: 499 (nobody hears it), one access-log line at info and a 4xx in
    the metrics, not a 500 with a traceback."""
    return Response(status_code=CLIENT_CLOSED)


async def deadline_handler(request: Request, exc: Exception) -> FaultList:
    assert isinstance(exc, DeadlineExceeded)
    msg = (f"the evaluation did not finish within the request timeout of {request.app.state.settings.request_timeout:g}"
           " s (JOINTLIMITS_REQUEST_TIMEOUT) and was stopped: retry later if the service is busy, or split the request")
    return one_fault(503, ["body"], msg, "timeout", {"Retry-After": str(RETRY_AFTER_SECONDS)})


# ------------------------------------------------------------------ refusals written by others

# For each status a client may meet before the routes: where the fault is and its type.
_FAULT = {
    400: (("header",), "bad_request"),
    401: (("header", "authorization"), "unauthorized"),
    403: (("header",), "forbidden"),
    404: (("path",), "not_found"),
    405: (("method",), "method_not_allowed"),
    406: (("header", "accept"), "not_acceptable"),
    408: (("body",), "timeout"),
    413: (("body",), "too_large"),
    415: (("header", "content-type"), "media_type"),
    429: (("header",), "too_many_requests"),
    503: (("body",), "busy"),
}


def _words(body: bytes, status: int) -> str:
    """What the original body said: its `detail` string, its text, or the status's reason."""
    try:
        doc = json.loads(body)
        if isinstance(doc, dict) and isinstance(doc.get("detail"), str):
            return doc["detail"]
    except ValueError:
        pass
    return body.decode("utf-8", "replace").strip()[:1024] or f"refused with HTTP {status}"


class FaultListMiddleware:
    """Rewrites a refusal's body into the fault list (inside the access log, which sees the final status); answers
    a WebSocket refused before its accept with a 403 (or the router's 404) that says why, where the server can."""

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
                return await self.send({k: v for k, v in message.items() if k != FAULT_LIST})
            self.start = message
            return
        if self.start is None or kind != f"{self.prefix}.response.body":
            return await self.send(message)
        self.body.append(message.get("body", b""))
        if not message.get("more_body", False):
            await self.flush()

    async def flush(self) -> None:
        start, body = self.start, b"".join(self.body)
        assert start is not None
        self.start = None
        status = start["status"]
        # Not the service's own (those pass marked): Starlette's 404/405, CORS's text, a refused upgrade.
        loc, type_ = _FAULT.get(status, (("body",), "http_error"))
        body = json.dumps(render([Fault(loc, _words(body, status), type_)])).encode()
        headers = [(k, v) for k, v in start.get("headers", []) if k.lower() not in (b"content-type", b"content-length")]
        headers += [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
        await self.send({**start, "headers": headers})
        await self.send({"type": f"{self.prefix}.response.body", "body": body})


class _WebSocketRefusal(_HttpRefusal):
    """A `websocket.close` before `websocket.accept` becomes an HTTP answer to the upgrade with a fault list."""

    def __init__(self, scope: Scope, send: Send) -> None:
        super().__init__(send, "websocket.http")
        self.scope, self.accepted = scope, False

    async def __call__(self, message: Message) -> None:
        kind = message["type"]
        if kind == "websocket.accept":
            self.accepted = True
        elif kind == "websocket.close" and not self.accepted:
            reason, status = message.get("reason") or "", 403
            # Starlette's router closes an upgrade to a path it has no WebSocket route for (it records no
            # endpoint in the scope): that is a 404.
            if not reason and message.get("code", 1000) == 1000 and self.scope.get("endpoint") is None:
                status, reason = 404, f"no WebSocket endpoint at {self.scope.get('path', '')}; sessions are at /v1/sessions"
            self.start = {"type": "websocket.http.response.start", "status": status, "headers": []}
            self.body = [reason.encode()]
            return await self.flush()
        await super().__call__(message)
