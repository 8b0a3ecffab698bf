"""`Robot`'s FK and coordinates on random URDF trees, against an FK written here from the URDF spec alone.

The reference reads the file with ElementTree (not yourdfpy): a joint's transform is origin * motion, the origin
Trans(xyz) Rz(yaw) Ry(pitch) Rx(roll) (fixed-axis XYZ; an absent `<origin>` or attribute is zero), the motion a
turn about (or slide along) the unit `<axis>` (absent: x), a mimic joint at multiplier * its joint's position +
offset (a mimic of a mimic composes; of a joint with no position, fixed, floating or planar, 0 + offset).
The trees branch (several children per link), carry fixed joints mid-chain and at leaves, floating and planar
joints, origins at near-gimbal pitch, axes not unit and negative, and joints at 0, +-1e-12, +-1e-9 and turns.
"""

from __future__ import annotations

import math
import pickle
import warnings
import xml.etree.ElementTree as ET

import numpy as np
import pytest

pytest.importorskip("yourdfpy")

from jointlimits import LocalClient, Robot  # noqa: E402

TYPES = ("revolute", "revolute", "continuous", "prismatic", "prismatic", "fixed", "mimic", "floating", "planar")
SMALL = (0.0, -0.0, 1e-12, -1e-12, 1e-9, -1e-9)


def number(rng: np.random.Generator) -> str:
    return repr(float(rng.choice([0.0, rng.uniform(-1, 1), rng.uniform(-0.3, 0.3)])))


def random_urdf(seed: int) -> str:
    """A random tree of 6..14 links: each link's parent any earlier one, its joint of a random type."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(6, 15))
    joints, moving = [], []
    for k in range(1, n):
        kind = str(rng.choice(TYPES))
        parent = int(rng.integers(0, k))
        parts = [f'<parent link="l{parent}"/><child link="l{k}"/>']
        form = rng.integers(0, 4)  # no origin, xyz only, rpy only, both
        pitch = rng.choice([rng.uniform(-3.2, 3.2), math.pi / 2 - 1e-9, -math.pi / 2, math.pi / 2])
        rpy = f"{rng.uniform(-3.2, 3.2)!r} {float(pitch)!r} {rng.uniform(-3.2, 3.2)!r}"
        xyz = " ".join(number(rng) for _ in range(3))
        parts.append(["", f'<origin xyz="{xyz}"/>', f'<origin rpy="{rpy}"/>', f'<origin xyz="{xyz}" rpy="{rpy}"/>'][form])
        if rng.random() < 0.85:  # else the default axis, x
            axis = rng.choice([[0, 0, 1], [0, -1, 0], [-2, 0, 0]]) if rng.random() < 0.4 else rng.normal(size=3) * 3
            parts.append('<axis xyz="{}"/>'.format(" ".join(repr(float(a)) for a in axis)))
        if kind == "mimic":
            if not moving:
                kind = "fixed"
            else:
                kind = str(rng.choice(["revolute", "prismatic", "continuous"]))
                target = str(rng.choice(moving + [j for j in ("j1", "j2") if j != f"j{k}"]))  # any kind, earlier
                parts.append(f'<mimic joint="{target}" multiplier="{rng.uniform(-2, 2)!r}" '
                             f'offset="{float(rng.choice([0.0, rng.uniform(-0.5, 0.5)]))!r}"/>')
        if kind in ("revolute", "prismatic") and rng.random() < 0.9:
            lo = float(rng.uniform(-2, 1))
            parts.append(f'<limit lower="{lo!r}" upper="{lo + float(rng.uniform(0, 2))!r}" effort="1" velocity="1"/>')
        joints.append(f'<joint name="j{k}" type="{kind}">{"".join(parts)}</joint>')
        if kind in ("revolute", "prismatic", "continuous"):
            moving.append(f"j{k}")
    order = rng.permutation(len(joints))  # the file's order is not the tree's
    links = "".join(f'<link name="l{k}"/>' for k in rng.permutation(n))
    return f'<robot name="r{seed}">{links}{"".join(joints[i] for i in order)}</robot>'


def rot(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' turn by `angle` about the unit `axis`."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def spec_fk(urdf: str, q: dict[str, float]) -> dict[str, np.ndarray]:
    """Every link's transform (4, 4) in the root's at positions `q` (a moving joint left out is at 0)."""
    xml = {j.get("name"): j for j in ET.fromstring(urdf).iter("joint")}

    def position(name: str, seen: tuple = ()) -> float:
        j = xml[name]
        m = j.find("mimic")
        if m is None:
            return q.get(name, 0.0) if j.get("type") in ("revolute", "prismatic", "continuous") else 0.0
        assert name not in seen
        target = m.get("joint")
        of = position(target, (*seen, name)) if target in xml else 0.0
        return float(m.get("multiplier", 1)) * of + float(m.get("offset", 0))

    local = {}
    for name, j in xml.items():
        o = j.find("origin")
        xyz = [0.0] * 3 if o is None else [float(v) for v in o.get("xyz", "0 0 0").split()]
        r, p, y = [0.0] * 3 if o is None else [float(v) for v in o.get("rpy", "0 0 0").split()]
        e = np.eye(3)
        T = np.eye(4)
        T[:3, :3] = rot(e[2], y) @ rot(e[1], p) @ rot(e[0], r)
        T[:3, 3] = xyz
        a = j.find("axis")
        axis = np.array([1.0, 0, 0]) if a is None else np.array([float(v) for v in a.get("xyz").split()])
        axis = axis / np.linalg.norm(axis)
        M = np.eye(4)
        kind, v = j.get("type"), position(name)
        if kind in ("revolute", "continuous"):
            M[:3, :3] = rot(axis, v)
        elif kind == "prismatic":
            M[:3, 3] = v * axis
        local[j.find("child").get("link")] = (j.find("parent").get("link"), T @ M)
    world: dict[str, np.ndarray] = {}

    def at(link: str) -> np.ndarray:
        if link not in world:
            world[link] = np.eye(4) if link not in local else at(local[link][0]) @ local[link][1]
        return world[link]

    for link in local:
        at(link)
    return world


def load(tmp_path, urdf: str, name: str = "r.urdf") -> Robot:
    path = tmp_path / name
    path.write_text(urdf)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # mimic, floating and planar joints are warned about
        return Robot.load(path)


def positions(robot: Robot, rng: np.random.Generator, kind: str) -> np.ndarray:
    n = len(robot.names)
    if kind == "small":
        return rng.choice(SMALL, size=n)
    if kind == "turns":  # several turns (each revolute limit is given its position: no wrapping)
        return rng.uniform(-25, 25, size=n) * rng.choice([1, 1, 1e-9], size=n)
    return rng.uniform(-1.5, 1.5, size=n)


def check_poses(robot: Robot, urdf: str, v: np.ndarray) -> None:
    world = spec_fk(urdf, dict(zip(robot.names, v.tolist())))
    got = robot.poses(v)
    want = np.array([[*world[f][:3, 3], *world[f][:3, :3].ravel()] for f in robot.frames])
    # A pose is a product of <= 14 transforms of O(1) entries, each a few roundings (sin, cos of |v| <= 25 to
    # ~1 ulp of 25 in libm, no worse); the translations scale with the tree's reach: 1e-13 of it, with margin.
    scale = max(1.0, float(np.abs(want).max()))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * scale)


SEEDS = range(40)


@pytest.mark.parametrize("seed", SEEDS)
def test_random_trees_poses_and_coordinates(tmp_path, seed):
    urdf = random_urdf(seed)
    robot = load(tmp_path, urdf)
    rng = np.random.default_rng(1000 + seed)
    lc = LocalClient()
    for kind in ("small", "plain", "turns", "small", "plain"):
        v = positions(robot, rng, kind)
        check_poses(robot, urdf, v)
        result = lc.evaluate(robot.request(v))
        for name, h in robot.handles.items():
            k = robot.names.index(name)
            got = result.joint(h).coordinate
            # A revolute coordinate is its position plus a wrapped step of 0: exact. A slide is read from the
            # poses, whose entries reach max|v| times the tree's <= 14 links and carry a few roundings per link:
            # 1e-13 of max|v| (measured: 6e-16 here; 1.3e-14 with sin and cos 4 ulps off, `--perturb-ulps 4`, as
            # another CPU's kernels may be): in the small poses (max|v| < 1) below a joint at 1e-12 read as 0.
            if next(jt.type for jt in robot.joints if jt.name == name) == "revolute":
                assert got == v[k], (name, got, v[k])
            assert abs(got - v[k]) <= 1e-13 * max(1.0, float(np.abs(v).max())), (name, got, v[k])


@pytest.mark.parametrize("seed", SEEDS[:12])
def test_no_dependence_on_call_order(tmp_path, seed):
    """A robot through a sequence of calls poses (and answers) bitwise as a fresh one does for each call."""
    urdf = random_urdf(seed)
    robot, rng = load(tmp_path, urdf), np.random.default_rng(seed)
    lc = LocalClient()
    for kind in ("plain", "small", "plain", "turns", "small"):
        v = positions(robot, rng, kind)
        ref = positions(robot, rng, "small")
        fresh = load(tmp_path, urdf, "fresh.urdf")
        assert robot.poses(v).tobytes() == fresh.poses(v).tobytes()
        a, b = (lc.evaluate(r.request(v, reference=ref)) for r in (robot, fresh))
        for h in robot.handles.values():
            assert (a.joint(h).coordinate, a.joint(h).x, a.joint(h).energy) == \
                   (b.joint(h).coordinate, b.joint(h).x, b.joint(h).energy)


MIMIC_CHAIN = """<robot name="mc"><link name="a"/><link name="b"/><link name="c"/><link name="d"/><link name="e"/>
<joint name="drive" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>
  <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
<joint name="follow" type="revolute"><parent link="b"/><child link="c"/><origin xyz="1 0 0"/><axis xyz="0 0 1"/>
  <mimic joint="drive" multiplier="2" offset="0.1"/></joint>
<joint name="follow2" type="prismatic"><parent link="c"/><child link="d"/><origin xyz="1 0 0"/><axis xyz="1 0 0"/>
  <mimic joint="follow" multiplier="-0.5" offset="0.2"/></joint>
<joint name="spin" type="continuous"><parent link="a"/><child link="e"/><axis xyz="0 1 0"/>
  <mimic joint="follow2" multiplier="3"/></joint>
</robot>"""


def test_a_mimic_of_a_mimic_follows_through_the_chain(tmp_path):
    """follow2 mimics follow, which mimics drive: follow2 is -0.5 (2 drive + 0.1) + 0.2 (the URDF reading, and
    ROS joint_state_publisher's); yourdfpy takes a mimicked joint that is no actuated one at 0 (+ offset)."""
    robot = load(tmp_path, MIMIC_CHAIN)
    for drive in (0.0, 0.3, -0.7):
        check_poses(robot, MIMIC_CHAIN, np.array([drive]))


def test_a_mimic_cycle_is_refused(tmp_path):
    urdf = MIMIC_CHAIN.replace('mimic joint="drive"', 'mimic joint="follow2"')
    with pytest.raises(ValueError, match="mimic"):
        load(tmp_path, urdf)


def test_a_pickled_robots_handles_read_a_fresh_robots_answer(tmp_path):
    urdf = random_urdf(3)
    robot = load(tmp_path, urdf)
    handles = pickle.loads(pickle.dumps(robot.handles))
    v = np.linspace(-0.4, 0.4, len(robot.names))
    result = LocalClient().evaluate(load(tmp_path, urdf, "again.urdf").request(v))
    for name, h in handles.items():
        assert result.joint(h).coordinate == result.joint(robot.handles[name]).coordinate


def test_a_mimic_of_no_joint_is_refused(tmp_path):
    """yourdfpy reads it and its FK takes 0 + offset (a warning in its log): a file's slip, named at load."""
    urdf = MIMIC_CHAIN.replace('mimic joint="follow2"', 'mimic joint="nobody"')
    with pytest.raises(ValueError, match="joint spin mimics nobody, no joint of the file"):
        load(tmp_path, urdf)


@pytest.mark.parametrize("seed", SEEDS)
def test_our_fk_is_yourdfpys_where_it_reads_right(tmp_path, seed):
    """Nothing else moved when the FK left yourdfpy's scene graph: at positions away from 0 (trimesh's 1e-8
    cases) every pose is yourdfpy's to 1e-15 of the tree's reach (measured: 2.5e-16 over these 40 trees), given
    the same unit axes (yourdfpy slides along the file's axis as written; a URDF's axis is a direction). Left out:
    a tree with a floating or planar joint and a mimic joint, where yourdfpy's mimic reads its configuration by
    joint index in a vector of degrees of freedom (a floating joint is 6), so reads another joint's value."""
    import logging

    import yourdfpy

    urdf = random_urdf(seed)
    robot = load(tmp_path, urdf)
    (tmp_path / "r.urdf").write_text(urdf)
    logging.getLogger("yourdfpy").setLevel(logging.ERROR)  # "mimics a joint not actuated: 0 + offset"
    theirs = yourdfpy.URDF.load(str(tmp_path / "r.urdf"), load_meshes=False, build_collision_scene_graph=False)
    kinds = {jt.type for jt in theirs.robot.joints}
    if kinds & {"floating", "planar"} and any(jt.mimic is not None for jt in theirs.robot.joints):
        pytest.skip("yourdfpy's mimic reads another joint's value after a floating or planar joint")
    for jt in theirs.robot.joints:
        jt.axis = jt.axis / np.linalg.norm(jt.axis)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        v = rng.uniform(0.01, 3, len(robot.names)) * rng.choice([1, -1], len(robot.names))
        theirs.update_cfg(dict(zip(robot.names, v)))
        want = np.array([[*T[:3, 3], *T[:3, :3].ravel()]
                         for T in (theirs.get_transform(f, theirs.base_link) for f in robot.frames)])
        if any(jt.mimic is not None and theirs._joint_map[jt.mimic.joint].mimic is not None
               for jt in theirs.robot.joints):
            continue  # yourdfpy takes a mimic of a mimic at 0 + offset
        np.testing.assert_allclose(robot.poses(v), want, rtol=0, atol=1e-15 * max(1.0, float(np.abs(want).max())))


@pytest.mark.parametrize("seed", SEEDS[:10])
def test_a_robot_leaves_the_callers_urdf_as_it_was(tmp_path, seed):
    """`Robot(urdf)` normalised each moving joint's axis in the caller's yourdfpy object: the caller's own FK then
    slid along another vector, and a second `Robot` of that object renormalised a unit axis, an ulp off a fresh
    load's (poses of 14 of these 40 trees differed bitwise)."""
    import yourdfpy

    urdf = random_urdf(seed)
    (tmp_path / "r.urdf").write_text(urdf)
    theirs = yourdfpy.URDF.load(str(tmp_path / "r.urdf"), load_meshes=False, build_collision_scene_graph=False)
    axes = [jt.axis.tobytes() for jt in theirs.robot.joints]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        first, second = Robot(theirs), Robot(theirs)
    assert [jt.axis.tobytes() for jt in theirs.robot.joints] == axes
    v = np.linspace(-2, 2, len(first.names))
    fresh = load(tmp_path, urdf, "fresh.urdf").poses(v).tobytes()
    assert first.poses(v).tobytes() == fresh and second.poses(v).tobytes() == fresh
