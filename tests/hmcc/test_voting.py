"""One-dimensional Hough voting: the accumulator, its peak, and the bins selected around it
(circular for the global direction vote of 36 bins, linear for the local vote of 10 bins)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hmcc.voting import HoughVote, hough_vote


def _votes(histogram: list[int]) -> np.ndarray:
    """The (M,) bin indices whose accumulator is ``histogram``, shuffled."""
    votes = np.repeat(np.arange(len(histogram)), histogram).astype(np.int64)
    return np.random.default_rng(0).permutation(votes)


def test_the_histogram_counts_the_votes_per_bin() -> None:
    counts = [0, 3, 1, 0, 7, 2, 0, 0, 0, 1]
    vote = hough_vote(_votes(counts), 10, window_bins=0, min_vote_ratio=0.0, circular=False)
    assert vote.histogram.dtype == np.int64
    np.testing.assert_array_equal(vote.histogram, counts)
    assert vote.peak_bin == 4
    assert vote.selected.dtype == bool
    assert vote.selected.shape == (10,)


def test_empty_bins_at_the_end_are_still_counted() -> None:
    vote = hough_vote(np.array([0, 0, 1], dtype=np.int64), 36, 0, 0.0, circular=True)
    assert vote.histogram.shape == (36,)
    assert vote.histogram.sum() == 3


def test_a_tie_takes_the_lowest_bin_as_the_peak() -> None:
    vote = hough_vote(_votes([0, 2, 5, 0, 5, 5]), 6, 0, 0.5, circular=False)
    assert vote.peak_bin == 2
    np.testing.assert_array_equal(np.flatnonzero(vote.selected), [2])


@pytest.mark.parametrize("circular", [True, False])
def test_an_empty_vote_selects_nothing(circular: bool) -> None:
    vote = hough_vote(np.array([], dtype=np.int64), 10, 3, 0.4, circular)
    np.testing.assert_array_equal(vote.histogram, np.zeros(10))
    assert not vote.selected.any()
    assert vote.selected.shape == (10,)


def test_only_bins_within_the_window_of_the_peak_are_selected() -> None:
    # every bin holds more than 0.4 of the peak's 10 votes; the window decides
    counts = [9, 9, 9, 9, 9, 10, 9, 9, 9, 9]
    vote = hough_vote(_votes(counts), 10, window_bins=2, min_vote_ratio=0.4, circular=False)
    assert vote.peak_bin == 5
    np.testing.assert_array_equal(np.flatnonzero(vote.selected), [3, 4, 5, 6, 7])


def test_a_bin_needs_strictly_more_than_the_ratio_of_the_peak() -> None:
    # peak 10, ratio 0.4: 4 votes (= 0.4 * 10) are not enough, 5 are
    counts = [4, 5, 10, 4, 5, 0]
    vote = hough_vote(_votes(counts), 6, window_bins=5, min_vote_ratio=0.4, circular=False)
    np.testing.assert_array_equal(np.flatnonzero(vote.selected), [1, 2, 4])


def test_the_peak_is_always_selected() -> None:
    # a ratio of 1 selects no bin by "strictly more than the peak's votes", yet the peak is in
    vote = hough_vote(_votes([1, 3, 3, 1]), 4, window_bins=0, min_vote_ratio=1.0, circular=False)
    np.testing.assert_array_equal(np.flatnonzero(vote.selected), [1])


def test_a_circular_window_wraps_around_and_a_linear_one_does_not() -> None:
    counts = [0] * 36
    counts[0], counts[1], counts[34], counts[35], counts[33] = 10, 8, 8, 8, 8
    votes = _votes(counts)
    circular = hough_vote(votes, 36, window_bins=2, min_vote_ratio=0.2, circular=True)
    assert circular.peak_bin == 0
    np.testing.assert_array_equal(np.flatnonzero(circular.selected), [0, 1, 34, 35])
    linear = hough_vote(votes, 36, window_bins=2, min_vote_ratio=0.2, circular=False)
    assert linear.peak_bin == 0
    np.testing.assert_array_equal(np.flatnonzero(linear.selected), [0, 1])


@pytest.mark.parametrize(
    ("n_bins", "window_bins", "min_vote_ratio", "circular"),
    [(36, 5, 0.2, True), (10, 3, 0.4, False)],
    ids=["global-direction", "local-change"],
)
def test_the_votes_of_the_paper_select_the_peak_and_its_supported_neighbours(
    n_bins: int, window_bins: int, min_vote_ratio: float, circular: bool
) -> None:
    """A concentrated vote (the inliers) over a uniform background (the outliers): the bins
    selected are contiguous around the peak, within the window, and hold most inliers."""
    rng = np.random.default_rng(1)
    peak = 4
    inliers = peak + rng.integers(-1, 2, size=300)
    outliers = rng.integers(0, n_bins, size=60)
    votes = np.concatenate((inliers, outliers)).astype(np.int64) % n_bins
    vote = hough_vote(votes, n_bins, window_bins, min_vote_ratio, circular)
    assert vote.peak_bin in (peak - 1, peak, peak + 1)
    selected = np.flatnonzero(vote.selected)
    assert set(range(peak - 1, peak + 2)) <= set(selected.tolist())
    threshold = min_vote_ratio * vote.histogram[vote.peak_bin]
    assert (vote.histogram[selected] > threshold).all()
    assert (np.abs(selected - vote.peak_bin) <= window_bins).all()
    # the background alone holds too few votes per bin to be selected
    assert len(selected) == 3


def test_to_stats_is_a_json_ready_summary() -> None:
    vote = hough_vote(_votes([1, 6, 4, 0, 2]), 5, window_bins=1, min_vote_ratio=0.5, circular=False)
    stats = vote.to_stats()
    assert stats == {
        "histogram": [1, 6, 4, 0, 2],
        "peak_bin": 1,
        "peak_votes": 6,
        "selected_bins": [1, 2],
    }
    assert json.loads(json.dumps(stats)) == stats  # plain Python numbers, no numpy scalars
    assert isinstance(vote, HoughVote)
