"""Error bodies: FastAPI's `{"detail": [{"loc", "msg", "type"}]}` for every 4xx of the service."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ValidationError

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


def validation_items(e: ValidationError, limit: int) -> list[tuple[tuple[Any, ...], str, str]]:
    """The first `limit` of pydantic's errors as `(loc, msg, type)`, without echoing the input back.

    JSON's `null` where a number belongs is what a NaN becomes in most JSON writers: it gets the
    words of every other non-finite number (pydantic would say "a valid number", as for a string).
    """
    errors = e.errors(include_url=False, include_input=False, include_context=False)[:limit]
    if any(err["type"] == "float_type" for err in errors):
        # Inputs only when needed: with them, pydantic rebuilds every faulty row (twice the time on a flood).
        errors = e.errors(include_url=False, include_context=False)[:limit]
    return [
        (tuple(err["loc"]), NONFINITE_MSG, NONFINITE_TYPE)
        if err["type"] == "float_type" and err["input"] is None
        else (tuple(err["loc"]), err["msg"], err["type"])
        for err in errors
    ]
