"""The JSON encoding: wire bytes <-> core arrays. No numerics beyond `np.asarray`."""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson
from pydantic import ValidationError
from pydantic_core import from_json

from jointlimits.schemas import OUTPUTS, EvaluateRequest
from jointlimits.schemas.constitutions import STRENGTH_DEFAULT
from jointlimits.schemas.session import OpeningRequest
from jointlimits.service.core import CONSTITUTIONS, Bodies, Evaluation, Fault, InputError, Joints
from jointlimits.service.core.errors import MAX_FAULTS, Loc
from jointlimits.service.core.prepared import input_faults
from jointlimits.service.core.validate import _element_faults as element_faults
from jointlimits.service.core.validate import as_array
from jointlimits.service.http import jsonkeys, limits
from jointlimits.service.http.errors import from_validation

MEDIA_TYPE = "application/json"


def decode(body: bytes, max_joints: int, opening: bool = False) -> dict[str, Any]:
    """Keyword arguments of `jointlimits.service.core.evaluate` for a JSON body (`opening`: a session's opening
    document, whose `id` is returned too, under "id").

    Raises `HttpError` (413) for too many joints, `InputError` (422) for a malformed body.
    """
    limits.check_joints(limits.json_joints_upper_bound(body), max_joints)
    req = parse(body, opening)
    limits.check_joints(sum(len(j.body_ids) for j in req.batches), max_joints)
    return to_core(req) | ({"id": req.id} if opening else {})  # type: ignore[attr-defined]


def parse(body: bytes, opening: bool = False) -> EvaluateRequest:
    """The request of a JSON body, or `InputError` with at most `MAX_FAULTS` faults, found cheaply.

    Keys first, on the bytes (`jsonkeys`): repeated ones, which pydantic would let through
    (last wins), and unknown and missing ones; at the cap pydantic never runs. Then the body is
    parsed once (`load`) and pydantic checks the document but its numeric arrays; its lists are
    `FailFast` (a list's first bad item ends its checks): its error list is bounded too, as long as
    unknown keys (the one error it lists without bound) are. Each array is built once from the same
    document (`validate.as_array`, in pydantic's words for an item that is not a number), and a wrong
    shape is named in the core's words. The request holds the arrays, of the schema's shapes.
    """
    keys = jsonkeys.scan(body, opening=opening)
    key_faults = keys.faults
    if len(key_faults) >= MAX_FAULTS:
        raise InputError(key_faults)
    if keys.stray is not None and jsonkeys.keys_after(body, keys.stray[0], MAX_FAULTS) >= MAX_FAULTS:
        # The scan stopped at an object no request holds, and enough keys follow to flood
        # pydantic's list with unknown ones: refuse here.
        _, loc, known_field = keys.stray
        if known_field:
            key_faults = [*key_faults, Fault(loc, "holds an object, where a request has numbers or lists", "model_type")]
        raise InputError(key_faults)
    doc = load(body)  # a broken document: the scan's findings mean nothing
    # The numeric arrays are set aside: pydantic checks the rest (no list of numbers walked or copied), each
    # array is built once from the parsed lists, and what is wrong inside one is the core's to name.
    raw = _set_aside(doc)
    try:
        req = (OpeningRequest if opening else EvaluateRequest).model_validate(doc)
        faults = []
    except ValidationError as e:
        req, faults = None, [json_words(f) for f in from_validation(e).faults]
    booleans = body.count(b"true") + body.count(b"false") > (isinstance(doc, dict) and isinstance(doc.get("active_only"), bool))
    built, found = _arrays(raw, booleans)
    faults = (faults + found)[:MAX_FAULTS]
    misshapen = [loc for loc, a in built.items() if not _well_shaped(loc[-1], a)]
    if misshapen and not faults:  # a row of 11 numbers, a pair of 3 indices: named as the core names them
        faults = _in_core_words(doc, built) or [Fault(misshapen[0], f"has shape {built[misshapen[0]].shape}")]
    if faults:
        seen = {(f.loc, f.type) for f in key_faults}
        raise InputError([*key_faults, *(f for f in faults if (f.loc, f.type) not in seen)])
    repeated = [f for f in key_faults if f.type == "duplicate_key"]
    if repeated:
        raise InputError(repeated)  # pydantic let them through (the last one wins)
    assert req is not None  # no fault, so pydantic passed
    for loc, a in built.items():  # the arrays into the request, whatever their shape (the core checks it)
        setattr(req.bodies if loc[0] == "bodies" else req.batches[loc[1]], loc[-1], a)
    return req


def load(body: bytes | str) -> Any:
    """A JSON document as plain data, parsed once by pydantic's own parser (jiter): NaN, Infinity and
    1e400 (inf) are read as floats, for the core to name as non-finite; `InputError` in pydantic's
    words for a broken document."""
    try:
        return from_json(body)
    except ValueError as e:
        raise InputError([Fault((), f"Invalid JSON: {e}", "json_invalid")]) from None


OBJECT = "Input should be an object"


def json_words(f: Fault) -> Fault:
    """A fault of pydantic's Python mode in the words its JSON mode uses for the same document."""
    if f.type == "model_type":
        return Fault(f.loc, OBJECT, f.type)
    if f.type == "model_attributes_type" and f.loc == ():
        return Fault((), OBJECT, "dict_type")
    return f


BODY_ARRAYS = ("q", "q_prev", "q_ref")
BATCH_ARRAYS = {"body_ids": True, "edges": False, "local_edges": False, "lower": False, "upper": False,
                "strength": False, "offset": False, "prev_coordinate": False}
"""The numeric arrays of a request (True: of integers), whose faults the core names on every path."""


_ROW_SHAPES = {"q": (12,), "q_prev": (12,), "q_ref": (12,), "body_ids": (2,), "edges": (2, 3), "local_edges": (2, 2, 3)}
"""The shape of one row of the arrays whose rows are lists (the others are lists of numbers)."""


def _well_shaped(name: str, a: np.ndarray) -> bool:
    """`a` has the shape the wire schema gives array `name` (any number of rows; an empty list is none)."""
    row = _ROW_SHAPES.get(name, ())
    return a.shape[1:] == row or (row != () and a.shape == (0,))


def _set_aside(doc: Any) -> dict[Loc, Any]:
    """The numeric arrays of the request's objects in `doc`, each replaced there by an empty list (a null too:
    named at the array, as msgpack's nil; a missing one stays missing, pydantic's to name)."""
    raw: dict[Loc, Any] = {}
    bodies = doc.get("bodies") if isinstance(doc, dict) else None
    if isinstance(bodies, dict):
        for name in BODY_ARRAYS:
            if name in bodies:
                raw["bodies", name], bodies[name] = bodies[name], []
    batches = doc.get("batches") if isinstance(doc, dict) else None
    for b, batch in enumerate(batches if isinstance(batches, list) else []):
        if isinstance(batch, dict):
            for name in BATCH_ARRAYS:
                if name in batch:
                    raw["batches", b, name], batch[name] = batch[name], []
    return raw


def _arrays(raw: dict[Loc, Any], booleans: bool) -> tuple[dict[Loc, np.ndarray], list[Fault]]:
    """Each array built whatever its shape (`validate.as_array`), or the faults inside it, in pydantic's words.

    `booleans`: the body may hold `true` or `false` in an array, which NumPy would read as 1 and 0 among
    numbers: then every array's items are read one by one first (`validate.element_faults`)."""
    built: dict[Loc, np.ndarray] = {}
    faults: list[Fault] = []
    for loc, value in raw.items():
        integer = BATCH_ARRAYS.get(loc[-1], False)
        found = element_faults(value, loc, integer) if booleans else []
        a, found = (None, found) if found else as_array(value, loc, integer)
        faults += found
        if a is not None:
            built[loc] = a
    return built, faults


def _in_core_words(doc: dict[str, Any], built: dict[Loc, np.ndarray]) -> list[Fault]:
    """The core's faults of a request whose arrays have the wrong shapes, as msgpack and the SDK get them."""
    fields: list[dict[str, np.ndarray]] = [{} for _ in doc["batches"]]
    for loc, a in built.items():
        if loc[0] == "batches":
            fields[loc[1]][loc[2]] = a
    return input_faults(
        bodies=Bodies(*(built["bodies", name] for name in BODY_ARRAYS)),
        batches=[_joints(raw, f) for raw, f in zip(doc["batches"], fields)],
        outputs=doc.get("outputs", list(OUTPUTS)), hessian_mode=doc.get("hessian_mode", "exact"),
        layout=doc.get("layout", "joints"),
    )


def _joints(raw: dict[str, Any], fields: dict[str, np.ndarray]) -> Joints:
    uid = raw["constitution_uid"]
    return Joints(
        constitution_uid=uid,
        base_uid=base_uid_of(uid) if raw.get("base_uid") is None else raw["base_uid"],
        body_ids=fields["body_ids"],
        edges=fields.get("edges"),
        local_edges=fields.get("local_edges"),
        origin=raw.get("origin", "q_ref"),
        lower=fields["lower"],
        upper=fields["upper"],
        strength=fields["strength"] if "strength" in fields else strength_of(None, len(fields["body_ids"])),
        offset=fields.get("offset"),
        prev_coordinate=fields.get("prev_coordinate"),
    )


def base_uid_of(constitution_uid: int) -> int:
    """The base joint an absent `base_uid` stands for (-1 for an unknown constitution, which is refused anyway)."""
    c = CONSTITUTIONS.get(constitution_uid)
    return c.base_uid if c is not None else -1


def strength_of(strength: Any, n: int) -> np.ndarray:
    """`strength` (N,) as given, or the reference engine's default for each of the `n` joints when absent."""
    return np.full(n, STRENGTH_DEFAULT) if strength is None else np.asarray(strength, dtype=np.float64)


def to_core(req: EvaluateRequest) -> dict[str, Any]:
    """Keyword arguments of `jointlimits.service.core.evaluate` for a parsed request."""
    b = req.bodies
    dof = lambda rows: np.asarray(rows, dtype=np.float64).reshape(len(rows), 12)  # noqa: E731
    return dict(
        bodies=Bodies(q=dof(b.q), q_prev=dof(b.q_prev), q_ref=dof(b.q_ref)),
        batches=[
            Joints(
                constitution_uid=j.constitution_uid,
                base_uid=base_uid_of(j.constitution_uid) if j.base_uid is None else j.base_uid,
                body_ids=np.asarray(j.body_ids, dtype=np.int64).reshape(len(j.body_ids), 2),
                edges=None if j.edges is None else np.asarray(j.edges, dtype=np.float64).reshape(len(j.edges), 2, 3),
                local_edges=None if j.local_edges is None else np.asarray(j.local_edges, dtype=np.float64).reshape(len(j.local_edges), 2, 2, 3),
                origin=j.origin,
                lower=np.asarray(j.lower, dtype=np.float64),
                upper=np.asarray(j.upper, dtype=np.float64),
                strength=strength_of(j.strength, len(j.body_ids)),
                offset=None if j.offset is None else np.asarray(j.offset, dtype=np.float64),
                prev_coordinate=None if j.prev_coordinate is None else np.asarray(j.prev_coordinate, dtype=np.float64),
            )
            for j in req.batches
        ],
        outputs=req.outputs,
        hessian_mode=req.hessian_mode,
        active_only=req.active_only,
        layout=req.layout,
    )


def to_wire(ev: Evaluation) -> dict[str, Any]:
    """The response body of contract v1.1 as NumPy arrays; `gradient`/`hessian` only when computed."""
    batches = []
    for r in ev.batches:
        out: dict[str, Any] = dict(constitution_uid=r.constitution_uid, index=r.index, x=r.x)
        if r.coordinate is not None:
            out["coordinate"] = r.coordinate
        out["energy"] = r.energy
        if r.gradient is not None:
            out["gradient"] = r.gradient
        if r.hessian is not None:
            out["hessian"] = r.hessian
        batches.append(out)
    doc = dict(total_energy=ev.total_energy, batches=batches)
    if ev.assembled is not None:  # layout="bodies"
        a = ev.assembled
        doc["assembled"] = {k: getattr(a, k) for k in ("gradient", "rows", "cols", "blocks") if getattr(a, k) is not None}
    return doc


FLOATS_PER_PIECE = 2**18
"""Numbers orjson writes in one call (~5 ms): between calls the GIL passes to other threads, so a
worker's event loop and uvicorn's health-check thread keep answering while a large answer is written."""


def encode(ev: Evaluation) -> bytes:
    """JSON bytes with each float in its shortest round-trip form, written in pieces.

    The bytes are those of `orjson.dumps(to_wire(ev))`; each array is written
    `FLOATS_PER_PIECE` numbers at a time and the pieces are joined once (`bytes.join`
    releases the GIL while it copies). The core guarantees finite numbers; orjson
    would write a stray NaN as `null`, never as `NaN`.
    """
    doc = to_wire(ev)
    out: list[bytes | memoryview] = [b'{"total_energy":', orjson.dumps(doc["total_energy"]), b',"batches":[']
    for i, b in enumerate(doc["batches"]):
        out += [b","] if i else []
        out += _object(b)
    out.append(b"]")
    if "assembled" in doc:  # layout="bodies": the per-body gradient and the block-sparse Hessian
        out += [b',"assembled":', *_object(doc["assembled"])]
    out.append(b"}")
    return b"".join(out)


def _object(d: dict[str, Any]) -> list[bytes | memoryview]:
    """A JSON object of scalars and arrays, each array in pieces (`_array_pieces`)."""
    out: list[bytes | memoryview] = [b"{"]
    for j, (k, v) in enumerate(d.items()):
        out += [b',"' if j else b'"', k.encode(), b'":']
        out += _array_pieces(v) if isinstance(v, np.ndarray) else [orjson.dumps(v)]
    out.append(b"}")
    return out


def _array_pieces(a: np.ndarray) -> list[bytes | memoryview]:
    """`a` (N, ...) as JSON: one orjson call per block of rows, the blocks' brackets dropped and rejoined."""
    a = np.ascontiguousarray(a)  # orjson serialises C-ordered arrays only
    rows = max(1, FLOATS_PER_PIECE // max(1, a[0].size if a.ndim > 1 and a.shape[0] else 1))
    if a.shape[0] <= rows:
        return [orjson.dumps(a, option=orjson.OPT_SERIALIZE_NUMPY)]
    out: list[bytes | memoryview] = [b"["]
    for start in range(0, a.shape[0], rows):
        out += [memoryview(orjson.dumps(a[start : start + rows], option=orjson.OPT_SERIALIZE_NUMPY))[1:-1], b","]
    out[-1] = b"]"
    return out
