"""Server errors as exceptions that carry the server's `loc` and message.

Each fault is a `Fault(loc, msg, type)`, the core's own (one item of the server's `detail`, `loc` like
`("body", "batches", 1, "lower", 2)`): a fault the SDK names before the service, or in-process, is the same object.
"""

from __future__ import annotations

from typing import Any

from jointlimits.service.core.errors import Fault


class ServiceError(Exception):
    """The service refused a request (4xx) or failed (5xx); `faults` is its `detail`.

    `where` opens the message: `"HTTP 422"` over HTTP, `"invalid input"` in the local mode.
    """

    def __init__(self, status: int, faults: list[Fault], where: str | None = None) -> None:
        self.status = status
        self.faults = faults
        self.where = where or f"HTTP {status}"
        lines = "; ".join(f"{'.'.join(map(str, f.loc))}: {f.msg}" if f.loc else f.msg for f in faults[:5])
        more = f" (and {len(faults) - 5} more)" if len(faults) > 5 else ""
        super().__init__(f"{self.where}: {lines}{more}")

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
            faults = [Fault(tuple(d.get("loc", ())), str(d.get("msg", "")), str(d.get("type", "")))
                      for d in detail if isinstance(d, dict)]
        else:
            faults = [Fault((), str(detail if detail is not None else body), "http_error")]
        busy = status == 503 and faults and faults[0].type == "busy"  # the one (status, type) with a class of its own
        return (Busy if busy else _BY_STATUS.get(status, cls))(status, faults)


class InvalidInput(ServiceError, ValueError):
    """422: the request is malformed or physically meaningless; `loc` names the field and joint. The SDK's
    constructors (`JointBatch.of`, `Scene`, `dofs`, `request_from_arrays`) raise it too, in the same words
    (a `ValueError` as well: the input is bad before any service sees it)."""


class TooLarge(ServiceError):
    """413: over the server's byte or joint limit (the clients split batches to avoid it)."""


class Unreachable(ServiceError):
    """No answer from the service: the connection was refused, timed out, or dropped before an answer,
    or a proxy in front of the service answered for it (a 502, 503 or 504 that is not the service's
    own error: an HTML page saying no upstream answered), on every attempt (`attempts` = 1 + the
    retries). `url` is what was asked; `status` is 0, or the proxy's status when a proxy answered
    the last attempt (`proxy`: its page in a few words; `retry_after`: its `Retry-After` seconds, or None)."""

    def __init__(self, url: str, attempts: int, cause: Exception | None = None, *, status: int = 0,
                 proxy: str | None = None, retry_after: float | None = None) -> None:
        self.url, self.attempts, self.proxy, self.cause, self.retry_after = url, attempts, proxy, cause, retry_after
        tries = f"{attempts} attempt{'s' * (attempts != 1)}"
        if cause is None:
            msg = (f"cannot reach the service at {url}: a proxy answered HTTP {status} in its stead ({proxy}) "
                   f"after {tries}; is the service running behind the proxy?")
        else:
            why = f"{type(cause).__name__}: {cause}" if str(cause) else type(cause).__name__
            msg = f"cannot reach {url} ({why}) after {tries}; is the service running there?"
        super().__init__(status, [Fault((), msg, "unreachable")], where="unreachable")

    def after(self, attempts: int) -> Unreachable:
        """The same failure, said of `attempts` attempts (retried by `transport.Retry`)."""
        return Unreachable(self.url, attempts, self.cause, status=self.status, proxy=self.proxy,
                           retry_after=self.retry_after)


class WrongURL(ServiceError):
    """A 404, an answer that is not the service's, or no http(s)://: `base_url` is not the service's root."""


class Busy(ServiceError):
    """503 whose first fault has type "busy": the server had no room for the request and computed
    nothing, so the clients retried it (after its `Retry-After`) until `retries` were spent, or
    stopped at once because it asked to wait longer than `max_retry_after`.

    `retry_after`: the seconds of the last answer's `Retry-After` header (None when absent or not
    a number of seconds); `attempts`: the tries made, every cause counted. `status` is 503. (The
    deadline's 503, type "timeout", is a plain `ServiceError`: it ran for the whole timeout and
    is never retried.)
    """

    def __init__(self, status: int, faults: list[Fault], where: str | None = None, *,
                 retry_after: float | None = None, attempts: int = 1, max_retry_after: float | None = None) -> None:
        """`max_retry_after`: set when the server's `Retry-After` was over it (the reason to stop)."""
        super().__init__(status, faults, where)
        self.retry_after, self.attempts = retry_after, attempts
        tries = f"{attempts} attempt{'s' * (attempts != 1)}"
        if max_retry_after is not None and retry_after is not None:
            why = (f"busy after {tries}; it asked to retry after {retry_after:g} s, "
                   f"over max_retry_after={max_retry_after:g} s")
        else:
            after = f"; Retry-After {retry_after:g} s" if retry_after is not None else ""
            why = f"busy after {tries}{after}"
        self.args = (f"{self.args[0]} ({why})",)


_BY_STATUS: dict[int, type[ServiceError]] = {422: InvalidInput, 413: TooLarge, 404: WrongURL}
