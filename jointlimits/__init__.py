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

_SUBPACKAGES = ("service", "schemas", "client")  # `from jointlimits import service` imports that, not the SDK


def _sdk() -> Any:
    return importlib.import_module("jointlimits.client")


def __getattr__(name: str) -> Any:
    # The SDK is imported on first use: `import jointlimits.service.cli` (the server) stays free of it,
    # and a broken dependency fails where the CLI reports it. `__all__` is the SDK's (`import *` asks here).
    if name == "__all__":
        return list(_sdk().__all__)
    if name not in _SUBPACKAGES and not name.startswith("__") and name in _sdk().__all__:
        return getattr(_sdk(), name)
    raise AttributeError(f"module 'jointlimits' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_sdk().__all__])
