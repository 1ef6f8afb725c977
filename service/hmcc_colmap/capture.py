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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from .errors import ColmapInputError

__all__ = ["Capture", "read_capture"]

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
    image Pillow reads."""
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
