"""Core input faults as FastAPI-style 422 responses."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import JSONResponse

from service.core import InputError


async def input_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, InputError)
    detail = [{"loc": ["body", *f.loc], "msg": f.msg, "type": f.type} for f in exc.faults]
    return JSONResponse({"detail": detail}, status_code=422)
