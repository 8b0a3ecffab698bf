"""Joint coordinates at every scale of `A` and of the edge: exact, or an input error naming the joint.

The revolute angle depends only on the directions of each body's frame vectors, so `A` scaled by
any k > 0 in any state gives the same angle; the prismatic slide scales with `A` but stays a
well-defined number. Over scales 1e-300 ... 1e300 of `A` (each body, each state) and edge lengths
1e-300 ... 1e300 the core answers the true coordinate of the float64 input (the 50-digit reference
of `bench/reference.py`) to 1e-12, or an `InputError` whose fault names the joint (and, for a
collapsed frame, the state): never another number. The issue's probes (issue 9, items 5 and 6)
are pinned by name.
"""

from __future__ import annotations

import itertools
from functools import lru_cache

import numpy as np
import pytest

from jointlimits.service.core import Bodies, Joints, evaluate  # checked itself (one code path)
from jointlimits.service.core.errors import InputError
from jointlimits.service.core.kinematics import BodyTable
from tests.conftest import relerr
from bench.reference import JointRef
from tests.scenes import pack, random_rotation, random_unit, rotation_about
from tests.http.test_contract_live import live  # noqa: F401 (fixture)

pytestmark = pytest.mark.slow  # 1e-300..1e300 scales (~4 s)

E_Z = np.array([0.0, 0.0, 1.0])
STATES = ("q_ref", "q_prev", "q")
SCALES = (1e-300, 1e-200, 1e-100, 1e-16, 1e-12, 1.0, 1e12, 1e100, 1e200, 1e300)
TOL = 1e-12


def _joint(uid: int, edge: np.ndarray, lower: float = -0.1, upper: float = 0.1) -> Joints:
    return Joints(uid, {670: 18, 669: 20}[uid], np.array([[0, 1]]), edge[None], np.array([lower]), np.array([upper]), np.array([1.0]))


def _answer(bodies: Bodies, joints: Joints, outputs: tuple[str, ...] = ("energy",)) -> float | InputError:
    """x of the one joint, or the InputError the service would answer."""
    try:
        return float(evaluate(bodies, [joints], outputs=outputs).batches[0].x[0])
    except InputError as err:
        return err


def _reference_x(bodies: Bodies, joints: Joints) -> float:
    ref = JointRef(joints.constitution_uid, bodies.q_ref[0], bodies.q_ref[1], joints.edges[0])
    return float(ref.x(*((getattr(bodies, s)[0], getattr(bodies, s)[1]) for s in ("q", "q_prev", "q_ref"))))


def _assert_refused(err: InputError, state: str | None = None) -> None:
    """Every fault names batch 0's joint 0 (and `state`, where given), not the whole request."""
    assert err.faults
    for f in err.faults:
        assert f.loc[:2] == ("batches", 0) and f.loc[-1] == 0, f.loc
        if state is not None:
            assert f"at {state} " in f.msg, f.msg


# ---------------------------------------------------------------- the issue's probes


def _revolute_probe(A_j: dict[str, np.ndarray], A_i: dict[str, np.ndarray] | None = None) -> Bodies:
    """Body i at the origin, body j at e_x; `A` per state (identity where not given); axis +z."""
    A_i = A_i or {}
    rows = {s: np.array([pack(np.zeros(3), A_i.get(s, np.eye(3))), pack([1.0, 0, 0], A_j.get(s, np.eye(3)))]) for s in STATES}
    return Bodies(rows["q"], rows["q_prev"], rows["q_ref"])


Z_EDGE = np.array([[0.0, 0, 0], [0, 0, 1.0]])
TURN = rotation_about(E_Z, 0.7)


@pytest.mark.parametrize("k", [1e-12, 1e-15, 1e-16, 3e-17, 1e-100, 1e-300, 1e100, 1e300])
def test_revolute_angle_of_scaled_A_at_q_is_the_unscaled_angle(k: float) -> None:
    """Issue 9 item 5: A_j(q) = k R(0.7) gave x = 0.7000061 (k = 1e-12), pi/2 (k <= 3e-17), a 422 on `strength` (1e-100)."""
    bodies = _revolute_probe({"q": k * TURN})
    joints = _joint(670, Z_EDGE)
    x = _answer(bodies, joints)
    assert abs(x - 0.7) <= TOL * 0.7
    assert abs(x - _reference_x(bodies, joints)) <= TOL * 0.7
    # E = (0.6 / 0.2)^3 = 27, as unscaled.
    energy = evaluate(bodies, [joints], outputs=("energy",)).batches[0].energy[0]
    assert abs(energy - 27.0) <= 1e-12 * 27


@pytest.mark.parametrize("k", [5e-324, 1e-320, 1e-310])
def test_revolute_subnormal_A_at_q_is_its_own_angle_or_refused(k: float) -> None:
    """k R(0.7) rounded to a few-bit subnormal is another rotation (5e-324: exactly pi/4): its angle, or a 422 at q."""
    bodies = _revolute_probe({"q": k * TURN})
    joints = _joint(670, Z_EDGE)
    x = _answer(bodies, joints)
    if isinstance(x, InputError):
        _assert_refused(x, "q")
    else:
        assert abs(x - _reference_x(bodies, joints)) <= TOL * abs(x)


def test_revolute_zero_A_is_a_collapsed_frame_naming_the_state() -> None:
    for state in STATES:
        x = _answer(_revolute_probe({state: np.zeros((3, 3))} if state != "q_ref" else {"q_ref": np.eye(3), "q_prev": np.zeros((3, 3))}), _joint(670, Z_EDGE))
        assert isinstance(x, InputError)
        _assert_refused(x, "q_prev" if state == "q_ref" else state)


def test_huge_A_ref_with_identity_q_prev_is_not_collapsed() -> None:
    """Issue 9 item 5: A_ref = 1e300 I, q_prev = I answered "collapses at q_prev" (F_ref + dF cancelled to 0)."""
    for bodies in (
        _revolute_probe({"q_ref": 1e300 * np.eye(3), "q": TURN}),
        _revolute_probe({"q_ref": 1e300 * np.eye(3), "q": TURN}, {"q_ref": 1e300 * np.eye(3)}),
    ):
        joints = _joint(670, Z_EDGE)
        x = _answer(bodies, joints, ("energy", "gradient", "hessian"))
        assert abs(x - 0.7) <= TOL * 0.7


def _prismatic_probe(length: float, slide: float = 0.7) -> tuple[Bodies, Joints]:
    """Body j slid by `slide` along +z; the edge [0, L e_z]."""
    ref = np.array([pack(np.zeros(3), np.eye(3)), pack(np.zeros(3), np.eye(3))])
    q = np.array([pack(np.zeros(3), np.eye(3)), pack([0.0, 0, slide], np.eye(3))])
    return Bodies(q, ref, ref), _joint(669, np.array([[0.0, 0, 0], [0, 0, length]]))


@pytest.mark.parametrize("length", [1e-158, 1e-161, 1e-300, 5e-324, 1e-10, 1e10, 1e300, 1.7e308])
def test_prismatic_slide_of_short_and_long_edges(length: float) -> None:
    """Issue 9 item 6: L = 1e-158 gave x = 0.70000000571, 1e-161 0.70419 (dot(d, d) subnormal)."""
    bodies, joints = _prismatic_probe(length)
    assert _answer(bodies, joints) == 0.7
    energy = evaluate(bodies, [joints], outputs=("energy",)).batches[0].energy[0]
    assert abs(energy - 27.0) <= 1e-12 * 27


@pytest.mark.parametrize("uid", [669, 670])
def test_zero_and_overflowing_edges_are_refused_naming_the_edge(uid: int) -> None:
    bodies, _ = _prismatic_probe(1.0)
    for edge, words in (([[1.0, 2, 3], [1.0, 2, 3]], "zero-length"), ([[0, 0, -1.7e308], [0, 0, 1.7e308]], "overflows")):
        x = _answer(bodies, _joint(uid, np.array(edge)))
        assert isinstance(x, InputError)
        assert [f.loc for f in x.faults] == [("batches", 0, "edges", 0)] and words in x.faults[0].msg


# ---------------------------------------------------------------- properties over scales


def _scaled_scene(
    uid: int, seed: int, scale: dict[tuple[int, str], float], length: float | None = None, anchored: bool = False
) -> tuple[Bodies, Joints]:
    """Two bodies turned about a random axis by random angles, each body's `A` in each state scaled by `scale[(body, state)]`.

    Well posed by construction: body j is body i's orientation turned about the joint axis (plus a
    common world turn per state), so no frame is near collapse and the revolute angle is the turn.
    Prismatic: body j also slides along the axis; the anchor is off both bodies' origins, unless
    `anchored` (both bodies' origins and the anchor at 0 in q_ref: `C = p` exactly, no rounding).
    """
    rng = np.random.default_rng(seed)
    t = random_unit(rng)
    G_i, G_j = random_rotation(rng), random_rotation(rng)
    turn = {"q_ref": 0.0, "q_prev": rng.uniform(-1.5, 1.5)}
    turn["q"] = turn["q_prev"] + rng.uniform(-1.5, 1.5)
    slide = {"q_ref": 0.0, "q_prev": rng.uniform(-1, 1), "q": rng.uniform(-1, 1)}
    p0 = rng.normal(size=3)
    rows = {}
    for s in STATES:
        W = np.eye(3) if s == "q_ref" else random_rotation(rng, 0.3)  # the whole pair turned in the world
        A_i = W @ G_i * scale.get((0, s), 1.0)
        A_j = W @ rotation_about(t, turn[s]) @ G_j * scale.get((1, s), 1.0)
        p_i = np.zeros(3) if s == "q_ref" else 0.1 * rng.normal(size=3)
        offset = np.zeros(3) if anchored else np.array([0.3, -0.2, 0.5])
        p_j = p_i + W @ (offset + (slide[s] * t if uid == 669 else 0.0))
        rows[s] = np.array([pack(p_i, A_i), pack(p_j, A_j)])
    # An edge of `length` (a short one next to the origin, so that p0 + L t keeps L's digits).
    p0 = np.zeros(3) if anchored else p0 * min(1.0, length or 1.0)
    edge = np.array([p0, p0 + (length or 1.0) * t])
    return Bodies(rows["q"], rows["q_prev"], rows["q_ref"]), _joint(uid, edge)


def _frame_size(bodies: Bodies, joints: Joints) -> float:
    """(|C_i| + |C_j|)(|T_i| + |T_j|) (prismatic), the largest over the three states, from the 50-digit frames."""
    ref = JointRef(669, bodies.q_ref[0], bodies.q_ref[1], joints.edges[0])
    size = 0.0
    for s in ("q", "q_prev", "q_ref"):
        F = ref.frames(getattr(bodies, s)[0], getattr(bodies, s)[1])
        n = [float(sum(v * v for v in F[k]) ** 0.5) for k in range(4)]
        size = max(size, (n[0] + n[2]) * (n[1] + n[3]))
    return size


CASES = [((body, state), k) for body in (0, 1) for state in STATES for k in SCALES]


@pytest.mark.parametrize("where,k", CASES, ids=[f"body{b}-{s}-{k:g}" for (b, s), k in CASES])
def test_revolute_angle_is_scale_invariant(where: tuple[int, str], k: float) -> None:
    """One body's A in one state scaled by k: the same angle as unscaled (and the reference's), or a 422 naming the joint and state."""
    seed = 100 + CASES.index((where, k)) % 7
    plain, joints = _scaled_scene(670, seed, {})
    bodies, _ = _scaled_scene(670, seed, {where: k})
    x = _answer(bodies, joints)
    if isinstance(x, InputError):  # no scale here makes a frame collapse: a refusal would be a bug
        pytest.fail(f"refused a well-posed scaled frame: {x}")
    x0 = _answer(plain, joints)
    assert abs(x - x0) <= TOL * max(abs(x0), 1e-3)
    assert abs(x - _reference_x(bodies, joints)) <= TOL * max(abs(x0), 1e-3)


@pytest.mark.parametrize("seed", range(6))
def test_revolute_every_state_scaled_at_once(seed: int) -> None:
    """Both bodies, all three states, independent scales from 1e-300 to 1e300: the unscaled angle."""
    rng = np.random.default_rng(seed)
    for _ in range(6):
        scale = {(b, s): 10.0 ** rng.integers(-300, 301) for b in (0, 1) for s in STATES}
        plain, joints = _scaled_scene(670, seed, {})
        bodies, _ = _scaled_scene(670, seed, scale)
        x, x0 = _answer(bodies, joints), _answer(plain, joints)
        assert not isinstance(x, InputError), x
        assert abs(x - x0) <= TOL * max(abs(x0), 1e-3)
        assert abs(x - _reference_x(bodies, joints)) <= TOL * max(abs(x0), 1e-3)


@pytest.mark.parametrize("where,k", CASES, ids=[f"body{b}-{s}-{k:g}" for (b, s), k in CASES])
def test_prismatic_slide_at_every_scale(where: tuple[int, str], k: float) -> None:
    """One body's A in one state scaled by k: the reference slide, or a 422 naming the joint.

    The slide is `(C_j - C_i) . (T_i + T_j) / 2` between two states, with anchors `C = p + A c`:
    float64 rounds each anchor to ~1e-16 of its size, so the error bound is relative to the
    frames' size `(|C_i| + |C_j|)(|T_i| + |T_j|)` (as large as |x| when A is not scaled, 1e300
    times larger when an anchor is scaled up by 1e300 against an unscaled axis); the test holds
    the core to 1e-12 of that, and of |x|, whichever is larger.
    """
    seed = 200 + CASES.index((where, k)) % 7
    bodies, joints = _scaled_scene(669, seed, {where: k})
    x = _answer(bodies, joints)
    if isinstance(x, InputError):  # the slide itself overflows float64 (e.g. anchors 1e300 x axes 1e300)
        _assert_refused(x)
        assert "overflow" in str(x)
        return
    want = _reference_x(bodies, joints)
    assert abs(x - want) <= TOL * max(abs(want), _frame_size(bodies, joints) * 1e-3)


@pytest.mark.parametrize("uid", [669, 670])
@pytest.mark.parametrize("length", [1e-300, 1e-200, 1e-161, 1e-158, 1e-100, 1e-12, 1e12, 1e100, 1e200, 1e300])
def test_edge_length_changes_nothing(uid: int, length: float) -> None:
    """The axis is the edge's direction: any length from 1e-300 to 1e300 gives the unit-edge answer."""
    for seed in range(3):
        bodies, joints = _scaled_scene(uid, 300 + seed, {}, length=length)
        unit_bodies, unit_joints = _scaled_scene(uid, 300 + seed, {}, length=1.0)
        x, x1 = _answer(bodies, joints), _answer(unit_bodies, unit_joints)
        assert not isinstance(x, InputError), x
        want = _reference_x(bodies, joints)
        size = _frame_size(bodies, joints) * 1e-3 if uid == 669 else 0.0  # see test_prismatic_slide_at_every_scale
        assert abs(x - want) <= TOL * max(abs(want), size, 1e-3)
        if uid == 670:  # the angle does not depend on where the axis passes: the unit edge's angle
            assert abs(x - x1) <= TOL * max(abs(x1), 1e-3)


# ---------------------------------------------------------------- derivatives of scaled frames


def _egh(bodies: Bodies, joints: Joints) -> tuple[float, np.ndarray, np.ndarray]:
    b = evaluate(bodies, [joints], outputs=("energy", "gradient", "hessian")).batches[0]
    return float(b.energy[0]), b.gradient[0], b.hessian[0]


@pytest.mark.parametrize("uid", [669, 670])
@pytest.mark.parametrize("k", [1e-12, 1e12])
def test_derivatives_of_scaled_frames_match_finite_differences(uid: int, k: float) -> None:
    """Both bodies' A scaled by k at q (well posed, x outside its range): gradient and Hessian finite,
    equal to the 50-digit reference, and to central differences of the core's own energy and gradient.

    The revolute derivatives scale like 1/k (the Hessian like 1/k^2): 1e12 and 1e24 here. The
    differences step each DOF by h = 1e-5 of its own size: truncation ~h^2 ~ 1e-10 and rounding
    ~eps E / h ~ 1e-11, both relative to the derivatives' norm, so 1e-9 is the tolerance they can
    meet (measured 1.3e-10 at worst; against the reference 5.5e-16). A formula that lost a factor
    k, or divided by an r^2 that underflowed, is off by 100%.
    """
    bodies, joints = _scaled_scene(uid, 400, {(0, "q"): k, (1, "q"): k}, anchored=True)
    x = _answer(bodies, joints)
    lower, upper = x - 2 * abs(x), x - 0.5 * abs(x)  # x past upper by half its size: well conditioned
    joints = Joints(joints.constitution_uid, joints.base_uid, joints.body_ids, joints.edges, np.array([lower]), np.array([upper]), np.array([1.0]))
    E, g, H = _egh(bodies, joints)
    assert E > 0 and np.isfinite(g).all() and np.isfinite(H).all()
    ref = JointRef(uid, bodies.q_ref[0], bodies.q_ref[1], joints.edges[0])
    want = ref.evaluate(*((getattr(bodies, s)[0], getattr(bodies, s)[1]) for s in ("q", "q_prev", "q_ref")), lower, upper, 1.0).as_float()
    assert relerr(g, want["gradient"]) <= 1e-12
    assert relerr(H, want["hessian_exact"]) <= 1e-12
    q = bodies.q.reshape(-1)
    fd_g, fd_H = np.empty(24), np.empty((24, 24))
    for d in range(24):
        h = 1e-5 * max(abs(q[d]), k if d % 12 >= 3 else 1.0)
        plus, minus = q.copy(), q.copy()
        plus[d] += h
        minus[d] -= h
        Ep, gp, _ = _egh(Bodies(plus.reshape(2, 12), bodies.q_prev, bodies.q_ref), joints)
        Em, gm, _ = _egh(Bodies(minus.reshape(2, 12), bodies.q_prev, bodies.q_ref), joints)
        fd_g[d] = (Ep - Em) / (2 * h)
        fd_H[:, d] = (gp - gm) / (2 * h)
    assert relerr(g, fd_g) <= 1e-9
    assert relerr(H, fd_H) <= 1e-9


def test_revolute_derivatives_of_tiny_and_huge_frames_are_finite_or_refused() -> None:
    """Frames at 1e-150 (r^2 subnormal) and 1e150 (r^4 infinite): the derivatives by scaling, or an overflow 422."""
    for k in (1e-150, 1e-100, 1e100, 1e150, 1e300):
        bodies = _revolute_probe({"q": k * TURN}, {"q": k * np.eye(3)})
        joints = _joint(670, Z_EDGE)
        try:
            ev = evaluate(bodies, [joints], outputs=("energy", "gradient", "hessian"))
        except InputError as err:
            _assert_refused(err)
            assert "overflow" in str(err)
            continue
        b = ev.batches[0]
        ref = JointRef(670, bodies.q_ref[0], bodies.q_ref[1], joints.edges[0])
        want = ref.evaluate(*((getattr(bodies, s)[0], getattr(bodies, s)[1]) for s in ("q", "q_prev", "q_ref")), -0.1, 0.1, 1.0).as_float()
        assert abs(b.x[0] - 0.7) <= TOL
        assert relerr(b.gradient[0], want["gradient"]) <= 1e-12
        assert relerr(b.hessian[0], want["hessian_exact"]) <= 1e-12


# ---------------------------------------------------------------- near a collapse: as exact as its conditioning, then refused


@pytest.mark.parametrize("eps", [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 0.0])
def test_nearly_flipped_frame_is_as_exact_as_its_conditioning_or_refused(eps: float) -> None:
    """Body j turned by pi - eps about an in-plane axis: (cos, sin) ~ eps^2 / 4 against frame vectors of size 1.

    Above `COLLAPSE_RATIO` (eps >~ 3e-6) the angle is answered to within a few roundings of the
    frames over hypot(cos, sin) (the angle's own condition number: x is decided by digits of F
    that float64 only keeps to ~1e-16); below it, or exactly flipped, a 422 naming the joint and q.
    """
    rng = np.random.default_rng(int(eps * 1e9) + 5)
    for _ in range(4):
        a = rng.uniform(0, 2 * np.pi)
        R = rotation_about(np.array([np.cos(a), np.sin(a), 0.0]), np.pi - eps) @ rotation_about(E_Z, rng.uniform(-1, 1))
        bodies = _revolute_probe({"q": R, "q_prev": R})
        x = _answer(bodies, _joint(670, Z_EDGE))
        r = eps * eps / 4  # hypot(cos, sin) to first order; the frame vectors have size ~1
        if r <= 1e-12 * 4:  # the threshold, with a margin of 4 for the first-order r and the size's sqrt(2)s
            if r < 1e-12 / 4:
                assert isinstance(x, InputError)
            if isinstance(x, InputError):  # at q_prev and q (the same A), one fault each
                _assert_refused(x)
                assert [next(s for s in STATES if f"at {s} " in f.msg) for f in x.faults] == ["q_prev", "q"], x
            continue
        assert not isinstance(x, InputError), x
        assert abs(x - _reference_x(bodies, _joint(670, Z_EDGE))) <= 8 * 2.2e-16 / r


# ---------------------------------------------------------------- the probes over HTTP


def test_issue_probes_over_http(live) -> None:  # noqa: F811
    """The issue's scaled frame answers 200 with x = 0.7; A = 0 a 422 whose loc names the joint, in both encodings."""
    from jointlimits.client import Client, InvalidInput, Scene

    def request(A_q: np.ndarray):
        scene = Scene()
        a = scene.add_body((np.zeros(3), np.eye(3)))
        b = scene.add_body((np.array([1.0, 0, 0]), A_q), ref=(np.array([1.0, 0, 0]), np.eye(3)))
        scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.1, upper=0.1, strength=1.0)
        return scene.request()

    for binary in (False, True):
        with Client(live, binary=binary) as c:
            for k in (1e-12, 3e-17, 1e-100):
                ev = c.evaluate(request(k * TURN))
                assert abs(ev.batches[0].x[0] - 0.7) <= TOL and abs(ev.batches[0].energy[0] - 27.0) <= 1e-12 * 27
            with pytest.raises(InvalidInput) as err:
                c.evaluate(request(np.zeros((3, 3))))
            assert err.value.status == 422
            assert [f.loc for f in err.value.faults] == [("body", "batches", 0, "body_ids", 0)]
            assert "collapses at q " in err.value.msg


# ---------------------------------------------------------------- the anchors' solve at extreme A_ref


@pytest.mark.parametrize("k", [1e-300, 1e-160, 1e-100, 1.0, 1e100, 1e160, 1e300])
def test_solve3_at_every_scale(k: float) -> None:
    """`A^-1 b` by cofactors with det ~ k^3 (under- or overflowing for |k| beyond 1e+-103): scaled, to ~1e-15."""
    from jointlimits.service.core.kinematics import solve3

    rng = np.random.default_rng(9)
    A = k * np.array([random_rotation(rng) @ np.diag(rng.uniform(0.5, 2.0, 3)) for _ in range(8)])
    b = rng.normal(size=(8, 3)) * np.array([1.0, 1e-300, 1e300])[rng.integers(0, 3, 8), None]
    with np.errstate(all="ignore"):  # as the core's public entry points call it (one errstate per call)
        x = solve3(A, b)
    with np.errstate(over="ignore"):
        want = np.stack([np.linalg.solve(A[n] / k, b[n]) / k for n in range(8)])
    finite = np.isfinite(want).all(axis=1)  # b = 1e300 over k = 1e-100: the anchor itself overflows
    assert np.isfinite(x[finite]).all()
    for n in np.flatnonzero(finite):
        assert relerr(x[n], want[n]) <= 1e-14


# ---------------------------------------------------------------- careful and common joints side by side


@pytest.mark.parametrize("uid", [669, 670])
def test_careful_joints_in_a_large_batch_answer_as_alone(uid: int) -> None:
    """Joints at extreme scales mixed with ordinary ones in one batch: each row is bitwise what the
    joint answers alone (the careful rows are found, recomputed and put back in their places)."""
    rng = np.random.default_rng(uid)
    scenes: list[tuple[Bodies, Joints]] = []
    for n in range(100):
        scale = {} if n % 3 else {(int(rng.integers(2)), STATES[int(rng.integers(3))]): 10.0 ** rng.integers(-300, 301)}
        scene = _scaled_scene(uid, 500 + n, scale)
        if not isinstance(_answer(*scene), InputError):  # a prismatic slide may overflow: not this test's point
            scenes.append(scene)
    scenes = scenes[:24]
    cat = lambda name: np.concatenate([getattr(b, name) for b, _ in scenes])  # noqa: E731
    bodies = Bodies(cat("q"), cat("q_prev"), cat("q_ref"))
    with np.errstate(all="ignore"):  # as `evaluate` builds it
        plain = BodyTable(bodies).plain
    assert 0 < plain.sum() < plain.shape[0]  # both paths in the batch
    ids = np.arange(2 * len(scenes)).reshape(-1, 2)
    xs = [_answer(b, j) for b, j in scenes]
    lower = np.array([x - 1.0 for x in xs])  # every joint active: derivatives for all rows
    joints = Joints(uid, {670: 18, 669: 20}[uid], ids, np.concatenate([j.edges for _, j in scenes]), lower - 1.0, lower, np.ones(len(scenes)))
    ev = evaluate(bodies, [joints], outputs=("energy", "gradient"))
    two = evaluate(bodies, [joints, joints], outputs=("energy", "gradient"), threads=2)  # batches side by side
    for r in two.batches:
        np.testing.assert_array_equal(r.x, ev.batches[0].x)
        np.testing.assert_array_equal(r.gradient, ev.batches[0].gradient)
    for n, (b, j) in enumerate(scenes):
        one = evaluate(b, [Joints(uid, j.base_uid, j.body_ids, j.edges, lower[n : n + 1] - 1.0, lower[n : n + 1], np.ones(1))], outputs=("energy", "gradient"))
        assert ev.batches[0].x[n] == one.batches[0].x[0] == xs[n]
        np.testing.assert_array_equal(ev.batches[0].gradient[n], one.batches[0].gradient[0])


def test_frames_prepared_on_threads_name_the_same_collapsed_joints_in_batch_order() -> None:
    """Each batch's frames are prepared on the core's threads: a frame collapsed at q_prev in batches 0
    and 2 (batch 1 is fine) is refused with the same faults on 1, 2 and 3 threads: a prepared scene
    names both in batch order, the stateless call the first batch's (it stops at the first batch)."""
    import dataclasses

    from jointlimits.service.core import prepare

    bodies = _revolute_probe({"q_prev": np.zeros((3, 3))})
    fine = Bodies(bodies.q, bodies.q_ref, bodies.q_ref)  # the same joint without the collapse
    rows = np.concatenate([bodies.q_prev, fine.q_prev])  # bodies 0, 1 collapse at q_prev; 2, 3 do not
    scene = Bodies(np.concatenate([bodies.q, fine.q]), rows, np.concatenate([bodies.q_ref, fine.q_ref]))
    joint = _joint(670, Z_EDGE)
    batches = [joint, dataclasses.replace(joint, body_ids=np.array([[2, 3]])), joint]
    faults = []
    for threads in (1, 2, 3):
        for call in (lambda: evaluate(scene, batches, threads=threads), lambda: prepare(scene, batches, threads=threads)):  # noqa: B023
            with pytest.raises(InputError) as err:
                call()
            faults.append([(f.loc, f.msg) for f in err.value.faults])
    assert [loc[:2] for loc, _ in faults[0]] == [("batches", 0)]
    assert [loc[:2] for loc, _ in faults[1]] == [("batches", 0), ("batches", 2)]
    assert all("at q_prev " in msg for _, msg in faults[1])
    assert all(f == faults[0] for f in faults[::2]) and all(f == faults[1] for f in faults[1::2])
