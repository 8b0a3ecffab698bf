"""`jointlimits.client.uipc` on real pyuipc scenes, end to end, against `tests/engine_ref.py` (libuipc's kernels).

Each scene is built as a libuipc user builds it (`AffineBodyConstitution().apply_to`,
`AffineBody*Joint().create_geometry`, `AffineBody*JointLimit().apply_to`). No simulation runs (the
engine's CUDA backend needs a GPU): what `world.init()` / a time step would publish (`angle`, moved
transforms, `backend_abd_body_offset`) is written into the scene by hand, as the engine writes it.
The reference reads the scene's attributes itself, joint by joint (no body numbering), and every
row of `request_from_scene` -> `LocalClient().evaluate` must match it to 1e-12 (normwise).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jointlimits.client import LocalClient
from tests import engine_ref as ref
from tests.conftest import relerr

TOL = 1e-12
FIELDS = ("x", "coordinate", "energy", "gradient", "hessian")
ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------- the transcription against the golden files


def _golden_cases() -> list[tuple[str, dict]]:
    out = []
    for name in ("golden_v12_cases.json", "golden_cases.json", "golden_state_cases.json"):
        path = Path(__file__).parents[1] / name
        if path.exists():
            out += [(f"{name}:{c['name']}", c) for c in json.loads(path.read_text())["cases"]]
    return out


@pytest.mark.parametrize("case", [c for _, c in _golden_cases()], ids=[n for n, _ in _golden_cases()])
def test_engine_ref_agrees_with_the_golden_cases(case):
    """x, coordinate, energy and gradient of every case; the Hessian where it is the engine's psd."""
    r, bodies = case["request"], case["request"]["bodies"]
    for batch, want in zip(r["batches"], case["expect"]):
        got = ref.evaluate_batch(batch, bodies["q"], bodies["q_prev"], bodies["q_ref"])
        fields = ["x", "energy", "gradient"] + ["coordinate"] * ("coordinate" in want)
        fields += ["hessian"] * (r.get("hessian_mode") == "psd")
        for f in fields:
            assert relerr(getattr(got, f), want[f]) <= TOL, (f, relerr(getattr(got, f), want[f]))


# ------------------------------------------------------------------------------ without pyuipc


def test_the_module_imports_without_pyuipc_and_says_which_extra_installs_it():
    code = (
        "import sys; sys.modules['uipc'] = None\n"  # an import of uipc now raises ImportError
        "import jointlimits.client.uipc as cu\n"
        "try:\n"
        "    cu.request_from_scene(object())\n"
        "except ImportError as e:\n"
        "    print('IMPORT-ERROR', e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "IMPORT-ERROR" in out.stdout and "pip install pyuipc (the uipc extra)" in out.stdout


def test_write_back_without_pyuipc_raises_the_same_import_error(monkeypatch):
    import jointlimits.client.uipc as cu

    monkeypatch.setitem(sys.modules, "uipc", None)
    with pytest.raises(ImportError, match=r"pip install pyuipc \(the uipc extra\)"):
        cu.write_back(object(), [], [])


# ------------------------------------------------------------------------------------ scene building

uipc = pytest.importorskip("uipc")  # the `test` extra installs it; everything below needs it

from uipc import Scene, builtin, view  # noqa: E402
from uipc.constitution import (  # noqa: E402
    AffineBodyConstitution,
    AffineBodyPrismaticJoint,
    AffineBodyPrismaticJointLimit,
    AffineBodyRevoluteJoint,
    AffineBodyRevoluteJointLimit,
)
from uipc.geometry import ground, tetmesh  # noqa: E402

from jointlimits.client.uipc import SceneError, request_from_scene, write_back  # noqa: E402

TET_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
TET_T = np.array([[0, 1, 2, 3]], dtype=np.int32)


def rot(axis, angle: float) -> np.ndarray:
    """(3, 3) rotation by `angle` about `axis` (right-hand rule)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def transform(A, p) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = A, p
    return T


def body(obj, transforms, arap: bool = False):
    """An affine-body geometry with one instance per (4, 4) transform; returns its slot."""
    m = tetmesh(TET_V, TET_T)
    AffineBodyConstitution({"name": "ARAP" if arap else "OrthoPotential"}).apply_to(m, 1e8)
    m.instances().resize(len(transforms))
    view(m.transforms())[:] = np.asarray(transforms)
    slot, _ = obj.geometries().create(m)
    return slot


def set_transform(slot, inst: int, T) -> None:
    """What a time step does to an instance: its current transform moves (the rest one stays)."""
    view(slot.geometry().transforms())[inst] = T


def edge_values(mesh, name: str, values) -> None:
    view(mesh.edges().find(name))[:] = np.asarray(values, dtype=np.float64)


def publish(scene, body_slots) -> None:
    """What `world.init()` of the CUDA backend publishes on the body geometries `body_slots`: the
    engine's body offset (affine-body geometries in slot order, stable-sorted by constitution UID,
    `AffineBodyDynamics::Impl::_build_geo_infos`)."""
    geos = [s.geometry() for s in body_slots]
    order = sorted(range(len(body_slots)), key=lambda k: (int(geos[k].meta().find(builtin.constitution_uid).view()[0]),
                                                          body_slots[k].id()))
    at = 0
    for k in order:
        geo = scene.geometries().find(body_slots[k].id())[0].geometry()
        attr = geo.meta().find(builtin.backend_abd_body_offset) or geo.meta().create(builtin.backend_abd_body_offset, 0)
        view(attr)[0] = at
        at += geo.instances().size()


# ------------------------------------------------------------------ the reference, from the attributes


def q_of(scene, gid: int, inst: int, rest: bool = False) -> np.ndarray:
    slot, rest_slot = scene.geometries().find(int(gid))
    T = np.asarray((rest_slot if rest else slot).geometry().transforms().view())[int(inst)]
    return ref.transform_to_q(T)[0]


def reference(scene, joints_of_batch, *, committed: bool, q_prev_of=None, q_ref_of=None,
              origin: str = "absolute") -> ref.Result:
    """The engine's numbers for the rows `[(geometry id, edge), ...]` of one batch, read straight
    from the scene's attributes: each side's body is its geometry's instance transform (current for
    `q`, rest for `q_ref`, unless `q_ref_of(gid, inst)` says; `q_prev_of(gid, inst)`, else the
    current transform when the committed `angle` is read (the engine publishes it for the transforms
    its next step takes as q_prev), else `q_ref`, for `q_prev`)."""
    rest = q_ref_of or (lambda g, i: q_of(scene, g, i, rest=True))
    if q_prev_of is None and committed:
        q_prev_of = lambda g, i: q_of(scene, g, i)  # noqa: E731
    rows = {k: [] for k in ("qi", "qj", "pi", "pj", "ri", "rj", "lo", "up", "s", "off", "angle", "e", "le")}
    uid = None
    for gid, e in joints_of_batch:
        geo = scene.geometries().find(gid)[0].geometry()
        base = int(geo.meta().find(builtin.constitution_uid).view()[0])
        uid = {18: 670, 20: 669}[base]
        a = lambda n: np.asarray(geo.edges().find(n).view())[e]  # noqa: E731
        li, lj = (int(a("l_geo_id")), int(a("l_inst_id"))), (int(a("r_geo_id")), int(a("r_inst_id")))
        rows["qi"].append(q_of(scene, *li))
        rows["qj"].append(q_of(scene, *lj))
        rows["ri"].append(rest(*li))
        rows["rj"].append(rest(*lj))
        rows["pi"].append(q_prev_of(*li) if q_prev_of else rest(*li))
        rows["pj"].append(q_prev_of(*lj) if q_prev_of else rest(*lj))
        rows["lo"].append(a("limit/lower"))
        rows["up"].append(a("limit/upper"))
        rows["s"].append(a("limit/strength"))
        rows["off"].append(a("init_angle" if uid == 670 else "init_distance"))
        if uid == 670:
            rows["angle"].append(a("angle"))
        if geo.edges().find("l_position0") is not None:
            rows["le"].append([[a("l_position0").ravel(), a("l_position1").ravel()],
                               [a("r_position0").ravel(), a("r_position1").ravel()]])
        else:
            P = np.asarray(geo.positions().view()).reshape(-1, 3)
            rows["e"].append(P[np.asarray(geo.edges().topo().view()).reshape(-1, 2)[e]])
    A = {k: np.array(v, dtype=np.float64) for k, v in rows.items() if v}
    kw = dict(edges=A.get("e"), local_edges=A.get("le"), offset=A["off"], origin=origin)
    args = ((A["qi"], A["qj"]), (A["pi"], A["pj"]), (A["ri"], A["rj"]), A["lo"], A["up"], A["s"])
    if uid == 670:
        return ref.revolute(*args, prev_coordinate=A["angle"] if committed else None, **kw)
    return ref.prismatic(*args, **kw)


def check_scene(scene, *, committed: bool = False, q_prev_of=None, q_ref_of=None, min_active: int = 1, **kw):
    """request_from_scene -> LocalClient against the reference, every batch and field; returns (req, joints, ev)."""
    req, joints = request_from_scene(scene, committed=committed, **kw)
    assert req.hessian_mode == "psd" and all(b.origin == "absolute" for b in req.batches)
    ev = LocalClient().evaluate(req)
    active = 0
    for k, (got, rows) in enumerate(zip(ev.batches, joints)):
        want = reference(scene, rows, committed=committed, q_prev_of=q_prev_of, q_ref_of=q_ref_of)
        for f in FIELDS:
            err = relerr(getattr(got, f), getattr(want, f))
            assert err <= TOL, f"batch {k} ({got.constitution_uid}), {f}: {err:.2e}"
        active += int(np.count_nonzero(want.energy))
    assert active >= min_active  # the comparison covers joints outside their range
    return req, joints, ev


# ------------------------------------------------------------------------------------------ scenes


def hinge_and_slider_scene(local: bool):
    """Two body geometries (3 and 2 instances, scaled and sheared rest transforms); 3 hinges and 2
    sliders sharing bodies; offsets; the current transforms turned and slid past the limits."""
    scene = Scene(Scene.default_config())
    scene.objects().create("ground").geometries().create(ground(-1.0))  # an implicit geometry: no body, no joint
    obj = scene.objects().create("links")
    shear = np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.2], [0.0, 0.0, 1.0]])
    stretch = np.diag([1.5, 0.7, 1.2])
    A = [rot([0, 0, 1], 0.2) @ shear, np.eye(3) * 2.0, rot([1, 1, 0], 0.4) @ stretch]
    a = body(obj, [transform(A[0], [0, 0, 0]), transform(A[1], [1, 0, 0]), transform(A[2], [2, 0.5, 0])])
    b = body(obj, [transform(stretch, [0, 1, 0]), transform(rot([0, 1, 0], 0.3), [1, 1, 1])])
    # hinges: a0-a1, a1-b0, a2-b0; sliders: a2-b1, a0-b0 (a0, a1, a2, b0 in two joints or more). a2 and
    # b0 stretch along different axes: their frames at q_ref are not at angle 0 (the engine's zero).
    l = ([a, a, a], [0, 1, 2], [a, b, b], [1, 0, 0])
    p0 = np.array([[0.5, 0.0, 0.0], [1.0, 0.5, 0.2], [0.5, 1.0, 0.5]])
    p1 = p0 + np.array([[0.0, 0.0, 1.0], [0.3, 1.0, 0.1], [1.0, 0.2, -0.4]])
    rj, pj = AffineBodyRevoluteJoint(), AffineBodyPrismaticJoint()
    s = ([a, a], [2, 0], [b, b], [1, 0])
    q0 = np.array([[2.0, 0.5, 0.0], [0.0, 0.5, 0.0]])
    q1 = q0 + np.array([[0.2, 0.1, 1.0], [1.0, 0.0, 0.0]])
    if local:
        l0 = np.array([[0.1, 0.2, 0.0], [0.0, 0.3, 0.1], [0.2, 0.2, 0.2]])
        l1 = np.array([[0.1, 0.2, 1.0], [0.4, 0.3, 0.9], [1.2, 0.1, 0.2]])
        r0, r1 = l0 * 0.5 + 0.1, l1 * 0.5 + 0.1
        hinges = rj.create_geometry(l0, l1, r0, r1, l[0], np.array(l[1], np.int32), l[2], np.array(l[3], np.int32),
                                    np.full(3, 100.0))
        # slider anchors apart: theta(q_ref) != 0 (the engine's absolute zero)
        sliders = pj.create_geometry(np.array([[0.0, 0.1, 0.0], [0.2, 0.0, 0.1]]), np.array([[0.3, 0.1, 1.0], [1.0, 0.2, 0.1]]),
                                     np.array([[0.3, 0.0, 0.2], [-0.1, 0.4, 0.0]]), np.array([[0.3, 0.0, 1.2], [0.9, 0.4, 0.0]]),
                                     s[0], np.array(s[1], np.int32), s[2], np.array(s[3], np.int32), np.full(2, 100.0))
    else:
        hinges = rj.create_geometry(p0, p1, l[0], np.array(l[1], np.int32), l[2], np.array(l[3], np.int32), np.full(3, 100.0))
        sliders = pj.create_geometry(q0, q1, s[0], np.array(s[1], np.int32), s[2], np.array(s[3], np.int32), np.full(2, 100.0))
    AffineBodyRevoluteJointLimit().apply_to(hinges, np.array([-0.2, -0.1, 0.0]), np.array([0.2, 0.3, 0.0]),
                                            np.array([100.0, 5.0, 7.0]))
    AffineBodyPrismaticJointLimit().apply_to(sliders, np.array([-0.05, 0.0]), np.array([0.05, 0.1]), np.array([50.0, 3.0]))
    edge_values(hinges, "init_angle", [0.1, -0.3, 0.0])
    edge_values(sliders, "init_distance", [0.02, -0.5])
    hs, _ = obj.geometries().create(hinges)
    ss, _ = obj.geometries().create(sliders)
    # a time step later: every instance turned and moved (an affine drift too)
    for slot, n in ((a, 3), (b, 2)):
        for i in range(n):
            T = np.asarray(slot.geometry().transforms().view())[i]
            turn = rot([np.sin(i + n), 1.0, 0.5 * i], 0.35 * (i + 1) * (-1) ** (i + n))
            drift = np.eye(3) + 0.01 * np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]]) * (i + 1)
            set_transform(slot, i, transform(drift @ turn @ T[:3, :3], T[:3, 3] + [0.05 * i, -0.1, 0.2 - 0.1 * n]))
    return scene, (a, b), (hs, ss)


@pytest.mark.parametrize("local", [False, True], ids=["world", "local"])
def test_world_and_local_scenes_match_the_engine(local):
    scene, _, (hs, ss) = hinge_and_slider_scene(local)
    req, joints, ev = check_scene(scene, min_active=3)
    assert [b.constitution_uid for b in req.batches] == [670, 669]
    assert joints == [[(hs.id(), 0), (hs.id(), 1), (hs.id(), 2)], [(ss.id(), 0), (ss.id(), 1)]]
    assert all((b.local_edges is not None) == local and (b.edges is None) == local for b in req.batches)
    np.testing.assert_array_equal(req.batches[0].body_ids, [[0, 1], [1, 3], [2, 3]])
    np.testing.assert_array_equal(req.batches[1].body_ids, [[2, 4], [0, 3]])
    np.testing.assert_array_equal(req.batches[0].offset, [0.1, -0.3, 0.0])
    np.testing.assert_array_equal(req.batches[1].offset, [0.02, -0.5])
    # the scene exercises the engine's zero: measured from q_ref, x would differ (670; 669 with apart anchors)
    for rows, got, moved in zip(joints, ev.batches, (True, local)):
        from_q_ref = reference(scene, rows, committed=False, origin="q_ref").x
        assert (np.max(np.abs(got.x - from_q_ref)) > 1e-2) == moved


def test_a_given_q_prev_and_q_ref():
    """`q_prev` and `q_ref` passed in (B, 12), in the engine's numbering, override the transforms
    (`q_prev` defaults to the given `q_ref`)."""
    scene, (a, b), _ = hinge_and_slider_scene(local=True)
    req0, _ = request_from_scene(scene)
    pos = {(a.id(), i): i for i in range(3)} | {(b.id(), i): 3 + i for i in range(2)}
    q_prev = req0.q_ref + 0.5 * (req0.q - req0.q_ref)  # halfway: the previous step
    check_scene(scene, q_prev=q_prev, q_prev_of=lambda g, i: q_prev[pos[(g, i)]])
    q_ref = req0.q_ref.copy()
    q_ref[:, 3:] = (req0.q_ref[:, 3:].reshape(-1, 3, 3) @ rot([0.2, 1.0, 0.3], 0.1)).reshape(-1, 9)  # at init, elsewhere
    req, _, _ = check_scene(scene, q_ref=q_ref, q_ref_of=lambda g, i: q_ref[pos[(g, i)]])
    np.testing.assert_array_equal(req.q_prev, q_ref)


def test_arap_body_next_to_an_orthotropic_one_is_numbered_as_the_engine_numbers_it():
    """The engine sorts affine-body geometries by constitution UID (OrthoPotential 1 before ARAP 2),
    stably, whatever the slot order; a non-body geometry in between takes no body row."""
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("o")
    T = [transform(rot([0, 0, 1], 0.1 * k) * (1 + 0.1 * k), [k, 0, 0]) for k in range(5)]
    arap = body(obj, T[0:2], arap=True)       # slot 0: ARAP, 2 bodies
    ortho = body(obj, T[2:3])                 # slot 1: ortho, 1 body
    arap2 = body(obj, T[3:5], arap=True)      # slot 2: ARAP, 2 bodies
    hinge = AffineBodyRevoluteJoint().create_geometry(
        np.array([[0.0, 0, 0], [1, 0, 0]]), np.array([[0.0, 0, 1], [1, 1, 1]]),
        [arap, ortho], np.array([1, 0], np.int32), [ortho, arap2], np.array([0, 1], np.int32), np.full(2, 10.0))
    AffineBodyRevoluteJointLimit().apply_to(hinge, -0.1, 0.1, 10.0)
    obj.geometries().create(hinge)
    set_transform(arap2, 1, transform(rot([1, 0.5, 0.2], 0.8) @ T[4][:3, :3], [4, 0.1, 0]))
    req, joints, _ = check_scene(scene)
    # ortho (slot 1) -> body 0; ARAP slot 0 -> 1, 2; ARAP slot 2 -> 3, 4
    np.testing.assert_array_equal(req.batches[0].body_ids, [[2, 0], [0, 4]])
    np.testing.assert_array_equal(req.q_ref, ref.transform_to_q(np.array([T[2], T[0], T[1], T[3], T[4]])))
    publish(scene, [arap, ortho, arap2])
    assert [int(scene.geometries().find(s.id())[0].geometry().meta().find(builtin.backend_abd_body_offset).view()[0])
            for s in (arap, ortho, arap2)] == [1, 0, 3]


def test_multi_turn_angle_is_the_committed_prev_coordinate():
    """`angle` (the engine's committed, unwrapped angle) several turns away, with init_angle: the
    limits bound it, and committed=True / None-once-published / False read it as the engine does."""
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("screw")
    base = body(obj, [transform(np.eye(3), [0, 0, 0]), transform(np.diag([1.0, 2.0, 0.5]), [0, 0, 2])])
    hinge = AffineBodyRevoluteJoint().create_geometry(
        np.array([[0.0, 0, 1], [0.0, 0, 1]]), np.array([[0.0, 0, 2], [0.0, 0, 0]]),
        [base, base], np.array([0, 1], np.int32), [base, base], np.array([1, 0], np.int32), np.full(2, 10.0))
    turns = 2.5 * 2 * np.pi
    AffineBodyRevoluteJointLimit().apply_to(hinge, np.array([-turns, 0.0]), np.array([turns, 0.4]), np.array([10.0, 2.0]))
    edge_values(hinge, "init_angle", [0.25, -1.0])
    hs, _ = obj.geometries().create(hinge)
    set_transform(base, 1, transform(rot([0, 0, 1], 0.3) @ np.diag([1.0, 2.0, 0.5]), [0, 0, 2]))
    edge_values(hs.geometry(), "angle", [turns + 0.25 + 0.1, -1.0 - 4 * np.pi + 0.2])  # beyond +2.5 turns; 2 turns back
    req, _, ev = check_scene(scene, committed=True, min_active=2)
    np.testing.assert_array_equal(req.batches[0].prev_coordinate, np.asarray(hs.geometry().edges().find("angle").view()))
    assert ev.batches[0].x[0] > turns and ev.batches[0].coordinate[1] < -4 * np.pi
    # None: not published yet -> the angle is not read (before world.init() it is only a placeholder)
    req, _ = request_from_scene(scene)
    assert req.batches[0].prev_coordinate is None
    check_scene(scene, committed=False, min_active=1)
    # None once published: read; False: never
    publish(scene, [base])
    req, _ = request_from_scene(scene)
    np.testing.assert_array_equal(req.batches[0].prev_coordinate, np.asarray(hs.geometry().edges().find("angle").view()))
    assert request_from_scene(scene, committed=False)[0].batches[0].prev_coordinate is None


def test_after_world_init_on_the_cpu_backend_nothing_is_published(tmp_path):
    """pyuipc's CPU backend ("none") runs `world.init()` (its checks, no simulation) but publishes
    nothing: no `backend_abd_body_offset`, `angle` stays as built, so committed=None does not read it.
    (The CUDA backend, which publishes them, needs a GPU.)"""
    from uipc import Engine, World

    scene, (a, b), _ = hinge_and_slider_scene(local=False)
    before, _ = request_from_scene(scene)
    engine = Engine("none", str(tmp_path))  # the World holds it weakly: keep it alive
    world = World(engine)
    world.init(scene)
    assert all(s.geometry().meta().find(builtin.backend_abd_body_offset) is None for s in (a, b))
    req, joints, _ = check_scene(scene)
    assert req.batches[0].prev_coordinate is None
    for f in ("q", "q_prev", "q_ref"):
        np.testing.assert_array_equal(getattr(req, f), getattr(before, f))


def test_write_back_commits_coordinates_and_the_next_request_reads_them():
    scene, _, (hs, ss) = hinge_and_slider_scene(local=False)
    req, joints = request_from_scene(scene)
    with LocalClient().session(req) as session:
        coords = session.commit(req.q)
    write_back(scene, coords, joints)
    np.testing.assert_array_equal(np.asarray(hs.geometry().edges().find("angle").view()), coords[0])
    np.testing.assert_array_equal(np.asarray(ss.geometry().edges().find("distance").view()), coords[1])
    # the committed step: q_prev := q, prev_coordinate := the written angle
    check_scene(scene, committed=True, q_prev=req.q, q_prev_of=lambda g, i: q_of(scene, g, i))
    # an Evaluation works too (every row present)
    ev = LocalClient().evaluate(req)
    write_back(scene, ev, joints)
    np.testing.assert_array_equal(np.asarray(hs.geometry().edges().find("angle").view()), ev.batches[0].coordinate)


def test_write_back_checks_everything_before_writing():
    scene, _, (hs, _) = hinge_and_slider_scene(local=False)
    req, joints = request_from_scene(scene)
    ev = LocalClient().evaluate(req)
    before = np.array(hs.geometry().edges().find("angle").view())
    bad = [ev.batches[0].coordinate, np.array([0.0, np.nan])]  # batch 0 fine, batch 1 not finite
    with pytest.raises(SceneError, match="not finite"):
        write_back(scene, bad, joints)
    np.testing.assert_array_equal(np.asarray(hs.geometry().edges().find("angle").view()), before)
    with pytest.raises(SceneError, match="1 batches of coordinates for 2"):
        write_back(scene, bad[:1], joints)
    edge_values(hs.geometry(), "limit/upper", [10.0, 10.0, 10.0])  # hinge 0 is now inside its range
    edge_values(hs.geometry(), "limit/lower", [-10.0, -10.0, -10.0])
    req, joints = request_from_scene(scene)
    req.active_only = True
    ev = LocalClient().evaluate(req)
    assert len(ev.batches[0].index) == 0
    with pytest.raises(SceneError, match="active_only"):
        write_back(scene, ev, joints)


def test_the_same_request_serves_the_http_clients_and_sessions(live):
    """Client, AsyncClient and a live session (binary and JSON) give LocalClient's numbers bit for bit."""
    import asyncio

    from jointlimits.client import AsyncClient, Client

    scene, _, _ = hinge_and_slider_scene(local=True)
    req, joints = request_from_scene(scene)
    want = LocalClient().evaluate(req)
    with LocalClient().session(req) as s:
        want_commit = s.commit(req.q)

    async def run():
        async with AsyncClient(live) as c:
            return await c.evaluate(req)

    evs = [asyncio.run(run())]
    for binary in (True, False):
        with Client(live, binary=binary) as c:
            evs.append(c.evaluate(req))
            with c.session(req) as s:
                evs.append(s.evaluate(req.q))
                got_commit = s.commit(req.q)
        for g, w in zip(got_commit, want_commit):
            np.testing.assert_array_equal(g, w)
    for ev in evs:
        for g, w in zip(ev.batches, want.batches):
            for f in FIELDS:
                np.testing.assert_array_equal(getattr(g, f), getattr(w, f))
    write_back(scene, got_commit, joints)


from tests.http.test_contract_live import live  # noqa: E402,F401 (fixture)


def random_affine(rng: np.random.Generator, stretch: float) -> np.ndarray:
    """A rotation times a positive-determinant stretch-and-shear (up to `stretch` off the identity)."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    M = np.eye(3) + stretch * rng.uniform(-1, 1, size=(3, 3))
    return q @ (M if np.linalg.det(M) > 0.2 else np.eye(3))


@pytest.mark.parametrize("seed", range(6))
def test_random_scenes_mixing_every_kind_of_joint(seed):
    """Body geometries of both affine-body constitutions with several instances, and world and local
    hinges and sliders between random bodies in one scene (4 batches); a committed multi-turn
    `angle` on every hinge; random current transforms."""
    rng = np.random.default_rng(seed)
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("random")
    slots = []
    for g in range(3):
        n = int(rng.integers(1, 4))
        T = [transform(random_affine(rng, 0.3), rng.normal(size=3)) for _ in range(n)]
        slots.append(body(obj, T, arap=bool(rng.integers(0, 2))))
    bodies = [(s, i) for s in slots for i in range(s.geometry().instances().size())]
    rj, pj = AffineBodyRevoluteJoint(), AffineBodyPrismaticJoint()
    made = []
    for joint, limit, local in ((rj, AffineBodyRevoluteJointLimit(), False), (pj, AffineBodyPrismaticJointLimit(), True),
                                (rj, AffineBodyRevoluteJointLimit(), True), (pj, AffineBodyPrismaticJointLimit(), False)):
        n = int(rng.integers(1, 4))
        pick = [rng.choice(len(bodies), size=2, replace=False) for _ in range(n)]
        ls, li = [bodies[p[0]][0] for p in pick], np.array([bodies[p[0]][1] for p in pick], np.int32)
        rs, ri = [bodies[p[1]][0] for p in pick], np.array([bodies[p[1]][1] for p in pick], np.int32)
        pts = [rng.normal(size=(n, 3)) for _ in range(4)]
        geo = (joint.create_geometry(*pts, ls, li, rs, ri, np.ones(n)) if local
               else joint.create_geometry(pts[0], pts[1], ls, li, rs, ri, np.ones(n)))
        lo = rng.uniform(-0.3, 0.0, n)
        limit.apply_to(geo, lo, lo + rng.choice([0.0, 0.2], n), rng.uniform(1, 100, n))
        edge_values(geo, "init_angle" if joint is rj else "init_distance", rng.uniform(-1, 1, n))
        made.append(obj.geometries().create(geo)[0])
    for s in (made[0], made[2]):  # committed angles, up to 3 turns away
        n = s.geometry().edges().size()
        init = np.asarray(s.geometry().edges().find("init_angle").view())
        edge_values(s.geometry(), "angle", init + rng.uniform(-1, 1, n) + 2 * np.pi * rng.integers(-3, 4, n))
    for s, i in bodies:
        T = np.asarray(s.geometry().transforms().view())[i]
        set_transform(s, i, transform(random_affine(rng, 0.02) @ T[:3, :3], T[:3, 3] + 0.2 * rng.normal(size=3)))
    req, joints, _ = check_scene(scene, committed=True, min_active=2)
    kinds = [(b.constitution_uid, b.local_edges is not None) for b in req.batches]
    assert kinds == [(670, False), (670, True), (669, True), (669, False)]
    assert [{g for g, _ in rows} for rows in joints] == [{made[0].id()}, {made[2].id()}, {made[1].id()}, {made[3].id()}]


# ----------------------------------------------------------------------------------------- errors


def test_a_limit_on_only_some_sibling_joint_geometries_is_refused():
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("o")
    a = body(obj, [np.eye(4), transform(np.eye(3), [1, 0, 0])])
    rj = AffineBodyRevoluteJoint()
    mk = lambda: rj.create_geometry(np.zeros((1, 3)), np.array([[0.0, 0, 1]]), [a], np.array([0], np.int32),  # noqa: E731
                                    [a], np.array([1], np.int32), np.array([1.0]))
    limited, bare = mk(), mk()
    AffineBodyRevoluteJointLimit().apply_to(limited, -0.1, 0.1)
    ls, _ = obj.geometries().create(limited)
    bs, _ = obj.geometries().create(bare)
    with pytest.raises(SceneError, match="not on their siblings") as e:
        request_from_scene(scene)
    assert e.value.geometry_id == bs.id()


def test_a_missing_body_geometry_is_refused():
    scene = Scene(Scene.default_config())
    bodies, joints_obj = scene.objects().create("bodies"), scene.objects().create("joints")
    a = body(bodies, [np.eye(4), transform(np.eye(3), [1, 0, 0])])
    hinge = AffineBodyRevoluteJoint().create_geometry(np.zeros((1, 3)), np.array([[0.0, 0, 1]]), [a], np.array([0], np.int32),
                                                      [a], np.array([1], np.int32), np.array([1.0]))
    AffineBodyRevoluteJointLimit().apply_to(hinge, -0.1, 0.1)
    hs, _ = joints_obj.geometries().create(hinge)
    scene.objects().destroy(bodies.id())
    with pytest.raises(SceneError, match="not an affine-body geometry") as e:
        request_from_scene(scene)
    assert (e.value.geometry_id, e.value.edge) == (hs.id(), 0)


def test_an_instance_out_of_range_is_refused():
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("o")
    a = body(obj, [np.eye(4), transform(np.eye(3), [1, 0, 0])])
    hinge = AffineBodyRevoluteJoint().create_geometry(np.zeros((2, 3)), np.array([[0.0, 0, 1]] * 2), [a, a], np.array([0, 0], np.int32),
                                                      [a, a], np.array([1, 1], np.int32), np.ones(2))
    AffineBodyRevoluteJointLimit().apply_to(hinge, -0.1, 0.1)
    view(hinge.edges().find("r_inst_id"))[1] = 2
    hs, _ = obj.geometries().create(hinge)
    with pytest.raises(SceneError, match="out of range") as e:
        request_from_scene(scene)
    assert (e.value.geometry_id, e.value.edge) == (hs.id(), 1)


def test_zero_edges_are_refused():
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("o")
    a = body(obj, [np.eye(4), transform(np.eye(3), [1, 0, 0])])
    with pytest.raises(SceneError, match="zero edges"):  # bodies, no limited joint
        request_from_scene(scene)
    hinge = AffineBodyRevoluteJoint().create_geometry(np.zeros((1, 3)), np.array([[0.0, 0, 1]]), [a], np.array([0], np.int32),
                                                      [a], np.array([1], np.int32), np.ones(1))
    AffineBodyRevoluteJointLimit().apply_to(hinge, -0.1, 0.1)  # pyuipc refuses a limit on an edge-less mesh,
    hinge.edges().resize(0)                                    # so the edges go afterwards
    obj.geometries().create(hinge)
    with pytest.raises(SceneError, match="zero edges"):  # a limited joint geometry without edges
        request_from_scene(scene)


@pytest.mark.parametrize("uid", [670, 669])
def test_a_zero_length_axis_is_refused_as_the_engine_refuses_it(uid):
    scene = Scene(Scene.default_config())
    obj = scene.objects().create("o")
    a = body(obj, [np.eye(4), transform(np.eye(3), [1, 0, 0])])
    joint, limit = ((AffineBodyRevoluteJoint(), AffineBodyRevoluteJointLimit()) if uid == 670
                    else (AffineBodyPrismaticJoint(), AffineBodyPrismaticJointLimit()))
    g = joint.create_geometry(np.array([[0.0, 0, 0], [0.5, 0.5, 0.5]]), np.array([[0.0, 0, 1], [0.5, 0.5, 0.5]]),
                              [a, a], np.array([0, 0], np.int32), [a, a], np.array([1, 1], np.int32), np.ones(2))
    limit.apply_to(g, -0.1, 0.1)
    s, _ = obj.geometries().create(g)
    with pytest.raises(SceneError, match="zero length") as e:
        request_from_scene(scene)
    assert (e.value.geometry_id, e.value.edge) == (s.id(), 1)


def test_partly_published_body_offsets_and_wrong_shapes_are_refused():
    scene, (a, b), _ = hinge_and_slider_scene(local=False)
    publish(scene, [a, b])
    geo = b.geometry()
    geo.meta().destroy(builtin.backend_abd_body_offset)
    with pytest.raises(SceneError, match="1 of 2 body geometries"):
        request_from_scene(scene)
    request_from_scene(scene, committed=False)  # an explicit rule needs no publication
    publish(scene, [a, b])
    view(geo.meta().find(builtin.backend_abd_body_offset))[0] = 7
    with pytest.raises(SceneError, match="numbers this body geometry's first body 7"):
        request_from_scene(scene)
    publish(scene, [a, b])
    with pytest.raises(SceneError, match=r"\(5, 12\)"):
        request_from_scene(scene, q=np.zeros((4, 12)))
