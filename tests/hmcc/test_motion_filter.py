"""The three HMCC stages on constructed motions, one documented rule per test."""

from __future__ import annotations

import numpy as np
import pytest

from hmcc.motion_filter import (
    DirectionChangeOptions,
    DirectionOptions,
    LengthOptions,
    circular_difference_deg,
    filter_lengths,
    vote_direction_changes,
    vote_directions,
)
from hmcc.voting import hough_vote


def test_hough_vote_selects_window_bins_strictly_above_the_ratio() -> None:
    votes = np.repeat(np.arange(10), [0, 2, 10, 3, 0, 0, 9, 0, 0, 0])
    vote = hough_vote(votes, 10, window_bins=3, min_vote_ratio=0.2, circular=False)
    assert vote.peak_bin == 2
    # bin 1 (2 votes) is exactly 20 %: not selected; bin 6 (9 votes) is 4 bins away.
    assert np.flatnonzero(vote.selected).tolist() == [2, 3]


def test_hough_vote_wraps_when_circular() -> None:
    votes = np.repeat([0, 35, 34, 30], [10, 8, 6, 9])
    vote = hough_vote(votes, 36, window_bins=5, min_vote_ratio=0.2, circular=True)
    assert np.flatnonzero(vote.selected).tolist() == [0, 34, 35]


def test_hough_vote_of_nothing_selects_nothing() -> None:
    vote = hough_vote(np.zeros(0, dtype=np.int64), 36, 5, 0.2, circular=True)
    assert not vote.selected.any()


def test_direction_vote_keeps_the_dominant_direction_and_drops_random_ones() -> None:
    rng = np.random.default_rng(0)
    good = rng.uniform(31.0, 59.0, 300)  # bins 3, 4, 5: each well above 20 % of the peak
    bad = rng.uniform(0, 360, 300)
    keep, stats = vote_directions(np.concatenate([good, bad]))
    assert keep[:300].all()
    assert keep[300:].mean() < 0.15  # random directions survive only in the selected bins
    assert stats["selected_bins"] == [3, 4, 5]


def test_direction_vote_drops_true_tails_below_twenty_percent_of_the_peak() -> None:
    """The paper's rule loses true matches whose direction spreads wider than one bin."""
    rng = np.random.default_rng(0)
    keep, stats = vote_directions(rng.normal(45.0, 4.0, 300))
    assert stats["selected_bins"] == [4]
    assert 0.6 < keep.mean() < 0.9


def test_direction_vote_is_circular_around_north_east_zero() -> None:
    rng = np.random.default_rng(1)
    directions = np.mod(rng.uniform(-9.0, 9.0, 500), 360)
    keep, stats = vote_directions(directions)
    assert keep.all() and stats["selected_bins"] == [0, 35]


def test_direction_vote_options_change_the_result() -> None:
    directions = np.array([5.0] * 10 + [25.0] * 5 + [65.0] * 5)
    assert vote_directions(directions)[0].sum() == 15  # 65 deg is 6 bins away
    wide = DirectionOptions(window_bins=6)
    assert vote_directions(directions, wide)[0].sum() == 20


def test_circular_difference() -> None:
    assert circular_difference_deg(np.array(359.0), np.array(1.0)) == pytest.approx(2.0)
    assert circular_difference_deg(np.array(10.0), np.array(190.0)) == pytest.approx(180.0)


def _grid_motions(n_side: int = 20, direction: float = 30.0, jitter: float = 1.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n_side), np.arange(n_side))
    start = np.column_stack([xs.ravel(), ys.ravel()]).astype(float) * 10.0
    directions = direction + rng.normal(0.0, jitter, len(start))
    return start, directions


def test_direction_change_removes_motions_inconsistent_with_their_neighbours() -> None:
    start, directions = _grid_motions()
    row, col = np.divmod(np.arange(len(start)), 20)
    bad = np.flatnonzero((row % 3 == 1) & (col % 3 == 1))  # isolated from each other
    directions[bad] += 40.0  # a local misfit that passed the global vote
    keep, stats = vote_direction_changes(start, np.mod(directions, 360))
    assert not keep[bad].any()
    good = np.setdiff1d(np.arange(len(start)), bad)
    assert keep[good].mean() > 0.95
    assert stats["k"] == 7 and sum(stats["histogram"]) == stats["votes_cast"]


def test_direction_change_median_outside_range_is_an_outlier() -> None:
    start, directions = _grid_motions(n_side=5, jitter=0.0)
    directions[12] += 90.0
    keep, _ = vote_direction_changes(start, directions, DirectionChangeOptions())
    assert not keep[12] and keep.sum() == 24


def test_direction_change_handles_tiny_and_duplicate_inputs() -> None:
    keep, stats = vote_direction_changes(np.zeros((1, 2)), np.array([10.0]))
    assert keep.tolist() == [True] and "skipped" in stats
    start = np.zeros((12, 2))  # all starts coincide: more ties than k
    keep, _ = vote_direction_changes(start, np.full(12, 45.0))
    assert keep.all()
    keep, stats = vote_direction_changes(np.array([[0.0, 0], [1, 1], [2, 2]]), np.full(3, 5.0))
    assert keep.all() and stats["k"] == 2


def test_length_z_score_removes_far_lengths_both_ways() -> None:
    rng = np.random.default_rng(2)
    lengths = np.concatenate([rng.normal(10.0, 0.5, 500), [30.0, 0.0]])
    keep, stats = filter_lengths(lengths)
    assert not keep[-2:].any() and keep[:-2].mean() > 0.99
    assert stats["mean_m"] == pytest.approx(lengths.mean())
    assert filter_lengths(lengths, LengthOptions(z_max=100.0))[0].all()


def test_length_with_no_spread_keeps_everything() -> None:
    assert filter_lengths(np.full(5, 3.0))[0].all()
    assert filter_lengths(np.zeros(0))[0].shape == (0,)


@pytest.mark.parametrize(
    ("cls", "kwargs", "field"),
    [
        (DirectionOptions, {"bin_deg": 7.0}, "bin_deg"),
        (DirectionOptions, {"min_vote_ratio": 1.5}, "min_vote_ratio"),
        (DirectionChangeOptions, {"k_neighbors": 0}, "k_neighbors"),
        (DirectionChangeOptions, {"bin_deg": 4.0}, "bin_deg"),
        (LengthOptions, {"z_max": 0.0}, "z_max"),
    ],
)
def test_options_are_validated_when_built(cls, kwargs, field) -> None:
    with pytest.raises(ValueError, match=field):
        cls(**kwargs)


def test_stages_scale_to_ten_thousand_motions_without_nans() -> None:
    rng = np.random.default_rng(3)
    start = rng.uniform(0, 500, (10_000, 2))
    directions = rng.uniform(0, 360, 10_000)
    k1, _ = vote_directions(directions)
    k2, _ = vote_direction_changes(start[k1], directions[k1])
    k3, stats = filter_lengths(rng.uniform(0, 5, k2.sum()))
    assert k3.dtype == bool and np.isfinite(stats["std_m"])
