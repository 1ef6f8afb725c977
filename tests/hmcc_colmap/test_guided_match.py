"""``hmcc match`` on a small simulated database: SIFT-like features of a flat scene seen by a
strip of nadir cameras, poses from a JSON file; the matches written, then verified by
``hmcc colmap`` as after COLMAP's matching."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import orjson
import pycolmap
import pytest

from hmcc.camera import Camera
from hmcc.guided import project_points
from hmcc.pose import Pose, rotation_from_yaw_pitch_roll
from hmcc_cli import main
from hmcc_colmap.errors import ColmapInputError
from hmcc_colmap.guided_match import GuidedMatchRun, MatchOptions
from tests.support.gps_flight import stored_matches

from .dbs import digest, geometry, rows

CAM = Camera(width=1200, height=900, fx=900.0, fy=900.0, cx=599.5, cy=449.5)
HEIGHT = 100.0
#: Image name -> camera x (m): a strip along east, 30 m apart, plus one image far away.
STRIP = {"a.jpg": 0.0, "b.jpg": 30.0, "c.jpg": 60.0, "d.jpg": 30.0, "far.jpg": 5000.0}


def _scene_db(path: Path, seed: int = 0) -> dict[str, set[tuple[int, int]]]:
    """The database of :data:`STRIP` (one PINHOLE camera, keypoints and uint8 descriptors in
    COLMAP's pixels); returns the true matches of each pair ``"x.jpg y.jpg"`` (first name the
    lower image id)."""
    rng = np.random.default_rng(seed)
    n = 4000
    world = np.column_stack((rng.uniform(-80, 150, n), rng.uniform(-60, 60, n), np.zeros(n)))
    base = np.abs(rng.normal(size=(n, 128)))
    db = pycolmap.Database.open(str(path))
    ids: dict[str, np.ndarray] = {}
    try:
        camera = pycolmap.Camera(
            model="PINHOLE", width=CAM.width, height=CAM.height, params=[900, 900, 600, 450]
        )
        camera_id = db.write_camera(camera)
        for name, x in STRIP.items():
            pose = Pose(rotation_from_yaw_pitch_roll(0, 0, 0), np.array([x, 0.0, HEIGHT]))
            px, front = project_points(CAM, pose, world)
            keep = np.flatnonzero(front & CAM.in_frame(px) & (px >= 0).all(axis=1))
            keep = keep[(px[keep, 0] <= CAM.width - 1) & (px[keep, 1] <= CAM.height - 1)]
            kps = px[keep] + rng.normal(scale=0.4, size=(len(keep), 2))
            desc = base[keep] + np.abs(rng.normal(scale=0.25, size=(len(keep), 128)))
            unit = desc / np.linalg.norm(desc, axis=1, keepdims=True)
            image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
            db.write_keypoints(image_id, (kps + 0.5).astype(np.float32))
            data = np.clip(np.round(512 * unit), 0, 255).astype(np.uint8)
            db.write_descriptors(
                image_id, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, data)
            )
            ids[name] = keep
    finally:
        db.close()
    truth = {}
    names = list(STRIP)
    for k, a in enumerate(names):
        for b in names[k + 1 :]:
            where = {p: j for j, p in enumerate(ids[b])}
            truth[f"{a} {b}"] = {(i, where[p]) for i, p in enumerate(ids[a]) if p in where}
    return truth


def _poses(path: Path, skip: tuple[str, ...] = (), turned: tuple[str, ...] = ()) -> Path:
    doc = {
        name: {
            "position": {"x": x, "y": 0.0, "z": HEIGHT},
            "attitude": {"yaw": 180.0 if name in turned else 0.0, "pitch": 0.0, "roll": 0.0},
        }
        for name, x in STRIP.items()
        if name not in skip
    }
    path.write_bytes(orjson.dumps(doc))
    return path


def _matches(path: Path) -> dict[str, np.ndarray]:
    """``"x.jpg y.jpg"`` -> the stored (M, 2) matches."""
    con = sqlite3.connect(path)
    try:
        names = dict(con.execute("SELECT image_id, name FROM images"))
    finally:
        con.close()
    return {f"{names[a]} {names[b]}": m for (a, b), m in stored_matches(path).items()}


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("guided")
    raw = folder / "raw.db"
    truth = _scene_db(raw)
    return raw, truth


def _copy(raw: Path, tmp_path: Path) -> Path:
    db = tmp_path / "db.db"
    db.write_bytes(raw.read_bytes())
    return db


def test_match_then_verify_end_to_end(scene, tmp_path: Path) -> None:
    raw, truth = scene
    db = _copy(raw, tmp_path)
    poses = _poses(tmp_path / "poses.json", skip=("d.jpg",))
    report = tmp_path / "report.json"
    argv = ["match", str(db), "--poses", str(poses), "--ground-z", "0", "--report", str(report)]
    assert main([*argv, "--processes", "2"]) == 0
    doc = orjson.loads(report.read_bytes())
    stored = _matches(db)
    assert len(stored) == 10  # every pair of the five images, empty ones included
    found = {(int(i), int(j)) for i, j in stored["a.jpg b.jpg"]}
    assert len(found & truth["a.jpg b.jpg"]) >= 0.95 * len(truth["a.jpg b.jpg"])
    modes = doc["totals"]["modes"]
    assert modes["brute-force (no pose)"] == 4  # d.jpg has no pose
    assert modes["no-overlap"] == 3  # far.jpg with a, b and c
    assert modes["guided"] == 3
    rows = {f"{r['image1']} {r['image2']}": r for r in doc["pairs"]}
    assert (
        rows["a.jpg b.jpg"]["candidates_per_keypoint"]
        < 0.1 * rows["a.jpg d.jpg"]["candidates_per_keypoint"]
    )
    # brute force (d has no pose) finds the same scene: d sits where b does
    brute = {(int(i), int(j)) for i, j in stored["a.jpg d.jpg"]}
    assert len(brute & truth["a.jpg d.jpg"]) >= 0.95 * len(truth["a.jpg d.jpg"])
    # verification goes on from the same file
    assert main(["colmap", str(db), "--poses", str(poses), "--processes", "0"]) == 0
    con = sqlite3.connect(db)
    try:
        verified = con.execute("SELECT COUNT(*) FROM two_view_geometries WHERE rows > 0")
        assert verified.fetchone()[0] >= 6
    finally:
        con.close()


@pytest.mark.parametrize("processes", [0, 2])
def test_verify_writes_what_hmcc_colmap_writes_after_it(
    scene, tmp_path: Path, processes: int
) -> None:
    """``hmcc match --verify``: one command, the same matches and two-view geometries as
    ``hmcc match`` then ``hmcc colmap``; each pair's row has its inliers and time."""
    raw, _ = scene
    poses = _poses(tmp_path / "poses.json", skip=("d.jpg",))
    args = ["--poses", str(poses), "--ground-z", "0", "--processes", str(processes)]
    two = tmp_path / "two.db"
    two.write_bytes(raw.read_bytes())
    assert main(["match", str(two), *args]) == 0
    assert main(["colmap", str(two), "--poses", str(poses), "--processes", "0"]) == 0
    one = tmp_path / "one.db"
    one.write_bytes(raw.read_bytes())
    report = tmp_path / "report.json"
    assert main(["match", str(one), *args, "--verify", "--report", str(report)]) == 0

    written = rows(one)
    assert written == rows(two) and len(written) >= 6  # d.jpg's pairs too (MAGSAC++)
    for a, b in written:
        g1, g2 = geometry(one, a, b), geometry(two, a, b)
        np.testing.assert_array_equal(g1.inlier_matches, g2.inlier_matches)
        np.testing.assert_allclose(g1.F, g2.F)
    stored = _matches(one)
    for key, m in _matches(two).items():
        np.testing.assert_array_equal(stored[key], m)
    doc = orjson.loads(report.read_bytes())
    assert doc["verification"]["method"] == "hmcc-plus"
    assert doc["totals"]["verified"] == sum(1 for r in written.values() if r[1] > 0)
    by_name = {f"{r['image1']} {r['image2']}": r for r in doc["pairs"]}
    ab = by_name["a.jpg b.jpg"]
    assert (
        ab["verification"] == "verified" and 0.9 * ab["matches"] <= ab["inliers"] <= ab["matches"]
    )
    assert ab["verify_ms"] > 0
    far = by_name["a.jpg far.jpg"]  # no overlap, no matches: nothing to verify
    assert far["inliers"] == 0 and far["verify_ms"] is None


def test_verify_after_an_interrupted_run_verifies_the_pairs_matched_before(
    scene, tmp_path: Path
) -> None:
    """A run that matched some pairs and stopped before their geometries: the rerun with
    ``--verify`` verifies those too (here), not only the pairs it matches."""
    raw, _ = scene
    db = _copy(raw, tmp_path)
    poses = _poses(tmp_path / "poses.json")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("a.jpg b.jpg\n")
    args = ["--poses", str(poses), "--ground-z", "0", "--processes", "0"]
    assert main(["match", str(db), *args, "--pairs-file", str(pairs)]) == 0  # no geometries
    report = tmp_path / "report.json"
    assert main(["match", str(db), *args, "--verify", "--report", str(report)]) == 0
    doc = orjson.loads(report.read_bytes())
    assert doc["totals"]["skipped_already_matched"] == 1
    assert len(rows(db)) == 6  # a-b among them: the pairs with matches (d's and far's none)
    geometries = doc["verification"]["pairs"]
    ab = next(r for r in geometries if (r["image1"], r["image2"]) == ("a.jpg", "b.jpg"))
    assert ab["status"] == "verified"


@pytest.mark.parametrize(
    ("flags", "said"),
    [
        (["--method", "ransac"], "--method: only with --verify"),
        (["--min-inliers", "20"], "--min-inliers: only with --verify"),
        (["--verify-params", "{}"], "--verify-params: only with --verify"),
        (["--verify", "--verify-params", "{x"], "--verify-params: not JSON"),
        (["--verify", "--verify-params", '{"plus": 3}'], "--verify-params: plus:"),
        (["--verify", "--min-inliers", "0"], "--min-inliers: must be at least 1"),
    ],
)
def test_bad_verification_flags_exit_2_and_leave_the_database_untouched(
    scene, tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], said: str
) -> None:
    raw, _ = scene
    db = _copy(raw, tmp_path)
    before = digest(db)
    poses = _poses(tmp_path / "poses.json")
    assert main(["match", str(db), "--poses", str(poses), "--ground-z", "0", *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {said}") and "\n" not in err
    assert digest(db) == before


def test_an_unknown_verification_method_exits_2(scene, tmp_path: Path) -> None:
    raw, _ = scene
    db = _copy(raw, tmp_path)
    with pytest.raises(SystemExit) as e:
        main(["match", str(db), "--poses", "p.json", "--verify", "--method", "nope"])
    assert e.value.code == 2


def test_in_process_and_on_children_write_the_same_matches(scene, tmp_path: Path) -> None:
    raw, _ = scene
    poses = _poses(tmp_path / "poses.json")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("a.jpg b.jpg\nc.jpg b.jpg\n")
    stored = []
    for processes in (0, 2):
        db = tmp_path / f"db{processes}.db"
        db.write_bytes(raw.read_bytes())
        args = ["--poses", str(poses), "--ground-z", "0", "--pairs-file", str(pairs)]
        assert main(["match", str(db), *args, "--processes", str(processes)]) == 0
        stored.append(_matches(db))
    assert sorted(stored[0]) == sorted(stored[1]) == ["a.jpg b.jpg", "b.jpg c.jpg"]
    for key in stored[0]:
        np.testing.assert_array_equal(stored[0][key], stored[1][key])


def test_a_turned_image_is_matched_turned_and_named(scene, tmp_path: Path) -> None:
    """b.jpg's POS says it looks south-up (yaw 180) while its pixels look north-up."""
    raw, truth = scene
    db = _copy(raw, tmp_path)
    run = GuidedMatchRun(
        db,
        poses=_poses(tmp_path / "poses.json", turned=("b.jpg",)),
        options=MatchOptions(processes=0, ground_z=0.0),
    )
    report = run.run()
    rows = {f"{r['image1']} {r['image2']}": r for r in report["pairs"]}
    assert rows["a.jpg b.jpg"]["mode"] == "guided-turned"
    assert rows["a.jpg c.jpg"]["mode"] == "guided"
    assert report["images"]["b.jpg"]["turned_deg"] == {"180": 2}  # with a and c
    assert report["images"]["a.jpg"]["turned_deg"] == {}
    found = {(int(i), int(j)) for i, j in _matches(db)["a.jpg b.jpg"]}
    assert len(found & truth["a.jpg b.jpg"]) >= 0.95 * len(truth["a.jpg b.jpg"])


def test_a_rerun_skips_matched_pairs_unless_overwrite(scene, tmp_path: Path) -> None:
    raw, _ = scene
    db = _copy(raw, tmp_path)
    poses = _poses(tmp_path / "poses.json")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("a.jpg b.jpg\n")
    options = MatchOptions(processes=0, ground_z=0.0)
    first = GuidedMatchRun(db, poses=poses, pairs=pairs, options=options).run()
    assert first["totals"]["written"] == 1
    again = GuidedMatchRun(db, poses=poses, pairs=pairs, options=options).run()
    assert again["totals"]["skipped_already_matched"] == 1 and again["totals"]["written"] == 0
    options.overwrite = True
    over = GuidedMatchRun(db, poses=poses, pairs=pairs, options=options).run()
    assert over["totals"]["written"] == 1


def test_without_a_ground_height_nothing_is_written(scene, tmp_path: Path) -> None:
    raw, _ = scene
    db = _copy(raw, tmp_path)
    before = digest(db)
    poses = _poses(tmp_path / "poses.json")
    with pytest.raises(ColmapInputError, match="--ground-z"):
        GuidedMatchRun(db, poses=poses, options=MatchOptions(processes=0)).run()
    assert main(["match", str(db), "--processes", "0"]) == 2  # no POS source at all
    assert digest(db) == before


def test_the_flying_height_gives_the_ground(scene, tmp_path: Path) -> None:
    raw, _ = scene
    db = _copy(raw, tmp_path)
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("a.jpg b.jpg\n")
    report = GuidedMatchRun(
        db,
        poses=_poses(tmp_path / "poses.json"),
        pairs=pairs,
        options=MatchOptions(processes=0, height_m=HEIGHT),
    ).run()
    assert report["ground_z_m"] == 0.0
    assert report["pairs"][0]["mode"] == "guided"


def test_gps_only_images_take_an_attitude_from_the_track(scene, tmp_path: Path) -> None:
    """Positions without attitudes: the attitude comes from the flight track (heading east
    along the strip, image top east: a quarter turn from these cameras, found by the turns'
    search), counted; without it the pair has no pose and is matched by brute force."""
    raw, truth = scene
    poses = tmp_path / "geo.txt"  # ODM's: a projected frame, positions only
    poses.write_text(
        "EPSG:32614\n" + "".join(f"{name} {x} 0 {HEIGHT}\n" for name, x in STRIP.items())
    )
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("a.jpg b.jpg\n")
    tracked = GuidedMatchRun(
        _copy(raw, tmp_path),
        poses=poses,
        pairs=pairs,
        options=MatchOptions(processes=0, ground_z=0.0),
    )
    report = tracked.run()
    assert report["totals"]["images_attitude_estimated"] == len(STRIP)
    assert report["images"]["a.jpg"]["attitude"] == "estimated from the track"
    row = report["pairs"][0]
    assert row["mode"].startswith("guided")
    found = {(int(i), int(j)) for i, j in _matches(tracked.database)["a.jpg b.jpg"]}
    assert len(found & truth["a.jpg b.jpg"]) >= 0.95 * len(truth["a.jpg b.jpg"])
    db = tmp_path / "untracked.db"
    db.write_bytes(raw.read_bytes())
    options = MatchOptions(processes=0, ground_z=0.0, track_attitude=False)
    untracked = GuidedMatchRun(db, poses=poses, pairs=pairs, options=options).run()
    assert untracked["totals"]["modes"] == {"brute-force (no pose)": 1}


def test_a_flying_height_ignores_altitudes_that_drift(scene, tmp_path: Path) -> None:
    """b.jpg's altitude reads 60 m high (a GPS altitude drifting along the flight): one plane
    under the altitudes scales b's predictions against a's (by 160 / 100: the first pass's
    motion takes the scale out); every camera the flying height above the ground below it
    does not."""
    raw, truth = scene
    doc = orjson.loads(_poses(tmp_path / "poses.json").read_bytes())
    doc["b.jpg"]["position"]["z"] = HEIGHT + 60.0
    poses = tmp_path / "drift.json"
    poses.write_bytes(orjson.dumps(doc))
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("a.jpg b.jpg\n")
    recall, scale = {}, {}
    for name, options in {
        "plane": MatchOptions(processes=0, ground_z=0.0),
        "flying": MatchOptions(processes=0, flying_height_m=HEIGHT),
    }.items():
        db = tmp_path / f"{name}.db"
        db.write_bytes(raw.read_bytes())
        report = GuidedMatchRun(db, poses=poses, pairs=pairs, options=options).run()
        found = {(int(i), int(j)) for i, j in _matches(db)["a.jpg b.jpg"]}
        recall[name] = len(found & truth["a.jpg b.jpg"]) / len(truth["a.jpg b.jpg"])
        scale[name] = abs(np.linalg.det(report["pairs"][0]["motion_linear"])) ** 0.5
        if name == "flying":
            assert report["ground_z_source"].endswith("(--flying-height)")
    assert recall["flying"] >= 0.95
    assert abs(scale["flying"] - 1.0) < 0.02
    assert abs(scale["plane"] - (HEIGHT + 60.0) / HEIGHT) < 0.05
    with pytest.raises(ColmapInputError, match="one of"):
        GuidedMatchRun(
            _copy(raw, tmp_path),
            poses=poses,
            options=MatchOptions(processes=0, ground_z=0.0, flying_height_m=HEIGHT),
        ).run()


def test_an_exif_focal_length_far_from_the_databases_replaces_it(
    scene, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """COLMAP's prior focal length of a downscaled image can be the original's: where the
    images' EXIF focal length is more than 20 % off the database's, it is used, and said."""
    from hmcc_colmap import capture, guided_match
    from hmcc_colmap.capture import Capture

    raw, _ = scene
    images = tmp_path / "images"
    images.mkdir()
    for name in STRIP:
        (images / name).write_bytes(b"")
    focal = {"a.jpg": 360.0, "b.jpg": 950.0}  # the database says 900
    monkeypatch.setattr(
        capture,
        "read_capture",
        lambda path: Capture(
            {"width": CAM.width, "height": CAM.height, "focal": focal[path.name]}
            if path.name in focal
            else None,
            None if path.name in focal else "no EXIF focal length",
            None,
        ),
    )
    run = GuidedMatchRun(
        _copy(raw, tmp_path),
        images=images,
        poses=_poses(tmp_path / "poses.json"),
        options=MatchOptions(processes=0, ground_z=0.0, track_attitude=False),
    )
    monkeypatch.setattr(run, "_pairs", lambda infos: [])  # the cameras alone are checked
    cameras = {}
    monkeypatch.setattr(
        guided_match, "_ship_features", lambda folder, features: cameras.setdefault("done", 1)
    )
    report = run.run()
    images_report = report["images"]
    assert images_report["a.jpg"]["focal_px"] == 360.0
    assert images_report["a.jpg"]["focal_source"] == "exif"
    assert images_report["b.jpg"]["focal_source"] == "database"
    assert images_report["c.jpg"]["focal_source"] == "database"
    assert report["totals"]["images_focal_from_exif"] == 1


def _threads_here(*_args: object) -> list[tuple[int, int]]:
    """In a pool's child: its OpenCV threads and its most threaded BLAS's."""
    import cv2
    from threadpoolctl import threadpool_info

    return [(cv2.getNumThreads(), max(lib["num_threads"] for lib in threadpool_info()))]


def test_the_pools_children_run_one_blas_and_one_opencv_thread(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The limits are set in the parent before the fork, after its own OpenCV thread pool has
    run (a child that set them itself could hang), and the parent's are given back after."""
    import cv2
    from threadpoolctl import threadpool_limits

    from hmcc_colmap import guided_match

    monkeypatch.setattr(guided_match, "_match_group", _threads_here)
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        cv2.GaussianBlur(np.ones((2000, 2000), np.float32), (31, 31), 0)  # the pool has run
        run = GuidedMatchRun(tmp_path / "unused.db", options=MatchOptions(processes=2))
        run._verifier = None
        tasks: Any = [SimpleNamespace(image_id1=i) for i in range(4)]  # four groups
        with threadpool_limits(2), run._runner(tmp_path) as pooled:
            assert list(pooled(tasks)) == [(1, 1)] * 4
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(before)
