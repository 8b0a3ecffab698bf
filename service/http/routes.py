"""Endpoints of contract v1 (+ discovery): parse, call the core once, encode."""

from __future__ import annotations

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from schemas import ConstitutionsResponse, EvaluateResponse
from service.core import InputError, evaluate
from service.http import binary, convert, discovery, limits, negotiate, openapi
from service.http.errors import HttpError, client_gone, http_error_handler, input_error_handler

router = APIRouter()
CODECS = {negotiate.JSON: convert, negotiate.BINARY: binary}


@router.get("/healthz")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get("/v1/constitutions", response_model=ConstitutionsResponse, summary="Supported constitutions")
def list_constitutions(request: Request) -> ConstitutionsResponse:
    return discovery.constitutions(request.app.state.settings)


@router.post(
    "/v1/evaluate",
    response_model=EvaluateResponse,
    response_model_exclude_none=True,
    summary="Energy, gradient and Hessian of a batch of joint limits",
    description="Body and answer in JSON or msgpack (`Content-Type` / `Accept`); errors are always JSON.",
    openapi_extra={"requestBody": openapi.request_body()},
    responses={
        200: {"content": {negotiate.BINARY: {"schema": {"type": "string", "format": "binary"}}}},
        **openapi.error_responses(),
    },
)
async def evaluate_joints(request: Request) -> Response:
    settings = request.app.state.settings
    decoder = CODECS[negotiate.request_type(request.headers.get("content-type"))]
    answer = negotiate.response_type(request.headers.get("accept"), decoder.MEDIA_TYPE)
    body = await limits.read_body(request, settings.max_body_bytes)
    # Parsing and NumPy run in a worker thread, so the event loop stays free.
    content = await run_in_threadpool(_evaluate, body, decoder, CODECS[answer], settings.max_joints, request.state)
    return Response(content, media_type=answer)


def _evaluate(body: bytes, decoder, encoder, max_joints: int, state=None) -> bytes:  # noqa: ANN001 (codec modules)
    kwargs = decoder.decode(body, max_joints)
    if state is not None:  # joint counts for the access log and metrics (service/observability.py)
        by_uid: dict[int, int] = {}
        for j in kwargs["batches"]:
            by_uid[int(j.constitution_uid)] = by_uid.get(int(j.constitution_uid), 0) + len(j.body_ids)
        state.joints_by_constitution = by_uid
        state.joints = sum(by_uid.values())
    # The core, with its guard that no answer carries NaN or Infinity (overflow is a 422 naming the joint).
    return encoder.encode(evaluate(**kwargs))


def install(app: FastAPI) -> None:
    """Routes, 4xx handlers and the OpenAPI components of the raw-bodied route."""
    app.include_router(router)
    app.add_exception_handler(InputError, input_error_handler)
    app.add_exception_handler(HttpError, http_error_handler)
    app.add_exception_handler(ClientDisconnect, client_gone)  # 499 / 408, not a 500 with a traceback
    build = app.openapi

    def openapi_with_components() -> dict:
        if app.openapi_schema is None:
            app.openapi_schema = openapi.add_components(build())
        return app.openapi_schema

    app.openapi = openapi_with_components  # type: ignore[method-assign]
