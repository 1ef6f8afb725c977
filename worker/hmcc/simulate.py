"""Synthetic UAV image pairs with exact ground truth, for testing geometric verification.

The model
---------
Frames and attitude conventions are those of :mod:`hmcc.pose`: the world is local ENU in
metres, platform attitude is aerospace yaw (clockwise from north) / pitch (nose up) / roll
(right wing down), Z-Y-X, and a camera with zero mounting looks straight down with the image top
toward the nose. Cameras are ideal pinholes (:class:`hmcc.camera.Camera`, no distortion) with
the principal point at the image centre; pixels follow OpenCV (the centre of the top-left pixel
is (0, 0)). The lever arm is zero, so a camera centre is its platform position.

* **Views.** Each exposure carries one camera of a penta-view rig: ``"V"`` nadir (zero
  mounting), ``"F"``/``"B"`` mounting pitch +45/-45 deg (front/back oblique), ``"L"``/``"R"``
  mounting roll +45/-45 deg (left/right oblique). Mountings are exact (known to the verifier).
* **True poses.** Both platforms fly ``altitude_m`` above ``ground_height_m`` with true yaw =
  ``heading_deg`` and an unknown pitch/roll wobble ~ N(0, ``platform_attitude_sigma_deg``).
  Exposure 1's principal ray hits the plane Z = ``ground_height_m`` at the ENU origin
  (its *footprint centre*); exposure 2 is placed so that its footprint centre lies ``baseline``
  metres from exposure 1's along heading 1. With oblique views the platforms themselves can be
  far apart (e.g. for ("B", "F") exposure 2 flies behind exposure 1 and looks forward onto the
  same ground). When ``baseline_m`` is None, the baseline is ``(1 - forward_overlap)`` times the
  along-track extent of a *nadir* footprint, ``altitude_m * height_px / focal_px``.
* **Rough poses** (what goes into the pair): true position + N(0, ``gnss_sigma_m``) (horizontal
  on E and N, vertical on U) and true attitude + N(0, ``imu_sigma_deg``) on yaw/pitch/roll.
* **Terrain.** A heightfield: ``ground_height_m`` + smooth relief (a sum of four random plane
  waves with wavelengths of 300-1000 m whose amplitudes add up to ``relief_m``) + axis-aligned
  box buildings with flat roofs on a 20 m grid of cells covering about ``building_fraction`` of
  the ground, heights uniform in ``building_height_m`` above the relief at the building centre.
  Buildings are generated lazily by hashing the cell index, so the scene is unbounded.
* **True matches.** Candidate points are drawn through uniformly random pixels of image 1
  (the ray is cut with the mean ground plane and the point is lifted onto the terrain), projected
  with the TRUE poses into both images, perturbed by N(0, ``keypoint_noise_px``) per coordinate
  and kept when both noisy keypoints lie in front of the camera and inside the image
  (``0 <= x <= width - 1``, ``0 <= y <= height - 1``). **Occlusion is ignored** (a point hidden
  behind a building in one view is still "visible"), as are lens distortion, rolling shutter,
  atmospheric refraction and earth curvature.
* **Keypoint size and angle** (OpenCV SIFT-like: size is a diameter in pixels, angle in degrees
  in [0, 360) measured in image coordinates, i.e. clockwise on screen). In image 1 the size is
  uniform in [2, 20] px and the angle uniform. Image 2 gets them mapped through the local affine
  ``A = J2 J1^-1`` between the images, where ``Jk`` is the Jacobian of the projection with
  respect to a horizontal ground offset at the point: ``size2 = size1 sqrt|det A|`` times a
  log-normal factor (sigma 5 %) and ``angle2`` = direction of ``A (cos a1, sin a1)`` + N(0, 3 deg).
* **Outliers.** ``n_out = round(n_inliers * r / (1 - r))``. ``"uniform"``: keypoints uniform in
  both images with random size (2-20 px) and angle. ``"mismatch"``: a fresh true feature of
  image 1 (a terrain point visible in both images, not one of the inliers) paired with the noisy
  image-2 keypoint of a *different* visible terrain point (new keypoint entries, random size and
  angle). In both modes an outlier whose keypoints lie within ``max(3 px, 6 keypoint_noise_px)``
  of their epipolar lines (under the true poses, checked in both images) is redrawn, so that no
  outlier is accidentally consistent with the true geometry.
* **Shuffling.** Keypoint lists of both images and the match list are independently permuted, so
  indices carry no information about the ground truth.

Everything is drawn from ``numpy.random.default_rng(seed)``; the result is deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Integral
from typing import Annotated, Any, Literal, get_args

import numpy as np
from annotated_types import Ge, Gt, Interval

from .bounds import check_fields
from .camera import Camera
from .pose import rotation_from_yaw_pitch_roll

__all__ = ["MOUNTINGS", "VIEWS", "SimulationOptions", "simulate_pair"]

#: Camera mounting (yaw, pitch, roll) in degrees of each view of the penta-view rig.
MOUNTINGS: dict[str, tuple[float, float, float]] = {
    "V": (0.0, 0.0, 0.0),
    "F": (0.0, 45.0, 0.0),
    "B": (0.0, -45.0, 0.0),
    "L": (0.0, 0.0, 45.0),
    "R": (0.0, 0.0, -45.0),
}
View = Literal["V", "F", "B", "L", "R"]
#: Valid view codes.
VIEWS: tuple[str, ...] = get_args(View)
NonNegative = Annotated[float, Ge(0.0)]

_SIZE_RANGE_PX = (2.0, 20.0)
_SIZE_NOISE_REL = 0.05
_ANGLE_NOISE_DEG = 3.0
_OUTLIER_MIN_EPIPOLAR_PX = 3.0
_OUTLIER_MIN_EPIPOLAR_SIGMAS = 6.0
_RELIEF_WAVES = 4
_RELIEF_WAVELENGTH_M = (300.0, 1000.0)
_BUILDING_CELL_M = 20.0
_BUILDING_ASPECT = 1.25
_MIN_AXIS_DOWN = 0.05  # a principal ray must descend at least this much (unit vector z)
_MAX_SAMPLING_ROUNDS = 5
_MAX_CANDIDATES = 400_000
_MAX_REDRAW_ROUNDS = 50

_U64 = np.uint64
_MASK53 = float(2**-53)


@dataclass(frozen=True)
class SimulationOptions:
    """Parameters of one simulated image pair; see the module docstring for the model.

    Lengths in metres, angles in degrees, image quantities in pixels. Sequences given as lists are
    stored as tuples. Every field is validated on construction (``ValueError`` naming the field).
    """

    views: tuple[View, View] = ("V", "V")
    altitude_m: Annotated[float, Gt(0.0)] = 120.0
    ground_height_m: float = 50.0
    relief_m: Annotated[float, Ge(0.0)] = 15.0
    building_fraction: Annotated[float, Interval(ge=0.0, le=1.0)] = 0.2
    building_height_m: tuple[NonNegative, NonNegative] = (5.0, 30.0)
    heading_deg: tuple[float, float] = (0.0, 0.0)
    baseline_m: Annotated[float, Ge(0.0)] | None = None
    forward_overlap: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.7
    width_px: Annotated[int, Ge(2)] = 6000
    height_px: Annotated[int, Ge(2)] = 4000
    focal_px: Annotated[float, Gt(0.0)] = 4000.0
    n_inliers: Annotated[int, Ge(1)] = 400
    outlier_ratio: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.5
    outlier_mode: Literal["uniform", "mismatch"] = "uniform"
    keypoint_noise_px: Annotated[float, Ge(0.0)] = 0.5
    gnss_sigma_m: tuple[NonNegative, NonNegative] = (1.5, 3.0)
    imu_sigma_deg: tuple[NonNegative, NonNegative, NonNegative] = (2.0, 1.0, 1.0)
    platform_attitude_sigma_deg: Annotated[float, Interval(ge=0.0, le=30.0)] = 2.0

    def __post_init__(self) -> None:
        check_fields(self)
        if self.building_height_m[0] > self.building_height_m[1]:
            raise ValueError(f"building_height_m: min must be <= max, got {self.building_height_m}")
        top = self.relief_m + (self.building_height_m[1] if self.building_fraction > 0 else 0.0)
        if self.altitude_m <= top:
            raise ValueError(
                f"altitude_m: must exceed relief_m + max building height ({top} m), "
                f"got {self.altitude_m}"
            )

    @property
    def n_outliers(self) -> int:
        """Number of outlier matches, ``round(n_inliers * r / (1 - r))``."""
        r = self.outlier_ratio
        return int(round(self.n_inliers * r / (1.0 - r)))

    @property
    def baseline(self) -> float:
        """Distance (m) between the two footprint centres along heading 1."""
        if self.baseline_m is not None:
            return float(self.baseline_m)
        along_track = self.altitude_m * self.height_px / self.focal_px
        return (1.0 - self.forward_overlap) * along_track

    @property
    def camera(self) -> Camera:
        """The (shared) ideal pinhole camera of both images."""
        return Camera(
            width=int(self.width_px),
            height=int(self.height_px),
            fx=float(self.focal_px),
            fy=float(self.focal_px),
            cx=(self.width_px - 1) / 2.0,
            cy=(self.height_px - 1) / 2.0,
        )


# --------------------------------------------------------------------------- terrain


@dataclass(frozen=True)
class _Terrain:
    """Heightfield parameters. Arrays: ``wave_k`` (W, 2) rad/m, ``wave_phase`` and
    ``wave_amp`` (W,) rad and m."""

    ground: float
    wave_k: np.ndarray
    wave_phase: np.ndarray
    wave_amp: np.ndarray
    salt: int
    building_prob: float
    building_area: float
    building_height: tuple[float, float]


def _make_terrain(o: SimulationOptions, rng: np.random.Generator) -> _Terrain:
    """Draw the relief waves and the building hash salt."""
    return make_terrain(
        o.ground_height_m, o.relief_m, o.building_fraction, o.building_height_m, rng
    )


def make_terrain(
    ground_height_m: float,
    relief_m: float,
    building_fraction: float,
    building_height_m: tuple[float, float],
    rng: np.random.Generator,
) -> _Terrain:
    """A terrain (see the module docstring): relief waves and buildings drawn from ``rng``."""
    direction = rng.uniform(0.0, 2.0 * np.pi, _RELIEF_WAVES)
    wavelength = rng.uniform(*_RELIEF_WAVELENGTH_M, _RELIEF_WAVES)
    unit = np.column_stack((np.cos(direction), np.sin(direction)))
    k = (2.0 * np.pi / wavelength)[:, None] * unit
    phase = rng.uniform(0.0, 2.0 * np.pi, _RELIEF_WAVES)
    weight = rng.uniform(0.5, 1.0, _RELIEF_WAVES)
    amp = relief_m * weight / weight.sum()
    salt = int(rng.integers(0, 2**62))
    f = float(building_fraction)
    prob = min(1.0, 2.0 * f)
    area = f / prob if prob > 0 else 0.0
    return _Terrain(
        float(ground_height_m),
        k,
        phase,
        amp,
        salt,
        prob,
        area,
        (float(building_height_m[0]), float(building_height_m[1])),
    )


def _relief(t: _Terrain, xy: np.ndarray) -> np.ndarray:
    """(N, 2) ENU east/north (m) -> (N,) relief (m) around zero."""
    return np.sin(xy @ t.wave_k.T + t.wave_phase) @ t.wave_amp


def _mix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser on a uint64 array (wrap-around arithmetic)."""
    x = x + _U64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> _U64(30))) * _U64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> _U64(27))) * _U64(0x94D049BB133111EB)
    return x ^ (x >> _U64(31))


def _cell_uniforms(i: np.ndarray, j: np.ndarray, salt: int, n: int) -> np.ndarray:
    """(N,) int64 cell indices -> (N, n) deterministic uniforms in [0, 1)."""
    key = _mix64(i.astype(np.uint64) ^ _U64(salt))
    key = _mix64(key ^ j.astype(np.uint64))
    h = _mix64(key[:, None] + np.arange(1, n + 1, dtype=np.uint64)[None, :])
    return (h >> _U64(11)).astype(np.float64) * _MASK53


def terrain_height(t: _Terrain, xy: np.ndarray) -> np.ndarray:
    """(N, 2) ENU east/north (m) -> (N,) terrain height Z (m): relief plus building roofs."""
    z = t.ground + _relief(t, xy)
    if t.building_prob <= 0.0 or len(xy) == 0:
        return z
    cell = np.floor(xy / _BUILDING_CELL_M)
    frac = xy / _BUILDING_CELL_M - cell
    ci = cell.astype(np.int64)
    u = _cell_uniforms(ci[:, 0], ci[:, 1], t.salt, 5)
    aspect = np.exp(np.log(_BUILDING_ASPECT) * (2.0 * u[:, 1] - 1.0))
    side = math.sqrt(t.building_area)
    wx = np.minimum(side * aspect, 1.0)
    wy = np.minimum(side / aspect, 1.0)
    ox = (1.0 - wx) * u[:, 2]
    oy = (1.0 - wy) * u[:, 3]
    inside = (
        (u[:, 0] < t.building_prob)
        & (frac[:, 0] >= ox)
        & (frac[:, 0] <= ox + wx)
        & (frac[:, 1] >= oy)
        & (frac[:, 1] <= oy + wy)
    )
    if not inside.any():
        return z
    centre = (cell[inside] + np.column_stack((ox + wx / 2, oy + wy / 2))[inside]) * _BUILDING_CELL_M
    lo, hi = t.building_height
    roof = t.ground + _relief(t, centre) + lo + (hi - lo) * u[inside, 4]
    z[inside] = np.maximum(z[inside], roof)
    return z


# --------------------------------------------------------------------------- geometry


def _project(K: np.ndarray, R: np.ndarray, C: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, ...]:
    """(N, 3) world points -> (N, 2) pixels, (N,) depths and (N, 3) camera coordinates."""
    xc = (X - C) @ R.T
    z = xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        px = np.column_stack((K[0, 0] * xc[:, 0] / z + K[0, 2], K[1, 1] * xc[:, 1] / z + K[1, 2]))
    return px, z, xc


def _ground_jacobian(K: np.ndarray, R: np.ndarray, xc: np.ndarray) -> np.ndarray:
    """(N, 3) camera coordinates -> (N, 2, 2) d(pixel)/d(east, north) of the projection."""
    z = xc[:, 2][:, None]
    r = R[:, :2]  # d(x_cam)/d(E, N), (3, 2)
    du = K[0, 0] * (r[0][None, :] * z - xc[:, :1] * r[2][None, :]) / z**2
    dv = K[1, 1] * (r[1][None, :] * z - xc[:, 1:2] * r[2][None, :]) / z**2
    return np.stack((du, dv), axis=1)


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def _fundamental(
    K: np.ndarray, R1: np.ndarray, C1: np.ndarray, R2: np.ndarray, C2: np.ndarray
) -> np.ndarray:
    """(3, 3) fundamental matrix with ``x2^T F x1 = 0`` for ``x_cam = R (X - C)``."""
    R = R2 @ R1.T
    t = R2 @ (C1 - C2)
    Kinv = np.linalg.inv(K)
    return Kinv.T @ _skew(t) @ R @ Kinv


def _epipolar_min_distance(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(N, 2) pixels in both images -> (N,) min of the point-to-epipolar-line distances (px)."""
    h1 = np.column_stack((p1, np.ones(len(p1))))
    h2 = np.column_stack((p2, np.ones(len(p2))))
    l2 = h1 @ F.T  # lines in image 2
    l1 = h2 @ F  # lines in image 1
    r = np.einsum("ij,ij->i", h2, l2)
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = np.abs(r) / np.hypot(l2[:, 0], l2[:, 1])
        d1 = np.abs(r) / np.hypot(l1[:, 0], l1[:, 1])
    return np.fmin(d1, d2)


def _footprint_offset(R: np.ndarray, height_above: float, index: int) -> np.ndarray:
    """(2,) horizontal offset (m) from the camera centre to where its principal ray meets a plane
    ``height_above`` metres below."""
    axis = R[2]
    if axis[2] > -_MIN_AXIS_DOWN:
        raise ValueError(
            f"views: the optical axis of image {index} does not look down onto the ground"
        )
    return axis[:2] * (height_above / -axis[2])


def _inside(px: np.ndarray, depth: np.ndarray, cam: Camera) -> np.ndarray:
    return (
        (depth > 0.0)
        & (px[:, 0] >= 0.0)
        & (px[:, 0] <= cam.width - 1)
        & (px[:, 1] >= 0.0)
        & (px[:, 1] <= cam.height - 1)
    )


# --------------------------------------------------------------------------- sampling


@dataclass(frozen=True)
class _Pool:
    """Terrain points visible in both images: ``X`` (N, 3) m, noisy keypoints ``p1``/``p2``
    (N, 2) px, camera coordinates ``xc1``/``xc2`` (N, 3) m under the true poses."""

    X: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    xc1: np.ndarray
    xc2: np.ndarray


def _sample_round(
    m: int,
    o: SimulationOptions,
    terrain: _Terrain,
    cam: Camera,
    poses: list[tuple[np.ndarray, np.ndarray]],
    rng: np.random.Generator,
) -> _Pool:
    """Draw ``m`` candidates through random pixels of image 1; keep those visible in both."""
    K = cam.K
    (R1, C1), (R2, C2) = poses
    pix = rng.uniform((0.0, 0.0), (cam.width - 1, cam.height - 1), size=(m, 2))
    noise = rng.normal(0.0, o.keypoint_noise_px, size=(m, 4)) if o.keypoint_noise_px > 0 else None
    rays = cam.rays(pix) @ R1  # world directions, (m, 3)
    down = rays[:, 2] < -1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (terrain.ground - C1[2]) / rays[:, 2]
    xy = C1[:2] + t[:, None] * rays[:, :2]
    xy[~down] = C1[:2]
    X = np.column_stack((xy, terrain_height(terrain, xy)))
    q1, d1, xc1 = _project(K, R1, C1, X)
    q2, d2, xc2 = _project(K, R2, C2, X)
    if noise is not None:
        q1 = q1 + noise[:, :2]
        q2 = q2 + noise[:, 2:]
    keep = down & _inside(q1, d1, cam) & _inside(q2, d2, cam)
    return _Pool(X[keep], q1[keep], q2[keep], xc1[keep], xc2[keep])


def _sample_pool(
    need: int,
    o: SimulationOptions,
    terrain: _Terrain,
    cam: Camera,
    poses: list[tuple[np.ndarray, np.ndarray]],
    rng: np.random.Generator,
) -> _Pool:
    """At least ``need`` visible terrain points in random order, or ``ValueError``."""
    parts: list[_Pool] = []
    total, m = 0, max(4 * need, 1000)
    for _ in range(_MAX_SAMPLING_ROUNDS):
        part = _sample_round(m, o, terrain, cam, poses, rng)
        parts.append(part)
        total += len(part.X)
        if total >= need:
            break
        rate = max(len(part.X), 1) / m  # optimistic when nothing was visible
        m = int(1.5 * (need - total) / rate) + 100
        if m > _MAX_CANDIDATES:  # the overlap is hopelessly small: fail fast
            break
    if total < need:
        raise ValueError(
            f"views: only {total} of the {need} required terrain points are visible in both "
            "images; increase the overlap (forward_overlap/baseline_m/heading_deg) or lower "
            "n_inliers"
        )
    return _Pool(
        *(
            np.concatenate([getattr(p, k) for p in parts])[:need]
            for k in ("X", "p1", "p2", "xc1", "xc2")
        )
    )


def _random_sizes_angles(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    return rng.uniform(*_SIZE_RANGE_PX, n), rng.uniform(0.0, 360.0, n)


def _inlier_keypoints(
    pool: _Pool, K: np.ndarray, R1: np.ndarray, R2: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) keypoints [x, y, size, angle] of the true matches in both images."""
    n = len(pool.X)
    size1, angle1 = _random_sizes_angles(n, rng)
    J1 = _ground_jacobian(K, R1, pool.xc1)
    J2 = _ground_jacobian(K, R2, pool.xc2)
    A = J2 @ np.linalg.inv(J1)  # local affine image 1 -> image 2, (N, 2, 2)
    a1 = np.radians(angle1)
    u2 = A @ np.column_stack((np.cos(a1), np.sin(a1)))[:, :, None]
    angle2 = np.degrees(np.arctan2(u2[:, 1, 0], u2[:, 0, 0])) + rng.normal(0, _ANGLE_NOISE_DEG, n)
    scale = np.sqrt(np.abs(np.linalg.det(A))) * np.exp(rng.normal(0.0, _SIZE_NOISE_REL, n))
    kp1 = np.column_stack((pool.p1, size1, angle1))
    kp2 = np.column_stack((pool.p2, size1 * scale, np.mod(angle2, 360.0)))
    return kp1, kp2


def _uniform_outliers(
    n: int, cam: Camera, F: np.ndarray, min_px: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) uniform keypoint positions in both images, away from their epipolar lines."""
    hi = (cam.width - 1, cam.height - 1)
    p1 = rng.uniform((0.0, 0.0), hi, size=(n, 2))
    p2 = rng.uniform((0.0, 0.0), hi, size=(n, 2))
    for _ in range(_MAX_REDRAW_ROUNDS):
        bad = np.flatnonzero(_epipolar_min_distance(F, p1, p2) < min_px)
        if len(bad) == 0:
            return p1, p2
        p1[bad] = rng.uniform((0.0, 0.0), hi, size=(len(bad), 2))
        p2[bad] = rng.uniform((0.0, 0.0), hi, size=(len(bad), 2))
    raise ValueError("outlier_mode: could not draw uniform outliers off the epipolar lines")


def _mismatch_partners(
    first: np.ndarray,
    n_pool: int,
    p1: np.ndarray,
    p2: np.ndarray,
    F: np.ndarray,
    min_px: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """(n,) pool indices of wrong image-2 partners of the pool points ``first`` (n,)."""
    partner = rng.integers(0, n_pool, len(first))
    for _ in range(_MAX_REDRAW_ROUNDS):
        bad = (partner == first) | (_epipolar_min_distance(F, p1[first], p2[partner]) < min_px)
        idx = np.flatnonzero(bad)
        if len(idx) == 0:
            return partner
        partner[idx] = rng.integers(0, n_pool, len(idx))
    raise ValueError("outlier_mode: could not find mismatch partners off the epipolar lines")


# --------------------------------------------------------------------------- public API


def _true_poses(o: SimulationOptions, rng: np.random.Generator) -> tuple[list[dict], list[tuple]]:
    """True platform attitudes/positions and camera poses of both exposures."""
    wobble = rng.normal(0.0, o.platform_attitude_sigma_deg, size=(2, 2))
    z = o.ground_height_m + o.altitude_m
    h1 = math.radians(o.heading_deg[0])
    centres = [np.zeros(2), o.baseline * np.array([math.sin(h1), math.cos(h1)])]
    platforms, poses = [], []
    for k in range(2):
        att = (float(o.heading_deg[k]), float(wobble[k, 0]), float(wobble[k, 1]))
        R = rotation_from_yaw_pitch_roll(*att, mounting=MOUNTINGS[o.views[k]])
        C = np.append(centres[k] - _footprint_offset(R, o.altitude_m, k + 1), z)
        platforms.append({"attitude": att, "position": C})
        poses.append((R, C))
    return platforms, poses


def _rough_pose_dict(
    o: SimulationOptions,
    view: str,
    attitude: tuple[float, float, float],
    position: np.ndarray,
    rng: np.random.Generator,
) -> dict:
    sh, sv = o.gnss_sigma_m
    dpos = rng.normal(0.0, 1.0, 3) * np.array([sh, sh, sv])
    datt = rng.normal(0.0, 1.0, 3) * np.asarray(o.imu_sigma_deg, dtype=float)
    pos = position + dpos
    yaw, pitch, roll = (a + d for a, d in zip(attitude, datt, strict=True))
    pose: dict[str, Any] = {
        "position": {"x": float(pos[0]), "y": float(pos[1]), "z": float(pos[2])},
        "attitude": {"yaw": float(yaw % 360.0), "pitch": float(pitch), "roll": float(roll)},
    }
    if view != "V":
        y, p, r = MOUNTINGS[view]
        pose["mounting"] = {"yaw": y, "pitch": p, "roll": r}
    return pose


def simulate_pair(options: SimulationOptions, seed: int) -> dict:
    """Simulate one UAV image pair with candidate matches and exact ground truth.

    Returns a JSON-ready dict (plain lists/floats/ints) in the project's pair format:
    ``image1``/``image2`` (``camera``: width, height, fx, fy, cx, cy in px; ``pose``: ROUGH
    ``position`` x/y/z ENU m, ROUGH ``attitude`` yaw/pitch/roll deg, exact ``mounting`` deg,
    omitted for nadir views), ``keypoints1``/``keypoints2`` ((N1, 4)/(N2, 4) lists of
    [x px, y px, size px, angle deg]), ``matches`` ((M, 2) index pairs, shuffled), ``plane``
    (``z``: mean terrain height of the true points, m, rounded to 0.1) and ``ground_truth``
    (``inliers``: sorted match indices of the true matches, ``outlier_ratio``, ``true_poses``:
    two ``{"R_world_to_cam": 3x3, "center": [3]}``, ``mean_ground_z`` m, ``views``, ``seed``).

    Raises ``ValueError`` when ``seed`` is not a non-negative integer or when fewer than
    ``options.n_inliers`` terrain points are visible in both images.
    """
    if not isinstance(options, SimulationOptions):
        raise ValueError(f"options: must be a SimulationOptions, got {type(options).__name__}")
    if not isinstance(seed, Integral) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed: must be a non-negative integer, got {seed!r}")
    o = options
    rng = np.random.default_rng(int(seed))
    cam = o.camera
    K = cam.K
    terrain = _make_terrain(o, rng)
    platforms, poses = _true_poses(o, rng)
    (R1, C1), (R2, C2) = poses
    F = _fundamental(K, R1, C1, R2, C2)
    min_px = max(_OUTLIER_MIN_EPIPOLAR_PX, _OUTLIER_MIN_EPIPOLAR_SIGMAS * o.keypoint_noise_px)

    n_in, n_out = o.n_inliers, o.n_outliers
    mismatch = o.outlier_mode == "mismatch"
    pool = _sample_pool(n_in + (n_out if mismatch else 0), o, terrain, cam, poses, rng)
    kp1_in, kp2_in = _inlier_keypoints(
        _Pool(pool.X[:n_in], pool.p1[:n_in], pool.p2[:n_in], pool.xc1[:n_in], pool.xc2[:n_in]),
        K,
        R1,
        R2,
        rng,
    )
    if mismatch:
        first = np.arange(n_in, n_in + n_out)
        partner = _mismatch_partners(first, len(pool.X), pool.p1, pool.p2, F, min_px, rng)
        q1, q2 = pool.p1[first], pool.p2[partner]
    else:
        q1, q2 = _uniform_outliers(n_out, cam, F, min_px, rng)
    s1, a1 = _random_sizes_angles(n_out, rng)
    s2, a2 = _random_sizes_angles(n_out, rng)
    kp1 = np.concatenate((kp1_in, np.column_stack((q1, s1, a1))))
    kp2 = np.concatenate((kp2_in, np.column_stack((q2, s2, a2))))

    n = n_in + n_out
    perm1, perm2, order = rng.permutation(n), rng.permutation(n), rng.permutation(n)
    pos1, pos2 = np.argsort(perm1), np.argsort(perm2)  # new index of original keypoint k
    matches = np.column_stack((pos1[order], pos2[order]))
    inliers = np.flatnonzero(order < n_in)

    images = {}
    for k in range(2):
        images[f"image{k + 1}"] = {
            "camera": {
                "width": cam.width,
                "height": cam.height,
                "fx": cam.fx,
                "fy": cam.fy,
                "cx": cam.cx,
                "cy": cam.cy,
            },
            "pose": _rough_pose_dict(
                o, o.views[k], platforms[k]["attitude"], platforms[k]["position"], rng
            ),
        }
    mean_z = float(pool.X[:n_in, 2].mean())
    return {
        **images,
        "keypoints1": kp1[perm1].tolist(),
        "keypoints2": kp2[perm2].tolist(),
        "matches": matches.tolist(),
        "plane": {"ground_z": round(mean_z, 1)},
        "ground_truth": {
            "inliers": inliers.tolist(),
            "outlier_ratio": n_out / n,
            "true_poses": [{"R_world_to_cam": R.tolist(), "center": C.tolist()} for R, C in poses],
            "mean_ground_z": mean_z,
            "views": list(o.views),
            "seed": int(seed),
        },
    }
