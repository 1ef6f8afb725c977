"""Counts in the commands' messages agree with their number: ``1 pair``, never ``1 pairs``."""

from __future__ import annotations

from hmcc_cli.colmap import summary
from hmcc_cli.plural import counted


def test_counted() -> None:
    assert [counted(n, "pair") for n in (0, 1, 2)] == ["0 pairs", "1 pair", "2 pairs"]
    assert counted(1, "inlier match", "inlier matches") == "1 inlier match"
    assert counted(3, "inlier match", "inlier matches") == "3 inlier matches"


def test_the_colmap_summary_of_one_pair() -> None:
    totals = dict.fromkeys(
        (
            "pairs verified inlier_matches fallback_pairs no_pose_pairs listed_without_matches "
            "under_min_inliers too_few_matches failed skipped_already_verified"
        ).split(),
        1,
    )
    totals |= {"plan_s": 0.1, "verify_s": 0.2, "startup_s": 0.3}
    text = summary(
        {
            "database": "db.db",
            "method": "hmcc-ransac",
            "where": "here",
            "min_inliers": 1,
            "fallback_method": "ransac",
            "totals": totals,
            "images": {
                "a.jpg": {
                    "pose_issue": None,
                    "pos_fits": False,
                    "fallback": 1,
                    "pairs": 1,
                    "pos_rotation_error_deg_median": 9.0,
                }
            },
        }
    )
    assert "pairs" not in text.replace("--pairs", ""), text
    assert "db.db: 1 pair with" in text and "verified 1 pair (1 inlier match)" in text
    assert "under 1 inlier," in text and "1 pair of --pairs has no matches" in text
