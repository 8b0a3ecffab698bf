"""Typed, NumPy-backed requests and results of the SDK (the wire's structure, arrays instead of lists), and what
`evaluate` takes made one `Request` (`as_request`: a `Request`, a wire JSON dict, a `schemas.EvaluateRequest`)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import orjson
from numpy.typing import ArrayLike, NDArray

from jointlimits.client.errors import InvalidInput
from jointlimits.schemas import OUTPUTS, EvaluateRequest
from jointlimits.service.core import prismatic, registry, revolute
from jointlimits.service.core.assembled import Assembled  # noqa: F401 (re-exported: Evaluation.assembled)
from jointlimits.service.core.errors import MAX_FAULTS, Fault
from jointlimits.service.core.validate import NOT_A_LIST, as_array

Array = NDArray[np.float64]


def invalid(faults: list[Fault], where: str) -> InvalidInput:
    """The validator's faults as the `InvalidInput` the service would answer (`where`: the constructor)."""
    return InvalidInput(422, faults[:MAX_FAULTS], where=f"invalid input ({where})")


def in_body(faults: list[Fault]) -> InvalidInput:
    """Faults named before or instead of the service, as the `InvalidInput` it would answer (`loc`s after "body")."""
    return InvalidInput(422, [replace(f, loc=("body", *f.loc)) for f in faults], where="invalid input")


def as_outputs(outputs: Any) -> tuple[str, ...]:
    """`outputs` as the wire's list: a list, tuple or array of names, or one name alone (a bare string asks for that
    output: `outputs="energy"`); anything else is the wire's fault for a value where a list belongs, on every path
    (Client, LocalClient, sessions). The names themselves are checked where the service checks them."""
    if isinstance(outputs, str):
        return (outputs,)
    if isinstance(outputs, (list, tuple, np.ndarray)):
        return tuple(np.asarray(outputs).tolist() if isinstance(outputs, np.ndarray) else outputs)
    raise in_body([Fault(("outputs",), *NOT_A_LIST)])


def as_flag(value: Any) -> bool:
    """`active_only` as the wire reads it, a strict boolean (numpy's too): 1 or "false" is its fault on every path,
    not a truthy True."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise in_body([Fault(("active_only",), "Input should be a valid boolean", "bool_type")])


def _array(value: ArrayLike, name: str, faults: list[Fault], integer: bool = False) -> np.ndarray | None:
    """`value` as an array, or None after adding the faults that prevent it (in the service's words)."""
    scalar = not isinstance(value, (list, tuple, np.ndarray))  # one value for every joint
    a, found = as_array([value] if scalar else value, (name,), integer)
    if found:
        faults += [Fault((name,), f.msg, f.type) for f in found] if scalar else found
        return None
    return a.reshape(()) if scalar else a


def _wrong_shape(name: str, a: np.ndarray, want: tuple[int, ...], faults: list[Fault]) -> None:
    faults.append(Fault((name,), f"must have shape {want} (one row per joint of body_ids), got {a.shape}"))


REVOLUTE_LIMIT, PRISMATIC_LIMIT = revolute.FACTS.uid, prismatic.FACTS.uid
NEEDED, OPTIONAL = ("body_ids", "lower", "upper", "strength"), ("edges", "local_edges", "offset", "prev_coordinate")
"""A `JointBatch`'s arrays: those it needs, and those it may leave None (one of the edges; v1.1's)."""


@dataclass
class JointBatch:
    """N joints of one constitution. `body_ids` (N, 2), `edges` (N, 2, 3) world space at q_ref,
    `lower`, `upper`, `strength` (N,); v1.1, optional: `offset` (N,) (coordinate = x + offset; the
    limits bound the coordinate) and, for 670, `prev_coordinate` (N,) (the committed coordinate at q_prev);
    v1.2: `local_edges` (N, 2, 2, 3) instead of `edges` (`[[l0, l1], [r0, r1]]` in bodies i's and j's
    own coordinates, the reference engine's local variant) and `origin` ("q_ref" or "absolute")."""

    constitution_uid: int
    body_ids: NDArray[np.int64]
    edges: Array | None
    lower: Array
    upper: Array
    strength: Array
    base_uid: int | None = None
    """Defaults to the constitution's base joint (its registered `base_uid`: 18 for 670, 20 for 669)."""
    offset: Array | None = None
    prev_coordinate: Array | None = None
    local_edges: Array | None = None
    origin: str = "q_ref"
    """"q_ref": x = 0 at q_ref (the specs); "absolute": the reference engine's zero (CONTRACT.md v1.2)."""

    def __post_init__(self) -> None:
        if self.base_uid is None:
            self.base_uid = registry.base_uid_of(self.constitution_uid)

    @classmethod
    def of(cls, constitution_uid: int, body_ids: ArrayLike, edges: ArrayLike | None, lower: ArrayLike,
           upper: ArrayLike, strength: ArrayLike = 1.0, *, offset: ArrayLike | None = None,
           prev_coordinate: ArrayLike | None = None, local_edges: ArrayLike | None = None,
           origin: str = "q_ref") -> JointBatch:
        """From array-likes; scalar `lower`, `upper`, `strength`, `offset`, `prev_coordinate` apply to every joint.

        Give the joints' geometry as world `edges` (N, 2, 3) at q_ref, or as body-local `local_edges`
        (N, 2, 2, 3) with `edges=None` (a libuipc scene's local variant; `origin="absolute"` for its zero).
        A solver that keeps its own state commits a time step by passing the `coordinate` it got at
        the accepted `q` as the next step's `prev_coordinate` (with `q_prev` := that `q`).
        """
        faults: list[Fault] = []
        ids = _array(body_ids, "body_ids", faults, integer=True)
        if ids is not None and ids.shape == (2,):
            ids = ids.reshape(1, 2)  # one joint's pair
        if ids is not None and (ids.ndim != 2 or ids.shape[1] != 2):
            faults.append(Fault(("body_ids",), f"must have shape (N, 2), one [i, j] per joint, got {ids.shape}"))
            ids = None
        n = -1 if ids is None else ids.shape[0]

        def shaped(name: str, v: ArrayLike | None, *tail: int) -> np.ndarray | None:
            a = None if v is None else _array(v, name, faults)
            if a is not None and a.shape == tail and n == 1:
                a = a.reshape(1, *tail)  # one joint's edge
            return a if a is None or n < 0 or a.shape == (n, *tail) else _wrong_shape(name, a, (n, *tail), faults)

        def per_joint(name: str, v: ArrayLike | None) -> np.ndarray | None:
            a = None if v is None else _array(v, name, faults)
            if a is None or n < 0:
                return a
            return np.broadcast_to(a, (n,)).copy() if a.shape in ((), (1,), (n,)) else _wrong_shape(name, a, (n,), faults)

        numbers = {"lower": lower, "upper": upper, "strength": strength, "offset": offset,
                   "prev_coordinate": prev_coordinate}
        batch = cls(constitution_uid, ids, shaped("edges", edges, 2, 3),  # type: ignore[arg-type]
                    local_edges=shaped("local_edges", local_edges, 2, 2, 3), origin=origin,
                    **{k: per_joint(k, v) for k, v in numbers.items()})  # type: ignore[arg-type]
        if faults:
            raise invalid(faults, "JointBatch.of")
        return batch

    def __len__(self) -> int:
        return int(np.shape(self.body_ids)[0])

    def key(self, row: int) -> tuple:
        """Which joint row `row` is, as its `Joint` handle knows it (`joint_key`)."""
        edges = self.edges if self.edges is not None else self.local_edges  # array-likes: a batch built by hand
        return joint_key(np.asarray(self.body_ids)[row], np.asarray(edges)[row], self.origin)


def joint_key(body_ids: NDArray[Any], edge: NDArray[Any], origin: str) -> tuple:
    """Which joint it is, for a `Joint` handle: its bodies (2,), its edge (2, 3) or (2, 2, 3) as nested lists, its
    origin; not its limits, strength or offset (a `Robot` rebuilds the same joints with others)."""
    return tuple(body_ids.tolist()), edge.tolist(), origin


@dataclass
class Request:
    """Bodies `q`, `q_prev`, `q_ref` (B, 12) and the joint batches that refer to them by row."""

    q: Array
    q_prev: Array
    q_ref: Array
    batches: list[JointBatch]
    outputs: tuple[str, ...] = OUTPUTS
    """Names of `OUTPUTS`; one name alone (`"energy"`) asks for that output (`as_outputs`)."""
    hessian_mode: str = "exact"
    active_only: bool = False
    layout: str = "joints"
    """"bodies": `Evaluation.assembled` holds the gradient and Hessian summed per body; batches carry none."""

    def __post_init__(self) -> None:
        self.outputs, self.active_only = as_outputs(self.outputs), as_flag(self.active_only)

    @property
    def n_joints(self) -> int:
        return sum(len(b) for b in self.batches)


def null_arrays(request: Request) -> list[Fault]:
    """None or a scalar where an array is needed (a state of the bodies, a batch's `body_ids`, `lower`, `upper`,
    `strength`; a given `edges`, `offset`, ...), named as the service names a `null` or a number there (a None
    optional array is an absent one)."""
    not_a_list = lambda a, need: (a is None and need) or (a is not None and np.ndim(a) == 0)  # noqa: E731
    faults = [Fault(("bodies", k), *NOT_A_LIST) for k in ("q", "q_prev", "q_ref") if not_a_list(getattr(request, k), True)]
    return faults + [Fault(("batches", b, k), *NOT_A_LIST) for b, batch in enumerate(request.batches)
                     for k in NEEDED + OPTIONAL if not_a_list(getattr(batch, k), k in NEEDED)]


_ACCEPTED = ("a client.Request (Scene().request(), request_from_arrays(...)), a dict in the wire JSON's shape, "
             "or a schemas.EvaluateRequest")


def _plain(a: Any) -> Any:
    """A NumPy array or scalar as Python numbers (`tolist`: a float32 widened exactly, as `np.asarray(a, np.float64)`)."""
    if isinstance(a, (np.ndarray, np.generic)):
        return a.tolist()
    raise TypeError(f"Type is not JSON serializable: {type(a).__module__}.{type(a).__qualname__}")


def as_request(request: Any) -> Request:
    """`request` as a `Request`.

    A dict (or an `EvaluateRequest`, as its dict) is read exactly as the service reads a JSON body (NumPy
    arrays in it are fine): its faults raise `InvalidInput` with the server's `loc`s and words. Anything
    else: `TypeError`.
    """
    if isinstance(request, Request):
        return request
    if isinstance(request, EvaluateRequest):
        request = request.model_dump(exclude_none=True)  # an absent optional field, as the wire has it
    if not isinstance(request, dict):
        raise TypeError(f"evaluate() takes {_ACCEPTED}; got {type(request).__module__}.{type(request).__qualname__}")
    try:  # NumPy values as Python's (a float32 at its value, not orjson's shortest float32 decimal: 0.7 for 0.69999999)
        body = orjson.dumps(request, default=_plain)
    except TypeError as e:
        try:  # an integer past 64 bits (orjson's bound, not JSON's: the server reads it): the standard library's JSON
            body = json.dumps(request, default=_plain).encode()
        except (TypeError, ValueError, RecursionError):  # (orjson's own depth limit is its TypeError)
            raise TypeError(f"evaluate(): the dict is not wire JSON ({e})") from None
    # The service's own JSON reader (imported here: HTTP alone never loads it): the same faults, in the same words.
    from jointlimits.service.core import InputError
    from jointlimits.service.http.convert import read

    try:
        kw = read(body)
    except InputError as e:
        raise in_body(e.faults) from None
    b = kw["bodies"]
    # The core's `Joints` has the SDK's `JointBatch` fields, by the same names.
    batches = [JointBatch(**{f.name: getattr(j, f.name) for f in fields(JointBatch)}) for j in kw["batches"]]
    return Request(b.q, b.q_prev, b.q_ref, batches, tuple(kw["outputs"]), kw["hessian_mode"], kw["active_only"],
                   kw["layout"])


class Joint(int):
    """A joint's handle, as `Scene.add_revolute_limit` / `add_prismatic_limit` return it.

    It is the joint's row in its batch (an `int`: `result.batches[j.batch].energy[j]` indexes rows) and
    knows its `constitution_uid` and its batch's position in the request, so `result.joint(j)` finds
    it whatever the batch (a scene with world and body-local edges, or both origins, has several
    batches of one constitution), and which joint it is (`JointBatch.key`): another scene's row is not read.
    """

    constitution_uid: int
    batch: int | None
    key: tuple | None

    def __new__(cls, row: int, constitution_uid: int, batch: int | None = None, key: tuple | None = None) -> Joint:
        self = super().__new__(cls, row)
        self.constitution_uid, self.batch, self.key = constitution_uid, batch, key
        return self

    def __getnewargs__(self) -> tuple[int, int, int | None, tuple | None]:  # pickle and copy keep all of it
        return int(self), self.constitution_uid, self.batch, self.key

    def __repr__(self) -> str:
        at = "" if self.batch is None else f", batch={self.batch}"
        return f"Joint({int(self)}, constitution_uid={self.constitution_uid}{at})"


@dataclass(frozen=True, repr=False)
class JointResult:
    """One joint's answer: `energy` (float), `gradient` (24,), `hessian` (24, 24) in the DOFs `[q_i, q_j]`.

    A joint inside its range (bounds included) has exact zeros for energy and derivatives. Under
    `active_only` such a joint is not in the answer at all: it reads as zero energy and zero
    derivatives, and `x` is None (the answer does not carry it; ask without `active_only` to get
    every `x`). `gradient` / `hessian` are None when the request did not ask for them.
    """

    constitution_uid: int
    row: int
    x: float | None
    energy: float
    gradient: Array | None
    hessian: Array | None
    coordinate: float | None = None
    """v1.1: x + offset (None where `x` is, or from a v1 server)."""

    def __repr__(self) -> str:
        # A summary: the Hessian alone is 24 x 24 numbers.
        shapes = ", ".join(f"{k}={'None' if v is None else 'array' + str(v.shape)}"
                           for k, v in (("gradient", self.gradient), ("hessian", self.hessian)))
        return (f"JointResult(constitution_uid={self.constitution_uid}, row={self.row}, x={self.x!r}, "
                f"coordinate={self.coordinate!r}, energy={self.energy!r}, {shapes})")


@dataclass(repr=False)
class BatchResult:
    """Rows `index` (M,) of a request batch: `x`, `energy` (M,), `gradient` (M, 24), `hessian` (M, 24, 24),
    and `coordinate` (M,) = x + offset (v1.1; None from a v1 server).

    Gradients and Hessians are in the DOFs `[q_i, q_j]` of the joint's two bodies. Without
    `active_only` row `k` is joint `k` (`index == arange(N)`); with it the rows are only the
    joints outside their range, so index by joint with `joint(k)`, not `x[k]`.
    """

    constitution_uid: int
    index: NDArray[np.int64]
    x: Array
    energy: Array
    gradient: Array | None = None
    hessian: Array | None = None
    coordinate: Array | None = None
    size: int | None = None
    """Joints in the request's batch (N); the clients set it, so `joint` can tell an inactive joint from no joint."""
    request: JointBatch | None = None
    """The request's batch; the clients set it, so `joint` can tell a handle of another scene's joint at its row."""

    def outputs(self) -> list[str]:
        """What this answer carries: `x`, `energy`, and `gradient` / `hessian` when asked for."""
        return ["x", "energy"] + [k for k in ("gradient", "hessian") if getattr(self, k) is not None]

    def __repr__(self) -> str:
        # A summary: the arrays themselves are ~250 lines per joint with Hessians.
        n = len(self.index) if self.size is None else self.size
        of = f" of {self.size}" if self.size is not None else ""
        return (f"BatchResult(constitution_uid={self.constitution_uid}, rows={len(self.index)}{of} "
                f"joint{'' if n == 1 else 's'}, "
                f"energy sum={float(np.sum(self.energy))!r}, outputs={', '.join(self.outputs())})")

    def joint(self, k: int) -> JointResult:
        """Joint `k` of the request's batch (its row there, or a `Joint` handle), with or without `active_only`.

        Raises `IndexError` when the batch has no joint `k`.
        """
        handle, k = k, int(k)
        if k < 0 or (self.size is not None and k >= self.size):
            raise IndexError(f"joint {k} out of range: the batch has {self.size} joint{'' if self.size == 1 else 's'}")
        here = None if self.request is None or getattr(handle, "key", None) is None else self.request.key(k)
        if here is not None and here != handle.key:  # type: ignore[union-attr]
            raise KeyError(f"{handle!r} is not a joint of this answer's request (its row there is another joint, "
                           f"{here}): pass the handle of the Scene that made it, or of one of the same joints")
        index = np.asarray(self.index)
        at = int(np.searchsorted(index, k))  # index is ascending (rows in request order)
        if at < index.size and index[at] == k:
            pick = lambda a: None if a is None else a[at]  # noqa: E731
            coordinate = None if self.coordinate is None else float(self.coordinate[at])
            return JointResult(self.constitution_uid, k, float(self.x[at]), float(self.energy[at]),
                               pick(self.gradient), pick(self.hessian), coordinate)
        if self.size is None and (index.size == 0 or k > index[-1]):
            raise IndexError(f"joint {k} is not in this answer (its batch size is unknown)")
        zeros = lambda a, shape: None if a is None else np.zeros(shape)  # noqa: E731
        return JointResult(self.constitution_uid, k, None, 0.0,
                           zeros(self.gradient, 24), zeros(self.hessian, (24, 24)))


@dataclass(repr=False)
class Evaluation:
    """The answer: `total_energy` and one `BatchResult` per request batch, in request order."""

    total_energy: float
    batches: list[BatchResult] = field(default_factory=list)
    assembled: Assembled | None = None
    """With `layout="bodies"`: `.gradient` (B, 12), `.rows`, `.cols`, `.blocks` (K, 12, 12), `.matrix()` (scipy)."""

    def batch(self, constitution_uid: int) -> BatchResult:
        """The first batch of a constitution (a `Scene` makes more where edges, origins or states differ)."""
        for b in self.batches:
            if b.constitution_uid == constitution_uid:
                return b
        raise KeyError(f"no batch of constitution {constitution_uid}")

    def __repr__(self) -> str:
        """A summary (batches, joints, total energy, outputs); the arrays are in `batches`."""
        rows = "".join(f"\n  {b!r}," for b in self.batches)
        return f"Evaluation(total_energy={self.total_energy!r}, batches=[{rows}{chr(10) if rows else ''}])"

    def sized(self, request: Request) -> Evaluation:
        """Itself, each batch told how many joints its request batch has (what `joint` needs under `active_only`),
        and told the request's batches (what `joint` checks a handle against)."""
        for r, b in zip(self.batches, request.batches):
            r.size, r.request = len(b), b
        if self.assembled is not None and self.assembled.n_bodies < 0:  # a session's reply does not say
            self.assembled.n_bodies = int(np.shape(request.q)[0])
        return self

    def joint(self, j: Joint | int) -> JointResult:
        """The answer of joint `j`, the handle `Scene` returned, with or without `active_only`
        (see `JointResult`: an inactive joint reads as zero energy and derivatives).

        A plain `int` is a row of the only batch; with several batches use `batch(uid).joint(row)`.
        """
        if isinstance(j, Joint):
            if j.batch is None:
                return self.batch(j.constitution_uid).joint(j)
            # A handle of another scene may point past this answer or at another constitution's batch.
            if not 0 <= j.batch < len(self.batches) or self.batches[j.batch].constitution_uid != j.constitution_uid:
                raise KeyError(f"{j!r} is not a joint of this answer's request (its batch {j.batch} is not one of "
                               f"constitution {j.constitution_uid}): pass the handle of the Scene that made it")
            return self.batches[j.batch].joint(j)
        if len(self.batches) != 1:
            raise TypeError(
                f"joint({j!r}): a plain row is ambiguous with {len(self.batches)} batches; pass the handle "
                "Scene returned, or use batch(constitution_uid).joint(row)"
            )
        return self.batches[0].joint(j)
