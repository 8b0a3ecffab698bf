"""`Scene._check`'s plain-Python path (a limit's numbers all floats) agrees with the full validation it skips.

Two `Scene`s take the same calls: today's, and today's with the plain path switched off (every limit through the
service's `check_joints`). (A third, the file before the plain-Python rewrite, `93e91b1^`, agreed too when this was
written; it is not kept: a file from the history breaks the test when its imports move on.) Each call either passes all three ways with the same request (bitwise, and the same handle) or raises the same
exception with the same faults (loc, msg, type). The inputs are random and adversarial: floats, np.float64,
np.float32, ints, bools, 0-d and 1-element arrays, -0.0, NaN, infinities, 1e308 (differences overflow),
lower == upper, lower > upper, negative strengths, offsets that make `lower - offset` overflow, equal, tiny
(1e-310) and huge edges, bodies out of range or equal or not integers, unknown origins and constitutions,
`prev_coordinate` given to a prismatic limit.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from jointlimits.client import scene as today
from jointlimits.client.errors import InvalidInput



def module(name: str, source: str, tmp: Path):
    path = tmp / f"{name}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("scenes")
    now = Path(today.__file__).read_text()
    assert now.count("        plain = (") == 1
    full = module("scene_full_check", now.replace("        plain = (", "        plain = False and ("), tmp)
    return today.Scene, full.Scene


SPECIAL = [0.0, -0.0, 1.0, -1.0, 0.5, 1e308, -1e308, 1.7e308, float("nan"), float("inf"), -float("inf"), 5e-324,
           1e-310, 2.0**53 + 1, 3e38, 4e38]
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
raw = st.one_of(st.sampled_from(SPECIAL), finite, st.floats(-10, 10))


@st.composite
def numbers(draw) -> object:
    """One number in one of the forms a caller may pass."""
    v = draw(raw)
    form = draw(st.sampled_from(["float"] * 4 + ["f64"] * 3 + ["f32", "int", "bool", "0d", "list", "arr1", "i64"]))
    if form == "float":
        return v
    if form == "f64":
        return np.float64(v)
    if form == "f32":
        with np.errstate(over="ignore"):
            return np.float32(v)
    if form in ("int", "i64"):
        if not np.isfinite(v):
            return v
        return int(v) if form == "int" or abs(v) >= 2**63 else np.int64(int(v))
    if form == "bool":
        return draw(st.booleans())
    if form == "0d":
        return np.array(v)
    return [v] if form == "list" else np.array([v])


point = st.one_of(st.lists(raw, min_size=3, max_size=3), st.sampled_from([[0, 0, 0], [1, 1, 1], [1e308, -1e308, 0]]))


@st.composite
def limits(draw) -> tuple[str, tuple, dict]:
    kind = draw(st.sampled_from(["revolute", "revolute", "prismatic", "prismatic", "other"]))
    i = draw(st.sampled_from([0, 1, 2, 3, -1, np.int64(1), True, 1.0]))
    j = draw(st.sampled_from([0, 1, 2, 3, -1, np.int64(2), 2]))
    lo = draw(numbers())
    up = draw(st.one_of(numbers(), st.just(lo)))
    kw = dict(lower=lo, upper=up, strength=draw(st.one_of(numbers(), st.just(1.0), st.just(-1.0))),
              offset=draw(st.one_of(st.just(0.0), numbers())),
              origin=draw(st.sampled_from(["q_ref", "q_ref", "absolute", "elsewhere"])))
    if draw(st.booleans()):
        p0 = draw(point)
        p1 = draw(st.one_of(point, st.just(list(p0)), st.builds(lambda p: [p[0] + 1e-310, p[1], p[2]], st.just(p0))))
        kw |= dict(p0=p0, p1=p1)
    else:
        l0, r0 = draw(point), draw(point)
        l1 = draw(st.one_of(point, st.just(list(l0))))
        kw["local_edge"] = [[l0, l1], [r0, draw(point)]]
    if draw(st.integers(0, 3)) == 0:  # to a prismatic limit too: its fault
        kw["prev_coordinate"] = draw(numbers())
    if kind == "other":
        return "add_limit", (draw(st.sampled_from([670, 669, 999])), i, j), kw
    if kind == "prismatic" and "prev_coordinate" in kw:  # not its argument: through add_limit
        return "add_limit", (669, i, j), kw
    return f"add_{kind}_limit", (i, j), kw


def outcome(scene, call: tuple[str, tuple, dict]) -> tuple:
    name, args, kw = call
    try:
        h = getattr(scene, name)(*args, **kw)
    except InvalidInput as e:
        return ("InvalidInput", e.status, tuple((f.loc, f.msg, f.type) for f in e.faults), str(e))
    except (TypeError, ValueError) as e:
        return (type(e).__name__, str(e))
    request = scene.request()
    arrays = tuple((b.constitution_uid, b.base_uid, b.origin) + tuple(
        None if getattr(b, k) is None else (np.asarray(getattr(b, k)).dtype.str, np.asarray(getattr(b, k)).tobytes())
        for k in ("body_ids", "edges", "local_edges", "lower", "upper", "strength", "offset", "prev_coordinate"))
        for b in request.batches)
    return ("ok", int(h), h.constitution_uid, h.batch, repr(h.key), arrays)


@st.composite
def near_valid(draw) -> tuple[str, tuple, dict]:
    """A limit every check passes, as floats (the plain path's input), with at most one argument from `limits`."""
    f = lambda a, b: draw(st.sampled_from([float, np.float64]))(draw(st.floats(a, b)))  # noqa: E731
    lo = f(-10, 10)
    kw = dict(lower=lo, upper=draw(st.one_of(st.just(lo), st.builds(lambda d: lo + d, st.floats(0, 10)))),
              strength=f(0, 1e3), offset=f(-5, 5), p0=[f(-9, 9) for _ in range(3)])
    kw["p1"] = [kw["p0"][0] + draw(st.sampled_from([1.0, -2.5, 1e-300, 1e-9])), kw["p0"][1], kw["p0"][2]]
    if draw(st.booleans()):
        kw["local_edge"] = [[kw.pop("p0"), kw.pop("p1")], [[f(-9, 9) for _ in range(3)] for _ in range(2)]]
    name = draw(st.sampled_from(["add_revolute_limit", "add_prismatic_limit"]))
    if name == "add_revolute_limit" and draw(st.booleans()):
        kw["prev_coordinate"] = f(-50, 50)
    args = draw(st.sampled_from([(0, 1), (2, 1), (1, 0)]))
    if draw(st.booleans()):  # one argument from the adversarial draw
        bad_name, bad_args, bad = draw(limits())
        key = draw(st.sampled_from(["ids", "origin", "lower", "upper", "strength", "offset", "edge", "prev_coordinate"]))
        if key == "ids":
            args = bad_args[-2:]
        elif key == "edge":
            for k in ("p0", "p1", "local_edge"):
                kw.pop(k, None)
            kw |= {k: bad[k] for k in ("p0", "p1", "local_edge") if k in bad}
        elif key in bad:
            kw[key] = bad[key]
        if "prev_coordinate" in kw and name == "add_prismatic_limit":
            return "add_limit", (669, *args), kw
    return name, args, kw


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.one_of(limits(), near_valid(), near_valid()), min_size=1, max_size=4))
def test_the_plain_path_and_the_full_check_agree(scenes, calls):
    made = []
    for Scene in scenes:
        s = Scene()
        for _ in range(3):
            s.add_body(np.eye(4))
        made.append(s)
    for call in calls:
        got = [outcome(s, call) for s in made]
        event(got[0][0])
        assert got[0] == got[1], call  # today's with and without the plain path


def test_the_comparison_sees_a_difference(scenes):
    """The harness can fail: a limit with lower > upper passes a scene whose checks are all skipped."""
    fast, full = scenes
    blind = fast()
    blind._check = lambda uid, where, ids, kind, edge, origin, numbers, prev=None: [float(v) for v in numbers]
    checked = full()
    for s in (blind, checked):
        s.add_body(np.eye(4)), s.add_body(np.eye(4))
    call = ("add_revolute_limit", (0, 1), dict(p0=[0, 0, 0], p1=[0, 0, 1], lower=1.0, upper=0.0))
    assert outcome(blind, call)[0] == "ok" and outcome(checked, call)[0] == "InvalidInput"


def test_a_local_edge_array_changed_after_the_call_changes_nothing():
    """A float64 `local_edge` array was kept by reference: a caller reusing one array for each joint (filled in
    place in a loop) gave every joint the last one's edge (the first joint's handle then raised KeyError, and
    the request's arrays were silently another scene's)."""
    from jointlimits import LocalClient

    s = today.Scene()
    a, b, c = (s.add_body(np.eye(4)) for _ in range(3))
    e = np.array([[[0, 0, 0], [0, 0, 1.0]], [[0, 0, 0], [0, 0, 1.0]]])
    first = s.add_revolute_limit(a, b, lower=-1.0, upper=1.0, local_edge=e)
    e[:, 1] = [1.0, 0, 0]
    second = s.add_revolute_limit(b, c, lower=-1.0, upper=1.0, local_edge=e)
    e[:] = np.nan
    request = s.request()
    assert request.batches[0].local_edges[:, 0, 1].tolist() == [[0, 0, 1.0], [1.0, 0, 0]]
    answer = LocalClient().evaluate(request)
    assert answer.joint(first).x == answer.joint(second).x == 0.0
