"""Shared fixtures: the golden cases and normwise error measures."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

GOLDEN = json.loads((Path(__file__).parent / "golden_cases.json").read_text())["cases"]


def relerr(got, want, floor: float = 0.0) -> float:
    """Normwise relative error `max|got - want| / max(max|want|, floor)` (0 when both are zero)."""
    got, want = np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape, (got.shape, want.shape)
    scale = max(float(np.max(np.abs(want), initial=0.0)), floor)
    diff = float(np.max(np.abs(got - want), initial=0.0))
    return diff / scale if scale > 0 else diff


@pytest.fixture(params=GOLDEN, ids=[c["name"] for c in GOLDEN])
def golden_case(request):
    return request.param


# ---------------------------------------------------------------- the fast subset
# `pytest -m "not slow"` leaves out the tests marked `slow` where they are: `pytestmark = pytest.mark.slow` at the top
# of a wholly slow module, `@pytest.mark.slow` on a test, each with its reason (live servers in subprocesses, the load
# and fault drills, the Dockerfile's replay, the bench, fuzzers, timers that wait on purpose, property tests over random
# scenes). tests/test_slow_marks.py checks that the tests known slow stay marked and that a test starting a process is.


# ---------------------------------------------------------------- one CA bundle per test run
# httpx builds an SSL context for every client it makes (the SDK's `Client`, each `httpx.get`/`httpx.post`), loading
# the system's CA bundle: `load_verify_locations` takes 40 ms on a quiet core and 170-290 ms on the loaded 2-core
# machine, and the suite makes thousands of clients, all to plain-HTTP servers on loopback that never use TLS. The test
# process builds that default context once and gives the same object to every client that asks for it (verify=True,
# no client certificate); any other request builds its own as before. What the clients send and receive is unchanged.
@pytest.fixture(scope="session", autouse=True)
def _one_default_ssl_context():
    try:
        from httpx._transports import default as transports  # where httpx's transports call it
    except ImportError:  # another httpx layout: every client builds its own context, as without this fixture
        yield
        return
    build = transports.create_ssl_context
    built: dict[tuple, object] = {}

    def create_ssl_context(verify=True, cert=None, trust_env=True):  # noqa: ANN001, ANN202 (httpx's signature)
        if verify is not True or cert is not None:
            return build(verify=verify, cert=cert, trust_env=trust_env)
        key = (trust_env, os.environ.get("SSL_CERT_FILE"), os.environ.get("SSL_CERT_DIR"))
        if key not in built:
            built[key] = build(verify=verify, cert=cert, trust_env=trust_env)
        return built[key]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(transports, "create_ssl_context", create_ssl_context)
        yield


# ---------------------------------------------------------------- CI's two runs
# CI runs `pytest -n 2 -m "not serial"` (pytest-xdist: 2 worker processes, each test module wholly on one worker,
# `--dist loadfile` in pyproject.toml, so that a module's fixtures (a built venv, a live server) are made once), then
# `pytest -m serial` alone: the tests that measure time or wait on wall-clock bounds (the `serial` marker). On the
# workers the longest modules go first, so that neither worker is left with one of them at the end while the other
# idles; a run without xdist keeps the files' order.
LONGEST_FIRST = ("tests/ops/test_docker.py", "tests/ops/test_newcomer_bench.py", "tests/ops/test_wheel.py")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # schemathesis (4.x, under pytest 9) names its items per API operation (`test_schemathesis_openapi[GET /healthz]`)
    # but gives them all the function's node id; xdist schedules by node id, so 3 of the 4 operations never ran on
    # the workers (and reports merged them). Each item gets its name as its node id, as any parametrized test has.
    seen: dict[str, int] = {}
    for item in items:
        seen[item.nodeid] = seen.get(item.nodeid, 0) + 1
    for item in items:
        if seen[item.nodeid] > 1 and item.parent is not None:
            item._id = item.parent.id.child(item.name)  # pytest 9's node id (Node.__init__ makes it so)
    worker = hasattr(config, "workerinput")  # an xdist worker: the controller schedules in this order
    if worker and len({item.nodeid for item in items}) != len(items):
        raise pytest.UsageError("two tests share a node id: pytest-xdist would run only one of them")
    if worker:
        rank = {path: k for k, path in enumerate(LONGEST_FIRST)}
        items.sort(key=lambda item: rank.get(item.nodeid.split("::", 1)[0], len(rank)))
