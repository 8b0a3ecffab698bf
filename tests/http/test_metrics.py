"""Prometheus /metrics and the JSON access log (in process; the multi-worker sums are in test_ops_load.py)."""

from __future__ import annotations

import json
import logging

import pytest
from fastapi.testclient import TestClient

from jointlimits.service.app import create_app
from jointlimits.service.observability import ACCESS_LOGGER, JsonFormatter, log_config
from jointlimits.service.settings import Settings
from tests.drills import metric_total, scene


@pytest.fixture
def client(monkeypatch) -> TestClient:
    monkeypatch.delenv("PROMETHEUS_MULTIPROC_DIR", raising=False)
    return TestClient(create_app(Settings()))


def metrics(c: TestClient) -> str:
    r = c.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    return r.text


def test_requests_by_status_latency_and_joints_by_constitution(client):
    body = scene(7, seed=1)  # 4 revolute (#670), 3 prismatic (#669)
    for _ in range(2):
        assert client.post("/v1/evaluate", json=body).status_code == 200
    assert client.post("/v1/evaluate", content=b"{not json", headers={"Content-Type": "application/json"}).status_code == 422
    assert client.get("/nope").status_code == 404
    text = metrics(client)
    req = "jointlimits_http_requests_total"
    assert metric_total(text, req, route="/v1/evaluate", status="200") == 2
    assert metric_total(text, req, route="/v1/evaluate", status="422") == 1
    assert metric_total(text, req, route="unmatched", status="404") == 1  # no label per unknown path
    assert metric_total(text, "jointlimits_http_request_duration_seconds_count", route="/v1/evaluate") == 3
    assert metric_total(text, "jointlimits_http_request_duration_seconds_bucket", route="/v1/evaluate", le="+Inf") == 3
    assert metric_total(text, "jointlimits_http_request_duration_seconds_sum", route="/v1/evaluate") > 0
    assert metric_total(text, "jointlimits_joints_evaluated_total", constitution="670") == 8
    assert metric_total(text, "jointlimits_joints_evaluated_total", constitution="669") == 6
    assert metric_total(text, "jointlimits_http_requests_in_flight") == 1  # this scrape


def test_rejected_requests_count_no_joints(client):
    bad = scene(3, seed=2)
    bad["batches"][0]["lower"][0] = 5.0  # lower > upper: 422 after parsing
    assert client.post("/v1/evaluate", json=bad).status_code == 422
    text = metrics(client)
    assert metric_total(text, "jointlimits_joints_evaluated_total") == 0


def test_two_apps_do_not_share_counts(client):
    client.get("/healthz")
    other = TestClient(create_app(Settings()))
    assert metric_total(metrics(other), "jointlimits_http_requests_total", route="/healthz") == 0


def test_401_is_labelled_with_its_route(monkeypatch):
    monkeypatch.delenv("PROMETHEUS_MULTIPROC_DIR", raising=False)
    c = TestClient(create_app(Settings(token="t")))
    assert c.post("/v1/evaluate", json={}).status_code == 401
    assert metric_total(metrics(c), "jointlimits_http_requests_total", route="/v1/evaluate", status="401") == 1


def test_access_log_line_per_request(client, caplog):
    with caplog.at_level(logging.INFO, logger=ACCESS_LOGGER):
        r = client.post("/v1/evaluate", json=scene(5, seed=3), headers={"X-Request-ID": "farm-42.step-7"})
        client.get("/healthz")
    assert r.headers["x-request-id"] == "farm-42.step-7"
    records = [rec for rec in caplog.records if rec.name == ACCESS_LOGGER]
    assert len(records) == 2
    line = json.loads(JsonFormatter().format(records[0]))
    assert line["request_id"] == "farm-42.step-7"
    assert line["status"] == 200 and line["method"] == "POST" and line["route"] == "/v1/evaluate"
    assert line["joints"] == 5
    assert isinstance(line["latency_ms"], float) and line["latency_ms"] > 0
    assert line["bytes_in"] == int(r.request.headers["content-length"])
    assert line["level"] == "info" and line["ts"].endswith("Z")
    health = json.loads(JsonFormatter().format(records[1]))
    assert health["joints"] is None and len(health["request_id"]) == 32  # one made up


@pytest.mark.parametrize("given", ["", "x" * 200, "spaces are not ok", "new\\nline"])
def test_unusable_request_ids_are_replaced(client, given):
    r = client.get("/healthz", headers={"X-Request-ID": given})
    assert r.headers["x-request-id"] != given and len(r.headers["x-request-id"]) == 32


def test_log_config_is_valid_and_silences_uvicorns_access_log():
    import logging.config

    cfg = log_config("warning", access_log=False)
    assert cfg["loggers"]["uvicorn.access"]["level"] == "CRITICAL"
    assert cfg["loggers"][ACCESS_LOGGER]["level"] == "CRITICAL"
    assert log_config()["loggers"][ACCESS_LOGGER]["level"] == "INFO"
    # dictConfig accepts it (validated on a copy of the logging module's state: restored after).
    saved = {name: (lg.handlers[:], lg.level, lg.propagate) for name in ("uvicorn", "jointlimits") for lg in [logging.getLogger(name)]}
    try:
        logging.config.dictConfig(cfg)
    finally:
        for name, (handlers, level, propagate) in saved.items():
            lg = logging.getLogger(name)
            lg.handlers[:] = handlers
            lg.setLevel(level)
            lg.propagate = propagate
        for name in ("uvicorn.error", "uvicorn.access", ACCESS_LOGGER):
            lg = logging.getLogger(name)
            lg.setLevel(logging.NOTSET)
            lg.propagate = True
            lg.handlers[:] = []


def test_exceptions_are_json_too():
    try:
        raise ValueError("boom")
    except ValueError:
        import sys

        rec = logging.LogRecord("jointlimits", logging.ERROR, __file__, 1, "failed %s", ("x",), sys.exc_info())
    line = json.loads(JsonFormatter().format(rec))
    assert line["msg"] == "failed x" and "ValueError: boom" in line["exc"]
