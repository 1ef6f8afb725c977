"""The relative pose of a verified pair from its essential matrix: of the four decompositions
of E, the one that puts the most matches in front of both cameras (what OpenCV's recoverPose
does with a full triangulation, about 1 ms a pair). Pure, no I/O; the vote runs compiled (with
it in numpy, ``hmcc colmap``'s children spent about 200 us a pair on the pose, now about 105,
most of it normalising the points and decomposing E)."""

from __future__ import annotations

import cv2
import numpy as np

from .jit import compiled

__all__ = ["POSE_POINTS", "Pose", "pose_sample", "relative_pose"]

#: Matches the cheirality vote uses, spread over the list (all: 2 ms a pair in recoverPose).
POSE_POINTS = 100

#: ``(R, t)``, both None when E gives none.
Pose = tuple[np.ndarray | None, np.ndarray | None]


def pose_sample(n: int) -> np.ndarray:
    """Indices of at most :data:`POSE_POINTS` of ``n`` points, spread over the list."""
    if n <= POSE_POINTS:
        return np.arange(n)
    return np.arange(POSE_POINTS) * (n - 1) // (POSE_POINTS - 1)  # floor(linspace), exactly


def relative_pose(E: np.ndarray, n1: np.ndarray, n2: np.ndarray) -> Pose:
    """``(R, t)`` with ``x2 = R x1 + t`` (|t| = 1) from E and the inliers' (N, 2) normalised
    points: of E's four decompositions, the one that puts most of the points (at most
    :data:`POSE_POINTS`, spread over the list) in front of both cameras, or (None, None)."""
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
    which, sign = _cheirality(
        np.ascontiguousarray(R1, dtype=np.float64),
        np.ascontiguousarray(R2, dtype=np.float64),
        np.ascontiguousarray(t, dtype=np.float64),
        np.ascontiguousarray(n1, dtype=np.float64),
        np.ascontiguousarray(n2, dtype=np.float64),
    )
    if which < 0:
        return None, None
    return (R1 if which == 0 else R2), sign * t


@compiled
def _cheirality(
    R1: np.ndarray, R2: np.ndarray, t: np.ndarray, n1: np.ndarray, n2: np.ndarray
) -> tuple[int, float]:
    """(rotation 0 or 1, sign of t) of the decomposition that puts the most points in front of
    both cameras; (-1, 0) when none does. The depths d1, d2 with ``d1 (R x1) - d2 x2 = -t``,
    least squares per point; with -t they are exactly -d1, -d2, so one solve serves both signs.
    Ties go to the first of R1 +t, R1 -t, R2 +t, R2 -t."""
    best, which, sign = 0, -1, 0.0
    for k in range(2):
        R = R1 if k == 0 else R2
        front = 0
        behind = 0
        for i in range(len(n1)):
            x1, y1 = n1[i, 0], n1[i, 1]
            x2, y2 = n2[i, 0], n2[i, 1]
            a0 = R[0, 0] * x1 + R[0, 1] * y1 + R[0, 2]  # R x1: ray 1 in camera 2's frame
            a1 = R[1, 0] * x1 + R[1, 1] * y1 + R[1, 2]
            a2 = R[2, 0] * x1 + R[2, 1] * y1 + R[2, 2]
            aa = a0 * a0 + a1 * a1 + a2 * a2
            ab = a0 * x2 + a1 * y2 + a2
            bb = x2 * x2 + y2 * y2 + 1.0
            at = a0 * t[0] + a1 * t[1] + a2 * t[2]
            bt = x2 * t[0] + y2 * t[1] + t[2]
            det = aa * bb - ab * ab
            if abs(det) <= 1e-12:
                continue
            d1 = (-at * bb + ab * bt) / det
            d2 = (ab * -at + aa * bt) / det
            if d1 > 0.0 and d2 > 0.0:
                front += 1
            elif d1 < 0.0 and d2 < 0.0:
                behind += 1
        if front > best:
            best, which, sign = front, k, 1.0
        if behind > best:
            best, which, sign = behind, k, -1.0
    return which, sign
