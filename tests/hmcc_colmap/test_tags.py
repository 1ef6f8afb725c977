"""hmcc_colmap.tags: the vendors' XMP attitude tags, on real senseFly tags and on packets built
from each vendor's documented tag names; each checked for what its convention means (where
the image top points, whether the camera looks down), not only for the numbers read."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hmcc_colmap.poses import image_pose
from hmcc_colmap.tags import read_tags, xmp_fields
from hmcc_schema.convert import to_rough_pose
from hmcc_schema.models import PoseModel
from tests.support.shared_data import SHARED

POS_TAGS = SHARED / "fixtures" / "pos-tags"
_POSITION = {"lat": 41.0, "lon": -83.0, "alt": 300.0}


def _bearing_deg(a: dict[str, float], b: dict[str, float]) -> float:
    """Clockwise from north, from position a to b (WGS84; a flat earth over metres)."""
    north = math.radians(b["lat"] - a["lat"])
    east = math.radians(b["lon"] - a["lon"]) * math.cos(math.radians(a["lat"]))
    return math.degrees(math.atan2(east, north)) % 360.0


def _diff_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def _view(pose: dict[str, Any]) -> tuple[float, float]:
    """(bearing of the image top, deg clockwise from north; up component of the optical
    axis) of a pose's camera in east-north-up."""
    R = to_rough_pose(PoseModel.model_validate(pose)).R_world_to_cam
    top = R.T @ np.array([0.0, -1.0, 0.0])  # camera y points to the image bottom
    axis = R.T @ np.array([0.0, 0.0, 1.0])
    return math.degrees(math.atan2(top[0], top[1])) % 360.0, float(axis[2])


def test_sensefly_heading_follows_the_flight_line() -> None:
    """Two Swinglet images one exposure apart on one line: each image's heading agrees with
    the direction between their GPS positions (within the crab of a light fixed wing in wind),
    the image top points that way and the camera looks down."""
    first = image_pose(POS_TAGS / "sensefly_IMG_0480.jpg")
    second = image_pose(POS_TAGS / "sensefly_IMG_0481.jpg")
    assert first.pose is not None and second.pose is not None
    assert "sensefly" in first.source
    assert first.position is not None and second.position is not None
    track = _bearing_deg(first.position, second.position)
    for pose in (first, second):
        assert pose.attitude is not None and pose.mounting is None
        assert _diff_deg(pose.attitude["yaw"], track) < 20.0
        top, up = _view(pose.pose)  # type: ignore[arg-type]
        assert _diff_deg(top, track) < 20.0
        assert up < -0.98  # a few degrees from straight down
    assert first.attitude == {  # the tags as they are, zero mounting
        "yaw": pytest.approx(43.87585068),
        "pitch": pytest.approx(5.340673923),
        "roll": pytest.approx(-0.05989515409),
    }
    # EXIF GPS and the senseFly tags name the same place
    assert first.position == pytest.approx(
        {"lat": 41.0370286, "lon": -83.3048093, "alt": 282.8370056}, abs=1e-5
    )


def test_sensefly_lines_flown_the_other_way_face_the_other_way() -> None:
    out = image_pose(POS_TAGS / "sensefly_IMG_0480.jpg")
    back = image_pose(POS_TAGS / "sensefly_IMG_0560.jpg")
    assert out.attitude is not None and back.attitude is not None
    assert _diff_deg(out.attitude["yaw"], back.attitude["yaw"]) > 150.0


def _packet(namespaces: dict[str, str], body: str, attributes: str = "") -> bytes:
    ns = " ".join(f'xmlns:{prefix}="{uri}"' for prefix, uri in namespaces.items())
    return (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
        'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        f'<rdf:Description rdf:about="" {ns} {attributes}>{body}</rdf:Description>'
        "</rdf:RDF></x:xmpmeta>"
    ).encode()


DJI = {"drone": "http://www.dji.com/drone-dji/1.0/"}  # Autel's prefix for DJI's namespace
PARROT = {
    "drone-parrot": "http://www.parrot.com/drone-parrot/1.0/",
    "Camera": "http://pix4d.com/camera/1.0/",
}
PIX4D = {"Camera": "http://pix4d.com/camera/1.0"}  # MicaSense writes it without the slash
SENSEFLY_CAMERA = {"Camera": "http://ns.sensefly.com/Camera/1.0/"}

VENDORS = [
    pytest.param(
        _packet(
            DJI,
            "",
            'drone:FlightYawDegree="+120.0" drone:FlightPitchDegree="0.0" '
            'drone:FlightRollDegree="0.0" drone:GimbalPitchDegree="-90.0" '
            'drone:GimbalYawDegree="+120.0"',
        ),
        "",
        "dji",
        {"yaw": 120.0, "pitch": 0.0, "roll": -0.0},
        None,
        (120.0, -1.0),
        id="autel-in-dji-namespace",
    ),
    pytest.param(
        _packet(
            DJI,
            "",
            'drone:GimbalYawDegree="-30.0" drone:GimbalPitchDegree="-45.0" '
            'drone:GimbalRollDegree="0.0"',
        ),
        "",
        "dji",
        {"yaw": -30.0, "pitch": 0.0, "roll": 0.0},
        {"pitch": 45.0},
        (330.0, -math.sqrt(0.5)),
        id="dji-oblique-gimbal",
    ),
    pytest.param(
        _packet(
            PARROT,
            "<drone-parrot:CameraYawDegree>200.0</drone-parrot:CameraYawDegree>"
            "<drone-parrot:CameraPitchDegree>-90.0</drone-parrot:CameraPitchDegree>"
            "<drone-parrot:CameraRollDegree>0.0</drone-parrot:CameraRollDegree>"
            # ANAFI writes the Pix4D tags too: its own namespace is read first
            "<Camera:Yaw>10.0</Camera:Yaw><Camera:Pitch>-90.0</Camera:Pitch>"
            "<Camera:Roll>0.0</Camera:Roll>",
        ),
        "Parrot",
        "parrot",
        {"yaw": 200.0, "pitch": 0.0, "roll": 0.0},
        {"pitch": 0.0},
        (200.0, -1.0),
        id="parrot-anafi",
    ),
    pytest.param(
        _packet(
            PIX4D,
            "<Camera:Yaw>75.5</Camera:Yaw><Camera:Pitch>2.0</Camera:Pitch>"
            "<Camera:Roll>-1.5</Camera:Roll>"
            # the light sensor's angles, in radians, in another namespace: not the attitude
            '<DLS:Yaw xmlns:DLS="http://micasense.com/DLS/1.0/">3.1</DLS:Yaw>',
        ),
        "MicaSense",
        "camera",
        {"yaw": 75.5, "pitch": 2.0, "roll": -1.5},
        None,
        (75.5, -0.99),
        id="micasense",
    ),
    pytest.param(
        _packet(PIX4D, "", 'Camera:Yaw="4500/100" Camera:Pitch="0/1" Camera:Roll="0"'),
        "Sentera",
        "camera",
        {"yaw": 45.0, "pitch": 0.0, "roll": 0.0},
        None,
        (45.0, -1.0),
        id="sentera-rationals",
    ),
    pytest.param(
        _packet(
            SENSEFLY_CAMERA,
            "<Camera:Yaw>300.0</Camera:Yaw><Camera:Pitch>1.0</Camera:Pitch>"
            "<Camera:Roll>4.0</Camera:Roll>",
        ),
        "",
        "camera",
        {"yaw": 300.0, "pitch": 1.0, "roll": -4.0},
        None,
        (300.0, -0.99),
        id="sensefly-ebee-roll-negated",
    ),
    pytest.param(
        _packet(
            PIX4D,
            "<Camera:Yaw>300.0</Camera:Yaw><Camera:Pitch>1.0</Camera:Pitch>"
            "<Camera:Roll>4.0</Camera:Roll>",
        ),
        "senseFly",
        "camera",
        {"yaw": 300.0, "pitch": 1.0, "roll": -4.0},
        None,
        (300.0, -0.99),
        id="sensefly-by-exif-make",
    ),
]


@pytest.mark.parametrize(("packet", "make", "reader", "attitude", "mounting", "view"), VENDORS)
def test_each_vendors_tags_give_its_convention(
    packet: bytes,
    make: str,
    reader: str,
    attitude: dict[str, float],
    mounting: dict[str, float] | None,
    view: tuple[float, float],
) -> None:
    reading, name = read_tags(xmp_fields(packet), make)
    assert name == reader
    assert reading.attitude == pytest.approx(attitude)
    assert reading.mounting == mounting
    pose: dict[str, Any] = {"position": _POSITION, "attitude": reading.attitude}
    if mounting is not None:
        pose["mounting"] = mounting
    top, up = _view(pose)
    assert _diff_deg(top, view[0]) < 5.0
    assert up == pytest.approx(view[1], abs=0.02)


def test_tags_without_an_attitude_give_none() -> None:
    assert read_tags(xmp_fields(b"")) == read_tags({})
    reading, name = read_tags(
        xmp_fields(_packet({"DLS": "http://micasense.com/DLS/1.0/"}, "<DLS:Yaw>1.0</DLS:Yaw>"))
    )
    assert name is None and reading.attitude is None
    assert read_tags(xmp_fields(b"<not xml"))[1] is None


def test_a_jpeg_carrying_a_vendors_packet_reads_through_the_file(tmp_path: Path) -> None:
    """The packet as Pillow writes it into a JPEG's APP1, read back by ``image_pose``; with
    no EXIF GPS the position is the vendor's XMP position."""
    from PIL import Image

    packet = _packet(
        {"sensefly": "http://ns.sensefly.com/sensefly/1.0/"},
        "<sensefly:Latitude>46.5</sensefly:Latitude><sensefly:Longitude>6.6</sensefly:Longitude>"
        "<sensefly:AltitudeWGS84>512.0</sensefly:AltitudeWGS84>"
        "<sensefly:Heading>90.0</sensefly:Heading><sensefly:PitchAngle>0.0</sensefly:PitchAngle>"
        "<sensefly:RollAngle>0.0</sensefly:RollAngle>",
    )
    path = tmp_path / "swinglet.jpg"
    Image.new("RGB", (32, 24)).save(path, xmp=packet)
    pose = image_pose(path)
    assert pose.pose == {
        "position": {"lat": 46.5, "lon": 6.6, "alt": 512.0},
        "attitude": {"yaw": 90.0, "pitch": 0.0, "roll": 0.0},
    }
    assert pose.source == "image metadata (EXIF GPS, XMP: sensefly)"


def test_sensefly_image_top_is_toward_the_nose() -> None:
    """The mounting on real pixels: between the two exposures the scene's SIFT matches move
    toward the image bottom, so that the camera's motion, turned from the image into the
    world by the read heading, follows the GPS track (19 deg apart here, with 18 matches on
    these small NIR images: the heading drifts 5 deg between them and the aircraft crabs)."""
    import cv2

    names = ("sensefly_IMG_0480.jpg", "sensefly_IMG_0481.jpg")
    first, second = (cv2.imread(str(POS_TAGS / n), cv2.IMREAD_GRAYSCALE) for n in names)
    sift = cv2.SIFT_create(nfeatures=4000, contrastThreshold=0.01)
    k1, d1 = sift.detectAndCompute(first, None)
    k2, d2 = sift.detectAndCompute(second, None)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m for m, n in knn if m.distance < 0.8 * n.distance]
    p1 = np.float32([k1[m.queryIdx].pt for m in good])
    p2 = np.float32([k2[m.trainIdx].pt for m in good])
    _, mask = cv2.findHomography(p1, p2, cv2.RANSAC, 4.0)
    inliers = mask.ravel().astype(bool)
    assert inliers.sum() >= 10
    dx, dy = np.median(p2[inliers] - p1[inliers], axis=0)
    assert dy > abs(dx)  # the scene moves down the image: the camera moves toward its top
    # the camera's motion, clockwise from the image top, then from north through the heading
    motion_in_image = math.degrees(math.atan2(-dx, dy))
    a, b = (image_pose(POS_TAGS / n) for n in names)
    assert a.pose is not None and a.position is not None and b.position is not None
    top, _ = _view(a.pose)
    assert _diff_deg(top + motion_in_image, _bearing_deg(a.position, b.position)) < 30.0
