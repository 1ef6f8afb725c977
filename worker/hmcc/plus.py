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

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from . import plus_kernels as kernels
from .ransac import ESTIMATORS, EstimatorName

__all__ = [
    "Correspondences",
    "PlusOptions",
    "epipolar_band",
    "fit_candidates",
    "motion_field_seeds",
    "plane_epipole_directions",
    "refine_fundamental",
    "sampson_distance",
]


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
    strong_parallax: float = 3.0  # off the seeds' field along the line by this x sigma: strong
    hypotheses: int = 32  # 8-point samples drawn from the candidates
    parallax_points: int = 3  # of each sample's 8 points, drawn from the strong-parallax ones
    polish: int = 3  # best-scored hypotheses refined by least squares on their inliers
    min_candidate_share: float = 0.7  # fewer candidates fit the model: USAC on the candidates
    model_max_iters: int = 500  # USAC iterations on the candidates (when sampling fails)
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
        if not 0.0 <= self.strong_parallax <= 100.0:
            raise ValueError("strong_parallax: must be in [0, 100]")
        if not 1 <= self.hypotheses <= 10_000:
            raise ValueError("hypotheses: must be in [1, 10000]")
        if not 0 <= self.parallax_points <= 8:
            raise ValueError("parallax_points: must be in [0, 8]")
        if not 1 <= self.polish <= self.hypotheses:
            raise ValueError("polish: must be in [1, hypotheses]")
        if not 0.0 <= self.min_candidate_share <= 1.0:
            raise ValueError("min_candidate_share: must be in [0, 1]")
        if not 1 <= self.model_max_iters <= 100_000:
            raise ValueError("model_max_iters: must be in [1, 100000]")
        if not 8 <= self.min_inliers <= 100_000:
            raise ValueError("min_inliers: must be in [8, 100000]")
        if not 0.0 <= self.min_seed_agreement <= 1.0:
            raise ValueError("min_seed_agreement: must be in [0, 1]")
        if self.fallback not in ESTIMATORS:
            raise ValueError(f"fallback: must be one of {list(ESTIMATORS)}")


# --------------------------------------------------------------------------- scoring
# The loops run compiled (:mod:`hmcc.plus_kernels`); here: options in, statistics out.


def motion_field_seeds(
    start: np.ndarray, vectors: np.ndarray, options: PlusOptions
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Seeds (indices, best first) and the (N,) squared Mahalanobis residuals to the robust
    affine motion field, with statistics."""
    cx, cy, cell, votes = kernels.motion_mode(vectors, options.grid_bins)
    seeds, m2, cov, on_field = kernels.motion_field(
        start, vectors, cx, cy, 1.5 * cell, options.max_seeds
    )
    (c00, c01), (_, c11) = cov.tolist()
    largest = 0.5 * (c00 + c11) + math.hypot(0.5 * (c00 - c11), c01)
    stats = {
        "peak_votes": votes,
        "peak_share": votes / len(start),
        "cell_m": cell,
        "field_sigma_m": math.sqrt(max(largest, 0.0)),
        "on_field": on_field,
        "seeds": len(seeds),
    }
    return seeds, m2, stats


def plane_epipole_directions(
    start: np.ndarray, center1: np.ndarray, center2: np.ndarray, z0: float
) -> np.ndarray | None:
    """(N, 2) unit directions of the epipolar lines on the plane Z = z0 through each start point:
    towards the point where the baseline meets the plane (parallel to the baseline when both
    cameras fly at the same height). None when the cameras coincide."""
    directions, ok = kernels.plane_epipole_directions(start, center1, center2, float(z0))
    return directions if ok else None


def epipolar_band(
    start: np.ndarray,
    vectors: np.ndarray,
    directions: np.ndarray,
    seeds: np.ndarray,
    options: PlusOptions,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """Indices of up to ``max_band`` matches closest to their epipolar line on the plane (after
    an affine field fitted on the seeds) among those whose parallax along it is plausible (off
    the seeds' affine field by at most ``band_length`` x their median parallax + 3 sigma), the
    (N,) mask of those plausible matches, and the (N,) mask of strong parallax (off the field
    along the line by more than ``strong_parallax`` sigma: another height than the seeds').

    The distance across the line is refitted twice on all matches, Cauchy-weighted; sigma is
    the seeds' scaled median absolute distance."""
    band, plausible, strong, sigma, parallax, reach = kernels.epipolar_band(
        start,
        vectors,
        directions,
        seeds,
        options.max_band,
        options.band_length,
        options.strong_parallax,
    )
    stats = {
        "across_sigma_m": sigma,
        "median_parallax_m": parallax,
        "parallax_reach_m": reach,
        "band": len(band),
        "strong_parallax": int(np.count_nonzero(strong[band])),
    }
    return band, plausible, strong, stats


# --------------------------------------------------------------------------- model


def sampson_distance(f: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(N,) Sampson distance (pixels) of (N, 2) correspondences to ``x2^T F x1 = 0``."""
    fx1 = p1 @ f[:, :2].T + f[:, 2]  # rows: F x1
    ftx2 = p2 @ f[:2, :] + f[2, :]  # rows: F^T x2
    r = (p2 * fx1[:, :2]).sum(axis=1) + fx1[:, 2]
    den = fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2
    return np.abs(r) / np.sqrt(np.maximum(den, 1e-300))


class Correspondences:
    """(N, 2) pixel pairs prepared once for every fit on them.

    Both images are normalised by one similarity each with a *common* scale (centroid to the
    origin, mean absolute coordinate 1), so a Sampson distance in normalised coordinates is the
    pixel one times ``scale``: models are fitted, scored and refined without going back to
    pixels. ``joint`` holds the homogeneous normalised points of both images side by side.
    """

    def __init__(self, p1: np.ndarray, p2: np.ndarray) -> None:
        self.p1 = np.ascontiguousarray(p1, dtype=np.float64)
        self.p2 = np.ascontiguousarray(p2, dtype=np.float64)
        self.joint, self.scale, self._t1, self._t2 = kernels.normalise(self.p1, self.p2)

    def __len__(self) -> int:
        return len(self.joint)

    def to_pixels(self, f: np.ndarray) -> np.ndarray:
        """The pixel model (unit Frobenius norm) of a normalised one."""
        return kernels.to_pixels(np.ascontiguousarray(f, dtype=np.float64), self._t1, self._t2)

    def from_pixels(self, f: np.ndarray) -> np.ndarray:
        """The normalised model of a pixel one."""
        return np.linalg.inv(self._t2).T @ f @ np.linalg.inv(self._t1)

    def sampson_sq(self, f: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """(R,) squared normalised Sampson distances of ``rows`` (all when None) to the
        normalised model ``f``."""
        return kernels.sampson_sq(np.ascontiguousarray(f), self.joint, self._rows(rows))

    def least_squares(self, mask: np.ndarray) -> np.ndarray | None:
        """The rank-2 normalised model minimising the algebraic error of the masked rows."""
        f, ok = kernels.least_squares(self.joint, np.flatnonzero(mask))
        return f if ok else None

    def minimal(self, samples: np.ndarray) -> np.ndarray:
        """(K, 3, 3) normalised models of (K, 8) row samples (8-point, gauge-fixed, no rank-2
        step: they are only scored); singular samples dropped."""
        return kernels.minimal_models(self.joint, np.ascontiguousarray(samples, dtype=np.int64))

    def _rows(self, rows: np.ndarray | None) -> np.ndarray:
        return np.arange(len(self.joint)) if rows is None else np.asarray(rows, dtype=np.int64)


def fit_candidates(
    corr: Correspondences,
    candidates: np.ndarray,
    strong: np.ndarray,
    options: PlusOptions,
    seed: int,
) -> tuple[np.ndarray | None, np.ndarray, dict[str, Any]]:
    """A normalised F from the candidate rows of ``corr``, its (C,) inlier mask over the
    candidates, and statistics.

    Candidates are mostly true but dominated by one height, so a uniform 8-point sample rarely
    holds enough parallax and its model is plane-degenerate. Each of ``hypotheses`` samples
    therefore takes ``parallax_points`` of its 8 points from the candidates with strong parallax
    (``strong``, off the seeds' affine field along the epipolar line). The ``polish`` best by
    truncated (MSAC) score at 2 x threshold are refitted by least squares on their candidate
    inliers within 2 x threshold; the one with the most candidate inliers is kept. If fewer
    than ``min_candidate_share`` of the candidates fit it, OpenCV's USAC (MAGSAC score,
    sigma-consensus) runs on the candidates instead (``usac``)."""
    stats: dict[str, Any] = {"usac": False, "hypotheses": 0, "candidate_share": 0.0}
    none = np.zeros(len(candidates), dtype=bool)
    if len(candidates) < 8:
        return None, none, stats
    t2 = (options.threshold_px * corr.scale) ** 2
    candidates = np.asarray(candidates, dtype=np.int64)
    f, found, inliers, stats["hypotheses"] = kernels.fit_candidates(
        corr.joint,
        candidates,
        np.asarray(strong, dtype=bool),
        options.hypotheses,
        options.parallax_points,
        options.polish,
        t2,
        seed,
    )
    if found:
        stats["candidate_share"] = int(np.count_nonzero(inliers)) / len(candidates)
        if stats["candidate_share"] >= options.min_candidate_share:
            return f, inliers, stats
    stats["usac"] = True
    rescue = _usac(corr.p1[candidates], corr.p2[candidates], options, seed)
    if rescue is None:
        return None, none, stats
    f = corr.from_pixels(rescue)
    return f, corr.sampson_sq(f, candidates) < t2, stats


def _usac(p1: np.ndarray, p2: np.ndarray, options: PlusOptions, seed: int) -> np.ndarray | None:
    """OpenCV's USAC with MAGSAC scoring, sigma-consensus local optimisation and the MAGSAC
    polish (measured: the MSAC + inner-LO variant stalled on plane-dominant models)."""
    params = cv2.UsacParams()
    params.sampler = cv2.SAMPLING_UNIFORM
    params.score = cv2.SCORE_METHOD_MAGSAC
    params.loMethod = cv2.LOCAL_OPTIM_SIGMA
    params.final_polisher = cv2.MAGSAC
    params.threshold = options.threshold_px
    params.confidence = 0.99
    params.maxIterations = options.model_max_iters
    params.randomGeneratorState = seed
    try:
        f, mask = cv2.findFundamentalMat(p1, p2, params)
    except cv2.error:  # USAC asserts on some degenerate candidate sets (OpenCV 5.0): no model
        return None
    if f is None or mask is None or f.shape[0] < 3 or not mask.any():
        return None
    return np.asarray(f[:3], dtype=np.float64)


def refine_fundamental(
    corr: Correspondences, f: np.ndarray, options: PlusOptions
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Local optimisation on all matches: for each multiplier m of ``lo_schedule``, refit the
    normalised F by least squares on the matches within m x threshold; keep the model with the
    most inliers at the threshold. Returns the pixel F, the (N,) inlier mask and statistics."""
    t2 = (options.threshold_px * corr.scale) ** 2
    best, inliers, first, count, steps = kernels.refine(
        corr.joint, np.ascontiguousarray(f), t2, np.asarray(options.lo_schedule, dtype=float)
    )
    stats = {"inliers_before": first, "inliers_after": count, "refits": steps}
    return corr.to_pixels(best), inliers, stats
