"""End to end over HTTP on loopback: a uvicorn server in a subprocess, JSON and (if present) the binary encoding."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import orjson

from bench.measure import document
from jointlimits.service.core import Bodies, Joints

try:  # the binary transport (msgpack, raw little-endian arrays) is being written concurrently
    from jointlimits.schemas import binary as wire
except ImportError:  # pragma: no cover - older trees
    wire = None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """`with Server() as srv:` the service under uvicorn on a free loopback port (`srv.url`), stopped on exit;
    `serve`: Python code run instead (in the repository's root, `port` bound), which serves on that port."""

    def __init__(self, serve: str | None = None) -> None:
        self.serve = serve
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> Server:
        argv = ([sys.executable, "-c", f"port = {self.port}\n{self.serve}"] if self.serve else
                [sys.executable, "-m", "uvicorn", "jointlimits.service.app:app", "--host", "127.0.0.1", "--port",
                 str(self.port), "--log-level", "warning"])
        self.proc = subprocess.Popen(
            argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=Path(__file__).resolve().parents[1],
            env={**os.environ, "JOINTLIMITS_SHUTDOWN_DELAY": "0"},  # no drain phase: stopping is not measured
        )
        for _ in range(200):
            try:
                if httpx.get(self.url + "/healthz", timeout=1).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.05)
        raise RuntimeError("server did not start")

    def __exit__(self, *exc: Any) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(10)


def encode(bodies: Bodies, batches: list[Joints], binary: bool, active_only: bool = False) -> tuple[bytes, dict[str, str]]:
    """The request body and headers: msgpack with raw float64/int64 buffers, or JSON straight from NumPy."""
    if binary:
        doc = document(bodies, batches, lambda a: wire.pack_array(a, wire.FLOAT64),
                       lambda a: wire.pack_array(a, wire.INT64), active_only=active_only)
        return wire.dumps(doc), {"Content-Type": wire.MEDIA_TYPE, "Accept": wire.MEDIA_TYPE}
    doc = document(bodies, batches, lambda a: np.ascontiguousarray(a, np.float64),
                   lambda a: np.ascontiguousarray(a, np.int64), active_only=active_only)
    return orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY), {"Content-Type": "application/json"}


def decode(resp: httpx.Response, binary: bool) -> Any:
    """The response document (what a client does with the answer, so it is part of the timing)."""
    if binary:
        return wire.loads(resp.content)
    return orjson.loads(resp.content)


def binary_available(url: str, bodies: Bodies, batches: list[Joints]) -> bool:
    """Whether the server answers a msgpack request in msgpack (the transport may be absent in older trees)."""
    if wire is None:
        return False
    body, headers = encode(bodies, batches, True)
    r = httpx.post(url + "/v1/evaluate", content=body, headers=headers, timeout=60)
    return r.status_code == 200 and r.headers.get("content-type", "").split(";")[0] in wire.MEDIA_TYPES


def measure(url: str, bodies: Bodies, batches: list[Joints], binary: bool, reps: int,
            active_only: bool = False) -> dict[str, float]:
    """Sequential requests (encode + POST + decode, as a client sees it): throughput, latency, bytes."""
    n = sum(j.body_ids.shape[0] for j in batches)
    with httpx.Client(timeout=300) as client:
        lat, sent, received = [], 0, 0
        for i in range(reps + 1):
            t = time.perf_counter()
            body, headers = encode(bodies, batches, binary, active_only)
            r = client.post(url + "/v1/evaluate", content=body, headers=headers)
            r.raise_for_status()
            decode(r, binary)
            if i:  # the first request is the warm-up
                lat.append(time.perf_counter() - t)
                sent, received = len(body), len(r.content)
    lat_a = np.array(lat)
    total = float(lat_a.sum())
    return {
        "joints": n,
        "requests_per_s": len(lat) / total,
        "joints_per_s": n * len(lat) / total,
        "p50_ms": float(np.percentile(lat_a, 50) * 1e3),
        "p99_ms": float(np.percentile(lat_a, 99) * 1e3),
        "bytes_per_joint": (sent + received) / n,
    }
