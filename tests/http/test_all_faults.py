"""Every fault of a request, of every class at once, up to the cap (MAX_FAULTS): a body index out of
range does not hide `lower > upper` of another joint, nor a shape fault the ranges of other fields."""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.client import InvalidInput, LocalClient
from jointlimits.service.core import InputError, evaluate
from jointlimits.service.core.errors import MAX_FAULTS
from jointlimits.service.core.scene import Bodies, Joints
from tests.http.test_errors_http import base_request, edit, with_batch


def _faults(request) -> list[tuple]:
    with pytest.raises(InvalidInput) as e:
        LocalClient().evaluate(request)
    return [(f.loc, f.type) for f in e.value.faults]


def test_index_range_and_strength_faults_together():
    r = edit(base_request(), 1, "body_ids", 2, [0, 3])  # out of range: 3 bodies
    r = edit(r, 1, "lower", 0, 5.0)  # lower > upper of another joint
    r = edit(r, 0, "strength", 1, -1.0)  # and of another batch
    assert _faults(r) == [
        (("body", "batches", 0, "strength", 1), "value_error"),
        (("body", "batches", 1, "body_ids", 2), "value_error"),
        (("body", "batches", 1, "lower", 0), "value_error"),
    ]


def test_a_shape_fault_does_not_hide_the_other_fields_rows():
    r = base_request()
    r = with_batch(r, 1, strength=r.batches[1].strength[:2])  # wrong length
    r = edit(r, 1, "lower", 1, 5.0)
    r = edit(r, 1, "body_ids", 0, [2, 2])
    assert _faults(r) == [
        (("body", "batches", 1, "strength"), "value_error"),
        (("body", "batches", 1, "body_ids", 0), "value_error"),
        (("body", "batches", 1, "lower", 1), "value_error"),
    ]


def test_unknown_constitution_and_its_ranges_together():
    r = with_batch(edit(base_request(), 1, "lower", 2, 5.0), 1, constitution_uid=671)
    assert _faults(r) == [
        (("body", "batches", 1, "constitution_uid"), "value_error"),
        (("body", "batches", 1, "lower", 2), "value_error"),
    ]


@pytest.mark.parametrize("n", [10, 100])
def test_faults_of_every_class_in_one_answer_up_to_the_cap(n):
    ids = np.tile([0, 1], (n, 1))
    ids[::2] = [0, 7]  # every other joint out of range
    lower = np.where(np.arange(n) % 2 == 1, 1.0, -1.0)  # the others: lower > upper
    joints = Joints(670, 18, ids, np.tile([[0.0, 0, 0], [0, 0, 1]], (n, 1, 1)), lower, np.zeros(n), np.ones(n))
    q = np.tile(np.r_[np.zeros(3), np.eye(3).ravel()], (2, 1))
    with pytest.raises(InputError) as e:
        evaluate(Bodies(q, q, q), [joints])
    faults = e.value.faults
    if n == 10:  # 5 indices out of range, 5 empty ranges: all of them
        assert [(f.loc[2], f.loc[3]) for f in faults] == [("body_ids", j) for j in range(0, n, 2)] + [("lower", j) for j in range(1, n, 2)]
    else:
        assert len(faults) == MAX_FAULTS
