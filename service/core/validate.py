"""Checks that need arithmetic, vectorised over joints; each fault names batch, field and joint.

The numeric arrays (and their shapes) of every path (JSON, msgpack, sessions, the in-process API) are checked
here. The checks are leaves: they return faults and evaluate nothing; the pipeline (`prepared`) calls them
in order and caps the faults of a request (`errors.FaultLog`).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from jointlimits.service.core.errors import MAX_FAULTS, NONFINITE_MSG, NONFINITE_TYPE, Fault, InputError, Loc
from jointlimits.service.core.kinematics import edge_vector, max_abs
from jointlimits.service.core.polar import SINGULAR_RATIO
from jointlimits.service.core.registry import CONSTITUTIONS
from jointlimits.service.core.scene import OUTPUTS, Array, Bodies, Evaluation, Joints

HESSIAN_MODES = ("exact", "psd")
ORIGINS = ("q_ref", "absolute")
EDGE_SHAPES = {"edges": (2, 3), "local_edges": (2, 2, 3)}
"""A batch's joint geometry, one of these per joint (CONTRACT.md v1.2): world edges or body-local edges."""


def _where(mask: np.ndarray) -> list[int]:
    if not mask.any():  # the common case: one flat reduction, no index array
        return []
    return [int(i) for i in np.flatnonzero(mask)[:MAX_FAULTS]]


def nonfinite_rows(a: np.ndarray) -> list[int]:
    """The first `MAX_FAULTS` rows of `a` (N, ...) holding a NaN or an infinity; N may be 0."""
    finite = np.isfinite(a)
    if finite.all():  # the common case: a flat reduction, much cheaper than one per row
        return []
    return _where(~finite.all(axis=tuple(range(1, a.ndim))))


def nonfinite_faults(a: np.ndarray, *loc: str | int) -> list[Fault]:
    """One fault per NaN or infinity of `a` (the first `MAX_FAULTS`), located to the element as JSON's
    parser locates it (`bodies.q.1.4`, `batches.1.edges.2.1.0`)."""
    if np.isfinite(a).all():  # the common case: one flat reduction
        return []
    return [
        Fault((*loc, *map(int, at)), NONFINITE_MSG, NONFINITE_TYPE)
        for at in np.argwhere(~np.isfinite(a))[:MAX_FAULTS]
    ]


def literal_msg(allowed: Sequence[str]) -> str:
    """pydantic's words for a value outside a set of strings: "Input should be 'a', 'b' or 'c'"."""
    quoted = [repr(a) for a in allowed]
    return "Input should be " + (", ".join(quoted[:-1]) + " or " + quoted[-1] if len(quoted) > 1 else quoted[0])


DUPLICATE_KEY_MSG = "Duplicate key: each key may appear once in an object (a msgpack map)"
NOT_A_LIST = ("Input should be a valid list", "list_type")
NOT_A_NUMBER = ("Input should be a valid number", "float_type")
NOT_AN_INTEGER = ("Input should be a valid integer", "int_type")
"""pydantic's words for these mistakes in JSON: every path (msgpack, sessions, the SDK) says the same."""


ROWS: dict[str | int, tuple[int, ...]] = {
    "q": (12,), "q_prev": (12,), "q_ref": (12,), "body_ids": (2,), "edges": (2, 3), "local_edges": (2, 2, 3),
    **dict.fromkeys(("lower", "upper", "strength", "offset", "prev_coordinate", "index"), ()),
}
"""The wire's shape of one item of each array (schemas/evaluate.py, schemas/session.py), by its name."""


def as_array(value: Any, loc: Loc, integer: bool = False) -> tuple[np.ndarray | None, list[Fault]]:
    """`value` (nested lists of numbers, or an array) as a float64 (int64) array of whatever shape it has (the
    shape checks judge it), else the faults that prevent it, each at its element: not a list, not a number,
    ragged rows (for an array the wire names, `ROWS` by the last key of `loc`, where its schema names them).
    JSON's `null` is NaN (named as non-finite later), as a NaN-less JSON writer means it."""
    if isinstance(value, (list, tuple)):
        try:  # numbers only, rectangular: NumPy builds it at C speed (the Python walk below names a fault)
            fast = np.asarray(value)
        except (ValueError, TypeError, OverflowError):
            fast = None
        if fast is not None and fast.dtype.kind in ("iu" if integer else "fiu"):
            value = fast
    if isinstance(value, np.ndarray) and value.ndim >= 1 and value.dtype.kind in ("iu" if integer else "fiu"):
        return value.astype(np.int64 if integer else np.float64, copy=False), []
    faults = _element_faults(value, loc, integer, ROWS.get(loc[-1]) if loc else None)
    if faults:
        return None, faults
    try:
        return np.array(value, dtype=np.int64 if integer else np.float64), []
    except OverflowError:  # an integer past float64 (JSON's 1 and 400 zeros; int64's are named above): +-inf, as 1e400
        return np.array(_past_range(value), dtype=np.float64), []  # the finiteness check names each element


def _past_range(value: Any) -> Any:
    """Nested lists `value` (or an object array: the SDK's), each integer that rounds past float64 (from 2^1024 - 2^970)
    made +-inf."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_past_range(x) for x in value]
    return value if not isinstance(value, int) or abs(value) < 2**1024 - 2**970 else np.inf if value > 0 else -np.inf


def _element_faults(value: Any, loc: Loc, integer: bool, row: tuple[int, ...] | None = None) -> list[Fault]:
    """The first element fault of `value`, or the first mismatch of row shapes."""
    value = value.tolist() if isinstance(value, np.ndarray) else value
    shape = _shape_of(value, loc, integer, row) if isinstance(value, (list, tuple)) else [Fault(loc, *NOT_A_LIST)]
    return shape if isinstance(shape, list) else []


def _shape_of(value: list | tuple, loc: Loc, integer: bool, row: tuple[int, ...] | None = None) -> tuple[int, ...] | list[Fault]:
    """The shape of nested lists `value` (of items of shape `row`, if given), or a fault: an item not a number
    (or list), or ragged rows."""
    if not value:
        return (0,)
    nested = isinstance(value[0], (list, tuple, np.ndarray)) if row is None else len(row) > 0
    if not nested:
        # pydantic's strict integers: 0.0 is a float, on every path (issue 27); None is a NaN, a bool no number
        kinds = (int, np.integer) if integer else (int, float, np.integer, np.floating, type(None))
        for i, x in enumerate(value):
            if isinstance(x, bool) or not isinstance(x, kinds):
                return [Fault((*loc, i), *(NOT_AN_INTEGER if integer else NOT_A_NUMBER))]
            if integer and not -(2**63) <= x < 2**63:  # pydantic's words for JSON's int64 bounds
                words = ("less_than_equal", "less than or equal to", 2**63 - 1) if x > 0 else ("greater_than_equal", "greater than or equal to", -(2**63))
                return [Fault((*loc, i), f"Input should be {words[1]} {words[2]}", words[0])]
        return (len(value),)
    shapes = []
    for i, item in enumerate(value):
        if not isinstance(item, (list, tuple, np.ndarray)):
            return [Fault((*loc, i), *NOT_A_LIST)]
        got = _shape_of(list(item), (*loc, i), integer, None if row is None else row[1:])
        if isinstance(got, list):
            return got
        shapes.append(got)
    counts = Counter(shapes)  # the odd row out is the one at fault (on a tie, not the first: dicts keep order),
    # or the first not of the wire's shape when it is known
    usual = row if row in counts else max(counts, key=counts.__getitem__)
    for i, got in enumerate(shapes):
        if got != usual:
            return [Fault((*loc, i), f"has shape {got} where the other rows have {usual}: the rows of an array are alike")]
    return (len(value), *usual)


def check_options(outputs: Sequence[str], hessian_mode: str) -> list[Fault]:
    """The options, in the words JSON's parser (pydantic) uses for them: every path says the same."""
    faults = [Fault(("outputs", i), literal_msg(OUTPUTS), "literal_error") for i, o in enumerate(outputs) if o not in OUTPUTS]
    if not outputs:
        faults.append(Fault(("outputs",), "List should have at least 1 item after validation, not 0", "too_short"))
    if hessian_mode not in HESSIAN_MODES:
        faults.append(Fault(("hessian_mode",), literal_msg(HESSIAN_MODES), "literal_error"))
    return faults


def check_bodies(bodies: Bodies, names: Sequence[str] = ("q", "q_prev", "q_ref")) -> list[Fault]:
    """Shape (B, 12) and finiteness of the states `names`; B is the first named state's row count."""
    first = getattr(bodies, names[0])
    n = np.shape(first)[0] if np.ndim(first) else 0
    return [f for name in names for f in check_dofs(name, getattr(bodies, name), n)]


def check_dofs(name: str, a: np.ndarray, n: int) -> list[Fault]:
    """One state `a` of the bodies: (n, 12) finite numbers (`loc` ("bodies", name, row))."""
    if a.ndim != 2 or a.shape[1] != 12 or a.shape[0] != n:
        hint = POSE_HINT if a.shape[-2:] == (4, 4) else ""
        return [Fault(("bodies", name), f"must be {n} row{'' if n == 1 else 's'} of 12 numbers, got shape {a.shape}{hint}")]
    return nonfinite_faults(a, "bodies", name)


POSE_HINT = (
    ": 4x4 poses? A body's 12 DOFs are [p, A row 0, A row 1, A row 2] of its transform [[A, p], [0, 1]]; "
    "the Python SDK's jointlimits.client.scene.dofs(pose) converts one"
)


def check_rotations(rotation_ratio: np.ndarray) -> list[Fault]:
    """Bodies whose `A_ref` is too close to singular for a polar factor (`rotation_ratio` (B,) = s_min / s_max)."""
    return [
        Fault(("bodies", "q_ref", i), f"A_ref is singular (smallest/largest singular value < {SINGULAR_RATIO:g})")
        for i in _where(~(rotation_ratio >= SINGULAR_RATIO))
    ]


def _rows(b: int, name: str, mask: np.ndarray, msg: Callable[[int], str], index: np.ndarray | None = None,
          type: str = "value_error") -> list[Fault]:
    """A fault at ("batches", b, name, joint) per True row `j` of `mask` (the first `MAX_FAULTS`), in the words
    `msg(j)`; the joint is `index[j]` if given, else `j`."""
    return [Fault(("batches", b, name, j if index is None else int(index[j])), msg(j), type) for j in _where(mask)]


def _empty_ranges(b: int, lower: np.ndarray, upper: np.ndarray, mask: np.ndarray,
                  index: np.ndarray | None = None) -> list[Fault]:
    return _rows(b, "lower", mask, lambda j: f"lower {float(lower[j])!r} > upper {float(upper[j])!r}: the range is empty",
                 index)


def _negative_strengths(b: int, strength: np.ndarray, mask: np.ndarray, index: np.ndarray | None = None) -> list[Fault]:
    return _rows(b, "strength", mask, lambda j: f"strength {float(strength[j])!r} < 0: must be >= 0", index)


def check_joints(b: int, joints: Joints, n_bodies: int) -> list[Fault]:
    """Every fault of batch `b`, of every class at once (structure, indices, ranges, geometry), up to the cap.

    A field of the wrong shape is named once and its rows are not read; the rows of the others are still
    checked, so a body index out of range does not hide `lower > upper` of another joint.
    """
    with np.errstate(all="ignore"):  # overflowing edges and offsets are named, not warned of
        return joint_faults(b, joints, n_bodies)[0]


def joint_faults(b: int, joints: Joints, n_bodies: int) -> tuple[list[Fault], Array | None]:
    """`check_joints` under the caller's `np.errstate`, and the edge vectors (N, 3) it took, `p1 - p0` (or
    `l1 - l0`; None where the geometry is not one field of its shape): the pipeline's axes start from them."""
    given = [k for k in EDGE_SHAPES if getattr(joints, k) is not None]
    geometry = given[0] if len(given) == 1 else None
    faults = _check_kind(b, joints, given)
    shaped = _check_shapes(b, joints, geometry, faults)
    edge = None
    if geometry in shaped:
        edge = edge_vector(joints.edges if geometry == "edges" else joints.local_edges[:, 0])
    if not faults and _clean(joints, n_bodies, edge):  # the common case: no per-joint check names anything
        return [], edge
    return (faults + _check_rows(b, joints, n_bodies, geometry, shaped, edge))[:MAX_FAULTS], edge


def _clean(joints: Joints, n_bodies: int, edge: Array) -> bool:
    """True only where `_check_rows` finds nothing, from a few flat reductions of a well-shaped batch: `up - lo`, the
    strengths and `dot(edge, edge)` are >= 0 (the last > 0) with a finite sum only where their fields are finite, in
    order and an edge has an axis (a NaN or an infinity survives a sum; an underflow or an overflow here, a sum that
    overflows among them, takes `_check_rows`' way)."""
    ids = joints.body_ids
    if ids.shape[0] == 0 or not (ids.min() >= 0 and ids.max() < n_bodies and (ids[:, 0] != ids[:, 1]).all()):
        return False
    d2 = np.add.reduce(edge * edge, axis=1)
    signed = np.concatenate((joints.upper - joints.lower, joints.strength, d2))
    rest = [a for a in (joints.offset, joints.prev_coordinate, None if joints.edges is not None else joints.local_edges[:, 1])
            if a is not None]  # r0, r1 of body-local edges are not in `edge`
    return bool(signed.min() >= 0 and d2.min() > 0) and math.isfinite(sum(np.add.reduce(a, None) for a in (signed, *rest)))


def _check_kind(b: int, joints: Joints, given: list[str]) -> list[Fault]:
    """The batch's constitution, base, geometry kind (`given`: its edge fields), origin and state fields."""
    faults: list[Fault] = []
    c = CONSTITUTIONS.get(joints.constitution_uid)
    if c is None:
        known = ", ".join(str(f.uid) for f in CONSTITUTIONS.values())
        faults.append(Fault(("batches", b, "constitution_uid"), f"unknown constitution {joints.constitution_uid}; supported: {known}"))
    elif joints.base_uid != c.base_uid:
        msg = f"constitution {c.uid} ({c.name}) needs base_uid {c.base_uid}, got {joints.base_uid}"
        faults.append(Fault(("batches", b, "base_uid"), msg))
    if len(given) != 1:
        said = "both" if given else "neither"
        faults.append(Fault(("batches", b), f"give exactly one of edges and local_edges (world edges (N, 2, 3) at q_ref, or body-local (N, 2, 2, 3)); got {said}"))
    if joints.origin not in ORIGINS:
        faults.append(Fault(("batches", b, "origin"), "Input should be 'q_ref' or 'absolute'", "literal_error"))
    if joints.prev_coordinate is not None and c is not None and not c.stateful:
        which = ", ".join(f"{f.kind} joints ({f.uid})" for f in CONSTITUTIONS.values() if f.stateful)
        msg = f"applies to {which} only: the {c.name} coordinate is absolute and has no state"
        faults.append(Fault(("batches", b, "prev_coordinate"), msg))
    return faults


def _check_shapes(b: int, joints: Joints, geometry: str | None, faults: list[Fault]) -> set[str]:
    """Appends a fault per per-joint field that is not one row per joint of `body_ids`; returns the others."""
    n = joints.body_ids.shape[0] if joints.body_ids.ndim == 2 else -1
    want = {"body_ids": (n, 2), "lower": (n,), "upper": (n,), "strength": (n,)}
    if geometry is not None:
        want[geometry] = (n, *EDGE_SHAPES[geometry])
    want |= {k: (n,) for k in ("offset", "prev_coordinate") if getattr(joints, k) is not None}  # v1.1's optional lists
    shaped = set()
    for name, shape in want.items():
        a = getattr(joints, name)
        if a.shape == shape:
            shaped.add(name)
        else:
            faults.append(Fault(("batches", b, name), f"must have shape {shape} (one row per joint of body_ids), got {a.shape}"))
    return shaped


def _check_rows(b: int, joints: Joints, n_bodies: int, geometry: str | None, shaped: set[str],
                edge: Array | None) -> list[Fault]:
    """Per-joint faults of the fields in `shaped`: non-finite numbers, indices, ranges, edges (`edge` their
    vectors)."""
    faults: list[Fault] = []
    for name in (geometry, "lower", "upper", "strength", "offset", "prev_coordinate"):
        if name in shaped:
            faults += nonfinite_faults(getattr(joints, name), "batches", b, name)
    if "body_ids" in shaped:
        ids = joints.body_ids
        there = "there is 1 body" if n_bodies == 1 else f"there are {n_bodies} bodies"
        faults += _rows(b, "body_ids", ((ids < 0) | (ids >= n_bodies)).any(axis=1),
                        lambda j: f"body index {ids[j].tolist()} out of range [0, {n_bodies}) ({there})")
        faults += _rows(b, "body_ids", ids[:, 0] == ids[:, 1], lambda j: f"joint couples body {ids[j, 0]} to itself")
    # The range checks read finite rows only: a row with a NaN or an infinity is named above, once.
    lo, up, s = joints.lower, joints.upper, joints.strength
    if {"lower", "upper"} <= shaped:
        both = np.isfinite(lo) & np.isfinite(up)
        faults += _empty_ranges(b, lo, up, both & (lo > up))
    if "strength" in shaped:
        faults += _negative_strengths(b, s, np.isfinite(s) & (s < 0))
    if edge is not None:
        faults += _check_edges(b, joints, geometry, edge)
    return faults


def _check_edges(b: int, joints: Joints, geometry: str, edge: Array) -> list[Fault]:
    """Exactly the edges `kinematics.axis` cannot normalise (it scales the edge vector `edge` (N, 3) by a power of
    two first: any nonzero, finite difference has an axis; a body-local one is then carried by a nonsingular A_ref)."""
    p0, p1 = ("p0", "p1") if geometry == "edges" else ("l0", "l1")
    size = max_abs(edge)
    # A non-finite edge is named as such (`_check_rows`), not as too long.
    ends = joints.edges if geometry == "edges" else joints.local_edges[:, 0]  # p0 -> p1, or l0 -> l1 on body i
    size[~np.isfinite(size) & ~np.isfinite(ends).all(axis=(1, 2))] = 1.0
    return _rows(b, geometry, size == 0, lambda j: f"zero-length edge: {p0} == {p1} gives no joint axis") + _rows(
        b, geometry, ~np.isfinite(size), lambda j: f"edge too long: {p1} - {p0} overflows float64")


def check_moved(b: int, x: np.ndarray, offset: np.ndarray, index: NDArray[np.int64]) -> list[Fault]:
    """Joints `index` (M,) of batch `b` whose coordinate `x + offset` (each (M,)) a new offset would overflow."""
    return _rows(b, "offset", ~np.isfinite(x + offset), lambda j: "the coordinate x + offset overflows float64", index)


def check_update_index(b: int, n_batches: int, n_joints: int, index: np.ndarray) -> list[Fault]:
    """The joints `index` of an update of batch `b`: distinct, in range (the batch has `n_joints`)."""
    if not 0 <= b < n_batches:
        return [Fault(("batches", b), f"no batch {b}: the scene has {n_batches} batch{'' if n_batches == 1 else 'es'}")]
    if index.ndim != 1 or not np.issubdtype(index.dtype, np.integer):
        return [Fault(("batches", b, "index"), f"must be a 1-d array of joint indices, got {index.dtype} of shape {index.shape}")]
    faults = _rows(b, "index", (index < 0) | (index >= n_joints), lambda i: f"joint index {int(index[i])} out of range [0, {n_joints})")
    if not faults and np.unique(index).shape[0] != index.shape[0]:
        faults.append(Fault(("batches", b, "index"), "names a joint more than once"))
    return faults


def check_update_values(b: int, index: np.ndarray, values: dict[str, np.ndarray]) -> list[Fault]:
    """The new `values` (name -> (M,)) of joints `index` (M,) of batch `b`: one finite number per index."""
    faults = [
        Fault(("batches", b, name), f"must have shape {index.shape} (one entry per index), got {a.shape}")
        for name, a in values.items()
        if a.shape != index.shape
    ]
    if faults:
        return faults
    for name, a in values.items():
        faults += _rows(b, name, ~np.isfinite(a), lambda j: NONFINITE_MSG, index, NONFINITE_TYPE)
    return faults


def check_update_ranges(b: int, index: np.ndarray, lower: np.ndarray, upper: np.ndarray, strength: np.ndarray) -> list[Fault]:
    """Joints `index` (M,) of batch `b` with their values after an update, each (M,): the request's range checks."""
    return _empty_ranges(b, lower, upper, lower > upper, index) + _negative_strengths(b, strength, strength < 0, index)


def check_evaluation(ev: Evaluation) -> list[Fault]:
    """Faults of a finished evaluation that would put NaN or Infinity in an answer: the core names overflowing
    energies and derivatives itself; this also catches an overflowed `x` of an inactive joint (x = NaN has no
    gap, so zero energy). (A total energy that overflows: `PreparedScene._run`, before the answer exists.)"""
    return check_coordinates([(b, r.index, r.x, r.coordinate) for b, r in enumerate(ev.batches)])


def check_coordinates(batches: Sequence[tuple[int, NDArray[np.int64], Array, Array | None]]) -> list[Fault]:
    """Per batch (its number `b`, joints `index`, their `x` and `coordinate` (M,) or None), the joints whose x or
    coordinate is not finite: an answer's, a commit's, the committed coordinates a session reports."""
    faults = [
        Fault(("batches", b, "body_ids", int(index[i])), "the joint coordinate x overflows float64 at this configuration (positions or edge too large)")
        for b, index, x, _ in batches
        for i in nonfinite_rows(x)
    ]
    faults += [
        Fault(("batches", b, "offset", int(index[i])), "the coordinate x + offset overflows float64")
        for b, index, x, c in batches
        if c is not None and not np.isfinite(c).all()  # the common case: one flat test
        for i in _where(np.isfinite(x) & ~np.isfinite(c))
    ]
    return faults[:MAX_FAULTS]


def raise_if(faults: list[Fault]) -> None:
    if faults:
        raise InputError(faults)
