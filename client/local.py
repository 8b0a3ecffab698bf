"""In-process mode: the same API as `Client`, calling the core directly (a notebook without a server)."""

from __future__ import annotations

import inspect
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np

from jointlimits.client.accept import as_request
from jointlimits.client.aio import AsyncClient
from jointlimits.client.model import NEEDED, OPTIONAL, BatchResult, Evaluation, Request, in_body, null_arrays
from jointlimits.client.transport import ProgressCallback
from jointlimits.schemas import ConstitutionsResponse, EvaluateRequest, Limits
from jointlimits.schemas.constitutions import describe
from jointlimits.service import core
from jointlimits.service.core import registry

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


if TYPE_CHECKING:  # sessions are imported when opened: HTTP alone never loads websockets
    from jointlimits.client.session_local import LocalSession


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
        from jointlimits.client.session_local import LocalSession

        return LocalSession(request, threads=self.threads)

    def close(self) -> None:
        pass

    def __enter__(self) -> LocalClient:
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        pass
