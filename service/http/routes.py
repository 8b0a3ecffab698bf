"""Endpoints of contract v1."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from schemas import EvaluateRequest, EvaluateResponse
from service.core import evaluate
from service.http.convert import to_core, to_wire

router = APIRouter()


@router.get("/healthz")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.post(
    "/v1/evaluate",
    response_model=EvaluateResponse,
    response_model_exclude_none=True,
    summary="Energy, gradient and Hessian of a batch of joint limits",
)
def evaluate_joints(req: EvaluateRequest) -> JSONResponse:
    # Sync route: FastAPI runs it in a worker thread, so the event loop stays free while NumPy works.
    return JSONResponse(to_wire(evaluate(**to_core(req))))
