"""`layout` in a session's opening document is honoured (issue 19): its evaluations answer `assembled`,
bitwise what `POST /v1/evaluate` answers with the same `layout`, in JSON and msgpack."""

from __future__ import annotations

import json

import msgpack
import pytest

from jointlimits.schemas import binary as wire
from tests.http.test_contract_live import live  # noqa: F401 (fixture)
from tests.http.test_sessions import BODY, PATH, Q, Binary, Json, app, open_binary, same


class BinaryWithLayout(Binary):
    """Binary side whose opening document carries the JSON document's top-level options too."""

    def send(self, doc: dict) -> dict:
        if "bodies" not in doc:
            return super().send(doc)
        top = {k: v for k, v in doc.items() if k not in ("bodies", "batches")}
        opening = wire.loads(open_binary(doc))
        self.ws.send_bytes(wire.dumps({**opening, **top}))
        return msgpack.unpackb(self.ws.receive_bytes())


@pytest.mark.parametrize("Side", [Json, BinaryWithLayout], ids=["json", "msgpack"])
@pytest.mark.parametrize("mode", ["exact", "psd"])
def test_layout_bodies_in_the_opening_answers_assembled(Side, mode):
    c = app()
    doc = {**BODY, "layout": "bodies", "hessian_mode": mode}
    http = c.post("/v1/evaluate", json=doc)
    assert http.status_code == 200 and "assembled" in http.json()
    with c.websocket_connect(PATH) as ws:
        s = Side(ws)
        assert s.send(doc)["kind"] == "opened"
        ev = s.send({"kind": "evaluate", "q": Q, "id": 1})
        assert ev.pop("kind") == "evaluation" and ev.pop("id") == 1
        assert "assembled" in ev and all(b.get("gradient") is None for b in ev["batches"])
        if Side is Json:
            same(ev, http.json())
        # A later evaluate's own options keep the session's layout.
        energy = s.send({"kind": "evaluate", "q": Q, "outputs": ["energy", "gradient"]})
        want = c.post("/v1/evaluate", json={**doc, "outputs": ["energy", "gradient"]}).json()
        del energy["kind"]
        if Side is Json:
            same(energy, want)
        assert "gradient" in energy["assembled"] and "blocks" not in energy["assembled"]


def test_default_layout_is_joints():
    c = app()
    with c.websocket_connect(PATH) as ws:
        s = Json(ws)
        assert s.send(BODY)["kind"] == "opened"
        ev = s.send({"kind": "evaluate", "q": Q})
        assert "assembled" not in ev and ev["batches"][0]["gradient"] is not None


def test_an_unknown_layout_in_the_opening_is_a_fault_naming_it():
    c = app()
    with c.websocket_connect(PATH) as ws:
        ws.send_text(json.dumps({**BODY, "layout": "pairs"}))
        reply = json.loads(ws.receive_text())
        assert reply["kind"] == "error" and reply["status"] == 422
        assert [d["loc"] for d in reply["detail"]] == [["body", "layout"]]


@pytest.mark.parametrize("binary", [False, True], ids=["json", "msgpack"])
def test_sdk_sessions_answer_what_evaluate_answers(live, binary):
    from jointlimits.client import Client, LocalClient
    from tests.http.test_layout_bodies import same as same_assembled, sdk_request

    req = sdk_request(30, 2, layout="bodies")
    with Client(live, binary=binary) as c:
        want = c.evaluate(req).assembled
        with c.session(req) as s:
            got = s.evaluate(req.q).assembled
    with LocalClient().session(req) as s:
        local = s.evaluate(req.q).assembled
    assert want is not None and got is not None and local is not None
    want.n_bodies = len(req.q)
    same_assembled(got, want)
    same_assembled(local, want)

