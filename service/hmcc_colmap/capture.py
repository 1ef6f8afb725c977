"""What an image file says of its capture, besides its pose (:mod:`hmcc_colmap.poses`): the
camera (EXIF focal length and sensor size) and the capture time (EXIF ``DateTimeOriginal``).
Read with Pillow, as the poses are (the height above the take-off point is the pose's:
:attr:`hmcc_colmap.poses.ImagePose.height_above_takeoff`).

The focal length in pixels of the stored image (which may be downscaled: EXIF keeps the
original's pixel size) is, in this order:

* ``FocalLength`` (mm) x the stored width / the sensor width, the sensor width being EXIF's
  ``PixelXDimension`` / ``FocalPlaneXResolution`` (in its ``FocalPlaneResolutionUnit``);
* ``FocalLengthIn35mmFilm`` x the stored longer side / 36 mm (the 35 mm frame's width; for a
  16:9 crop of a 4:3 sensor it reads about 5 % short, e.g. DJI's FC300S);
* otherwise none: give the cameras in a COLMAP database (``hmcc pairs --database``).

The principal point is the image centre, no distortion: a footprint needs no more.

A COLMAP database's prior focal length can be far off for downscaled images (COLMAP reads
``FocalPlaneXResolution``, which describes the original's pixels, against the stored image):
:func:`exif_focal_cameras` replaces it by the EXIF one where they disagree by more than
:data:`FOCAL_DISAGREEMENT` (``hmcc colmap`` and ``hmcc match``; ``--database-focal`` keeps the
database's).
"""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .errors import ColmapInputError

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from hmcc import Camera

    from .database import ImageInfo

__all__ = ["FOCAL_DISAGREEMENT", "Capture", "exif_focal_cameras", "read_capture"]

_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0}  # EXIF FocalPlaneResolutionUnit: inch, cm, mm


@dataclass(frozen=True)
class Capture:
    """One image's ``camera`` (an API camera object, or None with ``camera_issue``), capture
    ``time`` (None when untagged)."""

    camera: dict[str, Any] | None
    camera_issue: str | None
    time: datetime | None


def read_capture(path: Path) -> Capture:
    """The :class:`Capture` of one image file; :class:`ColmapInputError` when it is not an
    image Pillow reads. Read once per process for a file of that size and modification time
    (``hmcc colmap`` reads an image's capture for its time and for its focal length), as
    :func:`hmcc_colmap.poses.read_image_poses` reads its pose."""
    try:
        stat = path.stat()
    except OSError as e:
        raise ColmapInputError(f"{path}: not an image Pillow can read ({e})") from None
    return copy.deepcopy(_capture_of(str(path.absolute()), stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=4096)
def _capture_of(path: str, mtime_ns: int, size: int) -> Capture:
    return _read_capture(Path(path))


def _read_capture(path: Path) -> Capture:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            width, height = image.size
            exif = image.getexif()
            tags = {**dict(exif), **dict(exif.get_ifd(0x8769))}  # IFD0 + the Exif IFD
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as e:
        raise ColmapInputError(f"{path}: not an image Pillow can read ({e})") from None
    focal, issue = _focal_px(tags, width, height)
    camera = None if focal is None else {"width": width, "height": height, "focal": focal}
    return Capture(camera, issue, _time(tags))


#: The images' EXIF focal length replaces a database camera's when one is more than this
#: factor of the other.
FOCAL_DISAGREEMENT = 1.2


def exif_focal_cameras(
    infos: Sequence[ImageInfo], cameras: Mapping[int, Camera], folder: Path
) -> tuple[dict[int, Camera], dict[str, tuple[float, str]]]:
    """The database ``cameras`` (by image id) with the EXIF focal length (scaled to the
    database camera's width) where it disagrees with the database's by more than
    :data:`FOCAL_DISAGREEMENT`; each image's focal length (pixels) and its source
    (``database`` or ``exif``). Images not in ``folder`` or without an EXIF focal keep the
    database's."""
    out = dict(cameras)
    used: dict[str, tuple[float, str]] = {}
    for info in infos:
        camera = cameras[info.image_id]
        focal_db = 0.5 * (camera.fx + camera.fy)
        used[info.name] = (focal_db, "database")
        path = folder / info.name
        exif = read_capture(path).camera if path.is_file() else None
        if not exif or not exif.get("focal") or not exif.get("width"):
            continue
        focal = float(exif["focal"]) * camera.width / float(exif["width"])
        if max(focal, focal_db) > FOCAL_DISAGREEMENT * min(focal, focal_db):
            out[info.image_id] = replace(camera, fx=focal, fy=focal * camera.fy / camera.fx)
            used[info.name] = (focal, "exif")
    return out, used


def _number(value: Any) -> float | None:
    try:
        x = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) else None


def _focal_px(tags: dict[int, Any], width: int, height: int) -> tuple[float | None, str | None]:
    focal_mm = _number(tags.get(0x920A))  # FocalLength
    exif_width = _number(tags.get(0xA002))  # PixelXDimension of the original
    plane_x = _number(tags.get(0xA20E))  # FocalPlaneXResolution, pixels per unit
    unit = _MM_PER_UNIT.get(int(_number(tags.get(0xA210)) or 2))
    if focal_mm and exif_width and plane_x and unit and focal_mm > 0 and plane_x > 0:
        sensor_mm = exif_width / plane_x * unit
        return focal_mm * width / sensor_mm, None
    f35 = _number(tags.get(0xA405))  # FocalLengthIn35mmFilm
    if f35 and f35 > 0:
        return f35 * max(width, height) / 36.0, None
    return None, (
        "no EXIF focal length with a sensor size (FocalLength + FocalPlaneXResolution, or "
        "FocalLengthIn35mmFilm); give the cameras with --database"
    )


def _time(tags: dict[int, Any]) -> datetime | None:
    raw = tags.get(0x9003) or tags.get(0x0132)  # DateTimeOriginal, else DateTime
    try:
        stamp = datetime.strptime(str(raw).strip(), "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    sub = str(tags.get(0x9291) or "").strip()  # SubSecTimeOriginal
    if sub.isdigit():
        stamp = stamp.replace(microsecond=int((sub + "000000")[:6]))
    return stamp
