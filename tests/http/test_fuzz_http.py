"""No input gets a 500, and no 200 carries NaN or Infinity: schemathesis on the OpenAPI schema and
hypothesis-generated garbage, all over real HTTP to uvicorn on loopback. Bounded in time."""

from __future__ import annotations

import json
import math

import httpx
import msgpack
import numpy as np
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jointlimits.client import codec
from jointlimits.service.app import create_app
from tests.http.test_contract_live import LIMITS, live  # noqa: F401 (fixture)
from tests.http.test_errors_http import base_request

pytestmark = pytest.mark.slow  # schemathesis and hypothesis over HTTP (~11 s)

ALLOWED = {200, 406, 413, 415, 422}
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck), database=None)


def _reject_constant(token: str):
    raise ValueError(f"{token} in a JSON answer")


def check_answer(r, allowed=ALLOWED) -> None:
    """The contract for any answer: an allowed status, errors in `detail` format, 200s finite."""
    assert r.status_code in allowed, (r.status_code, r.text[:300])
    if r.status_code in (405, 404):  # schemathesis also tries methods and paths that do not exist
        return
    if r.status_code != 200:
        detail = json.loads(r.content)["detail"]
        assert detail and all(isinstance(d["loc"], list) and d["msg"] for d in detail)
        return
    content_type = r.headers["content-type"]
    content_type = content_type[0] if isinstance(content_type, list) else content_type
    if not str(r.request.url).endswith("/v1/evaluate"):
        return
    if content_type.startswith("application/json"):
        doc = json.loads(r.content, parse_constant=_reject_constant)
        assert "null" not in r.text
        assert math.isfinite(doc["total_energy"])
    else:
        doc = msgpack.unpackb(r.content)
        for b in doc["batches"]:
            for k in ("x", "energy", "gradient", "hessian"):
                if k in b:
                    assert np.isfinite(np.frombuffer(b[k]["data"], "<f8")).all()


schema = schemathesis.openapi.from_dict(create_app(LIMITS).openapi())


@pytest.mark.serial  # its items share one node id: on xdist's workers only one would run (tests/conftest.py)
@schema.parametrize()
@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck), database=None)
def test_schemathesis_openapi(case, live):
    r = case.call(base_url=live, timeout=30)
    check_answer(r, ALLOWED | {404, 405})


def _json_values(leaf):
    return st.recursive(
        leaf, lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids, max_size=4), max_leaves=20
    )


_NUMBER = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from([0.0, -0.0, 1e308, -1e308, 5e-324, 1e154, 1e-154, 2.0**63]),
    st.integers(min_value=-(2**70), max_value=2**70),
)
_TOKENS = ["NaN", "Infinity", "-Infinity", "1e400", "-1e400", "1e-400", "null", "true", '"x"', "[]", "{}", "[1,2]", "99999999999999999999999"]
_PATHS = [
    ("bodies", "q", 1, 4), ("bodies", "q_prev", 2), ("bodies", "q_ref", 0, 0), ("bodies", "q"),
    ("batches", 0, "body_ids", 1, 0), ("batches", 1, "body_ids", 2), ("batches", 1, "edges", 0, 1, 2),
    ("batches", 1, "edges", 2), ("batches", 0, "lower", 0), ("batches", 1, "upper", 2), ("batches", 1, "strength", 1),
    ("batches", 0, "constitution_uid"), ("batches", 1, "base_uid"), ("outputs",), ("outputs", 0), ("hessian_mode",),
    ("active_only",), ("batches", 0), ("batches",), ("bodies",),
]  # fmt: skip


def _base_doc() -> dict:
    return json.loads(codec.encode(base_request(), binary=False)[0])


def _put(doc, path, value):
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


@given(path=st.sampled_from(_PATHS), value=_json_values(_NUMBER | st.text(max_size=5) | st.booleans() | st.none()))
@FUZZ
def test_mutated_json_requests(live, path, value):
    doc = _base_doc()
    _put(doc, path, value)
    check_answer(httpx.post(f"{live}/v1/evaluate", content=json.dumps(doc).encode(), headers={"Content-Type": "application/json"}))


@given(path=st.sampled_from(_PATHS), token=st.sampled_from(_TOKENS), mode=st.sampled_from(["exact", "psd"]))
@FUZZ
def test_raw_json_tokens(live, path, token, mode):
    doc = _base_doc()
    doc["hessian_mode"] = mode
    _put(doc, path, "@@")
    body = json.dumps(doc).encode().replace(b'"@@"', token.encode())
    check_answer(httpx.post(f"{live}/v1/evaluate", content=body, headers={"Content-Type": "application/json"}))


@given(scale=st.sampled_from([1e-300, 1e-150, 1e100, 1e154, 1e200, 1e300]), rows=st.lists(st.integers(0, 2), min_size=1, max_size=3),
       cols=st.lists(st.integers(0, 11), min_size=1, max_size=4), which=st.sampled_from(["q", "q_prev", "q_ref"]),
       mode=st.sampled_from(["exact", "psd"]), binary=st.booleans())  # fmt: skip
@FUZZ
def test_extreme_magnitudes_never_leak_non_finite_numbers(live, scale, rows, cols, which, mode, binary):
    from dataclasses import replace

    r = base_request()
    a = getattr(r, which).copy()
    a[np.ix_(rows, cols)] *= scale
    a[np.ix_(rows, cols)] += scale
    body, content_type = codec.encode(replace(r, **{which: a}, hessian_mode=mode), binary=binary)
    check_answer(httpx.post(f"{live}/v1/evaluate", content=body, headers={"Content-Type": content_type}))


_MSGPACK_LEAF = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**63), 2**64 - 1), st.floats(), st.text(max_size=6), st.binary(max_size=48)
)


def _mutate_msgpack(doc, path, value):
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


_BIN_PATHS = [
    ("bodies", "q"), ("bodies", "q", "shape"), ("bodies", "q", "dtype"), ("bodies", "q", "data"), ("bodies", "q_ref", "shape", 0),
    ("batches", 0, "body_ids"), ("batches", 0, "body_ids", "data"), ("batches", 1, "edges", "shape"), ("batches", 1, "lower", "data"),
    ("batches", 1, "strength"), ("batches", 0, "constitution_uid"), ("batches", 1, "base_uid"), ("outputs",), ("hessian_mode",),
    ("active_only",), ("batches",), ("bodies",), ("batches", 0),
]  # fmt: skip


@given(path=st.sampled_from(_BIN_PATHS), value=st.recursive(_MSGPACK_LEAF, lambda k: st.lists(k, max_size=3) | st.dictionaries(st.text(max_size=6), k, max_size=3), max_leaves=10))
@FUZZ
def test_mutated_msgpack_requests(live, path, value):
    doc = msgpack.unpackb(codec.encode(base_request(), binary=True)[0])
    _mutate_msgpack(doc, path, value)
    body = msgpack.packb(doc)
    check_answer(httpx.post(f"{live}/v1/evaluate", content=body, headers={"Content-Type": "application/msgpack"}))


@given(body=st.binary(max_size=256), content_type=st.sampled_from(["application/json", "application/msgpack", "text/plain", ""]),
       accept=st.sampled_from([None, "*/*", "application/msgpack", "text/html;q=0.3", "application/json;q=abc", ",,;"]))  # fmt: skip
@FUZZ
def test_random_bytes(live, body, content_type, accept):
    headers = {"Content-Type": content_type} | ({"Accept": accept} if accept else {})
    check_answer(httpx.post(f"{live}/v1/evaluate", content=body, headers=headers))


@pytest.mark.parametrize("method", ["GET", "PUT", "DELETE"])
def test_other_methods_are_4xx(live, method):
    assert httpx.request(method, f"{live}/v1/evaluate").status_code == 405
