"""Every 4xx of the service in FastAPI's `{"detail": [{"loc", "msg", "type"}]}` format."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import JSONResponse
from pydantic import ValidationError

from service.core import Fault, InputError
from service.core.errors import MAX_FAULTS, DeadlineExceeded

RETRY_AFTER_SECONDS = 5
"""`Retry-After` of a 503 past the request deadline: the worker is free again at once, a busy pod soon."""


class HttpError(Exception):
    """A request refused before the core sees it: 413 too large, 415 / 406 unknown media type."""

    def __init__(self, status: int, faults: list[Fault]) -> None:
        self.status = status
        self.faults = faults
        super().__init__("; ".join(f.msg for f in faults))


def _body(faults: list[Fault], where: str = "body") -> dict:
    return {"detail": [{"loc": [where, *f.loc], "msg": f.msg, "type": f.type} for f in faults]}


async def input_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, InputError)
    return JSONResponse(_body(exc.faults), status_code=422)


async def http_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, HttpError)
    # These faults carry their own full loc (["body"], ["header", "accept"], ...).
    detail = [{"loc": list(f.loc), "msg": f.msg, "type": f.type} for f in exc.faults]
    return JSONResponse({"detail": detail}, status_code=exc.status)


async def deadline_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, DeadlineExceeded)
    timeout = request.app.state.settings.request_timeout
    msg = (
        f"the evaluation did not finish within the request timeout of {timeout:g} s (JOINTLIMITS_REQUEST_TIMEOUT) "
        "and was stopped: retry later if the service is busy, or split the request"
    )
    detail = [{"loc": ["body"], "msg": msg, "type": "timeout"}]
    return JSONResponse({"detail": detail}, status_code=503, headers={"Retry-After": str(RETRY_AFTER_SECONDS)})


def from_validation(e: ValidationError) -> InputError:
    """Pydantic's errors as core faults (same loc, same msg), without echoing the input back."""
    faults = [
        Fault(tuple(err["loc"]), err["msg"], err["type"])
        for err in e.errors(include_url=False, include_input=False, include_context=False)[: 4 * MAX_FAULTS]
    ]
    return InputError(faults)
