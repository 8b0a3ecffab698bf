"""Optional bearer token on the API; health, metrics and CORS preflights stay open."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.drills import scene

BODY = scene(2, seed=1)


def client(**settings) -> TestClient:
    return TestClient(create_app(Settings(**settings)))


def test_open_when_no_token_is_configured():
    assert client(token=None).post("/v1/evaluate", json=BODY).status_code == 200


@pytest.mark.parametrize(
    "headers",
    [{}, {"Authorization": "Bearer wrong"}, {"Authorization": "s3cret"}, {"Authorization": "Basic s3cret"},
     {"Authorization": "Bearer s3cret-and-more"}, {"Authorization": "Bearer "}],
    ids=["none", "wrong", "no-scheme", "basic", "longer", "empty"],
)  # fmt: skip
def test_evaluate_without_the_right_token_is_401(headers):
    r = client(token="s3cret").post("/v1/evaluate", json=BODY, headers=headers)
    assert r.status_code == 401
    assert r.headers["www-authenticate"].startswith("Bearer")
    assert r.json() == {"detail": [{"loc": ["header", "authorization"], "msg": "missing or invalid bearer token", "type": "unauthorized"}]}


def test_every_v1_route_is_protected():
    c = client(token="s3cret")
    assert c.get("/v1/constitutions").status_code == 401
    assert c.get("/v1/constitutions", headers={"Authorization": "Bearer s3cret"}).status_code == 200


@pytest.mark.parametrize("scheme", ["Bearer", "bearer", "BEARER"])
def test_the_right_token_passes(scheme):
    r = client(token="s3cret").post("/v1/evaluate", json=BODY, headers={"Authorization": f"{scheme} s3cret"})
    assert r.status_code == 200 and r.json()["batches"]


def test_health_metrics_and_docs_stay_open():
    c = client(token="s3cret")
    assert c.get("/healthz").status_code == 200
    assert c.get("/metrics").status_code == 200
    assert c.get("/openapi.json").status_code == 200


def test_refused_before_the_body_is_read():
    """An unauthenticated request over the size limit is a 401, not a 413: nothing was read."""
    c = client(token="s3cret", max_body_bytes=100)
    assert c.post("/v1/evaluate", json=BODY).status_code == 401
    assert c.post("/v1/evaluate", json=BODY, headers={"Authorization": "Bearer s3cret"}).status_code == 413


def test_token_from_the_environment(monkeypatch):
    monkeypatch.setenv("JOINTLIMITS_TOKEN", "from-env")
    c = TestClient(create_app())
    assert c.post("/v1/evaluate", json=BODY).status_code == 401
    assert c.post("/v1/evaluate", json=BODY, headers={"Authorization": "Bearer from-env"}).status_code == 200


PREFLIGHT = {"Origin": "https://solver.example", "Access-Control-Request-Method": "POST",
             "Access-Control-Request-Headers": "authorization,content-type"}  # fmt: skip


def test_cors_is_off_by_default():
    c = client()
    r = c.options("/v1/evaluate", headers=PREFLIGHT)
    assert "access-control-allow-origin" not in r.headers
    r = c.post("/v1/evaluate", json=BODY, headers={"Origin": "https://solver.example"})
    assert r.status_code == 200 and "access-control-allow-origin" not in r.headers


def test_cors_when_configured_even_with_a_token():
    c = client(cors_origins=("https://solver.example",), token="s3cret")
    r = c.options("/v1/evaluate", headers=PREFLIGHT)  # a preflight carries no credentials
    assert r.status_code == 200
    assert r.headers["access-control-allow-origin"] == "https://solver.example"
    assert "authorization" in r.headers["access-control-allow-headers"].lower()
    r = c.post("/v1/evaluate", json=BODY, headers={"Origin": "https://solver.example", "Authorization": "Bearer s3cret"})
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://solver.example"
    r = c.options("/v1/evaluate", headers={**PREFLIGHT, "Origin": "https://evil.example"})
    assert r.headers.get("access-control-allow-origin") != "https://evil.example"


def test_cors_origins_from_the_environment(monkeypatch):
    monkeypatch.setenv("JOINTLIMITS_CORS_ORIGINS", "https://a.example,https://b.example")
    r = TestClient(create_app()).options("/v1/evaluate", headers={**PREFLIGHT, "Origin": "https://b.example"})
    assert r.headers["access-control-allow-origin"] == "https://b.example"
