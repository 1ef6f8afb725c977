"""The rough POS in an image's XMP tags: one reader per vendor's tag family.

:data:`READERS` is the table: each entry names the vendors, the tags it reads and a function
of the image's XMP fields (and EXIF ``Make``) returning the attitude in this project's
platform convention (``yaw`` clockwise from north, ``pitch`` nose up, ``roll`` right wing
down, applied Z-Y-X to north-east-down; the zero mounting looks straight down with the image
top toward the nose), with a ``mounting`` where the camera is not that nadir mount, and the
position where the family carries one (EXIF GPS is read first, by :mod:`.poses`). The first
reader that finds its tags gives the image's attitude; each function's docstring states its
convention and where it comes from.

XMP fields are keyed by namespace URI (lower case, no trailing ``/``) and local name, not by
prefix: vendors reuse prefixes (Autel writes DJI's namespace under ``drone:``) and the same
local names (``Yaw``) mean different things in different namespaces (MicaSense's ``DLS:Yaw``
is the light sensor's, in radians).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

__all__ = [
    "NS_CAMERA",
    "NS_DJI",
    "NS_PARROT",
    "NS_SENSEFLY",
    "NS_SENSEFLY_CAMERA",
    "OBLIQUE_GIMBAL_DEG",
    "READERS",
    "Reading",
    "TagReader",
    "XmpFields",
    "exif_make",
    "read_tags",
    "xmp_altitude",
    "xmp_relative_altitude",
    "xmp_fields",
]

#: (namespace URI, local name) -> text of an XMP property (attribute or simple element).
XmpFields = Mapping[tuple[str, str], str]

NS_DJI = "http://www.dji.com/drone-dji/1.0"
NS_SENSEFLY = "http://ns.sensefly.com/sensefly/1.0"
NS_SENSEFLY_CAMERA = "http://ns.sensefly.com/camera/1.0"
NS_PARROT = "http://www.parrot.com/drone-parrot/1.0"
NS_CAMERA = "http://pix4d.com/camera/1.0"

#: A gimbal this far from nadir (deg) is an oblique camera: its own angles are used.
OBLIQUE_GIMBAL_DEG = 10.0


@dataclass(frozen=True)
class Reading:
    """What one tag family says of an image: the platform ``attitude`` (None: the family's
    tags are incomplete), a ``mounting`` when the camera is not the nadir mount, and a WGS84
    ``position`` (lat, lon, alt) when the family carries one."""

    attitude: dict[str, float] | None
    mounting: dict[str, float] | None = None
    position: dict[str, float] | None = None


@dataclass(frozen=True)
class TagReader:
    """One row of :data:`READERS`: who writes the tags, which tags, and the reader."""

    name: str
    vendors: str
    tags: str
    read: Callable[[XmpFields, str], Reading]


def xmp_fields(packet: bytes | str | None) -> dict[tuple[str, str], str]:
    """Every simple property of an XMP packet, keyed by (namespace URI, local name), parsed
    with defusedxml (as Pillow's ``getxmp``, which drops the namespaces). Attributes of
    ``rdf:Description`` and elements holding text both count; an unreadable packet gives
    nothing."""
    if not packet:
        return {}
    from defusedxml import ElementTree

    try:
        root = ElementTree.fromstring(packet)
    except (ElementTree.ParseError, ValueError):  # defusedxml's refusals are ValueErrors
        return {}
    found: dict[tuple[str, str], str] = {}

    def add(tag: str, value: str) -> None:
        if not tag.startswith("{"):
            return
        uri, _, local = tag[1:].partition("}")
        found.setdefault((_namespace(uri), local), value.strip())

    for element in root.iter():
        for tag, value in element.attrib.items():
            add(tag, value)
        if len(element) == 0 and element.text and element.text.strip():
            add(element.tag, element.text)
    return found


def _namespace(uri: str) -> str:
    return uri.strip().lower().rstrip("/")


def _number(fields: XmpFields, namespaces: tuple[str, ...], name: str) -> float | None:
    for ns in namespaces:
        raw = fields.get((ns, name))
        if raw is None:
            continue
        try:
            if "/" in raw:  # XMP rationals ("1234/100")
                num, den = raw.split("/", 1)
                x = float(num) / float(den)
            else:
                x = float(raw)
        except (ValueError, ZeroDivisionError):
            return None
        return x if math.isfinite(x) else None
    return None


def _all(*values: float | None) -> bool:
    return all(v is not None for v in values)


def _position(
    fields: XmpFields, ns: str, lat: str, lons: tuple[str, ...], alt: str
) -> dict[str, float] | None:
    la = _number(fields, (ns,), lat)
    lo = next((v for v in (_number(fields, (ns,), n) for n in lons) if v is not None), None)
    al = _number(fields, (ns,), alt)
    if la is None or lo is None or al is None or not (-90 <= la <= 90 and -180 <= lo <= 180):
        return None
    return {"lat": la, "lon": lo, "alt": al}


# --------------------------------------------------------------------------- the readers


def read_dji(fields: XmpFields, make: str) -> Reading:
    """DJI ``drone-dji:`` (and Autel's EVO II / XT705 series, which write DJI's namespace).

    The convention that fits real DJI data (``shared/fixtures/brighton-beach/README.md``):
    ``R_ned_cam = Rz(FlightYaw) Ry(FlightRoll) Rx(-FlightPitch)`` with the camera looking
    straight down and the image top toward the nose, i.e. ``yaw = FlightYaw``, ``pitch =
    FlightRoll``, ``roll = -FlightPitch`` with the zero mounting (checked on the Brighton
    Beach images). When the gimbal is tilted (``GimbalPitch`` more than 10 deg from -90, an
    oblique photo) or the flight angles are missing, the gimbal's own angles: ``yaw =
    GimbalYaw`` and a mounting pitch of ``90 + GimbalPitch`` (forward tilt; gimbal roll
    taken as 0; not checked on real oblique data). Position: ``GpsLatitude``,
    ``GpsLongitude`` (or DJI's ``GpsLongtitude``), ``AbsoluteAltitude``."""
    ns = (NS_DJI,)
    fy, fp, fr = (_number(fields, ns, f"Flight{k}Degree") for k in ("Yaw", "Pitch", "Roll"))
    gy, gp = _number(fields, ns, "GimbalYawDegree"), _number(fields, ns, "GimbalPitchDegree")
    position = _position(
        fields, NS_DJI, "GpsLatitude", ("GpsLongitude", "GpsLongtitude"), "AbsoluteAltitude"
    )
    oblique = gp is not None and abs(gp + 90.0) > OBLIQUE_GIMBAL_DEG
    if fy is not None and fp is not None and fr is not None and not oblique:
        return Reading({"yaw": fy, "pitch": fr, "roll": -fp}, None, position)
    if gy is not None and gp is not None:
        return Reading({"yaw": gy, "pitch": 0.0, "roll": 0.0}, {"pitch": 90.0 + gp}, position)
    return Reading(None, None, position)


def read_sensefly(fields: XmpFields, make: str) -> Reading:
    """senseFly's own ``sensefly:`` namespace (Swinglet CAM, early eBee): the autopilot's
    ``Heading``, ``PitchAngle`` and ``RollAngle`` (degrees) for a camera fixed in the
    airframe, looking down, no gimbal: ``yaw = Heading``, ``pitch = PitchAngle``, ``roll =
    RollAngle`` with the zero mounting (image top toward the nose). The heading and the
    mounting are checked on real Swinglet images (``shared/fixtures/pos-tags``: the heading
    follows the direction between consecutive GPS positions, and the overlapping pair's
    pixels move toward the image bottom, the camera's motion turned by the heading following
    the track to 19 deg); the signs of pitch and roll are the aerospace ones assumed, not
    checked (the fixtures' few degrees cannot show them). Position: ``Latitude``, ``Longitude``,
    ``AltitudeWGS84``."""
    ns = (NS_SENSEFLY,)
    heading, pitch, roll = (_number(fields, ns, k) for k in ("Heading", "PitchAngle", "RollAngle"))
    position = _position(fields, NS_SENSEFLY, "Latitude", ("Longitude",), "AltitudeWGS84")
    if heading is None or pitch is None or roll is None:
        return Reading(None, None, position)
    return Reading({"yaw": heading, "pitch": pitch, "roll": roll}, None, position)


def read_parrot(fields: XmpFields, make: str) -> Reading:
    """Parrot's ``drone-parrot:`` namespace (ANAFI family): the gimbal camera's
    ``CameraYawDegree`` and ``CameraPitchDegree`` (-90 looking straight down, 0 at the
    horizon, as DJI's gimbal), read as DJI's gimbal angles are: ``yaw = CameraYaw`` and a
    mounting pitch of ``90 + CameraPitch`` (gimbal roll taken as 0). From Parrot's photo
    metadata documentation and the readers that use these tags; not checked on real
    images."""
    ns = (NS_PARROT,)
    yaw, pitch = _number(fields, ns, "CameraYawDegree"), _number(fields, ns, "CameraPitchDegree")
    if yaw is None or pitch is None:
        return Reading(None)
    return Reading({"yaw": yaw, "pitch": 0.0, "roll": 0.0}, {"pitch": 90.0 + pitch})


def read_camera(fields: XmpFields, make: str) -> Reading:
    """The Pix4D ``Camera:`` namespace (``Camera:Yaw``, ``Camera:Pitch``, ``Camera:Roll``,
    degrees), written by MicaSense (RedEdge-MX, Altum), Sentera, Parrot Sequoia, senseFly
    eBee (under senseFly's own ``Camera`` namespace URI), older Autel firmware and others.
    OpenDroneMap's reader (``opendm/photo.py``) takes them as the platform's attitude for a
    nadir camera: yaw clockwise from north with the image top forward, pitch 0 looking
    straight down (+90 forward), roll 0 level, so ``yaw, pitch, roll`` are ours with the
    zero mounting; for senseFly (its namespace, or EXIF ``Make`` senseFly) ODM negates the
    roll, and so do we. From ODM's reader and the vendors' docs, not checked on real
    images."""
    ns = (NS_CAMERA, NS_SENSEFLY_CAMERA)
    yaw, pitch, roll = (_number(fields, ns, k) for k in ("Yaw", "Pitch", "Roll"))
    if yaw is None or pitch is None or roll is None:
        return Reading(None)
    sensefly = make.strip().lower() == "sensefly" or (NS_SENSEFLY_CAMERA, "Roll") in fields
    return Reading({"yaw": yaw, "pitch": pitch, "roll": -roll if sensefly else roll})


#: The tag families read, in order: the first that gives an attitude is used.
READERS: tuple[TagReader, ...] = (
    TagReader(
        "dji",
        "DJI, Autel EVO II",
        "drone-dji:Flight{Yaw,Pitch,Roll}Degree, else Gimbal{Yaw,Pitch}Degree",
        read_dji,
    ),
    TagReader(
        "sensefly",
        "senseFly Swinglet CAM, early eBee",
        "sensefly:Heading, PitchAngle, RollAngle",
        read_sensefly,
    ),
    TagReader(
        "parrot",
        "Parrot ANAFI family",
        "drone-parrot:CameraYawDegree, CameraPitchDegree",
        read_parrot,
    ),
    TagReader(
        "camera",
        "MicaSense, Sentera, Parrot Sequoia, senseFly eBee, older Autel, others",
        "Camera:Yaw, Camera:Pitch, Camera:Roll",
        read_camera,
    ),
)


def read_tags(fields: XmpFields, make: str = "") -> tuple[Reading, str | None]:
    """The first reading of :data:`READERS` with an attitude and its reader's name; else a
    reading with the first position found (or nothing) and None."""
    position = None
    for reader in READERS:
        reading = reader.read(fields, make)
        if reading.attitude is not None:
            if reading.position is None and position is not None:
                reading = Reading(reading.attitude, reading.mounting, position)
            return reading, reader.name
        position = position or reading.position
    return Reading(None, None, position), None


def xmp_altitude(fields: XmpFields) -> float | None:
    """An altitude in the XMP for an image whose EXIF GPS has none: DJI's
    ``AbsoluteAltitude`` or senseFly's ``AltitudeWGS84``."""
    dji = _number(fields, (NS_DJI,), "AbsoluteAltitude")
    return dji if dji is not None else _number(fields, (NS_SENSEFLY,), "AltitudeWGS84")


def xmp_relative_altitude(fields: XmpFields) -> float | None:
    """DJI's ``RelativeAltitude``: metres above the take-off point (the ground of a flat
    site, for a matcher that needs the ground's height); None elsewhere."""
    return _number(fields, (NS_DJI,), "RelativeAltitude")


def exif_make(exif: Mapping[int, Any]) -> str:
    """EXIF ``Make`` (tag 271) as text ('' when absent)."""
    make = exif.get(271, "")
    if isinstance(make, bytes):
        make = make.decode("latin-1", "replace")
    return str(make).strip("\x00 ")
