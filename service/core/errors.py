"""Input faults found by the core, located the way FastAPI locates its own."""

from __future__ import annotations

import time
from dataclasses import dataclass

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


class DeadlineExceeded(Exception):
    """An evaluation passed its deadline (a `time.monotonic()` value) and stopped: no answer, no input fault."""


def check_deadline(deadline: float | None) -> None:
    """Raise `DeadlineExceeded` once `time.monotonic()` is past `deadline` (None: no deadline)."""
    if deadline is not None:
        late = time.monotonic() - deadline
        if late > 0:
            raise DeadlineExceeded(f"deadline passed {late:.3f} s ago")
