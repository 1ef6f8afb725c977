"""bench_relaxed's scoring of a verified database and its targets (no mapping, no timing)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
from benchmarks.bench_relaxed import precision_recall, targets

PAIR = 1 * 2147483647 + 2


def _database(path: Path, raw: np.ndarray, inliers: np.ndarray | None) -> Path:
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE matches (pair_id INTEGER, rows INTEGER, cols INTEGER, data BLOB)")
    con.execute(
        "CREATE TABLE two_view_geometries (pair_id INTEGER, rows INTEGER, cols INTEGER, data BLOB)"
    )
    con.execute("INSERT INTO matches VALUES (?, ?, 2, ?)", (PAIR, len(raw), raw.tobytes()))
    if inliers is not None:
        con.execute(
            "INSERT INTO two_view_geometries VALUES (?, ?, 2, ?)",
            (PAIR, len(inliers), inliers.tobytes()),
        )
    con.commit()
    con.close()
    return path


def test_verified_inliers_are_scored_against_the_raw_matches_labels(tmp_path: Path) -> None:
    raw = np.array([[0, 5], [1, 6], [2, 7], [3, 8], [4, 9]], dtype=np.uint32)
    labels = {PAIR: np.array([True, True, True, False, False])}
    raw_db = _database(tmp_path / "raw.db", raw, None)
    # three kept, in another order: two true (rows 2 and 0), one false (row 3)
    kept = raw[[2, 3, 0]]
    verified = _database(tmp_path / "verified.db", raw, kept)
    figures = precision_recall(verified, raw_db, labels)
    assert figures["kept_labelled"] == 3
    assert figures["precision"] == 2 / 3
    assert figures["recall"] == 2 / 3
    # nothing verified: no precision, recall 0
    empty = _database(tmp_path / "empty.db", raw, None)
    assert precision_recall(empty, raw_db, labels)["recall"] == 0


def test_targets_need_more_points_than_magsac_and_strict_and_a_faster_stage() -> None:
    def row(name: str, method: str, points: int, stage: float) -> dict[str, object]:
        return {"set": name, "row": method, "points3d": points, "stage_s": stage}

    rows = [
        row("strict", "hmcc-plus", 100, 1.0),
        row("strict", "magsac++", 100, 1.0),
        row("ratio 0.9", "hmcc-plus", 120, 1.0),
        row("ratio 0.9", "magsac++", 110, 2.0),
    ]
    assert [t["ok"] for t in targets(rows)] == [True, True, True]
    rows[2] = row("ratio 0.9", "hmcc-plus", 105, 3.0)
    assert [t["ok"] for t in targets(rows)] == [False, True, False]
