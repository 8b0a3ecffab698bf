"""Vectorised NumPy core: one cubic penalty, per-constitution coordinates, a shared chain rule."""

# First: the constitutions of the specs register themselves (670, then 669) before anything reads the registry.
from jointlimits.service.core import revolute as _revolute  # noqa: F401  isort: skip
from jointlimits.service.core import prismatic as _prismatic  # noqa: F401  isort: skip

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
