"""A solver-shaped test (issue 10, item 6): a screw joint driven three full turns, then a Newton solve at its limit.

A revolute joint about +z between a fixed body 0 and body 1, upper limit at 2.5 turns plus an
offset. Body 1 turns in 0.4 rad steps with a commit per step: in-process through
`PreparedScene.commit`, and through `LocalClient` and HTTP (JSON and msgpack) as a solver that
keeps its own state does it (the answer's `coordinate` at the accepted `q` is the next step's
`prev_coordinate`, `q_prev` := that `q`). Then a damped Newton iteration with the PSD Hessian
on `E(q) + 1/2 |q - q_target|^2` pulls the screw past its limit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np
import pytest

from jointlimits.client import Client, JointBatch, LocalClient, Request
from jointlimits.service.core import Bodies, Joints, prepare
from tests.scenes import pack, rotation_about
from tests.http.test_contract_live import live  # noqa: F401 (fixture)

pytestmark = pytest.mark.slow  # a screw driven three turns in-process and over HTTP (~3 s)

Z = np.array([0.0, 0.0, 1.0])
EDGE = [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
OFFSET = 0.3
LOWER, UPPER = -0.5 + OFFSET, 5 * np.pi + OFFSET  # absolute bounds on the coordinate: the limit at 2.5 turns
STRENGTH = 1e4
STEP = 0.4
ANGLES = STEP * np.arange(1, int(np.ceil(6 * np.pi / STEP)) + 1)  # three full turns (and a bit)
Q_REF = np.stack([pack(np.zeros(3), np.eye(3))] * 2)


def q_at(angle: float) -> np.ndarray:
    """Both bodies (2, 12): body 0 at rest, body 1 turned by `angle` about +z."""
    return np.stack([Q_REF[0], pack(np.zeros(3), rotation_about(Z, angle))])


class Stateless:
    """A solver that keeps the joint's state itself and sends it with each stateless request."""

    def __init__(self, evaluate: Callable[[Request], object]) -> None:
        self._evaluate = evaluate
        self.q_prev, self.prev_coordinate = Q_REF, None  # v1's default to start: x from DeltaTheta(q_prev, q_ref)

    def evaluate(self, q: np.ndarray):
        batch = JointBatch.of(
            670, [[0, 1]], [EDGE], LOWER, UPPER, STRENGTH, offset=OFFSET, prev_coordinate=self.prev_coordinate
        )
        return self._evaluate(Request(q, self.q_prev, Q_REF, [batch], hessian_mode="psd"))

    def commit(self, q: np.ndarray) -> float:
        coordinate = self.evaluate(q).batches[0].coordinate
        self.q_prev, self.prev_coordinate = q, coordinate
        return float(coordinate[0])


class InProcess:
    """The core's prepared scene holds the state."""

    def __init__(self) -> None:
        joints = Joints(
            670, 18, np.array([[0, 1]]), np.array([EDGE]), np.array([LOWER]), np.array([UPPER]), np.array([STRENGTH]),
            offset=np.array([OFFSET]),
        )
        self.scene = prepare(Bodies(Q_REF, Q_REF, Q_REF), [joints])

    def evaluate(self, q: np.ndarray):
        return self.scene.evaluate(q, hessian_mode="psd")

    def commit(self, q: np.ndarray) -> float:
        return float(self.scene.commit(q)[0][0])


@pytest.fixture(params=["in-process", "local", "http-msgpack", "http-json"])
def solver(request, live) -> Iterator[object]:  # noqa: F811
    if request.param == "in-process":
        yield InProcess()
    elif request.param == "local":
        yield Stateless(LocalClient().evaluate)
    else:
        with Client(live, binary=request.param == "http-msgpack") as client:
            yield Stateless(client.evaluate)


def drive(solver) -> tuple[np.ndarray, np.ndarray]:
    """Each step: the energy at the step's q (before its commit), then the committed coordinate."""
    coords, energies = [], []
    for angle in ANGLES:
        q = q_at(angle)
        energies.append(solver.evaluate(q).total_energy)
        coords.append(solver.commit(q))
    return np.array(coords), np.array(energies)


def newton(solver, q0: np.ndarray, q_target: np.ndarray, iterations: int = 12) -> tuple[list[float], list[np.ndarray]]:
    """Damped Newton on f(q) = E(q) + |q - q_target|^2 / 2 (PSD Hessian + I, halving steps until f
    decreases); the objective after each iteration and the iterates."""

    def f_g_h(q: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        ev = solver.evaluate(q)
        r = ev.batches[0]
        g, H = q - q_target, np.eye(24)
        g = g.reshape(24).copy()
        if r.index.size and r.gradient is not None:
            g += r.gradient[0]
            H = H + r.hessian[0]
        return ev.total_energy + 0.5 * float(np.sum((q - q_target) ** 2)), g, H

    q = q0
    f, g, H = f_g_h(q)
    objective, iterates = [f], [q]
    for _ in range(iterations):
        d = -np.linalg.solve(H, g).reshape(2, 12)
        alpha = 1.0
        while True:
            f_new, g_new, H_new = f_g_h(q + alpha * d)
            if f_new < f or alpha < 1e-8:
                break
            alpha /= 2
        if not f_new < f:
            break  # converged to rounding: no decrease left to find
        q, f, g, H = q + alpha * d, f_new, g_new, H_new
        objective.append(f)
        iterates.append(q)
    return objective, iterates


def test_screw_coordinate_follows_the_accumulated_angle_and_the_limit(solver) -> None:
    coords, energies = drive(solver)
    # The reported coordinate is the true accumulated angle plus the offset, through every wrap.
    np.testing.assert_allclose(coords, ANGLES + OFFSET, rtol=0, atol=1e-11)
    assert coords[-1] > 6 * np.pi
    inside = ANGLES + OFFSET <= UPPER
    assert inside.sum() > 30 and (~inside).sum() > 3
    assert np.all(energies[inside] == 0.0)
    assert np.all(energies[~inside] > 0.0)
    assert np.all(np.diff(energies[~inside]) > 0)  # further past the limit: more energy


def test_screw_newton_at_the_limit_decreases_monotonically(solver) -> None:
    """After 2.5 turns less 0.3 rad (committed), pull body 1 to 0.5 rad past the limit."""
    for angle in STEP * np.arange(1, 40):
        if angle > 5 * np.pi - 0.3:
            break
        solver.commit(q_at(angle))
    q0 = q_at(angle - STEP)  # the last committed pose
    q_target = q_at(5 * np.pi + 0.5)
    objective, iterates = newton(solver, q0, q_target)
    assert len(objective) >= 4
    assert np.all(np.diff(objective) < 0)
    final = solver.evaluate(iterates[-1])
    # The penalty holds the screw between its limit and the target.
    assert UPPER < final.batches[0].coordinate[0] < 5 * np.pi + 0.5 + OFFSET
    assert final.total_energy > 0


def test_screw_same_numbers_in_process_local_and_http(live) -> None:  # noqa: F811
    """The four paths' coordinates, energies and Newton iterates agree (Local and HTTP bit for bit)."""
    runs = {}
    with Client(live) as binary, Client(live, binary=False) as as_json:
        for name, make in {
            "in-process": InProcess,
            "local": lambda: Stateless(LocalClient().evaluate),
            "http-msgpack": lambda: Stateless(binary.evaluate),
            "http-json": lambda: Stateless(as_json.evaluate),
        }.items():
            s = make()
            coords, energies = drive(s)
            objective, iterates = newton(s, q_at(ANGLES[-1]), q_at(ANGLES[-1] + 0.3), iterations=5)
            runs[name] = (coords, energies, np.array(objective), np.array(iterates))
    for name in ("http-msgpack", "http-json"):
        for a, b in zip(runs[name], runs["local"]):
            np.testing.assert_array_equal(a, b)
    for a, b in zip(runs["in-process"], runs["local"]):
        # The commit's rem rule and the client's prev_coordinate round differently: a few ulps of ~19 rad.
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13)
