"""Request limits: 413 before a body is parsed (bytes while it streams in, joints from the bytes), and
admission by cost (joints, batches, the answer's size) before any evaluation."""

from __future__ import annotations

import re
from collections.abc import Callable

from fastapi import Request

from jointlimits.service.core import Fault
from jointlimits.service.http.errors import HttpError
from jointlimits.schemas.answer import BATCH_OVERHEAD_BYTES, FLOATS_PER_JOINT, answer_bytes  # noqa: F401 (re-exported)
from jointlimits.service.settings import Settings

# A per-joint list of the JSON body: `"lower": [ ... ]`. Its commas bound its length from above.
_PER_JOINT_LIST = re.compile(rb'"(?:lower|upper|strength)"\s*:\s*\[([^\[\]]*)\]')


def _too_large(loc: tuple[str, ...], msg: str) -> HttpError:
    return HttpError(413, [Fault(loc, msg, "too_large")])


async def read_body(request: Request, max_bytes: int, take: Callable[[int], bool] | None = None) -> bytes | None:
    """The body, refused with 413 as soon as it is known to exceed `max_bytes` (by header or while streaming).

    `take(n)` is asked with each chunk's size as it arrives whether to keep it (the worker's upload
    budget, `budget.receive`); after a refusal the rest is read and dropped (the client gets an answer,
    not a reset connection, and nothing is held) and the result is None."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > max_bytes:
        raise _too_large(("body",), f"request body is {int(declared)} bytes; this service accepts at most {max_bytes}")
    chunks: list[bytes] | None = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > max_bytes:
            raise _too_large(("body",), f"request body exceeds {max_bytes} bytes, the most this service accepts")
        if chunks is not None and (take is None or take(len(chunk))):
            chunks.append(chunk)
        else:
            chunks = None  # refused: drain
    return None if chunks is None else b"".join(chunks)


def json_joints_upper_bound(body: bytes) -> int:
    """Joints in a JSON body, counted in its bytes without parsing it (C-speed regex and counts).

    Each batch counts as its longest per-joint list. Only an estimate for hostile
    bodies (a key spelt with escapes escapes it), so the exact count is checked again
    after parsing; for every well-formed body it is exact.
    """
    counts = [_list_length(body, m) for m in _PER_JOINT_LIST.finditer(body)]
    # Three equally long lists per well-formed batch; the longest list alone bounds a lopsided one.
    return max(max(counts, default=0), -(-sum(counts) // 3))


def _list_length(body: bytes, m: re.Match[bytes]) -> int:
    commas = body.count(b",", m.start(1), m.end(1))
    return commas + 1 if commas or m.group(1).strip() else 0


def check_joints(n_joints: int, max_joints: int) -> None:
    if n_joints > max_joints:
        raise _too_large(
            ("body", "batches"),
            f"request has {n_joints} joint{'' if n_joints == 1 else 's'}; this service accepts at most {max_joints} per request "
            "(split the batch; the Python SDK does it for you)",
        )


# ------------------------------------------------------------------ admission by cost, before any work


def admit(
    *,
    joints: int | list[int],
    batches: int,
    outputs: list[str] | tuple[str, ...],
    binary_answer: bool,
    settings: Settings,
) -> None:
    """Refuse with 413 a request that would cost more than this service's bounds, before any work.

    `joints`: joints per batch (a list) or their total alone (an int: then the answer is
    bounded as if they were all in one batch, which is what a single count can say).
    Raises `HttpError` (413) naming the bound, the figure and what to do.
    """
    per_batch = joints if isinstance(joints, list) else [joints]
    check_joints(sum(per_batch), settings.max_joints)
    check_batches(batches, settings.max_batches)
    size = answer_bytes(per_batch, outputs, binary_answer)
    if size > settings.max_answer_bytes:
        encoding = "msgpack" if binary_answer else "JSON"
        hint = "" if binary_answer else ", or ask for msgpack (Accept: application/msgpack, a third of JSON's bound)"
        raise _too_large(
            ("body", "outputs"),
            f"the answer to this request may reach {size} bytes in {encoding} ({sum(per_batch)} joints x "
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


def json_batches_upper_bound(body: bytes) -> int:
    """Batches of a valid JSON request, bounded from its bytes: each is an object, so it has a `{`
    (the document and `bodies` have the two others; a `{` inside a string only overcounts junk)."""
    return body.count(b"{") - 2


def check_json_values(body: bytes, max_values: int) -> int:
    """Refuse a JSON body whose parse would cost too much, before parsing it (one C-speed count).

    Parsing costs time (0.2-2.5 us, more under load) and memory (~60-90 bytes as Python objects) per value,
    whatever its length: `[0,0,...]` weighs 40 times its bytes, full-precision floats 3 times.
    Every value but the last of each list or object is followed by a comma, so `commas + 1`
    bounds the values from above for well-formed bodies. Returns that bound.
    """
    values = body.count(b",") + 1
    if values > max_values:
        raise _too_large(
            ("body",),
            f"the JSON body holds up to {values} values (counted by its commas); this service parses at most "
            f"{max_values} per JSON request (JOINTLIMITS_MAX_JSON_VALUES): send msgpack "
            "(Content-Type: application/msgpack, no per-value cost), or split the request",
        )
    return values
