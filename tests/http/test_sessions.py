"""The session protocol (`/v1/sessions`, docs/sessions.md) through FastAPI's TestClient: every message kind in
JSON and msgpack, faults as messages that keep the session, auth on the upgrade, each bound's close code, metrics."""

from __future__ import annotations

import json
import time

import msgpack
import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse

from jointlimits.client import InvalidInput, LocalClient
from jointlimits.schemas import binary as wire
from jointlimits.schemas import session as proto
from jointlimits.service import sizing
from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.drills import scene

PATH = proto.PATH
BODY = scene(6, seed=3)  # 3 revolute + 3 prismatic joints, about half outside their range
Q = BODY["bodies"]["q"]


def app(**settings) -> TestClient:
    return TestClient(create_app(Settings(**{"token": None, **settings})))


def pack(doc: dict) -> bytes:
    """A msgpack message, numeric lists as the binary transport's array maps."""
    def arr(v, key):
        if key in ("q",):
            return wire.pack_array(np.array(v, dtype=np.float64), wire.FLOAT64)
        if key == "index":
            return wire.pack_array(np.array(v, dtype=np.int64), wire.INT64)
        if key in proto.UPDATABLE:
            return wire.pack_array(np.array(v, dtype=np.float64), wire.FLOAT64)
        return v
    return wire.dumps({k: arr(v, k) for k, v in doc.items()})


def open_binary(body: dict) -> bytes:
    """The opening document in msgpack (the HTTP binary transport's request)."""
    b = body["bodies"]
    f = lambda v, shape: wire.pack_array(np.array(v, dtype=np.float64).reshape(shape), wire.FLOAT64)  # noqa: E731
    return wire.dumps({
        "bodies": {k: f(b[k], (-1, 12)) for k in ("q", "q_prev", "q_ref")},
        "batches": [{"constitution_uid": j["constitution_uid"], "base_uid": j["base_uid"],
                     "body_ids": wire.pack_array(np.array(j["body_ids"], dtype=np.int64).reshape(-1, 2), wire.INT64),
                     "edges": f(j["edges"], (-1, 2, 3)),
                     **{k: f(j[k], (-1,)) for k in ("lower", "upper", "strength", "offset", "prev_coordinate") if k in j}}
                    for j in body["batches"]],
        **{k: v for k, v in body.items() if k not in ("bodies", "batches")},  # options, id
    })  # fmt: skip


class Json:
    """One side of a session in JSON text frames."""

    def __init__(self, ws) -> None:
        self.ws = ws

    def send(self, doc: dict) -> dict:
        self.ws.send_text(json.dumps(doc))
        return json.loads(self.ws.receive_text())


class Binary:
    def __init__(self, ws) -> None:
        self.ws = ws

    def send(self, doc: dict) -> dict:
        self.ws.send_bytes(open_binary(doc) if "bodies" in doc else pack(doc))
        return msgpack.unpackb(self.ws.receive_bytes())


def arrays(doc):
    """A reply with every array map (msgpack) or list (JSON) as a NumPy array, for comparing the two encodings."""
    if isinstance(doc, dict) and set(doc) == {"dtype", "shape", "data"}:
        return wire.unpack_array(doc, doc["dtype"], len(doc["shape"]))
    if isinstance(doc, dict):
        return {k: arrays(v) for k, v in doc.items()}
    if isinstance(doc, list) and doc and not isinstance(doc[0], (dict, str)):
        return np.array(doc)
    if isinstance(doc, list):
        return [arrays(v) for v in doc]
    return doc


def same(a, b) -> None:
    """Bitwise equal documents (arrays compared by their float64 bits)."""
    a, b = arrays(a), arrays(b)
    if isinstance(a, dict):
        assert set(a) == set(b), (set(a), set(b))
        for k in a:
            same(a[k], b[k])
    elif isinstance(a, list):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            same(x, y)
    elif isinstance(a, np.ndarray):
        assert a.shape == b.shape and a.tobytes() == np.asarray(b, dtype=a.dtype).tobytes()
    else:
        assert a == b


@pytest.mark.parametrize("Side", [Json, Binary], ids=["json", "msgpack"])
def test_every_message_kind(Side):
    c = app()
    http = c.post("/v1/evaluate", json=BODY).json()
    with c.websocket_connect(PATH) as ws:
        s = Side(ws)
        opened = s.send(BODY)
        assert opened["kind"] == "opened" and opened["bodies"] == len(Q) and opened["batch_sizes"] == [3, 3]
        assert opened["limits"] == {"max_frame_bytes": 64 * 2**20, "idle_seconds": 300.0}
        start = arrays(opened["coordinates"])

        ev = s.send({"kind": "evaluate", "q": Q, "id": 7})
        assert ev.pop("kind") == "evaluation" and ev.pop("id") == 7
        same(ev, http)  # the answer document of POST /v1/evaluate, bit for bit

        # Options: per message, else the opening document's (its defaults here: all outputs, exact, all joints).
        ev = s.send({"kind": "evaluate", "q": Q, "outputs": ["energy"], "hessian_mode": "psd", "active_only": True})
        want = c.post("/v1/evaluate", json={**BODY, "outputs": ["energy"], "hessian_mode": "psd", "active_only": True}).json()
        del ev["kind"]
        same(ev, want)

        committed = s.send({"kind": "commit", "q": Q, "id": "step-1"})
        assert committed["kind"] == "committed" and committed["id"] == "step-1"
        coords = arrays(committed["coordinates"])
        # Committing the state the scene opened at changes nothing; committing q reports x at q.
        assert [c.shape for c in coords] == [(3,), (3,)]
        np.testing.assert_allclose(np.concatenate(coords), np.concatenate([b["x"] for b in http["batches"]]),
                                   rtol=1e-13, atol=1e-15)
        assert not np.array_equal(np.concatenate(start), np.concatenate(coords))

        upd = s.send({"kind": "update", "batch": 1, "index": [0, 2], "lower": [-5.0, -5.0], "upper": [5.0, 5.0],
                      "strength": [2.0, 3.0]})
        assert upd == {"kind": "updated", "batch": 1, "joints": 2}
        after = s.send({"kind": "evaluate", "q": Q, "outputs": ["energy"]})
        e = np.array(arrays(after["batches"][1]["energy"]))
        assert e[0] == 0 and e[2] == 0  # both now well inside [-5, 5]

        ws.send_text(json.dumps({"kind": "close"}))
        msg = ws.receive()
        assert msg["type"] == "websocket.close" and msg["code"] == proto.NORMAL


FAULTS = [
    ({"kind": "evaluate", "q": Q[:2]}, ["body", "q"]),
    ({"kind": "evaluate"}, ["body", "q"]),
    ({"kind": "evaluate", "q": Q, "outputs": ["energy", "curvature"]}, ["body", "outputs", 1]),
    ({"kind": "evaluate", "q": Q, "hessian_mode": "approx"}, ["body", "hessian_mode"]),
    ({"kind": "commit", "q": [r[:11] for r in Q]}, ["body", "q"]),  # JSON names row 0, msgpack the array
    ({"kind": "dance"}, ["body", "kind"]),
    ({"kind": "update", "batch": 0, "index": [1], "lower": [9.0]}, ["body", "batches", 0, "lower", 1]),
    ({"kind": "update", "batch": 0, "index": [1], "strength": [-1.0]}, ["body", "batches", 0, "strength", 1]),
    # An update's faults name the scene's batch, field and joint, as the opening request would.
    ({"kind": "update", "batch": 5, "index": [0], "lower": [0.0]}, ["body", "batches", 5]),
    ({"kind": "update", "batch": 0, "index": [3], "lower": [0.0]}, ["body", "batches", 0, "index", 0]),
    ({"kind": "update", "batch": 0, "index": [0, 1], "lower": [0.0]}, ["body", "batches", 0, "lower"]),
    ({"kind": "evaluate", "q": Q, "extra": 1}, ["body", "extra"]),
]  # fmt: skip


@pytest.mark.parametrize("Side", [Json, Binary], ids=["json", "msgpack"])
def test_faults_are_messages_and_the_session_goes_on(Side):
    c = app()
    with c.websocket_connect(PATH) as ws:
        s = Side(ws)
        assert s.send(BODY)["kind"] == "opened"
        first = s.send({"kind": "evaluate", "q": Q})
        for doc, loc in FAULTS:
            reply = s.send({**doc, "id": 3})
            assert reply["kind"] == "error" and reply["status"] == 422 and reply["id"] == 3, (doc, reply)
            assert reply["detail"][0]["loc"][: len(loc)] == loc, (doc, reply)
            assert {"loc", "msg", "type"} == set(reply["detail"][0]) and reply["detail"][0]["msg"]
            same(s.send({"kind": "evaluate", "q": Q}), first)  # the scene is untouched: an update is all or nothing


def test_non_finite_q_in_msgpack_names_the_body():
    c = app()
    with c.websocket_connect(PATH) as ws:
        s = Binary(ws)
        s.send(BODY)
        q = np.array(Q)
        q[4, 7] = np.nan
        reply = s.send({"kind": "evaluate", "q": q})
        assert reply["status"] == 422 and reply["detail"][0]["loc"] == ["body", "q", 4, 7], reply


def test_a_faulty_opening_document_is_a_fault_then_a_good_one_opens():
    c = app()
    bad = json.loads(json.dumps(BODY))
    bad["batches"][1]["lower"][2] = 7.0
    with c.websocket_connect(PATH) as ws:
        s = Json(ws)
        reply = s.send(bad)
        http = c.post("/v1/evaluate", json=bad)
        assert http.status_code == 422 and reply["kind"] == "error" and reply["detail"] == http.json()["detail"]
        ws.send_bytes(b"\xc1")  # not msgpack at all
        reply = msgpack.unpackb(ws.receive_bytes())
        assert reply["detail"][0]["type"] == "msgpack_invalid"
        assert s.send(BODY)["kind"] == "opened"


EYE = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
FAR = [0.0, 0.0, 1e300] + [1e300 * v for v in EYE[3:]]  # p and A near 1e300: a slide (C_j - C_i) . T_j overflows
X_OVERFLOWS = {"loc": ["body", "batches", 0, "body_ids", 0], "type": "value_error",
               "msg": "the joint coordinate x overflows float64 at this configuration (positions or edge too large)"}


def slide(q_prev: list) -> dict:
    """A #669 joint along +z between two bodies at the origin; body 1 at `q_prev` at the previous step."""
    return {"bodies": {"q": [EYE, EYE], "q_prev": [EYE, q_prev], "q_ref": [EYE, EYE]},
            "batches": [{"constitution_uid": 669, "base_uid": 20, "body_ids": [[0, 1]], "edges": [[[0, 0, 0], [0, 0, 1]]],
                         "lower": [-1.0], "upper": [1.0], "strength": [1.0]}]}


@pytest.mark.parametrize("Side", [Json, Binary], ids=["json", "msgpack"])
def test_a_slide_past_float64_is_a_fault_at_the_opening_and_at_a_commit(Side):
    """The opening (its coordinates at q_prev) and a commit name the joint whose slide overflows; before, their
    replies carried inf (JSON: null). A refused scene holds no room."""
    with app(max_session_joints=sizing.session_weight(1, 2)).websocket_connect(PATH) as ws:
        s = Side(ws)
        reply = s.send(slide(FAR))
        assert (reply["kind"], reply["status"], reply["detail"]) == ("error", 422, [X_OVERFLOWS]), reply
        assert s.send(slide(EYE))["kind"] == "opened"  # the worker's room for one scene was given back
        reply = s.send({"kind": "commit", "q": [EYE, FAR]})
        assert (reply["kind"], reply["status"], reply["detail"]) == ("error", 422, [X_OVERFLOWS]), reply
        assert arrays(s.send({"kind": "commit", "q": [EYE, EYE]}))["coordinates"][0].tolist() == [0.0]


def test_a_slide_past_float64_in_a_local_session():
    want = [(tuple(X_OVERFLOWS["loc"]), X_OVERFLOWS["msg"], X_OVERFLOWS["type"])]
    with pytest.raises(InvalidInput) as e:
        LocalClient().session(slide(FAR))
    assert [(f.loc, f.msg, f.type) for f in e.value.faults] == want
    with LocalClient().session(slide(EYE)) as s:
        with pytest.raises(InvalidInput) as e:
            s.commit([EYE, FAR])
        assert [(f.loc, f.msg, f.type) for f in e.value.faults] == want
        assert s.commit([EYE, EYE])[0].tolist() == [0.0]


OFFSET_OVERFLOWS = (("body", "batches", 0, "offset", 0), "the coordinate x + offset overflows float64", "value_error")


def far_hinge() -> dict:
    """A #670 hinge about +z carried in at the angle 1e308 (`prev_coordinate`), its bounds +-1.5e308."""
    return {"bodies": {"q": [EYE, EYE], "q_prev": [EYE, EYE], "q_ref": [EYE, EYE]},
            "batches": [{"constitution_uid": 670, "base_uid": 18, "body_ids": [[0, 1]], "edges": [[[0, 0, 0], [0, 0, 1]]],
                         "lower": [-1.5e308], "upper": [1.5e308], "strength": [1.0], "prev_coordinate": [1e308]}]}


@pytest.mark.parametrize("side", ["json", "msgpack", "local"])
def test_an_offset_that_would_overflow_the_committed_coordinate_is_refused_alike_and_changes_nothing(side):
    """An update whose offset 1e308 moves the committed 1e308 past float64 (update's `check_moved`): the same
    fault on every session path (tests/core/test_prepared.py has it in-process), and the scene answers after it
    bit for bit as before (an evaluation and a commit)."""
    update = {"batch": 0, "index": [0], "lower": [1.5e308], "upper": [1.7e308], "offset": [1e308]}
    with LocalClient().session(far_hinge()) as fresh:
        committed = fresh.commit([EYE, EYE])[0].tolist()  # (1e308 + 1 ulp: rem() of the angle at that scale)
    if side == "local":
        with LocalClient().session(far_hinge()) as s:
            before = s.evaluate([EYE, EYE])
            with pytest.raises(InvalidInput) as e:
                s.update(0, [0], lower=[1.5e308], upper=[1.7e308], offset=[1e308])
            assert [(f.loc, f.msg, f.type) for f in e.value.faults] == [OFFSET_OVERFLOWS]
            after = s.evaluate([EYE, EYE])
            assert (after.total_energy, after.batches[0].coordinate.tolist()) == (before.total_energy, [1e308])
            assert s.commit([EYE, EYE])[0].tolist() == committed
        return
    with app().websocket_connect(PATH) as ws:
        s = Json(ws) if side == "json" else Binary(ws)
        assert arrays(s.send(far_hinge()))["coordinates"][0].tolist() == [1e308]
        before = s.send({"kind": "evaluate", "q": [EYE, EYE]})
        reply = s.send({"kind": "update", **update})
        assert (reply["kind"], reply["status"]) == ("error", 422)
        assert [(tuple(f["loc"]), f["msg"], f["type"]) for f in reply["detail"]] == [OFFSET_OVERFLOWS]
        same(s.send({"kind": "evaluate", "q": [EYE, EYE]}), before)
        assert arrays(s.send({"kind": "commit", "q": [EYE, EYE]}))["coordinates"][0].tolist() == committed


def test_the_bearer_token_is_checked_on_the_upgrade():
    c = app(token="s3cret")
    for headers in ({}, {"Authorization": "Bearer wrong"}):
        with pytest.raises(WebSocketDenialResponse) as e, c.websocket_connect(PATH, headers=headers):
            pass
        assert e.value.status_code == 401 and e.value.headers["www-authenticate"].startswith("Bearer")
    with c.websocket_connect(PATH, headers={"Authorization": "Bearer s3cret"}) as ws:
        assert Json(ws).send(BODY)["kind"] == "opened"


def closed(ws) -> dict:
    """The server's close message (after any replies still queued)."""
    while True:
        msg = ws.receive()
        if msg["type"] == "websocket.close":
            return msg


def assert_counted(c: TestClient, reason: str) -> None:
    """The session's end is counted under `reason` (the handler counts it once its close is sent)."""
    line = f'jointlimits_sessions_total{{reason="{reason}"}} 1.0'
    deadline = time.monotonic() + 10
    while line not in (text := c.get("/metrics").text):
        assert time.monotonic() < deadline, text
        time.sleep(0.01)
    assert "jointlimits_sessions_open 0.0" in text


def test_too_many_sessions_on_a_worker():
    c = app(max_sessions=1)
    with c.websocket_connect(PATH) as first:
        Json(first).send(BODY)
        with c.websocket_connect(PATH) as second:
            msg = closed(second)
            assert msg["code"] == proto.TOO_MANY_SESSIONS and "maximum of 1 session;" in msg["reason"]
        assert Json(first).send({"kind": "evaluate", "q": Q})["kind"] == "evaluation"
    with c.websocket_connect(PATH) as third:  # the first one's place is free again
        assert Json(third).send(BODY)["kind"] == "opened"


def test_oversized_frame_closes_with_1009():
    c = app(max_frame_bytes=20_000)
    with c.websocket_connect(PATH) as ws:
        assert Json(ws).send(BODY)["kind"] == "opened"
        ws.send_bytes(b"\x00" * 20_001)
        msg = closed(ws)
        assert msg["code"] == proto.MESSAGE_TOO_BIG and "at most 20000" in msg["reason"]
    assert_counted(c, "frame_too_large")


def test_idle_session_closes_with_4408():
    c = app(session_idle_seconds=0.3)
    with c.websocket_connect(PATH) as ws:
        assert Json(ws).send(BODY)["kind"] == "opened"
        t = time.monotonic()
        msg = closed(ws)
        assert msg["code"] == proto.IDLE_TIMEOUT and "no message for 0.3 s" in msg["reason"]
        assert time.monotonic() - t >= 0.25
    assert_counted(c, "idle")


def test_scene_over_the_joint_limit_is_refused_and_closed():
    c = app(max_joints=5)
    with c.websocket_connect(PATH) as ws:
        reply = Json(ws).send(BODY)
        assert reply["kind"] == "error" and reply["status"] == 413
        assert reply["detail"][0]["loc"] == ["body", "batches"] and "at most 5" in reply["detail"][0]["msg"]
        close = closed(ws)
        assert close["code"] == proto.SCENE_TOO_LARGE and "request has 6 joints; this service accepts at most 5" in close["reason"]
    assert_counted(c, "scene_too_large")


def test_an_evaluate_over_the_answer_bound_is_a_413_fault_and_the_session_goes_on():
    """Sessions admit each evaluate on cost as POST /v1/evaluate does: the answer bound for its outputs."""
    c = app(max_answer_bytes=20_000)
    with c.websocket_connect(PATH) as ws:
        s = Json(ws)
        assert s.send({**BODY, "outputs": ["energy"]})["kind"] == "opened"
        energy = s.send({"kind": "evaluate", "q": Q, "outputs": ["energy"]})
        assert energy["kind"] == "evaluation"
        reply = s.send({"kind": "evaluate", "q": Q, "outputs": ["energy", "gradient", "hessian"]})
        assert reply["kind"] == "error" and reply["status"] == 413, reply
        assert "JOINTLIMITS_MAX_ANSWER_BYTES" in reply["detail"][0]["msg"]
        same(s.send({"kind": "evaluate", "q": Q, "outputs": ["energy"]}), energy)


def test_the_sessions_of_a_worker_hold_at_most_max_session_joints():
    """A scene that would bring the worker's sessions past the bound is refused (413, close 4413); one that
    fits opens; closing a session gives its joints back, and a refused scene holds nothing."""
    c = app(max_session_joints=sizing.session_weight(sum(len(b["body_ids"]) for b in BODY["batches"]), len(Q)))
    with c.websocket_connect(PATH) as first:
        assert Json(first).send(BODY)["kind"] == "opened"
        with c.websocket_connect(PATH) as second:
            reply = Json(second).send(BODY)
            assert reply["kind"] == "error" and reply["status"] == 413, reply
            assert "JOINTLIMITS_MAX_SESSION_JOINTS" in reply["detail"][0]["msg"]
            assert closed(second)["code"] == proto.SCENE_TOO_LARGE
    with c.websocket_connect(PATH) as third:  # the first session's joints were given back
        assert Json(third).send(BODY)["kind"] == "opened"


def test_metrics_count_sessions_and_messages():
    c = app(max_sessions=1)
    with c.websocket_connect(PATH) as ws:
        s = Json(ws)
        s.send(BODY)
        s.send({"kind": "evaluate", "q": Q})
        s.send({"kind": "evaluate", "q": Q[:1]})
        s.send({"kind": "commit", "q": Q})
        text = c.get("/metrics").text
        assert "jointlimits_sessions_open 1.0" in text
        with c.websocket_connect(PATH) as other:
            closed(other)
        ws.send_text(json.dumps({"kind": "close"}))
        closed(ws)
    text = c.get("/metrics").text
    for line in (
        "jointlimits_sessions_open 0.0",
        'jointlimits_sessions_total{reason="client"} 1.0',
        'jointlimits_sessions_total{reason="too_many_sessions"} 1.0',
        'jointlimits_session_messages_total{kind="open",outcome="ok"} 1.0',
        'jointlimits_session_messages_total{kind="evaluate",outcome="ok"} 1.0',
        'jointlimits_session_messages_total{kind="evaluate",outcome="fault"} 1.0',
        'jointlimits_session_messages_total{kind="commit",outcome="ok"} 1.0',
        'jointlimits_session_messages_total{kind="close",outcome="ok"} 1.0',
        'jointlimits_session_message_duration_seconds_count{kind="evaluate"} 2.0',
    ):
        assert line in text, line


def test_a_client_that_vanishes_frees_its_place():
    c = app(max_sessions=1)
    with c.websocket_connect(PATH) as ws:
        Json(ws).send(BODY)
    with c.websocket_connect(PATH) as ws:  # the first one closed without `close`
        assert Json(ws).send(BODY)["kind"] == "opened"
    text = c.get("/metrics").text
    assert "jointlimits_sessions_open 0.0" in text and 'jointlimits_sessions_total{reason="client"} 2.0' in text


def test_a_client_going_away_mid_session_ends_it_cleanly():
    c = app()
    with c.websocket_connect(PATH) as ws:
        Json(ws).send(BODY)
        ws.close(1001)
    deadline = time.monotonic() + 10
    while 'jointlimits_sessions_total{reason="disconnect"} 1.0' not in (text := c.get("/metrics").text):
        assert time.monotonic() < deadline, text
        time.sleep(0.01)
    assert 'reason="error"' not in text


def test_the_readme_hex_example_is_what_the_service_sends():
    from pathlib import Path

    from jointlimits.service.http import sessions as session_codec

    text = (Path(__file__).parents[2] / "docs" / "sessions.md").read_text()  # moved from the README
    block = text.split("For a scene of one revolute batch of one joint", 1)[1].split("```\n", 2)[1]
    dump = bytes.fromhex(" ".join(line.split("  ")[0] for line in block.splitlines()))
    reply = session_codec.encode({"kind": "committed", "coordinates": [np.array([0.7]), np.zeros(0)]}, True)
    assert dump == reply and len(reply) == 89
    assert msgpack.unpackb(pack({"kind": "commit", "q": np.zeros((2, 12))}))["q"]["data"] == bytes(192)
    assert pack({"kind": "commit", "q": np.zeros((2, 12))})[:42].hex() == (
        "82a46b696e64a6636f6d6d6974a17183a56474797065a33c6638a5736861706592020ca464617461c4c0")


def test_a_scene_over_the_inline_size_is_evaluated_in_a_thread_with_the_same_numbers():
    from jointlimits.service.http.sessions import INLINE_JOINTS

    body = scene(INLINE_JOINTS + 44, seed=5)
    c = app()
    http = c.post("/v1/evaluate", json={**body, "hessian_mode": "psd"}).json()
    with c.websocket_connect(PATH) as ws:
        s = Binary(ws)
        assert s.send(body)["batch_sizes"] == [150, 150]
        ev = s.send({"kind": "evaluate", "q": body["bodies"]["q"], "hessian_mode": "psd"})
        del ev["kind"]
        same(ev, http)
        reply = s.send({"kind": "commit", "q": body["bodies"]["q"][:-1]})
        assert reply["status"] == 422 and reply["detail"][0]["loc"] == ["body", "q"]


def test_pipelined_messages_are_answered_in_order():
    c = app()
    with c.websocket_connect(PATH) as ws:
        Json(ws).send(BODY)
        for i, doc in enumerate([{"kind": "evaluate", "q": Q}, {"kind": "commit", "q": Q[:1]}, {"kind": "commit", "q": Q}]):
            ws.send_text(json.dumps({**doc, "id": i}))
        replies = [json.loads(ws.receive_text()) for _ in range(3)]
    assert [(r["id"], r["kind"]) for r in replies] == [(0, "evaluation"), (1, "error"), (2, "committed")]


@pytest.mark.parametrize("Side", [Json, Binary], ids=["json", "msgpack"])
def test_the_opening_may_carry_an_id_that_its_reply_repeats(Side):
    with app().websocket_connect(PATH) as ws:
        s = Side(ws)
        bad = s.send({**BODY, "id": "open-1", "hessian_mode": "fast"})  # a fault repeats it too
        assert bad["kind"] == "error" and bad["id"] == "open-1"
        assert [d["loc"] for d in bad["detail"]] == [["body", "hessian_mode"]]
        too_long = s.send({**BODY, "id": "x" * 129})
        assert too_long["kind"] == "error" and too_long["detail"][0]["loc"][:2] == ["body", "id"]
        opened = s.send({**BODY, "id": 42})
        assert opened["kind"] == "opened" and opened["id"] == 42
        assert s.send({"kind": "evaluate", "q": Q, "id": 43})["id"] == 43


def faulty_opening(fault: str) -> dict:
    """An opening document with `fault`: 25 faults of the document (an unknown key in each of 25 batches), 30 of the
    core's (30 joints of negative strength), one of the core's, or 40 joints, over `max_joints=35` (a 413)."""
    if fault == "document":
        doc = scene(2, seed=3)
        return doc | {"batches": [doc["batches"][0] | {"spare": 1}] * 25}
    doc = scene({"core": 30, "admission": 40}.get(fault, 6), seed=3)
    for b in doc["batches"]:
        b["strength"] = [-1.0] * len(b["strength"]) if fault == "core" else b["strength"]
    doc["batches"][0]["strength"][0] = -1.0 if fault == "core one" else doc["batches"][0]["strength"][0]
    return doc


def in_order(doc: dict) -> bytes:
    """`doc` in msgpack, its keys in its own order, each numeric list an array map (`body_ids` int64)."""
    def walk(v, k=None):
        if isinstance(v, dict):
            return {kk: walk(vv, kk) for kk, vv in v.items()}
        if k == "batches":
            return [walk(b) for b in v]
        if isinstance(v, list) and k != "outputs":
            return wire.pack_array(np.array(v, np.int64 if k == "body_ids" else np.float64), wire.INT64 if k == "body_ids" else wire.FLOAT64)
        return v
    return wire.dumps(walk(doc))


@pytest.mark.parametrize("binary", [False, True], ids=["json", "msgpack"])
@pytest.mark.parametrize("first", [True, False], ids=["id first", "id last"])
@pytest.mark.parametrize("fault", ["document", "core", "core one", "admission"])
def test_a_faulty_opening_gets_its_id_back_whatever_its_faults(binary, first, fault):
    """The fault list is capped at MAX_FAULTS, and a msgpack opening's batches are checked as they are read: the cap
    must not stop the read before its `id` (failed before: no `id` in msgpack at the cap, and none on either
    encoding for a fault found by the core or by admission, after the document was read)."""
    doc = faulty_opening(fault)
    doc = {"id": "open-7", **doc} if first else {**doc, "id": "open-7"}
    with app(max_joints=35).websocket_connect(PATH) as ws:
        if binary:
            ws.send_bytes(in_order(doc))
            reply = msgpack.unpackb(ws.receive_bytes())
        else:
            ws.send_text(json.dumps(doc))
            reply = json.loads(ws.receive_text())
        assert reply["kind"] == "error" and reply["id"] == "open-7", reply
        assert (reply["status"], len(reply["detail"])) == {"document": (422, 20), "core": (422, 20), "core one": (422, 1),
                                                           "admission": (413, 1)}[fault], reply
        if fault != "admission":  # the session still waits for its opening
            opened = Json(ws).send({**scene(4, seed=3), "id": 8})
            assert opened["kind"] == "opened" and opened["id"] == 8, opened


@pytest.mark.parametrize("Side", [Json, Binary], ids=["json", "msgpack"])
@pytest.mark.parametrize("kind", ["evaluate", "commit", "update", "close"])
def test_a_message_before_the_opening_gets_one_clear_fault(Side, kind):
    from jointlimits.service.http.sessions import NOT_OPEN

    doc = {"kind": kind, "id": 5} | ({"q": Q} if kind in ("evaluate", "commit") else {})
    with app().websocket_connect(PATH) as ws:
        s = Side(ws)
        reply = s.send(doc)
        assert reply == {"kind": "error", "status": 422, "id": 5,
                         "detail": [{"loc": ["body", "kind"], "msg": NOT_OPEN, "type": "session_not_open"}]}
        assert s.send(BODY)["kind"] == "opened"  # the session still waits for its opening
