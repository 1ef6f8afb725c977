"""Pinhole cameras with optional OpenCV distortion: pixels to viewing rays."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Camera"]


@dataclass(frozen=True)
class Camera:
    """Intrinsics in pixels; principal point measured from the centre of the top-left pixel.

    ``distortion`` is OpenCV's (k1, k2, p1, p2, k3) or None for an ideal pinhole.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] | None = None

    @property
    def distorted(self) -> bool:
        """True when a non-zero distortion model is given."""
        return self.distortion is not None and any(self.distortion)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def normalize(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) undistorted normalised image coordinates (x/z, y/z)."""
        pts = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
        if self.distorted:
            out = cv2.undistortPoints(pts.reshape(-1, 1, 2), self.K, np.asarray(self.distortion))
            return out.reshape(-1, 2)
        return np.column_stack(((pts[:, 0] - self.cx) / self.fx, (pts[:, 1] - self.cy) / self.fy))

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) pixels of the ideal pinhole camera with the same K."""
        if not self.distorted:
            return np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        n = self.normalize(pixels)
        return np.column_stack((n[:, 0] * self.fx + self.cx, n[:, 1] * self.fy + self.cy))

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) camera-frame ray directions (x, y, 1), not unit length."""
        normalized = self.normalize(pixels)
        out = np.ones((len(normalized), 3))
        out[:, :2] = normalized
        return out
