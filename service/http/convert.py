"""The JSON encoding: body bytes to plain data (checked by the one validator, `document`), an `Evaluation` to JSON."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import orjson
from pydantic_core import from_json

from jointlimits.service.core import Evaluation, Fault, InputError
from jointlimits.service.http import document, limits

MEDIA_TYPE = "application/json"


def decode(body: bytes, max_values: int, max_batches: int, opening: bool = False,
           checker: document.Checker | None = None) -> dict[str, Any]:
    """Keyword arguments of `jointlimits.service.core.evaluate` for a JSON body (`opening`: a session's opening
    document, whose `id` is returned too, under "id"): its values and batches bounded on its bytes
    (`limits.check_json`: 413 `HttpError`, the bound kept in `checker.values`), then parsed once and checked
    (`read`: `InputError`, 422)."""
    checker = checker or document.Checker(binary=False)
    checker.values = limits.check_json(body, max_values, max_batches)
    return read(body, opening, checker)


def read(body: bytes, opening: bool = False, checker: document.Checker | None = None) -> dict[str, Any]:
    """A JSON body parsed once (`load`) and checked by the one validator (`document.Checker.request`)."""
    checker = checker or document.Checker(binary=False)
    doc = load(body)
    checker.booleans = booleans(body)
    return checker.request(doc, opening)


def booleans(text: bytes | str) -> int:
    """How many `true` and `false` a JSON text may hold (C-speed counts): NumPy would read one in an array of
    numbers as 1 or 0, so the validator reads the arrays item by item when one may be there."""
    t, f = ("true", "false") if isinstance(text, str) else (b"true", b"false")
    return text.count(t) + text.count(f)  # type: ignore[arg-type]


def load(body: bytes) -> Any:
    """A JSON document as plain data, parsed once by pydantic's own parser (jiter): NaN, Infinity and 1e400
    (inf) are read as floats, for the core to name as non-finite; `InputError` in pydantic's words for a
    broken document.

    jiter keeps the last of two equal keys. Each key is followed by a colon, so a body whose colons are
    exactly the keys of the request's objects (and the colons inside their strings) repeats none: one C-speed
    count proves it for every clean body. A body with more colons (a repeated key, or an object or a colon
    where no request has one: refused either way) is read by `json` with its keys' list
    (`document.pairs` marks the repeated ones), for the validator to name them.
    """
    try:
        doc = from_json(body)
    except ValueError as e:
        raise InputError([Fault((), f"Invalid JSON: {e}", "json_invalid")]) from None
    if isinstance(doc, dict) and (colons := body.count(b":")) != (keys := sum(map(len, _objects(doc)))) \
            and colons != keys + _string_colons(doc):
        try:
            doc = json.loads(body, object_pairs_hook=document.pairs)
        except ValueError:
            pass  # jiter read it: the validator names what is wrong
    return doc


def _objects(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """`doc` and the objects in its values: `bodies` and each batch of a request (a list that does not start with
    an object, such as `q`'s rows, is not walked: keys left out only send a body to `json`'s careful read)."""
    return [doc, *(v for v in doc.values() if isinstance(v, dict)),
            *(o for v in doc.values() if isinstance(v, list) and v and isinstance(v[0], dict) for o in v if isinstance(o, dict))]


def _string_colons(doc: dict[str, Any]) -> int:
    """The colons inside the strings of `doc`'s objects (keys and values) and of the lists in its values."""
    strings = [x for o in _objects(doc) for kv in o.items() for x in kv if isinstance(x, str)]
    strings += [x for v in doc.values() if isinstance(v, list) for x in v if isinstance(x, str)]
    return sum(x.count(":") for x in strings)


ROW = ("constitution_uid", "index", "x", "coordinate", "energy", "gradient", "hessian")
"""A batch's answer fields, in the wire's order."""


def to_wire(ev: Evaluation) -> dict[str, Any]:
    """The response body of contract v1.2 as NumPy arrays; what the core did not compute (None) left out."""
    doc = {"total_energy": ev.total_energy, "batches": [_present(r, ROW) for r in ev.batches]}
    if ev.assembled is not None:  # layout="bodies"
        doc["assembled"] = _present(ev.assembled, ("gradient", "rows", "cols", "blocks"))
    return doc


def _present(obj: Any, names: tuple[str, ...]) -> dict[str, Any]:
    return {k: v for k in names if (v := getattr(obj, k)) is not None}


FLOATS_PER_PIECE = 2**18
"""Numbers orjson writes in one call (~5 ms): between calls the GIL passes to other threads, so a
worker's event loop and uvicorn's health-check thread keep answering while a large answer is written."""


def encode(ev: Evaluation) -> bytes:
    """The answer's JSON bytes (`dumps`)."""
    return dumps(to_wire(ev))


def dumps(doc: dict[str, Any]) -> bytes:
    """The bytes of `orjson.dumps(doc, option=OPT_SERIALIZE_NUMPY)` (each float in its shortest round-trip form),
    each array written `FLOATS_PER_PIECE` numbers at a time and the pieces joined once (`bytes.join` releases the
    GIL while it copies). The core guarantees finite numbers; orjson would write a stray NaN as `null`."""
    return b"".join(_pieces(doc))


def _pieces(v: Any) -> list[bytes | memoryview]:
    """`v` (a document of objects, lists, scalars and arrays; keys plain ASCII) as JSON, in pieces."""
    if isinstance(v, np.ndarray):
        return _array_pieces(v)
    if isinstance(v, dict):
        out: list[bytes | memoryview] = [b"{"]
        for j, (k, x) in enumerate(v.items()):
            out += [b',"' if j else b'"', k.encode(), b'":', *_pieces(x)]
        return [*out, b"}"]
    if isinstance(v, list):
        out = [b"["]
        for j, x in enumerate(v):
            out += [b"," if j else b"", *_pieces(x)]
        return [*out, b"]"]
    return [orjson.dumps(v, option=orjson.OPT_SERIALIZE_NUMPY)]


def _array_pieces(a: np.ndarray) -> list[bytes | memoryview]:
    """`a` (N, ...) as JSON: one orjson call per block of rows, the blocks' brackets dropped and rejoined."""
    a = np.ascontiguousarray(a)  # orjson serialises C-ordered arrays only
    rows = max(1, FLOATS_PER_PIECE // max(1, a[0].size if a.ndim > 1 and a.shape[0] else 1))
    if a.shape[0] <= rows:
        return [orjson.dumps(a, option=orjson.OPT_SERIALIZE_NUMPY)]
    out: list[bytes | memoryview] = [b"["]
    for start in range(0, a.shape[0], rows):
        out += [memoryview(orjson.dumps(a[start : start + rows], option=orjson.OPT_SERIALIZE_NUMPY))[1:-1], b","]
    out[-1] = b"]"
    return out
