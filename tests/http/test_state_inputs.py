"""Contract v1.1 inputs that are faults: each a 422 naming batch, field and joint, the same on every path."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import InvalidInput, LocalClient, codec
from jointlimits.service.app import app
from jointlimits.service.core import InputError, evaluate
import orjson

from jointlimits.service.http.convert import read
from tests.core.test_golden_state import CASES, _sdk_request

REVOLUTE = next(c["request"] for c in CASES if c["name"] == "revolute_turns_1_above")
PRISMATIC = next(c["request"] for c in CASES if c["name"] == "prismatic_offset")


def _with(doc: dict, **fields) -> dict:
    doc = copy.deepcopy(doc)
    doc["batches"][0].update(fields)
    return doc


def _locs_everywhere(doc: dict) -> list[list]:
    """The 422's locs over JSON, msgpack and the in-process client (asserted equal), as JSON has them."""
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=doc)
        assert r.status_code == 422, r.text
        body, ct = codec.encode(_sdk_request(doc, raw=True), binary=True)
        rb = client.post("/v1/evaluate", content=body, headers={"Content-Type": ct})
        assert rb.status_code == 422, rb.text
    with pytest.raises(InvalidInput) as local:
        LocalClient().evaluate(_sdk_request(doc, raw=True))
    locs = [d["loc"] for d in r.json()["detail"]]
    assert [d["loc"] for d in rb.json()["detail"]] == locs
    assert [list(f.loc) for f in local.value.faults] == locs
    return locs


def test_prev_coordinate_on_a_prismatic_batch_is_a_422_naming_the_field():
    doc = _with(PRISMATIC, prev_coordinate=[0.5])
    assert _locs_everywhere(doc) == [["body", "batches", 0, "prev_coordinate"]]


@pytest.mark.parametrize("field", ["offset", "prev_coordinate"])
def test_state_list_of_the_wrong_length_is_a_422(field):
    doc = _with(REVOLUTE, **{field: [0.1, 0.2]})
    assert _locs_everywhere(doc) == [["body", "batches", 0, field]]


def test_offset_whose_bounds_on_x_overflow_is_answered_on_every_path():
    """`lower - offset` overflows float64 but no number of the answer does (the penalty takes the coordinate against
    [lower, upper]): a 200 over JSON and msgpack and an answer in-process, the same coordinate (was a 422 on `offset`)."""
    doc = _with(REVOLUTE, offset=[1.7e308], lower=[-1.7e308], upper=[1.0])
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=doc)
        body, ct = codec.encode(_sdk_request(doc, raw=True), binary=True)
        rb = client.post("/v1/evaluate", content=body, headers={"Content-Type": ct, "Accept": "application/json"})
    assert (r.status_code, rb.status_code) == (200, 200), (r.text, rb.text)
    local = LocalClient().evaluate(_sdk_request(doc, raw=True)).batches[0].coordinate.tolist()
    assert r.json()["batches"][0]["coordinate"] == rb.json()["batches"][0]["coordinate"] == local


@pytest.mark.parametrize("field", ["offset", "prev_coordinate"])
def test_non_finite_state_in_process_names_the_joint(field):
    args = read(orjson.dumps(REVOLUTE))
    j = args["batches"][0]
    bad = np.array([np.nan])
    args["batches"] = [type(j)(**{**j.__dict__, field: bad})]
    with pytest.raises(InputError) as e:
        evaluate(**args)
    assert [f.loc for f in e.value.faults] == [("batches", 0, field, 0)]


def test_v1_request_answers_coordinate_equal_to_x():
    doc = copy.deepcopy(REVOLUTE)
    for k in ("offset", "prev_coordinate"):
        doc["batches"][0].pop(k)
    with TestClient(app) as client:
        b = client.post("/v1/evaluate", json=doc).json()["batches"][0]
    assert b["coordinate"] == b["x"]


def test_joint_handle_reads_the_coordinate():
    """Scene offsets reach the answer; `result.joint(handle).coordinate` is x + offset (None when not answered)."""
    from jointlimits.client import Scene
    from tests.scenes import rotation_about

    scene = Scene()
    a = scene.add_body(np.eye(4))
    turned = np.eye(4)
    turned[:3, :3] = rotation_about(np.array([0.0, 0.0, 1.0]), 0.7)
    b = scene.add_body(turned, ref=np.eye(4))
    j = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=0.0, upper=0.5, strength=100.0, offset=0.25)
    k = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-1.0, upper=1.0)
    full = LocalClient().evaluate(scene.request())
    assert abs(full.joint(j).coordinate - 0.95) <= 1e-15 and abs(full.joint(k).coordinate - 0.7) <= 1e-15
    assert full.joint(j).energy > 0 and full.joint(k).energy == 0.0
    active = LocalClient().evaluate(scene.request(active_only=True))
    assert active.joint(j).coordinate == full.joint(j).coordinate and active.joint(k).coordinate is None


def test_sdk_takes_a_wire_dict_with_the_v11_fields():
    """A wire JSON dict with offset and prev_coordinate, given to the SDK as it is: the same answer as the server's."""
    from tests.core.test_golden_state import FIELDS, TOL
    from tests.conftest import relerr

    case = next(c for c in CASES if c["name"] == "revolute_turns_-2_above")
    ev = LocalClient().evaluate(copy.deepcopy(case["request"]))
    for got, want in zip(ev.batches, case["expect"]):
        for f in FIELDS:
            assert relerr(getattr(got, f), want[f]) <= TOL, f
