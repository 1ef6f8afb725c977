"""How the compute pool cuts a flight into tasks (:func:`hmcc_worker.pool.task_pairs`,
:func:`~hmcc_worker.pool.task_plan`)."""

from __future__ import annotations

import math

import pytest

from hmcc_worker.pool import task_pairs, task_plan


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


@pytest.mark.parametrize("processes", [1, 2, 3, 8])
@pytest.mark.parametrize("n", [1, 2, 5, 17, 108, 500, 4_000, 18_283])
def test_the_plan_hands_out_every_pair_once_in_rounds(n: int, processes: int) -> None:
    plan = task_plan(n, processes)
    assert sorted(i for task in plan for i in task) == list(range(n))
    assert all(task for task in plan) and max(len(task) for task in plan) <= 256
    if n >= 4 * processes:  # whole rounds, one task a child
        assert len(plan) % processes == 0


def test_the_last_tasks_are_the_smallest_and_a_rounds_tasks_are_alike() -> None:
    """The Brighton database (108 pairs, heaviest first, 2 children): rounds of 27, 18 and 9
    pairs a task; the two tasks of a round take the pairs in turn, there and back."""
    plan = task_plan(108, 2)
    assert [len(task) for task in plan] == [27, 27, 18, 18, 9, 9]
    assert plan[0][:4] == [0, 3, 4, 7] and plan[1][:4] == [1, 2, 5, 6]
    for first, second in zip(plan[::2], plan[1::2], strict=True):
        assert abs(sum(first) - sum(second)) <= len(first)  # as heavy, by rank
    assert task_plan(108, 2, chunk_pairs=50) == [
        list(range(0, 50)),
        list(range(50, 100)),
        list(range(100, 108)),
    ]
