"""Issue 29: a robot from its URDF (`jointlimits.client.robot`), posed by a joint vector.

On tests/robots/arm7.urdf (written here: 7 revolute joints, one range across pi, a continuous wheel, two
fixed joints, a prismatic gripper whose second finger mimics the first): at poses inside, at and past the
limits, past +-pi and several turns out, each joint's coordinate (and, from the zero reference, x) is its
position in q to 1e-12, and the energies and gradients are the 50-digit reference's (bench/reference.py)
for the same request: stateless in process, over HTTP (JSON and msgpack), in a session in process and over
a live server's WebSocket. The same revolute robot read by pyuipc's UrdfIO gives the same answers.
"""

from __future__ import annotations

import functools
import math
import re
import warnings
from pathlib import Path

import numpy as np
import orjson
import pytest

pytest.importorskip("yourdfpy")  # the `test` extra installs it (and the `robot` extra)

from bench.reference import reference_request  # noqa: E402
from jointlimits.client import Client, LocalClient, codec  # noqa: E402
from jointlimits.client.robot import Robot  # noqa: E402
from tests.conftest import relerr  # noqa: E402
from tests.http.test_contract_live import serve  # noqa: E402

ARM = Path(__file__).parents[1] / "robots" / "arm7.urdf"
REVOLUTE = [f"joint{k}" for k in range(1, 8)]
LIMITS = {"joint1": (-2.8973, 2.8973), "joint2": (-1.7628, 1.7628), "joint3": (-2.8973, 2.8973),
          "joint4": (-3.0718, -0.0698), "joint5": (-2.8973, 2.8973), "joint6": (-0.0175, 3.7525),
          "joint7": (-2.8973, 2.8973), "finger_left": (0.0, 0.04)}  # as the file says
TAU = 2 * math.pi
POSES = {
    "zero": {},
    "inside": {"joint1": 0.4, "joint2": -0.7, "joint3": 1.1, "joint4": -1.5, "joint5": 0.3, "joint6": 1.9,
               "joint7": -0.6, "finger_left": 0.02, "wheel": 0.8},
    "at_lower": {n: lo for n, (lo, _) in LIMITS.items()},
    "at_upper": {n: up for n, (_, up) in LIMITS.items()},
    "past": {"joint1": 3.0, "joint2": -1.9, "joint3": -3.0, "joint4": 0.2, "joint5": 2.95, "joint6": -0.4,
             "joint7": 3.1, "finger_left": 0.046},
    # the Panda readings: past -pi, below the lower limit, where a wrapped angle reads +2.47 / +2.59;
    # joint6 inside its range past +pi
    "past_pi": {"joint1": -3.81, "joint3": 3.5, "joint4": -3.70, "joint6": 3.6, "joint7": -3.3, "wheel": -4.0},
    "turns": {"joint1": 2 * TAU + 0.3, "joint3": -3 * TAU - 1.0, "joint6": TAU + 3.0, "joint7": -2 * TAU,
              "wheel": 5 * TAU + 1.0, "finger_left": -0.01},
}
FLOOR = 1e-16  # see check()
GRADIENT_FLOOR = 1e-13  # see check()
STEP = {n: -0.4 for n in REVOLUTE} | {"finger_left": 0.003, "wheel": 0.5}  # q_prev = q + STEP, under pi


@pytest.fixture(scope="module")
def arm() -> Robot:
    with pytest.warns(UserWarning, match="finger_right: mimics finger_left"):
        return Robot.load(ARM)


@pytest.fixture(scope="module")
def live():
    with serve() as url:
        yield url


def vec(robot: Robot, pose: dict[str, float]) -> np.ndarray:
    return np.array([pose.get(n, 0.0) for n in robot.names])


@functools.cache
def _reference(body: bytes) -> list[dict]:
    return reference_request(orjson.loads(body), hessians=False)


def reference(request) -> list[dict]:
    """The 50-digit reference's x, energy and gradient of `request` (what these tests compare: no Hessian), once per
    request in the module: the in-process, HTTP and session tests ask it of the same requests (~1 s each)."""
    return _reference(codec.encode(request, binary=False)[0])


def check(robot: Robot, request, result, q: np.ndarray) -> None:
    """x and coordinate equal q (zero reference); energies and gradients the 50-digit reference's."""
    want = reference(request)
    for name, handle in robot.handles.items():
        k = robot.names.index(name)
        got = result.joint(handle)
        ref = want[handle.batch]
        # x is the sum of the committed position and one wrapped increment between two FK poses (0 when
        # q_prev = q): its error is a few roundings of O(1) rotation entries, 1e-15 measured; 1e-12 leaves
        # room for any libm and for positions of several turns (|q| ~ 20, ulp 3.6e-15).
        assert abs(got.x - q[k]) <= 1e-12 and abs(got.coordinate - q[k]) <= 1e-12, (name, got.x, q[k])
        assert abs(ref["x"][handle] - q[k]) <= 1e-12, name  # the request itself says q (50 digits)
    for b, (got, ref) in enumerate(zip(result.batches, want)):
        # Same float64 inputs both sides, so only the service's arithmetic differs: the energy is a cubic
        # in x (relative error ~3 eps |E'/E| |x|, at most ~1e-14 here) and the gradient chains E'(x) through
        # the 24 DOFs (the v1.2 cases hold these to 1e-13). Normwise over the batch. The floor: a joint placed
        # at its limit lands within x's rounding (delta ~ 1e-15) of it, on either side, with E ~ delta^3 and
        # E' ~ delta^2 ~ 1e-30 (strength 1, ranges O(1)); 1e-13 x FLOOR = 1e-29 lets an exact 0 stand for those.
        assert relerr(got.energy, ref["energy"], FLOOR) <= 1e-13, b
        # The gradient's floor is wider: E' = 3 s delta^2 moves by 6 s delta dx when x's last bits do, and another
        # CPU's arctan2/sin/cos may move x by ulps (dx ~ 1e-16; delta up to ~1e-14 at a limit, times DOF factors
        # ~ 10): a few 1e-28, 2.4% of a 3.4e-27 gradient under `--perturb-ulps 1` (tests/perturb.py). 1e-13 x
        # GRADIENT_FLOOR = 1e-26 absolute; a joint past its limit has E' ~ 0.01-1 and keeps the relative 1e-13.
        assert relerr(got.gradient, ref["gradient"], GRADIENT_FLOOR) <= 1e-13, b


def active(robot: Robot, result) -> int:
    return sum(r.active for r in robot.readings(result, np.zeros(len(robot.names))) if r.lower is not None)


# ------------------------------------------------------------------------------------------ reading


def test_links_bodies_joints_and_what_is_not_modelled(arm):
    # world + base (fixed), link7 + hand (fixed) are one body each; the mimic finger is a body of its own
    assert arm.frames == ["world", "wheel", *(f"link{k}" for k in range(1, 8)), "finger_left", "finger_right"]
    assert arm.links["base"] == "world" and arm.links["hand"] == "link7"
    assert arm.names == ["wheel", *REVOLUTE, "finger_left"]
    types = {j.name: (j.type, j.lower, j.upper) for j in arm.joints}
    assert types["wheel"] == ("continuous", None, None)  # no limit
    assert {n: types[n][1:] for n in LIMITS} == LIMITS
    assert types["finger_left"][0] == "prismatic" and "finger_right" not in types
    assert [(h.constitution_uid, h.batch) for h in arm.handles.values()] == [(670, 0)] * 7 + [(669, 1)]
    assert arm.unmodelled == ["prismatic joint finger_right: mimics finger_left (1 x finger_left + 0), posed by FK, no limit"]
    # a joint's edge: its origin and a unit step along its axis, in the parent body's frame and the child's
    j1 = next(j for j in arm.joints if j.name == "joint1")
    assert j1.body_ids == (0, 2)
    np.testing.assert_allclose(j1.local_edge[0], [[0.1, -0.2, 0.383], [0.1, -0.2, 1.383]], atol=1e-15)
    np.testing.assert_array_equal(j1.local_edge[1], [[0, 0, 0], [0, 0, 1]])


def test_the_mimic_finger_follows_by_fk(arm):
    P = arm.poses(vec(arm, {"finger_left": 0.03}))
    hand = arm.poses(vec(arm, {}))
    left, right = P[9, :3] - hand[9, :3], P[10, :3] - hand[10, :3]
    np.testing.assert_allclose(np.linalg.norm(left), 0.03, atol=1e-15)
    np.testing.assert_allclose(left, -right, atol=1e-15)  # the second finger moves the other way, as much


def test_floating_planar_and_unjoined_links_are_reported(tmp_path):
    urdf = tmp_path / "odd.urdf"
    urdf.write_text("""<robot name="odd"><link name="a"/><link name="b"/><link name="c"/><link name="d"/>
      <joint name="free" type="floating"><parent link="a"/><child link="b"/></joint>
      <joint name="slide2d" type="planar"><parent link="a"/><child link="c"/><axis xyz="0 0 1"/></joint></robot>""")
    with pytest.warns(UserWarning) as w:
        robot = Robot.load(urdf)
    assert robot.unmodelled == [
        "link d: not joined to a, fixed to it",
        "floating joint free: not modelled, its child stays at the joint's origin",
        "planar joint slide2d: not modelled, its child stays at the joint's origin",
    ]
    said = [str(x.message) for x in w if x.category is UserWarning]  # not an earlier test's ResourceWarning
    assert "floating joint free" in said[0] and robot.names == [] and robot.handles == {}


def test_a_moving_joint_not_joined_to_the_root_is_named_and_so_is_a_loop(tmp_path):
    """A moving joint in a second tree (c -> d) failed at load with "'d' is not in list" (yourdfpy's FK has no
    path from the root to d); a loop (a -> b -> a) the same way. Both are said, naming the joint or link."""
    urdf = tmp_path / "two.urdf"
    urdf.write_text("""<robot name="two"><link name="a"/><link name="b"/><link name="c"/><link name="d"/>
      <joint name="j" type="revolute"><parent link="a"/><child link="b"/><limit lower="-1" upper="1"/></joint>
      <joint name="k" type="revolute"><parent link="c"/><child link="d"/><limit lower="-1" upper="1"/></joint>
      </robot>""")
    with pytest.raises(ValueError, match="two: joint k moves link d, not joined to a"):
        Robot.load(urdf)
    urdf.write_text(urdf.read_text().replace('<link name="c"/><link name="d"/>', "").replace(
        '<parent link="c"/><child link="d"/>', '<parent link="b"/><child link="a"/>'))
    with pytest.raises(ValueError, match=r"two: no root link \(each link is some joint's child: a loop\)"):
        Robot.load(urdf)


def test_a_bad_limit_in_the_file_is_named_at_load(tmp_path):
    urdf = tmp_path / "bad.urdf"
    urdf.write_text("""<robot name="bad"><link name="a"/><link name="b"/><joint name="elbow" type="revolute">
      <parent link="a"/><child link="b"/><axis xyz="0 0 1"/><limit lower="1" upper="-1" effort="1" velocity="1"/>
      </joint></robot>""")
    with pytest.raises(ValueError, match="joint elbow: .*lower"):
        Robot.load(urdf)


@pytest.mark.filterwarnings("ignore:invalid value encountered in divide")  # yourdfpy's scene graph, built at load
def test_a_joint_without_a_direction_is_named(tmp_path):
    urdf = tmp_path / "flat.urdf"
    urdf.write_text("""<robot name="flat"><link name="a"/><link name="b"/><joint name="wrist" type="continuous">
      <parent link="a"/><child link="b"/><axis xyz="0 0 0"/></joint></robot>""")
    with pytest.raises(ValueError, match=r"joint wrist: its axis \[0.0, 0.0, 0.0\] has no direction"):
        Robot.load(urdf)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # yourdfpy's scene graph (trimesh), built at load
@pytest.mark.parametrize("origin", ['xyz="nan 0 0"', 'xyz="1e400 0 0"', 'rpy="0 inf 0"'])
def test_a_joint_whose_origin_is_not_finite_is_named(tmp_path, origin):
    """Before, the fault named the limited joint below it, by its local edge (`joint k: ... local_edge.0.0.0`),
    or, with no limit below, a 422 on `bodies.q` at the first call."""
    urdf = tmp_path / "far.urdf"
    urdf.write_text(f"""<robot name="far"><link name="a"/><link name="b"/><link name="c"/>
      <joint name="j" type="fixed"><parent link="a"/><child link="b"/><origin {origin}/></joint>
      <joint name="k" type="revolute"><parent link="b"/><child link="c"/><limit lower="-1" upper="1"/></joint></robot>""")
    with pytest.raises(ValueError, match=r"^joint j: its <origin> is not finite"):
        Robot.load(urdf)


def test_a_yourdfpy_object_built_without_its_scene_graph_is_read(arm):
    """Before: `Robot(URDF.load(path, build_scene_graph=False))` said "no root link (... a loop)", which was false:
    yourdfpy leaves `base_link` None without a scene graph, and the robot needs none (its FK is ours)."""
    import yourdfpy

    with pytest.warns(UserWarning, match="finger_right: mimics finger_left"):
        bare = Robot(yourdfpy.URDF.load(str(ARM), build_scene_graph=False, load_meshes=False))
    q = np.linspace(-2.0, 2.0, len(arm.names))
    assert bare.names == arm.names and bare.links == arm.links and bare.frames == arm.frames
    assert codec.encode(bare.request(q), binary=True)[0] == codec.encode(arm.request(q), binary=True)[0]


def test_two_joints_of_one_name_are_refused(tmp_path):
    """yourdfpy reads them (urdfdom refuses: names must be unique); `q` by name or position then moved both by
    the first one's position, so the second's energy was that of the wrong angle (0 at 3 rad past [-1, 1])."""
    urdf = tmp_path / "twice.urdf"
    urdf.write_text("""<robot name="twice"><link name="a"/><link name="b"/><link name="c"/>
      <joint name="j" type="revolute"><parent link="a"/><child link="b"/><limit lower="-1" upper="1"/></joint>
      <joint name="j" type="revolute"><parent link="b"/><child link="c"/><limit lower="-1" upper="1"/></joint>
      </robot>""")
    with pytest.raises(ValueError, match=r"twice: joint names must be unique: \['j'\] is more than one joint's"):
        Robot.load(urdf)


def test_a_file_yourdfpy_cannot_read_is_named(tmp_path):
    urdf = tmp_path / "xacro.urdf"  # a xacro leftover, as some published robots ship
    urdf.write_text("""<robot name="x"><link name="a"/><link name="b"/><joint name="j" type="revolute">
      <parent link="a"/><child link="b"/><origin xyz="$(optenv X 0) 0 0"/><limit lower="-1" upper="1"/></joint></robot>""")
    with pytest.raises(ValueError, match=r"xacro.urdf: not a URDF yourdfpy reads \(ValueError: could not convert"):
        Robot.load(urdf)


def test_a_urdf_with_an_undeclared_namespace_prefix_loads_as_yourdfpy_reads_it(tmp_path):
    """xacro leftovers (<xacro:property>) and old Gazebo tags (<sensor:camera>) whose prefix no xmlns declares: ROS's
    parser reads such a file, and so does yourdfpy (it drops the prefixed elements). Since 0197cbf, lxml's strict
    pre-parse refused it as "not XML (Namespace prefix xacro on property is not defined)"; at cac2726 it loaded.
    The same request bytes as arm7's."""
    urdf = tmp_path / "leftovers.urdf"
    urdf.write_text(ARM.read_text().replace('<link name="world"/>', '<link name="world"/><xacro:property name="pi" '
                                            'value="3.14"/><gazebo><sensor:camera name="c"/></gazebo>'))
    q = {"joint1": -3.81, "joint4": -1.0, "finger_left": 0.02}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # arm7's mimic joint
        got, want = Robot.load(urdf).request(q), Robot.load(ARM).request(q)
    assert codec.encode(got, True)[0] == codec.encode(want, True)[0]


@pytest.mark.parametrize("content, said", [
    ("hello", r"not XML \(Start tag expected, '<' not found, line 1, column 1\)$"),
    ('{"robot": 1}', r"not XML \(Start tag expected"),
    ("", r"not XML \(Document is empty"),
    ('<robot name="r"><link name="a"/>', r"not XML \(Premature end of data in tag robot"),
    ('<?xml version="1.0"?><sdf version="1.9"><model name="m"/></sdf>', r"not a URDF: its root element is <sdf>"),
    ('<robot><link name="a"/></robot>', r"its <robot> has no name \(URDF requires one\)$"),
    ('<robot name="r"><link name="a"/><joint name="j" type="fixed"><parent link="a"/><child link="c"/></joint></robot>',
     r"joint j: its <child link='c'> names no <link> of the file$"),  # was yourdfpy's "list.remove(x): x not in list"
    ('<robot name="r"><link name="a"/><joint name="j" type="fixed"><child link="a"/></joint></robot>',
     r"joint j: its <parent link=''> names no <link> of the file$"),  # was "AttributeError: 'NoneType' object ..."
])
def test_a_file_that_is_not_a_urdf_says_what_is_wrong_in_one_line(tmp_path, capfd, content, said):
    """Before: yourdfpy logged lxml's error and "Using different parsing approach." to stderr, then the message
    carried its "Invalid input object: NoneType" or "KeyError: 'name'"; a file cut short loaded what lxml
    recovered of it, silently (a robot missing its end)."""
    urdf = tmp_path / "odd.urdf"
    urdf.write_text(content)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(urdf))}: {said}"):
        Robot.load(urdf)
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("kind", ['type="hinge"', 'type="Revolute"', ""])
def test_a_joint_of_no_urdf_type_is_named_and_a_robot_of_no_link_is_no_loop(tmp_path, kind):
    """yourdfpy reads any joint type (or none): such a joint, a typo of "revolute", was posed as fixed and carried
    no limit, silently (`names == []`). And a <robot> with no <link> was said to close a loop."""
    urdf = tmp_path / "typo.urdf"
    urdf.write_text(f"""<robot name="typo"><link name="a"/><link name="b"/><joint name="elbow" {kind}>
      <parent link="a"/><child link="b"/><limit lower="-1" upper="1"/></joint></robot>""")
    with pytest.raises(ValueError, match=r"^joint elbow: its type .* is none of URDF's \(revolute, continuous, pr"):
        Robot.load(urdf)
    urdf.write_text('<robot name="bare"/>')
    with pytest.raises(ValueError, match=r"^bare: no root link \(no <link> at all\)$"):
        Robot.load(urdf)


def test_a_joint_vector_of_the_wrong_size_or_names_is_refused(arm):
    with pytest.raises(ValueError, match=r"q: 9 positions, one per joint of \['wheel'"):
        arm.request([0.0, 1.0])
    with pytest.raises(ValueError, match=r"no moving joint named \['finger_right'\]"):
        arm.request({"finger_right": 0.01})
    with pytest.raises(ValueError, match=r"q_prev: not finite at \['joint2'\]"):
        arm.request({}, q_prev=vec(arm, {"joint2": math.nan}))


@pytest.mark.parametrize("value, kind", [(True, "a boolean"), (np.True_, "a boolean"), ("0.5", "a string"),
                                         (None, "None"), (np.complex128(0.5 + 2j), "a complex number"),
                                         (np.complex64(0.5 + 2j), "a complex number")])
@pytest.mark.parametrize("given", ["q", "q_prev", "reference"])
def test_a_position_that_is_not_a_number_is_refused_in_every_vector(arm, given, value, kind):
    """The wire and `Scene` refuse a boolean, a string, null and a complex number as a number. Before, NumPy read
    "0.5" as 0.5 rad in any vector, None as nan ("not finite"), and a NumPy complex 0.5+2j as 0.5 (a ComplexWarning,
    until the audit of 08c7530); a boolean was refused (f04a107). Each names its vector and joint."""
    vectors = {"q": {"joint1": 0.1}, given: {"joint1": value}}
    with pytest.raises(ValueError, match=rf"^{given}: a position is a number, not {kind} \(joint1: "):
        arm.request(**vectors)
    with pytest.raises(ValueError, match=rf"^{given}: a position is a number, not {kind} \(wheel: "):
        arm.request(**{**vectors, given: [value] + [0.0] * 8})
    with pytest.raises(ValueError, match=r"^joint joint1: .*strength: Input should be a (valid|finite) number"):
        arm.request({"joint1": 0.1}, strength={"joint1": value})  # held before: `Scene`'s fault, the joint named


def test_a_strength_for_no_limited_joint_is_refused(arm):
    """A misspelt name (or one without a limit) in a strength mapping was dropped: that joint silently kept
    strength 1 (energy 0.0034 instead of 0.34 for joint1 at 3.1 below)."""
    with pytest.raises(ValueError, match=r"strength: no limited joint named \['jont1', 'wheel'\] \(the limited"):
        arm.request({"joint1": 3.1}, strength={"jont1": 100.0, "wheel": 2.0, "joint2": 3.0})
    r = LocalClient().evaluate(arm.request({"joint1": 3.1}, strength={"joint1": 100.0})).joint(arm.handles["joint1"])
    assert r.energy == pytest.approx(100.0 * ((3.1 - 2.8973) / (2 * 2.8973)) ** 3, rel=1e-12)


def test_a_previous_pose_pi_or_more_away_is_refused(arm):
    """x = q_prev's position + the turn from q_prev to q wrapped into (-pi, pi]: with joint1 at 1.0 and
    q_prev at 5.0 it read 7.28 (past the upper limit, penalised) instead of 1.0. Refused, naming the joint."""
    with pytest.raises(ValueError, match=r"joint1: q is 4 rad from q_prev.*less than pi"):
        arm.request({"joint1": 1.0}, q_prev={"joint1": 5.0})
    with pytest.raises(ValueError, match=r"joint7: q is 3.14"):
        arm.request({"joint7": -math.pi}, q_prev={})
    ok = arm.request({"joint1": 1.0, "finger_left": 9.0, "wheel": 40.0}, q_prev={"joint1": 1.0 + 0.99 * math.pi})
    assert abs(LocalClient().evaluate(ok).joint(arm.handles["joint1"]).coordinate - 1.0) <= 1e-12


# ---------------------------------------------------------------------- x equals q, every path


@pytest.mark.parametrize("with_prev", [False, True], ids=["q_prev=q", "q_prev=q+step"])
@pytest.mark.parametrize("pose", list(POSES), ids=list(POSES))
def test_x_is_q_and_the_answers_are_the_references_in_process(arm, pose, with_prev):
    q = vec(arm, POSES[pose])
    req = arm.request(q, q + vec(arm, STEP) if with_prev else None)
    result = LocalClient().evaluate(req)
    check(arm, req, result, q)
    readings = arm.readings(result, q)
    assert [r.position for r in readings if r.lower is None] == [q[0]]  # the wheel: its position, no limit
    if pose in ("past", "past_pi", "turns"):
        assert active(arm, result) >= 4


def test_past_pi_is_penalised_from_the_right_side(arm):
    """The issue's trap: joint1 at -3.81 (lower -2.90) wrapped would read +2.47 and no penalty; joint4 at
    -3.70 (lower -3.07) would read +2.59 and be pushed from its upper side."""
    q = vec(arm, POSES["past_pi"])
    result = LocalClient().evaluate(arm.request(q))
    by_name = {r.name: r for r in arm.readings(result, q)}
    assert by_name["joint1"].active and by_name["joint4"].active and not by_name["joint6"].active
    for name in ("joint1", "joint4"):
        g = result.joint(arm.handles[name]).gradient
        assert np.linalg.norm(g) > 0
    # E'(x) < 0 below the lower limit: pushing the joint up (the reference agrees in sign and size above)
    b = result.batches[0]
    assert all(b.x[arm.handles[n]] < LIMITS[n][0] for n in ("joint1", "joint4"))


def test_a_reference_configuration_moves_x_not_the_coordinate(arm):
    q = vec(arm, POSES["turns"])
    ref = vec(arm, POSES["inside"])
    req = arm.request(q, reference=ref)
    result = LocalClient().evaluate(req)
    want = reference(req)
    for name, h in arm.handles.items():
        k = arm.names.index(name)
        assert abs(result.joint(h).coordinate - q[k]) <= 1e-12 and abs(result.joint(h).x - (q[k] - ref[k])) <= 1e-12
    for got, r in zip(result.batches, want):
        assert relerr(got.energy, r["energy"], FLOOR) <= 1e-13 and relerr(got.gradient, r["gradient"], FLOOR) <= 1e-13


@pytest.mark.parametrize("binary", [True, False], ids=["msgpack", "json"])
def test_x_is_q_over_http(arm, live, binary):
    client = Client(live, binary=binary)
    for pose in ("past", "past_pi", "turns"):
        q = vec(arm, POSES[pose])
        req = arm.request(q, q + vec(arm, STEP))
        check(arm, req, client.evaluate(req), q)


def path(robot: Robot) -> list[np.ndarray]:
    """joint7 driven three turns down in 0.45 rad steps, joint1 two turns up, the finger out past its limit."""
    steps = 42
    return [vec(robot, {"joint7": -0.45 * k, "joint1": 0.3 * k, "joint6": 0.1 * k, "finger_left": 0.0015 * k})
            for k in range(steps + 1)]


def drive(robot: Robot, session) -> int:
    """Each step: evaluate at q (x = q), every 6th also against the reference of the stateless request
    with the last commit as q_prev (the 50-digit reference costs ~0.4 s a step); then commit. Returns how
    many steps had active joints."""
    qs = path(robot)
    busy = 0
    for step, (prev, q) in enumerate(zip(qs, qs[1:]), 1):
        result = session.evaluate(robot.poses(q))
        if step % 6 == 0:
            check(robot, robot.request(q, prev), result, q)
        for name, h in robot.handles.items():
            assert abs(result.joint(h).x - q[robot.names.index(name)]) <= 1e-12, (step, name)
        committed = session.commit(robot.poses(q))
        np.testing.assert_allclose(committed[0], [q[robot.names.index(n)] for n in REVOLUTE], rtol=0, atol=1e-12)
        busy += active(robot, result) > 0
    assert abs(qs[-1][robot.names.index("joint7")]) > 3 * TAU - 1  # three turns down
    return busy


def test_x_is_q_over_several_turns_in_a_local_session(arm):
    with LocalClient().session(arm.request(path(arm)[0])) as s:
        assert drive(arm, s) > 20


def test_x_is_q_over_several_turns_in_a_live_session(arm, live):
    with Client(live).session(arm.request(path(arm)[0])) as s:
        assert drive(arm, s) > 20


# ---------------------------------------------------------------------- pyuipc's UrdfIO, the same robot


def revolute_variant(tmp_path: Path) -> Path:
    """arm7's revolute joints alone (UrdfIO refuses prismatic joints), base as the root, a closed cube mesh
    on every link (UrdfIO needs one): written by yourdfpy from the file it read."""
    import yourdfpy

    from tests.sdk.test_uipc_engine_path import CUBE

    (tmp_path / "cube.obj").write_text(CUBE)
    src = yourdfpy.URDF.load(str(ARM), build_scene_graph=False, load_meshes=False)
    joints = [j for j in src.robot.joints if j.type == "revolute"]
    mesh = yourdfpy.Geometry(mesh=yourdfpy.Mesh(filename="cube.obj"))
    links = [yourdfpy.Link(name=n, visuals=[yourdfpy.Visual(geometry=mesh)],
                           collisions=[yourdfpy.Collision(name=None, geometry=mesh)])
             for n in ["base", *(f"link{k}" for k in range(1, 8))]]
    out = tmp_path / "arm7_revolute.urdf"
    robot = yourdfpy.Robot(name="arm7_revolute", links=links, joints=joints)
    yourdfpy.URDF(robot, build_scene_graph=False, load_meshes=False).write_xml_file(str(out))
    return out


def urdfio_arm(urdf: Path):
    """The robot the engine's way (as tests/sdk/test_uipc_engine_path.py builds it): `UrdfIO.read`, a body per
    link, a #18 joint through each child link's origin along its axis at UrdfIO's zero pose, #670 limits
    from the file (strength 10), the snapshot `world.init()` would take there. Returns (scene, controller,
    joint slot, snapshot, W): UrdfIO turns the robot up (libuipc's y is up), its root link sits at W."""
    from uipc import Scene
    from uipc.constitution import AffineBodyConstitution, AffineBodyRevoluteJoint, AffineBodyRevoluteJointLimit
    from uipc.geometry import UrdfIO

    import jointlimits.client.uipc as cu

    scene = Scene(Scene.default_config())
    obj = scene.objects().create("arm")
    ctrl = UrdfIO({"load_visual_mesh": False}).read(obj, str(urdf))
    links = {s.id(): s for s in ctrl.links()}
    for s in links.values():
        AffineBodyConstitution().apply_to(s.geometry(), 1e8)
    rj = ctrl.revolute_joints().geometry()
    assert list(rj.instances().find("name").view()) == REVOLUTE
    ids = np.asarray(rj.instances().find("link_ids").view()).reshape(-1, 2)
    axes = np.asarray(rj.instances().find("local_axis").view()).reshape(-1, 3)
    T = {g: np.asarray(s.geometry().transforms().view())[0] for g, s in links.items()}
    P0 = np.array([T[c][:3, 3] for _, c in ids])
    P1 = P0 + np.array([T[c][:3, :3] @ a for (_, c), a in zip(ids, axes)])
    zeros = np.zeros(len(ids), np.int32)
    hinge = AffineBodyRevoluteJoint().create_geometry(P0, P1, [links[int(p)] for p, _ in ids], zeros,
                                                      [links[int(c)] for _, c in ids], zeros, np.full(len(ids), 100.0))
    AffineBodyRevoluteJointLimit().apply_to(hinge, *(np.array([LIMITS[n][k] for n in REVOLUTE]) for k in (0, 1)),
                                            np.full(len(ids), 10.0))
    js, _ = obj.geometries().create(hinge)
    return scene, ctrl, js, cu.reference(scene), T[int(ids[0][0])][:3, :3]


@pytest.mark.parametrize("pose", ["inside", "past", "at_upper", "past_pi"])
def test_urdfio_and_our_reader_give_the_same_answers(tmp_path, pose):
    pytest.importorskip("uipc")
    from uipc import builtin, view

    from jointlimits.client.uipc import request_from_scene
    from tests.sdk.test_uipc import publish

    urdf = revolute_variant(tmp_path)
    ours = Robot.load(urdf)
    assert ours.names == REVOLUTE and ours.unmodelled == []
    scene, ctrl, js, snap, W = urdfio_arm(urdf)

    def turned(g: np.ndarray) -> np.ndarray:  # UrdfIO's DOFs are p' = W p, A' = W A: dE/dp' = W dE/dp, dE/dA' = W dE/dA
        g = g.reshape(2, 4, 3)  # per body: p, then A's three rows
        return np.concatenate([(W @ g[:, 0].T).T[:, None], W @ g[:, 1:]], axis=1).reshape(24)

    angles = {n: POSES[pose].get(n, 0.0) for n in REVOLUTE}
    for name, a in angles.items():
        ctrl.rotate_to(name, a)
    ctrl.apply_to(builtin.transform)
    q = np.array(list(angles.values()))
    theirs = LocalClient().evaluate(request_from_scene(scene, reference=snap)[0]).batches[0]
    if np.any(np.abs(q) > np.pi):  # read as it stands, each angle is wrapped: 2 pi off past pi
        np.testing.assert_allclose(np.abs(theirs.x - q)[np.abs(q) > np.pi], 2 * np.pi, rtol=1e-13)
        publish(scene, ctrl.links())  # the engine, having stepped there, publishes the unwrapped angle
        view(js.geometry().edges().find("angle"))[:] = q
        theirs = LocalClient().evaluate(request_from_scene(scene, reference=snap)[0]).batches[0]
    mine = LocalClient().evaluate(ours.request(q, strength=10.0))
    for k, name in enumerate(REVOLUTE):
        a, b = theirs.joint(k), mine.joint(ours.handles[name])
        # two FKs (UrdfIO's, yourdfpy's) and two edge forms: a few roundings of O(1) numbers apart
        assert abs(a.x - b.x) <= 1e-12 and abs(a.energy - b.energy) <= 1e-12 * max(1.0, abs(b.energy)), name
        assert np.max(np.abs(a.gradient - turned(b.gradient))) <= 1e-12 * max(1e-3, np.max(np.abs(b.gradient))), name
    assert (pose in ("past", "past_pi")) == bool(np.any(theirs.energy > 0))  # inside and at the limits: none


def test_no_warning_for_a_plain_arm(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Robot.load(revolute_variant(tmp_path))
