"""A rough attitude for images with a position and no attitude (a camera with a GPS tag and
nothing else): the camera is taken to look straight down with the top of the image toward the
direction of travel, the heading taken from the flight track.

* **Capture order**: EXIF ``DateTimeOriginal`` (then the name) when every image has one,
  otherwise the names' order (cameras number their files in order).
* **Heading** of an exposure: the direction from the nearest earlier exposure at least
  ``min_step_m`` away to the nearest later one (a central difference; at the ends of the
  flight the one side there is), clockwise from north. Exposures closer than that (a hover,
  a repeated GPS fix) are skipped so that GNSS noise does not give the direction.
* **Attitude**: ``yaw`` = that heading, ``pitch`` = ``roll`` = 0 with the zero mounting (our
  platform convention): the camera nadir, image top toward the nose.

What it cannot know: the camera's rotation about the vertical relative to the direction of
travel (a camera mounted sideways, image top toward a wing, is 90 deg off) and its tilt.
Where a strip turns, the heading is the chord across the turn. Such an attitude is an
estimate: its source says so, and it is meant for what tolerates it (a footprint's
orientation for choosing pairs), not for a verification's motions.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path

import numpy as np

from hmcc.pose import geodetic_to_enu

from .capture import read_capture
from .errors import ColmapInputError
from .poses import ImagePose, pose_sources

__all__ = [
    "ESTIMATED",
    "capture_order",
    "capture_times",
    "rough_sources",
    "track_attitude",
    "track_headings",
    "with_track_attitude",
]

#: Appended to the source of a pose whose attitude was estimated here.
ESTIMATED = "attitude estimated: nadir, heading from the flight track"


def capture_order(names: Sequence[str], times: Mapping[str, datetime | None]) -> list[str]:
    """``names`` in capture order: by time when every image has one, else by name."""
    if names and all(times.get(n) is not None for n in names):
        return sorted(names, key=lambda n: (times[n], n))
    return sorted(names)


def capture_times(folder: Path | None, names: Sequence[str]) -> dict[str, datetime | None]:
    """Each image's EXIF ``DateTimeOriginal`` where ``folder`` holds it (None otherwise: no
    folder, a missing file, no tag)."""
    if folder is None:
        return {}
    times: dict[str, datetime | None] = {}
    for name in names:
        path = folder / name
        times[name] = read_capture(path).time if path.is_file() else None
    return times


def rough_sources(
    names: Sequence[str], poses: Path | None, images: Path | None, *, track: bool
) -> tuple[dict[str, ImagePose], list[str]]:
    """Each image's rough pose (:func:`~hmcc_colmap.poses.pose_sources`) and, when ``track``,
    the attitude from the flight track for the images with a position and no attitude
    (:func:`track_attitude`); the names of those."""
    sources = pose_sources(names, poses, images)
    if not track:
        return sources, []
    return track_attitude(sources, names, capture_times(images, names), poses or images)


def track_attitude(
    poses: Mapping[str, ImagePose],
    names: Sequence[str],
    times: Mapping[str, datetime | None],
    where: object,
) -> tuple[dict[str, ImagePose], list[str]]:
    """:func:`with_track_attitude` in :func:`capture_order` (by ``times``), as ``hmcc pairs``
    and ``hmcc colmap`` take it: positions that mix WGS84 and local metres are a
    :class:`ColmapInputError` naming ``where`` (the folder or pose file)."""
    try:
        return with_track_attitude(poses, capture_order(names, times))
    except ValueError as e:
        raise ColmapInputError(f"{where}: {e}") from None


def track_headings(positions: np.ndarray, min_step_m: float = 1.0) -> np.ndarray:
    """(N,) headings (deg clockwise from north, in [0, 360)) of exposures at (N, 2|3) ENU
    positions (metres) in capture order; NaN where no other exposure is ``min_step_m`` away."""
    xy = np.asarray(positions, dtype=np.float64)[:, :2]
    n = len(xy)
    out = np.full(n, np.nan)
    for i in range(n):
        before = next(
            (j for j in range(i - 1, -1, -1) if np.hypot(*(xy[i] - xy[j])) >= min_step_m), None
        )
        after = next((k for k in range(i + 1, n) if np.hypot(*(xy[k] - xy[i])) >= min_step_m), None)
        if before is None and after is None:
            continue
        start = xy[i] if before is None else xy[before]
        end = xy[i] if after is None else xy[after]
        east, north = end - start
        out[i] = math.degrees(math.atan2(east, north)) % 360.0
    return out


def with_track_attitude(
    poses: Mapping[str, ImagePose], order: Sequence[str], min_step_m: float = 1.0
) -> tuple[dict[str, ImagePose], list[str]]:
    """``poses`` with an estimated attitude for each image that has a position and no
    attitude, and the names of those, in capture ``order`` (the images of ``poses``). The
    track is that of every image with a position; positions all WGS84 or all local metres
    (else ``ValueError``)."""
    tracked = [n for n in order if poses.get(n) is not None and poses[n].position is not None]
    wanting = [n for n in tracked if poses[n].attitude is None]
    out = dict(poses)
    if not wanting:
        return out, []
    headings = dict(
        zip(tracked, track_headings(_enu([poses[n] for n in tracked]), min_step_m), strict=True)
    )
    estimated = []
    for name in wanting:
        heading = headings[name]
        if not math.isfinite(heading):
            continue
        pose = poses[name]
        out[name] = ImagePose(
            f"{pose.source}; {ESTIMATED}",
            pose.position,
            {"yaw": round(float(heading), 3), "pitch": 0.0, "roll": 0.0},
            None,
            None,
        )
        estimated.append(name)
    return out, estimated


def _enu(poses: Sequence[ImagePose]) -> np.ndarray:
    """(N, 3) positions in one local frame (metres)."""
    positions = [p.position for p in poses if p.position is not None]
    if all("lat" in p for p in positions):
        lat = np.array([p["lat"] for p in positions])
        lon = np.array([p["lon"] for p in positions])
        alt = np.array([p["alt"] for p in positions])
        return geodetic_to_enu(lat, lon, alt, (float(lat.mean()), float(lon.mean()), 0.0))
    if all("x" in p for p in positions):
        return np.array([[p["x"], p["y"], p["z"]] for p in positions], dtype=np.float64)
    raise ValueError("the positions mix WGS84 and local metres")
