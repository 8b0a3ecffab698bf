"""The binary encoding's layout, byte for byte, as the README documents it for other languages."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from jointlimits.client import LocalClient, codec
from jointlimits.schemas import binary as wire
from tests.http.test_errors_http import base_request


def test_array_layout_is_the_documented_bytes():
    packed = wire.dumps({"x": wire.pack_array(np.array([1.0, -2.5]), wire.FLOAT64)})
    expected = (
        b"\x81\xa1x"  # map of 1, key "x"
        + b"\x83\xa5dtype\xa3<f8"  # map of 3: "dtype": "<f8"
        + b"\xa5shape\x91\x02"  # "shape": [2]
        + b"\xa4data\xc4\x10"  # "data": bin 8 of 16 bytes
        + np.array([1.0, -2.5], dtype="<f8").tobytes()
    )
    assert packed == expected


@pytest.mark.parametrize("shape", [(0,), (0, 12), (3, 12), (2, 24, 24), (5, 2, 3)])
def test_round_trip_is_bit_exact_and_zero_copy(shape):
    a = np.random.default_rng(0).normal(size=shape) * 1e-300
    doc = wire.loads(wire.dumps({"a": wire.pack_array(a, wire.FLOAT64)}))
    b = wire.unpack_array(doc["a"], wire.FLOAT64, len(shape))
    assert b.shape == shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))
    assert not b.flags.writeable  # a view on the received bytes, not a copy


def test_non_contiguous_and_big_endian_inputs_are_sent_little_endian_row_major():
    a = np.arange(6.0).reshape(2, 3).T.astype(">f8")
    packed = wire.pack_array(a, wire.FLOAT64)
    assert packed["shape"] == [3, 2] and bytes(packed["data"]) == np.ascontiguousarray(a, dtype="<f8").tobytes()


@pytest.mark.parametrize(
    ("obj", "words"),
    [
        ([1.0, 2.0], "array map"),
        ({"dtype": "<f4", "shape": [1], "data": b"\x00" * 4}, "dtype"),
        ({"dtype": "<f8", "shape": [1, 1], "data": b"\x00" * 8}, "shape must be a list of 1"),
        ({"dtype": "<f8", "shape": [True], "data": b"\x00" * 8}, "non-negative integers"),
        ({"dtype": "<f8", "shape": [2], "data": b"\x00" * 8}, "needs 16 bytes"),
        ({"dtype": "<f8", "shape": [2**61], "data": b""}, "needs"),
        ({"dtype": "<f8", "shape": [1], "data": "text"}, "bin"),
        ({"dtype": "<f8", "shape": [1], "data": b"\x00" * 8, "extra": 1}, "array map"),
    ],
)
def test_malformed_arrays_are_refused_with_a_reason(obj, words):
    with pytest.raises(ValueError, match=words):
        wire.unpack_array(obj, wire.FLOAT64, 1)


def test_sdk_request_document_has_the_json_structure():
    doc = msgpack.unpackb(codec.encode(base_request(), binary=True)[0])
    assert set(doc) == {"bodies", "batches", "outputs", "hessian_mode", "active_only"}
    assert doc["bodies"]["q"]["dtype"] == "<f8" and doc["bodies"]["q"]["shape"] == [3, 12]
    assert doc["batches"][0]["body_ids"]["dtype"] == "<i8" and doc["batches"][1]["edges"]["shape"] == [3, 2, 3]
    assert doc["batches"][1]["constitution_uid"] == 669 and doc["batches"][1]["base_uid"] == 20


def test_response_decoding_matches_local_bits():
    from jointlimits.service.http import binary

    request = base_request()
    local = LocalClient().evaluate(request)
    ev = codec.decode(binary.encode(local), "application/msgpack")
    assert ev.total_energy == local.total_energy
    for a, b in zip(ev.batches, local.batches):
        assert np.array_equal(a.hessian, b.hessian) and a.index.dtype == np.int64


@pytest.mark.parametrize("n_bytes", [0, 8, 248, 256, 65528, 65536, 1 << 20, (1 << 20) + 8])
def test_service_dumps_is_wire_dumps_byte_for_byte(n_bytes):
    """`service.http.binary.dumps` writes small documents with one msgpack call, large ones with `wire.dumps`:
    either way the bytes are `wire.dumps`' (bin 8/16/32 headers at 255/65535, ints, floats, nesting)."""
    from jointlimits.service.http import binary

    rng = np.random.default_rng(n_bytes)
    doc = {"kind": "evaluation", "id": -(2**40), "total_energy": float(rng.normal()),
           "batches": [{"constitution_uid": 670, "index": np.arange(3), "x": rng.normal(size=n_bytes // 8),
                        "hessian": rng.normal(size=(0, 24, 24)), "energy": np.float64(1.5)}, {"shape": [2, None, True]}],
           "assembled": {"rows": np.arange(4, dtype=np.int32)}}
    expected = wire.dumps(binary._pack(doc, []))
    assert binary.dumps(doc) == expected
    assert wire.loads(expected)["batches"][0]["x"]["data"] == doc["batches"][0]["x"].tobytes()
