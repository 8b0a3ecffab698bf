"""`python -m bench.robot_scale`: the fixed cost per call, where robots live.

1, 10, 100, 1000 joints, every joint active (`make_scene(n, outside=1.0)`: half #670, half #669):
the core's stateless energy, E+G+H exact and E+G+H psd, and a prepared scene's (`prepare(...)`,
`.evaluate(q)`, a session's evaluation in-process) E+G+H psd; beside them the JAX `jit(vmap)` peer
(same inputs, bench/peer_jax.py) and the Warp CPU peer's energy (bench/peer_warp.py) when importable,
else "not installed". Medians of `--reps` calls, every column's calls alternated (`measure.median_times`:
drift moves them alike), one thread. The last columns are the targets' ratios (issue 28).

Over the wire (`--wire-joints`, 1 10 100; `--no-wire` skips it): the service's app as `jointlimits serve` runs it
(its uvicorn protocol classes and options) in a subprocess on loopback, with one more WebSocket route, the bench's
own (`ECHO`, never in the product's routes). Per iteration, alternated: a session's `evaluate(q)` (E+G+H psd, msgpack,
`Client(...).session`, blocking), and a bare round trip of the same bytes (a frame of the session's request size out,
one of its reply size back) to `ECHO` from the SDK's library (`websockets.sync`, its connect options): p50, p99 and
their ratio. Then each alone for the same count: the server process's CPU per message (/proc; clock ticks, so at
least a few hundred messages) and the client's, beside the prepared scene's in-process time.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from starlette.websockets import WebSocket  # at the top: FastAPI reads the echo's annotation from the module

from bench.measure import median_times
from bench.scenes import make_scene
from jointlimits.service.core import evaluate, prepare

SIZES = (1, 10, 100, 1000)
WIRE_SIZES = (1, 10, 100)
ECHO = "/bench/echo"
WIRE_HEAD = ["joints", "request B", "reply B", "session p50", "session p99", "bare p50", "bare p99", "session/bare p50",
             "server CPU/msg", "server CPU/echo", "client CPU/iter", "prepared in-process"]
CORE = (("core E", "e"), ("core EGH", "egh"), ("core EGH psd", "psd"), ("prepared EGH psd", "prep"))
PEERS = (("JAX E", "jax_e"), ("JAX EGH", "jax_egh"), ("Warp E", "warp_e"))


def _peers() -> dict[str, Any]:
    """The importable peers' modules ("jax", "warp"); a missing one is absent."""
    found: dict[str, Any] = {}
    try:
        from bench import peer_jax

        found["jax"] = peer_jax
    except ImportError:
        pass
    try:
        from bench import peer_warp

        found["warp"] = peer_warp
    except ImportError:
        pass
    return found


def calls(n: int, peers: dict[str, Any]) -> dict[str, Callable[[], Any]]:
    """The timed calls on the robot scene of `n` joints, by column key."""
    bodies, batches = make_scene(n, outside=1.0, seed=n % 89)
    batches = [b for b in batches if b.body_ids.shape[0]]  # 1 joint: the #669 batch is empty
    egh = ("energy", "gradient", "hessian")
    scene = prepare(bodies, batches)
    fns: dict[str, Callable[[], Any]] = {
        "e": lambda: evaluate(bodies, batches, outputs=("energy",)),
        "egh": lambda: evaluate(bodies, batches, outputs=egh),
        "psd": lambda: evaluate(bodies, batches, outputs=egh, hessian_mode="psd"),
        "prep": lambda: scene.evaluate(bodies.q, outputs=egh, hessian_mode="psd"),
    }
    if "jax" in peers:
        jp = peers["jax"].JaxPeer(bodies, batches, same_work=True)
        jp("e"), jp("egh")  # compiled outside the timing
        fns["jax_e"] = lambda: jp("e")
        fns["jax_egh"] = lambda: jp("egh")
    if "warp" in peers:
        wpeer = peers["warp"].WarpPeer(bodies, batches)
        fns["warp_e"] = lambda: wpeer("e")
    return fns


def table(sizes: tuple[int, ...] = SIZES, reps: int = 301) -> list[dict[str, Any]]:
    """One row per size: its medians (s) by column key (absent: the peer is not installed)."""
    peers = _peers()
    rows = []
    for n in sizes:
        fns = calls(n, peers)
        times = median_times(fns, reps=reps, warmup=max(1, reps // 20))
        rows.append({"joints": n, **times})
    return rows


def echo_app() -> Any:
    """The service's app plus the bench's echo: `ECHO?reply=N` answers each message with N bytes."""
    from jointlimits.service.app import create_app

    app = create_app()

    async def echo(websocket: WebSocket) -> None:
        await websocket.accept()
        reply = bytes(int(websocket.query_params["reply"]))
        while (await websocket.receive())["type"] != "websocket.disconnect":
            await websocket.send_bytes(reply)

    app.add_api_websocket_route(ECHO, echo)  # a route as the sessions' (FastAPI's)
    return app


def serve(port: int) -> None:
    """`echo_app()` on loopback, as `jointlimits serve` configures uvicorn (service/cli.py), one worker."""
    import uvicorn

    from jointlimits.service.http.timeouts import server_options
    from jointlimits.service.observability import log_config
    from jointlimits.service.settings import Settings

    uvicorn.run(echo_app(), host="127.0.0.1", port=port, log_config=log_config("warning", False), log_level="warning",
                access_log=False, server_header=False, http="jointlimits.service.http.timeouts:ReadTimeoutProtocol",
                **server_options(Settings().max_frame_bytes))


def _cpu(pid: int) -> float:
    """CPU seconds of process `pid` so far, every thread (user + system, in clock ticks)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wire(sizes: tuple[int, ...] = WIRE_SIZES, reps: int = 2001) -> list[dict[str, Any]]:
    """One row per size: the session's and the bare round trip's latencies (s), bytes and CPU per message."""
    from websockets.sync.client import connect

    from bench.http_bench import Server
    from jointlimits.client import Client
    from jointlimits.client.model import JointBatch, Request
    from jointlimits.client.session import CONNECT_OPTIONS

    rows = []
    with Server("from bench.robot_scale import serve; serve(port)") as srv, Client(srv.url, binary=True) as client:
        assert srv.proc is not None
        for n in sizes:
            bodies, batches = make_scene(n, outside=1.0, seed=n % 89)
            sdk_batches = [JointBatch(j.constitution_uid, j.body_ids, j.edges, j.lower, j.upper, j.strength, j.base_uid)
                           for j in batches]
            request = Request(q=bodies.q, q_prev=bodies.q_prev, q_ref=bodies.q_ref, batches=sdk_batches,
                              outputs=("energy", "gradient", "hessian"), hessian_mode="psd")
            with client.session(request) as s:
                s.evaluate(bodies.q)  # warm-up
                sent, received = s.bytes_sent, s.bytes_received
                s.evaluate(bodies.q)
                out, back = s.bytes_sent - sent, s.bytes_received - received
                frame = bytes(out)
                with connect(srv.url.replace("http", "ws") + f"{ECHO}?reply={back}", **CONNECT_OPTIONS) as ws:
                    calls = {"session": lambda: s.evaluate(bodies.q), "bare": lambda: (ws.send(frame), ws.recv())}
                    assert len(calls["bare"]()[1]) == back
                    lat = {k: np.empty(reps) for k in calls}
                    for i in range(reps):
                        for k, call in calls.items():
                            t = time.perf_counter()
                            call()
                            lat[k][i] = time.perf_counter() - t
                    row: dict[str, Any] = {"joints": n, "out": out, "back": back}
                    for k, call in calls.items():
                        c, p = _cpu(srv.proc.pid), time.process_time()
                        for _ in range(reps):
                            call()
                        row[k + "_server_cpu"] = (_cpu(srv.proc.pid) - c) / reps
                        row[k + "_client_cpu"] = (time.process_time() - p) / reps
                        row[k + "_p50"], row[k + "_p99"] = np.percentile(lat[k], 50), np.percentile(lat[k], 99)
            rows.append(row)
    return rows


def render_wire(wire_rows: list[dict[str, Any]], rows: list[dict[str, Any]]) -> str:
    """The wire table: ms per message, bytes, the ratio; the prepared scene's in-process time where measured."""
    prep = {r["joints"]: r["prep"] for r in rows}
    lines = ["| " + " | ".join(WIRE_HEAD) + " |", "|" + "---|" * len(WIRE_HEAD)]
    for w in wire_rows:
        ms = [w[k] * 1e3 for k in ("session_p50", "session_p99", "bare_p50", "bare_p99")]
        cpu = [w[k] * 1e3 for k in ("session_server_cpu", "bare_server_cpu", "session_client_cpu")]
        cells = [str(w["joints"]), str(w["out"]), str(w["back"]), *(f"{v:.3f}" for v in ms),
                 f"{w['session_p50'] / w['bare_p50']:.2f}x", *(f"{v:.3f}" for v in cpu),
                 f"{prep[w['joints']] * 1e3:.3f}" if w["joints"] in prep else "not measured"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render(rows: list[dict[str, Any]], bare: dict[int, float] | None = None) -> str:
    """The table: medians in ms, then the targets' ratios (JAX EGH / core EGH, Warp E / core E, prepared / the bare
    round trip's p50 at the same joints, `bare`, when measured)."""
    bare = bare or {}
    cols = [*CORE, *PEERS]
    head = ["joints", *(name for name, _ in cols), "JAX EGH/core", "Warp E/core", "prepared/bare"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [str(r["joints"])]
        for _, key in cols:
            cells.append(f"{r[key] * 1e3:.3f}" if key in r else "not installed")
        ratio = lambda a, b: f"{r[a] / r[b]:.2f}x" if a in r and b in r else "not installed"  # noqa: E731
        n = r["joints"]
        cells += [ratio("jax_egh", "egh"), ratio("warp_e", "e"),
                  f"{r['prep'] / bare[n]:.2f}x" if n in bare else "not measured"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.robot_scale", description=__doc__.split("\n\n")[0])
    ap.add_argument("--joints", type=int, nargs="+", default=list(SIZES), help="scene sizes (default 1 10 100 1000)")
    ap.add_argument("--reps", type=int, default=301, help="timed calls per column (default 301)")
    ap.add_argument("--wire-joints", type=int, nargs="+", default=list(WIRE_SIZES),
                    help="session sizes (default 1 10 100)")
    ap.add_argument("--wire-reps", type=int, default=2001, help="messages per measurement over the wire (default 2001)")
    ap.add_argument("--no-wire", action="store_true", help="no server: the in-process table alone")
    args = ap.parse_args(argv)
    from jointlimits.service.core.heap import keep_heap

    keep_heap()  # as the service and the bench run
    print(f"robot scale: every joint active, half #670 half #669, one thread, medians of {args.reps} calls (ms)")
    rows = table(tuple(args.joints), args.reps)
    wire_rows = [] if args.no_wire else wire(tuple(args.wire_joints), args.wire_reps)
    print(render(rows, {w["joints"]: w["bare_p50"] for w in wire_rows}))
    if wire_rows:
        print(f"\nsession over loopback (E+G+H psd, msgpack) against a bare WebSocket round trip of the same bytes, "
              f"{args.wire_reps} messages each (ms; CPU per message)")
        print(render_wire(wire_rows, rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
