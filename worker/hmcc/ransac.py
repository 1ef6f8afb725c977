"""Robust two-view model estimation with OpenCV: the final stage and the plain baselines.

Models: ``fundamental`` (pixels, x2^T F x1 = 0), ``essential`` (fitted on normalised
coordinates, x2n^T E x1n = 0, threshold converted with the mean focal length) and
``homography`` (x2 ~ H x1). Estimators:

* ``ransac``: OpenCV's classic RANSAC (FM_RANSAC: 7-point minimal solver for F, inliers by
  the larger of the two point-to-epipolar-line distances), as in the paper;
* ``lo-ransac``: USAC with uniform sampling, inlier-count score and inner local optimisation
  (Chum et al. 2003);
* ``lmeds``; ``magsac++`` (USAC_MAGSAC); ``usac-default``, ``usac-accurate``, ``usac-fast``,
  ``usac-prosac`` (OpenCV's presets).

Every result is reproducible. ``lo-ransac`` takes the seed as USAC's ``randomGeneratorState``.
OpenCV's classic methods (``ransac``, ``lmeds``) and its USAC presets (``magsac++``,
``usac-*``) draw from a fixed internal seed that its Python API does not expose
(``cv2.setRNGSeed`` does not reach them): they give the same answer for every ``seed``.
OpenCV does not report how many iterations it ran; ``iterations_estimated`` is the adaptive
stopping bound ``log(1 - confidence) / log(1 - w^s)`` for the final inlier ratio w and sample
size s (capped at ``max_iters``), the number a standard RANSAC would run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

__all__ = [
    "ESTIMATORS",
    "MIN_MATCHES",
    "ModelFit",
    "RansacOptions",
    "estimate_model",
]

ModelType = Literal["fundamental", "essential", "homography"]
EstimatorName = Literal[
    "ransac",
    "lo-ransac",
    "lmeds",
    "magsac++",
    "usac-default",
    "usac-accurate",
    "usac-fast",
    "usac-prosac",
]

#: Matches an estimator needs per model (OpenCV's FM_RANSAC refuses fewer than 8 for F).
MIN_MATCHES: dict[str, int] = {"fundamental": 8, "essential": 5, "homography": 4}
_SAMPLE_SIZE = {"fundamental": 7, "essential": 5, "homography": 4}

_USAC_FLAGS = {
    "magsac++": cv2.USAC_MAGSAC,
    "usac-default": cv2.USAC_DEFAULT,
    "usac-accurate": cv2.USAC_ACCURATE,
    "usac-fast": cv2.USAC_FAST,
    "usac-prosac": cv2.USAC_PROSAC,
}
ESTIMATORS: tuple[str, ...] = ("ransac", "lo-ransac", "lmeds", *_USAC_FLAGS)


@dataclass(frozen=True)
class RansacOptions:
    """Final-stage estimator. Defaults are the paper's: F, classic RANSAC, 1.0 px."""

    model: ModelType = "fundamental"
    estimator: EstimatorName = "ransac"
    threshold_px: float = 1.0
    confidence: float = 0.999
    max_iters: int = 10_000

    def __post_init__(self) -> None:
        if self.model not in MIN_MATCHES:
            raise ValueError(f"model: must be one of {sorted(MIN_MATCHES)}")
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator: must be one of {list(ESTIMATORS)}")
        if not 0.0 < self.threshold_px <= 100.0:
            raise ValueError("threshold_px: must be in (0, 100]")
        if not 0.0 < self.confidence < 1.0:
            raise ValueError("confidence: must be in (0, 1)")
        if not 1 <= self.max_iters <= 1_000_000:
            raise ValueError("max_iters: must be in [1, 1000000]")


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


def _estimated_iterations(inlier_ratio: float, sample: int, options: RansacOptions) -> int:
    w = inlier_ratio**sample
    if w >= 1.0:
        return 1
    if w <= 0.0:
        return options.max_iters
    # log1p: for a tiny w, log(1 - w) rounds to 0.0 and the bound divides by zero.
    bound = math.log1p(-options.confidence) / math.log1p(-w)
    return int(min(options.max_iters, max(1, math.ceil(bound))))


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
    need = MIN_MATCHES[options.model]
    if n < need:
        stats: dict[str, object] = {
            "estimator": options.estimator,
            "inlier_ratio": 0.0,
            "iterations_estimated": 0,
            "degenerate": f"{n} matches, the model needs {need}",
        }
        return ModelFit(options.model, None, np.zeros(n, dtype=bool), stats)
    p1 = np.ascontiguousarray(points1, dtype=np.float64)
    p2 = np.ascontiguousarray(points2, dtype=np.float64)
    threshold = options.threshold_px
    if options.model == "essential":
        if normalized1 is None or normalized2 is None:
            raise ValueError("normalized1/normalized2: the essential model needs them")
        p1 = np.ascontiguousarray(normalized1, dtype=np.float64)
        p2 = np.ascontiguousarray(normalized2, dtype=np.float64)
        threshold = options.threshold_px / focal_px

    failure = None
    try:
        matrix, mask = _call_opencv(options, p1, p2, threshold, seed)
    except cv2.error as e:  # USAC asserts on some degenerate samples (OpenCV 5.0): no model
        matrix, mask, failure = None, None, f"OpenCV: {e.err or e}".strip()
    if matrix is None or mask is None or matrix.shape[0] < 3 or not mask.any():
        inliers = np.zeros(n, dtype=bool)
        matrix = None
    else:
        inliers = mask.reshape(-1).astype(bool)
        matrix = np.asarray(matrix[:3], dtype=np.float64)
    ratio = float(inliers.mean())
    stats = {
        "estimator": options.estimator,
        "inlier_ratio": ratio,
        "iterations_estimated": _estimated_iterations(ratio, _SAMPLE_SIZE[options.model], options),
    }
    if matrix is None:
        stats["degenerate"] = failure or "no model found"
    return ModelFit(options.model, matrix, inliers, stats)


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
