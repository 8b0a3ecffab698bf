"""Endpoints of contract v1 and discovery: negotiate the encodings, parse, call the core once, encode."""

from __future__ import annotations

import time
from collections import Counter

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import JSONResponse, RedirectResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from jointlimits.schemas import ConstitutionsResponse, EvaluateResponse, Limits
from jointlimits.schemas.binary import MEDIA_TYPES as BINARY_TYPES
from jointlimits.schemas.constitutions import describe
from jointlimits.service import sizing
from jointlimits.service.core import Fault, InputError, evaluate, registry
from jointlimits.service.core.errors import DeadlineExceeded, check_deadline
from jointlimits.service.http import binary, budget, convert, document, limits, openapi
from jointlimits.service.http.errors import FaultList, HttpError, client_gone, deadline_handler, fault_handler, one_fault
from jointlimits.service.settings import Settings

router = APIRouter()
JSON, BINARY = convert.MEDIA_TYPE, binary.MEDIA_TYPE
CODECS = {JSON: convert, BINARY: binary}
SUPPORTED = f"{JSON} or {BINARY}"


def _media_type(value: str) -> str:
    return value.split(";", 1)[0].strip().lower()


def request_type(content_type: str | None) -> str:
    """`JSON` or `BINARY` from `Content-Type`; no header at all is read as JSON, as FastAPI does. Else 415."""
    t = _media_type(content_type or JSON)
    if t == JSON or t.endswith("+json"):
        return JSON
    if t in BINARY_TYPES:
        return BINARY
    raise HttpError(415, [Fault(("header", "content-type"), f"unsupported Content-Type {t!r}; send {SUPPORTED}",
                                "media_type")])


def response_type(accept: str | None, requested: str) -> str:
    """The acceptable type with the highest q; ties and a missing header answer in the request's encoding."""
    if not accept or not accept.strip():
        return requested
    quality = {JSON: 0.0, BINARY: 0.0}
    for part in accept.split(","):
        media, *params = part.split(";")
        t = _media_type(media)
        q = _quality(params)
        for candidate, aliases in ((JSON, {JSON}), (BINARY, BINARY_TYPES)):
            if t in aliases or t in ("*/*", "application/*"):
                quality[candidate] = max(quality[candidate], q)
    best = max(quality.values())
    if best <= 0.0:
        raise HttpError(406, [Fault(("header", "accept"), f"cannot answer in {accept!r}; accept {SUPPORTED}",
                                    "not_acceptable")])
    return requested if quality[requested] == best else max(quality, key=quality.__getitem__)


def _quality(params: list[str]) -> float:
    for p in params:
        name, _, value = p.partition("=")
        if name.strip().lower() == "q":
            try:
                q = float(value)
            except ValueError:
                return 0.0
            return q if 0.0 <= q <= 1.0 else 0.0
    return 1.0


@router.get("/", include_in_schema=False)
def root(request: Request) -> RedirectResponse:
    """A browser at the service's root lands on its docs, under whatever prefix a proxy mounts the service at."""
    return RedirectResponse(request.scope.get("root_path", "").rstrip("/") + "/docs")


@router.get("/healthz", summary="Liveness: the worker answers")
def healthz() -> dict[str, str]:
    """200 `{"status": "ok"}` while the worker answers at all, draining or not: a liveness probe (a worker
    that does not answer is restarted). Not for load balancing: that is `/readyz`."""
    return {"status": "ok"}


DRAINING = ("this worker is draining (SIGTERM): it goes on answering for {delay:g} s after the signal "
            "(JOINTLIMITS_SHUTDOWN_DELAY), then stops accepting; send new requests elsewhere")


@router.get(
    "/readyz",
    summary="Readiness: the worker takes new requests",
    responses={503: {"description": "Draining after SIGTERM: it still answers, send new requests elsewhere",
                     "content": {"application/json": {"example": {"detail": [
                         {"loc": [], "msg": DRAINING.format(delay=5), "type": "draining"}]}}}}},
)
def readyz(request: Request) -> Response:
    """200 `{"status": "ready"}`; from SIGTERM on, a 503 fault of type `draining`, for the
    `JOINTLIMITS_SHUTDOWN_DELAY` seconds the worker still accepts and answers before it stops
    accepting: a readiness probe, or a load balancer's health check, takes the worker out of rotation
    meanwhile (docs/deployment.md, "Stopping without a failed request")."""
    if request.app.state.draining:
        return draining(request.app.state.settings)
    return JSONResponse({"status": "ready"})


def draining(settings: Settings) -> FaultList:
    """The 503 of a worker that drains: to `/readyz`, and to the upgrade of a new session (which the worker
    would close within the delay: the client's retry, through a balancer, opens it elsewhere)."""
    return one_fault(503, [], DRAINING.format(delay=settings.shutdown_delay), "draining")


@router.get("/v1/constitutions", response_model=ConstitutionsResponse, summary="Supported constitutions")
def list_constitutions(request: Request) -> ConstitutionsResponse:
    infos = [describe(f) for f in sorted(registry.CONSTITUTIONS.values(), key=lambda f: -f.uid)]
    bounds = {k: getattr(request.app.state.settings, k) for k in Limits.model_fields}  # each a setting's name
    return ConstitutionsResponse(constitutions=infos, limits=Limits(**bounds))


@router.post(
    "/v1/evaluate",
    response_model=EvaluateResponse,
    response_model_exclude_none=True,
    summary="Energy, gradient and Hessian of a batch of joint limits",
    description="Body and answer in JSON or msgpack (`Content-Type` / `Accept`); errors are always JSON.",
    openapi_extra={"requestBody": openapi.REQUEST_BODY},
    responses={200: {"content": {BINARY: {"schema": {"type": "string", "format": "binary"}}}},
               **openapi.ERROR_RESPONSES},
)
async def evaluate_joints(request: Request) -> Response:
    settings = request.app.state.settings
    decoder = CODECS[request_type(request.headers.get("content-type"))]
    answer = response_type(request.headers.get("accept"), decoder.MEDIA_TYPE)
    # Received within the worker's memory budgets, then its turn among the requests in flight.
    body = await budget.receive(request, settings, decoder is binary, answer == BINARY)
    # The deadline covers the work (parse, core, encode), not the upload or the wait (bounded above).
    deadline = time.monotonic() + settings.request_timeout
    # Parsing and NumPy run in a worker thread, so the event loop stays free.
    content = await run_in_threadpool(_evaluate, body, decoder, CODECS[answer], settings, request.state, deadline)
    return Response(content, media_type=answer)


def _evaluate(  # noqa: ANN001 (codec modules)
    body: bytes, decoder, encoder, settings: Settings, state=None, deadline: float | None = None
) -> bytes:
    # Batches (and a JSON body's values) are counted before they are parsed (service/http/limits.py).
    checker = document.Checker(binary=decoder is binary)
    if decoder is convert:
        kwargs = convert.decode(body, settings.max_json_values, settings.max_batches, checker=checker)
    else:
        kwargs = binary.decode(body, settings.max_batches, checker=checker)
    check_deadline(deadline)
    # Admission by cost, before any evaluation: joints, the answer's size in its encoding.
    batch_joints = [len(j.body_ids) for j in kwargs["batches"]]
    outputs, binary_answer = kwargs["outputs"], encoder is binary
    limits.admit(joints=batch_joints, outputs=outputs, binary_answer=binary_answer, settings=settings)
    if state is not None:  # from the bound of its size to what it holds (room for the requests waiting)
        n_bodies = kwargs["bodies"].q.shape[0]
        state.in_flight.shrink(sizing.request_cost(len(body), checker.values, batch_joints, n_bodies, outputs,
                                                   binary_answer, settings))
        by_uid: Counter[int] = Counter()  # joint counts for the access log and metrics (service/observability.py)
        for j in kwargs["batches"]:
            by_uid[int(j.constitution_uid)] += len(j.body_ids)
        state.joints_by_constitution = by_uid
        state.joints = sum(batch_joints)
    # The core, with its guard that no answer carries NaN or Infinity (overflow is a 422 naming the joint).
    ev = evaluate(**kwargs, deadline=deadline)
    check_deadline(deadline)
    return encoder.encode(ev)


def install(app: FastAPI) -> None:
    """Routes, 4xx handlers and the OpenAPI components of the raw-bodied route."""
    app.include_router(router)
    app.add_exception_handler(InputError, fault_handler)
    app.add_exception_handler(HttpError, fault_handler)
    app.add_exception_handler(ClientDisconnect, client_gone)  # 499 / 408, not a 500 with a traceback
    app.add_exception_handler(DeadlineExceeded, deadline_handler)
    build = app.openapi

    def openapi_with_components() -> dict:
        if app.openapi_schema is None:
            app.openapi_schema = openapi.add_components(build())
        return app.openapi_schema

    app.openapi = openapi_with_components  # type: ignore[method-assign]
