"""Scales varied jointly (the scale-sweep audit): the combinations that broke, each at its simplest, then a seeded sweep.

The offset far from the bounds and from the committed coordinate. The contract's penalty bounds the coordinate:
`l = lower - offset`, `u = upper - offset` on `x`, so the gap `x - u` is `coordinate - upper` and the width `u - l`
is `upper - lower` whatever the offset. Formed on `x` in float64 they were not: with `|offset|` far above the
width, `lower - offset` and `upper - offset` round to within ulps of `offset` of each other (a range of 10 read as
degenerate under an offset of 1e17, 1000x the energy); with a `prev_coordinate`, `x = (prev_coordinate - offset) +
DeltaTheta(q, q_prev)` rounds `prev_coordinate` to ulps of `offset`, and `coordinate = x + offset` answered 0 for
0.8. Neither depends on the offset mathematically (perturbing it moves neither the gap, the width nor the
coordinate), so both were silent wrong numbers of well-conditioned answers. Each case is checked against the
50-digit reference (`bench/reference.py`), which takes the contract's `lower - offset` exactly.

A small penalty curvature on frames far from 1: the chain rule splits the Hessian into factors of E', E'' and of
the frames, and such a factor under- or overflowed where the Hessian is a normal number (`evaluate._near_one`).
"""

from __future__ import annotations

import numpy as np
import pytest
from mpmath import mp, mpf

from jointlimits.service.core import Bodies, Joints, evaluate, prepare
from bench.reference import JointRef
from tests.conftest import relerr
from tests.scenes import pack, rotation_about

E_Z = np.array([0.0, 0.0, 1.0])
EDGE = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])


def _hinge(turn_prev: float, turn: float) -> Bodies:
    """Body i fixed at the identity, body j turned about +z by `turn_prev` at q_prev and `turn` at q (q_ref: 0)."""
    rows = lambda a: np.array([pack(np.zeros(3), np.eye(3)), pack([1.0, 0, 0], rotation_about(E_Z, a))])  # noqa: E731
    return Bodies(rows(turn), rows(turn_prev), rows(0.0))


def _joints(lower: float, upper: float, offset: float, prev: float | None = None, strength: float = 1.0) -> Joints:
    return Joints(670, 18, np.array([[0, 1]]), EDGE, np.array([lower]), np.array([upper]), np.array([strength]),
                  np.array([offset]), None if prev is None else np.array([prev]))


def _reference(bodies: Bodies, j: Joints) -> dict:
    ref = JointRef(670, bodies.q_ref[0], bodies.q_ref[1], EDGE[0])
    states = [(getattr(bodies, s)[0], getattr(bodies, s)[1]) for s in ("q", "q_prev", "q_ref")]
    prev = None if j.prev_coordinate is None else j.prev_coordinate[0]
    return ref.evaluate(*states, j.lower[0], j.upper[0], j.strength[0], True, j.offset[0], prev, hessians=False).as_float()


def _close(got: float, want: float, rtol: float) -> bool:
    return abs(got - want) <= rtol * abs(want)


# (bodies, joints): each a well-conditioned answer that a float64 penalty on x lost. The bounds: the coordinate is
# prev_coordinate + DeltaTheta or x + offset, rounded once (u |coordinate|); the gap `coordinate - upper` then rounds
# by u |upper| more, its relative error (|coordinate| + |upper|) u / g <= 4u here, the energy's 3x that, the
# gradient's 2x (E' = 3 s g^2 / w^3, J^T dx exact for a pure hinge up to u); 1e-14 is ~20x the largest.
CASES = {
    # Width: [-5, 5] under an offset of 1e17, x = 0.7; lower - offset == upper - offset in float64 (degenerate: w = 1).
    "width_under_a_far_offset": (_hinge(0.0, 0.7), _joints(-5.0, 5.0, 1e17)),
    # A nanometre-wide range 1e6 from the offset: w from `(1e-9 - 1e6) - (0 - 1e6)` is off by an ulp of 1e6 (12%).
    "narrow_range_under_an_offset_of_1e6": (_hinge(0.0, 0.7), _joints(0.0, 1e-9, 1e6)),
    # prev_coordinate 0.5 under an offset of 1e17, turned 0.3 since q_prev: coordinate 0.8 (answered 0), E > 0 (0).
    "committed_coordinate_under_a_far_offset": (_hinge(0.0, 0.3), _joints(-1.0, 0.6, 1e17, prev=0.5)),
    # The same with the offset 1e6 (the angle prev - offset keeps prev to an ulp of 1e6, 1.2e-10: 1e-6 of the gap).
    "committed_coordinate_under_an_offset_of_1e6": (_hinge(0.0, 0.3), _joints(-1.0, 0.6, 1e6, prev=0.5)),
}


@pytest.mark.parametrize("name", list(CASES))
def test_the_offset_moves_neither_the_gap_nor_the_width(name: str) -> None:
    bodies, joints = CASES[name]
    want = _reference(bodies, joints)
    assert want["energy"] > 0
    for path in ("stateless", "prepared"):
        if path == "stateless":
            r = evaluate(bodies, [joints], outputs=("energy", "gradient")).batches[0]
        else:
            r = prepare(bodies, [joints]).evaluate(bodies.q, outputs=("energy", "gradient")).batches[0]
        assert _close(r.coordinate[0], want["coordinate"], 1e-15), (path, r.coordinate[0], want["coordinate"])
        assert _close(r.x[0], want["x"], 1e-15), (path, r.x[0], want["x"])
        assert _close(r.energy[0], want["energy"], 1e-14), (path, r.energy[0], want["energy"])
        g = want["gradient"]
        assert np.max(np.abs(r.gradient[0] - g)) <= 1e-14 * np.max(np.abs(g)), path


def test_an_offset_whose_bounds_on_x_overflow_is_answered() -> None:
    """`lower - offset` of -1e308 - 1e308 overflows float64, and was refused (422 on `offset`), while nothing of the
    answer does: the coordinate 1e308 + 0.7 is past `upper` = 1 by 1e308 in a range 1e308 + 1 wide, E = s r^3 with
    r ~ 1 (exactly (1e308 - 0.3) / (1e308 + 1)). Answered, as the reference, by the request and by a scene's update."""
    bodies, joints = _hinge(0.0, 0.7), _joints(-1e308, 1.0, 1e308)
    want = _reference(bodies, joints)
    r = evaluate(bodies, [joints], outputs=("energy", "gradient")).batches[0]
    assert (r.coordinate[0], r.x[0]) == (want["coordinate"], want["x"])
    assert _close(r.energy[0], want["energy"], 1e-15)
    assert np.max(np.abs(r.gradient[0] - want["gradient"])) <= 1e-14 * np.max(np.abs(want["gradient"]))
    scene = prepare(bodies, [_joints(-1.0, 1.0, 0.0)])
    scene.update(0, [0], lower=[-1e308], offset=[1e308])
    assert scene.evaluate(bodies.q, outputs=("energy",)).batches[0].energy[0] == r.energy[0]


def _rule(bodies: Bodies, joints: Joints) -> float:
    """The contract's commit at q, exactly: `r + rem(theta(q) - r) + offset`, r = prev_coordinate - offset, theta(q) =
    DeltaTheta(q, q_ref) (mpmath, from the float64 inputs)."""
    ref = JointRef(670, bodies.q_ref[0], bodies.q_ref[1], EDGE[0])
    with mp.workdps(60):
        theta = ref.x(*[(getattr(bodies, s)[0], getattr(bodies, s)[1]) for s in ("q", "q_ref", "q_ref")])
        r = mpf(joints.prev_coordinate[0]) - mpf(joints.offset[0])
        y = theta - r
        return float(r + (y - 2 * mp.pi * mp.nint(y / (2 * mp.pi))) + mpf(joints.offset[0]))


def test_a_commit_keeps_the_committed_coordinate_under_a_far_offset() -> None:
    """The rule with r = 1000 - 1e89 in float64 kept nothing of the 1000: `r + rem(...)`, then `+ offset`, came back
    0.0, and `rem` of 1e89 rad (past 2^24 turns) was 1e73, not within pi. Exactly, the rule moves the committed
    coordinate by `rem(...)`, at most pi; here `rem`'s argument carries the offset's turns (1e89 rad, to ulps of 1e73:
    no digit of its remainder is determined by the float64 inputs), so every committed coordinate within pi of 1000
    is the rule's answer to inputs within their rounding; 0.0 is none of them."""
    bodies, joints = _hinge(0.0, 0.3), _joints(-1.0, 2000.0, 1e89, prev=1000.0)
    committed = prepare(bodies, [joints]).commit(bodies.q)[0][0]
    assert abs(committed - 1000.0) <= np.pi + 4 * np.spacing(1000.0), committed


@pytest.mark.parametrize("offset", [0.35, 1e6])
def test_a_commit_under_an_offset_is_the_contracts_rule(offset: float) -> None:
    """prev_coordinate 0.5, turned 0.3 since q_prev = q_ref: the rule's committed coordinate is 0.5 + rem(0.3 + offset
    - 0.5) (the offset's whole turns taken off, exactly in `rem` for |turns| < 2^24), to the rounding of `0.5 - offset`
    (an ulp of the offset, which the contract's `r` carries) and of `rem`'s argument (another)."""
    bodies, joints = _hinge(0.0, 0.3), _joints(-1.0, 0.6, offset, prev=0.5)
    committed = prepare(bodies, [joints]).commit(bodies.q)[0][0]
    assert abs(committed - _rule(bodies, joints)) <= 4 * np.spacing(max(offset, 1.0)), committed


# ---------------------------------------------------------------- the Hessian's factors, from E', E'' near 1


@pytest.mark.parametrize("mode", ["exact", "psd"])
def test_a_small_penalty_curvature_on_frames_far_from_one_keeps_its_hessian(mode: str) -> None:
    """Body i's A at 1e-65, body j's at 1e133 (the hinge's angle does not see scales), 0.4 above a range 1e80 wide:
    E'' = 2.4e-240 and the Hessian's body-i block E'' (dx/dA_i)^2 ~ 1e-110, both normal numbers. The chain rule's
    factors split them as E'' times coefficients of 1/r^2 ~ 1e-136 (r = cos^2 + sin^2 ~ 1e68): 1e-376, zero in
    float64, and the Hessian was answered 0. E', E'' are taken times a power of two near 1 and the derivatives
    scaled back (`evaluate._near_one`). Bound: E'' rounds by 2u of the gap, the hinge's frames by a few u: 1e-14."""
    bodies = _hinge(0.0, 0.5)
    scale = np.r_[np.ones(3), np.full(9, 1e-65)], np.r_[np.ones(3), np.full(9, 1e133)]
    bodies = Bodies(*(np.array([state[0] * scale[0], state[1] * scale[1]]) for state in (bodies.q, bodies.q_prev, bodies.q_ref)))
    joints = Joints(670, 18, np.array([[0, 1]]), EDGE, np.array([0.1 - 1e80]), np.array([0.1]), np.array([1.0]))
    ref = JointRef(670, bodies.q_ref[0], bodies.q_ref[1], EDGE[0])
    states = [(getattr(bodies, s)[0], getattr(bodies, s)[1]) for s in ("q", "q_prev", "q_ref")]
    want = ref.evaluate(*states, 0.1 - 1e80, 0.1, 1.0).as_float()["hessian_" + mode]
    got = evaluate(bodies, [joints], hessian_mode=mode).batches[0].hessian[0]
    assert np.max(np.abs(want)) > 1e-120 and relerr(got, want) <= 1e-14, (np.max(np.abs(got)), np.max(np.abs(want)))
