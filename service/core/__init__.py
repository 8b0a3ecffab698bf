"""Vectorised NumPy core: one cubic penalty, per-constitution coordinates, a shared chain rule."""

from service.core.errors import Fault, InputError
from service.core.prepared import PreparedScene, evaluate, prepare
from service.core.registry import CONSTITUTIONS
from service.core.scene import BatchResult, Bodies, Evaluation, Joints

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
