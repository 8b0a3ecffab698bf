"""Memory a worker needs at its limits, and a pod with several workers (README, "Sizing a pod").

An upper bound from the settings alone, with coefficients measured as the peak RSS
(`VmHWM`) of one worker serving the largest request of each kind (commands in the
README); each is rounded up. The terms of one request do not all peak at once, so the
bound is loose by up to ~1.6x at the defaults: a budget, not a prediction.
"""

from __future__ import annotations

from service.settings import Settings

MiB = 2**20

WORKER_BASE_BYTES = 96 * MiB
"""A worker after start-up, imports and first request (measured 65 MiB)."""
SUPERVISOR_BYTES = 64 * MiB
"""uvicorn's supervisor with several workers (it never imports the application; ~30 MiB)."""
JSON_BYTES_PER_VALUE = 96
"""A JSON body's parse, per value (Python objects, then arrays): measured 89 B at 8e6 values of `0`."""
BYTES_PER_JOINT = 1100
"""A msgpack joint: its 88 body bytes, their copy, the core's per-joint temporaries and its energy answer
(measured 1.03 KB: 1e6 joints, energy only, +1005 MiB)."""
BYTES_PER_BODY = 1500
"""A msgpack body row triple (288 bytes): body, copy, the body table and its polar factors
(measured 1.44 KB: 9.2e5 bodies, +1265 MiB)."""
MSGPACK_BYTES = {"joint": 8 * (2 + 6 + 3), "body": 3 * 12 * 8}
"""Request bytes of one joint and of one body in msgpack: a body of given size holds at most so many."""
SESSION_BYTES_PER_JOINT = 768
"""A joint of a WebSocket session's prepared scene, held for the connection's life (measured ~700 B:
67 MB for the bench's 1e5-joint scene)."""
ANSWER_FACTOR = 2.5
"""Peak over the answer's bound: the answer's arrays and the encoded message (measured <= 2.0 in
msgpack at the bound once the request's own cost is taken off; JSON answers reach their bound only
with the longest floats, and the arrays are then a third of it)."""


def request_bytes(s: Settings) -> int:
    """The costlier of the largest JSON body (its bytes and parse) and the largest msgpack body (bytes and core)."""
    json_body = s.max_body_bytes + JSON_BYTES_PER_VALUE * s.max_json_values
    # msgpack: joints cost more per request byte than bodies, so the worst body is as many joints as
    # allowed and bodies in the rest of its bytes.
    joints = min(s.max_joints, s.max_body_bytes // MSGPACK_BYTES["joint"])
    bodies = (s.max_body_bytes - joints * MSGPACK_BYTES["joint"]) // MSGPACK_BYTES["body"]
    return max(json_body, BYTES_PER_JOINT * joints + BYTES_PER_BODY * bodies)


def worker_bytes(s: Settings) -> int:
    """Memory one worker may reach on the costliest request its limits admit (then keeps, with keep_heap),
    beside the prepared scenes of its open sessions."""
    sessions = SESSION_BYTES_PER_JOINT * s.max_session_joints
    return WORKER_BASE_BYTES + request_bytes(s) + int(ANSWER_FACTOR * s.max_answer_bytes) + sessions


def pod_bytes(s: Settings, workers: int) -> int:
    """A pod running `jointlimits serve --workers N`: every worker at its peak at once, and the supervisor."""
    return workers * worker_bytes(s) + (SUPERVISOR_BYTES if workers > 1 else 0)
