"""Issue 28: a JSON body is parsed once. The faults of its arrays are worded from that one document,
in the core's words, never by reading the body again."""

from __future__ import annotations

import json

import pytest

from jointlimits.service.core import InputError, evaluate
from jointlimits.service.http import convert
from tests.http.test_errors_http import _json


@pytest.fixture
def parses(monkeypatch) -> list[bytes]:
    """The bodies the JSON decoder parsed, one entry per parse."""
    seen: list[bytes] = []
    real = convert.from_json

    def counting(body, *a, **kw):
        seen.append(body)
        return real(body, *a, **kw)

    monkeypatch.setattr(convert, "from_json", counting)
    return seen


def _faults(doc: dict) -> list[tuple]:
    with pytest.raises(InputError) as e:  # a shape is the core's to name, as on the service's path
        evaluate(**convert.decode(json.dumps(doc).encode(), 10**9, 10**6))
    return [(f.loc, f.msg, f.type) for f in e.value.faults]


def test_an_array_fault_is_worded_from_the_one_parse(parses):
    doc = _json()
    doc["bodies"]["q"] = [row[:11] for row in doc["bodies"]["q"]]  # rows of 11 numbers: the core's words, not pydantic's
    faults = _faults(doc)
    assert len(parses) == 1
    assert faults and faults[0][0] == ("bodies", "q") and "12 numbers, got shape" in faults[0][1], faults
    doc = _json()
    doc["batches"][0]["lower"][1] = "x"  # not a number: named at the element
    assert _faults(doc) == [(("batches", 0, "lower", 1), "Input should be a valid number", "float_type")]
    assert len(parses) == 2


def test_a_clean_body_is_parsed_once(parses):
    kwargs = convert.decode(json.dumps(_json()).encode(), 10**9, 10**6)
    assert len(parses) == 1 and kwargs["batches"]


def test_a_session_message_is_parsed_once(parses):
    """A later message of a session: its faults are worded from its one parse (issue 28, step 4)."""
    from jointlimits.service.http import sessions as session_codec

    q = [[0.0] * 11, [0.0] * 11]  # rows of 11: the core names the shape later, as for msgpack
    message = session_codec.decode(json.dumps({"kind": "evaluate", "id": 7, "q": q}), 10**9)
    assert message.q.shape == (2, 11) and message.id == 7 and len(parses) == 1
    with pytest.raises(InputError) as e:
        session_codec.decode(json.dumps({"kind": "evaluate", "q": [[0.0, "x"]]}), 10**9)
    assert [(f.loc, f.type) for f in e.value.faults] == [(("q", 0, 1), "float_type")] and len(parses) == 2
    with pytest.raises(InputError) as e:
        session_codec.decode("[1]", 10**9)
    assert [(f.loc, f.msg, f.type) for f in e.value.faults] == [((), "Input should be an object", "dict_type")]
    assert len(parses) == 3


@pytest.mark.parametrize("active_only", [False, True])
def test_a_boolean_among_numbers_is_not_a_number(active_only):
    """NumPy would read `true` among numbers as 1: the arrays are read item by item when the body holds one."""
    doc = _json()
    doc["active_only"] = active_only
    assert convert.decode(json.dumps(doc).encode(), 10**9, 10**6)["active_only"] is active_only
    doc["batches"][0]["lower"][1] = True
    assert _faults(doc) == [(("batches", 0, "lower", 1), "Input should be a valid number", "float_type")]
    doc = _json()
    doc["batches"][1]["body_ids"][0][1] = False
    assert _faults(doc) == [(("batches", 1, "body_ids", 0, 1), "Input should be a valid integer", "int_type")]


def test_the_request_holds_its_arrays_once_built(parses):
    kwargs = convert.read(json.dumps(_json()).encode())
    assert kwargs["bodies"].q.dtype == "float64" and kwargs["batches"][0].body_ids.dtype == "int64" and len(parses) == 1
