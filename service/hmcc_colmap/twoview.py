"""A verified pair's relative pose (``R``, ``t``) from its fundamental matrix, computed where
the pair is verified: on the compute pool, in the child, beside the verification
(:func:`verify_and_pose`), so the run's process only writes it; here otherwise.

Light on purpose (no pycolmap): the pool's children import this module with their first task.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from hmcc import Camera, Verification
from hmcc.flight import Flight
from hmcc_worker.outcomes import PairOutcome, finished, verify_flight

__all__ = [
    "POSE_POINTS",
    "PosedOutcome",
    "pair_pose",
    "pose_sample",
    "relative_pose",
    "result_model",
    "verify_and_pose",
]

#: Inliers the relative pose's cheirality vote uses (all: 2 ms a pair in recoverPose).
POSE_POINTS = 100

#: ``(R, t)`` of a pair, both None when E gives none.
Pose = tuple[np.ndarray | None, np.ndarray | None]


@dataclass(frozen=True)
class PosedOutcome(PairOutcome):
    """A finished pair's outcome with the relative pose of its result (:func:`pair_pose`)."""

    pose: Pose = (None, None)


def verify_and_pose(flight: Flight, min_inliers: int) -> list[PairOutcome]:
    """:func:`verify_flight`, with the relative pose of each pair whose result is a
    fundamental matrix with at least ``min_inliers`` inliers (what is written), from the
    verification itself (not its JSON); run in a pool's child (``functools.partial`` of it
    pickles)."""

    def finish(index: int, verification: Verification) -> PairOutcome:
        outcome = finished(verification)
        F, inliers = verification.model_matrix, verification.inliers
        if verification.model_type != "fundamental" or F is None or len(inliers) < min_inliers:
            return outcome
        pair = flight.pairs[index]
        image1, image2 = flight.images[pair.image1], flight.images[pair.image2]
        kp1 = pair.keypoints1 if pair.keypoints1 is not None else image1.keypoints
        kp2 = pair.keypoints2 if pair.keypoints2 is not None else image2.keypoints
        assert kp1 is not None and kp2 is not None
        pose = pair_pose(F, pair.matches[inliers], image1.camera, image2.camera, kp1, kp2)
        return PosedOutcome(outcome.status, outcome.body, outcome.timings_ms, pose)

    return verify_flight(flight, finish)


def result_model(result: dict[str, Any]) -> tuple[np.ndarray | None, np.ndarray]:
    """A result's fundamental matrix (None for another model or none) and its inliers."""
    inliers = np.asarray(result.get("inliers") or [], dtype=np.int64)
    model = result.get("model") or {}
    if model.get("matrix") is None or model.get("type") != "fundamental":
        return None, inliers
    return np.asarray(model["matrix"], dtype=np.float64), inliers


def pair_pose(
    F: np.ndarray,
    kept: np.ndarray,
    camera1: Camera,
    camera2: Camera,
    keypoints1: np.ndarray,
    keypoints2: np.ndarray,
) -> Pose:
    """The relative pose of F (our pixels) and the pair's inlier matches ``kept``."""
    sample = kept[pose_sample(len(kept))]  # only these are read: normalise only these
    n1 = camera1.normalize(keypoints1[sample[:, 0], :2])
    n2 = camera2.normalize(keypoints2[sample[:, 1], :2])
    E = camera2.K.T @ F @ camera1.K
    return relative_pose(E, n1, n2)


def relative_pose(E: np.ndarray, n1: np.ndarray, n2: np.ndarray) -> Pose:
    """``(R, t)`` with ``x2 = R x1 + t`` (|t| = 1) from E and the inliers' normalised points:
    of E's four decompositions, the one that puts most of the points (at most
    :data:`POSE_POINTS`, spread over the list) in front of both cameras (OpenCV's recoverPose
    does the same with a full triangulation, 1 ms a pair), or (None, None)."""
    if len(n1) < 5 or not np.isfinite(E).all():
        return None, None
    if len(n1) > POSE_POINTS:
        pick = pose_sample(len(n1))
        n1, n2 = n1[pick], n2[pick]
    try:
        R1, R2, t = cv2.decomposeEssentialMat(E)
    except cv2.error:
        return None, None
    t = t.ravel()
    x1 = np.column_stack((n1, np.ones(len(n1))))
    x2 = np.column_stack((n2, np.ones(len(n2))))
    bb = np.sum(x2 * x2, 1)
    bt = x2 @ t
    best: tuple[int, np.ndarray | None, np.ndarray | None] = (-1, None, None)
    for R in (R1, R2):
        a = x1 @ R.T  # R x1: ray 1 in camera 2's frame
        # depths d1, d2 with d1 (R x1) - d2 x2 = -t, least squares per point; with -t they
        # are exactly -d1, -d2 (every term changes sign), so one solve serves both
        aa, ab = np.sum(a * a, 1), np.sum(a * x2, 1)
        at = a @ t
        det = aa * bb - ab * ab
        ok = np.abs(det) > 1e-12
        d1 = np.where(ok, (-at * bb + ab * bt) / np.where(ok, det, 1.0), 0.0)
        d2 = np.where(ok, (ab * -at + aa * bt) / np.where(ok, det, 1.0), 0.0)
        for front, tt in (
            (np.count_nonzero((d1 > 0) & (d2 > 0)), t),
            (np.count_nonzero((d1 < 0) & (d2 < 0)), -t),
        ):
            if front > best[0]:
                best = (int(front), R, tt)
    if best[0] <= 0:
        return None, None
    return best[1], best[2]


def pose_sample(n: int) -> np.ndarray:
    """Indices of at most :data:`POSE_POINTS` of ``n`` points, spread over the list."""
    if n <= POSE_POINTS:
        return np.arange(n)
    return np.linspace(0, n - 1, POSE_POINTS).astype(np.int64)
