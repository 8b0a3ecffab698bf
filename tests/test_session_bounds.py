"""Sessions bounded and consistent (issue 27, item 5): integers are integers on every path; unfinished messages
count in the worker's upload budget as they arrive; a message over the limit is read as 1009 with its reason,
whatever its framing, and the rest the server drains is bounded in bytes and time."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from jointlimits.client import InvalidInput, JointBatch
from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.test_one_fault_every_path import base_doc, http

NOT_AN_INTEGER = ("Input should be a valid integer", "int_type")


@pytest.fixture(scope="module")
def app() -> TestClient:
    return TestClient(create_app(Settings(token=None, cors_origins=())))


# ---------------------------------------------------------------- integers are integers


def test_an_update_index_of_0_0_is_the_fault_of_a_body_id_of_0_0(app):
    """`"index": [0.0]` was accepted (and changed the scene) while `"body_ids": [[0.0, 1.0]]` got 422 int_type."""
    doc = base_doc()
    bad = json.loads(json.dumps(doc))
    bad["batches"][1]["body_ids"][2] = [0.0, 1.0]
    assert http(app, bad, False) == [(("body", "batches", 1, "body_ids", 2, 0), *NOT_AN_INTEGER)]
    with app.websocket_connect("/v1/sessions") as ws:
        ws.send_text(json.dumps(doc))
        assert json.loads(ws.receive_text())["kind"] == "opened"
        before = _evaluate(ws, doc)
        for index, at in (([0.0], 0), ([1, 0.0], 1), ([1e0], 0)):
            ws.send_text(json.dumps({"kind": "update", "batch": 0, "index": index, "upper": [9.0] * len(index), "id": 7}))
            reply = json.loads(ws.receive_text())
            assert reply == {"kind": "error", "status": 422, "id": 7,
                             "detail": [{"loc": ["body", "index", at], "msg": NOT_AN_INTEGER[0], "type": NOT_AN_INTEGER[1]}]}
        assert _evaluate(ws, doc) == before  # nothing changed
        ws.send_text(json.dumps({"kind": "update", "batch": 0, "index": [0], "upper": [9.0]}))  # an integer still is
        assert json.loads(ws.receive_text()) == {"kind": "updated", "batch": 0, "joints": 1}


def test_a_whole_float_body_id_is_named_beside_another_fault_and_by_the_sdk(app):
    """The one validator's integers are pydantic's: a body id of 1.0 is a fault on the lenient re-reading of a
    request with another array fault (it vanished before) and in the SDK's constructor, as 1.5 is."""
    doc = base_doc()
    doc["batches"][1]["body_ids"][2] = [0.0, 1.0]
    doc["batches"][1]["lower"][1] = "x"
    assert http(app, doc, False) == [(("body", "batches", 1, "body_ids", 2, 0), *NOT_AN_INTEGER),
                                     (("body", "batches", 1, "lower", 1), "Input should be a valid number", "float_type")]
    edge = [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    with pytest.raises(InvalidInput) as e:
        JointBatch.of(670, [[0, 1.0]], [edge], -1, 1)
    assert [(f.loc, f.msg, f.type) for f in e.value.faults] == [(("body_ids", 0, 1), *NOT_AN_INTEGER)]


def _evaluate(ws, doc: dict) -> str:
    ws.send_text(json.dumps({"kind": "evaluate", "q": doc["bodies"]["q"]}))
    return ws.receive_text()
