"""Rebalancing after a rollout (issue 30): a keep-alive connection older than `JOINTLIMITS_MAX_CONNECTION_AGE`
gets `Connection: close` with its next answer and is closed after it, so the client's next request opens a new
connection, which a load balancer places anew (an L4 balancer, a Kubernetes Service: on a restarted pod too).

In-process uvicorn with the protocols `jointlimits serve` runs (the connection's age comes from its HTTP protocol).
"""

from __future__ import annotations

import socket
import time

import httpx
import pytest

from jointlimits.client import Client
from jointlimits.service.settings import Settings
from tests.inprocess import serve
from tests.sdk.test_client_sdk import readme_scene

pytestmark = pytest.mark.serial  # connections closed at their age, in seconds

AGE = 0.5


def settings(age: float) -> Settings:
    return Settings(max_body_bytes=2_000_000, token=None, cors_origins=(), max_connection_age=age)


def ask(sock: socket.socket) -> bytes:
    """`GET /healthz` on a kept connection: the answer's head and body (it is small: one read suffices)."""
    sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
    answer = b""
    while b'"ok"}' not in answer:
        chunk = sock.recv(65536)
        assert chunk, answer
        answer += chunk
    return answer


@pytest.mark.parametrize("age", [AGE, 0.0])
def test_an_old_connection_is_told_to_close_and_closed(age):
    with serve(settings(age)) as live, socket.create_connection(("127.0.0.1", live.port), timeout=5) as sock:
        for _ in range(3):  # young: kept
            assert b"connection: close" not in ask(sock).lower()
        time.sleep(AGE + 0.1)
        answer = ask(sock).lower()
        if age == 0:  # no limit
            assert b"connection: close" not in answer and b"connection: close" not in ask(sock).lower()
            return
        assert answer.startswith(b"http/1.1 200") and b"connection: close" in answer
        assert sock.recv(1) == b""  # then closed by the server


@pytest.mark.slow  # waits out four connection ages (~2.3 s)
def test_clients_reconnect_without_an_error():
    """Requests spread over four ages: every one answered (the SDK retrying nothing), on a new connection after
    each age (httpx reads the answer that says close whole, then opens the next connection)."""
    request = readme_scene().request()
    with serve(settings(AGE)) as live:
        url = f"http://127.0.0.1:{live.port}"
        ports = set()

        def port(r: httpx.Response) -> None:  # on the head, before the body is read and a closing stream closed
            ports.add(r.extensions["network_stream"].get_extra_info("client_addr")[1])

        hooks = {"response": [port]}
        with Client(url, retries=0) as client, httpx.Client(base_url=url, trust_env=False, event_hooks=hooks) as plain:
            end = time.monotonic() + 4 * AGE
            while time.monotonic() < end:
                assert client.evaluate(request).total_energy > 0
                r = plain.get("/healthz")
                assert r.status_code == 200
                time.sleep(0.05)
    assert 3 <= len(ports) <= 6  # one connection per age (4 ages, a first partial one, scheduling slack)
