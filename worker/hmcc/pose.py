"""Camera poses from rough POS: attitude conventions, mounting (paper Eq. 1) and geodesy.

Frames (all right-handed):

* **world**: local east-north-up (ENU), metres.
* **body** (platform): x toward the nose, y toward the right wing, z down (aerospace).
* **NED**: north-east-down, the frame in which yaw/pitch/roll are applied.
* **camera** (OpenCV): x toward the image right, y toward the image bottom, z along the
  optical axis (into the scene). Pixels: origin at the centre of the top-left pixel.

Every rotation here is a 3x3 float64 ndarray. ``R_world_to_cam`` maps a world vector into the
camera frame: ``x_cam = R_world_to_cam @ (X_world - C)`` where ``C`` is the camera centre.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "CAM_FROM_BODY_NADIR",
    "ENU_FROM_NED",
    "Pose",
    "camera_pose",
    "ecef_to_enu",
    "geodetic_to_ecef",
    "geodetic_to_enu",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotation_body_to_ned",
    "rotation_from_omega_phi_kappa",
    "rotation_from_yaw_pitch_roll",
]

#: NED vector -> ENU vector.
ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

#: Camera-to-body rotation of a camera with zero mounting: it looks straight down (camera z =
#: body z) with the top of the image toward the nose (camera -y = body x), so the image right
#: is the right wing (camera x = body y).
CAM_FROM_BODY_NADIR = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
_BODY_FROM_CAM_NADIR = CAM_FROM_BODY_NADIR.T

#: Photogrammetric camera (x right, y toward the image top, z backward) -> OpenCV camera.
_CV_FROM_PHOTO = np.diag([1.0, -1.0, -1.0])


def rot_x(deg: float) -> np.ndarray:
    """Right-handed (active) rotation by ``deg`` degrees about the x axis."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(deg: float) -> np.ndarray:
    """Right-handed (active) rotation by ``deg`` degrees about the y axis."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(deg: float) -> np.ndarray:
    """Right-handed (active) rotation by ``deg`` degrees about the z axis."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_body_to_ned(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Aerospace Z-Y-X attitude: ``R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)``, degrees.

    yaw is clockwise from north seen from above, pitch is nose up, roll is right wing down.
    """
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def rotation_from_yaw_pitch_roll(
    yaw: float,
    pitch: float,
    roll: float,
    mounting: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """World(ENU)-to-camera rotation of a camera on a platform with aerospace attitude.

    ``mounting`` is the camera's (yaw, pitch, roll) relative to the body, same Z-Y-X
    convention, applied on top of the nadir mount: a mounting pitch of +45 tilts the optical
    axis forward (a front oblique camera), -45 backward, a mounting roll of +45 tilts it to the
    left wing and -45 to the right wing. This is the paper's Eq. 1, ``R_c = r R``.
    """
    r_body_cam = _body_from_cam(*mounting, *(math.copysign(1.0, a) for a in mounting))
    r_enu_cam = ENU_FROM_NED @ rotation_body_to_ned(yaw, pitch, roll) @ r_body_cam
    return np.ascontiguousarray(r_enu_cam.T)


@functools.lru_cache(maxsize=64)
def _body_from_cam(yaw: float, pitch: float, roll: float, *signs: float) -> np.ndarray:
    """The camera-to-body rotation of a mounting (read-only): a flight's cameras share a few,
    and the rotation took half of reading each image's pose. ``signs``: the angles' signs, so
    that -0.0 and 0.0 are told apart (as cached values they compare equal)."""
    rotation = rotation_body_to_ned(yaw, pitch, roll) @ _BODY_FROM_CAM_NADIR
    rotation.setflags(write=False)
    return rotation


def rotation_from_omega_phi_kappa(omega: float, phi: float, kappa: float) -> np.ndarray:
    """World(ENU)-to-camera rotation from photogrammetric omega/phi/kappa, degrees.

    Convention (Pix4D's): ``Rx(omega) Ry(phi) Rz(kappa)`` maps the photogrammetric camera frame
    (x image right, y image top, z backward, away from the scene) to the world frame. At zero
    angles the camera looks straight down with the image top toward north and the image right
    toward east.
    """
    r_world_photo = rot_x(omega) @ rot_y(phi) @ rot_z(kappa)
    return np.ascontiguousarray(_CV_FROM_PHOTO @ r_world_photo.T)


@dataclass(frozen=True)
class Pose:
    """A camera's rough pose: ``x_cam = R_world_to_cam @ (X - center)``.

    ``R_world_to_cam``: (3, 3) float64 rotation; ``center``: (3,) float64, metres, ENU.
    """

    R_world_to_cam: np.ndarray
    center: np.ndarray


def camera_pose(
    position_enu: np.ndarray,
    R_world_to_cam: np.ndarray,
    lever_arm_body: np.ndarray | None = None,
    R_ned_body: np.ndarray | None = None,
) -> Pose:
    """Camera pose from the platform position and the camera rotation (paper Eq. 1).

    ``T_c = R^T t + T``: the lever arm ``t`` (metres, body frame: x nose, y right wing, z down)
    is rotated into the world by the platform attitude ``R_ned_body`` and added to the platform
    position ``T`` (ENU metres). Without an attitude of the platform (a camera given by omega/
    phi/kappa or by its matrix) a lever arm cannot be applied and must be absent.
    """
    center = np.asarray(position_enu, dtype=np.float64).reshape(3)
    if lever_arm_body is not None:
        if R_ned_body is None:
            raise ValueError("a lever arm needs the platform attitude (yaw/pitch/roll)")
        center = center + ENU_FROM_NED @ R_ned_body @ np.asarray(lever_arm_body, float)
    return Pose(np.asarray(R_world_to_cam, dtype=np.float64), center)


def geodetic_to_enu(
    lat: ArrayLike, lon: ArrayLike, alt: ArrayLike, origin: tuple[float, float, float]
) -> np.ndarray:
    """WGS84 latitude/longitude (deg) and ellipsoidal height (m) to local ENU metres, (N, 3).

    ``origin`` is (lat, lon, h) of the tangent point; with h = 0 the ENU z of a point is its
    height minus the earth's curvature drop, so a ground plane can be given as a height.
    """
    return ecef_to_enu(geodetic_to_ecef(lat, lon, alt), origin)


def geodetic_to_ecef(lat: ArrayLike, lon: ArrayLike, alt: ArrayLike) -> np.ndarray:
    """WGS84 latitude/longitude (deg) and ellipsoidal height (m) to earth-centred earth-fixed
    metres, (N, 3)."""
    import pymap3d  # here: 12 ms of every import of the core (dateutil), for geodetic poses

    x, y, z = pymap3d.geodetic2ecef(
        np.asarray(lat, float), np.asarray(lon, float), np.asarray(alt, float)
    )
    return np.stack([np.atleast_1d(x), np.atleast_1d(y), np.atleast_1d(z)], axis=-1)


def ecef_to_enu(ecef: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    """(N, 3) earth-centred earth-fixed metres to local ENU metres about ``origin``, (lat,
    lon, h) as in :func:`geodetic_to_enu`."""
    import pymap3d

    e, n, u = pymap3d.ecef2enu(ecef[:, 0], ecef[:, 1], ecef[:, 2], *origin)
    return np.stack([np.atleast_1d(e), np.atleast_1d(n), np.atleast_1d(u)], axis=-1)
