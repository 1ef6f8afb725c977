"""hmcc_colmap.poses: EXIF GPS + XMP of the real images, and the pose files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hmcc_colmap import ColmapInputError
from hmcc_colmap.poses import (
    ImagePose,
    image_pose,
    load_pose_file,
    read_image_poses,
    with_prior_positions,
)
from hmcc_schema.convert import to_rough_pose
from hmcc_schema.models import PoseModel
from tests.support.shared_data import BRIGHTON

P = np.diag([-1.0, -1.0, 1.0])  # the 180 deg turn of strip 1's pixels


@pytest.mark.parametrize(
    ("pair_file", "rotated"),
    [
        ("pair_DJI_0030_DJI_0031.json", False),
        ("pair_DJI_0019_DJI_0020.json", False),
        ("pair_DJI_0024_DJI_0025.json", True),
    ],
)
def test_dji_tags_give_the_fixtures_convention(pair_file: str, rotated: bool) -> None:
    """Read with Pillow, the EXIF GPS and the DJI flight angles give the fixture's rotation
    (the convention that fits the real data) and position; for strip 1, whose pixels were
    turned after capture, the tags' rotation is the fixture's without that turn."""
    fixture = json.loads((BRIGHTON / pair_file).read_text())["image1"]
    pose = image_pose(BRIGHTON / "images" / f"{fixture['id']}.JPG")
    assert pose.pose is not None
    assert pose.position == pytest.approx(
        {"lat": fixture["lat"], "lon": fixture["lon"], "alt": fixture["gps_altitude"]}
    )
    assert pose.attitude == {
        "yaw": fixture["flight_yaw"],
        "pitch": fixture["flight_roll"],
        "roll": -fixture["flight_pitch"],
    }
    R = to_rough_pose(PoseModel.model_validate(pose.pose)).R_world_to_cam
    expected = np.asarray(fixture["R_world_to_cam"])
    np.testing.assert_allclose(P @ R if rotated else R, expected, atol=1e-9)


def test_images_missing_from_the_folder_are_named(tmp_path: Path) -> None:
    with pytest.raises(ColmapInputError, match=r"2 of the database's 2 images are not in"):
        read_image_poses(tmp_path, ["DJI_0030.JPG", "DJI_0031.JPG"])
    poses = read_image_poses(BRIGHTON / "images", ["DJI_0030.JPG"])
    assert poses["DJI_0030.JPG"].pose is not None


def test_an_image_is_read_again_once_its_file_changes(tmp_path: Path) -> None:
    import shutil

    from PIL import Image

    name = "DJI_0030.JPG"
    shutil.copy(BRIGHTON / "images" / name, tmp_path / name)
    first = read_image_poses(tmp_path, [name])[name]
    assert first.position is not None
    first.position["lat"] = 0.0  # the caller's copy, not the remembered one
    again = read_image_poses(tmp_path, [name])[name]
    assert again.position is not None and again.position["lat"] != 0.0
    Image.new("RGB", (64, 48)).save(tmp_path / name)  # other size: no tags any more
    assert read_image_poses(tmp_path, [name])[name].pose is None


def test_an_image_without_tags_has_no_usable_pose(tmp_path: Path) -> None:
    from PIL import Image

    Image.new("RGB", (64, 48)).save(tmp_path / "plain.jpg")
    pose = image_pose(tmp_path / "plain.jpg")
    assert pose.pose is None
    assert pose.why_unusable == "no position and no attitude in the image metadata (EXIF GPS, XMP)"


KNOWN = ["a.jpg", "b.jpg", "c.jpg"]


def _file(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_odm_geo_txt_in_wgs84_and_in_utm(tmp_path: Path) -> None:
    geo = _file(
        tmp_path,
        "geo.txt",
        "EPSG:4326\n"
        "a.jpg -91.99 46.84 198.6 46.2 1.0 -2.0 5 10 label\n"
        "b.jpg -91.98 46.85 198.7\n"
        "c.jpg -91.97 46.86 198.8 0 0 0\n",
    )
    poses = load_pose_file(geo, KNOWN)
    assert poses["a.jpg"].pose == {
        "position": {"lat": 46.84, "lon": -91.99, "alt": 198.6},
        "attitude": {"yaw": 46.2, "pitch": 1.0, "roll": -2.0},
    }
    assert poses["b.jpg"].pose is None and poses["b.jpg"].position is not None
    assert poses["c.jpg"].attitude is None  # all zero: "not available" in ODM's docs
    utm = _file(tmp_path, "utm.txt", "WGS84 UTM 15N\na.jpg 500100.5 5187000.25 198.6 10 0 0\n")
    assert load_pose_file(utm, KNOWN)["a.jpg"].position == {
        "x": 500100.5,
        "y": 5187000.25,
        "z": 198.6,
    }


def test_the_two_csv_forms(tmp_path: Path) -> None:
    geo = _file(
        tmp_path,
        "poses.csv",
        "image,lat,lon,alt,yaw,pitch,roll\na.jpg,46.84,-91.99,198.6,46.2,1,-2\n",
    )
    assert load_pose_file(geo, KNOWN)["a.jpg"].pose == {
        "position": {"lat": 46.84, "lon": -91.99, "alt": 198.6},
        "attitude": {"yaw": 46.2, "pitch": 1.0, "roll": -2.0},
    }
    local = _file(tmp_path, "opk.csv", "image,x,y,z,omega,phi,kappa\nb.jpg,1,2,100,0.5,-0.5,-46\n")
    assert load_pose_file(local, KNOWN)["b.jpg"].pose == {
        "position": {"x": 1.0, "y": 2.0, "z": 100.0},
        "attitude": {"omega": 0.5, "phi": -0.5, "kappa": -46.0},
    }


def test_a_json_file_takes_any_api_pose(tmp_path: Path) -> None:
    R = [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]
    doc = {
        "a.jpg": {"position": {"x": 1, "y": 2, "z": 3}, "attitude": {"matrix": R}},
        "b.jpg": {
            "position": {"lat": 46.8, "lon": -92.0, "alt": 200},
            "attitude": {"yaw": 10, "pitch": 0, "roll": 0},
            "mounting": {"pitch": 45},
        },
    }
    poses = load_pose_file(_file(tmp_path, "poses.json", json.dumps(doc)), KNOWN)
    assert poses["a.jpg"].pose is not None
    assert poses["a.jpg"].pose["attitude"] == {"matrix": R}
    assert poses["b.jpg"].pose is not None
    assert poses["b.jpg"].pose["mounting"]["pitch"] == 45


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        (
            "geo.txt",
            "EPSG:4326\na.jpg 1 2 3\nzzz.jpg 1 2 3\n",
            r"geo.txt:3: image 'zzz.jpg' is not in",
        ),
        ("geo.txt", "EPSG:4326\na.jpg 1 north 3\n", r"geo.txt:2: expected 'image x y"),
        ("geo.txt", "a.jpg 1 2 3\n", r"geo.txt:1: expected a projection"),
        ("p.csv", "image,lat,lon,alt,yaw,pitch,roll\na.jpg,1,2,3,4,5\n", r"p.csv:2: expected an"),
        (
            "p.csv",
            "image,lat,lon,alt,yaw,pitch,roll\nq.jpg,1,2,3,4,5,6\n",
            r"p.csv:2: image 'q.jpg'",
        ),
        ("p.csv", "image,east,north,up\na.jpg,1,2,3\n", r"p.csv:1: unknown CSV header"),
        ("p.json", '{"a.jpg": {"position": {"x": 1}}}', r"p.json: a\.jpg\.(position|attitude)"),
        ("p.json", '{"a.jpg": ', r"p.json: not valid JSON"),
        (
            "p.json",
            '{"nope.jpg": {"position": {"x": 1, "y": 2, "z": 3}, "attitude": '
            '{"yaw": 0, "pitch": 0, "roll": 0}}}',
            r"p.json: image 'nope.jpg' is not in",
        ),
    ],
)
def test_bad_pose_files_say_where(tmp_path: Path, name: str, text: str, message: str) -> None:
    with pytest.raises(ColmapInputError, match=message):
        load_pose_file(_file(tmp_path, name, text), KNOWN)


def test_pose_priors_fill_positions_never_attitudes() -> None:
    prior = {"lat": 1.0, "lon": 2.0, "alt": 3.0}
    poses = with_prior_positions(
        {
            "a.jpg": ImagePose("src", None, {"yaw": 1.0, "pitch": 0.0, "roll": 0.0}),
            "b.jpg": ImagePose("src", {"x": 0.0, "y": 0.0, "z": 9.0}, None),
        },
        {"a.jpg": prior, "b.jpg": prior, "c.jpg": prior},
    )
    assert poses["a.jpg"].pose == {
        "position": prior,
        "attitude": {"yaw": 1.0, "pitch": 0.0, "roll": 0.0},
    }
    assert poses["b.jpg"].position == {"x": 0.0, "y": 0.0, "z": 9.0}  # the source's stays
    assert poses["b.jpg"].pose is None and poses["c.jpg"].pose is None
    assert poses["c.jpg"].why_unusable == "no attitude in the COLMAP pose_priors (position only)"


def test_a_pose_out_of_range_names_its_line(tmp_path: Path) -> None:
    csv_file = _file(
        tmp_path,
        "p.csv",
        "image,lat,lon,alt,yaw,pitch,roll\na.jpg,46.8,-92,200,0,0,0\nb.jpg,146.8,-92,200,0,0,0\n",
    )
    with pytest.raises(ColmapInputError, match=r"p.csv:3: b.jpg: position.lat"):
        load_pose_file(csv_file, KNOWN)


def test_the_takeoff_ground_is_the_median_altitude_less_dji_relative_altitude() -> None:
    """DJI's RelativeAltitude is read with the pose; the take-off point's height is each
    image's altitude less it, the median over the images that carry it."""
    from hmcc_colmap.poses import image_pose, takeoff_ground

    names = ["DJI_0018.JPG", "DJI_0019.JPG", "DJI_0020.JPG"]
    sources = {n: image_pose(BRIGHTON / "images" / n) for n in names}
    assert sources["DJI_0018.JPG"].height_above_takeoff == pytest.approx(39.8)
    altitudes = {n: s.position["alt"] for n, s in sources.items() if s.position}
    ground, count = takeoff_ground(altitudes, sources) or (None, 0)
    assert count == 3
    expected = sorted(a - (sources[n].height_above_takeoff or 0) for n, a in altitudes.items())[1]
    assert ground == pytest.approx(expected)
    assert takeoff_ground(altitudes, {}) is None
