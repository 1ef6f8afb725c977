"""The compiled loops of hmcc-plus against numpy/LAPACK references (hmcc.plus_kernels)."""

from __future__ import annotations

import numpy as np
import pytest

from hmcc import plus_kernels as kernels
from tests.hmcc.test_plus import exact_pair


def design(joint: np.ndarray) -> np.ndarray:
    """(N, 9) rows of x2^T F x1 = 0 for row-major F."""
    x1, y1, x2, y2 = joint[:, 0], joint[:, 1], joint[:, 3], joint[:, 4]
    return np.column_stack((x2 * x1, x2 * y1, x2, y2 * x1, y2 * y1, y2, x1, y1, np.ones(len(x1))))


def reference_least_squares(joint: np.ndarray) -> np.ndarray:
    """Unit-norm null vector of the design by SVD, then the nearest rank-2 matrix."""
    f = np.linalg.svd(design(joint))[2][-1].reshape(3, 3)
    u, s, vt = np.linalg.svd(f)
    return (u * np.array([s[0], s[1], 0.0])) @ vt


def same_up_to_sign(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - np.sign((a * b).sum()) * b).max())


@pytest.mark.parametrize("outliers", [0.0, 0.3, 0.6])
def test_least_squares_is_the_svd_solution(outliers: float) -> None:
    """Inverse iteration on well-posed fits, LAPACK on the ill-posed ones (many outliers):
    both give the SVD answer."""
    rng = np.random.default_rng(int(outliers * 10))
    for seed in range(20):
        p1, p2, _ = exact_pair(int(rng.integers(8, 200)), seed)
        p2 = p2 + rng.normal(0.0, 1.0, p2.shape)
        bad = rng.random(len(p2)) < outliers
        p2[bad] = rng.uniform(0.0, 1200.0, (int(bad.sum()), 2))
        joint = kernels.normalise(p1, p2)[0]
        f, ok = kernels.least_squares(joint, np.arange(len(p1)))
        assert ok
        assert same_up_to_sign(f, reference_least_squares(joint)) < 1e-7
        assert abs(np.linalg.det(f)) < 1e-12


def test_rank2_is_the_nearest_rank_two_matrix() -> None:
    """The closed form against the SVD, over scales from 1e-6 to 1e3."""
    rng = np.random.default_rng(4)
    for _ in range(500):
        g = rng.normal(size=(3, 3)) * rng.uniform(1e-6, 1e3)
        u, s, vt = np.linalg.svd(g)
        nearest = (u * np.array([s[0], s[1], 0.0])) @ vt
        kernels._rank2(g)
        assert np.abs(g - nearest).max() <= 1e-9 * s[0]


def test_leave_one_out_follows_the_refit_without_each_row() -> None:
    """The one-step downdate against least_squares refitted without each row: on noisy true
    matches the held-out distances agree within 30 % (or 0.05 px); fewer than 9 rows: inf."""
    rng = np.random.default_rng(5)
    for seed in range(10):
        p1, p2, _ = exact_pair(40, seed)
        p2 = p2 + rng.normal(0.0, 0.5, p2.shape)
        joint, scale = kernels.normalise(p1, p2)[:2]
        rows = np.arange(40)
        fast = np.sqrt(kernels.leave_one_out(joint, rows)) / scale
        exact = []
        for r in range(len(rows)):
            f, _ = kernels.least_squares(joint, np.delete(rows, r))
            exact.append(np.sqrt(kernels.sampson_sq(f, joint, rows[r : r + 1])[0]) / scale)
        np.testing.assert_allclose(fast, exact, rtol=0.3, atol=0.05)
        assert np.isinf(kernels.leave_one_out(joint, rows[:8])).all()


def test_smallest_eigenvector_of_an_exact_null_space() -> None:
    a = np.random.default_rng(0).normal(size=(8, 9))
    null = np.linalg.svd(a)[2][-1]
    v = kernels._smallest_eigenvector(a.T @ a, kernels._GAUGE)
    assert same_up_to_sign(v, null) < 1e-9


def test_lu_solves_and_reports_singular_systems() -> None:
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(9, 9)), rng.normal(size=9)
    lu, perm, x = a.copy(), np.empty(9, dtype=np.int64), np.empty(9)
    assert kernels._lu(lu, perm)
    kernels._lu_solve(lu, perm, b, x)
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10)
    a[3] = 0.0
    assert not kernels._lu(a, perm)


def test_minimal_models_fit_their_samples_and_drop_singular_ones() -> None:
    p1, p2, _ = exact_pair(40, 3)
    joint = kernels.normalise(p1, p2)[0]
    samples = np.array([np.arange(8), np.arange(8, 16), [0, 0, 1, 2, 3, 4, 5, 6]])
    models = kernels.minimal_models(joint, samples)
    assert models.shape == (2, 3, 3)  # the repeated row makes the third singular
    for model, sample in zip(models, samples[:2], strict=True):
        assert np.abs(design(joint[sample]) @ model.ravel()).max() < 1e-9
        assert model.ravel() @ kernels._GAUGE == pytest.approx(1.0)


def test_samples_are_deterministic_distinct_and_stratified() -> None:
    strong = np.zeros(50, dtype=bool)
    strong[[3, 9, 17, 21, 40]] = True
    samples = kernels._draw_samples(strong, 32, 3, 7)
    assert samples.shape == (32, 8)
    np.testing.assert_array_equal(samples, kernels._draw_samples(strong, 32, 3, 7))
    assert not np.array_equal(samples, kernels._draw_samples(strong, 32, 3, 8))
    assert all(len(set(row)) == 8 for row in samples.tolist())
    assert strong[samples[:, :3]].all() and not strong[samples[:, 3:]].any()
    # Too few strong candidates for the share: 8 from all.
    few = kernels._draw_samples(strong, 32, 6, 7)
    assert all(len(set(row)) == 8 for row in few.tolist())


def test_scoring_takes_every_candidate_up_to_its_limit_then_a_weighted_stratified_sample() -> None:
    strong = np.zeros(100, dtype=bool)
    strong[::10] = True
    positions, weights = kernels._scored_rows(strong, 100)
    np.testing.assert_array_equal(positions, np.arange(100))
    np.testing.assert_array_equal(weights, np.ones(100))
    strong = np.zeros(2000, dtype=bool)
    strong[::4] = True  # 500 strong: more than half of the sample's 256
    positions, weights = kernels._scored_rows(strong, 256)
    assert len(positions) == 256 and len(set(positions.tolist())) == 256
    assert np.count_nonzero(strong[positions]) == 128
    # each group's weights stand for the whole group
    assert weights[strong[positions]].sum() == pytest.approx(500)
    assert weights[~strong[positions]].sum() == pytest.approx(1500)
    few = np.zeros(2000, dtype=bool)
    few[:5] = True  # the rare group whole, the rest from the others
    positions, weights = kernels._scored_rows(few, 256)
    assert np.count_nonzero(few[positions]) == 5 and len(positions) == 256
    assert weights[few[positions]].tolist() == [1.0] * 5


def test_a_scored_sample_finds_the_model_scoring_every_candidate_finds() -> None:
    """Candidates of a real flight's pair (1 500, a fifth of them outliers): the model kept
    from hypotheses scored on 256 of them keeps every true match in each of 20 pairs, as the
    one scored on all does (scored on one candidate, it misses most of them in some)."""
    for seed in range(20):
        rng = np.random.default_rng(seed)
        p1, p2, _ = exact_pair(1500, seed)
        p2 = p2 + rng.normal(0.0, 0.3, p2.shape)
        bad = rng.random(len(p2)) < 0.2
        p2[bad] = rng.uniform(0.0, 1200.0, (int(bad.sum()), 2))
        joint, scale, _, _ = kernels.normalise(p1, p2)
        strong = rng.random(len(p1)) < 0.1
        args = (joint, np.arange(len(p1)), strong, 32, 3, 3, scale**2, seed)
        for scored in (10**9, 256):
            f, found, kept, _ = kernels.fit_candidates(*args, scored)
            assert found and kept[~bad].all(), (seed, scored)
            assert np.count_nonzero(kept & bad) <= 3


def test_motion_mode_is_the_densest_window_of_the_histogram() -> None:
    rng = np.random.default_rng(2)
    vectors = np.concatenate(
        (rng.normal((30.0, -5.0), 0.5, (60, 2)), rng.uniform(-80, 80, (140, 2)))
    )
    cx, cy, cell, votes = kernels.motion_mode(vectors, 24)
    assert np.hypot(cx - 30.0, cy + 5.0) < 1.5 * cell
    inside = (np.abs(vectors[:, 0] - cx) <= 1.5 * cell) & (np.abs(vectors[:, 1] - cy) <= 1.5 * cell)
    assert votes == pytest.approx(np.count_nonzero(inside), abs=3)  # cell edges vs the box


def test_motion_field_does_not_depend_on_where_the_points_are() -> None:
    """The affine design is centred: moving every start point leaves the seeds unchanged."""
    rng = np.random.default_rng(3)
    start = rng.uniform(-300, 300, (120, 2))
    vectors = start @ np.array([[0.01, 0.002], [-0.003, 0.01]]) + (12.0, 4.0)
    vectors += rng.normal(0.0, 0.05, vectors.shape)
    vectors[:30] = rng.uniform(-50, 50, (30, 2))
    seeds, m2, _, on_field = kernels.motion_field(start, vectors, 12.0, 4.0, 2.0, 60)
    moved = kernels.motion_field(start + (5e5, -3e5), vectors, 12.0, 4.0, 2.0, 60)
    np.testing.assert_array_equal(seeds, moved[0])
    assert len(seeds) == 60 and (seeds >= 30).all() and 70 <= on_field <= 90
    np.testing.assert_array_equal(seeds, np.argsort(m2, kind="stable")[:60])
