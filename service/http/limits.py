"""Request size limits: 413 before a body is parsed (bytes while it streams in, joints from the bytes)."""

from __future__ import annotations

import re

from fastapi import Request

from service.core import Fault
from service.http.errors import HttpError

# A per-joint list of the JSON body: `"lower": [ ... ]`. Its commas bound its length from above.
_PER_JOINT_LIST = re.compile(rb'"(?:lower|upper|strength)"\s*:\s*\[([^\[\]]*)\]')


def _too_large(loc: tuple[str, ...], msg: str) -> HttpError:
    return HttpError(413, [Fault(loc, msg, "too_large")])


async def read_body(request: Request, max_bytes: int) -> bytes:
    """The body, refused with 413 as soon as it is known to exceed `max_bytes` (by header or while streaming)."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > max_bytes:
        raise _too_large(("body",), f"request body is {int(declared)} bytes; this service accepts at most {max_bytes}")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > max_bytes:
            raise _too_large(("body",), f"request body exceeds {max_bytes} bytes, the most this service accepts")
        chunks.append(chunk)
    return b"".join(chunks)


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
            f"request has {n_joints} joints; this service accepts at most {max_joints} per request "
            "(split the batch; the Python SDK does it for you)",
        )
