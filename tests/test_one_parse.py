"""Issue 28: a JSON body is parsed once. The faults of its arrays are worded from that one document,
in the core's words, never by reading the body again."""

from __future__ import annotations

import json

import pytest

from jointlimits.service.core import InputError
from jointlimits.service.http import convert
from tests.test_errors_http import _json


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
    with pytest.raises(InputError) as e:
        convert.decode(json.dumps(doc).encode(), 10**6)
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
    kwargs = convert.decode(json.dumps(_json()).encode(), 10**6)
    assert len(parses) == 1 and kwargs["batches"]
