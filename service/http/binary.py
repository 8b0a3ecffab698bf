"""The binary encoding (schemas/binary.py): msgpack bytes <-> core arrays, no Python lists of numbers.

Numeric payloads bypass pydantic: each array is one `np.frombuffer` view. Structure
faults get the same `loc` a JSON request would get (`("batches", 1, "lower")`);
per-row faults (non-finite, ranges) come from the core, as for JSON.
"""

from __future__ import annotations

import io
from typing import Any

import msgpack
import numpy as np

from jointlimits.schemas import OUTPUTS
from jointlimits.schemas import binary as wire
from jointlimits.schemas import evaluate as models
from jointlimits.service.core import Bodies, Evaluation, Fault, InputError, Joints
from jointlimits.service.core.errors import MAX_FAULTS, Loc
from jointlimits.service.core.validate import DUPLICATE_KEY_MSG, HESSIAN_MODES, NOT_A_LIST, ORIGINS, literal_msg
from jointlimits.service.http import limits
from jointlimits.service.http.errors import HttpError
from jointlimits.service.http.convert import base_uid_of, strength_of

MEDIA_TYPE = wire.MEDIA_TYPE

# Each map's keys (True: required), as the wire models (schemas/evaluate.py) define them.
_REQUEST_KEYS, _BODY_KEYS, _BATCH_KEYS = (
    {k: f.is_required() for k, f in model.model_fields.items()} for model in (models.EvaluateRequest, models.Bodies, models.JointBatch)
)
_OPENING_KEYS = {**_REQUEST_KEYS, "id": False}  # a session's opening document may carry an `id`
_JOINT_ARRAYS = {"body_ids": (wire.INT64, 2), "edges": (wire.FLOAT64, 3), "local_edges": (wire.FLOAT64, 4)} | {
    k: (wire.FLOAT64, 1) for k in ("lower", "upper", "strength", "offset", "prev_coordinate")
}
_INT64_RANGE = range(-(2**63), 2**63)
_EMPTY = {"f": np.zeros((0, 12)), "i": np.zeros((0, 2), dtype=np.int64)}
_MAP_HEADERS = frozenset(range(0x80, 0x90)) | {0xDE, 0xDF}  # fixmap, map 16, map 32
_ARRAY_HEADERS = frozenset(range(0x90, 0xA0)) | {0xDC, 0xDD}


class _Map(dict):
    """A msgpack map that repeated a key (last value kept, as `dict` does); `repeated` lists the keys."""

    repeated: list[Any]


def _pairs(pairs: list[tuple[Any, Any]]) -> dict[str, Any]:
    """`object_pairs_hook` of the unpacker: a plain dict, or a `_Map` that remembers its repeated keys."""
    d = dict(pairs)
    if len(d) == len(pairs):
        return d
    m, seen = _Map(d), set()
    m.repeated = [k for k, _ in pairs if k in seen or seen.add(k)]  # type: ignore[func-returns-value]
    return m


class _Reader:
    """Walks the document's few structural levels (never its joints), collecting faults.

    It stops at the `MAX_FAULTS`-th fault (raising them): a body of 300k bad batches costs
    its unpacking and 20 faults' worth of walking, not 300k.
    """

    def __init__(self) -> None:
        self.faults: list[Fault] = []

    def fault(self, loc: Loc, msg: str, type: str = "value_error") -> None:
        self.faults.append(Fault(loc, msg, type))
        if len(self.faults) >= MAX_FAULTS:
            raise InputError(self.faults)

    def keys(self, obj: dict, loc: Loc) -> None:
        """Faults for the keys `dict` hides: repeated ones and non-string ones (a msgpack `bin` key)."""
        for k in getattr(obj, "repeated", ()):
            self.fault((*loc, k), DUPLICATE_KEY_MSG, "duplicate_key")
        for k in obj:
            if not isinstance(k, str):
                self.fault((*loc, k), f"Map keys must be msgpack str, got {type(k).__name__}", "key_type")

    def fields(self, obj: Any, loc: Loc, keys: dict[str, bool]) -> dict[str, Any]:
        if not isinstance(obj, dict):
            self.fault(loc, "Input should be a map (a msgpack map, as a JSON object)", "model_type")
            return {}
        self.keys(obj, loc)
        for k in obj:
            if not isinstance(k, str):
                continue  # named above
            if k not in keys:
                self.fault((*loc, k), "Extra inputs are not permitted", "extra_forbidden")
        for k, required in keys.items():
            if required and k not in obj:
                self.fault((*loc, k), "Field required", "missing")
        return {k: v for k, v in obj.items() if k in keys}

    def array(self, obj: Any, loc: Loc, dtype: str, ndim: int, empty: np.ndarray) -> np.ndarray:
        if obj is None or isinstance(obj, (bool, int, float, str)):  # nil or a scalar: named as in JSON
            self.fault(loc, *NOT_A_LIST)
            return empty
        if isinstance(obj, dict):
            n = len(self.faults)
            self.keys(obj, loc)
            if len(self.faults) > n:
                return empty
        try:
            a = wire.unpack_array(obj, dtype, None)  # of any shape: the core names a wrong one, as for JSON
        except ValueError as e:
            self.fault(loc, str(e))
            return empty
        if a.ndim == 0:  # a number where an array belongs
            self.fault(loc, *NOT_A_LIST)
            return empty
        return a

    def int64(self, obj: Any, loc: Loc) -> int:
        if isinstance(obj, bool) or not isinstance(obj, int) or obj not in _INT64_RANGE:
            self.fault(loc, "Input should be a valid integer in int64 range", "int_type")
            return 0
        return obj


MAX_CONTAINERS = 64
"""Maps and arrays one top-level value or one batch may hold (a batch has 11, `bodies` 7)."""
MAX_ITEMS = 4096
"""Items of one msgpack map or array (numbers travel as `bin`: a request's longest list is its `outputs`)."""


class _TooMany(Exception):
    pass


class _Budget:
    """The unpacker's hooks: build each map and array, and count them against `MAX_CONTAINERS`."""

    def __init__(self) -> None:
        self.left = MAX_CONTAINERS

    def pairs(self, pairs: list[tuple[Any, Any]]) -> dict[str, Any]:
        self.tick()
        return _pairs(pairs)

    def items(self, items: list[Any]) -> list[Any]:
        self.tick()
        return items

    def tick(self) -> None:
        self.left -= 1
        if self.left < 0:
            raise _TooMany


class _Checked(list):
    """The request's batches, each already checked (`_batch`) as it was unpacked."""


def _unpack(body: bytes, r: _Reader, max_batches: int | None = None) -> Any:
    """The document, its top-level `batches` unpacked and checked one batch at a time.

    A body of 30M empty maps as batches would otherwise become 30M dicts (~2 GB) before the
    first check; this way the reader's fault cap stops the unpacking after a few batches.
    Every other value is unpacked whole, but holds at most `MAX_CONTAINERS` maps and arrays
    of at most `MAX_ITEMS` items each: no value costs more than a bounded number of objects.
    """
    budget = _Budget()
    # Read in 8 MiB steps from the body itself: `feed(body)` would hold a whole second copy.
    u = msgpack.Unpacker(
        io.BytesIO(body), read_size=2**23, max_buffer_size=max(len(body), 2**23),
        raw=False, strict_map_key=True, object_pairs_hook=budget.pairs, list_hook=budget.items,
        max_map_len=MAX_ITEMS, max_array_len=MAX_ITEMS,
    )  # fmt: skip

    def value(loc: Loc) -> Any:
        budget.left = MAX_CONTAINERS
        try:
            return u.unpack()
        except _TooMany:
            msg = f"holds more than {MAX_CONTAINERS} maps and arrays: not the structure of a request"
            raise InputError([*r.faults, Fault(loc, msg, "structure")]) from None
        except ValueError as e:
            if "exceeds max_" not in str(e):
                raise
            msg = f"holds a map or array of {str(e).split()[0]} items; a request's have at most {MAX_ITEMS}"
            raise InputError([*r.faults, Fault(loc, msg, "structure")]) from None

    try:
        if not body or body[0] not in _MAP_HEADERS:
            u.skip()  # a valid document that is not a map (walked, never built), or garbage
            doc: Any = None
        else:
            doc = {}
            repeated = []
            n = u.read_map_header()
            if n > MAX_ITEMS:
                raise ValueError(f"{n} exceeds max_map_len({MAX_ITEMS})")
            for _ in range(n):
                k = value(())
                if k in doc:
                    repeated.append(k)
                if k == "batches" and u.tell() < len(body) and body[u.tell()] in _ARRAY_HEADERS:
                    n_batches = u.read_array_header()
                    if max_batches is not None:  # a 413 before any batch is read: each costs Python work
                        limits.check_batches(n_batches, max_batches)
                    doc[k] = _Checked(_batch(r, b, value(("batches", b))) for b in range(n_batches))
                else:
                    doc[k] = value((k,))
            if repeated:
                doc = _Map(doc)
                doc.repeated = repeated
        if u.tell() != len(body):
            raise ValueError(f"{len(body) - u.tell()} bytes after the document")
    except (InputError, HttpError):
        raise  # the fault cap, reached inside the batches; too many batches
    except Exception as e:  # msgpack raises several unrelated types for malformed input
        raise InputError([Fault((), f"body is not a valid msgpack document ({type(e).__name__}: {e})", "msgpack_invalid")]) from None
    return doc


def decode(body: bytes, max_joints: int, max_batches: int | None = None, opening: bool = False) -> dict[str, Any]:
    """Keyword arguments of `jointlimits.service.core.evaluate` for a msgpack body; `InputError` / 413 `HttpError`.

    More batches than `max_batches` is a 413 before any batch is read (each costs Python work here).
    `opening`: a session's opening document, whose optional `id` is returned too, under "id".
    """
    r = _Reader()
    doc = _unpack(body, r, max_batches)
    top = r.fields(doc, (), _OPENING_KEYS if opening else _REQUEST_KEYS)
    opening_id = message_id(r, top.get("id")) if opening else None
    # A missing or malformed `bodies` is one fault, not four.
    raw_bodies = r.fields(top["bodies"], ("bodies",), _BODY_KEYS) if "bodies" in top else {}
    f = {
        k: r.array(raw_bodies[k], ("bodies", k), wire.FLOAT64, 2, _EMPTY["f"]) if k in raw_bodies else _EMPTY["f"]
        for k in _BODY_KEYS
    }
    batches = top.get("batches", [])
    if not isinstance(batches, _Checked):
        if batches != []:
            r.fault(("batches",), "Input should be a valid list", "list_type")
        batches = []
    outputs, hessian_mode, active_only = _options(r, top)
    layout = _layout(r, top)
    if r.faults:
        raise InputError(r.faults)
    limits.check_joints(sum(j.body_ids.shape[0] for j in batches), max_joints)
    return ({"id": opening_id} if opening else {}) | dict(
        bodies=Bodies(q=f["q"], q_prev=f["q_prev"], q_ref=f["q_ref"]),
        batches=batches,
        outputs=outputs,
        hessian_mode=hessian_mode,
        active_only=active_only,
        layout=layout,
    )


def message_id(r: _Reader, v: Any) -> int | str | None:
    """A session message's `id`: an int64 or a string of at most 128 characters (else a fault)."""
    if v is None or (isinstance(v, str) and len(v) <= 128):
        return v
    return r.int64(v, ("id",))


def _batch(r: _Reader, b: int, raw: Any) -> Joints:
    loc = ("batches", b)
    fields = r.fields(raw, loc, _BATCH_KEYS)
    arrays = {
        k: r.array(fields.get(k), (*loc, k), dtype, ndim, np.zeros((0,) * ndim))
        for k, (dtype, ndim) in _JOINT_ARRAYS.items()
        if k in fields
    }
    uid = r.int64(fields.get("constitution_uid", 0), (*loc, "constitution_uid"))
    ids = arrays.get("body_ids", _EMPTY["i"])
    return Joints(
        constitution_uid=uid,
        base_uid=r.int64(fields["base_uid"], (*loc, "base_uid")) if "base_uid" in fields else base_uid_of(uid),
        body_ids=ids,
        edges=arrays.get("edges"),
        local_edges=arrays.get("local_edges"),
        origin=_literal(r, fields.get("origin", "q_ref"), (*loc, "origin"), ORIGINS),
        lower=arrays.get("lower", np.zeros(0)),
        upper=arrays.get("upper", np.zeros(0)),
        strength=arrays["strength"] if "strength" in fields else strength_of(None, ids.shape[0]),
        offset=arrays.get("offset"),
        prev_coordinate=arrays.get("prev_coordinate"),
    )


def _options(r: _Reader, top: dict[str, Any]) -> tuple[list[str], str, bool]:
    """The options' msgpack types; their values are the core's to check (`validate.check_options`), as for JSON."""
    outputs = top.get("outputs", list(OUTPUTS))
    if not isinstance(outputs, list):
        r.fault(("outputs",), "Input should be a valid list", "list_type")
        outputs = list(OUTPUTS)
    for i, o in enumerate(outputs):
        if not isinstance(o, str):
            r.fault(("outputs", i), literal_msg(OUTPUTS), "literal_error")
    hessian_mode = top.get("hessian_mode", "exact")
    if not isinstance(hessian_mode, str):
        r.fault(("hessian_mode",), literal_msg(HESSIAN_MODES), "literal_error")
        hessian_mode = "exact"
    active_only = top.get("active_only", False)
    if not isinstance(active_only, bool):
        r.fault(("active_only",), "Input should be a valid boolean", "bool_type")
        active_only = False
    return outputs, hessian_mode, active_only


def _layout(r: _Reader, top: dict[str, Any]) -> str:
    return _literal(r, top.get("layout", "joints"), ("layout",), ("joints", "bodies"))


def _literal(r: _Reader, value: Any, loc: Loc, allowed: tuple[str, ...]) -> str:
    """`value` if it is one of `allowed`, else a fault in pydantic's words and `allowed[0]` (the default)."""
    if isinstance(value, str) and value in allowed:
        return value
    r.fault(loc, "Input should be " + " or ".join(repr(a) for a in allowed), "literal_error")
    return allowed[0]


def encode(ev: Evaluation) -> bytes:
    """The response document: arrays as raw little-endian buffers (one copy each, into the message)."""
    batches = []
    for res in ev.batches:
        out: dict[str, Any] = {
            "constitution_uid": res.constitution_uid,
            "index": wire.pack_array(res.index, wire.INT64),
            "x": wire.pack_array(res.x, wire.FLOAT64),
            **({} if res.coordinate is None else {"coordinate": wire.pack_array(res.coordinate, wire.FLOAT64)}),
            "energy": wire.pack_array(res.energy, wire.FLOAT64),
        }
        for k in ("gradient", "hessian"):
            a = getattr(res, k)
            if a is not None:
                out[k] = wire.pack_array(a, wire.FLOAT64)
        batches.append(out)
    doc: dict[str, Any] = {"total_energy": float(ev.total_energy), "batches": batches}
    if ev.assembled is not None:  # layout="bodies"
        a = ev.assembled
        doc["assembled"] = {k: wire.pack_array(getattr(a, k), wire.INT64 if k in ("rows", "cols") else wire.FLOAT64)
                            for k in ("gradient", "rows", "cols", "blocks") if getattr(a, k) is not None}
    return wire.dumps(doc)
