"""Hostile bodies (issue 9): never a 500, one fault cap per request, keys checked, echoes bounded.

The probes of the issue, over real HTTP: a msgpack `bin` map key at any depth, repeated keys
in both encodings, a 2 MB unknown key, and 300k empty batches (300 KB of msgpack, its JSON
twin), which once took 18.7 s and answered 177 MB of faults.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import fields

import httpx
import msgpack
import pytest
from pydantic import ValidationError

from jointlimits.schemas import EvaluateRequest
from jointlimits.schemas.session import OpeningRequest

from jointlimits.service.core import InputError, evaluate
from jointlimits.service.core.errors import MAX_FAULTS
from jointlimits.service.http import binary, convert
from jointlimits.service.http.errors import MAX_KEY_CHARS, render
from jointlimits.service.settings import Settings
from tests.http.test_contract_live import serve
from tests.http.test_errors_http import _bin, _json

pytestmark = pytest.mark.slow  # floods of hostile bodies (millions of items) through both decoders (~2.5 s)

J, B = "application/json", "application/msgpack"


def _roomy() -> Settings:
    """Limits that let every probe reach the decoders: 8 MB bodies, and any batch-count limit set high."""
    high = {f.name: 10**7 for f in fields(Settings) if "batch" in f.name}
    return Settings(max_body_bytes=8_000_000, token=None, cors_origins=(), **high)


@pytest.fixture(scope="module")
def roomy() -> Iterator[str]:
    with serve(_roomy()) as url:
        yield url


def post(url: str, body: bytes, content_type: str) -> httpx.Response:
    return httpx.post(f"{url}/v1/evaluate", content=body, headers={"Content-Type": content_type}, timeout=120)


def _dup_map(*pairs: tuple[str, object]) -> bytes:
    """A msgpack map written pair by pair, so that a key may repeat (a dict cannot hold that)."""
    return bytes([0x80 | len(pairs)]) + b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in pairs)


# ----------------------------------------------------------------------------- bin keys (item 1)

BIN_KEYS = [
    ("top", {b"bodies": 1}, ["body", "b'bodies'"]),
    ("bodies", lambda d: d["bodies"].__setitem__(b"q", 1), ["body", "bodies", "b'q'"]),
    ("batch", lambda d: d["batches"][1].__setitem__(b"lower", 1), ["body", "batches", 1, "b'lower'"]),
    ("array_map", lambda d: d["batches"][0]["upper"].__setitem__(b"data", b""), ["body", "batches", 0, "upper", "b'data'"]),
]


@pytest.mark.parametrize(("name", "doc", "loc"), BIN_KEYS, ids=[c[0] for c in BIN_KEYS])
def test_bin_map_key_at_any_depth_is_a_422_naming_it(roomy, name, doc, loc):
    body = msgpack.packb(doc, use_bin_type=True) if isinstance(doc, dict) else _bin_with(doc)
    r = post(roomy, body, B)
    assert r.status_code == 422, r.text[:300]
    assert any(d["loc"] == loc and d["type"] == "key_type" for d in r.json()["detail"]), r.json()


def _bin_with(mutate) -> bytes:
    doc = msgpack.unpackb(_bin(), raw=False)
    mutate(doc)
    return msgpack.packb(doc, use_bin_type=True)


def test_render_makes_any_loc_json_safe_and_short():
    from jointlimits.service.core import Fault

    import numpy as np

    out = render([Fault((b"\xff" * 10, "k" * 10_000, np.int64(3), True, 1.5), "m" * 10_000)], ("body",))
    loc = out["detail"][0]["loc"]
    json.dumps(out)  # no bytes, nothing unserialisable
    assert loc[0] == "body" and loc[3] == 3 and type(loc[3]) is int and all(isinstance(x, (int, str)) for x in loc)
    assert loc[2] == "k" * MAX_KEY_CHARS + "..." and all(len(str(x)) <= MAX_KEY_CHARS + 3 for x in loc)
    assert len(out["detail"][0]["msg"]) < 1100


# ----------------------------------------------------------------------------- duplicate keys

JSON_DUPS = [
    ("top", b'{"bodies": {"q": [], "q_prev": [], "q_ref": []}, "batches": [], "batches": []}', ["body", "batches"]),
    ("bodies", b'{"bodies": {"q": [], "q_prev": [], "q_ref": [], "q": []}, "batches": []}', ["body", "bodies", "q"]),
    ("escaped", None, ["body", "batches", 1, "lower"]),
    ("batch", None, ["body", "batches", 0, "strength"]),
]


def _json_dup(name: str) -> bytes:
    text = json.dumps(_json())
    if name == "escaped":  # "\u006cower" is "lower": the same key, spelt otherwise
        i = text.index('"lower"', text.index('"constitution_uid": 669'))
        return (text[:i] + '"\\u006cower": [0.0, 0.0, 0.0], ' + text[i:]).encode()
    i = text.index('"strength"')
    return (text[:i] + '"strength": [1.0, 1.0], ' + text[i:]).encode()


@pytest.mark.parametrize(("name", "body", "loc"), JSON_DUPS, ids=[c[0] for c in JSON_DUPS])
def test_json_duplicate_key_is_refused_naming_it(roomy, name, body, loc):
    r = post(roomy, body or _json_dup(name), J)
    assert r.status_code == 422, r.text[:300]
    assert any(d["loc"] == loc and d["type"] == "duplicate_key" for d in r.json()["detail"]), r.json()


def test_json_without_duplicates_still_answers_200(roomy):
    r = post(roomy, json.dumps(_json()).encode(), J)
    assert r.status_code == 200, r.text[:300]


def test_msgpack_duplicate_key_is_refused_naming_it(roomy):
    r = post(roomy, _dup_map(("bodies", {}), ("bodies", {}), ("batches", [])), B)
    assert r.status_code == 422
    assert any(d["loc"] == ["body", "bodies"] and d["type"] == "duplicate_key" for d in r.json()["detail"]), r.json()
    doc = msgpack.unpackb(_bin(), raw=False)
    lower = doc["batches"][1]["lower"]
    batch = {k: v for k, v in doc["batches"][1].items()}
    batch_bytes = _dup_map(*batch.items(), ("lower", lower))
    top = msgpack.packb({"bodies": doc["bodies"], "batches": [doc["batches"][0]]})
    # splice the hand-written batch in as batch 1: fixarray of 2 = 0x92
    i = top.index(msgpack.packb("batches")) + len(msgpack.packb("batches"))
    body = top[:i] + b"\x92" + top[i + 1 :] + batch_bytes
    r = post(roomy, body, B)
    assert r.status_code == 422, r.text[:300]
    assert any(d["loc"] == ["body", "batches", 1, "lower"] and d["type"] == "duplicate_key" for d in r.json()["detail"]), r.json()


# ----------------------------------------------------------------------------- long unknown keys


@pytest.mark.parametrize("content_type", [J, B])
def test_2mb_unknown_key_is_echoed_cut(roomy, content_type):
    doc = {"k" * 2_000_000: 1}
    body = json.dumps(doc).encode() if content_type == J else msgpack.packb(doc)
    r = post(roomy, body, content_type)
    assert r.status_code == 422
    assert len(r.content) < 4096, len(r.content)
    assert ["body", "k" * MAX_KEY_CHARS + "..."] in [d["loc"] for d in r.json()["detail"]]


# ----------------------------------------------------------------------------- one fault cap (item 4)

HOSTILE = {"bodies": {}, "batches": [{}] * 300_000}


@pytest.mark.parametrize("content_type", [B, J])
def test_300k_empty_batches_get_at_most_max_faults_quickly(roomy, content_type):
    body = msgpack.packb(HOSTILE) if content_type == B else json.dumps(HOSTILE).encode()
    t = time.perf_counter()
    r = post(roomy, body, content_type)
    elapsed = time.perf_counter() - t
    print(f"\n300k empty batches, {content_type}: {len(body)} B body -> {r.status_code}, {len(r.content)} B answer, {elapsed:.3f} s")
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert 0 < len(detail) <= MAX_FAULTS
    assert ["body", "batches", 0, "constitution_uid"] in [d["loc"] for d in detail]


@pytest.mark.parametrize(
    "doc",
    [
        {"bodies": {"q": [[]] * 100_000, "q_prev": [], "q_ref": []}, "batches": []},  # a million short rows
        {"bodies": {"q": [], "q_prev": [], "q_ref": []}, "batches": [], **{f"k{i}": 0 for i in range(100_000)}},
        {"bodies": {"q": [], "q_prev": [], "q_ref": []}, "batches": [{"constitution_uid": "x", "base_uid": "x", "body_ids": 1, "edges": 1, "lower": 1, "upper": 1, "strength": 1}] * 50_000},
        {"bodies": {"q": [], "q_prev": [], "q_ref": []}, "batches": [], "outputs": ["jacobian"] * 100_000},
    ],
    ids=["short_rows", "extra_keys", "bad_values", "bad_outputs"],
)
def test_every_flood_of_bad_items_is_capped_in_both_decoders(doc, monkeypatch):
    built = pydantic_error_counts(monkeypatch)
    for decode, body in ((lambda b: convert.decode(b, 10**9, 10**6), json.dumps(doc).encode()),
                         (lambda b: binary.decode(b, 10**6), msgpack.packb(doc))):
        with pytest.raises(InputError) as e:
            evaluate(**decode(body))  # a shape is the core's to name (short rows), as on the service's path
        assert 0 < len(e.value.faults) <= MAX_FAULTS, (body[:1], len(e.value.faults))
    # Not only the answer: pydantic itself listed a handful of errors, if it ran at all.
    assert all(n <= 2 * MAX_FAULTS for n in built), built


def pydantic_error_counts(monkeypatch) -> list[int]:
    """Records each time pydantic validates a request document (the decoders never do: the one validator,
    service/http/document.py, reads the plain document), and how many errors it built."""
    counts: list[int] = []
    for model in (EvaluateRequest, OpeningRequest):
        real = model.model_validate

        def counting(*args, real=real, **kwargs):
            try:
                return real(*args, **kwargs)
            except ValidationError as e:
                counts.append(e.error_count())
                raise

        monkeypatch.setattr(model, "model_validate", counting)
    return counts


def test_keys_are_named_from_the_parsed_document_up_to_the_cap():
    with pytest.raises(InputError) as e:
        convert.read(json.dumps(HOSTILE).encode())
    assert len(e.value.faults) == MAX_FAULTS and ("batches", 0, "constitution_uid") in [f.loc for f in e.value.faults]
    convert.read(json.dumps(_json()).encode())  # no fault
    # Braces and colons inside strings are not structure (no key repeats, none is unknown).
    kwargs = convert.read(b'{"bodies": {"q": [], "q_prev": [], "q_ref": []}, "batches": [], "id": "{\\"a\\": 1} }"}', opening=True)
    assert kwargs["id"] == '{"a": 1} }'


@pytest.mark.parametrize(
    ("stray", "loc"),
    [(b'"x": {"a": 1}', ["body", "x"]), (b'"outputs": [{"a": 1}]', ["body", "outputs", 0])],
    ids=["under_an_unknown_key", "under_a_known_key"],
)
def test_extra_keys_after_a_stray_object_are_capped(stray, loc, monkeypatch):
    """An object no request holds is named, and 100k unknown keys after it cost 20 faults (pydantic never runs)."""
    built = pydantic_error_counts(monkeypatch)
    extras = ", ".join(f'"k{i}": 0' for i in range(100_000)).encode()
    body = b"{" + stray + b', "bodies": {"q": [], "q_prev": [], "q_ref": [], ' + extras + b'}, "batches": []}'
    with pytest.raises(InputError) as e:
        convert.decode(body, 10**9, 10)
    assert 0 < len(e.value.faults) <= MAX_FAULTS and built == []
    assert tuple(loc[1:]) in [f.loc for f in e.value.faults]


@pytest.mark.parametrize(
    ("doc", "loc"),
    [
        ({"bodies": {}, "batches": [{}] * 3_000_000}, ["body", "batches", 0, "constitution_uid"]),  # 3 MB
        ({"bodies": [{}] * 3_000_000, "batches": []}, ["body", "bodies"]),  # not the batches: bounded all the same
        ({"bodies": {}, "batches": [], "outputs": ["energy"] * 100_000}, ["body", "outputs"]),
        ({"bodies": [[[[]] * 60] * 60], "batches": []}, ["body", "bodies"]),  # 3600 nested arrays in 4 KB
    ],
    ids=["3M_empty_batches", "3M_maps_as_bodies", "100k_outputs", "nested_arrays"],
)
def test_msgpack_floods_are_refused_before_they_are_built(roomy, doc, loc):
    """msgpack turns 1 byte into a 64-byte dict: batches are unpacked one at a time (up to the fault
    cap) and every other value holds at most MAX_CONTAINERS maps and arrays of MAX_ITEMS items."""
    body = msgpack.packb(doc)
    t = time.perf_counter()
    r = post(roomy, body, B)
    print(f"\n{len(body)} B msgpack flood -> {r.status_code} in {time.perf_counter() - t:.3f} s")
    assert r.status_code == 422
    assert loc in [d["loc"] for d in r.json()["detail"]], r.json()
    assert len(r.json()["detail"]) <= MAX_FAULTS
