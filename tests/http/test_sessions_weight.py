"""Everything a session holds is counted (issue 19): its prepared scene's bodies go against
JOINTLIMITS_MAX_SESSION_JOINTS with its joints (a body counts as 4/3 joint, `sizing.session_weight`), so the
sessions of a worker stay within `768 B x MAX_SESSION_JOINTS`, the sizing rule's term, whatever their mix."""

from __future__ import annotations

import gc
import json
import tracemalloc

import numpy as np
import pytest

from jointlimits.client.local import core_batches
from jointlimits.schemas import session as proto
from jointlimits.service import sizing
from jointlimits.service.core import Bodies
from jointlimits.service.core.prepared import prepare
from tests.drills import array_scene, scene
from tests.http.test_sessions import PATH, Json, app, closed


def many_bodies(n_bodies: int) -> dict:
    """A 1-joint scene (JSON) with `n_bodies` bodies: the joint on the first two, the rest at rest."""
    doc = scene(1, seed=5)
    for k in ("q", "q_prev", "q_ref"):
        rows = doc["bodies"][k]
        doc["bodies"][k] = rows + [rows[0]] * (n_bodies - len(rows))
    return doc


def test_a_scene_of_bodies_weighs_its_bodies():
    doc = many_bodies(3000)
    weight = sizing.session_weight(1, 3000)
    assert weight == 1 + 4000
    c = app(max_session_joints=weight - 1)
    with c.websocket_connect(PATH) as ws:
        reply = Json(ws).send(doc)
        assert reply["kind"] == "error" and reply["status"] == 413, reply
        assert reply["detail"][0]["loc"] == ["body", "bodies"] and "3000 bodies" in reply["detail"][0]["msg"]
        assert closed(ws)["code"] == proto.SCENE_TOO_LARGE
    c = app(max_session_joints=weight)
    with c.websocket_connect(PATH) as ws:
        assert Json(ws).send(doc)["kind"] == "opened"
        with c.websocket_connect(PATH) as second:  # the first holds the whole bound: even 1 joint and 2 bodies wait
            reply = Json(second).send(scene(1, seed=5))
            assert reply["status"] == 413 and "JOINTLIMITS_MAX_SESSION_JOINTS" in reply["detail"][0]["msg"]
    with c.websocket_connect(PATH) as ws:  # given back when the first closed
        assert Json(ws).send(doc)["kind"] == "opened"


@pytest.mark.parametrize("joints,bodies", [(1, 20_000), (20_000, 40_000), (20_000, 2)])
def test_the_weight_bounds_what_a_prepared_scene_holds(joints, bodies):
    """Bytes a prepared scene allocates (tracemalloc) plus its input rows, against the weight in bytes."""
    req = array_scene(joints, pairs=max(1, min(joints, bodies // 2)))
    reps = -(-bodies // len(req.q))
    tile = lambda a: np.tile(np.asarray(a, dtype=np.float64), (reps, 1))[:bodies].copy()  # noqa: E731
    b = Bodies(tile(req.q), tile(req.q_prev), tile(req.q_ref))
    batches = core_batches(req, copy=True)
    gc.collect()
    tracemalloc.start()
    try:
        kept = prepare(b, batches)
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    inputs = 3 * b.q.nbytes + sum(j.body_ids.nbytes + j.edges.nbytes + 3 * j.lower.nbytes for j in batches)
    assert kept is not None
    assert held + inputs <= sizing.SESSION_BYTES_PER_JOINT * sizing.session_weight(joints, bodies), (held, inputs)


def test_the_worker_rule_still_counts_sessions_by_the_bound():
    from jointlimits.service.settings import Settings

    s = Settings(max_session_joints=1000)
    assert sizing.worker_bytes(s) - sizing.worker_bytes(Settings(max_session_joints=0)) == 768 * 1000
    assert json.dumps(sizing.session_weight(0, 3)) == "4"  # rounded up


def test_a_sessions_json_messages_are_bounded_in_values_before_they_are_parsed(monkeypatch):
    """JOINTLIMITS_MAX_JSON_VALUES bounds every JSON text the service parses, a session's messages too: the in-flight
    budget charges an opening by it (`sizing.cost_before_body`), and without it a 63 MiB opening of empty batches
    took +1.7 GB to parse and refuse, a 63 MiB `q` of zeros +0.7 GB. Its batches are counted by their braces,
    as a request's."""
    from jointlimits.service.http import convert

    doc = scene(2, seed=5)
    values = json.dumps(doc).count(",") + 1
    c = app(max_json_values=values - 1, max_batches=len(doc["batches"]) - 1)
    with c.websocket_connect(PATH) as ws:
        monkeypatch.setattr(convert, "from_json", lambda *a: pytest.fail("parsed"))
        reply = Json(ws).send({**doc, "id": 4})
        assert reply["status"] == 413 and reply["detail"][0]["loc"] == ["body"] and "id" not in reply, reply
        assert f"holds up to {values + 1} values" in reply["detail"][0]["msg"]  # the `id` adds one
        close = closed(ws)  # an opening over a request's bounds, as over its joints; the reason names the bound
        assert close["code"] == proto.SCENE_TOO_LARGE and f"holds up to {values + 1} values" in close["reason"], close
    c = app(max_json_values=values, max_batches=len(doc["batches"]) - 1)
    with c.websocket_connect(PATH) as ws:
        reply = Json(ws).send(doc)
        assert reply["status"] == 413 and "(counted by their braces)" in reply["detail"][0]["msg"], reply
    monkeypatch.undo()
    c = app(max_json_values=values)
    with c.websocket_connect(PATH) as ws:
        s = Json(ws)
        assert s.send(doc)["kind"] == "opened"
        monkeypatch.setattr(convert, "from_json", lambda *a: pytest.fail("parsed"))
        q = doc["bodies"]["q"]
        reply = s.send({"kind": "evaluate", "q": q * (values // (12 * len(q)) + 1)})
        assert reply["status"] == 413 and "JOINTLIMITS_MAX_JSON_VALUES" in reply["detail"][0]["msg"], reply
        monkeypatch.undo()
        assert s.send({"kind": "evaluate", "q": q, "id": 1})["kind"] == "evaluation"  # the session stays as it was
