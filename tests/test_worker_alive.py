"""A worker stays alive whatever a legal request costs (issue 9, item 2), on a real 2-worker server.

uvicorn's supervisor pings each worker and kills one that does not answer within
`--healthcheck-timeout`; the answer comes from a thread of the worker, which needs the
GIL, and a JSON parse holds it throughout. Before the fix, a legal 93.6 MB JSON body
(1.2e6 bodies, 43e6 values) held it past the old 5 s and the worker was SIGKILLed.
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

from client import codec
from service import cli
from service import loadtest as lt
from tests.test_admission import scene

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
        # Issue 9's probes: a 700k-joint energy-only JSON request, a 1e6-joint msgpack request answered in JSON.
        for n, binary_request, answer in ((700_000, False, J), (1_000_000, True, J)):
            body, ctype = codec.encode(scene(n, outputs=("energy",)), binary=binary_request)
            r = httpx.post(url, content=body, headers={"Content-Type": ctype, "Accept": answer}, timeout=120)
            assert r.status_code == 200, r.text[:300]
            x = np.asarray(r.json()["batches"][0]["x"])
            assert x.shape == (n,) and np.allclose(x, 0.7, rtol=1e-13, atol=0)
        # A JSON body at the value bound parses (the longest admitted GIL hold); one past it is refused unparsed.
        at_bound = many_bodies_json(222_000)
        assert at_bound.count(b",") + 1 <= 8_000_000
        assert httpx.post(url, content=at_bound, headers={"Content-Type": J}, timeout=120).status_code == 200
        r = httpx.post(url, content=many_bodies_json(1_200_000), headers={"Content-Type": J}, timeout=120)
        assert r.status_code == 413 and "JOINTLIMITS_MAX_JSON_VALUES" in r.text
        time.sleep(1.5)  # the supervisor pings every 0.5 s
        assert server.worker_pids() == pids, "a worker was killed and replaced"
        assert "died" not in server.log()
