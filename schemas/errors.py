"""Error bodies: FastAPI's `{"detail": [{"loc", "msg", "type"}]}` for every 4xx of the service."""

from __future__ import annotations

from pydantic import BaseModel

NONFINITE_MSG, NONFINITE_TYPE = "Input should be a finite number", "finite_number"
"""A NaN, an infinity (or JSON's `null`, `1e400`): pydantic's own words for JSON, said by every path."""


class ErrorItem(BaseModel):
    """One fault. `loc` starts with where it is (`body`, `header`) and then names the field,
    e.g. `["body", "batches", 1, "lower", 2]`: batch 1, joint 2."""

    loc: list[str | int]
    msg: str
    type: str


class ErrorResponse(BaseModel):
    detail: list[ErrorItem]


