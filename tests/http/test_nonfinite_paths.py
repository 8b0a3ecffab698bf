"""One NaN, one message: a non-finite number gets the same `loc` (to the element), words and type on every path.

Paths: JSON `null`, `NaN`, `Infinity`, `-Infinity`, `1e400` and a 401-digit integer (raw bodies); msgpack NaN and infinity bits;
the SDK over HTTP in both encodings (its JSON writes NaN as `null`); the local mode.
"""

from __future__ import annotations

import json

import httpx
import msgpack
import numpy as np
import pytest

from jointlimits.client import Client, InvalidInput, LocalClient, codec
from jointlimits.schemas import binary as wire
from tests.http.test_contract_live import live  # noqa: F401 (fixture)
from tests.http.test_errors_http import base_request, edit, edit_body, with_batch

pytestmark = pytest.mark.slow  # each fault through JSON, msgpack, local and sessions on a live server (~3 s)

FINITE = ("Input should be a finite number", "finite_number")
PAST_RANGE = "1" + "0" * 400  # 1e400 as a JSON integer: no float64 holds it, so it is infinite as 1e400 is

# Where the bad number goes: the path in the request document, and the mutation of the SDK request.
PLACES = [
    (("bodies", "q", 1, 4), lambda r, v: edit_body(r, "q", 1, v, 4)),
    (("bodies", "q_ref", 2, 0), lambda r, v: edit_body(r, "q_ref", 2, v, 0)),
    (("batches", 1, "lower", 2), lambda r, v: edit(r, 1, "lower", 2, v)),
    (("batches", 0, "upper", 1), lambda r, v: edit(r, 0, "upper", 1, v)),
    (("batches", 1, "strength", 0), lambda r, v: edit(r, 1, "strength", 0, v)),
    (("batches", 1, "edges", 2, 1, 0), lambda r, v: _edge(r, v)),
]


def _edge(r, v):
    e = np.array(r.batches[1].edges, copy=True)
    e[2, 1, 0] = v
    return with_batch(r, 1, edges=e)


def _json_with(token: str, path: tuple) -> bytes:
    doc = json.loads(codec.encode(base_request(), binary=False)[0])
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = "@@"
    return json.dumps(doc).encode().replace(b'"@@"', token.encode())


def _msgpack_with(value: float, path: tuple) -> bytes:
    doc = msgpack.unpackb(codec.encode(base_request(), binary=True)[0])
    if path[0] == "bodies":
        node, field, at = doc["bodies"], path[1], path[2:]
    else:
        node, field, at = doc["batches"][path[1]], path[2], path[3:]
    a = wire.unpack_array(node[field], "<f8", len(at)).copy()
    a[at] = value
    node[field] = wire.pack_array(a, "<f8")
    return msgpack.packb(doc)


def _items(detail: list[dict]) -> list[tuple]:
    return [(tuple(d["loc"]), d["msg"], d["type"]) for d in detail]


def _raw(url: str, content_type: str, body: bytes) -> list[tuple]:
    r = httpx.post(url + "/v1/evaluate", content=body, headers={"Content-Type": content_type})
    assert r.status_code == 422, r.text
    return _items(r.json()["detail"])


def _sdk(client, request) -> list[tuple]:
    with pytest.raises(InvalidInput) as err:
        client.evaluate(request)
    return [(f.loc, f.msg, f.type) for f in err.value.faults]


@pytest.mark.parametrize(("path", "mutate"), PLACES, ids=[".".join(map(str, p)) for p, _ in PLACES])
def test_every_path_says_the_same(live, path, mutate):
    want = [(("body", *path), *FINITE)]
    got = {
        **{f"json {t}": _raw(live, "application/json", _json_with(t, path))
           for t in ("null", "NaN", "Infinity", "-Infinity", "1e400", "-1e400", PAST_RANGE, "-" + PAST_RANGE)},
        **{f"msgpack {v}": _raw(live, "application/msgpack", _msgpack_with(v, path)) for v in (np.nan, np.inf, -np.inf)},
        **{f"sdk binary {v}": _sdk(Client(live), mutate(base_request(), v)) for v in (np.nan, -np.inf)},
        **{f"sdk json {v}": _sdk(Client(live, binary=False), mutate(base_request(), v)) for v in (np.nan, np.inf)},
        **{f"local {v}": _sdk(LocalClient(), mutate(base_request(), v)) for v in (np.nan, np.inf)},
    }
    assert {k: v for k, v in got.items() if v != want} == {}


def test_several_bad_numbers_in_one_row_are_each_named(live):
    r = edit_body(edit_body(base_request(), "q", 1, np.nan, 4), "q", 1, np.inf, 7)
    want = [(("body", "bodies", "q", 1, c), *FINITE) for c in (4, 7)]
    assert _sdk(LocalClient(), r) == want
    assert _sdk(Client(live), r) == want
    assert _sdk(Client(live, binary=False), r) == want


def test_a_string_is_still_not_a_number(live):
    """Only `null` joins the non-finite numbers; `"0.5"` keeps pydantic's "valid number"."""
    items = _raw(live, "application/json", _json_with('"0.5"', ("batches", 1, "upper", 1)))
    assert items == [(("body", "batches", 1, "upper", 1), "Input should be a valid number", "float_type")]
