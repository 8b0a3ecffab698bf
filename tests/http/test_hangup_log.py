"""A client that pipelines requests and hangs up (a reset or a FIN) before their answers are written is no application
error: uvicorn tells only the last request read that its client is gone, so the one being answered ahead of it wrote
to the closed transport (uvloop raises) and uvicorn logged "Exception in ASGI application" with a traceback for a
client's hang-up (`service/http/timeouts.py:ReadTimeoutProtocol.connection_lost` now tells the one being answered).
The request answered still logs its one access line (docs/deployment.md), and a route that raises still logs its
traceback, its client there or gone.

On an in-process uvicorn with the project's protocols; the app has two routes of its own that answer only once the
test has seen the connection gone, so the answer is always written after the hang-up."""

from __future__ import annotations

import asyncio
import logging
import socket
import struct
import threading
import time
from collections.abc import Iterator

import httpx
import pytest
from starlette.requests import Request

from jointlimits.service.app import create_app
from jointlimits.service.observability import ACCESS_LOGGER
from jointlimits.service.settings import Settings
from tests import inprocess
from tests.drills import scraped

pytestmark = pytest.mark.slow  # a real server on loopback, its connections reset by the test

RELEASE = threading.Event()  # set by the test: the held routes answer


@pytest.fixture(scope="module")
def live() -> Iterator[inprocess.Live]:
    settings = Settings(token=None, cors_origins=())
    app = create_app(settings)

    async def held(request: Request) -> None:
        # Its body read first, as the evaluate route does: a read resumes reading the connection (uvicorn paused it
        # for the requests queued behind), so the server sees the hang-up before the answer is written.
        await request.body()
        await asyncio.to_thread(RELEASE.wait, 10)

    @app.get("/held")
    async def answers(request: Request) -> dict[str, bool]:
        await held(request)
        return {"held": True}

    @app.get("/boom")
    async def boom(request: Request) -> None:
        await held(request)
        raise RuntimeError("a genuine fault of the route")

    with inprocess.serve(settings, app=app) as live:
        yield live


def counted(live: inprocess.Live, route: str, status: str) -> float:
    return scraped(live.port, "jointlimits_http_requests_total", route=route, status=status)


def pipelined_then_gone(live: inprocess.Live, caplog: pytest.LogCaptureFixture, path: str, reset: bool,
                        requests: int = 3) -> list[logging.LogRecord]:
    """`requests` times `GET path` in one write, the client gone before any answer; the routes then answer. The
    access lines of `path`, once the one answered has logged."""
    RELEASE.clear()
    with socket.create_connection(("127.0.0.1", live.port)) as s:
        if reset:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode() * requests)
        deadline = time.monotonic() + 5
        while not live.server.server_state.tasks and time.monotonic() < deadline:  # the first request started
            time.sleep(0.01)
    deadline = time.monotonic() + 5
    while live.connections() and time.monotonic() < deadline:  # the server saw the hang-up
        time.sleep(0.01)
    assert live.connections() == 0
    RELEASE.set()
    deadline = time.monotonic() + 5
    while live.server.server_state.tasks and time.monotonic() < deadline:  # the request answered (or raised)
        time.sleep(0.01)
    time.sleep(0.1)  # anything logged after the task ends
    return [r for r in caplog.records if r.name == ACCESS_LOGGER and r.fields["path"] == path]


@pytest.mark.parametrize("requests", [3, 1], ids=["pipelined", "alone"])
@pytest.mark.parametrize("reset", [True, False], ids=["reset", "fin"])
def test_a_pipelining_client_that_hangs_up_logs_its_answered_request_and_no_error(live, caplog, reset, requests):
    """Pipelined, as a request alone: one access line and one count for the request started, with the status it
    answered (to nobody); those queued behind it never started, and are neither logged nor counted. Before the fix,
    pipelined (reset or FIN) also logged ERROR "Exception in ASGI application" with a RuntimeError ("unable to
    perform operation on <TCPTransport closed=True ...>; the handler is closed")."""
    caplog.set_level(logging.INFO)
    before = counted(live, "/held", "200"), counted(live, "/held", "500")
    access = pipelined_then_gone(live, caplog, "/held", reset, requests)
    assert not [(r.name, r.getMessage()) for r in caplog.records if r.levelno >= logging.WARNING or r.exc_info]
    assert [r.fields["status"] for r in access] == [200]
    assert (counted(live, "/held", "200"), counted(live, "/held", "500")) == (before[0] + 1, before[1])


def test_a_route_that_raises_logs_its_traceback_its_client_there_or_gone(live, caplog):
    caplog.set_level(logging.INFO)
    RELEASE.set()
    assert httpx.get(f"http://127.0.0.1:{live.port}/boom", timeout=10).status_code == 500
    access = pipelined_then_gone(live, caplog, "/boom", reset=True)
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert [(r.getMessage().strip(), str(r.exc_info[1])) for r in errors] == 2 * [
        ("Exception in ASGI application", "a genuine fault of the route")]
    assert [r.fields["status"] for r in access] == [500, 500]


@pytest.mark.parametrize("first", ["answered", "pipelined"])
def test_the_request_marked_gone_is_the_one_being_answered_not_the_first_nor_the_last_read(live, caplog, first):
    """The request answered when the client leaves is neither the connection's first (a keep-alive `/healthz`
    answered and read before, or pipelined ahead of it) nor the last read (two `/healthz` queued behind it): it
    alone is told, logs its one access line and count, no error, and its budget is given back."""
    caplog.set_level(logging.INFO)
    RELEASE.clear()
    before = counted(live, "/held", "200")
    fast, held = b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n", b"GET /held HTTP/1.1\r\nHost: x\r\n\r\n"
    with socket.create_connection(("127.0.0.1", live.port)) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # a reset: uvloop's write raises
        if first == "answered":
            s.sendall(fast)
            assert s.recv(65536).startswith(b"HTTP/1.1 200")
            s.sendall(held + 2 * fast)
        else:
            s.sendall(fast + held + 2 * fast)
        deadline = time.monotonic() + 5
        while len(live.server.server_state.tasks) == 0 or not any(
                r.name == ACCESS_LOGGER and r.fields["path"] == "/healthz" for r in caplog.records):
            assert time.monotonic() < deadline
            time.sleep(0.01)  # /healthz answered, /held started
    deadline = time.monotonic() + 5
    while live.connections() and time.monotonic() < deadline:  # the server saw the hang-up
        time.sleep(0.01)
    RELEASE.set()
    while live.server.server_state.tasks and time.monotonic() < deadline:  # the held route answered (to nobody)
        time.sleep(0.01)
    time.sleep(0.1)  # anything logged after the task ends
    assert not [(r.name, r.getMessage()) for r in caplog.records if r.levelno >= logging.WARNING or r.exc_info]
    access = [(r.fields["path"], r.fields["status"]) for r in caplog.records if r.name == ACCESS_LOGGER]
    assert [a for a in access if a[0] != "/metrics"] == [("/healthz", 200), ("/held", 200)]
    assert counted(live, "/held", "200") == before + 1 and live.held() == 0
