"""The SDK's `outputs`: one name alone asks for that output; a value that is not a list gets the wire's fault.

`outputs="energy"` used to be split into its characters (then refused, one fault per letter) and `outputs=5`
raised TypeError. Now a bare string is that one output (`client.model.as_outputs`), on every path: `Scene.request`,
`request_from_arrays`, a `Request` made directly, `Client`, `LocalClient`, and a session's `evaluate`, over the
wire and in-process. Anything else that is not a list, tuple or array (a number, None, a set, a dict) is the
fault the service answers for `"outputs": 5` in a document: ("body", "outputs"), "Input should be a valid
list", list_type.
"""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from jointlimits.client import Client, InvalidInput, LocalClient, Scene, request_from_arrays
from jointlimits.client.model import Request
from tests.http.test_contract_live import live  # noqa: F401 (fixture)

NOT_A_LIST = [(("body", "outputs"), "Input should be a valid list", "list_type")]


def scene() -> Scene:
    s = Scene()
    s.add_body(np.eye(4))
    moved = np.eye(4)
    moved[:3, 3] = [1.0, 0.0, 0.0]
    s.add_body(moved)
    s.add_revolute_limit(0, 1, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], lower=-0.5, upper=0.5)
    return s


def faults(fn) -> list[tuple]:
    with pytest.raises(InvalidInput) as e:
        fn()
    return [(tuple(f.loc), f.msg, f.type) for f in e.value.faults]


def test_the_wire_answers_a_number_for_outputs_with_this_fault(live):  # noqa: F811
    doc = {"bodies": {"q": [], "q_prev": [], "q_ref": []}, "batches": [], "outputs": 5}
    detail = httpx.post(f"{live}/v1/evaluate", json=doc).json()["detail"]
    assert [(tuple(d["loc"]), d["msg"], d["type"]) for d in detail] == NOT_A_LIST


@pytest.mark.parametrize("path", ["local", "http", "local session", "http session"])
def test_one_name_alone_is_that_output_on_every_path(live, path):  # noqa: F811
    s = scene()
    client = LocalClient() if path.startswith("local") else Client(live)
    if path.endswith("session"):
        with client.session(s.request()) as session:
            ev = session.evaluate(s.request().q, outputs="gradient")
    else:
        ev = client.evaluate(s.request(outputs="gradient"))
    b = ev.batches[0]
    assert b.gradient is not None and b.hessian is None  # only the gradient asked for (energy always comes)


@pytest.mark.parametrize("bad", [5, None, {"energy"}, {"energy": 1}, 1.5])
def test_a_value_that_is_not_a_list_gets_the_wires_fault_on_every_path(live, bad):  # noqa: F811
    s = scene()
    req = s.request()
    assert faults(lambda: s.request(outputs=bad)) == NOT_A_LIST
    assert faults(lambda: request_from_arrays(req.q, req.batches, outputs=bad)) == NOT_A_LIST
    assert faults(lambda: Request(req.q, req.q_prev, req.q_ref, req.batches, bad)) == NOT_A_LIST
    if bad is None:
        return  # a session's `outputs=None` is the opening's (the message leaves the key out)
    for client in (LocalClient(), Client(live)):
        with client.session(req) as session:
            assert faults(lambda: session.evaluate(req.q, outputs=bad)) == NOT_A_LIST
            assert session.evaluate(req.q).total_energy >= 0  # the session goes on


def test_unknown_names_are_named_by_position_as_the_service_names_them(live):  # noqa: F811
    s = scene()
    want = [(("body", "outputs", 0), "Input should be 'energy', 'gradient' or 'hessian'", "literal_error")]
    for client in (LocalClient(), Client(live)):
        assert faults(lambda: client.evaluate(s.request(outputs="jacobian"))) == want
        with client.session(s.request()) as session:
            assert faults(lambda: session.evaluate(s.request().q, outputs="jacobian")) == want


NOT_A_BOOL = [(("body", "active_only"), "Input should be a valid boolean", "bool_type")]


@pytest.mark.parametrize("bad", ["false", 1, 0, None, 1.0])
def test_active_only_is_a_boolean_as_the_wire_reads_it(live, bad):  # noqa: F811
    """The wire's `active_only` is a strict boolean ("false" and 1 are refused, `bool_type`). The SDK took
    `bool(active_only)`: `active_only="false"` asked for active joints only, silently dropping the others' rows."""
    doc = {"bodies": {"q": [], "q_prev": [], "q_ref": []}, "batches": [], "active_only": bad}
    detail = httpx.post(f"{live}/v1/evaluate", json=doc).json()["detail"]
    assert [(tuple(d["loc"]), d["msg"], d["type"]) for d in detail] == NOT_A_BOOL
    s = scene()
    req = s.request()
    assert faults(lambda: s.request(active_only=bad)) == NOT_A_BOOL
    assert faults(lambda: request_from_arrays(req.q, req.batches, active_only=bad)) == NOT_A_BOOL
    if bad is None:
        return  # a session's `active_only=None` is the opening's
    for client in (LocalClient(), Client(live)):
        with client.session(req) as session:
            assert faults(lambda: session.evaluate(req.q, active_only=bad)) == NOT_A_BOOL
            rows = [len(session.evaluate(req.q, active_only=flag).batches[0].index) for flag in (np.False_, np.True_)]
            assert rows == [1, 0]  # numpy's bools are booleans (the joint is inside its range)
