"""Sessions through the SDK against a real uvicorn on 127.0.0.1: the same numbers as POST /v1/evaluate and the
in-process modes (bitwise, golden cases), async, auth, bounds as `SessionClosed`, and reopening after a drop."""

from __future__ import annotations

import asyncio
import socket
import time

import numpy as np
import pytest

from jointlimits.client import AsyncClient, Client, InvalidInput, JointBatch, LocalClient, ServiceError, SessionClosed, request_from_arrays
from jointlimits.schemas import binary as wire
from jointlimits.schemas import session as proto
from jointlimits.service.settings import Settings
from tests.conftest import GOLDEN, same_evaluation
from tests.http.test_contract_live import sdk_request, serve

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # sessions over real WebSockets, the idle timer's waits (~22 s)


@pytest.fixture(scope="module")
def live():
    with serve() as url:
        yield url


@pytest.mark.parametrize("binary", [True, False], ids=["msgpack", "json"])
def test_golden_cases_are_bitwise_the_same_by_session_http_and_local(live, binary):
    client, local = Client(live, binary=binary), LocalClient()
    for case in GOLDEN:
        req = sdk_request(case["request"])
        want = client.evaluate(req)
        same_evaluation(local.evaluate(req), want)
        with client.session(req) as s, local.session(req) as ls:
            same_evaluation(s.evaluate(req.q), want)
            same_evaluation(ls.evaluate(req.q), want)
            # Another mode than the opening request's, per call.
            for kw in ({"hessian_mode": "psd"}, {"outputs": ("energy",), "active_only": True}):
                other = client.evaluate(type(req)(**{**req.__dict__, **kw}))
                same_evaluation(s.evaluate(req.q, **kw), other)
                same_evaluation(ls.evaluate(req.q, **kw), other)


def test_v1_1_state_cases_are_bitwise_the_same_by_session_and_http(live):
    """The 50-digit state cases (offset, prev_coordinate): a session opened with them answers as HTTP does."""
    from tests.core.test_golden_state import CASES, _sdk_request

    for binary in (True, False):
        client = Client(live, binary=binary)
        for case in CASES:
            req = _sdk_request(case["request"])
            want = client.evaluate(req)
            with client.session(req) as s, LocalClient().session(req) as ls:
                same_evaluation(s.evaluate(req.q), want)
                same_evaluation(ls.evaluate(req.q), want)
                # The opened coordinates are the state at q_prev: prev_coordinate where it is given, kept as
                # (prev_coordinate - offset) + offset, so within one rounding of each (an ulp of the larger).
                for b, coords in zip(req.batches, s.coordinates):
                    if b.prev_coordinate is not None:
                        p = np.asarray(b.prev_coordinate, dtype=np.float64)
                        o = np.zeros_like(p) if b.offset is None else np.asarray(b.offset, dtype=np.float64)
                        assert np.all(np.abs(coords - p) <= 2.3e-16 * (np.abs(p) + 2 * np.abs(o)))


def chain(n: int = 4, turn: float = 0.7):
    """`n` revolute joints about z between consecutive bodies, body k turned by k * turn; limits +-0.5."""
    def pose(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([0, 0, 0, c, -s, 0, s, c, 0, 0, 0, 1.0])
    q = np.array([pose(k * turn) for k in range(n + 1)])
    ref = np.array([pose(0.0)] * (n + 1))
    ids = [[k, k + 1] for k in range(n)]
    edges = [[[0, 0, 0], [0, 0, 1]]] * n
    return request_from_arrays(q, [JointBatch.of(670, ids, edges, -0.5, 0.5, 10.0)], q_prev=ref, q_ref=ref), pose


def test_async_session_has_the_same_numbers(live):
    req, _ = chain()
    want = Client(live).evaluate(req)

    async def run():
        async with AsyncClient(live).session(req) as s:
            same_evaluation(await s.evaluate(req.q), want)
            coords = await s.commit(req.q)
            with pytest.raises(InvalidInput) as e:
                await s.evaluate(req.q[:2])
            assert e.value.loc == ("body", "q")
            await s.update(0, [1], upper=[2.0])
            return coords, await s.evaluate(req.q, outputs=("energy",))
        
    coords, after = asyncio.run(run())
    np.testing.assert_allclose(coords[0], want.batches[0].x, rtol=1e-14)
    with LocalClient().session(req) as ls:
        ls.commit(req.q)
        ls.update(0, [1], upper=[2.0])
        same_evaluation(after, ls.evaluate(req.q, outputs=("energy",)))

    async def awaited():
        s = await AsyncClient(live).session(req)
        try:
            return await s.evaluate(req.q)
        finally:
            await s.close()

    same_evaluation(asyncio.run(awaited()), want)


def test_the_bearer_token_on_the_upgrade():
    req, _ = chain()
    with serve(Settings(max_body_bytes=2_000_000, max_joints=400, token="s3cret", cors_origins=())) as url:
        with pytest.raises(ServiceError) as e:
            Client(url).session(req)
        assert e.value.status == 401 and not isinstance(e.value, SessionClosed)
        with Client(url, token="s3cret").session(req) as s:
            assert s.evaluate(req.q).total_energy > 0


def test_a_full_worker_is_waited_for_then_the_session_opens():
    """4429 (the worker holds its maximum of sessions) means "retry later": with `resume` (the default) the opening
    is tried again after `backoff`, doubling, and lands once a slot is free; with `resume=False` it raises at once."""
    import threading

    req, _ = chain()
    settings = Settings(max_body_bytes=2_000_000, max_joints=20, token=None, cors_origins=(), max_sessions=1)
    with serve(settings) as url:
        client = Client(url, retries=6, backoff=0.05)
        first = client.session(req)
        t0 = time.monotonic()
        with pytest.raises(SessionClosed) as e:
            client.session(req, resume=False)
        assert e.value.code == proto.TOO_MANY_SESSIONS and time.monotonic() - t0 < 1.0
        threading.Timer(0.3, first.close).start()  # a slot frees while the second one waits
        with client.session(req) as second:
            assert time.monotonic() - t0 >= 0.3
            assert second.evaluate(req.q).total_energy == pytest.approx(LocalClient().evaluate(req).total_energy, rel=1e-15)


def test_bounds_close_the_session_with_their_code():
    req, _ = chain()
    big, _ = chain(50)
    settings = Settings(max_body_bytes=2_000_000, max_joints=20, token=None, cors_origins=(), max_sessions=1,
                        max_frame_bytes=20_000)
    with serve(settings) as url:
        client = Client(url)
        with client.session(req) as s:
            with pytest.raises(SessionClosed) as e:
                client.session(req)
            assert e.value.code == proto.TOO_MANY_SESSIONS and url.replace("http", "ws") in str(e.value)
            assert s.evaluate(req.q).total_energy > 0  # the first one is unaffected
        with pytest.raises(ServiceError) as e:
            client.session(big)  # 50 joints > 20: a 413 fault, then the close
        assert e.value.status == 413
        with client.session(req) as s:
            with pytest.raises(SessionClosed) as e:
                s.evaluate(np.zeros((300, 12)))  # 28.8 kB > 20 kB
            assert e.value.code == proto.MESSAGE_TOO_BIG


def test_a_client_that_disappears_is_closed_by_the_idle_timer_and_reopens():
    req, pose = chain()
    settings = Settings(max_body_bytes=2_000_000, max_joints=400, token=None, cors_origins=(), session_idle_seconds=0.5)
    with serve(settings) as url:
        s = Client(url).session(req)
        q = req.q.copy()
        q[2] = pose(0.8)
        s.commit(q)
        time.sleep(1.5)
        with pytest.raises(SessionClosed) as e:
            s.evaluate(q)
        assert e.value.code == proto.IDLE_TIMEOUT and "ws://127.0.0.1" in str(e.value)
        s.reopen()
        with Client(url).session(req) as ref:
            ref.commit(q)
            same_evaluation(s.evaluate(q), ref.evaluate(q))
        s.close()


def test_reopening_after_a_dropped_connection_loses_nothing(live):
    """Steps past a half turn, a drop, a reopen: the same numbers as a session that never dropped."""
    req, pose = chain(2)
    q = req.q.copy()
    with Client(live).session(req, resume=False) as s, LocalClient().session(req) as ref:  # resumed: test_session_resume.py
        for k in range(1, 9):  # body 2 turns 0.5 rad per step to 4 rad: 3.3 rad from body 1, past pi
            q[2] = pose(0.5 * k)
            assert s.commit(q)[0].tobytes() == ref.commit(q)[0].tobytes()
        s.update(0, [1], upper=[3.0])
        ref.update(0, [1], upper=[3.0])
        s._ws.socket.shutdown(socket.SHUT_RDWR)  # the network drops the connection
        with pytest.raises(SessionClosed) as e:
            s.evaluate(q)
        assert e.value.url == s.url
        s.reopen()
        assert np.array_equal(s.q_prev, q)
        q[2] = pose(4.2)
        same_evaluation(s.evaluate(q), ref.evaluate(q))
        assert s.commit(q)[0].tobytes() == ref.commit(q)[0].tobytes()
        # The committed angle is the true one (past pi), not its wrapped value.
        assert abs(s.coordinates[0][1] - 3.5) < 1e-12


def test_jointlimits_serve_passes_the_session_bounds():
    """`jointlimits serve --max-frame-bytes --max-sessions --session-idle-seconds` reach every worker; uvicorn's own
    message limit (`ws_max_size`, set from --max-frame-bytes) closes with 1009 too."""
    from tests.drills import LOOPBACK, Server
    from tests.http.test_cli import console_script

    req, _ = chain()
    server = Server(workers=1, command=console_script(),
                    extra_args=["--max-frame-bytes", "20000", "--max-sessions", "1", "--session-idle-seconds", "30"])
    with server:
        client = Client(f"http://{LOOPBACK}:{server.port}")
        with client.session(req) as s:
            assert s.evaluate(req.q).total_energy > 0
            with pytest.raises(SessionClosed) as e:
                client.session(req)
            assert e.value.code == proto.TOO_MANY_SESSIONS
            with pytest.raises(SessionClosed) as e:
                s.evaluate(np.zeros((300, 12)))
            assert e.value.code == proto.MESSAGE_TOO_BIG


def test_async_session_reopens_after_a_drop(live):
    req, pose = chain(2)
    q = req.q.copy()

    async def run():
        async with AsyncClient(live).session(req, resume=False) as s:
            for k in range(1, 9):
                q[2] = pose(0.5 * k)
                await s.commit(q)
            await s._ws.close(1001)  # the connection ends under the session
            with pytest.raises(SessionClosed) as e:
                await s.evaluate(q)
            assert e.value.url == s.url
            await s.reopen()
            q[2] = pose(4.2)
            return await s.evaluate(q), await s.commit(q)

    got, coords = asyncio.run(run())
    with LocalClient().session(req) as ref:
        for k in range(1, 9):
            q[2] = pose(0.5 * k)
            ref.commit(q)
        q[2] = pose(4.2)
        same_evaluation(got, ref.evaluate(q))
        assert coords[0].tobytes() == ref.commit(q)[0].tobytes()


def test_a_client_that_stops_reading_is_dropped_and_frees_its_place(monkeypatch):
    """Replies pile up unread (the server's send waits on a full buffer): JOINTLIMITS_WRITE_TIMEOUT after they
    stopped leaving, the connection is dropped (issue 19: the write side is bounded, at the depth of the
    protocol that `jointlimits serve` runs) and the worker's only place is free again, whatever the client does."""
    import httpx
    from websockets.sync.client import connect

    from jointlimits.client.codec import encode

    monkeypatch.setenv("JOINTLIMITS_WRITE_TIMEOUT", "2")  # read by the WebSocket protocol per connection
    req, _ = chain(2000)  # E+G+H of 2000 joints, all outside: ~9 MB per answer
    settings = Settings(max_body_bytes=2_000_000, max_joints=4000, token=None, cors_origins=(), max_sessions=1,
                        session_idle_seconds=300.0)
    with serve(settings) as url:
        ws_url = url.replace("http", "ws") + proto.PATH
        # max_queue=1: the client library stops reading from the socket after one unread message.
        with connect(ws_url, max_size=None, max_queue=1, compression=None) as ws:
            ws.send(encode(req, True)[0])
            frame = {"kind": "evaluate", "q": wire.pack_array(req.q, wire.FLOAT64)}
            for _ in range(6):
                ws.send(wire.dumps(frame))
            deadline = time.monotonic() + 30  # the write timeout (2 s) once the buffer is full, not the idle time (300 s)
            while 'jointlimits_sessions_total{reason="disconnect"} 1.0' not in (m := httpx.get(url + "/metrics").text):
                assert time.monotonic() < deadline, m
                time.sleep(0.2)
            assert "jointlimits_sessions_open 0.0" in m
        with Client(url).session(chain()[0]) as s:  # the worker's only place is free
            assert s.evaluate(chain()[0].q).total_energy > 0


def test_sessions_take_what_evaluate_takes_and_answer_per_joint(live):
    """A session opens from wire JSON as a dict too, and its answers know their batch sizes: `joint(k)` reads an
    inactive joint as zeros under active_only, as `Client.evaluate`'s answers do."""
    body = GOLDEN[0]["request"]
    want = Client(live).evaluate(body)
    for client in (Client(live), Client(live, binary=False), LocalClient()):
        with client.session(body) as s:
            q = np.asarray(body["bodies"]["q"], dtype=np.float64)
            same_evaluation(s.evaluate(q), want)
            ev = s.evaluate(q, active_only=True)
            for r, w in zip(ev.batches, want.batches):
                assert r.size == w.size == len(w.x)
                for k in range(r.size):
                    assert r.joint(k).energy == w.joint(k).energy
