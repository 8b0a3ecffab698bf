"""Issue 29: the engine's own robot path gives the engine's numbers, not silently wrong ones.

1. `q_ref` is what the engine builds its joint frames from: the transforms at `world.init()`
   (`AffineBodyRevoluteJoint::do_init` reads the scene's current transforms then), not the rest
   geometries'. pyuipc's `UrdfIO` creates each link and poses it afterwards, so every rest transform
   is the identity. `reference(scene)`, taken where `world.init()` is called, is passed to every later
   read; without one, a scene whose rest transforms can only be a guess raises `SceneError`.
2. A published `angle` belongs to the current transforms, which the engine's next step takes as
   `q_prev` (the limit reads `current_angles` as the frame-start angle): it is paired with them.

A robot of our own (a URDF written here: three revolute joints with non-identity origins, a closed
cube mesh per link) read by `UrdfIO` and posed by its controller's FK, and hand-built scenes; every
answer against `tests/engine_ref.py` (libuipc's kernels) with the engine's `q_ref` and `q_prev`.
No simulation runs (the CUDA backend needs a GPU).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("uipc")  # the `test` extra installs pyuipc

from uipc import Scene, builtin, view  # noqa: E402
from uipc.constitution import AffineBodyConstitution, AffineBodyRevoluteJoint, AffineBodyRevoluteJointLimit  # noqa: E402
from uipc.geometry import UrdfIO  # noqa: E402

import jointlimits.client.uipc as cu  # noqa: E402
from jointlimits.client import LocalClient  # noqa: E402
from jointlimits.client.uipc import SceneError, request_from_scene  # noqa: E402
from tests import engine_ref as ref  # noqa: E402
from tests.sdk.test_uipc import body, check_scene, publish, q_of, rot, set_transform, transform  # noqa: E402

CUBE = """\
v -0.05 -0.05 -0.05
v 0.05 -0.05 -0.05
v 0.05 0.05 -0.05
v -0.05 0.05 -0.05
v -0.05 -0.05 0.05
v 0.05 -0.05 0.05
v 0.05 0.05 0.05
v -0.05 0.05 0.05
f 1 3 2
f 1 4 3
f 5 6 7
f 5 7 8
f 1 2 6
f 1 6 5
f 2 3 7
f 2 7 6
f 3 4 8
f 3 8 7
f 4 1 5
f 4 5 8
"""
LINK = ('<link name="{0}"><collision><geometry><mesh filename="cube.obj"/></geometry></collision>'
        '<visual><geometry><mesh filename="cube.obj"/></geometry></visual></link>')
JOINT = ('<joint name="{0}" type="revolute"><parent link="{1}"/><child link="{2}"/><origin xyz="{3}" rpy="{4}"/>'
         '<axis xyz="{5}"/><limit lower="{6}" upper="{7}" effort="1" velocity="1"/></joint>')
# (name, parent, child, origin xyz, origin rpy, axis, lower, upper): every origin turned and moved
JOINTS = [
    ("j1", "base", "l1", "0 0 0.2", "0 0 0.3", "0 0 1", -1.0, 1.0),
    ("j2", "l1", "l2", "0.3 0 0", "1.5708 0 0", "0 0 1", -0.5, 0.5),
    ("j3", "l2", "l3", "0 0.25 0.1", "0.2 -0.4 0.1", "1 0 0", -0.3, 0.8),
]
POSE = {"j1": 0.4, "j2": -0.7, "j3": 0.9}  # j2 and j3 past their limits


def robot(tmp_path: Path, local: bool = False):
    """The robot as a libuipc user builds it: `UrdfIO.read`, an affine-body constitution on every link,
    one #18 revolute joint per URDF joint through the child link's origin along its axis (at the pose
    UrdfIO wrote), #670 limits from the URDF. Returns (scene, controller, joint slot)."""
    (tmp_path / "cube.obj").write_text(CUBE)
    urdf = tmp_path / "arm.urdf"
    urdf.write_text('<?xml version="1.0"?><robot name="arm">' + "".join(LINK.format(n) for n in ("base", "l1", "l2", "l3"))
                    + "".join(JOINT.format(*j) for j in JOINTS) + "</robot>")
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("arm")
    ctrl = UrdfIO({"load_visual_mesh": False}).read(obj, str(urdf))
    links = {s.id(): s for s in ctrl.links()}
    for s in links.values():
        AffineBodyConstitution().apply_to(s.geometry(), 1e8)
    rj = ctrl.revolute_joints().geometry()
    names = list(rj.instances().find("name").view())
    ids = np.asarray(rj.instances().find("link_ids").view()).reshape(-1, 2)
    axes = np.asarray(rj.instances().find("local_axis").view()).reshape(-1, 3)
    assert names == [j[0] for j in JOINTS]
    n = len(names)
    T = {g: np.asarray(s.geometry().transforms().view())[0] for g, s in links.items()}
    P0 = np.array([T[c][:3, 3] for _, c in ids])
    P1 = P0 + np.array([T[c][:3, :3] @ a for (_, c), a in zip(ids, axes)])
    L, R = [links[int(p)] for p, _ in ids], [links[int(c)] for _, c in ids]
    zeros = np.zeros(n, np.int32)
    if local:  # the edge in each link's own coordinates
        inv = lambda g, P: (np.linalg.inv(T[g]) @ np.append(P, 1.0))[:3]  # noqa: E731
        l0 = np.array([inv(int(p), a) for (p, _), a in zip(ids, P0)])
        l1 = np.array([inv(int(p), a) for (p, _), a in zip(ids, P1)])
        r0 = np.array([inv(int(c), a) for (_, c), a in zip(ids, P0)])
        r1 = np.array([inv(int(c), a) for (_, c), a in zip(ids, P1)])
        hinge = AffineBodyRevoluteJoint().create_geometry(l0, l1, r0, r1, L, zeros, R, zeros, np.full(n, 100.0))
    else:
        hinge = AffineBodyRevoluteJoint().create_geometry(P0, P1, L, zeros, R, zeros, np.full(n, 100.0))
    AffineBodyRevoluteJointLimit().apply_to(hinge, np.array([j[6] for j in JOINTS]), np.array([j[7] for j in JOINTS]),
                                            np.full(n, 10.0))
    js, _ = obj.geometries().create(hinge)
    return scene, ctrl, js


def pose(ctrl, angles: dict[str, float]) -> None:
    """The robot's own FK: the controller turns the joints and writes the links' transforms."""
    for name, a in angles.items():
        ctrl.rotate_to(name, a)
    ctrl.apply_to(builtin.transform)


def snapshot_q(snap: cu.Reference):
    return lambda g, i: ref.transform_to_q(snap.transforms[int(g)][int(i)])[0]


# ----------------------------------------------------------------------------- q_ref: the robot


@pytest.mark.parametrize("local", [False, True], ids=["world", "local"])
def test_a_urdf_robot_without_a_reference_is_refused_not_answered_wrong(tmp_path, local):
    scene, ctrl, _ = robot(tmp_path, local)
    rest = [np.asarray(scene.geometries().find(s.id())[1].geometry().transforms().view())[0] for s in ctrl.links()]
    assert all(np.array_equal(T, np.eye(4)) for T in rest)  # UrdfIO poses the links after creating them
    with pytest.raises(SceneError, match="UrdfIO link geometries") as e:
        request_from_scene(scene)
    assert "reference(scene)" in str(e.value)
    # what the old default answered: the rest transforms as q_ref give x far from the engine's zeros
    req, _ = request_from_scene(scene, reference="rest")
    assert np.max(np.abs(LocalClient().evaluate(req).batches[0].x)) > 0.1


@pytest.mark.parametrize("local", [False, True], ids=["world", "local"])
def test_a_urdf_robot_posed_by_its_fk_reads_the_fk_angles_with_the_snapshot(tmp_path, local):
    scene, ctrl, js = robot(tmp_path, local)
    snap = cu.reference(scene)  # where world.init() is called: the zero pose UrdfIO wrote
    req, joints = request_from_scene(scene, reference=snap)
    assert joints == [[(js.id(), e) for e in range(3)]]
    np.testing.assert_allclose(LocalClient().evaluate(req).batches[0].x, 0.0, atol=1e-12)
    pose(ctrl, POSE)
    req, _, ev = check_scene(scene, reference=snap, q_ref_of=snapshot_q(snap), min_active=2)
    np.testing.assert_allclose(ev.batches[0].x, list(POSE.values()), atol=1e-12)
    assert ev.batches[0].energy[0] == 0 and np.all(ev.batches[0].energy[1:] > 0)
    # the snapshot and q_ref by hand are the same request, bit for bit
    by_hand, _ = request_from_scene(scene, q_ref=req.q_ref)
    for f in ("q", "q_prev", "q_ref"):
        np.testing.assert_array_equal(getattr(by_hand, f), getattr(req, f))
    # the snapshot is a copy: later poses do not move it
    np.testing.assert_array_equal(request_from_scene(scene, reference=snap)[0].q_ref, req.q_ref)


def test_a_urdf_robot_snapshotted_at_a_pose_measures_from_there(tmp_path):
    """world.init() at a posed robot: the engine's zero is that pose, whatever UrdfIO's zero. (Local
    edges, which move with the links: world edges hold the axes where they were at UrdfIO's zero.)"""
    scene, ctrl, _ = robot(tmp_path, local=True)
    pose(ctrl, {"j1": 0.2, "j2": 0.1, "j3": -0.1})
    snap = cu.reference(scene)
    pose(ctrl, {"j1": 0.5, "j2": -0.7, "j3": 0.4})
    _, _, ev = check_scene(scene, reference=snap, q_ref_of=snapshot_q(snap), min_active=1)
    np.testing.assert_allclose(ev.batches[0].x, [0.3, -0.8, 0.5], atol=1e-12)


def test_a_published_angle_on_the_robot_pairs_with_the_current_transforms(tmp_path):
    """The engine, after steps that brought the robot to POSE, publishes `angle` = the FK angles and
    the offsets; the next read gives x = angle (no step taken), and a trial q adds its increment."""
    scene, ctrl, js = robot(tmp_path)
    snap = cu.reference(scene)
    pose(ctrl, POSE)
    publish(scene, ctrl.links())
    view(js.geometry().edges().find("angle"))[:] = np.array(list(POSE.values()))
    req, _, ev = check_scene(scene, committed=True, reference=snap, q_ref_of=snapshot_q(snap), min_active=2)
    assert req.batches[0].prev_coordinate is not None
    np.testing.assert_array_equal(req.q_prev, req.q)
    np.testing.assert_allclose(ev.batches[0].x, list(POSE.values()), atol=1e-15)
    assert request_from_scene(scene, reference=snap)[0].batches[0].prev_coordinate is not None  # None: published


# ---------------------------------------------------------------------- q_ref: hand-built scenes


def door(turn: float = 0.0):
    """A frame and a door (two instances of one body geometry, both created at the identity) on a +z
    hinge at the origin, limits +-0.5; the door then turned by `turn`."""
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("room")
    bodies = body(obj, [np.eye(4), np.eye(4)])
    hinge = AffineBodyRevoluteJoint().create_geometry(np.array([[0.0, 0, 0]]), np.array([[0.0, 0, 1]]), [bodies],
                                                      np.array([0], np.int32), [bodies], np.array([1], np.int32),
                                                      np.array([100.0]))
    AffineBodyRevoluteJointLimit().apply_to(hinge, -0.5, 0.5, 100.0)
    hs, _ = obj.geometries().create(hinge)
    return scene, bodies, hs


def test_identity_rest_transforms_with_moved_bodies_are_refused_until_a_reference_says():
    scene, bodies, _ = door()
    snap = cu.reference(scene)                 # world.init() here
    set_transform(bodies, 1, transform(rot([0, 0, 1], 0.7), [0, 0, 0]))
    with pytest.raises(SceneError, match="every body's rest transform is the identity"):
        request_from_scene(scene)
    for kw in ({"reference": snap}, {"reference": "rest"}, {"q_ref": np.tile(ref.transform_to_q(np.eye(4)), (2, 1))}):
        req, _ = request_from_scene(scene, **kw)
        np.testing.assert_allclose(LocalClient().evaluate(req).batches[0].x, [0.7], rtol=1e-15)
    request_from_scene(door()[0])              # nothing moved: the rest transforms are the only answer


def test_a_body_created_at_a_pose_and_initialised_elsewhere_measures_from_the_snapshot():
    """Rest transforms not the identity (no guess to refuse): the body moved before world.init(),
    the snapshot holds that pose and the engine's numbers follow it, not the rest geometry's."""
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("o")
    bodies = body(obj, [transform(rot([1, 0, 0], 0.2), [0, 0, 0]), transform(rot([1, 0, 0], 0.2), [1, 0, 0])])
    hinge = AffineBodyRevoluteJoint().create_geometry(np.array([[0.5, 0, 0]]), np.array([[0.5, 1.0, 0.3]]), [bodies],
                                                      np.array([0], np.int32), [bodies], np.array([1], np.int32), np.ones(1))
    AffineBodyRevoluteJointLimit().apply_to(hinge, -0.1, 0.1, 10.0)
    obj.geometries().create(hinge)
    set_transform(bodies, 1, transform(rot([0.5, 1, 0.3], 0.25) @ rot([1, 0, 0], 0.2), [1, 0, 0]))
    snap = cu.reference(scene)                 # world.init() after that move
    set_transform(bodies, 1, transform(rot([0.5, 1, 0.3], 0.55) @ rot([1, 0, 0], 0.2), [1, 0, 0]))
    _, _, ev = check_scene(scene, reference=snap, q_ref_of=snapshot_q(snap))
    assert abs(ev.batches[0].x[0] - 0.3) < 0.05   # from the snapshot's pose, not 0.55 from the rest's
    rest, _ = request_from_scene(scene)        # the rest transforms are no guess here: read, not refused
    assert abs(LocalClient().evaluate(rest).batches[0].x[0] - ev.batches[0].x[0]) > 0.2


@pytest.mark.parametrize("local", [False, True], ids=["world", "local"])
def test_hinges_and_sliders_initialised_at_a_moved_pose_measure_from_the_snapshot(local):
    """Both constitutions (the prismatic limit's `ref_qs` are the transforms at world.init() too):
    the scene of tests/sdk/test_uipc.py, world.init() after its move, then every body moved again."""
    from tests.sdk.test_uipc import hinge_and_slider_scene

    scene, (a, b), _ = hinge_and_slider_scene(local)
    snap = cu.reference(scene)
    for slot, n in ((a, 3), (b, 2)):
        for i in range(n):
            T = np.asarray(slot.geometry().transforms().view())[i]
            set_transform(slot, i, transform(rot([1.0, 0.2 * i, 0.5], 0.3) @ T[:3, :3], T[:3, 3] + [0.1, 0.05 * i, -0.2]))
    req, _, ev = check_scene(scene, reference=snap, q_ref_of=snapshot_q(snap), min_active=2)
    assert [b_.constitution_uid for b_ in req.batches] == [670, 669]
    rest, _ = request_from_scene(scene)  # the rest transforms (creation): other numbers
    assert all(np.max(np.abs(g.x - w.x)) > 1e-2 for g, w in zip(LocalClient().evaluate(rest).batches, ev.batches))


def test_a_snapshot_must_cover_every_body_and_comes_alone():
    scene, bodies, _ = door()
    snap = cu.reference(scene)
    with pytest.raises(SceneError, match="not both"):
        request_from_scene(scene, reference=snap, q_ref=np.zeros((2, 12)))
    with pytest.raises(SceneError, match="snapshot from reference"):
        request_from_scene(scene, reference="init")
    with pytest.raises(SceneError, match="snapshot from reference"):
        request_from_scene(scene, reference={bodies.id(): np.eye(4)})
    late = body(scene.objects().create("late"), [transform(np.eye(3), [3, 0, 0])])
    with pytest.raises(SceneError, match="not in the reference snapshot") as e:
        request_from_scene(scene, reference=snap)
    assert e.value.geometry_id == late.id()


# -------------------------------------------------------------------- the published angle and q_prev


def test_a_published_angle_is_counted_once():
    """The door turned 0.4 rad, the engine publishes angle 0.4 (and the body offsets): x = 0.4, E = 0,
    where pairing the angle with q_prev = q_ref counted the turn twice (x = 0.8, E = 2.7)."""
    scene, bodies, hs = door()
    snap = cu.reference(scene)
    set_transform(bodies, 1, transform(rot([0, 0, 1], 0.4), [0, 0, 0]))
    publish(scene, [bodies])
    view(hs.geometry().edges().find("angle"))[:] = [0.4]
    req, _ = request_from_scene(scene, reference=snap)
    np.testing.assert_array_equal(req.q_prev, req.q)
    ev = LocalClient().evaluate(req)
    np.testing.assert_allclose(ev.batches[0].x, [0.4], rtol=1e-15)
    assert ev.batches[0].energy[0] == 0.0
    check_scene(scene, committed=True, reference=snap, q_ref_of=snapshot_q(snap), min_active=0)
    # a trial q (the next step's iterate): x = angle + DeltaTheta(q, current), still one count
    q = req.q.copy()
    q[1] = ref.transform_to_q(transform(rot([0, 0, 1], 0.6), [0, 0, 0]))[0]
    ev = LocalClient().evaluate(request_from_scene(scene, q=q, reference=snap)[0])
    np.testing.assert_allclose(ev.batches[0].x, [0.6], rtol=1e-14)
    # a given q_prev still wins; without the angle, q_prev is q_ref (the engine's first step)
    req, _ = request_from_scene(scene, q_prev=req.q_ref, reference=snap)
    np.testing.assert_array_equal(req.q_prev, req.q_ref)
    req, _ = request_from_scene(scene, committed=False, reference=snap)
    np.testing.assert_array_equal(req.q_prev, req.q_ref)
    assert req.batches[0].prev_coordinate is None


def test_a_multi_turn_published_angle_pairs_with_the_current_transforms():
    """Two turns and a bit: the angle carries the turns, the current transforms the wrapped pose."""
    scene, bodies, hs = door()
    snap = cu.reference(scene)
    turned = 4 * np.pi + 0.45
    set_transform(bodies, 1, transform(rot([0, 0, 1], turned), [0, 0, 0]))
    publish(scene, [bodies])
    view(hs.geometry().edges().find("angle"))[:] = [turned]
    edges = hs.geometry().edges()
    view(edges.find("limit/upper"))[:] = [4 * np.pi + 0.5]
    _, _, ev = check_scene(scene, committed=True, reference=snap, q_ref_of=snapshot_q(snap), min_active=0)
    np.testing.assert_allclose(ev.batches[0].x, [turned], rtol=1e-15)
    assert ev.batches[0].energy[0] == 0.0


# ------------------------------------------------- the SDK's Scene: a joint's known coordinate (issue 29)


def test_scene_a_joint_past_pi_given_its_known_coordinate_is_exact():
    """Scene.add_revolute_limit(prev_coordinate=) is the wire's prev_coordinate: the joint's committed
    angle at the bodies' `prev` poses. Past +-pi (and turns away) x is exact; without it each
    increment wraps into (-pi, pi] and the joint reads 2 pi off, as the docstring says."""
    from jointlimits.client import Scene as SdkScene

    at = lambda a: transform(rot([0, 0, 1], a), [0, 0, 0])  # noqa: E731
    for turns in (0, 2):
        scene = SdkScene()
        a = scene.add_body(np.eye(4))
        b = scene.add_body(at(3.5), prev=at(3.4), ref=np.eye(4))
        j = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-3.45, upper=3.45 + 2 * np.pi * turns,
                                     strength=100.0, prev_coordinate=3.4 + 2 * np.pi * turns)
        req = scene.request()
        np.testing.assert_array_equal(req.batches[0].prev_coordinate, [3.4 + 2 * np.pi * turns])
        r = LocalClient().evaluate(req).joint(j)
        assert abs(r.x - (3.5 + 2 * np.pi * turns)) < 1e-13 and r.energy > 0
    scene = SdkScene()
    a = scene.add_body(np.eye(4))
    b = scene.add_body(at(3.5), ref=np.eye(4))                       # prev = ref: one increment, wrapped
    j = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-3.45, upper=3.45, strength=100.0)
    assert scene.request().batches[0].prev_coordinate is None
    assert abs(LocalClient().evaluate(scene.request()).joint(j).x - (3.5 - 2 * np.pi)) < 1e-13


def test_scene_prev_coordinate_with_an_offset_and_beside_joints_without_it():
    """The known coordinate is in the reported frame (x + offset); joints given it make a batch of their
    own (the wire's prev_coordinate is all of a batch or none), handles still find their rows."""
    from jointlimits.client import Scene as SdkScene

    at = lambda a: transform(rot([0, 0, 1], a), [0, 0, 0])  # noqa: E731
    scene = SdkScene()
    a = scene.add_body(np.eye(4))
    b = scene.add_body(at(0.3), prev=at(0.2), ref=np.eye(4))
    plain = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.1, upper=0.1, strength=10.0)
    known = scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.1, upper=0.1, strength=10.0,
                                     offset=0.5, prev_coordinate=0.5 + 0.2 + 2 * np.pi)
    req = scene.request()
    assert [b_.prev_coordinate is None for b_ in req.batches] == [True, False]
    ev = LocalClient().evaluate(req)
    assert abs(ev.joint(plain).x - 0.3) < 1e-14
    r = ev.joint(known)
    assert abs(r.x - (0.3 + 2 * np.pi)) < 1e-13 and abs(r.coordinate - (0.8 + 2 * np.pi)) < 1e-13


def test_scene_prev_coordinate_is_checked_where_given_and_revolute_only():
    from jointlimits.client import InvalidInput, Scene as SdkScene

    scene = SdkScene()
    a, b = scene.add_body(np.eye(4)), scene.add_body(np.eye(4))
    with pytest.raises(InvalidInput, match="prev_coordinate") as e:
        scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-1, upper=1, prev_coordinate=np.nan)
    assert e.value.faults[0].loc[0] == "prev_coordinate"
    assert scene.request().batches == []
    with pytest.raises(TypeError):  # the wire refuses it on 669: its slide is absolute, it has no state
        scene.add_prismatic_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-1, upper=1, prev_coordinate=0.0)
