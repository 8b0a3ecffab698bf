"""`strength` and `base_uid` may be left out on the wire (both encodings, and the OpenAPI schema says so).

Absent `strength` is discovery's advertised default for every joint; absent `base_uid` is the
constitution's base joint. Given, both are validated as before.
"""

from __future__ import annotations

import json

import httpx
import msgpack
import numpy as np
import pytest

from jointlimits.client import codec
from tests.http.test_contract_live import live  # noqa: F401 (fixture)
from tests.http.test_errors_http import base_request

J, B = "application/json", "application/msgpack"


def _post(url: str, doc: dict, binary: bool) -> httpx.Response:
    body = msgpack.packb(doc) if binary else json.dumps(doc).encode()
    return httpx.post(url + "/v1/evaluate", content=body, headers={"Content-Type": B if binary else J, "Accept": J})


def _doc(binary: bool) -> dict:
    body, _ = codec.encode(base_request(), binary)
    return msgpack.unpackb(body) if binary else json.loads(body)


@pytest.mark.parametrize("binary", [False, True], ids=["json", "msgpack"])
def test_absent_strength_and_base_uid_take_their_defaults(live, binary):
    advertised = {
        c["uid"]: {a["field"]: a["default"] for a in c["attributes"]}
        for c in httpx.get(live + "/v1/constitutions").json()["constitutions"]
    }
    assert advertised[670]["strength"] == advertised[669]["strength"] == 1.0
    explicit = _doc(binary)
    for b, joints in zip(explicit["batches"], base_request().batches):  # the defaults spelt out
        n = len(joints)
        b["strength"] = {"dtype": "<f8", "shape": [n], "data": np.ones(n).tobytes()} if binary else [1.0] * n
    implicit = _doc(binary)
    for b in implicit["batches"]:
        del b["strength"], b["base_uid"]
    want, got = _post(live, explicit, binary), _post(live, implicit, binary)
    assert want.status_code == got.status_code == 200, got.text
    assert got.content == want.content
    assert json.loads(got.content)["batches"][1]["energy"][0] > 0  # 669 row 0 is outside its range: strength counts


@pytest.mark.parametrize("binary", [False, True], ids=["json", "msgpack"])
def test_given_they_are_still_validated(live, binary):
    doc = _doc(binary)
    doc["batches"][0]["base_uid"] = 20
    r = _post(live, doc, binary)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "batches", 0, "base_uid"]
    doc = _doc(binary)
    doc["batches"][1]["base_uid"] = None  # absent is allowed, null is not
    r = _post(live, doc, binary)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "batches", 1, "base_uid"]
    doc = _doc(binary)
    doc["batches"][1]["strength"] = None
    r = _post(live, doc, binary)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][:4] == ["body", "batches", 1, "strength"]


def test_openapi_marks_them_optional(live):
    schema = httpx.get(live + "/openapi.json").json()["components"]["schemas"]["JointBatch"]
    # v1.2: exactly one of edges and local_edges, so neither is required by the schema (the core names the batch).
    assert set(schema["required"]) == {"constitution_uid", "body_ids", "lower", "upper"}
    for name in ("base_uid", "strength", "edges", "local_edges"):
        assert "default" not in schema["properties"][name]
        assert '"type": "null"' not in json.dumps(schema["properties"][name])  # absent, never null
