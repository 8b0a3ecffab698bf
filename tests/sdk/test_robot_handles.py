"""A `Robot`'s handles (`robot.handles`, made once at load) keep reading their joints: across calls with other
strengths, references and previous poses, under `active_only`, in a session (opened, evaluated, committed,
updated, reopened), pickled, and from another `Robot` of the same file; another robot's joint at the row is refused."""

from __future__ import annotations

import math
import pickle
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("yourdfpy")

from jointlimits import LocalClient, Robot  # noqa: E402

ARM = Path(__file__).parents[1] / "robots" / "arm7.urdf"


def load(path: Path = ARM) -> Robot:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # arm7's mimic finger
        return Robot.load(path)


def test_handles_read_their_joints_across_calls():
    robot, lc = load(), LocalClient()
    rng = np.random.default_rng(5)
    n = len(robot.names)
    for k in range(12):
        q = rng.uniform(-4, 4, n) + (0 if k % 3 else 2 * math.tau)
        ref = rng.uniform(-1, 1, n) if k % 2 else None
        prev = q - rng.uniform(-1, 1, n) if k % 4 == 1 else None
        strength = ({name: float(rng.uniform(0.5, 50)) for name in list(robot.handles)[k % 3::2]} if k % 3
                    else float(rng.uniform(0.5, 50)))
        scene, handles = robot.scene(q, prev, ref, strength)
        assert {name: (int(h), h.batch, h.key) for name, h in handles.items()} == \
               {name: (int(h), h.batch, h.key) for name, h in robot.handles.items()}
        result = lc.evaluate(scene.request(active_only=k % 2 == 0))
        r0 = np.zeros(n) if ref is None else ref
        for name, h in robot.handles.items():
            i = robot.names.index(name)
            got = result.joint(h)
            if got.x is None:  # inside its range, left out by active_only: it reads zero
                assert got.energy == 0.0
                continue
            # A revolute coordinate is q + one wrapped step of q - q_prev from the poses (a few ulps of 8 rad);
            # a slide is measured from the poses (arm7's reach ~1 m).
            assert abs(got.coordinate - q[i]) <= 1e-12 * max(1, abs(q[i])), name
            assert abs(got.x - (q[i] - r0[i])) <= 1e-12 * max(1, abs(q[i]), abs(r0[i])), name


def test_handles_in_a_session_with_updates_and_a_reopen():
    """docs/robots.md's "In a session", with a reference and strengths, an offset update and a reopen."""
    robot = load()
    ref = {"joint7": 0.25, "joint2": -0.1}
    with LocalClient().session(robot.request({}, reference=ref, strength={"joint7": 4.0})) as session:
        for k in range(1, 13):  # joint7 driven 6 rad down, 0.5 rad a step: x = position - its reference
            dofs = robot.poses({"joint7": -0.5 * k, "joint2": 0.05 * k})
            ev = session.evaluate(dofs)
            session.commit(dofs)
            if k == 6:
                session.reopen()
        seven, two = robot.handles["joint7"], robot.handles["joint2"]
        assert ev.joint(seven).x == pytest.approx(-6.0 - 0.25, abs=1e-12)
        assert ev.joint(seven).coordinate == pytest.approx(-6.0, abs=1e-12)
        assert ev.joint(two).coordinate == pytest.approx(0.6, abs=1e-12)
        # 4 gap^3 / (upper - lower)^3: the handle reads joint7's strength, not another joint's
        lo, up = next((jt.lower, jt.upper) for jt in robot.joints if jt.name == "joint7")
        assert ev.joint(seven).energy == pytest.approx(4.0 * ((lo - (-6.0)) / (up - lo)) ** 3, rel=1e-12)
        # An offset update keeps the committed angle x (docs/sessions.md): the coordinate moves with the offset.
        session.update(seven.batch, [int(seven)], offset=[0.0])
        after = session.evaluate(robot.poses({"joint7": -6.5, "joint2": 0.6}))
        assert after.joint(seven).x == pytest.approx(-6.75, abs=1e-12)
        assert after.joint(seven).coordinate == pytest.approx(-6.75, abs=1e-12)
        assert after.joint(two).coordinate == pytest.approx(0.6, abs=1e-12)


def test_pickled_handles_and_another_robot_of_the_same_file():
    robot, again = load(), load()
    handles = pickle.loads(pickle.dumps(robot.handles))
    q = np.linspace(-3.5, 3.5, len(robot.names))
    result = LocalClient().evaluate(again.request(q, strength=2.0))
    for name, h in handles.items():
        assert result.joint(h).coordinate == result.joint(again.handles[name]).coordinate
        assert abs(result.joint(h).coordinate - q[robot.names.index(name)]) <= 1e-12 * 3.5, name


def test_another_robots_joint_at_the_row_is_refused(tmp_path):
    """A second arm whose first joint's origin differs: the same rows and batches, other joints."""
    other = tmp_path / "other.urdf"
    other.write_text(ARM.read_text().replace('<origin xyz="0 0 0.333"', '<origin xyz="0 0 0.334"', 1))
    assert other.read_text() != ARM.read_text()
    robot, moved = load(), load(other)
    result = LocalClient().evaluate(moved.request({}))
    refused = [name for name, h in robot.handles.items() if not _reads(result, h)]
    assert refused and "joint1" in refused


def _reads(result, handle) -> bool:
    try:
        result.joint(handle)
    except KeyError:
        return False
    return True
