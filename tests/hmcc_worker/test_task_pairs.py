"""How the compute pool cuts a flight into tasks (:func:`hmcc_worker.pool.task_pairs`,
:func:`~hmcc_worker.pool.task_plan`)."""

from __future__ import annotations

import pytest

from hmcc_worker.pool import task_pairs, task_plan


@pytest.mark.parametrize("processes", [1, 2, 3, 8])
@pytest.mark.parametrize("n", [1, 2, 5, 17, 108, 500, 4_000, 18_283])
def test_tasks_are_equal_shares_for_every_child(n: int, processes: int) -> None:
    plan = task_plan(n, processes)
    assert sorted(i for task in plan for i in task) == list(range(n))  # every pair once
    sizes = [len(task) for task in plan]
    assert 1 <= min(sizes) and max(sizes) <= 256
    assert len(plan) >= min(n, processes)  # every child has work
    if n >= processes:  # whole rounds, their tasks as large as each other (to one pair)
        assert len(plan) % processes == 0
        for r in range(0, len(plan), processes):
            assert max(sizes[r : r + processes]) - min(sizes[r : r + processes]) <= 1


def test_tasks_are_as_few_as_their_size_allows() -> None:
    """One task a child up to 256 pairs each (the hand-off costs more than the tail it would
    shorten), then rounds of them."""
    assert task_pairs(108, 2) == 54  # the Brighton database: 2 tasks, 1 a child
    assert task_pairs(512, 2) == 256 and task_pairs(513, 2) == 129
    assert task_pairs(100_000, 2) <= 256
    assert task_pairs(10, 2) == 5


def test_a_rounds_tasks_take_its_pairs_in_turn() -> None:
    """The Brighton database (108 pairs, heaviest first, 2 children): two tasks of 54 pairs,
    dealt there and back, so neither holds the heaviest pairs."""
    plan = task_plan(108, 2)
    assert [len(task) for task in plan] == [54, 54]
    assert plan[0][:4] == [0, 3, 4, 7] and plan[1][:4] == [1, 2, 5, 6]
    assert abs(sum(plan[0]) - sum(plan[1])) <= 54  # as heavy, by rank
    rounds = task_plan(1_000, 2)
    assert [len(task) for task in rounds] == [250] * 4
    assert max(rounds[1]) < min(rounds[2])  # the heaviest pairs in the first round
    assert task_plan(108, 2, chunk_pairs=50) == [
        list(range(0, 50)),
        list(range(50, 100)),
        list(range(100, 108)),
    ]
