"""`result.joint(handle)`: one joint's answer by the handle `Scene` returned, with and without `active_only`."""

from __future__ import annotations

import dataclasses
import pickle
import re

import numpy as np
import pytest

from jointlimits.client import Client, Joint, JointBatch, LocalClient, Scene
from tests.http.test_contract_live import live  # noqa: F401 (fixture)


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def scene() -> tuple[Scene, list[Joint]]:
    """Revolute joints 0 (inside), 1 (0.2 above), 2 (inside); prismatic 0 (0.1 above), 1 (inside)."""
    s = Scene()
    a = s.add_body((np.zeros(3), np.eye(3)))
    b = s.add_body((np.zeros(3), rot_z(0.7)), ref=(np.zeros(3), np.eye(3)))
    c = s.add_body((np.array([0.0, 0.0, 1.3]), np.eye(3)), ref=(np.array([0.0, 0.0, 1.0]), np.eye(3)))
    js = [
        s.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-1.0, upper=1.0),
        s.add_prismatic_limit(a, c, [0, 0, 0], [0, 0, 1], lower=-0.1, upper=0.2, strength=10.0),
        s.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5, strength=100.0),
        s.add_prismatic_limit(a, c, [0, 0, 0], [0, 0, 1], lower=-0.1, upper=0.5),
        s.add_revolute_limit(b, a, [0, 0, 0], [0, 0, 1], lower=-1.0, upper=1.0),
    ]
    return s, js


def test_the_handle_is_the_row_and_knows_its_constitution():
    _, js = scene()
    assert [int(j) for j in js] == [0, 0, 1, 1, 2]
    assert [j.constitution_uid for j in js] == [670, 669, 670, 669, 670]
    assert [(k, k.constitution_uid) for k in pickle.loads(pickle.dumps(js))] == [(j, j.constitution_uid) for j in js]


@pytest.mark.parametrize("mode", ["local", "binary", "json"])
@pytest.mark.parametrize("outputs", [("energy",), ("energy", "gradient", "hessian")])
def test_joint_lookup_is_the_same_with_and_without_active_only(live, mode, outputs):
    s, js = scene()
    client = LocalClient() if mode == "local" else Client(live, binary=mode == "binary")
    full = client.evaluate(s.request(outputs=outputs))
    only = client.evaluate(s.request(outputs=outputs, active_only=True))
    assert [len(b.index) for b in only.batches] == [1, 1]  # the scene has one active joint per batch
    for j in js:
        f, a = full.joint(j), only.joint(j)
        assert f.x == full.batch(j.constitution_uid).x[j]
        assert f.energy == a.energy and f.energy == full.batch(j.constitution_uid).energy[j]
        for name in ("gradient", "hessian"):
            fv, av = getattr(f, name), getattr(a, name)
            if name in outputs:
                assert fv.shape == av.shape == ((24,) if name == "gradient" else (24, 24))
                assert np.array_equal(fv, av)
            else:
                assert fv is None and av is None
        active = f.energy > 0
        assert (a.x == f.x) if active else (a.x is None and f.energy == 0.0)
    assert only.joint(js[2]).energy == pytest.approx(100 * 0.2**3, rel=1e-14)
    assert only.joint(js[1]).x == pytest.approx(0.3, rel=1e-14)


def test_joint_out_of_range_and_ambiguous_rows():
    s, js = scene()
    only = LocalClient().evaluate(s.request(active_only=True))
    with pytest.raises(IndexError, match="3 joints"):
        only.joint(Joint(3, 670))
    with pytest.raises(TypeError, match="handle"):
        only.joint(0)  # two batches: a bare row names no batch
    assert only.batch(670).joint(2).energy == 0.0 and only.batch(670).joint(2).x is None
    one = Scene()
    a, b = one.add_body(np.eye(4)), one.add_body(np.eye(4))
    one.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-1, upper=1)
    assert LocalClient().evaluate(one.request()).joint(0).x == 0.0  # one batch: a bare row is fine


def test_joint_lookup_after_a_split(live):
    s, js = scene()
    split = Client(live, max_joints_per_request=1).evaluate(s.request(active_only=True))
    whole = LocalClient().evaluate(s.request(active_only=True))
    for j in js:
        assert split.joint(j).energy == whole.joint(j).energy
        assert np.array_equal(split.joint(j).hessian, whole.joint(j).hessian)


def test_a_handle_of_another_scene_is_refused_not_read_as_another_joint():
    """A handle is a row of a batch: in another scene's answer that batch may be another constitution's (a
    revolute handle read a prismatic joint's numbers) or absent (an IndexError of the list, not the SDK's)."""
    s, js = scene()
    other = Scene()
    a, c = other.add_body(np.eye(4)), other.add_body(np.eye(4))
    other.add_prismatic_limit(a, c, [0, 0, 0], [0, 0, 1], lower=-0.1, upper=0.2)  # batch 0 holds #669 here
    answer = LocalClient().evaluate(other.request())
    with pytest.raises(KeyError, match="constitution 670"):
        answer.joint(js[0])  # batch 0, #670 in its own scene
    with pytest.raises(KeyError, match="batch 1"):
        answer.joint(js[1])  # batch 1: the other scene has one batch
    assert answer.joint(Joint(0, 669, 0)).x == answer.batch(669).x[0]  # a handle that fits is read


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def two_arms(swap: bool = False, turn: float = 0.0, strength: float = 7.0) -> tuple[Scene, list[Joint]]:
    """Two revolute limits in [-0.5, 0.5]: bodies (0, 1) about z turned 0.2 (inside), (0, 2) about x turned 0.9
    (0.4 above); `swap` adds them in the other order (handles still in arm order), `turn` turns both more."""
    s = Scene()
    a = s.add_body(np.eye(4))
    b = s.add_body((np.zeros(3), rot_z(0.2 + turn)), ref=np.eye(4))
    c = s.add_body((np.zeros(3), rot_x(0.9 + turn)), ref=np.eye(4))
    arms = [lambda: s.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5),
            lambda: s.add_revolute_limit(a, c, [0, 0, 0], [1, 0, 0], lower=-0.5, upper=0.5, strength=strength)]
    js = [add() for add in (arms[::-1] if swap else arms)]
    return s, js[::-1] if swap else js


@pytest.mark.parametrize("how", ["local", "binary", "json", "split", "session", "local session"])
def test_a_handle_of_another_scene_of_the_same_constitutions_is_refused(live, how):
    """Batch 0 is #670 in both scenes, so the batch and constitution checks pass: only the joint at the
    handle's row tells them apart. Before the fix the first arm's handle read the second arm's numbers."""
    s, js = two_arms()
    other, theirs = two_arms(swap=True)
    client = LocalClient() if how.startswith("local") else Client(
        live, binary=how != "json", max_joints_per_request=1 if how == "split" else None)
    if how.endswith("session"):
        with client.session(other.request()) as session:
            answer = session.evaluate(other.request().q)
    else:
        answer = client.evaluate(other.request())
    assert answer.batch(670).energy[0] > 0 and answer.batch(670).energy[1] == 0  # the rows differ in value
    for j in js:
        said = f"{j!r} is not a joint of this answer's request (its row there is another joint, ((0, {2 - j})"  # swapped
        with pytest.raises(KeyError, match=re.escape(said)):
            answer.joint(j)
        with pytest.raises(KeyError, match=re.escape(said)):  # the batch's own lookup checks it too
            answer.batch(670).joint(j)
    mine = LocalClient().evaluate(s.request())
    assert [answer.joint(k).energy for k in theirs] == [mine.joint(j).energy for j in js]
    assert mine.joint(js[1]).energy == pytest.approx(7.0 * 0.4**3, rel=1e-13)


def test_the_same_joints_rebuilt_are_read_by_the_first_scenes_handles():
    """A new Scene of the same joints (other poses and strength: the joints are the same), as `Robot` builds one
    per call while keeping the first one's handles, answers those handles, pickled ones too."""
    _, js = two_arms()
    again, mine = two_arms(turn=0.4, strength=3.0)
    answer = LocalClient().evaluate(again.request(active_only=True))
    assert [answer.joint(j).energy for j in js] == [answer.joint(k).energy for k in mine]
    # x - upper = 0.6 - 0.5: x's few ulps of 0.6 are ~1e-15 of 0.1, ~3e-15 of its cube (default strength 1).
    assert answer.joint(js[0]).energy == pytest.approx(0.1**3, rel=1e-13)  # the turn made the first arm active
    assert answer.joint(pickle.loads(pickle.dumps(js[1]))).energy == pytest.approx(3.0 * 0.8**3, rel=1e-13)


def test_a_handle_of_the_same_bodies_about_another_edge_is_refused():
    _, js = two_arms()
    s = Scene()
    a, b = s.add_body(np.eye(4)), s.add_body((np.zeros(3), rot_x(0.2)), ref=np.eye(4))
    s.add_revolute_limit(a, b, [0, 0, 0], [1, 0, 0], lower=-0.5, upper=0.5)  # about x, where js[0] is about z
    said = "another joint, ((0, 1), [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], 'q_ref')"  # body_ids, edge, origin
    with pytest.raises(KeyError, match=re.escape(said)):
        LocalClient().evaluate(s.request()).joint(js[0])


def test_a_request_built_by_hand_of_plain_lists_is_checked_too():
    """A `JointBatch` made by its constructor keeps the caller's lists: the check reads them as arrays (it raised
    AttributeError on `list.tolist` before), and tells the same joint from another."""
    s, js = two_arms()
    built = s.request()
    b = built.batches[0]
    by_hand = JointBatch(670, b.body_ids.tolist(), b.edges.tolist(), b.lower.tolist(), b.upper.tolist(),
                         b.strength.tolist())
    answer = LocalClient().evaluate(dataclasses.replace(built, batches=[by_hand]))
    assert [answer.joint(j).energy for j in js] == [LocalClient().evaluate(built).joint(j).energy for j in js]
    swapped = dataclasses.replace(by_hand, body_ids=by_hand.body_ids[::-1], edges=by_hand.edges[::-1])
    with pytest.raises(KeyError, match="another joint"):
        LocalClient().evaluate(dataclasses.replace(built, batches=[swapped])).joint(js[0])
