"""Content negotiation: `Content-Type` picks the request decoder, `Accept` the response encoder."""

from __future__ import annotations

from jointlimits.schemas.binary import MEDIA_TYPES as BINARY_TYPES
from jointlimits.service.core import Fault
from jointlimits.service.http import binary, convert
from jointlimits.service.http.errors import HttpError

JSON, BINARY = convert.MEDIA_TYPE, binary.MEDIA_TYPE
SUPPORTED = f"{JSON} or {BINARY}"


def _media_type(value: str) -> str:
    return value.split(";", 1)[0].strip().lower()


def request_type(content_type: str | None) -> str:
    """`JSON` or `BINARY`; no header at all is read as JSON, as FastAPI does. Else 415."""
    t = _media_type(content_type or JSON)
    if t == JSON or t.endswith("+json"):
        return JSON
    if t in BINARY_TYPES:
        return BINARY
    raise HttpError(
        415,
        [Fault(("header", "content-type"), f"unsupported Content-Type {t!r}; send {SUPPORTED}", "media_type")],
    )


def response_type(accept: str | None, requested: str) -> str:
    """The acceptable type with the highest q; ties and a missing header answer in the request's encoding."""
    if not accept or not accept.strip():
        return requested
    quality = {JSON: 0.0, BINARY: 0.0}
    for part in accept.split(","):
        media, *params = part.split(";")
        t = _media_type(media)
        q = _quality(params)
        for candidate, aliases in ((JSON, {JSON}), (BINARY, BINARY_TYPES)):
            if t in aliases or t in ("*/*", "application/*"):
                quality[candidate] = max(quality[candidate], q)
    best = max(quality.values())
    if best <= 0.0:
        raise HttpError(
            406, [Fault(("header", "accept"), f"cannot answer in {accept!r}; accept {SUPPORTED}", "not_acceptable")]
        )
    return requested if quality[requested] == best else max(quality, key=quality.__getitem__)


def _quality(params: list[str]) -> float:
    for p in params:
        name, _, value = p.partition("=")
        if name.strip().lower() == "q":
            try:
                q = float(value)
            except ValueError:
                return 0.0
            return q if 0.0 <= q <= 1.0 else 0.0
    return 1.0
