"""One image pair as the core sees it: cameras, rough poses, keypoint arrays, matches, plane."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .errors import InputError
from .pose import Pose

__all__ = ["PairData", "require_matches"]


@dataclass(frozen=True)
class PairData:
    """One image pair as arrays.

    ``keypoints1``/``keypoints2``: (N1, 2|4) / (N2, 2|4) float64, [x, y] or [x, y, size,
    angle_deg], pixels with the centre of the top-left pixel at (0, 0), x right, y down.
    ``matches``: (M, 2) integer indices into them. The plane: ``plane_z`` (Z0, ENU metres) if
    given; else ``ground_z`` (the ground height; the plane goes below it, see
    :class:`hmcc.projection.GroundOptions`); else the ground is estimated from the matches.
    """

    camera1: Camera
    pose1: Pose
    camera2: Camera
    pose2: Pose
    keypoints1: np.ndarray
    keypoints2: np.ndarray
    matches: np.ndarray
    plane_z: float | None = None
    ground_z: float | None = None

    def matched_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """(M, 2) pixels of each match's keypoint in image 1 and in image 2."""
        # np.take: a few times faster than fancy indexing on rows
        return (
            np.take(self.keypoints1, self.matches[:, 0], axis=0)[:, :2],
            np.take(self.keypoints2, self.matches[:, 1], axis=0)[:, :2],
        )


def require_matches(pair: PairData, need: int, model: str) -> None:
    """Raise :class:`InputError` on ``matches`` when the pair has fewer than ``need``."""
    m = len(pair.matches)
    if m < need:
        raise InputError("matches", f"{m} matches; a {model} model needs {need}")
