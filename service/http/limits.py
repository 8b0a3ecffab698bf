"""Request limits, each checked once, here: the bytes and time while a body streams in (`read_body`); a JSON text's
values and batches on its bytes, before its parse (`check_json`); a msgpack request's batches from its header
(`check_batches`); the joints and the answer's size once parsed, before any evaluation (`admit`).

Values and JSON batches are counted on the bytes because parsing is what they bound: a JSON value costs 24 (`0,`)
to 96 (`[],`) bytes of Python objects once parsed, so the largest body (256 MiB) of `0,` would take ~3 GB, of `{},`
~7 GB (2e6 empty batches take ~0.8 s to parse; their braces, one C count). Under the value bound a body holds at
most `max_json_values / 11` joints, so joints are counted once parsed.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from fastapi import Request

from jointlimits.service.core import Fault
from jointlimits.service.http.errors import HttpError
from jointlimits.service.http.errors import too_large as _too_large
from jointlimits.service.http.timeouts import CHUNK_BYTES, CHUNKS, MIN_CHUNKS, too_many_pieces
from jointlimits.schemas.answer import BATCH_OVERHEAD_BYTES, FLOATS_PER_JOINT, answer_bytes  # noqa: F401 (re-exported)
from jointlimits.service.settings import Settings

async def read_body(request: Request, max_bytes: int, timeout: float, take: Callable[[int], bool]) -> bytes | None:
    """The body, refused with 413 as soon as it is known to exceed `max_bytes` (by header or while streaming), with
    408 if it is not all received within `timeout` seconds (JOINTLIMITS_BODY_TIMEOUT: a slowloris body, closed).
    `take(n)` says whether to keep each chunk (the upload budget, `budget.receive`); once it says no, the rest is
    read and dropped (the client gets an answer, not a reset, and nothing is held) and the result is None."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > max_bytes:
        raise _too_large(("body",), f"request body is {int(declared)} bytes; this service accepts at most {max_bytes}")
    chunks: list[bytes] | None = []
    size = 0
    chunks_in = request.scope.get("extensions", {}).get(CHUNKS)  # counted by the connection layer (`jointlimits serve`)
    try:
        async with asyncio.timeout(timeout):
            async for chunk in request.stream():
                size += len(chunk)
                if size > max_bytes:
                    msg = f"request body exceeds {max_bytes} bytes, the most this service accepts"
                    raise _too_large(("body",), msg)
                if chunks_in is not None and too_many_pieces(chunks_in[0], size):
                    raise _too_large(("body",), f"request body arrived in {chunks_in[0]} pieces (chunks, or reads of "
                                     f"its bytes) for {size} bytes; this service reads {MIN_CHUNKS} pieces, then one "
                                     f"per {CHUNK_BYTES} bytes: send it in larger chunks or writes")
                if chunks is not None and take(len(chunk)):
                    chunks.append(chunk)
                else:
                    chunks = None  # refused: drain
    except TimeoutError:
        msg = f"request body not received within {timeout:g} s (JOINTLIMITS_BODY_TIMEOUT)"
        raise HttpError(408, [Fault(("body",), msg, "timeout")], headers={"Connection": "close"}) from None
    return None if chunks is None else b"".join(chunks)


def admit(*, joints: list[int], outputs: list[str] | tuple[str, ...], binary_answer: bool, settings: Settings) -> None:
    """413 for a parsed request (or a session's scene and options) whose joints (`joints`: per batch) or answer
    would cost more than this service's bounds, before any work, naming the bound, the figure and what to do."""
    n_joints = sum(joints)
    if n_joints > settings.max_joints:
        raise _too_large(
            ("body", "batches"),
            f"request has {n_joints} joint{'' if n_joints == 1 else 's'}; this service accepts at most {settings.max_joints} "
            "per request (split the batch; the Python SDK does it for you)",
        )
    size = answer_bytes(joints, outputs, binary_answer)
    if size > settings.max_answer_bytes:
        encoding = "msgpack" if binary_answer else "JSON"
        hint = "" if binary_answer else ", or ask for msgpack (Accept: application/msgpack, a third of JSON's bound)"
        raise _too_large(
            ("body", "outputs"),
            f"the answer to this request may reach {size} bytes in {encoding} ({n_joints} joints x "
            f"{', '.join(o for o in FLOATS_PER_JOINT if o in outputs or o == 'energy')}); this service answers "
            f"at most {settings.max_answer_bytes} bytes (JOINTLIMITS_MAX_ANSWER_BYTES): split the batch, "
            f"ask for fewer outputs{hint}. active_only does not lower this bound: it is checked before knowing "
            "which joints are active",
        )


def check_batches(n_batches: int, max_batches: int, counted_by: str = "") -> None:
    """413 for more batches than `max_batches`; `counted_by` says how an estimate made before parsing was made."""
    if n_batches > max_batches:
        has = f"has up to {n_batches} batches ({counted_by})" if counted_by else f"has {n_batches} batches"
        raise _too_large(
            ("body", "batches"),
            f"request {has}; this service accepts at most {max_batches} per request "
            "(JOINTLIMITS_MAX_BATCHES): merge batches of the same constitution, or split the request",
        )


def check_json(text: bytes, max_values: int, max_batches: int | None = None) -> int:
    """Refuse a JSON text whose parse would cost too much, before parsing it (C-speed counts); returns the bound
    on its values: its commas + 1 (every value but the last of each list or object is followed by a comma), or twice
    its lists and objects + 1, or 8 times its colons (keys) + 1, where more. Nested lists hold values no comma counts
    (1e6 `[[[[[[[[0]]]]]]]]` took a worker to 993 MiB and the GIL for 8-10 s): a list costs the parse 3 to 7 numbers,
    a key 1 to 4 lists (2e6 keys 2.3-2.7 s, 5.4 s in a list, which `convert.load` reads twice; 1e6 lists 0.7-1.2 s).
    A request has a list per 2 commas at most (`local_edges`), a dozen keys per batch: near the bound, its commas.

    `max_batches` (a request document): each batch is an object, so it has a `{` (the document and `bodies` have
    the two others; a `{` inside a string, which only a session opening's `id` may hold in a valid document,
    overcounts)."""
    braces = text.count(b"{")
    values = max(text.count(b","), 2 * (braces + text.count(b"[")), 8 * text.count(b":")) + 1
    if values > max_values:
        raise _too_large(
            ("body",),
            f"the JSON body holds up to {values} values (counted by its commas, brackets and keys); this service "
            f"parses at most {max_values} per JSON request (JOINTLIMITS_MAX_JSON_VALUES): send msgpack "
            "(Content-Type: application/msgpack, no per-value cost), or split the request",
        )
    if max_batches is not None:
        check_batches(braces - 2, max_batches, "counted by their braces")
    return values
