"""A verified pair's relative pose (``R``, ``t``) from its fundamental matrix, computed where
the pair is verified: on the compute pool, in the child, beside the verification
(:func:`verify_and_pose`), so the run's process only writes it; here otherwise.

Light on purpose (no pycolmap): the pool's children import this module with their first task.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hmcc import Camera, Verification
from hmcc.flight import Flight
from hmcc.relative_pose import POSE_POINTS, Pose, pose_sample, relative_pose
from hmcc_worker.outcomes import PairOutcome, finished, verify_flight

__all__ = [
    "POSE_POINTS",
    "Pose",
    "PosedOutcome",
    "pair_pose",
    "pose_sample",
    "relative_pose",
    "result_model",
    "run_result",
    "verify_and_pose",
]


@dataclass(frozen=True)
class PosedOutcome(PairOutcome):
    """A finished pair's outcome as the run reads it: ``body`` the JSON of
    :func:`run_result` (no inliers), the ``inliers`` as an array beside it (no list of numbers
    to encode and decode: 48 000 of them on the Brighton flight), and the relative pose of its
    result (:func:`pair_pose`)."""

    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    pose: Pose = (None, None)


def verify_and_pose(flight: Flight, min_inliers: int) -> list[PairOutcome]:
    """:func:`verify_flight`, with the relative pose of each pair whose result is a
    fundamental matrix with at least ``min_inliers`` inliers (what is written), from the
    verification itself (not its JSON); run in a pool's child (``functools.partial`` of it
    pickles). Each result is what the run reads of it (:class:`PosedOutcome`), not the full
    one: the run's process decodes 0.23 MB instead of 0.54 MB for the 108 Brighton pairs (1 ms
    against 5), and no inliers at all."""

    def finish(index: int, verification: Verification) -> PairOutcome:
        outcome = finished(verification, run_result(verification))
        F, inliers = verification.model_matrix, verification.inliers
        pose: Pose = (None, None)
        written = verification.model_type == "fundamental" and len(inliers) >= min_inliers
        if written and F is not None:
            pair = flight.pairs[index]
            image1, image2 = flight.images[pair.image1], flight.images[pair.image2]
            kp1 = pair.keypoints1 if pair.keypoints1 is not None else image1.keypoints
            kp2 = pair.keypoints2 if pair.keypoints2 is not None else image2.keypoints
            assert kp1 is not None and kp2 is not None
            pose = pair_pose(F, pair.matches[inliers], image1.camera, image2.camera, kp1, kp2)
        return PosedOutcome(
            outcome.status, outcome.body, outcome.timings_ms, inliers=inliers, pose=pose
        )

    return verify_flight(flight, finish)


def run_result(verification: Verification) -> dict[str, Any]:
    """What ``hmcc colmap`` reads of a result apart from its inliers: the rest of its
    ``inliers`` form (method, model, total time) and ``statistics.fallback``."""
    result = verification.to_dict("inliers", inliers=False)
    return result | {"statistics": {"fallback": verification.statistics.get("fallback")}}


def result_model(result: dict[str, Any]) -> tuple[np.ndarray | None, np.ndarray]:
    """A result's fundamental matrix (None for another model or none) and its inliers (a list
    or an array)."""
    inliers = np.asarray(result.get("inliers", ()), dtype=np.int64)
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
