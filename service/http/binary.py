"""The binary encoding (schemas/binary.py): msgpack bytes <-> plain data, and an `Evaluation` to msgpack.

The msgpack library unpacks the document, within bounds that keep a hostile body from building
millions of objects; the one validator (`document.Checker`) checks it, and each array map becomes
one `np.frombuffer` view there (no Python list of numbers).
"""

from __future__ import annotations

import io
from typing import Any

import msgpack
import numpy as np

from jointlimits.schemas import binary as wire
from jointlimits.service.core import Evaluation, Fault, InputError
from jointlimits.service.core.errors import Loc
from jointlimits.service.http import document, limits
from jointlimits.service.http.convert import to_wire
from jointlimits.service.http.errors import HttpError

MEDIA_TYPE = wire.MEDIA_TYPE

_MAP_HEADERS = frozenset(range(0x80, 0x90)) | {0xDE, 0xDF}  # fixmap, map 16, map 32
_ARRAY_HEADERS = frozenset(range(0x90, 0xA0)) | {0xDC, 0xDD}
_STR_HEADERS = frozenset(range(0xA0, 0xC0)) | {0xD9, 0xDA, 0xDB}  # fixstr, str 8, 16, 32


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
        return document.pairs(pairs)

    def items(self, items: list[Any]) -> list[Any]:
        self.tick()
        return items

    def tick(self) -> None:
        self.left -= 1
        if self.left < 0:
            raise _TooMany


def _unpacker(body: bytes, **options: Any) -> msgpack.Unpacker:
    """An unpacker reading `body` itself in steps of at most 8 MiB (`feed(body)` would hold a whole second copy;
    a small body, a session's step, allocates no more than its size), strings as UTF-8."""
    return msgpack.Unpacker(io.BytesIO(body), read_size=max(1, min(len(body), 2**23)),
                            max_buffer_size=max(len(body), 2**23), raw=False, **options)


def unpack(body: bytes, r: document.Checker, max_batches: int | None = None, message: bool = False,
           opening: bool = False) -> Any:
    """The document, its top-level `batches` unpacked and checked one batch at a time (`message`: a session's
    later message, which has no batches, and whose faults say "message"). A session's document (`message`,
    `opening`) that is refused keeps its readable `id` in `r.message_id` (its fault reply repeats it): the read
    may stop before the `id`, at the fault cap inside `batches` or at malformed bytes.

    A body of 30M empty maps as batches would otherwise become 30M dicts (~2 GB) before the
    first check; this way the validator's fault cap stops the unpacking after a few batches.
    Every other value is unpacked whole, but holds at most `MAX_CONTAINERS` maps and arrays
    of at most `MAX_ITEMS` items each: no value costs more than a bounded number of objects.
    """
    what = "message" if message else "request"
    budget = _Budget()
    u = _unpacker(body, strict_map_key=True, object_pairs_hook=budget.pairs, list_hook=budget.items,
                  max_map_len=MAX_ITEMS, max_array_len=MAX_ITEMS)

    def value(loc: Loc) -> Any:
        budget.left = MAX_CONTAINERS
        try:
            return u.unpack()
        except _TooMany:
            msg = f"holds more than {MAX_CONTAINERS} maps and arrays: not the structure of a {what}"
            raise InputError([*r.faults, Fault(loc, msg, "structure")]) from None
        except ValueError as e:
            if "exceeds max_" not in str(e):
                raise
            msg = f"holds a map or array of {str(e).split()[0]} items; a {what}'s have at most {MAX_ITEMS}"
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
                if k == "batches" and not message and u.tell() < len(body) and body[u.tell()] in _ARRAY_HEADERS:
                    n_batches = u.read_array_header()
                    if max_batches is not None:  # a 413 before any batch is read: each costs Python work
                        limits.check_batches(n_batches, max_batches)
                    doc[k] = document.Checked(r.batch(b, value(("batches", b))) for b in range(n_batches))
                else:
                    doc[k] = value((k,))
            if repeated:
                doc = document.Repeated(doc)
                doc.repeated = repeated
        if u.tell() != len(body):
            raise ValueError(f"{len(body) - u.tell()} bytes after the document")
    except HttpError:
        raise  # too many batches
    except Exception as e:
        if not isinstance(e, InputError):  # msgpack raises several unrelated types for malformed input
            msg = f"{'message' if message else 'body'} is not a valid msgpack document ({type(e).__name__}: {e})"
            e = InputError([Fault((), msg, "msgpack_invalid")])
        if message or opening:
            r.message_id = document.readable_id(_top_level_id(body))
        raise e from None
    return doc


def decode(body: bytes, max_batches: int | None = None, opening: bool = False,
           checker: document.Checker | None = None) -> dict[str, Any]:
    """`convert.decode` for a msgpack body: `InputError`, or 413 `HttpError` for more batches than `max_batches`
    before any batch is read (each costs Python work here; its joints are counted once it is read, `limits.admit`)."""
    r = checker or document.Checker(binary=True)
    return r.request(unpack(body, r, max_batches, opening=opening), opening)


def _top_level_id(body: bytes) -> Any:
    """The top-level `id` of a msgpack map unless it is a map or an array (every other value walked, never built:
    a C-speed pass over bytes already received); None when absent, or when the body breaks before it."""
    u = _unpacker(body)
    try:
        for _ in range(u.read_map_header()):
            key = u.unpack() if body[u.tell()] in _STR_HEADERS else u.skip()
            if key == "id" and body[u.tell()] not in _MAP_HEADERS | _ARRAY_HEADERS:
                return u.unpack()
            u.skip()
    except Exception:  # msgpack raises several unrelated types for malformed input
        pass
    return None


SMALL_ARRAYS = 1 << 20
"""A document whose arrays hold at most this many bytes (a robot's answer, a session's step) is written by one
msgpack call: byte for byte `wire.dumps`' output at a fifth of its time; a larger one by `wire.dumps`, which copies
each array once where msgpack's own buffer would copy it several times."""


def dumps(doc: Any) -> bytes:
    """`doc` in msgpack, each array an array map (integers as int64, the rest float64)."""
    sizes: list[int] = []
    packed = _pack(doc, sizes)
    return msgpack.packb(packed, use_bin_type=True) if sum(sizes) <= SMALL_ARRAYS else wire.dumps(packed)


def _pack(doc: Any, sizes: list[int]) -> Any:
    if isinstance(doc, np.ndarray):
        sizes.append(doc.nbytes)
        return wire.pack_array(doc, wire.INT64 if doc.dtype.kind in "iu" else wire.FLOAT64)
    if isinstance(doc, dict):
        return {k: _pack(v, sizes) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_pack(v, sizes) for v in doc]
    return doc


def encode(ev: Evaluation) -> bytes:
    """The answer document (`convert.to_wire`), arrays as raw little-endian buffers (one copy each)."""
    return dumps(to_wire(ev))
