"""The hierarchical motion consistency constraint (paper sections 2.2 and 3) and the two methods
built on it: ``hmcc`` (the filter alone) and ``hmcc-ransac`` (the paper: the filter, then the
final estimator on its survivors).

Three stages, each a pure function of the surviving motions that returns a keep-mask over
its input and JSON-ready statistics:

1. :func:`vote_directions` - global direction vote (circular Hough, 36 bins of 10 deg,
   peak +- 5 bins with more than 20 % of the peak's votes);
2. :func:`vote_direction_changes` - local direction-change vote (k = 7 nearest motions by
   start point, median change per motion, 10 bins of 3 deg over 0-30 deg, peak +- 3 bins
   with more than 40 %);
3. :func:`filter_lengths` - global length z-score, |z| > 3 removed.

Every threshold is a named field of the stage's options with the paper's value as default.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree

from .pair import PairData, require_matches
from .projection import project_pair
from .ransac import fit_final, min_matches
from .stage_options import DirectionChangeOptions, DirectionOptions, LengthOptions
from .stages import MethodResult, Stages
from .voting import hough_vote

if TYPE_CHECKING:
    from .options import VerifyOptions

__all__ = [
    "DirectionChangeOptions",
    "DirectionOptions",
    "LengthOptions",
    "filter_lengths",
    "verify_hmcc",
    "verify_hmcc_ransac",
    "vote_direction_changes",
    "vote_directions",
]


def _bin_index(values: np.ndarray, bin_deg: float, n_bins: int) -> np.ndarray:
    """Bin of each value in [0, n_bins * bin_deg); guards float rounding at the top edge."""
    return np.minimum((values // bin_deg).astype(np.int64), n_bins - 1)


def circular_difference_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| on the circle, degrees in [0, 180]."""
    d = np.abs(np.mod(a - b, 360.0))
    return np.minimum(d, 360.0 - d)


def vote_directions(
    direction_deg: np.ndarray, options: DirectionOptions = DirectionOptions()
) -> tuple[np.ndarray, dict[str, Any]]:
    """Stage 1: keep the motions whose direction falls in a selected bin of the global vote.

    ``direction_deg``: (N,) in [0, 360). Returns ((N,) bool keep, stats).
    """
    n_bins = options.n_bins
    bins = _bin_index(np.mod(direction_deg, 360.0), options.bin_deg, n_bins)
    vote = hough_vote(bins, n_bins, options.window_bins, options.min_vote_ratio, circular=True)
    stats = vote.to_stats()
    stats["peak_direction_deg"] = (vote.peak_bin + 0.5) * options.bin_deg
    return vote.selected[bins], stats


def _neighbours(start: np.ndarray, k: int) -> np.ndarray:
    """(N, k) indices of each start point's k nearest other start points."""
    _, idx = cKDTree(start).query(start, k=k + 1)
    idx = idx.reshape(len(start), k + 1)
    own = np.arange(len(start))
    if np.array_equal(idx[:, 0], own):  # the usual case: each point is its own nearest
        return idx[:, 1:]
    is_self = idx == own[:, None]
    # With more than k coincident points a row may not contain itself: drop its last column.
    is_self[:, -1] |= ~is_self.any(axis=1)
    return idx[~is_self].reshape(len(start), k)


def vote_direction_changes(
    start: np.ndarray,
    direction_deg: np.ndarray,
    options: DirectionChangeOptions = DirectionChangeOptions(),
) -> tuple[np.ndarray, dict[str, Any]]:
    """Stage 2: local direction-change consistency.

    ``start``: (N, 2) start points (metres), ``direction_deg``: (N,). For each motion, the
    direction changes to its k nearest motions (by start point; the "absolute subtraction" of
    Eq. 4 taken on the circle, so 359 and 1 deg differ by 2) each cast a vote; the motion's own
    bin is that of the median change. Changes of ``max_deg`` or more cast no vote, and a
    motion whose median is that large is an outlier. With fewer than two motions nothing is
    removed. Returns ((N,) bool keep, stats).
    """
    n = len(direction_deg)
    k = min(options.k_neighbors, n - 1)
    n_bins = options.n_bins
    if k < 1:
        return np.ones(n, dtype=bool), {"skipped": "fewer than two motions", "k": max(k, 0)}
    nbr = _neighbours(start, k)
    change = circular_difference_deg(direction_deg[:, None], direction_deg[nbr])
    in_range = change < options.max_deg
    votes = _bin_index(change[in_range], options.bin_deg, n_bins)
    vote = hough_vote(votes, n_bins, options.window_bins, options.min_vote_ratio, circular=False)
    ordered = np.sort(change, axis=1)
    median = 0.5 * (ordered[:, (k - 1) // 2] + ordered[:, k // 2])
    own_bin = _bin_index(np.minimum(median, options.max_deg), options.bin_deg, n_bins + 1)
    selectable = np.append(vote.selected, False)  # the overflow bin is never selected
    stats = vote.to_stats()
    stats.update({"k": k, "votes_cast": int(in_range.sum())})
    return selectable[own_bin], stats


def filter_lengths(
    length: np.ndarray, options: LengthOptions = LengthOptions()
) -> tuple[np.ndarray, dict[str, Any]]:
    """Stage 3: remove motions whose length z-score (population std) exceeds ``z_max``.

    ``length``: (N,) metres. With zero spread (or N < 2) nothing is removed.
    """
    if len(length) == 0:
        return np.ones(0, dtype=bool), {"mean_m": None, "std_m": None}
    mean = float(np.mean(length))
    std = float(np.std(length))
    stats: dict[str, object] = {"mean_m": mean, "std_m": std, "z_max": options.z_max}
    if std == 0.0:
        return np.ones(len(length), dtype=bool), stats
    return np.abs(length - mean) <= options.z_max * std, stats


def verify_hmcc(pair: PairData, options: VerifyOptions, stages: Stages) -> MethodResult:
    """Method ``hmcc``: projection and the three HMCC stages; the survivors are the inliers."""
    inliers, statistics = _filter(pair, options, stages)
    return MethodResult(inliers, None, None, statistics, options)


def verify_hmcc_ransac(pair: PairData, options: VerifyOptions, stages: Stages) -> MethodResult:
    """Method ``hmcc-ransac`` (the paper): the HMCC filter, then ``options.ransac`` on its
    survivors."""
    ransac = options.ransac
    require_matches(pair, min_matches(ransac.model, ransac.estimator), ransac.model)
    candidates, statistics = _filter(pair, options, stages)
    px1, px2 = pair.matched_pixels()
    with stages.stage("ransac", len(candidates)) as st:
        fit = fit_final(pair, px1[candidates], px2[candidates], options.ransac, options.seed)
        inliers = candidates[st.done(fit.inliers, fit.stats)]
    stages.survivors["ransac"] = inliers
    if "degenerate" in fit.stats:
        statistics["degenerate"] = fit.stats["degenerate"]
    return MethodResult(inliers, fit.model, fit.matrix, statistics, options)


def _filter(
    pair: PairData, options: VerifyOptions, stages: Stages
) -> tuple[np.ndarray, dict[str, Any]]:
    """Projection and the three HMCC stages: the surviving match indices, statistics."""
    px1, px2 = pair.matched_pixels()
    with stages.stage("projection", len(px1)) as st:
        motions, valid, stats = project_pair(pair, px1, px2, options.ground)
        idx = np.flatnonzero(st.done(valid, stats))
    stages.survivors["projection"] = idx
    direction = motions.direction_deg

    with stages.stage("direction", len(idx)) as st:
        keep = st.done(*vote_directions(direction, options.direction))
    idx, motions, direction = idx[keep], motions.subset(keep), direction[keep]
    stages.survivors["direction"] = idx

    with stages.stage("direction_change", len(idx)) as st:
        keep = st.done(*vote_direction_changes(motions.start, direction, options.direction_change))
    idx, motions = idx[keep], motions.subset(keep)
    stages.survivors["direction_change"] = idx

    with stages.stage("length", len(idx)) as st:
        keep = st.done(*filter_lengths(motions.length, options.length))
    stages.survivors["length"] = idx[keep]
    return idx[keep], {"z0_m": stats["z0_m"]}
