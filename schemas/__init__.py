"""Wire schemas of contract v1: shared by the service and the client, no numerics."""

from schemas.evaluate import (
    OUTPUTS,
    BatchResult,
    Bodies,
    EvaluateRequest,
    EvaluateResponse,
    HessianMode,
    JointBatch,
    Output,
)

__all__ = [
    "OUTPUTS",
    "BatchResult",
    "Bodies",
    "EvaluateRequest",
    "EvaluateResponse",
    "HessianMode",
    "JointBatch",
    "Output",
]
