"""A session call interrupted between its message and the reply (an asyncio cancellation, a timeout around the
call, Ctrl-C) must not leave that reply on the connection: the next call would read it as its own and return the
numbers of the interrupted call's `q` (silently wrong, found by the audit of issue 28's client refactor; the
same at 004f4f9). The connection is given up instead; the next call reopens in the committed state (`resume`)."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest

from jointlimits.client import AsyncClient, Client, LocalClient, SessionClosed
from tests.sdk.test_session_resume import replica
from tests.sdk.test_sessions_live import chain, same


class Held:
    """A session's connection whose replies are awaited only after `waiting` is set and a pause, so that the
    interruption lands while the message has left and its reply is on its way."""

    def __init__(self, ws, waiting) -> None:
        self.ws, self.waiting = ws, waiting

    def __getattr__(self, name):
        return getattr(self.ws, name)


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
            same(await s.evaluate(q), ref.evaluate(q))  # was the interrupted call's answer (x of `a`)
            assert (await s.commit(q))[0].tobytes() == ref.commit(q)[0].tobytes()
        await s.close()

    with replica() as (_, port), LocalClient().session(req) as ref:
        asyncio.run(run(port, ref))


def test_a_blocking_evaluate_interrupted_by_ctrl_c_leaves_no_reply_for_the_next_call():
    req, pose = chain(2)
    q = req.q.copy()
    with replica() as (_, port), LocalClient().session(req) as ref:
        s = Client(f"http://127.0.0.1:{port}").session(req)
        held = Held(s._ws, threading.Event())

        def recv(timeout=None):  # the message has left; Ctrl-C arrives before its reply is read (once)
            if held.waiting.is_set():
                return held.ws.recv(timeout=timeout)
            held.waiting.set()
            raise KeyboardInterrupt

        held.recv = recv
        s._ws = held
        q[2] = pose(0.6)
        with pytest.raises(KeyboardInterrupt):
            s.evaluate(q)
        q[2] = pose(0.9)
        same(s.evaluate(q), ref.evaluate(q))
        assert s.commit(q)[0].tobytes() == ref.commit(q)[0].tobytes()
        s.close()


def test_without_resume_an_interrupted_session_says_it_is_closed():
    """No silent answer either way: without `resume`, the call after the interruption raises `SessionClosed`,
    and `reopen()` continues from the last commit."""
    req, pose = chain(2)
    q = req.q.copy()
    with replica() as (_, port), LocalClient().session(req) as ref:
        s = Client(f"http://127.0.0.1:{port}").session(req, resume=False)
        held = Held(s._ws, threading.Event())

        def recv(timeout=None):
            if held.waiting.is_set():
                return held.ws.recv(timeout=timeout)
            held.waiting.set()
            raise KeyboardInterrupt

        held.recv = recv
        s._ws = held
        with pytest.raises(KeyboardInterrupt):
            s.evaluate(q)
        with pytest.raises(SessionClosed):
            s.evaluate(q)
        s.reopen()
        q[2] = pose(0.2)
        same(s.evaluate(q), ref.evaluate(q))
        assert np.array_equal(s.commit(q)[0], ref.commit(q)[0])
        s.close()
