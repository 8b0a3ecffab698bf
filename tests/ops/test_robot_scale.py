"""bench/robot_scale.py at tiny repetition counts: every column timed, the table printed (peers skipped: the bench extra is optional)."""

from __future__ import annotations

from bench import robot_scale


def test_robot_scale_prints_its_table(monkeypatch, capsys):
    monkeypatch.setattr(robot_scale, "_peers", lambda: {})
    assert robot_scale.main(["--joints", "1", "10", "--reps", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("robot scale: every joint active")
    assert out[1].startswith("| joints | core E | core EGH | core EGH psd | prepared EGH psd | JAX E | JAX EGH | Warp E")
    rows = [line.split(" | ") for line in out[3:]]
    assert [r[0] for r in rows] == ["| 1", "| 10"]
    for r in rows:
        assert all(float(c) > 0 for c in r[1:5])  # the core's four medians, in ms
        assert r[5:8] == ["not installed"] * 3


def test_robot_scale_rows_time_every_column(monkeypatch):
    monkeypatch.setattr(robot_scale, "_peers", lambda: {})
    rows = robot_scale.table((10,), reps=1)
    assert {"e", "egh", "psd", "prep"} <= set(rows[0]) and rows[0]["joints"] == 10
