"""hmcc_colmap.ColmapRun on databases of simulated pairs: what is written is what the core
finds, in COLMAP's conventions; reruns, fallbacks and pairs under the threshold."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import time
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
import pytest

from hmcc_colmap import ColmapRun, RunOptions
from hmcc_colmap.verify import blame
from hmcc_schema import parse_pair
from hmcc_schema.convert import to_rough_pose
from hmcc_schema.models import PoseModel
from tests.hmcc_colmap.dbs import db_from_pairs, geometry, pose_file, rows, sim_pair

INLINE = RunOptions(processes=0)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_the_written_inliers_and_F_are_the_cores_in_colmaps_pixels(tmp_path: Path) -> None:
    pairs = [sim_pair(1), sim_pair(2, views=("V", "F"))]
    db = tmp_path / "db.db"
    ids = db_from_pairs(db, pairs)
    report = ColmapRun(db, poses=pose_file(tmp_path / "p.json", pairs), options=INLINE).run()
    assert report["totals"]["verified"] == 2 and report["totals"]["fallback_pairs"] == 0
    for k, pair in enumerate(pairs):
        a, b = ids[2 * k], ids[2 * k + 1]
        # as one pair: its keypoints' x, y and the automatic plane, as hmcc colmap sends it
        alone = {k: v for k, v in pair.items() if k not in ("plane", "ground_truth")}
        for key in ("keypoints1", "keypoints2"):
            alone[key] = [row[:2] for row in pair[key]]
        expected = parse_pair(alone).verify(0)
        g = geometry(db, a, b)
        assert g.config == pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
        matches = np.asarray(pair["matches"])
        np.testing.assert_array_equal(g.inlier_matches, matches[expected.inliers])
        # F holds in COLMAP's pixels (ours + 0.5) on the written inliers
        kp1 = np.asarray(pair["keypoints1"])[:, :2] + 0.5
        kp2 = np.asarray(pair["keypoints2"])[:, :2] + 0.5
        x1 = np.column_stack((kp1[g.inlier_matches[:, 0]], np.ones(len(g.inlier_matches))))
        x2 = np.column_stack((kp2[g.inlier_matches[:, 1]], np.ones(len(g.inlier_matches))))
        Fx1, Ftx2 = x1 @ g.F.T, x2 @ g.F
        err = np.sum(x2 * Fx1, axis=1) ** 2 / (
            Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
        )
        assert np.sqrt(np.median(err)) < 0.5  # Sampson, px
        row = report["pairs"][k]
        assert row["status"] == "verified" and row["inliers"] == len(expected.inliers)
        assert row["pos_rotation_error_deg"] < 5  # simulated rough POS: a few degrees


def test_calibrated_cameras_get_E_and_the_relative_pose(tmp_path: Path) -> None:
    pair = sim_pair(3)
    db = tmp_path / "db.db"
    a, b = db_from_pairs(db, [pair], prior_focal=True)
    ColmapRun(db, poses=pose_file(tmp_path / "p.json", [pair]), options=INLINE).run()
    g = geometry(db, a, b)
    assert g.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    truth = pair["ground_truth"]["true_poses"]
    R1, R2 = (np.asarray(t["R_world_to_cam"]) for t in truth)
    C1, C2 = (np.asarray(t["center"]) for t in truth)
    R = g.cam2_from_cam1.rotation.matrix()
    assert _angle_deg(R.T @ (R2 @ R1.T)) < 1.0
    t_true = R2 @ (C1 - C2)
    t = np.asarray(g.cam2_from_cam1.translation)
    assert np.degrees(np.arccos(t @ t_true / np.linalg.norm(t) / np.linalg.norm(t_true))) < 3
    E = g.E / np.linalg.norm(g.E)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E_pose = tx @ R
    assert (
        min(
            np.abs(E - E_pose / np.linalg.norm(E_pose)).max(),
            np.abs(E + E_pose / np.linalg.norm(E_pose)).max(),
        )
        < 1e-6
    )


def test_a_rerun_skips_verified_pairs_unless_overwrite(tmp_path: Path) -> None:
    pair = sim_pair(4)
    db = tmp_path / "db.db"
    a, b = db_from_pairs(db, [pair])
    poses = pose_file(tmp_path / "p.json", [pair])
    ColmapRun(db, poses=poses, options=RunOptions(processes=0, min_inliers=500)).run()
    assert rows(db)[(a, b)][1] == 0  # under the threshold: no inliers
    again = ColmapRun(db, poses=poses, options=INLINE).run()
    assert again["totals"]["pairs"] == 0 and again["totals"]["skipped_already_verified"] == 1
    assert rows(db)[(a, b)][1] == 0
    over = ColmapRun(db, poses=poses, options=RunOptions(processes=0, overwrite=True)).run()
    assert over["totals"]["verified"] == 1 and rows(db)[(a, b)][1] > 0


def test_pairs_under_min_inliers_are_written_as_colmap_writes_them(tmp_path: Path) -> None:
    """The same database verified by COLMAP and by us with a threshold no pair reaches (600
    matches, about 300 true): the same rows (config, no inlier matches, no matrices)."""
    pairs = [sim_pair(5), sim_pair(6)]
    ours, theirs = tmp_path / "ours.db", tmp_path / "theirs.db"
    db_from_pairs(ours, pairs)
    shutil.copy(ours, theirs)
    options = pycolmap.TwoViewGeometryOptions()
    options.min_num_inliers = 500
    pycolmap.geometric_verification(str(theirs), two_view_geometry_options=options)
    run = ColmapRun(
        ours,
        poses=pose_file(tmp_path / "p.json", pairs),
        options=RunOptions(processes=0, min_inliers=500),
    ).run()
    assert run["totals"]["under_min_inliers"] == 2
    assert rows(ours) == rows(theirs)
    assert len(rows(ours)) == 2


def test_an_image_without_a_pose_sends_its_pairs_to_the_fallback(tmp_path: Path) -> None:
    pairs = [sim_pair(7), sim_pair(8)]
    db = tmp_path / "db.db"
    ids = db_from_pairs(db, pairs)
    poses = pose_file(tmp_path / "p.json", pairs, skip={"p1b.jpg"})
    report = ColmapRun(db, poses=poses, options=INLINE).run()
    t = report["totals"]
    assert t["verified"] == 2 and t["no_pose_pairs"] == 1 and t["images_without_pose"] == 1
    assert t["fallback_pairs"] == 0, "a pair without a pose is counted once, as such"
    first, second = report["pairs"]
    assert first["method"] == "hmcc-plus" and not first["fallback"]
    assert second["method"] == "magsac++" and second["fallback"]
    assert "p1b.jpg: not in the pose file" in second["fallback_reason"]
    assert report["images"]["p1b.jpg"]["pose_issue"] == "not in the pose file"
    assert len(geometry(db, ids[2], ids[3]).inlier_matches) > 100


def test_matches_beyond_the_keypoints_fail_their_pair_only(tmp_path: Path) -> None:
    """A match that indexes no keypoint (a damaged database) fails its pair, named in the
    report; the run goes on and writes the other pairs."""
    pairs = [sim_pair(7), sim_pair(8)]
    db = tmp_path / "db.db"
    ids = db_from_pairs(db, pairs)
    con = sqlite3.connect(db)
    with con:
        pair_id = pycolmap.image_pair_to_pair_id(ids[0], ids[1])
        (blob,) = con.execute("SELECT data FROM matches WHERE pair_id = ?", (pair_id,)).fetchone()
        bad = np.frombuffer(blob, dtype=np.uint32).copy()
        bad[1] = 10**6  # the first match's keypoint in the second image
        con.execute("UPDATE matches SET data = ? WHERE pair_id = ?", (bad.tobytes(), pair_id))
    con.close()
    report = ColmapRun(db, poses=pose_file(tmp_path / "p.json", pairs), options=INLINE).run()
    first, second = report["pairs"]
    assert first["status"] == "failed"
    assert "index keypoint 1000000" in first["error"] and "image 2" in first["error"]
    assert second["status"] == "verified"
    assert report["totals"]["failed"] == 1 and report["totals"]["verified"] == 1
    assert len(geometry(db, ids[2], ids[3]).inlier_matches) > 100


def test_methods_without_poses_need_no_pose_source(tmp_path: Path) -> None:
    pair = sim_pair(9)
    db = tmp_path / "db.db"
    db_from_pairs(db, [pair])
    report = ColmapRun(db, options=RunOptions(method="magsac++", processes=0)).run()
    assert report["totals"]["verified"] == 1
    assert report["pairs"][0]["method"] == "magsac++"


@pytest.mark.procs  # the compute pool's children
def test_the_compute_pool_writes_what_the_inline_run_writes(tmp_path: Path) -> None:
    pairs = [sim_pair(k) for k in range(10, 15)]
    inline, pooled = tmp_path / "inline.db", tmp_path / "pooled.db"
    ids = db_from_pairs(inline, pairs, prior_focal=True)  # CALIBRATED: E and the pose too
    shutil.copy(inline, pooled)
    poses = pose_file(tmp_path / "p.json", pairs)
    ColmapRun(inline, poses=poses, options=INLINE).run()
    pool = RunOptions(processes=2, chunk_pairs=2, in_process_max=0)
    assert ColmapRun(pooled, poses=poses, options=pool).run()["where"] == "2 processes"
    for k in range(len(pairs)):
        a, b = ids[2 * k], ids[2 * k + 1]
        here, there = geometry(inline, a, b), geometry(pooled, a, b)
        np.testing.assert_array_equal(here.inlier_matches, there.inlier_matches)
        # the relative pose, computed in the pool's child there, here in this process
        assert here.config == there.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
        for name in ("F", "E"):
            np.testing.assert_array_equal(getattr(here, name), getattr(there, name))
        np.testing.assert_array_equal(here.cam2_from_cam1.matrix(), there.cam2_from_cam1.matrix())


def test_a_run_of_few_pairs_starts_no_children(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """At most ``in_process_max`` pairs to verify: verified in this process (no pool is
    built), and the report says so; one more pair and the pool is built."""
    import hmcc_worker.pool

    built = []

    class Refused:
        def __init__(self, *args: object, **kwargs: object) -> None:
            built.append(args)
            raise RuntimeError("no pool for a small run")

    monkeypatch.setattr(hmcc_worker.pool, "ComputePool", Refused)
    pairs = [sim_pair(k) for k in range(20, 23)]
    db = tmp_path / "db.db"
    db_from_pairs(db, pairs)
    poses = pose_file(tmp_path / "p.json", pairs)
    small = RunOptions(processes=2, in_process_max=len(pairs))
    report = ColmapRun(db, poses=poses, options=small).run()
    assert report["where"] == "inline" and report["totals"]["verified"] == len(pairs)
    assert built == []
    larger = RunOptions(processes=2, in_process_max=len(pairs) - 1, overwrite=True)
    with pytest.raises(RuntimeError, match="no pool for a small run"):
        ColmapRun(db, poses=poses, options=larger).run()
    assert built == [(2,)]


def test_ctrl_c_leaves_whole_chunks_and_a_rerun_finishes(tmp_path: Path) -> None:
    """Interrupted in the middle of its second chunk, a run has written its first chunk
    whole and nothing of the second; the rerun does the rest."""
    pairs = [sim_pair(k) for k in range(20, 26)]
    db = tmp_path / "db.db"
    db_from_pairs(db, pairs)
    poses = pose_file(tmp_path / "p.json", pairs)

    def interrupt(done: int, total: int) -> None:
        if done == 3:
            raise KeyboardInterrupt

    run = ColmapRun(
        db, poses=poses, options=RunOptions(processes=0, chunk_pairs=2), progress=interrupt
    )
    with pytest.raises(KeyboardInterrupt):
        run.run()
    assert run.report["totals"]["written"] == 2 and len(rows(db)) == 2
    again = ColmapRun(db, poses=poses, options=INLINE).run()
    assert again["totals"]["skipped_already_verified"] == 2
    assert again["totals"]["verified"] == 4 and len(rows(db)) == 6


def test_ctrl_c_during_a_write_waits_for_its_end() -> None:
    from hmcc_colmap.verify import sigint_held

    finished = []
    with pytest.raises(KeyboardInterrupt), sigint_held():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        finished.append(True)
    assert finished == [True]


def test_the_images_to_blame_for_pairs_whose_pos_does_not_fit() -> None:
    """Three strips, the middle one turned: every pair across it is off. Images of the outer
    strips have as many bad pairs as good; the middle strip's have more bad: they are named,
    one after the other, and no other."""
    strips = [[f"s{s}_{k}" for k in range(4)] for s in range(3)]
    pairs = []
    for s1 in range(3):
        for s2 in range(s1, 3):
            for a in strips[s1]:
                for b in strips[s2]:
                    if a < b:
                        pairs.append((a, b, (s1 == 1) != (s2 == 1)))
    assert blame(pairs) == set(strips[1])
    assert blame([("a", "b", True)]) == set()  # one bad pair: cannot say which
    two_and_two = [("a", "b", False), ("c", "d", False)]
    two_and_two += [(x, y, True) for x in "ab" for y in "cd"]
    assert blame(two_and_two) == set("abcd")  # nothing says which group is right
    assert blame([(a, b, False) for a, b, _ in pairs]) == set()


def test_the_relative_pose_is_opencvs() -> None:
    """Of E's four decompositions, the one with the points in front of both cameras: the pose
    OpenCV's recoverPose gives, on noisy points."""
    import cv2

    from hmcc_colmap.twoview import relative_pose as _relative_pose

    rng = np.random.default_rng(0)
    for _ in range(10):
        X = np.column_stack((rng.uniform(-10, 10, (300, 2)), rng.uniform(30, 40, 300)))
        R = cv2.Rodrigues(rng.normal(0, 0.3, 3))[0]
        t = rng.normal(0, 1, 3)
        t /= np.linalg.norm(t)
        n1 = X[:, :2] / X[:, 2:] + rng.normal(0, 1e-4, (300, 2))
        X2 = X @ R.T + t
        n2 = X2[:, :2] / X2[:, 2:] + rng.normal(0, 1e-4, (300, 2))
        E, _ = cv2.findEssentialMat(n1, n2, np.eye(3), cv2.RANSAC, 0.999, 1e-3)
        _, R_cv, t_cv, _ = cv2.recoverPose(E[:3], n1, n2, np.eye(3))
        R_ours, t_ours = _relative_pose(E[:3], n1, n2)
        assert R_ours is not None and t_ours is not None
        np.testing.assert_allclose(R_ours, R_cv, atol=1e-9)
        np.testing.assert_allclose(t_ours, t_cv.ravel(), atol=1e-9)
        assert _angle_deg(R_ours.T @ R) < 1.0


def _default_sigint() -> None:
    """In the child, before exec: SIGINT as a shell's foreground command has it. A child
    inherits an ignored or blocked SIGINT, and Python then never raises KeyboardInterrupt; in
    the full suite (never alone) the command ran to its end after the signal, and this rules
    that cause out."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


@pytest.mark.procs  # runs hmcc colmap as a process and interrupts it
def test_ctrl_c_stops_the_command_between_chunks(tmp_path: Path) -> None:
    """SIGINT to a running ``hmcc colmap``: exit 130, whole chunks written (a multiple of the
    chunk size), a sound database, and a rerun that does the rest."""
    import sqlite3
    import subprocess
    import sys

    pair = sim_pair(30)
    n, chunk = 150, 3
    db = tmp_path / "db.db"
    db_from_pairs(db, [pair] * n)
    hmcc = str(Path(sys.executable).parent / "hmcc")
    argv = [hmcc, "colmap", str(db), "--method", "usac-accurate", "--processes", "0"]
    # Every pair sleeps 50 ms first, so the run outlasts the look below on a loaded machine
    # (it took 3 s in all: a starved poller could see the first rows only after the end).
    env = {**os.environ, "HMCC_FAULT_SLOW_PAIR_ID": "*", "HMCC_FAULT_SLOW_S": "0.05"}
    proc = subprocess.Popen(
        [*argv, "--chunk-pairs", str(chunk)],
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=_default_sigint,
    )
    deadline = time.monotonic() + 60
    written = 0
    while not written and time.monotonic() < deadline and proc.poll() is None:
        try:
            written = len(rows(db))
        except sqlite3.OperationalError:  # locked by a write
            pass
        time.sleep(0.002)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, f"rows seen before the signal: {written}\n{err}"
    written = len(rows(db))
    assert 0 < written < n and written % chunk == 0
    assert f"interrupted: {written} pairs written" in err
    con = sqlite3.connect(db)
    assert con.execute("PRAGMA integrity_check").fetchone() == ("ok",)
    con.close()
    again = ColmapRun(db, options=RunOptions(method="usac-accurate", processes=0)).run()
    assert again["totals"]["skipped_already_verified"] == written
    assert len(rows(db)) == n


def test_the_relative_pose_picks_what_solving_all_four_decompositions_picks() -> None:
    """One depth solve per rotation serves t and -t (the depths change sign exactly): the
    same choice as solving each of the four, on noisy, degenerate and random inputs."""
    import cv2

    from hmcc_colmap.twoview import pose_sample, relative_pose

    def four(E: np.ndarray, n1: np.ndarray, n2: np.ndarray) -> tuple[Any, Any]:
        pick = pose_sample(len(n1))
        n1, n2 = n1[pick], n2[pick]
        R1, R2, t = cv2.decomposeEssentialMat(E)
        t = t.ravel()
        x1 = np.column_stack((n1, np.ones(len(n1))))
        x2 = np.column_stack((n2, np.ones(len(n2))))
        best: tuple[int, Any, Any] = (-1, None, None)
        for R in (R1, R2):
            a = x1 @ R.T
            for tt in (t, -t):
                aa, bb, ab = np.sum(a * a, 1), np.sum(x2 * x2, 1), np.sum(a * x2, 1)
                at, bt = a @ tt, x2 @ tt
                det = aa * bb - ab * ab
                ok = np.abs(det) > 1e-12
                d1 = np.where(ok, (-at * bb + ab * bt) / np.where(ok, det, 1.0), 0.0)
                d2 = np.where(ok, (ab * -at + aa * bt) / np.where(ok, det, 1.0), 0.0)
                front = int(np.count_nonzero((d1 > 0) & (d2 > 0)))
                if front > best[0]:
                    best = (front, R, tt)
        return (None, None) if best[0] <= 0 else (best[1], best[2])

    rng = np.random.default_rng(1)
    for trial in range(500):
        n = int(rng.integers(5, 300))
        X = np.column_stack((rng.uniform(-10, 10, (n, 2)), rng.uniform(-5, 40, n)))
        R = cv2.Rodrigues(rng.normal(0, 1.0, 3))[0]
        t = rng.normal(0, 1, 3)
        t /= np.linalg.norm(t)
        n1 = X[:, :2] / X[:, 2:] + rng.normal(0, 1e-3, (n, 2))
        X2 = X @ R.T + t
        n2 = X2[:, :2] / X2[:, 2:] + rng.normal(0, 1e-3, (n, 2))
        E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
        if trial % 4 == 0:
            E = rng.normal(0, 1, (3, 3))
        if trial % 5 == 0:
            n2 = rng.normal(0, 1, (n, 2))
        (Ra, ta), (Rb, tb) = relative_pose(E, n1, n2), four(E, n1, n2)
        assert (Ra is None) == (Rb is None)
        if Ra is not None:
            np.testing.assert_array_equal(Ra, Rb)
            np.testing.assert_array_equal(ta, tb)


def _copy_images(folder: Path, sources: list[Path], names: list[str]) -> Path:
    folder.mkdir()
    for source, name in zip(sources, names, strict=True):
        shutil.copy(source, folder / name)
    return folder


def _priors(db: Path) -> dict[int, pycolmap.PosePrior]:
    database = pycolmap.Database.open(str(db))
    try:
        return {int(p.corr_data_id.id): p for p in database.read_all_pose_priors()}
    finally:
        database.close()


def test_a_run_without_poses_says_so_once_and_writes_the_gps_priors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Images with a GPS tag and nothing else (the Caliterra camera): the run still verifies
    (exit 0, every pair on the fallback), says once on standard error, and in the report,
    how many images lack a pose, what was looked for and how to give poses; their positions
    go to COLMAP's pose_priors (WGS84) for the pose-prior mapper."""
    from hmcc_cli import main
    from hmcc_colmap.poses import image_pose
    from tests.support.shared_data import SHARED

    pairs = [sim_pair(7), sim_pair(8)]
    db = tmp_path / "db.db"
    ids = db_from_pairs(db, pairs)
    names = ["p0a.jpg", "p0b.jpg", "p1a.jpg", "p1b.jpg"]
    caliterra = sorted((SHARED / "fixtures" / "caliterra" / "images").iterdir())[:4]
    images = _copy_images(tmp_path / "images", caliterra, names)
    report_path = tmp_path / "report.json"
    argv = ["colmap", str(db), "--images", str(images), "--processes", "0"]
    argv.append("--no-track-attitude")  # else the track gives them an attitude
    assert main([*argv, "--report", str(report_path)]) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1, err
    warning = warnings[0]
    assert "4 of the 4 images have no usable pose" in warning
    for looked in ("EXIF GPS", "drone-dji:", "sensefly:Heading", "drone-parrot:", "Camera:Yaw"):
        assert looked in warning
    assert "--poses FILE" in warning and "geo.txt" in warning
    report = json.loads(report_path.read_text())
    assert report["pose_warning"] == warning
    assert report["totals"]["no_pose_pairs"] == 2 and report["totals"]["verified"] == 2
    assert report["totals"]["pose_priors_written"] == {"positions": 4, "gravity": 0}
    priors = _priors(db)
    wgs84 = pycolmap.PosePriorCoordinateSystem.WGS84
    for image_id, name in zip(ids, names, strict=True):
        prior = priors[image_id]
        position = image_pose(images / name).position
        assert position is not None
        assert prior.coordinate_system == wgs84 and not prior.has_gravity()
        np.testing.assert_allclose(
            prior.position, [position["lat"], position["lon"], position["alt"]]
        )
    # a second run writes no prior again and says it again
    assert main([*argv, "--overwrite"]) == 0
    assert capsys.readouterr().err.count("warning:") == 1
    assert len(_priors(db)) == 4


def test_the_pose_priors_get_positions_and_gravity_never_overwritten(tmp_path: Path) -> None:
    """With a pose for every image: no warning; each image without a prior gets its position
    and the gravity direction in its camera frame (the world's down through its rough
    rotation); an image with a prior keeps its position and only gains the gravity it lacked."""
    pairs = [sim_pair(7), sim_pair(8)]
    db = tmp_path / "db.db"
    ids = db_from_pairs(db, pairs)
    kept = pycolmap.PosePrior()
    kept.corr_data_id = pycolmap.data_t(
        sensor_id=pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=1), id=ids[0]
    )
    kept.position = np.array([46.8, -92.0, 200.0])
    kept.coordinate_system = pycolmap.PosePriorCoordinateSystem.WGS84
    database = pycolmap.Database.open(str(db))
    database.write_pose_prior(kept)
    database.close()
    report = ColmapRun(db, poses=pose_file(tmp_path / "p.json", pairs), options=INLINE).run()
    assert report["pose_warning"] is None
    assert report["totals"]["pose_priors_written"] == {"positions": 3, "gravity": 4}
    priors = _priors(db)
    poses = [pair[f"image{side}"]["pose"] for pair in pairs for side in (1, 2)]
    for k, (image_id, pose) in enumerate(zip(ids, poses, strict=True)):
        prior = priors[image_id]
        R = to_rough_pose(PoseModel.model_validate(pose)).R_world_to_cam
        np.testing.assert_allclose(prior.gravity, R @ [0.0, 0.0, -1.0], atol=1e-12)
        assert 0.98 < prior.gravity[2] <= 1.0  # near nadir: down is along the optical axis
        if k == 0:
            np.testing.assert_allclose(prior.position, [46.8, -92.0, 200.0])
            assert prior.coordinate_system == pycolmap.PosePriorCoordinateSystem.WGS84
            continue
        p = pose["position"]
        np.testing.assert_allclose(prior.position, [p["x"], p["y"], p["z"]])
        assert prior.coordinate_system == pycolmap.PosePriorCoordinateSystem.CARTESIAN
