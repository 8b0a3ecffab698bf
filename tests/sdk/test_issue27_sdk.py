"""Issue 27 (items 4 and 6): the SDK keeps a wire document's `layout`; a `null` array is one fault on every path;
`Scene` checks a joint where it is added; `GET /` points to the docs; the SDK's token from the environment."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import AsyncClient, Client, InvalidInput, LocalClient
from jointlimits.schemas import EvaluateRequest
from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.http.test_contract_live import live  # noqa: F401 (fixture)
from tests.http.test_one_fault_every_path import base_doc

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
            async with c.session(wire_forms()[form]) as s:
                assert_per_body(await s.evaluate(base_doc()["bodies"]["q"]))
            return await c.evaluate(wire_forms()[form])

    assert_per_body(asyncio.run(run()))


# ---------------------------------------------------------------- 2. a `null` array, from the SDK's arrays too

NULLS = {("batches", 1, "lower"), ("batches", 0, "body_ids"), ("bodies", "q_prev"), ("batches", 1, "strength")}


def null_request(loc: tuple):
    """The base request with None where the wire document would have `null` at `loc`."""
    from tests.http.test_one_fault_every_path import put, to_request

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


# ---------------------------------------------------------------- 3. `Scene` checks a joint where it is added


def two_bodies():
    from jointlimits.client import Scene

    scene = Scene()
    scene.add_body(np.eye(4))
    scene.add_body(np.eye(4))
    return scene


EDGE = ([0, 0, 0], [0, 0, 1])
# The mistake (arguments of add_revolute_limit after the two bodies) -> (loc, msg, type) Scene raises.
SCENE_MISTAKES = {
    "lower > upper": (dict(i=0, j=1, lower=5.0, upper=0.2),
                      ("lower",), "lower 5.0 > upper 0.2: the range is empty", "value_error"),
    "a body not added": (dict(i=0, j=2, lower=-1, upper=1),
                         ("j",), "body index [0, 2] out of range [0, 2) (there are 2 bodies)", "value_error"),
    "a negative body": (dict(i=-1, j=1, lower=-1, upper=1),
                        ("i",), "body index [-1, 1] out of range [0, 2) (there are 2 bodies)", "value_error"),
    "one body": (dict(i=1, j=1, lower=-1, upper=1), ("j",), "joint couples body 1 to itself", "value_error"),
    "strength < 0": (dict(i=0, j=1, lower=-1, upper=1, strength=-1.0),
                     ("strength",), "strength -1.0 < 0: must be >= 0", "value_error"),
    "a NaN bound": (dict(i=0, j=1, lower=float("nan"), upper=1), ("lower",), "Input should be a finite number", "finite_number"),
    "a zero-length edge": (dict(i=0, j=1, p0=[0, 0, 1], p1=[0, 0, 1], lower=-1, upper=1),
                           ("p1",), "zero-length edge: p0 == p1 gives no joint axis", "value_error"),
    "an infinite point": (dict(i=0, j=1, p0=[0, 0, float("inf")], lower=-1, upper=1),
                          ("p0", 2), "Input should be a finite number", "finite_number"),
    "an unknown origin": (dict(i=0, j=1, lower=-1, upper=1, origin="world"),
                          ("origin",), "Input should be 'q_ref' or 'absolute'", "literal_error"),
    "an edge too long": (dict(i=0, j=1, p0=[-1e308, 0, 0], p1=[1e308, 0, 0], lower=-1, upper=1),
                         ("p1",), "edge too long: p1 - p0 overflows float64", "value_error"),
    "a list for a bound": (dict(i=0, j=1, lower=[-1, -2], upper=1), ("lower",), "must be one number, got shape (2,)", "value_error"),
    # A body is an integer, as the wire's body_ids and JointBatch.of say: 1.7 was truncated to body 1 (another
    # joint than asked, silently), "1" and True taken as 1, an array a bare numpy TypeError.
    "a float body": (dict(i=0, j=1.7, lower=-1, upper=1), ("j",), "Input should be a valid integer", "int_type"),
    "a float body 0.0": (dict(i=0.0, j=1, lower=-1, upper=1), ("i",), "Input should be a valid integer", "int_type"),
    "a string body": (dict(i=0, j="1", lower=-1, upper=1), ("j",), "Input should be a valid integer", "int_type"),
    "a bool body": (dict(i=False, j=1, lower=-1, upper=1), ("i",), "Input should be a valid integer", "int_type"),
    "an array body": (dict(i=0, j=np.array([1]), lower=-1, upper=1), ("j",), "Input should be a valid integer", "int_type"),
}


def test_scene_takes_numpy_integers_for_bodies():
    scene = two_bodies()
    scene.add_revolute_limit(np.int64(0), np.int32(1), *EDGE, lower=-1, upper=1)
    assert scene.request().batches[0].body_ids.tolist() == [[0, 1]]


@pytest.mark.parametrize("name", SCENE_MISTAKES)
def test_scene_refuses_a_bad_joint_at_the_call_naming_the_argument(name):
    kwargs, loc, msg, kind = SCENE_MISTAKES[name]
    kwargs = {"p0": EDGE[0], "p1": EDGE[1], **kwargs}
    scene = two_bodies()
    with pytest.raises(ValueError) as e:
        scene.add_revolute_limit(**kwargs)
    assert isinstance(e.value, InvalidInput) and "invalid input (Scene.add_revolute_limit)" in str(e.value)
    if name == "lower > upper":  # docs/sdk.md quotes it
        assert str(e.value) == "invalid input (Scene.add_revolute_limit): lower: lower 5.0 > upper 0.2: the range is empty"
    assert [(f.loc, f.msg, f.type) for f in e.value.faults] == [(loc, msg, kind)]
    assert scene.request().batches == []  # nothing was added
    with pytest.raises(InvalidInput, match="Scene.add_prismatic_limit"):
        scene.add_prismatic_limit(**kwargs)


def test_scene_local_edges_and_the_services_words():
    scene = two_bodies()
    with pytest.raises(InvalidInput) as e:
        scene.add_prismatic_limit(0, 1, local_edge=[[[0, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 1]]], lower=-1, upper=1)
    assert [(f.loc, f.msg) for f in e.value.faults] == [(("local_edge",), "zero-length edge: l0 == l1 gives no joint axis")]
    # The service says the same of the same joint (the errors table's `lower > upper` row, here batch 0).
    scene.add_revolute_limit(0, 1, *EDGE, lower=-1, upper=1)
    bad = scene.request()
    bad.batches[0].lower[0] = 5.0
    with pytest.raises(InvalidInput) as service:
        LocalClient().evaluate(bad)
    assert service.value.msg == "lower 5.0 > upper 1.0: the range is empty"
    with pytest.raises(InvalidInput) as sdk:
        scene.add_revolute_limit(0, 1, *EDGE, lower=5.0, upper=1.0)
    assert sdk.value.msg == service.value.msg


# ---------------------------------------------------------------- 4. `GET /` points to the docs


def test_the_root_redirects_to_the_docs_and_stays_out_of_the_schema():
    c = TestClient(create_app(Settings(token="s3cret", cors_origins=())))  # open, as /docs is, with a token set
    r = c.get("/", follow_redirects=False)
    assert r.status_code == 307 and r.headers["location"] == "/docs"
    assert c.get("/").status_code == 200 and "swagger" in c.get("/").text.lower()
    assert "/" not in c.get("/openapi.json").json()["paths"]
    # Behind a proxy that mounts the service under a prefix, the redirect keeps it (as /docs finds its openapi.json).
    mounted = TestClient(create_app(Settings(token=None, cors_origins=())), root_path="/jl")
    assert mounted.get("/", follow_redirects=False).headers["location"] == "/jl/docs"


# ---------------------------------------------------------------- 5. the SDK's token from the environment


def test_the_sdk_takes_the_servers_token_variable(monkeypatch):
    from jointlimits.client import ServiceError
    from tests.http.test_contract_live import serve

    monkeypatch.setenv("JOINTLIMITS_TOKEN", "s3cret")
    assert Settings().token == "s3cret"  # the server's setting of the same name
    with serve(Settings(max_body_bytes=2_000_000, max_joints=400, token="s3cret", cors_origins=())) as url:
        doc = base_doc()
        for binary in (True, False):
            with Client(url, binary=binary) as c:
                assert c.evaluate(doc).total_energy > 0
                with c.session(doc) as s:
                    assert s.evaluate(doc["bodies"]["q"]).total_energy > 0

        async def run(**kw):
            async with AsyncClient(url, **kw) as c:
                return await c.evaluate(doc)

        assert asyncio.run(run()).total_energy > 0
        # A token passed wins over the variable; "" sends none.
        for token in ("wrong", ""):
            with pytest.raises(ServiceError) as e, Client(url, token=token) as c:
                c.evaluate(doc)
            assert e.value.status == 401
        monkeypatch.delenv("JOINTLIMITS_TOKEN")
        with pytest.raises(ServiceError) as e:
            asyncio.run(run())
        assert e.value.status == 401
        monkeypatch.setenv("JOINTLIMITS_TOKEN", "")  # empty: unset, as the server reads it
        with pytest.raises(ServiceError) as e, Client(url) as c:
            c.evaluate(doc)
        assert e.value.status == 401


@pytest.mark.parametrize("token", ["a\nb", "tab\there", " lead", "trail ", "caf\u00e9"])
def test_a_token_no_header_can_carry_is_named_at_construction(token, monkeypatch):
    """Before, `Client(token="a\\nb").evaluate` raised httpx's LocalProtocolError and a session WrongURL ("no
    joint-limit service"); now both clients refuse it where it is given, naming the argument or the variable."""
    for make in (Client, AsyncClient):
        with pytest.raises(ValueError, match=r"^token: a bearer token is printable ASCII"):
            make("http://127.0.0.1:9", token=token)
        monkeypatch.setenv("JOINTLIMITS_TOKEN", token)
        with pytest.raises(ValueError, match=r"^JOINTLIMITS_TOKEN: a bearer token"):
            make("http://127.0.0.1:9")
        monkeypatch.delenv("JOINTLIMITS_TOKEN")
    with Client("http://127.0.0.1:9", token="Abc-._~+/=") as client:  # RFC 6750's characters pass
        assert client._headers["Authorization"] == "Bearer Abc-._~+/="
