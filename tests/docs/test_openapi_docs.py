"""`/openapi.json` is enough for a C++ or Julia author alone, and `/docs` works without internet."""

from __future__ import annotations

import re

import httpx
import orjson
import pytest

from jointlimits.schemas import EvaluateRequest
from jointlimits.service.http import openapi as text
from jointlimits.service.settings import Settings
from tests.conftest import same_numbers
from tests.http.test_contract_live import live, serve  # noqa: F401 (fixture)


@pytest.fixture(scope="module")
def spec(live) -> dict:
    return httpx.get(live + "/openapi.json").json()


def test_every_field_of_every_model_is_described(spec):
    missing = [
        f"{model}.{name}"
        for model, schema in spec["components"]["schemas"].items()
        for name, prop in schema.get("properties", {}).items()
        if len(prop.get("description", "")) < 10
    ]
    assert missing == []


def test_uids_shapes_dof_order_and_index(spec):
    s = spec["components"]["schemas"]
    assert s["JointBatch"]["properties"]["constitution_uid"]["enum"] == [670, 669]
    assert s["JointBatch"]["properties"]["base_uid"]["enum"] == [18, 20]
    result = s["BatchResult"]["properties"]
    assert "(M, 24)" in result["gradient"]["description"] and "(M, 24, 24)" in result["hessian"]["description"]
    assert "[q_i (12), q_j (12)]" in result["hessian"]["description"]
    assert "active_only" in result["index"]["description"]
    assert "[p (3), A row 0 (3), A row 1 (3), A row 2 (3)]" in s["Bodies"]["properties"]["q"]["description"]
    assert "world space at q_ref" in s["JointBatch"]["properties"]["edges"]["description"]
    assert "radians for 670" in s["JointBatch"]["properties"]["lower"]["description"]


def test_the_example_answer_is_what_the_example_request_gets(live, spec):
    post = spec["paths"]["/v1/evaluate"]["post"]
    example = post["requestBody"]["content"]["application/json"]["example"]
    EvaluateRequest.model_validate(example)
    answer = httpx.post(live + "/v1/evaluate", json=example)
    assert answer.status_code == 200
    shown = post["responses"]["200"]["content"]["application/json"]["example"]
    assert orjson.dumps(shown) == orjson.dumps(text.EXAMPLE_RESPONSE)  # as text: -0.0 included
    assert same_numbers(answer.text, orjson.dumps(shown).decode()), answer.text  # up to another CPU's last bits


def test_bearer_security_401_and_request_id(spec):
    assert spec["components"]["securitySchemes"]["bearer"] == {**text.BEARER}
    for path, ops in spec["paths"].items():
        for op in ops.values():
            assert any(p["name"] == "X-Request-ID" and p["in"] == "header" for p in op["parameters"]), path
            assert all("X-Request-ID" in r.get("headers", {}) for r in op["responses"].values()), path
            if path.startswith("/v1/"):
                assert op["security"] == [{"bearer": []}, {}]
                assert "WWW-Authenticate" in op["responses"]["401"]["headers"]


def test_the_401_is_what_the_spec_says():
    with serve(Settings(max_body_bytes=10**6, max_joints=10, token="s3cret", cors_origins=())) as url:
        r = httpx.post(url + "/v1/evaluate", json=text.EXAMPLE_REQUEST)
    assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer")
    assert r.json() == text.UNAUTHORIZED["content"]["application/json"]["example"]


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_load_without_any_external_url(live, page):
    html = httpx.get(live + page).text
    assert re.findall(r"(?:https?:)?//[\w.-]+", html) == []  # nothing leaves the service
    assets = re.findall(r'(?:src|href)="([^"]+)"', html)
    assert len(assets) >= 2
    for asset in assets:
        r = httpx.get(live + asset)
        assert r.status_code == 200 and len(r.content) > 1000, asset
    if page == "/docs":
        assert '"validatorUrl": null' in html  # the validator badge would fetch from outside
        assert "url: '/openapi.json'" in html


def test_the_document_is_valid_openapi(spec):
    """openapi-spec-validator against the version the document declares (3.1): a Media Type Object with a
    `description` key, as `application/msgpack` once had, fails it."""
    from openapi_spec_validator import validate

    assert spec["openapi"].startswith("3.1")
    validate(spec)
    media = spec["paths"]["/v1/evaluate"]["post"]["requestBody"]["content"]["application/msgpack"]
    bad = orjson.loads(orjson.dumps(spec))
    bad["paths"]["/v1/evaluate"]["post"]["requestBody"]["content"]["application/msgpack"] = {**media, "description": "x"}
    with pytest.raises(Exception, match="description"):
        validate(bad)
