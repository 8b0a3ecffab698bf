"""The SDK's composite paths give the plain one-shot call's numbers (`LocalClient().evaluate`).

- a request split into parts (client/split.py) and merged: every joint's `x`, `energy`, `gradient`, `hessian`,
  `coordinate` and `index` bitwise the whole request's; `total_energy` and the per-body sums of
  `layout="bodies"` (a body shared by parts) within the bound of their summation order (`_summed`);
- the same request by msgpack, JSON and in-process: bitwise;
- a session's evaluate / commit / update against the stateless request those calls imply (`q_prev` the
  committed `q`, `prev_coordinate` the committed coordinate, the updated fields), over turns past +-pi.

Scenes (`wire`) mix both constitutions over several batches, world and body-local edges, both origins, offsets,
prev_coordinate, joints past their limits by tiny and huge gaps, exact and psd, active_only on and off.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from jointlimits.client import Client, LocalClient, split
from jointlimits.client.model import as_request
from tests.conftest import same_joints
from tests.http.test_contract_live import live  # noqa: F401 (the fixture)
from tests.scenes import place_limits, random_chain_scene, random_scene, random_unit, rotation_about

EPS = np.finfo(np.float64).eps


def wire(rng: np.random.Generator, big: bool) -> dict:
    """A random wire request over the option space (always valid: every scene evaluates); some joints past a
    limit by tiny (down to 5e-324) or huge gaps, the others `place_limits`' well-conditioned ones (>= 0.05)."""
    if big:
        uids = tuple(int(u) for u in rng.choice([670, 669], size=int(rng.integers(1, 5))))
        sc = place_limits(random_chain_scene(rng, n_bodies=int(rng.integers(6, 14)),
                                             extra_joints=int(rng.integers(3, 20)), batch_uids=uids), rng)
    else:
        sc = random_scene(rng)
    d = sc.request(hessian_mode=str(rng.choice(["exact", "psd"])), active_only=bool(rng.integers(2)))
    for x, b, joints in zip(sc.x(), d["batches"], sc.batches):
        n = len(x)
        lo, up = np.array(b["lower"]), np.array(b["upper"])
        past = rng.uniform(size=n) < 0.5
        if rng.uniform() < 0.3:  # above the upper limit by a tiny gap (down to the smallest subnormal)
            up = np.where(past, x - rng.choice([5e-324, 1e-300, 1e-15, 1e-9], size=n), up)
            lo = np.minimum(lo, up)
        elif rng.uniform() < 0.4:  # below the lower one by a huge (or tiny) gap
            lo = np.where(past, x + rng.choice([1e6, 1e3, 1e-12], size=n), lo)
            up = np.maximum(lo, up)
        if rng.uniform() < 0.5:
            off = rng.uniform(-7.0, 7.0, size=n)
            b["offset"] = off.tolist()
            lo, up = lo + off, up + off
        b["lower"], b["upper"] = lo.tolist(), up.tolist()
        if b["constitution_uid"] == 670 and rng.uniform() < 0.5:
            b["prev_coordinate"] = rng.uniform(-12.0, 12.0, size=n).tolist()
        if rng.uniform() < 0.3:
            b["origin"] = "absolute"
        if rng.uniform() < 0.3:  # the same edges in each body's own coordinates at q_ref
            ref = sc.q_ref[joints.body_ids]  # (N, 2, 12): l = A_ref^-1 (e - p_ref), per body and end
            p, A = ref[..., :3], ref[..., 3:].reshape(n, 2, 3, 3)
            local = np.linalg.solve(A[:, :, None], (joints.edges[:, None] - p[:, :, None])[..., None])[..., 0]
            del b["edges"]
            b["local_edges"] = local.tolist()
    if rng.uniform() < 0.3:
        d["layout"] = "bodies"
    if rng.uniform() < 0.2:
        d["outputs"] = [str(o) for o in rng.choice(["energy", "gradient", "hessian"], size=int(rng.integers(1, 3)),
                                                  replace=False)]
    return d


def scenes(seed: int, n: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [wire(rng, big=bool(k % 2)) for k in range(n)]


def _summed(got: np.ndarray, want: np.ndarray, terms: np.ndarray, count: int) -> None:
    """`got` and `want` sum the same `count` terms per entry in other orders; `terms` bounds the sum of their
    absolute values per entry. Any order of a sum of m terms is within (m - 1) eps sum|terms| of the exact sum
    (Higham, 4.2), so two orders are within 2 (m - 1) eps sum|terms| of each other (+ the tiniest subnormal)."""
    assert got.shape == want.shape
    bound = 2 * max(count - 1, 1) * EPS * terms + 5e-324
    assert np.all(np.abs(got - want) <= bound), float(np.max(np.abs(got - want) - bound))


def merged_as_whole(req, got, want) -> None:
    """A merged answer against the whole request's: joints bitwise, sums within their order's bound."""
    same_joints(got, want)
    energies = [np.abs(r.energy).sum() for r in want.batches if r.energy is not None]
    if energies:  # total_energy sums every joint's energy (>= 0): one sum of n_joints terms
        _summed(np.float64(got.total_energy), np.float64(want.total_energy), np.float64(sum(energies)), req.n_joints)
    else:
        assert got.total_energy == want.total_energy
    if want.assembled is None:
        assert got.assembled is None
        return
    # The per-body sums: bounded by the same sums of absolute values, from the joints' own answers.
    joints = LocalClient().evaluate(as_request({**_wire_of(req), "layout": "joints", "active_only": False}))
    n = want.assembled.n_bodies
    ga, wa = got.assembled, want.assembled
    abs_g, count = np.zeros((n, 12)), np.zeros(n, np.int64)
    blocks: dict[tuple[int, int], np.ndarray] = {}
    for b, r in zip(req.batches, joints.batches):
        ids = np.asarray(b.body_ids)
        np.add.at(count, ids.reshape(-1), 1)
        if r.gradient is not None:
            np.add.at(abs_g, ids.reshape(-1), np.abs(r.gradient).reshape(-1, 12))
        if r.hessian is not None:
            H = np.abs(r.hessian).reshape(-1, 2, 12, 2, 12)
            for k, (i, j) in enumerate(ids):
                for s, t in ((0, 0), (1, 1), (0, 1)):
                    key, h = ((ids[k, s], ids[k, t]), H[k, s, :, t]) if ids[k, s] <= ids[k, t] else \
                        ((ids[k, t], ids[k, s]), H[k, t, :, s])
                    blocks[key] = blocks.get(key, 0.0) + h
    if wa.gradient is not None:
        _summed(ga.gradient, wa.gradient, abs_g, int(count.max(initial=1)))
    if wa.blocks is not None:
        assert ga.rows.tobytes() == wa.rows.tobytes() and ga.cols.tobytes() == wa.cols.tobytes()
        terms = np.stack([blocks.get((int(i), int(j)), np.zeros((12, 12))) for i, j in zip(wa.rows, wa.cols)]) \
            if len(wa.rows) else np.zeros((0, 12, 12))
        _summed(ga.blocks, wa.blocks, terms, 3 * int(count.max(initial=1)))


def _wire_of(req) -> dict:
    """A `Request` back as a wire dict (arrays as lists)."""
    batches = []
    for b in req.batches:
        d = {"constitution_uid": b.constitution_uid, "base_uid": b.base_uid, "origin": b.origin}
        for k in ("body_ids", "edges", "local_edges", "lower", "upper", "strength", "offset", "prev_coordinate"):
            if getattr(b, k) is not None:
                d[k] = np.asarray(getattr(b, k)).tolist()
        batches.append(d)
    return {"bodies": {k: np.asarray(getattr(req, k)).tolist() for k in ("q", "q_prev", "q_ref")},
            "batches": batches, "outputs": list(req.outputs), "hessian_mode": req.hessian_mode,
            "active_only": req.active_only, "layout": req.layout}


@pytest.mark.parametrize("seed", range(4))
def test_parts_of_any_size_merge_to_the_whole_answer(seed):
    """In-process, so that many scenes and part sizes are cheap: each joint's answer must not depend on which
    other joints share its request (a psd revolute Hessian did, by 1 ulp: einsum sums a lone joint's
    |g_c|^2 in another order than a batch's)."""
    local = LocalClient()
    for d in scenes(seed, 12):
        req = as_request(d)
        want = local.evaluate(req)
        for size in (1, 2, 3, 7):
            parts = split.plan(req, size)
            got = split.merge(req, parts, [local.evaluate(p.request) for p in parts]).sized(req)
            merged_as_whole(req, got, want)


@pytest.mark.parametrize("binary", [True, False], ids=["msgpack", "json"])
def test_split_over_http_merges_to_the_in_process_answer(live, binary):  # noqa: F811
    """`Client` against the server, whole (bitwise the in-process answer, total and sums included) and in parts
    of 1 and 3 joints (`max_joints_per_request`), from a dict and from a `Request`."""
    local = LocalClient()
    clients = {k: Client(live, binary=binary, max_joints_per_request=k) for k in (None, 1, 3)}
    for d in scenes(10 + binary, 6):
        req = as_request(d)
        want = local.evaluate(req)
        for k, client in clients.items():
            for given in (d, req):
                got = client.evaluate(given)
                if k is None:
                    same_joints(got, want)
                    assert got.total_energy == want.total_energy
                    if want.assembled is not None:
                        for f in ("gradient", "rows", "cols", "blocks"):
                            a, b = getattr(got.assembled, f), getattr(want.assembled, f)
                            assert (a is None) == (b is None) and (a is None or a.tobytes() == b.tobytes()), f
                else:
                    merged_as_whole(req, got, want)


def _turned(q0: np.ndarray, axes: list[np.ndarray], speed: np.ndarray, angle: float) -> np.ndarray:
    q = q0.copy()
    for b, (axis, w) in enumerate(zip(axes, speed)):
        R = rotation_about(axis, angle * w)
        q[b, :3] = R @ q0[b, :3]
        q[b, 3:] = (R @ q0[b, 3:].reshape(3, 3)).reshape(9)
    return q


@pytest.mark.parametrize("seed", range(3))
def test_a_session_answers_as_the_stateless_request_of_its_state(seed):
    """evaluate / commit / update in random order, bodies turning up to ~2 turns: each evaluate against the
    stateless request with `q_prev` the last committed q, the committed coordinates as `prev_coordinate` (after
    an update of offsets, as its reply carries them), the updated limits, strengths and offsets: bitwise (both take
    the angle as `coordinate - offset`). Each commit against that request's `coordinate` at q, not bitwise:
    a commit takes `r + rem(theta(q) - r)` where the request takes `r + DeltaTheta(q, q_prev)`: two angle
    evaluations (each within a few eps of pi) and a few roundings of numbers up to max(|coordinate|, |offset|)
    (+ 2 pi): `_coordinates_close`'s 8 eps (max(|coordinate|, |offset|) + 2 pi) (18 eps of 1 seen). Limits
    past x by tiny gaps too (down to 5e-324): bitwise needs no well-conditioned penalty.
    """
    rng = np.random.default_rng(100 + seed)
    local = LocalClient()
    for k in range(8):
        d = wire(rng, big=bool(k % 2))
        d.pop("outputs", None)
        # prev_coordinate consistent with q_prev (+ whole turns): a commit's rem() then agrees with DeltaTheta.
        at_prev = copy.deepcopy(d)
        at_prev["bodies"]["q"], at_prev["active_only"] = at_prev["bodies"]["q_prev"], False
        for b in at_prev["batches"]:
            b.pop("prev_coordinate", None)
        for b, r in zip(d["batches"], local.evaluate(at_prev).batches):
            if "prev_coordinate" in b:
                b["prev_coordinate"] = (r.coordinate + 2 * np.pi * rng.integers(-2, 3, size=len(r.x))).tolist()
        state, session = copy.deepcopy(d), local.session(d)
        q0 = np.asarray(d["bodies"]["q"])
        axes, speed, angle = [random_unit(rng) for _ in q0], rng.uniform(-1.0, 1.0, size=len(q0)), 0.0
        for _ in range(14):
            angle += rng.uniform(0.1, 0.6)  # each step < pi, as the commit rule needs
            q = _turned(q0, axes, speed, angle)
            op = rng.choice(["evaluate", "commit", "update"], p=[0.45, 0.35, 0.2])
            if op == "update":
                _update(rng, session, state)
                continue
            want = local.evaluate({**state, "bodies": {**state["bodies"], "q": q.tolist()}})
            if op == "evaluate":
                got = session.evaluate(q)
                same_joints(got, want)
                assert got.total_energy == want.total_energy
            else:
                committed = session.commit(q)
                for c, w, b in zip(committed, want.batches, state["batches"]):
                    _coordinates_close(c[w.index], w.coordinate, _offset(b)[w.index])
                state["bodies"]["q_prev"] = q.tolist()
                for c, b in zip(committed, state["batches"]):
                    if b["constitution_uid"] == 670:
                        b["prev_coordinate"] = c.tolist()
        session.close()


def _update(rng: np.random.Generator, session, state: dict) -> None:
    """Some joints of one batch get new limits, strengths or offsets, in the session and in `state`."""
    b = int(rng.integers(len(state["batches"])))
    batch = state["batches"][b]
    n = len(batch["lower"])
    index = rng.choice(n, size=int(rng.integers(1, n + 1)), replace=False)
    given = {"strength": rng.uniform(1.0, 100.0, size=len(index))}
    if rng.uniform() < 0.5:
        lower = np.asarray(batch["lower"])[index] - rng.uniform(0.0, 1.0, size=len(index))
        given |= {"lower": lower, "upper": lower + rng.uniform(0.0, 2.0, size=len(index))}
    if rng.uniform() < 0.5:
        given["offset"] = rng.uniform(-5.0, 5.0, size=len(index))
    session.update(b, index, **given)
    for key, v in given.items():
        a = np.asarray(batch.get(key, np.zeros(n)), dtype=np.float64).copy()
        if key == "offset" and "prev_coordinate" in batch:  # the coordinate moves with the offset (the angle stays)
            batch["prev_coordinate"] = session.coordinates[b].tolist()  # as the update's reply carries it
        a[index] = v
        batch[key] = a.tolist()


def _offset(batch: dict) -> np.ndarray:
    return np.asarray(batch.get("offset", np.zeros(len(batch["lower"]))), dtype=np.float64)


def _coordinates_close(got: np.ndarray, want: np.ndarray, offset: np.ndarray) -> None:
    scale = np.maximum(np.abs(want), np.abs(offset)) + 2 * np.pi
    assert np.all(np.abs(got - want) <= 8 * EPS * scale)


def _pose(rng: np.random.Generator, q: np.ndarray):
    """One body's DOFs (12,) in one of the three forms `Scene.add_body` takes."""
    form = rng.integers(3)
    if form == 0:
        return q.copy()
    p, A = q[:3].copy(), q[3:].reshape(3, 3).copy()
    if form == 1:
        return (p, A)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = A, p
    return T


@pytest.mark.parametrize("seed", range(3))
def test_scene_builder_is_the_hand_written_request(seed):
    """The same joints through `Scene` (poses in any form, one `add_limit` per joint, batches as it groups them)
    and as the wire dict written by hand: every joint's answer bitwise (a joint's numbers do not depend on its
    batch), the total within its summation order's bound."""
    from jointlimits.client import Scene

    rng = np.random.default_rng(200 + seed)
    local = LocalClient()
    for k in range(8):
        d = wire(rng, big=bool(k % 2))
        want = local.evaluate(d)
        bodies = {name: np.asarray(v) for name, v in d["bodies"].items()}
        scene = Scene()
        for b in range(len(bodies["q"])):
            scene.add_body(_pose(rng, bodies["q"][b]), prev=_pose(rng, bodies["q_prev"][b]),
                           ref=_pose(rng, bodies["q_ref"][b]))
        handles = []
        for batch in d["batches"]:
            for j, (i0, i1) in enumerate(batch["body_ids"]):
                given = {"origin": batch.get("origin", "q_ref"), "strength": batch["strength"][j]}
                if "edges" in batch:
                    given["p0"], given["p1"] = batch["edges"][j]
                else:
                    given["local_edge"] = batch["local_edges"][j]
                if "offset" in batch:
                    given["offset"] = batch["offset"][j]
                if "prev_coordinate" in batch:
                    given["prev_coordinate"] = batch["prev_coordinate"][j]
                handles.append(scene.add_limit(batch["constitution_uid"], i0, i1, lower=batch["lower"][j],
                                               upper=batch["upper"][j], **given))
        req = scene.request(outputs=d.get("outputs", ("energy", "gradient", "hessian")),
                            hessian_mode=d["hessian_mode"], active_only=d["active_only"],
                            layout=d.get("layout", "joints"))
        for name in ("q", "q_prev", "q_ref"):
            assert np.asarray(getattr(req, name)).tobytes() == bodies[name].tobytes()
        got = local.evaluate(req)
        rows = [(b, j) for b, batch in enumerate(d["batches"]) for j in range(len(batch["lower"]))]
        for h, (b, j) in zip(handles, rows):
            g, w = got.joint(h), want.batches[b].joint(j)
            for f in ("x", "energy", "coordinate"):
                assert np.float64(getattr(g, f) if getattr(g, f) is not None else np.nan).tobytes() == \
                    np.float64(getattr(w, f) if getattr(w, f) is not None else np.nan).tobytes(), f
            for f in ("gradient", "hessian"):
                a, c = getattr(g, f), getattr(w, f)
                assert (a is None) == (c is None) and (a is None or a.tobytes() == c.tobytes()), f
        energies = [np.abs(r.energy).sum() for r in want.batches if r.energy is not None]
        if energies:
            _summed(np.float64(got.total_energy), np.float64(want.total_energy), np.float64(sum(energies)),
                    len(rows))


def _two_slides(strength: float, n: int = 2, pairs: list | None = None) -> dict:
    """`n` prismatic joints along x (bodies 0 and 1, or `pairs`), slid 0.5 from q_ref, beyond their range [-0.1, 0]
    by 0.4 or more: gradients of size ~`strength`, per-body sums of n of them (`layout="bodies"`)."""
    eye = np.eye(3).reshape(9).tolist()
    ref = [[0.0, 0.0, 0.0, *eye], [0.0, 0.0, 0.0, *eye], [0.0, 0.0, 0.0, *eye]]
    q = [[0.0, 0.0, 0.0, *eye], [0.5, 0.0, 0.0, *eye], [0.0, 1.0, 0.0, *eye]]
    return {"bodies": {"q": q, "q_prev": ref, "q_ref": ref},
            "batches": [{"constitution_uid": 669, "body_ids": pairs or [[0, 1]] * n,
                         "edges": [[[0, 0, 0], [1, 0, 0]]] * n, "lower": [-0.1] * n, "upper": [0.0] * n,
                         "strength": [strength] * n}],
            "layout": "bodies", "outputs": ["gradient"]}


@pytest.mark.parametrize("size", [1, 2])
def test_a_per_body_sum_that_overflows_only_once_merged_is_the_whole_requests_fault(size):
    """Each part's per-body gradient is finite (0.9 of float64's largest), their sum is not: the merge must refuse
    it as the whole request is refused (422 on `layout`, naming the body), never answer an infinity."""
    from jointlimits.client import InvalidInput

    local = LocalClient()
    one = np.abs(local.evaluate(_two_slides(1.0, 1)).assembled.gradient).max()
    d = _two_slides(0.9 * np.finfo(np.float64).max / one, 3, [[1, 2]] * 3)  # body 0 unused: parts renumber
    with pytest.raises(InvalidInput) as whole:
        local.evaluate(d)
    req = as_request(d)
    assert len(split.plan(req, size)) > 1
    with pytest.raises(InvalidInput) as merged:  # parts of 2: the first part's own sum overflows, relocated
        _in_parts(req, size)
    assert merged.value.status == whole.value.status == 422
    assert [(f.loc, f.msg, f.type) for f in merged.value.faults] == [(f.loc, f.msg, f.type) for f in whole.value.faults]


@pytest.mark.parametrize("size", [1, 2])
def test_a_total_energy_that_overflows_only_once_merged_is_the_whole_requests_fault(size):
    """Each part's total energy is finite (0.6 of float64's largest per joint), their sum is not: the merge must
    refuse it as the whole request is refused (422 on `batches`), never answer an infinity (it did)."""
    from jointlimits.client import InvalidInput

    local = LocalClient()
    energy = lambda d: {**d, "layout": "joints", "outputs": ["energy"]}  # noqa: E731
    one = local.evaluate(energy(_two_slides(1.0, 1))).total_energy
    d = energy(_two_slides(0.6 * np.finfo(np.float64).max / one, 3))
    with pytest.raises(InvalidInput) as whole:
        local.evaluate(d)
    with pytest.raises(InvalidInput) as merged:
        _in_parts(as_request(d), size)
    assert merged.value.status == whole.value.status == 422
    assert [(f.loc, f.msg, f.type) for f in merged.value.faults] == [(f.loc, f.msg, f.type) for f in whole.value.faults]


@pytest.mark.parametrize("size", [1, 2])
def test_a_parts_fault_names_the_callers_bodies(size):
    """Parts carry only their joints' bodies, renumbered; a fault whose message names a body (a joint coupling a
    body to itself, a per-body sum that overflows within the part) must name it as the caller numbered it."""
    from jointlimits.client import InvalidInput

    local = LocalClient()
    d = _two_slides(1.0, 3, [[1, 2], [2, 2], [1, 2]])
    one = np.abs(local.evaluate(_two_slides(1.0, 1)).assembled.gradient).max()
    e = _two_slides(0.9 * np.finfo(np.float64).max / one, 4, [[1, 2]] * 4)  # parts of 2 overflow on their own
    for given in (d, e) if size == 2 else (d,):
        with pytest.raises(InvalidInput) as whole:
            local.evaluate(given)
        with pytest.raises(InvalidInput) as got:
            _in_parts(as_request(given), size)
        assert [(f.loc, f.msg) for f in got.value.faults] == [(f.loc, f.msg) for f in whole.value.faults]


def test_a_parts_hessian_block_fault_names_the_callers_bodies():
    """The same for a per-body Hessian block, `(r, c)` in the message (split._renumber reads the core's words)."""
    from jointlimits.client import InvalidInput

    local = LocalClient()
    hessian = lambda d: {**d, "outputs": ["hessian"]}  # noqa: E731
    one = np.abs(local.evaluate(hessian(_two_slides(1.0, 1))).assembled.blocks).max()
    e = hessian(_two_slides(0.9 * np.finfo(np.float64).max / one, 4, [[1, 2]] * 4))  # parts of 2 overflow
    with pytest.raises(InvalidInput) as whole:
        local.evaluate(e)
    with pytest.raises(InvalidInput) as got:
        _in_parts(as_request(e), 2)
    assert any("block (1, 2)" in f.msg for f in whole.value.faults)  # the caller's bodies 1, 2 (the part's 0, 1)
    assert [(f.loc, f.msg) for f in got.value.faults] == [(f.loc, f.msg) for f in whole.value.faults]


def _in_parts(req, size: int):
    """`Client.evaluate`'s path in-process: parts of `size` joints, a part's fault relocated, the answers merged."""
    from jointlimits.client import InvalidInput

    parts, results = split.plan(req, size), []
    for part in parts:
        try:
            results.append(LocalClient().evaluate(part.request))
        except InvalidInput as e:
            raise split.relocate(part, e) from None
    return split.merge(req, parts, results)


def _chain_with_offsets(offset):
    """`chain(2)` (body 2 turning about z) with joint offsets and limits +-0.5 about them; `pose(a)`."""
    from jointlimits.client import JointBatch
    from tests.sdk.test_sessions_live import chain

    req, pose = chain(2)
    off = 0.0 if offset is None else np.asarray(offset)
    req.batches[0] = JointBatch.of(670, [[0, 1], [1, 2]], [[[0, 0, 0], [0, 0, 1]]] * 2, off - 0.5, off + 0.5, 10.0,
                                   offset=offset)
    return req, pose


def test_a_reopened_session_with_offsets_keeps_the_bits_of_one_never_interrupted():
    """`reopen` is what a resume after a server restart does (`request_for_reopen`): the committed coordinates
    travel as `prev_coordinate` (`r + offset`), and every scene takes the angle as `coordinate - offset`, so the
    reopened session is the uninterrupted one bit for bit: before any commit (the reopen then carries no state: x
    is summed from q_ref, as in the opening), after a change of offsets, after a commit, and after a change of
    offsets then. At c2b3bc0 (the core kept `r`, a reopen before a commit sent the opening's coordinates) x moved
    by an ulp at those four points in 28, 30, 14 and 25 of the 30 angles."""
    req, pose = _chain_with_offsets([0.3, -2.9])
    req = dataclasses.replace(req, q_prev=req.q.copy())  # q_prev off q_ref: the coordinate at q_prev is not the offset
    for a in np.linspace(0.1, 3.0, 30):
        ref, s = LocalClient().session(req), LocalClient().session(req)
        q = req.q.copy()
        q[2] = pose(a)
        s.reopen()
        same_joints(s.evaluate(q), ref.evaluate(q))
        s.update(0, [0], offset=[-a]), ref.update(0, [0], offset=[-a])
        s.reopen()
        same_joints(s.evaluate(q), ref.evaluate(q))
        assert s.commit(q)[0].tobytes() == ref.commit(q)[0].tobytes()
        s.reopen()
        q[2] = pose(a + 0.2)
        same_joints(s.evaluate(q), ref.evaluate(q))
        s.update(0, [1], offset=[a * 7.0]), ref.update(0, [1], offset=[a * 7.0])
        assert s.coordinates[0].tobytes() == ref.coordinates[0].tobytes()
        s.reopen()
        same_joints(s.evaluate(q), ref.evaluate(q))
        assert s.commit(q)[0].tobytes() == ref.commit(q)[0].tobytes()


@pytest.mark.parametrize("binary", [True, False], ids=["msgpack", "json"])
def test_a_live_session_reopened_after_each_commit_is_the_uninterrupted_one(live, binary):  # noqa: F811
    """The same over the wire: a server's session whose connection is dropped after every commit and reopened
    from what the client kept (`prev_coordinate` as msgpack or JSON carries it) answers as an in-process session
    never interrupted, bit for bit (at c2b3bc0, x moved an ulp after 6 of these 15 reopens)."""
    from jointlimits.client import Client

    req, pose = _chain_with_offsets([0.3, -2.9])
    q = req.q.copy()
    with Client(live, binary=binary).session(req) as s, LocalClient().session(req) as ref:
        for a in np.linspace(0.1, 3.0, 15):
            q[2] = pose(a)
            assert s.commit(q)[0].tobytes() == ref.commit(q)[0].tobytes()
            s._ws.close()  # the connection ends under the session
            s.reopen()
            q[2] = pose(a + 0.2)
            same_joints(s.evaluate(q), ref.evaluate(q))


@pytest.mark.parametrize("offset", [None, [0.3, -2.9], [1e6, -7.5]])
def test_a_stateless_request_of_a_sessions_committed_state_is_its_next_answer_bitwise(offset):
    """Contract v1.1's client-kept state: a stateless request whose `q_prev` is the session's committed `q` and
    whose `prev_coordinate` its committed coordinates answers what the session answers next, bit for bit (both
    take the angle as `coordinate - offset`; an offset of 1e6 rounds it to 1.2e-10, as it rounds `lower - offset`).
    Body 2 turns two whole turns, a commit every 0.3 rad: the committed angle unwraps past +-pi."""
    req, pose = _chain_with_offsets(offset)
    s, local, q = LocalClient().session(req), LocalClient(), req.q.copy()
    for a in np.arange(0.3, 4 * np.pi + 1.0, 0.3):
        q[2] = pose(a)
        committed = s.commit(q)
        q[2] = pose(a + 0.2)
        kept = dataclasses.replace(req, q=q.copy(), q_prev=s.q_prev.copy(),
                                   batches=[dataclasses.replace(req.batches[0], prev_coordinate=committed[0])])
        same_joints(local.evaluate(kept), s.evaluate(q))
    assert committed[0][1] - (0.0 if offset is None else offset[1]) > 4 * np.pi  # past two turns, not wrapped
