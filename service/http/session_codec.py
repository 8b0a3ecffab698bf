"""Session messages (schemas/session.py): frames <-> core arguments and answers. No numerics.

The opening message is decoded by the HTTP decoders themselves (`convert.decode` for JSON,
`binary.decode` for msgpack); a later message is parsed once by the same parsers and checked by
the one validator (`document.Checker.message`). A reply is encoded in the encoding of the message it answers.
"""

from __future__ import annotations

from typing import Any

from jointlimits.schemas import session as proto
from jointlimits.service.core import Evaluation, Fault, InputError
from jointlimits.service.core.assembled import check_layout
from jointlimits.service.core.validate import check_bodies, check_options, raise_if
from jointlimits.service.http import binary, convert, document, limits
from jointlimits.service.http.document import NOT_OPEN, Message  # noqa: F401 (the session's names)
from jointlimits.service.http.errors import HttpError, render

Frame = bytes | str


def decode_open(frame: Frame, max_values: int, max_batches: int) -> dict[str, Any]:
    """Keyword arguments of the core for the opening document, plus its `id` (under "id", None when absent);
    `InputError` (422) or `HttpError` (413: its JSON values or its batches, counted before they are parsed, as
    in a request), carrying the document's readable `id` (`message_id`)."""
    checker = document.Checker(binary=isinstance(frame, bytes))
    try:
        if isinstance(frame, str):
            kwargs = convert.decode(frame.encode(), max_values, max_batches, opening=True, checker=checker)
        else:
            kwargs = binary.decode(frame, max_batches, opening=True, checker=checker)
        # The options become the session's defaults: checked now; `q` is part of the document, checked as
        # POST /v1/evaluate checks it (the scene is prepared at q_prev).
        raise_if(check_options(kwargs["outputs"], kwargs["hessian_mode"]) + check_layout(kwargs["layout"])
                 + check_bodies(kwargs["bodies"]))
        return kwargs
    except (InputError, HttpError) as e:
        # A later kind of message sent first: one fault that says so, not the opening document's five.
        if isinstance(e, InputError) and any(f.loc == ("kind",) and f.type == "extra_forbidden" for f in e.faults):
            e = InputError([Fault(("kind",), NOT_OPEN, "session_not_open")])
        raise with_id(e, checker.message_id) from None


def decode(frame: Frame, max_values: int) -> Message:
    """A later message; `InputError` naming the key at fault, or `HttpError` (413) for a JSON text of more
    values than `max_values` (before its parse), carrying the message's readable `id`."""
    checker = document.Checker(binary=isinstance(frame, bytes))
    try:
        if isinstance(frame, str):
            text = frame.encode()  # counts are faster on bytes than on str
            limits.check_json(text, max_values)
            doc = convert.load(text)
            checker.booleans = convert.booleans(text)
        else:
            doc = binary.unpack(frame, checker, message=True)
        return checker.message(doc)
    except (InputError, HttpError) as e:
        raise with_id(e, checker.message_id) from None


def with_id(e: Exception, id: int | str | None) -> Exception:
    """`e`, carrying the `id` its fault reply repeats (`message_id`)."""
    e.id = id  # type: ignore[attr-defined]
    return e


def message_id(e: Exception) -> int | str | None:
    """The `id` of a message that could not be decoded, if it has a readable one (its fault reply repeats it)."""
    return getattr(e, "id", None)


# ------------------------------------------------------------------ replies


def encode(doc: dict[str, Any], binary_frame: bool) -> Frame:
    """A reply in the encoding of the message it answers: arrays as array maps (msgpack) or lists of shortest
    round-trip floats (JSON), written as `POST /v1/evaluate`'s answers are."""
    return binary.dumps(doc) if binary_frame else convert.dumps(doc).decode()


def encode_evaluation(ev: Evaluation, binary_frame: bool, id: int | str | None) -> Frame:
    """`POST /v1/evaluate`'s answer document with `kind` (and `id`) in front."""
    head = {"kind": proto.EVALUATION} if id is None else {"kind": proto.EVALUATION, "id": id}
    return encode({**head, **convert.to_wire(ev)}, binary_frame)


def at_message_q(e: InputError) -> InputError:
    """The core names a bad `q` as in a request (`("bodies", "q", i)`); in a session message it is `("q", i)`."""
    return InputError([Fault(f.loc[1:], f.msg, f.type) if f.loc[:2] == ("bodies", "q") else f for f in e.faults])


def error(exc: InputError | HttpError, id: int | str | None) -> dict[str, Any]:
    """A fault reply: HTTP's 4xx body (`detail`, every `loc` starting with "body") with its `status`."""
    # Rendered as HTTP's (cut, JSON-safe): a key the client sent is echoed as POST echoes it, never whole.
    http = isinstance(exc, HttpError)
    status, detail = (exc.status, render(exc.faults)) if http else (422, render(exc.faults, ("body",)))
    doc: dict[str, Any] = {"kind": proto.ERROR, "status": status, **detail}
    if id is not None:
        doc["id"] = id
    return doc
