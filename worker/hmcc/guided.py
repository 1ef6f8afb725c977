"""Feature matching guided by the rough POS (Jiang & Jiang 2017): each keypoint of image 1 is
compared only with the keypoints of image 2 near its predicted position.

**Prediction.** A keypoint of image 1 is projected along its viewing ray to the ground plane
Z = Z0 with the rough pose of camera 1 (the core's :func:`hmcc.projection.project_to_plane`,
the paper's section 2.1) and that ground point into camera 2 with its rough pose
(:func:`predict_in_image2`). With exact poses and a flat ground at Z0 the prediction is the
true match; the POS errors move it.

**Wide radius** (:func:`wide_radius_px`), the worst case of the POS errors in image 2's pixels
at the pair's flying height H above Z0 and focal length f (pixels):

* attitude: each camera's attitude error ``a`` turns its rays by ``a``, which moves a point
  by about ``f tan a`` in the image; the two cameras' errors add: ``2 f tan a``;
* position: each camera's horizontal position error ``e`` moves the ground point (camera 1)
  or the viewpoint (camera 2) by ``e``, seen from H: ``2 f e / H``;
* ground height: Z0 off by ``g H`` moves the ground point along image 1's ray, which camera 2
  sees across the baseline B as the parallax ``f (B / H) g / (1 - g)``.

Their sum, at most ``max_wide_fraction`` of image 2's larger side.

**Two passes** (:func:`match_guided`). The first matches a sample of the keypoints (those
predicted inside image 2, evenly spread in index order) within the wide radius, and fits the
motion of the predictions to their matches (:func:`_consistent_motion`); on half of
``sample_size`` keypoints first, and on all of them where that half does not fit (most pairs
fit on the half: the first pass was about half of a pair's candidates) and did not hold every
keypoint predicted inside already. Most of the POS
error is one consistent shift of the whole prediction (attitude, position and ground height
all shift the predictions of a nadir pair alike): the median offset between the predictions
and their first-pass matches, re-taken over the matches within a quarter of the wide radius
of it (the cap), is that shift. What is left is mostly a turn and a scale about the image
(a yaw or a height off) or a tilt: an affine map of the predictions (``A p + t``, 6
parameters) takes it out, fitted by least squares to the matches within the tight radius of
the shift, then again to those within the tight radius of that fit (the shift stays with
fewer than 18 such matches, 3 per parameter, or a tight radius at its least already). The
tight radius is three times the median remaining offset of the matches within the cap (at
least ``tight_min_px``, at most the cap).
The pose fits when at least ``min_support`` first-pass matches, and ``min_support_fraction`` of
them, lie within the tight radius of the motion; then every keypoint is matched within the
search radius of its moved prediction: the tight radius, or the radius holding
``SEARCH_SHARE`` (95 %) of the first-pass matches within the cap where that is wider (relief:
a building's parallax is no part of the motion, and 3 x the median offset of the ground's
matches left a tenth of a low flight's true matches over a town out). The keypoints within
``ratio_radius_factor`` times the tight radius (at least ``ratio_radius_min_px``) compete in
the ratio rule without being matched (a repeated texture just outside the tight radius
still makes a match ambiguous, as it does for brute force; with the ratio taken among the
searched keypoints alone, Brighton's mapped model had a 12 % higher mean reprojection error
than COLMAP's, ``docs/benchmarks/match.md``; with the affine map's tight radius, mostly its
least, 3 x that radius alone left it 6.6 % higher, 48 px at least 4.3 %).

**Turned images.** When the poses as given do not fit over an overlap, an image may have been
turned after capture (or its camera mounted otherwise than its tags say): the first pass is
tried again, on a smaller sample (``turn_sample_size``), with each camera turned by 0, 90,
180 or 270 deg about its optical axis (15 hypotheses, half turns first, each a few hundredths
of brute force), and the best that fits is taken (``guided-turned``, its ``turn_deg``
reported); one where half the first pass's matches move alike ends the search. A flight's
caller that knows an image's turn (found in its other pairs) passes it (``turns``) and spares
the search. A pose that still does not fit gives no matches (``pose-mismatch-unmatched``:
mostly pairs whose footprints barely overlap, or over ground without texture), or with
``brute_force_on_mismatch`` brute force (``pose-mismatch``; off by default: on 2-core
machines one brute-force pair of 12 000 keypoints costs as much as some 50 guided ones); a
pair whose predictions miss image 2 has no matches (``no-overlap``).

**Any yaw** (:func:`_rotation_pass`). A yaw off by an angle no quarter turn absorbs (an
attitude estimated from the flight track, a camera that swings): where no turn fits and both
images' keypoints have orientations, ``turn_sample_size`` keypoints are matched by brute
force, the peak of their orientation changes (within ``rotation_window_deg``) is the
rotation between the images, camera 2 is turned about its optical axis until the poses
predict it, and the sample's matches that agree with it give the motion and the support, as a
first pass's (``guided-rotated``, ``turn_deg`` camera 2's turn). A flight's caller that
matches many pairs of such images corrects each image's yaw once instead (:mod:`hmcc.yaw`,
from the matches of a few of its pairs) and matches the rest with the corrected poses,
searching nothing.

**Rules** (COLMAP's defaults): descriptors as unit vectors (COLMAP's uint8 SIFT divided by
their norm), distance the angle between them; a keypoint's best candidate is kept when its
angle is at most ``max_distance_rad`` and less than ``max_ratio`` times the second best
candidate's (no second candidate: the ratio holds); and when it is mutual as COLMAP's cross
check has it: the same rules taken the other way, over the keypoints of image 1 having that
keypoint of image 2 as a candidate, give back the keypoint of image 1 (its best, within the
distance and ratio rules among them). Brute force (:func:`match_brute_force`) applies the
same rules with every keypoint a candidate (COLMAP's exhaustive matching); the guided matcher
with an unbounded radius gives the same matches.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from .camera import Camera
from .jit import compiled_reassociating
from .pose import Pose, rot_z
from .projection import project_to_plane
from .stage_options import GuidedOptions

__all__ = [
    "Features",
    "GridIndex",
    "GuidedOptions",
    "MatchResult",
    "match_brute_force",
    "match_guided",
    "match_within",
    "normalize_descriptors",
    "predict_in_image2",
    "predicted_overlap",
    "project_points",
    "wide_radius_px",
    "with_options",
]

#: Rows of image 1 per block of the brute-force distance matrix (block x N2 float32).
_BRUTE_BLOCK_ROWS = 1024
#: The grid's cells are never smaller than this (pixels): a tiny radius would make a huge grid.
_MIN_CELL_PX = 4.0
#: The cell of the one grid a pair's passes share (pixels): a tight radius spans a few cells,
#: a wide one a few hundred, whose rows are scanned as one run each.
_GRID_CELL_PX = 32.0


@dataclass(frozen=True)
class Features:
    """An image's features: ``keypoints`` (N, 2) float64 pixels (ours: the centre of the
    top-left pixel at (0, 0)), ``descriptors`` (N, D) float32 unit rows
    (:func:`normalize_descriptors`) and, when known, ``orientations`` (N,) float64 radians
    (each keypoint's direction in the image, x right, y down; NaN where unknown), which the
    rotation search reads."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    orientations: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.keypoints.ndim != 2 or self.keypoints.shape[1] < 2:
            raise ValueError(f"keypoints: expected (N, 2), got {self.keypoints.shape}")
        if self.descriptors.ndim != 2 or len(self.descriptors) != len(self.keypoints):
            raise ValueError(
                f"descriptors: expected ({len(self.keypoints)}, D), got {self.descriptors.shape}"
            )
        if self.descriptors.dtype != np.float32:
            raise ValueError("descriptors: float32 unit rows (normalize_descriptors)")
        if self.orientations is not None and self.orientations.shape != (len(self.keypoints),):
            raise ValueError(
                f"orientations: expected ({len(self.keypoints)},), got {self.orientations.shape}"
            )

    @classmethod
    def from_raw(
        cls,
        keypoints: np.ndarray,
        descriptors: np.ndarray,
        orientations: np.ndarray | None = None,
    ) -> Features:
        """From (N, >=2) pixels, (N, D) descriptors of any numeric type (COLMAP's uint8) and
        optionally (N,) orientations (radians)."""
        kp = np.ascontiguousarray(np.asarray(keypoints, dtype=np.float64)[:, :2])
        angles = None if orientations is None else np.asarray(orientations, dtype=np.float64)
        return cls(kp, normalize_descriptors(descriptors), angles)

    def __len__(self) -> int:
        return len(self.keypoints)

    @functools.cached_property
    def grid(self) -> GridIndex:
        """The keypoints' grid index as image 2 of a pair (cells of :data:`_GRID_CELL_PX`),
        built on first use and kept with the features: an image matched in many pairs (one
        whose features the caller keeps) builds it once. It holds a copy of the descriptors
        in the grid's order."""
        return GridIndex.build(self, _GRID_CELL_PX)


@dataclass(frozen=True)
class MatchResult:
    """A pair's matches: ``matches`` (M, 2) int64 indices (image 1, image 2) and ``stats``:
    ``mode`` (``guided``, ``guided-turned`` (with ``turn_deg``: image 1's and image 2's turns
    about their optical axes), ``guided-rotated`` (``turn_deg``: camera 2 turned by any angle,
    from the keypoints' orientations), ``brute-force``, ``pose-mismatch`` (brute force after first
    passes that did not fit; ``pose-mismatch-unmatched`` without it), ``no-overlap``),
    ``candidates_per_keypoint`` (descriptors compared per keypoint of image 1, both passes),
    ``matches``, ``time_ms``, and the passes' radii, motion and support."""

    matches: np.ndarray
    stats: dict[str, Any] = field(default_factory=dict)


def normalize_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """(N, D) descriptors -> (N, D) float32 rows of unit length (zero rows stay zero)."""
    d = np.asarray(descriptors, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"descriptors: expected (N, D), got {d.shape}")
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return np.ascontiguousarray(d / np.where(norm > 0, norm, 1.0), dtype=np.float32)


@functools.lru_cache(maxsize=64)
def with_options(options: GuidedOptions, **changes: Any) -> GuidedOptions:
    """``options`` with ``changes`` (``dataclasses.replace``), kept: a replace checks every
    field again (about 0.3 ms), and a flight's pairs ask for the same few variants."""
    return replace(options, **changes)


# --------------------------------------------------------------------------- prediction


def project_points(camera: Camera, pose: Pose, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world points -> ((N, 2) pixels, (N,) bool in front of the camera); distorted
    cameras through OpenCV's model. Points behind the camera hold zeros."""
    x_cam = (np.asarray(points, dtype=np.float64) - pose.center) @ pose.R_world_to_cam.T
    front = x_cam[:, 2] > 1e-9
    pixels = np.zeros((len(x_cam), 2))
    if not front.any():
        return pixels, front
    if camera.distorted:
        assert camera.distortion is not None
        dist = np.asarray(camera.distortion, dtype=np.float64)
        px, _ = cv2.projectPoints(
            np.ascontiguousarray(x_cam[front]), np.zeros(3), np.zeros(3), camera.K, dist
        )
        pixels[front] = px.reshape(-1, 2)
    else:
        xy = x_cam[front, :2] / x_cam[front, 2:3]
        pixels[front] = xy * (camera.fx, camera.fy) + (camera.cx, camera.cy)
    return pixels, front


def predict_in_image2(
    camera1: Camera,
    pose1: Pose,
    pixels1: np.ndarray,
    camera2: Camera,
    pose2: Pose,
    z0: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Where image 1's ``pixels1`` (N, 2) appear in image 2 if they lie on the plane Z = ``z0``:
    ((N, 2) pixels of image 2, (N,) bool: the ray reaches the plane and the point is in front
    of camera 2). Both poses in one world frame (ENU metres)."""
    ground, valid = project_to_plane(camera1, pose1, pixels1, z0)
    points = np.column_stack((ground, np.full(len(ground), float(z0))))
    pred, front = project_points(camera2, pose2, points)
    return pred, valid & front


def predicted_overlap(
    camera1: Camera, pose1: Pose, camera2: Camera, pose2: Pose, z0: float, steps: int = 16
) -> float:
    """The share of a ``steps`` x ``steps`` grid over image 1 predicted inside image 2: the
    two footprints' overlap on the plane as seen from image 1 (0 to 1)."""
    cells = (np.arange(steps) + 0.5) / steps  # the cells' centres
    x, y = cells * (camera1.width - 1), cells * (camera1.height - 1)
    grid = np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)
    pred, valid = predict_in_image2(camera1, pose1, grid, camera2, pose2, z0)
    return float((valid & _in_frame(pred, camera2, 0.0)).mean())


def wide_radius_px(
    camera2: Camera, pose1: Pose, pose2: Pose, z0: float, options: GuidedOptions
) -> tuple[float, dict[str, float]]:
    """The first pass's search radius in image 2 (pixels) and its terms (module docstring)."""
    f = 0.5 * (camera2.fx + camera2.fy)
    height = max(0.5 * (pose1.center[2] + pose2.center[2]) - z0, 1e-3)
    baseline = float(np.hypot(*(pose2.center[:2] - pose1.center[:2])))
    g = options.ground_error_fraction
    terms = {
        "attitude_px": 2.0 * f * math.tan(math.radians(options.attitude_error_deg)),
        "position_px": 2.0 * f * options.position_error_m / height,
        "ground_px": f * baseline / height * g / (1.0 - g),
    }
    cap = options.max_wide_fraction * max(camera2.width, camera2.height)
    return float(min(sum(terms.values()), cap)), {k: round(float(v), 1) for k, v in terms.items()}


# --------------------------------------------------------------------------- grid and kernels


@dataclass(frozen=True)
class GridIndex:
    """Image 2's keypoints bucketed in square cells of ``cell`` pixels and stored cell by cell
    (a cell's candidates then lie side by side in memory): ``points`` (N, 2) and
    ``descriptors`` (N, D) in that order, ``order[k]`` the original index of row k, the rows
    of cell ``c`` (row-major from ``origin``) ``starts[c]:starts[c + 1]``."""

    points: np.ndarray
    descriptors: np.ndarray
    order: np.ndarray
    origin: tuple[float, float]
    cell: float
    cols: int
    rows: int
    starts: np.ndarray

    @classmethod
    def build(cls, features: Features, cell: float) -> GridIndex:
        pts = np.ascontiguousarray(features.keypoints[:, :2], dtype=np.float64)
        cell = max(float(cell), _MIN_CELL_PX)
        if len(pts) == 0:
            empty = np.zeros(0, dtype=np.int64)
            return cls(
                pts, features.descriptors, empty, (0.0, 0.0), cell, 1, 1, np.zeros(2, np.int64)
            )
        x0, y0 = float(pts[:, 0].min()), float(pts[:, 1].min())
        cx = ((pts[:, 0] - x0) // cell).astype(np.int64)
        cy = ((pts[:, 1] - y0) // cell).astype(np.int64)
        cols, rows = int(cx.max()) + 1, int(cy.max()) + 1
        ids = cy * cols + cx
        order = np.argsort(ids, kind="stable").astype(np.int64)
        starts = np.zeros(cols * rows + 1, dtype=np.int64)
        np.cumsum(np.bincount(ids, minlength=cols * rows), out=starts[1:])
        return cls(
            np.ascontiguousarray(pts[order]),
            np.ascontiguousarray(features.descriptors[order]),
            order,
            (x0, y0),
            cell,
            cols,
            rows,
            starts,
        )


@compiled_reassociating
def _scan_candidates(
    pred: np.ndarray,
    active: np.ndarray,
    desc1: np.ndarray,
    desc2: np.ndarray,
    points2: np.ndarray,
    order: np.ndarray,
    starts: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    cols: int,
    rows: int,
    radius: float,
    radius_best: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """For each active keypoint i of image 1, its candidates: image 2's keypoints within
    ``radius`` of ``pred[i]`` (``desc2``, ``points2`` in the grid's order, ``order`` their
    indices); a candidate farther than ``radius_best`` only competes (the second best), it is
    never the best. Returns the best candidate of each i and the dot products of its best and
    second best (-2: none); the same the other way, for each keypoint j of image 2 over the
    i having j as a candidate (its best i, best and second best dot products); and the
    descriptors compared."""
    n1, n2, dim = len(pred), len(points2), desc1.shape[1]
    best = np.full(n1, -1, dtype=np.int64)
    dot_best = np.full(n1, -2.0, dtype=np.float32)
    dot_second = np.full(n1, -2.0, dtype=np.float32)
    col_best = np.full(n2, -1, dtype=np.int64)
    col_dot = np.full(n2, -2.0, dtype=np.float32)
    col_second = np.full(n2, -2.0, dtype=np.float32)
    compared = 0
    r2 = radius * radius
    rb2 = radius_best * radius_best
    for i in range(n1):
        if not active[i]:
            continue
        px, py = pred[i, 0], pred[i, 1]
        c0 = max(int(math.floor((px - radius - x0) / cell)), 0)
        c1 = min(int(math.floor((px + radius - x0) / cell)), cols - 1)
        r0 = max(int(math.floor((py - radius - y0) / cell)), 0)
        r1 = min(int(math.floor((py + radius - y0) / cell)), rows - 1)
        if c0 > c1 or r0 > r1:
            continue  # the circle misses the grid: no cell to read
        b, bd, sd = -1, np.float32(-2.0), np.float32(-2.0)
        for row in range(r0, r1 + 1):
            # the row's cells c0..c1 are consecutive: one run of candidates
            for k in range(starts[row * cols + c0], starts[row * cols + c1 + 1]):
                dx, dy = points2[k, 0] - px, points2[k, 1] - py
                dd = dx * dx + dy * dy
                if dd > r2:
                    continue
                d = np.float32(0.0)
                for t in range(dim):
                    d += desc1[i, t] * desc2[k, t]
                compared += 1
                j = order[k]
                if dd > rb2:  # a competitor only
                    if d > sd:
                        sd = d
                    if d > col_second[j]:
                        col_second[j] = d
                    continue
                if d > bd:
                    sd, bd, b = bd, d, j
                elif d > sd:
                    sd = d
                if d > col_dot[j]:
                    col_second[j], col_dot[j], col_best[j] = col_dot[j], d, i
                elif d > col_second[j]:
                    col_second[j] = d
        best[i], dot_best[i], dot_second[i] = b, bd, sd
    return best, dot_best, dot_second, col_best, col_dot, col_second, compared


def _select(
    best: np.ndarray,
    dot_best: np.ndarray,
    dot_second: np.ndarray,
    col_best: np.ndarray,
    col_dot: np.ndarray,
    col_second: np.ndarray,
    options: GuidedOptions,
) -> np.ndarray:
    """(M, 2) matches under the distance and ratio rules and (``cross_check``) the mutual
    rule, COLMAP's: the same rules taken the other way (image 2's keypoint to its best
    candidate of image 1) give back the keypoint of image 1."""
    rows = np.flatnonzero(best >= 0)
    cols = best[rows]
    keep = _passes(dot_best[rows], dot_second[rows], options)
    if options.cross_check:
        keep &= col_best[cols] == rows
        keep &= _passes(col_dot[cols], col_second[cols], options)
    return np.column_stack((rows[keep], cols[keep])).astype(np.int64)


def _passes(dot_best: np.ndarray, dot_second: np.ndarray, options: GuidedOptions) -> np.ndarray:
    """(N,) bool: the best candidate's angle is at most ``max_distance_rad`` and less than
    ``max_ratio`` times the second best's (dot products; -2 or less: no such candidate)."""
    angle = np.arccos(np.clip(dot_best.astype(np.float64), -1.0, 1.0))
    second = dot_second.astype(np.float64)
    angle2 = np.where(second > -1.5, np.arccos(np.clip(second, -1.0, 1.0)), np.inf)
    return (
        (dot_best > -1.5)
        & (angle <= options.max_distance_rad)
        & (angle < options.max_ratio * angle2)
    )


def match_within(
    pred: np.ndarray,
    active: np.ndarray,
    f1: Features,
    f2: Features,
    radius: float,
    options: GuidedOptions,
    grid: GridIndex | None = None,
    ratio_radius: float | None = None,
) -> tuple[np.ndarray, int]:
    """One pass: each ``active`` keypoint of image 1 against the keypoints of image 2 within
    ``radius`` pixels of its prediction ``pred`` (N1, 2); ((M, 2) matches under the rules,
    descriptors compared). ``grid``: image 2's index, built for ``radius`` when None.
    ``ratio_radius`` (>= ``radius``): the keypoints within it compete in the ratio rule (both
    ways) without being matched."""
    if grid is None:
        grid = GridIndex.build(f2, radius)
    outer = float(radius) if ratio_radius is None else max(float(ratio_radius), float(radius))
    best, dot1, dot2, col_best, col1, col2, compared = _scan_candidates(
        np.ascontiguousarray(pred, dtype=np.float64),
        np.ascontiguousarray(active, dtype=np.bool_),
        f1.descriptors,
        grid.descriptors,
        grid.points,
        grid.order,
        grid.starts,
        grid.origin[0],
        grid.origin[1],
        grid.cell,
        grid.cols,
        grid.rows,
        outer,
        float(radius),
    )
    return _select(best, dot1, dot2, col_best, col1, col2, options), int(compared)


# --------------------------------------------------------------------------- matchers


def match_brute_force(f1: Features, f2: Features, options: GuidedOptions) -> MatchResult:
    """Every keypoint of image 1 against every keypoint of image 2, the same rules (float32
    dot products in blocks of rows)."""
    t0 = time.perf_counter()
    matches = _brute_force(f1, f2, options)
    return MatchResult(
        matches,
        {
            "mode": "brute-force",
            "candidates_per_keypoint": float(len(f2)) if len(f1) else 0.0,
            "matches": len(matches),
            "time_ms": round(1e3 * (time.perf_counter() - t0), 2),
        },
    )


def _brute_force(f1: Features, f2: Features, options: GuidedOptions) -> np.ndarray:
    n1, n2 = len(f1), len(f2)
    if n1 == 0 or n2 == 0:
        return np.zeros((0, 2), dtype=np.int64)
    best = np.empty(n1, dtype=np.int64)
    dot_best = np.empty(n1, dtype=np.float32)
    dot_second = np.full(n1, -2.0, dtype=np.float32)
    col_best = np.full(n2, -1, dtype=np.int64)
    col_dot = np.full(n2, -2.0, dtype=np.float32)
    col_second = np.full(n2, -2.0, dtype=np.float32)
    d2t = np.ascontiguousarray(f2.descriptors.T)
    cols = np.arange(n2)
    for s in range(0, n1, _BRUTE_BLOCK_ROWS):
        e = min(s + _BRUTE_BLOCK_ROWS, n1)
        dots = f1.descriptors[s:e] @ d2t
        j = np.argmax(dots, axis=0)
        m = dots[j, cols]
        # the block's second best of each column, then merged with the running best two
        if e - s > 1:
            dots[j, cols] = -np.inf
            m2 = dots.max(axis=0)
            dots[j, cols] = m
        else:
            m2 = np.full(n2, -2.0, dtype=np.float32)
        better = m > col_dot
        col_second = np.where(better, np.maximum(col_dot, m2), np.maximum(col_second, m))
        col_dot[better], col_best[better] = m[better], j[better] + s
        rows = np.arange(e - s)
        b = np.argmax(dots, axis=1)
        best[s:e], dot_best[s:e] = b, dots[rows, b]
        if n2 > 1:
            dots[rows, b] = -np.inf
            dot_second[s:e] = dots.max(axis=1)
    return _select(best, dot_best, dot_second, col_best, col_dot, col_second, options)


def match_guided(
    camera1: Camera,
    pose1: Pose,
    f1: Features,
    camera2: Camera,
    pose2: Pose,
    f2: Features,
    z0: float,
    options: GuidedOptions,
    turns: tuple[int, int] = (0, 0),
) -> MatchResult:
    """Match image 1's features to image 2's guided by the rough poses (module docstring):
    both poses in one world frame (ENU metres), ``z0`` the ground's height (metres).
    ``turns``: each camera known to be turned by that many degrees (0, 90, 180, 270) about
    its optical axis (a flight's images found turned in other pairs)."""
    t0 = time.perf_counter()
    stats: dict[str, Any] = {}
    if len(f1) == 0 or len(f2) == 0:
        return _finish(np.zeros((0, 2), dtype=np.int64), "no-overlap", 0, len(f1), t0, stats)
    views = (camera1, pose1, f1, camera2, pose2, f2, z0)
    grid = f2.grid  # one for every pass of the pair (and every pair of image 2's features)
    # half the sample first: most pairs fit on it; the whole where it does not, unless the
    # half held every keypoint predicted inside already
    h = _first_pass(*views, options, options.sample_size // 2, turns, grid)
    compared = h.compared
    if not h.fits and h.overlap >= options.min_overlap and h.sampled < h.inside:
        h = _first_pass(*views, options, options.sample_size, turns, grid)
        compared += h.compared
    mode = "guided" if turns == (0, 0) else "guided-turned"
    if turns != (0, 0):
        stats["turn_deg"] = list(turns)
    stats.update({"wide_radius_px": round(h.r_wide, 1), "wide_terms": h.terms})
    stats["predicted_overlap"] = round(h.overlap, 3)
    if h.overlap < options.min_overlap:
        return _finish(np.zeros((0, 2), dtype=np.int64), "no-overlap", 0, len(f1), t0, stats)
    if not h.fits and options.try_turns:
        # an image turned after capture (or mounted otherwise than its tags say): its rough
        # rotation is off by a quarter turn or more about the optical axis
        best = None
        for turn in _TURNS:
            if turn == turns:
                continue
            t = _first_pass(*views, options, options.turn_sample_size, turn, grid)
            compared += t.compared
            if t.fits and (best is None or t.support > best.support):
                best = t
            if t.fits and t.support >= max(2 * options.min_support, t.matches // 2):
                break  # half the matches move alike: no other turn comes close
        if best is not None:
            h, mode = best, "guided-turned"
            stats["turn_deg"] = list(best.turn)
    if not h.fits and options.search_rotation:
        # a yaw off by more than the turns absorb (an attitude estimated from the track): the
        # keypoints' orientations over a sample matched by brute force give the rotation
        rotated = _rotation_pass(*views, options)
        if rotated is not None:
            compared += rotated.compared
            if rotated.fits:
                h, mode = rotated, "guided-rotated"
                stats["turn_deg"] = [round(float(t), 1) for t in rotated.turn]
    stats["first_pass"] = {
        "sampled": h.sampled,
        "matches": h.matches,
        "support": h.support,
    }
    centre = np.array([[camera2.cx, camera2.cy]])
    stats["offset_px"] = [round(float(v), 1) for v in (apply_motion(h.motion, centre) - centre)[0]]
    stats["motion_linear"] = [[round(float(v), 4) for v in row] for row in h.motion[:, :2]]
    stats["tight_radius_px"] = round(h.r_tight, 1)
    stats["search_radius_px"] = round(h.r_search, 1)
    if not h.fits:
        if not options.brute_force_on_mismatch:
            return _finish(
                np.zeros((0, 2), np.int64), "pose-mismatch-unmatched", compared, len(f1), t0, stats
            )
        matches = _brute_force(f1, f2, options)
        compared += len(f1) * len(f2)
        return _finish(matches, "pose-mismatch", compared, len(f1), t0, stats)

    # second pass: every keypoint, the search radius around the moved prediction
    moved = apply_motion(h.motion, h.pred)
    active = h.valid & _in_frame(moved, camera2, h.r_search)
    ratio_radius = max(options.ratio_radius_factor * h.r_tight, options.ratio_radius_min_px)
    matches, second = match_within(moved, active, f1, f2, h.r_search, options, grid, ratio_radius)
    return _finish(matches, mode, compared + second, len(f1), t0, stats)


#: The turns (degrees about each camera's optical axis, image 1 and image 2) tried when the
#: rough poses as given do not fit; half turns first (an image stored upside down, a camera
#: mounted facing backward), then the rest.
_TURNS = ((0, 180), (180, 0), (180, 180)) + tuple(
    (a, b)
    for a in (0, 90, 180, 270)
    for b in (0, 90, 180, 270)
    if (a, b) not in ((0, 0), (0, 180), (180, 0), (180, 180))
)


@dataclass(frozen=True)
class _FirstPass:
    """A first pass under one hypothesis of the cameras' turns: the predictions, the wide
    radius, the predicted overlap, the keypoints the sample was drawn from and the sample's
    size, the matches found, the motion ((2, 3) affine of the predictions), tight and search
    radii and support (by default: none sampled, nothing found)."""

    turn: tuple[float, float]
    pred: np.ndarray
    valid: np.ndarray
    r_wide: float
    terms: dict[str, float]
    overlap: float
    inside: int
    sampled: int = 0
    matches: int = 0
    compared: int = 0
    motion: np.ndarray = field(default_factory=lambda: np.eye(2, 3))
    r_tight: float = 0.0
    r_search: float = 0.0
    support: int = 0
    fits: bool = False


def _turned(pose: Pose, degrees: float) -> Pose:
    """The camera turned by ``degrees`` about its optical axis."""
    return pose if degrees == 0 else Pose(rot_z(degrees) @ pose.R_world_to_cam, pose.center)


def _first_pass(
    camera1: Camera,
    pose1: Pose,
    f1: Features,
    camera2: Camera,
    pose2: Pose,
    f2: Features,
    z0: float,
    options: GuidedOptions,
    sample_size: int,
    turn: tuple[float, float] = (0, 0),
    grid: GridIndex | None = None,
) -> _FirstPass:
    """A sample of the keypoints predicted inside image 2 matched within the wide radius."""
    p1, p2 = _turned(pose1, turn[0]), _turned(pose2, turn[1])
    pred, valid = predict_in_image2(camera1, p1, f1.keypoints, camera2, p2, z0)
    r_wide, terms = wide_radius_px(camera2, p1, p2, z0, options)
    inside = valid & _in_frame(pred, camera2, r_wide)
    overlap = float(inside.mean()) if len(inside) else 0.0
    if overlap < options.min_overlap:
        return _FirstPass(turn, pred, valid, r_wide, terms, overlap, int(inside.sum()))
    candidates = np.flatnonzero(inside)
    step = max(1, len(candidates) // sample_size)
    sample = np.zeros(len(f1), dtype=np.bool_)
    sample[candidates[::step][:sample_size]] = True
    first, compared = match_within(pred, sample, f1, f2, r_wide, options, grid)
    motion, r_tight, r_search, support = _consistent_motion(
        pred, f2.keypoints, first, r_wide, options
    )
    fits = support >= options.min_support and support >= options.min_support_fraction * len(first)
    return _FirstPass(
        turn,
        pred,
        valid,
        r_wide,
        terms,
        overlap,
        len(candidates),
        sampled=int(sample.sum()),
        matches=len(first),
        compared=compared,
        motion=motion,
        r_tight=r_tight,
        r_search=r_search,
        support=support,
        fits=fits,
    )


def _rotation_pass(
    camera1: Camera,
    pose1: Pose,
    f1: Features,
    camera2: Camera,
    pose2: Pose,
    f2: Features,
    z0: float,
    options: GuidedOptions,
) -> _FirstPass | None:
    """A first pass for a yaw off by any angle: ``turn_sample_size`` keypoints of image 1
    matched by brute force (distance and ratio rules); the peak of their orientation
    changes (image 2's keypoint's less image 1's, within ``rotation_window_deg``) is the
    rotation from image 1 to image 2; camera 2 is turned about its optical axis so that the
    poses predict it, and the matches that agree with it give the motion, as a first pass's.
    None without orientations or matches."""
    if f1.orientations is None or f2.orientations is None:
        return None
    known = np.flatnonzero(np.isfinite(f1.orientations))
    if len(known) == 0 or len(f2) < 2:
        return None
    idx = known[:: max(1, len(known) // options.turn_sample_size)][: options.turn_sample_size]
    sample = Features(f1.keypoints[idx], f1.descriptors[idx])
    found = _brute_force(sample, f2, with_options(options, cross_check=False))
    compared = len(idx) * len(f2)
    if len(found) < options.min_support:
        return None
    change = np.degrees(f2.orientations[found[:, 1]] - f1.orientations[idx[found[:, 0]]])
    change = change[np.isfinite(change)] % 360.0
    if len(change) < options.min_support:
        return None
    window = options.rotation_window_deg
    bins = np.histogram(change, bins=int(round(360 / window)), range=(0.0, 360.0))[0]
    bins = bins + np.roll(bins, 1) + np.roll(bins, -1)  # circular, a window either side
    centre = (np.argmax(bins) + 0.5) * window
    near = np.abs((change - centre + 180.0) % 360.0 - 180.0) <= window
    if not near.any():
        return None
    rotation = centre + float(np.mean((change[near] - centre + 180.0) % 360.0 - 180.0))
    # camera 2 turned so that the poses predict that rotation between the images
    probe = np.array([[camera1.cx, camera1.cy], [camera1.cx + 100.0, camera1.cy]])
    turn = 0.0
    for _ in range(2):  # the predicted rotation is near linear in the turn: twice suffices
        p, ok = predict_in_image2(camera1, pose1, probe, camera2, _turned(pose2, turn), z0)
        if not ok.all():
            return None
        predicted = math.degrees(math.atan2(*(p[1] - p[0])[::-1]))
        turn += (rotation - predicted + 180.0) % 360.0 - 180.0
    turned2 = _turned(pose2, turn)
    pred, valid = predict_in_image2(camera1, pose1, f1.keypoints, camera2, turned2, z0)
    r_wide, terms = wide_radius_px(camera2, pose1, turned2, z0, options)
    agree = np.flatnonzero(np.isfinite(f2.orientations[found[:, 1]]))
    agree = agree[
        np.abs(
            (
                np.degrees(f2.orientations[found[agree, 1]] - f1.orientations[idx[found[agree, 0]]])
                - rotation
                + 180.0
            )
            % 360.0
            - 180.0
        )
        <= window
    ]
    first = np.column_stack((idx[found[agree, 0]], found[agree, 1]))
    first = first[valid[first[:, 0]]]
    motion, r_tight, r_search, support = _consistent_motion(
        pred, f2.keypoints, first, r_wide, options
    )
    fits = support >= options.min_support and support >= options.min_support_fraction * len(first)
    moved = apply_motion(motion, pred)
    overlap = float((valid & _in_frame(moved, camera2, 0.0)).mean())
    return _FirstPass(
        (0.0, turn),
        pred,
        valid,
        r_wide,
        terms,
        overlap,
        len(known),
        len(idx),
        len(first),
        compared,
        motion,
        r_tight,
        r_search,
        support,
        fits and overlap >= options.min_overlap,
    )


def _in_frame(pixels: np.ndarray, camera: Camera, margin: float) -> np.ndarray:
    x, y = pixels[:, 0], pixels[:, 1]
    return (
        (x >= -margin)
        & (x <= camera.width - 1 + margin)
        & (y >= -margin)
        & (y <= camera.height - 1 + margin)
    )


#: The first pass's motion model: an affine map of the predictions (6 parameters), fitted
#: where at least this many matches per parameter lie near it; fewer keep the shift.
_AFFINE_PARAMS = 6
_MATCHES_PER_PARAM = 3
#: The second pass's search radius holds at least this share of the first pass's matches
#: within the cap (relief: a building's parallax is no part of the motion).
SEARCH_SHARE = 0.95
#: Least-squares rounds of the affine fit, each on the matches within the tight radius of
#: the last model.
_AFFINE_ROUNDS = 2


def apply_motion(motion: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) predictions moved by a (2, 3) affine ``motion``: ``[A | t]``, ``A p + t``."""
    return pixels @ motion[:, :2].T + motion[:, 2]


def _consistent_motion(
    pred: np.ndarray,
    points2: np.ndarray,
    first: np.ndarray,
    r_wide: float,
    options: GuidedOptions,
) -> tuple[np.ndarray, float, float, int]:
    """The first pass's consistent motion of the predictions ((2, 3) affine, pixels), the
    tight radius, the search radius (:data:`SEARCH_SHARE`) and the support: the first-pass
    matches within the tight radius of the motion. The median offset (re-taken over the
    offsets within the cap: a quarter of the wide radius) starts it as a shift; then, with
    enough matches near it and the tight radius above its least, an affine map fitted by
    least squares to the matches within the tight radius, ``_AFFINE_ROUNDS`` times."""
    cap = max(0.25 * r_wide, options.tight_min_px)
    motion = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    if len(first) == 0:
        return motion, cap, cap, 0
    src, dst = pred[first[:, 0]], points2[first[:, 1]]
    offsets = dst - src
    shift = np.median(offsets, axis=0)
    near = np.hypot(*(offsets - shift).T) <= cap
    if near.any():
        shift = np.median(offsets[near], axis=0)
    motion[:, 2] = shift

    def tight(residual: np.ndarray) -> float:
        within = residual <= cap
        spread = float(np.median(residual[within])) if within.any() else cap
        return float(np.clip(3.0 * spread, options.tight_min_px, cap))

    residual = np.hypot(*(dst - apply_motion(motion, src)).T)
    r_tight = tight(residual)
    for _ in range(_AFFINE_ROUNDS):
        use = residual <= r_tight
        if r_tight <= options.tight_min_px or use.sum() < _MATCHES_PER_PARAM * _AFFINE_PARAMS:
            break  # the radius at its least already, or too few matches for the fit
        x = np.column_stack((src[use] - src[use].mean(axis=0), np.ones(int(use.sum()))))
        try:  # the normal equations (3 x 3) of the least squares, centred for their condition
            fitted = np.linalg.solve(x.T @ x, x.T @ dst[use]).T
        except np.linalg.LinAlgError:
            break  # the matches on a line
        fitted[:, 2] -= fitted[:, :2] @ src[use].mean(axis=0)
        fitted_residual = np.hypot(*(dst - apply_motion(fitted, src)).T)
        if tight(fitted_residual) > r_tight:
            break  # a worse fit than the last (matches far from the rest): keep the last
        motion, residual = fitted, fitted_residual
        r_tight = tight(residual)
    within = residual[residual <= cap]
    held = float(np.quantile(within, SEARCH_SHARE)) if len(within) else cap
    r_search = float(np.clip(held, r_tight, cap))
    return motion, r_tight, r_search, int((residual <= r_tight).sum())


def _finish(
    matches: np.ndarray, mode: str, compared: int, n1: int, t0: float, stats: dict[str, Any]
) -> MatchResult:
    stats.update(
        {
            "mode": mode,
            "candidates_per_keypoint": round(compared / n1, 2) if n1 else 0.0,
            "matches": len(matches),
            "time_ms": round(1e3 * (time.perf_counter() - t0), 2),
        }
    )
    return MatchResult(matches, stats)
