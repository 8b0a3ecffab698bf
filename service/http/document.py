"""The one validator: a plain document checked, every fault named, and turned into the core's arguments.

The decoders only turn bytes into plain data (`convert`: JSON by jiter; `binary`: msgpack, its arrays as maps
`{dtype, shape, data}`). A `Checker` reads that document, a request (or a session's opening) or a session's later
message, in either encoding: the keys, the structure and each numeric array (made a NumPy array, an array map a
view without a copy). What needs arithmetic (shapes, finiteness, indices, geometry) is the core's
(`service/core/validate.py`). The words are pydantic's, as JSON's users have always read them; msgpack keeps its
own for what only it can say. The `MAX_FAULTS`-th fault ends the check: a flood of bad batches costs 20 faults.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from jointlimits.schemas import OUTPUTS
from jointlimits.schemas import binary as wire
from jointlimits.schemas import evaluate as models
from jointlimits.schemas import session as proto
from jointlimits.schemas.constitutions import STRENGTH_DEFAULT
from jointlimits.service.core import Bodies, Fault, InputError, Joints, registry
from jointlimits.service.core.assembled import LAYOUTS
from jointlimits.service.core.errors import MAX_FAULTS, Loc
from jointlimits.service.core.validate import _element_faults as element_faults
from jointlimits.service.core.validate import (DUPLICATE_KEY_MSG, HESSIAN_MODES, NOT_A_LIST, NOT_AN_INTEGER, ORIGINS,
                                               ROWS, as_array, check_options, literal_msg)

# Each object's keys (True: required), as the wire models define them.
REQUEST, BODIES, BATCH = ({k: f.is_required() for k, f in m.model_fields.items()} for m in (models.EvaluateRequest, models.Bodies, models.JointBatch))
OPENING = {**REQUEST, "id": False}  # a session's opening document may carry an `id`
BODY_ARRAYS = ("q", "q_prev", "q_ref")
BATCH_ARRAYS = {"body_ids": True, "edges": False, "local_edges": False, "lower": False, "upper": False,
                "strength": False, "offset": False, "prev_coordinate": False}
"""The numeric arrays of a request (True: of integers)."""

OBJECT = "Input should be an object"
MAP = "Input should be a map (a msgpack map, as a JSON object)"
MISSING = ("Field required", "missing")
BAD_KIND = (literal_msg(tuple(proto.KEYS)), "union_tag_invalid")
INT64 = range(-(2**63), 2**63)
NOT_OPEN = (
    "open a scene first: the first message of a session is the opening document (a POST /v1/evaluate body, "
    "with an optional id), not a message with a kind"
)


def readable_id(v: Any) -> int | str | None:
    """`v` if it is a valid `id` (an int64 or a string of at most 128 characters), else None."""
    ok = (isinstance(v, int) and not isinstance(v, bool) and v in INT64) or (isinstance(v, str) and len(v) <= 128)
    return v if ok else None


class Repeated(dict):
    """A map that repeated a key (the last value kept, as `dict` does); `repeated` lists those keys."""

    repeated: list[Any]


def pairs(items: list[tuple[Any, Any]]) -> dict[Any, Any]:
    """The decoders' `object_pairs_hook`: a plain dict, or a `Repeated` that remembers its repeated keys."""
    d = dict(items)
    if len(d) == len(items):
        return d
    m, seen = Repeated(d), set()
    m.repeated = [k for k, _ in items if k in seen or seen.add(k)]  # type: ignore[func-returns-value]
    return m


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


class Checker:
    """The faults of one document, in its encoding's words (`binary`: msgpack). `booleans` (JSON): the body
    may hold `true`/`false` inside an array, which NumPy would read as 1 and 0: its arrays are then read item
    by item (a count the decoder made on the bytes, not a parse)."""

    def __init__(self, binary: bool) -> None:
        self.binary, self.booleans = binary, 0
        self.faults: list[Fault] = []
        self.values: int | None = None
        """A JSON text's values (`limits.check_json`), counted before its parse: the request's cost (`sizing`)."""
        self.message_id: int | str | None = None
        """The document's `id` if it is a readable one (a session's fault reply repeats it), once it is read."""

    def _start(self, doc: Any) -> None:
        """Before any fault: the readable `id`; and `true`/`false` other than `active_only`'s may be in an array."""
        if isinstance(doc, dict):
            self.message_id = readable_id(doc.get("id"))
            self.booleans = max(0, self.booleans - isinstance(doc.get("active_only"), bool))

    def fault(self, loc: Loc, msg: str, type: str = "value_error") -> None:
        self.faults.append(Fault(loc, msg, type))
        if len(self.faults) >= MAX_FAULTS:
            raise InputError(self.faults)

    def raise_if_any(self) -> None:
        if self.faults:
            raise InputError(self.faults)

    # ------------------------------------------------------------------ the leaves

    def object(self, obj: Any, loc: Loc, keys: dict[str, bool]) -> dict[str, Any] | None:
        """`obj`'s known fields, after its key faults (repeated, not a string, unknown, missing); None if not a map."""
        if not isinstance(obj, dict):
            if self.binary:
                self.fault(loc, MAP, "model_type")
            else:
                self.fault(loc, OBJECT, "dict_type" if loc == () else "model_type")
            return None
        self.repeated_keys(obj, loc)
        for k in obj:
            if isinstance(k, str) and k not in keys:
                self.fault((*loc, k), "Extra inputs are not permitted", "extra_forbidden")
        for k, required in keys.items():
            if required and k not in obj:
                self.fault((*loc, k), *MISSING)
        return {k: v for k, v in obj.items() if k in keys}

    def repeated_keys(self, obj: dict, loc: Loc) -> bool:
        """Faults for the keys a `dict` hides: repeated ones and (msgpack) ones that are not strings."""
        n = len(self.faults)
        for k in getattr(obj, "repeated", ()):
            self.fault((*loc, k), DUPLICATE_KEY_MSG, "duplicate_key")
        for k in obj:
            if not isinstance(k, str):
                self.fault((*loc, k), f"Map keys must be msgpack str, got {type(k).__name__}", "key_type")
        return len(self.faults) > n

    def int64(self, v: Any, loc: Loc) -> int:
        if isinstance(v, int) and not isinstance(v, bool) and v in INT64:
            return v
        if self.binary:
            self.fault(loc, "Input should be a valid integer in int64 range", "int_type")
        elif isinstance(v, int) and not isinstance(v, bool):  # pydantic's words for JSON's int64 bounds
            above = v > 0
            self.fault(loc, f"Input should be {'less' if above else 'greater'} than or equal to {2**63 - 1 if above else -(2**63)}",
                       "less_than_equal" if above else "greater_than_equal")
        else:
            self.fault(loc, *NOT_AN_INTEGER)
        return 0

    def id(self, v: Any, loc: Loc = ("id",)) -> int | str | None:
        """A message's `id`: an int64 or a string of at most 128 characters (JSON: pydantic's union words)."""
        if v is None or (isinstance(v, str) and len(v) <= 128):
            return v
        if self.binary or (isinstance(v, int) and not isinstance(v, bool) and v in INT64):
            return self.int64(v, loc)
        self.int64(v, (*loc, "constrained-int"))
        if isinstance(v, str):
            self.fault((*loc, "constrained-str"), "String should have at most 128 characters", "string_too_long")
        else:
            self.fault((*loc, "constrained-str"), "Input should be a valid string", "string_type")
        return None

    def literal(self, value: Any, loc: Loc, allowed: tuple[str, ...]) -> str:
        """`value` if it is one of `allowed`, else a fault in pydantic's words and `allowed[0]` (the default)."""
        if isinstance(value, str) and value in allowed:
            return value
        self.fault(loc, literal_msg(allowed), "literal_error")
        return allowed[0]

    def array(self, value: Any, loc: Loc, integer: bool = False) -> np.ndarray:
        """A numeric array of whatever shape it has (the core judges the shape): nested lists of numbers (JSON), an
        array map as a view of its bytes (msgpack), or a NumPy array; else its faults and an empty array."""
        a: np.ndarray | None = None
        if value is None or isinstance(value, (bool, int, float, str)):  # null or a scalar
            self.fault(loc, *NOT_A_LIST)
        elif self.binary:
            if not (isinstance(value, dict) and self.repeated_keys(value, loc)):
                try:
                    a = wire.unpack_array(value, wire.INT64 if integer else wire.FLOAT64, None)
                except ValueError as e:
                    self.fault(loc, str(e))
                if a is not None and a.ndim == 0:  # a number in an array map of shape []
                    self.fault(loc, *NOT_A_LIST)
                    a = None
        else:
            found = element_faults(value, loc, integer, ROWS[loc[-1]]) if self.booleans else []
            a, found = (None, found) if found else as_array(value, loc, integer)
            for f in found:
                self.fault(f.loc, f.msg, f.type)
            if a is not None and a.shape == (0,):
                a = a.reshape(0, *ROWS[loc[-1]])
        return np.zeros(0, np.int64 if integer else np.float64) if a is None else a

    def options(self, top: dict[str, Any]) -> dict[str, Any]:
        """The evaluate options `top` gives, checked by the core's `check_options` (which the core runs again for
        the in-process arrays) once `outputs` is a list: a document with a faulty option is refused here."""
        out = {k: top[k] for k in ("outputs", "hessian_mode", "active_only") if k in top}
        if not isinstance(out.get("outputs", []), list):
            self.fault(("outputs",), *NOT_A_LIST)
            out["outputs"] = list(OUTPUTS)
        for f in check_options(out.get("outputs", OUTPUTS), out.get("hessian_mode", HESSIAN_MODES[0])):
            self.fault(f.loc, f.msg, f.type)
        if not isinstance(out.get("active_only", False), bool):
            self.fault(("active_only",), "Input should be a valid boolean", "bool_type")
        return out

    # ------------------------------------------------------------------ a request

    def batch(self, b: int, raw: Any) -> Joints:
        """Batch `b` of a request (the msgpack decoder calls it as each batch is read: the cap ends a flood early)."""
        loc = ("batches", b)
        fields = self.object(raw, loc, BATCH) or {}
        arrays = {k: self.array(fields[k], (*loc, k), BATCH_ARRAYS[k]) for k in BATCH_ARRAYS if k in fields}
        uid = self.int64(fields.get("constitution_uid", 0), (*loc, "constitution_uid"))
        ids = arrays.get("body_ids", np.zeros((0, 2), np.int64))
        return Joints(
            constitution_uid=uid,
            base_uid=self.int64(fields["base_uid"], (*loc, "base_uid")) if "base_uid" in fields else registry.base_uid_of(uid),
            body_ids=ids,
            edges=arrays.get("edges"),
            local_edges=arrays.get("local_edges"),
            origin=self.literal(fields.get("origin", "q_ref"), (*loc, "origin"), ORIGINS),
            lower=arrays.get("lower", np.zeros(0)),
            upper=arrays.get("upper", np.zeros(0)),
            strength=arrays["strength"] if "strength" in fields else np.full(len(ids), STRENGTH_DEFAULT),
            offset=arrays.get("offset"),
            prev_coordinate=arrays.get("prev_coordinate"),
        )

    def request(self, doc: Any, opening: bool = False) -> dict[str, Any]:
        """Keyword arguments of `jointlimits.service.core.evaluate` (`opening`: a session's opening document,
        whose `id` is returned too, under "id"); `InputError` naming every fault of the document.

        `doc["batches"]` may be a `Checked` list: its batches were checked as they were decoded."""
        self._start(doc)
        top = self.object(doc, (), OPENING if opening else REQUEST) or {}
        # The document's own scalars first: a flood of keys in `bodies` or of batches does not hide them.
        options = {"outputs": list(OUTPUTS), "hessian_mode": "exact", "active_only": False} | self.options(top)
        layout = self.literal(top.get("layout", "joints"), ("layout",), LAYOUTS)
        opening_id = self.id(top.get("id")) if opening else None
        bodies = self.object(top["bodies"], ("bodies",), BODIES) if "bodies" in top else None
        q = {k: self.array(bodies[k], ("bodies", k)) if bodies and k in bodies else np.zeros((0, 12)) for k in BODY_ARRAYS}
        batches = top.get("batches", [])
        if not isinstance(batches, Checked):
            if not isinstance(batches, list):
                self.fault(("batches",), *NOT_A_LIST)
                batches = []
            batches = [self.batch(b, raw) for b, raw in enumerate(batches)]
        self.raise_if_any()
        return ({"id": opening_id} if opening else {}) | dict(bodies=Bodies(**q), batches=list(batches), **options, layout=layout)

    # ------------------------------------------------------------------ a session's later message

    def message(self, doc: Any) -> Message:
        """A session message after the opening one; `InputError` naming its faults."""
        if not isinstance(doc, dict):
            raise InputError([Fault((), OBJECT, "dict_type")])
        self._start(doc)
        kind = doc.get("kind")
        if not isinstance(kind, str) or kind not in proto.KEYS:
            if kind is None:
                # A request document sent as a message: the session is not open for it.
                raise InputError([Fault(("kind",), *MISSING)])
            raise InputError([Fault(("kind",), *BAD_KIND)])
        fields = self.object(doc, (), proto.KEYS[kind]) or {}
        out = Message(kind=kind, id=self.id(fields.get("id")))
        if "q" in fields:
            out.q = self.array(fields["q"], ("q",))
        if kind == proto.EVALUATE:
            out.options = self.options(fields)
        if kind == proto.UPDATE:
            out.batch = self.int64(fields.get("batch", 0), ("batch",))
            out.index = self.array(fields["index"], ("index",), True) if "index" in fields else None  # else: missing
            out.values = {k: self.array(fields[k], (k,)) for k in proto.UPDATABLE if k in fields}
        self.raise_if_any()
        return out


class Checked(list):
    """A request's batches, each already checked (`Checker.batch`) as it was decoded."""
