"""Sessions honour the CORS allow-list (issue 19): a WebSocket upgrade from an `Origin` outside
JOINTLIMITS_CORS_ORIGINS is refused at the upgrade (403, fault list), token or not; no `Origin` is allowed."""

from __future__ import annotations

import json

import pytest
from starlette.testclient import WebSocketDenialResponse

from jointlimits.service.settings import Settings
from tests.inprocess import serve, upgrade
from tests.http.test_sessions import BODY, PATH, Json, app

GOOD, EVIL = "https://good.example", "https://evil.example"


def refused(c, headers: dict) -> WebSocketDenialResponse:
    with pytest.raises(WebSocketDenialResponse) as e, c.websocket_connect(PATH, headers=headers):
        pass
    return e.value


@pytest.mark.parametrize("token", [None, "s3cret"])
def test_a_foreign_origin_gets_no_session(token):
    c = app(cors_origins=(GOOD,), token=token)
    auth = {"Authorization": f"Bearer {token}"} if token else {}
    for origin in (EVIL, "null", GOOD + ".evil.example", "http://good.example"):
        r = refused(c, {**auth, "Origin": origin})
        assert r.status_code == 403, origin
        detail = r.json()["detail"]
        assert [d["loc"] for d in detail] == [["header", "origin"]] and detail[0]["type"] == "origin_not_allowed"
        assert set(detail[0]) == {"loc", "msg", "type"} and origin in detail[0]["msg"]
    for headers in ({**auth, "Origin": GOOD}, auth):  # the allowed origin, and no Origin (a non-browser client)
        with c.websocket_connect(PATH, headers=headers) as ws:
            assert Json(ws).send(BODY)["kind"] == "opened"


def test_without_a_token_the_origin_is_checked_before_auth():
    c = app(cors_origins=(GOOD,), token="s3cret")
    assert refused(c, {"Origin": EVIL}).status_code == 403  # not 401: the origin alone refuses it
    assert refused(c, {"Origin": GOOD}).status_code == 401


def test_without_an_allow_list_every_origin_is_served_and_star_allows_all():
    for origins in ((), ("*",)):
        c = app(cors_origins=origins)
        with c.websocket_connect(PATH, headers={"Origin": EVIL}) as ws:
            assert Json(ws).send(BODY)["kind"] == "opened"


def test_http_preflight_and_upgrade_agree():
    c = app(cors_origins=(GOOD,))
    pre = c.options("/v1/evaluate", headers={"Origin": EVIL, "Access-Control-Request-Method": "POST"})
    assert pre.status_code == 400  # Starlette's CORS refuses the preflight
    assert refused(c, {"Origin": EVIL}).status_code == 403


def test_on_a_real_server_the_upgrade_is_answered_403_with_the_fault_list():
    with serve(Settings(token=None, cors_origins=(GOOD,))) as live:
        s, head = upgrade(live.port, {"Origin": EVIL})
        try:
            assert head.startswith(b"HTTP/1.1 403"), head
            length = int(next(h.split(b":")[1] for h in head.split(b"\r\n") if h.lower().startswith(b"content-length")))
            body = b""
            while len(body) < length:
                body += s.recv(length - len(body))
            assert json.loads(body)["detail"][0]["loc"] == ["header", "origin"]
        finally:
            s.close()
        s, head = upgrade(live.port, {"Origin": GOOD})
        s.close()
        assert head.startswith(b"HTTP/1.1 101"), head
