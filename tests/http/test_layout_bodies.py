"""`layout="bodies"` over HTTP (JSON and msgpack) and in the SDK (HTTP, async, local, split requests).

Each answer is compared with the scatter-add of the same request's per-joint answer; the live
server (tests/http/test_contract_live.py) accepts at most 400 joints, so a 1000-joint request is split.
"""

from __future__ import annotations

import asyncio
from dataclasses import replace

import httpx
import msgpack
import numpy as np
import pytest

from bench import measure as M
from bench.scenes import make_scene
from jointlimits.client import AsyncClient, Client, JointBatch, LocalClient, Request
from jointlimits.schemas import binary as wire
from jointlimits.service.core import evaluate
from tests.assembled_ref import assemble
from tests.http.test_contract_live import live  # noqa: F401 (fixture)


def sdk_request(n: int, seed: int, **kw) -> Request:
    bodies, batches = make_scene(n, 0.5, seed=seed)
    return Request(bodies.q, bodies.q_prev, bodies.q_ref,
                   [JointBatch(j.constitution_uid, j.body_ids, j.edges, j.lower, j.upper, j.strength) for j in batches],
                   **kw)


def expected(req: Request, mode: str = "exact"):
    bodies, batches = M.from_request(M.to_request(*make_scene_of(req)))
    ev = evaluate(bodies, batches, hessian_mode=mode)
    return assemble(bodies.q.shape[0], batches, ev, False)


def make_scene_of(req: Request):
    from jointlimits.service.core import Bodies, Joints

    return Bodies(req.q, req.q_prev, req.q_ref), [
        Joints(b.constitution_uid, b.base_uid, b.body_ids, b.edges, b.lower, b.upper, b.strength) for b in req.batches]


def same(got, want) -> None:
    assert got.n_bodies == want.n_bodies
    np.testing.assert_allclose(got.gradient, want.gradient, rtol=0, atol=1e-14 * np.abs(want.gradient).max())
    assert np.array_equal(got.rows, want.rows) and np.array_equal(got.cols, want.cols)
    np.testing.assert_allclose(got.blocks, want.blocks, rtol=0, atol=1e-14 * np.abs(want.blocks).max())


@pytest.mark.parametrize("binary", [False, True], ids=["json", "msgpack"])
@pytest.mark.parametrize("mode", ["exact", "psd"])
def test_sdk_over_http_equals_the_scatter_add(live, binary: bool, mode: str):
    req = sdk_request(60, 1, layout="bodies", hessian_mode=mode)
    with Client(live, binary=binary) as c:
        ev = c.evaluate(req)
    same(ev.assembled, expected(req, mode))
    assert all(b.gradient is None and b.hessian is None for b in ev.batches)
    assert sum(len(b.x) for b in ev.batches) == 60


def test_split_request_sums_the_parts(live):
    req = sdk_request(1000, 2, layout="bodies")  # > 400 joints: three parts, bodies renumbered per part
    with Client(live) as c:
        ev = c.evaluate(req)
    same(ev.assembled, expected(req))


def test_async_and_local_agree(live):
    req = sdk_request(50, 3, layout="bodies", active_only=True)

    async def go():
        async with AsyncClient(live) as c:
            return await c.evaluate(req)

    a = asyncio.run(go()).assembled
    b = LocalClient().evaluate(req).assembled
    same(a, expected(req))
    same(b, expected(req))
    M_ = pytest.importorskip("scipy.sparse")
    assert M_.issparse(b.matrix())


def test_raw_wire_documents(live):
    req = sdk_request(20, 4)
    body = M.to_request(*make_scene_of(req))
    body["layout"] = "bodies"
    r = httpx.post(f"{live}/v1/evaluate", json=body)
    assert r.status_code == 200, r.text
    doc = r.json()
    assert set(doc["assembled"]) == {"gradient", "rows", "cols", "blocks"}
    assert "gradient" not in doc["batches"][0] and "hessian" not in doc["batches"][0]
    want = expected(req)
    assert np.asarray(doc["assembled"]["gradient"]).shape == (want.n_bodies, 12)
    body["outputs"] = ["energy", "gradient"]
    packed = msgpack.packb({**body, "bodies": {k: wire.pack_array(np.asarray(v), wire.FLOAT64) for k, v in body["bodies"].items()},
                            "batches": [{**b, **{k: wire.pack_array(np.asarray(b[k]), wire.INT64 if k == "body_ids" else wire.FLOAT64)
                                                 for k in ("body_ids", "edges", "lower", "upper", "strength")}}
                                        for b in body["batches"]]})
    r = httpx.post(f"{live}/v1/evaluate", content=packed, headers={"content-type": wire.MEDIA_TYPE, "accept": wire.MEDIA_TYPE})
    assert r.status_code == 200, r.text
    doc = wire.loads(r.content)
    assert set(doc["assembled"]) == {"gradient"}


@pytest.mark.parametrize("binary", [False, True], ids=["json", "msgpack"])
def test_unknown_layout_is_a_422_naming_the_field(live, binary: bool):
    req = sdk_request(4, 5)
    body = M.to_request(*make_scene_of(req))
    body["layout"] = "rows"
    if binary:
        content = msgpack.packb(body)
        r = httpx.post(f"{live}/v1/evaluate", content=content, headers={"content-type": wire.MEDIA_TYPE})
    else:
        r = httpx.post(f"{live}/v1/evaluate", json=body)
    assert r.status_code == 422
    assert any(d["loc"][-1] == "layout" for d in r.json()["detail"]), r.text
    with pytest.raises(Exception, match="layout"):
        LocalClient().evaluate(replace(req, layout="rows"))


def assert_bitwise(got, want) -> None:
    """Bitwise, except the sign of a zero gradient entry: the SDK adds each part's gradient onto
    zeros (client/split.py), and 0.0 + -0.0 is 0.0."""
    assert got.n_bodies == want.n_bodies
    for k in ("gradient", "rows", "cols", "blocks"):
        a, b = getattr(got, k), getattr(want, k)
        assert (a is None) == (b is None), k
        if a is not None:
            assert a.dtype == b.dtype and a.shape == b.shape, k
            if k == "gradient":
                a, b = a + 0.0, b + 0.0  # -0.0 -> 0.0, every other value as it is
            assert np.array_equal(np.ascontiguousarray(a).view(np.uint8), np.ascontiguousarray(b).view(np.uint8)), k


@pytest.mark.parametrize("binary", [False, True], ids=["json", "msgpack"])
@pytest.mark.parametrize("mode", ["exact", "psd"])
def test_http_answers_the_local_bits(live, binary: bool, mode: str):
    # Not split (60 joints): the server's sums are the core's, bit for bit, with K > 0 and K = 0.
    with Client(live, binary=binary) as c:
        for outside in (0.5, 0.0):
            bodies, batches = make_scene(60, outside, seed=6)
            for active_only in (False, True):
                req = Request(bodies.q, bodies.q_prev, bodies.q_ref,
                              [JointBatch(j.constitution_uid, j.body_ids, j.edges, j.lower, j.upper, j.strength) for j in batches],
                              layout="bodies", hessian_mode=mode, active_only=active_only)
                local, remote = LocalClient().evaluate(req), c.evaluate(req)
                assert_bitwise(remote.assembled, local.assembled)
                assert (remote.assembled.blocks.shape[0] == 0) == (outside == 0.0)
                assert remote.total_energy == local.total_energy
