"""The Errors table (docs/http-api.md, moved from the README) shows real answers: each row's example is the first `detail` item the server sends.

`python -m tests.docs.test_readme_errors` rewrites the table's example column from a live server.
"""

from __future__ import annotations

import asyncio
import json
import re
import socket
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import httpx
import msgpack
import numpy as np
import pytest

from jointlimits.client import Request, codec
from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.http.test_contract_live import serve
from tests.http.test_errors_http import base_request, edit, edit_body, with_batch

pytestmark = pytest.mark.slow  # the Errors table's 30 answers from live servers (~2 s)

README_PATH = Path(__file__).resolve().parents[2] / "docs" / "http-api.md"
# The limits the table's 413 rows quote: the default body, batch and JSON-value limits, a 400-joint
# limit, a 1 MiB answer bound (the base request's answer is ~80 KB).
SETTINGS = Settings(max_body_bytes=256 * 2**20, max_joints=400, max_answer_bytes=2**20, token=None, cors_origins=())
J = "application/json"


def _sdk(mutate: Callable[[Request], Request], binary: bool = False) -> Callable[[str], httpx.Response]:
    """POST the base request (3 bodies; batch 0: 2 revolute, batch 1: 3 prismatic), changed by `mutate`."""
    def send(url: str) -> httpx.Response:
        body, content_type = codec.encode(mutate(base_request()), binary)
        return httpx.post(url + "/v1/evaluate", content=body, headers={"Content-Type": content_type})
    return send


def _doc(change: Callable[[dict], None], binary: bool = False, **headers: str) -> Callable[[str], httpx.Response]:
    """POST the base request's wire document after `change` edits it in place."""
    def send(url: str) -> httpx.Response:
        body, content_type = codec.encode(base_request(), binary)
        doc = msgpack.unpackb(body) if binary else json.loads(body)
        change(doc)
        content = msgpack.packb(doc) if binary else json.dumps(doc).encode()
        return httpx.post(url + "/v1/evaluate", content=content, headers={"Content-Type": content_type, **headers})
    return send


def _raw(content: bytes, content_type: str, **headers: str) -> Callable[[str], httpx.Response]:
    return lambda url: httpx.post(url + "/v1/evaluate", content=content, headers={"Content-Type": content_type, **headers})


def _declared_length(n: int) -> Callable[[str], httpx.Response]:
    """A request whose Content-Length says `n` bytes: refused from its header, before any byte of body."""
    def send(url: str) -> httpx.Response:
        host, port = url.removeprefix("http://").split(":")
        with socket.create_connection((host, int(port)), timeout=10) as s:
            s.sendall(f"POST /v1/evaluate HTTP/1.1\r\nHost: {host}\r\nContent-Type: {J}\r\n"
                      f"Content-Length: {n}\r\nConnection: close\r\n\r\n".encode())
            data = b""
            while chunk := s.recv(65536):
                data += chunk
        head, body = data.split(b"\r\n\r\n", 1)
        return httpx.Response(int(head.split()[1]), content=body)
    return send


def _lower_nan(doc: dict) -> None:
    doc["batches"][1]["lower"][2] = "@NaN"


def _twice(key: str) -> Callable[[str], httpx.Response]:
    """The base request as JSON text with batch 1 naming `key` twice."""
    def send(url: str) -> httpx.Response:
        doc = json.loads(codec.encode(base_request(), False)[0])
        batch = json.dumps(doc["batches"][1])
        twice = batch.replace("{", "{" + json.dumps(key) + ": " + json.dumps(doc["batches"][1][key]) + ", ", 1)
        return _raw(json.dumps(doc).replace(batch, twice, 1).encode(), J)(url)
    return send


def _set(*path: str | int, value: object) -> Callable[[dict], None]:
    def change(doc: dict) -> None:
        node = doc
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    return change


def _nan_json(url: str) -> httpx.Response:
    body, _ = codec.encode(base_request(), False)
    doc = json.loads(body)
    _lower_nan(doc)
    return httpx.post(url + "/v1/evaluate", content=json.dumps(doc).encode().replace(b'"@NaN"', b"NaN"),
                      headers={"Content-Type": J})


def _joints(n: int) -> Callable[[str], httpx.Response]:
    """The base request with `n` joints in all (batch 1 grown), as JSON."""
    def send(url: str) -> httpx.Response:
        r = base_request()
        b = r.batches[1]
        k = n - len(r.batches[0])
        many = replace(b, body_ids=np.tile(b.body_ids[:1], (k, 1)), edges=np.tile(b.edges[:1], (k, 1, 1)),
                       lower=np.full(k, -0.1), upper=np.full(k, 0.2), strength=np.ones(k))
        fields = {f: getattr(many, f) for f in ("body_ids", "edges", "lower", "upper", "strength")}
        return _sdk(lambda r: with_batch(r, 1, **fields))(url)
    return send


def _past_deadline(url: str) -> httpx.Response:
    """The base request on a server whose request timeout has passed before the core starts."""
    with serve(replace(SETTINGS, request_timeout=1e-9)) as other:
        return _sdk(lambda r: r)(other)


def _busy(budget: str) -> Callable[[str], httpx.Response]:
    """The base request on a server whose `budget` ("uploads" or "in_flight") other requests hold in full."""
    def send(url: str) -> httpx.Response:
        app = create_app(replace(SETTINGS, queue_timeout=0.1))
        b = getattr(app.state, budget)
        hold = asyncio.run(b.acquire(b.capacity, 1.0))
        try:
            with serve(app=app) as other:
                return _sdk(lambda r: r)(other)
        finally:
            hold.release()
    return send


EMPTY_BATCH = {"constitution_uid": 670, "body_ids": [], "edges": [], "lower": [], "upper": []}


# The table's first column -> the request that shows it.
CASES: dict[str, Callable[[str], httpx.Response]] = {
    "non-finite number (`NaN`, `Infinity`, `1e400`, `null`), in JSON, msgpack or local": _nan_json,
    "wrong row length / not a number / misspelt or missing field": _doc(_set("bodies", "q", value=[list(range(1, 12))] * 3)),
    "per-joint lists of different lengths, body rows that disagree": _sdk(lambda r: with_batch(r, 1, lower=r.batches[1].lower[:2])),
    "body index out of range or negative": _sdk(lambda r: edit(r, 1, "body_ids", 2, [0, 3])),
    "a joint on one body": _sdk(lambda r: edit(r, 1, "body_ids", 0, [2, 2])),
    "`lower > upper`": _sdk(lambda r: edit(r, 1, "lower", 2, 5.0)),
    "`strength < 0`": _sdk(lambda r: edit(r, 1, "strength", 2, -1.0)),
    "zero-length or overflowing edge": _sdk(lambda r: edit(r, 1, "edges", 2, [[0, 0, 1], [0, 0, 1]])),
    "singular `A_ref`": _sdk(lambda r: edit_body(r, "q_ref", 2, 0.0, slice(3, 12))),
    "UID pairing": _sdk(lambda r: with_batch(r, 0, base_uid=20)),
    "unknown constitution": _sdk(lambda r: with_batch(r, 1, constitution_uid=671)),
    "unknown `outputs` / `hessian_mode`": _doc(_set("outputs", value=["energy", "jacobian"])),
    "collapsed revolute frame (`cos = sin = 0`)": _sdk(lambda r: edit_body(r, "q", 1, 0.0, slice(3, 12))),
    "energy or derivatives overflow": _sdk(lambda r: with_batch(
        r, 0, lower=np.array([0.0, -1.0]), upper=np.array([1e-300, 1.0]), strength=np.array([1e308, 1.0]))),
    "joint coordinate overflows": _sdk(lambda r: edit_body(edit_body(r, "q", 2, 1e308, slice(0, 3)), "q", 0, -1e308, slice(0, 3))),
    "invalid JSON": _raw(b'{"bodies": ', J),
    "invalid msgpack": _raw(b"\x81\xa6bodies", "application/msgpack"),
    "malformed binary array": _doc(_set("bodies", "q", "shape", value=[2, 12]), binary=True),
    "body over `JOINTLIMITS_MAX_BODY_BYTES` (by header or while streaming)": _declared_length(300_000_000),
    "more joints than `JOINTLIMITS_MAX_JOINTS` (counted once parsed, before any work)": _joints(401),
    "`Content-Type` neither JSON nor msgpack": _raw(b"{}", "text/plain"),
    "`Accept` names neither": _doc(lambda doc: None, Accept="text/html"),
    "answer bound (joints x outputs x encoding) over `JOINTLIMITS_MAX_ANSWER_BYTES`, before any work": _joints(100),
    "more batches than `JOINTLIMITS_MAX_BATCHES`": _doc(_set("batches", value=[EMPTY_BATCH] * 4097)),
    "JSON body with more values than `JOINTLIMITS_MAX_JSON_VALUES` (commas + 1, or twice its lists and objects, or 8 times its keys, before parsing)": _raw(
        b'{"bodies": {"q": [' + b"0," * 2_000_000 + b"0]}}", J),
    "evaluation past `JOINTLIMITS_REQUEST_TIMEOUT`": _past_deadline,
    "body over the worker's upload budget (other bodies being received)": _busy("uploads"),
    "not started within `JOINTLIMITS_QUEUE_TIMEOUT` (the worker's in-flight budget held by other requests)": _busy("in_flight"),
    "a key twice in one object / map (JSON or msgpack)": _twice("lower"),
    "a msgpack map key that is not a `str` (e.g. `bin`)": _doc(
        lambda doc: doc["batches"][0].__setitem__(b"lower", doc["batches"][0].pop("lower")), binary=True),
    "a msgpack value with more than 64 maps and arrays, or one of more than 4096 items": _doc(
        _set("bodies", value=[0] * 5000), binary=True),
}


def table_rows(text: str) -> list[tuple[str, str, str]]:
    """(class, status, example) of each row of the page's Errors table."""
    section = text.split("\n## Errors\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ") and not line.startswith("| class")]
    return [tuple(c.strip() for c in re.split(r" \| ", row.strip("| "), maxsplit=2)) for row in rows]


def answers(url: str) -> Iterator[tuple[str, int, dict]]:
    for name, send in CASES.items():
        r = send(url)
        yield name, r.status_code, r.json()["detail"][0]


def cell(item: dict) -> str:
    return "`" + json.dumps(item) + "`"


@pytest.fixture(scope="module")
def real() -> dict[str, tuple[int, dict]]:
    with serve(SETTINGS) as url:
        return {name: (status, item) for name, status, item in answers(url)}


def test_every_row_of_the_table_has_a_request():
    assert [row[0] for row in table_rows(README_PATH.read_text())] == list(CASES)


@pytest.mark.parametrize("name", list(CASES))
def test_the_row_shows_the_real_answer(real, name):
    rows = {row[0]: row for row in table_rows(README_PATH.read_text())}
    status, item = real[name]
    assert (rows[name][1], rows[name][2]) == (str(status), cell(item))


def regenerate() -> None:
    text = README_PATH.read_text()
    with serve(SETTINGS) as url:
        for name, status, item in answers(url):
            old = next(row for row in table_rows(text) if row[0] == name)
            text = text.replace(f"| {' | '.join(old)} |", f"| {name} | {status} | {cell(item)} |")
    README_PATH.write_text(text)


if __name__ == "__main__":
    regenerate()
