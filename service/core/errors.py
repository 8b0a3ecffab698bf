"""Input faults found by the core, located the way FastAPI locates its own."""

from __future__ import annotations

import time
from dataclasses import dataclass

from jointlimits.schemas.errors import NONFINITE_MSG, NONFINITE_TYPE  # noqa: F401 (the wire's words for a NaN, said on every path)

Loc = tuple[str | int, ...]

MAX_FAULTS = 20
"""Faults listed in one answer: a request with a million bad joints gets a readable 422."""


@dataclass(frozen=True)
class Fault:
    """One fault; `loc` is relative to the request body, e.g. `("batches", 1, "lower", 2)`."""

    loc: Loc
    msg: str
    type: str = "value_error"


class InputError(ValueError):
    """The request is malformed or physically meaningless; carries every fault found."""

    def __init__(self, faults: list[Fault]) -> None:
        self.faults = faults
        super().__init__("; ".join(f"{'.'.join(map(str, f.loc))}: {f.msg}" for f in faults))


class FaultLog:
    """The faults of one request, at most `MAX_FAULTS` in all (across batches and checks)."""

    def __init__(self, *faults: list[Fault]) -> None:
        self.faults: list[Fault] = []
        for f in faults:  # each check's, in order
            self.add(f)

    def add(self, faults: list[Fault]) -> None:
        self.faults += faults[: MAX_FAULTS - len(self.faults)]

    def raise_if_any(self) -> None:
        if self.faults:
            raise InputError(self.faults)


class DeadlineExceeded(Exception):
    """An evaluation passed its deadline (a `time.monotonic()` value) and stopped: no answer, no input fault."""


def check_deadline(deadline: float | None) -> None:
    """Raise `DeadlineExceeded` once `time.monotonic()` is past `deadline` (None: no deadline)."""
    if deadline is not None:
        late = time.monotonic() - deadline
        if late > 0:
            raise DeadlineExceeded(f"deadline passed {late:.3f} s ago")
