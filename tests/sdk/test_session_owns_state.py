"""What a session owns. Its committed state (`s.q_prev`, `s.coordinates`) is the session's own: what `commit` returns is the
caller's to change, and changing it does not change what a reopen (or a resume after a drop) starts from.

Before, `commit` returned the very arrays the session kept for reopening: a solver that reused them as scratch
(`coords[0][:] = 0`) silently moved every revolute angle of the reopened session by its committed turns (a joint
at 3.28 rad read 0.28 after `reopen()`, no error). The state is shared by the three sessions (`SessionState`), so
the local session shows it; `live` checks the WebSocket one too.

And its connection: a blocking session dropped without `close()` (a notebook cell run again, `s = client.session(...)`)
kept its socket, its two threads and its place among the server's sessions (64 a worker) until the process ended;
an asyncio session so dropped kept them until its event loop ended.
"""

from __future__ import annotations

import asyncio
import gc

import numpy as np
import pytest
from websockets.protocol import State

from jointlimits.client import AsyncClient, Client, LocalClient, Scene
from tests.http.test_contract_live import live  # noqa: F401 (fixture)


def _turned(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0])


def _x_after_reopen(client, scratch: bool) -> np.ndarray:
    """Commit a hinge at 3 rad (past pi), optionally scribble on what commit returned, reopen, read x at -3 rad."""
    scene = Scene()
    a, b = scene.add_body(np.eye(4)), scene.add_body(np.eye(4))
    scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5)
    with client.session(scene.request()) as s:
        q = s.q_prev.copy()
        q[1, 3:] = _turned(3.0)
        coords = s.commit(q)
        if scratch:
            coords[0][:] = 0.0  # the caller's array: its own to reuse
            with pytest.raises(ValueError):  # the session's own state is read-only, not silently changed
                s.q_prev[0, 0] = 1.0
            with pytest.raises(ValueError):
                s.coordinates[0][0] = 1.0
        q[1, 3:] = _turned(-3.0)
        s.reopen()
        return s.evaluate(q).batches[0].x


@pytest.mark.parametrize("where", ["local", "live"])
def test_what_commit_returns_is_the_callers_and_reopen_keeps_the_committed_angle(where, request):
    client = LocalClient() if where == "local" else Client(request.getfixturevalue("live"))
    x = _x_after_reopen(client, scratch=True)
    # 3 rad committed, then -3 rad: 2 pi - 6 rad further on, so x = 2 pi - 3 (no wrap: the committed angle counts).
    # Both readings are of the same q through the same arithmetic, so they agree to the bit.
    assert np.array_equal(x, _x_after_reopen(client, scratch=False))
    assert abs(x[0] - (2 * np.pi - 3.0)) < 1e-12


def test_a_session_dropped_without_close_closes_its_connection(live):  # noqa: F811
    scene = Scene()
    a, b = scene.add_body(np.eye(4)), scene.add_body(np.eye(4))
    scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5)
    s = Client(live).session(scene.request())
    s.evaluate(scene.request().q)
    ws = s._ws  # the connection, held here only to look at it
    # Its own threads (not the process's count: other tests' threads come and go in the same process).
    threads = [t for t in (ws.recv_events_thread, ws.keepalive_thread) if t is not None]
    assert ws.state is State.OPEN and all(t.is_alive() for t in threads)
    del s
    gc.collect()
    for t in threads:
        t.join(timeout=5.0)  # they end once the close handshake is done (milliseconds here)
    assert ws.state is State.CLOSED and ws.close_code == 1000  # closed as close() does, not cut
    assert not any(t.is_alive() for t in threads)


def test_an_async_session_dropped_without_close_closes_its_connection(live):  # noqa: F811
    scene = Scene()
    a, b = scene.add_body(np.eye(4)), scene.add_body(np.eye(4))
    scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5)

    async def drop() -> None:
        s = await AsyncClient(live).session(scene.request())
        await s.evaluate(scene.request().q)
        ws = s._ws  # the connection, held here only to look at it
        assert ws.state is State.OPEN
        del s
        gc.collect()
        for _ in range(100):  # the close handshake runs on the loop: milliseconds here, 5 s at most
            if ws.state is State.CLOSED:
                break
            await asyncio.sleep(0.05)
        assert ws.state is State.CLOSED and ws.close_code == 1000  # closed as close() does, not cut

    asyncio.run(drop())
