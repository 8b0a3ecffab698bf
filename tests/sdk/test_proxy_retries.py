"""The SDK behind a proxy (issue 30): a proxy's 502/503/504 (an HTML page, not the service's fault
list) and a connection reset are retried for the idempotent calls, from the same `retries` budget
and backoff as connection errors and the service's busy 503; the service's own 503s keep their
meaning (tests/sdk/test_client_busy.py).

The server is the real app behind an `httpx.MockTransport` (tests/sdk/test_client_busy.py's `Server`)
that answers chosen `POST /v1/evaluate`s (or `GET /v1/constitutions`) as a proxy would; sleeps are
recorded, not slept. Every scenario runs for `Client` and `AsyncClient`.
"""

from __future__ import annotations

import httpx
import pytest

from jointlimits.client import Busy, LocalClient, ServiceError, Unreachable
from jointlimits.client import transport
from tests.sdk.test_client_busy import (  # noqa: F401 (fixtures)
    BUSY_MSG,
    Server,
    app,
    busy,
    deadline,
    evaluate,
    mode,
    pauses,
    refused,
    same,
)
from tests.sdk.test_client_sdk import readme_scene

PAGES = {
    502: b"<html><head><title>502 Bad Gateway</title></head><body><center><h1>502 Bad Gateway</h1></center>"
         b"<hr><center>nginx</center></body></html>",
    503: b"<html><body><h1>503 Service Unavailable</h1>\nNo server is available to handle this request.\n</body></html>",
    504: b"<html><body><h1>504 Gateway Time-out</h1>\nThe server didn't respond in time.\n</body></html>",
}


def proxy(status: int, content_type: str = "text/html", after: str | None = None):
    """A proxy's error page (HAProxy's and nginx's words) for one request."""
    headers = {"Content-Type": content_type, **({"Retry-After": after} if after else {})}
    return lambda request: httpx.Response(status, headers=headers, content=PAGES[status])


def reset(request: httpx.Request) -> httpx.Response:
    """The connection reset while the answer was awaited (a worker's listener closed under a proxy)."""
    raise httpx.ReadError("[Errno 104] Connection reset by peer", request=request)


def test_a_proxys_502_503_504_are_retried_then_answered(app, mode, pauses):
    request = readme_scene().request()
    server = Server(app, proxy(502), proxy(503), proxy(504))
    same(evaluate(mode, server, request, retries=3, backoff=0.5), LocalClient().evaluate(request))
    assert server.evaluates == 4 and pauses == [0.5, 1.0, 2.0]  # the backoff steps


def test_plain_text_and_empty_bodies_are_a_proxys_too(app, mode, pauses):
    """Envoy's "no healthy upstream" (text/plain), an empty 502: anything that is not the service's error body."""
    script = (
        lambda r: httpx.Response(503, headers={"Content-Type": "text/plain"}, content=b"no healthy upstream"),
        lambda r: httpx.Response(502),
        lambda r: httpx.Response(504, json=["not", "the", "service's"]),
    )
    server = Server(app, *script)
    evaluate(mode, server, readme_scene().request(), retries=3, backoff=1.0)
    assert server.evaluates == 4 and pauses == [1.0, 2.0, 4.0]


def test_a_connection_reset_is_retried(app, mode, pauses):
    request = readme_scene().request()
    server = Server(app, reset, reset)
    same(evaluate(mode, server, request, retries=2, backoff=1.0), LocalClient().evaluate(request))
    assert server.evaluates == 3 and pauses == [1.0, 2.0]


def test_a_proxys_retry_after_is_honoured_like_the_services(app, mode, pauses):
    server = Server(app, proxy(503, after="3"))
    evaluate(mode, server, readme_scene().request(), backoff=1.0)
    assert server.evaluates == 2 and pauses == [3.0]


def test_every_cause_shares_one_budget(app, mode, pauses):
    request = readme_scene().request()
    server = Server(app, proxy(502), busy("0"), refused, reset)
    same(evaluate(mode, server, request, retries=4, backoff=1.0), LocalClient().evaluate(request))
    assert server.evaluates == 5 and pauses == [1.0, 2.0, 4.0, 8.0]


def test_a_proxy_answering_every_time_raises_unreachable_after_the_budget(app, mode, pauses):
    server = Server(app, *[proxy(502)] * 10)
    with pytest.raises(Unreachable) as err:
        evaluate(mode, server, readme_scene().request(), retries=2, backoff=1.0)
    e = err.value
    assert server.evaluates == 3 and pauses == [1.0, 2.0]
    assert isinstance(e, ServiceError) and e.status == 502 and e.attempts == 3 and e.proxy == "502 Bad Gateway"
    assert str(e) == (
        "unreachable: cannot reach the service at POST http://test/v1/evaluate: a proxy answered HTTP 502 in its stead "
        "(502 Bad Gateway) after 3 attempts; is the service running behind the proxy?"
    )
    assert "<html>" not in str(e) and e.faults[0].type == "unreachable"


def test_the_last_cause_names_the_error(app, mode, pauses):
    """Mixed causes: the kind of the last failure is raised, attempts count all of them."""
    with pytest.raises(Unreachable) as err:
        evaluate(mode, Server(app, busy("0"), refused, proxy(503)), readme_scene().request(), retries=2)
    assert err.value.status == 503 and err.value.attempts == 3
    assert err.value.proxy == "503 Service Unavailable No server is available to handle this request."
    with pytest.raises(Busy) as busy_err:
        evaluate(mode, Server(app, proxy(504), reset, busy("0")), readme_scene().request(), retries=2)
    assert busy_err.value.attempts == 3 and busy_err.value.msg == BUSY_MSG
    with pytest.raises(Unreachable) as unreachable:
        evaluate(mode, Server(app, proxy(504), reset), readme_scene().request(), retries=1)
    assert unreachable.value.status == 0 and "ReadError" in str(unreachable.value)


def test_no_retries_raises_on_the_first_proxy_answer(app, mode, pauses):
    server = Server(app, proxy(504))
    with pytest.raises(Unreachable) as err:
        evaluate(mode, server, readme_scene().request(), retries=0)
    assert server.evaluates == 1 and pauses == [] and err.value.status == 504 and err.value.attempts == 1


def test_a_proxys_retry_after_over_max_retry_after_stops_at_once(app, mode, pauses):
    server = Server(app, proxy(503, after="60"))
    with pytest.raises(Unreachable) as err:
        evaluate(mode, server, readme_scene().request(), max_retry_after=30)
    assert server.evaluates == 1 and pauses == [] and err.value.status == 503


def test_discovery_is_retried_too(app, mode, pauses):
    """`GET /v1/constitutions` (sent before the first evaluate) through a proxy without upstream for a while."""
    failures = [proxy(502), proxy(503)]

    class Discovery(Server):
        def __call__(self, request: httpx.Request) -> httpx.Response:
            if request.url.path == "/v1/constitutions" and failures:
                return failures.pop(0)(request)
            return super().__call__(request)

    request = readme_scene().request()
    same(evaluate(mode, Discovery(app), request, backoff=1.0), LocalClient().evaluate(request))
    assert failures == [] and pauses == [1.0, 2.0]


def test_the_services_own_503s_keep_their_meaning(app, mode, pauses):
    """Busy is retried after its Retry-After and raises `Busy`; the deadline's 503 and any JSON `detail` are not retried."""
    server = Server(app, busy("5"))
    evaluate(mode, server, readme_scene().request())
    assert server.evaluates == 2 and pauses == [5.0]
    pauses.clear()
    with pytest.raises(Busy):
        evaluate(mode, Server(app, *[busy("0")] * 3), readme_scene().request(), retries=2)
    pauses.clear()
    for step in (deadline, lambda r: httpx.Response(503, json={"detail": "maintenance"}),
                 lambda r: httpx.Response(502, json={"detail": [{"loc": [], "msg": "m", "type": "t"}]})):
        server = Server(app, step)
        with pytest.raises(ServiceError) as err:
            evaluate(mode, server, readme_scene().request())
        assert type(err.value) is ServiceError and server.evaluates == 1
    assert pauses == []


def test_other_statuses_are_not_retried_even_from_a_proxy(app, mode, pauses):
    for status in (500, 501, 429, 403):
        server = Server(app, lambda r, s=status: httpx.Response(s, headers={"Content-Type": "text/html"},
                                                                content=b"<html>no</html>"))
        with pytest.raises(ServiceError) as err:
            evaluate(mode, server, readme_scene().request())
        assert err.value.status == status and server.evaluates == 1
    assert pauses == []


@pytest.mark.parametrize(
    "status, body, ours",
    [(502, PAGES[502], False), (503, b"", False), (504, b"upstream request timeout", False),
     (503, b'{"detail": [{"loc": ["body"], "msg": "m", "type": "busy"}]}', True), (503, b'{"detail": "x"}', True),
     (500, b"<html></html>", True), (200, b"<html></html>", True)],
)
def test_from_proxy(status, body, ours):
    assert transport.from_proxy(httpx.Response(status, content=body)) is (not ours)


@pytest.mark.parametrize(
    "page, words",
    [(PAGES[502], "502 Bad Gateway"), (b"no healthy upstream", "no healthy upstream"), (b"", "an empty body"),
     (b"<p>" + b"x" * 300 + b"</p>", "x" * 117 + "...")],
)
def test_proxy_page(page, words):
    assert transport.proxy_page(page) == words
