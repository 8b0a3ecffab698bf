"""What the sync and async HTTP clients share, free of I/O: settings, headers, retries, part size, answers.

As in httpx's own `BaseClient`, the subclasses only send (blocking or awaited), sleep between retries (as
long as `Retry` says), and run the parts of a split in turn or concurrently. A step that needs I/O (a request
and its retries here, a session's open or message in `client/session.py`) is a generator of the I/O it asks
for (the sans-I/O pattern), run to the end by `run` (blocking) or `arun` (asyncio).
"""

from __future__ import annotations

import functools
import os
import re
import ssl
import sys
import time
from collections.abc import Awaitable, Callable, Generator, Sequence
from typing import Any, TypeVar

import httpx
import orjson

from jointlimits.client import codec, split
from jointlimits.client.errors import Busy, Fault, ServiceError, Unreachable, WrongURL
from jointlimits.client.model import Evaluation, Request, in_body, null_arrays
from jointlimits.schemas import OUTPUTS, ConstitutionsResponse, answer
from jointlimits.schemas import session as proto
from jointlimits.service.settings import bearer_token

DEFAULT_URL = "http://127.0.0.1:8000"
RETRYABLE = (httpx.ConnectError, httpx.ConnectTimeout, httpx.RemoteProtocolError, httpx.ReadError, httpx.WriteError)
"""Connection failures: the request never reached the server, or was dropped before an answer (both calls are
idempotent). A busy 503 and a proxy's 502/503/504 are retried too (`Retry`); nothing else is."""
PROXY_STATUSES = frozenset({502, 503, 504})
MAX_RETRY_AFTER = 30.0
"""Longest `Retry-After` (seconds) the clients sleep for; a server asking more raises `Busy` at once."""
CONNECT_TIMEOUT = 5.0
"""Seconds to open a connection: a host that drops packets fails in seconds, not in `timeout`."""
DEFAULT_PART_JOINTS = 20_000
"""Joints per request when splitting (each Hessian is 4.6 kB: ~90 MB of answer per part)."""
# Worst-case request bytes per joint: its arrays plus two bodies' three 12-DOF rows.
_BYTES_PER_JOINT = {True: 8 * (2 + 6 + 3) + 2 * 3 * 12 * 8 + 64, False: 2 * 3 * 12 * 25 + 11 * 25 + 64}
_JSON_VALUES_PER_JOINT = 11 + 2 * 3 * 12 + 8  # its 11 numbers, two bodies' three 12-DOF rows, separators
TOKEN_ENV = "JOINTLIMITS_TOKEN"
"""The bearer token when a client is given none: the server's own setting (service/settings.py)."""
ProgressCallback = Callable[[int, int], None]
"""Called with `(joints_done, joints_total)` after each part of a split request."""
T = TypeVar("T")
Steps = Generator[tuple[str, Any], Any, T]
"""A step, free of I/O: it yields each I/O it needs, `(op, argument)`, and is sent its result (or its failure)."""


def run(steps: Steps[T], io: Callable[[str, Any], Any]) -> T:
    """`steps` run to the end, each I/O it asks for done by `io`, blocking, and its result (or failure) sent back."""
    reply: Any = None
    error: BaseException | None = None
    while True:
        try:
            op, arg = steps.throw(error) if error is not None else steps.send(reply)
        except StopIteration as done:
            return done.value
        try:
            reply, error = io(op, arg), None
        except BaseException as e:  # thrown into `steps`, where it is handled or raised on
            reply, error = None, e


async def arun(steps: Steps[T], io: Callable[[str, Any], Awaitable[Any]]) -> T:
    """`run`, each I/O awaited."""
    reply: Any = None
    error: BaseException | None = None
    while True:
        try:
            op, arg = steps.throw(error) if error is not None else steps.send(reply)
        except StopIteration as done:
            return done.value
        try:
            reply, error = await io(op, arg), None
        except BaseException as e:
            reply, error = None, e


class BaseClient:
    """Settings and request logic of the HTTP clients; a subclass names its httpx client (`_HTTP`) and does the I/O."""

    _HTTP: Any
    _http: Any

    def __init__(self, base_url: str = DEFAULT_URL, *, binary: bool = True, timeout: float | httpx.Timeout = 60.0,
                 connect_timeout: float = CONNECT_TIMEOUT, retries: int = 3, backoff: float = 0.2,
                 token: str | None = None, max_joints_per_request: int | None = None,
                 progress: bool | ProgressCallback = False, max_retry_after: float = MAX_RETRY_AFTER,
                 http_transport: httpx.BaseTransport | httpx.AsyncBaseTransport | None = None) -> None:
        if httpx.URL(base_url).scheme not in ("http", "https"):  # "localhost:8000": said here, not in httpx's words
            msg = f"base_url {base_url!r} is not an http:// or https:// URL; the service's root, e.g. {DEFAULT_URL}"
            raise WrongURL(0, [Fault((), msg, "wrong_url")], where="wrong url")
        self.binary = binary
        self.retries, self.backoff = retries, backoff
        self.max_retry_after = max_retry_after
        self.max_joints_per_request = max_joints_per_request
        self.progress = progress
        self._limits: ConstitutionsResponse | None = None
        if not isinstance(timeout, httpx.Timeout):  # `timeout` reads, writes and waits; `connect_timeout` connects
            timeout = httpx.Timeout(timeout, connect=connect_timeout)
        self._headers = {"Accept": codec.BINARY if binary else codec.JSON}
        given, token = token is not None, os.environ.get(TOKEN_ENV) if token is None else token  # "": none
        try:  # the server's rule (httpx's words otherwise, at the first call)
            bearer_token(token or "")
        except ValueError as e:
            raise ValueError(f"{'token' if given else TOKEN_ENV}: {e} (it goes in the Authorization header)") from None
        if token:
            self._headers["Authorization"] = f"Bearer {token}"
        verify = _ssl_context(os.environ.get("SSL_CERT_FILE"), os.environ.get("SSL_CERT_DIR"))
        self._http = self._HTTP(base_url=base_url, timeout=timeout, headers=self._headers, transport=http_transport,
                                verify=verify)

    def _session_options(self) -> dict[str, Any]:
        """A session's URL (http -> ws, https -> wss), upgrade headers (the token) and settings from this client's."""
        base = str(self._http.base_url).rstrip("/")
        scheme, _, rest = base.partition("://")
        t = self._http.timeout
        return dict(url={"http": "ws", "https": "wss"}.get(scheme, scheme) + "://" + rest + proto.PATH,
                    headers={k: v for k, v in self._headers.items() if k == "Authorization"},
                    timeout=t.read, binary=self.binary, retries=self.retries, backoff=self.backoff,
                    max_retry_after=self.max_retry_after)

    def _constitutions_request(self) -> httpx.Request:
        return self._http.build_request("GET", "/v1/constitutions")

    def _evaluate_request(self, part: split.Part) -> httpx.Request:
        content, content_type = codec.encode(part.request, self.binary)
        return self._http.build_request("POST", "/v1/evaluate", content=content, headers={"Content-Type": content_type})

    def _sending(self, request: httpx.Request) -> Steps[httpx.Response]:
        """`request`'s answer, `("send", request)` tried again after a connection failure, a busy 503 or a proxy's
        502/503/504, `("sleep", seconds)` between, as `Retry` says."""
        url, retry = f"{request.method} {request.url}", Retry(self.retries, self.backoff, self.max_retry_after)
        while True:
            try:
                response = yield "send", request
            except RETRYABLE as e:
                refused: ServiceError | None = Unreachable(url, 1, e)
            else:  # None: the answer; else a busy 503 or a proxy's 502/503/504 to retry
                refused = refusal(url, response, response.status_code, response.content, from_proxy(response))
                if refused is None:
                    return response
            yield "sleep", retry.pause(refused)

    def _job(self, request: Request, progress: bool | ProgressCallback | None) -> Job:
        """`request` in parts that fit `self._limits` (fetched by the caller: that is I/O); a None array
        is refused here, as the service would (it cannot be counted, split or encoded)."""
        if missing := null_arrays(request):
            raise in_body(missing)
        n = part_joints(self._limits, self.binary, self.max_joints_per_request, request.outputs, len(request.batches))
        parts = split.plan(request, n)
        progress = self.progress if progress is None else progress
        report = progress if callable(progress) else bar() if progress and len(parts) > 1 else None
        return Job(request, parts, report)


class Job:
    """One `evaluate` call: its parts, their answers in whatever order they arrive, the progress so far."""

    def __init__(self, request: Request, parts: list[split.Part], report: ProgressCallback | None) -> None:
        self.request, self.parts = request, parts
        self._report = report
        self._done = 0

    def receive(self, part: split.Part, response: httpx.Response) -> Evaluation:
        """The part's evaluation; a server error is raised with `loc`s in the numbering of the whole request."""
        try:
            result = _result(response)
        except ServiceError as e:
            raise split.relocate(part, e) from None
        self._done += part.request.n_joints
        if self._report:
            self._report(self._done, self.request.n_joints)
        return result

    def merge(self, results: list[Evaluation]) -> Evaluation:
        """The parts' evaluations, in the order of `parts`, as one."""
        return split.merge(self.request, self.parts, results).sized(self.request)


def bar(width: int = 30) -> ProgressCallback:
    """A tiny stderr progress bar (no dependency): `done / total` joints of a split request."""
    t0 = time.perf_counter()

    def draw(done: int, total: int) -> None:
        filled = int(width * (done / total if total else 1.0))
        sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {done}/{total} joints {time.perf_counter() - t0:5.1f}s")
        sys.stderr.write("\n" if done >= total else "")
        sys.stderr.flush()

    return draw


@functools.lru_cache(maxsize=4)
def _ssl_context(cert_file: str | None, cert_dir: str | None) -> ssl.SSLContext:
    """httpx's default context (its CA bundle, or the variables' files), built once per process and bundle: httpx
    builds one per client, and loading the bundle costs 40-170 ms, more than a small evaluation's round trip."""
    return httpx.create_ssl_context()


def retry_after(response: Any) -> float | None:
    """The seconds of `response`'s `Retry-After` header (digits, with or without a decimal part), else None;
    `response` is httpx's, or websockets' answer to a session's upgrade."""
    value = response.headers.get("retry-after", "").strip()
    return float(value) if re.fullmatch(r"[0-9]+(\.[0-9]+)?", value) else None


def is_fault_list(body: bytes) -> bool:
    """Whether `body` is the service's error (a JSON object whose `detail` is a list)."""
    try:
        return isinstance(orjson.loads(body).get("detail"), list)
    except (orjson.JSONDecodeError, AttributeError):
        return False


def from_proxy(response: httpx.Response) -> bool:
    """True for a 502/503/504 that is not the service's own answer: e.g. an HTML page of HAProxy, nginx, Envoy
    or a cloud load balancer that had no upstream to hand the request to (every error of the service has `detail`)."""
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
    text = " ".join((title.group(1) if title else re.sub(r"<[^>]*>", " ", text)).split())
    return (text[:117] + "...") if len(text) > 120 else (text or "an empty body")


def refusal(url: str, response: Any, status: int, body: bytes, proxy: bool) -> ServiceError | None:
    """An answer that computed nothing, to retry (`response`'s `Retry-After` in it): a proxy's 502/503/504 (`proxy`:
    not the service's) as `Unreachable` with its status and page, a busy 503 as `Busy`; else None."""
    if proxy:
        return Unreachable(url, 1, status=status, proxy=proxy_page(body), retry_after=retry_after(response))
    error = codec.error(status, body) if status == 503 else None  # the deadline's 503 ran for the whole timeout
    return Busy(status, error.faults, retry_after=retry_after(response)) if isinstance(error, Busy) else None


class Retry:
    """The retries of one request (and of a session's steps, `client/session.py:Resume`): connection errors, busy
    503s and a proxy's 502/503/504 draw on the same budget and the same backoff steps: each retry, whatever its
    cause, spends the next step."""

    def __init__(self, retries: int, backoff: float, max_retry_after: float = MAX_RETRY_AFTER) -> None:
        self._pauses = (backoff * 2**k for k in range(retries))  # the sleep before each retry
        self.max_retry_after = max_retry_after
        self.attempts = 0

    def pause(self, e: ServiceError) -> float:
        """Seconds to sleep after `e` (`Unreachable` or `Busy`: nothing was computed) before the next try: its
        `Retry-After`, at least the backoff step. When no retry is left, or `e` asks to wait more than
        `max_retry_after`: `e` raised, said of every attempt."""
        self.attempts += 1
        after = getattr(e, "retry_after", None)
        too_long = after is not None and after > self.max_retry_after
        step = None if too_long else next(self._pauses, None)
        if step is not None:
            return max(step, after or 0.0)
        if isinstance(e, Busy):
            raise Busy(e.status, e.faults, retry_after=after, attempts=self.attempts,
                       max_retry_after=self.max_retry_after if too_long else None)
        if isinstance(e, Unreachable):
            raise e.after(self.attempts) from e.cause
        raise e from None


def part_joints(limits: ConstitutionsResponse | None, binary: bool, user_max: int | None,
                outputs: Sequence[str] = OUTPUTS, batches: int = 1) -> int:
    """Joints per request: the user's cap, else the default, within the server's limits: its joints and body
    bytes, and where the server tells them, the bound of the answer to `outputs` in this client's encoding
    (over `batches` batches) and a JSON body's values."""
    n = user_max or DEFAULT_PART_JOINTS
    if limits is not None:
        lim = limits.limits
        n = min(n, lim.max_joints, max(1, lim.max_body_bytes // _BYTES_PER_JOINT[binary]))
        if lim.max_answer_bytes is not None:
            n = min(n, answer.joints_within(lim.max_answer_bytes, outputs, binary, max(1, batches)))
        if lim.max_json_values is not None and not binary:
            n = min(n, lim.max_json_values // _JSON_VALUES_PER_JOINT)
    return max(1, n)


def _result(response: httpx.Response) -> Evaluation:
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
        msg = "answered 200 with something that is not this service's discovery document"
        raise wrong_url(str(response.request.url), msg, 200) from None


def _error(response: httpx.Response) -> Exception:
    if response.status_code == 404:
        return wrong_url(str(response.request.url), "answered 404", 404)
    return codec.error(response.status_code, response.content)


def wrong_url(url: str, what: str, status: int) -> WrongURL:
    """Say that `url` (HTTP or WebSocket) is not under the service's root (the usual slip: a trailing `/v1`)."""
    root = url.rsplit("/v1/", 1)[0].replace("ws://", "http://", 1).replace("wss://", "https://", 1).rstrip("/")
    hint = " (drop the trailing /v1: the client adds it)" if root.endswith("/v1") else ""
    msg = (f"{url} {what}: no joint-limit service at base_url {root!r}{hint}; "
           "base_url is the service's root, e.g. http://127.0.0.1:8000")
    return WrongURL(status, [Fault((), msg, "wrong_url")], where=None if status else "wrong url")  # 0: none read
