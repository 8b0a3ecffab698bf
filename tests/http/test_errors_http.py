"""Every error class: a precise 4xx (never 500, never a silent number) whose `loc` names field, batch and joint.

Semantic faults go through the SDK in every mode (binary and JSON over real HTTP, async,
local) and must name the same place; wire faults are raw JSON / msgpack bodies over real HTTP.
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import replace

import httpx
import msgpack
import numpy as np
import pytest

from jointlimits.client import AsyncClient, Client, InvalidInput, LocalClient, Request, Scene, codec
from jointlimits.schemas import binary as wire
from tests.http.test_contract_live import live  # noqa: F401 (fixture)

TURN = 0.7  # body 1 is turned by this about +z relative to body 0


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def base_request() -> Request:
    """3 bodies; batch 0: two revolute limits (670), batch 1: three prismatic limits (669)."""
    scene = Scene()
    a = scene.add_body((np.zeros(3), np.eye(3)))
    b = scene.add_body((np.zeros(3), rot_z(TURN)), ref=(np.zeros(3), np.eye(3)))
    c = scene.add_body((np.array([0.0, 0.0, 1.3]), np.eye(3)), ref=(np.array([0.0, 0.0, 1.0]), np.eye(3)))
    scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5, strength=100.0)
    scene.add_revolute_limit(b, a, [0, 0, 0], [0, 0, 1], lower=-1.0, upper=1.0)
    for k in range(3):
        scene.add_prismatic_limit(a, c, [0, 0, 0], [0, 0, 1], lower=-0.1 * k, upper=0.2, strength=10.0)
    return scene.request()


def with_batch(r: Request, b: int, **fields) -> Request:
    batches = list(r.batches)
    batches[b] = replace(batches[b], **fields)
    return replace(r, batches=batches)


def edit(r: Request, b: int, name: str, row: int, value) -> Request:
    a = np.array(getattr(r.batches[b], name), copy=True)
    a[row] = value
    return with_batch(r, b, **{name: a})


def edit_body(r: Request, name: str, row: int, value, cols=slice(None)) -> Request:
    a = np.array(getattr(r, name), copy=True)
    a[row, cols] = value
    return replace(r, **{name: a})


def _far_edge(r: Request) -> Request:
    return edit(r, 1, "edges", 2, [[-1e308, 0, 0], [1e308, 0, 0]])


# name, mutation of the base request, expected loc (after "body"), words of the message (binary and local).
SEMANTIC = [
    ("lower_gt_upper", lambda r: edit(r, 1, "lower", 2, 5.0), ("batches", 1, "lower", 2), "> upper"),
    ("strength_negative", lambda r: edit(r, 1, "strength", 2, -1.0), ("batches", 1, "strength", 2), "< 0"),
    ("lower_nan", lambda r: edit(r, 1, "lower", 2, np.nan), ("batches", 1, "lower", 2), "finite"),
    ("upper_inf", lambda r: edit(r, 0, "upper", 1, np.inf), ("batches", 0, "upper", 1), "finite"),
    ("edge_nan", lambda r: edit(r, 1, "edges", 1, np.nan), ("batches", 1, "edges", 1), "finite"),
    ("q_inf", lambda r: edit_body(r, "q", 1, np.inf, 5), ("bodies", "q", 1), "finite"),
    ("q_ref_nan", lambda r: edit_body(r, "q_ref", 2, np.nan, 0), ("bodies", "q_ref", 2), "finite"),
    ("body_index_out_of_range", lambda r: edit(r, 1, "body_ids", 2, [0, 3]), ("batches", 1, "body_ids", 2), "out of range"),
    ("body_index_negative", lambda r: edit(r, 0, "body_ids", 1, [-1, 0]), ("batches", 0, "body_ids", 1), "out of range"),
    ("joint_on_itself", lambda r: edit(r, 1, "body_ids", 0, [2, 2]), ("batches", 1, "body_ids", 0), "itself"),
    ("zero_length_edge", lambda r: edit(r, 1, "edges", 2, [[0, 0, 1], [0, 0, 1]]), ("batches", 1, "edges", 2), "zero-length"),
    ("edge_overflows", _far_edge, ("batches", 1, "edges", 2), "overflows"),
    ("singular_A_ref", lambda r: edit_body(r, "q_ref", 2, 0.0, slice(3, 12)), ("bodies", "q_ref", 2), "singular"),
    ("uid_pairing_670_20", lambda r: with_batch(r, 0, base_uid=20), ("batches", 0, "base_uid"), "needs base_uid 18"),
    ("uid_pairing_669_18", lambda r: with_batch(r, 1, base_uid=18), ("batches", 1, "base_uid"), "needs base_uid 20"),
    ("unknown_uid", lambda r: with_batch(r, 1, constitution_uid=671), ("batches", 1, "constitution_uid"), "unknown"),
    ("unknown_output", lambda r: replace(r, outputs=("energy", "jacobian")), ("outputs", 1), "'energy', 'gradient' or 'hessian'"),
    ("no_outputs", lambda r: replace(r, outputs=()), ("outputs",), ""),
    ("unknown_hessian_mode", lambda r: replace(r, hessian_mode="fast"), ("hessian_mode",), "'exact' or 'psd'"),
    ("lengths_mismatch", lambda r: with_batch(r, 1, lower=r.batches[1].lower[:2]), ("batches", 1, "lower"), "shape"),
    ("rows_mismatch", lambda r: replace(r, q_prev=r.q_prev[:2]), ("bodies", "q_prev"), "rows"),
    ("collapsed_frame", lambda r: edit_body(r, "q", 1, 0.0, slice(3, 12)), ("batches", 0, "body_ids", 0), "collapses"),
    (
        "energy_overflow",
        lambda r: with_batch(r, 0, lower=np.array([0.0, -1.0]), upper=np.array([1e-300, 1.0]), strength=np.array([1e308, 1.0])),
        ("batches", 0, "strength", 0),
        "overflow",
    ),
    (
        "psd_overflow",
        lambda r: replace(edit_body(r, "q", 2, 1e200, slice(3, 12)), hessian_mode="psd"),
        ("batches", 1),
        "overflow",
    ),
]
MODES = ["binary", "json", "async", "local"]


def _call(mode: str, url: str, request: Request):
    if mode == "local":
        return LocalClient().evaluate(request)
    if mode == "async":

        async def run():
            async with AsyncClient(url) as c:
                return await c.evaluate(request)

        return asyncio.run(run())
    with Client(url, binary=mode == "binary") as c:
        return c.evaluate(request)


def test_the_base_request_is_valid(live):
    ev = Client(live).evaluate(base_request())
    assert ev.batches[0].x[0] == pytest.approx(TURN) and ev.batches[0].energy[0] == pytest.approx(100 * 0.2**3)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize(("name", "mutate", "loc", "words"), SEMANTIC, ids=[c[0] for c in SEMANTIC])
def test_semantic_fault_names_batch_and_joint(live, mode, name, mutate, loc, words):
    with pytest.raises(InvalidInput) as err:
        _call(mode, live, mutate(base_request()))
    e = err.value
    assert e.status == 422
    assert e.loc[: len(loc) + 1] == ("body", *loc), e.faults
    if mode != "json":  # JSON carries NaN as null, which pydantic names itself (same loc, its own words)
        assert words in e.msg, e.msg
    assert all(f.msg for f in e.faults)


def _json(**changes) -> dict:
    body, _ = codec.encode(base_request(), binary=False)
    doc = json.loads(body)
    doc.update(changes)
    return doc


def _dumps(doc) -> bytes:
    return json.dumps(doc).encode()


def _with_token(token: str, path: tuple) -> bytes:
    """The base request with the number at `path` replaced by a raw JSON token (NaN, 1e400, ...)."""
    doc = _json()
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = "@@"
    return _dumps(doc).replace(b'"@@"', token.encode())


def _bin(mutate=None) -> bytes:
    doc = msgpack.unpackb(codec.encode(base_request(), binary=True)[0])
    if mutate:
        mutate(doc)
    return msgpack.packb(doc)


def _set(path, value):
    def mutate(doc):
        node = doc
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value

    return mutate


def _drop(path):
    def mutate(doc):
        node = doc
        for k in path[:-1]:
            node = node[k]
        del node[path[-1]]

    return mutate


_F8 = lambda a: wire.pack_array(np.asarray(a, dtype=float), "<f8")  # noqa: E731
J, B = "application/json", "application/msgpack"
# name, content type, body, status, loc
WIRE = [
    ("json_1e400", J, _with_token("1e400", ("bodies", "q", 0, 11)), 422, ["body", "bodies", "q", 0, 11]),
    ("json_bare_NaN", J, _with_token("NaN", ("batches", 1, "lower", 2)), 422, ["body", "batches", 1, "lower", 2]),
    ("json_Infinity", J, _with_token("Infinity", ("batches", 0, "edges", 1, 1, 2)), 422, ["body", "batches", 0, "edges", 1, 1, 2]),
    ("json_minus_Infinity", J, _with_token("-Infinity", ("batches", 1, "strength", 0)), 422, ["body", "batches", 1, "strength", 0]),
    ("json_minus_1e400", J, _with_token("-1e400", ("bodies", "q_prev", 2, 0)), 422, ["body", "bodies", "q_prev", 2, 0]),
    ("json_row_of_11", J, _with_token("[1,2,3,4,5,6,7,8,9,10,11]", ("bodies", "q", 1)), 422, ["body", "bodies", "q", 1]),
    ("json_row_of_13", J, _with_token("[" + ",".join(["0"] * 13) + "]", ("bodies", "q_ref", 0)), 422, ["body", "bodies", "q_ref", 0]),
    ("json_point_of_2", J, _with_token("[0, 1]", ("batches", 1, "edges", 2, 1)), 422, ["body", "batches", 1, "edges", 2, 1]),
    ("json_pair_of_3", J, _with_token("[0, 1, 2]", ("batches", 1, "body_ids", 2)), 422, ["body", "batches", 1, "body_ids", 2]),
    ("json_float_body_id", J, _with_token("1.5", ("batches", 1, "body_ids", 2, 0)), 422, ["body", "batches", 1, "body_ids", 2, 0]),
    ("json_body_id_2_63", J, _with_token(str(2**63), ("batches", 0, "body_ids", 0, 1)), 422, ["body", "batches", 0, "body_ids", 0, 1]),
    ("json_string_number", J, _with_token('"0.5"', ("batches", 1, "upper", 1)), 422, ["body", "batches", 1, "upper", 1]),
    ("json_string_uid", J, _with_token('"670"', ("batches", 0, "constitution_uid")), 422, ["body", "batches", 0, "constitution_uid"]),
    ("json_huge_uid", J, _with_token("1" + "0" * 30, ("batches", 0, "constitution_uid")), 422, ["body", "batches", 0, "constitution_uid"]),
    ("json_missing_q_ref", J, _dumps({**_json(), "bodies": {k: v for k, v in _json()["bodies"].items() if k != "q_ref"}}), 422, ["body", "bodies", "q_ref"]),
    ("json_misspelt_field", J, _dumps(_json(batchs=[])), 422, ["body", "batchs"]),
    ("json_truncated", J, _dumps(_json())[:-7], 422, ["body"]),
    ("json_top_level_array", J, b"[1, 2, 3]", 422, ["body"]),
    ("json_empty_body", J, b"", 422, ["body"]),
    ("json_deep_nesting", J, b"[" * 100_000 + b"]" * 100_000, 422, ["body"]),
    ("json_outputs_empty", J, _dumps(_json(outputs=[])), 422, ["body", "outputs"]),
    ("json_outputs_unknown", J, _dumps(_json(outputs=["energy", "jacobian"])), 422, ["body", "outputs", 1]),
    ("json_hessian_mode_unknown", J, _dumps(_json(hessian_mode="fast")), 422, ["body", "hessian_mode"]),
    ("json_active_only_junk", J, _dumps(_json(active_only="maybe")), 422, ["body", "active_only"]),
    ("json_not_utf8", J, b'{"bodies": "\xff\xfe"}', 422, ["body"]),
    ("bin_garbage", B, b"\xc1\x00\x01", 422, ["body"]),
    ("bin_trailing_bytes", B, _bin() + b"\x00", 422, ["body"]),
    ("bin_top_level_array", B, msgpack.packb([1, 2]), 422, ["body"]),
    ("bin_big_endian", B, _bin(_set(("bodies", "q", "dtype"), ">f8")), 422, ["body", "bodies", "q"]),
    ("bin_shape_vs_data", B, _bin(_set(("bodies", "q", "shape"), [2, 12])), 422, ["body", "bodies", "q"]),
    ("bin_huge_shape_claim", B, _bin(_set(("bodies", "q_prev", "shape"), [2**40, 12])), 422, ["body", "bodies", "q_prev"]),
    ("bin_negative_shape", B, _bin(_set(("batches", 1, "lower", "shape"), [-3])), 422, ["body", "batches", 1, "lower"]),
    ("bin_plain_list", B, _bin(_set(("batches", 1, "upper"), [0.1, 0.2, 0.3])), 422, ["body", "batches", 1, "upper"]),
    ("bin_wrong_ndim", B, _bin(_set(("batches", 1, "edges"), _F8(np.zeros((3, 6))))), 422, ["body", "batches", 1, "edges"]),
    ("bin_float_ids", B, _bin(_set(("batches", 0, "body_ids"), _F8(np.zeros((2, 2))))), 422, ["body", "batches", 0, "body_ids"]),
    ("bin_row_of_11", B, _bin(_set(("bodies", "q"), _F8(np.zeros((3, 11))))), 422, ["body", "bodies", "q"]),
    ("bin_float_uid", B, _bin(_set(("batches", 0, "constitution_uid"), 670.0)), 422, ["body", "batches", 0, "constitution_uid"]),
    ("bin_uint64_uid", B, _bin(_set(("batches", 0, "base_uid"), 2**64 - 1)), 422, ["body", "batches", 0, "base_uid"]),
    ("bin_misspelt_field", B, _bin(_set(("batches", 1, "lowr"), 1)), 422, ["body", "batches", 1, "lowr"]),
    ("bin_missing_batches", B, _bin(_drop(("batches",))), 422, ["body", "batches"]),
    ("bin_missing_upper", B, _bin(_drop(("batches", 1, "upper"))), 422, ["body", "batches", 1, "upper"]),  # strength may be absent
    ("bin_outputs_not_list", B, _bin(_set(("outputs",), "energy")), 422, ["body", "outputs"]),
    ("bin_active_only_int", B, _bin(_set(("active_only",), 1)), 422, ["body", "active_only"]),
    ("bin_nan_bits", B, _bin(_set(("batches", 1, "lower"), _F8([0.0, np.nan, 0.0]))), 422, ["body", "batches", 1, "lower", 1]),
    ("bin_1e400_is_inf", B, _bin(_set(("batches", 1, "upper"), _F8([0.2, np.inf, 0.2]))), 422, ["body", "batches", 1, "upper", 1]),
    ("bin_lower_gt_upper", B, _bin(_set(("batches", 1, "lower"), _F8([0.0, 0.0, 9.0]))), 422, ["body", "batches", 1, "lower", 2]),
    ("bin_body_index_oob", B, _bin(_set(("batches", 1, "body_ids"), wire.pack_array(np.array([[0, 2], [0, 2], [0, -7]]), "<i8"))), 422, ["body", "batches", 1, "body_ids", 2]),
]


@pytest.mark.parametrize(("name", "content_type", "body", "status", "loc"), WIRE, ids=[c[0] for c in WIRE])
def test_wire_fault(live, name, content_type, body, status, loc):
    r = httpx.post(f"{live}/v1/evaluate", content=body, headers={"Content-Type": content_type})
    assert r.status_code == status, r.text[:300]
    assert r.headers["content-type"] == "application/json"  # errors are always JSON
    detail = r.json()["detail"]
    assert detail and all(d["msg"] for d in detail)
    assert any(d["loc"][: len(loc)] == loc for d in detail), detail


def _joints_json(n: int, key: bytes = b'"lower"') -> bytes:
    r = base_request()
    big = replace(
        r.batches[1],
        body_ids=np.tile(r.batches[1].body_ids[:1], (n, 1)),
        edges=np.tile(r.batches[1].edges[:1], (n, 1, 1)),
        lower=np.full(n, -0.1),
        upper=np.full(n, 0.2),
        strength=np.full(n, 1.0),
    )
    return codec.encode(replace(r, batches=[big]), binary=False)[0].replace(b'"lower"', key)


def test_413_by_declared_length_before_reading(live):
    r = httpx.post(f"{live}/v1/evaluate", content=b" " * 2_000_001, headers={"Content-Type": J})
    assert r.status_code == 413 and r.json()["detail"][0]["loc"] == ["body"]


def test_413_while_streaming_without_length(live):
    def chunks():
        for _ in range(40):
            yield b" " * 100_000

    r = httpx.post(f"{live}/v1/evaluate", content=chunks(), headers={"Content-Type": J})
    assert r.status_code == 413, r.text
    assert "2000000" in r.json()["detail"][0]["msg"]


@pytest.mark.parametrize("binary", [False, True])
def test_413_too_many_joints(live, binary):
    r = base_request()
    n = 401  # the live server allows 400
    many = replace(r, batches=[replace(r.batches[1], body_ids=np.tile([[0, 2]], (n, 1)), edges=np.tile(r.batches[1].edges[:1], (n, 1, 1)), lower=np.zeros(n), upper=np.ones(n), strength=np.ones(n))])
    body, content_type = codec.encode(many, binary=binary)
    resp = httpx.post(f"{live}/v1/evaluate", content=body, headers={"Content-Type": content_type})
    assert resp.status_code == 413
    d = resp.json()["detail"][0]
    assert d["loc"] == ["body", "batches"] and "401 joints" in d["msg"] and "400" in d["msg"]


def test_413_joints_even_when_keys_hide_from_the_byte_scan(live):
    r = httpx.post(f"{live}/v1/evaluate", content=_joints_json(401, b'"\\u006cower"'), headers={"Content-Type": J})
    assert r.status_code == 413 and "401 joints" in r.json()["detail"][0]["msg"]
    assert httpx.post(f"{live}/v1/evaluate", content=_joints_json(400), headers={"Content-Type": J}).status_code == 200


def test_415_unknown_content_type(live):
    r = httpx.post(f"{live}/v1/evaluate", content=b"q=1", headers={"Content-Type": "application/x-www-form-urlencoded"})
    assert r.status_code == 415 and r.json()["detail"][0]["loc"] == ["header", "content-type"]


def test_406_unacceptable_accept(live):
    r = httpx.post(f"{live}/v1/evaluate", json=_json(), headers={"Accept": "text/html"})
    assert r.status_code == 406 and r.json()["detail"][0]["loc"] == ["header", "accept"]


def test_faults_are_capped_and_all_located(live):
    """A million-joint-style mistake gets a readable answer: every bad joint up to the cap, each named."""
    doc = _json()
    doc["batches"][1]["lower"] = [9.0, 9.0, 9.0]
    doc["batches"][0]["strength"] = [-1.0, -2.0]
    r = httpx.post(f"{live}/v1/evaluate", json=doc)
    locs = [d["loc"] for d in r.json()["detail"]]
    assert r.status_code == 422
    assert ["body", "batches", 0, "strength", 1] in locs and ["body", "batches", 1, "lower", 2] in locs


@pytest.mark.parametrize("mode", MODES)
def test_empty_batches_and_no_bodies_are_valid(live, mode):
    r = base_request()
    empty = replace(r.batches[0], body_ids=np.zeros((0, 2), np.int64), edges=np.zeros((0, 2, 3)), lower=np.zeros(0), upper=np.zeros(0), strength=np.zeros(0))
    ev = _call(mode, live, replace(r, batches=[empty, r.batches[1], empty]))
    assert [len(b.index) for b in ev.batches] == [0, 3, 0] and ev.batches[2].hessian.shape == (0, 24, 24)
    assert _call(mode, live, replace(r, q=np.zeros((0, 12)), q_prev=np.zeros((0, 12)), q_ref=np.zeros((0, 12)), batches=[])).batches == []
    with pytest.raises(InvalidInput) as err:  # an empty batch is still checked, and named in the caller's numbering
        _call(mode, live, replace(r, batches=[r.batches[1], replace(empty, base_uid=20)]))
    assert err.value.loc == ("body", "batches", 1, "base_uid")
