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
    def K(self) -> np.ndarray:
        """(3, 3) calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def normalize(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) undistorted normalised image coordinates (x/z, y/z)."""
        pts = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
        if self.distortion is not None and any(self.distortion):
            out = cv2.undistortPoints(pts.reshape(-1, 1, 2), self.K, np.asarray(self.distortion))
            return out.reshape(-1, 2)
        return np.column_stack(((pts[:, 0] - self.cx) / self.fx, (pts[:, 1] - self.cy) / self.fy))

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) pixels of the ideal pinhole camera with the same K."""
        if self.distortion is None or not any(self.distortion):
            return np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        n = self.normalize(pixels)
        return np.column_stack((n[:, 0] * self.fx + self.cx, n[:, 1] * self.fy + self.cy))

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) camera-frame ray directions (x, y, 1), not unit length."""
        pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        out = np.ones((len(pts), 3))
        if self.distortion is not None and any(self.distortion):
            out[:, :2] = self.normalize(pts)
        else:
            out[:, 0] = (pts[:, 0] - self.cx) / self.fx
            out[:, 1] = (pts[:, 1] - self.cy) / self.fy
        return out
