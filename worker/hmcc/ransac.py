"""Robust two-view model estimation with OpenCV: the final stage and the plain baselines.

Models: ``fundamental`` (pixels, x2^T F x1 = 0), ``essential`` (fitted on normalised
coordinates, x2n^T E x1n = 0, threshold converted with the mean focal length) and
``homography`` (x2 ~ H x1). Estimators:

* ``ransac``: classic RANSAC, as in the paper. For F it is our own seven-point RANSAC
  (:mod:`hmcc.seven_point`: inliers by the larger of the two point-to-epipolar-line
  distances, the adaptive iteration rule, seeded, for every n >= 7), because OpenCV's
  FM_RANSAC silently runs LMedS, which ignores the threshold, on 14 matches or fewer. For E
  and H it is OpenCV's RANSAC (5-point, 4-point), which has no such switch;
* ``lo-ransac``: USAC with uniform sampling, inlier-count score and inner local optimisation
  (Chum et al. 2003);
* ``lmeds``; ``magsac++`` (USAC_MAGSAC); ``usac-default``, ``usac-accurate``, ``usac-fast``,
  ``usac-prosac`` (OpenCV's presets).

**Bounded inputs** (measured on OpenCV 5.0 in isolated processes over 5 000 runs, every data
kind: random, true geometry with outliers, identical, collinear, duplicated, 1e-9 to 1e300
coordinates): OpenCV's ``USAC_ACCURATE`` sizes a buffer with ``n * n`` in 32-bit integers in its
graph-cut local optimisation, so above 46 340 matches it raises ``std::bad_alloc`` and from
65 536 it **segfaults**, whatever the data; with E it also takes 96 s at 40 000 matches. Plain
RANSAC costs ``n x max_iters`` on outliers (about 20 minutes at 100 000 matches and 10^6
iterations). Every other estimator ran in at most a few seconds at 100 000 matches. So
:func:`estimate_model` gives an estimator at most :data:`MAX_ESTIMATOR_MATCHES` matches (and
RANSAC at most ``MAX_RANSAC_WORK / max_iters``): above that it runs on a seeded random subset of
that size, and every match is then decided by its distance to the subset's model (Sampson
distance for F and E, reprojection distance for H, at the threshold); ``stats["subsample"]``
says so. Non-finite coordinates never reach OpenCV (the caller checks undistortion).

Every result is reproducible. ``lo-ransac`` takes the seed as USAC's ``randomGeneratorState``
and the seven-point RANSAC (``ransac`` on F) as the seed of its own generator (xorshift64*,
``seven_point.py``). OpenCV's other classic methods (``ransac`` on E and H, ``lmeds``) and its
USAC presets (``magsac++``, ``usac-*``) draw from a fixed internal seed that its Python API does
not expose (``cv2.setRNGSeed`` does not reach them): they give the same answer for every
``seed``.
OpenCV does not report how many iterations it ran; ``iterations_estimated`` is the adaptive
stopping bound ``log(1 - confidence) / log(1 - w^s)`` for the final inlier ratio w and sample
size s (capped at ``max_iters``), the number a standard RANSAC would run. The seven-point
RANSAC also reports ``iterations``, the samples it drew.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, get_args

import cv2
import numpy as np

from .pair import PairData, require_matches
from .seven_point import ransac_fundamental
from .stage_options import EstimatorName, RansacOptions
from .stages import Method, MethodResult, Stages

if TYPE_CHECKING:
    from .options import VerifyOptions

__all__ = [
    "ESTIMATORS",
    "ESTIMATOR_METHODS",
    "MIN_MATCHES",
    "EstimatorName",
    "MAX_ESTIMATOR_MATCHES",
    "MAX_RANSAC_WORK",
    "ModelFit",
    "RansacOptions",
    "estimate_model",
    "fit_final",
    "iterations_bound",
    "min_matches",
    "sample_draws",
    "sampson_distance",
]


#: Most matches an estimator is given at once (see the module docstring): USAC_ACCURATE's
#: graph-cut buffer overflows above 46 340 (F, H), and on E it is slow well before.
MAX_ESTIMATOR_MATCHES: dict[tuple[str, str], int] = {
    ("usac-accurate", "fundamental"): 40_000,
    ("usac-accurate", "homography"): 40_000,
    ("usac-accurate", "essential"): 10_000,
}
#: Plain RANSAC: most matches x iterations at once (about 12 s for F, 10 s for E).
MAX_RANSAC_WORK: dict[str, float] = {"fundamental": 1e9, "homography": 1e9, "essential": 2e8}

#: Matches an estimator needs per model (OpenCV's F estimators refuse fewer than 8); the
#: seven-point RANSAC (``ransac`` on F) needs 7, see :func:`min_matches`.
MIN_MATCHES: dict[str, int] = {"fundamental": 8, "essential": 5, "homography": 4}
_SAMPLE_SIZE = {"fundamental": 7, "essential": 5, "homography": 4}


def min_matches(model: str, estimator: str) -> int:
    """Fewest matches ``estimator`` can fit ``model`` to: 7 for the seven-point RANSAC on F,
    else :data:`MIN_MATCHES`."""
    if model == "fundamental" and estimator == "ransac":
        return _SAMPLE_SIZE["fundamental"]
    return MIN_MATCHES[model]


_USAC_FLAGS = {
    "magsac++": cv2.USAC_MAGSAC,
    "usac-default": cv2.USAC_DEFAULT,
    "usac-accurate": cv2.USAC_ACCURATE,
    "usac-fast": cv2.USAC_FAST,
    "usac-prosac": cv2.USAC_PROSAC,
}
ESTIMATORS: tuple[str, ...] = get_args(EstimatorName)


@dataclass(frozen=True)
class ModelFit:
    """``matrix``: (3, 3) float64 or None when no model was found; ``inliers``: (N,) bool."""

    model: str
    matrix: np.ndarray | None
    inliers: np.ndarray
    stats: dict[str, object]


def _lo_ransac_params(options: RansacOptions, threshold: float, seed: int) -> cv2.UsacParams:
    params = cv2.UsacParams()
    params.sampler = cv2.SAMPLING_UNIFORM
    params.score = cv2.SCORE_METHOD_RANSAC
    params.loMethod = cv2.LOCAL_OPTIM_INNER_LO
    params.final_polisher = cv2.NONE_POLISHER
    params.threshold = threshold
    params.confidence = options.confidence
    params.maxIterations = options.max_iters
    params.randomGeneratorState = seed
    return params


def iterations_bound(inlier_ratio: float, options: RansacOptions) -> int:
    """The iterations a standard RANSAC needs to draw, at ``options.confidence``, one sample of
    only inliers when ``inlier_ratio`` of the matches are (capped at ``options.max_iters``)."""
    return _estimated_iterations(inlier_ratio, _SAMPLE_SIZE[options.model], options)


def _estimated_iterations(inlier_ratio: float, sample: int, options: RansacOptions) -> int:
    return sample_draws(inlier_ratio, sample, options.confidence, options.max_iters)


def sample_draws(inlier_ratio: float, sample: int, confidence: float, most: int) -> int:
    """Draws of ``sample`` matches that find, at ``confidence``, one of only inliers when
    ``inlier_ratio`` of the matches are; at least 1, at most ``most``."""
    w = inlier_ratio**sample
    if w >= 1.0:
        return 1
    if w <= 0.0:
        return most
    # log1p: for a tiny w, log(1 - w) rounds to 0.0 and the bound divides by zero.
    bound = math.log1p(-confidence) / math.log1p(-w)
    return int(min(most, max(1, math.ceil(bound))))


def estimate_model(
    points1: np.ndarray,
    points2: np.ndarray,
    options: RansacOptions = RansacOptions(),
    seed: int = 0,
    normalized1: np.ndarray | None = None,
    normalized2: np.ndarray | None = None,
    focal_px: float = 1.0,
) -> ModelFit:
    """Fit ``options.model`` robustly to (N, 2) pixel correspondences.

    For the essential matrix pass ``normalized1``/``normalized2`` (N, 2) undistorted normalised
    coordinates and the mean ``focal_px`` that converts the pixel threshold. Fewer matches than
    the model needs give no model and no inliers (``stats["degenerate"]`` says why).
    """
    n = len(points1)
    need = min_matches(options.model, options.estimator)
    if n < need:
        degenerate: dict[str, object] = {
            "estimator": options.estimator,
            "inlier_ratio": 0.0,
            "iterations_estimated": 0,
            "degenerate": f"{n} matches, the model needs {need}",
        }
        return ModelFit(options.model, None, np.zeros(n, dtype=bool), degenerate)
    p1 = np.ascontiguousarray(points1, dtype=np.float64)
    p2 = np.ascontiguousarray(points2, dtype=np.float64)
    threshold = options.threshold_px
    if options.model == "essential":
        if normalized1 is None or normalized2 is None:
            raise ValueError("normalized1/normalized2: the essential model needs them")
        p1 = np.ascontiguousarray(normalized1, dtype=np.float64)
        p2 = np.ascontiguousarray(normalized2, dtype=np.float64)
        threshold = options.threshold_px / focal_px

    cap = _bound(options, n)
    subset = None
    if cap < n:
        subset = np.sort(np.random.default_rng(seed).choice(n, size=cap, replace=False))
    failure = None
    iterations: int | None = None
    matrix: np.ndarray | None
    mask: np.ndarray | None
    try:
        s1, s2 = (p1, p2) if subset is None else (p1[subset], p2[subset])
        if options.model == "fundamental" and options.estimator == "ransac":
            seven = ransac_fundamental(
                s1, s2, threshold, options.confidence, options.max_iters, seed
            )
            matrix, mask, iterations = seven.matrix, seven.inliers, seven.iterations
        else:
            matrix, mask = _call_opencv(options, s1, s2, threshold, seed)
    except cv2.error as e:  # USAC asserts on some degenerate samples (OpenCV 5.0): no model
        matrix, mask, failure = None, None, f"OpenCV: {e.err or e}".strip()
    if matrix is None or mask is None or matrix.shape[0] < 3 or not mask.any():
        inliers = np.zeros(n, dtype=bool)
        matrix = None
    else:
        matrix = np.asarray(matrix[:3], dtype=np.float64)
        if subset is None:
            inliers = mask.reshape(-1).astype(bool)
        else:  # every match decided by its distance to the subset's model
            inliers = _distance(options.model, matrix, p1, p2) <= threshold
    ratio = float(inliers.mean())
    stats: dict[str, object] = {
        "estimator": options.estimator,
        "inlier_ratio": ratio,
        "iterations_estimated": _estimated_iterations(ratio, _SAMPLE_SIZE[options.model], options),
    }
    if iterations is not None:
        stats["iterations"] = iterations
    if subset is not None:
        stats["subsample"] = {"matches": n, "used": cap}
    if matrix is None:
        stats["degenerate"] = failure or "no model found"
    return ModelFit(options.model, matrix, inliers, stats)


def _bound(options: RansacOptions, n: int) -> int:
    """How many of ``n`` matches the estimator may be given at once."""
    cap = MAX_ESTIMATOR_MATCHES.get((options.estimator, options.model), n)
    if options.estimator == "ransac":
        cap = min(cap, int(MAX_RANSAC_WORK[options.model] // options.max_iters))
    return max(min(cap, n), min_matches(options.model, options.estimator))


def sampson_distance(f: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(N,) Sampson distance of (N, 2) correspondences to ``x2^T F x1 = 0`` (in the points'
    units)."""
    fx1 = p1 @ f[:, :2].T + f[:, 2]  # rows: F x1
    ftx2 = p2 @ f[:2, :] + f[2, :]  # rows: F^T x2
    r = (p2 * fx1[:, :2]).sum(axis=1) + fx1[:, 2]
    den = fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2
    return np.abs(r) / np.sqrt(np.maximum(den, 1e-300))


def _distance(model: str, matrix: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(N,) distance of each correspondence to the model: Sampson for F and E, the
    reprojection distance in image 2 for H (infinite behind the camera)."""
    if model != "homography":
        return sampson_distance(matrix, p1, p2)
    h = np.column_stack((p1, np.ones(len(p1)))) @ matrix.T
    w = h[:, 2]
    safe = np.where(np.abs(w) > 1e-12, w, np.nan)
    projected = h[:, :2] / safe[:, None]
    d = np.hypot(*(projected - p2).T)
    return np.where(np.isfinite(d), d, np.inf)


def _call_opencv(
    options: RansacOptions, p1: np.ndarray, p2: np.ndarray, threshold: float, seed: int
) -> tuple[np.ndarray | None, np.ndarray | None]:
    est = options.estimator
    conf, iters = options.confidence, options.max_iters
    eye = np.eye(3)
    if est == "lo-ransac":
        params = _lo_ransac_params(options, threshold, seed)
        if options.model == "fundamental":
            return cv2.findFundamentalMat(p1, p2, params)
        if options.model == "homography":
            return cv2.findHomography(p1, p2, params)
        no_distortion = np.zeros(5)
        return cv2.findEssentialMat(p1, p2, eye, eye, no_distortion, no_distortion, params)
    flag = {"ransac": None, "lmeds": cv2.LMEDS}.get(est, _USAC_FLAGS.get(est))
    if options.model == "fundamental":
        return cv2.findFundamentalMat(
            p1, p2, cv2.FM_RANSAC if flag is None else flag, threshold, conf, iters
        )
    if options.model == "homography":
        return cv2.findHomography(
            p1, p2, cv2.RANSAC if flag is None else flag, threshold, maxIters=iters, confidence=conf
        )
    return cv2.findEssentialMat(
        p1, p2, eye, cv2.RANSAC if flag is None else flag, conf, threshold, iters
    )


def fit_final(
    pair: PairData, px1: np.ndarray, px2: np.ndarray, options: RansacOptions, seed: int
) -> ModelFit:
    """The final estimator on (K, 2) candidate pixels of both images: undistorted pixels for F
    and H, normalised coordinates (and the mean focal length) for E."""
    if options.model == "essential":
        focal = (pair.camera1.fx + pair.camera1.fy + pair.camera2.fx + pair.camera2.fy) / 4.0
        return estimate_model(
            px1,
            px2,
            options,
            seed,
            normalized1=pair.camera1.normalize(px1),
            normalized2=pair.camera2.normalize(px2),
            focal_px=focal,
        )
    return estimate_model(
        pair.camera1.undistort_pixels(px1), pair.camera2.undistort_pixels(px2), options, seed
    )


def _verify_estimator(
    estimator: EstimatorName, pair: PairData, options: VerifyOptions, stages: Stages
) -> MethodResult:
    """An estimator on all matches, no pre-filter; the method name sets ``ransac.estimator``."""
    options = dataclasses.replace(
        options, ransac=dataclasses.replace(options.ransac, estimator=estimator)
    )
    require_matches(pair, min_matches(options.ransac.model, estimator), options.ransac.model)
    px1, px2 = pair.matched_pixels()
    with stages.stage("ransac", len(px1)) as st:
        fit = fit_final(pair, px1, px2, options.ransac, options.seed)
        inliers = np.flatnonzero(st.done(fit.inliers, fit.stats))
    stages.survivors["ransac"] = inliers
    statistics = {"degenerate": fit.stats["degenerate"]} if "degenerate" in fit.stats else {}
    return MethodResult(inliers, fit.model, fit.matrix, statistics, options)


#: One method per estimator name (``ransac``, ``magsac++``, ...).
ESTIMATOR_METHODS: dict[str, Method] = {
    name: functools.partial(_verify_estimator, name) for name in get_args(EstimatorName)
}
