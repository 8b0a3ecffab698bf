"""Session messages (schemas/session.py): frames <-> core arguments and answers. No numerics.

The opening message is decoded by the HTTP decoders themselves (`convert.decode` for JSON,
`binary.decode` for msgpack); later messages by `CLIENT_MESSAGE` (JSON) or the binary
transport's reader (msgpack). A reply is encoded in the encoding of the message it answers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import orjson
from pydantic import ValidationError

from jointlimits.schemas import binary as wire
from jointlimits.schemas import session as proto
from jointlimits.service.core import Evaluation, Fault, InputError
from jointlimits.service.core.errors import Loc
from jointlimits.service.core.assembled import check_layout
from jointlimits.service.core.validate import NOT_A_LIST, as_array, check_bodies, check_options, literal_msg, raise_if
from jointlimits.service.http import binary, convert
from jointlimits.service.http.errors import HttpError, from_validation

Frame = bytes | str


@dataclass
class Message:
    """One client message after the opening one; `options` holds only the evaluate options it gave."""

    kind: str
    id: int | str | None = None
    q: np.ndarray | None = None  # (B, 12)
    options: dict[str, Any] = field(default_factory=dict)
    batch: int = 0
    index: np.ndarray | None = None  # (K,) int64
    values: dict[str, np.ndarray] = field(default_factory=dict)  # update: (K,) per field given


NOT_OPEN = (
    "open a scene first: the first message of a session is the opening document (a POST /v1/evaluate body, "
    "with an optional id), not a message with a kind"
)


def decode_open(frame: Frame, max_joints: int) -> dict[str, Any]:
    """Keyword arguments of the core for the opening document, plus its `id` (under "id", None when absent);
    `InputError` (422) or `HttpError` (413)."""
    try:
        if isinstance(frame, str):
            kwargs = convert.decode(frame.encode(), max_joints, opening=True)
        else:
            kwargs = binary.decode(frame, max_joints, opening=True)
        # The options become the session's defaults: checked now, on both encodings (JSON's parser already did);
        # `q` is part of the document, checked as POST /v1/evaluate checks it (the scene is prepared at q_prev).
        raise_if(check_options(kwargs["outputs"], kwargs["hessian_mode"]) + check_layout(kwargs["layout"])
                 + check_bodies(kwargs["bodies"]))
        return kwargs
    except InputError as e:
        # A later kind of message sent first: one fault that says so, not the opening document's five.
        if any(f.loc == ("kind",) and f.type == "extra_forbidden" for f in e.faults):
            raise InputError([Fault(("kind",), NOT_OPEN, "session_not_open")]) from None
        raise


def decode(frame: Frame) -> Message:
    """A later message; `InputError` naming the key at fault."""
    return _decode_json(frame) if isinstance(frame, str) else _decode_binary(frame)


MESSAGE_ARRAYS = {"q": False, "index": True, **{k: False for k in proto.UPDATABLE}}
"""A message's numeric arrays (True: of integers): their shapes are the core's to name, on both encodings."""
NOT_A_MAP = ("Input should be an object", "dict_type")
MISSING = ("Field required", "missing")
BAD_KIND = (literal_msg(tuple(proto.KEYS)), "union_tag_invalid")


def _decode_json(frame: str) -> Message:
    doc = convert.load(frame)  # parsed once: pydantic checks the document, the faults are worded from it
    try:
        m = proto.CLIENT_MESSAGE.validate_python(doc)
    except ValidationError as e:
        # The discriminated union puts the kind in front of each loc: ("evaluate", "q", 3) -> ("q", 3).
        tag = doc.get("kind") if isinstance(doc, dict) and isinstance(doc.get("kind"), str) else None
        faults = [_untagged(convert.json_words(f), tag) for f in from_validation(e).faults]
        if not any(_in_array(f) for f in faults):
            raise InputError(faults) from None
        return _arrays_in_core_words(doc, tag, faults)
    out = Message(kind=m.kind, id=m.id)
    if m.kind in (proto.EVALUATE, proto.COMMIT):
        out.q = np.asarray(m.q, dtype=np.float64).reshape(len(m.q), 12)
    if m.kind == proto.EVALUATE:
        out.options = {k: getattr(m, k) for k in ("outputs", "hessian_mode", "active_only") if getattr(m, k) is not None}
    if m.kind == proto.UPDATE:
        out.batch, out.index = m.batch, np.asarray(m.index, dtype=np.int64)
        out.values = {k: np.asarray(getattr(m, k), dtype=np.float64) for k in proto.UPDATABLE if getattr(m, k) is not None}
    return out


def _arrays_in_core_words(doc: dict[str, Any], kind: str | None, faults: list[Fault]) -> Message:
    """A JSON message whose only faults are inside its arrays (a row of 11 numbers): its arrays as they are,
    whatever their shape, for the core to name as it names msgpack's; a non-number is named here, in the
    same words (`validate.as_array`). Any other fault is raised with them."""
    others = [f for f in faults if not _in_array(f)]
    arrays: dict[str, np.ndarray] = {}
    found: list[Fault] = []
    for name, integer in MESSAGE_ARRAYS.items():
        if name in doc and name in proto.KEYS.get(kind or "", {}):  # a null too: named at the array, as msgpack's nil
            a, bad = as_array(doc[name], (name,), integer)
            found += bad
            if a is not None:
                arrays[name] = a
    if others or found or kind is None:
        raise InputError(others + found or faults)
    out = Message(kind=kind, id=doc.get("id"), q=arrays.get("q"))
    if kind == proto.EVALUATE:
        out.options = {k: doc[k] for k in ("outputs", "hessian_mode", "active_only") if k in doc}
    if kind == proto.UPDATE:
        out.batch, out.index = doc["batch"], arrays["index"]
        out.values = {k: arrays[k] for k in proto.UPDATABLE if k in arrays}
    return out


def _in_array(f: Fault) -> bool:
    """A fault inside one of the message's arrays (not its absence, "Field required", nor another kind's array,
    "Extra inputs are not permitted": pydantic's to name)."""
    return bool(f.loc[:1]) and f.loc[0] in MESSAGE_ARRAYS and f.type not in ("missing", "extra_forbidden")


def _untagged(f: Fault, tag: str | None) -> Fault:
    if f.type == "union_tag_invalid":
        return Fault(("kind",), *BAD_KIND)
    if f.type == "union_tag_not_found":
        return Fault(("kind",), *MISSING)
    if f.type == "dict_type" and f.loc == ():
        return Fault((), *NOT_A_MAP)
    if f.type == "list_type":  # pydantic's JSON mode says "a valid array"; msgpack and requests "a valid list"
        f = Fault(f.loc, *NOT_A_LIST)
    return Fault(f.loc[1:], f.msg, f.type) if tag is not None and f.loc[:1] == (tag,) else f


def _decode_binary(frame: bytes) -> Message:
    try:
        doc = wire.loads(frame)
    except ValueError as e:
        raise InputError([Fault((), str(e).replace("body is", "message is"), "msgpack_invalid")]) from None
    r = binary._Reader()  # the binary transport's own reader: same checks, same messages
    # The words of JSON's parser for a message that is not a map, has no kind, or an unknown one.
    if not isinstance(doc, dict):
        raise InputError([Fault((), *NOT_A_MAP)])
    kind = doc.get("kind")
    if kind is None or not isinstance(kind, str) or kind not in proto.KEYS:
        raise InputError([Fault(("kind",), *(MISSING if kind is None else BAD_KIND))])
    fields = r.fields(doc, (), proto.KEYS[kind])
    out = Message(kind=kind, id=binary.message_id(r, fields.get("id")))
    if "q" in fields:
        out.q = _array(r, fields["q"], ("q",), wire.FLOAT64, 2)
    if kind == proto.EVALUATE:
        given = {k: fields[k] for k in ("outputs", "hessian_mode", "active_only") if k in fields}
        parsed = dict(zip(("outputs", "hessian_mode", "active_only"), binary._options(r, given)))
        out.options = {k: parsed[k] for k in given}
    if kind == proto.UPDATE:
        out.batch = r.int64(fields.get("batch", 0), ("batch",))
        out.index = _array(r, fields.get("index"), ("index",), wire.INT64, 1)
        out.values = {k: _array(r, fields[k], (k,), wire.FLOAT64, 1) for k in proto.UPDATABLE if k in fields}
    if r.faults:
        raise InputError(r.faults)
    return out


def _array(r: binary._Reader, obj: Any, loc: Loc, dtype: str, ndim: int) -> np.ndarray:
    """The binary reader's array, but a number or a string where an array belongs is named as in JSON (the
    reader says "must be an array map"); its nil and its 0-d array map are already."""
    empty = np.zeros((0,) * ndim, np.int64 if dtype == wire.INT64 else np.float64)
    if isinstance(obj, (bool, int, float, str)):
        r.fault(loc, *NOT_A_LIST)
        return empty
    return r.array(obj, loc, dtype, ndim, empty)


def message_id(frame: Frame) -> int | str | None:
    """The `id` of a message that could not be decoded, if it has a readable one (its fault reply repeats it)."""
    try:
        doc = orjson.loads(frame) if isinstance(frame, str) else wire.loads(frame)
    except (orjson.JSONDecodeError, ValueError):
        return None
    v = doc.get("id") if isinstance(doc, dict) else None
    ok = (isinstance(v, int) and not isinstance(v, bool) and -(2**63) <= v < 2**63) or (isinstance(v, str) and len(v) <= 128)
    return v if ok else None


# ------------------------------------------------------------------ replies


def encode(doc: dict[str, Any], binary_frame: bool) -> Frame:
    """A reply (not an evaluation): arrays as array maps (msgpack) or lists of shortest round-trip floats (JSON)."""
    if binary_frame:
        return wire.dumps(_walk(doc, lambda a: wire.pack_array(a, wire.INT64 if a.dtype.kind == "i" else wire.FLOAT64)))
    return orjson.dumps(_walk(doc, np.ascontiguousarray), option=orjson.OPT_SERIALIZE_NUMPY).decode()


def _walk(obj: Any, array: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return array(obj)
    if isinstance(obj, dict):
        return {k: _walk(v, array) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_walk(v, array) for v in obj]
    return obj


def encode_evaluation(ev: Evaluation, binary_frame: bool, id: int | str | None) -> Frame:
    """`POST /v1/evaluate`'s answer document, bytes from its own encoder, with `kind` (and `id`) added in front."""
    head = {"kind": proto.EVALUATION} if id is None else {"kind": proto.EVALUATION, "id": id}
    if binary_frame:
        body = binary.encode(ev)
        # A msgpack map is a header (fixmap 0x80 | count, for < 16 keys) then its key/value pairs, in order.
        assert 0x80 <= body[0] < 0x90 - len(head), "the answer document is a small map"
        pairs = b"".join(wire.dumps({k: v})[1:] for k, v in head.items())
        return bytes([body[0] + len(head)]) + pairs + body[1:]
    body = convert.encode(ev)
    return (orjson.dumps(head)[:-1] + b"," + body[1:]).decode()


def at_message_q(e: InputError) -> InputError:
    """The core names a bad `q` as in a request (`("bodies", "q", i)`); in a session message it is `("q", i)`."""
    return InputError([Fault(f.loc[1:], f.msg, f.type) if f.loc[:2] == ("bodies", "q") else f for f in e.faults])


def error(exc: InputError | HttpError, id: int | str | None) -> dict[str, Any]:
    """A fault reply: HTTP's 4xx body (`detail`, every `loc` starting with "body") with its `status`."""
    if isinstance(exc, HttpError):  # these faults carry their full loc already
        status, detail = exc.status, [{"loc": list(f.loc), "msg": f.msg, "type": f.type} for f in exc.faults]
    else:
        status, detail = 422, [{"loc": ["body", *f.loc], "msg": f.msg, "type": f.type} for f in exc.faults]
    doc: dict[str, Any] = {"kind": proto.ERROR, "status": status, "detail": detail}
    if id is not None:
        doc["id"] = id
    return doc
