"""From matched keypoints to ground motions (paper section 2.1), and the ground height.

Both keypoints of a match are back-projected along their viewing rays onto the horizontal
plane Z = Z0 of the world (ENU) frame; the two intersections are the motion's start (image 1)
and end (image 2). A ray that does not reach the plane in front of its camera (pointing up, or
parallel to it) is marked invalid and never produces a NaN.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from annotated_types import Ge, Interval

from .bounds import PYDANTIC_CONFIG, check_fields
from .camera import Camera
from .errors import InputError
from .jit import compiled
from .pose import Pose

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


def project_to_plane(
    camera: Camera, pose: Pose, pixels: np.ndarray, z0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Intersect the viewing rays of ``pixels`` (N, 2) with the plane Z = ``z0`` (metres).

    Returns ``(points, valid)``: (N, 2) ENU x/y of the intersections and (N,) bool, False where
    the ray is parallel to the plane or meets it behind the camera; invalid rows hold zeros.
    """
    pixels = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
    if camera.distorted:  # undistort to normalised coordinates first (OpenCV)
        intrinsics, pixels = (1.0, 1.0, 0.0, 0.0), camera.normalize(pixels)
    else:
        intrinsics = (camera.fx, camera.fy, camera.cx, camera.cy)
    rotation = np.ascontiguousarray(pose.R_world_to_cam, dtype=np.float64)
    center = np.ascontiguousarray(pose.center, dtype=np.float64)
    return _plane_points(pixels, *intrinsics, rotation, center, float(z0))


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


@dataclass(frozen=True)
class GroundOptions:
    """Where the projection plane goes when the pair gives the ground, not the plane.

    With a ground height G (given as ``plane.ground_z`` or estimated for ``plane.z = "auto"``)
    the plane is ``Z0 = G - plane_depth_fraction * (mean camera height - G)``. The rule is
    ours: the paper gives one instance, a plane at -100 m for a site near 0 m flown at 300 m
    (section 4.2) "to decrease the influence of terrain relief" (section 5: its planes were
    approximated by the sites' average altitudes), and the default 1/3 reproduces it. Below
    the ground every true motion gains a parallax component along the baseline that dominates
    pose noise and relief. 0 projects onto the ground itself.

    How ``"auto"`` estimates G from the matches:

    Every match is triangulated with the rough poses (midpoint method); the heights of the
    points in front of both cameras, below both, and seen under at least
    ``min_parallax_deg`` form a sample that mixes true ground points with outliers'
    scattered heights. The narrowest window holding ``mode_fraction`` of the sample (at least
    ``min_points``) is the densest cluster, the ground, even under a large majority of
    outliers; the estimate is the median of the heights within ``refine_window`` x the flying
    height around that window's median.
    """

    __pydantic_config__ = PYDANTIC_CONFIG

    plane_depth_fraction: Annotated[float, Interval(ge=0, le=10)] = 1.0 / 3.0
    min_parallax_deg: Annotated[float, Interval(ge=0, lt=90)] = 1.0
    mode_fraction: Annotated[float, Interval(gt=0, le=1)] = 0.15
    refine_window: Annotated[float, Interval(gt=0, le=1)] = 0.1
    min_points: Annotated[int, Ge(1)] = 5

    def __post_init__(self) -> None:
        check_fields(self)


def _densest_window_centre(values: np.ndarray, count: int) -> float:
    """Median of the narrowest window of sorted ``values`` holding ``count`` of them."""
    x = np.sort(values)
    widths = x[count - 1 :] - x[: len(x) - count + 1]
    i = int(np.argmin(widths))
    return float(np.median(x[i : i + count]))


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
    d1 = world_rays(camera1, pose1, pixels1)
    d2 = world_rays(camera2, pose2, pixels2)
    points, valid = triangulate_midpoints(pose1.center, d1, pose2.center, d2)
    cos_parallax = np.einsum("ij,ij->i", d1, d2) / (
        np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1)
    )
    valid &= cos_parallax < np.cos(np.radians(options.min_parallax_deg))
    below = np.minimum(pose1.center[2], pose2.center[2])
    valid &= points[:, 2] < below
    z = points[valid, 2]
    stats: dict[str, object] = {"triangulated": int(valid.sum()), "candidates": len(points)}
    if len(z) < options.min_points:
        return None, stats
    mode = _densest_window_centre(z, max(options.min_points, int(options.mode_fraction * len(z))))
    window = options.refine_window * max(below - mode, 1.0)
    near = z[np.abs(z - mode) <= window]
    ground_z = float(np.median(near))
    stats.update(
        {
            "mode": mode,
            "window_m": window,
            "support": len(near),
            "z0": ground_z,  # the ground estimate (the projection plane goes below it)
            "mad_m": float(np.median(np.abs(near - ground_z))),
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
