"""Error bodies: FastAPI's `{"detail": [{"loc", "msg", "type"}]}` for every 4xx of the service."""

from __future__ import annotations

from pydantic import BaseModel, Field

NONFINITE_MSG, NONFINITE_TYPE = "Input should be a finite number", "finite_number"
"""A NaN, an infinity (or JSON's `null`, `1e400`): pydantic's own words for JSON, said by every path."""


class ErrorItem(BaseModel):
    """One fault. `loc` starts with where it is (`body`, `header`) and then names the field,
    e.g. `["body", "batches", 1, "lower", 2]`: batch 1, joint 2."""

    loc: list[str | int] = Field(
        description="Where: starts with body (or header), then field, batch, joint, element, e.g. "
        '["body", "batches", 1, "lower", 2].'
    )
    msg: str = Field(description="What is wrong, in words.")
    type: str = Field(
        description="A stable machine-readable kind, e.g. finite_number, too_short, missing, value_error, too_large."
    )


class ErrorResponse(BaseModel):
    detail: list[ErrorItem] = Field(description="Every fault found (up to 20 per check).")
