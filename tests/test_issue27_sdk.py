"""Issue 27 (items 4 and 6): the SDK keeps a wire document's `layout`; a `null` array is one fault on every path;
`Scene` checks a joint where it is added; `GET /` points to the docs; the SDK's token from the environment."""

from __future__ import annotations

import asyncio
import json

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import AsyncClient, Client, InvalidInput, LocalClient
from jointlimits.schemas import EvaluateRequest
from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.test_contract_live import live  # noqa: F401 (fixture)
from tests.test_one_fault_every_path import base_doc

# ---------------------------------------------------------------- 1. `layout` of a wire document


def bodies_doc() -> dict:
    return {**base_doc(), "layout": "bodies"}


def wire_forms() -> dict[str, object]:
    """The document in each form `evaluate` and `session` take besides a `Request`."""
    return {"dict": bodies_doc(), "EvaluateRequest": EvaluateRequest.model_validate(bodies_doc())}


def assert_per_body(ev) -> None:
    assert ev.assembled is not None and ev.assembled.gradient.shape == (3, 12)
    assert all(b.gradient is None and b.hessian is None for b in ev.batches)


def test_posting_the_document_answers_assembled():
    r = TestClient(create_app(Settings(token=None, cors_origins=()))).post("/v1/evaluate", json=bodies_doc())
    assert r.status_code == 200 and "assembled" in r.json()


@pytest.mark.parametrize("form", ["dict", "EvaluateRequest"])
def test_local_client_keeps_the_layout_of_a_document(form):
    assert_per_body(LocalClient().evaluate(wire_forms()[form]))
    with LocalClient().session(wire_forms()[form]) as s:
        assert_per_body(s.evaluate(base_doc()["bodies"]["q"]))


@pytest.mark.parametrize("binary", [True, False], ids=["msgpack", "json"])
@pytest.mark.parametrize("form", ["dict", "EvaluateRequest"])
def test_http_clients_keep_the_layout_of_a_document(live, form, binary):  # noqa: F811
    with Client(live, binary=binary) as c:
        assert_per_body(c.evaluate(wire_forms()[form]))
        with c.session(wire_forms()[form]) as s:
            assert_per_body(s.evaluate(base_doc()["bodies"]["q"]))

    async def run():
        async with AsyncClient(live, binary=binary) as c:
            return await c.evaluate(wire_forms()[form])

    assert_per_body(asyncio.run(run()))


# ---------------------------------------------------------------- 2. a `null` array, from the SDK's arrays too

NULLS = {("batches", 1, "lower"), ("batches", 0, "body_ids"), ("bodies", "q_prev"), ("batches", 1, "strength")}


def null_request(loc: tuple):
    """The base request with None where the wire document would have `null` at `loc`."""
    from tests.test_one_fault_every_path import put, to_request

    doc = base_doc()
    put(*loc, value=None)(doc)
    return to_request(doc)


def faults_of(fn) -> list:
    with pytest.raises(InvalidInput) as e:
        fn()
    return [(f.loc, f.msg, f.type) for f in e.value.faults]


@pytest.mark.parametrize("loc", sorted(NULLS, key=str))
def test_a_none_array_in_the_sdks_arrays_is_the_services_null_fault(live, loc):  # noqa: F811
    want = [(("body", *loc), "Input should be a valid list", "list_type")]
    assert faults_of(lambda: LocalClient().evaluate(null_request(loc))) == want
    assert faults_of(lambda: LocalClient().session(null_request(loc))) == want
    for binary in (True, False):
        with Client(live, binary=binary) as c:
            assert faults_of(lambda: c.evaluate(null_request(loc))) == want
            assert faults_of(lambda: c.session(null_request(loc))) == want

    async def run():
        async with AsyncClient(live) as c:
            await c.evaluate(null_request(loc))

    assert faults_of(lambda: asyncio.run(run())) == want
