"""Rough poses of a COLMAP project's images, in the API's ``pose`` form (``hmcc_schema``).

Sources, one per run:

* the image files (default): EXIF GPS (latitude, longitude, altitude) and the attitude in
  the XMP tags of the common vendors (DJI, senseFly, Parrot, the ``Camera:`` tags of
  MicaSense, Sentera and others: the table of readers in :mod:`.tags`, each stating its
  convention), read with Pillow (``Image.getexif``, and the XMP packet parsed with
  defusedxml, as ``Image.getxmp`` does, keeping the namespaces);
* a ``--poses`` file: OpenDroneMap's ``geo.txt``, a CSV ``image,lat,lon,alt,yaw,pitch,roll``
  (our platform convention), a CSV ``image,x,y,z,omega,phi,kappa`` (local metres, Pix4D's
  angles) or a JSON object mapping image name to an API ``pose`` object.

COLMAP's ``pose_priors`` table fills the position of an image whose source gave an attitude
but no position (its gravity direction is not read back: an attitude is never invented; a run
writes the positions and gravity directions it has where the table has none, see
:meth:`.database.ColmapDatabase.fill_pose_priors`). An image left without
a position or an attitude has no usable pose (:attr:`ImagePose.pose` None, ``issue`` says why):
its pairs go to the method's fallback estimator.

Every image source's convention is its reader's (:data:`.tags.READERS`).
"""

from __future__ import annotations

import copy
import csv
import functools
import io
import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import orjson
from pydantic import ValidationError

from hmcc_schema import validation_issues
from hmcc_schema.models import PoseModel

from .errors import ColmapInputError
from .tags import (
    READERS,
    exif_make,
    read_tags,
    xmp_altitude,
    xmp_fields,
    xmp_relative_altitude,
)

__all__ = [
    "IMAGE_SOURCE",
    "ImagePose",
    "load_pose_file",
    "looked_for",
    "pose_sources",
    "read_image_poses",
    "takeoff_ground",
    "with_prior_positions",
]

#: The source named for a pose read from an image's tags.
IMAGE_SOURCE = "image metadata (EXIF GPS, XMP)"


def looked_for() -> str:
    """The tags an image's pose is looked for in, for a message."""
    families = "; ".join(f"{r.tags} ({r.vendors})" for r in READERS)
    return f"EXIF GPS for the position; for the attitude, XMP {families}"


@dataclass(frozen=True)
class ImagePose:
    """What a source says of one image: ``position`` and ``attitude`` (API objects, or None
    when the source has none), a ``mounting`` with a yaw/pitch/roll attitude, the source's
    name, why the pose is unusable (``issue``), and the height above the take-off point
    where the images' tags give it (DJI's ``RelativeAltitude``, metres)."""

    source: str
    position: dict[str, float] | None = None
    attitude: dict[str, Any] | None = None
    mounting: dict[str, Any] | None = None
    issue: str | None = None
    height_above_takeoff: float | None = None

    @property
    def pose(self) -> dict[str, Any] | None:
        """The API ``pose`` object, or None when a position or an attitude is missing."""
        if self.position is None or self.attitude is None:
            return None
        pose: dict[str, Any] = {"position": self.position, "attitude": self.attitude}
        if self.mounting is not None:
            pose["mounting"] = self.mounting
        return pose

    @property
    def why_unusable(self) -> str | None:
        if self.pose is not None:
            return None
        if self.issue:
            return self.issue
        missing = [k for k in ("position", "attitude") if getattr(self, k) is None]
        return f"no {' and no '.join(missing)} in the {self.source}"


# --------------------------------------------------------------------------- image files


def read_image_poses(folder: Path, names: Iterable[str]) -> dict[str, ImagePose]:
    """EXIF GPS and XMP attitude of every image ``names`` (paths relative to ``folder``,
    as COLMAP stores them). Raises :class:`ColmapInputError` when the folder holds none of
    them or some are missing."""
    names = list(names)
    if not folder.is_dir():
        raise ColmapInputError(f"{folder}: no such image folder")
    missing = [n for n in names if not (folder / n).is_file()]
    if missing:
        some = ", ".join(missing[:3]) + (" ..." if len(missing) > 3 else "")
        are = "is" if len(missing) == 1 else "are"
        raise ColmapInputError(
            f"{folder}: {len(missing)} of the database's {len(names)} images {are} not in this "
            f"folder ({some}); give the folder the images were extracted from"
        )
    return {name: _known_image_pose(folder / name) for name in names}


def _known_image_pose(path: Path) -> ImagePose:
    """:func:`image_pose`, read once per process for a file of that size and modification
    time (a running process verifies the same images again: 0.5 ms an image in Pillow)."""
    stat = path.stat()
    return copy.deepcopy(_image_pose_of(str(path.absolute()), stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=4096)
def _image_pose_of(path: str, mtime_ns: int, size: int) -> ImagePose:
    return image_pose(Path(path))


def image_pose(path: Path) -> ImagePose:
    """One image's EXIF GPS position and XMP attitude (either may be None); the source names
    the tag family the attitude came from."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            exif = image.getexif()
            gps = dict(exif.get_ifd(0x8825))  # GPSInfo
            make = exif_make(exif)
            fields = xmp_fields(_xmp_packet(image))
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as e:
        return ImagePose("image metadata", issue=f"its metadata cannot be read ({e})")
    reading, reader = read_tags(fields, make)
    position = _gps_position(gps, xmp_altitude(fields)) or reading.position
    source = IMAGE_SOURCE if reader is None else f"image metadata (EXIF GPS, XMP: {reader})"
    return ImagePose(
        source,
        position,
        reading.attitude,
        reading.mounting,
        height_above_takeoff=xmp_relative_altitude(fields),
    )


def _xmp_packet(image: Any) -> bytes | str | None:
    """The image's raw XMP packet: JPEG and WebP keep it in ``info["xmp"]``, PNG in
    ``info["XML:com.adobe.xmp"]``, TIFF in tag 700."""
    packet = image.info.get("xmp") or image.info.get("XML:com.adobe.xmp")
    if packet is None and hasattr(image, "tag_v2"):
        packet = image.tag_v2.get(700)
    if isinstance(packet, tuple):  # TIFF's bytes may come as a tuple
        packet = bytes(packet)
    return packet if isinstance(packet, bytes | str) else None


def _number(value: Any) -> float | None:
    try:
        x = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) else None


def _dms(value: Any) -> float | None:
    try:
        d, m, s = (float(v) for v in value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    x = d + m / 60.0 + s / 3600.0
    return x if math.isfinite(x) else None


def _gps_position(gps: Mapping[int, Any], xmp_alt: float | None) -> dict[str, float] | None:
    """EXIF GPS latitude/longitude (tags 1-4) and altitude (5, 6; else the XMP's,
    ``xmp_alt``)."""
    lat, lon = _dms(gps.get(2)), _dms(gps.get(4))
    if lat is None or lon is None:
        return None
    if str(gps.get(1, "N")).upper().startswith("S"):
        lat = -lat
    if str(gps.get(3, "E")).upper().startswith("W"):
        lon = -lon
    alt = _number(gps.get(6))
    if alt is not None and gps.get(5) in (1, b"\x01"):
        alt = -alt
    if alt is None:
        alt = xmp_alt
    if alt is None or not (-90 <= lat <= 90 and -180 <= lon <= 180):
        return None
    return {"lat": lat, "lon": lon, "alt": alt}


# --------------------------------------------------------------------------- pose files


def pose_sources(
    names: Sequence[str], poses: Path | None, images: Path | None
) -> dict[str, ImagePose]:
    """Each image's rough pose: from the pose file ``poses`` when given (an image it lacks
    says so), else from the tags of the images in ``images`` (:func:`read_image_poses`)."""
    if poses is None:
        if images is None:
            raise ColmapInputError("--images DIR (POS from the images' EXIF/XMP) or --poses FILE")
        return read_image_poses(images, names)
    found = load_pose_file(poses, names)
    source = f"pose file {poses.name}"
    return {n: found.get(n) or ImagePose(source, issue="not in the pose file") for n in names}


def load_pose_file(path: Path, known: Iterable[str]) -> dict[str, ImagePose]:
    """A ``--poses`` file (format by its content: JSON, a CSV with a header, or ODM's
    geo.txt). Raises :class:`ColmapInputError` (``file:line: reason``) for a line it cannot
    read or an image that is not in the database (``known``)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise ColmapInputError(f"{path}: {e}") from None
    known = set(known)
    stripped = text.lstrip()
    if stripped.startswith("{"):
        poses = _json_poses(path, text)
    else:
        first = stripped.splitlines()[0] if stripped else ""
        header = [c.strip().lower() for c in first.split(",")]
        if len(header) > 1 and header[0] in ("image", "name", "image_name"):
            poses = _csv_poses(path, text)
        else:
            poses = _geo_txt_poses(path, text)
    if not poses:
        raise ColmapInputError(f"{path}: no pose in this file")
    for name, (line, pose) in poses.items():
        where = f"{path}:{line}" if line else str(path)
        if name not in known:
            raise ColmapInputError(f"{where}: image {name!r} is not in the database")
        if pose.position is not None and pose.attitude is not None:
            try:
                PoseModel.model_validate(pose.pose)
            except ValidationError as e:
                issue = validation_issues(e)[0]
                raise ColmapInputError(f"{where}: {name}: {issue.field}: {issue.reason}") from None
    return {name: pose for name, (_, pose) in poses.items()}


def _json_poses(path: Path, text: str) -> dict[str, tuple[int, ImagePose]]:
    try:
        doc = orjson.loads(text)
    except orjson.JSONDecodeError as e:
        raise ColmapInputError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(doc, dict):
        raise ColmapInputError(f"{path}: a JSON pose file maps image names to pose objects")
    out = {}
    for name, pose in doc.items():
        try:
            model = PoseModel.model_validate(pose)
        except ValidationError as e:
            issue = validation_issues(e)[0]
            raise ColmapInputError(f"{path}: {name}.{issue.field}: {issue.reason}") from None
        dumped = model.model_dump(mode="json", exclude_none=True)
        out[name] = (
            0,
            ImagePose(
                f"pose file {path.name}",
                dumped["position"],
                dumped["attitude"],
                dumped.get("mounting"),
            ),
        )
    return out


_CSV_FORMATS: dict[tuple[str, ...], str] = {
    ("lat", "lon", "alt", "yaw", "pitch", "roll"): "geodetic",
    ("x", "y", "z", "omega", "phi", "kappa"): "local",
}


def _csv_poses(path: Path, text: str) -> dict[str, tuple[int, ImagePose]]:
    rows = list(csv.reader(io.StringIO(text)))
    header = tuple(c.strip().lower() for c in rows[0][1:])
    kind = _CSV_FORMATS.get(header)
    if kind is None:
        wanted = " or ".join("image," + ",".join(k) for k in _CSV_FORMATS)
        raise ColmapInputError(f"{path}:1: unknown CSV header {','.join(rows[0])!r}; {wanted}")
    out = {}
    for line, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        values = [_number(v) for v in row[1:]]
        if len(row) != 7 or any(v is None for v in values):
            raise ColmapInputError(
                f"{path}:{line}: expected an image name and 6 numbers, got {','.join(row)!r}"
            )
        a, b, c, d, e, f = (float(v) for v in values if v is not None)
        if kind == "geodetic":
            pose = ImagePose(
                f"pose file {path.name}",
                {"lat": a, "lon": b, "alt": c},
                {"yaw": d, "pitch": e, "roll": f},
            )
        else:
            pose = ImagePose(
                f"pose file {path.name}",
                {"x": a, "y": b, "z": c},
                {"omega": d, "phi": e, "kappa": f},
            )
        out[row[0].strip()] = (line, pose)
    return out


def _geo_txt_poses(path: Path, text: str) -> dict[str, tuple[int, ImagePose]]:
    """ODM's geo.txt: a projection line, then ``image x y [z] [yaw pitch roll] [accuracies]
    [extras]``. EPSG:4326 (or 4979, WGS84 without UTM) gives longitude x and latitude y;
    any other projection is read as metres east, north and up (a projected frame such as UTM:
    close to a local east-north-up frame over one flight, rough POS after all). ODM's angles
    (yaw clockwise from north with the image top forward, pitch 0 at nadir, roll 0) are our
    platform angles with the zero mounting; all three 0 means "not available" in ODM's docs,
    so such a line has no attitude."""
    lines = text.splitlines()
    projection = lines[0].strip() if lines else ""
    geodetic = projection.upper() in ("EPSG:4326", "EPSG:4979", "WGS84", "WGS 84")
    if not projection or (
        not geodetic
        and not projection.upper().startswith(("EPSG:", "+PROJ", "WGS84 UTM", "WGS 84 UTM"))
    ):
        raise ColmapInputError(
            f"{path}:1: expected a projection (EPSG:4326, a PROJ string, WGS84 UTM 16N), got "
            f"{projection[:80]!r}"
        )
    out = {}
    for line, raw in enumerate(lines[1:], start=2):
        fields = raw.split()
        if not fields or fields[0].startswith("#"):
            continue
        numbers = [_number(v) for v in fields[1:7]]
        count = len(numbers)
        if count < 2 or count in (4, 5) or any(v is None for v in numbers):
            raise ColmapInputError(
                f"{path}:{line}: expected 'image x y [z] [yaw pitch roll] ...', got {raw[:120]!r}"
            )
        x, y = float(numbers[0] or 0.0), float(numbers[1] or 0.0)
        z = float(numbers[2] or 0.0) if count >= 3 else 0.0
        if geodetic:
            position: dict[str, float] = {"lat": y, "lon": x, "alt": z}
        else:
            position = {"x": x, "y": y, "z": z}
        attitude = None
        if count >= 6:
            yaw, pitch, roll = (float(v or 0.0) for v in numbers[3:6])
            if (yaw, pitch, roll) != (0.0, 0.0, 0.0):
                attitude = {"yaw": yaw, "pitch": pitch, "roll": roll}
        out[fields[0]] = (line, ImagePose(f"geo file {path.name}", position, attitude))
    return out


# --------------------------------------------------------------------------- pose priors


def with_prior_positions(
    poses: Mapping[str, ImagePose], priors: Mapping[str, dict[str, float]]
) -> dict[str, ImagePose]:
    """``poses`` with COLMAP's prior positions filled in where a source gave none (never an
    attitude: the table has none)."""
    out = dict(poses)
    for name, position in priors.items():
        current = out.get(name)
        if current is None:
            out[name] = ImagePose("COLMAP pose_priors (position only)", position)
        elif current.position is None:
            out[name] = ImagePose(
                f"{current.source} + COLMAP pose_priors position",
                position,
                current.attitude,
                current.mounting,
                current.issue,
                current.height_above_takeoff,
            )
    return out


def takeoff_ground(
    altitudes: Mapping[str, float], sources: Mapping[str, ImagePose]
) -> tuple[float, int] | None:
    """The take-off point's height on the scale of ``altitudes`` (image name -> the camera's
    height): the median of each image's altitude less its height above the take-off point
    (DJI's ``RelativeAltitude``), with the number of images that gave it; None when none
    did. The ground of a flat site, for the plane of footprints and predictions."""
    grounds = [
        altitude - above
        for name, altitude in altitudes.items()
        if name in sources and (above := sources[name].height_above_takeoff) is not None
    ]
    if not grounds:
        return None
    return float(statistics.median(grounds)), len(grounds)
