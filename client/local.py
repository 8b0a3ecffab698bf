"""In-process mode: the same API as `Client` and its sessions, calling the core directly (a notebook without a
server): `LocalClient`, and `LocalClient().session(request)` straight on the core's prepared scene."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import replace
from types import TracebackType
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from jointlimits.client.aio import AsyncClient
from jointlimits.client.model import NEEDED, OPTIONAL, Array, BatchResult, Evaluation, Request, as_request, in_body
from jointlimits.client.model import null_arrays
from jointlimits.client.session import CLOSED, SessionClosed, SessionState, evaluate_message, message_array, owned
from jointlimits.client.session import update_message
from jointlimits.client.transport import ProgressCallback
from jointlimits.schemas import ConstitutionsResponse, EvaluateRequest, Limits
from jointlimits.schemas.constitutions import describe
from jointlimits.service import core
from jointlimits.service.core import registry
from jointlimits.service.core.prepared import prepare

T = TypeVar("T")
URL = "local://in-process"

HTTP_OPTIONS = frozenset(inspect.signature(AsyncClient).parameters) - {"base_url"}
"""Keywords of `Client` / `AsyncClient` that `LocalClient` accepts and ignores."""


def core_batches(request: Request, copy: bool = False) -> list[core.Joints]:
    """The request's batches as the core's `Joints`; `copy`: arrays of their own (a session's scene
    changes with updates), else the request's own arrays (the core only reads them).

    A None where an array is needed is `core.InputError` (`model.null_arrays`: the core would fail on it)."""
    if missing := null_arrays(request):
        raise core.InputError(missing)
    own = np.array if copy else (lambda a: a)
    return [
        core.Joints(
            constitution_uid=b.constitution_uid, origin=b.origin,
            base_uid=b.base_uid if b.base_uid is not None else -1,  # None only for an unknown constitution: refused
            **{k: None if (a := getattr(b, k)) is None else own(a) for k in NEEDED + OPTIONAL},
        )
        for b in request.batches
    ]


def result(ev: core.Evaluation) -> Evaluation:
    """The core's answer as the SDK's `Evaluation` (the same arrays, no copy)."""
    batches = [BatchResult(r.constitution_uid, r.index, r.x, r.energy, r.gradient, r.hessian, r.coordinate)
               for r in ev.batches]
    return Evaluation(ev.total_energy, batches, ev.assembled)


class LocalClient:
    """`evaluate` and `constitutions` as `Client` has them, without HTTP.

    Numbers are bit-identical to the service's. Input faults raise `InvalidInput` with
    the `loc` the server would answer (`("body", "batches", 1, "lower", 2)`).
    """

    def __init__(self, *, threads: int = 1, **http_options: object) -> None:
        """`threads` > 1 lets the core use that many threads (bitwise the same numbers). The HTTP
        clients' options (`binary`, `timeout`, ...) are accepted and ignored, so switching mode is
        one word; any other keyword is a `TypeError`."""
        if unknown := sorted(set(http_options) - HTTP_OPTIONS):
            raise TypeError(f"LocalClient() got an unexpected keyword argument {unknown[0]!r}; it takes threads=N "
                            f"(and ignores the HTTP clients' {', '.join(sorted(HTTP_OPTIONS))})")
        self.threads = threads

    def constitutions(self) -> ConstitutionsResponse:
        infos = [describe(f) for f in sorted(registry.CONSTITUTIONS.values(), key=lambda f: -f.uid)]
        return ConstitutionsResponse(constitutions=infos, limits=Limits(max_body_bytes=2**63 - 1, max_joints=2**63 - 1))

    def evaluate(self, request: Request | dict | EvaluateRequest, *,
                 progress: bool | ProgressCallback | None = None) -> Evaluation:
        """`Client.evaluate` in-process: the same arguments, results and bit-identical numbers.

        Input faults raise `InvalidInput` (no HTTP involved: its message starts "invalid input",
        `e.loc` is what the service would answer); a non-request is a `TypeError`.
        """
        request = as_request(request)
        try:
            ev = core.evaluate(bodies=core.Bodies(request.q, request.q_prev, request.q_ref),
                               batches=core_batches(request), outputs=request.outputs,
                               hessian_mode=request.hessian_mode, active_only=request.active_only,
                               threads=self.threads, layout=request.layout)
        except core.InputError as e:
            raise in_body(e.faults) from None
        if callable(progress):
            progress(request.n_joints, request.n_joints)
        return result(ev).sized(request)

    def session(self, request: Request | dict | EvaluateRequest, *, resume: bool = True) -> LocalSession:
        """`Client.session`'s API in-process, on the core's prepared scene (bitwise the same numbers); `resume`
        is taken for the same calls to work: there is no connection to lose."""
        return LocalSession(request, threads=self.threads)

    def close(self) -> None:
        pass

    def __enter__(self) -> LocalClient:
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        pass


def _call(fn: Callable[[], T]) -> T:
    """`fn()`, its input faults raised as `LocalClient` raises them (`loc` starting with "body", as the server's)."""
    try:
        with np.errstate(all="ignore"):
            return fn()
    except core.InputError as e:
        # A session message's `q` is a top-level field, as the server names it: ("bodies", "q", i) -> ("q", i).
        raise in_body([replace(f, loc=f.loc[1:]) if f.loc[:2] == ("bodies", "q") else f for f in e.faults]) from None


class LocalSession(SessionState):
    """`jointlimits.client.sync.Session`'s API on a `PreparedScene` in this process: bitwise the same numbers."""

    def __init__(self, request: Request, *, threads: int = 1) -> None:
        super().__init__(request, URL)
        self.threads = threads
        self._open()

    def _open(self) -> None:
        r = self.request
        bodies = core.Bodies(np.asarray(r.q, np.float64), np.asarray(r.q_prev, np.float64), np.asarray(r.q_ref, np.float64))
        scene = _call(lambda: prepare(bodies, core_batches(r, copy=True), threads=self.threads))
        self._coordinates = [owned(c) for c in _call(scene.coordinates)]  # InvalidInput where they overflow
        self._scene = scene

    def _live(self) -> Any:
        if self._scene is None:
            raise SessionClosed(URL, None, "", CLOSED)
        return self._scene

    def evaluate(self, q: ArrayLike, *, outputs: Any = None, hessian_mode: str | None = None,
                 active_only: bool | None = None) -> Evaluation:
        r, scene = self.request, self._live()
        # The opening's options where not given; its `layout` always, as the server keeps it (a message cannot change it).
        opts = {"outputs": r.outputs, "hessian_mode": r.hessian_mode, "active_only": r.active_only, "layout": r.layout,
                **evaluate_message(q, outputs, hessian_mode, active_only)}  # as the service reads a message's arrays
        return result(_call(lambda: scene.evaluate(**opts))).sized(r)

    def commit(self, q: ArrayLike) -> list[Array]:
        scene, q = self._live(), np.array(message_array(q, "q"))
        return self._keep(_call(lambda: scene.commit(q)), q)

    def update(self, batch: int, index: ArrayLike, *, lower: ArrayLike | None = None, upper: ArrayLike | None = None,
               strength: ArrayLike | None = None, offset: ArrayLike | None = None) -> None:
        scene = self._live()
        values = {"lower": lower, "upper": upper, "strength": strength, "offset": offset}
        _call(lambda: scene.update(**update_message(batch, index, values)))
        self._apply_update(batch, index, values)
        if offset is not None:  # a new offset moves the batch's committed coordinates with it
            self._coordinates[batch] = owned(scene.coordinates([batch])[0])

    def reopen(self) -> None:
        self.request = self.request_for_reopen()
        self._open()

    def close(self) -> None:
        self._scene = None

    def __enter__(self) -> LocalSession:
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        self.close()
