"""The pairs worth matching in a folder of images, chosen from the rough POS by footprint
overlap (the paper's rule, :mod:`hmcc.footprint`), for COLMAP's pairs file (``name1 name2`` a
line: ``colmap matches_importer``, ``pycolmap.match_image_pairs``). ``hmcc pairs``.

* **Poses** as ``hmcc colmap`` reads them (:func:`~hmcc_colmap.poses.read_image_poses`, or
  :func:`~hmcc_colmap.poses.load_pose_file`); an image with a position and no attitude gets
  one estimated from the flight track (:mod:`hmcc_colmap.track`): a nadir footprint needs
  its heading.
* **Cameras** from the images' EXIF (:mod:`hmcc_colmap.capture`) or, with a database, as
  COLMAP holds them (``hmcc colmap``'s reading, our pixel convention).
* **The ground** (the plane the footprints lie on, ENU z on the positions' height scale):
  ``ground_z`` when given; else each image's ground ``flying_height`` below its camera (for
  heights that drift or follow the terrain); else the take-off point's height, the median of
  the images' ``altitude - RelativeAltitude`` (DJI XMP); else an error. Not the projection's
  plane, which a verification puts a third of the flying height *below* the ground
  (:class:`hmcc.projection.GroundOptions`): a footprint is what the camera sees of the
  ground, so it lies on the ground itself. Nor the projection's ``"auto"`` estimate, which
  triangulates matches: pairs are chosen before there are any.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from hmcc import InputError
from hmcc.camera import Camera
from hmcc.footprint import FootprintOptions, PairOverlap, footprint, select_pairs
from hmcc.pose import Pose, geodetic_to_enu
from hmcc_schema import validation_issues
from hmcc_schema.convert import to_camera, to_rough_pose
from hmcc_schema.models import CameraModel, PoseModel

from .capture import Capture, read_capture
from .errors import ColmapInputError
from .poses import ImagePose, pose_sources, takeoff_ground
from .track import capture_order, track_attitude

__all__ = ["IMAGE_SUFFIXES", "PairChoice", "choose_pairs", "image_names", "write_pairs_file"]

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


@dataclass
class PairChoice:
    """The chosen ``pairs`` (names in capture order within a pair, overlap fraction), the
    images whose attitude was ``estimated`` from the track, those ``without_pose`` (name ->
    why; they take part in no pair), and how the ground was chosen."""

    names: list[str]
    pairs: list[tuple[str, str, float]]
    estimated: list[str] = field(default_factory=list)
    without_pose: dict[str, str] = field(default_factory=dict)
    ground: str = ""
    footprints: dict[str, np.ndarray] = field(default_factory=dict)


def image_names(folder: Path) -> list[str]:
    """The images under ``folder`` (paths relative to it, as COLMAP names them), sorted."""
    if not folder.is_dir():
        raise ColmapInputError(f"{folder}: no such image folder")
    names = sorted(
        p.relative_to(folder).as_posix()
        for p in folder.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    )
    if not names:
        raise ColmapInputError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
    return names


def choose_pairs(
    images: Path,
    *,
    poses: Path | None = None,
    database: Path | None = None,
    ground_z: float | None = None,
    flying_height: float | None = None,
    min_overlap: float = 0.5,
    max_per_image: int | None = None,
    min_partners: int = 0,
    options: FootprintOptions | None = None,
) -> PairChoice:
    """Everything read and checked, then the pairs (see the module doc).
    :class:`ColmapInputError` (one line naming the file or option) for refused input."""
    if not 0.0 <= min_overlap <= 1.0:
        raise ColmapInputError(f"--min-overlap: {min_overlap:g} is not in [0, 1]")
    if max_per_image is not None and max_per_image < 1:
        raise ColmapInputError(f"--max-per-image: {max_per_image} is not at least 1")
    if min_partners < 0:
        raise ColmapInputError(f"--min-partners: {min_partners} is below 0")
    if flying_height is not None and not flying_height > 0:
        raise ColmapInputError(f"--flying-height: {flying_height:g} is not above 0")
    if database is not None:
        names, cameras = _database_cameras(database)
    else:
        names, cameras = image_names(images), {}
    if poses is not None and not images.is_dir():
        raise ColmapInputError(f"{images}: no such image folder")
    sources = pose_sources(names, poses, images)  # the images' tags: all in the folder
    captures = {name: read_capture(images / name) for name in names}
    if database is None:
        cameras = {name: _exif_camera(images / name, captures[name]) for name in names}
    times = {n: c.time for n, c in captures.items()}
    order = capture_order(names, times)
    sources, estimated = track_attitude(sources, names, times, poses or images)
    placed, positions, without = _place(order, sources)
    if len(placed) < 2:
        raise ColmapInputError(
            f"{poses or images}: fewer than two images have a usable pose "
            f"({len(without)} without: {next(iter(without.values()), '')})"
        )
    ground, how = _ground(placed, positions, sources, captures, ground_z, flying_height)
    prints = {}
    for name, pose in placed.items():
        try:
            prints[name] = footprint(
                cameras[name], pose, ground[name], options or FootprintOptions()
            )
        except ValueError as e:
            raise ColmapInputError(f"{name}: {e}; the ground ({how}) must lie below it") from None
    kept = list(placed)
    chosen: Sequence[PairOverlap] = select_pairs(
        [prints[n] for n in kept], min_overlap, max_per_image, min_partners
    )
    pairs = [(kept[p.i], kept[p.j], p.overlap) for p in chosen]
    return PairChoice(order, pairs, estimated, without, how, prints)


def write_pairs_file(path: Path, pairs: Sequence[tuple[str, str, float]]) -> None:
    """COLMAP's pairs file: ``name1 name2`` a line."""
    path.write_text("".join(f"{a} {b}\n" for a, b, _ in pairs))


def _database_cameras(database: Path) -> tuple[list[str], dict[str, Camera]]:
    from .database import read_snapshot

    if not database.is_file():
        raise ColmapInputError(f"{database}: no such database")
    snapshot = read_snapshot(database)
    if not snapshot.images:
        raise ColmapInputError(f"{database}: no images in this database")
    cameras = {}
    for info in snapshot.images:
        cameras[info.name] = _camera(info.camera, f"{database}: camera {info.camera_id}")
    return [i.name for i in snapshot.images], cameras


def _exif_camera(path: Path, capture: Capture) -> Camera:
    if capture.camera is None:
        raise ColmapInputError(f"{path}: {capture.camera_issue}")
    return _camera(capture.camera, str(path))


def _camera(doc: dict[str, Any], where: str) -> Camera:
    try:
        return to_camera(CameraModel.model_validate(doc))
    except (ValidationError, InputError) as e:
        issue = validation_issues(e)[0]
        raise ColmapInputError(f"{where}: {issue.field}: {issue.reason}") from None


def _place(
    order: Sequence[str], sources: dict[str, ImagePose]
) -> tuple[dict[str, Pose], dict[str, np.ndarray], dict[str, str]]:
    """The usable poses in one local ENU frame (WGS84 positions about their mean latitude and
    longitude, height 0, as a pair's frame is made), the platforms' positions, and why the
    others are unusable."""
    rough, without = {}, {}
    for name in order:
        source = sources.get(name)
        pose = None if source is None else source.pose
        if pose is None:
            without[name] = "no pose" if source is None else str(source.why_unusable)
            continue
        try:
            rough[name] = to_rough_pose(PoseModel.model_validate(pose))
        except (ValidationError, InputError) as e:
            issue = validation_issues(e)[0]
            without[name] = f"unusable pose ({issue.field}: {issue.reason})"
    geodetic = {r.geodetic for r in rough.values()}
    if len(geodetic) > 1:
        raise ColmapInputError("the positions mix WGS84 and local metres")
    if not rough:
        return {}, {}, without
    xyz = np.array([r.position for r in rough.values()])
    if geodetic == {True}:
        origin = (float(xyz[:, 0].mean()), float(xyz[:, 1].mean()), 0.0)
        xyz = geodetic_to_enu(xyz[:, 0], xyz[:, 1], xyz[:, 2], origin)
    positions = dict(zip(rough, xyz, strict=True))
    placed = {name: r.at(positions[name]) for name, r in rough.items()}
    return placed, positions, without


def _ground(
    placed: dict[str, Pose],
    positions: dict[str, np.ndarray],
    sources: dict[str, ImagePose],
    captures: dict[str, Capture],
    ground_z: float | None,
    flying_height: float | None,
) -> tuple[dict[str, float], str]:
    """Each image's ground height (ENU z) and how it was chosen (see the module doc)."""
    if ground_z is not None:
        return {n: float(ground_z) for n in placed}, f"--ground-z {ground_z:g} m"
    if flying_height is not None:
        ground = {n: float(p.center[2]) - flying_height for n, p in placed.items()}
        return ground, f"{flying_height:g} m below each camera (--flying-height)"
    takeoff = takeoff_ground({n: float(positions[n][2]) for n in placed}, sources)
    if takeoff is None:
        raise ColmapInputError(
            "--ground-z or --flying-height is needed: the images give no height above the "
            "ground (DJI XMP RelativeAltitude)"
        )
    z = takeoff[0]
    return {n: z for n in placed}, f"the take-off point, {z:.2f} m (altitude - RelativeAltitude)"
