"""Tests of hmcc.gc: the Lu et al. (2016) geometrical-consistency voting pre-filter."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hmcc.gc_filter import GCOptions, gc_filter

IMAGE_W, IMAGE_H = 2000.0, 1500.0


def _similarity_pair(
    n: int,
    outlier_ratio: float,
    *,
    rotation_deg: float = 30.0,
    scale: float = 1.5,
    noise_px: float = 1.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image 2 = image 1 under a similarity; outliers are random in both images.

    Returns kp1, kp2 (N, 4) [x, y, size, angle_deg] and the (N,) inlier mask, rows shuffled.
    """
    rng = np.random.default_rng(seed)
    n_out = round(n * outlier_ratio)
    n_in = n - n_out
    th = math.radians(rotation_deg)
    sr = scale * np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    t = np.array([300.0, -120.0])
    p1 = rng.uniform([0.0, 0.0], [IMAGE_W, IMAGE_H], size=(n, 2))
    p2 = p1 @ sr.T + t + rng.normal(0.0, noise_px, size=(n, 2))
    corners = np.array([[0, 0], [IMAGE_W, 0], [0, IMAGE_H], [IMAGE_W, IMAGE_H]]) @ sr.T + t
    p2[n_in:] = rng.uniform(corners.min(axis=0), corners.max(axis=0), size=(n_out, 2))
    size1 = rng.uniform(2.0, 20.0, n)
    angle1 = rng.uniform(0.0, 360.0, n)
    size2 = size1 * scale * np.exp(rng.normal(0.0, 0.05, n))
    angle2 = np.mod(angle1 + rotation_deg + rng.normal(0.0, 2.0, n), 360.0)
    size2[n_in:] = rng.uniform(2.0, 30.0, n_out)
    angle2[n_in:] = rng.uniform(0.0, 360.0, n_out)
    inlier = np.arange(n) < n_in
    perm = rng.permutation(n)
    kp1 = np.column_stack([p1, size1, angle1])[perm]
    kp2 = np.column_stack([p2, size2, angle2])[perm]
    return kp1, kp2, inlier[perm]


def _recall_removal(keep: np.ndarray, inlier: np.ndarray) -> tuple[float, float]:
    return float(keep[inlier].mean()), float(1.0 - keep[~inlier].mean())


def _precision(keep: np.ndarray, inlier: np.ndarray) -> float:
    return float(inlier[keep].mean())


# ---------------------------------------------------------------------------------- accuracy


@pytest.mark.parametrize("outlier_ratio", [0.3, 0.6, 0.8])
def test_similarity_with_outliers(outlier_ratio: float) -> None:
    kp1, kp2, inlier = _similarity_pair(500, outlier_ratio, seed=1)
    keep, stats = gc_filter(kp1, kp2)
    recall, removal = _recall_removal(keep, inlier)
    assert recall >= 0.9, (recall, removal)
    assert removal >= 0.8, (recall, removal)
    assert keep.dtype == bool and keep.shape == (500,)
    # The overall peak recovers the similarity to within one bin.
    assert abs(stats["peak_rotation_deg"] - 30.0) <= stats["rotation_bin_deg"]
    assert abs(math.log(stats["peak_scale"] / 1.5)) <= stats["log_scale_bin"]
    assert stats["n_kept"] == int(keep.sum())
    assert not stats["subsampled"]
    assert stats["pairs_evaluated"] == 500 * 499


@pytest.mark.parametrize(
    ("rotation_deg", "scale"),
    [(-5.0, 1.0), (355.0, 0.8), (359.0, 1.0), (1.0, 1.2), (-1.0, 1.5)],
)
def test_rotation_wraps_around_zero(rotation_deg: float, scale: float) -> None:
    # -5 deg sits on the boundary between the 350 and 0 deg bins: the inliers' own peaks split
    # between bins 35 and 0, which are neighbours only if rotation distance is circular.
    kp1, kp2, inlier = _similarity_pair(
        500, 0.6, rotation_deg=rotation_deg, scale=scale, noise_px=2.0, seed=4
    )
    keep, stats = gc_filter(kp1, kp2)
    recall, removal = _recall_removal(keep, inlier)
    assert recall >= 0.9, (recall, removal, stats["n_correct_bins"])
    assert removal >= 0.8, (recall, removal)
    diff = (stats["peak_rotation_deg"] - rotation_deg) % 360.0
    assert min(diff, 360.0 - diff) <= stats["rotation_bin_deg"]


def test_pairwise_rotation_across_atan2_branch() -> None:
    # Segments pointing near 180 deg in image 1 and near -180 deg in image 2 differ by 2 deg,
    # not 358: all pairs must vote in the 0 deg bin.
    kp1 = np.array([[0.0, 0.0, 1.0, 0.0], [-100.0, 1.7, 1.0, 0.0], [-200.0, 3.5, 1.0, 0.0]])
    kp2 = kp1.copy()
    kp2[:, 1] = -kp1[:, 1]  # angles 179 deg -> -179 deg (a 2 deg rotation, mirrored slightly)
    keep, stats = gc_filter(kp1, kp2)
    assert keep.all()
    assert stats["peak_rotation_deg"] == 0.0


def test_keypoint_size_and_angle_columns_are_ignored() -> None:
    kp1, kp2, _ = _similarity_pair(300, 0.5, seed=5)
    keep_a, _ = gc_filter(kp1, kp2)
    kp1b, kp2b = kp1.copy(), kp2.copy()
    kp1b[:, 2] = -1.0
    kp2b[:, 2] = 0.0
    kp1b[:, 3] = 359.0
    kp2b[:, 3] = np.nan
    keep_b, stats = gc_filter(kp1b, kp2b)
    np.testing.assert_array_equal(keep_a, keep_b)
    json.dumps(stats, allow_nan=False)


# ------------------------------------------------------------------------------ subsampling


def test_subsampled_path_gives_similar_precision() -> None:
    kp1, kp2, inlier = _similarity_pair(1500, 0.6, seed=6)
    keep_full, stats_full = gc_filter(kp1, kp2, GCOptions(max_partners=2000))
    keep_sub, stats_sub = gc_filter(kp1, kp2, GCOptions(max_partners=64, seed=3))
    assert not stats_full["subsampled"] and stats_sub["subsampled"]
    assert stats_sub["partners_per_match"] == 64
    assert stats_sub["pairs_evaluated"] == 1500 * 64
    recall, removal = _recall_removal(keep_sub, inlier)
    assert recall >= 0.9 and removal >= 0.8, (recall, removal)
    assert abs(_precision(keep_sub, inlier) - _precision(keep_full, inlier)) <= 0.05
    assert stats_sub["peak_rotation_deg"] == stats_full["peak_rotation_deg"]
    assert stats_sub["peak_scale"] == stats_full["peak_scale"]


def test_deterministic_for_a_seed() -> None:
    kp1, kp2, _ = _similarity_pair(800, 0.7, seed=7)
    opts = GCOptions(max_partners=32, seed=11)
    keep_a, stats_a = gc_filter(kp1, kp2, opts)
    keep_b, stats_b = gc_filter(kp1, kp2, opts)
    np.testing.assert_array_equal(keep_a, keep_b)
    assert stats_a == stats_b


def test_exact_path_ignores_seed() -> None:
    kp1, kp2, _ = _similarity_pair(200, 0.5, seed=8)
    keep_a, stats_a = gc_filter(kp1, kp2, GCOptions(seed=1))
    keep_b, stats_b = gc_filter(kp1, kp2, GCOptions(seed=2))
    np.testing.assert_array_equal(keep_a, keep_b)
    assert stats_a == stats_b


# ------------------------------------------------------------------------------ degenerate


def _check_clean(keep: np.ndarray, stats: dict, n: int) -> None:
    assert keep.shape == (n,) and keep.dtype == bool
    json.dumps(stats, allow_nan=False)  # raises on NaN / inf / non-JSON types
    assert np.isfinite(np.asarray(stats["histogram"], dtype=float)).all()


@pytest.mark.parametrize("n", [0, 1, 2])
def test_tiny_inputs(n: int) -> None:
    kp1, kp2, _ = _similarity_pair(max(n, 1), 0.0, seed=9)
    keep, stats = gc_filter(kp1[:n], kp2[:n])
    _check_clean(keep, stats, n)
    assert stats["n_matches"] == n
    if n < 2:
        assert not keep.any()
        assert stats["peak_rotation_deg"] is None and stats["pairs_evaluated"] == 0
    else:
        assert keep.all()  # two consistent matches vote for each other


def test_all_duplicate_points_do_not_vote() -> None:
    kp = np.tile([[10.0, 20.0, 3.0, 45.0]], (50, 1))
    keep, stats = gc_filter(kp, kp.copy())
    _check_clean(keep, stats, 50)
    assert not keep.any()
    assert stats["pairs_voting"] == 0 and stats["peak_votes"] == 0.0
    assert stats["peak_scale"] is None


def test_some_duplicates_sizes_and_nonfinite_rows() -> None:
    kp1, kp2, inlier = _similarity_pair(300, 0.3, seed=10)
    kp1[:, 2] = 0.0  # sizes <= 0
    kp2[:, 2] = -5.0
    kp1[1] = kp1[0]  # duplicate match: its segment to match 0 has zero length
    kp2[1] = kp2[0]
    kp1[2, 0] = np.nan  # non-finite position: neither votes nor is kept
    kp2[3, 1] = np.inf
    keep, stats = gc_filter(kp1, kp2)
    _check_clean(keep, stats, 300)
    assert not keep[2] and not keep[3]
    recall, removal = _recall_removal(keep, inlier)
    assert recall >= 0.9 and removal >= 0.8


@pytest.mark.parametrize(
    ("kp1_shape", "kp2_shape"), [((5, 3), (5, 4)), ((5, 4), (6, 4)), ((4,), (4,))]
)
def test_bad_shapes_raise(kp1_shape: tuple[int, ...], kp2_shape: tuple[int, ...]) -> None:
    with pytest.raises(ValueError):
        gc_filter(np.zeros(kp1_shape), np.zeros(kp2_shape))


# --------------------------------------------------------------------------------- options


def test_default_options_are_the_papers() -> None:
    opts = GCOptions()
    _, stats = gc_filter(np.zeros((0, 4)), np.zeros((0, 4)), opts)
    assert len(stats["rotation_bin_centres_deg"]) == 36
    assert len(stats["scale_bin_centres"]) == 17
    assert stats["scale_bin_centres"][0] == pytest.approx(0.2)
    assert stats["scale_bin_centres"][-1] == pytest.approx(5.0)
    assert opts.min_vote_ratio == 0.4 and opts.peak_radius_bins == 3
    # Lu et al. as the HMCC paper times it: every pair (quadratic), unweighted votes.
    assert opts.max_partners is None and opts.distance_weight_px == 0.0


def test_without_a_cap_every_match_votes_for_every_other() -> None:
    """The default is the quadratic filter: 2 000 matches, 2 000 x 1 999 pairs, no subsample
    (the former default capped partners at 512)."""
    kp1, kp2, inlier = _similarity_pair(2000, 0.5, seed=4)
    keep, stats = gc_filter(kp1, kp2)
    assert not stats["subsampled"] and stats["partners_per_match"] == 1999
    assert stats["pairs_evaluated"] == 2000 * 1999
    assert _precision(keep, inlier) >= 0.95


def test_knn_candidate_lists_vote_through_first_candidates() -> None:
    """Two candidates per feature of image 1 (the true one first for even features, second for
    odd ones, a random wrong one otherwise): a feature votes through its first candidate, every
    candidate is voted on by the other features, and the true candidates are the ones kept."""
    rng = np.random.default_rng(9)
    kp1, kp2, inlier = _similarity_pair(400, 0.0, seed=9)
    wrong2 = kp2.copy()
    wrong2[:, :2] = rng.uniform([0.0, 0.0], [IMAGE_W, IMAGE_H], size=(400, 2))
    ids = np.arange(400)
    first_true = ids % 4 != 3  # a quarter of the features list the wrong candidate first
    rows1 = np.vstack((kp1, kp1))
    rows2 = np.vstack(
        (np.where(first_true[:, None], kp2, wrong2), np.where(first_true[:, None], wrong2, kp2))
    )
    true_rows = np.r_[first_true, ~first_true]
    query = np.r_[ids, ids]
    keep, stats = gc_filter(rows1, rows2, query_ids=query)
    assert stats["features"] == 400
    assert stats["partners_per_match"] == 399
    assert stats["pairs_evaluated"] == 800 * 399
    assert keep[true_rows].mean() >= 0.9
    assert keep[~true_rows].mean() <= 0.05


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("rotation_tolerance_deg", 0.0),
        ("rotation_tolerance_deg", -10.0),
        ("rotation_tolerance_deg", float("nan")),
        ("rotation_tolerance_deg", 200.0),
        ("rotation_tolerance_deg", "10"),
        ("log_scale_tolerance", 0.0),
        ("log_scale_tolerance", float("inf")),
        ("log_scale_tolerance", 5.0),
        ("min_vote_ratio", 0.0),
        ("min_vote_ratio", 1.5),
        ("min_vote_ratio", float("nan")),
        ("peak_radius_bins", -1),
        ("peak_radius_bins", 1.5),
        ("scale_range", 1.0),
        ("scale_range", float("inf")),
        ("distance_weight_px", -1.0),
        ("max_partners", 0),
        ("max_partners", 2.5),
        ("max_partners", True),
        ("seed", -1),
        ("seed", 1.0),
    ],
)
def test_invalid_options_name_the_field(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=rf"^{field}: "):
        GCOptions(**{field: value})


# ---------------------------------------------------------------------------------- sizes


@pytest.mark.parametrize("n", [100, 1000])
def test_keeps_the_true_matches_and_drops_the_outliers_at_either_size(n: int) -> None:
    """The filter at 100 and 1000 matches (60 % outliers), every match voted on by every
    other (its time is bench_paper's, not a test's)."""
    kp1, kp2, inlier = _similarity_pair(n, 0.6, seed=12)
    keep, stats = gc_filter(kp1, kp2)
    recall, removal = _recall_removal(keep, inlier)
    assert stats["partners_per_match"] == n - 1
    assert recall >= 0.95, (recall, removal)
    assert removal >= 0.9, (recall, removal)


@pytest.mark.parametrize("weight", [0.0, 10.0])
def test_compiled_vote_equals_the_numpy_vote(
    monkeypatch: pytest.MonkeyPatch, weight: float
) -> None:
    """The uncapped vote runs compiled; the numpy path (used with a cap) gives the same result
    on the same pairs: duplicates, a non-finite row, k-NN candidate lists."""
    from hmcc import gc_filter as module

    kp1, kp2, _ = _similarity_pair(300, 0.5, seed=13)
    kp1[5] = kp1[6]
    kp2[5] = kp2[6]
    kp1[7, 0] = np.nan
    query = np.arange(300) // 2  # two candidates per feature
    options = GCOptions(distance_weight_px=weight)
    compiled = gc_filter(kp1, kp2, options, query_ids=query)
    monkeypatch.setattr(module, "_COMPILED", False)
    numpy_path = gc_filter(kp1, kp2, options, query_ids=query)
    np.testing.assert_array_equal(compiled[0], numpy_path[0])
    assert compiled[1]["pairs_voting"] == numpy_path[1]["pairs_voting"]
    np.testing.assert_allclose(compiled[1]["histogram"], numpy_path[1]["histogram"], rtol=1e-12)
