"""Contract v1 over real HTTP: golden cases in JSON and binary, SDK sync/async/local, bit-identical."""

from __future__ import annotations

import asyncio
import json
import re

import httpx
import msgpack
import numpy as np
import pytest

from jointlimits.client import AsyncClient, Client, LocalClient
from jointlimits.schemas import binary as wire
from tests.conftest import GOLDEN, relerr, same_evaluation
from tests.http.test_contract_live import LIMITS, live, sdk_request  # noqa: F401 (fixture)

TOL = 1e-12


@pytest.mark.parametrize("case", GOLDEN, ids=[c["name"] for c in GOLDEN])
def test_golden_identical_across_json_binary_async_and_local(live, case):
    request = sdk_request(case["request"])
    local = LocalClient().evaluate(request)
    with Client(live) as binary, Client(live, binary=False) as as_json:
        same_evaluation(binary.evaluate(request), local)
        same_evaluation(as_json.evaluate(request), local)

    async def run():
        async with AsyncClient(live) as a, AsyncClient(live, binary=False) as b:
            return await a.evaluate(request), await b.evaluate(request)

    for ev in asyncio.run(run()):
        same_evaluation(ev, local)
    for got, want in zip(local.batches, case["expect"]):
        for f in ("x", "energy", "gradient", "hessian"):
            assert relerr(getattr(got, f), want[f]) <= TOL, f


def test_raw_json_and_raw_binary_carry_the_same_bits(live):
    """Without the SDK: a plain JSON POST and a hand-made msgpack POST agree to the bit."""
    case = next(c for c in GOLDEN if c["name"] == "chain_shared_bodies")["request"]
    as_json = httpx.post(f"{live}/v1/evaluate", json=case)
    assert as_json.status_code == 200 and as_json.headers["content-type"] == "application/json"
    r = case
    doc = {
        "bodies": {k: wire.pack_array(np.array(v), "<f8") for k, v in r["bodies"].items()},
        "batches": [
            {
                "constitution_uid": b["constitution_uid"],
                "base_uid": b["base_uid"],
                "body_ids": wire.pack_array(np.array(b["body_ids"]), "<i8"),
                **{k: wire.pack_array(np.array(b[k], dtype=float), "<f8") for k in ("edges", "lower", "upper", "strength")},
            }
            for b in r["batches"]
        ],
    }
    as_bin = httpx.post(
        f"{live}/v1/evaluate", content=msgpack.packb(doc), headers={"Content-Type": "application/msgpack"}
    )
    assert as_bin.status_code == 200 and as_bin.headers["content-type"] == "application/msgpack"
    j, b = json.loads(as_json.content), msgpack.unpackb(as_bin.content)
    assert j["total_energy"] == b["total_energy"]
    for jb, bb in zip(j["batches"], b["batches"]):
        for f, dtype, ndim in (("index", "<i8", 1), ("x", "<f8", 1), ("energy", "<f8", 1), ("gradient", "<f8", 2), ("hessian", "<f8", 3)):
            arr = wire.unpack_array(bb[f], dtype, ndim)
            assert np.array_equal(np.array(jb[f], dtype=arr.dtype), arr), f


@pytest.mark.parametrize(
    ("content_type", "accept", "answer"),
    [
        ("application/json", None, "application/json"),
        ("application/msgpack", None, "application/msgpack"),
        ("application/x-msgpack", "*/*", "application/msgpack"),
        ("application/json", "application/msgpack", "application/msgpack"),
        ("application/msgpack", "application/json", "application/json"),
        ("application/json", "application/json;q=0.5, application/msgpack", "application/msgpack"),
        ("application/json; charset=utf-8", "text/html, application/*;q=0.1", "application/json"),
    ],
)
def test_content_negotiation(live, content_type, accept, answer):
    from jointlimits.client import codec

    request = sdk_request(GOLDEN[0]["request"])
    body, _ = codec.encode(request, binary="msgpack" in content_type)
    headers = {"Content-Type": content_type} | ({"Accept": accept} if accept else {})
    r = httpx.post(f"{live}/v1/evaluate", content=body, headers=headers)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == answer
    same_evaluation(codec.decode(r.content, r.headers["content-type"]), LocalClient().evaluate(request))


def test_discovery_lists_both_constitutions_with_spec_names(live):
    r = httpx.get(f"{live}/v1/constitutions")
    assert r.status_code == 200
    body = r.json()
    by_uid = {c["uid"]: c for c in body["constitutions"]}
    assert by_uid[670]["base_uid"] == 18 and by_uid[670]["name"] == "AffineBodyRevoluteJointLimit"
    assert by_uid[669]["base_uid"] == 20 and by_uid[669]["name"] == "AffineBodyPrismaticJointLimit"
    state = {670: {"init_angle": "offset", "angle": "prev_coordinate"}, 669: {"init_distance": "offset"}}  # v1.1
    for uid, c in by_uid.items():
        names = {a["name"]: a for a in c["attributes"]}
        geometry = {"position": "edges", "l_position0, l_position1, r_position0, r_position1": "local_edges"}  # v1.2
        assert set(names) == {"limit/lower", "limit/upper", "limit/strength", *state[uid], *geometry}
        assert {n: names[n]["field"] for n in geometry} == geometry
        assert "absolute" in c["origin"]
        assert names["limit/strength"]["default"] == 1.0 and names["limit/lower"]["default"] is None
        assert {n: names[n]["field"] for n in state[uid]} == state[uid]
        assert names[next(iter(state[uid]))]["default"] == 0.0  # the offset
    assert {a["unit"] for a in by_uid[670]["attributes"]} >= {"rad"}
    assert body["limits"] == {
        "max_body_bytes": 2_000_000,
        "max_joints": 400,
        **{k: getattr(LIMITS, k) for k in ("max_batches", "max_answer_bytes", "max_json_values")},
    }
    assert Client(live).constitutions().model_dump() == body
    assert [c.uid for c in LocalClient().constitutions().constitutions] == [c["uid"] for c in body["constitutions"]]


def _digits(token: str) -> str:
    mantissa = token.lstrip("-").lower().split("e")[0].replace(".", "")
    return mantissa.strip("0")


def test_json_floats_are_shortest_round_trip(live):
    """Every number of a JSON answer has exactly the significant digits of Python's shortest repr."""
    r = httpx.post(f"{live}/v1/evaluate", json=GOLDEN[4]["request"])
    tokens = re.findall(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?", r.text.split('"batches"', 1)[1])
    floats = [t for t in tokens if "." in t or "e" in t.lower()]
    assert len(floats) > 500
    for t in floats:
        assert _digits(t) == _digits(repr(float(t))), t
    assert "NaN" not in r.text and "Infinity" not in r.text
