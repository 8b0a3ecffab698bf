"""A worker's memory budgets (service/http/budget.py): what its requests in flight hold together.

Before them, every request was admitted on its own cost alone: at the manifest's limits
(deploy/deployment.yaml) four concurrent requests at the body bound took a worker to 1470 MiB
and four at the answer bound to 1037 MiB, against the 939 MiB per worker the pod was sized for.
Here: the budget's queue and its bookkeeping, the sizes it charges, that every reservation is
given back whatever the request's fate, the 503 `busy` answers, and the probe itself on a real
server.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time

import httpx
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import codec
from jointlimits.service import sizing
from jointlimits.service.app import create_app
from jointlimits.service.http.budget import Budget
from jointlimits.service.http.errors import HttpError
from jointlimits.service.settings import Settings
from tests import drills as lt

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # concurrent requests at the limits (~10 s)

J, B = "application/json", "application/msgpack"
DEPLOY = {  # deploy/deployment.yaml's limits (tests/ops/test_deploy.py keeps the manifest to the sizing rule)
    "JOINTLIMITS_MAX_BODY_BYTES": str(64 * 2**20),
    "JOINTLIMITS_MAX_JOINTS": "250000",
    "JOINTLIMITS_MAX_ANSWER_BYTES": str(128 * 2**20),
    "JOINTLIMITS_MAX_JSON_VALUES": "2000000",
    "JOINTLIMITS_MAX_SESSION_JOINTS": "50000",
}


def run(coro):  # noqa: ANN001, ANN201
    return asyncio.run(coro)


# ------------------------------------------------------------------ the budget's queue


def test_waiters_start_in_arrival_order_as_bytes_are_given_back():
    async def go() -> list[str]:
        b = Budget(10)
        first = await b.acquire(6, 1.0)
        order: list[str] = []

        async def wait(name: str, size: int) -> None:
            r = await b.acquire(size, 5.0)
            order.append(name)
            await asyncio.sleep(0.01)
            r.release()

        big = asyncio.create_task(wait("big", 8))
        await asyncio.sleep(0.01)
        assert b.queued == 1 and b.held == 6
        small = asyncio.create_task(wait("small", 3))  # 6 + 8 + 3 > 10: it queues behind the big one
        await asyncio.sleep(0.01)
        assert b.queued == 2 and order == []
        first.release()
        await asyncio.gather(big, small)
        assert b.held == 0 and b.queued == 0
        return order

    assert run(go()) == ["big", "small"]


def test_a_small_arrival_that_fits_passes_the_waiters():
    async def go() -> None:
        b = Budget(16)  # small: at most 16 / SMALL_SHARE = 1
        running = await b.acquire(10, 1.0)
        big = asyncio.create_task(b.acquire(8, 5.0))  # 10 + 8 > 16: waits
        await asyncio.sleep(0.01)
        assert not big.done() and b.queued == 1
        tiny = await asyncio.wait_for(b.acquire(1, 5.0), 0.5)  # small and fits: starts at once
        mid = asyncio.create_task(b.acquire(3, 5.0))  # fits, but not small: behind the big one
        await asyncio.sleep(0.01)
        assert not mid.done() and b.queued == 2 and b.held == 11
        running.release()
        (await big).release()
        (await mid).release()
        tiny.release()
        assert b.held == 0 and b.queued == 0

    run(go())


def test_a_waiter_past_its_timeout_is_busy_and_leaves_the_queue():
    async def go() -> None:
        b = Budget(10)
        held = await b.acquire(9, 1.0)
        t = time.monotonic()
        with pytest.raises(HttpError, match="JOINTLIMITS_QUEUE_TIMEOUT"):
            await b.acquire(5, 0.05)
        assert 0.04 < time.monotonic() - t < 1.0
        assert b.queued == 0 and b.held == 9
        held.release()
        assert b.held == 0

    run(go())


def test_the_first_waiter_giving_up_wakes_the_next():
    async def go() -> None:
        b = Budget(10)
        held = await b.acquire(6, 1.0)
        first = asyncio.create_task(b.acquire(8, 0.05))  # will time out
        await asyncio.sleep(0.005)
        second = asyncio.create_task(b.acquire(4, 5.0))  # 6 + 8 + 4 > 10: queued behind `first`
        await asyncio.sleep(0.005)
        assert b.queued == 2
        with pytest.raises(HttpError, match="JOINTLIMITS_QUEUE_TIMEOUT"):
            await first
        r = await asyncio.wait_for(second, 1.0)  # 6 + 4 fits once `first` has left
        assert b.held == 10
        r.release()
        held.release()

    run(go())


def test_shrink_and_release_from_another_thread_wake_the_waiters():
    async def go() -> None:
        b = Budget(10)
        r = await b.acquire(8, 1.0)
        waiter = asyncio.create_task(b.acquire(5, 5.0))
        await asyncio.sleep(0.01)
        t = threading.Thread(target=r.shrink, args=(3,))  # what the route does in its worker thread
        t.start()
        t.join()
        w = await asyncio.wait_for(waiter, 1.0)
        assert b.held == 8 and r.size == 3
        r.shrink(7)  # never grows
        assert r.size == 3 and b.held == 8
        threading.Thread(target=r.release).start()
        w.release()
        await asyncio.sleep(0.01)
        r.release()  # idempotent
        assert b.held == 0

    run(go())


def test_a_request_cancelled_as_it_is_granted_gives_the_bytes_back():
    async def go() -> None:
        b = Budget(10)
        r = await b.acquire(10, 1.0)
        waiter = asyncio.create_task(b.acquire(4, 5.0))
        await asyncio.sleep(0.01)
        r.release()  # grants the waiter (its wake-up is scheduled) ...
        waiter.cancel()  # ... and its client leaves before it runs
        try:  # Python 3.11's wait_for returns a result that arrived with the cancellation
            got = await waiter
        except asyncio.CancelledError:
            got = None
        if got is not None:
            assert b.held == 4
            got.release()  # what ReleaseMiddleware does after the route
        assert b.held == 0 and b.queued == 0
        # Cancelled while still waiting: it leaves the queue, holding nothing.
        r = await b.acquire(10, 1.0)
        waiter = asyncio.create_task(b.acquire(4, 5.0))
        await asyncio.sleep(0.01)
        waiter.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiter
        assert b.queued == 0 and b.held == 10
        r.release()
        assert b.held == 0

    run(go())


def test_sizes_beyond_the_capacity_run_alone_and_uploads_never_wait():
    async def go() -> None:
        b = Budget(10)
        r = await b.acquire(10**9, 1.0)
        assert r.size == 10 and b.held == 10
        r.release()
        up = b.reserve_now()
        assert up.try_grow(7) and not up.try_grow(4) and up.size == 7
        up.release()
        assert not up.try_grow(1) and b.held == 0  # a released reservation holds nothing again

    run(go())


# ------------------------------------------------------------------ what a request is charged


@pytest.mark.parametrize("case", sorted(lt.peak_cases()))
def test_a_request_is_charged_within_the_budget_and_its_parsed_cost_within_its_first_bound(case):
    """For the largest request of each limit: the bound from its size alone covers what it holds once
    parsed, and both fit in the in-flight budget, which the sizing rule counts."""
    s = Settings()
    body, content_type, accept, joints = lt.peak_cases()[case]()
    binary_request, binary_answer = content_type == B, accept == B
    first = sizing.cost_before_body(len(body), binary_request, binary_answer, s)
    if binary_request:
        from jointlimits.service.http import binary

        kwargs = binary.decode(body, max_batches=s.max_batches)
        values = None
    else:
        from jointlimits.service.http import convert, document

        checker = document.Checker(binary=False)
        kwargs = convert.decode(body, s.max_json_values, s.max_batches, checker=checker)
        values = checker.values
    batch_joints = [len(j.body_ids) for j in kwargs["batches"]]
    parsed = sizing.request_cost(
        len(body), values, batch_joints, kwargs["bodies"].q.shape[0], kwargs["outputs"], binary_answer, s
    )
    assert 0 < parsed <= first <= sizing.inflight_bytes(s)
    assert sum(batch_joints) == joints


def test_the_sizing_rule_counts_both_budgets():
    s = Settings()
    assert sizing.worker_bytes(s) == (
        sizing.WORKER_BASE_BYTES
        + sizing.CONNECTION_BYTES * s.max_connections
        + sizing.upload_bytes(s)
        + sizing.inflight_bytes(s)
        + sizing.SESSION_BYTES_PER_JOINT * s.max_session_joints
    )
    assert sizing.WORKER_BASE_BYTES + sizing.CONNECTION_BYTES * s.max_connections == 96 * 2**20  # as before the cap
    assert sizing.upload_bytes(s) == 2 * s.max_body_bytes  # one body at the limit, chunks and joined copy
    assert sizing.upload_bytes(Settings(max_body_bytes=2**20)) == sizing.UPLOAD_FLOOR


# ------------------------------------------------------------------ every reservation given back


def _client(**settings) -> TestClient:
    return TestClient(create_app(Settings(**{"token": None, "cors_origins": (), **settings})))


def _soon(ok, seconds: float = 5.0) -> bool:  # noqa: ANN001
    """`ok()` becomes true within `seconds` (the server gives a session's share back just after its reply)."""
    deadline = time.monotonic() + seconds
    while not ok():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def _budgets_free(c: TestClient) -> bool:
    state = c.app.state
    return state.uploads.held == 0 and state.in_flight.held == 0 and state.in_flight.queued == 0


def test_every_answer_gives_its_reservations_back():
    c = _client(max_joints=50)
    ok = lt.scene(4)
    cases = [
        ("200", orjson_bytes(ok), J, 200),
        ("422 broken JSON", b'{"bodies": ', J, 422),
        ("422 lower > upper", orjson_bytes(_bad_range(ok)), J, 422),
        ("413 joints", orjson_bytes(lt.scene(60)), J, 413),
        ("415", b"x", "text/plain", 415),
        ("200 msgpack", codec.encode(lt.array_scene(3), True)[0], B, 200),
    ]
    for name, body, content_type, status in cases:
        r = c.post("/v1/evaluate", content=body, headers={"Content-Type": content_type})
        assert r.status_code == status, (name, r.text[:200])
        assert _budgets_free(c), name
    metrics = c.get("/metrics").text
    assert "jointlimits_inflight_budget_bytes 0.0" in metrics and "jointlimits_upload_budget_bytes 0.0" in metrics


def test_a_body_over_the_upload_budget_is_drained_and_503_busy():
    # Bodies being received hold all but 1000 bytes of the upload budget: the next body is refused as
    # its chunk arrives.
    c = _client(max_body_bytes=2**20)
    held = c.app.state.uploads.reserve_now()
    assert held.try_grow(c.app.state.uploads.capacity - 1000)
    r = c.post("/v1/evaluate", content=orjson_bytes(lt.scene(4)), headers={"Content-Type": J})
    assert r.status_code == 503
    item = r.json()["detail"][0]
    assert item["type"] == "busy" and item["loc"] == ["body"]
    assert "upload budget" in item["msg"] and "nothing was evaluated" in item["msg"]
    assert r.headers["retry-after"] == "5" and "connection" not in r.headers  # drained: keep-alive
    held.release()
    assert _budgets_free(c)
    assert c.post("/v1/evaluate", content=orjson_bytes(lt.scene(4)), headers={"Content-Type": J}).status_code == 200


def test_a_request_that_waits_past_the_queue_timeout_is_503_busy():
    c = _client(queue_timeout=0.2)
    budget = c.app.state.in_flight
    hog = asyncio.run(budget.acquire(budget.capacity, 1.0))  # every byte held by a request in flight
    t = time.monotonic()
    r = c.post("/v1/evaluate", content=orjson_bytes(lt.scene(4)), headers={"Content-Type": J})
    waited = time.monotonic() - t
    assert r.status_code == 503 and 0.15 < waited < 5.0
    item = r.json()["detail"][0]
    assert item["type"] == "busy" and "JOINTLIMITS_QUEUE_TIMEOUT" in item["msg"] and "0.2 s" in item["msg"]
    assert r.headers["retry-after"] == "5" and "connection" not in r.headers  # its body was read: keep-alive
    hog.release()
    assert _budgets_free(c)
    assert c.post("/v1/evaluate", content=orjson_bytes(lt.scene(4)), headers={"Content-Type": J}).status_code == 200


def orjson_bytes(doc) -> bytes:  # noqa: ANN001
    return json.dumps(doc).encode()


def _bad_range(doc: dict) -> dict:
    doc = json.loads(json.dumps(doc))
    doc["batches"][0]["lower"][0] = 10.0
    return doc


# ------------------------------------------------------------------ the probe, on a real server


def test_concurrent_requests_at_the_limits_keep_a_worker_within_the_sizing_rule(monkeypatch):
    """Six concurrent copies of the costliest request of each kind (`drills.scenario_burst`: the answer bound,
    the body bound), at the manifest's limits, on one worker: each answers 200 or 503 busy (a body refused
    as it arrives is drained, not reset), at least one is served, the worker survives, serves the request
    again once quiet, and its peak memory stays within `sizing.worker_bytes`."""
    for k, v in DEPLOY.items():
        monkeypatch.setenv(k, v)
    report = lt.scenario_burst(6, env=DEPLOY)
    for case, r in report.items():
        assert r["same_worker"] and r["alone_after"] == 200, (case, r)
        assert r["answers"].count(200) >= 1, (case, r)
        assert set(r["answers"]) <= {200, 503}, (case, r)
        assert r["peak_rss_mib"] <= r["rule_mib"] == round(sizing.worker_bytes(Settings()) / 2**20), (case, r)


def test_a_session_evaluate_takes_its_share_and_waits_its_turn():
    """A WebSocket session's evaluate is charged to the same in-flight budget (its core and its answer): while
    it is full, the evaluate is a 503 busy fault and the session goes on; its share is back once replied."""
    from tests.http.test_sessions import BODY, PATH, Q, Json

    c = _client(queue_timeout=0.2)
    budget = c.app.state.in_flight
    with c.websocket_connect(PATH) as ws:
        s = Json(ws)
        assert s.send(BODY)["kind"] == "opened"
        first = s.send({"kind": "evaluate", "q": Q})
        assert first["kind"] == "evaluation" and _soon(lambda: budget.held == 0)  # given back once sent
        hog = asyncio.run(budget.acquire(budget.capacity, 1.0))
        reply = s.send({"kind": "evaluate", "q": Q, "id": 7})
        assert reply["kind"] == "error" and reply["status"] == 503 and reply.get("id") == 7, reply
        assert reply["detail"][0]["type"] == "busy" and "JOINTLIMITS_QUEUE_TIMEOUT" in reply["detail"][0]["msg"]
        hog.release()
        again = s.send({"kind": "evaluate", "q": Q})
        assert again["kind"] == "evaluation" and again["total_energy"] == first["total_energy"]
    assert _soon(lambda: _budgets_free(c))


def test_the_sdk_waits_out_a_busy_worker_and_gets_the_same_answer(monkeypatch):
    """End to end: a real server whose in-flight budget is held answers 503 busy; the SDK sleeps the
    server's Retry-After (recorded here instead of slept; the budget comes free meanwhile) and retries."""
    import jointlimits.client.sync as sdk_sync
    from jointlimits.client import Client, LocalClient
    from tests.http.test_contract_live import serve

    app = create_app(Settings(token=None, cors_origins=(), queue_timeout=0.1))
    b = app.state.in_flight
    hold = asyncio.run(b.acquire(b.capacity, 1.0))
    pauses: list[float] = []

    def sleep(seconds: float) -> None:
        pauses.append(seconds)
        hold.release()  # the other requests finish while the client waits

    monkeypatch.setattr(sdk_sync, "time", type("Clock", (), {"sleep": staticmethod(sleep)}))  # the SDK's sleeps only
    request = lt.array_scene(5)
    with serve(app=app) as url, Client(url) as c:
        got = c.evaluate(request)
    want = LocalClient().evaluate(request)
    assert pauses == [5.0]
    assert got.total_energy == want.total_energy
    for g, w in zip(got.batches, want.batches):
        assert (g.hessian == w.hessian).all() and (g.gradient == w.gradient).all()
    assert b.held == 0


def test_a_client_that_leaves_mid_body_or_mid_queue_holds_nothing():
    """Raw sockets on a live server: a body cut off halfway, and a request that leaves while it waits for the
    in-flight budget, give every byte back (the metrics' gauges read 0 again)."""
    import socket

    from tests.http.test_contract_live import serve

    app = create_app(Settings(token=None, cors_origins=(), queue_timeout=1.0))
    body = orjson_bytes(lt.scene(50))
    head = (f"POST /v1/evaluate HTTP/1.1\r\nHost: x\r\nContent-Type: {J}\r\nContent-Length: {len(body)}\r\n\r\n").encode()
    with serve(app=app) as url:
        port = int(url.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port)) as s:  # half a body, then gone
            s.sendall(head + body[: len(body) // 2])
            assert _soon(lambda: app.state.uploads.held > 0)
        assert _soon(lambda: app.state.uploads.held == 0)
        b = app.state.in_flight
        hog = asyncio.run(b.acquire(b.capacity, 1.0))
        with socket.create_connection(("127.0.0.1", port)) as s:  # a whole body, then gone while queued
            s.sendall(head + body)
            assert _soon(lambda: b.queued == 1)
        hog.release()
        assert _soon(lambda: _budgets_free(type("C", (), {"app": app})()))
        with httpx.Client(base_url=url) as c:
            assert c.post("/v1/evaluate", content=body, headers={"Content-Type": J}).status_code == 200
            assert "jointlimits_inflight_budget_bytes 0.0" in c.get("/metrics").text


def test_opening_a_session_waits_for_its_share_too():
    """Preparing a scene is charged like a request of its message's size: while the in-flight budget is full,
    the opening document is a 503 busy fault (the connection stays, a later opening works)."""
    from tests.http.test_sessions import BODY, PATH, Json

    c = _client(queue_timeout=0.2)
    b = c.app.state.in_flight
    hog = asyncio.run(b.acquire(b.capacity, 1.0))
    with c.websocket_connect(PATH) as ws:
        s = Json(ws)
        reply = s.send(BODY)
        assert reply["kind"] == "error" and reply["status"] == 503 and reply["detail"][0]["type"] == "busy", reply
        hog.release()
        assert s.send(BODY)["kind"] == "opened"
    assert _soon(lambda: _budgets_free(c))
