"""The one validator (`service/http/document.py`) and the wire's pydantic models (`schemas/evaluate.py`) agree.

The models no longer validate requests, but they still describe the wire: `/openapi.json` and the SDK's
`EvaluateRequest` are made from them. Over generated documents (valid ones, and ones with one mutation: a key
missing, unknown or repeated, a value of the wrong type, a null, a literal that is not one), the service refuses
exactly what `EvaluateRequest.model_validate_json` refuses, at the same locations. The service splits that work
between the validator (keys, structure, types) and the core (shapes, and what needs arithmetic), so "the service
refuses" is the validator or, after it, the core's checks. The generated scenes are arithmetically sound (unit
frames, ranges lower < upper, body ids in range), so a fault of the core's after a mutation is the mutation's.

Where they differ, the service is right and the test says why (`_pydantic_is_laxer`, `_a_shape`). A session's
later messages are held to `schemas/session.py`'s models the same way.
"""

from __future__ import annotations

import copy
import json
from typing import Any

import hypothesis.strategies as st
from hypothesis import HealthCheck, given, settings

from pydantic import ValidationError

from jointlimits.schemas import EvaluateRequest
from jointlimits.schemas import session as proto
from jointlimits.service import core
from jointlimits.service.http import convert
from jointlimits.service.http import sessions as session_codec

ROW = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]  # a body at the origin, unit frame


@st.composite
def documents(draw: st.DrawFn) -> dict[str, Any]:
    """A valid request: 2 bodies, 0-2 batches of 0-2 joints, each optional field given or not."""
    q = [[x + i for x in ROW[:3]] + ROW[3:] for i in range(2)]
    doc: dict[str, Any] = {"bodies": {"q": q, "q_prev": copy.deepcopy(q), "q_ref": copy.deepcopy(q)}, "batches": []}
    for _ in range(draw(st.integers(0, 2))):
        n = draw(st.integers(0, 2))
        uid = draw(st.sampled_from([669, 670]))
        b: dict[str, Any] = {"constitution_uid": uid, "body_ids": [[0, 1]] * n, "lower": [-0.5] * n, "upper": [0.5] * n}
        if draw(st.booleans()):
            b["edges"] = [[[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]] * n
        else:
            b["local_edges"] = [[[[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], [[-1.0, 0.0, 0.0], [-1.0, 0.0, 1.0]]]] * n
        for k in ("strength", "offset") + (("prev_coordinate",) if uid == 670 else ()):
            if draw(st.booleans()):
                b[k] = [1.0] * n
        if draw(st.booleans()):
            b["origin"] = draw(st.sampled_from(["q_ref", "absolute"]))
        doc["batches"].append(b)
    for k, values in {"outputs": [["energy"], ["energy", "gradient", "hessian"]], "hessian_mode": ["exact", "psd"],
                      "active_only": [False, True], "layout": ["joints", "bodies"]}.items():
        if draw(st.booleans()):
            doc[k] = draw(st.sampled_from(values))
    return doc


def _paths(node: Any, loc: tuple = ()) -> list[tuple]:
    """Every location in the document: each key's value and each list item, at any depth."""
    out = [loc] if loc else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*loc, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*loc, i))
    return out


def _objects(node: Any, loc: tuple = ()) -> list[tuple]:
    """The locations of the document's objects (the document, `bodies`, each batch)."""
    if isinstance(node, dict):
        return [loc] + [p for k, v in node.items() for p in _objects(v, (*loc, k))]
    if isinstance(node, list):
        return [p for i, v in enumerate(node) for p in _objects(v, (*loc, i))]
    return []


def _at(doc: Any, loc: tuple) -> Any:
    for k in loc:
        doc = doc[k]
    return doc


@st.composite
def mutated(draw: st.DrawFn) -> tuple[str, str, tuple]:
    """A document's JSON text after one mutation, its kind and where it was made."""
    doc = draw(documents())
    kind = draw(st.sampled_from(["none", "missing", "unknown", "repeated", "type", "null", "literal"]))
    if kind == "none":
        return json.dumps(doc), kind, ()
    if kind in ("missing", "unknown", "repeated"):
        loc = draw(st.sampled_from(_objects(doc)))
        obj = _at(doc, loc)
        if kind == "missing":
            if not obj:
                return json.dumps(doc), "none", ()
            key = draw(st.sampled_from(sorted(obj)))
            del obj[key]
            return json.dumps(doc), kind, (*loc, key)
        if kind == "unknown":
            obj[draw(st.sampled_from(["zz", "Lower", "bodies", "q", "kind"]))] = 1
            return json.dumps(doc), kind, loc
        # repeated: written by hand, a `dict` cannot hold it
        if not obj:
            return json.dumps(doc), "none", ()
        key = draw(st.sampled_from(sorted(obj)))
        marker = "__REPEATED__"
        obj[marker] = None
        text = json.dumps(doc).replace(f'"{marker}": null', f'{json.dumps(key)}: {json.dumps(obj[key])}')
        return text, kind, (*loc, key)
    if kind == "literal":
        choices = [p for p in _paths(doc) if p[-1:] in (("hessian_mode",), ("layout",), ("origin",))
                   or (len(p) == 2 and p[0] == "outputs")]
        if not choices:
            return json.dumps(doc), "none", ()
        loc = draw(st.sampled_from(choices))
    else:
        loc = draw(st.sampled_from(_paths(doc)))
    parent = _at(doc, loc[:-1])
    if kind == "null":
        parent[loc[-1]] = None
    elif kind == "literal":
        parent[loc[-1]] = draw(st.sampled_from(["Energy", "", "nope"]))
    else:
        old = parent[loc[-1]]
        new = draw(st.sampled_from(["x", {}, [], 1.5, True, 7, [1.0], {"a": 1}]))
        if type(new) is type(old) and new == old:
            return json.dumps(doc), "none", ()
        parent[loc[-1]] = new
    return json.dumps(doc), kind, loc


def pydantic_faults(text: str) -> dict[tuple, tuple[str, str]]:
    try:
        EvaluateRequest.model_validate_json(text)
    except ValidationError as e:
        return {tuple(err["loc"]): (err["msg"], err["type"]) for err in e.errors()}
    return {}


def service_faults(text: str) -> tuple[dict[tuple, tuple[str, str]], str]:
    """The service's faults: the validator's, else (the structure passed) the core's; and whose they are."""
    try:
        kwargs = convert.read(text.encode())
    except core.InputError as e:
        return {f.loc: (f.msg, f.type) for f in e.faults}, "validator"
    try:
        core.evaluate(**kwargs)
    except core.InputError as e:
        return {f.loc: (f.msg, f.type) for f in e.faults}, "core"
    return {}, ""


SHAPES = {"too_short", "too_long"}
"""pydantic's faults of a row's length."""


def _a_shape(pyd: dict, service: dict, who: str) -> bool:
    """A shape: rows of the wrong length, or lists of numbers nested one level too deep or too shallow, make an
    array of the wrong shape, as a msgpack array map or a NumPy array of that shape would be; the core names it
    at the array (a prefix of pydantic's loc). Rows that make no array (of different lengths): the validator
    names the first one of another length than the wire's, where pydantic does."""
    if who == "validator":
        return all(t in SHAPES for _, t in pyd.values()) and set(pyd) == set(service)
    return who == "core" and all(any(p[: len(s)] == s for s in service) for p in pyd) and (
        all(t in SHAPES for _, t in pyd.values()) or all("shape" in m for m, _ in service.values())
    )


def _pydantic_is_laxer(kind: str, service: dict, who: str) -> bool:
    """Documents the models accept and the service refuses, rightly: a repeated key (jiter keeps the last; the
    wire forbids it), and the core's checks: a null (NaN) where a number belongs, neither or both of `edges` and
    `local_edges` (the models cannot say "exactly one"), ids and ranges the arithmetic refuses."""
    if kind == "repeated":
        return who == "validator" and all(t == "duplicate_key" for _, t in service.values())
    return who in ("core", "")


def _same(pyd: dict, service: dict) -> bool:
    """The same locations and types; the same words, but for "a valid list" (the errors table's, on every path),
    which pydantic's JSON mode now words "a valid array"."""
    words = {loc: (m.replace("valid array", "valid list"), t) for loc, (m, t) in pyd.items()}
    return words == service


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutated())
def test_the_validator_refuses_what_the_models_refuse_at_the_same_locations(case: tuple[str, str, tuple]) -> None:
    text, kind, where = case
    pyd = pydantic_faults(text)
    service, who = service_faults(text)
    if kind == "none":
        assert pyd == {} and service == {}, text
    elif not pyd:
        assert _pydantic_is_laxer(kind, service, who), (kind, where, service, who)
    else:
        assert _a_shape(pyd, service, who) or (who == "validator" and _same(pyd, service)), (kind, where, pyd, service, who)


# ------------------------------------------------------------------ a session's later messages (schemas/session.py)

WIRE_NDIM = {"q": 2, "index": 1, "lower": 1, "upper": 1, "strength": 1, "offset": 1}


@st.composite
def messages(draw: st.DrawFn) -> tuple[str, str]:
    """A message after the opening one (its `kind` kept: the service names a bad kind at `kind`, pydantic's
    tagged union at the document), valid or with one mutation."""
    kind = draw(st.sampled_from([proto.EVALUATE, proto.COMMIT, proto.UPDATE, proto.CLOSE]))
    doc: dict[str, Any] = {"kind": kind}
    if draw(st.booleans()):
        doc["id"] = draw(st.sampled_from([7, "a"]))
    if kind in (proto.EVALUATE, proto.COMMIT):
        doc["q"] = [list(ROW)] * draw(st.integers(0, 2))
    if kind == proto.EVALUATE:
        for k, v in {"outputs": ["gradient"], "hessian_mode": "psd", "active_only": True}.items():
            if draw(st.booleans()):
                doc[k] = v
    if kind == proto.UPDATE:
        doc |= {"batch": 0, "index": [0]} | {k: [0.5] for k in proto.UPDATABLE if draw(st.booleans())}
    mutation = draw(st.sampled_from(["none", "missing", "unknown", "type", "null", "repeated"]))
    keys = [k for k in doc if k != "kind"]
    if mutation == "missing" and keys:
        del doc[draw(st.sampled_from(keys))]
    elif mutation == "unknown":
        doc[draw(st.sampled_from(["zz", "bodies", "batches", "prev_coordinate"]))] = 1
    elif mutation in ("type", "null") and _paths(doc)[1:]:
        loc = draw(st.sampled_from([p for p in _paths(doc) if p != ("kind",)]))
        new = None if mutation == "null" else draw(st.sampled_from(["x", {}, [], 1.5, True, 7, [1.0]]))
        _at(doc, loc[:-1])[loc[-1]] = new
    elif mutation == "repeated" and keys:
        key = draw(st.sampled_from(keys))
        return json.dumps(doc)[:-1] + f", {json.dumps(key)}: {json.dumps(doc[key])}}}", mutation
    return json.dumps(doc), mutation


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages())
def test_a_sessions_messages_are_refused_as_the_models_refuse_them(case: tuple[str, str]) -> None:
    text, mutation = case
    kind = json.loads(text)["kind"]
    try:
        proto.CLIENT_MESSAGE.validate_json(text)
        pyd: dict[tuple, tuple[str, str]] = {}
    except ValidationError as e:  # the tagged union puts the kind in front of each loc
        pyd = {tuple(err["loc"])[1:]: (err["msg"], err["type"]) for err in e.errors()}
    try:
        message = session_codec.decode(text, 10**9)
    except core.InputError as e:
        service = {f.loc: (f.msg, f.type) for f in e.faults}
        if mutation == "repeated":
            assert all(t == "duplicate_key" for _, t in service.values()), service
        else:
            assert _same(pyd, service) or _a_shape(pyd, service, "validator"), (text, pyd, service)
        return
    assert mutation == "repeated" or not pyd or all(
        # an array of another shape than the wire's: the session's core names it, as for msgpack's arrays
        loc[0] in WIRE_NDIM and (a := message.q if loc[0] == "q" else message.index if loc[0] == "index"
                                 else message.values[loc[0]]) is not None
        and (a.ndim != WIRE_NDIM[loc[0]] or (loc[0] == "q" and a.shape[1:] != (12,)))
        for loc in pyd
    ), (text, pyd, kind)
