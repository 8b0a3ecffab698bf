"""Python SDK of the joint-limit constitution service.

    from jointlimits.client import Client, LocalClient, Scene
    scene = Scene(); ...; result = Client("http://127.0.0.1:8000").evaluate(scene.request())

`Client` (sync) and `AsyncClient` speak HTTP (binary by default); `LocalClient` calls the
core in-process with the same API. Server faults raise `ServiceError` / `InvalidInput`
(`Busy`: a busy 503 still busy after the retries).
`client.session(request)` on any of the three keeps the scene prepared (a WebSocket session,
or in-process) for a solver loop: `evaluate(q)`, `commit(q)`, `update(...)`; a lost connection
resumes from the last commit (with `resume=False` it raises `SessionClosed`, and `reopen()` does it).
`Robot.load("arm.urdf")` reads a URDF (the `robot` extra): `robot.request(q)` poses it by its joint vector.
"""

from jointlimits.client.aio import AsyncClient
from jointlimits.client.errors import Busy, Fault, InvalidInput, ServiceError, TooLarge, Unreachable, WrongURL
from jointlimits.client.local import LocalClient
from jointlimits.client.model import PRISMATIC_LIMIT, REVOLUTE_LIMIT, BatchResult, Evaluation, Joint, JointBatch
from jointlimits.client.model import JointResult, Request
from jointlimits.client.robot import Reading, Robot
from jointlimits.client.scene import Scene, dofs, request_from_arrays
from jointlimits.client.session import SessionClosed
from jointlimits.client.sync import Client

__all__ = [
    "PRISMATIC_LIMIT", "REVOLUTE_LIMIT", "AsyncClient", "BatchResult", "Busy", "Client", "Evaluation", "Fault",
    "InvalidInput", "Joint", "JointBatch", "JointResult", "LocalClient", "Reading", "Request", "Robot", "Scene",
    "ServiceError", "SessionClosed", "TooLarge", "Unreachable", "WrongURL", "dofs", "request_from_arrays",
]
