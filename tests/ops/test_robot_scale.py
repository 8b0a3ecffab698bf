"""bench/robot_scale.py at tiny repetition counts: every column timed, the table printed (peers skipped: the bench extra is optional)."""

from __future__ import annotations

import pytest

from bench import robot_scale

pytestmark = pytest.mark.serial  # times every column of the bench's robot table


def test_robot_scale_prints_its_table(monkeypatch, capsys):
    monkeypatch.setattr(robot_scale, "_peers", lambda: {})
    assert robot_scale.main(["--joints", "1", "10", "--reps", "2", "--no-wire"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("robot scale: every joint active")
    assert out[1].startswith("| joints | core E | core EGH | core EGH psd | prepared EGH psd | JAX E | JAX EGH | Warp E")
    rows = [line.split(" | ") for line in out[3:]]
    assert [r[0] for r in rows] == ["| 1", "| 10"]
    for r in rows:
        assert all(float(c) > 0 for c in r[1:5])  # the core's four medians, in ms
        assert r[5:8] == ["not installed"] * 3 and r[-1] == "not measured |"  # prepared/bare: no server


def test_robot_scale_rows_time_every_column(monkeypatch):
    monkeypatch.setattr(robot_scale, "_peers", lambda: {})
    rows = robot_scale.table((10,), reps=1)
    assert {"e", "egh", "psd", "prep"} <= set(rows[0]) and rows[0]["joints"] == 10


@pytest.mark.slow  # starts the service (and the bench's echo) in a subprocess
def test_robot_scale_wire_table(monkeypatch, capsys):
    monkeypatch.setattr(robot_scale, "_peers", lambda: {})
    assert robot_scale.main(["--joints", "10", "--reps", "2", "--wire-joints", "1", "10", "--wire-reps", "3"]) == 0
    out = capsys.readouterr().out.split("\n\n")[1].splitlines()
    assert out[0].startswith("session over loopback (E+G+H psd, msgpack) against a bare WebSocket round trip")
    assert out[1] == "| " + " | ".join(robot_scale.WIRE_HEAD) + " |"
    rows = [line.strip("| ").split(" | ") for line in out[3:]]
    assert [r[0] for r in rows] == ["1", "10"]
    for r in rows:
        assert int(r[1]) > 0 and int(r[2]) > 0 and all(float(c) > 0 for c in r[3:7])
        assert r[7].endswith("x") and all(float(c) >= 0 for c in r[8:11])
    assert int(rows[1][2]) > int(rows[0][2])  # 10 joints answer more than one
    assert rows[0][11] == "not measured" and float(rows[1][11]) > 0  # in-process at 10 joints only
