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
    "Correspondences",
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


# Small dense algebra here is done with closed forms, cv2 and few numpy calls: a numpy call costs
# about 1-10 us whatever its size, and these stages run on every pair (measured in
# benchmarks/bench_default.py; the whole method takes well under a millisecond).


def _median(x: np.ndarray) -> float:
    """Median (the upper one for an even count) by partition: np.median costs 10x more."""
    k = len(x) // 2
    return float(np.partition(x, k)[k]) if len(x) else 0.0


def _weighted_lsq(xr: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(3, k) coefficients of the weighted least-squares fit of the columns ``xr[:, 3:]`` on the
    design ``xr[:, :3]`` (one matrix product for the normal equations of every column)."""
    m = (xr[:, :3] * w[:, None]).T @ xr
    normal = m[:, :3] + 1e-9 * np.eye(3)
    return cv2.invert(normal)[1] @ m[:, 3:]


def _inverse2(cov: np.ndarray) -> tuple[float, float, float]:
    """(a, b, d) of the inverse [[a, b], [b, d]] of a symmetric 2x2 covariance."""
    (c00, c01), (_, c11) = cov.tolist()
    det = max(c00 * c11 - c01 * c01, 1e-300)
    return c11 / det, -c01 / det, c00 / det


def _mahalanobis_sq(residual: np.ndarray, cov: np.ndarray) -> np.ndarray:
    a, b, d = _inverse2(cov)
    x, y = residual[:, 0], residual[:, 1]
    return (a * x + 2.0 * b * y) * x + d * y * y


def _motion_mode(vectors: np.ndarray, bins: int) -> tuple[np.ndarray, float, int]:
    """Centre of the densest 3x3 window of a ``bins`` x ``bins`` histogram of the motion
    vectors over their 2-98 % range; the cell size (m) and the window's votes."""
    n = len(vectors)
    k_lo, k_hi = int(0.02 * (n - 1)), int(0.98 * (n - 1))
    q = np.partition(vectors, (k_lo, k_hi), axis=0)
    lo = q[k_lo]
    (x0, y0), (x1, y1) = lo.tolist(), q[k_hi].tolist()
    cell = max(x1 - x0, y1 - y0, 1e-9 * bins) / bins
    # Cells 2 .. bins+1 of a grid padded by two: everything outside the range lands in the
    # outer ring (clipped), which no window reaches.
    side = bins + 4
    # + 2 before the cast: truncation is the floor for everything that is not clipped anyway
    ij = np.minimum(np.maximum(((vectors - lo) * (1.0 / cell) + 2.0).astype(np.int64), 0), side - 1)
    h = np.bincount(ij[:, 0] * side + ij[:, 1], minlength=side * side).reshape(side, side)
    window = h[1 : bins + 1, 1 : bins + 1].copy()
    for da, db in ((0, 1), (0, 2), (1, 0), (1, 1), (1, 2), (2, 0), (2, 1), (2, 2)):
        window += h[1 + da : bins + 1 + da, 1 + db : bins + 1 + db]
    i, j = divmod(int(window.argmax()), bins)
    centre = np.array([x0 + (i + 0.5) * cell, y0 + (j + 0.5) * cell])
    return centre, cell, int(window[i, j])


def motion_field_seeds(
    start: np.ndarray, vectors: np.ndarray, options: PlusOptions
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Seeds (indices, best first) and the (N,) squared Mahalanobis residuals to the robust
    affine motion field, with statistics."""
    centre, cell, votes = _motion_mode(vectors, options.grid_bins)
    radius = 1.5 * cell
    n = len(start)
    xr = np.empty((n, 5))  # design [x, y, 1] (start, centred) | the motion vectors
    xr[:, :2] = start - start.sum(axis=0) / n
    xr[:, 2] = 1.0
    xr[:, 3:] = vectors
    residual = vectors - centre
    cov = np.eye(2) * (radius * radius / 4.0)
    m2 = _mahalanobis_sq(residual, cov)
    near = m2 < 4.0  # within the radius of the mode
    if np.count_nonzero(near) < 3:  # no mode to speak of (degenerate spread): use everything
        near = np.ones(n, dtype=bool)
    for _ in range(_CAUCHY_ITERATIONS):
        w = near / (1.0 + m2)
        residual = vectors - xr[:, :3] @ _weighted_lsq(xr, w)
        cov = (residual * w[:, None]).T @ residual / max(float(w.sum()), 1e-12)
        cov += 1e-12 * np.eye(2)
        m2 = _mahalanobis_sq(residual, cov)
        near = m2 < 4.0 * _FIELD_CHI2
    order = np.argsort(m2, kind="stable")
    on_field = int(np.count_nonzero(m2 < _FIELD_CHI2))
    seeds = order[: int(np.clip(on_field, 8, options.max_seeds))]
    (c00, c01), (_, c11) = cov.tolist()
    largest = 0.5 * (c00 + c11) + float(np.hypot(0.5 * (c00 - c11), c01))
    stats = {
        "peak_votes": votes,
        "peak_share": votes / n,
        "cell_m": cell,
        "field_sigma_m": float(np.sqrt(max(largest, 0.0))),
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
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """Indices of up to ``max_band`` matches closest to their epipolar line on the plane (after
    an affine field fitted on the seeds) among those whose parallax along it is plausible (off
    the seeds' affine field by at most ``band_length`` x their median parallax + 3 sigma), the
    (N,) mask of those plausible matches, and the (N,) mask of strong parallax (off the field
    along the line by more than ``strong_parallax`` sigma: another height than the seeds')."""
    n = len(start)
    d0, d1 = directions[:, 0], directions[:, 1]
    v0, v1 = vectors[:, 0], vectors[:, 1]
    xr = np.empty((n, 5))  # design [x, y, 1] | across the line | along it
    xr[:, :2] = start - start.sum(axis=0) / n
    xr[:, 2] = 1.0
    xr[:, 3] = v1 * d0 - v0 * d1
    xr[:, 4] = v0 * d0 + v1 * d1
    w = np.zeros(n)
    w[seeds] = 1.0
    off = xr[:, 3:] - xr[:, :3] @ _weighted_lsq(xr, w)  # both fitted on the seeds
    along_off = off[:, 1]
    across = off[:, 0]
    sigma = max(1.4826 * _median(np.abs(across[seeds])), 1e-9)
    for _ in range(_CAUCHY_ITERATIONS - 1):  # then all matches, Cauchy-weighted, across only
        w = 1.0 / (1.0 + (across / (2.0 * sigma)) ** 2)
        across = xr[:, 3] - xr[:, :3] @ _weighted_lsq(xr[:, :4], w)[:, 0]
        sigma = max(1.4826 * _median(np.abs(across[seeds])), 1e-9)
    parallax = _median(xr[seeds, 4])
    along_sigma = 1.4826 * _median(np.abs(along_off[seeds]))
    reach = options.band_length * abs(parallax) + 3.0 * max(sigma, along_sigma)
    along_abs = np.abs(along_off)
    plausible = along_abs <= reach
    score = np.where(plausible, np.abs(across), np.inf)
    k = min(options.max_band, int(np.count_nonzero(score < 3.0 * sigma)))
    band = np.argsort(score, kind="stable")[:k]
    strong = along_abs > options.strong_parallax * max(sigma, along_sigma)
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


#: Normalises the 8-point systems of the minimal samples: f . _GAUGE = 1 (a fixed generic
#: direction; f33 = 1 would fail where the centroids correspond, the usual case).
_GAUGE = np.array([0.31, -0.27, 0.42, 0.19, 0.36, -0.33, 0.28, -0.39, 0.41])


class Correspondences:
    """(N, 2) pixel pairs prepared once for every fit on them.

    Both images are normalised by one similarity each with a *common* scale (centroid to the
    origin, mean absolute coordinate 1), so a Sampson distance in normalised coordinates is the
    pixel one times ``scale``: models are fitted, scored and refined without going back to
    pixels. ``design`` holds the rows of ``x2^T F x1 = 0`` for row-major F; ``joint`` the
    homogeneous points of both images side by side.
    """

    def __init__(self, p1: np.ndarray, p2: np.ndarray) -> None:
        self.p1, self.p2 = p1, p2
        n = len(p1)
        c1, c2 = p1.sum(axis=0) / max(n, 1), p2.sum(axis=0) / max(n, 1)
        d1, d2 = p1 - c1, p2 - c2
        spread = (np.abs(d1).sum() + np.abs(d2).sum()) / max(4 * n, 1)
        self.scale = 1.0 / max(float(spread), 1e-12)
        joint = np.ones((n, 6))
        joint[:, :2] = d1 * self.scale
        joint[:, 3:5] = d2 * self.scale
        self.joint = joint
        (x1, y1), (x2, y2) = joint[:, :2].T, joint[:, 3:5].T
        a = np.empty((n, 9))
        a[:, 0], a[:, 1], a[:, 2] = x2 * x1, x2 * y1, x2
        a[:, 3], a[:, 4], a[:, 5] = y2 * x1, y2 * y1, y2
        a[:, 6], a[:, 7], a[:, 8] = x1, y1, 1.0
        self.design = a
        s = self.scale
        self._t1 = np.array([[s, 0.0, -s * c1[0]], [0.0, s, -s * c1[1]], [0.0, 0.0, 1.0]])
        self._t2 = np.array([[s, 0.0, -s * c2[0]], [0.0, s, -s * c2[1]], [0.0, 0.0, 1.0]])

    def __len__(self) -> int:
        return len(self.design)

    def to_pixels(self, f: np.ndarray) -> np.ndarray:
        """The pixel model (unit Frobenius norm) of a normalised one."""
        g = self._t2.T @ f @ self._t1
        return g / float(np.sqrt((g * g).sum()))

    def from_pixels(self, f: np.ndarray) -> np.ndarray:
        """The normalised model of a pixel one."""
        return np.linalg.inv(self._t2).T @ f @ np.linalg.inv(self._t1)

    def sampson_sq(self, f: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """(N,) squared normalised Sampson distances to the normalised model ``f``."""
        return self.batched_sampson_sq(f[None], rows)[0]

    def batched_sampson_sq(self, models: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """(K, R) squared normalised Sampson distances of ``rows`` (all when None) to K models
        (K, 3, 3)."""
        joint = self.joint if rows is None else self.joint[rows]
        q1, q2 = joint[:, :3].T, joint[:, 3:].T
        fx1 = models @ q1  # (K, 3, R)
        ftx2 = models.transpose(0, 2, 1) @ q2
        r = (fx1 * q2).sum(axis=1)
        den = fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2
        return r * r / np.maximum(den, 1e-300)

    def least_squares(self, mask: np.ndarray) -> np.ndarray | None:
        """The rank-2 normalised model minimising the algebraic error of the masked rows."""
        a = self.design[mask]
        if len(a) < 8:
            return None
        _, _, vt = cv2.SVDecomp(a.T @ a)
        w, u, vt3 = cv2.SVDecomp(vt[8].reshape(3, 3))
        f = (u * np.array([w[0, 0], w[1, 0], 0.0])) @ vt3
        return f if np.isfinite(f).all() else None

    def minimal(self, samples: np.ndarray) -> np.ndarray:
        """(K, 3, 3) normalised models of (K, 8) row samples (8-point, gauge-fixed, no rank-2
        step: they are only scored); singular samples dropped."""
        k = len(samples)
        a = np.empty((k, 9, 9))
        a[:, :8] = self.design[samples]
        a[:, 8] = _GAUGE
        rhs = np.zeros((k, 9, 1))
        rhs[:, 8] = 1.0
        with np.errstate(all="ignore"):
            try:
                f = np.linalg.solve(a, rhs)[:, :, 0]
            except np.linalg.LinAlgError:  # one singular sample sinks the batch: one by one
                f = np.array([_solve_or_nan(m) for m in a])
        f = f[np.isfinite(f).all(axis=1)]
        return f.reshape(-1, 3, 3)


def _solve_or_nan(a: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.solve(a, np.eye(9)[8])
    except np.linalg.LinAlgError:
        return np.full(9, np.nan)


def _samples(
    rng: np.random.Generator, strong: np.ndarray, count: int, per_sample: int
) -> np.ndarray:
    """(count, 8) indices into ``strong``'s candidates: ``per_sample`` of them from those with
    strong parallax and the rest from the others (each group drawn from a repeated
    permutation, so the members of a sample are distinct), or 8 from all when a group is too
    small."""
    picked, others = np.flatnonzero(strong), np.flatnonzero(~strong)
    if per_sample == 0 or len(picked) < per_sample or len(others) < 8 - per_sample:
        picked, others, per_sample = picked[:0], np.arange(len(strong)), 0
    parts = []
    for group, k in ((picked, per_sample), (others, 8 - per_sample)):
        if k:
            parts.append(np.resize(group[rng.permutation(len(group))], count * k).reshape(count, k))
    return np.concatenate(parts, axis=1)


def fit_candidates(
    corr: Correspondences,
    candidates: np.ndarray,
    strong: np.ndarray,
    options: PlusOptions,
    seed: int,
) -> tuple[np.ndarray | None, dict[str, Any]]:
    """A normalised F from the candidate rows of ``corr``, and statistics.

    Candidates are mostly true but dominated by one height, so a uniform 8-point sample rarely
    holds enough parallax and its model is plane-degenerate. Each of ``hypotheses`` samples
    therefore takes ``parallax_points`` of its 8 points from the candidates with strong parallax
    (``strong``, off the seeds' affine field along the epipolar line). The ``polish`` best by
    truncated (MSAC) score at 2 x threshold are refitted by least squares on their candidate
    inliers within 2 x threshold; the one with the most candidate inliers is kept. If fewer
    than ``min_candidate_share`` of the candidates fit it, OpenCV's USAC (MAGSAC score,
    sigma-consensus) runs on the candidates instead (``usac``)."""
    stats: dict[str, Any] = {"usac": False, "hypotheses": 0, "candidate_share": 0.0}
    if len(candidates) < 8:
        return None, stats
    t2 = (options.threshold_px * corr.scale) ** 2
    rng = np.random.default_rng(seed)
    samples = _samples(rng, strong, options.hypotheses, options.parallax_points)
    models = corr.minimal(candidates[samples])
    stats["hypotheses"] = len(models)
    best_f, best_in = None, -1
    if len(models):
        d2 = corr.batched_sampson_sq(models, candidates)
        score = np.minimum(d2, 4.0 * t2).sum(axis=1)
        within = np.zeros(len(corr), dtype=bool)
        for k in np.argsort(score, kind="stable")[: options.polish]:
            within[candidates] = d2[k] < 4.0 * t2
            f = corr.least_squares(within)
            if f is None:
                continue
            inliers = int(np.count_nonzero(corr.sampson_sq(f, candidates) < t2))
            if inliers > best_in:
                best_f, best_in = f, inliers
    if best_f is not None:
        stats["candidate_share"] = best_in / len(candidates)
        if stats["candidate_share"] >= options.min_candidate_share:
            return best_f, stats
    stats["usac"] = True
    f = _usac(corr.p1[candidates], corr.p2[candidates], options, seed)
    return (None if f is None else corr.from_pixels(f)), stats


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
    best_f, best_d2 = f, corr.sampson_sq(f)
    best_count = first = int(np.count_nonzero(best_d2 < t2))
    steps = 0
    for m in options.lo_schedule:
        refit = corr.least_squares(best_d2 < m * m * t2)
        steps += 1
        if refit is None:
            break
        d2 = corr.sampson_sq(refit)
        count = int(np.count_nonzero(d2 < t2))
        if count >= best_count:
            best_f, best_d2, best_count = refit, d2, count
    stats = {"inliers_before": first, "inliers_after": best_count, "refits": steps}
    return corr.to_pixels(best_f), best_d2 < t2, stats
