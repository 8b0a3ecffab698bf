"""bench/sessions.py: prepared scenes and sessions against the stateless call (a tiny run; speed is not asserted)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import sessions as S
from bench.__main__ import main as bench_main
from bench.scenes import make_scene
from jointlimits.service.core import evaluate
from jointlimits.service.core.prepared import prepare

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # the sessions bench against a uvicorn subprocess (~3 s)


def test_the_prepared_scene_timed_is_the_stateless_answer():
    """What the bench compares computes the same thing: bitwise the same answer."""
    bodies, batches = make_scene(100, S.OUTSIDE, seed=100 % 89)
    a = evaluate(bodies, batches)
    b = prepare(bodies, batches).evaluate(bodies.q)
    assert a.total_energy == b.total_energy
    for ra, rb in zip(a.batches, b.batches):
        assert ra.hessian.tobytes() == rb.hessian.tobytes() and ra.x.tobytes() == rb.x.tobytes()


def test_sessions_only_run_writes_its_report(tmp_path, capsys):
    assert bench_main(["--sessions-only", "--sizes", "100", "300", "--no-http", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "sessions.json").read_text())
    rows = res["sessions"]["inprocess"]
    assert [(r["n"], r["mode"]) for r in rows] == [(100, "energy"), (100, "E+G+H exact"), (300, "energy"),
                                                     (300, "E+G+H exact")]
    assert all(r["stateless"] > 0 and r["prepared"] > 0 for r in rows)
    text = (tmp_path / "sessions.md").read_text()
    assert "Prepared scene vs stateless" in text and "6. prepared energy at 300" in text
    assert "not measured" in text  # the wire target, with --no-http
    out = capsys.readouterr().out
    assert "5. session evaluate" in out and "6. prepared energy" in out


def test_wire_rows_have_both_transports_and_encodings():
    rows = S.wire({10: 3, 1_000: 2, 10_000: 1})
    keys = {(r["joints"], r["encoding"], r["transport"]) for r in rows}
    assert keys == {(n, e, t) for n in S.WIRE_SIZES for e in ("msgpack", "json") for t in ("HTTP (stateless)", "session")}
    for r in rows:
        assert 0 < r["p50_ms"] <= r["p99_ms"] and r["bytes_per_iteration"] > 0
    # A session sends q only: fewer bytes per iteration than re-sending the scene.
    by = {(r["joints"], r["encoding"], r["transport"]): r["bytes_per_iteration"] for r in rows}
    assert all(by[(n, e, "session")] < by[(n, e, "HTTP (stateless)")] for n in S.WIRE_SIZES for e in ("msgpack", "json"))
    (t5,) = [t for t in S.targets({"inprocess": [], "wire": rows}) if t["group"] == 5]
    assert t5["met"] is not None and np.isfinite(float(t5["measured"].rstrip("x")))


def test_the_full_report_has_the_sessions_section_and_targets():
    from bench import report
    from tests.ops.test_bench import synthetic_result

    res = synthetic_result()
    res["sessions"] = {
        "inprocess": [{"n": 100_000, "mode": "energy", "stateless": 0.1, "prepared": 0.025, "speedup": 4.0}],
        "wire": [{"joints": 10, "encoding": "msgpack", "transport": t, "iterations": 300, "p50_ms": p, "p99_ms": 2 * p,
                  "bytes_per_iteration": 6000.0} for t, p in (("HTTP (stateless)", 2.2), ("session", 0.7))],
    }
    res["targets"] = report.targets(res) + S.targets(res["sessions"])
    md = report.markdown(res)
    assert "## Prepared scene vs stateless, in-process" in md and "## Sessions vs stateless HTTP on loopback" in md
    assert "| 5. session evaluate, 10 joints, loopback, p50: speedup over stateless Client.evaluate (msgpack) | 3.14x" in md
    assert "| 6. prepared energy at 1e5 in-process: speedup over the stateless call | 4.00x" in md
