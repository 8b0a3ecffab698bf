"""One fault per mistake, whatever the path (docs/http-api.md, "Errors"; issue 20).

Each malformed input of the errors table (docs/http-api.md), as one wire document, goes through every path that can
carry it: JSON and msgpack over HTTP, a session's opening (then an `evaluate`) in JSON and in msgpack, the
local mode from the dict and from arrays. Every path answers the same `(loc, msg, type)` list. The rows
of the table that only one encoding can carry (invalid JSON, a msgpack `bin` key, ...) are listed as such,
and every row of the table is one or the other.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import InvalidInput, LocalClient, codec
from jointlimits.client.model import JointBatch, Request
from jointlimits.schemas import binary as wire
from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.http.test_errors_http import base_request
from tests.docs.test_readme_errors import README_PATH, table_rows

Doc = dict[str, Any]
F8, I8 = "<f8", "<i8"
BODY_ARRAYS = ("q", "q_prev", "q_ref")
BATCH_ARRAYS = {"body_ids": I8, "edges": F8, "local_edges": F8, "lower": F8, "upper": F8, "strength": F8,
                "offset": F8, "prev_coordinate": F8}


def base_doc() -> Doc:
    """The errors table's base request (3 bodies; batch 0: 2 revolute joints, batch 1: 3 prismatic) as wire JSON."""
    return json.loads(codec.encode(base_request(), binary=False)[0])


def put(*path: str | int, value: Any) -> Callable[[Doc], None]:
    def change(doc: Doc) -> None:
        node = doc
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    return change


def cols(name: str, row: int, value: float, start: int, stop: int) -> Callable[[Doc], None]:
    def change(doc: Doc) -> None:
        doc["bodies"][name][row][start:stop] = [value] * (stop - start)
    return change


def both(*changes: Callable[[Doc], None]) -> Callable[[Doc], None]:
    def change(doc: Doc) -> None:
        for c in changes:
            c(doc)
    return change


def drop(*path: str | int) -> Callable[[Doc], None]:
    def change(doc: Doc) -> None:
        node = doc
        for k in path[:-1]:
            node = node[k]
        del node[path[-1]]
    return change


def q_of_rows_of(n: int) -> Callable[[Doc], None]:
    return lambda doc: doc["bodies"].__setitem__("q", [row[:n] + [0.0] * (n - 12) for row in doc["bodies"]["q"]])


# The errors table's row (its first column) -> the malformed input that shows it on every path.
CASES: dict[str, Callable[[Doc], None]] = {
    "non-finite number (`NaN`, `Infinity`, `1e400`, `null`), in JSON, msgpack or local": put("batches", 1, "lower", 2, value=float("nan")),
    "wrong row length / not a number / misspelt or missing field": q_of_rows_of(11),
    "per-joint lists of different lengths, body rows that disagree": lambda doc: doc["batches"][1]["lower"].pop(),
    "body index out of range or negative": put("batches", 1, "body_ids", 2, value=[0, 3]),
    "a joint on one body": put("batches", 1, "body_ids", 0, value=[2, 2]),
    "`lower > upper`": put("batches", 1, "lower", 2, value=5.0),
    "`strength < 0`": put("batches", 1, "strength", 2, value=-1.0),
    "zero-length or overflowing edge": put("batches", 1, "edges", 2, value=[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]),
    "singular `A_ref`": cols("q_ref", 2, 0.0, 3, 12),
    "UID pairing": put("batches", 0, "base_uid", value=20),
    "unknown constitution": put("batches", 1, "constitution_uid", value=671),
    "unknown `outputs` / `hessian_mode`": put("outputs", value=["energy", "jacobian"]),
    "collapsed revolute frame (`cos = sin = 0`)": cols("q", 1, 0.0, 3, 12),
    "energy or derivatives overflow": both(put("batches", 0, "lower", value=[0.0, -1.0]), put("batches", 0, "upper", value=[1e-300, 1.0]),
                                           put("batches", 0, "strength", value=[1e308, 1.0])),
    "joint coordinate overflows": both(cols("q", 2, 1e308, 0, 3), cols("q", 0, -1e308, 0, 3)),
}
# More mistakes of the same rows, each a different way to get them wrong (issue 20's examples among them).
MORE: dict[str, Callable[[Doc], None]] = {
    "q of 13 numbers a row": q_of_rows_of(13),
    "q one level too deep": lambda doc: doc["bodies"].__setitem__("q", [[[x] for x in row] for row in doc["bodies"]["q"]]),
    "q_prev of 2 rows": lambda doc: doc["bodies"]["q_prev"].pop(),
    "edges with points of 2": put("batches", 1, "edges", value=[[p[:2] for p in e] for e in base_doc()["batches"][1]["edges"]]),
    "body_ids of triples": put("batches", 1, "body_ids", value=[[0, 1, 2]] * 3),
    "a missing field": drop("batches", 1, "upper"),
    "a misspelt field": lambda doc: doc["batches"][1].__setitem__("lowr", doc["batches"][1].pop("lower")),
    "no outputs": put("outputs", value=[]),
    "unknown hessian_mode": put("hessian_mode", value="fast"),
    "unknown layout": put("layout", value="rows"),
    # A `null` where an array belongs (issue 27): "Input should be a valid list", list_type, at the array.
    "a null per-joint array": put("batches", 1, "lower", value=None),
    "a null body_ids": put("batches", 0, "body_ids", value=None),
    "a null state of the bodies": put("bodies", "q_prev", value=None),
    "a null optional array": put("batches", 1, "strength", value=None),
    "a null edges": put("batches", 1, "edges", value=None),
    "null outputs": put("outputs", value=None),
    # A number where an array belongs: the same words (a bare msgpack number, a 0-d array in the local mode).
    "a number for a per-joint array": put("batches", 1, "lower", value=5.0),
    "a number for a state of the bodies": put("bodies", "q_prev", value=1.0),
    "a number for body_ids": put("batches", 0, "body_ids", value=0),
    "a number for an optional array": put("batches", 1, "offset", value=0.5),
    "faults of every class at once": both(put("batches", 1, "body_ids", 2, value=[0, 3]), put("batches", 1, "lower", 0, value=5.0),
                                          put("batches", 0, "strength", 1, value=-1.0), put("batches", 0, "upper", 0, value=float("inf"))),
}
# Rows only one encoding (or HTTP alone) can show: nothing to compare across paths.
ONE_PATH = {
    "invalid JSON", "invalid msgpack", "malformed binary array", "a msgpack map key that is not a `str` (e.g. `bin`)",
    "a msgpack value with more than 64 maps and arrays, or one of more than 4096 items",
    "a key twice in one object / map (JSON or msgpack)",  # a dict cannot hold one: tests/http/test_hostile_wire.py, both encodings
}

Item = tuple[tuple[Any, ...], str, str]


def items(detail: list[dict]) -> list[Item]:
    return [(tuple(d["loc"]), d["msg"], d["type"]) for d in detail]


def to_msgpack(doc: Doc) -> bytes:
    """The document in the binary encoding: its arrays as array maps (a ragged list cannot be one); a null stays
    nil and a number a msgpack number."""
    out = copy.deepcopy(doc)
    for name in BODY_ARRAYS:
        if isinstance(out.get("bodies", {}).get(name), list):
            out["bodies"][name] = wire.pack_array(np.asarray(out["bodies"][name], dtype=np.float64), F8)
    for batch in out.get("batches", []):
        for name, dtype in BATCH_ARRAYS.items():
            if isinstance(batch.get(name), list):
                batch[name] = wire.pack_array(np.asarray(batch[name], dtype=np.dtype(dtype)), dtype)
    return wire.dumps(out)


def to_request(doc: Doc) -> Request:
    """The document as the SDK's arrays, taken as they are (no constructor's checks): the local mode's input."""
    arr = lambda v, t=np.float64: None if v is None else np.asarray(v, dtype=t)  # noqa: E731
    batches = [JointBatch(constitution_uid=b["constitution_uid"], base_uid=b.get("base_uid"), body_ids=arr(b["body_ids"], np.int64),
                          edges=arr(b.get("edges")), local_edges=arr(b.get("local_edges")), lower=arr(b["lower"]), upper=arr(b["upper"]),
                          strength=arr(b["strength"]), offset=arr(b.get("offset")), prev_coordinate=arr(b.get("prev_coordinate")))
               for b in doc["batches"]]
    bodies = doc["bodies"]
    return Request(arr(bodies["q"]), arr(bodies["q_prev"]), arr(bodies["q_ref"]), batches,
                   tuple(doc.get("outputs", ("energy", "gradient", "hessian"))), doc.get("hessian_mode", "exact"),
                   doc.get("active_only", False), doc.get("layout", "joints"))


@pytest.fixture(scope="module")
def app() -> TestClient:
    return TestClient(create_app(Settings(token=None, cors_origins=())))


def http(app: TestClient, doc: Doc, binary: bool) -> list[Item]:
    body, kind = (to_msgpack(doc), "application/msgpack") if binary else (json.dumps(doc).encode(), "application/json")
    r = app.post("/v1/evaluate", content=body, headers={"Content-Type": kind})
    assert r.status_code == 422, r.text[:300]
    return items(r.json()["detail"])


def session(app: TestClient, doc: Doc, binary: bool) -> list[Item]:
    """The opening's fault; if it opens (the fault is the evaluation's), the `evaluate` of its q.
    A session message names `q` as `["body", "q", ...]`: compared as the request's `bodies.q`."""
    send = (lambda ws, m: ws.send_bytes(m)) if binary else (lambda ws, m: ws.send_text(m))
    read = (lambda ws: msgpack.unpackb(ws.receive_bytes())) if binary else (lambda ws: json.loads(ws.receive_text()))
    with app.websocket_connect("/v1/sessions") as ws:
        send(ws, to_msgpack(doc) if binary else json.dumps(doc))
        reply = read(ws)
        if reply["kind"] == "opened":
            q = doc["bodies"]["q"]
            message = {"kind": "evaluate", "q": wire.pack_array(np.asarray(q, dtype=np.float64), F8) if binary else q}
            send(ws, wire.dumps(message) if binary else json.dumps(message))
            reply = read(ws)
    assert reply["kind"] == "error" and reply["status"] == 422, reply
    return [((*loc[:1], "bodies", *loc[1:]) if loc[1:2] == ("q",) else loc, msg, t) for loc, msg, t in items(reply["detail"])]


def local_dict(doc: Doc) -> list[Item]:
    with pytest.raises(InvalidInput) as e:
        LocalClient().evaluate(doc)
    return [(f.loc, f.msg, f.type) for f in e.value.faults]


def local_arrays(doc: Doc) -> list[Item]:
    with pytest.raises(InvalidInput) as e:
        LocalClient().evaluate(to_request(doc))
    return [(f.loc, f.msg, f.type) for f in e.value.faults]


def answers(app: TestClient, change: Callable[[Doc], None]) -> dict[str, list[Item]]:
    doc = base_doc()
    change(doc)
    out = {"json": http(app, doc, False), "session json": session(app, doc, False), "local dict": local_dict(doc)}
    try:
        to_msgpack(doc)
    except ValueError:
        return out  # ragged: no binary or array form
    out |= {"msgpack": http(app, doc, True), "session msgpack": session(app, doc, True)}
    # The SDK's arrays hold what a dict does, but a None edges or offset is an absent one, and outputs are no array.
    optional = (b.get(k, 0) is None for b in doc["batches"] for k in ("edges", "local_edges", "offset", "prev_coordinate"))
    if (all(k in doc["batches"][b] for b in range(len(doc["batches"])) for k in ("lower", "upper", "strength"))
            and doc.get("outputs", ()) is not None and not any(optional)):
        out["local arrays"] = local_arrays(doc)
    return out


@pytest.mark.parametrize("name", [*CASES, *MORE])
def test_every_path_answers_the_same_faults(app, name):
    got = answers(app, {**CASES, **MORE}[name])
    assert len(got) >= 5
    if name == "faults of every class at once":  # and all of them, not one class at a time
        assert len(got["json"]) == 4
    want = got["json"]
    assert want and all(loc[0] == "body" for loc, _, _ in want)
    assert {path: faults for path, faults in got.items() if faults != want} == {}, want


def test_a_null_array_is_named_at_the_array_as_not_a_list(app):
    """Issue 27: the words of a number where an array belongs (and of JSON's `q: null` before), on every path."""
    nulls = {"a null per-joint array": ("batches", 1, "lower"), "a null body_ids": ("batches", 0, "body_ids"),
             "a null state of the bodies": ("bodies", "q_prev"), "a null optional array": ("batches", 1, "strength"),
             "a null edges": ("batches", 1, "edges"), "null outputs": ("outputs",),
             "a number for a per-joint array": ("batches", 1, "lower"), "a number for a state of the bodies": ("bodies", "q_prev"),
             "a number for body_ids": ("batches", 0, "body_ids"), "a number for an optional array": ("batches", 1, "offset")}
    for name, loc in nulls.items():
        got = answers(app, MORE[name])
        assert len(got) >= 5 and all(f == [(("body", *loc), "Input should be a valid list", "list_type")] for f in got.values()), got


def test_every_row_of_the_errors_table_is_compared_or_one_paths_own():
    rows = {row[0]: row[1] for row in table_rows(README_PATH.read_text())}
    input_rows = {name for name, status in rows.items() if status == "422"}
    assert input_rows == set(CASES) | ONE_PATH


def test_the_table_example_is_what_every_path_says(app):
    """Where the table's example is the first fault of the case above, every path says exactly it."""
    rows = {row[0]: row[2] for row in table_rows(README_PATH.read_text())}
    for name, change in CASES.items():
        example = json.loads(rows[name].strip("`"))
        first = answers(app, change)["json"][0]
        if first[0][1:3] == tuple(example["loc"][1:3]):
            assert first == (tuple(example["loc"]), example["msg"], example["type"]), name


# The SDK's constructors raise the same faults, naming the field, before any request is made.


def _raised(fn: Callable[[], Any]) -> list[Item]:
    with pytest.raises(InvalidInput) as e:
        fn()
    assert isinstance(e.value, ValueError) and "invalid input (" in str(e.value)
    return [(f.loc, f.msg, f.type) for f in e.value.faults]


def test_joint_batch_of_names_the_field_in_the_services_words(app):
    from jointlimits.client import JointBatch

    edge = [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    assert _raised(lambda: JointBatch.of(669, [[0, 1], [1, 2]], np.zeros((2, 2, 2)), -1, 1)) == [
        (("edges",), "must have shape (2, 2, 3) (one row per joint of body_ids), got (2, 2, 2)", "value_error")]
    # ... the words the service uses for the same edges (here batch 1 of the base request, whose edges have points of 2)
    wire_words = answers(app, MORE["edges with points of 2"])["json"][0][1]
    assert wire_words == "must have shape (3, 2, 3) (one row per joint of body_ids), got (3, 2, 2)"
    assert _raised(lambda: JointBatch.of(670, [[0, 1, 2]], [edge], -1, 1)) == [
        (("body_ids",), "must have shape (N, 2), one [i, j] per joint, got (1, 3)", "value_error")]
    assert _raised(lambda: JointBatch.of(670, [[0, 1], [1, 2]], [edge, edge], [0.0, 1.0, 2.0], 1)) == [
        (("lower",), "must have shape (2,) (one row per joint of body_ids), got (3,)", "value_error")]
    # `upper` holds numbers: a list in it is the item at fault, as the wire's schema says (tests/http/test_validator_contract.py)
    assert _raised(lambda: JointBatch.of(670, [[0, 1]], [edge], -1, [["x"]])) == [(("upper", 0), "Input should be a valid number", "float_type")]
    assert _raised(lambda: JointBatch.of(670, [[0, 1.5]], [edge], -1, 1)) == [(("body_ids", 0, 1), "Input should be a valid integer", "int_type")]


def test_scene_and_dofs_name_the_pose_and_hint_at_4x4_poses():
    from jointlimits.client.scene import Scene, dofs, request_from_arrays

    assert _raised(lambda: dofs(np.zeros(5))) == [(("pose",), "a pose is a 4x4 transform, a (p, A) pair or 12 DOFs, got shape (5,)", "value_error")]
    scene = Scene()
    scene.add_body(np.eye(4))
    assert _raised(lambda: scene.add_body(np.eye(4), ref=np.eye(3)))[0][0] == ("bodies", "q_ref", 1)
    assert _raised(lambda: scene.add_revolute_limit(0, 0, [0, 0], [0, 0, 1], lower=-1, upper=1)) == [
        (("p0",), "must be a point (3,), got shape (2,)", "value_error")]
    poses = np.tile(np.eye(4), (2, 1, 1))  # 4x4 poses where DOFs belong
    (loc, msg, _), = _raised(lambda: request_from_arrays(poses, []))
    assert loc == ("bodies", "q") and "got shape (2, 4, 4)" in msg and "jointlimits.client.scene.dofs" in msg
    # The service says the same of the same arrays (the hint is the core's, on every path).
    with pytest.raises(InvalidInput, match="jointlimits.client.scene.dofs"):
        LocalClient().evaluate(Request(poses, poses, poses, []))
