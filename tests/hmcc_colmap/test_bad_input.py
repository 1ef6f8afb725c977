"""``hmcc colmap`` on input it cannot use: one line on standard error, exit 2, and the
database byte for byte as it was."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pycolmap
import pytest

from hmcc_cli import main
from tests.hmcc_colmap.dbs import db_from_pairs, digest, pose_file, sim_pair
from tests.support.procs import free_port


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str], message: str) -> None:
    assert main(["colmap", *argv, "--processes", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("error: ") and message in err, err


@pytest.fixture
def matched(tmp_path: Path) -> tuple[Path, Path]:
    pair = sim_pair(1)
    db = tmp_path / "db.db"
    db_from_pairs(db, [pair])
    return db, pose_file(tmp_path / "poses.json", [pair])


def test_a_missing_database(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _refused([str(tmp_path / "nope.db"), "--images", str(tmp_path)], capsys, "no such database")
    assert not (tmp_path / "nope.db").exists()


def test_a_file_that_is_no_colmap_database(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = tmp_path / "notes.db"
    text.write_text("hello")
    _refused([str(text)], capsys, "not an SQLite database")
    old = tmp_path / "old.db"
    con = sqlite3.connect(old)
    for table in ("cameras", "images", "keypoints", "matches", "two_view_geometries"):
        con.execute(f"CREATE TABLE {table} (x INTEGER)")
    con.commit()
    con.close()
    before = digest(old)
    _refused([str(old)], capsys, "a database of COLMAP < 4")
    assert digest(old) == before


def test_a_database_without_matches(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pair = sim_pair(1)
    db = tmp_path / "db.db"
    db_from_pairs(db, [pair], matches=False)
    before = digest(db)
    _refused(
        [str(db), "--poses", str(pose_file(tmp_path / "p.json", [pair]))], capsys, "no matches"
    )
    assert digest(db) == before


def test_an_image_folder_without_the_images(
    matched: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db, _ = matched
    before = digest(db)
    empty = tmp_path / "images"
    empty.mkdir()
    _refused([str(db), "--images", str(empty)], capsys, "2 of the database's 2 images are not")
    _refused([str(db), "--images", str(tmp_path / "nowhere")], capsys, "no such image folder")
    assert digest(db) == before


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "EPSG:4326\np0a.jpg -91.99 46.84 198\nother.jpg -91.99 46.84 198\n",
            "image 'other.jpg' is not in the database",
        ),
        ("EPSG:4326\np0a.jpg -91.99 46.84 198 ten 0 0\n", "geo.txt:2: expected 'image x y"),
    ],
)
def test_a_pose_file_that_does_not_fit(
    matched: tuple[Path, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    text: str,
    message: str,
) -> None:
    db, _ = matched
    before = digest(db)
    geo = tmp_path / "geo.txt"
    geo.write_text(text)
    _refused([str(db), "--poses", str(geo)], capsys, message)
    assert digest(db) == before


def test_a_camera_model_we_do_not_read(
    matched: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    db, poses = matched
    colmap = pycolmap.Database.open(str(db))
    camera = colmap.read_camera(1)
    fisheye = pycolmap.Camera(
        camera_id=1,
        model="OPENCV_FISHEYE",
        width=camera.width,
        height=camera.height,
        params=[4000, 4000, 3000, 2000, 0, 0, 0, 0],
    )
    colmap.update_camera(fisheye)
    colmap.close()
    before = digest(db)
    _refused([str(db), "--poses", str(poses)], capsys, "model OPENCV_FISHEYE is not supported")
    assert digest(db) == before


def test_a_pairs_file_naming_unknown_images(
    matched: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db, poses = matched
    before = digest(db)
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("p0a.jpg p0b.jpg\np0a.jpg ghost.jpg\n")
    _refused([str(db), "--poses", str(poses), "--pairs", str(pairs)], capsys, "pairs.txt:2")
    assert digest(db) == before


def test_unknown_params(matched: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    db, poses = matched
    before = digest(db)
    argv = [str(db), "--poses", str(poses), "--params", '{"plus": {"threshold_px": -1}}']
    _refused(argv, capsys, "--params: plus.threshold_px")
    assert digest(db) == before


def test_a_model_the_method_does_not_fit(
    matched: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """hmcc-plus (the default) fits F alone: an essential model is refused before anything is
    verified, not pair by pair."""
    db, poses = matched
    before = digest(db)
    argv = [str(db), "--poses", str(poses), "--params", '{"ransac": {"model": "essential"}}']
    _refused(argv, capsys, "--params: ransac.model: hmcc-plus fits a fundamental matrix")
    assert digest(db) == before


def test_a_good_run_after_all_that(
    matched: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db, poses = matched
    report = tmp_path / "report.json"
    argv = ["colmap", str(db), "--poses", str(poses), "--processes", "0", "--report", str(report)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "verified 1 pair (" in out and report.is_file()


def test_an_unreachable_service(
    matched: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """Not the caller's input: exit 1, one line, and the database untouched (the service is
    asked before the database is opened for writing)."""
    db, poses = matched
    before = digest(db)
    url = f"http://127.0.0.1:{free_port()}"
    assert main(["colmap", str(db), "--poses", str(poses), "--url", url]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: {url}:") and "Traceback" not in err, err
    assert digest(db) == before
