"""A COLMAP database (COLMAP >= 4 schema) in our conventions, and verified geometries back.

Pixels: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), we (OpenCV) at (0, 0).
Keypoints and principal points are shifted by -0.5 on the way in; a fundamental matrix is
taken back to COLMAP's pixels on the way out (``F_colmap = T^T F T``, ``T`` the shift).

Pairs: COLMAP stores a pair once, under ``pair_id`` of ``(image_id1, image_id2)`` with
``image_id1 < image_id2``, its matches' columns in that order. We read and write every pair in
that order, so nothing is swapped (pycolmap's ``read_matches`` and ``write_two_view_geometry``
would swap for the other order).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from .errors import ColmapInputError

__all__ = [
    "PIXEL_OFFSET",
    "SUPPORTED_MODELS",
    "ColmapDatabase",
    "Geometry",
    "ImageInfo",
    "PriorFill",
    "Snapshot",
    "check_database",
    "fundamental_to_colmap",
    "read_snapshot",
    "snapshot_features",
    "snapshot_orientations",
    "snapshot_keypoints",
]

#: COLMAP's pixel coordinates minus ours.
PIXEL_OFFSET = 0.5
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
_TABLES = ("cameras", "images", "keypoints", "matches", "two_view_geometries")
_COLMAP4_TABLES = ("rigs", "frames")


def check_database(path: Path) -> None:
    """Refuse, without touching it, what is not a COLMAP >= 4 database (read-only look)."""
    with _read_only(path) as con:
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    missing = [t for t in _TABLES if t not in tables]
    if missing:
        raise ColmapInputError(f"{path}: not a COLMAP database (no table {', '.join(missing)})")
    if any(t not in tables for t in _COLMAP4_TABLES):
        raise ColmapInputError(
            f"{path}: a database of COLMAP < 4 (no rigs/frames tables); hmcc colmap reads the "
            "COLMAP >= 4 schema: extract and match with COLMAP >= 4 (pycolmap >= 4)"
        )


#: How much of the database a read-only connection maps (SQLite's ``mmap_size``).
_READ_MAP_BYTES = 1 << 30


@contextmanager
def _read_only(path: Path) -> Iterator[sqlite3.Connection]:
    if not path.is_file():
        raise ColmapInputError(f"{path}: no such database file")
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.DatabaseError as e:
        raise ColmapInputError(f"{path}: cannot open it ({e})") from None
    try:
        # the blobs read from the mapped file rather than copied page by page: the 18 Brighton
        # images' keypoints (5 MB) in 2.2 ms instead of 3.4
        con.execute(f"PRAGMA mmap_size = {_READ_MAP_BYTES}")
        yield con
    except sqlite3.DatabaseError as e:
        raise ColmapInputError(f"{path}: not an SQLite database ({e})") from None
    finally:
        con.close()


@dataclass(frozen=True)
class Snapshot:
    """What a run checks before it opens the database for writing, read through a read-only
    SQLite connection (pycolmap's ``Database.open`` writes to the file even when it changes
    nothing): the images with their cameras, the matched pairs ``(id1, id2, matches)`` and
    the pairs that have a geometry already."""

    images: list[ImageInfo]
    matched: list[tuple[int, int, int]]
    verified: set[tuple[int, int]]


def read_snapshot(path: Path) -> Snapshot:
    """The :class:`Snapshot` of a COLMAP >= 4 database; :class:`ColmapInputError` for
    anything else, and for a camera model other than :data:`SUPPORTED_MODELS`."""
    check_database(path)
    with _read_only(path) as con:
        cameras = {}
        for camera_id, model, width, height, params, prior in con.execute(
            "SELECT camera_id, model, width, height, params, prior_focal_length FROM cameras"
        ):
            camera = pycolmap.Camera(
                camera_id=camera_id,
                model=pycolmap.CameraModelId(model),
                width=width,
                height=height,
                params=np.frombuffer(params, dtype=np.float64),
            )
            cameras[camera_id] = (camera_object(camera), bool(prior))
        images = []
        for image_id, name, camera_id in con.execute(
            "SELECT image_id, name, camera_id FROM images ORDER BY image_id"
        ):
            if camera_id not in cameras:
                raise ColmapInputError(f"{path}: image {name}: camera {camera_id} is missing")
            doc, prior = cameras[camera_id]
            K = np.array([[doc["fx"], 0, doc["cx"]], [0, doc["fy"], doc["cy"]], [0, 0, 1.0]])
            images.append(ImageInfo(int(image_id), name, int(camera_id), doc, prior, K))
        matched = sorted(
            (*_pair(pair_id), int(rows))
            for pair_id, rows in con.execute("SELECT pair_id, rows FROM matches")
        )
        verified = {_pair(p) for (p,) in con.execute("SELECT pair_id FROM two_view_geometries")}
    return Snapshot(images, matched, verified)


def snapshot_keypoints(path: Path, image_ids: Iterable[int]) -> Iterator[tuple[int, np.ndarray]]:
    """``(image_id, (N, 2) keypoints in our pixels)`` of ``image_ids``, read-only (COLMAP's
    keypoints blob: ``rows`` x ``cols`` float32, x and y first)."""
    with _read_only(path) as con:
        for image_id in image_ids:
            row = con.execute(
                "SELECT rows, cols, data FROM keypoints WHERE image_id = ?", (image_id,)
            ).fetchone()
            if row is None or not row[0] or row[2] is None:
                yield image_id, np.zeros((0, 2))
                continue
            rows, cols, data = row
            raw = np.frombuffer(data, dtype=np.float32).reshape(rows, cols)
            yield image_id, raw[:, :2].astype(np.float64) - PIXEL_OFFSET


#: COLMAP's descriptor type of SIFT (``FeatureExtractorType.SIFT``): uint8, 128 columns.
_SIFT_TYPE = 0


def snapshot_features(
    path: Path, image_ids: Iterable[int]
) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """``(image_id, (N, 2) keypoints in our pixels, (N, 128) uint8 SIFT descriptors)`` of
    ``image_ids``, read-only; an image without keypoints or descriptors gives (0, 2) and
    (0, 128). :class:`ColmapInputError` for descriptors that are not COLMAP's SIFT or do not
    fit the keypoints."""
    with _read_only(path) as con:
        for image_id in image_ids:
            kp = con.execute(
                "SELECT rows, cols, data FROM keypoints WHERE image_id = ?", (image_id,)
            ).fetchone()
            desc = con.execute(
                "SELECT type, rows, cols, data FROM descriptors WHERE image_id = ?", (image_id,)
            ).fetchone()
            if kp is None or not kp[0] or kp[2] is None or desc is None or desc[3] is None:
                yield image_id, np.zeros((0, 2)), np.zeros((0, 128), dtype=np.uint8)
                continue
            rows, cols, data = kp
            xy = np.frombuffer(data, dtype=np.float32).reshape(rows, cols)[:, :2]
            kind, d_rows, d_cols, d_data = desc
            if kind != _SIFT_TYPE or d_cols != 128 or len(d_data) != d_rows * d_cols:
                raise ColmapInputError(
                    f"{path}: image {image_id}: descriptors of type {kind}, {d_cols} columns; "
                    "guided matching reads COLMAP's SIFT (uint8, 128 columns)"
                )
            if d_rows != rows:
                raise ColmapInputError(
                    f"{path}: image {image_id}: {d_rows} descriptors for {rows} keypoints"
                )
            descriptors = np.frombuffer(d_data, dtype=np.uint8).reshape(d_rows, d_cols)
            yield image_id, xy.astype(np.float64) - PIXEL_OFFSET, descriptors


def snapshot_orientations(path: Path, image_ids: Iterable[int]) -> Iterator[tuple[int, np.ndarray]]:
    """``(image_id, (N,) keypoint orientations)`` of ``image_ids``, read-only: radians, the
    direction of each keypoint's frame's x axis in the image (x right, y down), from COLMAP's
    affine shape (``atan2(a21, a11)``) or its older (x, y, scale, orientation) rows; NaN
    where the keypoints hold none (two columns)."""
    with _read_only(path) as con:
        for image_id in image_ids:
            kp = con.execute(
                "SELECT rows, cols, data FROM keypoints WHERE image_id = ?", (image_id,)
            ).fetchone()
            if kp is None or not kp[0] or kp[2] is None:
                yield image_id, np.zeros(0)
                continue
            rows, cols, data = kp
            table = np.frombuffer(data, dtype=np.float32).reshape(rows, cols).astype(np.float64)
            if cols >= 6:
                yield image_id, np.arctan2(table[:, 4], table[:, 2])
            elif cols == 4:
                yield image_id, table[:, 3]
            else:
                yield image_id, np.full(rows, np.nan)


def _pair(pair_id: int) -> tuple[int, int]:
    a, b = pycolmap.pair_id_to_image_pair(pair_id)
    return int(a), int(b)


@dataclass(frozen=True)
class ImageInfo:
    """An image of the database: id, name, and its camera as an API ``camera`` object (our
    pixel convention), whether COLMAP trusts its focal length (``prior_focal_length``), and
    its calibration matrix in our pixels."""

    image_id: int
    name: str
    camera_id: int
    camera: dict[str, Any]
    trusted_focal: bool
    K: np.ndarray


def camera_object(camera: pycolmap.Camera) -> dict[str, Any]:
    """The API ``camera`` object of a COLMAP camera; :class:`ColmapInputError` for a model
    other than :data:`SUPPORTED_MODELS`."""
    name = camera.model.name
    p = [float(v) for v in camera.params]
    dist: list[float] | None = None
    if name == "SIMPLE_PINHOLE":
        (f, cx, cy), fx, fy = p, p[0], p[0]
    elif name == "PINHOLE":
        fx, fy, cx, cy = p
    elif name == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        fx = fy = f
        dist = [k, 0.0, 0.0, 0.0]
    elif name == "RADIAL":
        f, cx, cy, k1, k2 = p
        fx = fy = f
        dist = [k1, k2, 0.0, 0.0]
    elif name == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        dist = [k1, k2, p1, p2]
    else:
        raise ColmapInputError(
            f"camera {camera.camera_id}: model {name} is not supported "
            f"({', '.join(SUPPORTED_MODELS)}); undistort the images or use one of these"
        )
    doc: dict[str, Any] = {
        "width": int(camera.width),
        "height": int(camera.height),
        "fx": fx,
        "fy": fy,
        "cx": cx - PIXEL_OFFSET,
        "cy": cy - PIXEL_OFFSET,
    }
    if dist is not None and any(dist):
        doc["distortion"] = dist
    return doc


def fundamental_to_colmap(F: np.ndarray) -> np.ndarray:
    """F of our pixels (x2^T F x1 = 0) -> F of COLMAP's pixels (x_ours = T x_colmap)."""
    T = np.array([[1.0, 0.0, -PIXEL_OFFSET], [0.0, 1.0, -PIXEL_OFFSET], [0.0, 0.0, 1.0]])
    out: np.ndarray = T.T @ F @ T
    return out


@dataclass(frozen=True)
class Geometry:
    """A pair's verified geometry to write. ``F`` in our pixels (None: the pair is written as
    COLMAP writes a pair it could not verify); with ``E``, ``R`` and ``t`` it is CALIBRATED
    (``x2 = R x1 + t`` in camera coordinates)."""

    image_id1: int
    image_id2: int
    inlier_matches: np.ndarray
    F: np.ndarray | None = None
    E: np.ndarray | None = None
    R: np.ndarray | None = None
    t: np.ndarray | None = None

    @property
    def config(self) -> str:
        if self.F is None:
            return "DEGENERATE"
        return "CALIBRATED" if self.E is not None else "UNCALIBRATED"

    def to_colmap(self) -> pycolmap.TwoViewGeometry:
        g = pycolmap.TwoViewGeometry()
        conf = pycolmap.TwoViewGeometryConfiguration
        if self.F is None:
            g.config = conf.DEGENERATE
            return g
        g.inlier_matches = np.ascontiguousarray(self.inlier_matches, dtype=np.uint32)
        g.F = fundamental_to_colmap(self.F)
        if self.E is not None and self.R is not None and self.t is not None:
            g.config = conf.CALIBRATED
            g.E = self.E
            g.cam2_from_cam1 = pycolmap.Rigid3d(
                pycolmap.Rotation3d(np.asarray(self.R, dtype=np.float64)),
                np.asarray(self.t, dtype=np.float64).reshape(3, 1),
            )
        else:
            g.config = conf.UNCALIBRATED
        return g


@dataclass(frozen=True)
class PriorFill:
    """What a run knows of an image for COLMAP's ``pose_priors``: its API ``position`` (WGS84
    ``lat``/``lon``/``alt``, or local ``x``/``y``/``z`` metres) and ``gravity``, the unit
    downward direction in its camera frame (COLMAP's and GLOMAP's convention: about (0, 1, 0)
    for an upright camera, (0, 0, 1) for one looking straight down); either may be None."""

    image: ImageInfo
    position: dict[str, float] | None
    gravity: np.ndarray | None


def _prior_position(position: dict[str, float]) -> tuple[np.ndarray, Any]:
    systems = pycolmap.PosePriorCoordinateSystem
    if "lat" in position:
        xyz = [position["lat"], position["lon"], position["alt"]]
        return np.asarray(xyz, dtype=np.float64), systems.WGS84
    xyz = [position["x"], position["y"], position["z"]]
    return np.asarray(xyz, dtype=np.float64), systems.CARTESIAN


class ColmapDatabase:
    """pycolmap's ``Database`` read in our conventions; a context manager."""

    def __init__(self, path: Path) -> None:
        check_database(path)  # pycolmap would create a missing file
        self.path = path
        self._db = pycolmap.Database.open(str(path))

    def __enter__(self) -> ColmapDatabase:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._db.close()

    def pose_prior_positions(self, images: Iterable[ImageInfo]) -> dict[str, dict[str, float]]:
        """Image name -> the API position of its pose prior (WGS84 lat/lon/alt or local x/y/z)."""
        names = {i.image_id: i.name for i in images}
        out: dict[str, dict[str, float]] = {}
        wgs84 = pycolmap.PosePriorCoordinateSystem.WGS84
        for prior in self._db.read_all_pose_priors():
            if not prior.has_position():
                continue
            name = names.get(int(prior.corr_data_id.id))
            if name is None:
                continue
            a, b, c = (float(v) for v in np.asarray(prior.position).ravel())
            if prior.coordinate_system == wgs84:
                out[name] = {"lat": a, "lon": b, "alt": c}
            else:
                out[name] = {"x": a, "y": b, "z": c}
        return out

    def fill_pose_priors(self, priors: Iterable[PriorFill]) -> dict[str, int]:
        """Write what ``priors`` know where the ``pose_priors`` table has nothing: a new row
        for an image without one (position, its coordinate system, gravity); on an image's
        existing row only the fields it lacks (a position, a gravity), never one that is
        there. One transaction; the counts ``{"positions": n, "gravity": m}`` written."""
        existing = {int(p.corr_data_id.id): p for p in self._db.read_all_pose_priors()}
        written = {"positions": 0, "gravity": 0}
        with pycolmap.DatabaseTransaction(self._db):
            for fill in priors:
                prior = existing.get(fill.image.image_id)
                new = prior is None
                if prior is None:
                    prior = pycolmap.PosePrior()
                    prior.corr_data_id = pycolmap.data_t(
                        sensor_id=pycolmap.sensor_t(
                            type=pycolmap.SensorType.CAMERA, id=fill.image.camera_id
                        ),
                        id=fill.image.image_id,
                    )
                changed = False
                if fill.position is not None and not prior.has_position():
                    prior.position, prior.coordinate_system = _prior_position(fill.position)
                    written["positions"] += 1
                    changed = True
                if fill.gravity is not None and not prior.has_gravity():
                    prior.gravity = np.asarray(fill.gravity, dtype=np.float64).reshape(3)
                    written["gravity"] += 1
                    changed = True
                if changed and new:
                    self._db.write_pose_prior(prior)
                elif changed:
                    self._db.update_pose_prior(prior)
        return written

    def keypoints(self, image_id: int, with_shape: bool = False) -> np.ndarray:
        """(N, 2) float64 keypoints in our pixels; (N, 4) ``[x, y, scale, angle_deg]`` with
        ``with_shape`` (from COLMAP's affine shape)."""
        raw = np.asarray(self._db.read_keypoints(image_id), dtype=np.float64)
        if raw.ndim != 2 or raw.shape[1] < 2:
            return np.zeros((0, 4 if with_shape else 2))
        xy = raw[:, :2] - PIXEL_OFFSET
        if not with_shape:
            return np.ascontiguousarray(xy)
        if raw.shape[1] >= 6:
            a11, a12, a21, a22 = raw[:, 2], raw[:, 3], raw[:, 4], raw[:, 5]
            scale = 0.5 * (np.hypot(a11, a21) + np.hypot(a12, a22))
            angle = np.degrees(np.arctan2(a21, a11))
        elif raw.shape[1] == 4:
            scale, angle = raw[:, 2], np.degrees(raw[:, 3])
        else:
            scale, angle = np.ones(len(raw)), np.zeros(len(raw))
        return np.column_stack((xy, scale, angle))

    def matches(self, image_id1: int, image_id2: int) -> np.ndarray:
        """(M, 2) int64 matches of the pair as stored (id1 < id2)."""
        return np.asarray(self._db.read_matches(image_id1, image_id2), dtype=np.int64)

    def write_matches(self, matches: Sequence[tuple[int, int, np.ndarray]], overwrite: bool) -> int:
        """``(image_id1, image_id2, (M, 2) matches)`` (id1 < id2, columns in that order) in
        one transaction; a pair that has matches is skipped, or replaced with ``overwrite``
        (its two-view geometry deleted too: it verified other matches). The pairs written."""
        written = 0
        with pycolmap.DatabaseTransaction(self._db):
            for a, b, m in matches:
                assert a < b, "pairs are written in COLMAP's stored order"
                if self._db.exists_matches(a, b):
                    if not overwrite:
                        continue
                    self._db.delete_matches(a, b)
                    if self._db.exists_two_view_geometry(a, b):
                        self._db.delete_two_view_geometry(a, b)
                self._db.write_matches(a, b, np.ascontiguousarray(m, dtype=np.uint32))
                written += 1
        return written

    def write(self, geometries: Sequence[Geometry], overwrite: bool) -> None:
        """All of ``geometries`` in one transaction (rows replaced with ``overwrite``)."""
        with pycolmap.DatabaseTransaction(self._db):
            for g in geometries:
                a, b = g.image_id1, g.image_id2
                if self._db.exists_two_view_geometry(a, b):
                    if not overwrite:
                        continue
                    self._db.delete_two_view_geometry(a, b)
                self._db.write_two_view_geometry(a, b, g.to_colmap())


def chunks(items: Sequence[Any], size: int) -> Iterator[Sequence[Any]]:
    for start in range(0, len(items), size):
        yield items[start : start + size]
