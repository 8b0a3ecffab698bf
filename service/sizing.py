"""Memory a worker needs at its limits, and a pod with several workers (docs/deployment.md, "Sizing a pod").

An upper bound from the settings alone, with coefficients measured as the peak RSS (`VmHWM`) of one worker serving
the largest request of each kind (commands in docs/deployment.md), each rounded up. The terms of one request do not
all peak at once, so the bound is loose by up to ~1.6x at the defaults: a budget, not a prediction.
"""

from __future__ import annotations

from collections.abc import Sequence

from jointlimits.schemas import OUTPUTS
from jointlimits.schemas.answer import answer_bytes
from jointlimits.service.settings import Settings

MiB = 2**20
WORKER_BASE_BYTES = 80 * MiB  # a worker after start-up, imports and first request (measured 65 MiB)
CONNECTION_BYTES = 16 * 2**10  # an idle connection (measured 14.9 KiB kept alive after a request, 7.6 KiB silent)
SUPERVISOR_BYTES = 64 * MiB  # uvicorn's supervisor with several workers (it never imports the application; ~30 MiB)
JSON_BYTES_PER_VALUE = 96  # a JSON body's parse, per value (objects, then arrays): measured 89 B at 8e6 `0`s
# A msgpack joint: its 88 body bytes, their copy, the core's per-joint temporaries and its energy answer
# (measured 1.03 KB: 1e6 joints, energy only, +1005 MiB).
BYTES_PER_JOINT = 1100
# A msgpack body row triple (288 bytes): body, copy, the body table and its polar factors (measured 1.44 KB:
# 9.2e5 bodies, +1265 MiB).
BYTES_PER_BODY = 1500
MSGPACK_BYTES = {"joint": 8 * (2 + 6 + 3), "body": 3 * 12 * 8}  # request bytes of one joint and of one body
JSON_BYTES_PER_VALUE_MIN = 2  # the shortest JSON value and its separator (`0,`): b bytes hold b / 2 + 1 values
JSON_VALUES_PER_JOINT = 11  # 2 body ids, 6 edge coordinates, lower, upper, strength
# A joint of a session's prepared scene, held for the connection's life (measured 496 B: 1e5 joints on 4 bodies).
SESSION_BYTES_PER_JOINT = 768
# A body of a session's prepared scene: its q, q_prev, q_ref rows (288 B) and what `prepare` adds per body (polar
# factors, frames: measured 609 B per body for a 1-joint scene of 2e5 bodies).
SESSION_BYTES_PER_BODY = 1024
# Peak over the answer's bound: its arrays and the encoded message (measured <= 2.0 in msgpack at the bound once
# the request's own cost is taken off; JSON answers reach their bound only with the longest floats).
ANSWER_FACTOR = 2.5
UPLOAD_FACTOR = 2  # a body being received is held twice at its end: its chunks and their joined copy
# The upload budget's least size: with small body limits, a burst of bodies being received (oversized ones among
# them, each held until it passes the limit) still leaves room for the others.
UPLOAD_FLOOR = 128 * MiB


def session_weight(joints: int, bodies: int) -> int:
    """What a session's scene counts against JOINTLIMITS_MAX_SESSION_JOINTS: its joints, and its bodies at their
    weight in joints (4/3, rounded up), so the bound stays `SESSION_BYTES_PER_JOINT x MAX_SESSION_JOINTS` bytes
    whatever the mix (a 1-joint scene of 2e5 bodies holds ~65 MB, not one joint's)."""
    return joints + -(-bodies * SESSION_BYTES_PER_BODY // SESSION_BYTES_PER_JOINT)


def _msgpack(body_bytes: int, s: Settings) -> tuple[int, int]:
    """The costliest msgpack body of this size and its joints: joints cost more per byte than bodies, so as many
    joints as allowed, bodies in the rest."""
    joints = min(s.max_joints, body_bytes // MSGPACK_BYTES["joint"])
    bodies = (body_bytes - joints * MSGPACK_BYTES["joint"]) // MSGPACK_BYTES["body"]
    return BYTES_PER_JOINT * joints + BYTES_PER_BODY * bodies, joints


def inflight_bytes(s: Settings) -> int:
    """The memory budget of a worker's requests in flight: the costliest request its limits admit (the largest JSON
    body, its bytes and parse, or the largest msgpack body, bytes and core) and its answer. Requests start only
    while their costs fit in it together (service/http/budget.py)."""
    request = max(s.max_body_bytes + JSON_BYTES_PER_VALUE * s.max_json_values, _msgpack(s.max_body_bytes, s)[0])
    return request + int(ANSWER_FACTOR * s.max_answer_bytes)


def upload_bytes(s: Settings) -> int:
    """The memory budget of the bodies a worker is receiving: one body at the limit, at least `UPLOAD_FLOOR`."""
    return max(UPLOAD_FACTOR * s.max_body_bytes, UPLOAD_FLOOR)


def worker_bytes(s: Settings) -> int:
    """Memory one worker may reach with its budgets full (then keeps, with keep_heap): its connections, the bodies
    it is receiving, its requests in flight, the prepared scenes of its open sessions."""
    sessions = SESSION_BYTES_PER_JOINT * s.max_session_joints
    return WORKER_BASE_BYTES + CONNECTION_BYTES * s.max_connections + upload_bytes(s) + inflight_bytes(s) + sessions


def cost_before_body(body_bytes: int, binary_request: bool, binary_answer: bool, s: Settings) -> int:
    """Memory a request of `body_bytes` bytes may take before it is parsed, by `inflight_bytes`' terms at this size
    (a JSON body's worst is its shortest values, `0,`), and its answer with every output. At most `inflight_bytes`."""
    b = min(body_bytes, s.max_body_bytes)
    if binary_request:
        request, joints = _msgpack(b, s)
    else:
        values = min(s.max_json_values, b // JSON_BYTES_PER_VALUE_MIN + 1)
        joints = min(s.max_joints, values // JSON_VALUES_PER_JOINT)
        request = b + JSON_BYTES_PER_VALUE * values
    return _with_answer(request, [joints], OUTPUTS, binary_answer, s)


def request_cost(body_bytes: int, json_values: int | None, batch_joints: Sequence[int], n_bodies: int,
                 outputs: Sequence[str], binary_answer: bool, s: Settings) -> int:
    """Memory of a parsed request by the same terms, from what it holds: its JSON values (None: a msgpack body),
    joints per batch, bodies and outputs. At most `inflight_bytes(s)`."""
    if json_values is None:
        request = BYTES_PER_JOINT * sum(batch_joints) + BYTES_PER_BODY * n_bodies
    else:
        request = body_bytes + JSON_BYTES_PER_VALUE * json_values
    return _with_answer(request, batch_joints, outputs, binary_answer, s)


def _with_answer(request: int, batch_joints: Sequence[int], outputs: Sequence[str], binary_answer: bool,
                 s: Settings) -> int:
    answer = min(s.max_answer_bytes, answer_bytes(batch_joints, outputs, binary_answer))
    return min(inflight_bytes(s), request + int(ANSWER_FACTOR * answer))


def pod_bytes(s: Settings, workers: int) -> int:
    """A pod running `jointlimits serve --workers N`: every worker at its peak at once, and the supervisor."""
    return workers * worker_bytes(s) + (SUPERVISOR_BYTES if workers > 1 else 0)
