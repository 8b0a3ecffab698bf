"""`Robot` against forward kinematics written here from the URDF spec (not yourdfpy's), on the trickiest file.

The file below has origins turned by rpy, axes not unit and negative, a prismatic joint with a non-unit axis,
a fixed joint mid-chain, a continuous joint, mimic joints with a multiplier and offset (a revolute and a
prismatic one), degenerate ranges (lower == upper) and a joint whose zero lies outside its range. Checked:
every body's pose, each limited joint's coordinate (= its position, over turns), the spec's energy of it,
the gradient against central differences of the energy in the bodies' 24 DOFs, and the readings.
"""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

pytest.importorskip("yourdfpy")

from jointlimits import LocalClient, Robot  # noqa: E402

J = '<joint name="{}" type="{}"><parent link="{}"/><child link="{}"/><origin xyz="{}" rpy="{}"/>{}</joint>'
LIM = '<axis xyz="{}"/><limit lower="{}" upper="{}" effort="1" velocity="1"/>'
URDF = "<robot name='odd'>" + "".join(f'<link name="{n}"/>' for n in "o a b bf c d e f g h m1 m2 k".split()) + "".join([
    J.format("ja", "revolute", "o", "a", "0.1 0.2 0.3", "0.4 -0.7 1.1", LIM.format("0 0 2", -1, 1)),
    J.format("jb", "revolute", "a", "b", "-0.3 0.5 0.05", "2.9 0.3 -2.2", LIM.format("-1 0 0", 0.5, 1.2)),  # 0 outside
    J.format("fix", "fixed", "b", "bf", "0.2 0 0.1", "0.1 0.2 0.3", ""),
    J.format("jc", "prismatic", "bf", "c", "0 0.1 0", "1.0 0.5 0.2", LIM.format("0 3 0", 0.1, 0.3)),
    J.format("jd", "continuous", "c", "d", "0.05 0.05 0.05", "0 1.2 0", '<axis xyz="1 2 3"/>'),
    J.format("je", "revolute", "d", "e", "0.3 -0.1 0.2", "-1.3 0.2 0.9", LIM.format("0.3 -0.4 1.2", -7.5, 7.0)),
    J.format("jf", "prismatic", "e", "f", "0 0 0.4", "0 0 0", LIM.format("0 0 -0.5", -0.2, 0.2)),
    J.format("jg", "revolute", "f", "g", "0 0 0", "0 0 0", LIM.format("1 0 0", 0.3, 0.3)),
    J.format("jh", "prismatic", "g", "h", "0.1 0 0", "0 0.3 0", LIM.format("1 1 0", -0.15, -0.15)),
    J.format("jm1", "revolute", "a", "m1", "0 0.3 0", "0.2 0 0", '<mimic joint="ja" multiplier="-2" offset="0.3"/>'
             + LIM.format("0 1 0", -1, 1)),
    J.format("jm2", "prismatic", "h", "m2", "0 0.3 0", "0.2 0 0", '<mimic joint="jc" multiplier="0.5" offset="0.01"/>'
             + LIM.format("0 1 0", -1, 1)),
    J.format("jk", "revolute", "o", "k", "1 0 0", "0 0 3.0", LIM.format("0 0 1", -4.0, -3.5)),
]) + "</robot>"
POSES = {  # each limited joint at least 0.1 from its range's ends when outside (the energy's bound below)
    "zero": {},
    "inside": dict(ja=0.3, jb=0.8, jc=0.2, jd=5.0, je=3.0, jf=0.1, jg=0.3, jk=-3.7),
    "outside": dict(ja=1.3, jb=-2.8, jc=0.45, jd=-9.0, je=-9.0, jf=-0.4, jg=0.5, jh=0.1, jk=-4.5),
    "turns": dict(ja=-1.3, jb=8.0, jc=-0.45, jd=19.0, je=3 * math.tau + 1.0, jf=0.35, jg=-3.5, jh=-0.3, jk=3.0),
}


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def fk(q: dict[str, float]) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
    """Every link's world transform (4, 4) at `q` (URDF spec: origin = Trans(xyz) Rz(y) Ry(p) Rx(r), then the
    motion about / along the unit axis), and each joint's facts with its position (mimic: k q + b)."""
    joints = {}
    for j in ET.fromstring(URDF).iter("joint"):
        o, ax, lim, mimic = (j.find(t) for t in ("origin", "axis", "limit", "mimic"))
        r, p, y = (float(v) for v in o.get("rpy").split())
        T = np.eye(4)
        e = np.eye(3)
        T[:3, :3] = rotation(e[2], y) @ rotation(e[1], p) @ rotation(e[0], r)
        T[:3, 3] = [float(v) for v in o.get("xyz").split()]
        pos = q.get(j.get("name"), 0.0)
        if mimic is not None:
            pos = float(mimic.get("multiplier")) * q.get(mimic.get("joint"), 0.0) + float(mimic.get("offset"))
        joints[j.get("name")] = dict(
            type=j.get("type"), parent=j.find("parent").get("link"), child=j.find("child").get("link"), T=T,
            mimic=mimic is not None, position=pos,
            axis=None if ax is None else np.array([float(v) for v in ax.get("xyz").split()]),
            limits=None if lim is None else (float(lim.get("lower")), float(lim.get("upper"))))
    world = {"o": np.eye(4)}
    for jt in joints.values():  # the file lists each parent's joint before its children's
        M = np.eye(4)
        if jt["type"] in ("revolute", "continuous"):
            M[:3, :3] = rotation(jt["axis"], jt["position"])
        elif jt["type"] == "prismatic":
            M[:3, 3] = jt["position"] * jt["axis"] / np.linalg.norm(jt["axis"])
        world[jt["child"]] = world[jt["parent"]] @ jt["T"] @ M
    return world, joints


def energy(x: float, lower: float, upper: float, s: float) -> float:
    """The specs' cubic penalty (boundary in range; s |x - l|^3 when lower == upper)."""
    gap = max(x - upper, lower - x, 0.0)
    return s * (gap if upper == lower else gap / (upper - lower)) ** 3


@pytest.fixture(scope="module")
def robot(tmp_path_factory) -> Robot:
    path = tmp_path_factory.mktemp("urdf") / "odd.urdf"
    path.write_text(URDF)
    with pytest.warns(UserWarning, match="jm1: mimics ja"):
        return Robot.load(path)


@pytest.mark.parametrize("pose", list(POSES))
def test_poses_coordinates_energies_gradients_and_readings(robot, pose):
    q, s = POSES[pose], 7.0
    world, joints = fk(q)
    # Poses: products of a few O(1) rotations and offsets, a few ulp each; 1e-13 holds on any libm.
    for b, link in enumerate(robot.frames):
        T = world[link]
        np.testing.assert_allclose(robot.poses(q)[b], [*T[:3, 3], *T[:3, :3].ravel()], rtol=0, atol=1e-13)
    request = robot.request(q, strength=s)
    result = LocalClient().evaluate(request)
    readings = {r.name: r for r in robot.readings(result, q)}
    assert set(readings) == {n for n, jt in joints.items() if jt["type"] != "fixed" and not jt["mimic"]}
    for name, jt in joints.items():
        if name not in robot.handles:
            continue
        got, (lo, up), x = result.joint(robot.handles[name]), jt["limits"], jt["position"]
        # A revolute coordinate is q exactly plus one wrapped step of 0; a slide is measured from the poses:
        # a few roundings of |x| <= 20 and O(1) poses, 1e-13 with margin.
        assert abs(got.coordinate - x) <= 1e-13 and abs(readings[name].position - x) <= 1e-13, name
        # E = s gap^3: |dE/E| <= 3 |dx| / gap; outside joints are >= 0.1 from their range, so 3e-12 + roundings.
        want = energy(x, lo, up, s)
        assert abs(got.energy - want) <= 4e-12 * want, (name, got.energy, want)
        assert (readings[name].lower, readings[name].upper) == (lo, up) and readings[name].energy == got.energy
        assert readings[name].active == (want > 0), name
        if want == 0:
            assert not np.any(got.gradient), name
            continue
        # Central differences of the energy in the two bodies' DOFs: truncation h^2 E'''/6 ~ 1e-12 and rounding
        # eps E / h ~ 1e-10 against |grad| ~ 1..1e3: 1e-6 of the largest entry is far above both and catches a
        # wrong edge (axis or origin), which changes dx/dq by O(1).
        i, j = next(rj.body_ids for rj in robot.joints if rj.name == name)
        fd, h = np.zeros(24), 1e-6
        for c in range(24):
            e = []
            for sign in (1, -1):
                Q = np.array(request.q)
                Q[(i, j)[c // 12], c % 12] += sign * h
                e.append(LocalClient().evaluate(dataclasses.replace(request, q=Q)).joint(robot.handles[name]).energy)
            fd[c] = (e[0] - e[1]) / (2 * h)
        assert np.abs(fd - got.gradient).max() <= 1e-6 * np.abs(got.gradient).max(), name


def test_a_previous_pose_and_a_reference_leave_the_coordinate_at_q(robot):
    q, ref = POSES["turns"], POSES["inside"]
    q_prev = {n: v - 0.9 for n, v in q.items()}  # under pi from q
    result = LocalClient().evaluate(robot.request(q, q_prev=q_prev, reference=ref))
    for name, h in robot.handles.items():
        got = result.joint(h)
        assert abs(got.coordinate - q.get(name, 0.0)) <= 1e-13, name
        assert abs(got.x - (q.get(name, 0.0) - ref.get(name, 0.0))) <= 1e-13, name
