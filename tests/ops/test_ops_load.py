"""Load and faults on a real 2-worker server on loopback (`tests/drills.py` does the work).

About 90 s in all: a 10 s mixed load (JOINTLIMITS_LOAD_SECONDS to change it), a flood of
oversized requests, a worker killed under load, SIGTERM under load, a slowloris of 50 connections,
an oversized answer under load. The figures in the
README come from `python -m tests.drills --spawn --scenario all`, the same code.
"""

from __future__ import annotations

import json
import os

import pytest

from tests import drills as lt

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # the drills against `jointlimits serve --workers 2` (~95 s)

# 10 s of mixed load (30 s until 2026-11-28): every assertion but the RSS growth's is a count that holds at any
# duration (no 5xx, no drop, every status as its kind calls for, /metrics exact), and 10 s is already ~1,700
# requests at a load of 6 on the 2 cores (~800 per worker, ~70 of them 100-joint psd Hessians, the largest answer).
# What 10 s loses is leak sensitivity at a fixed RSS bound, so the bound scales with the duration (below): 24 MiB
# in 10 s is about the 64 MiB in 30 s it was, per second (2.4 against 2.1 MiB/s). Measured growth at 10 s: 1.8 and
# 3.2 MiB per worker, so the bound keeps a margin of 7x over a healthy worker.
LOAD_SECONDS = float(os.environ.get("JOINTLIMITS_LOAD_SECONDS", "10"))
RSS_GROWTH_KIB = int(max(24.0, 64.0 * LOAD_SECONDS / 30.0) * 1024)
MAX_BODY_BYTES, MAX_JOINTS = 1_000_000, 1_000
LIMITS = ["--max-body-bytes", str(MAX_BODY_BYTES), "--max-joints", str(MAX_JOINTS)]


@pytest.fixture(scope="module")
def shared_server():
    """One server for the mixed load and the flood (a start is 3-8 s here): each reads only deltas of what it
    did (RSS after its own warm-up, /metrics counts, the worker pids), so either may run first."""
    with lt.Server(workers=2, extra_args=LIMITS) as s:
        yield s


@pytest.fixture
def server():
    with lt.Server(workers=2, extra_args=LIMITS) as s:
        yield s


def show(name: str, report: dict) -> None:
    print(f"\n{name}: " + json.dumps({k: v for k, v in report.items() if k != "by_kind"}))


def test_mixed_load_two_workers_sixteen_clients(shared_server):
    r = lt.scenario_mixed(shared_server, clients=16, duration=LOAD_SECONDS)
    show("mixed", r)
    assert r["requests"] > 0 and r["throughput_rps"] > 0
    assert r["server_errors_5xx"] == 0
    assert r["dropped"] == 0 and r["connection_errors"] == 0
    assert r["unexpected"] == {}, "every request got the status its kind calls for"
    assert {"200", "404", "422"} <= r["statuses"].keys()
    assert not r["workers_replaced"]
    for pid, rss in r["workers_rss_kib"].items():
        assert rss["growth"] is not None and rss["growth"] < RSS_GROWTH_KIB, f"worker {pid} grew {rss['growth']} KiB"
    # /metrics counts every evaluate request exactly, whichever worker answered it.
    assert r["metrics_evaluate_delta"] == r["evaluate_answered"]
    assert shared_server.proc.poll() is None


def test_flood_of_oversized_requests_neither_downs_nor_starves(shared_server):
    pids = shared_server.worker_pids()
    r = lt.scenario_flood(shared_server, clients=16, duration=8, max_body_bytes=MAX_BODY_BYTES, max_joints=MAX_JOINTS)
    for part in ("valid_alone", "valid_under_flood", "flood"):
        show(part, r[part])
    flood, valid = r["flood"], r["valid_under_flood"]
    assert flood["requests"] > 0 and set(flood["statuses"]) == {"413"}
    assert flood["server_errors_5xx"] == 0 and flood["dropped"] == 0
    assert {"oversized_declared", "oversized_chunked", "too_many_joints"} <= flood["by_kind"].keys()
    assert valid["requests"] > 0 and set(valid["statuses"]) == {"200"}
    assert valid["dropped"] == 0 and valid["connection_errors"] == 0
    # Not starved: valid clients keep a useful share of their throughput and a bounded p99. The share is bounded
    # from below by 10%, not more: the 8 flooders run in the valid clients' own process and event loop, on the same
    # 2 cores as the 2 workers, so sending 1 MB bodies takes the valid clients' CPU as much as the server's. Measured
    # on a quiet machine (2026-11-28, this tree and the tree before that day's changes alike): 0.20, 0.22, 0.23, 0.33,
    # 0.86 of a 4 s baseline that itself moved 90-313 rps between runs; a starved worker (a blocked loop) answers
    # nothing, which this bound and the p99 bound below both catch.
    assert valid["throughput_rps"] > 0.1 * r["valid_alone"]["throughput_rps"]
    assert valid["p99_ms"] < max(2000.0, 5 * r["valid_alone"]["p99_ms"])
    assert r["healthz_after"] == 200 and shared_server.proc.poll() is None
    assert shared_server.worker_pids() == pids  # nothing crashed and was respawned


# uvicorn's supervisor pings each worker in turn and keeps both ends of each ping pipe, so a worker killed while
# its ping is pending gives no EOF: the supervisor waits out the whole health-check timeout (30 s by default)
# before it replaces it. Under load the busiest worker (the victim) answers slowly, so the kill lands in that
# window now and then (seen failing 1 in ~4 runs with the default). With 5 s the replacement comes within
# ~0.5 s (the supervisor's tick) + 5 s + a spawn, inside the drill's 10 s; this server's limits (1 MB bodies)
# hold the GIL far less than 5 s in any parse, so the shorter timeout kills no healthy worker.
KILL_HEALTHCHECK = ["--healthcheck-timeout", "5"]


def test_killed_worker_is_replaced_and_retrying_clients_see_no_error():
    with lt.Server(workers=2, extra_args=[*LIMITS, *KILL_HEALTHCHECK]) as server:
        r = lt.scenario_kill(server, clients=16, duration=10)
        show("kill", r)
        assert r["killed"] in r["workers_before"] and r["killed"] not in r["workers_after"]
        assert r["replaced_by"] and len(r["workers_after"]) == 2 and r["replaced_after_s"] < 10
        assert r["dropped"] == 0, "a client that retries sees no error"
        assert r["server_errors_5xx"] == 0 and r["unexpected"] == {}
        assert r["connection_errors"] >= 1, "the kill broke connections (else the drill tested nothing)"
        assert r["healthz_after"] == 200
        # The metrics of the dead worker survive it (multiprocess mode): the sum still matches, give or
        # take the requests the kill cut between the answer and its count.
        assert abs(r["metrics_evaluate_delta"] - r["evaluate_answered"]) <= 16


def test_sigterm_under_load_lets_in_flight_requests_finish(server):
    r = lt.scenario_sigterm(server, clients=16)
    show("sigterm", r)
    assert r["in_flight_at_sigterm"] == 16
    assert r["statuses"] == {"200": 16}, "every in-flight request completed"
    assert r["exit_code"] == 0
    assert r["last_completion_after_sigterm_s"] > 0  # they were still running when the signal came


HEADER_TIMEOUT, BODY_TIMEOUT = 3.0, 4.0


def test_slowloris_connections_are_closed_and_normal_clients_unaffected():
    """50 slow connections (silent, headers or body at 1 byte/s) are closed by the read timeouts; ~20 s."""
    timeouts = ["--header-timeout", str(HEADER_TIMEOUT), "--body-timeout", str(BODY_TIMEOUT)]
    with lt.Server(workers=2, extra_args=[*LIMITS, *timeouts]) as server:
        pids = server.worker_pids()
        r = lt.scenario_slowloris(server, clients=8, slow=50, header_timeout=HEADER_TIMEOUT, body_timeout=BODY_TIMEOUT)
        for part in ("valid_alone", "valid_under_slowloris", "slow"):
            show(part, r[part])
        assert server.worker_pids() == pids and server.proc.poll() is None
    # 2 s of slack: the timers are exact, the loaded 2-core machine is not.
    limit = {"silent": HEADER_TIMEOUT, "headers": HEADER_TIMEOUT, "body": BODY_TIMEOUT}
    for kind, s in r["slow"].items():
        assert s["connections"] >= 16 and s["closed"] == s["connections"], (kind, s)
        assert s["max_closed_after_s"] < limit[kind] + 2.0, (kind, s)
    assert r["slow"]["headers"]["statuses"] == {"408": r["slow"]["headers"]["connections"]}
    assert r["slow"]["body"]["statuses"] == {"408": r["slow"]["body"]["connections"]}
    assert r["slow"]["silent"]["statuses"] == {"None": r["slow"]["silent"]["connections"]}  # closed, no answer
    # /metrics (both workers) counts each connection the head's timeout closed, by what it had sent.
    assert r["metrics_closed_delta"] == {"silent": r["slow"]["silent"]["connections"],
                                         "slow_head": r["slow"]["headers"]["connections"]}
    valid = r["valid_under_slowloris"]
    assert valid["requests"] > 0 and set(valid["statuses"]) == {"200"}
    assert valid["dropped"] == 0 and valid["connection_errors"] == 0
    assert valid["p99_ms"] < max(2000.0, 5 * r["valid_alone"]["p99_ms"])
    assert r["healthz_after"] == 200


def test_oversized_answer_while_clients_run_is_refused_and_nobody_suffers():
    """One request over the answer bound (413 before any work) and one at it (200), under load, default limits."""
    with lt.Server(workers=2) as s:
        r = lt.scenario_answer(s, clients=8, duration=8)
        for part in ("valid_alone", "valid_during"):
            show(part, r[part])
        print("\nheavy: " + json.dumps(r["heavy"]))
        assert r["heavy"]["over_bound"]["status"] == 413
        assert r["heavy"]["at_bound"]["status"] == 200 and r["heavy"]["at_bound"]["answer_bytes"] > 0
        valid = r["valid_during"]
        assert valid["requests"] > 0 and set(valid["statuses"]) == {"200"}
        assert valid["server_errors_5xx"] == 0 and valid["dropped"] == 0 and valid["connection_errors"] == 0
        assert r["workers_after"] == r["workers_before"], "a worker was killed and replaced"
        assert r["healthz_after"] == 200 and s.proc.poll() is None
