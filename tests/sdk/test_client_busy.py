"""The SDK and a busy server: a 503 "busy" (nothing computed) is retried after its Retry-After,
from the same `retries` budget as connection errors; the deadline's 503 "timeout" is not.

The server is the real app (answers computed by it) behind an `httpx.MockTransport` that puts
scripted failures before chosen `POST /v1/evaluate`s; sleeps are recorded, not slept.
Every scenario runs for `Client` and `AsyncClient`.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import (AsyncClient, Busy, Client, Evaluation, LocalClient, Request, ServiceError,
                               SessionClosed, Unreachable)
from jointlimits.client import split, transport
from jointlimits.client.errors import Fault
from jointlimits.client.session import Exchange, Resume, handshake_error
from jointlimits.client.transport import run
from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.sdk.test_client_sdk import chain, readme_scene

BUSY_MSG = "the server has no room for this request now (JOINTLIMITS_QUEUE_TIMEOUT); nothing was computed"
TIMEOUT_MSG = "the evaluation did not finish within the request timeout and was stopped"

Step = Callable[[httpx.Request], httpx.Response] | None
"""What the server does with one `POST /v1/evaluate`: None answers it, else the step's response (or raise)."""


def busy(after: str | None = "5") -> Step:
    """A busy 503 with `Retry-After: after` (no header when None)."""
    headers = {} if after is None else {"Retry-After": after}
    body = {"detail": [{"loc": ["body"], "msg": BUSY_MSG, "type": "busy"}]}
    return lambda request: httpx.Response(503, headers=headers, json=body)


def deadline(request: httpx.Request) -> httpx.Response:
    """The request deadline's 503: it ran for the whole timeout."""
    body = {"detail": [{"loc": ["body"], "msg": TIMEOUT_MSG, "type": "timeout"}]}
    return httpx.Response(503, headers={"Retry-After": "5"}, json=body)


def refused(request: httpx.Request) -> httpx.Response:
    raise httpx.ConnectError("simulated refusal", request=request)


_CLIENT_DIR = str(Path(transport.__file__).parent)


class Server:
    """A MockTransport handler: the real app answers, after the scripted steps of `/v1/evaluate`s."""

    def __init__(self, app: TestClient, *script: Step) -> None:
        self.app, self.script = app, list(script)
        self.evaluates = 0

    def __call__(self, request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/evaluate":
            self.evaluates += 1
            step = self.script.pop(0) if self.script else None
            if step is not None:
                return step(request)
        r = self.app.request(request.method, request.url.path, content=request.content, headers=dict(request.headers))
        return httpx.Response(r.status_code, headers=r.headers, content=r.content)


@pytest.fixture(scope="module")
def app() -> Iterator[TestClient]:
    yield TestClient(create_app(Settings(max_body_bytes=2_000_000, max_joints=400, token=None, cors_origins=())))


@pytest.fixture
def pauses(monkeypatch) -> list[float]:
    """The seconds the clients sleep between tries (`time.sleep`, `asyncio.sleep` called from `client/`), not slept."""
    seen: list[float] = []
    real_async_sleep = asyncio.sleep

    def from_client(frame) -> bool:
        return frame is not None and frame.f_code.co_filename.startswith(_CLIENT_DIR)

    def fake_sleep(seconds: float) -> None:
        assert from_client(sys._getframe(1)), "only the SDK sleeps in these tests"
        seen.append(seconds)

    async def fake_async_sleep(seconds: float, *args) -> object:
        if not from_client(sys._getframe(1)):  # someone else's sleep (asyncio internals): a real one
            return await real_async_sleep(seconds, *args)
        seen.append(seconds)
        return None

    monkeypatch.setattr(time, "sleep", fake_sleep)
    monkeypatch.setattr(asyncio, "sleep", fake_async_sleep)
    return seen


@pytest.fixture(params=["sync", "async"])
def mode(request) -> str:
    return request.param


def evaluate(mode: str, server: Server, request: Request, **options) -> Evaluation:
    """`request` through `Client` or `AsyncClient` (`mode`) on `server`."""
    if mode == "sync":
        with Client("http://test", http_transport=httpx.MockTransport(server), **options) as c:
            return c.evaluate(request)

    async def run() -> Evaluation:
        async with AsyncClient("http://test", http_transport=httpx.MockTransport(server), **options) as c:
            return await c.evaluate(request)

    return asyncio.run(run())


def parts_in_turn(mode: str, **options) -> dict:
    """`options`, with `AsyncClient` sending one part at a time: the script's steps meet the parts in order."""
    return {**options, "concurrency": 1} if mode == "async" else options


def same(a: Evaluation, b: Evaluation) -> None:
    """Bit for bit the same answer."""
    assert a.total_energy == b.total_energy
    assert len(a.batches) == len(b.batches)
    for ra, rb in zip(a.batches, b.batches):
        assert ra.constitution_uid == rb.constitution_uid
        for f in ("index", "x", "energy", "gradient", "hessian"):
            np.testing.assert_array_equal(getattr(ra, f), getattr(rb, f))


def test_busy_then_answered_after_retry_after(app, mode, pauses):
    request = readme_scene().request()
    server = Server(app, busy("5"))
    same(evaluate(mode, server, request), LocalClient().evaluate(request))
    assert server.evaluates == 2 and pauses == [5.0]


def test_a_fractional_retry_after_is_slept_as_given(app, mode, pauses):
    server = Server(app, busy("1.5"), busy("7"))
    evaluate(mode, server, readme_scene().request(), backoff=0.25)
    assert server.evaluates == 3 and pauses == [1.5, 7.0]  # above the steps 0.25, 0.5


def test_short_missing_or_dated_retry_after_waits_the_backoff_steps(app, mode, pauses):
    """Retry-After 0, under the step, absent, or an HTTP-date (read as absent): the backoff step."""
    script = busy("0"), busy("0.25"), busy(None), busy("Wed, 21 Oct 2026 07:28:00 GMT")
    server = Server(app, *script)
    request = readme_scene().request()
    same(evaluate(mode, server, request, retries=4, backoff=0.5), LocalClient().evaluate(request))
    assert server.evaluates == 5 and pauses == [0.5, 1.0, 2.0, 4.0]


def test_retry_after_over_max_retry_after_raises_busy_at_once(app, mode, pauses):
    server = Server(app, busy("31"))
    with pytest.raises(Busy) as err:
        evaluate(mode, server, readme_scene().request(), max_retry_after=30)
    e = err.value
    assert server.evaluates == 1 and pauses == []
    assert e.retry_after == 31.0 and e.attempts == 1 and e.status == 503 and isinstance(e, ServiceError)
    assert e.msg == BUSY_MSG and e.loc == ("body",) and e.faults[0].type == "busy"
    assert BUSY_MSG in str(e) and "1 attempt" in str(e) and "max_retry_after=30" in str(e)


def test_the_default_max_retry_after_is_30_seconds(app, mode, pauses):
    server = Server(app, busy("30"), busy("30.5"))
    with pytest.raises(Busy) as err:
        evaluate(mode, server, readme_scene().request())
    assert pauses == [30.0] and server.evaluates == 2  # 30 s is slept; 30.5 s is over the default
    assert err.value.retry_after == 30.5 and err.value.attempts == 2


def test_busy_every_time_raises_busy_after_all_the_retries(app, mode, pauses):
    server = Server(app, *[busy("1.5")] * 10)
    with pytest.raises(Busy) as err:
        evaluate(mode, server, readme_scene().request(), retries=3, backoff=1.0)
    e = err.value
    assert server.evaluates == 4 and e.attempts == 4  # 1 + retries
    assert pauses == [1.5, 2.0, 4.0]  # Retry-After, then the backoff steps once they are longer
    assert e.retry_after == 1.5 and e.status == 503 and e.msg == BUSY_MSG
    assert str(e).startswith(f"HTTP 503: body: {BUSY_MSG}") and "4 attempts" in str(e)


def test_no_retries_means_busy_on_the_first_503(app, mode, pauses):
    server = Server(app, busy(None))
    with pytest.raises(Busy) as err:
        evaluate(mode, server, readme_scene().request(), retries=0)
    assert server.evaluates == 1 and pauses == [] and err.value.retry_after is None and err.value.attempts == 1


def test_the_deadlines_503_is_not_retried(app, mode, pauses):
    server = Server(app, deadline, busy())
    with pytest.raises(ServiceError) as err:
        evaluate(mode, server, readme_scene().request(), retries=3)
    e = err.value
    assert not isinstance(e, Busy) and type(e) is ServiceError
    assert server.evaluates == 1 and pauses == []
    assert e.status == 503 and e.faults == [Fault(("body",), TIMEOUT_MSG, "timeout")]


def test_other_statuses_are_not_retried(app, mode, pauses):
    """A 503 of the service's own that is not "busy" (its JSON `detail`), and a 500, raise at once (only "busy"
    says that nothing ran; a proxy's 503, a body that is not the service's, is retried: tests/sdk/test_proxy_retries.py)."""
    for status, body in ((503, b'{"detail": "maintenance"}'), (500, b'{"detail": "boom"}')):
        server = Server(app, lambda r, s=status, b=body: httpx.Response(s, headers={"Retry-After": "1"}, content=b))
        with pytest.raises(ServiceError) as err:
            evaluate(mode, server, readme_scene().request())
        assert type(err.value) is ServiceError and err.value.status == status and server.evaluates == 1
    assert pauses == []


def test_connection_errors_and_busy_share_one_budget(app, mode, pauses):
    request = readme_scene().request()
    # Three retries answered: refused, busy (3 s over the step 2 s), refused; the fourth try is answered.
    server = Server(app, refused, busy("3"), refused)
    same(evaluate(mode, server, request, retries=3, backoff=1.0), LocalClient().evaluate(request))
    assert server.evaluates == 4 and pauses == [1.0, 3.0, 4.0]
    pauses.clear()
    # One failure more than the budget: the kind of the last one is raised, attempts count both kinds.
    server = Server(app, busy(None), refused, busy("0"), busy("0"))
    with pytest.raises(Busy) as err:
        evaluate(mode, server, request, retries=3, backoff=1.0)
    assert err.value.attempts == 4 and server.evaluates == 4 and pauses == [1.0, 2.0, 4.0]
    pauses.clear()
    server = Server(app, busy("0"), busy("0"), refused)
    with pytest.raises(Unreachable) as unreachable:
        evaluate(mode, server, request, retries=2, backoff=1.0)
    assert unreachable.value.attempts == 3 and server.evaluates == 3 and pauses == [1.0, 2.0]


def test_a_split_request_retries_its_busy_part(app, mode, pauses):
    """Three parts; the second is busy once: the merged answer is the one without failures."""
    request = chain(12, 10, seed=3)
    options = parts_in_turn(mode, max_joints_per_request=4)
    server = Server(app, None, busy("2"))
    ev = evaluate(mode, server, request, **options)
    assert server.evaluates == 4 and pauses == [2.0]
    same(ev, evaluate(mode, Server(app), request, **options))  # the same parts, none busy
    whole = LocalClient().evaluate(request)  # unsplit: the same rows; the total is a sum of the parts'
    assert ev.total_energy == pytest.approx(whole.total_energy, rel=1e-13)
    for a, b in zip(ev.batches, whole.batches):
        for f in ("index", "x", "energy", "gradient", "hessian"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_each_part_has_its_own_retries(app, mode, pauses):
    """Every part may spend the whole budget (as with connection errors): 2 busy tries for each of 3 parts."""
    request = chain(12, 10, seed=4)
    options = parts_in_turn(mode, max_joints_per_request=4, retries=2, backoff=1.0)
    server = Server(app, busy("0"), busy("0"), None, busy("0"), busy("0"), None, busy("0"), busy("0"), None)
    same(evaluate(mode, server, request, **options), evaluate(mode, Server(app), request, **options))
    assert server.evaluates == 9 and sorted(pauses) == [1.0, 1.0, 1.0, 2.0, 2.0, 2.0]


@pytest.mark.parametrize(
    "value, seconds",
    [("5", 5.0), ("0", 0.0), ("2.5", 2.5), (" 7 ", 7.0), ("120", 120.0), (None, None), ("", None), ("-1", None),
     ("nan", None), ("inf", None), ("1e3", None), ("1_000", None), ("Wed, 21 Oct 2026 07:28:00 GMT", None)],
)
def test_retry_after_reads_seconds_only(value, seconds):
    headers = {} if value is None else {"Retry-After": value}
    assert transport.retry_after(httpx.Response(503, headers=headers)) == seconds


def test_busy_is_classified_by_status_and_type():
    body = lambda kind: {"detail": [{"loc": ["body"], "msg": "m", "type": kind}]}  # noqa: E731
    assert type(ServiceError.from_body(503, body("busy"))) is Busy
    assert type(ServiceError.from_body(503, body("timeout"))) is ServiceError
    assert type(ServiceError.from_body(500, body("busy"))) is ServiceError  # "busy" means something only on a 503
    assert type(ServiceError.from_body(422, body("busy"))).__name__ == "InvalidInput"
    e = ServiceError.from_body(503, body("busy"))
    assert e.retry_after is None and e.attempts == 1 and e.status == 503
    part = split.plan(chain(12, 10), 4)[1]
    moved = split.relocate(part, e)  # a part's error keeps its class through relocation
    assert type(moved) is Busy and moved.faults == e.faults


def test_max_retry_after_is_an_option_of_every_client():
    assert Client("http://test").max_retry_after == 30.0 == AsyncClient("http://test").max_retry_after
    assert Client("http://test", max_retry_after=5).max_retry_after == 5
    LocalClient(max_retry_after=5)  # accepted and ignored, as the other HTTP options


def upgrade_refused(after: str | None) -> Exception:
    """websockets' failure of a session's upgrade answered a busy 503 with `Retry-After: after` (none when None), as a
    worker at its connection cap answers it."""
    from websockets.datastructures import Headers
    from websockets.exceptions import InvalidStatus
    from websockets.http11 import Response

    headers = Headers({"Content-Type": "application/json", **({} if after is None else {"Retry-After": after})})
    body = json.dumps({"detail": [{"loc": ["body"], "msg": BUSY_MSG, "type": "busy"}]}).encode()
    return InvalidStatus(Response(503, "Service Unavailable", headers, body))


PROXY_PAGE = b"<html><body><h1>503 Service Unavailable</h1>\nNo server is available to handle this request.\n</body></html>"


def proxy_503(after: str | None = None) -> Step:
    """A proxy's 503 (its HTML page, not the service's fault list) with `Retry-After: after` (none when None)."""
    headers = {"Content-Type": "text/html", **({} if after is None else {"Retry-After": after})}
    return lambda request: httpx.Response(503, headers=headers, content=PROXY_PAGE)


def upgrade_failed(step: tuple[str, str | None]) -> Exception:
    """What websockets raises when a session's upgrade meets `step`: a busy 503, a proxy's 503, or no server."""
    from websockets.datastructures import Headers
    from websockets.exceptions import InvalidStatus
    from websockets.http11 import Response

    kind, after = step
    if kind == "refused":
        return ConnectionRefusedError(111, "Connect call failed")
    if kind == "busy":
        return upgrade_refused(after)
    headers = Headers({"Content-Type": "text/html", **({} if after is None else {"Retry-After": after})})
    return InvalidStatus(Response(503, "Service Unavailable", headers, PROXY_PAGE))


B, P, R = "busy", "proxy", "refused"


@pytest.mark.parametrize(("script", "options"), [
    (((B, "5"),), {}),  # busy 503s alone: the opening slept 0.2, 0.4, 0.8 s whatever the server asked
    (((B, "1.5"), (B, "7")), {"backoff": 0.25}),
    (((B, "0"), (B, "0.25"), (B, None), (B, "Wed, 21 Oct 2026 07:28:00 GMT")), {"retries": 4, "backoff": 0.5}),
    (((B, "31"),), {"max_retry_after": 30}),
    (((B, "30"), (B, "30.5")), {}),
    (((B, "1.5"),) * 10, {"retries": 3, "backoff": 1.0}),
    (((B, None),), {"retries": 0}),
    (((B, "0"),) * 3 + ((R, None),), {}),  # the audit's sequence: Unreachable after 4 attempts
    (((B, "0"), (R, None), (P, None)), {"retries": 2}),  # the last kind is raised, every attempt counted
    (((R, None), (B, "0"), (R, None), (R, None)), {}),
    (((R, None), (P, None), (B, "0")), {"retries": 2}),
    (((R, None),) * 4, {}),
    (((P, None),) * 10, {"retries": 3, "backoff": 1.0}),
    (((P, "3"),), {"backoff": 1.0}),  # a proxy's Retry-After over the step: waited
    (((P, "60"),), {"max_retry_after": 30}),  # over max_retry_after: Unreachable at once
    (((P, "30"), (P, "30.5")), {}),
    (((P, "1.5"),) * 10, {"retries": 3, "backoff": 1.0}),
])  # fmt: skip
def test_a_session_opening_retries_every_cause_as_evaluate_does(app, pauses, script, options):
    """Busy 503s, a proxy's 503s (with or without `Retry-After`) and no server, to a session's upgrade
    (`handshake_error`, then `Resume`) and to `POST /v1/evaluate`: the same sleeps, then the same failure (its kind,
    attempts, `Retry-After`, proxy status) or none. Before, the opening raised its first failure said of one attempt
    (busy x3 then refused: `Busy`, "busy after 1 attempt"), and slept only the backoff steps after a proxy's 503."""
    steps = {B: busy, P: proxy_503, R: lambda after: refused}
    http: ServiceError | None = None
    try:
        evaluate("sync", Server(app, *[steps[kind](after) for kind, after in script]), readme_scene().request(),
                 **options)
    except ServiceError as e:
        http = e
    http_pauses, session = list(pauses), None
    given = {"retries": 3, "backoff": 0.2, "max_retry_after": transport.MAX_RETRY_AFTER, **options}  # the clients'
    resume = Resume(given["retries"], given["backoff"], True, given["max_retry_after"])
    session_pauses = []
    try:
        for step in script:
            session_pauses.append(resume.pause(handshake_error("ws://test/v1/sessions", upgrade_failed(step))))
    except ServiceError as e:
        session = e
    assert session_pauses == http_pauses
    assert type(session) is type(http)
    if isinstance(http, ServiceError):
        assert (session.status, session.attempts, session.retry_after) == (http.status, http.attempts, http.retry_after)
        assert f"after {http.attempts} attempt" in str(session)
    if isinstance(http, Busy):
        assert str(session) == str(http)
    if isinstance(http, Unreachable):
        assert (session.proxy, session.cause is None) == (http.proxy, http.cause is None)


@pytest.mark.parametrize("script", [(R, R, R), (P, P, P), (B, R, P), (R, B, R)])
def test_a_lost_message_whose_reopenings_reach_no_server_counts_every_attempt(script):
    """A message step (not the opening) whose connection drops, then whose reopenings meet no server (`Resume`, as
    `Exchange._exchange` meets them): `SessionClosed` (sessions.md: "a resume that found no server"), its cause the
    last failure said of every attempt, as `Busy` is when the last was busy. Before, the cause said "after 1 attempt"
    whatever the retries (the failure as `handshake_error` made it)."""
    url = "ws://test/v1/sessions"
    resume = Resume(3, 0.0, True)
    lost = SessionClosed(url, None, "", "dropped (no close frame)", resumable=True)
    assert resume.pause(lost) == 0.0
    with pytest.raises(SessionClosed) as err:
        for kind in script:
            resume.pause(handshake_error(url, upgrade_failed((kind, None if kind == R else "0"))))
    assert err.value is lost
    cause = err.value.__cause__
    assert isinstance(cause, Unreachable) and cause.attempts == 4 and "after 4 attempts" in str(cause)
    assert cause.status == (0 if script[-1] == R else 503)


class _ScriptedSession(Exchange):
    """A session run against a script (no server): each connect of a reopening meets the next failure of
    `script`; a commit's connection drops `lose` times; every other send is answered."""

    def __init__(self, script: list[tuple[str, str | None]]) -> None:
        self.script, self.sleeps, self.lose = list(script), [], 0
        super().__init__("ws://test/v1/sessions", readme_scene().request(), binary=False)
        run(self._opening(), self._io)

    def _io(self, op: str, arg: object) -> object:
        if op == "sleep":
            self.sleeps.append(arg)
        elif op == "drop":
            self._ws = None
        elif op == "connect":
            if self.script:
                raise handshake_error(self.url, upgrade_failed(self.script.pop(0)))
            self._ws = "open"
        elif op == "send":
            kind = json.loads(arg).get("kind")
            if kind == "commit" and self.lose:
                self.lose, self._ws = self.lose - 1, None
                raise SessionClosed(self.url, None, "", "dropped (no close frame)", resumable=True)
            return json.dumps({"kind": "committed" if kind == "commit" else "opened", "coordinates": [[0.0]]})
        return None


@pytest.mark.parametrize(("script", "raised"), [((B, B, B), Busy), ((R, R, R), SessionClosed),
                                                ((B, R, P), SessionClosed)])
def test_a_lost_message_past_its_retries_leaves_the_session_usable(script, raised):
    """A commit whose connection drops, then whose reopenings meet busy 503s, no server or a proxy (the message step
    through `Exchange._exchange`, not the opening): the backoff steps slept, `Busy` (every attempt: 4) or
    `SessionClosed` raised; the session holds no connection, and the next call reopens it and is answered."""
    s = _ScriptedSession([])
    s.script, s.lose = [(kind, "0" if kind == B else None) for kind in script], 1
    with pytest.raises(raised) as err:
        run(s._commit(s.request.q_prev), s._io)
    assert s.sleeps == [0.2, 0.4, 0.8] and s._ws is None and not s.script
    assert getattr(err.value, "attempts", 4) == 4
    assert run(s._commit(s.request.q_prev), s._io)[0].tolist() == [0.0] and s._ws == "open"
