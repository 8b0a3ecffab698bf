"""Contract v1.2 (body-local edges, `origin`, the engine's prismatic psd): the 50-digit cases through every
path (in-process, HTTP JSON and msgpack, `LocalClient`, sessions local and live in both encodings), and the
faults of the new fields, the same on each path."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import Client, InvalidInput, LocalClient
from jointlimits.client import codec
from jointlimits.client.model import as_request
from jointlimits.schemas import binary as wire
from jointlimits.service.app import app
from jointlimits.service.core import InputError, evaluate
import orjson

from jointlimits.service.http.convert import read
from tests.conftest import relerr
from tests.core.test_golden_state import _check as check_state_case
from tests.http.test_contract_live import serve

CASES = json.loads((Path(__file__).parents[1] / "golden_v12_cases.json").read_text())["cases"]
TOL = 1e-13  # every v1.2 case is in the well-conditioned family
FIELDS = ("x", "coordinate", "energy", "gradient", "hessian")


@pytest.fixture(params=CASES, ids=[c["name"] for c in CASES])
def case(request):
    return request.param


@pytest.fixture(scope="module")
def live():
    with serve() as url:
        yield url


def _check(batches, case) -> None:
    check_state_case(batches, case, TOL)


def test_v12_case_in_process(case):
    _check(evaluate(**read(orjson.dumps(case["request"]))).batches, case)


def test_v12_case_over_json_and_msgpack(case):
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=case["request"])
        assert r.status_code == 200, r.text
        _check(r.json()["batches"], case)
        body, ct = codec.encode(as_request(case["request"]), binary=True)
        r = client.post("/v1/evaluate", content=body, headers={"Content-Type": ct, "Accept": ct})
        assert r.status_code == 200, r.text
        _check(codec.decode(r.content, r.headers["content-type"]).batches, case)


def test_v12_case_local_client_and_local_session(case):
    req = as_request(case["request"])
    _check(LocalClient().evaluate(req).batches, case)
    with LocalClient().session(req) as s:
        _check(s.evaluate(req.q).batches, case)


@pytest.mark.parametrize("binary", [True, False], ids=["msgpack", "json"])
def test_v12_cases_by_live_http_and_session(live, binary):
    client = Client(live, binary=binary)
    for case in CASES:
        req = as_request(case["request"])
        _check(client.evaluate(req).batches, case)
        with client.session(req) as s:
            _check(s.evaluate(req.q).batches, case)


def test_reference_reproduces_the_v12_cases(case):
    """The project's own 50-digit reference (bench/reference.py), extended to v1.2, agrees with the cases."""
    from bench.reference import reference_request

    mode = "hessian_" + case["request"]["hessian_mode"]
    for got, want in zip(reference_request(case["request"]), case["expect"]):
        for f in FIELDS:
            assert relerr(got[mode if f == "hessian" else f], want[f]) <= 1e-15, f


def test_v1_prismatic_psd_case_is_the_engines_projection():
    """cases.json's `prismatic_psd`, recomputed for v1.2, is answered (the old 12-quantity answer is not)."""
    from tests.conftest import GOLDEN

    case = next(c for c in GOLDEN if c["name"] == "prismatic_psd")
    ev = evaluate(**read(orjson.dumps(case["request"])))
    assert relerr(ev.batches[0].hessian, case["expect"][0]["hessian"]) <= 1e-13


# ---------------------------------------------------------------- faults of the new fields, every path


def _batch(**kw) -> dict:
    b = {"constitution_uid": 670, "body_ids": [[0, 1]], "lower": [-0.5], "upper": [0.5], "strength": [1.0]}
    return {**b, **kw}


def _request(batch: dict) -> dict:
    eye = [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]
    return {"bodies": {k: [eye, eye] for k in ("q", "q_prev", "q_ref")}, "batches": [batch]}


EDGE = [[[0, 0, 0], [0, 0, 1]]]
LOCAL = [[[[0, 0, 0], [0, 0, 1]], [[0, 0, 0], [0, 0, 1]]]]
FAULTS = {
    "both": (_batch(edges=EDGE, local_edges=LOCAL), ("batches", 0), "exactly one of edges and local_edges"),
    "neither": (_batch(), ("batches", 0), "exactly one of edges and local_edges"),
    "zero_local": (_batch(local_edges=[[[[1, 2, 3], [1, 2, 3]], [[0, 0, 0], [0, 0, 1]]]]),
                   ("batches", 0, "local_edges", 0), "zero-length edge: l0 == l1"),
    "nonfinite_r1": (_batch(local_edges=[[[[0, 0, 0], [0, 0, 1]], [[0, 0, 0], [0, 0, None]]]]),
                     ("batches", 0, "local_edges", 0, 1, 1, 2), ""),
    "origin": (_batch(edges=EDGE, origin="engine"), ("batches", 0, "origin"), "Input should be 'q_ref' or 'absolute'"),
}


@pytest.mark.parametrize("name", FAULTS)
def test_v12_faults_are_the_same_on_every_path(name):
    batch, loc, words = FAULTS[name]
    doc = _request(batch)
    seen = []
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=doc)
        assert r.status_code == 422, r.text
        seen.append([(tuple(d["loc"][1:]), d["msg"]) for d in r.json()["detail"]])  # loc[0] is "body"
        if name != "origin":
            body, ct = codec.encode(as_request(doc), binary=True)
        else:  # the SDK's own reading refuses a bad origin (pydantic): the msgpack document is edited instead
            body, ct = codec.encode(as_request(_request(_batch(edges=EDGE))), binary=True)
            sent = wire.loads(body)
            sent["batches"][0]["origin"] = "engine"
            body = wire.dumps(sent)
        r = client.post("/v1/evaluate", content=body, headers={"Content-Type": ct})
        assert r.status_code == 422, r.text
        seen.append([(tuple(d["loc"][1:]), d["msg"]) for d in r.json()["detail"]])
    if name != "origin":  # the SDK's own reading refuses a bad origin itself (pydantic, as JSON above)
        with pytest.raises(InvalidInput) as e:
            LocalClient().evaluate(as_request(doc))
        seen.append([(tuple(f.loc[1:]) if f.loc[:1] == ("body",) else tuple(f.loc), f.msg) for f in e.value.faults])
    for faults in seen:
        assert faults == seen[0]
    assert [f for f in seen[0] if f[0] == loc and words in f[1]], seen[0]


def test_core_refuses_an_unknown_origin_in_process():
    kw = read(orjson.dumps(_request(_batch(edges=EDGE))))
    kw["batches"][0] = type(kw["batches"][0])(**{**kw["batches"][0].__dict__, "origin": "engine"})
    with pytest.raises(InputError) as e:
        evaluate(**kw)
    assert e.value.faults[0].loc == ("batches", 0, "origin")


SHARED = Path(__file__).resolve().parents[3] / "shared"


@pytest.mark.skipif(not SHARED.is_dir(), reason="no ../shared beside the clone (a user's clone has none; CI has it)")
def test_the_project_holds_the_shared_golden_files_and_contract_as_they_are():
    """tests/ keeps ../shared/golden's three files byte for byte, and schemas/CONTRACT.md opens with
    ../shared/CONTRACT.md whole (the project's extensions follow it)."""
    here = Path(__file__).parents[1]
    for ours, theirs in (("golden_cases.json", "cases.json"), ("golden_state_cases.json", "state_cases.json"),
                         ("golden_v12_cases.json", "v12_cases.json")):
        assert (here / ours).read_bytes() == (SHARED / "golden" / theirs).read_bytes(), ours
    contract = (here.parent / "schemas" / "CONTRACT.md").read_text()
    assert contract.startswith((SHARED / "CONTRACT.md").read_text())


@pytest.mark.parametrize("uid", [670, 669])
@pytest.mark.parametrize("origin", ["q_ref", "absolute"])
def test_an_empty_batch_of_local_edges_is_answered(uid, origin):
    """A batch of no joints given by `local_edges` (N = 0) answers an empty batch, as an empty `edges` batch does
    (schemathesis once found a 500 here: the local axis' scaling took the largest entry of zero rows)."""
    doc = _request({"constitution_uid": uid, "body_ids": [], "local_edges": [], "lower": [], "upper": [], "origin": origin})
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=doc)
    assert r.status_code == 200, r.text
    assert r.json()["batches"][0]["x"] == [] and r.json()["total_energy"] == 0.0
    assert LocalClient().evaluate(as_request(doc)).batches[0].x.shape == (0,)
