"""The joint-limit constitution service and its Python SDK, under one import namespace.

    from jointlimits import Client, AsyncClient, LocalClient, Scene, Request, JointBatch

`jointlimits.client` is the SDK (its public names are this package's), `jointlimits.service` the
numerical core and its HTTP shell (the ASGI app `jointlimits.service.app:app`, the CLI
`jointlimits`), `jointlimits.schemas` the wire they share. In the repository the three are the
top-level folders `client/`, `service/` and `schemas/`, linked into this folder.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "PRISMATIC_LIMIT",
    "REVOLUTE_LIMIT",
    "AsyncClient",
    "BatchResult",
    "Busy",
    "Client",
    "Evaluation",
    "Fault",
    "InvalidInput",
    "Joint",
    "JointBatch",
    "JointResult",
    "LocalClient",
    "Request",
    "Scene",
    "ServiceError",
    "SessionClosed",
    "TooLarge",
    "Unreachable",
    "WrongURL",
    "dofs",
    "request_from_arrays",
]


def __getattr__(name: str) -> Any:
    # The SDK is imported on first use: `import jointlimits.service.cli` (the server) stays free of it,
    # and a broken dependency fails where the CLI reports it.
    if name in __all__:
        return getattr(importlib.import_module("jointlimits.client"), name)
    raise AttributeError(f"module 'jointlimits' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
