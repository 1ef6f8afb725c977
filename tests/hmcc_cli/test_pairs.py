"""``hmcc pairs``: COLMAP's pairs file chosen by footprint overlap; bad input exits 2."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from hmcc_cli import main
from tests.support.shared_data import BRIGHTON, SHARED

IMAGES = BRIGHTON / "images"
CALITERRA = SHARED / "fixtures" / "caliterra" / "images"
ERROR_LINE = re.compile(r"^error: \S.*: \S.*$")


def _reference() -> dict[tuple[str, str], float]:
    """The fixtures' pairs (image names) and their footprint overlaps."""
    out = {}
    for path in BRIGHTON.glob("pair_*.json"):
        doc = json.loads(path.read_text())
        a, b = (doc[k]["id"] + ".JPG" for k in ("image1", "image2"))
        out[(min(a, b), max(a, b))] = doc["footprint_overlap"]
    return out


def _pairs(path: Path) -> set[tuple[str, str]]:
    lines = [line.split() for line in path.read_text().splitlines()]
    assert all(len(f) == 2 for f in lines)
    return {(min(f), max(f)) for f in lines}


def _error(code: int, capsys: pytest.CaptureFixture[str]) -> str:
    out, err = capsys.readouterr()
    assert code == 2 and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and ERROR_LINE.match(lines[0]), err
    return lines[0]


def test_brighton_pairs_include_the_reference_pairs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """POS from EXIF + DJI XMP, ground at the take-off point: the default 0.5 keeps every
    reference pair whose fixture overlap is above 0.5 (and no pair twice); 0.1 keeps all 14."""
    reference = _reference()
    assert len(reference) == 14
    out = tmp_path / "pairs.txt"
    assert main(["pairs", "--images", str(IMAGES), "-o", str(out)]) == 0
    summary = capsys.readouterr().out
    assert "take-off point" in summary
    chosen = _pairs(out)
    assert len(chosen) == len(out.read_text().splitlines())
    wanted = {p for p, overlap in reference.items() if overlap > 0.5}
    assert len(wanted) == 9 and wanted <= chosen
    assert len(chosen) < 18 * 17 // 2 // 3  # far fewer than exhaustive
    wide = tmp_path / "wide.txt"
    assert main(["pairs", "--images", str(IMAGES), "--min-overlap", "0.1", "-o", str(wide)]) == 0
    assert set(reference) <= _pairs(wide)
    capped = tmp_path / "capped.txt"
    argv = ["pairs", "--images", str(IMAGES), "--min-overlap", "0.1", "--max-per-image", "3"]
    assert main([*argv, "-o", str(capped)]) == 0
    assert _pairs(capped) < _pairs(wide)
    partners = tmp_path / "partners.txt"
    assert main(["pairs", "--images", str(IMAGES), "--min-partners", "4", "-o", str(partners)]) == 0
    assert "4 largest" in capsys.readouterr().out
    names = [n for pair in _pairs(partners) for n in pair]
    assert chosen < _pairs(partners) and min(names.count(n) for n in set(names)) >= 4


def test_a_pose_file_and_an_explicit_ground(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """ODM's geo.txt without angles (positions only): the track gives the attitudes."""
    lines = ["EPSG:4326"]
    for path in sorted(BRIGHTON.glob("pair_*.json")):
        doc = json.loads(path.read_text())
        for key in ("image1", "image2"):
            im = doc[key]
            lines.append(f"{im['id']}.JPG {im['lon']} {im['lat']} {im['absolute_altitude']}")
    geo = tmp_path / "geo.txt"
    geo.write_text("\n".join(dict.fromkeys(lines)) + "\n")
    out = tmp_path / "pairs.txt"
    argv = ["pairs", "--images", str(IMAGES), "--poses", str(geo), "--ground-z", "158.5"]
    assert main([*argv, "-o", str(out)]) == 0
    summary = capsys.readouterr().out
    assert "attitude estimated" in summary and "no usable pose" in summary  # 2 images unnamed
    assert ("DJI_0033.JPG", "DJI_0034.JPG") in _pairs(out)


def test_caliterra_gps_only(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """No attitude, no height above ground: the flying height is asked for, then given."""
    out = tmp_path / "pairs.txt"
    line = _error(main(["pairs", "--images", str(CALITERRA), "-o", str(out)]), capsys)
    assert "--ground-z or --flying-height" in line
    assert main(["pairs", "--images", str(CALITERRA), "--flying-height", "60", "-o", str(out)]) == 0
    assert "75 images have a position and no attitude" in capsys.readouterr().out
    chosen = _pairs(out)
    assert ("IMG_9367.jpg", "IMG_9368.jpg") in chosen
    assert 75 < len(chosen) < 75 * 74 // 2


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--min-overlap", "1.5"], "--min-overlap"),
        (["--max-per-image", "0"], "--max-per-image"),
        (["--min-partners", "-1"], "--min-partners"),
        (["--flying-height", "-3"], "--flying-height"),
        (["--max-range", "0"], "--max-range"),
        (["--ground-z", "500"], "must lie below it"),
    ],
)
def test_bad_options(
    extra: list[str], needle: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "pairs.txt"
    line = _error(main(["pairs", "--images", str(IMAGES), *extra, "-o", str(out)]), capsys)
    assert needle in line
    assert not out.exists()


def test_bad_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = str(tmp_path / "pairs.txt")
    line = _error(main(["pairs", "--images", str(tmp_path / "nope"), "-o", out]), capsys)
    assert "no such image folder" in line
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "no images" in _error(main(["pairs", "--images", str(empty), "-o", out]), capsys)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "a.jpg").write_bytes(b"not a jpeg")
    line = _error(main(["pairs", "--images", str(broken), "-o", out]), capsys)
    assert "a.jpg" in line
    bad_poses = tmp_path / "poses.csv"
    bad_poses.write_text("image,lat,lon,alt,yaw,pitch,roll\nDJI_0018.JPG,46.8,x,198,0,0,0\n")
    argv = ["pairs", "--images", str(IMAGES), "--poses", str(bad_poses), "-o", out]
    assert f"{bad_poses}:2" in _error(main(argv), capsys)
    argv = ["pairs", "--images", str(IMAGES), "--database", str(tmp_path / "no.db"), "-o", out]
    assert "no such database" in _error(main(argv), capsys)


def test_cameras_from_a_database(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--database``: the images and cameras COLMAP holds (here the fixtures' f = 1170.178 px,
    COLMAP's pixel centre at 0.5) instead of the EXIF focal; the reference pairs still in."""
    import pycolmap

    db_path = tmp_path / "database.db"
    db = pycolmap.Database.open(str(db_path))
    try:
        camera = pycolmap.Camera(
            model="PINHOLE", width=2000, height=1125, params=[1170.178, 1170.178, 1000.0, 562.5]
        )
        camera_id = db.write_camera(camera)
        for path in sorted(IMAGES.glob("*.JPG")):
            db.write_image(pycolmap.Image(name=path.name, camera_id=camera_id))
    finally:
        db.close()
    out = tmp_path / "pairs.txt"
    argv = ["pairs", "--images", str(IMAGES), "--database", str(db_path), "-o", str(out)]
    assert main(argv) == 0
    capsys.readouterr()
    wanted = {p for p, overlap in _reference().items() if overlap > 0.55}
    assert wanted <= _pairs(out)
