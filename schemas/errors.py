"""Error bodies: FastAPI's `{"detail": [{"loc", "msg", "type"}]}` for every 4xx of the service."""

from __future__ import annotations

from pydantic import BaseModel


class ErrorItem(BaseModel):
    """One fault. `loc` starts with where it is (`body`, `header`) and then names the field,
    e.g. `["body", "batches", 1, "lower", 2]`: batch 1, joint 2."""

    loc: list[str | int]
    msg: str
    type: str


class ErrorResponse(BaseModel):
    detail: list[ErrorItem]
