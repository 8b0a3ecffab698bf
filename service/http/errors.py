"""Every 4xx (and 503) of the service in FastAPI's `{"detail": [{"loc", "msg", "type"}]}` format.

`render` is the one place faults become JSON: whatever a decoder put in a fault (a msgpack
`bin` key, a 2 MB misspelt key, a list of a million faults), the answer is JSON-safe and
bounded: at most `MAX_FAULTS` faults, every `loc` element an `int` or a `str` of at most
`MAX_KEY_CHARS` characters (longer ones cut, marked with `...`), every `msg` at most `MAX_MSG_CHARS`.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence

from fastapi import Request
from fastapi.responses import JSONResponse, Response
from starlette.types import Message, Receive, Scope, Send

from jointlimits.service.core import Fault, InputError
from jointlimits.service.core.errors import MAX_FAULTS, DeadlineExceeded
from jointlimits.service.http.refusals import FAULT_LIST

RETRY_AFTER_SECONDS = 5
"""`Retry-After` of a 503 past the request deadline: the worker is free again at once, a busy pod soon."""

MAX_KEY_CHARS = 64
"""A `loc` element echoed back (an unknown key) is cut to this many characters plus `...`."""
MAX_MSG_CHARS = 1024
"""A message quoting the input (a dtype string, a shape) is cut to this many characters plus `...`."""


class HttpError(Exception):
    """A request refused before the core sees it: 413 too large, 415 / 406 unknown media type, 503 busy."""

    def __init__(self, status: int, faults: list[Fault], headers: dict[str, str] | None = None) -> None:
        self.status = status
        self.faults = faults
        self.headers = headers  # e.g. Retry-After of a 503 busy
        super().__init__("; ".join(f.msg for f in faults))


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
    """A refusal rendered here, marked so that `refusals.FaultListMiddleware` passes it on without reading it."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def marked(message: Message) -> None:
            await send({**message, FAULT_LIST: True} if message["type"].endswith("response.start") else message)

        await super().__call__(scope, receive, marked)


async def input_error_handler(request: Request, exc: Exception) -> FaultList:
    assert isinstance(exc, InputError)
    return FaultList(render(exc.faults, ("body",)), status_code=422)


async def http_error_handler(request: Request, exc: Exception) -> FaultList:
    assert isinstance(exc, HttpError)
    # These faults carry their own full loc (["body"], ["header", "accept"], ...).
    return FaultList(render(exc.faults), status_code=exc.status, headers=exc.headers)


CLIENT_CLOSED = 499
"""Status recorded (metrics, access log) for a request whose client left before its body was read (nginx's 499)."""


async def client_gone(request: Request, exc: Exception) -> Response:
    """`ClientDisconnect` while reading the body: 408 if the body timed out, else 499 (nobody hears it).

    Either way one access-log line at info and a 4xx in the metrics: not a 500 with a traceback.
    """
    from jointlimits.service.http.timeouts import BODY_TIMED_OUT

    timeout = request.scope.get("state", {}).get(BODY_TIMED_OUT)
    if timeout is not None:
        fault = Fault(("body",), f"request body not received within {timeout:g} s (JOINTLIMITS_BODY_TIMEOUT)", "timeout")
        return FaultList(render([fault]), status_code=408, headers={"Connection": "close"})
    return Response(status_code=CLIENT_CLOSED)


async def deadline_handler(request: Request, exc: Exception) -> FaultList:
    assert isinstance(exc, DeadlineExceeded)
    timeout = request.app.state.settings.request_timeout
    msg = (
        f"the evaluation did not finish within the request timeout of {timeout:g} s (JOINTLIMITS_REQUEST_TIMEOUT) "
        "and was stopped: retry later if the service is busy, or split the request"
    )
    detail = [{"loc": ["body"], "msg": msg, "type": "timeout"}]
    return FaultList({"detail": detail}, status_code=503, headers={"Retry-After": str(RETRY_AFTER_SECONDS)})
