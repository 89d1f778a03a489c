"""Placement of FE2's RVEs over ranks (`coupling.fe2_placement.balance`): the work evens out
within the tolerance, few points move, and the answer depends only on its inputs (every rank
computes it alone). The routing and migration run in tests/coupling/test_fe2.py (2 ranks)."""

import numpy as np
import pytest

from coupling.fe2_placement import balance


def loads(cost, worker, size):
    return np.bincount(worker, cost, minlength=size)


def test_balance_evens_the_ranks_work_within_the_tolerance():
    """16 points on two ranks, a band of expensive points all on rank 0: after balancing the
    loads differ by less than the tolerance x their mean, or by less than the cheapest point
    (no move can do better)."""
    rng = np.random.default_rng(3)
    cost = rng.uniform(1.0, 1.2, 16)
    cost[:5] *= 3.0  # the band
    worker = np.repeat([0, 1], 8)
    before = loads(cost, worker, 2)
    new = balance(cost, worker, 2, tolerance=0.05)
    after = loads(cost, new, 2)
    assert after.sum() == pytest.approx(before.sum())
    assert np.ptp(before) > 0.5 * before.mean()
    assert np.ptp(after) <= max(0.05 * after.mean(), cost.min())
    assert (new != worker).sum() <= 3  # a few moves, not a reshuffle


def test_balance_keeps_a_balanced_placement_and_is_deterministic():
    """Within the tolerance nothing moves; the same inputs give the same moves; zero-cost
    points (not evaluated) never move; three ranks, one of them empty, fill up."""
    cost = np.ones(8)
    worker = np.repeat([0, 1], 4)
    np.testing.assert_array_equal(balance(cost, worker, 2, 0.05), worker)
    cost = np.array([5.0, 1, 1, 0, 2, 2, 2, 2, 3])
    worker = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1])
    a = balance(cost, worker, 3, 0.0)
    np.testing.assert_array_equal(a, balance(cost, worker, 3, 0.0))
    assert a[3] == 0
    assert (a == 2).any()
    assert np.ptp(loads(cost, a, 3)) < np.ptp(loads(cost, worker, 3))


def test_balance_moves_nothing_when_no_move_helps():
    """Two points of cost 10 and 1 on two ranks: moving either makes the top load no lower."""
    worker = np.array([0, 1])
    np.testing.assert_array_equal(balance(np.array([10.0, 1.0]), worker, 2, 0.0), worker)
