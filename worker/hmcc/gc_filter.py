"""GC pre-filter: the geometrical-consistency voting of Lu, Zhang & Tao (2016).

The HMCC-RANSAC paper compares itself with "GC-RANSAC": the candidate-match filter of
Lu, L., Zhang, Y., Tao, P., 2016. *Geometrical Consistency Voting Strategy for Outlier Detection
in Image Matching*. PE&RS 82 (7), 559-570, followed by a plain RANSAC on the survivors. This
module implements the filter only; RANSAC is done elsewhere. The HMCC paper describes it as a
"candidate match filter ... based on the Hough voting scheme" on "pairwise geometrical
comparisons" whose time grows with the number of matches (its Fig. 15, Tables 3, 4 and 6), and
it feeds it k nearest-neighbour candidate lists; this is that filter, quadratic by default.

Method (as read from Lu et al., PE&RS July 2016 pp. 561-563)
------------------------------------------------------------
A feature p_i of image 1 has a list of candidates q_i_0, q_i_1, ... in image 2 (its k nearest
neighbours by descriptor); each (p_i, q_i_m) is one input match. The candidate (p_i, q_i_m) is
voted on by every other feature p_j through its first candidate q_j_0: the pair defines a
segment in each image, ``v1 = p_j - p_i`` and ``v2 = q_j_0 - q_i_m``, and votes for

* the rotation ``rho = atan2(v2) - atan2(v1)`` (degrees, wrapped to [0, 360)), and
* the scale ``sigma = |v2| / |v1|`` (binned on ln(sigma)).

The parameter space is a 2D accumulator: scale in [1/5, 5] and rotation in [0, 360) with the
paper's sampling intervals (17 x 36 bins). Each candidate has its own accumulator; its *peak
bin* is its estimate of the image-to-image rotation/scale, and its *confidence* is the share of
its votes in that bin. The sum of all candidates' accumulators is the overall accumulator. Its
peak bin gives the global rotation and scale; a bin is a *correct bin* iff it lies within +-3
bins of the overall peak and holds at least 40 % of the peak's votes. A candidate is kept iff
its own peak bin is a correct bin. Every feature votes for every candidate of every other
feature: the cost is O(candidates x features), quadratic in the matches.

Choices where the papers are silent (each one ours, named)
---------------------------------------------------------
* **Candidate lists from the matches.** The input here is a list of matches
  ``(keypoint1, keypoint2)``. The matches sharing a keypoint of image 1 are that feature's
  candidate list, in input order; the first of them is its q_j_0. With one match per keypoint
  (1-NN matching with a ratio test, the usual input, and the paper's), every match votes for
  every other match.
* **Vote weight: none by default.** Lu et al. recommend weighting a vote by the p_i-p_j distance
  and the descriptor similarity but give no formula, and the HMCC paper mentions no weight;
  descriptors are not inputs here. Votes are unweighted (``distance_weight_px = 0``). The option
  ``distance_weight_px = d0 > 0`` weights a vote by ``d^2 / (d^2 + d0^2)`` with
  ``d = min(|v1|, |v2|)`` (short segments count less), off by default.
* **Keypoint orientation and size are not used.** Lu et al. state that "the scale parameter
  and the orientation parameter in our method are not provided by the feature description
  method": rotation and scale come only from pairs of matches. The method ``gc-ransac`` still
  requires ``[x, y, size, angle_deg]`` keypoints, the input the papers' SIFT pipeline produces;
  only x, y enter the vote.
* **Bins** are centred on 0 deg and on scale 1 (the paper does not say where bin edges lie);
  the rotation distance to the peak is taken circularly (359 deg neighbours 1 deg); pairs
  whose scale falls outside [1/5, 5] and zero-length segments (duplicate points) do not vote.
  Ties (a candidate's or the overall peak) go to the lowest bin index.
* **The overall accumulator** sums every candidate's votes (not only first candidates').
* **Confidence** is not thresholded (Lu et al. plot it as a "confidence curve"); it is
  reported in ``stats`` only.
* **Cost cap: off by default.** ``max_partners = P`` (not in either paper) has each candidate
  voted on by a seeded random subset of P other features (a window of one random permutation),
  O(N x P) instead of O(N^2); the default ``None`` uses every feature. The uncapped vote is
  one compiled loop (numba, like the paper's C++); the capped one runs in numpy, rows in
  chunks so that temporaries stay around 50 MB.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import InputError
from .jit import compiled as _jit
from .pair import PairData, require_matches
from .ransac import fit_final, min_matches
from .stage_options import GCOptions
from .stages import MethodResult, Stages

if TYPE_CHECKING:
    from .options import VerifyOptions

__all__ = ["GCOptions", "gc_filter", "verify_gc_ransac"]

_CHUNK_BYTES = 50_000_000
_BYTES_PER_PAIR = 22 * 8  # peak float64/int64 temporaries per evaluated pair (measured)
_EPS_PX = 1e-9  # segments shorter than this (pixels) are degenerate and do not vote
#: Without a partner cap the vote runs as one compiled loop (:func:`_vote_every_pair`); the
#: numpy path (chunks of pairs) serves the capped option. Tests compare the two.
_COMPILED = True


@dataclass(frozen=True)
class _Grid:
    """Accumulator geometry: n_scale x n_rot bins, flattened as scale_bin * n_rot + rot_bin."""

    n_rot: int
    rot_width_deg: float
    n_scale_half: int
    log_width: float

    @property
    def n_scale(self) -> int:
        return 2 * self.n_scale_half + 1

    @property
    def n_bins(self) -> int:
        return self.n_scale * self.n_rot


def _make_grid(options: GCOptions) -> _Grid:
    n_rot = max(1, round(360.0 / options.rotation_tolerance_deg))
    half = max(0, math.floor(math.log(options.scale_range) / options.log_scale_tolerance + 1e-9))
    return _Grid(n_rot, 360.0 / n_rot, half, float(options.log_scale_tolerance))


def _validate_keypoints(kp1: np.ndarray, kp2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) arrays -> two (N, 2) float64 position arrays; raise ValueError on bad shapes."""
    a = np.asarray(kp1, dtype=np.float64)
    b = np.asarray(kp2, dtype=np.float64)
    for name, arr in (("kp1", a), ("kp2", b)):
        if arr.ndim != 2 or arr.shape[1] != 4:
            raise ValueError(f"{name}: expected shape (N, 4), got {arr.shape}")
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"kp2: expected {a.shape[0]} rows like kp1, got {b.shape[0]}")
    return a[:, :2].copy(), b[:, :2].copy()


def _partners(
    own: np.ndarray, n: int, n_partners: int, perm: np.ndarray | None, offsets: np.ndarray | None
) -> np.ndarray:
    """(R,) positions of the rows' own features among ``n`` features -> (R, n_partners)
    distinct partner positions, never the row's own feature.

    Without ``perm`` every other feature is a partner (n_partners == n - 1). With ``perm`` (a
    random permutation of range(n)) and (R,) ``offsets``, row r takes the window
    perm[o_r : o_r + n_partners + 1] (cyclic) and drops its own feature, or the window's last
    entry if it is not in it.
    """
    if perm is None:
        cols = np.arange(n - 1)
        return cols[None, :] + (cols[None, :] >= own[:, None])
    assert offsets is not None
    window = perm[(offsets[:, None] + np.arange(n_partners + 1)[None, :]) % n]
    drop = window == own[:, None]
    drop[:, -1] |= ~drop.any(axis=1)
    return window[~drop].reshape(len(own), n_partners)


def _features(query_ids: np.ndarray | None, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(F,) row of each feature's first candidate and (N,) each row's feature position."""
    if query_ids is None:
        return np.arange(n), np.arange(n)
    ids = np.asarray(query_ids)
    if ids.shape != (n,):
        raise ValueError(f"query_ids: expected shape ({n},), got {ids.shape}")
    _, first, position = np.unique(ids, return_index=True, return_inverse=True)
    return first, position.reshape(n)


def _pair_bins(
    xy1: np.ndarray,
    xy2: np.ndarray,
    valid_pt: np.ndarray,
    rows: np.ndarray,
    partners: np.ndarray,
    grid: _Grid,
    d0: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Flattened accumulator bin (R, P) int64 and vote weight (R, P) float64 of each pair.

    Pairs that cannot vote (zero-length or non-finite segment, scale out of range) get weight 0
    and bin 0. No NaN or warning is produced for degenerate input.
    """
    v1 = xy1[partners] - xy1[rows][:, None, :]
    v2 = xy2[partners] - xy2[rows][:, None, :]
    len1 = np.hypot(v1[..., 0], v1[..., 1])
    len2 = np.hypot(v2[..., 0], v2[..., 1])
    ok = valid_pt[partners] & valid_pt[rows][:, None] & (len1 > _EPS_PX) & (len2 > _EPS_PX)
    safe1 = np.where(ok, len1, 1.0)
    safe2 = np.where(ok, len2, 1.0)
    # Rotation from v1 to v2 = atan2(v2) - atan2(v1), wrapped by atan2(cross, dot).
    cross = v1[..., 0] * v2[..., 1] - v1[..., 1] * v2[..., 0]
    dot = v1[..., 0] * v2[..., 0] + v1[..., 1] * v2[..., 1]
    rot_deg = np.degrees(np.arctan2(np.where(ok, cross, 0.0), np.where(ok, dot, 1.0)))
    rot_bin = np.floor(np.mod(rot_deg + 0.5 * grid.rot_width_deg, 360.0) / grid.rot_width_deg)
    rot_bin = rot_bin.astype(np.int64) % grid.n_rot
    scale_bin = np.rint(np.log(safe2 / safe1) / grid.log_width).astype(np.int64)
    ok &= np.abs(scale_bin) <= grid.n_scale_half
    flat = np.where(ok, (scale_bin + grid.n_scale_half) * grid.n_rot + rot_bin, 0)
    if d0 > 0.0:
        d2 = np.minimum(safe1, safe2) ** 2
        weight = np.where(ok, d2 / (d2 + d0 * d0), 0.0)
    else:
        weight = ok.astype(np.float64)
    return flat, weight


@_jit
def _vote_every_pair(
    xy1: np.ndarray,
    xy2: np.ndarray,
    valid_pt: np.ndarray,
    first: np.ndarray,
    position: np.ndarray,
    n_rot: int,
    rot_width_deg: float,
    n_scale_half: int,
    log_width: float,
    d0: float,
    overall: np.ndarray,
    peak_bin: np.ndarray,
    peak_votes: np.ndarray,
    total: np.ndarray,
) -> int:
    """The uncapped vote in one loop, exactly :func:`_pair_bins` + the per-row histograms:
    every row voted on by every other feature's first candidate. Fills ``overall`` (n_bins,)
    and the (N,) ``peak_bin``, ``peak_votes``, ``total``; returns the pairs that voted."""
    n = xy1.shape[0]
    n_bins = overall.shape[0]
    hist = np.zeros(n_bins)
    voting = 0
    for i in range(n):
        hist[:] = 0.0
        if valid_pt[i]:
            for f in range(first.shape[0]):
                if f == position[i]:
                    continue
                j = first[f]
                if not valid_pt[j]:
                    continue
                v1x, v1y = xy1[j, 0] - xy1[i, 0], xy1[j, 1] - xy1[i, 1]
                v2x, v2y = xy2[j, 0] - xy2[i, 0], xy2[j, 1] - xy2[i, 1]
                len1 = math.hypot(v1x, v1y)
                len2 = math.hypot(v2x, v2y)
                if not (len1 > _EPS_PX and len2 > _EPS_PX):
                    continue
                rot = math.degrees(math.atan2(v1x * v2y - v1y * v2x, v1x * v2x + v1y * v2y))
                rot_bin = int(math.floor(((rot + 0.5 * rot_width_deg) % 360.0) / rot_width_deg))
                rot_bin %= n_rot
                scale_bin = int(np.rint(math.log(len2 / len1) / log_width))
                if abs(scale_bin) > n_scale_half:
                    continue
                weight = 1.0
                if d0 > 0.0:
                    d = min(len1, len2)
                    weight = d * d / (d * d + d0 * d0)
                hist[(scale_bin + n_scale_half) * n_rot + rot_bin] += weight
                voting += 1
        best = 0
        for b in range(n_bins):
            if hist[b] > hist[best]:
                best = b
        peak_bin[i] = best
        peak_votes[i] = hist[best]
        total[i] = hist.sum()
        overall += hist
    return voting


def _correct_bins(overall: np.ndarray, grid: _Grid, options: GCOptions) -> np.ndarray:
    """(n_bins,) votes -> (n_bins,) bool: within +-radius of the peak (circular in rotation)
    and holding >= min_vote_ratio of the peak's votes. All False when nothing voted."""
    peak = int(np.argmax(overall))
    peak_votes = overall[peak]
    if not peak_votes > 0.0:
        return np.zeros(grid.n_bins, dtype=bool)
    ps, pr = divmod(peak, grid.n_rot)
    s_idx, r_idx = np.divmod(np.arange(grid.n_bins), grid.n_rot)
    dr = np.abs(r_idx - pr)
    dr = np.minimum(dr, grid.n_rot - dr)
    near = (np.abs(s_idx - ps) <= options.peak_radius_bins) & (dr <= options.peak_radius_bins)
    return near & (overall >= options.min_vote_ratio * peak_votes)


def gc_filter(
    kp1: np.ndarray,
    kp2: np.ndarray,
    options: GCOptions = GCOptions(),
    query_ids: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Lu et al. (2016) geometrical-consistency voting filter for putative matches.

    Args:
        kp1, kp2: (N, 4) float64 ``[x_px, y_px, size_px, angle_deg]`` of the two keypoints of
            each match (row i = match i). Only x, y are used (see the module docstring); rows
            with non-finite x or y neither vote nor are kept.
        options: voting parameters.
        query_ids: (N,) the image-1 keypoint of each match: rows sharing one are a feature's
            candidate list, the first row of each its first candidate. None: every row is a
            feature of its own.

    Returns:
        keep: (N,) bool, True for matches whose own peak bin is a correct bin of the overall
            accumulator. Matches that received no vote (N < 2, duplicates only, ...) are False.
        stats: JSON-ready dict: accumulator ``histogram`` (n_scale x n_rot nested list of vote
            weights, rows = scale bins, columns = rotation bins), bin centres, the peak rotation
            (deg, [0, 360)) and scale, ``vote_threshold`` (= min_vote_ratio * peak votes), the
            number of correct bins, pairs evaluated/voting, partners per match, whether
            partners were subsampled, and confidence summaries.
    """
    xy1, xy2 = _validate_keypoints(kp1, kp2)
    n = xy1.shape[0]
    grid = _make_grid(options)
    valid_pt = np.isfinite(xy1).all(axis=1) & np.isfinite(xy2).all(axis=1)
    xy1[~valid_pt] = 0.0
    xy2[~valid_pt] = 0.0

    first, position = _features(query_ids, n)
    n_features = len(first)
    cap = options.max_partners
    subsample = cap is not None and n_features - 1 > cap
    n_partners = cap if subsample and cap is not None else max(n_features - 1, 0)
    perm: np.ndarray | None = None
    offsets: np.ndarray | None = None
    if subsample:
        rng = np.random.default_rng(options.seed)
        perm = rng.permutation(n_features)
        offsets = np.asarray(rng.integers(0, n_features, size=n))

    overall = np.zeros(grid.n_bins, dtype=np.float64)
    peak_bin = np.zeros(n, dtype=np.int64)
    total = np.zeros(n, dtype=np.float64)
    peak_votes = np.zeros(n, dtype=np.float64)
    pairs_voting = 0
    if n_features >= 2 and not subsample and _COMPILED:
        pairs_voting = _vote_every_pair(
            xy1,
            xy2,
            valid_pt,
            np.ascontiguousarray(first, dtype=np.int64),
            np.ascontiguousarray(position, dtype=np.int64),
            grid.n_rot,
            grid.rot_width_deg,
            grid.n_scale_half,
            grid.log_width,
            float(options.distance_weight_px),
            overall,
            peak_bin,
            peak_votes,
            total,
        )
    elif n_features >= 2:
        per_row = n_partners * _BYTES_PER_PAIR + grid.n_bins * 8
        chunk = max(1, _CHUNK_BYTES // per_row)
        for start in range(0, n, chunk):
            rows = np.arange(start, min(start + chunk, n))
            chunk_offsets = None if offsets is None else offsets[rows]
            partners = first[_partners(position[rows], n_features, n_partners, perm, chunk_offsets)]
            flat, weight = _pair_bins(
                xy1, xy2, valid_pt, rows, partners, grid, float(options.distance_weight_px)
            )
            pairs_voting += int(np.count_nonzero(weight))
            local = np.arange(len(rows))[:, None] * grid.n_bins + flat
            hist = np.bincount(
                local.ravel(), weights=weight.ravel(), minlength=len(rows) * grid.n_bins
            ).reshape(len(rows), grid.n_bins)
            overall += hist.sum(axis=0)
            best = np.argmax(hist, axis=1)
            peak_bin[rows] = best
            peak_votes[rows] = hist[np.arange(len(rows)), best]
            total[rows] = hist.sum(axis=1)

    correct = _correct_bins(overall, grid, options)
    keep = correct[peak_bin] & (total > 0.0) & valid_pt
    confidence = np.divide(peak_votes, total, out=np.zeros(n), where=total > 0.0)
    stats = _stats(
        overall, correct, keep, confidence, grid, options, n, n_partners, subsample, pairs_voting
    )
    stats["features"] = n_features
    if n_features < 2:
        stats["pairs_evaluated"] = 0
    return keep, stats


def _stats(
    overall: np.ndarray,
    correct: np.ndarray,
    keep: np.ndarray,
    confidence: np.ndarray,
    grid: _Grid,
    options: GCOptions,
    n: int,
    n_partners: int,
    subsample: bool,
    pairs_voting: int,
) -> dict[str, Any]:
    """JSON-ready summary of one filter run (plain Python scalars and lists, no NaN)."""
    peak = int(np.argmax(overall))
    peak_votes = float(overall[peak])
    voted = peak_votes > 0.0
    ps, pr = divmod(peak, grid.n_rot)
    rot_centres = [k * grid.rot_width_deg for k in range(grid.n_rot)]
    scale_centres = [
        math.exp((k - grid.n_scale_half) * grid.log_width) for k in range(grid.n_scale)
    ]

    def _summary(values: np.ndarray) -> float | None:
        return float(np.median(values)) if values.size else None

    return {
        "method": "lu2016_geometrical_consistency_voting",
        "n_matches": n,
        "n_kept": int(np.count_nonzero(keep)),
        "partners_per_match": n_partners,
        "subsampled": bool(subsample),
        "pairs_evaluated": n * n_partners if n >= 2 else 0,
        "pairs_voting": pairs_voting,
        "rotation_bin_deg": grid.rot_width_deg,
        "log_scale_bin": grid.log_width,
        "rotation_bin_centres_deg": rot_centres,
        "scale_bin_centres": scale_centres,
        "histogram": overall.reshape(grid.n_scale, grid.n_rot).tolist(),
        "peak_rotation_deg": rot_centres[pr] if voted else None,
        "peak_scale": scale_centres[ps] if voted else None,
        "peak_votes": peak_votes,
        "vote_threshold": options.min_vote_ratio * peak_votes,
        "n_correct_bins": int(np.count_nonzero(correct)),
        "median_confidence_kept": _summary(confidence[keep]),
        "median_confidence_rejected": _summary(confidence[~keep]),
    }


def verify_gc_ransac(pair: PairData, options: VerifyOptions, stages: Stages) -> MethodResult:
    """Method ``gc-ransac``: the Lu et al. (2016) pre-filter (needs keypoint size and angle),
    then ``options.ransac`` on its survivors; the filter draws from ``options.seed``."""
    for name, kp in (("keypoints1", pair.keypoints1), ("keypoints2", pair.keypoints2)):
        if kp.shape[1] != 4:
            raise InputError(name, "gc-ransac needs [x, y, size, angle_deg] keypoints")
    ransac = options.ransac
    require_matches(pair, min_matches(ransac.model, ransac.estimator), ransac.model)
    if options.gc.seed != options.seed:  # one seed for every random stage, echoed truthfully
        options = dataclasses.replace(
            options, gc=dataclasses.replace(options.gc, seed=options.seed)
        )
    kp1 = pair.keypoints1[pair.matches[:, 0]]
    kp2 = pair.keypoints2[pair.matches[:, 1]]
    with stages.stage("gc", len(kp1)) as st:
        keep, stats = gc_filter(kp1, kp2, options.gc, query_ids=pair.matches[:, 0])
        candidates = np.flatnonzero(st.done(keep, stats))
    stages.survivors["gc"] = candidates
    px1, px2 = kp1[candidates, :2], kp2[candidates, :2]
    with stages.stage("ransac", len(candidates)) as st:
        fit = fit_final(pair, px1, px2, options.ransac, options.seed)
        inliers = candidates[st.done(fit.inliers, fit.stats)]
    stages.survivors["ransac"] = inliers
    statistics = {"degenerate": fit.stats["degenerate"]} if "degenerate" in fit.stats else {}
    return MethodResult(inliers, fit.model, fit.matrix, statistics, options)
