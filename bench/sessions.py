"""Per-iteration cost of a prepared scene against the stateless call (issue 10 item 5).

In-process: `prepare(...)` once, then `scene.evaluate(q)` per iteration, against the stateless
`jointlimits.service.core.evaluate` (which prepares and evaluates once) on the same scene, energy and E+G+H.
Over the wire (a uvicorn subprocess on loopback, as bench/http_bench.py): a session's `evaluate`
against the stateless `Client.evaluate` of the same scene, msgpack and JSON, 10 / 1e3 / 1e4 joints;
per iteration p50, p99 and the bytes both ways. A solver's iteration: E+G+H exact, `active_only`.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench import measure as M
from bench import report
from bench.scenes import make_scene
from jointlimits.service.core import Bodies, Joints, evaluate
from jointlimits.service.core.prepared import prepare

WIRE_SIZES = (10, 1_000, 10_000)
ITERATIONS = {10: 300, 1_000: 60, 10_000: 15}  # per measurement: small calls are cheap and noisy, so more of them
OUTSIDE = 0.1


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ------------------------------------------------------------------ in-process


def inprocess(sizes: list[int], reps: int) -> list[dict[str, Any]]:
    """Median seconds per iteration, stateless and prepared, per size and mode ("e", "egh")."""
    rows = []
    for n in sizes:
        bodies, batches = make_scene(n, OUTSIDE, seed=n % 89)
        scene = prepare(bodies, batches)
        for mode in ("e", "egh"):
            out = M.OUTPUTS[mode]
            t_stateless = M.median_time(lambda: evaluate(bodies, batches, outputs=out), reps)
            t_prepared = M.median_time(lambda: scene.evaluate(bodies.q, outputs=out), reps)
            rows.append({"n": n, "mode": M.MODE_NAMES[mode], "stateless": t_stateless, "prepared": t_prepared,
                         "speedup": t_stateless / t_prepared})
            log(f"prepared vs stateless N={n} {mode}: {t_stateless:.4g}s / {t_prepared:.4g}s")
    return rows


# ------------------------------------------------------------------ over the wire


def sdk_request(bodies: Bodies, batches: list[Joints]) -> Any:
    from jointlimits.client.model import JointBatch, Request

    return Request(
        q=bodies.q, q_prev=bodies.q_prev, q_ref=bodies.q_ref,
        batches=[JointBatch(j.constitution_uid, j.body_ids, j.edges, j.lower, j.upper, j.strength, j.base_uid)
                 for j in batches],
        outputs=M.OUTPUTS["egh"], hessian_mode="exact", active_only=True,
    )  # fmt: skip


def _latencies(call: Callable[[], Any], iterations: int) -> np.ndarray:
    call()  # warm-up (and, for HTTP, the client's one-off GET /v1/constitutions)
    lat = np.empty(iterations)
    for i in range(iterations):
        t = time.perf_counter()
        call()
        lat[i] = time.perf_counter() - t
    return lat


def _http_bytes(url: str, request: Any, binary: bool) -> int:
    """Bytes of one stateless iteration both ways: the request body and the answer body."""
    import httpx

    from jointlimits.client import codec

    content, content_type = codec.encode(request, binary)
    r = httpx.post(url + "/v1/evaluate", content=content, timeout=300,
                   headers={"Content-Type": content_type, "Accept": content_type})
    r.raise_for_status()
    return len(content) + len(r.content)


def wire(iterations: dict[int, int] | None = None) -> list[dict[str, Any]]:
    """Session `evaluate` and stateless `Client.evaluate` per iteration at WIRE_SIZES, msgpack and JSON."""
    from bench.http_bench import Server
    from jointlimits.client import Client

    iterations = iterations or ITERATIONS
    rows = []
    with Server() as srv:
        for n in WIRE_SIZES:
            request = sdk_request(*make_scene(n, OUTSIDE, seed=7))
            for binary in (True, False):
                enc = "msgpack" if binary else "json"
                client = Client(srv.url, binary=binary, timeout=300)
                lat = _latencies(lambda: client.evaluate(request), iterations[n])
                rows.append(_row(n, enc, "HTTP (stateless)", lat, _http_bytes(srv.url, request, binary)))
                with client.session(request) as s:
                    lat = _latencies(lambda: s.evaluate(request.q), 1)  # the warm-up's bytes are not counted
                    before = s.bytes_sent + s.bytes_received
                    lat = _latencies(lambda: s.evaluate(request.q), iterations[n])
                    per = (s.bytes_sent + s.bytes_received - before) / (iterations[n] + 1)
                rows.append(_row(n, enc, "session", lat, per))
                client.close()
                log(f"wire N={n} {enc}: " + ", ".join(f"{r['transport']} p50 {r['p50_ms']:.3g} ms"
                                                      for r in rows[-2:]))
    return rows


def _row(n: int, encoding: str, transport: str, lat: np.ndarray, nbytes: float) -> dict[str, Any]:
    return {"joints": n, "encoding": encoding, "transport": transport, "iterations": int(lat.shape[0]),
            "p50_ms": float(np.percentile(lat, 50) * 1e3), "p99_ms": float(np.percentile(lat, 99) * 1e3),
            "bytes_per_iteration": float(nbytes)}


# ------------------------------------------------------------------ run, targets, report


def run(sizes: list[int], reps: int, with_wire: bool = True) -> dict[str, Any]:
    out: dict[str, Any] = {"inprocess": inprocess(sizes, reps)}
    if with_wire:
        out["wire"] = wire()
    return out


def targets(s: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue 10's two speed targets: session vs stateless over loopback at 10 joints (p50, msgpack, the SDK's
    default), prepared vs stateless energy in-process at the largest size (1e5 in the full run)."""
    rows = []
    w = {(r["joints"], r["encoding"], r["transport"]): r for r in s.get("wire", [])}
    key = (10, "msgpack")
    if (*key, "session") in w:
        ratio = w[(*key, "HTTP (stateless)")]["p50_ms"] / w[(*key, "session")]["p50_ms"]
        rows.append(report._at_least(5, "5. session evaluate, 10 joints, loopback, p50: speedup over stateless "
                                        "Client.evaluate (msgpack)", ratio, 2.0, "{:.2f}x"))
    else:
        rows.append(report._not_measured(5, "5. session evaluate vs stateless Client.evaluate, 10 joints", ">= 2x",
                                         "no wire measurement (--no-http)"))
    energy = [r for r in s["inprocess"] if r["mode"] == M.MODE_NAMES["e"]]
    if energy:
        big = max(energy, key=lambda r: r["n"])
        rows.append(report._at_least(6, f"6. prepared energy at {report.count(big['n'])} in-process: speedup over "
                                        "the stateless call", big["speedup"], 2.0, "{:.2f}x"))
    return rows


def section(s: dict[str, Any]) -> list[str]:
    """The report's section on sessions and prepared scenes (Markdown lines)."""
    lines = report._section(
        "Prepared scene vs stateless, in-process (median seconds per iteration)",
        *report._table(["N", "mode", "stateless", "prepared", "speedup"],
                       [[report.count(r["n"]), r["mode"], f"{r['stateless']:.3g}", f"{r['prepared']:.3g}",
                         f"**{r['speedup']:.2f}x**"] for r in s["inprocess"]]))
    if s.get("wire"):
        lines += report._section(
            "Sessions vs stateless HTTP on loopback (E+G+H exact, active_only, per iteration, SDK to SDK)",
            "Stateless: `Client.evaluate` sends the whole scene and the service prepares it each time; session: "
            "`s.evaluate(q)` sends `q` only. Bytes: both ways, message payloads (HTTP: bodies; session: frames).", "",
            *report._table(["joints", "encoding", "transport", "iterations", "p50 ms", "p99 ms", "bytes/iteration"],
                           [[str(r["joints"]), r["encoding"], r["transport"], str(r["iterations"]),
                             f"{r['p50_ms']:.3g}", f"{r['p99_ms']:.3g}", f"{r['bytes_per_iteration']:.0f}"]
                            for r in s["wire"]]))
    return lines


def write(res: dict[str, Any], out: Path, stem: str = "sessions") -> list[Path]:
    """`--sessions-only`: its own report files (the full run's report.* stay as they are)."""
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / f"{stem}.md", out / f"{stem}.json"
    text = [f"# Sessions and prepared scenes (`{res['command']}`)", "", res["machine"]]
    text += report._section("Targets", *report._table(
        ["target", "measured", "required", "status"],
        [[t["target"], t["measured"], t["required"], t["status"]] for t in res["targets"]]))
    text += section(res["sessions"])
    md.write_text("\n".join(text) + "\n")
    js.write_text(json.dumps(res, indent=1, default=float))
    return [md, js]


def only(command: str, sizes: list[int], reps: int, out: Path, with_wire: bool) -> int:
    """`python -m bench --sessions-only`: this module alone, its report in `out`/sessions.*."""
    import os
    import platform

    from jointlimits.service.core.heap import keep_heap

    keep_heap()  # as the service runs
    res: dict[str, Any] = {"command": command, "machine": f"{platform.processor() or platform.machine()}, "
                           f"{os.cpu_count()} cores, Python {platform.python_version()}, NumPy {np.__version__}; "
                           f"in-process: medians of {reps} after one warm-up"}
    res["sessions"] = run(sizes, reps, with_wire)
    res["targets"] = targets(res["sessions"])
    log("wrote " + ", ".join(str(f) for f in write(res, out)))
    for t in res["targets"]:
        print(f"{t['target']}: {t['measured']} ({t['status']})")
    return 0
