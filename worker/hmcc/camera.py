"""Pinhole cameras with optional OpenCV distortion: pixels to viewing rays."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

__all__ = ["FRAME_MARGIN", "Camera"]


#: Keypoints may lie this fraction of the frame outside it (detectors' sub-pixel positions at
#: the border, generously); further out they belong to another image size.
FRAME_MARGIN = 0.1


@dataclass(frozen=True)
class Camera:
    """Intrinsics in pixels; principal point measured from the centre of the top-left pixel.

    ``distortion`` is OpenCV's (k1, k2, p1, p2, k3) or None for an ideal pinhole. Building one
    checks that its normalisation stays finite over the frame and its margin (extreme
    coefficients or a vanishing focal length send points to infinity, and OpenCV's estimators
    then return a model and wrong inliers without complaint): ``ValueError`` otherwise.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] | None = None

    def __post_init__(self) -> None:
        f = min(self.fx, self.fy)
        finite = bool(np.isfinite((self.fx, self.fy, self.cx, self.cy)).all())
        with np.errstate(over="ignore"):
            # 1/f finite too: a subnormal focal length would normalise every pixel to infinity
            if not (finite and f > 0 and np.isfinite(1.0 / f)):
                raise ValueError("fx: focal lengths must be positive and finite")
        if not self.distorted:
            return  # a pinhole's normalisation is then finite everywhere
        x = np.linspace(-FRAME_MARGIN * self.width, (1 + FRAME_MARGIN) * self.width, 5)
        y = np.linspace(-FRAME_MARGIN * self.height, (1 + FRAME_MARGIN) * self.height, 5)
        probe = np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)
        if not np.isfinite(self.normalize(probe)).all():
            raise ValueError("distortion: the image's points do not undistort to finite values")

    def in_frame(self, pixels: np.ndarray) -> np.ndarray:
        """(N,) bool: the (N, 2) pixels lie in the frame or its margin (:data:`FRAME_MARGIN`)."""
        x, y = pixels[:, 0], pixels[:, 1]
        mx, my = FRAME_MARGIN * self.width, FRAME_MARGIN * self.height
        return (x >= -mx) & (x <= self.width + mx) & (y >= -my) & (y <= self.height + my)

    @property
    def distorted(self) -> bool:
        """True when a non-zero distortion model is given."""
        return self.distortion is not None and any(self.distortion)

    @cached_property
    def K(self) -> np.ndarray:
        """(3, 3) calibration matrix (read-only: built once, an image is in dozens of pairs)."""
        k = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        k.setflags(write=False)
        return k

    def normalize(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) undistorted normalised image coordinates (x/z, y/z)."""
        pts = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
        if self.distorted:
            import cv2  # here: parsing a flight needs no OpenCV

            out = cv2.undistortPoints(pts.reshape(-1, 1, 2), self.K, np.asarray(self.distortion))
            return out.reshape(-1, 2)
        return np.column_stack(((pts[:, 0] - self.cx) / self.fx, (pts[:, 1] - self.cy) / self.fy))

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) pixels of the ideal pinhole camera with the same K, always
        C-contiguous (a pair's pixels are columns of its keypoints: numba compiles the kernels
        they go to anew for each layout)."""
        if not self.distorted:
            return np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
        n = self.normalize(pixels)
        return np.column_stack((n[:, 0] * self.fx + self.cx, n[:, 1] * self.fy + self.cy))

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) camera-frame ray directions (x, y, 1), not unit length."""
        normalized = self.normalize(pixels)
        out = np.ones((len(normalized), 3))
        out[:, :2] = normalized
        return out
