"""Server errors as exceptions that carry the server's `loc` and message."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Fault:
    """One item of the server's `detail`: `loc` like `("body", "batches", 1, "lower", 2)`."""

    loc: tuple[str | int, ...]
    msg: str
    type: str = "value_error"


class ServiceError(Exception):
    """The service refused a request (4xx) or failed (5xx); `faults` is its `detail`."""

    def __init__(self, status: int, faults: list[Fault]) -> None:
        self.status = status
        self.faults = faults
        lines = "; ".join(f"{'.'.join(map(str, f.loc))}: {f.msg}" for f in faults[:5])
        more = f" (and {len(faults) - 5} more)" if len(faults) > 5 else ""
        super().__init__(f"HTTP {status}: {lines}{more}")

    @property
    def loc(self) -> tuple[str | int, ...]:
        """The first fault's location."""
        return self.faults[0].loc if self.faults else ()

    @property
    def msg(self) -> str:
        return self.faults[0].msg if self.faults else ""

    @classmethod
    def from_body(cls, status: int, body: Any) -> ServiceError:
        detail = body.get("detail") if isinstance(body, dict) else None
        if isinstance(detail, list):
            faults = [
                Fault(tuple(d.get("loc", ())), str(d.get("msg", "")), str(d.get("type", "")))
                for d in detail
                if isinstance(d, dict)
            ]
        else:
            faults = [Fault((), str(detail if detail is not None else body), "http_error")]
        return _BY_STATUS.get(status, cls)(status, faults)


class InvalidInput(ServiceError):
    """422: the request is malformed or physically meaningless; `loc` names the field and joint."""


class TooLarge(ServiceError):
    """413: over the server's byte or joint limit (the clients split batches to avoid it)."""


_BY_STATUS: dict[int, type[ServiceError]] = {422: InvalidInput, 413: TooLarge}
