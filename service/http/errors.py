"""Every 4xx of the service in FastAPI's `{"detail": [{"loc", "msg", "type"}]}` format."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import JSONResponse
from pydantic import ValidationError

from service.core import Fault, InputError
from schemas.errors import validation_items
from service.core.errors import MAX_FAULTS


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


def from_validation(e: ValidationError) -> InputError:
    """Pydantic's errors as core faults (same loc, same msg; `null` for a number reads as non-finite)."""
    return InputError([Fault(*item) for item in validation_items(e, 4 * MAX_FAULTS)])
