"""Messages of the session protocol (`/v1/sessions`), shared by the service and the client; no numerics.

docs/sessions.md, "The protocol, byte by byte", is its reference: the opening message is `POST /v1/evaluate`'s
body, then each message is a small map whose `kind` (below) says what it asks, answered in its own encoding; a
fault is a reply `{"kind": "error", "status", "detail"}` and leaves the session as it was.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, FailFast, Field, TypeAdapter

from jointlimits.schemas.evaluate import Dof, EvaluateRequest, HessianMode, Int64, Output, Real

PATH = "/v1/sessions"

# Kinds of messages, client to server and server to client.
EVALUATE, COMMIT, UPDATE, CLOSE = "evaluate", "commit", "update", "close"
OPENED, EVALUATION, COMMITTED, UPDATED, ERROR = "opened", "evaluation", "committed", "updated", "error"
UPDATABLE = ("lower", "upper", "strength", "offset")
"""Per-joint fields an `update` may change (one entry per index)."""

# WebSocket close codes (RFC 6455 section 7.4; 4000-4999 are the application's: 4000 + the HTTP status
# the same refusal would get).
NORMAL = 1000  # the client sent `close` (or closed itself)
GOING_AWAY = 1001  # the server is shutting down (uvicorn's)
SERVICE_RESTART = 1012  # the server is restarting (`jointlimits serve` after SIGTERM): reopen, another one answers
MESSAGE_TOO_BIG = 1009  # a message over the frame limit (uvicorn's own limit closes with it too)
INTERNAL_ERROR = 1011  # a server failure (a bug: never for any input)
TRY_AGAIN_LATER = 1013  # the worker's upload budget is full (service/http/timeouts.py): reopen later, as after 4429
IDLE_TIMEOUT = 4408  # no message for the idle time
SCENE_TOO_LARGE = 4413  # the opening scene has more joints than the limit
TOO_MANY_SESSIONS = 4429  # this worker holds its maximum number of sessions

Id = Union[Int64, Annotated[str, Field(max_length=128)]]


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid")
    id: Id | None = None


class OpeningRequest(EvaluateRequest):
    """The opening message: `POST /v1/evaluate`'s body, plus an optional `id` that the `opened` reply repeats."""

    id: Id | None = None


# An optional field is absent (the session's default, or unchanged), never null: a null is refused, as in a
# request (`Field(None)`: None only as the default, which pydantic does not validate).
# FailFast: a list's first bad item is named, as in a request (and by the service).
class EvaluateMessage(_Message):
    kind: Literal["evaluate"]
    q: Annotated[list[Dof], FailFast()]
    outputs: Annotated[list[Output], Field(min_length=1), FailFast()] = Field(None)
    hessian_mode: HessianMode = Field(None)
    active_only: Annotated[bool, Field(strict=True)] = Field(None)


class CommitMessage(_Message):
    kind: Literal["commit"]
    q: Annotated[list[Dof], FailFast()]


class UpdateMessage(_Message):
    kind: Literal["update"]
    batch: Int64
    index: Annotated[list[Int64], FailFast()]
    lower: Annotated[list[Real], FailFast()] = Field(None)
    upper: Annotated[list[Real], FailFast()] = Field(None)
    strength: Annotated[list[Real], FailFast()] = Field(None)
    offset: Annotated[list[Real], FailFast()] = Field(None)


class CloseMessage(_Message):
    kind: Literal["close"]


ClientMessage = Annotated[
    Union[EvaluateMessage, CommitMessage, UpdateMessage, CloseMessage], Field(discriminator="kind")
]
CLIENT_MESSAGE = TypeAdapter(ClientMessage)
"""Parses one JSON client message (after the opening one)."""

# The keys of each kind in a msgpack message (True: required), for the binary reader: the models' own fields.
KEYS: dict[str, dict[str, bool]] = {
    m.model_fields["kind"].annotation.__args__[0]: {k: f.is_required() for k, f in m.model_fields.items()}
    for m in (EvaluateMessage, CommitMessage, UpdateMessage, CloseMessage)
}
