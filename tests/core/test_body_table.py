"""`kinematics.BodyTable`: which bodies the frames' common path serves (`plain_over`), taken after the
rows are filled and kept until the rows change."""

from __future__ import annotations

import numpy as np
import pytest

from jointlimits.service.core import Bodies
from jointlimits.service.core.kinematics import PREV_STEP, STEP, TOTAL_STEP, BodyTable, _plain_bodies
from tests.scenes import random_scene


def _bodies(seed: int) -> Bodies:
    """A random scene's bodies, one of them shrunk 1e6-fold between q_prev and q and one shrunk 1e250-fold at q_ref."""
    sc = random_scene(np.random.default_rng(90_000 + seed))
    q, q_prev, q_ref = sc.q.copy(), sc.q_prev.copy(), sc.q_ref.copy()
    q[0, 3:] *= 1e-6
    q_ref[1, 3:] *= 1e-250
    return Bodies(q, q_prev, q_ref)


def _fresh(table: BodyTable, rows: set[int]) -> np.ndarray:
    """`_plain_bodies` of the table's current rows, every norm taken anew."""
    return _plain_bodies(table.states, table.linear, rows)


@pytest.mark.parametrize("seed", range(4))
def test_plains_taken_with_the_rows_are_those_taken_after(seed: int) -> None:
    bodies = _bodies(seed)
    with np.errstate(all="ignore"):  # as the pipeline builds it (prepared.py): the shrunk A_ref's polar estimate
        table = BodyTable(bodies, rows={PREV_STEP, STEP, TOTAL_STEP})
    for rows in ({PREV_STEP}, {PREV_STEP, STEP}, {TOTAL_STEP}, {STEP}):
        got = table.plain_over(rows)
        np.testing.assert_array_equal(got, _fresh(table, rows))
    np.testing.assert_array_equal(table.plain, _fresh(table, {PREV_STEP, STEP, TOTAL_STEP}))
    assert not table.plain_over({PREV_STEP, STEP})[0] and not table.plain_over({TOTAL_STEP})[1]


def test_plains_follow_a_new_q() -> None:
    """After `load` and `increments` the kept masks are dropped: the shrunk body is plain again at a q
    of its own size."""
    bodies = _bodies(0)
    with np.errstate(all="ignore"):  # as the pipeline builds it (prepared.py): the shrunk A_ref's polar estimate
        table = BodyTable(bodies, rows={PREV_STEP, STEP})
    assert not table.plain_over({PREV_STEP, STEP})[0]
    table.load(2, bodies.q_prev)
    table.increments((STEP,))
    after = table.plain_over({PREV_STEP, STEP})
    assert after[0]
    np.testing.assert_array_equal(after, _fresh(table, {PREV_STEP, STEP}))


@pytest.mark.parametrize("shrunk", [False, True])
def test_the_stateless_tables_q_is_loaded_once(shrunk: bool) -> None:
    """The stateless call's table is built with its q and every row, `plain` over the prepared rows alone; `load` of
    that same q keeps rows and masks (one pass), of another q takes them anew: each as a fresh computation."""
    bodies = _bodies(1) if shrunk else random_scene(np.random.default_rng(5)).bodies()
    every = {PREV_STEP, STEP, TOTAL_STEP}
    with np.errstate(all="ignore"):  # as the pipeline builds it (prepared.py): the shrunk A_ref's polar estimate
        table = BodyTable(bodies, rows=every, plain={PREV_STEP})
        np.testing.assert_array_equal(table.plain, _fresh(table, {PREV_STEP}))
        for q in (bodies.q, bodies.q_prev, bodies.q):
            table.load(2, q)
            table.increments((STEP, TOTAL_STEP))
            other = BodyTable(Bodies(q, bodies.q_prev, bodies.q_ref), rows=every)
            assert all(np.array_equal(a, b) for a, b in zip(table.linear, other.linear))
            for rows in ({PREV_STEP}, {STEP}, {TOTAL_STEP}, every):
                np.testing.assert_array_equal(table.plain_over(rows), _fresh(table, rows))
    assert table.plain_over(every).all() != shrunk
