"""Build a `Request` from a scene: bodies' poses and joints with their edges and limits.

A pose is a body's transform, given as any of: a 4 x 4 homogeneous matrix `[[A, p], [0, 1]]`,
a pair `(p (3,), A (3, 3))`, or the 12 DOFs `q = [p, A row 0, A row 1, A row 2]`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Union

import numpy as np
from numpy.typing import ArrayLike

from client.model import PRISMATIC_LIMIT, REVOLUTE_LIMIT, Joint, JointBatch, Request
from schemas import OUTPUTS
from schemas.constitutions import STRENGTH_DEFAULT

Pose = Union[ArrayLike, tuple[ArrayLike, ArrayLike]]


def dofs(pose: Pose) -> np.ndarray:
    """The 12 DOFs (12,) of one pose."""
    if isinstance(pose, tuple) and len(pose) == 2:
        p, A = (np.asarray(v, dtype=np.float64) for v in pose)
        return np.concatenate([p.reshape(3), A.reshape(9)])
    a = np.asarray(pose, dtype=np.float64)
    if a.shape == (4, 4):
        return np.concatenate([a[:3, 3], a[:3, :3].reshape(9)])
    if a.shape == (12,):
        return a.copy()
    raise ValueError(f"a pose is a 4x4 transform, a (p, A) pair or 12 DOFs, got shape {a.shape}")


class Scene:
    """Collects bodies and joint limits; `request()` assembles the arrays of the wire.

    >>> scene = Scene()
    >>> a = scene.add_body(np.eye(4))
    >>> b = scene.add_body(turned, ref=np.eye(4))       # current pose, and the pose the joint was built at
    >>> j = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5, strength=100)
    >>> result = client.evaluate(scene.request())
    >>> result.joint(j).hessian                           # (24, 24) in the DOFs [q_a, q_b]

    A joint given in the bodies' own coordinates, as a libuipc scene holds it (CONTRACT.md v1.2):

    >>> k = scene.add_revolute_limit(a, b, lower=-0.5, upper=0.5, local_edge=[[l0, l1], [r0, r1]], origin="absolute")
    """

    def __init__(self) -> None:
        self._q: list[np.ndarray] = []
        self._q_prev: list[np.ndarray] = []
        self._q_ref: list[np.ndarray] = []
        # One batch per (constitution, "edges" or "local_edges", origin), in the order first used.
        self._joints: dict[tuple[int, str, str], list[tuple]] = {}

    def add_body(self, pose: Pose, *, prev: Pose | None = None, ref: Pose | None = None) -> int:
        """A body at `pose` now; `prev` (last time step) defaults to `ref`, `ref` (when the joints
        were built) to `pose`. Returns its row, for joints to refer to."""
        q = dofs(pose)
        q_ref = dofs(ref) if ref is not None else q
        self._q.append(q)
        self._q_ref.append(q_ref)
        self._q_prev.append(dofs(prev) if prev is not None else q_ref)
        return len(self._q) - 1

    def add_revolute_limit(
        self,
        i: int,
        j: int,
        p0: ArrayLike | None = None,
        p1: ArrayLike | None = None,
        lower: float | None = None,
        upper: float | None = None,
        strength: float = STRENGTH_DEFAULT,
        *,
        offset: float = 0.0,
        local_edge: ArrayLike | None = None,
        origin: str = "q_ref",
    ) -> Joint:
        """#670 on the revolute joint of bodies `i`, `j` about the edge `p0 -> p1` (world, at ref); angles in rad.
        Or, instead of `p0`, `p1`, `local_edge` `[[l0, l1], [r0, r1]]`: the edge in body i's and body j's own
        coordinates (v1.2). `origin` "absolute" measures x from the reference engine's zero (v1.2).
        `offset` is the spec's `init_angle`: the reported coordinate is x + offset, which `lower` and
        `upper` bound. Returns the joint's handle: its row in its batch, for `result.joint(handle)`."""
        return self._add(REVOLUTE_LIMIT, i, j, p0, p1, local_edge, origin, lower, upper, strength, offset)

    def add_prismatic_limit(
        self,
        i: int,
        j: int,
        p0: ArrayLike | None = None,
        p1: ArrayLike | None = None,
        lower: float | None = None,
        upper: float | None = None,
        strength: float = STRENGTH_DEFAULT,
        *,
        offset: float = 0.0,
        local_edge: ArrayLike | None = None,
        origin: str = "q_ref",
    ) -> Joint:
        """#669 on the prismatic joint of bodies `i`, `j` sliding along `p0 -> p1`, or along `local_edge`
        (anchors `l0` on body i, `r0` on body j); `offset` is the spec's `init_distance` (as for
        `add_revolute_limit`). Returns its handle (its row in its batch)."""
        return self._add(PRISMATIC_LIMIT, i, j, p0, p1, local_edge, origin, lower, upper, strength, offset)

    def _add(
        self, uid: int, i: int, j: int, p0: ArrayLike | None, p1: ArrayLike | None, local_edge: ArrayLike | None,
        origin: str, lower: float | None, upper: float | None, *rest: float,
    ) -> Joint:
        if lower is None or upper is None:
            raise TypeError("a joint limit needs lower and upper")
        if (local_edge is None) == (p0 is None or p1 is None):
            raise TypeError("give the joint's edge either as p0, p1 (world, at ref) or as local_edge, not both")
        if local_edge is None:
            kind, edge = "edges", np.stack([np.asarray(p, float).reshape(3) for p in (p0, p1)])
        else:
            kind, edge = "local_edges", np.asarray(local_edge, float).reshape(2, 2, 3)
        key = (uid, kind, origin)
        rows = self._joints.setdefault(key, [])
        rows.append(((int(i), int(j)), edge, lower, upper, *rest))
        return Joint(len(rows) - 1, uid, list(self._joints).index(key))

    def request(
        self, outputs: Sequence[str] = OUTPUTS, hessian_mode: str = "exact", active_only: bool = False,
        layout: str = "joints",
    ) -> Request:
        """The request: one batch per constitution, in the order first used; bodies in the order added.

        `layout="bodies"` asks for the gradient and Hessian summed per body (`Evaluation.assembled`)."""
        batches = []
        for (uid, kind, origin), rows in self._joints.items():
            ids, edges, lower, upper, strength, offset = zip(*rows)
            # v1.1's offsets only where one is set: a scene without them makes a v1 request.
            off = offset if any(o != 0.0 for o in offset) else None
            geometry = {kind: np.stack(edges)}
            batches.append(JointBatch.of(uid, ids, geometry.pop("edges", None), lower, upper, strength, offset=off,
                                         origin=origin, **geometry))
        stack = lambda rows: np.array(rows, dtype=np.float64).reshape(-1, 12)  # noqa: E731
        return Request(
            q=stack(self._q),
            q_prev=stack(self._q_prev),
            q_ref=stack(self._q_ref),
            batches=batches,
            outputs=tuple(outputs),
            hessian_mode=hessian_mode,
            active_only=active_only,
            layout=layout,
        )


def request_from_arrays(
    q: ArrayLike,
    joints: Sequence[JointBatch],
    *,
    q_prev: ArrayLike | None = None,
    q_ref: ArrayLike | None = None,
    outputs: Sequence[str] = OUTPUTS,
    hessian_mode: str = "exact",
    active_only: bool = False,
    layout: str = "joints",
) -> Request:
    """The vectorised builder: bodies' DOFs (B, 12) (`q_ref` defaults to `q`, `q_prev` to `q_ref`) and
    batches made with `JointBatch.of(uid, body_ids, edges, lower, upper, strength)`; `layout` as in `Scene.request`."""
    q = np.asarray(q, dtype=np.float64)
    q_ref = q if q_ref is None else np.asarray(q_ref, dtype=np.float64)
    q_prev = q_ref if q_prev is None else np.asarray(q_prev, dtype=np.float64)
    return Request(q, q_prev, q_ref, list(joints), tuple(outputs), hessian_mode, active_only, layout)
