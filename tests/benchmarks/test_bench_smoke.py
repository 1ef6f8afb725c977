"""Smoke tests of the benchmark scripts: each quick run writes its JSON and markdown reports.

No timing is asserted (machines are noisy); only that the script runs end to end and writes
the expected structure.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks import (
    bench_core,
    bench_default,
    bench_guards,
    bench_hard,
    bench_paper,
    common,
    paper_report,
    reference_audit,
)
from hmcc_schema import parse_pair, reference_to_pair
from tests.support.shared_data import BRIGHTON
from tests.support.sim_pairs import simulated

TOP_LEVEL_KEYS = {
    "meta",
    "filter_scaling",
    "pipeline_vs_baselines",
    "robustness",
    "stage_losses",
    "summary",
}


def test_quick_run_writes_reports(tmp_path: Path) -> None:
    bench = bench_core
    assert bench.main(["--quick", "--out", str(tmp_path)]) == 0

    report = tmp_path / "core.json"
    assert report.is_file()
    assert (tmp_path / "core.md").is_file()
    doc = json.loads(report.read_text())
    assert TOP_LEVEL_KEYS <= set(doc)

    assert [row["n"] for row in doc["filter_scaling"]["rows"]]
    assert doc["pipeline_vs_baselines"]["rows"]
    cells = doc["robustness"]["cells"]
    assert {"sim V-V", "sim V-F", "sim B-F", "sim L-F"} <= set(cells)
    for per_ratio in cells.values():
        for cell in per_ratio.values():
            assert set(cell["methods"]) == set(bench.METHODS)
            for method in bench.FILTER_STAGE:  # the paper's metrics beside the truth's
                assert {"paper_precision", "paper_recall"} <= set(cell["methods"][method])
    assert doc["stage_losses"]
    assert all(row["trace_consistent"] for row in doc["stage_losses"])
    assert all(t["ok"] in (True, False, None) for t in doc["summary"])


def test_default_method_quick_run_writes_reports(tmp_path: Path) -> None:
    """benchmarks/bench_default.py --quick: every method in every cell, targets evaluated,
    hmcc-plus's fallbacks recorded (the plot only where matplotlib is installed)."""
    module = bench_default
    # BRIGHTON honours HMCC_SHARED, unlike the script's default
    assert module.main(["--quick", "--out", str(tmp_path), "--fixtures", str(BRIGHTON)]) == 0
    doc = json.loads((tmp_path / "default.json").read_text())
    assert (tmp_path / "default.md").is_file()
    assert {"real", "sim V-V", "sim V-F", "sim B-F", "sim L-F"} <= set(doc["cells"])
    for per_ratio in doc["cells"].values():
        for cell in per_ratio.values():
            assert set(module.METHODS) <= set(cell["methods"])
    assert doc["pairs"]
    assert all(set(r["fallback"]) == {"used", "reason"} for r in doc["pairs"])
    assert all("fallbacks" in cell for per in doc["cells"].values() for cell in per.values())


def test_colmap_quick_run_writes_reports(tmp_path: Path, sift_cache: Path) -> None:
    """benchmarks/bench_colmap.py --quick: five real images through COLMAP's SIFT (the
    database bench_real's quick run built, if it ran first), then COLMAP's verification and
    ours, each mapped."""
    from benchmarks import bench_colmap

    argv = ["--quick", "--out", str(tmp_path), "--cache", str(sift_cache)]
    assert bench_colmap.main([*argv, "--images", str(BRIGHTON / "images")]) == 0
    doc = json.loads((tmp_path / "colmap.json").read_text())
    assert (tmp_path / "colmap.md").is_file()
    assert [r["row"] for r in doc["rows"]] == list(bench_colmap.QUICK_ROWS)
    for row in doc["rows"]:
        assert row["verified_pairs"] >= 1 and row["registered"] >= 2
    assert doc["rows"][1]["pos_not_fitting"] == ["DJI_0024.JPG", "DJI_0025.JPG"]  # strip 1
    assert doc["targets"]


def test_match_quick_run_writes_reports(tmp_path: Path, sift_cache: Path) -> None:
    """benchmarks/bench_match.py --quick: five real images' SIFT (the features database
    bench_real's or bench_colmap's quick run extracted, if one ran first) matched by COLMAP
    and by ``hmcc match``, each verified and mapped; strip 1's two images are found turned."""
    from benchmarks import bench_match

    argv = ["--quick", "--out", str(tmp_path), "--cache", str(sift_cache)]
    assert bench_match.main([*argv, "--images", str(BRIGHTON / "images")]) == 0
    doc = json.loads((tmp_path / "match.json").read_text())
    assert (tmp_path / "match.md").is_file()
    assert [r["row"] for r in doc["rows"]] == list(bench_match.ROWS)
    for row in doc["rows"]:
        assert row["verified_pairs"] >= 1 and row["registered"] >= 2
    ours = doc["rows"][1]
    assert ours["modes"].get("guided", 0) >= 1
    assert set(ours["turned_images"]) == {"DJI_0024.JPG", "DJI_0025.JPG"}  # strip 1
    assert doc["targets"]


def test_paper_quick_run_and_report(tmp_path: Path) -> None:
    """bench_paper --quick writes paper.json; paper_report turns it into the report with a
    section and figures for every experiment of the paper's section 4."""
    assert bench_paper.main(["--quick", "--out", str(tmp_path), "--fixtures", str(BRIGHTON)]) == 0
    doc = json.loads((tmp_path / "paper.json").read_text())
    assert {r["pair"] for r in doc["stages"]} == {"V-V", "V-F", "B-F", "L-F"}
    assert {c["protocol"] for c in doc["robustness"]["cells"]} == {
        "paper",
        "ours",
        "paper, 0.25 px noise",
    }
    assert doc["flight"]["records"]
    out = paper_report.build(tmp_path, tmp_path / "docs")
    text = out.read_text()
    for marker in ("Figs. 7-12", "Figs. 13-14", "Table 3", "Table 4", "Table 5", "Table 6"):
        assert marker in text, marker
    figures = tmp_path / "docs" / "figures"
    for name in ("robustness.png", "methods.png", "flight.png", "motions-L-F-hmcc-plus.png"):
        assert (figures / name).read_bytes().startswith(b"\x89PNG"), name


def test_hard_pairs_quick_run_writes_reports(tmp_path: Path) -> None:
    """benchmarks/bench_hard.py --quick: every geometry and both real sets, a verdict per pair,
    the worst pairs of each method; a second run compares with the first (``--before``)."""
    module = bench_hard
    args = ["--quick", "--out", str(tmp_path), "--fixtures", str(BRIGHTON)]
    assert module.main(args) == 0
    doc = json.loads((tmp_path / "hard.json").read_text())
    assert (tmp_path / "hard.md").is_file()
    sets = {"real", "real+outliers", *(f"sim {'-'.join(g)}" for g in module.GEOMETRIES)}
    assert set(doc["sets"]) == sets
    for record in doc["pairs"]:
        assert set(module.METHODS) <= set(record["methods"])
        assert {"recall", "precision", "all", "deficit"} <= set(record["targets"])
        real = record["set"].startswith("real")
        assert record["baselines"] == (["usac-accurate"] if real else list(module.BASELINES))
    sim = [r for r in doc["pairs"] if r["set"].startswith("sim")]
    assert len(sim) == 3 * len(module.GEOMETRIES)
    assert all(set(r["methods"][module.PLUS]["fallback"]) == {"used", "reason"} for r in sim)

    again = ["--name", "again", "--before", str(tmp_path / "hard.json")]
    assert module.main(args + again) == 0
    compared = json.loads((tmp_path / "again.json").read_text())["before"]
    assert compared["pairs_in_both"] == len(doc["pairs"])
    assert compared["changed"] == []  # the same code on the same pairs


def test_reference_audit_drops_matches_whose_rays_meet_above_the_drone(tmp_path: Path) -> None:
    """DJI_0021-0023's reference holds 5 matches whose rays meet 40-180 m above the drone (the
    patches differ, results/reference_audit.jpg); the audit drops exactly those. A match moved
    along its epipolar line behind camera 2 is dropped too, and no true simulated match is."""
    doc = reference_to_pair(json.loads((BRIGHTON / "pair_DJI_0021_DJI_0023.json").read_text()))
    data = parse_pair(doc).pair_data(0)
    reference = np.asarray(sorted(doc["ground_truth"]["inliers"]))
    kept, dropped = common.audited_reference(data, reference)
    assert dropped.tolist() == [3, 10, 42, 50, 51] and len(kept) == 27

    pair, mask = simulated(("V", "F"), ratio=0.0, seed=3, n_inliers=200)
    truth = np.flatnonzero(mask)
    assert len(common.impossible_matches(pair, truth)) == 0
    # Match 0's image-2 keypoint moved to where image 2 sees the point 1 km behind camera 1 on
    # match 0's ray: on its epipolar line (F cannot tell), but the rays meet behind camera 1.
    i1, i2 = pair.matches[truth[0]]
    ray = pair.camera1.rays(pair.keypoints1[i1 : i1 + 1, :2])[0] @ pair.pose1.R_world_to_cam
    behind = pair.pose1.center - 1e3 * ray / np.linalg.norm(ray)
    seen = pair.camera2.K @ (pair.pose2.R_world_to_cam @ (behind - pair.pose2.center))
    moved = pair.keypoints2.copy()
    moved[i2, :2] = seen[:2] / seen[2]
    wrong = dataclasses.replace(pair, keypoints2=moved)
    assert common.impossible_matches(wrong, truth[:3]).tolist() == [truth[0]]

    assert reference_audit.main(["--fixtures", str(BRIGHTON), "--out", str(tmp_path)]) == 0
    assert "15 of 2978 reference inliers" in (tmp_path / "reference_audit.md").read_text()
    assert (tmp_path / "reference_audit.jpg").stat().st_size > 0


@pytest.mark.procs  # a compute-pool child runs the cases
def test_guards_quick_run_no_estimator_crashes_on_degenerate_input(tmp_path: Path) -> None:
    """Every method, estimator and model on identical, collinear and minimal inputs, in an
    isolated child: none crashes it (the full run adds the limits' 100 000 matches and
    200 000 keypoints)."""
    assert bench_guards.main(["--quick", "--timeout", "60", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "guards_quick.json").read_text())
    rows = doc["rows"]
    assert len(rows) == 3 * len(bench_guards.configurations())
    assert {r["case"] for r in rows} == {"identical", "collinear", "minimal"}
    assert not [r for r in rows if r["code"] in ("worker_crashed", "timeout", "internal_error")]
    # every configuration got past validation and its method's own checks at least once
    # (gc-ransac needs the keypoints' size and angle: the cases give them; a method that fits
    # F alone refuses another model, so it is not run with one)
    assert {(r["method"], r["model"]) for r in rows if r["status"] == "finished"} == set(
        bench_guards.configurations()
    )
    assert (tmp_path / "guards_quick.md").is_file()


@pytest.mark.procs  # embedded and RQ services, a redis-server, workers
def test_flight_quick_run_writes_every_row_and_target(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """benchmarks/bench_flight.py --quick: a 600-pair flight through every path, the HTTP rows
    with the core's precision and recall (its times are too short to hold the targets). The
    slow rows run 20 sampled pairs, the RQ rows 2 workers only (the targets' rows; a third
    worker is the same code), each service is warmed by 50 pairs (the warm-up is for the
    timings, which this test does not check)."""
    from benchmarks import bench_flight

    monkeypatch.setattr(bench_flight, "WARM_PAIRS", 50)
    argv = ["--quick", "--sample", "20", "--rq-workers", "2", "--out", str(tmp_path)]
    assert bench_flight.main(argv) in (0, 1)
    doc = json.loads((tmp_path / "quick" / "flight.json").read_text())
    paths = {(r["path"], r["processes"]) for r in doc["records"]}
    assert {("core", 1), ("HTTP embedded", 2), ("HTTP + RQ", 2)} <= paths
    assert doc["flight"]["batch_json_before_bytes"] > 0
    quality = [t for t in doc["targets"] if "precision and recall" in t["target"]]
    # 2 HTTP, 5 hmcc flight (JSON file; binary file and columns file, each also with
    # --result inliers)
    assert len(quality) == 7 and all(t["ok"] for t in quality), quality
    # every row with children has its serial share: CPU outside the compute and in it
    for r in doc["records"]:
        if r["path"].startswith(("HTTP", "hmcc flight")):
            assert r["cpu_outside_s"] > 0 and r["cpu_children_s"] > 0, r
            assert 0 < r["serial_share"] < 1
    # every row's CPU per pair against the core's in one process (the core itself: 1)
    cpu = {(r["path"], r["processes"]): r["cpu_per_pair_vs_core_1"] for r in doc["records"]}
    assert cpu[("core", 1)] == 1.0
    assert all(
        v is not None and v > 0 for k, v in cpu.items() if k[0] != "COLMAP two-view geometry"
    ), cpu
    assert (tmp_path / "quick" / "flight.md").is_file()


def test_pairs_quick_run_writes_reports(tmp_path: Path) -> None:
    """benchmarks/bench_pairs.py --quick: five Brighton images, every row matched and mapped,
    the footprint rows matching fewer pairs than the exhaustive one."""
    from benchmarks import bench_pairs

    assert bench_pairs.main(["--quick", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "pairs.json").read_text())
    (flight,) = doc["flights"]
    rows = {r["row"]: r for r in flight["rows"]}
    assert list(rows) == list(bench_pairs.ROWS)
    assert rows["exhaustive"]["matched_pairs"] == 10
    assert 0 < rows["footprint"]["matched_pairs"] < 10
    assert (tmp_path / "pairs.md").read_text().startswith("# Pair selection")
