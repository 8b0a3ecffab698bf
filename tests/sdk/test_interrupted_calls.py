"""Calls that end early leave nothing behind (found by the audit of issue 28's client refactor; the same at 004f4f9).

- A session call interrupted between its message and the reply (an asyncio cancellation, a timeout around the
  call, Ctrl-C) must not leave that reply on the connection: the next call would read it as its own and return the
  numbers of the interrupted call's `q`, silently. The connection is given up instead; the next call reopens in
  the committed state (`resume`).
- `AsyncClient.evaluate` of a split request that fails (a part refused, a `progress` callback raising) sends no
  part after it has raised, as `Client.evaluate` stops at the failing part.
"""

from __future__ import annotations

import asyncio
import threading

import httpx
import numpy as np
import pytest

from jointlimits.client import AsyncClient, Client, LocalClient, SessionClosed
from tests.conftest import same_evaluation
from tests.http.test_contract_live import serve
from tests.sdk.test_session_resume import replica
from tests.sdk.test_sessions_live import chain


class Held:
    """A session's connection whose replies are awaited only after `waiting` is set and a pause, so that the
    interruption lands while the message has left and its reply is on its way."""

    def __init__(self, ws, waiting) -> None:
        self.ws, self.waiting = ws, waiting

    def __getattr__(self, name):
        return getattr(self.ws, name)


def interrupt_next_reply(s) -> None:
    """Blocking session `s`'s next call sends its message, then Ctrl-C arrives before its reply is read (once)."""
    held = Held(s._ws, threading.Event())

    def recv(timeout=None):
        if held.waiting.is_set():
            return held.ws.recv(timeout=timeout)
        held.waiting.set()
        raise KeyboardInterrupt

    held.recv = recv
    s._ws = held


def test_a_cancelled_async_evaluate_leaves_no_reply_for_the_next_call():
    req, pose = chain(2)
    q = req.q.copy()

    async def run(port: int, ref) -> None:
        s = await AsyncClient(f"http://127.0.0.1:{port}").session(req)
        for a in (0.4, 1.1):  # each time the cancelled call's reply is due: never read as the next call's
            held = Held(s._ws, asyncio.Event())

            async def recv(held=held):
                held.waiting.set()
                await asyncio.sleep(0.05)  # the reply arrives meanwhile
                return await held.ws.recv()

            held.recv = recv
            s._ws = held
            q[2] = pose(a)
            call = asyncio.create_task(s.evaluate(q))
            await held.waiting.wait()
            call.cancel()
            with pytest.raises(asyncio.CancelledError):
                await call
            q[2] = pose(a + 0.3)
            same_evaluation(await s.evaluate(q), ref.evaluate(q))  # was the interrupted call's answer (x of `a`)
            assert (await s.commit(q))[0].tobytes() == ref.commit(q)[0].tobytes()
        await s.close()

    with replica() as (_, port), LocalClient().session(req) as ref:
        asyncio.run(run(port, ref))


def test_a_blocking_evaluate_interrupted_by_ctrl_c_leaves_no_reply_for_the_next_call():
    req, pose = chain(2)
    q = req.q.copy()
    with replica() as (_, port), LocalClient().session(req) as ref:
        s = Client(f"http://127.0.0.1:{port}").session(req)
        interrupt_next_reply(s)
        q[2] = pose(0.6)
        with pytest.raises(KeyboardInterrupt):
            s.evaluate(q)
        q[2] = pose(0.9)
        same_evaluation(s.evaluate(q), ref.evaluate(q))
        assert s.commit(q)[0].tobytes() == ref.commit(q)[0].tobytes()
        s.close()


def test_without_resume_an_interrupted_session_says_it_is_closed():
    """No silent answer either way: without `resume`, the call after the interruption raises `SessionClosed`,
    and `reopen()` continues from the last commit."""
    req, pose = chain(2)
    q = req.q.copy()
    with replica() as (_, port), LocalClient().session(req) as ref:
        s = Client(f"http://127.0.0.1:{port}").session(req, resume=False)
        interrupt_next_reply(s)
        with pytest.raises(KeyboardInterrupt):
            s.evaluate(q)
        with pytest.raises(SessionClosed, match=r"dropped \(a lost connection, or a call interrupted .* resume off"):
            s.evaluate(q)
        s.reopen()
        q[2] = pose(0.2)
        same_evaluation(s.evaluate(q), ref.evaluate(q))
        assert np.array_equal(s.commit(q)[0], ref.commit(q)[0])
        s.close()
        ref.close()
        for closed in (s, ref):  # what happened, in its words: a close is not a drop
            with pytest.raises(SessionClosed, match=r"closed by close\(\); reopen\(\) continues"):
                closed.evaluate(q)


class Counted(httpx.AsyncHTTPTransport):
    """Counts the evaluate requests sent through it (each counted when it starts)."""

    def __init__(self) -> None:
        super().__init__()
        self.sent = 0

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        self.sent += request.url.path == "/v1/evaluate"
        return await super().handle_async_request(request)


def test_an_async_split_evaluate_sends_nothing_after_it_raised():
    """A progress callback that raises at the first part's answer: `evaluate` raises its error, and the parts
    not yet answered are cancelled, not sent on in the background (8 parts, 2 at a time; before, every part was
    sent, 4 or 5 of them after `evaluate` had raised)."""
    req, _ = chain(40)
    sent_after = []

    def fails(done: int, total: int) -> None:
        raise RuntimeError("the caller's progress callback failed")

    async def run(url: str) -> None:
        counted = Counted()
        async with AsyncClient(url, max_joints_per_request=5, concurrency=2, progress=fails,
                               http_transport=counted) as client:
            with pytest.raises(RuntimeError, match="progress callback failed"):
                await client.evaluate(req)
            at_raise = counted.sent
            await asyncio.sleep(0.5)  # a part still running would be sent meanwhile
            sent_after.append(counted.sent - at_raise)
            assert counted.sent < 8  # not every part

    with serve() as url:
        asyncio.run(run(url))
    assert sent_after == [0]
