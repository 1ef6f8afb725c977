"""A simulated UAV flight with exact ground truth: a penta-view block like the paper's dataset 3
(750 images, 18 283 pairs), every image's keypoints once, every pair's candidate matches.

The model (terrain, cameras, rough POS, noise) is :mod:`hmcc.simulate`'s; what a flight adds:

* **Stations** on ``strips`` parallel strips flown north and south in turn (a serpentine),
  ``stations_per_strip`` exposures each, spaced for ``forward_overlap`` / ``side_overlap`` of a
  nadir footprint; each station carries the cameras of ``views`` (a penta-view rig: nadir and
  four 45 deg obliques), all sharing the station's platform pose. The rough POS is per station:
  GNSS and IMU noise are the same for its cameras (the mountings are exact).
* **Features**: terrain points spread uniformly over the block; an image detects the points it
  sees (in front, in the frame; occlusion ignored), at most ``keypoints_per_image`` of them
  (a random subset), with ``keypoint_noise_px`` of noise. Keypoints are [x, y] pixels.
* **Pairs**: the ``pairs`` image pairs sharing the most detected points (the paper selects
  pairs by footprint overlap). A shared point becomes a candidate match with probability
  ``match_rate`` (descriptor matching misses the rest); outliers then join at
  ``outlier_ratio``: random keypoints of both images, redrawn when within
  max(3 px, 6 x noise) of their true epipolar line.

Everything is drawn from ``numpy.random.default_rng(seed)``; the result is deterministic. Arrays
stay arrays (a flight holds millions of matches): :func:`simulate_flight` returns a flight body
(``images`` with keypoints, ``pairs`` with matches, ``plane``) whose arrays are ndarrays, and
each pair's true match indices.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np
from annotated_types import Ge, Gt, Interval
from scipy import sparse

from .bounds import check_fields
from .pose import rotation_from_yaw_pitch_roll
from .simulate import MOUNTINGS, View, make_terrain, terrain_height

__all__ = ["FlightOptions", "SimulatedFlight", "simulate_flight"]

_MIN_EPIPOLAR_PX = 3.0
_REDRAW_ROUNDS = 20


@dataclass(frozen=True)
class FlightOptions:
    """A simulated flight (see the module docstring); metres, degrees, pixels. The defaults
    give the paper's dataset 3: 150 stations x 5 cameras at 300 m, 18 283 pairs."""

    strips: Annotated[int, Ge(1)] = 10
    stations_per_strip: Annotated[int, Ge(1)] = 15
    views: tuple[View, ...] = ("V", "F", "B", "L", "R")
    altitude_m: Annotated[float, Gt(0.0)] = 300.0
    ground_height_m: float = 0.0
    relief_m: Annotated[float, Ge(0.0)] = 15.0
    building_fraction: Annotated[float, Interval(ge=0.0, le=1.0)] = 0.2
    building_height_m: tuple[float, float] = (5.0, 30.0)
    forward_overlap: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.7
    side_overlap: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.6
    width_px: Annotated[int, Ge(2)] = 6000
    height_px: Annotated[int, Ge(2)] = 4000
    focal_px: Annotated[float, Gt(0.0)] = 4000.0
    keypoints_per_image: Annotated[int, Ge(8)] = 2900
    match_rate: Annotated[float, Interval(gt=0.0, le=1.0)] = 0.85
    pairs: Annotated[int, Ge(1)] = 18_283
    outlier_ratio: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.5
    keypoint_noise_px: Annotated[float, Ge(0.0)] = 0.5
    gnss_sigma_m: tuple[float, float] = (1.5, 3.0)
    imu_sigma_deg: tuple[float, float, float] = (2.0, 1.0, 1.0)
    platform_attitude_sigma_deg: Annotated[float, Interval(ge=0.0, le=30.0)] = 2.0

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass
class SimulatedFlight:
    """``body``: the flight (``images``: name -> {camera, pose, keypoints (N, 2) ndarray},
    ``pairs``: [{id, image1, image2, matches (M, 2) int32 ndarray}], ``plane``); ``truth``:
    pair id -> sorted indices of its true matches; ``stations`` and ``views`` per image."""

    body: dict[str, Any]
    truth: dict[str, np.ndarray]
    image_views: dict[str, str] = field(default_factory=dict)

    @property
    def matches(self) -> int:
        return int(sum(len(p["matches"]) for p in self.body["pairs"]))


def _footprint_steps(o: FlightOptions) -> tuple[float, float]:
    """Metres between exposures along a strip and between strips (nadir footprint: image
    height along the track, width across it)."""
    along = o.altitude_m * o.height_px / o.focal_px
    across = o.altitude_m * o.width_px / o.focal_px
    return (1.0 - o.forward_overlap) * along, (1.0 - o.side_overlap) * across


def simulate_flight(options: FlightOptions, seed: int) -> SimulatedFlight:
    """Simulate a flight; see the module docstring."""
    o = options
    rng = np.random.default_rng(seed)
    terrain = make_terrain(
        o.ground_height_m, o.relief_m, o.building_fraction, o.building_height_m, rng
    )
    K = np.array(
        [[o.focal_px, 0, (o.width_px - 1) / 2], [0, o.focal_px, (o.height_px - 1) / 2], [0, 0, 1.0]]
    )
    step, spacing = _footprint_steps(o)
    z = o.ground_height_m + o.altitude_m

    # Stations (serpentine), true and rough platform poses; cameras.
    names, views, rotations, centres, rough = [], [], [], [], []
    for s in range(o.strips):
        north = s % 2 == 0
        heading = 0.0 if north else 180.0
        for t in range(o.stations_per_strip):
            along = t if north else o.stations_per_strip - 1 - t
            position = np.array([s * spacing, along * step, z])
            wobble = rng.normal(0.0, o.platform_attitude_sigma_deg, 2)
            attitude = (heading, float(wobble[0]), float(wobble[1]))
            noise = rng.normal(0.0, 1.0, 6)
            gnss = noise[:3] * np.array([o.gnss_sigma_m[0], o.gnss_sigma_m[0], o.gnss_sigma_m[1]])
            imu = noise[3:] * np.asarray(o.imu_sigma_deg)
            rough_position = position + gnss
            rough_attitude = tuple(float(a + d) for a, d in zip(attitude, imu, strict=True))
            for view in o.views:
                names.append(f"s{s:02d}_{t:02d}{view}")
                views.append(view)
                rotations.append(rotation_from_yaw_pitch_roll(*attitude, mounting=MOUNTINGS[view]))
                centres.append(position)
                rough.append((rough_position, rough_attitude, view))

    # Terrain points over the block and its margins (obliques look out by the altitude).
    margin = 1.5 * o.altitude_m
    lo = np.array([-margin, -margin])
    hi = np.array([(o.strips - 1) * spacing + margin, (o.stations_per_strip - 1) * step + margin])
    footprint = (o.altitude_m * o.width_px / o.focal_px) * (o.altitude_m * o.height_px / o.focal_px)
    density = 1.3 * o.keypoints_per_image / footprint
    n_points = int(density * np.prod(hi - lo))
    xy = rng.uniform(lo, hi, (n_points, 2))
    order = np.argsort(xy[:, 0], kind="stable")
    xy = xy[order]
    points = np.column_stack((xy, terrain_height(terrain, xy)))

    # Each image: the points it sees, at most keypoints_per_image of them.
    detected: list[np.ndarray] = []
    keypoints: list[np.ndarray] = []
    for R, C in zip(rotations, centres, strict=True):
        x0, x1, y0, y1 = _ground_box(K, R, C, o)
        first, last = np.searchsorted(points[:, 0], [x0, x1])
        idx = first + np.flatnonzero((points[first:last, 1] >= y0) & (points[first:last, 1] <= y1))
        cam = (points[idx] - C) @ R.T
        depth = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            px = (cam[:, :2] / depth[:, None]) @ K[:2, :2].T + K[:2, 2]
        seen = (
            (depth > 0)
            & (px[:, 0] >= 0)
            & (px[:, 0] <= o.width_px - 1)
            & (px[:, 1] >= 0)
            & (px[:, 1] <= o.height_px - 1)
        )
        idx, px = idx[seen], px[seen]
        if len(idx) > o.keypoints_per_image:
            chosen = np.sort(rng.choice(len(idx), o.keypoints_per_image, replace=False))
            idx, px = idx[chosen], px[chosen]
        px = px + rng.normal(0.0, o.keypoint_noise_px, px.shape)
        inside = (
            (px[:, 0] >= 0)
            & (px[:, 0] <= o.width_px - 1)
            & (px[:, 1] >= 0)
            & (px[:, 1] <= o.height_px - 1)
        )
        detected.append(idx[inside])  # ascending point ids, one per keypoint
        keypoints.append(px[inside])

    # The pairs sharing the most points.
    n_images = len(names)
    incidence = sparse.csr_matrix(
        (
            np.ones(sum(len(d) for d in detected)),
            (np.repeat(np.arange(n_images), [len(d) for d in detected]), np.concatenate(detected)),
        ),
        shape=(n_images, n_points),
    )
    shared = (incidence @ incidence.T).toarray()
    i_up, j_up = np.triu_indices(n_images, k=1)
    counts = shared[i_up, j_up]
    best = np.argsort(-counts, kind="stable")[: o.pairs]
    best = best[counts[best] > 0]

    pairs, truth = [], {}
    min_px = max(_MIN_EPIPOLAR_PX, 6.0 * o.keypoint_noise_px)
    for k in np.sort(best):
        a, b = int(i_up[k]), int(j_up[k])
        _, ia, ib = np.intersect1d(
            detected[a], detected[b], assume_unique=True, return_indices=True
        )
        keep = rng.random(len(ia)) < o.match_rate
        true = np.column_stack((ia[keep], ib[keep]))
        n_out = int(round(len(true) * o.outlier_ratio / (1.0 - o.outlier_ratio)))
        F = _fundamental(K, rotations[a], centres[a], rotations[b], centres[b])
        out = _outliers(n_out, keypoints[a], keypoints[b], detected[a], detected[b], F, min_px, rng)
        matches = np.concatenate((true, out)).astype(np.int32)
        shuffle = rng.permutation(len(matches))
        pair_id = f"{names[a]}-{names[b]}"
        pairs.append(
            {"id": pair_id, "image1": names[a], "image2": names[b], "matches": matches[shuffle]}
        )
        truth[pair_id] = np.sort(np.flatnonzero(shuffle < len(true)))

    camera = {"width": o.width_px, "height": o.height_px, "focal": o.focal_px}
    images = {}
    for name, kps, (xyz, ypr, view) in zip(names, keypoints, rough, strict=True):
        pose: dict[str, Any] = {
            "position": {"x": float(xyz[0]), "y": float(xyz[1]), "z": float(xyz[2])},
            "attitude": {"yaw": ypr[0] % 360.0, "pitch": ypr[1], "roll": ypr[2]},
        }
        if view != "V":
            y, p, r = MOUNTINGS[view]
            pose["mounting"] = {"yaw": y, "pitch": p, "roll": r}
        images[name] = {"camera": camera, "pose": pose, "keypoints": kps}
    body = {"images": images, "pairs": pairs, "plane": {"ground_z": o.ground_height_m}}
    return SimulatedFlight(body, truth, dict(zip(names, views, strict=True)))


def _ground_box(
    K: np.ndarray, R: np.ndarray, C: np.ndarray, o: FlightOptions
) -> tuple[float, float, float, float]:
    """x/y bounds of where the image's rays meet the terrain's range of heights (corners, with
    rays above the horizon clipped at a few flying heights)."""
    w, h = o.width_px - 1, o.height_px - 1
    corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], dtype=float)
    rays = (np.linalg.inv(K) @ corners.T).T @ R  # world directions
    top = o.ground_height_m + o.relief_m + o.building_height_m[1]
    xs, ys = [], []
    for zz in (o.ground_height_m - o.relief_m, top):
        down = np.minimum(rays[:, 2], -0.2)  # rays near the horizon: clip their reach
        t = (zz - C[2]) / down
        xs.extend(C[0] + t * rays[:, 0])
        ys.extend(C[1] + t * rays[:, 1])
    return min(xs), max(xs), min(ys), max(ys)


def _fundamental(
    K: np.ndarray, R1: np.ndarray, C1: np.ndarray, R2: np.ndarray, C2: np.ndarray
) -> np.ndarray:
    R = R2 @ R1.T
    t = R2 @ (C1 - C2)
    skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Kinv = np.linalg.inv(K)
    return Kinv.T @ skew @ R @ Kinv


def _outliers(
    n: int,
    kp1: np.ndarray,
    kp2: np.ndarray,
    ids1: np.ndarray,
    ids2: np.ndarray,
    F: np.ndarray,
    min_px: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """(n, 2) random keypoint pairs that are not a true correspondence and lie further than
    ``min_px`` from their true epipolar lines in both images (redrawn otherwise)."""
    out = np.zeros((0, 2), dtype=np.int64)
    for _ in range(_REDRAW_ROUNDS):
        need = n - len(out)
        if need <= 0:
            break
        a = rng.integers(0, len(kp1), 2 * need)
        b = rng.integers(0, len(kp2), 2 * need)
        ok = (ids1[a] != ids2[b]) & (_epipolar_min_distance(F, kp1[a], kp2[b]) > min_px)
        out = np.concatenate((out, np.column_stack((a[ok], b[ok]))[:need]))
    return out[:n]


def _epipolar_min_distance(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    h1 = np.column_stack((p1, np.ones(len(p1))))
    h2 = np.column_stack((p2, np.ones(len(p2))))
    l2 = h1 @ F.T
    l1 = h2 @ F
    r = np.abs((h2 * l2).sum(axis=1))
    d2 = r / np.maximum(np.hypot(l2[:, 0], l2[:, 1]), 1e-300)
    d1 = r / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-300)
    return np.minimum(d1, d2)
