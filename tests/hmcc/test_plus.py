"""hmcc-plus (the default method): scoring, model, refine and fallback, against exact truth.

Simulated pairs carry their true matches; the real fixtures their automatic reference inliers.
The thresholds below sit under what the method measures (benchmarks/results/default.md) with a
margin, and above what the paper's hmcc-ransac reaches on the same pairs, so they fail when a
stage regresses to the paper's behaviour.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hmcc import DEFAULT_METHOD, PairData, VerifyOptions, plus_kernels, verify
from hmcc import plus as plus_module
from hmcc.errors import InputError
from hmcc.flight import Flight
from hmcc.method_names import F_ONLY_METHODS
from hmcc.plus import (
    Calibration,
    Correspondences,
    PlusOptions,
    _usac,
    coverage,
    epipolar_band,
    fit_candidates,
    motion_field_seeds,
    parallax_group,
    plane_epipole_directions,
    ray_arguments,
    sampson_distance,
)
from hmcc.pose import Pose
from hmcc.projection import project_pair
from hmcc.ransac import RansacOptions, iterations_bound, sample_draws
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_pair, reference_to_pair
from tests.support.shared_data import BRIGHTON
from tests.support.sim_pairs import precision_recall, scene_pair, simulated

PLUS_STAGES = ["projection", "consistency", "model", "refine", "check"]


def _diverging(pair: PairData, u1: np.ndarray, u2: np.ndarray, limit_deg: float) -> np.ndarray:
    """The matches whose rays diverge by more than ``limit_deg`` (the gate's mask)."""
    return plus_kernels.diverging(u1, u2, *ray_arguments(pair), np.radians(limit_deg))


def fired_and_action(result: Any) -> tuple[bool, str]:
    return result.statistics["check"]["fired"], result.statistics["check"]["action"]


def cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def pixels(pair: PairData) -> tuple[np.ndarray, np.ndarray]:
    return pair.keypoints1[pair.matches[:, 0], :2], pair.keypoints2[pair.matches[:, 1], :2]


# --------------------------------------------------------------------------- building blocks


def test_sampson_distance_is_the_first_order_geometric_error() -> None:
    """For F = [e]_x of a pure x-translation the epipolar lines are horizontal: a match off by
    dy in image 2 has Sampson distance |dy| / sqrt(2) (error shared by both points)."""
    f = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # y2 = y1
    p1 = np.array([[10.0, 20.0], [300.0, -5.0], [7.0, 7.0]])
    dy = np.array([0.0, 2.0, -3.0])
    p2 = p1 + np.column_stack((np.array([5.0, -40.0, 0.0]), dy))
    assert sampson_distance(f, p1, p2) == pytest.approx(np.abs(dy) / np.sqrt(2.0))


def test_plane_epipole_directions() -> None:
    """Same flying height: every line runs along the baseline; one camera higher: the lines
    meet where the baseline crosses the plane; the same centre twice: no lines."""
    start = np.array([[0.0, 0.0], [50.0, -20.0], [-30.0, 80.0]])
    c1, c2 = np.array([0.0, 0.0, 100.0]), np.array([30.0, 40.0, 100.0])
    d = plane_epipole_directions(start, c1, c2, z0=-20.0)
    assert d is not None
    assert cross2(d, np.array([0.6, 0.8])) == pytest.approx(np.zeros(3), abs=1e-12)
    higher = np.array([30.0, 40.0, 160.0])  # baseline meets z = -20 at (-60, -80)
    d = plane_epipole_directions(start, c1, higher, z0=-20.0)
    assert d is not None
    towards = np.array([-60.0, -80.0]) - start
    assert cross2(d, towards) == pytest.approx(np.zeros(3), abs=1e-9)
    assert plane_epipole_directions(start, c1, c1, z0=-20.0) is None


def exact_pair(n: int = 60, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise-free projections of points at several depths by two cameras; (p1, p2, F)."""
    rng = np.random.default_rng(seed)
    k = np.array([[1000.0, 0.0, 640.0], [0.0, 1000.0, 480.0], [0.0, 0.0, 1.0]])
    x = np.column_stack((rng.uniform(-40, 40, (n, 2)), rng.uniform(80, 140, n)))
    angle = 0.05
    r = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    t = np.array([-20.0, 3.0, 1.0])
    h1 = x @ k.T
    h2 = (x @ r.T + t) @ k.T
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    f = np.linalg.inv(k).T @ tx @ r @ np.linalg.inv(k)
    return h1[:, :2] / h1[:, 2:], h2[:, :2] / h2[:, 2:], f / np.linalg.norm(f)


def test_normalised_sampson_distance_is_the_pixel_one_times_the_scale() -> None:
    p1, p2, f = exact_pair()
    p2 = p2 + np.random.default_rng(1).normal(0.0, 2.0, p2.shape)
    corr = Correspondences(p1, p2)
    d_px = sampson_distance(f, p1, p2)
    d_norm = np.sqrt(corr.sampson_sq(corr.from_pixels(f)))
    assert d_norm == pytest.approx(d_px * corr.scale, rel=1e-9)
    rows = np.array([3, 7, 11])
    assert corr.sampson_sq(corr.from_pixels(f), rows) == pytest.approx(d_norm[rows] ** 2)


def test_least_squares_and_minimal_samples_recover_an_exact_model() -> None:
    p1, p2, f = exact_pair()
    corr = Correspondences(p1, p2)
    ls = corr.to_pixels(corr.least_squares(np.ones(len(p1), dtype=bool)))
    assert np.abs(ls - np.sign((ls * f).sum()) * f).max() < 1e-8
    models = corr.minimal(np.arange(32).reshape(4, 8))
    assert models.shape == (4, 3, 3)
    d2 = np.array([corr.sampson_sq(m) for m in models])
    assert d2.shape == (4, len(p1)) and d2.max() < 1e-16
    assert corr.least_squares(np.arange(len(p1)) < 7) is None  # 7 rows do not fix F


def test_the_model_stage_rejects_outliers_among_the_candidates() -> None:
    """A fifth of the candidates are off their epipolar line by 20-80 px: the sampled model
    still fits every true one (a single least-squares fit would not: it bends towards them)."""
    p1, p2, f = exact_pair(n=80)
    rng = np.random.default_rng(2)
    bad = rng.choice(80, 16, replace=False)
    p2 = p2.copy()
    p2[bad] += rng.uniform(20, 80, (16, 2)) * rng.choice([-1, 1], (16, 2))
    corr = Correspondences(p1, p2)
    model, inliers, stats = fit_candidates(
        corr, np.arange(80), np.zeros(80, bool), PlusOptions(), seed=0
    )
    assert model is not None and not stats["usac"]
    good = np.setdiff1d(np.arange(80), bad)
    assert inliers[good].all() and not inliers[bad].any()
    assert sampson_distance(corr.to_pixels(model), p1[good], p2[good]).max() < 0.5
    naive = corr.to_pixels(corr.least_squares(np.ones(80, dtype=bool)))
    assert sampson_distance(naive, p1[good], p2[good]).max() > 1.5


def test_opencv_usac_assertions_are_no_model_not_a_crash() -> None:
    """OpenCV 5.0's USAC asserts ``!model.empty()`` on this candidate set (found by the
    benchmark); the model stage treats it as "no model" and the fallback decides."""
    data = json.loads((Path(__file__).parent / "data" / "usac_assert.json").read_text())
    p1, p2 = np.asarray(data["p1"]), np.asarray(data["p2"])
    assert _usac(p1, p2, PlusOptions(), seed=data["seed"]) is None


def test_usac_samples_only_for_min_inliers_true_matches(monkeypatch: pytest.MonkeyPatch) -> None:
    """The model and check stages' USAC, like the fallback, draws the samples that find
    min_inliers (15) true matches among its points at its confidence: a handful on 16
    points (an SfM project's barely overlapping pairs), model_max_iters on hundreds."""
    import cv2

    seen: list[int] = []
    real = cv2.findFundamentalMat

    def spy(p1: np.ndarray, p2: np.ndarray, params: Any) -> Any:
        seen.append(params.maxIterations)
        return real(p1, p2, params)

    monkeypatch.setattr(cv2, "findFundamentalMat", spy)
    pair, _ = simulated(("V", "V"), ratio=0.3, seed=7, n_inliers=200)
    p1, p2 = pair.matched_pixels()
    options = PlusOptions()
    _usac(p1[:16], p2[:16], options, seed=0)
    _usac(p1, p2, options, seed=0)
    assert seen == [sample_draws(15 / 16, 7, 0.99, 500), options.model_max_iters]
    assert 1 < seen[0] < 10


def test_estimators_report_opencv_errors_as_degenerate(monkeypatch) -> None:
    import cv2

    from hmcc import ransac

    def boom(*args, **kwargs):
        raise cv2.error("!model.empty()")

    monkeypatch.setattr(ransac, "_call_opencv", boom)
    p1, p2, _ = exact_pair()
    fit = ransac.estimate_model(p1, p2, ransac.RansacOptions(estimator="magsac++"), 0)
    assert fit.matrix is None and not fit.inliers.any()
    assert fit.stats["degenerate"].startswith("OpenCV")


@pytest.mark.parametrize("views", [("V", "V"), ("V", "F"), ("B", "F")])
def test_seeds_are_clean_at_ninety_percent_outliers(views) -> None:
    """The 2-D motion vote + affine field picks seeds that are nearly all true matches even
    when nine in ten matches are outliers (where the paper's 1-D direction peak flips)."""
    pair, truth = simulated(views, ratio=0.9, seed=1, n_inliers=200)
    result = verify(pair, "hmcc")  # only for the projected motions' indices
    assert result.stages[0].name == "projection"
    px1, px2 = pixels(pair)
    motions, valid, _ = project_pair(pair, px1, px2, VerifyOptions().ground)
    seeds, _, stats = motion_field_seeds(motions.start, motions.vectors, PlusOptions())
    idx = np.flatnonzero(valid)[seeds]
    assert len(idx) >= 16
    assert truth[idx].mean() >= 0.9, (views, truth[idx].mean(), stats)


# --------------------------------------------------------------------------- the method


def test_default_method_is_hmcc_plus() -> None:
    pair = simulate_pair(SimulationOptions(n_inliers=60, outlier_ratio=0.3), seed=0)
    pair.pop("method", None)
    flight = parse_pair(pair)
    assert flight.method == DEFAULT_METHOD == "hmcc-plus"
    result = verify(flight.pair_data(0))
    assert result.method == "hmcc-plus"
    assert [s.name for s in result.stages] == PLUS_STAGES
    assert result.statistics["fallback"] == {"used": False, "reason": None, "outscored": False}
    assert result.model_type == "fundamental" and result.model_matrix is not None
    assert result.stages[-1].kept == len(result.inliers)
    assert result.params["plus"] == dataclasses.asdict(PlusOptions())


@pytest.mark.parametrize("views", [("V", "V"), ("V", "F"), ("B", "F")])
@pytest.mark.parametrize("ratio", [0.1, 0.5, 0.9])
def test_precise_and_complete_where_the_paper_loses_matches(views, ratio) -> None:
    """Precision >= 0.97 and recall >= 0.85 at every outlier ratio (typically >= 0.98; a model
    fitted on a plane-dominant candidate set can miss the roofs, see the README's known
    limits); the paper's hmcc-ransac keeps at most ~0.75 of the true matches on the same
    pairs (its votes cut them)."""
    pair, truth = simulated(views, ratio=ratio, seed=3, n_inliers=200)
    result = verify(pair, "hmcc-plus")
    precision, recall = precision_recall(result.inliers, truth)
    assert precision >= 0.97 and recall >= 0.85, (views, ratio, precision, recall)
    _, paper_recall = precision_recall(verify(pair, "hmcc-ransac").inliers, truth)
    assert recall > paper_recall + 0.1, (recall, paper_recall)


def test_every_match_is_decided_not_only_the_candidates() -> None:
    """The refine stage classifies all matches: most inliers were never candidates."""
    pair, truth = simulated(("V", "F"), ratio=0.5, seed=4, n_inliers=400)
    result = verify(pair, "hmcc-plus")
    stages = {s.name: s for s in result.stages}
    assert stages["refine"].input == len(truth)
    candidates = result.survivors["consistency"]
    assert len(candidates) < 0.5 * len(result.inliers)
    assert not np.isin(result.inliers, candidates).all()
    # At most 150 + 60 candidates of 400 true matches: recall 0.95 needs the refine stage.
    # (This pair, at params.seed 0, lands on a plane-dominant model, recall 0.89, that the
    # check replaces: 1.0 with it.)
    assert precision_recall(result.inliers, truth)[1] >= 0.95


def test_real_fixtures_agree_with_their_reference() -> None:
    """On every brighton-beach pair (its own candidate matches, reference = MAGSAC++ at 1 px):
    precision >= 0.9 and recall >= 0.8 against the reference, >= 0.95 on average, no
    fallback needed. (DJI_0021-0023 has 32 reference matches; hmcc-plus keeps 27: the other 5
    meet above the drone, benchmarks/results/reference_audit.md.)"""
    recalls = []
    for path in sorted(BRIGHTON.glob("pair_*.json")):
        doc = reference_to_pair(json.loads(path.read_text()))
        pair = parse_pair(doc).pair_data(0)
        truth = np.zeros(len(pair.matches), dtype=bool)
        truth[doc["ground_truth"]["inliers"]] = True
        result = verify(pair, "hmcc-plus")
        precision, recall = precision_recall(result.inliers, truth)
        assert precision >= 0.9 and recall >= 0.8, (path.name, precision, recall)
        assert not result.statistics["fallback"]["used"], result.statistics["fallback"]
        recalls.append(recall)
    assert np.mean(recalls) >= 0.95


def test_seeded_and_deterministic() -> None:
    pair, _ = simulated(("B", "F"), ratio=0.8, seed=5)
    a = verify(pair, "hmcc-plus", VerifyOptions(seed=7))
    b = verify(pair, "hmcc-plus", VerifyOptions(seed=7))
    assert np.array_equal(a.inliers, b.inliers)
    assert np.array_equal(a.model_matrix, b.model_matrix)


def test_the_parallax_gate_removes_outliers_on_their_epipolar_line() -> None:
    """With the gate off, random matches that happen to lie on their epipolar line stay in; the
    gate removes them (their parallax is implausible) without losing true matches."""
    pair, truth = simulated(("V", "V"), ratio=0.9, seed=1, n_inliers=200)
    gated = verify(pair, "hmcc-plus")
    open_ = verify(pair, "hmcc-plus", VerifyOptions(plus=PlusOptions(gate=False)))
    assert "gated" in gated.statistics and "gated" not in open_.statistics
    assert gated.statistics["gated"] > 0  # this pair has such matches
    refine = {s.name: s for s in gated.stages}["refine"]
    assert refine.kept == len(gated.inliers) and refine.stats["gated"] > 0
    p_gated, r_gated = precision_recall(gated.inliers, truth)
    p_open, r_open = precision_recall(open_.inliers, truth)
    assert p_gated >= p_open and r_gated >= r_open - 0.01
    assert set(gated.inliers) <= set(open_.inliers)


def test_an_inlier_may_not_meet_below_the_plane() -> None:
    """Seeds with a parallax of 10 m along their plane epipolar lines (the ground, Z0 10 m of
    parallax below it): a match 6 m below the seeds' field is plausible, one 15 m below meets
    under the plane and is not, although the band (which reaches 3 x 10 m both ways) still
    takes it as a candidate; 25 m above is plausible, 35 m above is not."""
    rng = np.random.default_rng(3)
    n_seeds = 60
    offsets = np.array([-6.0, -15.0, 25.0, 35.0])
    n = n_seeds + len(offsets)
    start = rng.uniform(0.0, 100.0, (n, 2))
    directions = np.tile([1.0, 0.0], (n, 1))
    along = np.concatenate((10.0 + rng.normal(0.0, 0.2, n_seeds), 10.0 + offsets))
    vectors = np.column_stack((along, rng.normal(0.0, 0.2, n)))
    seeds = np.arange(n_seeds)
    options = PlusOptions(max_band=n)
    band, plausible, _, across, _, stats = epipolar_band(
        start, vectors, directions, seeds, options, parallax_floor=0.0
    )
    assert stats["median_parallax_m"] == pytest.approx(10.0, abs=0.2)
    assert plausible[:n_seeds].all()
    assert plausible[n_seeds:].tolist() == [True, False, True, False]
    assert np.isfinite(across[n_seeds:]).tolist() == [True, True, True, False]  # the band's
    assert n_seeds + 1 in band


# --------------------------------------------------------------------------- check


def test_coverage_counts_the_true_matches_a_model_should_explain() -> None:
    """40 true matches close to their plane epipolar line among 400 outliers spread over +-60
    sigma across it: the control band beside the band (as wide) estimates the outliers inside
    it, so about 40 true matches are expected; likewise 30 near misses 2-10 px off the model
    among outliers spread over 0-100 px. A model keeping all of them explains the pair, one
    keeping every other band match does not."""
    rng = np.random.default_rng(0)
    n_true, n_out, n_near = 40, 400, 30
    across = np.abs(np.concatenate((rng.normal(0.0, 1.0, n_true), rng.uniform(-60, 60, n_out))))
    t = 1.5
    d = np.concatenate((rng.uniform(0.0, 1.0, n_true), rng.uniform(0.0, 100.0, n_out)))
    truth = np.arange(n_true + n_out) < n_true
    gated = np.zeros(len(d), dtype=bool)
    rows = np.arange(len(d))
    options = PlusOptions(check_sigmas=3.0)
    cover = coverage(truth, d**2, gated, rows, across, t * t, options)
    assert cover.kept == n_true and 30 <= cover.band_expected <= 50
    assert cover.band_kept == np.count_nonzero(across[:n_true] < 3.0) and cover.band_share > 0.8
    assert abs(cover.near_expected) <= 8 and cover.explains(options)
    half = truth & (np.arange(len(d)) % 2 == 0)
    half_cover = coverage(half, d**2, gated, rows, across, t * t, options)
    assert half_cover.missing >= 15 and not half_cover.explains(options)
    # Near misses of a height the model does not explain: 2-10 px off it.
    d_near = np.concatenate((d, rng.uniform(2.0, 10.0, n_near)))
    truth_near = np.concatenate((truth, np.zeros(n_near, dtype=bool)))
    across_near = np.concatenate((across, np.full(n_near, np.inf)))
    gated_near = np.zeros(len(d_near), dtype=bool)
    rows_near = np.arange(len(d_near))
    near = coverage(truth_near, d_near**2, gated_near, rows_near, across_near, t * t, options)
    assert n_near - 8 <= near.near_expected <= n_near + 3 and not near.explains(options)
    gated_near[-n_near:] = True  # implausible parallax: not counted
    assert coverage(
        truth_near, d_near**2, gated_near, rows_near, across_near, t * t, options
    ).explains(options)


#: Pairs of the hard sweep's tuning seeds (benchmarks/bench_hard.py --seed-base 1000) on which
#: the model misses a height without the check: (views, simulation options, seed, recall of
#: MAGSAC++ and USAC_ACCURATE on the pair).
MISSED_HEIGHTS = [
    (
        ("V", "V"),
        {
            "relief_m": 13.170079277059225,
            "building_fraction": 0.06700173592097114,
            "building_height_m": (5.0, 22.97966279614656),
            "heading_deg": (63.440059926756376, 243.44005992675636),
            "forward_overlap": 0.4076823325467079,
            "n_inliers": 32,
            "outlier_ratio": 0.2,
        },
        1042767785,
    ),
    (
        ("V", "F"),
        {
            "relief_m": 7.420886630252118,
            "building_fraction": 0.2279277215872508,
            "building_height_m": (5.0, 28.459880418499562),
            "heading_deg": (24.941835676211795, 204.94183567621178),
            "forward_overlap": 0.38191592100702293,
            "n_inliers": 140,
            "outlier_ratio": 0.4,
        },
        2053476562,
    ),
    (
        ("L", "F"),
        {
            "relief_m": 13.024210550629729,
            "building_fraction": 0.24165298213890174,
            "building_height_m": (5.0, 24.927130935433382),
            "heading_deg": (49.057521603257946, 49.057521603257946),
            "forward_overlap": 0.3956635392365079,
            "n_inliers": 40,
            "outlier_ratio": 0.4,
        },
        1795107502,
    ),
]


@pytest.mark.parametrize(("views", "scene", "seed"), MISSED_HEIGHTS)
def test_the_check_finds_the_height_the_model_missed(
    views, scene, seed, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Few true matches, a small frame, wide baselines: the model fitted on the candidates keeps
    one height (recall 0.72-0.80 with the check off, where MAGSAC++ and USAC_ACCURATE reach
    0.90-0.96); the check sees the band and near misses it leaves out, samples a second model
    across the heights and keeps it (recall >= 0.97; the calibrated model may improve on it
    after), and says so. (The posed model, off here, finds the height first.)"""
    monkeypatch.setattr(plus_module, "_POSED_MAX_INLIERS", 0)
    frame = {"width_px": 2000, "height_px": 1500, "focal_px": 1700.0}
    doc = simulate_pair(
        SimulationOptions(views=views, altitude_m=120.0, **frame, **scene), seed=seed
    )
    pair = parse_pair(doc).pair_data(0)
    truth = np.zeros(len(pair.matches), dtype=bool)
    truth[doc["ground_truth"]["inliers"]] = True
    unchecked = verify(pair, "hmcc-plus", VerifyOptions(plus=PlusOptions(check=False)))
    assert precision_recall(unchecked.inliers, truth)[1] < 0.85
    assert "check" not in unchecked.statistics
    result = verify(pair, "hmcc-plus")
    precision, recall = precision_recall(result.inliers, truth)
    assert recall >= 0.97 and precision >= 0.95, (precision, recall)
    fired, action = fired_and_action(result)
    assert fired and action in ("second model", "calibrated model"), action
    check = {s.name: s for s in result.stages}["check"]
    assert check.stats["coverage"]["kept"] < check.stats["coverage_after"]["kept"]
    assert not result.statistics["fallback"]["used"]


def test_without_a_second_model_usac_on_the_missed_matches_repairs_it(monkeypatch) -> None:
    """When the second model cannot be sampled, the pair is still not explained: USAC runs on
    the model's inliers and the matches it missed (not on all matches) and its model is
    kept."""
    from hmcc import plus

    monkeypatch.setattr(plus, "second_model", lambda *args, **kwargs: None)
    views, scene, seed = MISSED_HEIGHTS[1]
    frame = {"width_px": 2000, "height_px": 1500, "focal_px": 1700.0}
    doc = simulate_pair(
        SimulationOptions(views=views, altitude_m=120.0, **frame, **scene), seed=seed
    )
    pair = parse_pair(doc).pair_data(0)
    truth = np.zeros(len(pair.matches), dtype=bool)
    truth[doc["ground_truth"]["inliers"]] = True
    result = verify(pair, "hmcc-plus", VerifyOptions(plus=PlusOptions(calibrated=False)))
    assert fired_and_action(result) == (True, "usac model")
    check = {s.name: s for s in result.stages}["check"]
    assert check.stats["usac_pool"] < len(pair.matches)
    precision, recall = precision_recall(result.inliers, truth)
    assert recall >= 0.97 and precision >= 0.95, (precision, recall)


def test_the_check_keeps_a_model_that_explains_the_pair() -> None:
    """An easy pair: the check counts, finds nothing missing and changes nothing."""
    pair, truth = simulated(("V", "V"), ratio=0.3, seed=2, n_inliers=300)
    result = verify(pair, "hmcc-plus")
    check = {s.name: s for s in result.stages}["check"]
    assert fired_and_action(result) == (False, "kept")
    assert check.stats["coverage"]["kept"] == len(result.inliers) == check.kept
    unchecked = verify(pair, "hmcc-plus", VerifyOptions(plus=PlusOptions(check=False)))
    np.testing.assert_array_equal(result.inliers, unchecked.inliers)


def test_parallax_group_falls_back_to_the_furthest_off_the_field() -> None:
    """Enough strong-parallax candidates: they are the group; too few (few matches, one
    height): the quarter furthest off the seeds' field, so no sample is all one height."""
    off_field = np.linspace(0.0, 4.0, 40)
    strong = off_field > 3.0
    assert np.count_nonzero(strong) >= 6
    np.testing.assert_array_equal(parallax_group(strong, off_field, 3), strong)
    weak = off_field > 3.8
    group = parallax_group(weak, off_field, 3)
    assert np.count_nonzero(group) == 10 and group[-10:].all()
    np.testing.assert_array_equal(parallax_group(weak, off_field, 0), weak)


def test_matches_whose_rays_meet_behind_a_camera_are_not_inliers() -> None:
    """A match moved along its true epipolar line to where image 2 sees the point 1 km behind
    camera 1 fits the geometry exactly, but its rays diverge: not an inlier (the real
    references hold 15 such matches, benchmarks/results/reference_audit.md). Without the
    gates F alone keeps it. The divergence mask flags it and no other true match (the
    parallax gate catches this one too)."""
    doc = simulate_pair(SimulationOptions(views=("V", "F"), outlier_ratio=0.3, n_inliers=200), 3)
    pair = parse_pair(doc).pair_data(0)
    truth = np.zeros(len(pair.matches), dtype=bool)
    truth[doc["ground_truth"]["inliers"]] = True
    true1, true2 = (
        (np.asarray(p["R_world_to_cam"]), np.asarray(p["center"]))
        for p in doc["ground_truth"]["true_poses"]
    )
    row = int(np.flatnonzero(truth)[0])
    i1, i2 = pair.matches[row]
    ray = pair.camera1.rays(pair.keypoints1[i1 : i1 + 1, :2])[0] @ true1[0]
    behind = true1[1] - 1e3 * ray / np.linalg.norm(ray)
    seen = pair.camera2.K @ (true2[0] @ (behind - true2[1]))
    moved = pair.keypoints2.copy()
    moved[i2, :2] = seen[:2] / seen[2]
    wrong = dataclasses.replace(pair, keypoints2=moved)
    result = verify(wrong, "hmcc-plus")
    assert row not in result.inliers
    assert precision_recall(result.inliers, truth)[1] >= 0.97
    ungated = VerifyOptions(plus=PlusOptions(gate=False))
    assert row in verify(wrong, "hmcc-plus", ungated).inliers  # F alone cannot tell
    px1, px2 = wrong.matched_pixels()
    u1, u2 = wrong.camera1.undistort_pixels(px1), wrong.camera2.undistort_pixels(px2)
    np.testing.assert_array_equal(np.flatnonzero(_diverging(wrong, u1, u2, 5.0) & truth), [row])
    assert not _diverging(wrong, u1, u2, 180.0).any()


@pytest.mark.parametrize("turned", ["image 2", "both images"])
def test_the_rays_are_not_used_where_the_poses_do_not_fit(turned: str) -> None:
    """An image turned by 180 deg after capture (Brighton's strip 1): the motions on the plane
    still hold (an affine field absorbs it) but every ray is wrong, so the diverging-rays gate
    would drop true matches. One image turned: the relative rotation is 175+ deg off the
    model's; both turned alike: it fits but most inliers diverge. Either way the gate is not
    applied (the same inliers as with it off) and the statistics say why."""
    pair, truth = simulated(("V", "V"), ratio=0.5, seed=0, n_inliers=150)
    turn = np.diag([-1.0, -1.0, 1.0])  # 180 deg about the optical axis
    pose2 = Pose(turn @ pair.pose2.R_world_to_cam, pair.pose2.center)
    wrong = dataclasses.replace(pair, pose2=pose2)
    if turned == "both images":
        pose1 = Pose(turn @ pair.pose1.R_world_to_cam, pair.pose1.center)
        wrong = dataclasses.replace(wrong, pose1=pose1)
    result = verify(wrong, "hmcc-plus")
    off = verify(wrong, "hmcc-plus", VerifyOptions(plus=PlusOptions(divergence_deg=180.0)))
    np.testing.assert_array_equal(result.inliers, off.inliers)
    ignored = result.statistics["rays_ignored"]
    assert ignored["pose_misfit_deg"] > 170 or ignored["diverging_share"] > 0.9
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    assert "rays_ignored" not in verify(pair, "hmcc-plus").statistics


def test_reference_matches_meeting_above_the_drone_diverge() -> None:
    """DJI_0021-0023's reference (MAGSAC++, no POS) holds 5 matches whose rays meet 40-180 m
    above the drone, different patches in the two images; 4 of them diverge by more than
    5 deg (the fifth meets above the drone in front of both cameras), and none is an inlier."""
    doc = reference_to_pair(json.loads((BRIGHTON / "pair_DJI_0021_DJI_0023.json").read_text()))
    pair = parse_pair(doc).pair_data(0)
    px1, px2 = pair.matched_pixels()
    u1, u2 = pair.camera1.undistort_pixels(px1), pair.camera2.undistort_pixels(px2)
    flagged = np.flatnonzero(_diverging(pair, u1, u2, 5.0))
    assert np.intersect1d(flagged, doc["ground_truth"]["inliers"]).tolist() == [3, 42, 50, 51]
    assert not np.intersect1d(verify(pair, "hmcc-plus").inliers, [3, 10, 42, 50, 51]).size


#: bench_hard's sim V-V #168 at 0.7 outliers (33 true matches): MAGSAC++, USAC_ACCURATE and
#: hmcc-plus without the leave-one-out and the gate all keep the same 2 mismatches, 185-231 px
#: off the model of the true matches alone.
SELF_FITTED_SCENE = {
    "views": ("V", "V"),
    "altitude_m": 120.0,
    "relief_m": 17.5872,
    "building_fraction": 0.00858195,
    "building_height_m": (5.0, 23.8142),
    "heading_deg": (159.497, 159.497),
    "forward_overlap": 0.585753,
    "width_px": 2000,
    "height_px": 1500,
    "focal_px": 1700.0,
    "n_inliers": 33,
    "outlier_ratio": 0.7,
    "outlier_mode": "mismatch",
}


def test_inliers_the_model_keeps_only_by_being_fitted_on_them_are_dropped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Held out one at a time, the 2 mismatches are 4.5+ px (3 thresholds) off the model of
    the other inliers: dropped, the model refitted; precision 0.94 -> 1.0 at the same recall,
    and the check says how many. Off (with the gate off too), the baselines' answer. With the
    gate, one of them meets under the plane and is gated first: the leave-one-out drops the
    other. (The essential matrix of the inliers would drop them too where the hold-outs are
    off: that rule is off here.)"""
    monkeypatch.setattr(plus_module, "_EPIPOLES_AGREE_COS", math.inf)
    pair, truth = scene_pair(SELF_FITTED_SCENE, 873007250)
    ungated = PlusOptions(gate=False)
    off = verify(pair, "hmcc-plus", VerifyOptions(plus=dataclasses.replace(ungated, self_fit=0)))
    assert precision_recall(off.inliers, truth) == pytest.approx((33 / 35, 1.0))
    dropped = verify(pair, "hmcc-plus", VerifyOptions(plus=ungated))
    assert precision_recall(dropped.inliers, truth) == (1.0, 1.0)
    assert dropped.statistics["check"]["self_fitted"] == 2
    gated_off = verify(pair, "hmcc-plus", VerifyOptions(plus=PlusOptions(self_fit=0)))
    assert precision_recall(gated_off.inliers, truth) == pytest.approx((33 / 34, 1.0))
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    assert result.statistics["gated"] == 1 and result.statistics["check"]["self_fitted"] == 1
    corr = Correspondences(
        *(
            c.undistort_pixels(p)
            for c, p in zip((pair.camera1, pair.camera2), pair.matched_pixels(), strict=True)
        )
    )
    assert (
        np.sqrt(corr.sampson_sq(corr.from_pixels(result.model_matrix), result.inliers)).max()
        / corr.scale
        < 2.0
    )


#: bench_hard's sim L-F #27 of seed base 4000 at 0.1 outliers (36 true matches among 40): few
#: matches on rolling ground, the oblique image's far rows at the frame's edge.
LEVERAGE_SCENE = {
    "views": ("L", "F"),
    "altitude_m": 120.0,
    "relief_m": 23.8734,
    "building_fraction": 0.00246781,
    "building_height_m": (5.0, 29.0791),
    "heading_deg": (169.762, 169.762),
    "forward_overlap": 0.485799,
    "width_px": 2000,
    "height_px": 1500,
    "focal_px": 1700.0,
    "n_inliers": 36,
    "outlier_ratio": 0.1,
    "outlier_mode": "uniform",
}


def test_self_fitted_true_matches_the_calibrated_model_of_the_others_keeps_stay() -> None:
    """Held out one at a time, 5 of the 36 true matches leave the least-squares model of the
    others by 3+ thresholds (leverage: the family of F the others leave open swings away),
    and without the intrinsics they are dropped (recall 0.86, MAGSAC++ and USAC_ACCURATE
    0.92). The essential matrix of the others keeps all 5 within the threshold: none is
    dropped, and the check says so."""
    pair, truth = scene_pair(LEVERAGE_SCENE, 1121252080)
    uncalibrated = verify(pair, "hmcc-plus", VerifyOptions(plus=PlusOptions(calibrated=False)))
    assert precision_recall(uncalibrated.inliers, truth) == pytest.approx((1.0, 31 / 36))
    assert uncalibrated.statistics["check"]["self_fitted"] == 5
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    check = {s.name: s for s in result.stages}["check"].stats
    assert check["self_fitted"] == 0 and check["self_fit_kept"] == 5


#: bench_hard's sim B-F #175 of seed base 4000 at 0.5 outliers (55 true matches among 110): the
#: model keeps the ground; 8 true matches on roofs lie 31-72 px off it, 22-63 seed sigmas
#: across their plane epipolar lines, half of them in the check's control band.
ONE_MISS_SCENE = {
    "views": ("B", "F"),
    "altitude_m": 120.0,
    "relief_m": 12.6578,
    "building_fraction": 0.111082,
    "building_height_m": (5.0, 28.0288),
    "heading_deg": (204.055, 190.423),
    "forward_overlap": 0.561911,
    "width_px": 2000,
    "height_px": 1500,
    "focal_px": 1700.0,
    "n_inliers": 55,
    "outlier_ratio": 0.5,
    "outlier_mode": "uniform",
}


def test_one_expected_miss_tries_the_calibrated_model(monkeypatch: pytest.MonkeyPatch) -> None:
    """The roofs' matches hide in the control band: the coverage expects one true match
    missed, below the check's trigger of 2, so the check does not fire (recall 0.85 without
    the intrinsics; MAGSAC++ 0.96). The calibrated model is still tried on one miss: E of the
    ground's matches puts all 8 within 1.3 px, and it is kept (recall 1.0, precision 1.0).
    (The posed model, off here, finds them first.)"""
    monkeypatch.setattr(plus_module, "_POSED_MAX_INLIERS", 0)
    pair, truth = scene_pair(ONE_MISS_SCENE, 1127723226)
    uncalibrated = verify(pair, "hmcc-plus", VerifyOptions(plus=PlusOptions(calibrated=False)))
    assert precision_recall(uncalibrated.inliers, truth) == pytest.approx((1.0, 47 / 55))
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    check = {s.name: s for s in result.stages}["check"].stats
    assert (
        not check["fired"]
        and check["coverage"]["band_expected"] - check["coverage"]["band_kept"] == 1
    )
    assert result.statistics["check"]["action"] == "calibrated model"


#: bench_hard's sim V-V #160 of seed base 4000 at 0.8 outliers (35 true matches among 175):
#: MAGSAC++ keeps 31 matches at precision 0.94, USAC_ACCURATE 32 at 0.97.
OFF_LINE_SCENE = {
    "views": ("V", "V"),
    "altitude_m": 120.0,
    "relief_m": 5.06909,
    "building_fraction": 0.304286,
    "building_height_m": (5.0, 28.0934),
    "heading_deg": (162.698, 153.57),
    "forward_overlap": 0.42782,
    "width_px": 6000,
    "height_px": 4000,
    "focal_px": 4000.0,
    "n_inliers": 35,
    "outlier_ratio": 0.8,
    "outlier_mode": "uniform",
}


def test_outliers_on_the_epipolar_lines_by_chance_are_dropped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Three outliers lie within the threshold of the fitted F (precision 0.91 without the
    rule). Their motions are 30-40 seed sigmas across their plane epipolar lines, and the
    essential matrix of all the inliers puts them 550-810 px off: dropped (precision 1.0, the
    same 30 true matches), and the check's stage says how many. (The posed model, off here,
    keeps all 35 true matches and none of them.)"""
    monkeypatch.setattr(plus_module, "_POSED_MAX_INLIERS", 0)
    pair, truth = scene_pair(OFF_LINE_SCENE, 977995576)
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == pytest.approx((1.0, 30 / 35))
    assert {s.name: s for s in result.stages}["check"].stats["off_line"] == 3
    monkeypatch.setattr(plus_module, "_OFF_LINE_SIGMAS", math.inf)
    monkeypatch.setattr(plus_module, "_EPIPOLES_AGREE_COS", math.inf)  # nor off the model
    kept = verify(pair, "hmcc-plus")
    assert precision_recall(kept.inliers, truth) == pytest.approx((30 / 33, 30 / 35))


#: bench_hard's sim L-F #32 of seed base 0 at 0.6 outliers (53 true matches among 132, an
#: oblique pair over roofs), to the digit: MAGSAC++ keeps every true match, USAC_ACCURATE 52.
POSED_SCENE = {
    "views": ("L", "F"),
    "altitude_m": 120.0,
    "relief_m": 14.961110591334187,
    "building_fraction": 0.16401842034464276,
    "building_height_m": (5.0, 22.194349735275097),
    "heading_deg": (83.40079365438203, 83.40079365438203),
    "forward_overlap": 0.3751933147721882,
    "width_px": 6000,
    "height_px": 4000,
    "focal_px": 4000.0,
    "n_inliers": 53,
    "outlier_ratio": 0.6,
    "outlier_mode": "mismatch",
}


def test_the_posed_model_keeps_the_height_the_fitted_ones_miss(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The model fitted on the candidates misses 4 true matches of another height by 4-26 px,
    and OpenCV's E of its inliers is a twisted solution (150-350 px off them): recall 0.92.
    The essential matrix refined from the rough poses on the same inliers puts all 53 within
    the threshold (the 4 missed ones 0.3-0.9 px off) and no outlier; refined as F, it is kept
    (recall 1.0, precision 1.0) and the check says so. Off, the fitted model stays."""
    pair, truth = scene_pair(POSED_SCENE, 76952191)
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    assert result.statistics["check"]["action"] == "posed model"
    monkeypatch.setattr(plus_module, "_POSED_MAX_INLIERS", 0)
    off = verify(pair, "hmcc-plus")
    assert precision_recall(off.inliers, truth) == pytest.approx((1.0, 49 / 53))


def test_the_posed_essential_matrix_recovers_the_pose_it_starts_near() -> None:
    """Noise-free matches of a relief scene: started from a pose 3 deg and 10 deg (baseline)
    off, the kernel returns the true E (up to scale and sign) and a start on the truth stays."""
    rng = np.random.default_rng(5)
    points = np.column_stack((rng.uniform(-40, 40, (60, 2)), rng.uniform(-5, 15, 60)))
    c1, c2 = np.array([0.0, 0.0, 100.0]), np.array([30.0, 5.0, 102.0])
    r1 = np.diag([1.0, -1.0, -1.0])  # nadir
    r2 = _rotation_z(4.0) @ r1
    x1 = (points - c1) @ r1.T
    x2 = (points - c2) @ r2.T
    n1, n2 = x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]
    rotation, t = r2 @ r1.T, r2 @ (c1 - c2)
    truth = np.cross(np.eye(3), t / np.linalg.norm(t)) @ rotation

    def unit(e: np.ndarray) -> np.ndarray:
        e = e / np.linalg.norm(e)
        return e * np.sign(e.ravel()[np.argmax(np.abs(e))])

    rough_t = _rotation_z(10.0) @ t
    for start, base in ((rotation, t), (_rotation_z(3.0) @ rotation, rough_t)):
        e, _, _, ok = plus_kernels.posed_essential(n1, n2, start, base, 1e-4, 50)
        assert ok
        np.testing.assert_allclose(unit(e), unit(truth), atol=1e-6)
    assert not plus_kernels.posed_essential(n1, n2, rotation, np.zeros(3), 1e-4, 50)[3]
    # in one call from pixels (K = identity here), with the epipoles checked against the
    # rough baseline in each camera: a baseline 90 deg off is refused
    rows, k = np.arange(len(n1)), np.eye(3)
    b1, b2 = r1 @ (c2 - c1), r2 @ (c1 - c2)
    e, ok = plus_kernels.posed_model(n1, n2, rows, k, k, rotation, b1, b2, 1e-4, 50, 0.9)
    assert ok
    np.testing.assert_allclose(unit(e), unit(truth), atol=1e-6)
    turned1, turned2 = _rotation_z(90.0) @ b1, _rotation_z(90.0) @ b2
    args = (n1, n2, rows, k, k, rotation, turned1, turned2, 1e-4, 50, 0.9)
    assert not plus_kernels.posed_model(*args)[1]


def _rotation_z(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


#: bench_hard's sim V-V #114 of seed base 0 at 0.7 outliers (42 true matches among 140, one
#: height of a 300 m flight): MAGSAC++ and USAC_ACCURATE keep 44 matches at precision 0.91.
OFF_MODEL_SCENE = {
    "views": ("V", "V"),
    "altitude_m": 300.0,
    "relief_m": 22.871,
    "building_fraction": 0.0401722,
    "building_height_m": (5.0, 43.424),
    "heading_deg": (338.336, 518.336),
    "forward_overlap": 0.429842,
    "width_px": 2000,
    "height_px": 1500,
    "focal_px": 1700.0,
    "n_inliers": 42,
    "outlier_ratio": 0.7,
    "outlier_mode": "mismatch",
}


def test_outliers_the_fitted_model_bends_to_are_dropped(monkeypatch: pytest.MonkeyPatch) -> None:
    """Three mismatches lie within 0.4 px of the fitted F, which bent to them (the truth's
    model puts them 9 px off; they are 1-3 seed sigmas across their plane epipolar lines, like
    the true ones). The essential matrix of all the inliers, whose epipoles agree with the
    rough poses, puts them 3.7-4.7 px off and the model of the other inliers 9 px: dropped
    (precision 0.93 -> 1.0, every true match kept), and the check's stage says how many."""
    pair, truth = scene_pair(OFF_MODEL_SCENE, 721489984)
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    assert {s.name: s for s in result.stages}["check"].stats["off_model"] == 3
    monkeypatch.setattr(plus_module, "_EPIPOLES_AGREE_COS", math.inf)  # E never trusted
    kept = verify(pair, "hmcc-plus")
    assert precision_recall(kept.inliers, truth) == pytest.approx((42 / 45, 1.0))


#: bench_hard's sim V-V #149 of seed base 2000 at 0.6 outliers (30 true matches among 75),
#: to the digit: its seeds disagree with the model, so the fallback (MAGSAC++) runs.
FALLBACK_OFF_MODEL_SCENE = {
    "views": ("V", "V"),
    "altitude_m": 300.0,
    "relief_m": 28.350044825932816,
    "building_fraction": 0.052098389368839905,
    "building_height_m": (5.0, 66.61587727078341),
    "heading_deg": (56.09348330583133, 30.40897189090635),
    "forward_overlap": 0.6054243425358581,
    "width_px": 2000,
    "height_px": 1500,
    "focal_px": 1700.0,
    "n_inliers": 30,
    "outlier_ratio": 0.6,
    "outlier_mode": "mismatch",
}


def test_the_fallbacks_model_drops_the_outliers_it_bends_to_too(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The fallback's model keeps two mismatches (truth puts them 99 and 226 px off):
    E of its inliers, whose epipoles agree with the rough poses, does not, and the model of
    the others neither; dropped (precision 0.93 -> 1.0), and the fallback's stage says so.
    (The model the seeds doubt outscores it, 29 of the 30 true matches, and is the result;
    here the fallback's is kept.)"""
    pair, truth = scene_pair(FALLBACK_OFF_MODEL_SCENE, 1046702550)
    own = verify(pair, "hmcc-plus")
    assert own.statistics["fallback"]["outscored"]
    assert precision_recall(own.inliers, truth) == pytest.approx((1.0, 29 / 30))
    monkeypatch.setattr(plus_module, "_lower_cost", lambda *args: False)
    result = verify(pair, "hmcc-plus")
    assert result.statistics["fallback"]["used"]
    assert precision_recall(result.inliers, truth) == pytest.approx((1.0, 28 / 30))
    assert {s.name: s for s in result.stages}["fallback"].stats["off_model"] == 2
    monkeypatch.setattr(plus_module, "_EPIPOLES_AGREE_COS", math.inf)
    kept = verify(pair, "hmcc-plus")
    assert precision_recall(kept.inliers, truth) == pytest.approx((28 / 30, 28 / 30))


#: bench_hard's sim V-V #32 of seed base 0 at 0.6 outliers (60 true matches among 150, a
#: flat 120 m scene with a few buildings), to the digit: rounded, its E is not twisted.
TWISTED_SCENE = {
    "views": ("V", "V"),
    "altitude_m": 120.0,
    "relief_m": 5.1972150192213515,
    "building_fraction": 0.10411117931466923,
    "building_height_m": (5.0, 23.864695107882067),
    "heading_deg": (117.65949685028862, 132.34059454645083),
    "forward_overlap": 0.4448226485549193,
    "width_px": 6000,
    "height_px": 4000,
    "focal_px": 4000.0,
    "n_inliers": 60,
    "outlier_ratio": 0.6,
    "outlier_mode": "uniform",
}


def test_an_essential_matrix_off_the_rough_poses_drops_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On a nearly flat scene, E of the inliers is one of the plane's twisted solutions: it
    fits most of them and puts 6 true matches (of the buildings) beyond the threshold, with
    its epipoles 70-80 deg off the rough baseline. Not trusted, it drops nothing (recall 1.0);
    trusted, it would drop them (recall 0.9)."""
    pair, truth = scene_pair(TWISTED_SCENE, 358981148)
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    assert {s.name: s for s in result.stages}["check"].stats["off_model"] == 0
    monkeypatch.setattr(plus_module, "_EPIPOLES_AGREE_COS", 0.0)  # E always trusted
    trusted = verify(pair, "hmcc-plus")
    assert precision_recall(trusted.inliers, truth) == (1.0, 0.9)


def test_the_epipoles_of_the_rough_poses_agree_with_their_own_essential_matrix() -> None:
    """E = [t]x R of the rough relative pose has its epipoles on the rough baseline, whichever
    way E's sign; an E of a baseline turned by 40 deg (or more) about the vertical does not,
    whatever its rotation."""
    pair, _ = simulated(ratio=0.5, seed=3)
    calibration = Calibration(pair)
    r1, r2 = pair.pose1.R_world_to_cam, pair.pose2.R_world_to_cam
    rotation = r2 @ r1.T
    baseline = pair.pose1.center - pair.pose2.center

    def essential(degrees: float) -> np.ndarray:
        c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return np.cross(np.eye(3), r2 @ turn @ baseline) @ rotation  # [t]x R

    assert calibration.epipoles_agree(essential(0.0))
    assert calibration.epipoles_agree(-essential(0.0))
    assert calibration.epipoles_agree(essential(20.0))
    assert not calibration.epipoles_agree(essential(40.0))
    assert not calibration.epipoles_agree(essential(90.0))
    same_place = dataclasses.replace(pair.pose2, center=pair.pose1.center)
    still = Calibration(dataclasses.replace(pair, pose2=same_place))
    assert not still.epipoles_agree(essential(0.0))  # the cameras coincide: no baseline


CORE_SCENE = {
    "views": ("V", "V"),
    "altitude_m": 120.0,
    "relief_m": 23.54541502489398,
    "building_fraction": 0.17799603869817654,
    "building_height_m": (5.0, 29.901055739592685),
    "heading_deg": (173.72025003260165, 353.72025003260165),
    "forward_overlap": 0.4210094712601363,
    "width_px": 6000,
    "height_px": 4000,
    "focal_px": 4000.0,
    "n_inliers": 35,
    "outlier_ratio": 0.6,
    "outlier_mode": "uniform",
}


def test_a_true_match_in_the_band_s_core_tries_the_posed_model(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The coverage counts nothing missing (the wide band's 35 matches less the 3 outliers
    its control band expects are the 32 inliers), but the 3 true matches in it that the model
    misses lie 3.5-10 sigmas from their plane lines and 95-220 px off the model, two of them
    in the band's core (5 sigmas). The posed model puts all 35 within the threshold; without
    the core (bench_hard seed base 10000, V-V #86) recall 32/35."""
    pair, truth = scene_pair(CORE_SCENE, 618265066)
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    check = {s.name: s for s in result.stages}["check"].stats
    assert check["action"] == "posed model" and check["coverage"]["band_expected"] == 32
    monkeypatch.setattr(plus_module, "_CORE_SIGMAS", 0.0)
    off = verify(pair, "hmcc-plus")
    assert precision_recall(off.inliers, truth) == pytest.approx((1.0, 32 / 35))


FAR_FIELD_SCENE = {
    "views": ("B", "F"),
    "altitude_m": 120.0,
    "relief_m": 20.123207188160464,
    "building_fraction": 0.34377339763832526,
    "building_height_m": (5.0, 23.710249921935002),
    "heading_deg": (321.2036690470614, 501.2036690470614),
    "forward_overlap": 0.7872737351119261,
    "width_px": 6000,
    "height_px": 4000,
    "focal_px": 4000.0,
    "n_inliers": 42,
    "outlier_ratio": 0.1,
    "outlier_mode": "mismatch",
}


def test_true_matches_an_extrapolated_field_gated_are_given_back(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Oblique pair: the seeds lie within 200 m of each other, and 11 true matches of the
    ground 270-430 m away fall 13-37 m off the seeds' affine field on the plane (the rough
    poses' field is a homography): gated, though the model puts them 0.04-0.7 px off.
    Triangulated with the model's pose they lie at the inliers' heights and are given back
    (recall 1.0, ``ungated`` 11); without that (bench_hard seed base 8000, B-F #162) recall
    31/42 where MAGSAC++ keeps all 42."""
    pair, truth = scene_pair(FAR_FIELD_SCENE, 416905026)
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    assert {s.name: s for s in result.stages}["check"].stats["ungated"] == 11
    monkeypatch.setattr(plus_module, "_UNGATE_MIN", 10**9)
    off = verify(pair, "hmcc-plus")
    assert precision_recall(off.inliers, truth) == pytest.approx((1.0, 31 / 42))


CHANCE_SCENE = {
    "views": ("B", "F"),
    "altitude_m": 120.0,
    "relief_m": 19.347294001874875,
    "building_fraction": 0.10966535151051948,
    "building_height_m": (5.0, 27.786700374080716),
    "heading_deg": (244.2215208632131, 244.2215208632131),
    "forward_overlap": 0.4951378380951468,
    "width_px": 2000,
    "height_px": 1500,
    "focal_px": 1700.0,
    "n_inliers": 260,
    "outlier_ratio": 0.9,
    "outlier_mode": "uniform",
}


def test_gated_matches_on_the_lines_by_chance_stay_gated(monkeypatch: pytest.MonkeyPatch) -> None:
    """0.9 outliers: 4 of the 691 gated matches lie within the threshold by chance, 3 of them
    at the inliers' heights. Too few of the gated to be given back (bench_hard seed base
    2000, B-F #107); without the share, they would be (3 false inliers more)."""
    pair, truth = scene_pair(CHANCE_SCENE, 1823688077)
    result = verify(pair, "hmcc-plus")
    assert {s.name: s for s in result.stages}["check"].stats["ungated"] == 0
    kept = len(result.inliers)
    monkeypatch.setattr(plus_module, "_UNGATE_SHARE", 0.0)
    off = verify(pair, "hmcc-plus")
    assert {s.name: s for s in off.stages}["check"].stats["ungated"] == 3
    assert len(off.inliers) == kept + 3
    assert precision_recall(off.inliers, truth)[0] < precision_recall(result.inliers, truth)[0]


DOUBTED_SCENE = {
    "views": ("L", "F"),
    "altitude_m": 120.0,
    "relief_m": 23.774900462951503,
    "building_fraction": 0.28057285816481353,
    "building_height_m": (5.0, 21.69559207397766),
    "heading_deg": (191.13808539287643, 191.13808539287643),
    "forward_overlap": 0.413673377139599,
    "width_px": 2000,
    "height_px": 1500,
    "focal_px": 1700.0,
    "n_inliers": 31,
    "outlier_ratio": 0.9,
    "outlier_mode": "mismatch",
}


def test_a_model_the_seeds_doubt_is_kept_when_it_outscores_the_fallback(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """0.9 mismatch outliers: half the seeds are false (agreement 0.48), yet the checked
    model keeps all 31 true matches (and 1 outlier). The fallback runs and finds 13 matches,
    1 of them true (MAGSAC++ alone does the same): the model with the lower truncated cost is
    kept, and the statistics say the fallback ran and was outscored (bench_hard seed base
    4000, L-F #152; before, recall 1/31)."""
    pair, truth = scene_pair(DOUBTED_SCENE, 1111277408)
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == pytest.approx((31 / 32, 1.0))
    fallback = result.statistics["fallback"]
    assert not fallback["used"] and fallback["outscored"]
    assert "seed agreement" in fallback["reason"]
    assert "fallback" in [s.name for s in result.stages]
    monkeypatch.setattr(plus_module, "_lower_cost", lambda *args: False)
    off = verify(pair, "hmcc-plus")
    assert off.statistics["fallback"]["used"] and not off.statistics["fallback"]["outscored"]
    assert precision_recall(off.inliers, truth)[1] == pytest.approx(1 / 31)


def test_a_model_its_inliers_do_not_fix_gets_the_usac_rescue(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """bench_hard's sim V-F #150: the model keeps one height (5 true matches 38-90 px off it,
    within the check's noise allowance); held out one at a time, 14 of its 30 inliers leave
    it: not fixed by its inliers, so nothing is dropped and USAC on its inliers and missed
    matches replaces it (recall 0.86 -> 1.0). (The calibrated model, off here, repairs it
    first: ``test_the_calibrated_model_finds_the_true_matches_the_fitted_ones_miss``. With the
    gate's floor at the plane, the outliers it gates leave the pool USAC samples from, and its
    model lands elsewhere on this pair (recall 0.86): the floor is set as far down as the band
    reaches, the gate before the floor, to show the rescue. With the floor at the plane and
    the calibrated model off, no simulated pair of bench_hard's seed bases 0-3000 has the
    rescue raise its recall by 0.08 or more.)"""
    monkeypatch.setattr(plus_module, "_FLOOR_LENGTH", PlusOptions().band_length)
    pair, truth = scene_pair(CALIBRATED_SCENE, 11154278)
    uncalibrated = PlusOptions(calibrated=False)
    off = verify(
        pair, "hmcc-plus", VerifyOptions(plus=dataclasses.replace(uncalibrated, self_fit=0))
    )
    assert precision_recall(off.inliers, truth)[1] < 0.9
    result = verify(pair, "hmcc-plus", VerifyOptions(plus=uncalibrated))
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    check = {s.name: s for s in result.stages}["check"].stats
    assert check["unstable"] and check["action"] == "usac model"


#: bench_hard's sim V-F #150 at 0.7 outliers (35 true matches among 117): the model fitted on
#: the candidates keeps one height; its second model and USAC on its inliers and the matches
#: it missed leave 5 true matches 38-90 px off it.
CALIBRATED_SCENE = SELF_FITTED_SCENE | {
    "views": ("V", "F"),
    "relief_m": 22.5403,
    "building_fraction": 0.21617,
    "building_height_m": (5.0, 27.8646),
    "heading_deg": (252.399, 432.399),
    "forward_overlap": 0.733329,
    "n_inliers": 35,
}


def test_the_calibrated_model_finds_the_true_matches_the_fitted_ones_miss(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The essential matrix of the inliers, with the cameras' intrinsics, has no family of
    models to choose from: refined as F it keeps all 35 true matches and nothing else, where
    the fundamental matrices fitted on the same matches miss 5 (recall 0.86). (The posed
    model, off here, finds them first.)"""
    monkeypatch.setattr(plus_module, "_POSED_MAX_INLIERS", 0)
    pair, truth = scene_pair(CALIBRATED_SCENE, 11154278)
    off = verify(pair, "hmcc-plus", VerifyOptions(plus=PlusOptions(calibrated=False)))
    assert precision_recall(off.inliers, truth)[1] < 0.9
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    assert result.statistics["check"]["action"] == "calibrated model"


# --------------------------------------------------------------------------- fallback


def test_unreliable_pairs_fall_back_and_say_why() -> None:
    """A pair whose consistency cannot be trusted (here: min_inliers above what it has) runs
    the fallback estimator on all matches; the result names the reason and keeps its recall."""
    pair, truth = simulated(("V", "V"), ratio=0.5, seed=7, n_inliers=200)
    options = VerifyOptions(plus=PlusOptions(min_inliers=5000, fallback="magsac++"))
    result = verify(pair, "hmcc-plus", options)
    fallback = result.statistics["fallback"]
    assert fallback["used"] and "min_inliers" in fallback["reason"]
    assert result.stages[-1].name == "fallback"
    assert result.stages[-1].stats["estimator"] == "magsac++"
    precision, recall = precision_recall(result.inliers, truth)
    assert precision >= 0.97 and recall >= 0.9


def test_the_fallback_on_few_matches_samples_only_for_min_inliers_true_ones(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A pair of 20 matches is verified only with at least min_inliers (15) true ones, so the
    fallback draws the samples that find 15 of 20 at the confidence (49), not
    max_iters; a pair of hundreds of matches keeps max_iters."""
    seen: list[int] = []
    real = plus_module.estimate_model

    def spy(u1: np.ndarray, u2: np.ndarray, ransac: RansacOptions, seed: int) -> Any:
        seen.append(ransac.max_iters)
        return real(u1, u2, ransac, seed)

    monkeypatch.setattr(plus_module, "estimate_model", spy)
    few = parse_pair(simulate_pair(SimulationOptions(n_inliers=8, outlier_ratio=0.6), 3))
    result = verify(few.pair_data(0), "hmcc-plus")
    assert result.statistics["fallback"]["used"]
    ransac = result.options.ransac
    assert seen == [iterations_bound(15 / 20, ransac)] and 20 < seen[0] < ransac.max_iters
    assert result.stages[-1].stats["max_iters"] == seen[0]
    many, _ = simulated(("V", "V"), ratio=0.5, seed=7, n_inliers=200)
    verify(many, "hmcc-plus", VerifyOptions(plus=PlusOptions(min_inliers=5000)))
    assert seen[1] == ransac.max_iters


def test_random_matches_fall_back_and_find_little() -> None:
    """Only outliers: no consistent motion field, the fallback runs, few matches survive."""
    pair, truth = simulated(("V", "V"), ratio=0.0, seed=8, n_inliers=300)
    rng = np.random.default_rng(0)
    shuffled = pair.matches.copy()
    shuffled[:, 1] = rng.permutation(shuffled[:, 1])
    garbage = dataclasses.replace(pair, matches=shuffled)
    result = verify(garbage, "hmcc-plus")
    assert result.statistics["fallback"]["used"]
    assert len(result.inliers) < 0.2 * len(shuffled)


def test_a_given_plane_no_ray_reaches_is_an_error_not_a_fallback() -> None:
    """A plane the user gave that no ray reaches stays a 4xx error naming plane.z (only an
    automatic plane that cannot be estimated falls back)."""
    pair, _ = simulated(("V", "V"), ratio=0.3, seed=9, n_inliers=100)
    above = dataclasses.replace(pair, plane_z=10_000.0, ground_z=None)
    with pytest.raises(InputError) as e:
        verify(above, "hmcc-plus")
    assert e.value.field == "plane.z"


def test_other_models_are_refused_by_name() -> None:
    pair, _ = simulated(("V", "V"), ratio=0.3, seed=10, n_inliers=60)
    options = VerifyOptions(ransac=dataclasses.replace(VerifyOptions().ransac, model="essential"))
    with pytest.raises(InputError) as e:
        verify(pair, "hmcc-plus", options)
    assert e.value.field == "params.ransac.model"
    assert verify(pair, "hmcc-ransac", options).model_type == "essential"


@pytest.mark.parametrize("method", sorted(F_ONLY_METHODS))
def test_a_flight_refuses_a_model_its_method_does_not_fit(method: str) -> None:
    """At once, when the flight is made (a service answers 422, a command exits 2), rather
    than pair by pair."""
    ransac = dataclasses.replace(VerifyOptions().ransac, model="homography")
    options = VerifyOptions(ransac=ransac)
    with pytest.raises(InputError) as e:
        Flight({}, [], method, options)
    assert e.value.field == "params.ransac.model"
    assert Flight({}, [], "hmcc-ransac", options).options.ransac.model == "homography"


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("threshold_px", 0.0),
        ("grid_bins", 2),
        ("max_seeds", 4),
        ("lo_schedule", (0.1,)),
        ("min_seed_agreement", 1.5),
        ("hypotheses", 0),
        ("parallax_points", 9),
        ("polish", 100),
        ("min_candidate_share", -0.1),
        ("strong_parallax", -1.0),
        ("fallback", "nope"),
        ("check_share", 1.5),
        ("check_sigmas", 0.0),
    ],
)
def test_options_are_validated(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        PlusOptions(**{field: value})


POSED_MODEL_SCENE = {
    "views": ("V", "F"),
    "altitude_m": 300.0,
    "relief_m": 47.14051126988693,
    "building_fraction": 0.16460649947441228,
    "building_height_m": (5.0, 68.90967474507326),
    "heading_deg": (1.0353049072648624, 1.0353049072648624),
    "forward_overlap": 0.3941443406836108,
    "width_px": 2000,
    "height_px": 1500,
    "focal_px": 1700.0,
    "n_inliers": 34,
    "outlier_ratio": 0.7,
    "outlier_mode": "mismatch",
}


def test_a_posed_model_is_checked_by_usac_s_essential_matrix(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The off-model rule fits E from the rough poses (30-40 us), except where the model kept
    is the posed one: an E fitted the same way finds nothing off it. There, USAC's E drops the
    2 outliers the posed model keeps (bench_hard seed base 4000, V-F #60); with the posed E
    everywhere they stay."""
    pair, truth = scene_pair(POSED_MODEL_SCENE, 1502700740)
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    check = {s.name: s for s in result.stages}["check"].stats
    assert check["action"] == "posed model" and check["off_model"] == 2
    monkeypatch.setattr(plus_module, "essential_matrix", plus_module.posed_essential_matrix)
    posed = verify(pair, "hmcc-plus")
    assert precision_recall(posed.inliers, truth) == pytest.approx((34 / 36, 1.0))


SELF_FIT_SCENE = {
    "views": ("V", "F"),
    "altitude_m": 300.0,
    "relief_m": 6.916008053347403,
    "building_fraction": 0.053564752076862156,
    "building_height_m": (5.0, 49.19531059895023),
    "heading_deg": (28.685399679264314, 28.685399679264314),
    "forward_overlap": 0.30050460177810334,
    "width_px": 6000,
    "height_px": 4000,
    "focal_px": 4000.0,
    "n_inliers": 33,
    "outlier_ratio": 0.1,
    "outlier_mode": "mismatch",
}


def test_the_posed_model_of_the_others_keeps_self_fitted_true_matches(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Two true matches leave the least-squares model when held out; the posed model of the
    other inliers puts both within the threshold, so they stay. Without it (USAC's E of the
    others) both are dropped (bench_hard seed base 5000, V-F #99: recall 31/33)."""
    pair, truth = scene_pair(SELF_FIT_SCENE, 1637465733)
    result = verify(pair, "hmcc-plus")
    assert precision_recall(result.inliers, truth) == (1.0, 1.0)
    check = {s.name: s for s in result.stages}["check"].stats
    assert check["action"] == "kept" and check["self_fit_kept"] == 2
    monkeypatch.setattr(plus_module, "posed_model", lambda *args: None)
    usac = verify(pair, "hmcc-plus")
    assert precision_recall(usac.inliers, truth) == pytest.approx((1.0, 31 / 33))
