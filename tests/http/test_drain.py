"""The drain on SIGTERM (issue 30): each worker's `/readyz` answers 503 "draining" at once and the worker
goes on accepting and answering for `--shutdown-delay` seconds, then stops accepting, finishes what it
holds and the server exits 0; `/healthz` (liveness) stays 200 throughout.

The live tests run `jointlimits serve` on a loopback port (tests/drills.py's `Server`) with a 1.5 s
delay, through uvicorn's supervisor (2 workers) and in a single process; every request after the signal
goes over a new connection, as a load balancer's would.
"""

from __future__ import annotations

import json
import signal
import threading
import time

import httpx
import pytest
from fastapi.testclient import TestClient

from jointlimits.service.app import create_app, drain_on_sigterm
from jointlimits.service.settings import Settings
from tests.drills import LOOPBACK, Server, get, scene

pytestmark = pytest.mark.serial  # drains timed against the shutdown delay

DELAY = 1.5


def new_connection(port: int) -> httpx.Client:
    return httpx.Client(base_url=f"http://{LOOPBACK}:{port}", timeout=10, trust_env=False)


def evaluate(port: int) -> httpx.Response:
    """`POST /v1/evaluate` of a 2-joint scene over a connection of its own."""
    with new_connection(port) as c:
        return c.post("/v1/evaluate", content=json.dumps(scene(2)).encode(), headers={"Content-Type": "application/json"})


def draining(port: int, timeout: float = 2.0) -> float:
    """Wait until `/readyz` (a new connection each time) answers 503; the time it took."""
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        status, body = get(port, "/readyz", timeout=2)
        if status == 503:
            fault = json.loads(body)["detail"][0]
            assert fault["type"] == "draining" and "JOINTLIMITS_SHUTDOWN_DELAY" in fault["msg"], body
            return time.monotonic() - start
        assert status == 200, (status, body)
        time.sleep(0.02)
    raise AssertionError(f"/readyz did not answer 503 within {timeout} s of SIGTERM")


@pytest.mark.slow  # `jointlimits serve` with 1 and 2 workers, a 1.5 s drain (~4.6 s)
@pytest.mark.parametrize("workers", [2, 1])
def test_sigterm_drains_then_stops(workers):
    """Readiness 503 at once (the supervisor passes the signal on within its 0.5 s poll), liveness 200, evaluations
    answered on new connections with `Connection: close` for the delay; then exit 0."""
    with Server(workers=workers, extra_args=["--shutdown-delay", str(DELAY)]) as server:
        assert get(server.port, "/readyz")[0] == 200
        kept = new_connection(server.port)  # a keep-alive connection opened before the signal
        assert kept.get("/healthz").status_code == 200
        pids = server.worker_pids()
        signalled = time.monotonic()
        server.proc.send_signal(signal.SIGTERM)
        assert draining(server.port) < (0.7 if workers > 1 else 0.3)
        checked = 0
        while time.monotonic() - signalled < DELAY - 0.3:  # the whole window, short of its end
            assert get(server.port, "/readyz")[0] == 503
            assert get(server.port, "/healthz")[0] == 200
            r = evaluate(server.port)
            assert r.status_code == 200 and r.json()["total_energy"] > 0
            assert r.headers["connection"] == "close"  # the client's next request goes elsewhere
            checked += 1
        assert checked >= 3 and server.proc.poll() is None
        r = kept.get("/healthz")  # the old connection is served too, and told to close
        assert r.status_code == 200 and r.headers["connection"] == "close"
        kept.close()
        assert server.proc.wait(DELAY + 10) == 0
        stopped = time.monotonic() - signalled
        log = [json.loads(line) for line in server.log().splitlines() if line.startswith("{")]
    assert DELAY <= stopped < DELAY + 8
    drains = {line["pid"] for line in log if line["logger"] == "jointlimits.drain" and "draining" in line["msg"]}
    assert drains == set(pids)  # every worker drained, once
    statuses = [(line["path"], line["status"]) for line in log if line["logger"] == "jointlimits.access"]
    assert ("/readyz", 503) in statuses and not [s for s in statuses if s[1] >= 500 and s[0] != "/readyz"]


@pytest.mark.slow  # `jointlimits serve`, two SIGTERMs then a SIGINT (~2 s)
def test_a_second_sigterm_changes_nothing_and_sigint_stops_at_once():
    """A process manager and the supervisor may both send SIGTERM: the drain goes on; Ctrl-C ends it."""
    with Server(workers=1, extra_args=["--shutdown-delay", "30"]) as server:
        signalled = time.monotonic()
        server.proc.send_signal(signal.SIGTERM)
        draining(server.port)
        server.proc.send_signal(signal.SIGTERM)
        time.sleep(0.3)
        assert server.proc.poll() is None and evaluate(server.port).status_code == 200
        server.proc.send_signal(signal.SIGINT)
        assert server.proc.wait(10) == 0
        assert time.monotonic() - signalled < 10  # not the 30 s delay


@pytest.mark.slow  # `jointlimits serve` drains an open session (~3 s)
def test_a_draining_worker_serves_its_sessions_refuses_new_ones_then_closes_them_with_1012():
    """During the delay the open session is answered and a new one's upgrade gets 503 `draining` (a balancer's
    retry lands elsewhere: tests/ops/test_lb_drill.py); at its end the session is closed with 1012, which the SDK
    resumes from (here `resume=False`, to see the close: one replica, nothing to resume on)."""
    from jointlimits.client import Client, ServiceError, SessionClosed
    from tests.sdk.test_client_sdk import readme_scene

    request = readme_scene().request()
    with Server(workers=1, extra_args=["--shutdown-delay", str(DELAY)]) as server:
        url = f"http://{LOOPBACK}:{server.port}"
        s = Client(url).session(request, resume=False)
        server.proc.send_signal(signal.SIGTERM)
        draining(server.port)
        with pytest.raises(ServiceError) as refused:
            Client(url, retries=0).session(request)
        assert refused.value.status == 503 and refused.value.faults[0].type == "draining"
        with pytest.raises(SessionClosed) as closed:
            for _ in range(int(10 * DELAY / 0.05)):  # bounded: past the delay by far
                assert s.evaluate(request.q).total_energy > 0
                time.sleep(0.05)
        assert closed.value.code == 1012 and closed.value.resumable and "shutting down" in closed.value.reason
        assert server.proc.wait(10) == 0


# --------------------------------------------------------------------------- in-process


def test_readiness_and_liveness_are_separate_endpoints():
    app = create_app(Settings(token="s3cret", cors_origins=()))
    with TestClient(app) as c:
        assert c.get("/readyz").json() == {"status": "ready"} and c.get("/healthz").json() == {"status": "ok"}
        assert "connection" not in c.get("/healthz").headers
        app.state.draining = True  # what SIGTERM does
        r = c.get("/readyz")  # open, like /healthz: probes carry no token
        assert r.status_code == 503 and r.headers["connection"] == "close"
        assert r.json()["detail"] == [{"loc": [], "type": "draining", "msg": (
            "this worker is draining (SIGTERM): it goes on answering for 5 s after the signal "
            "(JOINTLIMITS_SHUTDOWN_DELAY), then stops accepting; send new requests elsewhere")}]
        r = c.get("/healthz")
        assert r.status_code == 200 and r.headers["connection"] == "close"
        assert c.post("/v1/evaluate", json={}).headers["connection"] == "close"  # a 401 too


def test_the_drain_is_installed_only_under_uvicorn_in_the_main_thread(monkeypatch):
    """A test's app (a thread), a delay of 0, or a SIGTERM handler that is not uvicorn's: SIGTERM is left alone."""
    import asyncio

    before = signal.getsignal(signal.SIGTERM)

    async def install(settings: Settings) -> bool:
        return drain_on_sigterm(create_app(settings))

    assert asyncio.run(install(Settings(shutdown_delay=2))) is False  # pytest's handler, not uvicorn's
    assert asyncio.run(install(Settings(shutdown_delay=0))) is False
    seen: list[bool] = []
    thread = threading.Thread(target=lambda: seen.append(asyncio.run(install(Settings(shutdown_delay=2)))))
    thread.start()
    thread.join()
    assert seen == [False] and signal.getsignal(signal.SIGTERM) is before


def test_the_delay_is_a_setting(monkeypatch):
    assert Settings().shutdown_delay == 5.0
    monkeypatch.setenv("JOINTLIMITS_SHUTDOWN_DELAY", "0")
    assert Settings().shutdown_delay == 0.0
    monkeypatch.setenv("JOINTLIMITS_SHUTDOWN_DELAY", "-1")
    with pytest.raises(ValueError, match="JOINTLIMITS_SHUTDOWN_DELAY: must be 0 or a positive number of seconds"):
        Settings()
