"""Every attitude and position convention of the README, proved on numbers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hmcc.pose import (
    CAM_FROM_BODY_NADIR,
    ENU_FROM_NED,
    camera_pose,
    geodetic_to_enu,
    rot_x,
    rot_y,
    rot_z,
    rotation_body_to_ned,
    rotation_from_omega_phi_kappa,
    rotation_from_yaw_pitch_roll,
)
from tests.support.shared_data import BRIGHTON

EAST, NORTH, UP = np.eye(3)


def image_axes(R: np.ndarray) -> dict[str, np.ndarray]:
    """World directions of the image's right, top and viewing axes."""
    return {"right": R[0], "top": -R[1], "view": R[2]}


def test_nadir_at_zero_attitude_looks_down_with_top_to_the_nose_north() -> None:
    axes = image_axes(rotation_from_yaw_pitch_roll(0, 0, 0))
    np.testing.assert_allclose(axes["view"], -UP, atol=1e-12)
    np.testing.assert_allclose(axes["top"], NORTH, atol=1e-12)
    np.testing.assert_allclose(axes["right"], EAST, atol=1e-12)


def test_yaw_is_clockwise_from_north() -> None:
    axes = image_axes(rotation_from_yaw_pitch_roll(90, 0, 0))
    np.testing.assert_allclose(axes["top"], EAST, atol=1e-12)  # nose east
    np.testing.assert_allclose(axes["right"], -NORTH, atol=1e-12)


def test_pitch_nose_up_tilts_a_nadir_view_forward() -> None:
    view = image_axes(rotation_from_yaw_pitch_roll(0, 10, 0))["view"]
    assert view[1] > 0.17 and view[2] < 0  # toward north (the nose), still downward


def test_roll_right_wing_down_tilts_a_nadir_view_left() -> None:
    view = image_axes(rotation_from_yaw_pitch_roll(0, 0, 10))["view"]
    assert view[0] < -0.17 and view[2] < 0  # toward west (left wing)


@pytest.mark.parametrize(
    ("mounting", "expected"),
    [
        ((0, 45, 0), np.array([0, 1, -1]) / np.sqrt(2)),  # front oblique
        ((0, -45, 0), np.array([0, -1, -1]) / np.sqrt(2)),  # back
        ((0, 0, 45), np.array([-1, 0, -1]) / np.sqrt(2)),  # left
        ((0, 0, -45), np.array([1, 0, -1]) / np.sqrt(2)),  # right
    ],
)
def test_mounting_angles_make_penta_view_obliques(mounting, expected) -> None:
    view = image_axes(rotation_from_yaw_pitch_roll(0, 0, 0, mounting))["view"]
    np.testing.assert_allclose(view, expected, atol=1e-12)


def test_mounting_is_applied_in_the_body_frame_eq1() -> None:
    # R_c = r R: a front camera on a platform flying east looks east.
    view = image_axes(rotation_from_yaw_pitch_roll(90, 0, 0, (0, 45, 0)))["view"]
    np.testing.assert_allclose(view, np.array([1, 0, -1]) / np.sqrt(2), atol=1e-12)


def test_rotations_are_proper() -> None:
    rng = np.random.default_rng(1)
    for angles in rng.uniform(-180, 180, (50, 6)):
        r = rotation_from_yaw_pitch_roll(*angles[:3], tuple(angles[3:]))
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)


def test_omega_phi_kappa_zero_is_nadir_north_up() -> None:
    np.testing.assert_allclose(
        rotation_from_omega_phi_kappa(0, 0, 0), rotation_from_yaw_pitch_roll(0, 0, 0), atol=1e-12
    )


def test_kappa_is_counter_clockwise_so_it_is_minus_yaw_for_a_level_nadir_camera() -> None:
    np.testing.assert_allclose(
        rotation_from_omega_phi_kappa(0, 0, 30), rotation_from_yaw_pitch_roll(-30, 0, 0), atol=1e-12
    )


def test_omega_and_phi_tilt_the_view_north_and_west() -> None:
    # camera -> world is Rx(omega) Ry(phi) Rz(kappa); the view is its -z column.
    assert image_axes(rotation_from_omega_phi_kappa(10, 0, 0))["view"][1] > 0.17
    assert image_axes(rotation_from_omega_phi_kappa(0, 10, 0))["view"][0] < -0.17
    r = rotation_from_omega_phi_kappa(5, -7, 12)
    c = (rot_x(5) @ rot_y(-7) @ rot_z(12)) @ np.diag([1, -1, -1])
    np.testing.assert_allclose(r, c.T, atol=1e-12)


def test_lever_arm_is_rotated_by_the_platform_attitude() -> None:
    pose = camera_pose(
        np.zeros(3), np.eye(3), np.array([1.0, 0.0, 2.0]), rotation_body_to_ned(90, 0, 0)
    )
    np.testing.assert_allclose(pose.center, [1.0, 0.0, -2.0], atol=1e-12)  # nose east, 2 m below


def test_lever_arm_without_platform_attitude_is_refused() -> None:
    with pytest.raises(ValueError, match="lever arm"):
        camera_pose(np.zeros(3), np.eye(3), np.ones(3))


def _fixture_docs() -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(BRIGHTON.glob("pair_*.json"))]


def test_yaw_pitch_roll_reproduces_the_fixture_convention() -> None:
    """The fixture README's formula Rz(yaw) Ry(flight_roll) Rx(-flight_pitch) C_mount0 is our
    Z-Y-X attitude with pitch = flight_roll and roll = -flight_pitch (strips 0 and 2)."""
    checked = 0
    for doc in _fixture_docs():
        for img in (doc["image1"], doc["image2"]):
            if img["pixel_rotation_after_capture_deg"] != 0:
                continue
            r = rotation_from_yaw_pitch_roll(
                img["flight_yaw"], img["flight_roll"], -img["flight_pitch"]
            )
            np.testing.assert_allclose(r, img["R_world_to_cam"], atol=1e-9)
            checked += 1
    assert checked >= 10


def test_geodetic_positions_match_the_fixture_enu_frame() -> None:
    for doc in _fixture_docs()[:3]:
        o = doc["enu_origin"]
        for img in (doc["image1"], doc["image2"]):
            enu = geodetic_to_enu(
                img["lat"], img["lon"], img["absolute_altitude"], (o["lat"], o["lon"], o["h"])
            )[0]
            np.testing.assert_allclose(enu, img["C_enu"], atol=0.01)


def test_geodetic_to_enu_axes() -> None:
    enu = geodetic_to_enu(
        np.array([46.001, 46.0, 46.0]),
        np.array([7.0, 7.001, 7.0]),
        np.array([0, 0, 10.0]),
        (46.0, 7.0, 0.0),
    )
    assert enu[0, 1] == pytest.approx(111.2, abs=0.5) and abs(enu[0, 0]) < 1e-6
    assert enu[1, 0] == pytest.approx(77.4, abs=0.5) and abs(enu[1, 1]) < 0.01
    assert enu[2, 2] == pytest.approx(10.0, abs=1e-6)


@pytest.mark.parametrize("mounting", [(0.0, 45.0, 0.0), (0.0, -0.0, 0.0), (-0.0, 0.0, 0.0)])
def test_a_mountings_rotation_is_computed_once_and_the_same(mounting) -> None:  # type: ignore[no-untyped-def]
    """The mounting's part of Eq. 1 is cached (a flight's cameras share a few mountings): the
    result is the same, to the bit, as computed afresh (a zero's sign included, whichever
    sign came first), and the caller's rotation is its own to change."""
    fresh = np.ascontiguousarray(
        (
            ENU_FROM_NED
            @ rotation_body_to_ned(10.0, 2.0, -3.0)
            @ (rotation_body_to_ned(*mounting) @ CAM_FROM_BODY_NADIR.T)
        ).T
    )
    rotation_from_yaw_pitch_roll(10.0, 2.0, -3.0, tuple(-a if a == 0 else a for a in mounting))
    for _ in range(2):
        got = rotation_from_yaw_pitch_roll(10.0, 2.0, -3.0, mounting)
        assert got.tobytes() == fresh.tobytes()
        got[0, 0] = 7.0  # its own copy
