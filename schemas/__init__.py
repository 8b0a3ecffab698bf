"""Wire schemas of contract v1: shared by the service and the client, no numerics."""

from jointlimits.schemas.constitutions import Attribute, ConstitutionInfo, ConstitutionsResponse, Limits
from jointlimits.schemas.errors import ErrorItem, ErrorResponse
from jointlimits.schemas.evaluate import OUTPUTS, BatchResult, Bodies, EvaluateRequest, EvaluateResponse, HessianMode
from jointlimits.schemas.evaluate import JointBatch, Output

__all__ = [
    "OUTPUTS", "Attribute", "BatchResult", "Bodies", "ConstitutionInfo", "ConstitutionsResponse", "ErrorItem",
    "ErrorResponse", "EvaluateRequest", "EvaluateResponse", "HessianMode", "JointBatch", "Limits", "Output",
]
