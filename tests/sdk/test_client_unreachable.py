"""No server, a silent host, a wrong base URL: each says what is wrong, quickly, as a `ServiceError`.

Everything runs on 127.0.0.1: a closed port (refused), a listening socket whose backlog is full and
that never accepts (connects time out, as with a host that drops packets), our own server under
a wrong base URL, and a small unrelated HTTP server.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, HTTPServer, SimpleHTTPRequestHandler

import httpx
import pytest
from fastapi import FastAPI

from jointlimits.client import AsyncClient, Client, ServiceError, Unreachable, WrongURL
from tests.http.test_contract_live import live, serve  # noqa: F401 (fixture)
from tests.sdk.test_client_sdk import readme_scene

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # connect timeouts, refused ports, unrelated servers (~4 s)


def closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    return port


@pytest.fixture
def silent_port() -> Iterator[int]:
    """A port whose connects hang: it listens with a full backlog and never accepts (SYNs are dropped)."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(0)
    port = server.getsockname()[1]
    fillers = []
    for _ in range(4):  # Linux queues backlog + 1 connections; the rest wait for SYN retries
        c = socket.socket()
        c.setblocking(False)
        c.connect_ex(("127.0.0.1", port))
        fillers.append(c)
    time.sleep(0.2)
    probe = socket.socket()
    probe.settimeout(0.5)
    try:
        probe.connect(("127.0.0.1", port))
        pytest.skip("this kernel accepts connections beyond a full backlog")
    except (TimeoutError, socket.timeout):
        pass
    finally:
        probe.close()
    yield port
    for c in fillers:
        c.close()
    server.close()


def test_connect_and_read_timeouts_are_separate():
    t = Client("http://127.0.0.1:1")._http.timeout
    assert (t.connect, t.read, t.write) == (5.0, 60.0, 60.0)
    t = Client("http://127.0.0.1:1", timeout=300, connect_timeout=2)._http.timeout
    assert (t.connect, t.read) == (2.0, 300.0)
    custom = httpx.Timeout(7.0, connect=1.0)
    assert Client("http://127.0.0.1:1", timeout=custom)._http.timeout == custom


def test_refused_names_the_url_and_the_attempts():
    url = f"http://127.0.0.1:{closed_port()}"
    with pytest.raises(Unreachable) as err:
        Client(url, retries=2, backoff=0.01).evaluate(readme_scene().request())
    e = err.value
    assert isinstance(e, ServiceError) and e.attempts == 3 and e.status == 0
    assert f"GET {url}/v1/constitutions" in str(e) and "3 attempts" in str(e) and "ConnectError" in str(e)
    assert isinstance(e.__cause__, httpx.ConnectError)


def test_refused_async():
    url = f"http://127.0.0.1:{closed_port()}"

    async def run():
        async with AsyncClient(url, retries=1, backoff=0.01) as c:
            await c.evaluate(readme_scene().request())

    with pytest.raises(Unreachable, match="2 attempts"):
        asyncio.run(run())


def test_a_silent_host_fails_on_the_connect_timeout(silent_port):
    """Before: the read timeout (60 s) applied to connecting, 4 times. Now each try waits `connect_timeout`."""
    client = Client(f"http://127.0.0.1:{silent_port}", timeout=600, connect_timeout=0.3, retries=1, backoff=0.01)
    start = time.monotonic()
    with pytest.raises(Unreachable, match="ConnectTimeout") as err:
        client.constitutions()
    assert err.value.attempts == 2
    assert time.monotonic() - start < 60  # two 0.3 s connects; the 600 s read timeout never applied


def test_base_url_with_v1_says_so(live):
    with pytest.raises(WrongURL) as err:
        Client(live + "/v1").evaluate(readme_scene().request())
    e = err.value
    assert isinstance(e, ServiceError) and e.status == 404
    assert "drop the trailing /v1" in str(e) and f"{live}/v1" in str(e)



@pytest.mark.parametrize("url", ["localhost:8000", "127.0.0.1:8000", "ws://127.0.0.1:8000"])
def test_base_url_without_http_says_wrong_url(url):
    """Before: `Client("localhost:8000")` was made, then its first call raised httpx's UnsupportedProtocol (not a
    `ServiceError`, no `base_url` named; `jointlimits evaluate --url` printed a traceback)."""
    for make in (Client, AsyncClient):
        with pytest.raises(WrongURL) as err:
            make(url)
        assert f"base_url {url!r} is not an http:// or https:// URL" in str(err.value) and err.value.status == 0

class _Unrelated(BaseHTTPRequestHandler):
    """Some other web server: an HTML 404 for every path, an HTML 200 at /v1/constitutions of 'other'."""

    def do_GET(self) -> None:  # noqa: N802
        ok = self.path.startswith("/other/")
        body = b"<html><body>" + (b"hello" if ok else b"Not Found") + b"</body></html>"
        self.send_response(200 if ok else 404)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    do_POST = do_GET

    def log_message(self, *args) -> None:
        pass


@pytest.fixture
def unrelated() -> Iterator[str]:
    server = HTTPServer(("127.0.0.1", 0), _Unrelated)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_port}"
    server.shutdown()
    server.server_close()


def test_an_unrelated_servers_404_page_says_wrong_url(unrelated):
    with pytest.raises(WrongURL) as err:
        Client(unrelated).evaluate(readme_scene().request())
    assert "answered 404" in str(err.value) and "no joint-limit service" in str(err.value)
    assert "<html>" not in str(err.value)


def test_an_unrelated_servers_200_page_says_wrong_url(unrelated):
    with pytest.raises(WrongURL, match="not this service's discovery document"):
        Client(unrelated + "/other").constitutions()


# Sessions check the URL as `evaluate` does (issue 20): the same three mistakes, the same errors.


def test_session_with_base_url_v1_says_wrong_url(live):
    with pytest.raises(WrongURL) as err:
        Client(live + "/v1").session(readme_scene().request())
    assert err.value.status == 404 and "drop the trailing /v1" in str(err.value)


def test_session_to_an_unrelated_server_says_wrong_url(unrelated):
    with pytest.raises(WrongURL, match="no joint-limit service") as err:
        Client(unrelated).session(readme_scene().request())
    assert "<html>" not in str(err.value) and "reopen" not in str(err.value)


def test_a_refused_session_opening_says_what_the_server_answered():
    """Before, each said "HTTP 404" where no 404 was read: Python's `http.server` answers `HTTP/1.0 404 File not
    found`, which websockets does not read (HTTP/1.1 only) and which was said as "InvalidMessage: did not receive a
    valid HTTP response"; a FastAPI app without the route answers 403 ("HTTP 404: ... answered HTTP 403"); a
    server that closes at once was "cannot reach (InvalidMessage: ...)". Now the message says what happened."""

    class Files(SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    files = HTTPServer(("127.0.0.1", 0), Files)
    threading.Thread(target=files.serve_forever, daemon=True).start()
    closer = socket.socket()
    closer.bind(("127.0.0.1", 0))
    closer.listen(8)

    def close_at_once() -> None:
        with contextlib.suppress(OSError):
            while True:
                closer.accept()[0].close()

    threading.Thread(target=close_at_once, daemon=True).start()

    async def opened(url: str) -> None:
        async with AsyncClient(url, retries=0) as c:
            await c.session(readme_scene().request())

    try:
        with serve(app=FastAPI()) as fastapi:
            for url, kind, status, said in [
                (f"http://127.0.0.1:{files.server_port}", WrongURL, 0, "(unsupported protocol; expected HTTP/1.1: "
                 "HTTP/1.0 404 File not found): no joint-limit service"),
                (fastapi, WrongURL, 403, "answered HTTP 403 Forbidden to the WebSocket upgrade"),
                (f"http://127.0.0.1:{closer.getsockname()[1]}", Unreachable, 0,
                 "(EOFError: connection closed while reading HTTP status line) after 1 attempt"),
            ]:
                for open_ in (lambda: Client(url, retries=0).session(readme_scene().request()),
                              lambda: asyncio.run(opened(url))):
                    with pytest.raises(kind) as err:
                        open_()
                    assert said in str(err.value) and err.value.status == status, str(err.value)
                    assert "404:" not in str(err.value) and "InvalidMessage" not in str(err.value)
    finally:
        files.shutdown()
        files.server_close()
        closer.close()


def test_session_to_a_closed_port_is_unreachable():
    url = f"http://127.0.0.1:{closed_port()}"
    with pytest.raises(Unreachable) as err:
        Client(url).session(readme_scene().request())
    assert f"ws://127.0.0.1:{url.rsplit(':', 1)[1]}/v1/sessions" in str(err.value)
    assert "reopen" not in str(err.value)


def test_a_session_open_counts_its_attempts_as_evaluate_does():
    """An open that reaches no server is tried `retries` more times (sessions.md); its `Unreachable` says how many
    times it tried, as `evaluate`'s does, not "after 1 attempt" (the first failure's count, as it was)."""
    url = f"http://127.0.0.1:{closed_port()}"
    with pytest.raises(Unreachable) as err:
        Client(url, retries=2, backoff=0.01).session(readme_scene().request())
    assert err.value.attempts == 3 and "after 3 attempts" in str(err.value)

    async def run() -> None:
        async with AsyncClient(url, retries=1, backoff=0.01) as c:
            await c.session(readme_scene().request())

    with pytest.raises(Unreachable, match="after 2 attempts") as err:
        asyncio.run(run())
    assert err.value.attempts == 2
    with pytest.raises(Unreachable, match="after 1 attempt;"):  # resume off: one attempt, said as one
        Client(url, retries=2, backoff=0.01).session(readme_scene().request(), resume=False)


def test_async_session_checks_the_url_too(live):
    async def run(url: str) -> None:
        async with AsyncClient(url) as c:
            await c.session(readme_scene().request())

    with pytest.raises(WrongURL, match="drop the trailing /v1"):
        asyncio.run(run(live + "/v1"))
    with pytest.raises(Unreachable):
        asyncio.run(run(f"http://127.0.0.1:{closed_port()}"))
