"""From matched keypoints to ground motions (paper section 2.1), and the ground height.

Both keypoints of a match are back-projected along their viewing rays onto the horizontal
plane Z = Z0 of the world (ENU) frame; the two intersections are the motion's start (image 1)
and end (image 2). A ray that does not reach the plane in front of its camera (pointing up, or
parallel to it) is marked invalid and never produces a NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .camera import Camera
from .errors import InputError
from .jit import compiled
from .pose import Pose
from .stage_options import GroundOptions

if TYPE_CHECKING:
    from .pair import PairData

__all__ = [
    "GroundOptions",
    "Motions",
    "estimate_ground_height",
    "project_pair",
    "project_to_plane",
    "triangulate_midpoints",
    "world_rays",
]

_PARALLEL_EPS = 1e-9


@dataclass(frozen=True)
class Motions:
    """Ground motions: ``start``/``end`` (N, 2) float64 ENU metres on the plane Z = Z0."""

    start: np.ndarray
    end: np.ndarray

    @property
    def vectors(self) -> np.ndarray:
        """(N, 2) end - start, metres."""
        return self.end - self.start

    @property
    def direction_deg(self) -> np.ndarray:
        """(N,) counter-clockwise angle from the world x (east) axis, in [0, 360) (Eq. 2)."""
        v = self.vectors
        d = np.mod(np.degrees(np.arctan2(v[:, 1], v[:, 0])), 360.0)
        return np.where(d >= 360.0, 0.0, d)  # mod of a tiny negative angle rounds to 360

    @property
    def length(self) -> np.ndarray:
        """(N,) motion lengths, metres (Eq. 3)."""
        return np.hypot(*self.vectors.T)

    def subset(self, keep: np.ndarray) -> Motions:
        return Motions(self.start[keep], self.end[keep])


def world_rays(camera: Camera, pose: Pose, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) pixels -> (N, 3) world-frame ray directions (not unit length)."""
    return camera.rays(pixels) @ pose.R_world_to_cam


def _kernel_pixels(camera: Camera, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) float64 pixels and the (4,) intrinsics (fx, fy, cx, cy) that normalise them;
    normalised coordinates and (1, 1, 0, 0) for a distorted camera (OpenCV undistorts)."""
    pixels = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
    if camera.distorted:  # undistort to normalised coordinates first (OpenCV)
        return camera.normalize(pixels), np.array((1.0, 1.0, 0.0, 0.0))
    return pixels, np.array((camera.fx, camera.fy, camera.cx, camera.cy))


def project_to_plane(
    camera: Camera, pose: Pose, pixels: np.ndarray, z0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Intersect the viewing rays of ``pixels`` (N, 2) with the plane Z = ``z0`` (metres).

    Returns ``(points, valid)``: (N, 2) ENU x/y of the intersections and (N,) bool, False where
    the ray is parallel to the plane or meets it behind the camera; invalid rows hold zeros.
    """
    pixels, intrinsics = _kernel_pixels(camera, pixels)
    rotation = np.ascontiguousarray(pose.R_world_to_cam, dtype=np.float64)
    center = np.ascontiguousarray(pose.center, dtype=np.float64)
    fx, fy, cx, cy = intrinsics.tolist()
    return _plane_points(pixels, fx, fy, cx, cy, rotation, center, float(z0))


@compiled
def _plane_points(
    pixels: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    r_world_to_cam: np.ndarray,
    center: np.ndarray,
    z0: float,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`project_to_plane` of a pinhole camera (fx, fy, cx, cy) at ``center``."""
    n = len(pixels)
    points = np.zeros((n, 2))
    valid = np.zeros(n, dtype=np.bool_)
    r = r_world_to_cam
    for i in range(n):
        x, y = (pixels[i, 0] - cx) / fx, (pixels[i, 1] - cy) / fy
        dx = x * r[0, 0] + y * r[1, 0] + r[2, 0]  # the ray (x, y, 1) in the world frame
        dy = x * r[0, 1] + y * r[1, 1] + r[2, 1]
        dz = x * r[0, 2] + y * r[1, 2] + r[2, 2]
        # |d| >= 1 (camera-frame z is 1), so this is "not parallel to the plane" to ~1e-9 rad.
        if not abs(dz) > _PARALLEL_EPS * (abs(dx) + abs(dy) + abs(dz)):
            continue
        t = (z0 - center[2]) / dz
        if t > 0.0:
            valid[i] = True
            points[i, 0] = dx * t + center[0]
            points[i, 1] = dy * t + center[1]
    return points, valid


def triangulate_midpoints(
    c1: np.ndarray, d1: np.ndarray, c2: np.ndarray, d2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Midpoints of the common perpendiculars of rays ``c1 + s d1`` and ``c2 + u d2``.

    ``d1``, ``d2``: (N, 3) directions. Returns ((N, 3) points, (N,) bool valid), valid where
    the rays are not parallel and the point lies in front of both cameras (s, u > 0).
    """
    w = c1 - c2
    a = np.einsum("ij,ij->i", d1, d1)
    b = np.einsum("ij,ij->i", d1, d2)
    c = np.einsum("ij,ij->i", d2, d2)
    d = d1 @ w
    e = d2 @ w
    denom = a * c - b * b
    ok = denom > 1e-12 * a * c
    safe = np.where(ok, denom, 1.0)
    s = (b * e - c * d) / safe
    u = (a * e - b * d) / safe
    valid = ok & (s > 0) & (u > 0)
    points = 0.5 * ((c1 + s[:, None] * d1) + (c2 + u[:, None] * d2))
    return np.where(valid[:, None], points, 0.0), valid


@compiled
def _sorted_median(x: np.ndarray) -> float:
    """np.median of the sorted ``x`` (the mean of the two middle values of an even count)."""
    m = len(x)
    return float(x[m // 2]) if m % 2 else float((x[m // 2 - 1] + x[m // 2]) / 2.0)


@compiled
def _ground_heights(
    n1: np.ndarray,
    k1: np.ndarray,
    n2: np.ndarray,
    k2: np.ndarray,
    r1: np.ndarray,
    r2: np.ndarray,
    c1: np.ndarray,
    c2: np.ndarray,
    cos_min: float,
    below: float,
) -> np.ndarray:
    """The heights of :func:`estimate_ground_height`'s sample: each match (pixels ``n1``,
    ``n2`` normalised by the intrinsics ``k`` = (fx, fy, cx, cy); rays R^T [x, y, 1])
    triangulated as :func:`triangulate_midpoints` does, kept in front of both cameras, seen
    under a parallax cosine below ``cos_min`` and below ``below``; in the matches' order."""
    z = np.empty(len(n1))
    k = 0
    w0, w1, w2 = c1[0] - c2[0], c1[1] - c2[1], c1[2] - c2[2]
    for i in range(len(n1)):
        x, y = (n1[i, 0] - k1[2]) / k1[0], (n1[i, 1] - k1[3]) / k1[1]
        p0 = x * r1[0, 0] + y * r1[1, 0] + r1[2, 0]
        p1 = x * r1[0, 1] + y * r1[1, 1] + r1[2, 1]
        p2 = x * r1[0, 2] + y * r1[1, 2] + r1[2, 2]
        x, y = (n2[i, 0] - k2[2]) / k2[0], (n2[i, 1] - k2[3]) / k2[1]
        q0 = x * r2[0, 0] + y * r2[1, 0] + r2[2, 0]
        q1 = x * r2[0, 1] + y * r2[1, 1] + r2[2, 1]
        q2 = x * r2[0, 2] + y * r2[1, 2] + r2[2, 2]
        a = p0 * p0 + p1 * p1 + p2 * p2
        b = p0 * q0 + p1 * q1 + p2 * q2
        c = q0 * q0 + q1 * q1 + q2 * q2
        d = p0 * w0 + p1 * w1 + p2 * w2
        e = q0 * w0 + q1 * w1 + q2 * w2
        denom = a * c - b * b
        if not denom > 1e-12 * a * c:
            continue
        s = (b * e - c * d) / denom
        u = (a * e - b * d) / denom
        if not (s > 0.0 and u > 0.0):
            continue
        if not b / (np.sqrt(a) * np.sqrt(c)) < cos_min:
            continue
        height = 0.5 * ((c1[2] + s * p2) + (c2[2] + u * q2))
        if height < below:
            z[k] = height
            k += 1
    return z[:k]


@compiled
def _ground_from_heights(
    z: np.ndarray, count: int, refine_window: float, below: float
) -> tuple[float, float, float, int, float]:
    """The ground of the (unsorted) heights ``z``: the median of the narrowest window of
    ``count`` sorted heights (the mode; the first of equal widths), then the median of the
    heights within ``refine_window`` x the flying height around that mode; (ground, mode,
    window, support, MAD of the support)."""
    x = np.sort(z)
    best = 0
    for i in range(1, len(x) - count + 1):
        if x[i + count - 1] - x[i] < x[best + count - 1] - x[best]:
            best = i
    mode = _sorted_median(x[best : best + count])
    window = refine_window * max(below - mode, 1.0)
    near = x[np.abs(x - mode) <= window]  # sorted, as x is
    ground = _sorted_median(near)
    spread = np.sort(np.abs(near - ground))
    return ground, mode, window, len(near), _sorted_median(spread)


def estimate_ground_height(
    camera1: Camera,
    pose1: Pose,
    pixels1: np.ndarray,
    camera2: Camera,
    pose2: Pose,
    pixels2: np.ndarray,
    options: GroundOptions = GroundOptions(),
) -> tuple[float | None, dict[str, object]]:
    """Robust ground height (ENU z, metres) from matched pixels (N, 2) of both images.

    Returns ``(ground_z, stats)``; ``ground_z`` is None when fewer than ``options.min_points``
    matches triangulate acceptably (the caller must then ask for an explicit height).
    """
    below = float(min(pose1.center[2], pose2.center[2]))
    z = _ground_heights(
        *_kernel_pixels(camera1, pixels1),
        *_kernel_pixels(camera2, pixels2),
        np.ascontiguousarray(pose1.R_world_to_cam, dtype=np.float64),
        np.ascontiguousarray(pose2.R_world_to_cam, dtype=np.float64),
        np.ascontiguousarray(pose1.center, dtype=np.float64),
        np.ascontiguousarray(pose2.center, dtype=np.float64),
        math.cos(math.radians(options.min_parallax_deg)),
        below,
    )
    stats: dict[str, object] = {"triangulated": len(z), "candidates": len(pixels1)}
    if len(z) < options.min_points:
        return None, stats
    count = max(options.min_points, int(options.mode_fraction * len(z)))
    ground_z, mode, window, support, mad = _ground_from_heights(
        z, count, options.refine_window, below
    )
    stats.update(
        {
            "mode": mode,
            "window_m": window,
            "support": support,
            "z0": ground_z,  # the ground estimate (the projection plane goes below it)
            "mad_m": mad,
        }
    )
    return ground_z, stats


def project_pair(
    pair: PairData, px1: np.ndarray, px2: np.ndarray, ground: GroundOptions
) -> tuple[Motions, np.ndarray, dict[str, Any]]:
    """Motions of the matches whose both rays reach the plane, the (M,) mask of those, and the
    projection's statistics (``z0_m``, ``z0_source``, rays missed per image, the ground).

    ``px1``/``px2``: (M, 2) matched pixels. Raises :class:`InputError` on ``plane.z`` (or
    ``plane.ground_z``) when no ray of an image reaches the plane or the ground cannot be used.
    """
    stats: dict[str, Any] = {}
    z0 = pair.plane_z
    if z0 is None:
        z0 = _plane_below_ground(pair, px1, px2, ground, stats)
    start, ok1 = project_to_plane(pair.camera1, pair.pose1, px1, z0)
    end, ok2 = project_to_plane(pair.camera2, pair.pose2, px2, z0)
    for name, ok in (("image1", ok1), ("image2", ok2)):
        if len(ok) and not ok.any():
            raise InputError("plane.z", f"no ray of {name} reaches the plane Z0 = {z0:g} m")
    valid = ok1 & ok2
    motions = Motions(start, end) if valid.all() else Motions(start[valid], end[valid])
    stats.update(
        {
            "z0_m": z0,
            "z0_source": _z0_source(pair),
            "rays_missed_image1": int((~ok1).sum()),
            "rays_missed_image2": int((~ok2).sum()),
        }
    )
    return motions, valid, stats


def _z0_source(pair: PairData) -> str:
    if pair.plane_z is not None:
        return "given"
    return "ground_z" if pair.ground_z is not None else "auto"


def _plane_below_ground(
    pair: PairData,
    px1: np.ndarray,
    px2: np.ndarray,
    ground: GroundOptions,
    stats: dict[str, Any],
) -> float:
    """Z0 from the given or estimated ground height (see :class:`GroundOptions`)."""
    ground_z = pair.ground_z
    field = "plane.ground_z"
    if ground_z is None:
        field = "plane.z"
        ground_z, stats["ground"] = estimate_ground_height(
            pair.camera1, pair.pose1, px1, pair.camera2, pair.pose2, px2, ground
        )
        if ground_z is None:
            raise InputError(
                field, "too few matches triangulate to estimate the ground height; give it"
            )
    height = 0.5 * (pair.pose1.center[2] + pair.pose2.center[2]) - ground_z
    if height <= 0.0:
        raise InputError(field, f"the ground ({ground_z:g} m) is not below the cameras")
    stats["ground_z_m"] = ground_z
    return float(ground_z - ground.plane_depth_fraction * height)
