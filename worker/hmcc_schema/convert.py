"""Validated request structure -> the core's objects (cameras, rough poses, images, plane)."""

from __future__ import annotations

import numpy as np

from hmcc import InputError
from hmcc.camera import Camera
from hmcc.flight import FlightImage, RoughPose
from hmcc.pose import (
    rotation_body_to_ned,
    rotation_from_omega_phi_kappa,
    rotation_from_yaw_pitch_roll,
)

from .models import (
    BatchImage,
    CameraModel,
    GeodeticPosition,
    ImageModel,
    Mounting,
    OmegaPhiKappa,
    Plane,
    PoseModel,
    YawPitchRoll,
)

__all__ = [
    "check_in_frame",
    "descriptor_array",
    "to_camera",
    "to_image",
    "to_plane",
    "to_rough_pose",
]


def to_camera(model: CameraModel, field: str = "camera") -> Camera:
    """The camera; ``focal`` stands for both focal lengths, the principal point defaults to the
    image centre, a 4-term distortion gets k3 = 0. Raises :class:`InputError` on ``field``
    when its points do not undistort to finite values."""
    fx = model.fx if model.fx is not None else model.focal
    fy = model.fy if model.fy is not None else model.focal
    assert fx is not None and fy is not None  # the model requires one or the other
    dist = None
    if model.distortion is not None:
        d = [*model.distortion, 0.0][:5]
        dist = (d[0], d[1], d[2], d[3], d[4])
    try:
        return Camera(
            model.width,
            model.height,
            fx,
            fy,
            (model.width - 1) / 2.0 if model.cx is None else model.cx,
            (model.height - 1) / 2.0 if model.cy is None else model.cy,
            dist,
        )
    except ValueError as e:
        name, _, reason = str(e).partition(": ")
        raise InputError(f"{field}.{name}", reason) from None


def to_rough_pose(model: PoseModel) -> RoughPose:
    """The rotation from whichever attitude form was given (with the mounting, paper Eq. 1) and
    the position as given (placed in a pair's frame later)."""
    pos = model.position
    if isinstance(pos, GeodeticPosition):
        position, geodetic = np.array([pos.lat, pos.lon, pos.alt]), True
    else:
        position, geodetic = np.array([pos.x, pos.y, pos.z]), False
    att = model.attitude
    lever = r_ned_body = None
    if isinstance(att, YawPitchRoll):
        mount = model.mounting or Mounting()
        rotation = rotation_from_yaw_pitch_roll(
            att.yaw, att.pitch, att.roll, (mount.yaw, mount.pitch, mount.roll)
        )
        if mount.lever_arm is not None:
            lever = np.asarray(mount.lever_arm, dtype=np.float64)
            r_ned_body = rotation_body_to_ned(att.yaw, att.pitch, att.roll)
    elif isinstance(att, OmegaPhiKappa):
        rotation = rotation_from_omega_phi_kappa(att.omega, att.phi, att.kappa)
    else:
        rotation = np.asarray(att.matrix, dtype=np.float64)
    return RoughPose(rotation, position, geodetic, lever, r_ned_body)


def to_image(
    model: ImageModel | BatchImage,
    keypoints: np.ndarray | None = None,
    field: str = "image",
    descriptors: np.ndarray | None = None,
) -> FlightImage:
    """The image ``field`` (its path in the body, for errors) with its keypoints and their
    descriptors ((N, D) uint8 or float32, :func:`descriptor_array`), if any; a batch's image
    may have no pose (None)."""
    camera = to_camera(model.camera, f"{field}.camera")
    if keypoints is not None:
        check_in_frame(camera, keypoints, f"{field}.keypoints", field)
    if descriptors is not None:
        if keypoints is None:
            raise InputError(f"{field}.descriptors", f"descriptors need {field}.keypoints")
        if len(descriptors) != len(keypoints):
            raise InputError(
                f"{field}.descriptors",
                f"{len(descriptors)} rows; one per keypoint: {len(keypoints)}",
            )
    pose = None if model.pose is None else to_rough_pose(model.pose)
    return FlightImage(camera, pose, keypoints, descriptors)


def descriptor_array(values: np.ndarray) -> np.ndarray | None:
    """(N, D) descriptors as uint8 (integers 0 to 255, as SIFT's) or float32 (any other
    finite numbers); None when they do not fit float32 (or are not finite)."""
    if values.dtype == np.uint8:
        return values
    if values.dtype.kind in "iu" or (
        values.dtype.kind == "f"
        and np.isfinite(values).all()
        and (values == np.round(values)).all()
    ):
        if values.size == 0 or (values.min() >= 0 and values.max() <= 255):
            return values.astype(np.uint8)
    with np.errstate(over="ignore", invalid="ignore"):
        array = values.astype(np.float32)
    return array if np.isfinite(array).all() else None


def check_in_frame(camera: Camera, keypoints: np.ndarray, field: str, image: str) -> None:
    """Raise :class:`InputError` on ``field`` for the first keypoint outside the camera's
    frame (and margin): keypoints in another image size are the usual cause."""
    outside = np.flatnonzero(~camera.in_frame(keypoints))
    if len(outside):
        i = int(outside[0])
        x, y = keypoints[i, 0], keypoints[i, 1]
        raise InputError(
            field,
            f"keypoint {i} at ({x:g}, {y:g}) lies outside the {camera.width} x "
            f"{camera.height} px frame of {image} ({len(outside)} keypoints do); keypoints "
            "are pixels of the camera's image size",
        )


def to_plane(model: Plane) -> tuple[float | None, float | None]:
    """``(plane_z, ground_z)`` of :class:`hmcc.PairData`: both None for ``"auto"``."""
    plane_z = None if model.z in (None, "auto") else float(model.z)
    return plane_z, model.ground_z
