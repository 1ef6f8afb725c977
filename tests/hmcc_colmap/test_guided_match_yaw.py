"""``hmcc match`` on simulated GPS-only flights whose cameras' yaws are off the flight track by
a different amount in every image (``tests/support/gps_flight.py``): each image's yaw is
corrected once from its anchor pairs, the other pairs are matched guided with the corrected
poses, and the simulator's truth judges the matches against brute force's."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from hmcc.guided import Features, GuidedOptions, match_brute_force
from hmcc_cli.match import summary
from hmcc_colmap.database import snapshot_features
from hmcc_colmap.guided_match import GuidedMatchRun, MatchOptions
from hmcc_colmap.verify import RunOptions
from tests.support.gps_flight import GpsFlight, gps_flight_db, stored_matches

#: A pair with fewer true matches than this is not counted as matched.
MATCHED = 15


def _stored(path: Path) -> dict[tuple[int, int], set[tuple[int, int]]]:
    return {k: {(int(i), int(j)) for i, j in m} for k, m in stored_matches(path).items()}


def _stored_inliers(path: Path) -> dict[tuple[int, int], set[tuple[int, int]]]:
    """The verified inlier matches, pair by pair."""
    stored = stored_matches(path, verified=True)
    return {k: {(int(i), int(j)) for i, j in m} for k, m in stored.items()}


def _brute_truth(flight: GpsFlight) -> dict[tuple[int, int], set[tuple[int, int]]]:
    """The true matches brute force finds, pair by pair (pairs of MATCHED true ones or
    more; the others none)."""
    feats = {
        i: Features.from_raw(k, d)
        for i, k, d in snapshot_features(flight.database, flight.image_ids)
    }
    out = {}
    for (a, b), true in flight.truth.items():
        if len(true) < MATCHED:
            out[(a, b)] = set()
            continue
        found = match_brute_force(feats[a], feats[b], GuidedOptions()).matches
        out[(a, b)] = {(int(i), int(j)) for i, j in found} & {(int(i), int(j)) for i, j in true}
    return out


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> dict[float, tuple[GpsFlight, Any]]:
    folder = tmp_path_factory.mktemp("gps")
    out = {}
    for seed, yaw in ((21, 10.0), (22, 60.0), (23, 180.0)):
        flight = gps_flight_db(folder / f"y{yaw:g}", seed, yaw, strips=2, per_strip=6)
        out[yaw] = (flight, _brute_truth(flight))
    return out


def _run(flight: GpsFlight, db: Path, geo: Path | None = None) -> dict[str, Any]:
    db.write_bytes(flight.database.read_bytes())
    options = MatchOptions(processes=0, ground_z=0.0)
    return GuidedMatchRun(db, poses=geo or flight.geo, options=options).run()


def _recall(
    stored: dict[tuple[int, int], set[tuple[int, int]]],
    brute: dict[tuple[int, int], set[tuple[int, int]]],
    skip: set[int] = frozenset(),  # type: ignore[assignment]
) -> tuple[float, list[tuple[int, int]]]:
    """The share of brute force's true matches found, and the pairs brute force matches that
    were not (fewer than MATCHED of them found); pairs with an image of ``skip`` left out."""
    found = wanted = 0
    lost = []
    for pair, true in brute.items():
        if set(pair) & skip:
            continue
        got = len(stored.get(pair, set()) & true)
        found, wanted = found + got, wanted + len(true)
        if len(true) >= MATCHED and got < MATCHED:
            lost.append(pair)
    return found / wanted, lost


@pytest.mark.parametrize("yaw_error", [10.0, 60.0, 180.0])
def test_yaws_off_the_track_by_any_angle_are_corrected_once_per_image(
    flights, tmp_path: Path, yaw_error: float
) -> None:
    """Every image's yaw is corrected from its anchors; the matches found are at least 93 %
    of the true matches brute force finds (0.73 to 0.83 on the per-pair searches before),
    every pair brute force matches is matched, and only anchor pairs are searched."""
    flight, brute = flights[yaw_error]
    report = _run(flight, tmp_path / "db.db")
    recall, lost = _recall(_stored(tmp_path / "db.db"), brute)
    assert recall >= 0.93
    assert lost == []
    assert report["totals"]["images_yaw_corrected"] == len(flight.names)
    modes = report["totals"]["modes"]
    assert modes["guided-corrected"] >= 0.6 * sum(len(t) >= MATCHED for t in flight.truth.values())
    assert modes.get("guided-rotated", 0) + modes.get("guided-turned", 0) <= 2 * len(flight.names)


def test_positions_recorded_late_are_corrected_once_per_image(tmp_path: Path) -> None:
    """Every position 15 m behind its camera along the track (a fix recorded late: the two
    strips, flown opposite ways, 30 m off each other; with the positions as given 0.86 of the
    true matches were found and 14 pairs lost): each image's position is corrected from its
    anchors, the matches found are at least 93 % of the true ones brute force finds, and
    every pair brute force matches is matched. (How much of the error the positions take
    and how much a turn of the whole flight does is not fixed by the matches: either moves
    no pair's predictions.)"""
    flight = gps_flight_db(tmp_path / "lag", 25, 60.0, strips=2, per_strip=6, gps_lag_m=15.0)
    brute = _brute_truth(flight)
    report = _run(flight, tmp_path / "db.db")
    recall, lost = _recall(_stored(tmp_path / "db.db"), brute)
    assert recall >= 0.93
    assert lost == []
    assert report["totals"]["images_position_corrected"] == len(flight.names)
    assert f"{len(flight.names)} positions corrected (median " in summary(report)


def test_pairs_that_do_not_overlap_are_rejected_without_a_search(tmp_path: Path) -> None:
    """One strip of 14 images, yaws anywhere: a pair without a true match gets none, and
    costs at most one first pass: no turn or rotation is searched for it (a first pass
    compares a sample of 1024 keypoints; a search adds 15 turns of 256 and a brute-force
    sample)."""
    flight = gps_flight_db(tmp_path / "strip", 24, 180.0, strips=1, per_strip=14)
    report = _run(flight, tmp_path / "db.db")
    stored = _stored(tmp_path / "db.db")
    ids = dict(zip(flight.names, flight.image_ids, strict=True))
    none = 0
    for row in report["pairs"]:
        pair = (ids[row["image1"]], ids[row["image2"]])
        if len(flight.truth[pair]) or pair not in stored:
            continue
        none += 1
        assert len(stored[pair]) == 0
        assert row["mode"] in ("no-overlap", "pose-mismatch-unmatched")
        kps = row["first_pass"]["sampled"] if "first_pass" in row else 0
        assert kps <= GuidedOptions().sample_size
        assert "turn_deg" not in row
    assert none >= 30


def test_an_image_without_a_position_is_brute_force_and_the_rest_corrected(
    flights, tmp_path: Path
) -> None:
    flight, brute = flights[60.0]
    lines = flight.geo.read_text().splitlines()
    geo = tmp_path / "geo.txt"
    geo.write_text("\n".join(line for line in lines if not line.startswith("img_003")) + "\n")
    report = _run(flight, tmp_path / "db.db", geo)
    assert report["totals"]["modes"]["brute-force (no pose)"] == len(flight.names) - 1
    assert report["totals"]["images_yaw_corrected"] == len(flight.names) - 1
    assert report["images"]["img_003.jpg"]["yaw_correction_deg"] is None
    recall, lost = _recall(_stored(tmp_path / "db.db"), brute)
    assert recall >= 0.93 and lost == []  # brute force finds img_003's own


def test_an_image_whose_position_is_wrong_leaves_the_others_corrected(
    flights, tmp_path: Path
) -> None:
    """img_004's position 300 m off: its anchors show it nothing, so its yaw is not
    corrected (its pairs are searched as before and mostly unmatched); the others' pairs
    are matched as without it."""
    flight, brute = flights[60.0]
    lines = flight.geo.read_text().splitlines()
    for k, line in enumerate(lines):
        if line.startswith("img_004"):
            name, x, y, z = line.split()
            lines[k] = f"{name} {float(x) + 300.0:.3f} {y} {z}"
    geo = tmp_path / "geo.txt"
    geo.write_text("\n".join(lines) + "\n")
    report = _run(flight, tmp_path / "db.db", geo)
    assert report["images"]["img_004.jpg"]["yaw_correction_deg"] is None
    assert report["totals"]["images_yaw_corrected"] == len(flight.names) - 1
    wrong = flight.image_ids[flight.names.index("img_004.jpg")]
    recall, lost = _recall(_stored(tmp_path / "db.db"), brute, skip={wrong})
    assert recall >= 0.93 and lost == []


def test_pairs_matched_with_corrected_yaws_are_verified_with_them(flights, tmp_path: Path) -> None:
    """``--verify`` on yaws off the track by up to 180 deg: a ``guided-corrected`` pair is
    verified with the rough poses it was matched with, so its rough relative rotation fits
    the matches and the method needs no fallback (with the poses as given, 11 of 42 such
    pairs fell back: too few matches triangulated); the inliers keep the true matches."""
    flight, _ = flights[180.0]
    db = tmp_path / "db.db"
    db.write_bytes(flight.database.read_bytes())
    options = MatchOptions(processes=0, ground_z=0.0, verify=RunOptions())
    report = GuidedMatchRun(db, poses=flight.geo, options=options).run()
    checks = {(r["image1"], r["image2"]): r for r in report["verification"]["pairs"]}
    corrected = [
        checks[(r["image1"], r["image2"])]
        for r in report["pairs"]
        if r["mode"] == "guided-corrected" and r["verification"] == "verified"
    ]
    assert len(corrected) >= 0.6 * sum(len(t) >= MATCHED for t in flight.truth.values())
    fell = [(c["image1"], c["image2"], c["fallback_reason"]) for c in corrected if c["fallback"]]
    assert len(fell) <= 0.05 * len(corrected), fell
    matches, inliers = _stored(db), _stored_inliers(db)
    kept = found = 0
    for pair, true in flight.truth.items():
        given = matches.get(pair, set()) & {(int(i), int(j)) for i, j in true}
        kept += len(inliers.get(pair, set()) & given)
        found += len(given)
    assert kept >= 0.97 * found
