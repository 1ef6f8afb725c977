"""One-dimensional Hough voting: accumulate, find the peak, select neighbouring bins.

This is the voting scheme of the paper's section 3, shared by the global direction vote
(circular, 36 bins) and the local direction-change vote (linear, 10 bins).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["HoughVote", "hough_vote"]


@dataclass(frozen=True)
class HoughVote:
    """The outcome of one vote.

    ``histogram``: (n_bins,) int64 votes per bin; ``peak_bin``: index of the most voted bin
    (the lowest index among ties); ``selected``: (n_bins,) bool, the bins accepted.
    """

    histogram: np.ndarray
    peak_bin: int
    selected: np.ndarray

    def to_stats(self) -> dict[str, object]:
        """JSON-ready summary for a stage's statistics."""
        return {
            "histogram": self.histogram.tolist(),
            "peak_bin": self.peak_bin,
            "peak_votes": int(self.histogram[self.peak_bin]),
            "selected_bins": np.flatnonzero(self.selected).tolist(),
        }


def hough_vote(
    votes: np.ndarray,
    n_bins: int,
    window_bins: int,
    min_vote_ratio: float,
    circular: bool,
) -> HoughVote:
    """Vote bin indices into an accumulator and select the bins around its peak.

    ``votes``: (M,) int bin indices in ``[0, n_bins)``. A bin is selected when it lies within
    ``window_bins`` steps of the peak (wrapping around when ``circular``) and its votes are
    strictly greater than ``min_vote_ratio`` times the peak's; the peak itself always is.
    An empty vote selects nothing.
    """
    histogram = np.bincount(votes, minlength=n_bins)[:n_bins].astype(np.int64)
    peak = int(np.argmax(histogram))
    if histogram[peak] == 0:
        return HoughVote(histogram, peak, np.zeros(n_bins, dtype=bool))
    offset = np.abs(np.arange(n_bins) - peak)
    if circular:
        offset = np.minimum(offset, n_bins - offset)
    selected = (offset <= window_bins) & (histogram > min_vote_ratio * histogram[peak])
    selected[peak] = True
    return HoughVote(histogram, peak, selected)
