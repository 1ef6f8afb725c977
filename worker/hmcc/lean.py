"""HMCC-lean (method ``hmcc-lean``): a proposal from the motions on the plane, a few candidate
models, one robust score over all matches, and MAGSAC++ only where no candidate is acceptable.

Six parts around one score (``docs/design/default-method.md``):

1. **proposal** - the paper's motions on the plane Z0 (:func:`hmcc.projection.project_pair`),
   their 2-D mode and the robust affine motion field around it
   (:func:`hmcc.plus_kernels.motion_field`); the *consistent set* is the matches on that field.
   An affine field, not a radius around the mode: it absorbs the linear trends a constant
   motion cannot (an oblique view's scale change, a yaw error, an image turned after capture).
2. **early exit** - no consensus (fewer consistent matches than ``min_consensus`` beyond what
   chance puts on the field): the fallback, nothing else run; and where the footprints do not
   overlap either, no model at all.
3. **candidates** - F sampled on the consistent set (mostly inliers: a few 8-point samples,
   least-squares polish; :func:`hmcc.plus_kernels.fit_candidates`) and E refined from the rough
   poses on it (:func:`hmcc.plus_kernels.posed_model`), as F. The posed E is refused when its
   epipoles leave the rough baseline or it explains less than ``pose_support`` of the
   consensus. Where it is refused, the **plane's** candidates (:func:`plane_candidates`): the
   consistent set's homography decomposed with both K into relative poses, each one's E
   refined as the posed E is; no rough attitude but the vertical is needed.
4. **selection** - the candidate of lowest truncated Sampson cost (MSAC) over *all* matches.
5. **classification** - every match by its Sampson distance at the threshold, one local
   optimisation (least-squares refits on all matches, :func:`hmcc.plus_kernels.refine`).
6. **acceptance** - at least ``min_inliers`` inliers, of which at least ``min_support`` x the
   consensus are consistent matches; else the **fallback** (``fallback``, MAGSAC++) on all
   matches and the same refit, or no model where the footprints do not overlap either.

The threshold is the final estimator's, ``ransac.threshold_px``, as for every estimator.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from . import plus_kernels as kernels
from .errors import InputError
from .method_names import model_refusal
from .pair import PairData, require_matches
from .plus import Calibration, Correspondences
from .projection import project_pair, project_to_plane
from .ransac import MIN_MATCHES, estimate_model, iterations_bound
from .stage_options import LeanOptions
from .stages import MethodResult, Stages

if TYPE_CHECKING:
    from .options import VerifyOptions

__all__ = [
    "LeanOptions",
    "footprints_overlap",
    "msac_cost",
    "plane_candidates",
    "plane_poses",
    "verify_lean",
]


_FIELD_CHI2 = 9.21
#: The E candidate is fitted on at most this many consistent matches, spread over them.
_POSED_POINTS = 200
_POSED_ITERATIONS = 20
#: Its epipoles must lie within this of the rough baseline (else the poses do not fit).
_EPIPOLES_COS = math.cos(math.radians(30.0))
#: The F candidate's hypotheses are scored on at most this many consistent matches (and the
#: plane's homography fitted on them).
_SCORED = 256
#: The plane's homography: RANSAC at this multiple of the threshold (the ground's relief
#: parts from a plane by more than the epipolar threshold), this many iterations at most.
_PLANE_PX = 4.0
_PLANE_ITERATIONS = 200
#: ... and its plane must be level within this (by the rough vertical).
_PLANE_LEVEL_COS = math.cos(math.radians(30.0))


# --------------------------------------------------------------------------- the parts


def consistent_set(
    start: np.ndarray, end: np.ndarray, options: LeanOptions
) -> tuple[np.ndarray, int, dict[str, Any]]:
    """Proposal: (N,) mask of the motions on the robust affine field around their 2-D mode,
    the consensus (that count minus what chance puts on the field) and statistics."""
    n, vectors = len(start), end - start
    cx, cy, cell, votes = kernels.motion_mode(vectors, options.grid_bins)
    _, m2, cov, _ = kernels.motion_field(start, vectors, cx, cy, 1.5 * cell, n)
    on = m2 < _FIELD_CHI2
    count = int(np.count_nonzero(on))
    # chance: a random match's residual to any field spreads at least as far as its end
    # point does (it is the end point less a function of the independent start point), so it
    # falls in the field's ellipse about as often as in that share of the end points' box
    lo, hi = np.percentile(end, (2.0, 98.0), axis=0)
    ellipse = math.pi * _FIELD_CHI2 * math.sqrt(max(float(np.linalg.det(cov)), 0.0))
    chance = n * min(1.0, ellipse / max(float(np.prod(hi - lo)), 1e-300))
    consensus = int(count - chance)
    stats = {"peak_votes": votes, "on_field": count, "chance": round(chance, 1)}
    return on, consensus, stats


def footprints_overlap(pair: PairData, z0: float, margin: float) -> bool:
    """Do the two images' footprints on the plane Z = ``z0`` (their corners projected with the
    rough poses, grown by ``margin`` of their size about their centre) overlap? True where a
    corner's ray misses the plane (an oblique view's horizon: no footprint to compare)."""
    polygons: list[np.ndarray] = []
    for camera, pose in ((pair.camera1, pair.pose1), (pair.camera2, pair.pose2)):
        w, h = camera.width - 1.0, camera.height - 1.0
        corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        points, ok = project_to_plane(camera, pose, corners, z0)
        if not ok.all():
            return True
        centre = points.mean(axis=0)
        polygons.append((centre + (1.0 + margin) * (points - centre)).astype(np.float32))
    area, _ = cv2.intersectConvexConvex(polygons[0], polygons[1])
    return bool(area > 0.0)


def candidates(
    corr: Correspondences,
    rows: np.ndarray,
    calibration: Calibration,
    t_px: float,
    options: LeanOptions,
    seed: int,
) -> dict[str, np.ndarray]:
    """The candidate models (normalised F) from the consistent ``rows``: ``fundamental``
    (8-point samples, least-squares polish) and ``posed`` (E refined from the rough poses, as
    F), each where it could be fitted."""
    out: dict[str, np.ndarray] = {}
    t2 = (t_px * corr.scale) ** 2
    none = np.zeros(len(rows), dtype=bool)
    f, found, _, _ = kernels.fit_candidates(
        corr.joint, rows, none, options.hypotheses, 0, min(3, options.hypotheses), t2, seed, _SCORED
    )
    if found:
        out["fundamental"] = f
    e = posed_e(corr, rows, calibration, t_px)
    if e is not None:
        out["posed"] = e
    return out


def plane_candidates(
    corr: Correspondences, rows: np.ndarray, calibration: Calibration, t_px: float
) -> dict[str, np.ndarray]:
    """``plane 0``, ``plane 1``...: E refined on the consistent ``rows`` from each relative pose
    of :func:`plane_poses` (normalised F), where its epipoles stay near that pose's."""
    out: dict[str, np.ndarray] = {}
    for k, pose in enumerate(plane_poses(corr, rows, calibration, t_px)):
        e = posed_e(corr, rows, calibration, t_px, pose)
        if e is not None:
            out[f"plane {k}"] = e
    return out


def plane_poses(
    corr: Correspondences, rows: np.ndarray, calibration: Calibration, t_px: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Relative poses without the rough ones: the homography of the consistent ``rows`` (a
    patch of ground, nearly planar: RANSAC at :data:`_PLANE_PX` x the threshold), decomposed
    with both K into (R, t) (camera 1's frame to camera 2's, ``t`` unit: camera 1's centre in
    camera 2's frame); only the solutions that put the plane's points in front of both
    cameras and whose plane is level within acos(:data:`_PLANE_LEVEL_COS`) by image 1's rough
    vertical (the ground: a rough yaw does not move the vertical; the two decompositions of a
    plane differ there). Each is one (3, 3) rotation and one (3,) direction."""
    if len(rows) < 8:
        return []
    if len(rows) > _SCORED:
        rows = rows[np.linspace(0, len(rows) - 1, _SCORED).astype(np.int64)]
    inv1, inv2 = calibration.inverses
    ones = np.ones((len(rows), 1))
    n1 = (np.hstack([corr.p1[rows], ones]) @ inv1.T)[:, :2]
    n2 = (np.hstack([corr.p2[rows], ones]) @ inv2.T)[:, :2]
    focal = 0.25 * float(np.trace(calibration.k1[:2, :2]) + np.trace(calibration.k2[:2, :2]))
    h, mask = cv2.findHomography(
        n1, n2, cv2.RANSAC, _PLANE_PX * t_px / focal, maxIters=_PLANE_ITERATIONS
    )
    if h is None or not np.isfinite(h).all():
        return []
    _, rotations, translations, normals = cv2.decomposeHomographyMat(h, np.eye(3))
    on = mask.ravel() > 0
    before = n1[on].reshape(-1, 1, 2).astype(np.float32)
    after = n2[on].reshape(-1, 1, 2).astype(np.float32)
    visible = cv2.filterHomographyDecompByVisibleRefpoints(rotations, normals, before, after)
    up = calibration.up1 / max(float(np.linalg.norm(calibration.up1)), 1e-300)
    out = []
    for k in [] if visible is None else [int(i) for i in visible.ravel()]:
        t = np.asarray(translations[k], dtype=np.float64).ravel()
        norm = float(np.linalg.norm(t))
        normal = np.asarray(normals[k], dtype=np.float64).ravel()
        level = abs(float(normal @ up)) >= _PLANE_LEVEL_COS * float(np.linalg.norm(normal))
        if norm > 1e-9 and level:
            out.append((np.ascontiguousarray(rotations[k], dtype=np.float64), t / norm))
    return out


def posed_e(
    corr: Correspondences,
    rows: np.ndarray,
    calibration: Calibration,
    t_px: float,
    pose: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray | None:
    """E refined on the consistent ``rows`` (normalised F) from the rough poses, or from
    ``pose`` (R, t: camera 1's centre in camera 2's frame) where given; None where its
    epipoles leave that pose's baseline."""
    spread = rows
    if len(rows) > _POSED_POINTS:
        spread = rows[np.linspace(0, len(rows) - 1, _POSED_POINTS).astype(np.int64)]
    if pose is None:
        rotation, base1, base2 = calibration.rotation, calibration.baseline1, calibration.baseline2
    else:
        rotation, base2 = pose
        base1 = np.ascontiguousarray(-rotation.T @ base2)
    e, ok = kernels.posed_model(
        corr.p1,
        corr.p2,
        spread,
        calibration.k1,
        calibration.k2,
        rotation,
        base1,
        base2,
        t_px,
        _POSED_ITERATIONS,
        _EPIPOLES_COS,
    )
    if not (ok and np.isfinite(e).all()):
        return None
    inv1, inv2 = calibration.inverses
    return corr.from_pixels(inv2.T @ e @ inv1)


def msac_cost(d2: np.ndarray, t2: float) -> float:
    """The truncated (MSAC) cost of squared distances ``d2`` at the squared threshold."""
    return float(np.minimum(d2, t2).sum())


# --------------------------------------------------------------------------- the method


def verify_lean(pair: PairData, options: VerifyOptions, stages: Stages) -> MethodResult:
    """Method ``hmcc-lean``: projection, proposal, candidates, selection, classification;
    ``fallback`` where the proposal has no consensus or no candidate enough inliers."""
    refused = model_refusal("hmcc-lean", options.ransac.model)
    if refused is not None:
        raise InputError("params.ransac.model", refused)
    require_matches(pair, MIN_MATCHES["fundamental"], "fundamental")
    lean, t_px = options.lean, options.ransac.threshold_px
    px1, px2 = pair.matched_pixels()
    u1 = pair.camera1.undistort_pixels(px1)
    u2 = pair.camera2.undistort_pixels(px2)
    n = len(px1)
    statistics: dict[str, Any] = {"selected": None}
    reason: str | None = None
    inliers = np.zeros(n, dtype=bool)
    f: np.ndarray | None = None
    corr = Correspondences(u1, u2)
    try:
        with stages.stage("projection", n) as st:
            motions, valid, stats = project_pair(pair, px1, px2, options.ground)
            idx = np.flatnonzero(st.done(valid, stats))
        statistics["z0_m"] = z0 = stats["z0_m"]
    except InputError as e:
        if pair.plane_z is not None or pair.ground_z is not None:
            raise  # the caller's plane is wrong: say so rather than hide it behind a fallback
        idx, reason = np.zeros(0, dtype=np.int64), f"projection: {e.reason}"
    stages.survivors["projection"] = idx

    if reason is None:
        with stages.stage("proposal", len(idx)) as st:
            on = np.zeros(len(idx), dtype=bool)
            consensus, stats = 0, {}
            if len(idx) >= 8:
                on, consensus, stats = consistent_set(motions.start, motions.end, lean)
            stats["consensus"] = statistics["consensus"] = consensus
            agreed = consensus >= lean.min_consensus
            if not agreed:
                stats["overlap"] = footprints_overlap(pair, z0, lean.footprint_margin)
            st.done(on if agreed else np.zeros(len(idx), dtype=bool), stats)
        rows = idx[on]
        stages.survivors["proposal"] = rows
        if not agreed:
            if not stats["overlap"]:
                statistics["fallback"] = {"used": False, "reason": "no overlap, no consensus"}
                statistics["degenerate"] = "no model: the footprints do not overlap"
                return MethodResult(
                    np.zeros(0, dtype=np.int64), "fundamental", None, statistics, options
                )
            reason = f"consensus {consensus} below min_consensus"

    compared = False  # the fallback's model was a candidate
    support = 0  # consistent matches within the threshold of the selected model
    if reason is None:
        t2 = (t_px * corr.scale) ** 2
        with stages.stage("candidates", len(rows)) as st:
            calibration = Calibration(pair)
            models = candidates(corr, rows, calibration, t_px, lean, options.seed)
            st.done(np.ones(len(rows), dtype=bool), {"models": sorted(models)})
        models = _supported(models, corr, rows, t2, lean.pose_support * consensus, statistics)
        if lean.yaw_from_field and "posed" not in models:
            with stages.stage("posed again", len(rows)) as st:
                turned, yaw = _turned_to_field(pair, motions.start[on], motions.end[on])
                essential = posed_e(corr, rows, Calibration(turned), t_px)
                again = {} if essential is None else {"posed": essential}
                models |= _supported(again, corr, rows, t2, lean.pose_support * consensus, {})
                st.done(np.ones(len(rows), dtype=bool), {"yaw_deg": round(yaw, 2)})
        if lean.plane_candidates and "posed" not in models:
            with stages.stage("plane", len(rows)) as st:
                planes = plane_candidates(corr, rows, calibration, t_px)
                models |= planes
                st.done(np.ones(len(rows), dtype=bool), {"models": sorted(planes)})
        if lean.compare_fallback and "posed" not in models:
            compared, g = True, _fallback_model(corr, options, stages)
            if g is not None:
                models["fallback"] = g
        with stages.stage("selection", n) as st:
            d2s = {name: corr.sampson_sq(g) for name, g in models.items()}
            costs = {name: msac_cost(d2, t2) for name, d2 in d2s.items()}
            stats = {"costs": {k: round(v / max(t2, 1e-300), 2) for k, v in costs.items()}}
            if costs:
                name = min(costs, key=lambda k: (costs[k], k))
                statistics["selected"] = stats["selected"] = name
                f, d2, before, after, _ = kernels.refine(
                    corr.joint, models[name], t2, np.asarray(lean.lo_schedule, dtype=float)
                )
                if after <= before and name != "fundamental":
                    # an E (rank 2, equal singular values with K) unless a refit explains more:
                    # on a plane the least-squares F fits as well with any epipole
                    f, d2 = models[name], d2s[name]
                inliers = d2 < t2
                support = int(np.count_nonzero(inliers[rows]))
                statistics["support"] = support
                stats |= {"inliers_before": before, "inliers_after": after, "support": support}
            st.done(inliers, stats)
        stages.survivors["selection"] = np.flatnonzero(inliers)
        if compared:
            reason = "posed E refused: the fallback's model a candidate"
        elif f is None:
            reason = "no candidate model"
        elif np.count_nonzero(inliers) < lean.min_inliers:
            reason = f"{int(np.count_nonzero(inliers))} inliers, fewer than min_inliers"
        elif support < lean.min_support * consensus:
            reason = f"the model explains {support} of the consensus {consensus}"
        if f is not None and (reason is None or compared):
            f = corr.to_pixels(f)
        if (
            reason is not None
            and not compared
            and not footprints_overlap(pair, z0, lean.footprint_margin)
        ):
            # no acceptable model and the footprints apart: the consensus was chance
            statistics["selected"] = None
            statistics["fallback"] = {"used": False, "reason": f"no overlap, {reason}"}
            statistics["degenerate"] = "no model: the footprints do not overlap"
            return MethodResult(
                np.zeros(0, dtype=np.int64), "fundamental", None, statistics, options
            )

    statistics["fallback"] = {"used": reason is not None, "reason": reason}
    if reason is not None and not compared:
        f, inliers = _fallback(corr, options, stages)
    if f is None:
        statistics["degenerate"] = "no model found"
    return MethodResult(np.flatnonzero(inliers), "fundamental", f, statistics, options)


def _supported(
    models: dict[str, np.ndarray],
    corr: Correspondences,
    rows: np.ndarray,
    t2: float,
    least: float,
    statistics: dict[str, Any],
) -> dict[str, np.ndarray]:
    """``models`` less the posed E where fewer than ``least`` of the consistent ``rows`` are
    within the threshold of it (the rough poses do not explain the proposal)."""
    if "posed" not in models:
        return models
    support = int(np.count_nonzero(corr.sampson_sq(models["posed"], rows) < t2))
    statistics["posed_support"] = support
    return models if support >= least else {k: v for k, v in models.items() if k != "posed"}


def _fallback_model(
    corr: Correspondences, options: VerifyOptions, stages: Stages
) -> np.ndarray | None:
    """``lean.fallback``'s model (normalised F) on all matches, or None: a candidate."""
    with stages.stage("fallback", len(corr)) as st:
        fit = _fallback_fit(corr, options)
        st.done(np.zeros(len(corr), dtype=bool), dict(fit.stats))
    return None if fit.matrix is None else corr.from_pixels(fit.matrix)


def _fallback_fit(corr: Correspondences, options: VerifyOptions) -> Any:
    """``lean.fallback`` on all matches, its iterations bounded for ``min_inliers`` true
    matches (the fewest the method accepts)."""
    lean, n = options.lean, len(corr)
    ransac = dataclasses.replace(options.ransac, estimator=lean.fallback)
    if lean.min_inliers < n:
        ransac = dataclasses.replace(
            ransac, max_iters=iterations_bound(lean.min_inliers / n, ransac)
        )
    return estimate_model(corr.p1, corr.p2, ransac, options.seed)


def _fallback(
    corr: Correspondences, options: VerifyOptions, stages: Stages
) -> tuple[np.ndarray | None, np.ndarray]:
    """``lean.fallback`` on all matches, then the same local optimisation; (F or None,
    inlier mask)."""
    lean, n = options.lean, len(corr)
    with stages.stage("fallback", n) as st:
        fit = _fallback_fit(corr, options)
        inliers = np.zeros(n, dtype=bool)
        stats = dict(fit.stats)
        f = fit.matrix
        if f is not None:
            t2 = (options.ransac.threshold_px * corr.scale) ** 2
            g, d2, _, stats["inliers_after"], _ = kernels.refine(
                corr.joint, corr.from_pixels(f), t2, np.asarray(lean.lo_schedule, dtype=float)
            )
            f, inliers = corr.to_pixels(g), d2 < t2
        st.done(inliers, stats)
    stages.survivors["fallback"] = np.flatnonzero(inliers)
    return f, inliers


def _turned_to_field(pair: PairData, start: np.ndarray, end: np.ndarray) -> tuple[PairData, float]:
    """The pair with image 2's rough attitude turned about the vertical by the rotation of
    the affine map start -> end of the consistent motions (the yaw error of its rough
    pose); and that angle (deg)."""
    design = np.column_stack([start - start.mean(axis=0), np.ones(len(start))])
    coef, *_ = np.linalg.lstsq(design, end, rcond=None)
    m = coef[:2].T  # end ~ m @ (start - mean) + b
    angle = math.atan2(m[1, 0] - m[0, 1], m[0, 0] + m[1, 1])
    c, s = math.cos(angle), math.sin(angle)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pose2 = dataclasses.replace(pair.pose2, R_world_to_cam=pair.pose2.R_world_to_cam @ rz)
    return dataclasses.replace(pair, pose2=pose2), math.degrees(angle)
