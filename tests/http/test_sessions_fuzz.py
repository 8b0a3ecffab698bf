"""Hostile session messages: whatever a client sends after opening, the reply is a fault or an answer and the
session goes on (never a 1011 close, never a NaN); generated with hypothesis, JSON and msgpack."""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jointlimits.schemas import binary as wire
from jointlimits.schemas import session as proto
from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.drills import scene
from tests.http.test_sessions import BODY, Q, open_binary

pytestmark = pytest.mark.slow  # fuzzes the session protocol (~3 s)

scalars = st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(allow_nan=False, allow_infinity=False),
                    st.text(max_size=8))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=6), inner, max_size=4)),
                      max_leaves=12)
keys = st.sampled_from(["kind", "q", "id", "outputs", "hessian_mode", "active_only", "batch", "index", "lower", "upper",
                        "strength", "offset", "extra"])
kinds = st.sampled_from([*proto.KEYS, "open", "", 3])


@st.composite
def messages(draw) -> dict:
    """Maps that look like messages: a kind (usually a real one) and some keys, each a real value or garbage."""
    doc = {"kind": draw(kinds)}
    for k in draw(st.lists(keys, max_size=5, unique=True)):
        real = {"q": Q, "index": [0, 1], "batch": 0, "lower": [-1.0, -1.0], "upper": [1.0, 1.0],
                "outputs": ["energy"], "hessian_mode": "psd", "active_only": True}
        doc[k] = real[k] if k in real and draw(st.booleans()) else draw(values)
    if doc["kind"] == "close":
        doc["kind"] = "evaluate"  # closing would end the session under test
    return doc


def _array_maps(doc: dict) -> dict:
    """Real-looking numeric lists as the binary transport's array maps (else sent as they are)."""
    out = {}
    for k, v in doc.items():
        try:
            a = np.array(v)
        except Exception:
            a = None
        if k in ("q", "lower", "upper", "strength", "offset") and a is not None and a.dtype.kind in "if":
            out[k] = wire.pack_array(a.astype(np.float64), wire.FLOAT64)
        elif k == "index" and a is not None and a.dtype.kind == "i" and np.all(np.abs(a) < 2**62):
            out[k] = wire.pack_array(a.astype(np.int64), wire.INT64)
        else:
            out[k] = v
    return out


APP = TestClient(create_app(Settings(token=None)))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(docs=st.lists(messages(), min_size=1, max_size=6), binary=st.booleans())
def test_any_message_gets_a_fault_or_an_answer_and_the_session_goes_on(docs, binary):
    with APP.websocket_connect(proto.PATH) as ws:
        if binary:
            ws.send_bytes(open_binary(BODY))
            assert msgpack.unpackb(ws.receive_bytes())["kind"] == "opened"
        else:
            ws.send_text(json.dumps(BODY))
            assert json.loads(ws.receive_text())["kind"] == "opened"
        for doc in docs:
            if binary:
                try:
                    frame = msgpack.packb(_array_maps(doc), use_bin_type=True)
                except (OverflowError, TypeError, ValueError):
                    continue  # not representable in msgpack at all
                ws.send_bytes(frame)
                reply = msgpack.unpackb(ws.receive_bytes())
            else:
                ws.send_text(json.dumps(doc))
                text = ws.receive_text()
                assert "NaN" not in text and "Infinity" not in text
                reply = json.loads(text)
            assert reply["kind"] in ("error", "evaluation", "committed", "updated"), reply
            if reply["kind"] == "error":
                assert reply["status"] in (413, 422) and reply["detail"] and all(
                    d["loc"][0] == "body" and d["msg"] for d in reply["detail"])
        # Still alive, still the same scene's numbers after any updates that were accepted.
        ws.send_text(json.dumps({"kind": "evaluate", "q": Q}))
        assert json.loads(ws.receive_text())["kind"] == "evaluation"


def test_garbage_frames_are_faults():
    with APP.websocket_connect(proto.PATH) as ws:
        ws.send_text(json.dumps(BODY))
        ws.receive_text()
        for frame in (b"", b"\xc1", b"\x93\x01\x02\x03", msgpack.packb({b"kind": b"evaluate"}), msgpack.packb([1, 2])):
            ws.send_bytes(frame)
            reply = msgpack.unpackb(ws.receive_bytes())
            assert reply["kind"] == "error" and reply["status"] == 422, (frame, reply)
        for frame in ("", "nul", "[1, 2]", '{"kind": "evaluate", "q": [[1e999]]}', "{" * 10_000):
            ws.send_text(frame)
            reply = json.loads(ws.receive_text())
            assert reply["kind"] == "error" and reply["status"] == 422, (frame, reply)
        other = scene(3, seed=9)["bodies"]["q"]  # another scene's bodies: 6 rows, this one has 12
        ws.send_text(json.dumps({"kind": "evaluate", "q": other}))
        assert json.loads(ws.receive_text())["detail"][0]["loc"] == ["body", "q"]
        ws.send_text(json.dumps({"kind": "evaluate", "q": Q}))
        assert json.loads(ws.receive_text())["kind"] == "evaluation"
