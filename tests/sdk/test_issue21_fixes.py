"""Issue 21's small fixes: `layout=` on both request builders, `.matrix()` a `csr_array`, a joint's repr a summary,
singular nouns for one of a thing, and the OpenAPI description naming the contract version it implements."""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.client import JointBatch, LocalClient, Scene, request_from_arrays
from jointlimits.service.core import InputError, Bodies, prepare
from jointlimits.service.core.validate import check_dofs
from tests.conftest import same_numbers


def _scene() -> Scene:
    c, s = np.cos(0.7), np.sin(0.7)
    scene = Scene()
    a = scene.add_body(np.eye(4))
    b = scene.add_body(np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), ref=np.eye(4))
    scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5, strength=100.0)
    return scene


def test_scene_request_takes_layout():
    req = _scene().request(layout="bodies")
    assert req.layout == "bodies" and _scene().request().layout == "joints"
    ev = LocalClient().evaluate(req)
    assert ev.assembled is not None and ev.assembled.gradient.shape == (2, 12)


def test_request_from_arrays_takes_layout():
    r = _scene().request()
    req = request_from_arrays(r.q, r.batches, q_prev=r.q_prev, q_ref=r.q_ref, layout="bodies")
    assert req.layout == "bodies"
    ev = LocalClient().evaluate(req)
    assert np.array_equal(ev.assembled.gradient, LocalClient().evaluate(_scene().request(layout="bodies")).assembled.gradient)


def test_matrix_is_a_csr_array():
    sparse = pytest.importorskip("scipy.sparse")
    M = LocalClient().evaluate(_scene().request(layout="bodies")).assembled.matrix()
    assert isinstance(M, sparse.csr_array) and M.shape == (24, 24)
    assert (M @ np.ones(24)).shape == (24,)


def test_repr_of_a_joint_result_is_a_summary():
    scene = _scene()
    r = LocalClient().evaluate(scene.request()).joint(0)
    text = repr(r)
    assert len(text) < 300 and "\n" not in text, text
    head = text.split(", gradient=", 1)[0]  # the floats up to another CPU's last bits (`same_numbers`)
    assert same_numbers(head, "JointResult(constitution_uid=670, row=0, x=0.7, coordinate=0.7, energy=0.7999999999999995"), text
    assert "gradient=array(24,)" in text and "hessian=array(24, 24)" in text


@pytest.mark.parametrize("n, words", [(1, "there is 1 body)"), (2, "there are 2 bodies)")])
def test_one_body_is_singular(n, words):
    q = np.tile(np.r_[0, 0, 0, np.eye(3).ravel()], (n, 1))
    batch = JointBatch.of(670, [[0, 5]], [[[0, 0, 0], [0, 0, 1]]], -1, 1)
    from jointlimits.client.local import core_batches
    from jointlimits.client import Request

    with pytest.raises(InputError) as e:
        prepare(Bodies(q, q, q), core_batches(Request(q, q, q, [batch]), copy=True))
    assert words in e.value.faults[0].msg


def test_one_row_is_singular():
    assert "must be 1 row of 12 numbers" in check_dofs("q", np.zeros((2, 12)), 1)[0].msg
    assert "must be 2 rows of 12 numbers" in check_dofs("q", np.zeros((1, 12)), 2)[0].msg


def test_openapi_names_the_contract_version():
    from jointlimits.service.app import create_app

    assert "contract v1.2" in create_app().openapi()["info"]["description"]
