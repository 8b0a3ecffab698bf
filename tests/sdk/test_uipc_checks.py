"""Issue 27 (3): a bad value written into a joint geometry after `apply_to` (which skips its checks) is
refused by `request_from_scene` as a `SceneError` naming the geometry and the edge, with words for
what is wrong, not later by `evaluate` as a batch row. What the engine refuses at `world.init()`
(`limit/lower <= limit/upper`, a zero axis) and what the service refuses although the engine takes
it (non-finite numbers, a negative strength, a body jointed to itself) alike; nothing more."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytest.importorskip("uipc")  # the `test` extra installs pyuipc

from uipc import view  # noqa: E402

from jointlimits.client import LocalClient  # noqa: E402
from jointlimits.client.uipc import SceneError, request_from_scene  # noqa: E402
from tests.sdk.test_uipc import hinge_and_slider_scene  # noqa: E402

EDGE = 1  # edge 0 stays good: the error must name the edge, not the first one


def write(attr: Any, row: int, value: Any) -> None:
    """What a user does after `apply_to`: one row of an attribute overwritten."""
    v = np.array(attr.view())
    v[row] = np.asarray(value, dtype=np.float64).reshape(v[row].shape)
    view(attr)[:] = v


def refused(scene: Any, **kw: Any) -> SceneError:
    with pytest.raises(SceneError) as e:
        request_from_scene(scene, **kw)
    return e.value


OFFSET = {670: "init_angle", 669: "init_distance"}
# (attribute, value, words): a row of an edge attribute; "{offset}" is init_angle or init_distance
EDGE_FAULTS = [
    ("limit/lower", np.nan, "`limit/lower` is NaN"),
    ("limit/lower", -np.inf, "`limit/lower` is not finite (-inf)"),
    ("limit/upper", np.inf, "`limit/upper` is not finite (inf)"),
    ("limit/strength", np.nan, "`limit/strength` is NaN"),
    ("limit/strength", np.inf, "`limit/strength` is not finite (inf)"),
    ("limit/strength", -1.0, "`limit/strength`: negative strength -1.0"),
    ("{offset}", np.nan, "`{offset}` is NaN"),
    ("{offset}", -np.inf, "`{offset}` is not finite (-inf)"),
]
LOCAL_FAULTS = [
    ("l_position1", [0.0, 0.0, np.inf], "`l_position1` is not finite ([0.0, 0.0, inf])"),
    ("l_position1", [np.nan, 0.0, 1.0], "`l_position1` is NaN ([nan, 0.0, 1.0])"),  # not "zero length"
    ("l_position0", [0.0, -np.inf, 0.0], "`l_position0` is not finite ([0.0, -inf, 0.0])"),
    ("r_position0", [np.nan, 0.0, 0.0], "`r_position0` is NaN"),
    ("r_position1", [0.0, np.inf, 0.0], "`r_position1` is not finite"),  # unused by 669, still a number the service reads
]


def case_scene(uid: int, local: bool) -> tuple[Any, Any]:
    """The hinge-and-slider scene and the joint geometry slot of constitution `uid`."""
    scene, _, (hs, ss) = hinge_and_slider_scene(local)
    return scene, hs if uid == 670 else ss


@pytest.mark.parametrize("local", [False, True], ids=["world", "local"])
@pytest.mark.parametrize("uid", [670, 669])
@pytest.mark.parametrize("name,value,words", EDGE_FAULTS)
def test_a_bad_limit_strength_or_offset_is_named_by_geometry_and_edge(uid, local, name, value, words):
    scene, slot = case_scene(uid, local)
    name, words = name.format(offset=OFFSET[uid]), words.format(offset=OFFSET[uid])
    write(slot.geometry().edges().find(name), EDGE, value)
    e = refused(scene)
    assert (e.geometry_id, e.edge) == (slot.id(), EDGE)
    assert words in e.msg, e.msg


@pytest.mark.parametrize("uid", [670, 669])
def test_a_missing_offset_is_named_as_the_engine_refuses_it(uid):
    """The base joints' `do_init` asserts `init_angle` / `init_distance` on the edges (libuipc 619a541,
    affine_body_{revolute,prismatic}_joint.cu); without it the adapter read an offset of 0."""
    scene, slot = case_scene(uid, False)
    slot.geometry().edges().destroy(OFFSET[uid])
    e = refused(scene)
    assert e.geometry_id == slot.id() and f"the joint edges have no `{OFFSET[uid]}` attribute" in e.msg, e.msg


@pytest.mark.parametrize("local", [False, True], ids=["world", "local"])
@pytest.mark.parametrize("uid", [670, 669])
def test_an_empty_range_is_named_as_the_engine_refuses_it(uid, local):
    scene, slot = case_scene(uid, local)
    edges = slot.geometry().edges()
    write(edges.find("limit/upper"), EDGE, 0.2)
    write(edges.find("limit/lower"), EDGE, 0.5)
    e = refused(scene)
    assert (e.geometry_id, e.edge) == (slot.id(), EDGE)
    assert "`limit/lower` 0.5 > `limit/upper` 0.2: an empty range" in e.msg, e.msg


@pytest.mark.parametrize("local", [False, True], ids=["world", "local"])
@pytest.mark.parametrize("uid", [670, 669])
def test_a_body_jointed_to_itself_is_named(uid, local):
    scene, slot = case_scene(uid, local)
    edges = slot.geometry().edges()
    g, i = (int(np.asarray(edges.find(n).view()).ravel()[EDGE]) for n in ("l_geo_id", "l_inst_id"))
    for n, v in (("r_geo_id", g), ("r_inst_id", i)):
        a = np.array(edges.find(n).view())
        a.ravel()[EDGE] = v
        view(edges.find(n))[:] = a
    e = refused(scene)
    assert (e.geometry_id, e.edge) == (slot.id(), EDGE)
    assert f"body (geometry {g}, instance {i}) is jointed to itself" in e.msg, e.msg


@pytest.mark.parametrize("uid", [670, 669])
@pytest.mark.parametrize("name,value,words", LOCAL_FAULTS)
def test_a_non_finite_local_edge_is_named(uid, name, value, words):
    scene, slot = case_scene(uid, local=True)
    write(slot.geometry().edges().find(name), EDGE, value)
    e = refused(scene)
    assert (e.geometry_id, e.edge) == (slot.id(), EDGE)
    assert words in e.msg and "zero length" not in e.msg, e.msg


@pytest.mark.parametrize("end", [0, 1])
@pytest.mark.parametrize("value,words", [(np.nan, "is NaN"), (np.inf, "is not finite")])
@pytest.mark.parametrize("uid", [670, 669])
def test_a_non_finite_vertex_of_a_world_edge_is_named(uid, value, words, end):
    scene, slot = case_scene(uid, local=False)
    geo = slot.geometry()
    vertex = int(np.asarray(geo.edges().topo().view()).reshape(-1, 2)[EDGE, end])
    write(geo.positions(), vertex, [0.0, value, 0.0])
    e = refused(scene)
    assert (e.geometry_id, e.edge) == (slot.id(), EDGE)
    assert f"`position` of vertex {vertex} {words}" in e.msg and "zero length" not in e.msg, e.msg


def test_a_nan_committed_angle_is_named_when_it_is_read():
    scene, slot = case_scene(670, local=False)
    write(slot.geometry().edges().find("angle"), EDGE, np.nan)
    e = refused(scene, committed=True)
    assert (e.geometry_id, e.edge, e.msg) == (slot.id(), EDGE, "`angle` is NaN")
    request_from_scene(scene, committed=False)  # not read: not refused


def test_what_the_engine_and_the_service_take_passes():
    """No more than they refuse: a zero-width range, zero strength, -0.0, a NaN `distance` (669's
    published slide, which the adapter does not read), a NaN vertex on no edge."""
    scene, (a, b), (hs, ss) = hinge_and_slider_scene(local=False)
    for slot in (hs, ss):
        edges = slot.geometry().edges()
        write(edges.find("limit/lower"), EDGE, 0.1)
        write(edges.find("limit/upper"), EDGE, 0.1)
        write(edges.find("limit/strength"), 0, 0.0)
        write(edges.find("limit/strength"), EDGE, -0.0)
    write(ss.geometry().edges().find("distance"), EDGE, np.nan)
    geo = hs.geometry()
    n = geo.positions().size()
    geo.vertices().resize(n + 1)  # a vertex on no edge: the engine reads only the edges' vertices
    write(geo.positions(), n, [np.nan, 0.0, 0.0])
    req, _ = request_from_scene(scene)
    assert all(np.isfinite(b.energy).all() for b in LocalClient().evaluate(req).batches)
