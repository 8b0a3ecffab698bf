"""What the sync and async clients share: headers, retry policy, part size, response handling."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence

import httpx
import orjson

from jointlimits.client import codec
from jointlimits.client.errors import Busy, Fault, Unreachable, WrongURL
from jointlimits.client.model import Evaluation
from jointlimits.schemas import OUTPUTS, ConstitutionsResponse, answer

RETRYABLE = (
    httpx.ConnectError,
    httpx.ConnectTimeout,
    httpx.RemoteProtocolError,
    httpx.ReadError,
    httpx.WriteError,
)
"""Connection failures: the request never reached the server, or the connection was dropped or
reset before an answer (the clients' calls, `GET /v1/constitutions` and `POST /v1/evaluate`, are
idempotent: sending one again is safe). Besides these, a busy 503 and a proxy's 502/503/504 are
retried (`Retry.again`); timeouts while the server computes, and every other answer, are never
retried."""

PROXY_STATUSES = frozenset({502, 503, 504})
"""What a proxy or load balancer answers in the service's stead (no upstream, upstream reset or
timed out): retried when the body is not the service's own error (`from_proxy`)."""

MAX_RETRY_AFTER = 30.0
"""Longest `Retry-After` (seconds) the clients sleep for; a server asking more raises `Busy` at once."""

CONNECT_TIMEOUT = 5.0
"""Seconds to open a connection: a host that drops packets fails in seconds, not in `timeout`."""

DEFAULT_PART_JOINTS = 20_000
"""Joints per request when splitting (each Hessian is 4.6 kB: ~90 MB of answer per part)."""

# Worst-case request bytes per joint: its arrays plus two bodies' three 12-DOF rows.
_BYTES_PER_JOINT = {True: 8 * (2 + 6 + 3) + 2 * 3 * 12 * 8 + 64, False: 2 * 3 * 12 * 25 + 11 * 25 + 64}


_JSON_VALUES_PER_JOINT = 11 + 2 * 3 * 12 + 8
"""Worst-case values of one joint in a JSON body: its 11 numbers, two bodies' three 12-DOF rows, separators."""


TOKEN_ENV = "JOINTLIMITS_TOKEN"
"""The bearer token when a client is given none: the server's own setting (service/settings.py), so a
client beside the server, or a job with the secret in its environment, needs no token in its code."""


def headers(token: str | None, binary: bool) -> dict[str, str]:
    """`token` None: `$JOINTLIMITS_TOKEN` (empty or unset: none); "": none."""
    h = {"Accept": codec.BINARY if binary else codec.JSON}
    if token is None:
        token = os.environ.get(TOKEN_ENV)
    if token:
        h["Authorization"] = f"Bearer {token}"
    return h


def timeouts(timeout: float | httpx.Timeout, connect_timeout: float) -> httpx.Timeout:
    """`timeout` for reading, writing and the pool; `connect_timeout` for opening a connection."""
    if isinstance(timeout, httpx.Timeout):
        return timeout
    return httpx.Timeout(timeout, connect=connect_timeout)


def delays(retries: int, backoff: float) -> list[float]:
    """Sleep before each retry: `backoff`, `2 backoff`, `4 backoff`, ..."""
    return [backoff * 2**k for k in range(retries)]


_SECONDS = re.compile(r"[0-9]+(\.[0-9]+)?")


def retry_after(response: httpx.Response) -> float | None:
    """The seconds of `response`'s `Retry-After` header (digits, with or without a decimal part),
    else None (absent, an HTTP-date, or anything else)."""
    value = response.headers.get("retry-after", "").strip()
    return float(value) if _SECONDS.fullmatch(value) else None


def from_proxy(response: httpx.Response) -> bool:
    """True for a 502/503/504 that is not the service's own answer: its body is not the service's
    error (a JSON object with `detail`, as every error of the service is), e.g. an HTML page of
    HAProxy, nginx, Envoy or a cloud load balancer that had no upstream to hand the request to."""
    if response.status_code not in PROXY_STATUSES:
        return False
    try:
        body = orjson.loads(response.content)
    except orjson.JSONDecodeError:
        return True
    return not (isinstance(body, dict) and "detail" in body)


def proxy_page(content: bytes) -> str:
    """A proxy's error page in a few words: its `<title>`, else its text without tags (at most 120 characters)."""
    text = content[:4096].decode("utf-8", "replace")
    title = re.search(r"<title[^>]*>(.*?)</title>", text, re.IGNORECASE | re.DOTALL)
    text = title.group(1) if title else re.sub(r"<[^>]*>", " ", text)
    text = " ".join(text.split())
    return (text[:117] + "...") if len(text) > 120 else (text or "an empty body")


class Retry:
    """The retries of one request: the pause before each next try, until `retries` are spent.

    Connection errors, busy 503s and a proxy's 502/503/504 draw on the same budget and the same
    backoff steps: each retry, whatever its cause, spends the next step.
    """

    def __init__(self, retries: int, backoff: float, url: str, max_retry_after: float = MAX_RETRY_AFTER) -> None:
        self._pauses = iter(delays(retries, backoff))
        self.url = url
        self.max_retry_after = max_retry_after
        self.attempts = 0

    def pause(self, error: Exception) -> float:
        """Seconds to sleep after `error` (one of `RETRYABLE`) before the next try; `Unreachable` if none is left."""
        self.attempts += 1
        pause = next(self._pauses, None)
        if pause is None:
            raise Unreachable(self.url, self.attempts, error) from error
        return pause

    def again(self, response: httpx.Response) -> float | None:
        """None if `response` is an answer to hand on; else (a busy 503, or a proxy's 502/503/504:
        nothing was computed) seconds to sleep before the next try: its `Retry-After`, at least the
        backoff step. When no retry is left, or the answer asks to wait more than `max_retry_after`
        seconds: `Busy` for the service's busy 503, `Unreachable` (with the proxy's `status`) for a
        proxy's answer."""
        if from_proxy(response):
            error = None
        elif response.status_code == 503:
            error = codec.error(response.status_code, response.content)
            if not isinstance(error, Busy):  # the deadline's 503 ran for the whole timeout: not retried
                return None
        else:
            return None
        self.attempts += 1
        after = retry_after(response)
        too_long = after is not None and after > self.max_retry_after
        step = None if too_long else next(self._pauses, None)
        if step is None:
            if error is None:
                raise Unreachable(self.url, self.attempts, status=response.status_code,
                                  proxy=proxy_page(response.content))
            raise Busy(error.status, error.faults, retry_after=after, attempts=self.attempts,
                       max_retry_after=self.max_retry_after if too_long else None)
        return max(step, after or 0.0)


def part_joints(
    limits: ConstitutionsResponse | None,
    binary: bool,
    user_max: int | None,
    outputs: Sequence[str] = OUTPUTS,
    batches: int = 1,
) -> int:
    """Joints per request: the user's cap, else the default, within the server's limits.

    Those are its joints and body bytes, and where the server tells them, the bound of the
    answer to `outputs` in this client's encoding (over `batches` batches) and a JSON body's values.
    """
    n = user_max or DEFAULT_PART_JOINTS
    if limits is not None:
        lim = limits.limits
        by_bytes = max(1, lim.max_body_bytes // _BYTES_PER_JOINT[binary])
        n = min(n, lim.max_joints, by_bytes)
        if lim.max_answer_bytes is not None:
            n = min(n, answer.joints_within(lim.max_answer_bytes, outputs, binary, max(1, batches)))
        if lim.max_json_values is not None and not binary:
            n = min(n, lim.max_json_values // _JSON_VALUES_PER_JOINT)
    return max(1, n)


def result(response: httpx.Response) -> Evaluation:
    """The evaluation of a 200, else the server's error as a `ServiceError` (with its `loc`s)."""
    if response.status_code != 200:
        raise _error(response)
    return codec.decode(response.content, response.headers.get("content-type", codec.JSON))


def constitutions(response: httpx.Response) -> ConstitutionsResponse:
    if response.status_code != 200:
        raise _error(response)
    try:
        return ConstitutionsResponse.model_validate_json(response.content)
    except ValueError:  # a 200 from some other server (a web page, another API)
        raise _wrong_url(response, "answered 200 with something that is not this service's discovery document") from None


def _error(response: httpx.Response) -> Exception:
    if response.status_code == 404:
        return _wrong_url(response, "answered 404")
    return codec.error(response.status_code, response.content)


def _wrong_url(response: httpx.Response, what: str) -> WrongURL:
    """Say that `base_url` is not the service's root (the usual slip: a trailing `/v1`)."""
    url = response.request.url
    root = str(url.copy_with(path=url.path.rsplit("/v1/", 1)[0] or "/", query=None)).rstrip("/")
    hint = " (drop the trailing /v1: the client adds it)" if root.endswith("/v1") else ""
    msg = (f"{url} {what}: no joint-limit service at base_url {root!r}{hint}; "
           "base_url is the service's root, e.g. http://127.0.0.1:8000")
    return WrongURL(response.status_code, [Fault((), msg, "wrong_url")])
