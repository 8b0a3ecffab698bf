"""Build a `Request` from a scene: bodies' poses and joints with their edges and limits.

A pose is a body's transform, given as any of: a 4 x 4 homogeneous matrix `[[A, p], [0, 1]]`,
a pair `(p (3,), A (3, 3))`, or the 12 DOFs `q = [p, A row 0, A row 1, A row 2]`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Union

import numpy as np
from numpy.typing import ArrayLike

from jointlimits.client.model import PRISMATIC_LIMIT, REVOLUTE_LIMIT, Joint, JointBatch, Request, _array, invalid
from jointlimits.client.model import joint_key
from jointlimits.service.core import registry
from jointlimits.service.core.errors import Fault
from jointlimits.service.core.scene import Bodies, Joints
from jointlimits.service.core.validate import NOT_AN_INTEGER, ORIGINS, check_bodies, check_joints
from jointlimits.schemas import OUTPUTS
from jointlimits.schemas.constitutions import STRENGTH_DEFAULT

Pose = Union[ArrayLike, tuple[ArrayLike, ArrayLike]]


def transforms_to_q(T: ArrayLike) -> np.ndarray:
    """Transforms (I, 4, 4) as DOFs (I, 12), `[T[0:3, 3], T[0, :3], T[1, :3], T[2, :3]]` (libuipc's transform_to_q)."""
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    return np.concatenate([T[:, :3, 3], T[:, :3, :3].reshape(-1, 9)], axis=1)


def dofs(pose: Pose, loc: tuple[str | int, ...] = ("pose",), where: str = "dofs") -> np.ndarray:
    """The 12 DOFs (12,) of one pose; `InvalidInput` naming `loc` for anything else."""
    faults: list[Fault] = []
    if isinstance(pose, tuple) and len(pose) == 2:
        p, A = (_array(v, "pose", faults) for v in pose)
        if p is not None and A is not None and p.size == 3 and A.size == 9:
            return np.concatenate([p.reshape(3), A.reshape(9)])
        shapes = tuple(None if v is None else v.shape for v in (p, A))
        msg = f"a (p, A) pose is p (3,) and A (3, 3), got shapes {shapes}"
    else:
        a = _array(pose, "pose", faults)
        if a is not None and a.shape == (4, 4):
            return transforms_to_q(a)[0]
        if a is not None and a.shape == (12,):
            return a.astype(np.float64, copy=True)
        msg = f"a pose is a 4x4 transform, a (p, A) pair or 12 DOFs, got shape {None if a is None else a.shape}"
    faults = [Fault((*loc, *f.loc[1:]), f.msg, f.type) for f in faults] or [Fault(loc, msg)]
    raise invalid(faults, where)


class Scene:
    """Collects bodies and joint limits; `request()` assembles the arrays of the wire.

    >>> import numpy as np
    >>> from jointlimits import LocalClient, Scene
    >>> c, s, scene = np.cos(0.7), np.sin(0.7), Scene()
    >>> a = scene.add_body(np.eye(4))
    >>> b = scene.add_body(([0, 0, 0], [[c, -s, 0], [s, c, 0], [0, 0, 1]]), ref=np.eye(4))  # turned; `ref`: when built
    >>> j = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5, strength=100)
    >>> result = LocalClient().evaluate(scene.request())  # or a `Client(url)`'s
    >>> result.joint(j).hessian.shape                     # in the DOFs [q_a, q_b]
    (24, 24)

    A joint given in the bodies' own coordinates, as a libuipc scene holds it (CONTRACT.md v1.2): its edge's two
    points in body a's frame (`l0`, `l1`), then in body b's (`r0`, `r1`):

    >>> l0, l1, r0, r1 = [0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1]
    >>> k = scene.add_revolute_limit(a, b, lower=-0.5, upper=0.5, local_edge=[[l0, l1], [r0, r1]], origin="absolute")
    """

    def __init__(self) -> None:
        self._q: list[np.ndarray] = []
        self._q_prev: list[np.ndarray] = []
        self._q_ref: list[np.ndarray] = []
        # One batch per (constitution, "edges" or "local_edges", origin, whether `prev_coordinate` is
        # given), in the order first used: the wire's `prev_coordinate` is all of a batch's joints or none.
        self._joints: dict[tuple[int, str, str, bool], list[tuple]] = {}

    def add_body(self, pose: Pose, *, prev: Pose | None = None, ref: Pose | None = None) -> int:
        """A body at `pose` now; `prev` (last time step) defaults to `ref`, `ref` (when the joints
        were built) to `pose`. Returns its row, for joints to refer to."""
        row = len(self._q)
        q = dofs(pose, ("bodies", "q", row), "Scene.add_body")
        q_ref = dofs(ref, ("bodies", "q_ref", row), "Scene.add_body") if ref is not None else q
        q_prev = dofs(prev, ("bodies", "q_prev", row), "Scene.add_body") if prev is not None else q_ref
        self._q.append(q)
        self._q_ref.append(q_ref)
        self._q_prev.append(q_prev)
        return len(self._q) - 1

    def add_limit(self, uid: int, i: int, j: int, p0: ArrayLike | None = None, p1: ArrayLike | None = None,
                  lower: float | None = None, upper: float | None = None, strength: float = STRENGTH_DEFAULT, *,
                  offset: float = 0.0, local_edge: ArrayLike | None = None, origin: str = "q_ref",
                  prev_coordinate: float | None = None) -> Joint:
        """A limit of the constitution `uid` (any registered one, `LocalClient().constitutions()`) on the joint of
        bodies `i`, `j`, as `add_revolute_limit` describes; `prev_coordinate` for a stateful one only."""
        return self._add(uid, "Scene.add_limit", i, j, p0, p1, local_edge, origin, lower, upper, strength, offset,
                         prev=prev_coordinate)

    def add_revolute_limit(self, i: int, j: int, p0: ArrayLike | None = None, p1: ArrayLike | None = None,
                           lower: float | None = None, upper: float | None = None, strength: float = STRENGTH_DEFAULT,
                           *, offset: float = 0.0, local_edge: ArrayLike | None = None, origin: str = "q_ref",
                           prev_coordinate: float | None = None) -> Joint:
        """#670 on the revolute joint of bodies `i`, `j` about the edge `p0 -> p1` (world, at ref); angles in rad.
        Or, instead of `p0`, `p1`, `local_edge` `[[l0, l1], [r0, r1]]`: the edge in body i's and body j's own
        coordinates (v1.2). `origin` "absolute" measures x from the reference engine's zero (v1.2).
        `offset` is the spec's `init_angle`: the reported coordinate is x + offset, which `lower` and
        `upper` bound. `prev_coordinate` (v1.1) is the joint's known coordinate at the bodies' `prev`
        poses (the committed, unwrapped angle, any number of turns): then x = (prev_coordinate - offset) plus
        DeltaTheta(q, q_prev), exact past +-pi. Without it x = DeltaTheta(q_prev, q_ref) plus
        DeltaTheta(q, q_prev) (plus the engine's zero under "absolute"), each term wrapped into (-pi, pi]:
        a joint turned past +-pi from `ref` (with `prev` = `ref`) reads 2 pi off. Joints given it go into a
        batch of their own. Returns the joint's handle: its row in its batch, for `result.joint(handle)`."""
        return self._add(REVOLUTE_LIMIT, "Scene.add_revolute_limit", i, j, p0, p1, local_edge, origin, lower, upper,
                         strength, offset, prev=prev_coordinate)

    def add_prismatic_limit(self, i: int, j: int, p0: ArrayLike | None = None, p1: ArrayLike | None = None,
                            lower: float | None = None, upper: float | None = None,
                            strength: float = STRENGTH_DEFAULT, *, offset: float = 0.0,
                            local_edge: ArrayLike | None = None, origin: str = "q_ref") -> Joint:
        """#669 on the prismatic joint of bodies `i`, `j` sliding along `p0 -> p1`, or along `local_edge`
        (anchors `l0` on body i, `r0` on body j); `offset` is the spec's `init_distance` (as for
        `add_revolute_limit`). Returns its handle (its row in its batch)."""
        return self._add(PRISMATIC_LIMIT, "Scene.add_prismatic_limit", i, j, p0, p1, local_edge, origin, lower, upper,
                         strength, offset)

    def _add(self, uid: int, where: str, i: int, j: int, p0: ArrayLike | None, p1: ArrayLike | None,
             local_edge: ArrayLike | None, origin: str, lower: float | None, upper: float | None, *rest: float,
             prev: float | None = None) -> Joint:
        if lower is None or upper is None:
            raise TypeError("a joint limit needs lower and upper")
        if (local_edge is None) == (p0 is None or p1 is None):
            raise TypeError("give the joint's edge either as p0, p1 (world, at ref) or as local_edge, not both")
        given = {"p0": p0, "p1": p1} if local_edge is None else {"local_edge": local_edge}
        kind, edge = "edges" if local_edge is None else "local_edges", self._edge(given)  # type: ignore[arg-type]
        not_ints = [Fault((k,), *NOT_AN_INTEGER) for k, v in (("i", i), ("j", j))  # as the wire's body_ids
                    if isinstance(v, bool) or not isinstance(v, (int, np.integer))]  # 1.7 is no body 1
        if not_ints:
            raise invalid(not_ints, where)
        ids = (int(i), int(j))
        lower, upper, *rest = self._check(uid, where, ids, kind, edge, origin, (lower, upper, *rest), prev)
        key = (uid, kind, origin, prev is not None)
        rows = self._joints.setdefault(key, [])
        rows.append((ids, edge, lower, upper, *rest))
        return Joint(len(rows) - 1, uid, list(self._joints).index(key), joint_key(np.array(ids), edge, origin))

    def _check(self, uid: int, where: str, ids: tuple[int, int], kind: str, edge: np.ndarray, origin: str,
               numbers: tuple[ArrayLike, ...], prev: ArrayLike | None = None) -> list[float]:
        """`lower`, `upper`, `strength`, `offset` (and `prev_coordinate` when given) as floats, once the
        service's checks of this one joint pass (its bodies added and two, finite numbers, `lower <= upper`,
        `strength >= 0`, its edge, `origin`, its constitution and state): else `InvalidInput` naming the argument,
        in the service's words, at the call that made the mistake."""
        facts = registry.CONSTITUTIONS.get(uid)
        faults: list[Fault] = []
        named = ("lower", "upper", "strength", "offset") + ("prev_coordinate",) * (prev is not None)
        given = (*numbers, prev)[:len(named)]
        if not all(type(v) in (float, np.float64) for v in given):  # one float each: nothing for `_array` to name
            values = {name: _array(v, name, faults) for name, v in zip(named, given)}
            faults += [Fault((name,), f"must be one number, got shape {a.shape}")
                       for name, a in values.items() if a is not None and a.size != 1]
            if faults:
                raise invalid(faults, where)
            given = tuple(a.reshape(1)[0] for a in values.values())  # type: ignore[union-attr]
        nums = [float(v) for v in given]
        lo, up, strength, offset = nums[:4]
        n_bodies = len(self._q)
        e = edge.ravel().tolist()  # [p0, p1] or [l0, l1, r0, r1]: p1 - p0 or l1 - l0 is what the service normalises
        g = [b - a for a, b in zip(e[:3], e[3:6])]  # Python floats: an overflow is inf, without a warning
        plain = (facts is not None and (prev is None or facts.stateful)
                 and 0 <= min(ids) and max(ids) < n_bodies and ids[0] != ids[1] and origin in ORIGINS
                 and all(map(math.isfinite, (*nums, lo - offset, up - offset, *e, *g))) and lo <= up and strength >= 0
                 and any(g))
        if plain:  # nothing the service would name (the common case): its checks, 3x this call's cost, are skipped
            return nums
        joint = Joints(constitution_uid=uid, base_uid=-1 if facts is None else facts.base_uid, body_ids=np.array([ids], dtype=np.int64),
                       edges=edge[None] if kind == "edges" else None, origin=origin,
                       local_edges=edge[None] if kind == "local_edges" else None,
                       **{name: np.array([v]) for name, v in zip(named, nums)})  # prev_coordinate too

        def argument(loc: tuple) -> tuple:  # ("batches", 0, field, 0, *rest) -> the argument that holds it
            field, rest = loc[2], tuple(loc[4:])
            if field == "body_ids":  # out of range (the first body outside) or both the same
                return ("i",) if not 0 <= ids[0] < n_bodies else ("j",)
            if field == "constitution_uid":
                return ("uid",)
            if field == "edges":  # an element of p0 or p1, or the edge as a whole
                return (("p0", "p1")[rest[0]], *rest[1:]) if rest else ("p1",)
            return ("local_edge" if field == "local_edges" else field, *rest)

        faults = [Fault(argument(f.loc), f.msg, f.type) for f in check_joints(0, joint, n_bodies)]
        if faults:
            raise invalid(faults, where)
        return nums

    @staticmethod
    def _edge(given: dict[str, ArrayLike]) -> np.ndarray:
        """`p0`, `p1` as the edge (2, 3), or `local_edge` (2, 2, 3); else `InvalidInput` naming the argument."""
        faults: list[Fault] = []
        arrays = {name: _array(v, name, faults) for name, v in given.items()}
        for name, a in arrays.items():
            local = name == "local_edge"
            want, what = ((2, 2, 3), "[[l0, l1], [r0, r1]] (2, 2, 3)") if local else ((3,), "a point (3,)")
            if a is not None and a.shape != want:
                faults.append(Fault((name,), f"must be {what}, got shape {a.shape}"))
        if faults:
            raise invalid(faults, "Scene: a joint's " + ("local edge" if "local_edge" in given else "edge"))
        # A copy: a float64 array is the caller's own, which they may fill again for the next joint.
        return arrays["local_edge"].copy() if "local_edge" in arrays else np.stack([arrays["p0"], arrays["p1"]])

    def request(self, outputs: Sequence[str] = OUTPUTS, hessian_mode: str = "exact", active_only: bool = False,
                layout: str = "joints") -> Request:
        """The request: one batch per constitution (and per edge kind, origin, and whether the joints were
        given `prev_coordinate`), in the order first used; bodies in the order added.

        `layout="bodies"` asks for the gradient and Hessian summed per body (`Evaluation.assembled`)."""
        batches = []
        for (uid, kind, origin, stated), rows in self._joints.items():
            ids, edges, lower, upper, strength, offset, *prev = zip(*rows)
            # v1.1's offsets only where one is set: a scene without them makes a v1 request.
            off = offset if any(o != 0.0 for o in offset) else None
            geometry = {kind: np.stack(edges)}
            batches.append(JointBatch.of(uid, ids, geometry.pop("edges", None), lower, upper, strength, offset=off,
                                         prev_coordinate=prev[0] if stated else None, origin=origin, **geometry))
        states = (self._q, self._q_prev, self._q_ref)
        q, q_prev, q_ref = (np.array(rows, dtype=np.float64).reshape(-1, 12) for rows in states)
        # `outputs`: one name alone too (Request.outputs).
        return Request(q, q_prev, q_ref, batches, outputs, hessian_mode, active_only, layout)  # type: ignore[arg-type]


def request_from_arrays(q: ArrayLike, joints: Sequence[JointBatch], *, q_prev: ArrayLike | None = None,
                        q_ref: ArrayLike | None = None, outputs: Sequence[str] = OUTPUTS, hessian_mode: str = "exact",
                        active_only: bool = False, layout: str = "joints") -> Request:
    """The vectorised builder: bodies' DOFs (B, 12) (`q_ref` defaults to `q`, `q_prev` to `q_ref`) and
    batches made with `JointBatch.of(uid, body_ids, edges, lower, upper, strength)`; `layout` as in `Scene.request`."""
    faults: list[Fault] = []
    given = {"q": q, "q_ref": q_ref, "q_prev": q_prev}
    states = {name: None if v is None else _array(v, name, faults) for name, v in given.items()}
    if faults:  # located as the wire locates them: bodies.q, ...
        raise invalid([Fault(("bodies", *f.loc), f.msg, f.type) for f in faults], "request_from_arrays")
    a = states["q"]
    a_ref = a if states["q_ref"] is None else states["q_ref"]
    a_prev = a_ref if states["q_prev"] is None else states["q_prev"]
    # The validator's shape check (every row 12 DOFs; a 4x4 pose per body gets a hint), not its finiteness:
    # a NaN is the service's to name, per element, on every path.
    named = {"q"} | {name for name, v in given.items() if v is not None}  # a defaulted state repeats q's fault
    shapes = [f for f in check_bodies(Bodies(a, a_prev, a_ref)) if f.type != "finite_number" and f.loc[1] in named]  # type: ignore[arg-type]
    if shapes:
        raise invalid(shapes, "request_from_arrays")
    return Request(a, a_prev, a_ref, list(joints), outputs, hessian_mode, active_only, layout)  # type: ignore[arg-type]
