"""The compiled inner loops of ``hmcc-plus``: scoring, sampling, fitting and refining.

A pure-numpy hmcc-plus spent about 200 small numpy calls per pair (about 1.5 ms), more than
OpenCV's MAGSAC++ needs for a whole easy pair; here each stage is one or two compiled calls
(:mod:`hmcc.jit`; measured in ``benchmarks/plus_stages.py``). :mod:`hmcc.plus` holds the
method around them: options, statistics and the OpenCV rescue.

The kernels take and return plain arrays and scalars. Matches are rows; models are normalised
fundamental matrices (see :class:`hmcc.plus.Correspondences`) in the row-major order of
``x2^T F x1 = 0``.
"""

from __future__ import annotations

import math

import numpy as np

from .jit import compiled as _jit

__all__ = [
    "check_counts",
    "epipolar_band",
    "fit_candidates",
    "least_squares",
    "minimal_models",
    "motion_field",
    "motion_mode",
    "normalise",
    "plane_epipole_directions",
    "posed_essential",
    "posed_model",
    "refine",
    "sampson_sq",
    "to_pixels",
]

#: Mahalanobis distance (squared) under which a match counts as on the motion field: chi2(2) 99 %.
_FIELD_CHI2 = 9.21
_CAUCHY_ITERATIONS = 3
#: Inverse iterations before LAPACK's ``eigh`` (about 7 us here): each divides the error by
#: the ratio of the two smallest eigenvalues, 0.1-0.3 on a sampled model's polish (12 steps
#: fell to ``eigh`` there: 16 us a least-squares fit of 106 rows, now 9).
_INVERSE_ITERATIONS = 40

#: Normalises the 8-point systems of the minimal samples: f . _GAUGE = 1 (a fixed generic
#: direction; f33 = 1 would fail where the centroids correspond, the usual case).
_GAUGE = np.array([0.31, -0.27, 0.42, 0.19, 0.36, -0.33, 0.28, -0.39, 0.41])


# --------------------------------------------------------------------------- small algebra


@_jit
def _median(x: np.ndarray) -> float:
    """The upper median (0 for no values)."""
    if len(x) == 0:
        return 0.0
    return float(np.sort(x)[len(x) // 2])


@_jit
def _solve3(m: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """(3, k) solution of the 3x3 system ``m x = rhs`` by the adjugate."""
    a, b, c = m[0, 0], m[0, 1], m[0, 2]
    d, e, f = m[1, 0], m[1, 1], m[1, 2]
    g, h, i = m[2, 0], m[2, 1], m[2, 2]
    c00, c01, c02 = e * i - f * h, c * h - b * i, b * f - c * e
    c10, c11, c12 = f * g - d * i, a * i - c * g, c * d - a * f
    c20, c21, c22 = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * c00 + b * c10 + c * c20
    inv = 1.0 / det
    out = np.empty_like(rhs)
    for k in range(rhs.shape[1]):
        r0, r1, r2 = rhs[0, k], rhs[1, k], rhs[2, k]
        out[0, k] = (c00 * r0 + c01 * r1 + c02 * r2) * inv
        out[1, k] = (c10 * r0 + c11 * r1 + c12 * r2) * inv
        out[2, k] = (c20 * r0 + c21 * r1 + c22 * r2) * inv
    return out


@_jit
def _affine_fit(design: np.ndarray, targets: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(N, k) residuals of the weighted least-squares fit of ``targets`` (N, k) on the affine
    ``design`` (N, 2) (the columns x, y and a constant)."""
    n, k = targets.shape
    normal = np.zeros((3, 3))
    rhs = np.zeros((3, k))
    for r in range(n):
        x, y, wr = design[r, 0], design[r, 1], w[r]
        if wr == 0.0:
            continue
        normal[0, 0] += wr * x * x
        normal[0, 1] += wr * x * y
        normal[0, 2] += wr * x
        normal[1, 1] += wr * y * y
        normal[1, 2] += wr * y
        normal[2, 2] += wr
        for c in range(k):
            t = wr * targets[r, c]
            rhs[0, c] += t * x
            rhs[1, c] += t * y
            rhs[2, c] += t
    normal[1, 0], normal[2, 0], normal[2, 1] = normal[0, 1], normal[0, 2], normal[1, 2]
    for j in range(3):
        normal[j, j] += 1e-9
    coef = _solve3(normal, rhs)
    out = np.empty_like(targets)
    for r in range(n):
        x, y = design[r, 0], design[r, 1]
        for c in range(k):
            out[r, c] = targets[r, c] - (coef[0, c] * x + coef[1, c] * y + coef[2, c])
    return out


@_jit
def _mahalanobis_sq(residual: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N,) squared Mahalanobis lengths of (N, 2) residuals under a symmetric 2x2 covariance."""
    c00, c01, c11 = cov[0, 0], cov[0, 1], cov[1, 1]
    det = max(c00 * c11 - c01 * c01, 1e-300)
    a, b, d = c11 / det, -c01 / det, c00 / det
    out = np.empty(len(residual))
    for r in range(len(residual)):
        x, y = residual[r, 0], residual[r, 1]
        out[r] = (a * x + 2.0 * b * y) * x + d * y * y
    return out


@_jit
def _centred(points: np.ndarray) -> np.ndarray:
    return points - points.sum(axis=0) / len(points)


# --------------------------------------------------------------------------- scoring


@_jit
def motion_mode(vectors: np.ndarray, bins: int) -> tuple[float, float, float, int]:
    """Centre (x, y) of the densest 3x3 window of a ``bins`` x ``bins`` histogram of the (N, 2)
    motion vectors over their 2-98 % range, the cell size and the window's votes."""
    n = len(vectors)
    k_lo, k_hi = int(0.02 * (n - 1)), int(0.98 * (n - 1))
    xs, ys = np.sort(vectors[:, 0]), np.sort(vectors[:, 1])
    x0, y0 = xs[k_lo], ys[k_lo]
    cell = max(xs[k_hi] - x0, ys[k_hi] - y0, 1e-9 * bins) / bins
    # Cells 2 .. bins+1 of a grid padded by two: everything outside the range lands in the
    # outer ring (clipped), which no window reaches.
    side = bins + 4
    top = side - 1.0
    h = np.zeros((side, side), dtype=np.int64)
    for r in range(n):
        i = int(min(max((vectors[r, 0] - x0) / cell + 2.0, 0.0), top))
        j = int(min(max((vectors[r, 1] - y0) / cell + 2.0, 0.0), top))
        h[i, j] += 1
    best, bi, bj = -1, 0, 0
    for i in range(bins):
        for j in range(bins):
            votes = 0
            for da in range(3):
                for db in range(3):
                    votes += h[1 + i + da, 1 + j + db]
            if votes > best:
                best, bi, bj = votes, i, j
    return x0 + (bi + 0.5) * cell, y0 + (bj + 0.5) * cell, cell, best


@_jit
def motion_field(
    start: np.ndarray,
    vectors: np.ndarray,
    centre_x: float,
    centre_y: float,
    radius: float,
    max_seeds: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Cauchy-weighted affine motion field ``v = A s + b`` around the mode: the seeds (the
    smallest residuals, best first, at least 8, at most ``max_seeds``), the (N,) squared
    Mahalanobis residuals, the 2x2 residual covariance and the count on the field."""
    n = len(start)
    design = _centred(start)
    residual = vectors.copy()
    residual[:, 0] -= centre_x
    residual[:, 1] -= centre_y
    cov = np.eye(2) * (radius * radius / 4.0)
    m2 = _mahalanobis_sq(residual, cov)
    near = m2 < 4.0  # within the radius of the mode
    if np.count_nonzero(near) < 3:  # no mode to speak of (degenerate spread): use everything
        near[:] = True
    for _ in range(_CAUCHY_ITERATIONS):
        w = np.where(near, 1.0 / (1.0 + m2), 0.0)
        residual = _affine_fit(design, vectors, w)
        cov = np.zeros((2, 2))
        for r in range(n):
            x, y = residual[r, 0], residual[r, 1]
            cov[0, 0] += w[r] * x * x
            cov[0, 1] += w[r] * x * y
            cov[1, 1] += w[r] * y * y
        total = max(w.sum(), 1e-12)
        cov[0, 0] = cov[0, 0] / total + 1e-12
        cov[1, 1] = cov[1, 1] / total + 1e-12
        cov[0, 1] /= total
        cov[1, 0] = cov[0, 1]
        m2 = _mahalanobis_sq(residual, cov)
        near = m2 < 4.0 * _FIELD_CHI2
    on_field = int(np.count_nonzero(m2 < _FIELD_CHI2))
    order = np.argsort(m2, kind="mergesort")
    return order[: min(max(on_field, 8), max_seeds)], m2, cov, on_field


@_jit
def plane_epipole_directions(
    start: np.ndarray, center1: np.ndarray, center2: np.ndarray, z0: float
) -> tuple[np.ndarray, bool]:
    """(N, 2) unit directions of the epipolar lines on the plane Z = z0 through each start
    point, towards the point where the baseline meets the plane; False when there are none
    (the cameras coincide)."""
    n = len(start)
    out = np.zeros((n, 2))
    a1, a2 = center1[2] - z0, center2[2] - z0
    ex = a2 * center1[0] - a1 * center2[0]
    ey = a2 * center1[1] - a1 * center2[1]
    ez = a2 - a1
    if not max(abs(ex), abs(ey), abs(ez)) > 1e-9 * max(abs(a1), abs(a2), 1.0) ** 2:
        return out, False
    for r in range(n):
        dx, dy = ex - ez * start[r, 0], ey - ez * start[r, 1]
        norm = np.hypot(dx, dy)
        if not norm > 0.0:
            return out, False
        out[r, 0], out[r, 1] = dx / norm, dy / norm
    return out, True


@_jit
def epipolar_band(
    start: np.ndarray,
    vectors: np.ndarray,
    directions: np.ndarray,
    seeds: np.ndarray,
    max_band: int,
    band_length: float,
    floor_length: float,
    strong_parallax: float,
    parallax_floor: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float, float]:
    """Band indices (closest to their line first), the (N,) masks of plausible parallax for
    an inlier (the band's, and not below the plane: see ``floor_length``) and of strong
    parallax, the (N,) distances across the line in sigmas (inf where the parallax is not
    plausible for the band) and off the seeds' field along it in sigmas, and sigma across the
    line, the seeds' median parallax and the parallax reach (metres; ``band_length`` x the
    larger of the seeds' median parallax and ``parallax_floor``, + 3 sigma). An inlier may lie
    at most ``floor_length`` x that larger parallax (+ 3 sigma) below the seeds' field: 1 is
    the plane itself. See :func:`hmcc.plus.epipolar_band`."""
    n = len(start)
    design = _centred(start)
    lines = np.empty((n, 2))  # across the line | along it
    for r in range(n):
        d0, d1, v0, v1 = directions[r, 0], directions[r, 1], vectors[r, 0], vectors[r, 1]
        lines[r, 0] = v1 * d0 - v0 * d1
        lines[r, 1] = v0 * d0 + v1 * d1
    w = np.zeros(n)
    w[seeds] = 1.0
    off = _affine_fit(design, lines, w)  # both fitted on the seeds
    along_off = off[:, 1].copy()
    across = off[:, 0].copy()
    sigma = max(1.4826 * _median(np.abs(across[seeds])), 1e-9)
    for _ in range(_CAUCHY_ITERATIONS - 1):  # then all matches, Cauchy-weighted, across only
        for r in range(n):
            z = across[r] / (2.0 * sigma)
            w[r] = 1.0 / (1.0 + z * z)
        across = _affine_fit(design, lines[:, :1].copy(), w)[:, 0]
        sigma = max(1.4826 * _median(np.abs(across[seeds])), 1e-9)
    parallax = _median(lines[seeds, 1])
    along_sigma = 1.4826 * _median(np.abs(along_off[seeds]))
    spread = max(sigma, along_sigma)
    scale = max(abs(parallax), parallax_floor)
    reach = band_length * scale + 3.0 * spread
    along_abs = np.abs(along_off)
    plausible = along_abs <= reach
    score = np.full(n, np.inf)
    for r in range(n):
        if plausible[r]:
            score[r] = abs(across[r]) / sigma
    k = min(max_band, int(np.count_nonzero(score < 3.0)))
    band = np.argsort(score, kind="mergesort")[:k]
    off_field = along_abs / spread
    strong = off_field > strong_parallax
    inlier = plausible & (along_off >= -(floor_length * scale + 3.0 * spread))
    return band, inlier, strong, score, off_field, sigma, parallax, reach


# --------------------------------------------------------------------------- models


@_jit
def normalise(p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """(N, 6) homogeneous points of both images side by side, each image moved by its centroid
    and both scaled by one factor (mean absolute coordinate 1); the scale and the two 3x3
    transforms (pixels to normalised)."""
    n = len(p1)
    c1 = p1.sum(axis=0) / max(n, 1)
    c2 = p2.sum(axis=0) / max(n, 1)
    spread = 0.0
    for r in range(n):
        spread += abs(p1[r, 0] - c1[0]) + abs(p1[r, 1] - c1[1])
        spread += abs(p2[r, 0] - c2[0]) + abs(p2[r, 1] - c2[1])
    scale = 1.0 / max(spread / max(4 * n, 1), 1e-12)
    joint = np.ones((n, 6))
    for r in range(n):
        joint[r, 0] = (p1[r, 0] - c1[0]) * scale
        joint[r, 1] = (p1[r, 1] - c1[1]) * scale
        joint[r, 3] = (p2[r, 0] - c2[0]) * scale
        joint[r, 4] = (p2[r, 1] - c2[1]) * scale
    transforms = []
    for c in (c1, c2):
        t = np.eye(3)
        t[0, 0], t[1, 1], t[0, 2], t[1, 2] = scale, scale, -scale * c[0], -scale * c[1]
        transforms.append(t)
    return joint, scale, transforms[0], transforms[1]


@_jit
def to_pixels(f: np.ndarray, t1: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """The pixel model ``t2^T f t1`` of a normalised one, scaled to unit Frobenius norm."""
    g = t2.T @ (f @ t1)
    return g / np.sqrt((g * g).sum())


@_jit
def _sampson_sq_row(f: np.ndarray, joint: np.ndarray, r: int) -> float:
    x1, y1, x2, y2 = joint[r, 0], joint[r, 1], joint[r, 3], joint[r, 4]
    a0 = f[0, 0] * x1 + f[0, 1] * y1 + f[0, 2]  # F x1
    a1 = f[1, 0] * x1 + f[1, 1] * y1 + f[1, 2]
    a2 = f[2, 0] * x1 + f[2, 1] * y1 + f[2, 2]
    b0 = f[0, 0] * x2 + f[1, 0] * y2 + f[2, 0]  # F^T x2
    b1 = f[0, 1] * x2 + f[1, 1] * y2 + f[2, 1]
    e = x2 * a0 + y2 * a1 + a2
    return e * e / max(a0 * a0 + a1 * a1 + b0 * b0 + b1 * b1, 1e-300)


@_jit
def sampson_sq(f: np.ndarray, joint: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Squared normalised Sampson distances of the ``rows`` of ``joint`` to the model ``f``."""
    out = np.empty(len(rows))
    for i in range(len(rows)):
        out[i] = _sampson_sq_row(f, joint, rows[i])
    return out


@_jit
def _design_row(joint: np.ndarray, r: int, out: np.ndarray) -> None:
    x1, y1, x2, y2 = joint[r, 0], joint[r, 1], joint[r, 3], joint[r, 4]
    out[0], out[1], out[2] = x2 * x1, x2 * y1, x2
    out[3], out[4], out[5] = y2 * x1, y2 * y1, y2
    out[6], out[7], out[8] = x1, y1, 1.0


@_jit
def _lu(a: np.ndarray, perm: np.ndarray) -> bool:
    """In-place LU factorisation with partial pivoting of the square ``a``; False if singular."""
    n = a.shape[0]
    for c in range(n):
        perm[c] = c
    for c in range(n):
        p = c
        for r in range(c + 1, n):
            if abs(a[r, c]) > abs(a[p, c]):
                p = r
        if a[p, c] == 0.0:
            return False
        if p != c:
            perm[c], perm[p] = perm[p], perm[c]
            for k in range(n):
                a[c, k], a[p, k] = a[p, k], a[c, k]
        inv = 1.0 / a[c, c]
        for r in range(c + 1, n):
            a[r, c] *= inv
            m = a[r, c]
            if m != 0.0:
                for k in range(c + 1, n):
                    a[r, k] -= m * a[c, k]
    return True


@_jit
def _lu_solve(lu: np.ndarray, perm: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out`` = the solution of ``a x = b`` from the factors of :func:`_lu`."""
    n = lu.shape[0]
    for i in range(n):
        s = b[perm[i]]
        for k in range(i):
            s -= lu[i, k] * out[k]
        out[i] = s
    for i in range(n - 1, -1, -1):
        s = out[i]
        for k in range(i + 1, n):
            s -= lu[i, k] * out[k]
        out[i] = s / lu[i, i]


@_jit
def _smallest_eigenvector(m: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Unit eigenvector of the smallest eigenvalue of the symmetric positive semi-definite
    ``m``. Inverse iteration from ``start`` first: each step divides the other components by
    their eigenvalue's ratio to the smallest, which is tiny for a well-posed fit (a shift of
    1e-13 x the trace keeps an exact null space solvable); LAPACK's ``eigh`` when that does
    not converge (near-equal smallest eigenvalues: a fit on mostly outliers)."""
    n = m.shape[0]
    lu = m.copy()
    trace = 0.0
    for i in range(n):
        trace += m[i, i]
    for i in range(n):
        lu[i, i] += 1e-13 * trace + 1e-300
    perm = np.empty(n, dtype=np.int64)
    x = start / np.sqrt((start * start).sum())
    if _lu(lu, perm):
        y = np.empty(n)
        for _ in range(_INVERSE_ITERATIONS):
            _lu_solve(lu, perm, x, y)
            norm = np.sqrt((y * y).sum())
            if not norm > 0.0 or not np.isfinite(norm):
                break
            if (y * x).sum() < 0.0:
                norm = -norm
            change = 0.0
            for i in range(n):
                v = y[i] / norm
                change = max(change, abs(v - x[i]))
                x[i] = v
            if change < 1e-13:
                return x
    return np.linalg.eigh(m)[1][:, 0].copy()


@_jit
def least_squares(joint: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, bool]:
    """The rank-2 model minimising the algebraic error of ``rows`` (at least 8) at unit norm;
    False when there are too few rows or the fit is not finite."""
    if len(rows) < 8:
        return np.zeros((3, 3)), False
    normal = np.zeros((9, 9))
    a = np.empty(9)
    for r in rows:
        _design_row(joint, r, a)
        for i in range(9):
            ai = a[i]
            for j in range(i, 9):
                normal[i, j] += ai * a[j]
    for i in range(9):
        for j in range(i):
            normal[i, j] = normal[j, i]
    f = _smallest_eigenvector(normal, _GAUGE).reshape(3, 3)
    # Rank 2 (the nearest in Frobenius norm): F (I - v v^T), v the right singular vector of
    # the smallest singular value, i.e. the smallest eigenvector of F^T F.
    v = _smallest_eigenvector(f.T @ f, _GAUGE[:3])
    fv = f @ v
    for i in range(3):
        for j in range(3):
            f[i, j] -= fv[i] * v[j]
    return f, bool(np.isfinite(f).all())


@_jit
def minimal_models(joint: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """(K', 3, 3) models of (K, 8) row samples (8-point, gauge-fixed ``f . _GAUGE = 1``, no
    rank-2 step: they are only scored); singular or non-finite samples dropped."""
    models = np.empty((len(samples), 3, 3))
    a = np.empty((9, 9))
    perm = np.empty(9, dtype=np.int64)
    rhs = np.zeros(9)
    rhs[8] = 1.0
    f = np.empty(9)
    kept = 0
    for s in range(len(samples)):
        for i in range(8):
            _design_row(joint, samples[s, i], a[i])
        a[8, :] = _GAUGE
        if not _lu(a, perm):
            continue
        _lu_solve(a, perm, rhs, f)
        if not np.isfinite(f).all():
            continue
        for i in range(3):
            for j in range(3):
                models[kept, i, j] = f[3 * i + j]
        kept += 1
    return models[:kept]


@_jit
def _draw_samples(strong: np.ndarray, count: int, per_sample: int, seed: int) -> np.ndarray:
    """(count, 8) positions among the candidates: ``per_sample`` from those with strong
    parallax and the rest from the others (each group drawn from a repeated permutation, so
    the members of a sample are distinct), or 8 from all when a group is too small."""
    picked, others = np.flatnonzero(strong), np.flatnonzero(~strong)
    if per_sample == 0 or len(picked) < per_sample or len(others) < 8 - per_sample:
        picked, others, per_sample = picked[:0], np.arange(len(strong)), 0
    # numba's own generator (thread-local state), seeded on every call: deterministic per seed
    np.random.seed(seed)  # noqa: NPY002
    samples = np.empty((count, 8), dtype=np.int64)
    column = 0
    for group, k in ((picked, per_sample), (others, 8 - per_sample)):
        if k == 0:
            continue
        order = group[np.random.permutation(len(group))]  # noqa: NPY002
        for i in range(count * k):
            samples[i // k, column + i % k] = order[i % len(order)]
        column += k
    return samples


@_jit
def _scored_rows(strong: np.ndarray, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions among the candidates the hypotheses are scored on, and each one's weight: all
    of them (weight 1) up to ``limit``; else a stratified sample of ``limit``, spread evenly
    over each group, the strong-parallax group (the rarer, and the one that tells the heights
    apart) up to half of them, each position weighted by the share of its group it stands
    for, so the score estimates the full one."""
    c = len(strong)
    if c <= limit:
        return np.arange(c), np.ones(c)
    picked, others = np.flatnonzero(strong), np.flatnonzero(~strong)
    take_o = min(len(others), limit - min(len(picked), limit // 2))
    take_p = min(len(picked), limit - take_o)
    positions = np.empty(take_p + take_o, dtype=np.int64)
    weights = np.empty(take_p + take_o)
    for i in range(take_p):
        positions[i] = picked[i * len(picked) // take_p]
        weights[i] = len(picked) / take_p
    for i in range(take_o):
        positions[take_p + i] = others[i * len(others) // take_o]
        weights[take_p + i] = len(others) / take_o
    return positions, weights


@_jit
def fit_candidates(
    joint: np.ndarray,
    candidates: np.ndarray,
    strong: np.ndarray,
    hypotheses: int,
    parallax_points: int,
    polish: int,
    t2: float,
    seed: int,
    scored: int,
) -> tuple[np.ndarray, bool, np.ndarray, int]:
    """The sampled model of :func:`hmcc.plus.fit_candidates`: the kept model, whether there is
    one, its inlier mask over the candidates and the number of hypotheses scored. The
    hypotheses are scored on at most ``scored`` candidates (:func:`_scored_rows`); the
    ``polish`` best are refitted and counted on all of them."""
    samples = _draw_samples(strong, hypotheses, parallax_points, seed)
    models = minimal_models(joint, candidates[samples])
    k, c = len(models), len(candidates)
    positions, weights = _scored_rows(strong, scored)
    score = np.zeros(k)
    for m in range(k):
        for j in range(len(positions)):
            d = _sampson_sq_row(models[m], joint, candidates[positions[j]])
            score[m] += weights[j] * min(d, 4.0 * t2)
    best_f, best_mask, found = np.zeros((3, 3)), np.zeros(c, dtype=np.bool_), False
    best_in = -1
    for m in np.argsort(score, kind="mergesort")[:polish]:
        d2 = sampson_sq(models[m], joint, candidates)
        f, ok = least_squares(joint, candidates[d2 < 4.0 * t2])
        if not ok:
            continue
        inliers = sampson_sq(f, joint, candidates) < t2
        count = int(np.count_nonzero(inliers))
        if count > best_in:
            best_f, best_mask, best_in, found = f, inliers, count, True
    return best_f, found, best_mask, k


@_jit
def refine(
    joint: np.ndarray, f: np.ndarray, t2: float, schedule: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int, int, int]:
    """Local optimisation on all rows: for each multiplier m of ``schedule``, refit by least
    squares on the rows within m^2 x ``t2``; keep the model with the most rows within ``t2``.
    Returns the model, its (N,) squared distances, the inliers before and after, and the
    refits."""
    rows = np.arange(len(joint))
    best_f, best_d2 = f, sampson_sq(f, joint, rows)
    best_count = first = int(np.count_nonzero(best_d2 < t2))
    steps = 0
    for m in schedule:
        refit, ok = least_squares(joint, rows[best_d2 < m * m * t2])
        steps += 1
        if not ok:
            break
        d2 = sampson_sq(refit, joint, rows)
        count = int(np.count_nonzero(d2 < t2))
        if count >= best_count:
            best_f, best_d2, best_count = refit, d2, count
    return best_f, best_d2, first, best_count, steps


@_jit
def check_counts(
    inliers: np.ndarray,
    d2: np.ndarray,
    gated: np.ndarray,
    rows: np.ndarray,
    across: np.ndarray,
    t2: float,
    band_sigmas: float,
    near: float,
    control_lo: float,
    control_hi: float,
) -> tuple[int, int, int, int, int, int]:
    """The counts of :func:`hmcc.plus.coverage` in one pass over the (N,) matches: the wide
    band (``across`` < ``band_sigmas``; ``across`` (R,) of the matches ``rows``, the others
    have none), its control band (to 2 x ``band_sigmas``), the band's inliers, all inliers,
    the near misses (plausible non-inliers with ``d2`` < ``near``^2 ``t2``) and their control
    band (``control_lo``^2 ``t2`` <= ``d2`` < ``control_hi``^2 ``t2``, plausible)."""
    band = band_control = band_kept = kept = near_count = near_control = 0
    for i in range(len(rows)):
        a = across[i]
        if a < band_sigmas:
            band += 1
            if inliers[rows[i]]:
                band_kept += 1
        elif a < 2.0 * band_sigmas:
            band_control += 1
    near_t2 = near * near * t2
    lo_t2, hi_t2 = control_lo * control_lo * t2, control_hi * control_hi * t2
    for r in range(len(d2)):
        if inliers[r]:
            kept += 1
        elif not gated[r]:
            if d2[r] < near_t2:
                near_count += 1
            elif lo_t2 <= d2[r] < hi_t2:
                near_control += 1
    return band, band_control, band_kept, kept, near_count, near_control


# --------------------------------------------------------------------------- rays


@_jit
def diverging(
    u1: np.ndarray,
    u2: np.ndarray,
    r1: np.ndarray,
    r2: np.ndarray,
    k1: np.ndarray,
    k2: np.ndarray,
    c1: np.ndarray,
    c2: np.ndarray,
    limit_rad: float,
) -> np.ndarray:
    """(N,) mask of the matches whose rays diverge by more than ``limit_rad``: the angle at
    the point in the triangle camera 1, camera 2, point (pi minus the rays' angles to the
    baseline) is below ``-limit_rad``, so they meet behind a camera. ``u1``/``u2`` (N, 2)
    undistorted pixels; per camera its world-to-camera rotation ``r``, ``k`` = (fx, fy, cx,
    cy) and centre ``c``. None flagged when the centres coincide."""
    n = len(u1)
    out = np.zeros(n, dtype=np.bool_)
    b = c2 - c1
    length = math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    if not length > 0.0:
        return out
    b = b / length
    # the baseline in each camera's frame: the rays' angles to it need no world rays
    b1 = r1 @ b
    b2 = r2 @ b
    # a1 + a2 > pi + limit, the rays' angles a1, a2 in [0, pi] to the baseline (at camera 2,
    # to its reverse), without arccos: sin(a1 + a2) < 0 and cos(a1 + a2) > -cos(limit)
    bound = -math.cos(limit_rad)
    for r in range(n):
        x, y = (u1[r, 0] - k1[2]) / k1[0], (u1[r, 1] - k1[3]) / k1[1]
        cos1 = (x * b1[0] + y * b1[1] + b1[2]) / math.sqrt(x * x + y * y + 1.0)
        x, y = (u2[r, 0] - k2[2]) / k2[0], (u2[r, 1] - k2[3]) / k2[1]
        cos2 = -(x * b2[0] + y * b2[1] + b2[2]) / math.sqrt(x * x + y * y + 1.0)
        sin1 = math.sqrt(max(0.0, 1.0 - cos1 * cos1))
        sin2 = math.sqrt(max(0.0, 1.0 - cos2 * cos2))
        out[r] = sin1 * cos2 + cos1 * sin2 < 0.0 and cos1 * cos2 - sin1 * sin2 > bound
    return out


# --------------------------------------------------------------------------- leave one out


@_jit
def _rank2(g: np.ndarray) -> None:
    """``g`` (3, 3) in place to its nearest rank-2 matrix (Frobenius): ``g (I - v v^T)``, v the
    eigenvector of the smallest eigenvalue of ``g^T g``, in closed form without allocating
    (the eigenvalue from the characteristic cubic's trigonometric roots, the vector the
    largest cross product of two rows of ``g^T g - lambda I``)."""
    a = g[0, 0] * g[0, 0] + g[1, 0] * g[1, 0] + g[2, 0] * g[2, 0]
    b = g[0, 1] * g[0, 1] + g[1, 1] * g[1, 1] + g[2, 1] * g[2, 1]
    c = g[0, 2] * g[0, 2] + g[1, 2] * g[1, 2] + g[2, 2] * g[2, 2]
    d = g[0, 0] * g[0, 1] + g[1, 0] * g[1, 1] + g[2, 0] * g[2, 1]
    e = g[0, 1] * g[0, 2] + g[1, 1] * g[1, 2] + g[2, 1] * g[2, 2]
    f = g[0, 0] * g[0, 2] + g[1, 0] * g[1, 2] + g[2, 0] * g[2, 2]
    q = (a + b + c) / 3.0
    p = math.sqrt(
        ((a - q) ** 2 + (b - q) ** 2 + (c - q) ** 2 + 2.0 * (d * d + e * e + f * f)) / 6.0
    )
    if not p > 0.0:
        return
    b00, b11, b22, b01, b12, b02 = (a - q) / p, (b - q) / p, (c - q) / p, d / p, e / p, f / p
    det = (
        b00 * (b11 * b22 - b12 * b12)
        - b01 * (b01 * b22 - b12 * b02)
        + b02 * (b01 * b12 - b11 * b02)
    )
    phi = math.acos(min(1.0, max(-1.0, 0.5 * det))) / 3.0
    lam = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    a, b, c = a - lam, b - lam, c - lam
    # rows (a, d, f), (d, b, e), (f, e, c): the largest of their three cross products
    v0, v1, v2 = d * e - f * b, f * d - a * e, a * b - d * d
    size = v0 * v0 + v1 * v1 + v2 * v2
    w0, w1, w2 = d * c - f * e, f * f - a * c, a * e - d * f
    if w0 * w0 + w1 * w1 + w2 * w2 > size:
        v0, v1, v2, size = w0, w1, w2, w0 * w0 + w1 * w1 + w2 * w2
    w0, w1, w2 = b * c - e * e, e * f - d * c, d * e - b * f
    if w0 * w0 + w1 * w1 + w2 * w2 > size:
        v0, v1, v2, size = w0, w1, w2, w0 * w0 + w1 * w1 + w2 * w2
    if not size > 0.0:
        return
    norm = 1.0 / math.sqrt(size)
    v0, v1, v2 = v0 * norm, v1 * norm, v2 * norm
    for i in range(3):
        gv = g[i, 0] * v0 + g[i, 1] * v1 + g[i, 2] * v2
        g[i, 0] -= gv * v0
        g[i, 1] -= gv * v1
        g[i, 2] -= gv * v2


@_jit
def leave_one_out(joint: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(R,) squared normalised Sampson distance of each of ``rows`` to the least-squares model
    of the other rows (no rank-2 step); inf when fewer than 9 rows, 0 (none stands out) when
    the rows leave the model free in more than one direction.

    The model without row i is one inverse-iteration step, from the model of all rows f, on
    the normal matrix N - a a^T (Sherman-Morrison): with N's eigenpairs (lambda_k, v_k), f =
    v_0, c_k = v_k . a, it is proportional to (1 - h) f + (a . f) sum_k>0 v_k c_k / lambda_k,
    h = sum_k>0 c_k^2 / lambda_k (h is the row's leverage). About 200 flops a row."""
    n = len(rows)
    out = np.full(n, np.inf)
    if n < 9:
        return out
    design = np.empty((n, 9))
    normal = np.zeros((9, 9))
    for k in range(n):
        _design_row(joint, rows[k], design[k])
        for i in range(9):
            for j in range(9):
                normal[i, j] += design[k, i] * design[k, j]
    values, vectors = np.linalg.eigh(normal)
    if not values[1] > 1e-12 * values[8]:
        out[:] = 0.0
        return out
    f = np.empty(9)
    g = np.empty((3, 3))
    for k in range(n):
        a = design[k]
        residual = 0.0
        for i in range(9):
            residual += vectors[i, 0] * a[i]
        h = 0.0
        for i in range(9):
            f[i] = 0.0
        for m in range(1, 9):
            c = 0.0
            for i in range(9):
                c += vectors[i, m] * a[i]
            h += c * c / values[m]
            w = residual * c / values[m]
            for i in range(9):
                f[i] += w * vectors[i, m]
        for i in range(9):
            g[i // 3, i % 3] = f[i] + (1.0 - h) * vectors[i, 0]
        _rank2(g)  # as least_squares
        out[k] = _sampson_sq_row(g, joint, rows[k])
    return out


@_jit
def pose_misfit_cos(f: np.ndarray, k1: np.ndarray, k2: np.ndarray, rough: np.ndarray) -> float:
    """Cosine of the angle between the rough relative rotation ``rough`` (camera 1 to camera
    2) and the nearer of the two rotations of the essential matrix ``k2^T f k1`` of the pixel
    model ``f``."""
    u, _, vt = np.linalg.svd(k2.T @ f @ k1)
    if np.linalg.det(u) < 0.0:
        u = -u
    if np.linalg.det(vt) < 0.0:
        vt = -vt
    swap = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    best = -1.0
    for w in (swap, swap.T.copy()):
        r = u @ w @ vt
        trace = 0.0
        for i in range(3):
            for j in range(3):
                trace += rough[i, j] * r[i, j]  # trace(rough^T r)
        best = max(best, (trace - 1.0) / 2.0)
    return min(1.0, max(-1.0, best))


@_jit
def ray_gate(
    u1: np.ndarray,
    u2: np.ndarray,
    r1: np.ndarray,
    r2: np.ndarray,
    k1: np.ndarray,
    k2: np.ndarray,
    c1: np.ndarray,
    c2: np.ndarray,
    limit_rad: float,
    inliers: np.ndarray,
    f: np.ndarray,
    max_share: float,
    min_cos: float,
) -> tuple[np.ndarray, int, float, float]:
    """The diverging-rays gate of :func:`hmcc.plus.verify_plus` in one call: the
    :func:`diverging` mask when the poses fit the pixels (at most ``max_share`` of the
    ``inliers`` diverge and :func:`pose_misfit_cos` of the pixel model ``f`` is at least
    ``min_cos``), else none; with a verdict (-1: nothing diverges, 1: applied, 0: the poses do
    not fit), the share and the cosine (1 when nothing diverges). ``k`` = (fx, fy, cx, cy)."""
    mask = diverging(u1, u2, r1, r2, k1, k2, c1, c2, limit_rad)
    if not mask.any():
        return mask, -1, 0.0, 1.0
    kept = 0
    both = 0
    for i in range(len(mask)):
        if inliers[i]:
            kept += 1
            if mask[i]:
                both += 1
    share = both / max(kept, 1)
    m1 = np.array([[k1[0], 0.0, k1[2]], [0.0, k1[1], k1[3]], [0.0, 0.0, 1.0]])
    m2 = np.array([[k2[0], 0.0, k2[2]], [0.0, k2[1], k2[3]], [0.0, 0.0, 1.0]])
    cos = pose_misfit_cos(f, m1, m2, r2 @ r1.T)
    if share <= max_share and cos >= min_cos:
        return mask, 1, share, cos
    return np.zeros(len(mask), dtype=np.bool_), 0, share, cos


# --------------------------------------------------------------------------- posed essential


@_jit
def _posed(
    rotation: np.ndarray,
    t: np.ndarray,
    b1: np.ndarray,
    b2: np.ndarray,
    step: np.ndarray,
    rot_out: np.ndarray,
    t_out: np.ndarray,
    e_out: np.ndarray,
) -> None:
    """The pose moved by ``step`` (a rotation vector applied in the second camera's frame, then
    the baseline's direction moved along its tangents ``b1``, ``b2``) into ``rot_out`` and
    ``t_out``, and its essential matrix ``[t]x R`` into ``e_out``; no allocation (these run
    six times an iteration)."""
    w0, w1, w2 = step[0], step[1], step[2]
    theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    if theta < 1e-15:
        for i in range(3):
            for j in range(3):
                rot_out[i, j] = rotation[i, j]
    else:
        kx, ky, kz = w0 / theta, w1 / theta, w2 / theta
        c, s = math.cos(theta), math.sin(theta)
        v = 1.0 - c
        # Rodrigues: cos I + sin [k]x + (1 - cos) k k^T
        r00, r01, r02 = c + kx * kx * v, kx * ky * v - kz * s, kx * kz * v + ky * s
        r10, r11, r12 = ky * kx * v + kz * s, c + ky * ky * v, ky * kz * v - kx * s
        r20, r21, r22 = kz * kx * v - ky * s, kz * ky * v + kx * s, c + kz * kz * v
        for j in range(3):
            a0, a1, a2 = rotation[0, j], rotation[1, j], rotation[2, j]
            rot_out[0, j] = r00 * a0 + r01 * a1 + r02 * a2
            rot_out[1, j] = r10 * a0 + r11 * a1 + r12 * a2
            rot_out[2, j] = r20 * a0 + r21 * a1 + r22 * a2
    u0 = t[0] + step[3] * b1[0] + step[4] * b2[0]
    u1 = t[1] + step[3] * b1[1] + step[4] * b2[1]
    u2 = t[2] + step[3] * b1[2] + step[4] * b2[2]
    norm = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    t_out[0], t_out[1], t_out[2] = u0 / norm, u1 / norm, u2 / norm
    for j in range(3):  # [t]x R
        a0, a1, a2 = rot_out[0, j], rot_out[1, j], rot_out[2, j]
        e_out[0, j] = -t_out[2] * a1 + t_out[1] * a2
        e_out[1, j] = t_out[2] * a0 - t_out[0] * a2
        e_out[2, j] = -t_out[1] * a0 + t_out[0] * a1


@_jit
def _essential_residuals(e: np.ndarray, n1: np.ndarray, n2: np.ndarray, out: np.ndarray) -> None:
    """Signed Sampson distances of the normalised point pairs to the essential matrix."""
    for i in range(len(n1)):
        x1, y1, x2, y2 = n1[i, 0], n1[i, 1], n2[i, 0], n2[i, 1]
        a0 = e[0, 0] * x1 + e[0, 1] * y1 + e[0, 2]
        a1 = e[1, 0] * x1 + e[1, 1] * y1 + e[1, 2]
        a2 = e[2, 0] * x1 + e[2, 1] * y1 + e[2, 2]
        b0 = e[0, 0] * x2 + e[1, 0] * y2 + e[2, 0]
        b1 = e[0, 1] * x2 + e[1, 1] * y2 + e[2, 1]
        out[i] = (x2 * a0 + y2 * a1 + a2) / math.sqrt(
            max(a0 * a0 + a1 * a1 + b0 * b0 + b1 * b1, 1e-300)
        )


@_jit
def _cauchy_cost(residuals: np.ndarray, scale: float) -> float:
    cost = 0.0
    for r in residuals:
        z = r / scale
        cost += math.log1p(z * z)
    return cost


@_jit
def posed_model(
    p1: np.ndarray,
    p2: np.ndarray,
    rows: np.ndarray,
    k1: np.ndarray,
    k2: np.ndarray,
    rotation: np.ndarray,
    baseline1: np.ndarray,
    baseline2: np.ndarray,
    threshold_px: float,
    iterations: int,
    min_cos: float,
) -> tuple[np.ndarray, bool]:
    """:func:`posed_essential` of the pixel pairs ``rows`` of ``p1``, ``p2`` (undistorted
    pixels of the cameras ``k1``, ``k2``) at ``threshold_px``, from the rough pose
    (``rotation``, camera 1's centre ``baseline2`` in camera 2's frame), in one call; False
    also when its epipoles (the baseline's direction in each camera) lie more than
    acos(``min_cos``) off the rough ``baseline1``, ``baseline2``, either way along them."""
    n = len(rows)
    n1, n2 = np.empty((n, 2)), np.empty((n, 2))
    for i in range(n):
        r = rows[i]
        n1[i, 0] = (p1[r, 0] - k1[0, 2]) / k1[0, 0]
        n1[i, 1] = (p1[r, 1] - k1[1, 2]) / k1[1, 1]
        n2[i, 0] = (p2[r, 0] - k2[0, 2]) / k2[0, 0]
        n2[i, 1] = (p2[r, 1] - k2[1, 2]) / k2[1, 1]
    focal = 0.25 * (k1[0, 0] + k1[1, 1] + k2[0, 0] + k2[1, 1])
    e, rot, t, ok = posed_essential(n1, n2, rotation, baseline2, threshold_px / focal, iterations)
    if not ok:
        return e, False
    # epipoles of [t]x R: t in image 2, R^T t in image 1 (both unit)
    e1 = rot.T @ t
    c1 = abs((e1 * baseline1).sum()) / math.sqrt((baseline1 * baseline1).sum())
    c2 = abs((t * baseline2).sum()) / math.sqrt((baseline2 * baseline2).sum())
    return e, c1 >= min_cos and c2 >= min_cos


@_jit
def posed_essential(
    n1: np.ndarray,
    n2: np.ndarray,
    rotation: np.ndarray,
    baseline: np.ndarray,
    scale: float,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """The essential matrix ``[t]x R`` nearest the rough relative pose (``rotation``: camera 1
    to camera 2; ``baseline``: camera 1's centre in camera 2's frame) that fits the (N, 2)
    normalised point pairs, and the pose it ends on (R, unit t): Levenberg-Marquardt on the
    rotation (3 parameters) and the baseline's direction (2), minimising the Cauchy cost of
    their Sampson distances at ``scale`` (normalised units), from the rough pose; it stops when
    a step lowers the cost by less than 1e-4 of it. False when the baseline is 0 or there are
    fewer than 5 pairs."""
    norm = math.sqrt((baseline * baseline).sum())
    if not norm > 0.0 or len(n1) < 5:
        return np.eye(3), np.eye(3), np.zeros(3), False
    n = len(n1)
    rot, t, e = np.ascontiguousarray(rotation).copy(), baseline / norm, np.empty((3, 3))
    rot_k, t_k = np.empty((3, 3)), np.empty(3)
    res, moved, jac = np.empty(n), np.empty(n), np.empty((n, 5))
    step, delta = np.zeros(5), np.empty(5)
    b1, b2 = np.zeros(3), np.zeros(3)
    perm = np.empty(5, dtype=np.int64)
    _posed(rot, t, b1, b2, step, rot_k, t_k, e)  # step 0: the rough pose's E
    _essential_residuals(e, n1, n2, res)
    cost = _cauchy_cost(res, scale)
    damping, h = 1e-3, 1e-7
    for _ in range(iterations):
        # tangents of the baseline's direction
        b1[0], b1[1], b1[2] = t[1], -t[0], 0.0  # t x (0, 0, 1)
        if b1[0] * b1[0] + b1[1] * b1[1] < 1e-12:
            b1[0], b1[1], b1[2] = 0.0, t[2], -t[1]  # t x (1, 0, 0)
        b1 /= math.sqrt((b1 * b1).sum())
        b2[0] = t[1] * b1[2] - t[2] * b1[1]
        b2[1] = t[2] * b1[0] - t[0] * b1[2]
        b2[2] = t[0] * b1[1] - t[1] * b1[0]
        for k in range(5):
            step[:] = 0.0
            step[k] = h
            _posed(rot, t, b1, b2, step, rot_k, t_k, e)
            _essential_residuals(e, n1, n2, moved)
            for i in range(n):
                jac[i, k] = (moved[i] - res[i]) / h
        normal = np.zeros((5, 5))
        gradient = np.zeros(5)
        for i in range(n):
            z = res[i] / scale
            w = 1.0 / (1.0 + z * z)
            for a in range(5):
                gradient[a] += w * jac[i, a] * res[i]
                for b in range(a, 5):
                    normal[a, b] += w * jac[i, a] * jac[i, b]
        for a in range(5):
            for b in range(a):
                normal[a, b] = normal[b, a]
        accepted = False
        for _ in range(10):
            lhs = normal.copy()
            for a in range(5):
                lhs[a, a] += damping * max(normal[a, a], 1e-300)
            if not _lu(lhs, perm):
                damping *= 10.0
                continue
            _lu_solve(lhs, perm, -gradient, delta)
            _posed(rot, t, b1, b2, delta, rot_k, t_k, e)
            _essential_residuals(e, n1, n2, moved)
            new_cost = _cauchy_cost(moved, scale)
            if new_cost < cost:
                accepted = cost - new_cost > 1e-4 * cost and (delta * delta).sum() > 1e-16
                rot[:, :] = rot_k
                t[:] = t_k
                cost = new_cost
                res[:] = moved
                damping = max(damping * 0.1, 1e-12)
                break
            damping *= 10.0
        if not accepted:  # the last step lowered the cost by less than 1e-4 (or moved 1e-8 rad)
            break
    step[:] = 0.0
    _posed(rot, t, b1, b2, step, rot_k, t_k, e)
    return e, rot, t, True
