"""Sessions resume by themselves (issue 30): a connection closed by a server that stops (1012, 1001) or dropped
is reopened in the committed state and the message in flight sent again, so the caller's loop sees no error; a
worker that drains (after SIGTERM) refuses new sessions with 503 `draining`, so a reopen lands elsewhere.

In-process uvicorn servers (the protocols `jointlimits serve` runs); a restart is one server stopped (its
sessions get 1012) and another started on the same port, as a balancer's address stays while its replicas
change. Every committed coordinate is compared bitwise with an in-process session that never lost its connection
(a reopen carries the committed angles as `prev_coordinate`: the state is the same bits, not a recomputation).
The live drill through HAProxy and real replicas is tests/ops/test_lb_drill.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
from contextlib import ExitStack

import numpy as np
import pytest
import uvicorn
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosedError, InvalidStatus
from websockets.frames import Close
from websockets.http11 import Response

from jointlimits.client import AsyncClient, Busy, Client, LocalClient, ServiceError, SessionClosed, Unreachable
from jointlimits.client.session import resumable
from jointlimits.client.session import closed_error, handshake_error
from jointlimits.schemas import session as proto
from jointlimits.service.app import create_app
from jointlimits.service.http.timeouts import server_options
from jointlimits.service.settings import Settings
from tests.conftest import same_evaluation
from tests.drills import ws_upgrade
from tests.http.test_contract_live import LIMITS, running
from tests.sdk.test_sessions_live import chain


def replica(port: int = 0, settings: Settings = LIMITS):
    """One replica: the app under uvicorn in a thread, on `port` (0: a free one)."""
    app = create_app(settings)
    config = uvicorn.Config(app, log_level="warning", lifespan="off", **server_options(settings.max_frame_bytes))
    return running(config, port)


def steps(session, ref, q, pose, angles) -> None:
    """evaluate, commit at each angle of body 2; every answer and committed coordinate bitwise `ref`'s."""
    for a in angles:
        q[2] = pose(a)
        same_evaluation(session.evaluate(q), ref.evaluate(q))
        assert session.commit(q)[0].tobytes() == ref.commit(q)[0].tobytes()


@pytest.mark.parametrize("binary", [True, False])
def test_a_restart_under_a_session_is_resumed_on_the_next_server(binary):
    """The server stops (1012) between two messages; the next one starts on the same address: no error reaches
    the loop, which turns body 2 past pi (the committed angle is the unwrapped one), bitwise as never interrupted."""
    req, pose = chain(2)
    q = req.q.copy()
    with LocalClient().session(req) as ref:
        with replica() as (_, port):
            s = Client(f"http://127.0.0.1:{port}", binary=binary).session(req)
            steps(s, ref, q, pose, [0.5 * k for k in range(1, 5)])
        # stopped: the session was closed with 1012; a new replica takes the address
        with replica(port):
            steps(s, ref, q, pose, [0.5 * k for k in range(5, 9)])
            assert abs(s.coordinates[0][1] - 3.3) < 1e-12  # 4 - 0.7 rad: past pi, not wrapped
            s.update(0, [1], upper=[3.0])
            ref.update(0, [1], upper=[3.0])
        with replica(port):
            steps(s, ref, q, pose, [4.2, 4.4])  # the update travelled with the state
            s.close()


def test_without_resume_the_restart_is_the_callers(monkeypatch):
    req, _ = chain(2)
    with replica() as (_, port):
        s = Client(f"http://127.0.0.1:{port}").session(req, resume=False)
    with pytest.raises(SessionClosed) as e:
        s.evaluate(req.q)
    assert e.value.code == proto.SERVICE_RESTART and e.value.resumable


def test_a_message_whose_reply_is_lost_is_sent_again():
    """The connection drops right after a commit left (the server may have committed it): the commit is sent
    again on a new connection opened at the last commit the client saw, and the coordinates are the same bits."""
    req, pose = chain(2)
    q = req.q.copy()
    with replica() as (_, port), LocalClient().session(req) as ref:
        s = Client(f"http://127.0.0.1:{port}").session(req)
        steps(s, ref, q, pose, [0.5, 1.0, 1.5])
        for a in (2.0, 2.5, 3.0):
            ws = s._ws

            def reply_lost(timeout=None, ws=ws):  # the commit has left; the network drops the connection under it
                ws.socket.shutdown(socket.SHUT_RDWR)
                raise ConnectionClosedError(None, None)

            ws.recv = reply_lost
            q[2] = pose(a)
            assert s.commit(q)[0].tobytes() == ref.commit(q)[0].tobytes()
            assert s._ws is not ws  # a new connection
        steps(s, ref, q, pose, [3.5, 4.0])
        s.close()


def test_async_sessions_resume_too():
    """`test_a_restart_under_a_session_is_resumed_on_the_next_server` with `AsyncClient`: the replicas stop and
    start in a thread while the session's event loop runs."""
    req, pose = chain(2)
    q = req.q.copy()

    async def run(ref) -> None:
        with ExitStack() as first, ExitStack() as second:
            _, port = first.enter_context(replica())
            s = await AsyncClient(f"http://127.0.0.1:{port}").session(req)
            for a in (0.5, 1.0, 1.5):
                q[2] = pose(a)
                same_evaluation(await s.evaluate(q), ref.evaluate(q))
                assert (await s.commit(q))[0].tobytes() == ref.commit(q)[0].tobytes()
            await asyncio.to_thread(first.close)  # stopped: 1012
            await asyncio.to_thread(second.enter_context, replica(port))
            for a in (2.0, 3.0, 4.0):
                q[2] = pose(a)
                same_evaluation(await s.evaluate(q), ref.evaluate(q))
                assert (await s.commit(q))[0].tobytes() == ref.commit(q)[0].tobytes()
            await s.close()

    with LocalClient().session(req) as ref:
        asyncio.run(run(ref))


def test_an_async_session_resumes_after_a_1012_close():
    req, pose = chain(2)
    q = req.q.copy()
    with replica() as (server, port), LocalClient().session(req) as ref:

        async def run():
            async with AsyncClient(f"http://127.0.0.1:{port}").session(req) as s:
                for k in range(1, 4):
                    q[2] = pose(0.5 * k)
                    assert (await s.commit(q))[0].tobytes() == ref.commit(q)[0].tobytes()
                await s._ws.close(proto.SERVICE_RESTART, "as a server that restarts would")
                q[2] = pose(2.5)
                same_evaluation(await s.evaluate(q), ref.evaluate(q))
                assert (await s.commit(q))[0].tobytes() == ref.commit(q)[0].tobytes()

        asyncio.run(run())


def test_a_draining_worker_refuses_new_sessions_and_serves_its_own():
    """After SIGTERM (here: `state.draining` set as the handler sets it) an upgrade gets 503 `draining` (a
    balancer's retry goes elsewhere), the session already open goes on; the SDK retries a refused open and
    opens once a worker takes it."""
    req, pose = chain(2)
    q = req.q.copy()
    with replica() as (server, port):
        app = server.config.app
        url = f"http://127.0.0.1:{port}"
        s = Client(url).session(req)
        app.state.draining = True
        sock, head = ws_upgrade(port)
        body = sock.makefile("rb").read()  # up to the server's close
        sock.close()
        assert head.startswith(b"HTTP/1.1 503") and b'"type":"draining"' in body and b"JOINTLIMITS_SHUTDOWN_DELAY" in body
        with pytest.raises(ServiceError) as e:
            Client(url, retries=0).session(req)
        assert e.value.status == 503 and e.value.faults[0].type == "draining" and resumable(e.value)
        q[2] = pose(0.9)
        assert s.commit(q)[0].size == 2  # the open session is served while draining
        threading.Timer(0.3, lambda: setattr(app.state, "draining", False)).start()
        with Client(url, retries=4, backoff=0.2).session(req) as late:  # 0.2 + 0.4 s: open on the third try
            assert late.evaluate(q).total_energy > 0
        s.close()


def test_a_proxys_page_to_the_upgrade_is_unreachable_and_resumable():
    """HAProxy or nginx answering the upgrade with its own 502/503/504 page (no upstream): `Unreachable` with the
    proxy's status, as `evaluate` says it, and tried again; the service's own 4xx is not."""
    page = b"<html><body><h1>503 Service Unavailable</h1>No server is available to handle this request.</body></html>"
    e = handshake_error("ws://lb/v1/sessions", InvalidStatus(Response(503, "Service Unavailable", Headers(), page)))
    assert isinstance(e, Unreachable) and e.status == 503 and "No server is available" in str(e) and resumable(e)
    body = b'{"detail":[{"loc":[],"msg":"bad token","type":"unauthorized"}]}'
    e = handshake_error("ws://lb/v1/sessions", InvalidStatus(Response(401, "Unauthorized", Headers(), body)))
    assert e.status == 401 and not resumable(e)
    for code, expected in ((proto.SERVICE_RESTART, True), (proto.GOING_AWAY, True), (None, True),
                           (proto.IDLE_TIMEOUT, False), (proto.MESSAGE_TOO_BIG, False), (proto.TOO_MANY_SESSIONS, True),
                           (proto.TRY_AGAIN_LATER, True), (proto.INTERNAL_ERROR, False)):
        lost = ConnectionClosedError(None if code is None else Close(code, "why"), None)
        assert resumable(closed_error("ws://x", lost)) == expected, code


def test_an_upgrade_the_server_hangs_up_on_is_tried_again_as_evaluate_does():
    """A server that closes the connection before any answer to the upgrade (a worker stopping between its accept
    and the request's read, a balancer's replica going away): websockets raises `InvalidMessage` from an
    `EOFError`. `evaluate` retries the same drop (httpx's `RemoteProtocolError`) and raises `Unreachable`; a session
    opening said `WrongURL` ("no joint-limit service") at once, not tried again. Now as `evaluate`: each client
    tries `retries` more times, then raises `Unreachable` (resumable); a server that answers something else is
    still `WrongURL` (test_client_unreachable.py)."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    accepted = []

    def hang_up() -> None:
        while True:
            try:
                c, _ = server.accept()
            except OSError:
                return
            accepted.append(c.recv(65536))  # the whole upgrade request, then a FIN: no answer
            c.close()

    threading.Thread(target=hang_up, daemon=True).start()
    url, req = f"http://127.0.0.1:{server.getsockname()[1]}", chain()[0]
    try:
        with pytest.raises(Unreachable) as e:
            Client(url, retries=2, backoff=0.01).session(req)
        assert resumable(e.value) and len(accepted) == 3 and all(b"Upgrade: websocket" in a for a in accepted)

        async def opened():
            await AsyncClient(url, retries=1, backoff=0.01).session(req)

        with pytest.raises(Unreachable):
            asyncio.run(opened())
        assert len(accepted) == 5
    finally:
        server.close()


def test_the_three_clients_take_the_same_session_arguments():
    """`resume` is a keyword of every client's `session` (the local one has no connection to lose)."""
    import inspect

    from jointlimits.client import LocalClient

    for client in (Client, AsyncClient, LocalClient):
        assert inspect.signature(client.session).parameters["resume"].default is True, client
    req, _ = chain(2)
    with LocalClient().session(req, resume=False) as s:
        assert s.evaluate(req.q).total_energy > 0


def test_a_refusal_read_before_the_upgrade_is_sent_logs_nothing(caplog, monkeypatch):
    """A worker at its connection cap writes its 503 at accept. When websockets' reader thread reads it before the
    blocking client queues the upgrade, its `send_context` fails an assertion with the upgrade queued, and the reader
    thread then wrote it to the closed socket: "unexpected internal error" and an EBADF (or EPIPE) traceback logged
    in the user's process (12 of 150 refused openings on a live server at its cap). Forced here every time: the
    upgrade waits until the refusal has been read. Before: the log line, every run; now the SDK's `Busy` alone."""
    from websockets.client import ClientProtocol
    from websockets.sync.client import ClientConnection

    body = b'{"detail":[{"loc":["connection"],"msg":"full (JOINTLIMITS_MAX_CONNECTIONS)","type":"busy"}]}'
    answer = (b"HTTP/1.1 503 Service Unavailable\r\nRetry-After: 5\r\nConnection: close\r\nContent-Type: "
              b"application/json\r\nContent-Length: %d\r\n\r\n%s" % (len(body), body))
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)

    done = threading.Event()

    def refuse_at_accept() -> None:
        with server.accept()[0] as c:
            c.sendall(answer)
            done.wait(5)  # held open (an EOF would end the client's reader before its upgrade is queued)

    connect = ClientProtocol.connect

    def late(self):  # the upgrade made only once the reader thread has read the refusal
        request = connect(self)
        for _ in range(2000):
            if self.handshake_exc is not None:
                break
            threading.Event().wait(0.001)
        return request

    close_socket = ClientConnection.close_socket

    def closed_first(self):  # and the socket closed before the reader thread is woken (it raced its last write)
        self.socket.close()
        close_socket(self)

    monkeypatch.setattr(ClientProtocol, "connect", late)
    monkeypatch.setattr(ClientConnection, "close_socket", closed_first)
    caplog.set_level(logging.DEBUG, logger="websockets")
    thread = threading.Thread(target=refuse_at_accept, daemon=True)
    thread.start()
    try:
        with pytest.raises(Busy) as err:
            Client(f"http://127.0.0.1:{server.getsockname()[1]}", max_retry_after=1).session(chain()[0])
    finally:
        done.set()
        thread.join(5)
        server.close()
    assert err.value.retry_after == 5 and "JOINTLIMITS_MAX_CONNECTIONS" in err.value.msg
    assert not [(r.getMessage(), r.exc_info) for r in caplog.records if r.levelno >= logging.WARNING]
