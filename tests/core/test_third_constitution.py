"""A third joint type, declared in this one file and registered, is served end to end with no other file changed:
the core, validation (in the service's words), discovery and OpenAPI, HTTP in JSON and msgpack, sessions, the SDK's
`Scene`, `LocalClient` and `Client` over a live server. Then unregistered, it is refused again.

The toy (UID 9001 on a made-up base joint 9000) is edge-based, as #669: anchors `C_k = p_k + A_k c_k` on both
bodies and body i's axis `T_i = A_i t_i`, with `D = C_j - C_i`,

    value(F) = D . T_i + |D|^2 / 2,   x = value(q) - value(q_ref)   (origin "absolute": value(q)),

the slide of body j's anchor along body i's axis plus half the squared distance between the anchors. In
F = [C_i, T_i, C_j, T_j] its derivatives are, by hand, dx/dC_i = -(T_i + D), dx/dT_i = D, dx/dC_j = T_i + D,
dx/dT_j = 0, and d2x/dF2 = kron(K, I_3) with the constant K below. x is checked against that formula written
on the bodies' DOFs, its energy's gradient and Hessian against central differences.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import httpx
import numpy as np
import pytest

from jointlimits.client import Client, InvalidInput, LocalClient, Scene
from jointlimits.service import core
from jointlimits.service.app import create_app
from jointlimits.service.core.constitution import Array, Curvature, Facts, Progress
from jointlimits.service.core.kinematics import CarefulFrames, dot, frame_quantities
from jointlimits.service.core.registry import CONSTITUTIONS, register, unregister
from tests.http.test_contract_live import serve

UID, BASE = 9001, 9000
NAME = "ToyAnchorSlideLimit"

# d2 value / dF2 = kron(K, I_3) in the blocks [C_i, T_i, C_j, T_j]: d2/dC_i2 = d2/dC_j2 = 1, d2/dC_i dC_j = -1,
# d2/dC_i dT_i = -1, d2/dC_j dT_i = +1; T_j does not enter.
K = np.array([[1.0, -1.0, -1.0, 0.0], [-1.0, 0.0, 1.0, 0.0], [-1.0, 1.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0]])


def _value(F: Array) -> Array:
    D = F[:, 2] - F[:, 0]
    return dot(D, F[:, 1]) + 0.5 * dot(D, D)


class ToySlide:
    facts = Facts(
        uid=UID, base_uid=BASE, name=NAME, base_name="ToyAnchorJoint", kind="toy slide",
        unit="length unit of the DOFs", coordinate="slide of body j's anchor along body i's axis, plus half the "
        "squared distance of the anchors", origin='"q_ref": x = 0 at q_ref; "absolute": x = value(q)',
        offset_name="init_slide", state_name="slide", alpha=np.array([1.0, 0.0, 1.0, 0.0]),
        telescopes=True, axis_by_rotation=False, unit_frames=False,
    )

    def local_vectors(self, t: Array, anchors: Array | None, R_ref: Array) -> Array:
        # t_k = R_k^T t (the frames of R^T with every v_k = t), then the anchors in place of the points
        v = frame_quantities(None, R_ref.transpose(0, 1, 3, 2), self.facts.alpha,
                             np.broadcast_to(t[:, None], (t.shape[0], 4, 3)))
        v[:, 0::2] = anchors
        return v

    def value(self, F: Array) -> Array:
        return _value(F)

    def begin(self, F: Array) -> Progress:
        return Progress(None, (F,), [None])

    def advance(self, progress: Progress, F: Array, dF: Array) -> Progress:
        # value(F + dF) - value(F) in increment form: D2 . dT + dD . T + (D2 + D) . dD / 2
        D, T, dD, dT = F[:, 2] - F[:, 0], F[:, 1], dF[:, 2] - dF[:, 0], dF[:, 1]
        x = dot(D + dD, dT) + dot(dD, T) + 0.5 * dot(D + D + dD, dD)
        return Progress(x if progress.x is None else progress.x + x, (), [*progress.known, None])

    def careful_coordinate(self, careful: CarefulFrames) -> Array:
        return _value(careful.unscaled(1)) - _value(careful.unscaled(0))

    def collapsed(self, F: Array, known: object = None, size_bound: Array | None = None) -> np.ndarray:
        return np.zeros(F.shape[0], dtype=bool)

    def derivatives(self, F: Array, second: bool) -> tuple[Array, Curvature | None]:
        n, D, T = F.shape[0], F[:, 2] - F[:, 0], F[:, 1]
        dx = np.zeros_like(F)
        dx[:, 0], dx[:, 1], dx[:, 2] = -(T + D), D, T + D
        if not second:
            return dx, None
        return dx, Curvature(kron=np.broadcast_to(K, (n, 4, 4)), basis=dx[:, None], coef=np.zeros((n, 1, 1)),
                             dx_coef=np.ones((n, 1)))

    def projected_curvature(self, dE: Array, curvature: Curvature) -> None:
        return None  # the eigensolver's projection


@contextmanager
def registered() -> Iterator[None]:
    register(ToySlide())
    try:
        yield
    finally:
        unregister(UID)


@pytest.fixture
def toy() -> Iterator[None]:
    with registered():
        yield


def rotation(axis, angle: float) -> np.ndarray:
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    W = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * W + (1 - np.cos(angle)) * W @ W


def pose(p, R) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


P0, P1 = np.array([0.3, -0.2, 0.5]), np.array([0.9, 0.4, 0.1])  # the edge at ref, world


def scene(lower: float = -0.1, upper: float = 0.1, offset: float = 0.0, origin: str = "q_ref") -> Scene:
    """Two bodies, each rotated and moved from its ref pose (rotations at ref too: A_ref_k = R_ref_k)."""
    s = Scene()
    s.add_body(pose([0.1, 0.0, -0.2], rotation([1, 2, 3], 0.3)), ref=pose([0.0, 0.1, 0.0], rotation([0, 1, 1], 0.2)))
    s.add_body(pose([0.7, 0.5, 0.3], rotation([3, -1, 2], 0.9)), ref=pose([0.5, 0.2, 0.4], rotation([1, 0, 1], -0.4)))
    s.add_limit(UID, 0, 1, P0, P1, lower=lower, upper=upper, strength=7.0, offset=offset, origin=origin)
    return s


def by_hand(q: np.ndarray, q_ref: np.ndarray) -> float:
    """x from the DOFs (rows [p, A row 0, A row 1, A row 2]) of bodies 0 (i) and 1 (j), as the docstring writes it."""
    p, A = q[:, :3], q[:, 3:].reshape(-1, 3, 3)
    p_ref, A_ref = q_ref[:, :3], q_ref[:, 3:].reshape(-1, 3, 3)
    t = (P1 - P0) / np.linalg.norm(P1 - P0)
    c = [np.linalg.solve(A_ref[k], P0 - p_ref[k]) for k in range(2)]  # body-local anchors
    t_i = A_ref[0].T @ t  # A_ref is a rotation: its polar factor is itself

    def value(p, A):
        D = (p[1] + A[1] @ c[1]) - (p[0] + A[0] @ c[0])
        return D @ (A[0] @ t_i) + 0.5 * D @ D

    return value(p, A) - value(p_ref, A_ref)


def core_at(req, q: np.ndarray, hessian_mode: str = "exact"):
    b = req.batches[0]
    joints = core.Joints(UID, BASE, b.body_ids, b.edges, b.lower, b.upper, b.strength, offset=b.offset)
    return core.evaluate(core.Bodies(q, req.q_prev, req.q_ref), [joints], hessian_mode=hessian_mode).batches[0]


def test_its_numbers_are_the_formula_and_its_derivatives_central_differences(toy):
    req = scene().request()
    r = core_at(req, req.q)
    x = by_hand(req.q, req.q_ref)
    # x ~ 0.4 of frames and positions O(1): a few roundings of the sums above (bound ~1e-15), 1e-13 relative
    assert r.x[0] == pytest.approx(x, rel=1e-13) and x > 0.1
    l, u, s = -0.1, 0.1, 7.0
    assert r.energy[0] == pytest.approx(s * ((x - u) / (u - l)) ** 3, rel=1e-13)
    # Central differences over the 24 DOFs [q_i, q_j]: x is a polynomial of degree 3 in q and E cubic in x,
    # so the truncation error is h^2 |third derivative| / 6 ~ 1e-12 and the rounding eps |E| / h ~ 1e-10
    # (h = 1e-6): 1e-7 of the largest entry is far above both and far below any wrong term.
    h = 1e-6
    grad = np.empty(24)
    hess = np.empty((24, 24))
    for k in range(24):
        up, down = req.q.copy(), req.q.copy()
        up[k // 12, k % 12] += h
        down[k // 12, k % 12] -= h
        a, b = core_at(req, up), core_at(req, down)
        grad[k] = (a.energy[0] - b.energy[0]) / (2 * h)
        hess[:, k] = (a.gradient[0] - b.gradient[0]) / (2 * h)
    np.testing.assert_allclose(r.gradient[0], grad, rtol=0, atol=1e-7 * np.abs(grad).max())
    np.testing.assert_allclose(r.hessian[0], hess, rtol=0, atol=1e-7 * np.abs(hess).max())
    assert np.array_equal(r.hessian[0], r.hessian[0].T)
    # psd: the eigensolver's projection of E' d2x/dF2 (projected_curvature None), the gradient unchanged
    p = core_at(req, req.q, "psd")
    assert np.array_equal(p.gradient[0], r.gradient[0]) and not np.allclose(p.hessian[0], r.hessian[0])
    lam = np.linalg.eigvalsh(p.hessian[0])
    assert lam.min() >= -1e-12 * lam.max()


def test_validation_names_it_in_the_service_words(toy):
    req = scene().request()
    b = req.batches[0]
    good = core.Joints(UID, BASE, b.body_ids, b.edges, b.lower, b.upper, b.strength)
    bodies = core.Bodies(req.q, req.q_prev, req.q_ref)
    with pytest.raises(core.InputError) as e:
        core.evaluate(bodies, [core.Joints(UID, 18, b.body_ids, b.edges, b.lower, b.upper, b.strength)])
    assert [(f.loc, f.msg) for f in e.value.faults] == [
        (("batches", 0, "base_uid"), f"constitution {UID} ({NAME}) needs base_uid {BASE}, got 18")]
    with pytest.raises(core.InputError) as e:
        core.evaluate(bodies, [good, core.Joints(UID, BASE, b.body_ids, b.edges, b.lower, b.upper, b.strength,
                                                 prev_coordinate=np.zeros(1))])
    assert [(f.loc, f.msg) for f in e.value.faults] == [(("batches", 1, "prev_coordinate"),
        f"applies to revolute joints (670) only: the {NAME} coordinate is absolute and has no state")]
    with pytest.raises(InvalidInput) as e:
        Scene().add_limit(UID, 0, 1, P0, P1, lower=0.0, upper=1.0, prev_coordinate=0.5)
    assert "invalid input (Scene.add_limit)" in str(e.value) and ("prev_coordinate",) in [f.loc for f in e.value.faults]


def test_served_over_http_json_msgpack_sessions_and_the_sdk(toy):
    req = scene(offset=0.25).request()
    local = LocalClient().evaluate(req)
    x = by_hand(req.q, req.q_ref)
    assert local.batches[0].constitution_uid == UID and local.batches[0].x[0] == pytest.approx(x, rel=1e-13)
    assert local.batches[0].coordinate[0] == local.batches[0].x[0] + 0.25
    with serve(app=create_app()) as url:
        # discovery, and OpenAPI made after the registration
        listed = {c["uid"]: c for c in httpx.get(url + "/v1/constitutions").json()["constitutions"]}
        assert set(listed) == {UID, 670, 669}
        toy_info = listed[UID]
        assert (toy_info["name"], toy_info["base_uid"], toy_info["base_name"]) == (NAME, BASE, "ToyAnchorJoint")
        fields = {a["field"]: a["name"] for a in toy_info["attributes"]}
        assert fields["offset"] == "init_slide" and "prev_coordinate" not in fields  # it telescopes: no state
        assert [c.uid for c in LocalClient().constitutions().constitutions if c.uid == UID] == [UID]
        spec = httpx.get(url + "/openapi.json").json()["components"]["schemas"]["JointBatch"]["properties"]
        assert spec["constitution_uid"]["enum"] == [670, 669, UID] and BASE in spec["base_uid"]["enum"]
        # the SDK over HTTP, both encodings: bitwise the in-process answer
        for binary in (True, False):
            got = Client(url, binary=binary).evaluate(req)
            for f in ("x", "coordinate", "energy", "gradient", "hessian"):
                assert getattr(got.batches[0], f).tobytes() == getattr(local.batches[0], f).tobytes(), (binary, f)
        # raw JSON without base_uid: the decoder takes it from the registry
        doc = {"bodies": {k: getattr(req, k).tolist() for k in ("q", "q_prev", "q_ref")},
               "batches": [{"constitution_uid": UID, "body_ids": [[0, 1]], "edges": [[P0.tolist(), P1.tolist()]],
                            "lower": [-0.1 + 0.25], "upper": [0.1 + 0.25], "strength": [7.0], "offset": [0.25]}],
               "outputs": ["energy"]}
        r = httpx.post(url + "/v1/evaluate", json=doc)
        assert r.status_code == 200 and r.json()["batches"][0]["x"] == local.batches[0].x.tolist()
        bad = httpx.post(url + "/v1/evaluate", json={**doc, "batches": [{**doc["batches"][0], "base_uid": 20}]})
        assert bad.status_code == 422 and bad.json()["detail"] == [{"loc": ["body", "batches", 0, "base_uid"],
            "msg": f"constitution {UID} ({NAME}) needs base_uid {BASE}, got 20", "type": "value_error"}]
        # sessions, over the WebSocket and in-process: the same numbers; a commit is x(q) + offset
        moved = req.q.copy()
        moved[1, :3] += [0.05, -0.02, 0.01]
        want = core_at(req, moved)
        for session in (Client(url).session(req), LocalClient().session(req)):
            with session as s:
                assert s.evaluate(req.q).batches[0].hessian.tobytes() == local.batches[0].hessian.tobytes()
                assert s.evaluate(moved).batches[0].energy.tobytes() == want.energy.tobytes()
                committed = s.commit(moved)[0]
                assert committed[0] == pytest.approx(by_hand(moved, req.q_ref) + 0.25, rel=1e-13)
                assert s.request_for_reopen().batches[0].prev_coordinate is None  # no state to carry


def test_unregistered_it_is_refused_again():
    with registered():
        with pytest.raises(ValueError, match="already registered"):
            register(ToySlide())
        req = scene().request()
    assert list(CONSTITUTIONS) == [670, 669]
    with pytest.raises(InvalidInput) as e:
        LocalClient().evaluate(req)
    assert [(f.loc, f.msg) for f in e.value.faults] == [
        (("body", "batches", 0, "constitution_uid"), f"unknown constitution {UID}; supported: 670, 669")]
    with pytest.raises(InvalidInput) as e:
        scene()
    assert [(f.loc, f.msg) for f in e.value.faults] == [(("uid",), f"unknown constitution {UID}; supported: 670, 669")]
