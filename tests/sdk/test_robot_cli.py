"""`jointlimits evaluate`: a robot file and a joint vector in, one line (or JSON object) per joint out."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("yourdfpy")

from jointlimits import cli  # noqa: E402
from jointlimits.client import LocalClient  # noqa: E402
from jointlimits.client.robot import Robot  # noqa: E402
from tests.http.test_cli import console_script  # noqa: E402
from tests.http.test_contract_live import serve  # noqa: E402

ARM = str(Path(__file__).parents[1] / "robots" / "arm7.urdf")
# wheel, joint1..7, finger_left: joint1 past -pi below its lower limit, joint6 inside past +pi, joint7 two
# turns out, the finger past its upper limit
Q = [12.0, -3.81, 0.2, 0.0, -1.0, 0.0, 3.6, 2 * math.tau + 0.1, 0.05]
PAST = {"joint1", "joint7", "finger_left"}


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = cli.main(["evaluate", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def expected() -> list:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        robot = Robot.load(ARM)
    return robot.readings(LocalClient().evaluate(robot.request(Q)), Q)


def test_the_table_has_one_line_per_joint(capsys):
    code, out, _ = run(capsys, ARM, *map(str, Q))
    assert code == 0
    lines = out.splitlines()
    assert lines[0].split() == ["joint", "position", "limits", "energy", "active"]
    rows = {line.split()[0]: line for line in lines[1:10]}
    assert list(rows) == ["wheel", *(f"joint{k}" for k in range(1, 8)), "finger_left"]
    assert "no limit" in rows["wheel"] and "12 rad" in rows["wheel"]
    assert "-3.81 rad" in rows["joint1"] and "[-2.8973, 2.8973]" in rows["joint1"]
    assert {n for n, line in rows.items() if line.endswith("ACTIVE")} == PAST
    for r in expected():
        assert f"{r.energy:.6g}" in rows[r.name].split()
    assert lines[10].startswith(f"total energy {math.fsum(r.energy for r in expected()):.6g}; 3 active of 9 joints")
    assert lines[11] == "not modelled: prismatic joint finger_right: mimics finger_left (1 x finger_left + 0), posed by FK, no limit"


def test_json_carries_every_reading_exactly(capsys):
    code, out, _ = run(capsys, ARM, *map(str, Q), "--json")
    assert code == 0
    got = json.loads(out)
    want = expected()
    assert [g["name"] for g in got] == [r.name for r in want]
    for g, r, q in zip(got, want, Q):
        assert g == {"name": r.name, "type": r.type, "position": r.position, "lower": r.lower, "upper": r.upper,
                     "energy": r.energy, "active": r.active}
        assert abs(g["position"] - q) <= 1e-12  # the position past pi and over turns, not wrapped
    assert {g["name"] for g in got if g["active"]} == PAST


def test_a_request_file_by_name_with_a_previous_pose(capsys, tmp_path):
    names = ["wheel", *(f"joint{k}" for k in range(1, 8)), "finger_left"]
    f = tmp_path / "request.json"
    f.write_text(json.dumps({"q": dict(zip(names, Q)), "q_prev": [q - 0.25 for q in Q], "strength": 4.0}))
    code, out, _ = run(capsys, ARM, "--request", str(f), "--json")
    assert code == 0
    got = {g["name"]: g for g in json.loads(out)}
    np.testing.assert_allclose([got[n]["position"] for n in names], Q, rtol=0, atol=1e-12)
    assert got["joint1"]["energy"] == pytest.approx(4.0 * next(r.energy for r in expected() if r.name == "joint1"), rel=1e-12)


def test_over_a_live_server_the_same(capsys):
    local = run(capsys, ARM, *map(str, Q), "--json")[1]
    with serve() as url:
        code, remote, _ = run(capsys, ARM, *map(str, Q), "--json", "--url", url)
    assert code == 0 and json.loads(remote) == json.loads(local)


def test_without_positions_it_lists_the_joints(capsys):
    code, out, _ = run(capsys, ARM)
    assert code == 0
    assert out.splitlines()[0].endswith("9 moving joints, give one position each: wheel joint1 joint2 joint3 "
                                        "joint4 joint5 joint6 joint7 finger_left")


@pytest.mark.parametrize("argv, words", [
    ([ARM, "0.1", "0.2"], "q: 9 positions, one per joint of ['wheel'"),
    (["no/such.urdf", "0"], "No such file or directory: 'no/such.urdf'"),
    ([ARM, "0", "--request", "no/such.json"], "No such file"),
])
def test_mistakes_are_said_in_one_line(capsys, argv, words):
    code, out, err = run(capsys, *argv)
    assert code == 2 and out == "" and words in err and err.count("\n") == 1


def test_a_request_file_that_is_not_an_object_and_a_server_that_is_not_there(capsys, tmp_path):
    f = tmp_path / "q.json"
    f.write_text("[1, 2]")
    code, out, err = run(capsys, ARM, "--request", str(f))
    assert code == 2 and "a JSON object is expected, got list" in err
    f.write_text("{q: [1]}")  # not JSON: json's words, which name no file, follow the file's name
    code, out, err = run(capsys, ARM, "--request", str(f))
    assert code == 2 and err.startswith(f"jointlimits evaluate: {f}: Expecting property name") and err.count("\n") == 1
    code, out, err = run(capsys, ARM, *map(str, Q), "--url", "http://127.0.0.1:9")  # the discard port: refused
    assert code == 1 and out == "" and err.startswith("jointlimits evaluate: ") and "Traceback" not in err



def test_a_missing_extra_and_a_bad_url_are_said_in_one_line(capsys, monkeypatch, tmp_path):
    """Before: without yourdfpy, or matplotlib for --plot (the readings then not printed either), or with a --url
    that lacks http://, a traceback."""
    code, out, err = run(capsys, ARM, *map(str, Q), "--url", "localhost:8000")
    assert code == 1 and out == "" and "not an http:// or https:// URL" in err and err.count("\n") == 1
    code, out, err = run(capsys, ARM, *map(str, Q), "--plot", str(tmp_path / "no" / "such" / "dir.png"))
    assert code == 1 and out == "" and err.startswith("jointlimits evaluate: ") and err.count("\n") == 1
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # `import` of it raises ImportError
    code, out, err = run(capsys, ARM, *map(str, Q), "--plot", str(tmp_path / "joints.png"))
    assert code == 1 and out == "" and "the picture needs matplotlib" in err and err.count("\n") == 1
    monkeypatch.setitem(sys.modules, "yourdfpy", None)
    code, out, err = run(capsys, ARM, *map(str, Q))
    assert code == 2 and out == "" and "reading a URDF needs yourdfpy" in err and err.count("\n") == 1

def test_a_fault_of_the_service_names_the_joint(capsys):
    """The service's fault (here an energy that overflows float64) was printed with its batch and row only
    ("body.batches.1.strength.0"): the person at the terminal is told the joint's name too."""
    code, out, err = run(capsys, ARM, *map(str, Q[:-1]), "1e200")
    assert code == 1 and out == "" and err.startswith("jointlimits evaluate: joint finger_left: ") and "overflow" in err


def test_the_picture(capsys, tmp_path):
    pytest.importorskip("matplotlib")
    png = tmp_path / "joints.png"
    assert run(capsys, ARM, *map(str, Q), "--plot", str(png))[0] == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_the_console_script_runs_it():
    done = subprocess.run([*console_script(), "evaluate", ARM, *map(str, Q), "--json"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert [g["energy"] for g in json.loads(done.stdout)] == [r.energy for r in expected()]
    help_text = subprocess.run([*console_script(), "--help"], capture_output=True, text=True).stdout
    assert "evaluate" in help_text and "serve" in help_text


def test_a_robot_with_no_moving_joint_reads_as_an_empty_table(capsys, tmp_path):
    """Before: a table of no rows raised TypeError (`max` of one int) from the column widths, a traceback."""
    urdf = tmp_path / "rigid.urdf"
    urdf.write_text('<robot name="rigid"><link name="a"/><link name="b"/>'
                    '<joint name="w" type="fixed"><parent link="a"/><child link="b"/></joint></robot>')
    request = tmp_path / "q.json"
    request.write_text('{"q": []}')
    code, out, err = run(capsys, str(urdf), "--request", str(request))
    assert (code, err) == (0, "")
    assert out.splitlines() == ["joint  position  limits  energy  active", "total energy 0; 0 active of 0 joints"]


@pytest.mark.parametrize(("doc", "name"), [({"q": {"joint1": "abc"}}, "q"), ({"q": Q, "q_prev": [0] * 8 + ["x"]}, "q_prev")])
def test_a_position_that_is_no_number_is_named(capsys, tmp_path, doc, name):
    """Before: numpy's words alone ("could not convert string to float: 'abc'"), naming no vector; now the vector
    and the joint, as "0.5" is refused (a string is no position, whatever it reads as)."""
    request = tmp_path / "q.json"
    request.write_text(json.dumps(doc))
    code, out, err = run(capsys, ARM, "--request", str(request))
    assert code == 2 and out == ""
    assert err.startswith(f"jointlimits evaluate: {name}: a position is a number, not a string")


@pytest.mark.parametrize("doc", [{"q": {"joint1": True}}, {"q": Q, "q_prev": [False] + [0] * 8}])
def test_a_boolean_position_is_refused(capsys, tmp_path, doc):
    """Before: JSON `true` read as 1 rad, where the wire and `Scene` refuse a boolean as a number."""
    request = tmp_path / "q.json"
    request.write_text(json.dumps(doc))
    code, out, err = run(capsys, ARM, "--request", str(request))
    assert code == 2 and out == "" and "not a boolean" in err


@pytest.mark.slow  # the console script in a process of its own (~1 s)
def test_a_reader_that_leaves_early_gets_no_traceback():
    """Before: `jointlimits evaluate ... --json | head -c 1` ended in a BrokenPipeError traceback on stderr."""
    with subprocess.Popen([*console_script(), "evaluate", ARM, *map(str, Q), "--json"], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True) as proc:
        proc.stdout.close()  # the reader is gone before the command writes (Python ignores SIGPIPE: EPIPE)
        err = proc.stderr.read()
    assert proc.returncode == 1 and err == ""
