"""Vectorised NumPy core: one cubic penalty, per-constitution coordinates, a shared chain rule."""

from jointlimits.service.core.errors import Fault, InputError
from jointlimits.service.core.prepared import PreparedScene, evaluate, prepare
from jointlimits.service.core.registry import CONSTITUTIONS
from jointlimits.service.core.scene import BatchResult, Bodies, Evaluation, Joints

__all__ = [
    "CONSTITUTIONS",
    "BatchResult",
    "Bodies",
    "Evaluation",
    "Fault",
    "InputError",
    "Joints",
    "PreparedScene",
    "evaluate",
    "prepare",
]
