"""`/v1/sessions`: a prepared scene per WebSocket connection (docs/sessions.md, "Sessions").

Parse a frame, call the prepared scene, encode the reply: nothing else. The opening message is decoded by the
HTTP decoders themselves, a later one parsed once and checked by the one validator (`document.Checker.message`);
a reply is written by the same encoders, in the encoding of the message it answers. The state (the prepared scene
with its `q_prev` and committed coordinates) lives with the connection, so any worker of any pod can hold a session.
Bounds: sessions per worker, frame bytes, idle seconds, scene joints (+ `limits.admit`), the in-flight budget.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, TypeVar

from fastapi import APIRouter, WebSocket
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect

from jointlimits.schemas import session as proto
from jointlimits.service import sizing
from jointlimits.service.core import Evaluation, Fault, InputError
from jointlimits.service.core.prepared import PreparedScene, prepare
from jointlimits.service.core.validate import check_bodies, raise_if
from jointlimits.service.http import binary, budget, convert, document, limits, routes
from jointlimits.service.http.budget import Reservation
from jointlimits.service.http.document import NOT_OPEN, Message
from jointlimits.service.http.errors import HttpError, render
from jointlimits.service.http.limits import admit
from jointlimits.service.http.timeouts import DRAIN, frame_limit
from jointlimits.service.observability import ACCESS_LOGGER, Metrics, peer
from jointlimits.service.settings import Settings

router = APIRouter()
log = logging.getLogger(ACCESS_LOGGER)
T = TypeVar("T")
Frame = bytes | str

# How long the session waits for its close frame to be sent (behind replies the client does not read) before it
# ends; the connection itself is dropped by the protocol's write timeout (JOINTLIMITS_WRITE_TIMEOUT).
CLOSE_SECONDS = 5.0

INLINE_JOINTS = 256
"""Scenes up to this many joints (a millisecond or so of work) are evaluated on the event loop: the hop to a
worker thread and back costs tens of microseconds on an idle machine and milliseconds on a loaded one
(docs/performance.md, "Sessions and prepared scenes"). Larger ones run in a worker thread, so that one large session does
not hold up the replies of the worker's other sessions."""

DISCONNECT_REASONS = {
    proto.NORMAL: "client",
    proto.MESSAGE_TOO_BIG: "frame_too_large",  # the server's own limit (service/http/timeouts.py)
    proto.TRY_AGAIN_LATER: "uploads_full",  # the message's bytes did not fit in the worker's upload budget
    1007: "invalid_utf8",
    1002: "protocol_error",
    proto.SERVICE_RESTART: "shutdown",
    1008: "slow_message",  # a message not all received within JOINTLIMITS_BODY_TIMEOUT
}
"""The metric's `reason` of a connection the server layer ended (any other code: "disconnect")."""


class Closing(Exception):
    """End the session with this WebSocket close code (schemas/session.py) and reason."""

    def __init__(self, code: int, reason: str, metric: str) -> None:
        self.code, self.reason, self.metric = code, reason, metric
        super().__init__(reason)


@dataclass
class Session:
    """One connection's state: the prepared scene (None until opened), the evaluate options of the opening
    document, and its weight in the worker's `session_joints` (joints, bodies at 4/3: `sizing.session_weight`)."""

    scene: PreparedScene | None = None
    defaults: dict[str, Any] | None = None
    joints: int = 0
    weight: int = 0
    costs: dict[tuple[frozenset[str], bool], int] = field(default_factory=dict)  # an evaluate's admitted cost


@router.websocket(proto.PATH)
async def sessions(websocket: WebSocket) -> None:
    state = websocket.app.state
    settings: Settings = state.settings
    limit = frame_limit(websocket, settings.max_frame_bytes)  # the server's own may be lower: report the one in force
    if limit != settings.max_frame_bytes:
        settings = replace(settings, max_frame_bytes=limit)
    metrics: Metrics = state.metrics
    if state.draining:  # after SIGTERM: a session opened here would be closed within the delay
        return await websocket.send_denial_response(routes.draining(settings))
    await websocket.accept()
    open_now = getattr(state, "open_sessions", 0)
    if open_now >= settings.max_sessions:
        metrics.sessions.labels("too_many_sessions").inc()
        n = settings.max_sessions
        reason = f"this worker holds its maximum of {n} session{'' if n == 1 else 's'}; retry later"
        return await websocket.close(proto.TOO_MANY_SESSIONS, reason)
    state.open_sessions = open_now + 1
    metrics.sessions_open.inc()
    started, reason, code = time.perf_counter(), "error", proto.INTERNAL_ERROR
    session = Session()
    reservations: list[Reservation] = []  # an evaluation's share of the in-flight budget, until its reply is sent
    try:
        await _messages(websocket, settings, metrics, session, reservations)
        reason, code = "client", proto.NORMAL
    except Closing as c:
        reason, code = c.metric, c.code
        await _close(websocket, c.code, c.reason)
    except WebSocketDisconnect as d:
        reason, code = DISCONNECT_REASONS.get(d.code, "disconnect"), d.code
    except asyncio.CancelledError:
        reason, code = "shutdown", proto.GOING_AWAY
        raise
    except Exception:
        logging.getLogger("jointlimits").exception("session failed")
        await _close(websocket, proto.INTERNAL_ERROR, "internal error")
    finally:
        for r in reservations:
            r.release()
        state.open_sessions -= 1
        _reserve(state, session, 0, settings.max_session_joints)  # its scene is gone
        metrics.sessions_open.dec()
        metrics.sessions.labels(reason).inc()
        if log.isEnabledFor(logging.INFO):
            fields = {"path": proto.PATH, "reason": reason, "close_code": code,
                      "duration_s": round(time.perf_counter() - started, 3), "client": peer(websocket.client),
                      "pid": os.getpid()}
            log.info("session", extra={"fields": fields})


async def _messages(websocket: WebSocket, settings: Settings, metrics: Metrics, session: Session,
                    reservations: list[Reservation]) -> None:
    """Open a scene from the first message that is a valid scene, then answer messages until `close`."""
    state = websocket.app.state
    drain = websocket.scope.get("extensions", {}).get(DRAIN)
    while True:
        if drain is not None:
            # One reply in the write buffer at most: the next message is read once the last reply has left (or the
            # connection is dropped after JOINTLIMITS_WRITE_TIMEOUT), so a session that does not read holds one.
            await drain.wait()
        frame = await _receive(websocket, settings)
        t0 = time.perf_counter()
        binary_frame = isinstance(frame, bytes)
        kind, outcome, mid = "open" if session.scene is None else "invalid", "ok", None
        try:
            if session.scene is None:
                # Preparing a scene takes what a request of its size may take: a share of the in-flight budget
                # (bounded from the message's size), until the reply is sent.
                cost = sizing.cost_before_body(len(frame), binary_frame, binary_frame, settings)  # JSON text: ASCII
                reservations.append(await state.in_flight.acquire(cost, settings.queue_timeout))
                reply = await run_in_threadpool(_open, frame, settings, state, session)
            else:
                message: Message = decode(frame, settings.max_json_values)
                kind, mid = message.kind, message.id
                if kind == proto.CLOSE:
                    metrics.session_messages.labels(kind, outcome).inc()
                    return await websocket.close(proto.NORMAL, "closed by the client")
                reply = await _answer(session, message, binary_frame, settings, state, reservations)
        except (InputError, HttpError) as e:
            outcome = "fault"
            reply = encode(error(e), binary_frame, getattr(e, "id", None) if mid is None else mid)
            if kind == "open" and isinstance(e, HttpError) and e.status == 413:
                await _send(websocket, reply, settings)
                metrics.session_messages.labels(kind, outcome).inc()
                # The reason names the bound that is over (joints, values, batches, answer, session joints).
                raise Closing(proto.SCENE_TOO_LARGE, e.faults[0].msg, "scene_too_large")
        await _send(websocket, reply, settings)
        # Sent is not gone: the reply's bytes stay counted until the write buffer drains (its arrays are free now).
        budget.hold_until_drained(websocket.scope, reservations, len(reply))
        metrics.session_messages.labels(kind, outcome).inc()
        metrics.session_latency.labels(kind).observe(time.perf_counter() - t0)


async def _receive(websocket: WebSocket, settings: Settings) -> Frame:
    """The next message's payload; `Closing` on idle time or an oversized frame, `WebSocketDisconnect` when gone."""
    idle = settings.session_idle_seconds
    try:
        async with asyncio.timeout(idle):  # not `wait_for`: no task per message
            message = await websocket.receive()
    except TimeoutError:
        raise Closing(proto.IDLE_TIMEOUT, f"no message for {idle:g} s: session closed", "idle") from None
    if message["type"] == "websocket.disconnect":
        raise WebSocketDisconnect(message.get("code", 1000), message.get("reason"))
    frame = message.get("bytes")
    if frame is None:
        frame = message.get("text") or ""
        # UTF-8 takes at most 4 bytes per character: encode only when the count could matter.
        size = len(frame) if len(frame) * 4 <= settings.max_frame_bytes else len(frame.encode())
    else:
        size = len(frame)
    if size > settings.max_frame_bytes:
        msg = f"message of {size} bytes; this service accepts at most {settings.max_frame_bytes}"
        raise Closing(proto.MESSAGE_TOO_BIG, msg, "frame_too_large")
    return frame


async def _close(websocket: WebSocket, code: int, reason: str) -> None:
    """Close with `code`; a client already gone, or not reading, has nothing left to tell (the close frame
    waits behind unread data at most CLOSE_SECONDS; the protocol drops the connection). A reason holds 123 bytes."""
    try:
        await asyncio.wait_for(websocket.close(code, reason.encode()[:123].decode(errors="ignore")), CLOSE_SECONDS)
    except (RuntimeError, OSError, WebSocketDisconnect, asyncio.TimeoutError):
        pass


async def _send(websocket: WebSocket, reply: Frame, settings: Settings) -> None:
    """Send a reply; a client that reads nothing for the idle time (the server's send buffer stays full) is closed."""
    try:
        async with asyncio.timeout(settings.session_idle_seconds):
            await (websocket.send_bytes(reply) if isinstance(reply, bytes) else websocket.send_text(reply))
    except TimeoutError:
        msg = f"no reply read for {settings.session_idle_seconds:g} s: session closed"
        raise Closing(proto.IDLE_TIMEOUT, msg, "idle") from None


_RESERVING = threading.Lock()  # opens run in worker threads: the check and the count change together


def _reserve(state: Any, session: Session, joints: int, most: int, bodies: int = 0) -> None:
    """Count this connection's scene, `joints` and `bodies` at their weight (`sizing.session_weight`), in the
    worker's `session_joints` (413 past `most`)."""
    weight = sizing.session_weight(joints, bodies)
    with _RESERVING:
        others = getattr(state, "session_joints", 0) - session.weight
        if others + weight > most:
            what = f"{joints} joint{'' if joints == 1 else 's'}"
            if bodies:
                what += f" and {bodies} bod{'y' if bodies == 1 else 'ies'} (a body counts as 4/3 joint)"
            msg = (
                f"this scene's {what} would bring the sessions of this worker to {others + weight} joints; it holds "
                f"at most {most} (JOINTLIMITS_MAX_SESSION_JOINTS): retry later, or use POST /v1/evaluate"
            )
            heavier = ("body", "bodies") if weight - joints > joints else ("body", "batches")  # what weighs most
            raise HttpError(413, [Fault(heavier, msg, "too_large")])
        state.session_joints, session.weight = others + weight, weight


def _open(frame: Frame, settings: Settings, state: Any, session: Session) -> Frame:
    """Open the session's scene from its opening document (in a worker thread); the `opened` reply."""
    kwargs = decode(frame, settings.max_json_values, settings.max_batches, opening=True)
    batch_joints = [int(j.body_ids.shape[0]) for j in kwargs["batches"]]
    joints, bodies = sum(batch_joints), int(kwargs["bodies"].q.shape[0])
    try:
        admit(joints=batch_joints, outputs=kwargs["outputs"], binary_answer=isinstance(frame, bytes), settings=settings)
        _reserve(state, session, joints, settings.max_session_joints, bodies)  # everything the scene will hold
        try:
            scene = prepare(kwargs["bodies"], kwargs["batches"])
            coordinates = scene.coordinates()  # the reply's: an InputError where they overflow
        except BaseException:
            _reserve(state, session, 0, settings.max_session_joints)  # a refused scene holds nothing
            raise
    except (InputError, HttpError) as e:
        raise with_id(e, kwargs["id"])  # its fault repeats the opening's id, as its reply would
    # Every evaluate option of the opening document is the session's default; `layout` too, which a later
    # message cannot change (schemas/session.py has no such field): a solver opens with the layout it needs.
    session.scene, session.joints = scene, joints
    session.defaults = {k: kwargs[k] for k in ("outputs", "hessian_mode", "active_only", "layout")}
    opened = {"kind": proto.OPENED, "bodies": scene.n_bodies, "batch_sizes": list(scene.batch_sizes),
              "coordinates": coordinates,
              "limits": {"max_frame_bytes": settings.max_frame_bytes, "idle_seconds": settings.session_idle_seconds}}
    return encode(opened, isinstance(frame, bytes), kwargs["id"])


async def _answer(session: Session, m: Message, binary_frame: bool, settings: Settings, state: Any,
                  reservations: list[Reservation]) -> Frame:
    """The reply to `m`; an evaluation first takes its share of the worker's in-flight budget (as `POST
    /v1/evaluate` does: its core and its answer), appended to `reservations` (released once the reply is sent)."""
    scene = session.scene
    assert scene is not None and session.defaults is not None
    if m.kind == proto.EVALUATE:
        options = {**session.defaults, **m.options}
        # Admitted once per set of outputs (all the bound reads; at most 16 keys): the scene's joints are fixed.
        key = (frozenset(options["outputs"]), binary_frame)
        cost = session.costs.get(key)
        if cost is None:
            batch_sizes = list(scene.batch_sizes)
            admit(joints=batch_sizes, outputs=options["outputs"], binary_answer=binary_frame, settings=settings)
            cost = session.costs[key] = sizing.request_cost(0, None, batch_sizes, scene.n_bodies, options["outputs"],
                                                            binary_frame, settings)
        reservations.append(await state.in_flight.acquire(cost, settings.queue_timeout))
        ev = await _run(session, lambda: scene.evaluate(m.q, **options))
        return encode_evaluation(ev, binary_frame, m.id)
    if m.kind == proto.COMMIT:
        reply: dict[str, Any] = {"kind": proto.COMMITTED, "coordinates": await _run(session, lambda: scene.commit(m.q))}
    else:  # update
        await _run(session, lambda: scene.update(m.batch, m.index, **m.values))
        reply = {"kind": proto.UPDATED, "batch": m.batch, "joints": int(m.index.shape[0])}
        if "offset" in m.values:  # a new offset moves the batch's committed coordinates with it
            reply["coordinates"] = scene.coordinates([m.batch])[0]
    return encode(reply, binary_frame, m.id)


async def _run(session: Session, fn: Callable[[], T]) -> T:
    try:
        return fn() if session.joints <= INLINE_JOINTS else await run_in_threadpool(fn)
    except InputError as e:
        raise at_message_q(e) from None


# ------------------------------------------------------------------ messages: frames <-> the scene's arguments


def decode(frame: Frame, max_values: int, max_batches: int = 0, opening: bool = False) -> Any:
    """A later message (a `Message`), or with `opening` the core's keyword arguments for the opening document plus
    its `id` (under "id", None when absent); `InputError` (422) or `HttpError` (413: a JSON text's values, or the
    opening's batches, counted before they are parsed, as in a request), carrying the document's readable `id`."""
    checker = document.Checker(binary=isinstance(frame, bytes))
    try:
        if not opening:
            if isinstance(frame, bytes):
                return checker.message(binary.unpack(frame, checker, message=True))
            text = frame.encode()  # counts are faster on bytes than on str
            limits.check_json(text, max_values)
            checker.booleans = convert.booleans(text)
            return checker.message(convert.load(text))
        if isinstance(frame, bytes):
            kwargs = binary.decode(frame, max_batches, opening=True, checker=checker)
        else:
            kwargs = convert.decode(frame.encode(), max_values, max_batches, opening=True, checker=checker)
        # The options, the session's defaults, were checked with the document; `q` is part of it, checked as
        # POST /v1/evaluate checks it (the scene is prepared at q_prev).
        raise_if(check_bodies(kwargs["bodies"]))
        return kwargs
    except (InputError, HttpError) as e:
        # A later kind of message sent first: one fault that says so, not the opening document's five.
        later = isinstance(e, InputError) and any(f.loc == ("kind",) and f.type == "extra_forbidden" for f in e.faults)
        if opening and later:
            e = InputError([Fault(("kind",), NOT_OPEN, "session_not_open")])
        raise with_id(e, checker.message_id) from None


def with_id(e: Exception, id: int | str | None) -> Exception:
    """`e`, carrying the `id` its fault reply repeats (a document refused before its `id` was read has none)."""
    e.id = id  # type: ignore[attr-defined]
    return e


# ------------------------------------------------------------------ replies


def encode(doc: dict[str, Any], binary_frame: bool, id: int | str | None = None) -> Frame:
    """A reply in the encoding of the message it answers (with the message's `id` last, if it had one): arrays as
    array maps (msgpack) or lists of shortest round-trip floats (JSON), written as `POST /v1/evaluate`'s answers are."""
    if id is not None:
        doc["id"] = id
    return binary.dumps(doc) if binary_frame else convert.dumps(doc).decode()


def encode_evaluation(ev: Evaluation, binary_frame: bool, id: int | str | None) -> Frame:
    """`POST /v1/evaluate`'s answer document with `kind` (and `id`) in front."""
    head = {"kind": proto.EVALUATION} if id is None else {"kind": proto.EVALUATION, "id": id}
    return encode({**head, **convert.to_wire(ev)}, binary_frame)


def at_message_q(e: InputError) -> InputError:
    """The core names a bad `q` as in a request (`("bodies", "q", i)`); in a session message it is `("q", i)`."""
    return InputError([Fault(f.loc[1:], f.msg, f.type) if f.loc[:2] == ("bodies", "q") else f for f in e.faults])


def error(exc: InputError | HttpError) -> dict[str, Any]:
    """A fault reply: HTTP's 4xx body (`detail`, every `loc` starting with "body") with its `status`."""
    # Rendered as HTTP's (cut, JSON-safe): a key the client sent is echoed as POST echoes it, never whole.
    http = isinstance(exc, HttpError)
    status, detail = (exc.status, render(exc.faults)) if http else (422, render(exc.faults, ("body",)))
    return {"kind": proto.ERROR, "status": status, **detail}
