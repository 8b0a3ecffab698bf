"""The 50-digit golden cases, in-process and over HTTP."""

from __future__ import annotations

import numpy as np
from fastapi.testclient import TestClient

from jointlimits.service.app import app
from jointlimits.service.core import evaluate
import orjson

from jointlimits.service.http.convert import read
from tests.conftest import relerr

TOL = 1e-12  # every golden case is in the well-conditioned family
FIELDS = ("x", "energy", "gradient", "hessian")


def test_golden_in_process(golden_case):
    ev = evaluate(**read(orjson.dumps(golden_case["request"])))
    assert len(ev.batches) == len(golden_case["expect"])
    for got, want in zip(ev.batches, golden_case["expect"]):
        for f in FIELDS:
            assert relerr(getattr(got, f), want[f]) <= TOL, f
    want_total = sum(sum(e["energy"]) for e in golden_case["expect"])
    assert relerr(ev.total_energy, want_total) <= TOL


def test_golden_over_http(golden_case):
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=golden_case["request"])
    assert r.status_code == 200, r.text
    body = r.json()
    for got, want in zip(body["batches"], golden_case["expect"]):
        assert got["index"] == list(range(len(want["x"])))
        for f in FIELDS:
            assert relerr(got[f], want[f]) <= TOL, f


def test_golden_hessians_are_symmetric(golden_case):
    ev = evaluate(**read(orjson.dumps(golden_case["request"])))
    for r in ev.batches:
        np.testing.assert_array_equal(r.hessian, r.hessian.transpose(0, 2, 1))
