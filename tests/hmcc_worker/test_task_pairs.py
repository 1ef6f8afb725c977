"""How the compute pool cuts a flight into tasks (:func:`hmcc_worker.pool.task_pairs`)."""

from __future__ import annotations

import math

import pytest

from hmcc_worker.pool import task_pairs


@pytest.mark.parametrize("processes", [1, 2, 3, 8])
@pytest.mark.parametrize("n", [1, 2, 5, 17, 108, 500, 4_000, 18_283])
def test_tasks_are_equal_shares_for_every_child(n: int, processes: int) -> None:
    size = task_pairs(n, processes)
    tasks = math.ceil(n / size)
    assert 1 <= size <= 256
    if n >= processes:  # every child has work
        assert tasks >= processes
    if n >= 4 * processes:  # as many tasks as the others, and of the same size (but the last)
        assert tasks % processes == 0 and size * tasks - n < tasks


def test_task_size_follows_the_hand_off_against_the_tail() -> None:
    """Small flights: a few tasks a child (the hand-off dominates); large ones: more tasks,
    up to 256 pairs each (the tail dominates)."""
    assert task_pairs(108, 2) == 18  # the Brighton database: 6 tasks, 3 a child
    assert task_pairs(1_000, 2) < task_pairs(4_000, 2) < task_pairs(100_000, 2) == 256
    assert task_pairs(10, 2) == 5
