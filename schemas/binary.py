"""The binary encoding of contract v1: msgpack with raw little-endian arrays (docs/http-api.md, "Binary transport").

The document has exactly the JSON body's structure and keys; every numeric array is instead a map
`{"dtype": "<f8" | "<i8", "shape": [d0, d1, ...], "data": bin}`, `data` holding the C-order elements,
little-endian. Nothing here is numerics: only bytes <-> `np.ndarray` views.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

MEDIA_TYPE = "application/msgpack"
MEDIA_TYPES = frozenset({MEDIA_TYPE, "application/x-msgpack", "application/vnd.msgpack"})
FLOAT64 = "<f8"
INT64 = "<i8"
ARRAY_KEYS = frozenset({"dtype", "shape", "data"})


def pack_array(a: np.ndarray, dtype: str) -> dict[str, Any]:
    """`a` as a wire array of `dtype`; one copy at most (none when `a` already is C-ordered `dtype`)."""
    a = np.ascontiguousarray(a, dtype=np.dtype(dtype))
    return {"dtype": dtype, "shape": list(a.shape), "data": memoryview(a.reshape(-1)).cast("B")}


def unpack_array(obj: Any, dtype: str, ndim: int | None) -> np.ndarray:
    """A read-only view of a wire array; `ValueError` with a readable reason when it is not one.

    `dtype` and `ndim` are what the field requires (`ndim` None: any number of dimensions, which the
    service's validator then judges, in the words it uses for JSON); sizes are checked against the data,
    never trusted (a claimed shape of 2**62 rows gets an error, not an allocation).
    """
    if not isinstance(obj, dict) or set(obj) != ARRAY_KEYS:
        raise ValueError(f'must be an array map {{"dtype": "{dtype}", "shape": [...], "data": bin}}')
    if obj["dtype"] != dtype:
        raise ValueError(f"dtype must be {dtype!r} (little-endian), got {obj['dtype']!r}")
    shape, data = obj["shape"], obj["data"]
    if not isinstance(shape, list) or (ndim is not None and len(shape) != ndim) or not all(_is_count(d) for d in shape):
        count = "" if ndim is None else f"{ndim} "
        raise ValueError(f"shape must be a list of {count}non-negative integers, got {shape!r}")
    if not isinstance(data, bytes):
        raise ValueError("data must be msgpack bin")
    count = 1
    for d in shape:
        count *= d
    itemsize = np.dtype(dtype).itemsize
    if count * itemsize != len(data):
        raise ValueError(f"shape {shape} needs {count * itemsize} bytes of data, got {len(data)}")
    return np.frombuffer(data, dtype=np.dtype(dtype)).reshape(shape)


def _is_count(d: Any) -> bool:
    return isinstance(d, int) and not isinstance(d, bool) and 0 <= d < 2**62


def dumps(doc: dict[str, Any]) -> bytes:
    """Encode a document; arrays' data is copied once, straight into the message."""
    return b"".join(_chunks(doc, msgpack.Packer(use_bin_type=True)))


def _chunks(obj: Any, packer: msgpack.Packer) -> list[bytes | memoryview]:
    # msgpack's own packer grows its buffer by reallocation: ~5 copies of a 50 MB Hessian.
    # Walking the few structural levels here lets each array's bytes be joined in place.
    if isinstance(obj, dict):
        out: list[bytes | memoryview] = [packer.pack_map_header(len(obj))]
        for k, v in obj.items():
            out.append(packer.pack(k))
            out += _chunks(v, packer)
        return out
    if isinstance(obj, list):
        out = [packer.pack_array_header(len(obj))]
        for v in obj:
            out += _chunks(v, packer)
        return out
    if isinstance(obj, memoryview):
        return [_bin_header(obj.nbytes), obj]
    return [packer.pack(obj)]


def _bin_header(n: int) -> bytes:
    """msgpack `bin 8/16/32` header (big-endian length, as msgpack specifies).

    msgpack has no bin longer than 2**32 - 1 bytes; the service's answer bound keeps far
    below it (docs/deployment.md, Limits), and a longer array is refused here rather than mis-encoded.
    """
    if n >= 2**32:
        raise ValueError(f"an array of {n} bytes exceeds msgpack's largest bin (2**32 - 1 bytes): split it")
    if n < 2**8:
        return b"\xc4" + n.to_bytes(1, "big")
    if n < 2**16:
        return b"\xc5" + n.to_bytes(2, "big")
    return b"\xc6" + n.to_bytes(4, "big")


def loads(body: bytes, object_pairs_hook: Any = None) -> Any:
    """Decode a msgpack document (each map through `object_pairs_hook` if given, as a list of its pairs);
    `ValueError` for anything that is not exactly one valid document."""
    try:
        # strict_map_key: keys are strings; raw=False: strings are UTF-8.
        return msgpack.unpackb(body, raw=False, strict_map_key=True, object_pairs_hook=object_pairs_hook)
    except Exception as e:  # msgpack raises several unrelated types for malformed input
        raise ValueError(f"body is not a valid msgpack document ({type(e).__name__}: {e})") from None
