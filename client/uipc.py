"""Read a libuipc scene (`uipc.core.Scene`, the `pyuipc` package) into a request, and write committed angles back.

    snapshot = reference(scene)                          # where you call world.init(): the engine's q_ref
    req, joints = request_from_scene(scene, reference=snapshot)   # every #670 / #669 joint edge
    ev = LocalClient().evaluate(req)                     # or Client / AsyncClient / .session(req)
    write_back(scene, [b.coordinate for b in ev.batches], joints)

It needs pyuipc (the `uipc` extra) and only reads the scene's geometries and attributes (CONTRACT
v1.2, "Reading an engine scene"; docs/uipc.md maps each engine attribute to its wire field). A scene the adapter
cannot read raises `SceneError` before anything is built or written.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from jointlimits.client.model import Array, BatchResult, Evaluation, JointBatch, Request
from jointlimits.client.scene import transforms_to_q
from jointlimits.service.core import registry
from jointlimits.service.core.constitution import Facts

LOCAL_ATTRS = ("l_position0", "l_position1", "r_position0", "r_position1")
BODY_OFFSET = "backend_abd_body_offset"

JointRef = tuple[int, int]
"""(joint geometry id, edge index)."""


class SceneError(ValueError):
    """The scene cannot be read (or written back to) as the engine would: `msg` says why,
    `geometry_id` / `edge` name the joint geometry slot and edge at fault when there is one.
    Raised before anything is built or written, so nothing is left half-converted."""

    def __init__(self, msg: str, geometry_id: int | None = None, edge: int | None = None, hint: str = "") -> None:
        self.msg, self.geometry_id, self.edge, self.hint = msg, geometry_id, edge, hint
        where = "" if geometry_id is None else f"geometry {geometry_id}" + ("" if edge is None else f", edge {edge}") + ": "
        super().__init__(f"{where}{msg}{f' ({hint})' if hint else ''}")


def _uipc() -> Any:
    """The `uipc` module, or an ImportError that says which extra installs it."""
    try:
        import uipc
    except ImportError as e:
        raise ImportError(
            "jointlimits.client.uipc reads libuipc scenes and needs pyuipc: pip install pyuipc (the uipc extra)"
        ) from e
    return uipc


# ------------------------------------------------------------------------------------- scene reads


def _slots(scene: Any) -> list[tuple[int, Any, Any]]:
    """Every geometry as `(id, slot, rest_slot)`, in the engine's slot order (ascending id)."""
    objects = scene.objects()  # object ids are 0..created_count-1, destroyed ones gone
    found = (objects.find(oid) for oid in range(objects.created_count()))
    ids = {int(i) for obj in found if obj is not None for i in np.asarray(obj.geometries().ids()).ravel()}
    slots = [(gid, *scene.geometries().find(gid)) for gid in sorted(ids)]
    return [(gid, slot, rest) for gid, slot, rest in slots if slot is not None]


def _transforms(geo: Any) -> Array:
    """A geometry's instance transforms (I, 4, 4), a copy."""
    return np.array(geo.transforms().view(), dtype=np.float64).reshape(-1, 4, 4)


def _meta_uid(geo: Any) -> int | None:
    attr = geo.meta().find("constitution_uid")
    return None if attr is None else int(np.asarray(attr.view()).ravel()[0])


def _extra_uids(geo: Any) -> set[int]:
    """meta `extra_constitution_uids` (a VectorXu64 that pyuipc only exposes through JSON)."""
    if geo.meta().find("extra_constitution_uids") is None:
        return set()
    values = geo.meta().to_json()["extra_constitution_uids"]["attribute"]["values"]
    if isinstance(values, str):  # defensive: some builds serialise nested JSON as a string
        values = json.loads(values)
    flat: list[Any] = [values]
    uids: set[int] = set()
    while flat:  # nested lists (one row, a column vector): collect the integers as they are (no float detour)
        v = flat.pop()
        flat.extend(v) if isinstance(v, list) else uids.add(int(v))
    return uids


def _is_affine_body(uid: int | None) -> bool:
    if uid is None:
        return False
    reg = _uipc().builtin.ConstitutionUIDCollection.instance()
    return bool(reg.exists(uid)) and reg.find(uid).type == "AffineBody"


def _limits_by_base() -> dict[int, Facts]:
    """The registered constitutions by the UID of the base joint they limit (a joint geometry's meta
    `constitution_uid`), in the order registered; each names the engine's edge attributes."""
    return {f.base_uid: f for f in registry.CONSTITUTIONS.values()}


@dataclass(frozen=True)
class Reference:
    """The affine bodies' transforms at one moment, by body geometry id (`transforms[id]` (I, 4, 4), a
    copy): made by `reference(scene)` where `world.init()` is called, the transforms the engine builds
    its joint frames from (`q_ref`)."""

    transforms: dict[int, Array]


def reference(scene: Any) -> Reference:
    """A snapshot of every affine-body instance's current `transform`: take it where you call
    `world.init()` (the engine builds its joint frames from the transforms then, not from the rest
    geometries, which e.g. `UrdfIO` leaves at the identity) and pass it to every later
    `request_from_scene(scene, reference=snapshot)` as the bodies' `q_ref`."""
    _uipc()
    return Reference({gid: _transforms(slot.geometry()) for gid, slot, _, _ in _affine_bodies(_slots(scene))})


@dataclass
class _Bodies:
    """The engine's body numbering: `offset[geo id]`, `count[geo id]`; `q`, `q_ref` (B, 12); `published`
    is how many body geometries carry `backend_abd_body_offset`."""

    offset: dict[int, int]
    count: dict[int, int]
    q: Array
    q_ref: Array
    published: int
    n_geometries: int
    guess: str = ""
    """Why the rest transforms can only be a guess for the transforms at `world.init()` ("": no sign)."""


def _affine_bodies(slots: list[tuple[int, Any, Any]]) -> list[tuple[int, Any, Any, int]]:
    """The affine-body geometries of `slots` as `(id, slot, rest_slot, constitution UID)`, in the engine's body
    order: by constitution UID, stable (slot order within one)."""
    geos = [(gid, slot, rest, _meta_uid(slot.geometry())) for gid, slot, rest in slots]
    return sorted((g for g in geos if _is_affine_body(g[3])), key=lambda g: g[3])


def _bodies(slots: list[tuple[int, Any, Any]], snapshot: Reference | None = None) -> _Bodies:
    geos = _affine_bodies(slots)
    offset, count, qs, q_refs, published, at = {}, {}, [], [], 0, 0
    all_identity, moved, urdf_posed = True, False, []
    for gid, slot, rest, _ in geos:
        geo = slot.geometry()
        T = _transforms(geo)
        if snapshot is not None:
            if gid not in snapshot.transforms:
                raise SceneError("the body geometry is not in the reference snapshot", gid,
                                 hint="created after reference(scene) was taken? take it again where world.init() is called")
            T_ref = snapshot.transforms[gid]
            if T_ref.shape != T.shape:
                raise SceneError(f"body geometry has {T.shape[0]} instances but {T_ref.shape[0]} in the reference snapshot", gid)
        else:
            T_ref = _transforms(rest.geometry()) if rest is not None else T
            if T_ref.shape != T.shape:
                raise SceneError(f"body geometry has {T.shape[0]} instances but its rest geometry {T_ref.shape[0]}", gid)
            identity = bool(np.all(T_ref == np.eye(4)))
            all_identity &= identity
            moved |= not np.array_equal(T, T_ref)
            link = geo.meta().find("urdf/type")
            if identity and not np.array_equal(T, T_ref) and link is not None and list(link.view()) == ["link"]:
                urdf_posed.append(gid)
        mine = geo.meta().find(BODY_OFFSET)
        if mine is not None:
            published += 1
            theirs = int(np.asarray(mine.view()).ravel()[0])
            if theirs != at:
                raise SceneError(
                    f"the engine numbers this body geometry's first body {theirs}, the adapter {at}", gid,
                    hint="geometries created or destroyed after world.init() and not yet rebuilt by the engine?")
        offset[gid], count[gid] = at, T.shape[0]
        qs.append(transforms_to_q(T))
        q_refs.append(transforms_to_q(T_ref))
        at += T.shape[0]
    guess = ""
    if snapshot is None and urdf_posed:
        guess = (f"the UrdfIO link geometries {urdf_posed} were posed after they were created: their rest "
                 "transforms are the identity, not the transforms the engine builds the joints from at world.init()")
    elif snapshot is None and geos and all_identity and moved:
        guess = ("every body's rest transform is the identity and some current transform is not: the rest "
                 "transforms may not be the transforms the engine builds the joints from at world.init()")
    empty = np.zeros((0, 12))
    return _Bodies(offset, count, np.concatenate(qs or [empty]), np.concatenate(q_refs or [empty]),
                   published, len(geos), guess)


def _edge_attr(geo: Any, name: str, gid: int) -> NDArray[Any]:
    attr = geo.edges().find(name)
    if attr is None:  # the engine asserts each attribute read here at world.init()
        raise SceneError(f"the joint edges have no `{name}` attribute", gid)
    return np.asarray(attr.view())


def _body_ids(bodies: _Bodies, gid: int, geo_ids: NDArray[Any], inst_ids: NDArray[Any], side: str) -> NDArray[np.int64]:
    """(E,) body rows of one side of a joint geometry's edges; a missing body geometry or instance is a SceneError."""
    out = np.empty(geo_ids.shape[0], dtype=np.int64)
    for g in np.unique(geo_ids):
        at = geo_ids == g
        if int(g) not in bodies.offset:
            e = int(np.flatnonzero(at)[0])
            raise SceneError(f"`{side}_geo_id` {int(g)} is not an affine-body geometry of the scene "
                             "(missing, destroyed, or without an affine-body constitution)", gid, e)
        inst = inst_ids[at].astype(np.int64)
        bad = (inst < 0) | (inst >= bodies.count[int(g)])
        if np.any(bad):
            e = int(np.flatnonzero(at)[np.argmax(bad)])
            raise SceneError(f"`{side}_inst_id` {int(inst[np.argmax(bad)])} is out of range: body geometry "
                             f"{int(g)} has {bodies.count[int(g)]} instances", gid, e)
        out[at] = bodies.offset[int(g)] + inst
    return out


def _bad_number(v: NDArray[Any]) -> str:
    """Words for a value (a number or a vector) holding a NaN or an infinity."""
    nan = bool(np.isnan(v).any())
    return ("is NaN" if nan else "is not finite") + ("" if nan and v.ndim == 0 else f" ({v.tolist()})")


def _read_joints(gid: int, geo: Any, limit: Facts, bodies: _Bodies, use_angle: bool) -> tuple[bool, dict[str, Any]]:
    """One limited joint geometry's edges, as arrays (E rows), with the engine's checks and the service's:
    a fault is named here by geometry and edge, not later by batch row. A value written after `apply_to`
    skips its checks, so they are all redone here."""
    E = int(geo.edges().size())
    floats = lambda name, *shape: np.asarray(_edge_attr(geo, name, gid), dtype=np.float64).reshape(E, *shape)  # noqa: E731
    ints = lambda name: np.asarray(_edge_attr(geo, name, gid)).astype(np.int64).reshape(E)  # noqa: E731
    local = all(geo.edges().find(n) is not None for n in LOCAL_ATTRS)  # the engine's `use_local`
    l_geo, l_inst = ints("l_geo_id"), ints("l_inst_id")
    ids = np.stack([_body_ids(bodies, gid, l_geo, l_inst, "l"),
                    _body_ids(bodies, gid, ints("r_geo_id"), ints("r_inst_id"), "r")], axis=1)
    if np.any(itself := ids[:, 0] == ids[:, 1]):  # the engine takes it; the service does not
        e = int(np.argmax(itself))
        raise SceneError(f"`l_geo_id`, `l_inst_id` = `r_geo_id`, `r_inst_id`: body (geometry {l_geo[e]}, "
                         f"instance {l_inst[e]}) is jointed to itself", gid, e)
    lim = {n: floats(f"limit/{n}") for n in ("lower", "upper", "strength")}
    offset = floats(limit.offset_name)  # the base joint's do_init asserts it, as the limit's attributes
    prev = floats(limit.state_name) if limit.stateful and use_angle else None
    if local:
        edges = np.stack([floats(n, 3) for n in LOCAL_ATTRS], axis=1).reshape(E, 2, 2, 3)  # [[l0, l1], [r0, r1]]
        axis = edges[:, 0, 1] - edges[:, 0, 0]
        named: dict[str, Array] = dict(zip(LOCAL_ATTRS, edges.reshape(E, 4, 3).transpose(1, 0, 2)))
    else:
        P = np.asarray(geo.positions().view(), dtype=np.float64).reshape(-1, 3)
        topo = np.asarray(geo.edges().topo().view()).reshape(E, 2)
        edges = P[topo]  # (E, 2, 3): world positions at q_ref
        axis = edges[:, 1] - edges[:, 0]
        if np.any(bad := ~np.isfinite(edges).all(axis=2)):  # (E, 2): the edges' vertices only
            e, k = (int(i) for i in np.argwhere(bad)[0])
            raise SceneError(f"`position` of vertex {topo[e, k]} {_bad_number(edges[e, k])}", gid, e)
        named = {}
    named |= {f"limit/{n}": v for n, v in lim.items()} | {limit.offset_name: offset}
    named |= {} if prev is None else {limit.state_name: prev}
    for name, v in named.items():
        if np.any(bad := ~np.isfinite(v).all(axis=tuple(range(1, v.ndim)))):  # per edge, also of 0 edges
            e = int(np.argmax(bad))
            raise SceneError(f"`{name}` {_bad_number(v[e])}", gid, e)
    lo, up, s = lim["lower"], lim["upper"], lim["strength"]
    if np.any(empty := lo > up):
        e = int(np.argmax(empty))
        raise SceneError(f"`limit/lower` {float(lo[e])!r} > `limit/upper` {float(up[e])!r}: an empty range "
                         "(the engine refuses it at world.init())", gid, e)
    if np.any(s < 0):  # the engine takes it; the service does not
        e = int(np.argmax(s < 0))
        raise SceneError(f"`limit/strength`: negative strength {float(s[e])!r}", gid, e)
    # The engine refuses a zero axis at world.init() (revolute: |t|^2 <= 1e-24, prismatic: P0 == P1);
    # a local axis turns by R_i (670) or A_ref_i (669), both invertible, so l1 - l0 decides.
    short = ~(np.einsum("ek,ek->e", axis, axis) > limit.engine_zero_axis)
    if np.any(short):
        raise SceneError("the joint's axis has zero length (the engine refuses it at world.init())",
                         gid, int(np.argmax(short)))
    return local, dict(
        refs=[(gid, e) for e in range(E)], body_ids=ids, edges=edges, prev=prev, offset=offset, **lim,
    )


def request_from_scene(scene: Any, q: ArrayLike | None = None, q_prev: ArrayLike | None = None,
                       q_ref: ArrayLike | None = None, committed: bool | None = None,
                       outputs: Sequence[str] = ("energy", "gradient", "hessian"), *,
                       reference: Reference | str | None = None) -> tuple[Request, list[list[JointRef]]]:
    """The request that evaluates every #670 / #669 joint of a `uipc.core.Scene` as the engine does,
    and `joints`: `joints[k][r]` = (joint geometry id, edge index) of batch `k`'s row `r` (docs/uipc.md).

    `q`, `q_prev`, `q_ref` (B, 12) override the bodies' DOFs (the engine's numbering). `q` defaults to the
    current transforms, `q_ref` to those at `world.init()`: `reference`, a snapshot `reference(scene)` taken
    then; None: the rest geometries' transforms, refused when they can only be a guess; "rest": those as they
    are. `committed`: whether the edges' `angle` is read as `prev_coordinate` (None: once the engine has
    published it); `q_prev` defaults to the current transforms when it is read, else to `q_ref`.
    One batch per constitution (670's first) and edge variant; rows in slot order, then edge order.
    Raises `SceneError` for a scene the engine would refuse or with values the service refuses (naming the
    geometry and edge), and ImportError without pyuipc.
    """
    _uipc()
    given_rest = isinstance(reference, str) and reference == "rest"
    if not (reference is None or given_rest or isinstance(reference, Reference)):
        got = repr(reference) if isinstance(reference, str) else type(reference).__name__
        raise SceneError(f"`reference` is a snapshot from reference(scene), \"rest\" or None, got {got}")
    if reference is not None and q_ref is not None:
        raise SceneError("give the transforms at world.init() once: `reference` or `q_ref`, not both")
    slots = _slots(scene)
    bodies = _bodies(slots, reference if isinstance(reference, Reference) else None)
    if reference is None and q_ref is None and bodies.guess:
        raise SceneError(bodies.guess, hint="take snapshot = reference(scene) where you call world.init() and pass "
                         "reference=snapshot; or pass q_ref=, or reference=\"rest\" to take the rest transforms as they are")
    if committed is None:
        if 0 < bodies.published < bodies.n_geometries:
            raise SceneError(f"{bodies.published} of {bodies.n_geometries} body geometries carry `{BODY_OFFSET}`: "
                             "the engine has not numbered every body yet", hint="pass committed=True or False")
        use_angle = bodies.n_geometries > 0 and bodies.published == bodies.n_geometries
    else:
        use_angle = bool(committed)

    # Joint geometries per base UID; the engine indexes a limit by its base joint's rows, so a limit
    # on only some of the base joint's geometries is refused at world.init() (joint count mismatch).
    limit_of = _limits_by_base()
    limited: dict[int, list[tuple[int, Any]]] = {base: [] for base in limit_of}
    bare: dict[int, list[int]] = {base: [] for base in limit_of}
    for gid, slot, _ in slots:
        geo = slot.geometry()
        base = _meta_uid(geo)
        if base in limit_of:
            (limited[base].append((gid, geo)) if limit_of[base].uid in _extra_uids(geo) else bare[base].append(gid))
    for base, with_limit in limited.items():
        if with_limit and bare[base]:
            raise SceneError(
                f"#{limit_of[base].uid} is on joint geometries {[g for g, _ in with_limit]} but not on their siblings "
                f"{bare[base]} (base joint UID {base}): the engine aligns the limit with every base joint row and "
                "refuses this scene at world.init()", bare[base][0],
                hint=f"apply the limit to every UID-{base} joint geometry (a wide range leaves a joint free)")

    rows: dict[tuple[int, bool], dict[str, list[Any]]] = {}  # (uid, local edges) -> the batch's arrays in parts
    for base, limit in limit_of.items():
        for gid, geo in limited[base]:
            local, arrays = _read_joints(gid, geo, limit, bodies, use_angle)
            r = rows.setdefault((limit.uid, local), {})
            for name, v in arrays.items():
                r.setdefault(name, []).extend([] if v is None else [v])  # `prev`: a state read, or none
    rows = {k: r for k, r in rows.items() if any(r["refs"])}
    if not rows:
        which = " or ".join(f"#{f.uid}" for f in limit_of.values())
        raise SceneError(f"the scene has no joint edge with a {which} limit (zero edges to evaluate)")

    B = bodies.q.shape[0]
    def dofs(a: ArrayLike | None, default: Array, name: str) -> Array:
        if a is None:
            return default
        a = np.asarray(a, dtype=np.float64)
        if a.shape != (B, 12):
            raise SceneError(f"`{name}` has shape {a.shape}; the scene has {B} affine bodies, so (B, 12) = ({B}, 12)")
        return a
    q_ref_ = dofs(q_ref, bodies.q_ref, "q_ref")
    q_ = dofs(q, bodies.q, "q")
    # The engine's `angle` belongs to the transforms it wrote back, its next step's q_prev
    # (affine_body_revolute_joint.cu: the limit reads current_angles as the frame-start angle).
    q_prev_ = dofs(q_prev, bodies.q if use_angle else q_ref_, "q_prev")

    batches, joints = [], []
    for (uid, local), r in rows.items():
        a = {name: np.concatenate(parts) for name, parts in r.items() if name != "refs" and parts}
        batches.append(JointBatch.of(
            uid, a["body_ids"], None if local else a["edges"], a["lower"], a["upper"], a["strength"],
            offset=a["offset"], prev_coordinate=a.get("prev"), local_edges=a["edges"] if local else None,
            origin="absolute"))
        joints.append([ref for refs in r["refs"] for ref in refs])
    req = Request(q=q_, q_prev=q_prev_, q_ref=q_ref_, batches=batches, outputs=tuple(outputs), hessian_mode="psd")
    return req, joints


# ------------------------------------------------------------------------------------- write back


def write_back(scene: Any, coordinates: Evaluation | Sequence[ArrayLike | BatchResult],
               joints: Sequence[Sequence[JointRef]]) -> None:
    """Write committed coordinates into the joint edges: `angle` (670, what the engine reads as
    `prev_coordinate`) and `distance` (669, the engine's published slide), row `r` of batch `k`
    into `joints[k][r]`.

    `coordinates`: one (N_k,) array per batch (a session's `commit(q)`), or an `Evaluation` /
    its `BatchResult`s (their `coordinate`; every row must be there, so no `active_only`).
    Everything is checked before the first write: a SceneError leaves the scene as it was.
    """
    _uipc()
    if isinstance(coordinates, Evaluation):
        coordinates = coordinates.batches
    if len(coordinates) != len(joints):
        raise SceneError(f"{len(coordinates)} batches of coordinates for {len(joints)} batches of joints")
    limit_of = _limits_by_base()
    writes: dict[int, tuple[Any, str, list[int], list[float]]] = {}
    for k, (c, refs) in enumerate(zip(coordinates, joints)):
        values = _batch_values(c, len(refs), k)
        for (gid, e), v in zip(refs, values):
            if gid not in writes:
                slot, _ = scene.geometries().find(int(gid))
                if slot is None:
                    raise SceneError("the joint geometry is not in the scene", int(gid))
                geo = slot.geometry()
                base = _meta_uid(geo)
                if base not in limit_of:
                    kinds = " or ".join(f.kind for f in limit_of.values())
                    raise SceneError(f"not a {kinds} joint geometry (constitution UID {base})", int(gid))
                name = limit_of[base].state_name
                _edge_attr(geo, name, int(gid))  # the attribute is there
                writes[gid] = (geo, name, [], [])
            geo, name, rows_, vals = writes[gid]
            if not 0 <= e < geo.edges().size():
                raise SceneError(f"edge out of range: the geometry has {geo.edges().size()} edges", int(gid), int(e))
            rows_.append(int(e))
            vals.append(float(v))
    view = _uipc().view
    for geo, name, rows_, vals in writes.values():
        view(geo.edges().find(name))[np.asarray(rows_)] = np.asarray(vals)


def _batch_values(c: ArrayLike | BatchResult, n: int, k: int) -> Array:
    """Batch `k`'s (n,) coordinates, all finite."""
    if isinstance(c, BatchResult):
        if c.coordinate is None or len(c.index) != n or not np.array_equal(c.index, np.arange(n)):
            raise SceneError(f"batch {k}: the answer lacks the coordinate of some of its {n} joints "
                             "(evaluate without active_only)")
        c = c.coordinate
    values = np.asarray(c, dtype=np.float64).reshape(-1)
    if values.shape != (n,):
        raise SceneError(f"batch {k}: {values.shape[0]} coordinates for {n} joints")
    if not np.all(np.isfinite(values)):
        raise SceneError(f"batch {k}: coordinate {int(np.argmax(~np.isfinite(values)))} is not finite")
    return values
