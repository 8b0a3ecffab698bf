"""A real uvicorn server on 127.0.0.1 (a free port) for the contract, error, fuzz and client tests.

Other test modules import `live` (the fixture) from here; each module gets its own server.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import httpx
import pytest
import uvicorn
from fastapi import FastAPI

from jointlimits.service.app import create_app
from jointlimits.service.http.timeouts import server_options
from jointlimits.service.settings import Settings

# Small limits, so that 413s and the SDK's splitting are exercised with small requests.
LIMITS = Settings(max_body_bytes=2_000_000, max_joints=400, token=None, cors_origins=())


@contextmanager
def running(config: uvicorn.Config, port: int = 0) -> Iterator[tuple[uvicorn.Server, int]]:
    """`config` served by uvicorn in a thread on a free loopback port (or `port`): yields the server and the port
    once it has started, stops it on exit (every in-process server of the tests runs so)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", port))
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.01)
    try:
        yield server, sock.getsockname()[1]
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        sock.close()


@contextmanager
def serve(settings: Settings = LIMITS, app: FastAPI | None = None) -> Iterator[str]:
    """Run the app (`create_app(settings)`, or `app`) under uvicorn in a thread; yields its base URL, stops it on exit."""
    app = app or create_app(settings)
    # The WebSocket options `jointlimits serve` passes: its protocol, the message limit of the app's settings.
    frame_bytes = getattr(getattr(app, "state", None), "settings", settings).max_frame_bytes
    with running(uvicorn.Config(app, log_level="warning", lifespan="off", **server_options(frame_bytes))) as (_, port):
        yield f"http://127.0.0.1:{port}"


@pytest.fixture(scope="module")
def live() -> Iterator[str]:
    with serve() as url:
        yield url


def test_live_server_answers_health_and_openapi(live):
    assert httpx.get(f"{live}/healthz").json() == {"status": "ok"}
    spec = httpx.get(f"{live}/openapi.json").json()
    body = spec["paths"]["/v1/evaluate"]["post"]["requestBody"]["content"]
    assert set(body) == {"application/json", "application/msgpack"}
    assert "EvaluateRequest" in spec["components"]["schemas"]
    assert {"413", "415", "422"} <= set(spec["paths"]["/v1/evaluate"]["post"]["responses"])


def sdk_request(wire_request: dict):
    """The SDK's `Request` of a JSON request body (the golden cases' format)."""
    import numpy as np

    from jointlimits.client import JointBatch, request_from_arrays

    b = wire_request["bodies"]
    batches = [
        JointBatch(
            constitution_uid=j["constitution_uid"],
            base_uid=j["base_uid"],
            body_ids=np.array(j["body_ids"], dtype=np.int64).reshape(-1, 2),
            edges=np.array(j["edges"], dtype=np.float64).reshape(-1, 2, 3),
            lower=np.array(j["lower"], dtype=np.float64),
            upper=np.array(j["upper"], dtype=np.float64),
            strength=np.array(j["strength"], dtype=np.float64),
        )
        for j in wire_request["batches"]
    ]
    return request_from_arrays(
        np.array(b["q"], dtype=np.float64).reshape(-1, 12),
        batches,
        q_prev=np.array(b["q_prev"], dtype=np.float64).reshape(-1, 12),
        q_ref=np.array(b["q_ref"], dtype=np.float64).reshape(-1, 12),
        outputs=wire_request.get("outputs", ("energy", "gradient", "hessian")),
        hessian_mode=wire_request.get("hessian_mode", "exact"),
        active_only=wire_request.get("active_only", False),
    )
