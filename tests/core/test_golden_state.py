"""Contract v1.1 (offset, prev_coordinate, coordinate): the 50-digit state cases in-process, over JSON and msgpack."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import codec
from jointlimits.client.model import JointBatch, Request
from jointlimits.schemas import binary as wire
from jointlimits.service.app import app
from jointlimits.service.core import evaluate
import orjson

from jointlimits.service.http.convert import read
from tests.conftest import relerr

CASES = json.loads((Path(__file__).parents[1] / "golden_state_cases.json").read_text())["cases"]
TOL = 1e-12  # the target: normwise relative error on x, coordinate, E, G, H
FIELDS = ("x", "coordinate", "energy", "gradient", "hessian")


@pytest.fixture(params=CASES, ids=[c["name"] for c in CASES])
def case(request):
    return request.param


def _check(batches, case, tol: float = TOL) -> None:
    """`batches` (dicts or objects with the FIELDS) against the case's 50-digit answers, to `tol`."""
    assert len(batches) == len(case["expect"])
    get = lambda b, f: b[f] if isinstance(b, dict) else getattr(b, f)  # noqa: E731
    for got, want in zip(batches, case["expect"]):
        assert list(get(got, "index")) == list(range(len(want["x"])))
        for f in FIELDS:
            assert relerr(get(got, f), want[f]) <= tol, f


def test_state_case_in_process(case):
    _check(evaluate(**read(orjson.dumps(case["request"]))).batches, case)


def test_state_case_over_json(case):
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=case["request"])
    assert r.status_code == 200, r.text
    _check(r.json()["batches"], case)


def _sdk_request(doc: dict, raw: bool = False) -> Request:
    """The case's wire request as the SDK's `Request` (so the msgpack body is the SDK's encoding);
    `raw`: the lists as they are (no broadcasting by `JointBatch.of`, so wrong lengths reach the server)."""
    b = doc["bodies"]
    f64 = lambda v: None if v is None else np.asarray(v, dtype=np.float64)  # noqa: E731
    raw_batches = [
        JointBatch(
            j["constitution_uid"],
            np.asarray(j["body_ids"], dtype=np.int64),
            *(f64(j[k]) for k in ("edges", "lower", "upper", "strength")),
            offset=f64(j.get("offset")),
            prev_coordinate=f64(j.get("prev_coordinate")),
        )
        for j in doc["batches"]
    ]
    batches = raw_batches if raw else [
        JointBatch.of(
            j["constitution_uid"],
            j["body_ids"],
            j["edges"],
            j["lower"],
            j["upper"],
            j["strength"],
            offset=j.get("offset"),
            prev_coordinate=j.get("prev_coordinate"),
        )
        for j in doc["batches"]
    ]
    arr = lambda k: np.asarray(b[k], dtype=np.float64)  # noqa: E731
    return Request(arr("q"), arr("q_prev"), arr("q_ref"), batches, tuple(doc["outputs"]), doc["hessian_mode"], doc["active_only"])


def test_state_case_over_msgpack(case):
    body, content_type = codec.encode(_sdk_request(case["request"]), binary=True)
    doc = wire.loads(body)
    for sent, j in zip(doc["batches"], case["request"]["batches"]):
        assert {"offset", "prev_coordinate"} & set(sent) == {"offset", "prev_coordinate"} & set(j)
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", content=body, headers={"Content-Type": content_type, "Accept": content_type})
    assert r.status_code == 200, r.text
    _check(codec.decode(r.content, r.headers["content-type"]).batches, case)


def test_coordinate_sits_next_to_x_in_both_encodings():
    """The answer's per-batch keys in order: coordinate right after x (contract v1.1)."""
    req = CASES[0]["request"]
    with TestClient(app) as client:
        as_json = client.post("/v1/evaluate", json=req).json()
        body, ct = codec.encode(_sdk_request(req), binary=True)
        as_msgpack = wire.loads(client.post("/v1/evaluate", content=body, headers={"Content-Type": ct, "Accept": ct}).content)
    for doc in (as_json, as_msgpack):
        keys = list(doc["batches"][0])
        assert keys[keys.index("x") + 1] == "coordinate"
    assert as_msgpack["batches"][0]["coordinate"]["dtype"] == "<f8"


def test_reference_reproduces_the_state_cases(case):
    """The project's own 50-digit reference, extended with offset and prev_coordinate, agrees with the cases."""
    from bench.reference import reference_request

    ref = reference_request(case["request"])
    mode = "hessian_" + case["request"]["hessian_mode"]
    for got, want in zip(ref, case["expect"]):
        for f in FIELDS:
            # Both sides are 50-digit answers rounded to float64: a few ulps apart at most.
            assert relerr(got[mode if f == "hessian" else f], want[f]) <= 1e-15, f
