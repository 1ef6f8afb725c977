"""Flight-level yaw correction: one rotation about the vertical per image, from the motion
fields of all its pairs, applied to the rough poses before any pair is verified.

Where an image's rough yaw is off by ``c`` (an image turned after capture, an attitude
estimated from the track), its rays meet the plane Z0 rotated by ``c`` about the vertical
through its centre. So the motion field of a pair (:func:`hmcc.lean.consistent_set`: the
robust affine field on the plane) is, up to relief, ``end = R(c_j - c_i) start + b``:

* its **rotation** is the pair's *relative* yaw error ``c_j - c_i`` (exact, whatever the
  baseline);
* its **translation** at the consistent motions' centroid ``m``, ``b(m) = N_j + R(c_j)(N_i -
  N_j) + R(c_j - c_i)(m - N_i)`` (``N`` the centres on the plane), gives an *absolute* yaw
  error ``c_j``, as good as the baseline ``|N_i - N_j|`` is long against the error of the
  rough positions (``position_sigma_m``).

:func:`solve_yaws` finds the corrections ``c`` that best agree with both kinds of
observation: a robust least squares on the circle (angles wrapped; Cauchy weights of scale
``scale_deg``), started on a maximum spanning tree of the pair graph and refined by
iteratively reweighted circular means, image by image. Applying ``c_k`` turns image ``k``'s
``R_world_to_cam`` to ``R_world_to_cam @ Rz(c_k)`` (:func:`corrected_pose`).

Arrays in, arrays out; nothing here reads files.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .lean import LeanOptions, consistent_set
from .pair import PairData
from .pose import Pose
from .projection import GroundOptions, project_pair


@dataclass(frozen=True)
class AttitudeOptions:
    """The few constants of the flight-level yaw correction (tuned on Brighton's tune half)."""

    #: Cauchy scale of the wrapped residuals (deg).
    scale_deg: float = 10.0
    #: Error of the rough positions on the plane (m): an absolute observation from a baseline
    #: ``B`` weighs ``(B / position_sigma_m)^2 * relative_sigma^2`` against a relative one.
    position_sigma_m: float = 5.0
    #: Spread of a relative observation (deg).
    relative_sigma_deg: float = 2.0
    #: A pair counts when at least this many matches lie on its motion field.
    min_consensus: int = 30
    #: Reweighting sweeps.
    iterations: int = 20


@dataclass(frozen=True)
class PairYaw:
    """What one pair's motion field says: ``relative`` = c_j - c_i and ``absolute`` = c_j
    (rad), the baseline on the plane (m) and the consensus behind them."""

    relative: float
    absolute: float
    baseline_m: float
    consensus: int


def wrap(angle: np.ndarray | float) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(angle, dtype=float) + math.pi) % (2.0 * math.pi) - math.pi


def rz(angle: float) -> np.ndarray:
    """Rotation about the world vertical."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def corrected_pose(pose: Pose, correction: float) -> Pose:
    """``pose`` turned about the vertical through its centre by ``correction`` (rad)."""
    return dataclasses.replace(pose, R_world_to_cam=pose.R_world_to_cam @ rz(correction))


def pair_yaw(
    pair: PairData,
    ground: GroundOptions | None = None,
    lean: LeanOptions | None = None,
) -> PairYaw | None:
    """The pair's yaw observations from its motion field, or None (no projection, or fewer
    than 8 matches on the field)."""
    px1, px2 = pair.matched_pixels()
    if len(px1) < 8:
        return None
    try:
        motions, _, stats = project_pair(pair, px1, px2, ground or GroundOptions())
    except InputError:
        return None
    if len(motions.start) < 8:
        return None
    on, consensus, _ = consistent_set(motions.start, motions.end, lean or LeanOptions())
    if np.count_nonzero(on) < 8:
        return None
    start, end = motions.start[on], motions.end[on]
    mean = start.mean(axis=0)
    design = np.column_stack([start - mean, np.ones(len(start))])
    coef, *_ = np.linalg.lstsq(design, end, rcond=None)
    m, b = coef[:2].T, coef[2]
    relative = math.atan2(m[1, 0] - m[0, 1], m[0, 0] + m[1, 1])
    n1, n2 = pair.pose1.center[:2], pair.pose2.center[:2]
    v = b - n2 - rz(relative)[:2, :2] @ (mean - n1)
    base = n1 - n2
    absolute = math.atan2(v[1], v[0]) - math.atan2(base[1], base[0])
    return PairYaw(float(wrap(relative)), float(wrap(absolute)), float(np.hypot(*base)), consensus)


def solve_yaws(
    n_images: int,
    first: np.ndarray,
    second: np.ndarray,
    yaws: Sequence[PairYaw],
    options: AttitudeOptions | None = None,
) -> np.ndarray:
    """(n_images,) corrections (rad, wrapped) from the pairs ``(first[k], second[k])`` and
    their observations ``yaws[k]``; an image in no counted pair gets 0."""
    opt = options or AttitudeOptions()
    sigma_rel = math.radians(opt.relative_sigma_deg)
    scale = math.radians(opt.scale_deg)
    # (i < j, relative c_j - c_i, weight) and (image, absolute c_image, weight)
    edges: dict[tuple[int, int], tuple[float, float]] = {}
    absolutes: list[tuple[int, float, float]] = []
    for a, b, y in zip(first.tolist(), second.tolist(), yaws, strict=True):
        if a == b or y.consensus < opt.min_consensus:
            continue
        w = 1.0 / sigma_rel**2
        i, j, rel = (a, b, y.relative) if a < b else (b, a, -y.relative)
        edges[(i, j)] = (rel, w)
        w_abs = (y.baseline_m / opt.position_sigma_m) ** 2
        absolutes.append((b, y.absolute, w_abs))
        absolutes.append((a, float(wrap(y.absolute - y.relative)), w_abs))
    c = np.zeros(n_images)
    if not edges:
        return c
    # start: a maximum spanning tree (weights, then indices: independent of the pairs' order)
    order = sorted(edges, key=lambda e: (-edges[e][1], e))
    degree = np.zeros(n_images)
    for (i, j), (_, w) in edges.items():
        degree[i] += w
        degree[j] += w
    reached = np.zeros(n_images, dtype=bool)
    components: list[list[int]] = []
    for root in sorted(range(n_images), key=lambda k: (-degree[k], k)):
        if reached[root] or degree[root] == 0.0:
            continue
        reached[root], members, grew = True, [root], True
        while grew:
            grew = False
            for i, j in order:
                if reached[i] != reached[j]:
                    rel = edges[(i, j)][0]
                    if reached[i]:
                        c[j], new = c[i] + rel, j
                    else:
                        c[i], new = c[j] - rel, i
                    reached[new], grew = True, True
                    members.append(new)
                    break
        components.append(members)
    # each component's gauge: the weighted circular median of its absolute residuals
    for members in components:
        inside = set(members)
        res = [(wrap(a - c[k]), w) for k, a, w in absolutes if k in inside]
        if res and sum(w for _, w in res) > 0.0:
            c[members] += _circular_median(
                np.array([r for r, _ in res]), np.array([w for _, w in res])
            )
    c = wrap(c)
    # iteratively reweighted circular means, image by image
    neighbours: list[list[tuple[int, float, float]]] = [[] for _ in range(n_images)]
    for (i, j), (rel, w) in edges.items():
        neighbours[j].append((i, rel, w))  # c_j ~ c_i + rel
        neighbours[i].append((j, -rel, w))  # c_i ~ c_j - rel
    own: list[list[tuple[float, float]]] = [[] for _ in range(n_images)]
    for k, a, w in absolutes:
        own[k].append((a, w))
    for _ in range(opt.iterations):
        for k in range(n_images):
            if not neighbours[k]:
                continue
            target = np.array([c[o] + rel for o, rel, _ in neighbours[k]] + [a for a, _ in own[k]])
            weight = np.array([w for _, _, w in neighbours[k]] + [w for _, w in own[k]])
            weight = weight / (1.0 + (wrap(target - c[k]) / scale) ** 2)
            c[k] = math.atan2(float(weight @ np.sin(target)), float(weight @ np.cos(target)))
    return wrap(c)


def _circular_median(angles: np.ndarray, weights: np.ndarray) -> float:
    """The angle among ``angles`` of least weighted sum of wrapped absolute distances."""
    cost = [float(weights @ np.abs(wrap(angles - a))) for a in angles]
    return float(angles[int(np.argmin(cost))])


def flight_yaw_corrections(
    n_images: int,
    first: np.ndarray,
    second: np.ndarray,
    pairs: Sequence[PairData],
    options: AttitudeOptions | None = None,
    ground: GroundOptions | None = None,
) -> np.ndarray:
    """:func:`solve_yaws` on every pair's :func:`pair_yaw` (the pairs with none left out)."""
    kept_a, kept_b, yaws = [], [], []
    for a, b, pair in zip(first.tolist(), second.tolist(), pairs, strict=True):
        y = pair_yaw(pair, ground)
        if y is not None:
            kept_a.append(a)
            kept_b.append(b)
            yaws.append(y)
    return solve_yaws(
        n_images, np.array(kept_a, dtype=int), np.array(kept_b, dtype=int), yaws, options
    )
