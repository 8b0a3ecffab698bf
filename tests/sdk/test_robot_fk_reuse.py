"""A robot's stateless call runs its FK once per distinct joint vector (brief robot-speed): `q_prev` equal
to `q` reuses q's poses, the reference's are kept for the next call while it is the same (by value: an array the
caller changes in place is a new reference), and no reuse or call order changes a bit of a pose or an answer.

FK sweeps are counted with a spy on `Robot._fk`."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("yourdfpy")

from jointlimits.client import LocalClient  # noqa: E402
from jointlimits.client.robot import Robot  # noqa: E402
from tests.conftest import same_evaluation  # noqa: E402

ARM = Path(__file__).parents[1] / "robots" / "arm7.urdf"
OUT = ("energy", "gradient", "hessian")


def load() -> Robot:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # arm7's mimic finger, warned about in test_robot.py
        return Robot.load(ARM)


@pytest.fixture
def counted(monkeypatch) -> tuple[Robot, list[int]]:
    """A fresh arm7 and a list counting its FK sweeps (`Robot._fk` calls)."""
    robot, calls = load(), []
    real = robot._fk
    monkeypatch.setattr(robot, "_fk", lambda *a, **k: calls.append(1) or real(*a, **k))
    return robot, calls


def fks(robot: Robot, calls: list[int], **kw) -> int:
    """FK sweeps one `robot.request(**kw)` ran."""
    calls.clear()
    robot.request(**kw)
    return len(calls)


def test_one_fk_per_call_with_the_default_previous_pose_and_reference(counted):
    robot, calls = counted
    q = np.linspace(-0.6, 0.9, len(robot.names))
    assert fks(robot, calls, q=q) == 1  # 3 before: q, q_prev (= q) and the zero reference
    assert fks(robot, calls, q=q + 0.1) == 1
    assert fks(robot, calls, q=q, q_prev=q.copy()) == 1  # the same vector by value
    assert fks(robot, calls, q=q, q_prev=q + 0.1) == 2
    assert fks(robot, calls, q={"joint1": 0.3}) == 1  # by name too


def test_the_reference_is_kept_by_value(counted):
    robot, calls = counted
    q, ref = np.full(len(robot.names), 0.2), np.full(len(robot.names), -0.1)
    assert fks(robot, calls, q=q, reference=ref) == 2
    assert fks(robot, calls, q=q, reference=ref.copy()) == 1
    ref[3] = 0.4  # changed in place: a new reference
    assert fks(robot, calls, q=q, reference=ref) == 2
    assert fks(robot, calls, q=q, reference=ref) == 1
    assert fks(robot, calls, q=q) == 2  # back to zero: the last one is kept, not every one
    assert fks(robot, calls, q=q, reference=-0.0 * ref) == 2  # -0.0 is not 0.0 to FK's sines: not reused


def test_no_reuse_or_order_changes_an_answer():
    """One robot through a sequence of calls answers bitwise as a fresh robot does for each call alone."""
    robot, lc = load(), LocalClient()
    n = len(robot.names)
    base, ref = np.linspace(-0.6, 0.9, n), np.full(n, 0.05)
    calls = [dict(q=base), dict(q=base + 3e-9), dict(q=base, q_prev=base.copy()), dict(q=base, q_prev=base - 0.2),
             dict(q=base, reference=ref), dict(q=base + 1e-10, reference=ref.copy(), q_prev=base),
             dict(q=base, reference=ref + 1e-9), dict(q=np.zeros(n)), dict(q=np.full(n, -0.0)), dict(q=base)]
    for kw in calls:
        same_evaluation(lc.evaluate(robot.request(**kw, outputs=OUT)), lc.evaluate(load().request(**kw, outputs=OUT)))


def test_poses_do_not_depend_on_the_pose_before():
    """trimesh keeps a joint's transform when the new one is within 1e-8 of it: a step of 3e-9 rad after a pose
    was lost (the poses stayed those of the pose before, 2.9e-9 off), so the poses depended on the call before."""
    robot = load()
    q = np.full(len(robot.names), 0.3)
    q2 = q.copy()
    q2[2] += 3e-9
    fresh = load().poses(q2)
    robot.poses(q)
    assert robot.poses(q2).tobytes() == fresh.tobytes()


TINY = """<robot name="tiny">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="l3"/>
  <joint name="turn" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="1" effort="1" velocity="1"/></joint>
  <joint name="slide" type="prismatic"><parent link="l1"/><child link="l2"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
  <joint name="tilt" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0 0 0.3"/><axis xyz="0 1 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>"""


@pytest.mark.parametrize("tiny", [1e-9, -3e-9, 2e-12, -5e-15])
def test_a_tiny_move_from_a_joints_identity_origin_is_not_lost(tmp_path, tiny):
    """Joints whose origin is the identity, at a position within 1e-8 of zero: their transform is within 1e-8 of
    the identity, which yourdfpy's scene graph (trimesh) dropped from a link's path, so `x` read 0, not the
    position (and a limit at 0 read no penetration). Each coordinate is its position to 1e-12, whatever was
    asked before (a call at zero first: trimesh also kept a transform within 1e-8 of the new one)."""
    path = tmp_path / "tiny.urdf"
    path.write_text(TINY)
    robot, lc = Robot.load(path), LocalClient()
    lc.evaluate(robot.request(np.zeros(3)))
    q = np.array([tiny, tiny, tiny])
    result = lc.evaluate(robot.request(q, outputs=OUT))
    for k, name in enumerate(robot.names):
        r = result.joint(robot.handles[name])
        assert abs(r.coordinate - q[k]) <= 1e-12 * max(1.0, abs(q[k])) and (r.coordinate == 0) == (q[k] == 0), name
    below = tiny < 0  # turn and slide are past their lower limit 0: E = (-x)^3 (strength 1: x = position)
    for name in ("turn", "slide"):
        assert result.joint(robot.handles[name]).energy == pytest.approx((-tiny) ** 3 if below else 0.0, rel=1e-9)


def test_a_call_between_another_calls_reference_and_its_scene_changes_nothing(monkeypatch):
    """The reference's poses are kept on the robot for the next call: a call made from another thread after this
    one stored its reference and before it built its bodies (forced here, deterministically, when the first
    call makes its Scene) gave this call the other reference's poses under its own offsets: a wrong x."""
    import jointlimits.client.robot as module

    robot, fresh = load(), load()
    n = len(robot.names)
    q, mine, theirs = np.full(n, 0.4), np.full(n, 0.1), np.full(n, -0.3)
    real, nested = module.Scene, []

    def interleaved():
        if not nested:
            nested.append(None)
            nested[0] = robot.request(q, reference=theirs)  # "another thread"
        return real()

    monkeypatch.setattr(module, "Scene", interleaved)
    got = robot.request(q, reference=mine)
    monkeypatch.setattr(module, "Scene", real)
    want = fresh.request(q, reference=mine)
    assert got.q_ref.tobytes() == want.q_ref.tobytes()
    assert nested[0].q_ref.tobytes() == load().request(q, reference=theirs).q_ref.tobytes()
