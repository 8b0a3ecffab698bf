"""A v1 request keeps bit-identical numbers: the answers' digests against those of the pre-v1.1 core."""

from __future__ import annotations

import json

import pytest

from tests.v1_answers import PATH, cases, digest
from jointlimits.service.core import evaluate

WANT = json.loads(PATH.read_text())


@pytest.mark.parametrize("name,bodies,batches,options", list(cases()), ids=lambda v: v if isinstance(v, str) else "")
def test_v1_answer_is_bitwise_the_pre_v11_answer(name, bodies, batches, options):
    assert digest(evaluate(bodies, batches, **options)) == WANT[name]
