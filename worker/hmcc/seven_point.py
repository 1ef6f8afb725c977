"""The paper's final estimator: classic RANSAC on the fundamental matrix with the seven-point
algorithm (section 3: "the classical RANSAC method estimating a fundamental matrix with the
seven-point algorithm (Zhang, 1998)", maximum residual 1.0 px).

Why our own: OpenCV's ``findFundamentalMat(FM_RANSAC)`` silently runs LMedS instead when it is
given 14 matches or fewer (``fundam.cpp``: RANSAC only ``if npoints >= 15``), and LMedS ignores
the threshold. The HMCC filter often leaves that few survivors on oblique pairs (the paper's own
pairs have 15 to 44 true matches), so ``hmcc-ransac`` would not be the paper's method exactly
where it matters. This one runs RANSAC for every n >= 7, seeded.

What it does (one compiled loop, :mod:`hmcc.jit`, about as fast as OpenCV's C++):

* a sample is 7 distinct matches drawn uniformly (a xorshift64* generator seeded with
  ``seed``, so the samples do not depend on numba's or numpy's generators);
* the seven-point solver on Hartley-normalised points (centroid at the origin, mean distance
  sqrt 2, over all n points): the 2-D null space of the 7 x 9 system (Gauss-Jordan with
  complete pivoting), then the real roots of
  det(F2 + a (F1 - F2)) = 0 (closed form), up to three models per sample;
* a match is an inlier of a model when the larger of its two point-to-epipolar-line distances
  (pixels) is at most the threshold (OpenCV's criterion for F);
* a model replaces the best one only with strictly more inliers (the earliest sample wins ties);
* the number of samples N starts at ``max_iters`` and, whenever the best model improves, becomes
  min(N, round(log(1 - confidence) / log(1 - w^7))) for its inlier ratio w (0 when w = 1);
  sampling stops once N samples are drawn (at least one). This is OpenCV's
  ``RANSACUpdateNumIters``, the standard adaptive rule;
* a sample whose 7 x 9 system has rank below 7 (a pivot below 1e-9 of the first: coincident
  or repeated matches) gives no model;
* the result is the best minimal-sample model (its smallest singular value set to 0 against
  rounding, unit norm) and its inliers, without a refit (classic RANSAC; OpenCV's FM_RANSAC
  does not refit either).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .jit import compiled as _jit

__all__ = ["SAMPLE_SIZE", "SevenPointFit", "epipolar_max_distance", "ransac_fundamental"]

SAMPLE_SIZE = 7


@dataclass(frozen=True)
class SevenPointFit:
    """``matrix``: (3, 3) F in pixels (x2^T F x1 = 0, unit Frobenius norm) or None when no
    sample gave a model; ``inliers``: (N,) bool; ``iterations``: samples drawn."""

    matrix: np.ndarray | None
    inliers: np.ndarray
    iterations: int


def _normalising_transform(p: np.ndarray) -> np.ndarray:
    """Hartley's similarity: centroid to the origin, mean distance to it sqrt(2)."""
    centre = p.mean(axis=0)
    spread = float(np.mean(np.hypot(*(p - centre).T)))
    s = math.sqrt(2.0) / spread if spread > 0 else 1.0
    return np.array([[s, 0.0, -s * centre[0]], [0.0, s, -s * centre[1]], [0.0, 0.0, 1.0]])


def epipolar_max_distance(f: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(N,) larger of the two point-to-epipolar-line distances (pixels) of (N, 2) pixel
    correspondences under F (infinite where a line is undefined)."""
    h1 = np.column_stack((p1, np.ones(len(p1))))
    h2 = np.column_stack((p2, np.ones(len(p2))))
    l2 = h1 @ f.T
    l1 = h2 @ f
    r2 = np.einsum("ij,ij->i", h2, l2) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        worst = np.fmax(r2 / (l2[:, 0] ** 2 + l2[:, 1] ** 2), r2 / (l1[:, 0] ** 2 + l1[:, 1] ** 2))
    return np.sqrt(np.where(np.isnan(worst), np.inf, worst))


@_jit
def _next(state: np.ndarray) -> int:
    """xorshift64*: the next 63-bit random integer (``state``: (1,) uint64, updated)."""
    x = state[0]
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    state[0] = x
    return int((x * np.uint64(2685821657736338717)) >> np.uint64(1))


@_jit
def _det3(m: np.ndarray) -> float:
    return (
        m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
        - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
        + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
    )


@_jit
def _real_roots(c3: float, c2: float, c1: float, c0: float, out: np.ndarray) -> int:
    """Real roots of c3 a^3 + c2 a^2 + c1 a + c0 into ``out``; their number."""
    scale = max(abs(c0), abs(c1), abs(c2), abs(c3))
    if scale == 0.0:
        return 0
    if abs(c3) < 1e-12 * scale:  # quadratic (or linear)
        if abs(c2) < 1e-12 * scale:
            if c1 == 0.0:
                return 0
            out[0] = -c0 / c1
            return 1
        disc = c1 * c1 - 4.0 * c2 * c0
        if disc < 0.0:
            return 0
        sq = math.sqrt(disc)
        out[0] = (-c1 + sq) / (2.0 * c2)
        out[1] = (-c1 - sq) / (2.0 * c2)
        return 2
    a, b, c = c2 / c3, c1 / c3, c0 / c3
    q = (a * a - 3.0 * b) / 9.0
    r = (2.0 * a * a * a - 9.0 * a * b + 27.0 * c) / 54.0
    if r * r < q * q * q:  # three real roots
        theta = math.acos(max(-1.0, min(1.0, r / math.sqrt(q * q * q))))
        sq = -2.0 * math.sqrt(q)
        out[0] = sq * math.cos(theta / 3.0) - a / 3.0
        out[1] = sq * math.cos((theta + 2.0 * math.pi) / 3.0) - a / 3.0
        out[2] = sq * math.cos((theta - 2.0 * math.pi) / 3.0) - a / 3.0
        return 3
    big = -math.copysign(1.0, r) * (abs(r) + math.sqrt(r * r - q * q * q)) ** (1.0 / 3.0)
    small = q / big if big != 0.0 else 0.0
    out[0] = big + small - a / 3.0
    return 1


@_jit
def _seven_point(q1: np.ndarray, q2: np.ndarray, sample: np.ndarray, models: np.ndarray) -> int:
    """Up to three normalised-coordinate F of one sample into ``models`` (3, 3, 3); their
    number (0 when the 7 equations are dependent)."""
    a = np.empty((7, 9))
    for i in range(7):
        k = sample[i]
        u1, v1, u2, v2 = q1[k, 0], q1[k, 1], q2[k, 0], q2[k, 1]
        a[i, 0], a[i, 1], a[i, 2] = u2 * u1, u2 * v1, u2
        a[i, 3], a[i, 4], a[i, 5] = v2 * u1, v2 * v1, v2
        a[i, 6], a[i, 7], a[i, 8] = u1, v1, 1.0
    # The 2-D null space by Gauss-Jordan elimination with complete pivoting (an SVD of the
    # 7 x 9 system costs ten times more in the loop).
    column = np.arange(9)
    scale = 0.0
    for k in range(7):
        best, pr, pc = 0.0, k, k
        for r in range(k, 7):
            for c in range(k, 9):
                if abs(a[r, c]) > best:
                    best, pr, pc = abs(a[r, c]), r, c
        if k == 0:
            scale = best
        if not best > 1e-9 * scale:  # rank below 7: coincident or repeated matches
            return 0
        for c in range(9):
            a[k, c], a[pr, c] = a[pr, c], a[k, c]
        for r in range(7):
            a[r, k], a[r, pc] = a[r, pc], a[r, k]
        column[k], column[pc] = column[pc], column[k]
        pivot = a[k, k]
        for c in range(k, 9):
            a[k, c] /= pivot
        for r in range(7):
            if r != k and a[r, k] != 0.0:
                factor = a[r, k]
                for c in range(k, 9):
                    a[r, c] -= factor * a[k, c]
    null = np.zeros((2, 9))  # a = [I | B] in permuted columns: x_free = e_j, x_bound = -B e_j
    for j in range(2):
        null[j, column[7 + j]] = 1.0
        for i in range(7):
            null[j, column[i]] = -a[i, 7 + j]
    f2 = np.empty((3, 3))
    d = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            f2[r, c] = null[1, 3 * r + c]
            d[r, c] = null[0, 3 * r + c] - null[1, 3 * r + c]
    p0 = _det3(f2)
    pp = _det3(f2 + d)
    pm = _det3(f2 - d)
    p2 = _det3(f2 + 2.0 * d)
    c2 = 0.5 * (pp + pm) - p0
    odd = 0.5 * (pp - pm)
    c3 = (0.5 * (p2 - p0 - 4.0 * c2) - odd) / 3.0
    c1 = odd - c3
    roots = np.empty(3)
    found = _real_roots(c3, c2, c1, p0, roots)
    count = 0
    for j in range(found):
        f = f2 + roots[j] * d
        norm = math.sqrt(np.sum(f * f))
        if math.isfinite(norm) and norm > 0.0:
            models[count] = f / norm
            count += 1
    return count


@_jit
def _to_pixels(t2_transposed: np.ndarray, f: np.ndarray, t1: np.ndarray, out: np.ndarray) -> None:
    """``out = T2^T f T1`` (3 x 3 loops: a BLAS call per product costs more than the product)."""
    tmp = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            tmp[r, c] = f[r, 0] * t1[0, c] + f[r, 1] * t1[1, c] + f[r, 2] * t1[2, c]
    for r in range(3):
        for c in range(3):
            out[r, c] = (
                t2_transposed[r, 0] * tmp[0, c]
                + t2_transposed[r, 1] * tmp[1, c]
                + t2_transposed[r, 2] * tmp[2, c]
            )


@_jit
def _count_inliers(f: np.ndarray, p1: np.ndarray, p2: np.ndarray, threshold_sq: float) -> int:
    """Matches whose larger squared point-to-epipolar-line distance is <= ``threshold_sq``."""
    count = 0
    for i in range(len(p1)):
        x1, y1, x2, y2 = p1[i, 0], p1[i, 1], p2[i, 0], p2[i, 1]
        a2 = f[0, 0] * x1 + f[0, 1] * y1 + f[0, 2]
        b2 = f[1, 0] * x1 + f[1, 1] * y1 + f[1, 2]
        c2 = f[2, 0] * x1 + f[2, 1] * y1 + f[2, 2]
        a1 = f[0, 0] * x2 + f[1, 0] * y2 + f[2, 0]
        b1 = f[0, 1] * x2 + f[1, 1] * y2 + f[2, 1]
        r = x2 * a2 + y2 * b2 + c2
        r2 = r * r
        # r2 / (a^2 + b^2) <= t^2, without dividing (a zero line is an outlier unless r = 0)
        if r2 <= threshold_sq * (a2 * a2 + b2 * b2) and r2 <= threshold_sq * (a1 * a1 + b1 * b1):
            count += 1
    return count


@_jit
def _ransac(
    q1: np.ndarray,
    q2: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    t1: np.ndarray,
    t2_transposed: np.ndarray,
    threshold_px: float,
    confidence: float,
    max_iters: int,
    seed: int,
) -> tuple[np.ndarray, int, int]:
    """The RANSAC loop: (best F in pixels (3, 3), its inlier count (-1: none), samples)."""
    n = len(p1)
    state = np.empty(1, dtype=np.uint64)
    state[0] = np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(0x2545F4914F6CDD1D)
    if state[0] == 0:
        state[0] = np.uint64(1)
    threshold_sq = threshold_px * threshold_px
    log_fail = math.log(max(1.0 - confidence, 2.2250738585072014e-308))
    sample = np.empty(7, dtype=np.int64)
    models = np.empty((3, 3, 3))
    best = np.zeros((3, 3))
    f = np.empty((3, 3))
    best_count = -1
    niters = max_iters
    it = 0
    while it < niters:
        it += 1
        for i in range(7):  # 7 distinct indices
            while True:
                k = _next(state) % n
                fresh = True
                for j in range(i):
                    if sample[j] == k:
                        fresh = False
                        break
                if fresh:
                    sample[i] = k
                    break
        found = _seven_point(q1, q2, sample, models)
        for m in range(found):
            _to_pixels(t2_transposed, models[m], t1, f)
            count = _count_inliers(f, p1, p2, threshold_sq)
            if count > max(best_count, 6):
                best_count = count
                best[:, :] = f
                good = (count / n) ** 7
                if good >= 1.0:
                    niters = 0
                else:
                    bound = log_fail / math.log1p(-good)
                    if bound < niters:
                        niters = max(0, int(round(bound)))
    return best, best_count, it


def ransac_fundamental(
    points1: np.ndarray,
    points2: np.ndarray,
    threshold_px: float,
    confidence: float,
    max_iters: int,
    seed: int,
) -> SevenPointFit:
    """Classic seven-point RANSAC on (N, 2) pixel correspondences, N >= 7 (see the module
    docstring). Deterministic for a seed."""
    n = len(points1)
    if n < SAMPLE_SIZE:
        raise ValueError(f"points1: {n} matches, the seven-point RANSAC needs {SAMPLE_SIZE}")
    p1 = np.ascontiguousarray(points1, dtype=np.float64)
    p2 = np.ascontiguousarray(points2, dtype=np.float64)
    t1, t2 = _normalising_transform(p1), _normalising_transform(p2)
    q1 = np.ascontiguousarray(p1 * t1[0, 0] + t1[:2, 2])
    q2 = np.ascontiguousarray(p2 * t2[0, 0] + t2[:2, 2])
    best, count, iterations = _ransac(
        q1,
        q2,
        p1,
        p2,
        t1,
        np.ascontiguousarray(t2.T),
        float(threshold_px),
        float(confidence),
        int(max_iters),
        int(seed),
    )
    if count < 0:
        return SevenPointFit(None, np.zeros(n, dtype=bool), iterations)
    u, s, vt = np.linalg.svd(best)  # rank 2 against rounding, unit norm
    best = u @ np.diag([s[0], s[1], 0.0]) @ vt
    best = best / np.linalg.norm(best)
    inliers = epipolar_max_distance(best, p1, p2) <= threshold_px
    return SevenPointFit(best, inliers, iterations)
