"""The keys of a JSON request body, checked on its bytes before pydantic parses it.

Pydantic (like orjson and `json`) keeps the last of two equal keys, and it lists one
error per unknown key and per missing field of every batch: a body of 300k `{}` batches
gave 2.1M errors. This scan, run first, finds

- repeated keys in any object (a solver that sends two `lower` lists has a bug);
- unknown and missing keys of the objects a request is made of: the request itself,
  `bodies`, and each batch;

and stops at the `MAX_FAULTS`-th fault. One C-speed regex finds the tokens it needs
(braces, keys, runs of string values); the numbers, which are nearly all of a real
body, are skipped inside the regex. Python only sees ~9 tokens per batch.

An object anywhere else (in a list of numbers, in an unknown field's value) is always
an error that pydantic names at its field: the scan stops there and leaves the rest of
the body to pydantic (which, with `FailFast` lists, lists a bounded number of errors),
so a flood of nested objects costs no Python loop.
"""

from __future__ import annotations

import itertools
import json
import re
from dataclasses import dataclass, field

from jointlimits.schemas.evaluate import Bodies, EvaluateRequest, JointBatch
from jointlimits.service.core.errors import MAX_FAULTS, Fault, Loc
from jointlimits.service.core.validate import DUPLICATE_KEY_MSG

# A string; one never closed runs to the end of the body (else each of its escaped quotes
# would start a new scan to the end: quadratic).
_STR = rb'"[^"\\]*(?:\\.[^"\\]*)*(?:"|\\?\Z)'
# Strings are found by a pattern with a literal first byte, which the regex engine skips to at
# memchr speed (~4 GB/s on numbers; one pattern with alternatives crawls at ~60 MB/s). Braces are
# looked for only between two strings. A run of string values (`"energy", "gradient"`) is one
# token; a key is a string followed by `:`.
_STRINGS = re.compile(_STR + rb"(?:\s*,\s*" + _STR + rb"(?!\s*:))*", re.S)
_BRACES = re.compile(rb"[{}]")
_COLON = re.compile(rb"\s*:\s*([\[{]?)")
_KEY_END = re.compile(rb'"\s*:')
_OBJECT_FIRST = re.compile(rb"\s*\{")

# The objects of a request: their keys (True: required), and which key leads to which object.
_TOP, _BODIES, _BATCH = (
    {k: f.is_required() for k, f in model.model_fields.items()} for model in (EvaluateRequest, Bodies, JointBatch)
)
_OPENING = {**_TOP, "id": False}  # a session's opening document: the request, and an optional `id`
_CHILD = {(id(top), key, starts): child for top in (_TOP, _OPENING) for key, starts, child in (("bodies", b"{", _BODIES), ("batches", b"[", _BATCH))}


@dataclass
class _Object:
    loc: Loc
    schema: dict[str, bool]
    keys: set[str] = field(default_factory=set)
    key: str = ""  # the last key seen, and how its value starts (b"{", b"[" or b"")
    starts: bytes = b""
    children: int = 0  # objects met so far in the value of `key` (the batch index)


def _key(raw: bytes) -> str:
    if b"\\" not in raw:
        return raw[1:-1].decode("utf-8", "replace")
    try:
        return json.loads(raw)  # escapes: "\u006cower" is "lower"
    except ValueError:
        return raw[1:-1].decode("utf-8", "replace")


@dataclass
class KeyScan:
    faults: list[Fault]
    """Repeated, unknown and missing keys, in document order (at most the cap)."""
    complete: bool
    """The scan covered the whole body (else it stopped at the cap or at something no request holds)."""
    stray: tuple[int, Loc, bool] | None = None
    """Where it stopped at an object outside the request's own objects: its offset, the field
    holding it, and whether that field is one of the request's (else it is already a fault)."""


def scan(body: bytes, cap: int = MAX_FAULTS, opening: bool = False) -> KeyScan:
    """The key faults of `body`; it stops at the `cap`-th fault, or at anything a valid body
    cannot hold (an object outside the request's own objects, a second document).
    `opening`: a session's opening document, which may also carry an `id`."""
    if not _OBJECT_FIRST.match(body):
        return KeyScan([], True)  # not an object: pydantic names that, in one error
    s = _Scan(body, cap, _OPENING if opening else _TOP)
    try:
        pos = 0
        for m in _STRINGS.finditer(body):
            a = m.start()
            if body.find(b"{", pos, a) >= 0 or body.find(b"}", pos, a) >= 0:  # memchr, before the slower regex
                for b in _BRACES.finditer(body, pos, a):
                    s.brace(b.group(), b.start())
            colon = _COLON.match(body, m.end())
            if colon is not None:
                s.key(m.group(), colon.group(1))
            elif s.closed:
                raise _Stop
            pos = m.end()
        for b in _BRACES.finditer(body, pos):
            s.brace(b.group(), b.start())
    except _Stop:
        return KeyScan(s.faults, False, s.stray)
    return KeyScan(s.faults, not s.stack)


def keys_after(body: bytes, pos: int, most: int) -> int:
    """Keys (a string, then `:`) in `body[pos:]`, counted up to `most` (C-speed, memory-free)."""
    return sum(1 for _ in itertools.islice(_KEY_END.finditer(body, pos), most))


class _Stop(Exception):
    """The scan ends here: the fault cap is reached, or the rest is pydantic's to name."""


class _Scan:
    def __init__(self, body: bytes, cap: int, top: dict[str, bool]) -> None:
        self.cap, self.top = cap, top
        self.faults: list[Fault] = []
        self.stack: list[_Object] = []
        self.closed = False  # the document's top object has closed
        self.stray: tuple[int, Loc, bool] | None = None

    def fault(self, loc: Loc, msg: str, type: str) -> None:
        self.faults.append(Fault(loc, msg, type))
        if len(self.faults) >= self.cap:
            raise _Stop

    def brace(self, b: bytes, pos: int) -> None:
        stack = self.stack
        if self.closed:
            raise _Stop  # more after the document
        if b == b"{":
            if not stack:
                stack.append(_Object((), self.top))
                return
            parent = stack[-1]
            schema = _CHILD.get((id(parent.schema), parent.key, parent.starts))
            if schema is None:
                self.stray = (pos, (*parent.loc, parent.key), parent.key in parent.schema)
                raise _Stop
            if parent.starts == b"[":
                loc = (*parent.loc, parent.key, parent.children)
                parent.children += 1
            else:
                loc = (*parent.loc, parent.key)
            stack.append(_Object(loc, schema))
            return
        if not stack:
            raise _Stop
        obj = stack.pop()
        for k, required in obj.schema.items():
            if required and k not in obj.keys:
                self.fault((*obj.loc, k), "Field required", "missing")
        self.closed = not stack

    def key(self, raw: bytes, starts: bytes) -> None:
        if not self.stack or self.closed:
            raise _Stop
        obj = self.stack[-1]
        k = _key(raw)
        if k in obj.keys:
            self.fault((*obj.loc, k), DUPLICATE_KEY_MSG, "duplicate_key")
        elif k not in obj.schema:
            self.fault((*obj.loc, k), "Extra inputs are not permitted", "extra_forbidden")
        obj.keys.add(k)
        obj.key, obj.starts, obj.children = k, starts, 0
