"""HMCC+ (method ``hmcc-plus``): motion consistency that ranks instead of cutting, a model fitted
on the most consistent matches, and every match decided against that model.

The paper's filter removes true matches at each vote and passes only its survivors on. Here the
ground motions (the same projection onto Z0) score the matches; the best-scored ones give a clean
fundamental matrix fast; then **all** matches are classified by their Sampson distance to it, with
local-optimisation refits (Chum et al. 2003), so the scoring's mistakes do not become the user's.

Scoring, two complementary views of one fact (a true motion is the same rigid displacement of the
plane plus a parallax along its epipolar line on the plane):

1. :func:`motion_field_seeds` - the 2-D mode of the motion vectors (a coarse 2-D Hough vote with
   a 3x3 window, so a flipped 1-D direction peak cannot fool it), then an affine motion field
   ``v = A s + b`` with its 2x2 residual covariance, fitted by Cauchy-weighted least squares
   around the mode. Matches whose Mahalanobis residual is smallest are the *seeds*: very clean,
   but they favour one height (parallax changes a motion's length).
2. :func:`epipolar_band` - the parallax of a true match lies on the line through its start point
   and the point where the camera baseline meets the plane (the plane's epipole, from the rough
   poses). Distance across that line, after removing an affine field fitted on the seeds, is
   independent of the point's height; matches in that band (and not absurdly far along it) add
   the roofs and hills the seeds miss, which keeps the fitted model from being planar-degenerate.

The fitted model is checked (enough inliers, the seeds agree with it); if not, a full robust
estimator runs on all matches instead (``fallback``) and the result says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from .ransac import ESTIMATORS, EstimatorName

__all__ = [
    "PlusOptions",
    "epipolar_band",
    "fit_candidates",
    "motion_field_seeds",
    "plane_epipole_directions",
    "refine_fundamental",
    "sampson_distance",
]

#: Mahalanobis distance (squared) under which a match counts as on the motion field: chi2(2) 99 %.
_FIELD_CHI2 = 9.21
_CAUCHY_ITERATIONS = 3


@dataclass(frozen=True)
class PlusOptions:
    """Parameters of ``hmcc-plus`` (see :mod:`hmcc.plus`); the defaults are the measured ones."""

    grid_bins: int = 24  # cells per axis of the 2-D motion vote over the 2-98 % range
    max_seeds: int = 60  # most seeds (smallest motion-field residuals)
    max_band: int = 150  # most band matches (smallest distance across the epipolar line)
    band_length: float = 3.0  # along the line: |parallax - seeds' median| <= this x median
    gate: bool = True  # inliers must also have a plausible parallax (within band_length)
    threshold_px: float = 1.5  # Sampson distance deciding inliers, pixels
    lo_schedule: tuple[float, ...] = (2.0, 1.0, 1.0)  # refit thresholds, x threshold_px
    model_max_iters: int = 500  # USAC iterations on the candidates
    min_inliers: int = 15  # fewer: HMCC is unreliable for the pair, fall back
    min_seed_agreement: float = 0.5  # smaller share of seeds among the inliers: fall back
    fallback: EstimatorName = "usac-accurate"

    def __post_init__(self) -> None:
        if not 4 <= self.grid_bins <= 1024:
            raise ValueError("grid_bins: must be in [4, 1024]")
        if not 8 <= self.max_seeds <= 100_000:
            raise ValueError("max_seeds: must be in [8, 100000]")
        if not 0 <= self.max_band <= 100_000:
            raise ValueError("max_band: must be in [0, 100000]")
        if not 0.0 <= self.band_length <= 100.0:
            raise ValueError("band_length: must be in [0, 100]")
        if not 0.0 < self.threshold_px <= 100.0:
            raise ValueError("threshold_px: must be in (0, 100]")
        if len(self.lo_schedule) > 10 or not all(0.5 <= m <= 20.0 for m in self.lo_schedule):
            raise ValueError("lo_schedule: at most 10 multipliers, each in [0.5, 20]")
        if not 1 <= self.model_max_iters <= 100_000:
            raise ValueError("model_max_iters: must be in [1, 100000]")
        if not 8 <= self.min_inliers <= 100_000:
            raise ValueError("min_inliers: must be in [8, 100000]")
        if not 0.0 <= self.min_seed_agreement <= 1.0:
            raise ValueError("min_seed_agreement: must be in [0, 1]")
        if self.fallback not in ESTIMATORS:
            raise ValueError(f"fallback: must be one of {list(ESTIMATORS)}")


# --------------------------------------------------------------------------- scoring


def _motion_mode(vectors: np.ndarray, bins: int) -> tuple[np.ndarray, float, int]:
    """Centre of the densest 3x3 window of a ``bins`` x ``bins`` histogram of the motion
    vectors over their 2-98 % range; the cell size (m) and the window's votes."""
    n = len(vectors)
    k_lo, k_hi = int(0.02 * (n - 1)), int(0.98 * (n - 1))
    lo = np.empty(2)
    hi = np.empty(2)
    for axis in range(2):
        q = np.partition(vectors[:, axis], (k_lo, k_hi))
        lo[axis], hi[axis] = q[k_lo], q[k_hi]
    cell = max(float((hi - lo).max()) / bins, 1e-9)
    ij = np.floor((vectors - lo) / cell).astype(np.int64)
    inside = (ij >= 0).all(axis=1) & (ij < bins).all(axis=1)
    side = bins + 2  # one empty cell of padding on each side
    flat = (ij[inside, 0] + 1) * side + ij[inside, 1] + 1
    h = np.bincount(flat, minlength=side * side).reshape(side, side)
    window = np.zeros((bins, bins), dtype=np.int64)
    for a in range(3):
        for b in range(3):
            window += h[a : a + bins, b : b + bins]
    i, j = divmod(int(window.argmax()), bins)
    centre = lo + (np.array([i, j]) + 0.5) * cell
    return centre, cell, int(window[i, j])


def motion_field_seeds(
    start: np.ndarray, vectors: np.ndarray, options: PlusOptions
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Seeds (indices, best first) and the (N,) squared Mahalanobis residuals to the robust
    affine motion field, with statistics."""
    centre, cell, votes = _motion_mode(vectors, options.grid_bins)
    radius = 1.5 * cell
    near = ((vectors - centre) ** 2).sum(axis=1) < radius * radius
    if np.count_nonzero(near) < 3:  # no mode to speak of (degenerate spread): use everything
        near = np.ones(len(vectors), dtype=bool)
    design = np.ones((len(start), 3))
    design[:, :2] = start - start[near].mean(axis=0)
    residual = vectors - np.median(vectors[near], axis=0)
    cov = np.eye(2) * (radius * radius / 4.0)
    for _ in range(_CAUCHY_ITERATIONS):
        m2 = _mahalanobis_sq(residual, cov)
        w = np.where(near, 1.0 / (1.0 + m2), 0.0)
        wd = design * w[:, None]
        field = np.linalg.solve(wd.T @ design + 1e-9 * np.eye(3), wd.T @ vectors)
        residual = vectors - design @ field
        rw = residual[near] * np.sqrt(w[near])[:, None]
        cov = rw.T @ rw / max(float(w[near].sum()), 1e-12) + 1e-12 * np.eye(2)
        near = _mahalanobis_sq(residual, cov) < 4.0 * _FIELD_CHI2
    m2 = _mahalanobis_sq(residual, cov)
    order = np.argsort(m2, kind="stable")
    k = int(np.clip(np.count_nonzero(m2 < _FIELD_CHI2), 8, options.max_seeds))
    seeds = order[:k]
    stats = {
        "peak_votes": votes,
        "peak_share": votes / len(vectors),
        "cell_m": cell,
        "field_sigma_m": float(np.sqrt(np.linalg.eigvalsh(cov)).max()),
        "on_field": int(np.count_nonzero(m2 < _FIELD_CHI2)),
        "seeds": len(seeds),
    }
    return seeds, m2, stats


def _mahalanobis_sq(residual: np.ndarray, cov: np.ndarray) -> np.ndarray:
    inv = np.linalg.inv(cov)
    return np.einsum("ij,jk,ik->i", residual, inv, residual)


def plane_epipole_directions(
    start: np.ndarray, center1: np.ndarray, center2: np.ndarray, z0: float
) -> np.ndarray | None:
    """(N, 2) unit directions of the epipolar lines on the plane Z = z0 through each start point:
    towards the point where the baseline meets the plane (parallel to the baseline when both
    cameras fly at the same height). None when the cameras coincide."""
    a1, a2 = center1[2] - z0, center2[2] - z0
    epipole = np.array(
        [a2 * center1[0] - a1 * center2[0], a2 * center1[1] - a1 * center2[1], a2 - a1]
    )
    if not np.abs(epipole).max() > 1e-9 * max(abs(a1), abs(a2), 1.0) ** 2:
        return None
    d = epipole[:2][None, :] - epipole[2] * start
    norm = np.hypot(d[:, 0], d[:, 1])
    if not (norm > 0).all():
        return None
    return d / norm[:, None]


def epipolar_band(
    start: np.ndarray,
    vectors: np.ndarray,
    directions: np.ndarray,
    seeds: np.ndarray,
    options: PlusOptions,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Indices of up to ``max_band`` matches closest to their epipolar line on the plane (after
    an affine field fitted on the seeds) among those whose parallax along it is plausible (off
    the seeds' affine field by at most ``band_length`` x their median parallax + 3 sigma), and
    the (N,) mask of those plausible matches."""
    across_dir = np.column_stack((-directions[:, 1], directions[:, 0]))
    across = (vectors * across_dir).sum(axis=1)
    along = (vectors * directions).sum(axis=1)
    design = np.ones((len(start), 3))
    design[:, :2] = start - start[seeds].mean(axis=0)
    w = np.zeros(len(start))
    w[seeds] = 1.0
    sigma = 1.0
    for _ in range(_CAUCHY_ITERATIONS):
        wd = design * w[:, None]
        coef = np.linalg.solve(wd.T @ design + 1e-9 * np.eye(3), wd.T @ across)
        off = across - design @ coef
        sigma = max(1.4826 * float(np.median(np.abs(off[seeds]))), 1e-9)
        w = 1.0 / (1.0 + (off / (2.0 * sigma)) ** 2)
    wd = design[seeds]
    coef = np.linalg.lstsq(wd, along[seeds], rcond=None)[0]
    along_off = along - design @ coef
    parallax = float(np.median(along[seeds]))
    along_sigma = 1.4826 * float(np.median(np.abs(along_off[seeds])))
    reach = options.band_length * abs(parallax) + 3.0 * max(sigma, along_sigma)
    plausible = np.abs(along_off) <= reach
    score = np.where(plausible, np.abs(off) / sigma, np.inf)
    k = min(options.max_band, int(np.count_nonzero(score < 3.0)))
    band = np.argsort(score, kind="stable")[:k]
    stats = {
        "across_sigma_m": sigma,
        "median_parallax_m": parallax,
        "parallax_reach_m": reach,
        "band": len(band),
    }
    return band, plausible, stats


# --------------------------------------------------------------------------- model


def sampson_distance(f: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(N,) Sampson distance (pixels) of (N, 2) correspondences to ``x2^T F x1 = 0``."""
    fx1 = p1 @ f[:, :2].T + f[:, 2]  # rows: F x1
    ftx2 = p2 @ f[:2, :] + f[2, :]  # rows: F^T x2
    r = (p2 * fx1[:, :2]).sum(axis=1) + fx1[:, 2]
    den = fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2
    return np.abs(r) / np.sqrt(np.maximum(den, 1e-300))


def _eight_point(p1: np.ndarray, p2: np.ndarray) -> np.ndarray | None:
    if len(p1) < 8:
        return None
    f, _ = cv2.findFundamentalMat(p1, p2, cv2.FM_8POINT)
    return f if f is not None and f.shape == (3, 3) and np.isfinite(f).all() else None


def fit_candidates(
    p1: np.ndarray, p2: np.ndarray, options: PlusOptions, seed: int
) -> np.ndarray | None:
    """F from the (K, 2) candidate pixels: OpenCV's USAC with MAGSAC scoring, sigma-consensus
    local optimisation and the MAGSAC polish (measured: the MSAC + inner-LO variant stalled on
    a plane-dominant model in oblique pairs)."""
    if len(p1) < 8:
        return None
    params = cv2.UsacParams()
    params.sampler = cv2.SAMPLING_UNIFORM
    params.score = cv2.SCORE_METHOD_MAGSAC
    params.loMethod = cv2.LOCAL_OPTIM_SIGMA
    params.final_polisher = cv2.MAGSAC
    params.threshold = options.threshold_px
    params.confidence = 0.99
    params.maxIterations = options.model_max_iters
    params.randomGeneratorState = seed
    f, mask = cv2.findFundamentalMat(p1, p2, params)
    if f is None or mask is None or f.shape[0] < 3 or not mask.any():
        return None
    return np.asarray(f[:3], dtype=np.float64)


def refine_fundamental(
    f: np.ndarray, p1: np.ndarray, p2: np.ndarray, options: PlusOptions
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Local optimisation on all matches: for each multiplier m of ``lo_schedule``, refit F by
    least squares on the matches within m x threshold; keep the model with the most inliers at
    the threshold. Returns F, the (N,) inlier mask and statistics."""
    t = options.threshold_px
    best_f, best_d = f, sampson_distance(f, p1, p2)
    first = int(np.count_nonzero(best_d < t))
    steps = 0
    for m in options.lo_schedule:
        within = best_d < m * t
        refit = _eight_point(p1[within], p2[within])
        steps += 1
        if refit is None:
            break
        d = sampson_distance(refit, p1, p2)
        if np.count_nonzero(d < t) >= np.count_nonzero(best_d < t):
            best_f, best_d = refit, d
    best = best_d < t
    stats = {"inliers_before": first, "inliers_after": int(best.sum()), "refits": steps}
    return best_f, best, stats
