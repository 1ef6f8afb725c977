"""Each image's yaw and position corrections, once per image, from the matches of a few of
its pairs: for a flight whose attitudes are estimated (from the flight track) and whose
cameras' real yaws differ from them by any angle, image by image, and whose positions are
off by metres.

**One pair** (:func:`fit_pair_yaws`). A yaw correction ``a`` (degrees, counterclockwise
seen from above) turns a camera's rays about the vertical through its centre: its
footprint on the plane Z = z0 turns by ``a`` about its nadir point ``n``. A pair's matches,
each keypoint taken to the plane with its camera's rough pose (``g1``, ``g2``), are the same
ground points once both cameras are corrected::

    n1 + R(a1) (g1 - n1) = n2 + R(a2) (g2 - n2)

The relative correction ``a2 - a1`` is the rotation that best aligns the two sets of points
about their centroids (2-D Procrustes: it does not depend on the positions); the absolute
one follows from the positions: ``(g1 - n1) - R(a2 - a1) (g2 - n2)`` averages to the
baseline ``n2 - n1`` turned by ``-a1``. The relative correction is as good as the matches
(a fraction of a degree); the absolute one as good as the positions over the baseline (GPS
errors of ``e`` metres over a baseline of ``B``: about ``e / B`` radians). Matches farther
than three times the median residual from the fit are dropped once and the fit repeated.

**The images** (:func:`solve_yaw_corrections`). The pairs' relative corrections tie the
images together, their absolute ones place the whole: one weighted least-squares solve
over the images' corrections (each pair gives ``a2 - a1`` with a weight of one over
:data:`RELATIVE_SIGMA_DEG`, and ``a1`` and ``a2`` each with a weight of one over its
positions' error over its baseline), linearised about each image's circular median of its
pairs' absolute estimates, angles wrapped; a pair whose relative correction then misses
by more than :data:`RELATIVE_OUTLIER_DEG` (a wrong fit) is dropped, the worst first, and
the solve repeated. A common error of all corrections moves every pair's predictions alike (the
guided matcher's first pass absorbs such a shift); an error between two images turns one's
predictions against the other's, which it does not: hence the relative corrections'
weight.

**Their positions** (:func:`solve_position_corrections`). A camera's GPS position can be off by
more than its yaw makes up for: a consumer camera's fix is several metres out, or recorded
a second or two late (every position behind the camera along its track; the images of a
strip flown the other way are then off the other way), and a tilt the attitude does not
carry moves the footprint alike. A correction ``e`` (east, north metres) moves a camera's
footprint by ``e``; with the yaws corrected, a pair's matches are the same ground points
when ``e2 - e1 = R(a1) u - R(a2) v - (n2 - n1)`` (``u``, ``v`` the mean of the matches'
``g1 - n1`` and ``g2 - n2``, which :func:`fit_pair_yaws` keeps). One least-squares solve
over the images' corrections, its minimum-norm solution (a shift of every image alike
moves no pair's predictions: each connected set of images keeps its mean position); a
pair that then misses by more than :data:`POSITION_OUTLIER_FRACTION` of its height above
the ground (a wrong fit) is dropped, the worst first, and the solve repeated.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .pose import Pose, rot_z
from .projection import project_to_plane

__all__ = [
    "PairYaws",
    "fit_pair_yaws",
    "solve_position_corrections",
    "solve_yaw_corrections",
    "yawed",
]

#: A pair's relative correction is this good (degrees): its matches' rotation.
RELATIVE_SIGMA_DEG = 1.0
#: A pair's relative correction this far from the solved ones (degrees): a wrong fit, dropped.
RELATIVE_OUTLIER_DEG = 5.0
#: Fewer matches on the plane than this: no fit.
MIN_FIT_MATCHES = 12
#: The absolute correction of a pair with a shorter baseline (metres) is not used.
MIN_BASELINE_M = 1.0
#: A pair whose position corrections miss the solved ones by this share of its height above
#: the ground: a wrong fit, dropped (0.1: a tenth of the focal length in pixels, a fraction of the
#: guided matcher's wide radius).
POSITION_OUTLIER_FRACTION = 0.1


@dataclass(frozen=True)
class PairYaws:
    """A pair's fit: ``yaw1_deg`` and ``yaw2_deg`` each camera's correction, ``baseline_m``
    the distance between their nadir points, ``used`` the matches of the fit; for the
    positions (:func:`solve_position_corrections`): ``mean1_m`` and ``mean2_m`` the mean of
    those matches' ground points from each camera's nadir point (east, north metres, before
    any correction), ``step_m`` camera 2's nadir point from camera 1's, and ``height_m``
    the cameras' mean height above the ground."""

    yaw1_deg: float
    yaw2_deg: float
    baseline_m: float
    used: int
    mean1_m: tuple[float, float]
    mean2_m: tuple[float, float]
    step_m: tuple[float, float]
    height_m: float


def yawed(pose: Pose, degrees: float) -> Pose:
    """The camera turned by ``degrees`` (counterclockwise seen from above) about the vertical
    through its centre."""
    if degrees == 0:
        return pose
    return Pose(pose.R_world_to_cam @ rot_z(degrees).T, pose.center)


def _wrap(deg: np.ndarray | float) -> np.ndarray:
    return (np.asarray(deg, dtype=np.float64) + 180.0) % 360.0 - 180.0


def fit_pair_yaws(
    camera1: Camera,
    pose1: Pose,
    keypoints1: np.ndarray,
    camera2: Camera,
    pose2: Pose,
    keypoints2: np.ndarray,
    matches: np.ndarray,
    z0: float,
) -> PairYaws | None:
    """Each camera's yaw correction from the pair's ``matches`` (M, 2) (module docstring):
    keypoints (N, 2) pixels, both poses in one world frame (ENU metres), ``z0`` the ground's
    height. None: fewer than :data:`MIN_FIT_MATCHES` on the plane, or nadir points closer
    than :data:`MIN_BASELINE_M`."""
    if len(matches) < MIN_FIT_MATCHES:
        return None
    g1, ok1 = project_to_plane(camera1, pose1, keypoints1[matches[:, 0], :2], z0)
    g2, ok2 = project_to_plane(camera2, pose2, keypoints2[matches[:, 1], :2], z0)
    ok = ok1 & ok2
    n1, n2 = pose1.center[:2], pose2.center[:2]
    u, v = g1[ok, :2] - n1, g2[ok, :2] - n2
    d = n2 - n1
    baseline = float(np.hypot(*d))
    if len(u) < MIN_FIT_MATCHES or baseline < MIN_BASELINE_M:
        return None
    keep = np.ones(len(u), dtype=bool)
    for _ in range(2):
        uc, vc = u[keep] - u[keep].mean(axis=0), v[keep] - v[keep].mean(axis=0)
        cross = float(np.sum(vc[:, 0] * uc[:, 1] - vc[:, 1] * uc[:, 0]))
        relative = math.atan2(cross, float(np.sum(vc * uc)))  # turns v onto u
        c, s = math.cos(relative), math.sin(relative)
        turned = v @ np.array([[c, s], [-s, c]])  # R(relative) v, row by row
        offsets = u - turned
        mean = offsets[keep].mean(axis=0)
        residual = np.hypot(*(offsets - mean).T)
        keep = residual <= max(3.0 * float(np.median(residual[keep])), 1e-6)
        if keep.sum() < MIN_FIT_MATCHES:
            return None
    yaw1 = math.degrees(math.atan2(d[1], d[0]) - math.atan2(mean[1], mean[0]))
    yaw1 = float(_wrap(yaw1))
    yaw2 = float(_wrap(yaw1 + math.degrees(relative)))  # R(a2 - a1) turns v onto u
    mean1, mean2 = u[keep].mean(axis=0), v[keep].mean(axis=0)
    height = 0.5 * float(pose1.center[2] + pose2.center[2]) - z0
    return PairYaws(
        yaw1,
        yaw2,
        baseline,
        int(keep.sum()),
        (float(mean1[0]), float(mean1[1])),
        (float(mean2[0]), float(mean2[1])),
        (float(d[0]), float(d[1])),
        height,
    )


def solve_yaw_corrections(
    fits: Sequence[tuple[int, int, PairYaws]], position_error_m: float
) -> dict[int, float]:
    """Each image's yaw correction (degrees, in -180..180) from its pairs' fits ``(image1,
    image2, fit)`` (module docstring); ``position_error_m`` each position's error
    (horizontal, metres), which weighs the absolute corrections. Images in no fit (once
    the wrong fits are dropped) are not in the answer."""
    if not fits:
        return {}
    images = sorted({i for a, b, _ in fits for i in (a, b)})
    col = {image: k for k, image in enumerate(images)}
    estimates: dict[int, list[float]] = {image: [] for image in images}
    for a, b, f in fits:
        estimates[a].append(f.yaw1_deg)
        estimates[b].append(f.yaw2_deg)
    start = np.array([_circular_median(estimates[i]) for i in images])
    used = list(fits)
    while True:
        x = _solve(used, col, start, position_error_m)
        solved = start + x
        misses = [
            abs(float(_wrap(f.yaw2_deg - f.yaw1_deg - (solved[col[b]] - solved[col[a]]))))
            for a, b, f in used
        ]
        worst = int(np.argmax(misses))
        if misses[worst] <= RELATIVE_OUTLIER_DEG or len(used) == 1:
            break
        del used[worst]  # a wrong fit: dropped, one at a time
    kept = {i for a, b, _ in used for i in (a, b)}
    return {image: float(_wrap(start[k] + x[k])) for image, k in col.items() if image in kept}


def solve_position_corrections(
    fits: Sequence[tuple[int, int, PairYaws]], yaws: Mapping[int, float]
) -> dict[int, tuple[float, float]]:
    """Each image's position correction (east, north metres) from its pairs' fits ``(image1,
    image2, fit)`` with both images' yaw corrections in ``yaws`` (degrees; module
    docstring). Images in no such fit (once the wrong fits are dropped) are not in the
    answer."""
    used = [(a, b, f) for a, b, f in fits if a in yaws and b in yaws]
    steps = [
        _turn(yaws[a], f.mean1_m) - _turn(yaws[b], f.mean2_m) - np.asarray(f.step_m)
        for a, b, f in used
    ]
    while used:
        images = sorted({i for a, b, _ in used for i in (a, b)})
        col = {image: k for k, image in enumerate(images)}
        rows = np.zeros((2 * len(used), 2 * len(images)))
        for k, (a, b, _) in enumerate(used):
            for axis in (0, 1):
                rows[2 * k + axis, 2 * col[b] + axis] = 1.0
                rows[2 * k + axis, 2 * col[a] + axis] = -1.0
        # the minimum-norm solution: each connected set of images keeps its mean position
        x = np.linalg.lstsq(rows, np.concatenate(steps), rcond=None)[0].reshape(-1, 2)
        misses = [
            float(np.hypot(*(x[col[b]] - x[col[a]] - step))) / f.height_m
            for (a, b, f), step in zip(used, steps, strict=True)
        ]
        worst = int(np.argmax(misses))
        if misses[worst] <= POSITION_OUTLIER_FRACTION or len(used) == 1:
            return {image: (float(x[k, 0]), float(x[k, 1])) for image, k in col.items()}
        del used[worst], steps[worst]  # a wrong fit: dropped, one at a time
    return {}


def _turn(degrees: float, xy: Sequence[float]) -> np.ndarray:
    """``xy`` turned counterclockwise by ``degrees``."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([c * xy[0] - s * xy[1], s * xy[0] + c * xy[1]])


def _solve(
    fits: Sequence[tuple[int, int, PairYaws]],
    col: dict[int, int],
    start: np.ndarray,
    position_error_m: float,
) -> np.ndarray:
    """The weighted least-squares step from ``start`` (degrees, one per image)."""
    rows, rhs, weights = [], [], []
    for a, b, f in fits:
        i, j = col[a], col[b]
        row = np.zeros(len(col))
        row[j], row[i] = 1.0, -1.0
        rows.append(row)
        rhs.append(float(_wrap(f.yaw2_deg - f.yaw1_deg - (start[j] - start[i]))))
        weights.append(1.0 / RELATIVE_SIGMA_DEG)
        sigma = math.degrees(math.sqrt(2.0) * max(position_error_m, 0.1) / f.baseline_m)
        for k, yaw in ((i, f.yaw1_deg), (j, f.yaw2_deg)):
            row = np.zeros(len(col))
            row[k] = 1.0
            rows.append(row)
            rhs.append(float(_wrap(yaw - start[k])))
            weights.append(1.0 / sigma)
    w = np.array(weights)
    return np.linalg.lstsq(np.array(rows) * w[:, None], np.array(rhs) * w, rcond=None)[0]


def _circular_median(degrees: Sequence[float]) -> float:
    """The angle of ``degrees`` nearest to all of them (least summed absolute wrapped
    difference; one of them)."""
    values = np.asarray(degrees, dtype=np.float64)
    cost = np.abs(_wrap(values[:, None] - values[None, :])).sum(axis=1)
    return float(values[int(np.argmin(cost))])
