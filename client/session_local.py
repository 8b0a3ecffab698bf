"""A session in-process (`LocalClient().session(request)`): the same API, straight on the core's prepared scene."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from types import TracebackType
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from jointlimits.client.model import Array, Evaluation, Request, in_body
from jointlimits.client.local import core_batches, result
from jointlimits.client.session import (SessionClosed, SessionState, StateView, batch_number, message_array, options,
                                        owned)
from jointlimits.service import core
from jointlimits.service.core.prepared import prepare

T = TypeVar("T")
URL = "local://in-process"


def _call(fn: Callable[[], T]) -> T:
    """`fn()`, its input faults raised as `LocalClient` raises them (`loc` starting with "body", as the server's)."""
    try:
        with np.errstate(all="ignore"):
            return fn()
    except core.InputError as e:
        # A session message's `q` is a top-level field, as the server names it: ("bodies", "q", i) -> ("q", i).
        raise in_body([replace(f, loc=f.loc[1:]) if f.loc[:2] == ("bodies", "q") else f for f in e.faults]) from None


class LocalSession(StateView):
    """`jointlimits.client.session_sync.Session`'s API on a `PreparedScene` in this process: bitwise the same numbers."""

    def __init__(self, request: Request, *, threads: int = 1) -> None:
        self.state = SessionState(request, URL, binary=True)
        self.threads = threads
        self._open()

    def _open(self) -> None:
        r = self.state.request
        bodies = core.Bodies(np.asarray(r.q, np.float64), np.asarray(r.q_prev, np.float64), np.asarray(r.q_ref, np.float64))
        self._scene = _call(lambda: prepare(bodies, core_batches(r, copy=True), threads=self.threads))
        self.state.coordinates = [owned(c) for c in self._scene.coordinates()]

    def _live(self) -> Any:
        if self._scene is None:
            raise SessionClosed(URL, None, "", "the session is closed")
        return self._scene

    def evaluate(self, q: ArrayLike, *, outputs: Any = None, hessian_mode: str | None = None,
                 active_only: bool | None = None) -> Evaluation:
        scene, opts = self._live(), options(self.state.request, outputs, hessian_mode, active_only)
        q = message_array(q, "q")  # as the service reads a message's arrays: no cast, no reshape
        return result(_call(lambda: scene.evaluate(q, **opts))).sized(self.state.request)

    def commit(self, q: ArrayLike) -> list[Array]:
        scene, q = self._live(), np.array(message_array(q, "q"))
        return self.state.keep(_call(lambda: scene.commit(q)), q)

    def update(self, batch: int, index: ArrayLike, *, lower: ArrayLike | None = None, upper: ArrayLike | None = None,
               strength: ArrayLike | None = None, offset: ArrayLike | None = None) -> None:
        scene = self._live()
        values = {"lower": lower, "upper": upper, "strength": strength, "offset": offset}
        given = {k: message_array(v, k) for k, v in values.items() if v is not None}  # None: left out
        b, idx = batch_number(batch), message_array(index, "index", integer=True)  # as the service reads them
        _call(lambda: scene.update(b, idx, **given))
        self.state.apply_update(batch, index, values)
        if offset is not None:  # a new offset moves the batch's committed coordinates with it
            self.state.coordinates[batch] = owned(scene.coordinates()[batch])

    def reopen(self) -> None:
        self.state.request = self.state.request_for_reopen()
        self._open()

    def close(self) -> None:
        self._scene = None

    def __enter__(self) -> LocalSession:
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        self.close()
