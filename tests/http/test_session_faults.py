"""One fault per mistake in a session's later messages (`evaluate`, `commit`, `update`), whatever the path: a JSON
message, a msgpack message, the SDK's sessions (in-process, and over WebSocket in either encoding). The same
`(loc, msg, type)` list on each, as tests/http/test_one_fault_every_path.py pins for requests; and the session goes on."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import Client, InvalidInput, LocalClient
from jointlimits.schemas import binary as wire
from jointlimits.schemas import session as proto
from jointlimits.service.app import create_app
from jointlimits.service.core import InputError
from jointlimits.service.settings import Settings
from tests.http.test_contract_live import live  # noqa: F401 (fixture)
from tests.http.test_one_fault_every_path import base_doc

APP = TestClient(create_app(Settings(token=None, cors_origins=())))
Q = base_doc()["bodies"]["q"]
NOT_A_LIST = ("Input should be a valid list", "list_type")
NOT_AN_INTEGER = ("Input should be a valid integer", "int_type")
Item = tuple[tuple[Any, ...], str, str]


def to_msgpack(message: dict) -> bytes:
    """A message in msgpack: each list of numbers an array map (`index` of <i8), anything else as it is."""
    out = {}
    for k, v in message.items():
        if isinstance(v, list) and k != "outputs":
            dtype = wire.INT64 if k == "index" else wire.FLOAT64
            out[k] = wire.pack_array(np.asarray(v, dtype=np.dtype(dtype)), dtype)
        else:
            out[k] = v
    return wire.dumps(out)


def replies(frames: list[str | bytes]) -> list[dict]:
    """Open the base scene (in the frames' encoding), send each frame, read each reply."""
    binary = isinstance(frames[0], bytes)
    doc = base_doc()
    with APP.websocket_connect(proto.PATH) as ws:
        if binary:
            ws.send_bytes(wire.dumps({**doc, "bodies": {k: wire.pack_array(np.asarray(v), wire.FLOAT64) for k, v in doc["bodies"].items()},
                                      "batches": [{k: wire.pack_array(np.asarray(v, np.int64 if k == "body_ids" else np.float64),
                                                                      wire.INT64 if k == "body_ids" else wire.FLOAT64)
                                                   if isinstance(v, list) else v for k, v in b.items()} for b in doc["batches"]]}))
        else:
            ws.send_text(json.dumps(doc))
        read = (lambda: msgpack.unpackb(ws.receive_bytes())) if binary else (lambda: json.loads(ws.receive_text()))
        assert read()["kind"] == proto.OPENED
        out = []
        for frame in frames:
            ws.send_bytes(frame) if binary else ws.send_text(frame)
            out.append(read())
    return out


def detail(reply: dict) -> list[Item]:
    assert reply["kind"] == proto.ERROR and reply["status"] == 422, reply
    return [(tuple(d["loc"]), d["msg"], d["type"]) for d in reply["detail"]]


def raised(fn: Callable[[], Any]) -> list[Item]:
    with pytest.raises(InvalidInput) as e:
        fn()
    return [(f.loc, f.msg, f.type) for f in e.value.faults]


# name -> (the message, the SDK's call that sends it (None: the SDK cannot), its one fault; msgpack: False where the
# mistake cannot be written in msgpack (an index is an <i8 array map)).
UPDATE = {"kind": "update", "batch": 0, "index": [0], "lower": [-0.25]}
CASES: dict[str, tuple[dict, Callable[[Any], Any] | None, Item, bool]] = {
    # A null array: "Input should be a valid list" at the array, as in a request (issue 27).
    "null q (evaluate)": ({"kind": "evaluate", "q": None}, lambda s: s.evaluate(None), (("body", "q"), *NOT_A_LIST), True),
    "null q (commit)": ({"kind": "commit", "q": None}, lambda s: s.commit(None), (("body", "q"), *NOT_A_LIST), True),
    "null index": ({**UPDATE, "index": None}, lambda s: s.update(0, None, lower=[-0.25]), (("body", "index"), *NOT_A_LIST), True),
    "null lower": ({**UPDATE, "lower": None}, None, (("body", "lower"), *NOT_A_LIST), True),
    "null offset": ({**UPDATE, "offset": None}, None, (("body", "offset"), *NOT_A_LIST), True),
    # ... and a null option, as in a request (in JSON it was taken as absent).
    "null outputs": ({"kind": "evaluate", "q": Q, "outputs": None}, None, (("body", "outputs"), *NOT_A_LIST), True),
    "null hessian_mode": ({"kind": "evaluate", "q": Q, "hessian_mode": None}, None,
                          (("body", "hessian_mode"), "Input should be 'exact' or 'psd'", "literal_error"), True),
    "null active_only": ({"kind": "evaluate", "q": Q, "active_only": None}, None,
                         (("body", "active_only"), "Input should be a valid boolean", "bool_type"), True),
    "a number for outputs": ({"kind": "evaluate", "q": Q, "outputs": 5}, None, (("body", "outputs"), *NOT_A_LIST), True),
    # A number (or a string) where an array belongs.
    "a number for q (evaluate)": ({"kind": "evaluate", "q": 5.0}, lambda s: s.evaluate(5.0), (("body", "q"), *NOT_A_LIST), True),
    "a number for q (commit)": ({"kind": "commit", "q": 5}, lambda s: s.commit(5), (("body", "q"), *NOT_A_LIST), True),
    "a number for index": ({**UPDATE, "index": 0}, lambda s: s.update(0, 0, lower=[-0.25]), (("body", "index"), *NOT_A_LIST), True),
    "a number for lower": ({**UPDATE, "lower": 5.0}, lambda s: s.update(0, [0], lower=5.0), (("body", "lower"), *NOT_A_LIST), True),
    "a string for upper": ({**UPDATE, "upper": "x"}, lambda s: s.update(0, [0], upper="x"), (("body", "upper"), *NOT_A_LIST), True),
    # An array as given: the SDK flattened [[2.5]].
    "rows for upper": ({**UPDATE, "upper": [[2.5]]}, lambda s: s.update(0, [0], upper=[[2.5]]),
                       (("body", "batches", 0, "upper"), "must have shape (1,) (one entry per index), got (1, 1)", "value_error"), True),
    # An index is an integer: the SDK cast [0.5] to joint 0.
    "an index of 0.5": ({**UPDATE, "index": [0.5]}, lambda s: s.update(0, np.array([0.5]), lower=[-0.25]), (("body", "index", 0), *NOT_AN_INTEGER), False),
    "an index of 0.0": ({**UPDATE, "index": [1, 0.0], "lower": [-0.25, -0.25]},
                        lambda s: s.update(0, [1, 0.0], lower=[-0.25, -0.25]), (("body", "index", 1), *NOT_AN_INTEGER), False),
    "an index of true": ({**UPDATE, "index": [True]}, lambda s: s.update(0, [True], lower=[-0.25]), (("body", "index", 0), *NOT_AN_INTEGER), False),
    "a batch of 0.5": ({**UPDATE, "batch": 0.5}, lambda s: s.update(0.5, [0], lower=[-0.25]), (("body", "batch"), *NOT_AN_INTEGER), False),
    # Another kind's array is an unknown key (JSON took an update's `q` as its own and applied the update).
    "q in an update": ({**UPDATE, "q": Q}, None, (("body", "q"), "Extra inputs are not permitted", "extra_forbidden"), True),
    "index in an evaluate": ({"kind": "evaluate", "q": Q, "index": [0.5]}, None,
                             (("body", "index"), "Extra inputs are not permitted", "extra_forbidden"), True),
}


@pytest.mark.parametrize("name", CASES)
def test_a_message_gets_one_fault_on_every_service_path_and_the_session_goes_on(name):
    message, _, want, in_msgpack = CASES[name]
    encodings = [json.dumps] + ([to_msgpack] if in_msgpack else [])
    for encode in encodings:
        # Then a real update, and an evaluate that sees it: the fault changed nothing, the connection is still open.
        got, updated, ev = replies([encode(message), encode(UPDATE), encode({"kind": "evaluate", "q": Q, "outputs": ["energy"]})])
        assert detail(got) == [want], (encode.__name__, name)
        assert updated["kind"] == proto.UPDATED and ev["kind"] == proto.EVALUATION


@pytest.mark.parametrize("name", [n for n, case in CASES.items() if case[1] is not None])
def test_the_sdk_raises_what_the_service_answers(live, name):  # noqa: F811
    """LocalSession and the WebSocket sessions (JSON, msgpack): the fault of the service, before anything changes."""
    _, call, want, _ = CASES[name]
    doc = base_doc()
    with LocalClient().session(doc) as s:
        assert raised(lambda: call(s)) == [want]
        before = s.evaluate(Q).total_energy
    for binary in (False, True):
        with Client(live, binary=binary).session(doc) as s:
            assert raised(lambda: call(s)) == [want], binary
            # Neither the server's scene nor the SDK's copy of it changed (the cast made joint 0's lower -0.25).
            assert s.evaluate(Q).total_energy == before
            assert s.request_for_reopen().batches[0].lower.tolist() == doc["batches"][0]["lower"]


def test_a_number_in_a_0d_array_map_is_named_as_a_bare_one():
    """msgpack's other way to put a number where an array belongs: an array map of shape []."""
    scalar = {"dtype": wire.FLOAT64, "shape": [], "data": np.float64(5.0).tobytes()}
    got, = replies([to_msgpack({**UPDATE, "lower": scalar})])
    assert detail(got) == [(("body", "lower"), *NOT_A_LIST)]


def test_an_absent_value_is_left_as_it_is():
    """docs/sessions.md: an update sets the values it gives (absent: unchanged; null: a fault, above)."""
    upper = base_doc()["batches"][0]["upper"][0]
    for encode in (json.dumps, to_msgpack):
        updated, ev = replies([encode({**UPDATE, "lower": [upper - 0.5]}), encode({"kind": "evaluate", "q": Q})])
        assert updated == {"kind": proto.UPDATED, "batch": 0, "joints": 1} and ev["kind"] == proto.EVALUATION


def test_try_again_later_is_a_close_code_of_the_protocol():
    """1013 (the upload budget full) is named beside 4429 in schemas/session.py, the codes the SDK knows."""
    from jointlimits.service.http import sessions, timeouts

    assert proto.TRY_AGAIN_LATER == timeouts.TRY_AGAIN_LATER == 1013
    assert sessions.DISCONNECT_REASONS[proto.TRY_AGAIN_LATER] == "uploads_full"


@pytest.mark.parametrize(
    ("flood", "loc"),
    [
        ({"kind": "evaluate", "id": 7, "q": None, "extra": [{}] * 3_000_000}, ("body", "extra")),  # 3 MB, 3M dicts
        ({"kind": "evaluate", "id": [[[[]] * 60] * 60]}, ("body", "id")),  # 3600 nested arrays in 4 KB
        ({"kind": "commit", "q": [0.0] * 100_000, "id": "step 3"}, ("body", "q")),  # numbers travel as bin
    ],
    ids=["3M_empty_maps", "nested_arrays", "100k_numbers"],
)
def test_a_msgpack_message_flood_is_refused_before_it_is_built(flood, loc):
    """A later message is unpacked within a request body's bounds (`binary.MAX_CONTAINERS` maps and arrays of at
    most `binary.MAX_ITEMS` items per value): a 3 MB frame of empty maps would otherwise be ~300 MB of dicts on
    the event loop, a 64 MiB frame several GB. The fault names the key, its reply repeats a readable `id`, and the
    session goes on."""
    import tracemalloc

    from jointlimits.service.http import sessions as session_codec

    frame = msgpack.packb(flood)
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as e:
            session_codec.decode(frame, 10**9)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * len(frame) + 2**20, peak  # nothing built beyond a few containers per value
    assert any(f.loc == loc[1:] and f.type == "structure" for f in e.value.faults), e.value.faults
    good = msgpack.packb({"kind": "evaluate", "q": wire.pack_array(np.asarray(Q), wire.FLOAT64)})
    reply, after = replies([frame, good])
    assert any(tuple(d["loc"]) == loc and d["type"] == "structure" for d in reply["detail"]), reply
    readable = flood["id"] if isinstance(flood.get("id"), (int, str)) else None
    assert reply.get("id") == readable  # a readable id comes back
    assert after["kind"] == proto.EVALUATION


LONG_KEY = "k" * 100_000


@pytest.mark.parametrize("key", [LONG_KEY, b"\xff\x00"], ids=["a 100 kB key", "a msgpack bin key"])
def test_a_fault_echoing_a_key_reads_as_post_evaluate_answers_it(key):
    """A fault's `loc` that echoes the client's key is cut and made JSON-safe (`errors.render`) on every path: a
    session's reply echoed a 1 MB key whole (POST cuts it to 64 characters and `...`), and a msgpack `bin` key as
    `bin` (POST shows it as `b'...'`), for a later message and for the opening document alike."""
    doc = {**base_doc(), key: 1}
    frame = msgpack.packb(doc)  # its arrays as lists, not array maps: faults of their own, filtered out below
    want = [d for d in APP.post("/v1/evaluate", content=frame, headers={"content-type": "application/msgpack"}).json()["detail"]
            if d["type"] in ("extra_forbidden", "key_type")]
    assert len(want) == 1 and len(str(want[0]["loc"][-1])) < 100, want
    message = {"kind": "commit", "q": Q, key: 1}
    encodings = [msgpack.packb] + ([json.dumps] if isinstance(key, str) else [])
    for encode in encodings:
        assert [d for d in replies([encode(message)])[0]["detail"] if d["type"] == want[0]["type"]] == want, encode
    with APP.websocket_connect(proto.PATH) as ws:  # the opening document: its reply, then the session goes on
        ws.send_bytes(frame)
        reply = msgpack.unpackb(ws.receive_bytes())
    assert [d for d in reply["detail"] if d["type"] == want[0]["type"]] == want
