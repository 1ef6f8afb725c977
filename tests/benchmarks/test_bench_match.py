"""``bench_match``'s count of verified pairs by part of a flight split for tuning."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from benchmarks.bench_match import by_part

MAX_ID = 2147483647  # COLMAP's pair id: id1 * MAX_ID + id2


def test_verified_pairs_are_counted_by_the_part_their_images_lie_in(tmp_path: Path) -> None:
    """Four images, the first two by name looked at: a pair of those two, a pair of the
    other two, two pairs across, and a pair without inliers (not counted)."""
    db = tmp_path / "db.db"
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE images (image_id INTEGER, name TEXT)")
    con.execute("CREATE TABLE two_view_geometries (pair_id INTEGER, rows INTEGER)")
    con.executemany(
        "INSERT INTO images VALUES (?, ?)", [(1, "d.jpg"), (2, "a.jpg"), (3, "c.jpg"), (4, "b.jpg")]
    )
    geometries = [((2, 4), 10), ((1, 3), 20), ((1, 2), 30), ((3, 4), 40), ((2, 3), 0)]
    con.executemany(
        "INSERT INTO two_view_geometries VALUES (?, ?)",
        [(a * MAX_ID + b, rows) for (a, b), rows in geometries],
    )
    con.commit()
    con.close()
    assert by_part(db, 2) == {"looked at": [1, 10], "held out": [1, 20], "across": [2, 70]}
