"""Pinhole cameras with optional OpenCV distortion: intrinsics, pixels to rays, undistortion,
the frame and its margin, and the checks made when a camera is built."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from hmcc.camera import FRAME_MARGIN, Camera

PINHOLE = Camera(width=4000, height=3000, fx=3000.0, fy=2900.0, cx=1999.5, cy=1499.5)
#: A wide-angle UAV lens's order of magnitude: radial and tangential terms.
DISTORTION = (-0.1, 0.02, 0.001, -0.001, 0.0)
DISTORTED = dataclasses.replace(PINHOLE, distortion=DISTORTION)


def _grid(camera: Camera, n: int = 9) -> np.ndarray:
    """(n * n, 2) pixels spread over the whole frame, corners included."""
    x = np.linspace(0.0, camera.width - 1.0, n)
    y = np.linspace(0.0, camera.height - 1.0, n)
    return np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)


def _distort(camera: Camera, normalized: np.ndarray) -> np.ndarray:
    """(N, 2) normalised coordinates -> (N, 2) distorted pixels (OpenCV's own model)."""
    points = np.column_stack((normalized, np.ones(len(normalized))))
    dist = np.zeros(5) if camera.distortion is None else np.asarray(camera.distortion)
    pixels, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.K, dist)
    return pixels.reshape(-1, 2)


def test_K_is_the_calibration_matrix_of_the_intrinsics() -> None:
    np.testing.assert_array_equal(
        PINHOLE.K, [[3000.0, 0.0, 1999.5], [0.0, 2900.0, 1499.5], [0.0, 0.0, 1.0]]
    )
    assert DISTORTED.K.shape == (3, 3)
    np.testing.assert_array_equal(DISTORTED.K, PINHOLE.K)  # the distortion is not in K


def test_a_pinhole_normalises_by_the_principal_point_and_the_focal_lengths() -> None:
    pixels = _grid(PINHOLE)
    expected = (pixels - [PINHOLE.cx, PINHOLE.cy]) / [PINHOLE.fx, PINHOLE.fy]
    np.testing.assert_allclose(PINHOLE.normalize(pixels), expected, rtol=0, atol=1e-15)
    # a single pixel given flat is one point
    np.testing.assert_allclose(PINHOLE.normalize(np.array([3499.5, 1499.5])), [[0.5, 0.0]])


@pytest.mark.parametrize("camera", [PINHOLE, DISTORTED], ids=["pinhole", "distorted"])
def test_the_ray_through_the_principal_point_is_the_optical_axis(camera: Camera) -> None:
    (ray,) = camera.rays(np.array([[camera.cx, camera.cy]]))
    np.testing.assert_allclose(ray, [0.0, 0.0, 1.0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("camera", [PINHOLE, DISTORTED], ids=["pinhole", "distorted"])
def test_rays_are_the_normalised_coordinates_with_z_one(camera: Camera) -> None:
    pixels = _grid(camera)
    rays = camera.rays(pixels)
    assert rays.shape == (len(pixels), 3)
    np.testing.assert_array_equal(rays[:, 2], 1.0)
    np.testing.assert_allclose(rays[:, :2], camera.normalize(pixels), rtol=0, atol=1e-15)
    # pixels right of / below the principal point look toward +x / +y of the camera
    right_below = (pixels[:, 0] > camera.cx) & (pixels[:, 1] > camera.cy)
    assert (rays[right_below, :2] > 0).all()


def test_undistortion_inverts_the_distortion() -> None:
    """Distort with OpenCV (cv2.projectPoints), then normalise: the input comes back."""
    rng = np.random.default_rng(0)
    half = [DISTORTED.width / 2 / DISTORTED.fx, DISTORTED.height / 2 / DISTORTED.fy]
    normalized = rng.uniform(np.negative(half), half, size=(500, 2))
    pixels = _distort(DISTORTED, normalized)
    # the distortion really moves the points (by tens of pixels at the edges)
    ideal = normalized * [DISTORTED.fx, DISTORTED.fy] + [DISTORTED.cx, DISTORTED.cy]
    assert np.abs(pixels - ideal).max() > 10.0
    np.testing.assert_allclose(DISTORTED.normalize(pixels), normalized, rtol=0, atol=1e-6)


def test_undistort_pixels_are_the_ideal_pinhole_pixels_with_the_same_K() -> None:
    pixels = _grid(DISTORTED)
    n = DISTORTED.normalize(pixels)
    expected = n * [DISTORTED.fx, DISTORTED.fy] + [DISTORTED.cx, DISTORTED.cy]
    undistorted = DISTORTED.undistort_pixels(pixels)
    np.testing.assert_allclose(undistorted, expected, rtol=0, atol=1e-9)
    assert np.abs(undistorted - pixels).max() > 10.0  # the corners did move
    # the principal point does not move
    np.testing.assert_allclose(
        DISTORTED.undistort_pixels(np.array([[DISTORTED.cx, DISTORTED.cy]])),
        [[DISTORTED.cx, DISTORTED.cy]],
        rtol=0,
        atol=1e-9,
    )


def test_a_pinhole_leaves_pixels_as_they_are() -> None:
    pixels = np.array([[0, 0], [10, 20], [3999, 2999]])  # ints in, float64 out
    out = PINHOLE.undistort_pixels(pixels)
    assert out.dtype == np.float64
    assert out.shape == (3, 2)
    np.testing.assert_array_equal(out, pixels)


def test_distorted_only_with_a_nonzero_model() -> None:
    assert not PINHOLE.distorted
    zeros = dataclasses.replace(PINHOLE, distortion=(0.0, 0.0, 0.0, 0.0, 0.0))
    assert not zeros.distorted
    assert DISTORTED.distorted
    assert dataclasses.replace(PINHOLE, distortion=(0.0, 0.0, 0.0, 0.0, 1e-3)).distorted
    # an all-zero model normalises exactly as the pinhole does
    pixels = _grid(PINHOLE)
    np.testing.assert_array_equal(zeros.normalize(pixels), PINHOLE.normalize(pixels))


def test_in_frame_accepts_the_frame_and_its_margin_only() -> None:
    mx, my = FRAME_MARGIN * PINHOLE.width, FRAME_MARGIN * PINHOLE.height
    inside = np.array(
        [
            [0.0, 0.0],
            [PINHOLE.width, PINHOLE.height],
            [-mx, -my],  # the margin's edges count
            [PINHOLE.width + mx, PINHOLE.height + my],
            [PINHOLE.cx, -my],
        ]
    )
    outside = np.array(
        [
            [-mx - 1.0, 0.0],
            [0.0, -my - 1.0],
            [PINHOLE.width + mx + 1.0, PINHOLE.cy],
            [PINHOLE.cx, PINHOLE.height + my + 1.0],
        ]
    )
    result = PINHOLE.in_frame(np.vstack((inside, outside)))
    assert result.dtype == bool
    np.testing.assert_array_equal(result, [True] * len(inside) + [False] * len(outside))


@pytest.mark.parametrize(
    "change",
    [
        {"fx": 0.0},
        {"fy": -1.0},
        {"fx": float("nan")},
        {"fy": float("inf")},
        {"cx": float("nan")},
        {"cy": float("-inf")},
        {"fx": 1e-310, "fy": 1e-310},
    ],
    ids=["fx-zero", "fy-negative", "fx-nan", "fy-inf", "cx-nan", "cy-inf", "f-subnormal"],
)
def test_intrinsics_must_be_finite_with_positive_focal_lengths(change: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="fx"):
        dataclasses.replace(PINHOLE, **change)


@pytest.mark.parametrize(
    "distortion",
    [
        (float("nan"), 0.0, 0.0, 0.0, 0.0),
        (float("inf"), 0.0, 0.0, 0.0, 0.0),
        (0.0, 0.0, 1e300, 1e300, 0.0),
    ],
    ids=["nan", "inf", "tangential-to-infinity"],
)
def test_a_distortion_sending_the_frame_to_infinity_is_refused(
    distortion: tuple[float, float, float, float, float],
) -> None:
    with pytest.raises(ValueError, match="distortion"):
        dataclasses.replace(PINHOLE, distortion=distortion)


def test_a_camera_is_immutable() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        PINHOLE.fx = 1.0  # type: ignore[misc]
