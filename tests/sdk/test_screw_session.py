"""Issue 10 item 6, the session half: a screw joint driven three turns through a session (in-process and over
WebSocket, JSON and msgpack), a commit per step, a limit at 2.5 turns plus an offset; then a damped Newton solve
on the session. The stateless half (Local, HTTP with client-kept `prev_coordinate`) is tests/sdk/test_screw.py."""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.client import Client, JointBatch, LocalClient, request_from_arrays
from tests.http.test_contract_live import serve

STEP = 0.4
TURNS = 3.0
OFFSET = 0.3  # the reported coordinate is the physical angle + OFFSET (the spec's init_angle)
UPPER = 2.5 * 2 * np.pi + OFFSET  # the limit at 2.5 turns of the physical angle, in the reported frame
LOWER = -1.0
STRENGTH = 50.0


def pose(angle: float) -> np.ndarray:
    """12 DOFs of a body turned by `angle` about +z (the screw axis), at the origin."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([0, 0, 0, c, -s, 0, s, c, 0, 0, 0, 1.0])


def request():
    q0 = np.array([pose(0.0), pose(0.0)])
    batch = JointBatch.of(670, [[0, 1]], [[[0, 0, 0], [0, 0, 1]]], LOWER, UPPER, STRENGTH, offset=OFFSET)
    return request_from_arrays(q0, [batch], q_prev=q0, q_ref=q0)


@pytest.fixture(scope="module")
def live():
    with serve() as url:
        yield url


def drive(session, steps: int, start: int = 0) -> list[tuple[float, float, float, float]]:
    """(true angle, coordinate at q, energy at q, committed coordinate) per step of STEP rad, after `start` steps."""
    rows = []
    for k in range(start + 1, start + steps + 1):
        q = np.array([pose(0.0), pose(STEP * k)])
        ev = session.evaluate(q, outputs=("energy",))
        b = ev.batches[0]
        committed = session.commit(q)[0][0]
        rows.append((STEP * k, float(b.coordinate[0]), float(b.energy[0]), float(committed)))
    return rows


@pytest.mark.parametrize("mode", ["local", "msgpack", "json"])
def test_screw_three_turns_follows_the_true_angle(live, mode):
    steps = int(np.ceil(TURNS * 2 * np.pi / STEP))  # 48 steps: 19.2 rad > 3 turns
    client = LocalClient() if mode == "local" else Client(live, binary=mode == "msgpack")
    with client.session(request()) as s:
        assert s.coordinates[0][0] == OFFSET  # opened at the built pose: the coordinate is the offset
        rows = drive(s, steps)
    for angle, coordinate, energy, committed in rows:
        # The angle is accumulated exactly (each step's DeltaTheta and the commit's rem are exact to rounding):
        # 1e-11 over 19 rad, the bound.
        assert abs(coordinate - (angle + OFFSET)) < 1e-11, (angle, coordinate)
        assert abs(committed - (angle + OFFSET)) < 1e-11
        past = angle + OFFSET - UPPER
        if past <= -1e-9:
            assert energy == 0.0, angle
        elif past >= 1e-9:
            # Cubic penalty past the upper bound, relative to the width u - l.
            want = STRENGTH * (past / (UPPER - LOWER)) ** 3
            assert energy > 0 and abs(energy - want) <= 1e-9 * want, (angle, energy, want)
    assert rows[-1][0] > TURNS * 2 * np.pi


def test_screw_the_same_numbers_locally_and_over_the_wire(live):
    """A session in-process and over WebSocket run the same code: bitwise the same coordinates and energies."""
    steps = 44
    with LocalClient().session(request()) as a, Client(live).session(request()) as b, \
            Client(live, binary=False).session(request()) as c:  # fmt: skip
        ra, rb, rc = drive(a, steps), drive(b, steps), drive(c, steps)
    assert ra == rb == rc


def test_damped_newton_on_the_session_decreases_the_objective(live):
    """`E(q) + 1/2 |q_1 - q_target|^2` over body 1's DOFs (body 0 fixed), psd Hessian, backtracking: monotone."""
    with Client(live).session(request()) as s:
        drive(s, 38)  # 15.2 rad: just below the limit at 2.5 turns (15.71 rad)
        target = pose(2.5 * 2 * np.pi + 0.6)  # 0.6 rad past the limit: the penalty pushes back
        q = np.array(s.q_prev)

        def objective(q_try):
            ev = s.evaluate(q_try, outputs=("energy", "gradient", "hessian"), hessian_mode="psd")
            b = ev.batches[0]
            d = q_try[1] - target
            return ev.total_energy + 0.5 * d @ d, b.gradient[0][12:] + d, b.hessian[0][12:, 12:] + np.eye(12), ev

        f, g, H, ev = objective(q)
        history, gnorms = [f], [np.linalg.norm(g)]
        while gnorms[-1] > 1e-9 and len(history) < 12:
            step = -np.linalg.solve(H, g)
            t = 1.0
            while True:
                trial = q.copy()
                trial[1] = q[1] + t * step
                f_new, g_new, H_new, ev = objective(trial)
                if f_new < f or t < 1e-8:
                    break
                t /= 2
            assert f_new < f, (f_new, f)
            q, f, g, H = trial, f_new, g_new, H_new
            history.append(f)
            gnorms.append(np.linalg.norm(g))
        assert len(history) >= 3 and all(b < a for a, b in zip(history, history[1:])), history
        assert gnorms[-1] <= 1e-9, gnorms  # converges (the psd Hessian drops curvature: not quadratically)
        assert ev.total_energy > 0  # the solution sits past the limit, held back by the penalty
        # The coordinate at the solution is between the limit and the target, in the multi-turn frame.
        coord = ev.batches[0].coordinate[0]
        assert UPPER < coord < 2.5 * 2 * np.pi + 0.6 + OFFSET


def test_reopening_mid_screw_keeps_the_turns(live):
    """A session dropped after 2 turns and reopened from what the client kept: the same numbers, bit for bit, as
    the session never dropped (the state travels as prev_coordinate = r + offset, and every scene takes its angle
    as coordinate - offset, the uninterrupted one too)."""
    with Client(live).session(request()) as s, LocalClient().session(request()) as ref:
        drive(s, 32)
        drive(ref, 32)
        s._ws.close()  # the connection ends under the session
        s.reopen()
        rows, want = drive(s, 10, 32), drive(ref, 10, 32)
    assert np.array(rows).tobytes() == np.array(want).tobytes()
    for angle, c, _, _ in rows:
        assert abs(c - (angle + OFFSET)) < 1e-11


@pytest.mark.parametrize("mode", ["local", "msgpack", "json"])
def test_an_offset_update_moves_the_committed_coordinate_and_survives_a_reopen(live, mode):
    client = LocalClient() if mode == "local" else Client(live, binary=mode == "msgpack")
    with client.session(request()) as s:
        drive(s, 20)  # 8 rad
        s.update(0, [0], offset=[1.0])
        assert abs(s.coordinates[0][0] - (8.0 + 1.0)) < 1e-11  # same physical angle, new offset
        s.reopen()
        (angle, coordinate, _, committed), = drive(s, 1, 20)
        assert abs(coordinate - (angle + 1.0)) < 1e-11 and abs(committed - (angle + 1.0)) < 1e-11
