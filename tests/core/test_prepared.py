"""The prepared scene (jointlimits.service.core.prepared): evaluate equals the stateless answer, commit follows the
contract's rem rule, update is validated and atomic."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from jointlimits.service.core import Bodies, Evaluation, InputError, Joints, evaluate, prepare
from jointlimits.service.core.errors import MAX_FAULTS
from jointlimits.service.core.prepared import rem
from tests.scenes import pack, random_scene, rotation_about

Z = np.array([0.0, 0.0, 1.0])
EDGE = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _same(a: Evaluation, b: Evaluation) -> None:
    assert a.total_energy == b.total_energy
    for p, q in zip(a.batches, b.batches, strict=True):
        for name in ("index", "x", "coordinate", "energy", "gradient", "hessian"):
            np.testing.assert_array_equal(getattr(p, name), getattr(q, name))


def _scene(seed: int):
    return random_scene(np.random.default_rng(70_000 + seed))


# ---------------------------------------------------------------- evaluate


@pytest.mark.parametrize("mode", ["exact", "psd"])
@pytest.mark.parametrize("seed", range(6))
def test_prepared_evaluate_is_bitwise_the_stateless_answer_at_every_q(seed: int, mode: str) -> None:
    """One prepared scene, several q in turn (and back): each the stateless answer, bit for bit."""
    sc = _scene(seed)
    rng = np.random.default_rng(seed)
    scene = prepare(sc.bodies(), [b.joints() for b in sc.batches])
    qs = [sc.q, sc.q + 1e-2 * rng.normal(size=sc.q.shape), sc.q]
    for q, active_only in zip(qs, (False, True, False)):
        options = dict(hessian_mode=mode, active_only=active_only)
        want = evaluate(Bodies(q, sc.q_prev, sc.q_ref), [b.joints() for b in sc.batches], **options)
        _same(scene.evaluate(q, **options), want)


def test_prepared_evaluate_with_threads_is_bitwise_the_same() -> None:
    sc = _scene(1)
    one = prepare(sc.bodies(), [b.joints() for b in sc.batches])
    two = prepare(sc.bodies(), [b.joints() for b in sc.batches], threads=2)
    assert one.n_bodies == sc.q.shape[0] and one.batch_sizes == [len(b.lower) for b in sc.batches]
    _same(one.evaluate(sc.q), two.evaluate(sc.q))


def test_prepared_scene_on_threads_gathers_every_q_afresh() -> None:
    """On threads each q gets its own gathers, and an evaluation stopped early (a deadline already past)
    leaves nothing for the next load to read (a commit's step from q_ref would otherwise take the stopped
    call's increments)."""
    import time

    from jointlimits.service.core.errors import DeadlineExceeded

    sc = _scene(4)
    rng = np.random.default_rng(4)
    joints = [b.joints() for b in sc.batches]
    two, one = prepare(sc.bodies(), joints, threads=2), prepare(sc.bodies(), joints)
    qs = [sc.q + 1e-2 * rng.normal(size=sc.q.shape) for _ in range(3)]
    for q in (sc.q, qs[0], sc.q):
        _same(two.evaluate(q), evaluate(Bodies(q, sc.q_prev, sc.q_ref), joints))
    with pytest.raises(DeadlineExceeded):
        two.evaluate(qs[1], deadline=time.monotonic() - 1.0)
    for a, b in zip(two.commit(qs[2]), one.commit(qs[2]), strict=True):
        np.testing.assert_array_equal(a, b)
    _same(two.evaluate(qs[0]), one.evaluate(qs[0]))


@pytest.mark.parametrize("threads", [2, 3])
def test_stateless_call_on_threads_names_the_faults_of_one_thread(threads: int) -> None:
    """The stateless call prepares each batch on the thread that then evaluates it: a frame collapsed at
    q_prev in batch 1 (found while preparing it) and one at q in batch 0 (found while evaluating it)
    are named as on one thread, whichever task ends first (batch 0's, the first in order)."""
    eye = pack(np.zeros(3), np.eye(3))
    flat = pack(np.zeros(3), np.zeros((3, 3)))  # A = 0: no angle
    ref = np.stack([eye] * 3)
    q, q_prev = ref.copy(), ref.copy()
    q[1], q_prev[2] = flat, flat
    batch = lambda j: Joints(670, 18, np.array([[0, j]]), EDGE[None], np.array([-1.0]), np.array([1.0]), np.ones(1))  # noqa: E731
    bodies, joints = Bodies(q, q_prev, ref), [batch(1), batch(2)]
    with pytest.raises(InputError) as want:
        evaluate(bodies, joints)
    assert [(f.loc, "collapses at q " in f.msg) for f in want.value.faults] == [(("batches", 0, "body_ids", 0), True)]
    with pytest.raises(InputError) as got:
        evaluate(bodies, joints, threads=threads)
    assert got.value.faults == want.value.faults
    with pytest.raises(InputError) as second:  # batch 1 alone: its fault at q_prev, from its preparation
        evaluate(bodies, joints[1:], threads=threads)
    assert [f.loc for f in second.value.faults] == [("batches", 0, "body_ids", 0)] and "at q_prev" in second.value.faults[0].msg


def test_prepare_does_not_use_q_nor_alias_the_callers_arrays() -> None:
    sc = _scene(2)
    joints = [b.joints() for b in sc.batches]
    scene = prepare(Bodies(np.full_like(sc.q, np.nan), sc.q_prev, sc.q_ref), joints)
    want = evaluate(sc.bodies(), joints)
    for j in joints:  # the caller reuses its arrays
        j.lower[:] = -1e9
        j.upper[:] = 1e9
    sc.q_prev[:] = 0.0
    _same(scene.evaluate(sc.q), want)


def test_bad_q_is_an_input_error_naming_the_body() -> None:
    sc = _scene(3)
    scene = prepare(sc.bodies(), [b.joints() for b in sc.batches])
    q = sc.q.copy()
    q[1, 4] = np.inf
    with pytest.raises(InputError) as e:
        scene.evaluate(q)
    assert [f.loc for f in e.value.faults] == [("bodies", "q", 1, 4)]  # to the element, as JSON locates it
    with pytest.raises(InputError) as e:
        scene.evaluate(q[:1])
    assert [f.loc for f in e.value.faults] == [("bodies", "q")]


def test_prepare_names_bad_static_data() -> None:
    sc = _scene(4)
    q_prev = sc.q_prev.copy()
    q_prev[0, 0] = np.nan
    with pytest.raises(InputError) as e:
        prepare(Bodies(sc.q, q_prev, sc.q_ref), [b.joints() for b in sc.batches])
    assert [f.loc for f in e.value.faults] == [("bodies", "q_prev", 0, 0)]


def test_one_fault_cap_for_the_whole_request() -> None:
    """Faults in several batches: MAX_FAULTS in all, the first batches' first."""
    sc = _scene(5)
    bad = []
    for b in sc.batches * 3:
        n = len(b.lower)
        bad.append(replace(b, strength=-np.ones(n)).joints())
    big = [replace(j, body_ids=np.tile(j.body_ids, (20, 1)), edges=np.tile(j.edges, (20, 1, 1)),
                   lower=np.tile(j.lower, 20), upper=np.tile(j.upper, 20), strength=-np.ones(20 * len(j.lower)))
           for j in bad]
    with pytest.raises(InputError) as e:
        prepare(sc.bodies(), big)
    locs = [f.loc for f in e.value.faults]
    assert len(locs) == MAX_FAULTS
    assert locs == sorted(locs, key=lambda loc: (loc[1], loc[3]))
    assert locs[0] == ("batches", 0, "strength", 0)


# ---------------------------------------------------------------- commit


def _screw(angle: float, offset: float = 0.0, prev_coordinate: float | None = None, lower=-100.0, upper=100.0):
    """Body 0 fixed, body 1 turned by `angle` about +z (the joint's axis); bodies (q at `angle`) and the joint."""
    eye = pack(np.zeros(3), np.eye(3))
    q = np.stack([eye, pack(np.zeros(3), rotation_about(Z, angle))])
    ref = np.stack([eye, eye])
    joints = Joints(
        670, 18, np.array([[0, 1]]), EDGE[None], np.array([lower]), np.array([upper]), np.array([10.0]),
        offset=np.array([offset]), prev_coordinate=None if prev_coordinate is None else np.array([prev_coordinate]),
    )
    return Bodies(q, ref, ref), joints


def _q(angle: float) -> np.ndarray:
    return _screw(angle)[0].q


@pytest.mark.parametrize("direction", [1.0, -1.0])
@pytest.mark.parametrize("step", [0.4, 3.0])
def test_commit_follows_many_turns_either_way(direction: float, step: float) -> None:
    """Steps of 0.4 and 3.0 rad (< pi) for 3.5 turns: the committed coordinate is the accumulated angle + offset."""
    bodies, joints = _screw(0.0, offset=0.25)
    scene = prepare(bodies, [joints])
    angle = 0.0
    for _ in range(int(7 * np.pi / step)):
        angle += direction * step
        (coord,) = scene.commit(_q(angle))
        assert abs(coord[0] - (angle + 0.25)) <= 1e-13 * max(1.0, abs(angle))
        np.testing.assert_array_equal(scene.coordinates()[0], coord)
    assert abs(angle) > 6 * np.pi


def test_commit_is_the_contract_rem_rule() -> None:
    """r := r + rem(DeltaTheta(q, q_ref) - r), DeltaTheta(q, q_ref) from the stateless evaluation with q_prev = q_ref."""
    rng = np.random.default_rng(7)
    sc = _scene(7)
    revolute = [b.joints() for b in sc.batches if b.uid == 670]
    scene = prepare(sc.bodies(), revolute)
    r = evaluate(Bodies(sc.q_prev, sc.q_ref, sc.q_ref), revolute, outputs=("energy",)).batches[0].x
    np.testing.assert_array_equal(scene.coordinates()[0], r)
    q = sc.q_prev
    for _ in range(5):
        q = q + 0.3 * rng.normal(size=q.shape)
        wrapped = evaluate(Bodies(q, sc.q_ref, sc.q_ref), revolute, outputs=("energy",)).batches[0].x
        r = r + rem(wrapped - r)
        np.testing.assert_array_equal(scene.commit(q)[0], r)


def test_commit_across_pi() -> None:
    """3.0 -> 3.3 rad: the wrapped angle jumps to -2.98; the committed one goes on to 3.3."""
    bodies, joints = _screw(3.0)
    scene = prepare(Bodies(bodies.q, bodies.q, bodies.q_ref), [joints])  # q_prev at 3.0
    # atan2 on another CPU's kernels is a few ulps off (tests/perturb.py: 3 ulps of 3.0 seen at --perturb-ulps 4)
    assert abs(scene.coordinates()[0][0] - 3.0) <= 4e-15
    (coord,) = scene.commit(_q(3.3))
    assert abs(coord[0] - 3.3) <= 1e-14
    # The next evaluation measures from the committed angle.
    assert abs(scene.evaluate(_q(3.5)).batches[0].x[0] - 3.5) <= 1e-14


def test_commit_from_prev_coordinate_and_the_stateless_equivalent() -> None:
    """Opened with prev_coordinate (4 turns + 0.1): commit and evaluate agree with the stateless
    request that carries the committed coordinate as its prev_coordinate."""
    phi0 = 8 * np.pi + 0.1
    bodies, joints = _screw(0.1, offset=-0.5, prev_coordinate=phi0 - 0.5, lower=-1e3, upper=phi0 - 0.2)
    scene = prepare(Bodies(bodies.q, bodies.q, bodies.q_ref), [joints])
    np.testing.assert_array_equal(scene.coordinates()[0], joints.prev_coordinate)
    coord = scene.commit(_q(0.45))[0]
    assert abs(coord[0] - (phi0 + 0.35 - 0.5)) <= 1e-13
    q = _q(0.7)
    stateless = evaluate(Bodies(q, _q(0.45), bodies.q_ref), [replace(joints, prev_coordinate=coord)])
    got = scene.evaluate(q)
    for f in ("x", "coordinate", "energy", "gradient", "hessian"):
        want = getattr(stateless.batches[0], f)
        np.testing.assert_allclose(getattr(got.batches[0], f), want, rtol=1e-14, atol=1e-14 * np.abs(want).max())
    assert got.batches[0].energy[0] > 0  # x = phi0 + 0.6 > u = upper - offset = phi0 + 0.3


def test_commit_prismatic_reports_the_slide_and_keeps_no_state() -> None:
    sc = _scene(8)
    prismatic = [replace(b.joints(), offset=np.full(len(b.lower), 0.75)) for b in sc.batches if b.uid == 669]
    if not prismatic:
        pytest.skip("no prismatic batch in this scene")
    scene = prepare(sc.bodies(), prismatic)
    x_prev = evaluate(Bodies(sc.q_prev, sc.q_prev, sc.q_ref), prismatic).batches[0].x
    np.testing.assert_allclose(scene.coordinates()[0], x_prev + 0.75, rtol=0, atol=1e-15)
    before = scene.evaluate(sc.q)
    coord = scene.commit(sc.q)[0]
    np.testing.assert_array_equal(coord, before.batches[0].coordinate)
    _same(scene.evaluate(sc.q), before)  # the slide is absolute: committing changes nothing


def test_commit_is_all_or_nothing() -> None:
    bodies, joints = _screw(0.0)
    scene = prepare(bodies, [joints, joints])
    scene.commit(_q(1.0))
    before = scene.coordinates()
    collapsed = _q(2.0)
    collapsed[1, 3:] = 0.0  # A_j = 0: no angle
    with pytest.raises(InputError) as e:
        scene.commit(collapsed)
    assert [f.loc for f in e.value.faults] == [("batches", 0, "body_ids", 0), ("batches", 1, "body_ids", 0)]
    bad = _q(2.0)
    bad[0, 0] = np.nan
    with pytest.raises(InputError) as e:
        scene.commit(bad)
    assert [f.loc for f in e.value.faults] == [("bodies", "q", 0, 0)]
    for a, b in zip(scene.coordinates(), before):
        np.testing.assert_array_equal(a, b)
    assert abs(scene.evaluate(_q(1.2)).batches[0].x[0] - 1.2) <= 1e-15


X_OVERFLOWS = "the joint coordinate x overflows float64 at this configuration (positions or edge too large)"


def _slide(far: np.ndarray) -> tuple[Bodies, Joints]:
    """A #669 joint along +z between two bodies at the origin, then body 1's DOFs `far` at q_prev and q."""
    eye = pack(np.zeros(3), np.eye(3))
    ref = np.stack([eye, eye])
    joints = Joints(669, 20, np.array([[0, 1]]), EDGE[None], np.array([-1.0]), np.array([1.0]), np.array([1.0]))
    return Bodies(np.stack([eye, far]), np.stack([eye, far]), ref), joints


def test_a_slide_past_float64_is_named_at_commit_and_in_the_committed_coordinates_never_returned() -> None:
    """x = (C_j - C_i) . (T_i + T_j) / 2 with C_j and T_j near 1e300 overflows: evaluate names the joint; so must
    commit (all or nothing) and the coordinates at q_prev (a session's opening reply): they returned inf."""
    far = pack(np.array([0.0, 0.0, 1e300]), 1e300 * np.eye(3))
    bodies, joints = _slide(pack(np.zeros(3), np.eye(3)))
    scene = prepare(bodies, [joints])
    with pytest.raises(InputError) as e:
        scene.evaluate(np.stack([bodies.q[0], far]))
    assert [f.loc[:2] + f.loc[-1:] for f in e.value.faults] == [("batches", 0, 0)]  # (its energy overflows first)
    with pytest.raises(InputError) as e:
        scene.commit(np.stack([bodies.q[0], far]))
    assert [(f.loc, f.msg) for f in e.value.faults] == [(("batches", 0, "body_ids", 0), X_OVERFLOWS)]
    assert scene.coordinates()[0].tolist() == [0.0]  # unchanged
    bodies, joints = _slide(far)  # q_prev far: the stateless answer at q needs no coordinate there
    scene = prepare(bodies, [joints])
    with pytest.raises(InputError) as e:
        scene.coordinates()
    assert [(f.loc, f.msg) for f in e.value.faults] == [(("batches", 0, "body_ids", 0), X_OVERFLOWS)]


# ---------------------------------------------------------------- update


def test_update_equals_a_scene_prepared_with_the_new_values() -> None:
    sc = _scene(9)
    joints = [replace(b.joints(), offset=np.zeros(len(b.lower))) for b in sc.batches]
    scene = prepare(sc.bodies(), joints)
    n = len(joints[0].lower)
    index = np.arange(0, n, 2)
    lo = joints[0].lower[index] - 0.3
    up = joints[0].upper[index] - 0.1
    s = joints[0].strength[index] * 2 + 1
    off = np.full(index.shape, 0.05)
    scene.evaluate(sc.q)  # the scene keeps its penalty's limits from here (`_limits`): the update must reach them
    scene.update(0, index, lower=lo, upper=up, strength=s, offset=off)
    new = joints[0]
    lower, upper, strength, offset = new.lower.copy(), new.upper.copy(), new.strength.copy(), new.offset.copy()
    lower[index], upper[index], strength[index], offset[index] = lo, up, s, off
    fresh = [replace(new, lower=lower, upper=upper, strength=strength, offset=offset), *joints[1:]]
    _same(scene.evaluate(sc.q), evaluate(sc.bodies(), fresh))


@pytest.mark.parametrize(
    "kwargs,loc",
    [
        (dict(index=[0, 1], lower=[0.0, 10.0], upper=[1.0, 5.0]), ("batches", 0, "lower", 1)),
        (dict(index=[1], strength=[-1.0]), ("batches", 0, "strength", 1)),
        (dict(index=[0], lower=[np.nan]), ("batches", 0, "lower", 0)),
        (dict(index=[0, 1], lower=[0.0]), ("batches", 0, "lower")),
        (dict(index=[0, 99]), ("batches", 0, "index", 1)),
        (dict(index=[1, 1], strength=[1.0, 2.0]), ("batches", 0, "index")),
        (dict(index=[0.5], strength=[1.0]), ("batches", 0, "index")),
        (dict(index=[0], offset=[np.inf]), ("batches", 0, "offset", 0)),
    ],
)
def test_update_is_validated_and_atomic(kwargs: dict, loc: tuple) -> None:
    bodies, joints = _screw(0.5, lower=0.0, upper=0.4)
    joints = replace(
        joints, **{k: np.repeat(getattr(joints, k), 3, axis=0) for k in ("body_ids", "edges", "lower", "upper", "strength", "offset")}
    )
    scene = prepare(Bodies(bodies.q, bodies.q_ref, bodies.q_ref), [joints])
    before = scene.evaluate(bodies.q)
    with pytest.raises(InputError) as e:
        scene.update(0, **kwargs)
    assert e.value.faults[0].loc == loc
    _same(scene.evaluate(bodies.q), before)


@pytest.mark.parametrize("committed", [False, True])
def test_an_offset_that_would_overflow_a_committed_coordinate_changes_nothing(committed: bool) -> None:
    """The angle 1e308 (prev_coordinate) plus a new offset 1e308 (its bounds finite) is inf: the update is refused
    naming the offset, and nothing changes; before, it was applied and the coordinates read inf."""
    bodies, joints = _screw(0.0, prev_coordinate=1e308, lower=-1.5e308, upper=1.5e308)
    scene = prepare(bodies, [joints])
    if committed:
        scene.commit(_q(0.5))
    before = scene.coordinates()
    with pytest.raises(InputError) as e:
        scene.update(0, [0], lower=[1.5e308], upper=[1.7e308], offset=[1e308])
    assert [(f.loc, f.msg) for f in e.value.faults] == [(("batches", 0, "offset", 0), "the coordinate x + offset overflows float64")]
    assert scene.coordinates()[0].tolist() == before[0].tolist()
    assert scene.evaluate(_q(0.5)).batches[0].energy.tolist() == [0.0]


def test_update_of_a_missing_batch() -> None:
    bodies, joints = _screw(0.5)
    scene = prepare(bodies, [joints])
    with pytest.raises(InputError) as e:
        scene.update(3, [0], lower=[0.0])
    assert [f.loc for f in e.value.faults] == [("batches", 3)]


def test_update_offset_keeps_the_angle_and_moves_the_coordinate() -> None:
    bodies, joints = _screw(0.0, offset=0.0)
    scene = prepare(bodies, [joints])
    scene.commit(_q(1.0))
    scene.update(0, [0], offset=[2.0])
    assert abs(scene.coordinates()[0][0] - 3.0) <= 4e-15  # a few ulps: atan2 (as in test_commit_across_pi)
    r = scene.evaluate(_q(1.1)).batches[0]
    assert abs(r.x[0] - 1.1) <= 4e-15 and abs(r.coordinate[0] - 3.1) <= 4e-15


def test_the_committed_coordinate_is_kept_as_the_wire_carries_it() -> None:
    """A scene keeps a revolute's committed coordinate and takes the angle as `coordinate - offset` on every
    path (so a reopened session, given the coordinate back, is bitwise the same). Here (0.1 - 3) + 3 is
    0.1 + 8e-17: the coordinate opened with comes back as sent, not re-rounded; an update of limits alone keeps it;
    an offset's update makes it the angle plus the new offset, the angle then taken from it as from a reopen's."""
    bodies, joints = _screw(0.5, offset=3.0, prev_coordinate=0.1)
    assert (0.1 - 3.0) + 3.0 != 0.1
    scene = prepare(bodies, [joints])
    assert scene.coordinates()[0].tobytes() == np.array([0.1]).tobytes()
    scene.update(0, [0], upper=[50.0])
    assert scene.coordinates()[0].tobytes() == np.array([0.1]).tobytes()
    scene.update(0, [0], offset=[-1.7])
    moved = np.array([(0.1 - 3.0) + -1.7])
    assert scene.coordinates()[0].tobytes() == moved.tobytes()
    reopened = prepare(bodies, [replace(joints, upper=np.array([50.0]), offset=np.array([-1.7]), prev_coordinate=moved)])
    _same(scene.evaluate(_q(0.7)), reopened.evaluate(_q(0.7)))


def test_checks_are_leaves() -> None:
    """validate.py imports neither the pipeline (prepared) nor the derivative code (evaluate), at any level."""
    import ast
    from pathlib import Path

    import jointlimits.service.core.validate as validate

    tree = ast.parse(Path(validate.__file__).read_text())
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not imported & {"jointlimits.service.core.evaluate", "jointlimits.service.core.prepared", "jointlimits.service.core"}


# ---------------------------------------------------------------- frames at every scale (issue 9's careful frames)


@pytest.mark.parametrize("k", [1e-300, 1e-100, 1e-12, 1e12, 1e300])
@pytest.mark.parametrize("uid", [670, 669])
def test_prepared_scene_forms_careful_frames_at_every_scale(k: float, uid: int) -> None:
    """A_j scaled by k in some states: the prepared scene answers as the stateless call (bitwise) at
    several q, and commits the scale-free angle."""
    from tests.core.test_degenerate_scales import TURN, Z_EDGE, _joint, _revolute_probe

    edge = Z_EDGE if uid == 670 else np.array([[0.0, 0, 0], [1.0, 0, 0]])
    joints = _joint(uid, edge)
    bodies = _revolute_probe({"q_ref": np.eye(3), "q_prev": k * np.eye(3), "q": k * TURN})
    scene = prepare(bodies, [joints])
    for q in (bodies.q, _revolute_probe({"q": TURN}).q, _revolute_probe({"q": 1e-3 * k * TURN}).q):
        # The same answer, or the same refusal (derivatives ~ 1/k^2 overflow at the smallest scales).
        try:
            want = evaluate(Bodies(q, bodies.q_prev, bodies.q_ref), [joints])
        except InputError as e:
            with pytest.raises(InputError) as got:
                scene.evaluate(q)
            assert got.value.faults == e.faults
            continue
        _same(scene.evaluate(q), want)
    if uid == 670:
        for angle in (0.7, 2.5, 4.0, 6.5):  # turns of < pi per commit, A_j at scale k
            (coord,) = scene.commit(_revolute_probe({"q": k * rotation_about(Z, angle)}).q)
            assert abs(coord[0] - angle) <= 1e-12 * angle


def test_rem_is_exact_to_rounding_over_many_turns() -> None:
    """rem(y) against 50 digits, y up to a million turns either way: within an ulp of |y|'s own rounding."""
    from mpmath import mp, mpf

    rng = np.random.default_rng(11)
    y = np.concatenate([rng.uniform(-1, 1, 50) * 10.0 ** rng.integers(0, 7, 50), [np.pi, -np.pi, 3 * np.pi + 1e-9]])
    got = rem(y)
    with mp.workdps(50):
        two_pi = 2 * mp.pi
        want = [float(mpf(float(v)) - two_pi * mp.nint(mpf(float(v)) / two_pi)) for v in y]
    assert np.all(np.abs(got) <= np.pi + 1e-15)
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-16 * 4)


def test_the_coordinates_of_chosen_batches_are_theirs_alone_and_named_by_their_own_number(monkeypatch) -> None:
    """An offset update's reply carries its batch's coordinates: `coordinates([b])` computes that batch's alone (a
    scene of many batches paid for all of them per update) and names a fault in it as batch `b`, not as the first."""
    far = pack(np.array([0.0, 0.0, 1e300]), 1e300 * np.eye(3))
    bodies, joints = _slide(far)  # x at q_prev overflows in batch 1 (batch 0 is a revolute screw, fine)
    screw = replace(joints, constitution_uid=670, base_uid=18)
    scene = prepare(bodies, [screw, joints, joints])
    computed = []
    x_prev = type(scene)._x_prev
    monkeypatch.setattr(type(scene), "_x_prev", lambda self, jb: computed.append(jb) or x_prev(self, jb))
    np.testing.assert_array_equal(scene.coordinates([0])[0], np.zeros(1))
    assert computed == [scene._batches[0]]
    with pytest.raises(InputError) as e:
        scene.coordinates([2])
    assert [f.loc for f in e.value.faults] == [("batches", 2, "body_ids", 0)]
    with pytest.raises(InputError) as e:
        scene.coordinates()
    assert [f.loc for f in e.value.faults] == [("batches", 1, "body_ids", 0), ("batches", 2, "body_ids", 0)]
