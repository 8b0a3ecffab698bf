"""A session reopened at each point of its life is bitwise the session that never dropped: at once after the
opening, after an offset update and after a limits update with no commit yet, after a commit, after a commit
then an offset update, twice in a row. On scenes the state tests (test_session_reference.py) do not have: two
revolute batches of which only one was opened with `prev_coordinate` (the SDK sends a batch's coordinates on a
reopen before the first commit only if it was opened with them: `SessionState.request_for_reopen`), a
prismatic-only scene (no state at all, yet `q_prev` moves with each commit), and the absolute origin with offsets
of 1e6. The reopened sessions and the uninterrupted one are compared on every evaluation, commit and coordinate."""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.client import Client, LocalClient
from tests.conftest import same_evaluation
from tests.http.test_contract_live import live  # noqa: F401 (the fixture)
from tests.scenes import random_chain_scene, random_rotation, rigid_motion

# (name, the batches' constitutions, offsets per revolute batch, prev_coordinate per revolute batch, origin)
SCENES = {
    "two revolute batches, one opened with prev_coordinate": ((670, 669, 670), (1e6, -2.9), (True, False), "q_ref"),
    "prismatic only": ((669, 669), (), (), "q_ref"),
    "absolute origin, offsets of 1e6": ((670, 669), (-1e6,), (False,), "absolute"),
}


def _request(uids, offsets, prevs, origin, seed=7) -> tuple[dict, np.ndarray]:
    sc = random_chain_scene(np.random.default_rng(seed), n_bodies=5, batch_uids=uids, extra_joints=2)
    doc = sc.request()
    doc["bodies"]["q"] = doc["bodies"]["q_prev"]
    revolute = iter(zip(offsets, prevs))
    for b in doc["batches"]:
        n = len(b["body_ids"])
        b["origin"] = origin
        b["lower"], b["upper"] = [-0.2] * n, [0.2] * n  # most joints outside their range once the bodies turn
        if b["constitution_uid"] == 670:
            offset, prev = next(revolute)
            b["offset"] = [offset * (k + 1) for k in range(n)]
            b["lower"] = [o - 0.2 for o in b["offset"]]
            b["upper"] = [o + 0.2 for o in b["offset"]]
            if prev:  # 3 turns out, and off the offset by a fraction
                b["prev_coordinate"] = [o + 6 * np.pi + 0.1 * k for k, o in enumerate(b["offset"])]
        else:
            b["offset"] = [0.5] * n
            b["lower"], b["upper"] = [0.3] * n, [0.7] * n
    return doc, np.array(doc["bodies"]["q_prev"])


def _poses(q0: np.ndarray, n: int, seed: int = 3) -> list[np.ndarray]:
    """`n` poses from `q0`: each body turned (< pi per step, the commit rule's premise) and moved a little."""
    rng, q, out = np.random.default_rng(seed), q0.copy(), []
    for _ in range(n):
        q = np.stack([rigid_motion(qk[None], random_rotation(rng, 2.5), rng.normal(0, 0.05, 3))[0] for qk in q])
        out.append(q)
    return out


def _run(sessions: dict, q0: np.ndarray, uids) -> None:
    """Drive every session the same way; those named `... reopened` reopen at each point; compare with "local"."""
    poses = iter(_poses(q0, 8))
    revolute = [k for k, u in enumerate(uids) if u == 670]
    last = len(uids) - 1  # the batch whose limits are updated (revolute or prismatic: any)

    def reopen():
        for name, s in sessions.items():
            if name.endswith("reopened"):
                s.reopen()

    def check_evaluate():
        q = next(poses)
        got = {name: s.evaluate(q) for name, s in sessions.items()}
        for name, ev in got.items():
            same_evaluation(ev, got["local"])
        return got["local"]

    def check_coordinates():
        want = sessions["local"].coordinates
        for name, s in sessions.items():
            assert [c.tobytes() for c in s.coordinates] == [c.tobytes() for c in want], name

    def update(batch, **values):
        for s in sessions.values():
            s.update(batch, [0, 1][: len(next(iter(values.values())))], **values)
        check_coordinates()

    def commit():
        q = next(poses)
        got = {name: s.commit(q) for name, s in sessions.items()}
        for name, c in got.items():
            assert [a.tobytes() for a in c] == [a.tobytes() for a in got["local"]], name

    reopen()  # at once after the opening
    check_evaluate()
    b = revolute[0] if revolute else 0
    update(b, offset=[3.25, -1.5])  # an offset update, no commit yet
    reopen()
    check_evaluate()
    update(last, lower=[-0.1], upper=[0.05])  # a limits update, no commit yet
    reopen()
    check_evaluate()
    commit()
    reopen()
    check_coordinates()
    check_evaluate()
    update(revolute[-1] if revolute else 1, offset=[1e6 + 0.1])  # after a commit: the committed angle stays
    reopen()
    reopen()  # twice in a row
    check_coordinates()
    check_evaluate()
    commit()
    update(b, offset=[-7.5, 2.0], lower=[-8.0, 1.5], upper=[-7.0, 2.5])
    reopen()
    check_coordinates()
    ev = check_evaluate()
    assert ev.total_energy > 0  # a scene whose joints are outside their ranges: the derivatives were compared too
    for s in sessions.values():
        s.close()


@pytest.mark.parametrize("scene", list(SCENES))
def test_a_local_session_reopened_at_every_point_is_the_uninterrupted_one(scene):
    uids, offsets, prevs, origin = SCENES[scene]
    doc, q0 = _request(uids, offsets, prevs, origin)
    c = LocalClient()
    _run({"local": c.session(doc), "local reopened": c.session(doc)}, q0, uids)


@pytest.mark.parametrize("scene", list(SCENES)[:2])
def test_live_sessions_reopened_at_every_point_are_the_uninterrupted_one(live, scene):  # noqa: F811
    """The same over a live server, msgpack and JSON: the reopen sends what the client kept, over the wire."""
    uids, offsets, prevs, origin = SCENES[scene]
    doc, q0 = _request(uids, offsets, prevs, origin)
    sessions = {"local": LocalClient().session(doc)}
    for binary, name in ((True, "msgpack"), (False, "json")):
        sessions[f"{name} reopened"] = Client(live, binary=binary).session(doc)
    _run(sessions, q0, uids)
