"""A simulated GPS-only flight as a COLMAP database, with exact truth: what ``hmcc match``
meets on a compact camera with a GPS tag and no attitude, whose real yaw is off the flight
track's by a different amount in every image.

* **Flight**: ``strips`` strips flown east and west in turn (a serpentine),
  ``per_strip`` exposures each, :data:`SPACING_M` apart along a strip and :data:`STRIP_M`
  across, :data:`HEIGHT_M` above a ground with a metre or two of relief.
* **Cameras**: one PINHOLE camera (:data:`CAM`); each image nadir within a couple of degrees
  (pitch and roll), its yaw the direction of travel plus its own error, drawn uniformly in
  +-``yaw_error_deg``.
* **POS**: an ODM ``geo.txt`` of positions only (:data:`GPS_SIGMA_M` of noise
  horizontally, a metre vertically), so the attitude comes from the flight track; with
  ``gps_lag_m`` every position that far behind the camera along its track (a fix recorded
  late: a strip flown the other way is off the other way).
* **Features**: ground points, each with a SIFT-like descriptor (non-negative, uint8 unit
  rows as COLMAP's) and a direction on the ground; an image detects the points it sees with
  probability 0.8, each keypoint 0.5 px off, its descriptor a noisy copy and its orientation
  the ground direction as the image sees it (4 deg of noise), in COLMAP's affine shape;
  15 % clutter keypoints of no point.

:func:`gps_flight_db` writes the database and the ``geo.txt`` and returns the truth: each
pair's true correspondences (keypoint indices sharing a ground point); :func:`stored_matches`
reads back what a run wrote (the matches, or the verified inliers).
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from hmcc.camera import Camera
from hmcc.guided import project_points
from hmcc.pose import Pose, rotation_from_yaw_pitch_roll

__all__ = ["CAM", "HEIGHT_M", "GpsFlight", "gps_flight_db"]

#: A compact camera's stored image at 1600 x 1200 px, about 62 deg across.
CAM = Camera(width=1600, height=1200, fx=1330.0, fy=1330.0, cx=799.5, cy=599.5)
HEIGHT_M = 62.0
#: Exposures along a strip (m): the footprint is 56 x 75 m, image top along the track.
SPACING_M = 14.0
STRIP_M = 40.0
GPS_SIGMA_M = 1.5
_DENSITY_PER_M2 = 0.75
_DETECT = 0.8
_CLUTTER = 0.15


@dataclass(frozen=True)
class GpsFlight:
    """The database's images (``names`` in capture order, ``image_ids`` theirs), the
    ``geo.txt`` path, each image's true pose and yaw error against its direction of travel
    (degrees), and ``truth[(id1, id2)]``: (K, 2) true correspondences of the pair (id1 <
    id2, indices into each image's keypoints)."""

    database: Path
    geo: Path
    names: list[str]
    image_ids: list[int]
    poses: list[Pose]
    yaw_errors_deg: np.ndarray
    truth: dict[tuple[int, int], np.ndarray]


def _ground_z(xy: np.ndarray) -> np.ndarray:
    return 1.5 * np.sin(xy[:, 0] / 30.0) * np.cos(xy[:, 1] / 25.0)


def gps_flight_db(
    folder: Path,
    seed: int,
    yaw_error_deg: float,
    strips: int = 3,
    per_strip: int = 10,
    gps_lag_m: float = 0.0,
) -> GpsFlight:
    """Write ``folder/flight.db`` and ``folder/geo.txt`` (module docstring)."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    length = (per_strip - 1) * SPACING_M
    lo, hi = np.array([-60.0, -60.0]), np.array([length + 60.0, (strips - 1) * STRIP_M + 60.0])
    n = int(_DENSITY_PER_M2 * np.prod(hi - lo))
    xy = rng.uniform(lo, hi, (n, 2))
    world = np.column_stack((xy, _ground_z(xy)))
    heading = rng.uniform(0.0, 2 * np.pi, n)  # each point's direction on the ground
    ahead = world + 0.3 * np.column_stack((np.cos(heading), np.sin(heading), np.zeros(n)))
    base = np.abs(rng.normal(size=(n, 128)))

    names: list[str] = []
    poses: list[Pose] = []
    errors: list[float] = []
    ids: list[tuple[int, np.ndarray]] = []
    lines = ["EPSG:32614"]
    for s in range(strips):
        east = s % 2 == 0
        for k in range(per_strip):
            x = k * SPACING_M if east else length - k * SPACING_M
            centre = np.array([x, s * STRIP_M, HEIGHT_M])
            error = rng.uniform(-yaw_error_deg, yaw_error_deg)
            yaw = (90.0 if east else 270.0) + error  # clockwise from north
            pitch, roll = rng.normal(scale=1.5, size=2)
            poses.append(Pose(rotation_from_yaw_pitch_roll(yaw, pitch, roll), centre))
            errors.append(error)
            name = f"img_{len(names):03d}.jpg"
            names.append(name)
            gps = centre + np.array([*rng.normal(scale=GPS_SIGMA_M, size=2), rng.normal()])
            gps[0] -= gps_lag_m if east else -gps_lag_m
            lines.append(f"{name} {gps[0]:.3f} {gps[1]:.3f} {gps[2]:.3f}")
    geo = folder / "geo.txt"
    geo.write_text("\n".join(lines) + "\n")

    database = folder / "flight.db"
    database.unlink(missing_ok=True)
    db = pycolmap.Database.open(str(database))
    try:
        camera = pycolmap.Camera(
            model="PINHOLE",
            width=CAM.width,
            height=CAM.height,
            params=[CAM.fx, CAM.fy, CAM.cx + 0.5, CAM.cy + 0.5],
        )
        camera_id = db.write_camera(camera)
        for name, pose in zip(names, poses, strict=True):
            px, front = project_points(CAM, pose, world)
            tip, _ = project_points(CAM, pose, ahead)
            seen = front & CAM.in_frame(px) & (rng.uniform(size=n) < _DETECT)
            seen &= (px >= 0).all(axis=1) & (px[:, 0] <= CAM.width - 1)
            seen &= px[:, 1] <= CAM.height - 1
            keep = np.flatnonzero(seen)
            kps = px[keep] + rng.normal(scale=0.5, size=(len(keep), 2))
            d = tip[keep] - px[keep]
            angle = np.arctan2(d[:, 1], d[:, 0]) + np.radians(rng.normal(scale=4.0, size=len(keep)))
            desc = base[keep] + np.abs(rng.normal(scale=0.3, size=(len(keep), 128)))
            m = int(_CLUTTER * len(keep))
            kps = np.vstack((kps, rng.uniform((0, 0), (CAM.width - 1, CAM.height - 1), (m, 2))))
            angle = np.concatenate((angle, rng.uniform(-np.pi, np.pi, m)))
            desc = np.vstack((desc, np.abs(rng.normal(size=(m, 128)))))
            points = np.concatenate((keep, np.full(m, -1)))
            order = rng.permutation(len(kps))
            kps, angle, desc, points = kps[order], angle[order], desc[order], points[order]
            scale = rng.uniform(1.5, 6.0, len(kps))
            c, s_ = scale * np.cos(angle), scale * np.sin(angle)
            rows = np.column_stack((kps + 0.5, c, -s_, s_, c)).astype(np.float32)
            unit = desc / np.linalg.norm(desc, axis=1, keepdims=True)
            image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
            db.write_keypoints(image_id, rows)
            data = np.clip(np.round(512 * unit), 0, 255).astype(np.uint8)
            db.write_descriptors(
                image_id, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, data)
            )
            ids.append((int(image_id), points))
    finally:
        db.close()

    truth: dict[tuple[int, int], np.ndarray] = {}
    for a, (id_a, pts_a) in enumerate(ids):
        where_a = {int(p): i for i, p in enumerate(pts_a) if p >= 0}
        for id_b, pts_b in ids[a + 1 :]:
            pairs = [(where_a[int(p)], j) for j, p in enumerate(pts_b) if int(p) in where_a]
            key = (id_a, id_b) if id_a < id_b else (id_b, id_a)
            arr = np.array(pairs, dtype=np.int64).reshape(-1, 2)
            truth[key] = arr if id_a < id_b else arr[:, ::-1]
    return GpsFlight(database, geo, names, [i for i, _ in ids], poses, np.array(errors), truth)


def stored_matches(path: Path, verified: bool = False) -> dict[tuple[int, int], np.ndarray]:
    """The matches stored in the COLMAP database at ``path`` (``verified``: the inlier
    matches of its two-view geometries): (image id 1, image id 2) -> its (M, 2) int64
    keypoint indices."""
    table = "two_view_geometries" if verified else "matches"
    con = sqlite3.connect(path)
    try:
        rows = con.execute(f"SELECT pair_id, rows, data FROM {table}").fetchall()
    finally:
        con.close()
    out = {}
    for pair_id, n, data in rows:
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        m = np.frombuffer(data, dtype=np.uint32).reshape(n, 2) if n else np.zeros((0, 2))
        out[(int(a), int(b))] = m.astype(np.int64)
    return out
