"""A worker stays alive whatever a legal request costs (issue 9, item 2), on a real 2-worker server.

uvicorn's supervisor pings each worker and kills one that does not answer within
`--healthcheck-timeout`; the answer comes from a thread of the worker, which needs the
GIL, and a JSON parse holds it throughout. Before the fix, a legal 93.6 MB JSON body
(1.2e6 bodies, 43e6 values) held it past the old 5 s and the worker was SIGKILLed; a
700k-joint JSON body (7.7e6 values, issue 9's probe) held it 12.5 s at a load average of 6.5.
Now: the JSON parse is bounded before it starts (`JOINTLIMITS_MAX_JSON_VALUES`), the
health check waits `JOINTLIMITS_HEALTHCHECK_TIMEOUT` (30 s, far above the longest
admitted parse), JSON answers are written in GIL-releasing pieces. Slow (~30 s).
"""

from __future__ import annotations

import os
import signal
import time

import httpx
import numpy as np
import pytest

from jointlimits.client import codec
from jointlimits.service import cli
from jointlimits.service.settings import Settings
from tests import drills as lt
from tests.http.test_admission import scene

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # the largest admitted bodies to a 2-worker server (~10 s)

J, B = "application/json", "application/msgpack"


many_bodies_json = lt.short_values_json


def test_the_supervisor_gets_the_health_check_timeout(monkeypatch):
    import uvicorn

    seen = {}
    monkeypatch.setattr(uvicorn, "run", lambda app, **kw: seen.update(kw))
    for name in list(os.environ):  # serve() hands the settings to workers through os.environ: restore it after
        if name.startswith(cli.ENV_PREFIX):
            monkeypatch.delenv(name)
    for name in ("MAX_JOINTS", "MAX_BODY_BYTES", "CORS_ORIGINS", "KEEP_HEAP", "MAX_BATCHES", "MAX_ANSWER_BYTES", "MAX_JSON_VALUES", "REQUEST_TIMEOUT"):
        monkeypatch.setenv(cli.ENV_PREFIX + name, "")
        monkeypatch.delenv(cli.ENV_PREFIX + name)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        args = cli.build_parser().parse_args(["serve", "--workers", "1", "--healthcheck-timeout", "17", "--request-timeout", "9"])
        assert cli.serve(args) == 0
        assert seen["timeout_worker_healthcheck"] == 17 and os.environ["JOINTLIMITS_REQUEST_TIMEOUT"] == "9.0"
        cli.serve(cli.build_parser().parse_args(["serve", "--workers", "1"]))
        assert seen["timeout_worker_healthcheck"] == 30  # the default: far above the longest admitted parse
    finally:
        for sig, h in handlers.items():
            signal.signal(sig, h)


def test_largest_legal_requests_neither_kill_nor_starve_a_worker():
    with lt.Server(workers=2) as server:
        pids = server.worker_pids()
        url = f"http://{lt.LOOPBACK}:{server.port}/v1/evaluate"
        # Issue 9's probes: a 700k-joint energy-only JSON request (7.7e6 values: now refused before
        # parsing, the SDK splits it) and a 1e6-joint msgpack request answered in JSON (answered).
        body, ctype = codec.encode(scene(700_000, outputs=("energy",)), binary=False)
        r = httpx.post(url, content=body, headers={"Content-Type": ctype}, timeout=120)
        assert r.status_code == 413 and "JOINTLIMITS_MAX_JSON_VALUES" in r.text
        body, ctype = codec.encode(scene(1_000_000, outputs=("energy",)), binary=True)
        r = httpx.post(url, content=body, headers={"Content-Type": ctype, "Accept": J}, timeout=120)
        assert r.status_code == 200, r.text[:300]
        x = np.asarray(r.json()["batches"][0]["x"])
        assert x.shape == (1_000_000,) and np.allclose(x, 0.7, rtol=1e-13, atol=0)
        # The largest JSON bodies admitted: short values (the most per byte) and joints (the most
        # nested), each at the value bound: the longest GIL holds a request can cause.
        at_bound = many_bodies_json(Settings().max_json_values // 36 - 1)
        n = Settings().max_json_values // 12
        joints, _ = codec.encode(scene(n, outputs=("energy",)), binary=False)
        for body in (at_bound, joints):
            assert body.count(b",") + 1 <= Settings().max_json_values
            r = httpx.post(url, content=body, headers={"Content-Type": J}, timeout=120)
            assert r.status_code == 200, r.text[:300]
        r = httpx.post(url, content=many_bodies_json(1_200_000), headers={"Content-Type": J}, timeout=120)
        assert r.status_code == 413 and "JOINTLIMITS_MAX_JSON_VALUES" in r.text
        time.sleep(1.5)  # the supervisor pings every 0.5 s
        assert server.worker_pids() == pids, "a worker was killed and replaced"
        assert "died" not in server.log()
