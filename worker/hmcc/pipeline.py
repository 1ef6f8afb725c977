"""Verify one image pair: projection -> HMCC stages (or a baseline pre-filter) -> final model.

``verify(pair, method, options)`` is the whole method on arrays; it does no I/O. Methods:

* ``hmcc-ransac`` (the paper): HMCC filter, then ``options.ransac`` on the survivors;
* ``hmcc-plus`` (the default, :mod:`hmcc.plus`): motion consistency ranks the matches, a
  fundamental matrix is fitted on the most consistent ones, then every match is decided by its
  Sampson distance with local-optimisation refits; an unreliable pair falls back to
  ``plus.fallback`` on all matches (``statistics.fallback`` says when and why);
* ``hmcc``: the HMCC filter alone, its survivors are the inliers;
* ``gc-ransac``: the pairwise rotation/scale pre-filter of Lu et al. (2016), then
  ``options.ransac`` (needs keypoint size and angle);
* any estimator name of :mod:`hmcc.ransac` (``ransac``, ``lo-ransac``, ``magsac++``,
  ``usac-accurate``, ...): that estimator on all matches, no pre-filter; the method name sets
  ``ransac.estimator``.

Matches whose rays miss the plane cannot be given a motion; HMCC methods drop them in the
``projection`` stage (counted there), the others ignore the projection.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass, field
from typing import Annotated, Any, cast

import cv2
import numpy as np
from pydantic import Field

from . import __version__
from .camera import Camera
from .errors import InputError
from .gc import GCOptions, gc_filter
from .hmcc import (
    DirectionChangeOptions,
    DirectionOptions,
    LengthOptions,
    filter_lengths,
    vote_direction_changes,
    vote_directions,
)
from .plus import (
    Correspondences,
    PlusOptions,
    epipolar_band,
    fit_candidates,
    motion_field_seeds,
    plane_epipole_directions,
    refine_fundamental,
)
from .pose import Pose
from .projection import GroundOptions, Motions, estimate_ground_height, project_to_plane
from .ransac import (
    ESTIMATORS,
    MIN_MATCHES,
    EstimatorName,
    ModelFit,
    RansacOptions,
    estimate_model,
)

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "PairData",
    "StageReport",
    "Verification",
    "VerifyOptions",
    "verify",
]

DEFAULT_METHOD = "hmcc-plus"
METHODS: tuple[str, ...] = (DEFAULT_METHOD, "hmcc-ransac", "hmcc", "gc-ransac", *ESTIMATORS)
_HMCC_METHODS = ("hmcc-ransac", "hmcc")


@dataclass(frozen=True)
class VerifyOptions:
    """Every parameter of every stage, defaults in one place (the paper's values; ``plus`` is
    ``hmcc-plus``'s own)."""

    seed: Annotated[int, Field(ge=0, lt=2**31)] = 0
    ground: GroundOptions = field(default_factory=GroundOptions)
    direction: DirectionOptions = field(default_factory=DirectionOptions)
    direction_change: DirectionChangeOptions = field(default_factory=DirectionChangeOptions)
    length: LengthOptions = field(default_factory=LengthOptions)
    ransac: RansacOptions = field(default_factory=RansacOptions)
    gc: GCOptions = field(default_factory=GCOptions)
    plus: PlusOptions = field(default_factory=PlusOptions)

    def __post_init__(self) -> None:
        if not 0 <= self.seed < 2**31:
            raise ValueError("seed: must be in [0, 2**31)")


_DEFAULT_OPTIONS = VerifyOptions()


@dataclass(frozen=True)
class PairData:
    """One image pair as arrays.

    ``keypoints1``/``keypoints2``: (N1, 2|4) / (N2, 2|4) float64, [x, y] or [x, y, size,
    angle_deg], pixels with the centre of the top-left pixel at (0, 0), x right, y down.
    ``matches``: (M, 2) int64 indices into them. The plane: ``plane_z`` (Z0, ENU metres) if
    given; else ``ground_z`` (the ground height; the plane goes below it, see
    :class:`GroundOptions`); else the ground is estimated from the matches.
    """

    camera1: Camera
    pose1: Pose
    camera2: Camera
    pose2: Pose
    keypoints1: np.ndarray
    keypoints2: np.ndarray
    matches: np.ndarray
    plane_z: float | None = None
    ground_z: float | None = None


@dataclass(frozen=True)
class StageReport:
    name: str
    input: int
    kept: int
    time_ms: float
    stats: dict[str, Any]


@dataclass
class Verification:
    """Result: ``inliers`` (K,) int64 ascending indices into the input matches.

    ``survivors`` maps each stage to the indices of the input matches it kept (not part of the
    JSON result; for analysis such as which stage loses true matches).
    """

    method: str
    inliers: np.ndarray
    model_type: str | None
    model_matrix: np.ndarray | None
    stages: list[StageReport]
    statistics: dict[str, Any]
    options: VerifyOptions
    survivors: dict[str, np.ndarray] = field(default_factory=dict)

    @functools.cached_property
    def params(self) -> dict[str, Any]:
        """The resolved parameters as echoed in the result (built on first use: it costs about
        as much as a small pair's verification stage)."""
        return dataclasses.asdict(self.options) | {"method": self.method}

    @property
    def timings_ms(self) -> dict[str, float]:
        timings = {s.name: s.time_ms for s in self.stages}
        timings["total"] = float(sum(timings.values()))
        return timings

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready result in the public format."""
        return {
            "method": self.method,
            "inliers": self.inliers.tolist(),
            "model": {
                "type": self.model_type,
                "matrix": None if self.model_matrix is None else self.model_matrix.tolist(),
            },
            "stages": [dataclasses.asdict(s) for s in self.stages],
            "timings_ms": self.timings_ms,
            "statistics": self.statistics,
            "params": self.params,
        }


class _Stages:
    """Times stages and records what went in and what was kept::

        with stages.stage("direction", n_in) as st:
            keep, stats = vote_directions(...)
            st.done(keep, stats)
    """

    def __init__(self) -> None:
        self.reports: list[StageReport] = []
        self.survivors: dict[str, np.ndarray] = {}

    def stage(self, name: str, n_in: int) -> _Stage:
        return _Stage(self.reports, name, n_in)


class _Stage:
    """One timed stage (a plain context manager: ``contextlib``'s costs a few us per use)."""

    def __init__(self, reports: list[StageReport], name: str, n_in: int) -> None:
        self.reports, self.name, self.n_in = reports, name, n_in
        self.keep: np.ndarray = np.zeros(0, dtype=bool)
        self.stats: dict[str, Any] = {}

    def __enter__(self) -> _Stage:
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        ms = (time.perf_counter() - self.t0) * 1e3
        kept = int(np.count_nonzero(self.keep))
        self.reports.append(StageReport(self.name, self.n_in, kept, ms, self.stats))

    def done(self, keep: np.ndarray, stats: dict[str, Any]) -> np.ndarray:
        self.keep, self.stats = keep, stats
        return keep


def _resolve(method: str, options: VerifyOptions) -> VerifyOptions:
    if method not in METHODS:
        raise InputError("method", f"unknown method {method!r}; one of {list(METHODS)}")
    # One seed for every random stage, echoed truthfully.
    if options.gc.seed != options.seed:
        options = dataclasses.replace(
            options, gc=dataclasses.replace(options.gc, seed=options.seed)
        )
    if method in ESTIMATORS and options.ransac.estimator != method:
        estimator = cast(EstimatorName, method)
        options = dataclasses.replace(
            options, ransac=dataclasses.replace(options.ransac, estimator=estimator)
        )
    return options


def verify(
    pair: PairData, method: str = DEFAULT_METHOD, options: VerifyOptions | None = None
) -> Verification:
    """Verify the matches of one pair; raises :class:`InputError` for input it cannot use."""
    options = _resolve(method, options or _DEFAULT_OPTIONS)
    m = len(pair.matches)
    need = MIN_MATCHES[options.ransac.model]
    if method != "hmcc" and m < need:
        raise InputError("matches", f"{m} matches; a {options.ransac.model} model needs {need}")
    px1 = pair.keypoints1[pair.matches[:, 0], :2]
    px2 = pair.keypoints2[pair.matches[:, 1], :2]
    stages = _Stages()
    statistics: dict[str, Any] = {"matches": m}
    candidates = np.arange(m)

    if method in _HMCC_METHODS:
        candidates = _hmcc(pair, px1, px2, options, stages, statistics)
    elif method == "gc-ransac":
        candidates = _gc(pair, options, stages)

    model_type: str | None = None
    matrix: np.ndarray | None = None
    inliers = candidates
    if method == DEFAULT_METHOD:
        if options.ransac.model != "fundamental":
            raise InputError(
                "params.ransac.model",
                f"{DEFAULT_METHOD} fits a fundamental matrix; name another method for "
                f"{options.ransac.model!r}",
            )
        matrix, inliers = _plus(pair, px1, px2, options, stages, statistics)
        model_type = "fundamental"
        if matrix is None:
            statistics["degenerate"] = "no model found"
    elif method != "hmcc":
        with stages.stage("ransac", len(candidates)) as st:
            fit = _final(pair, px1[candidates], px2[candidates], options)
            inliers = candidates[st.done(fit.inliers, fit.stats)]
        stages.survivors["ransac"] = inliers
        model_type, matrix = fit.model, fit.matrix
        if "degenerate" in fit.stats:
            statistics["degenerate"] = fit.stats["degenerate"]

    inliers = np.sort(inliers).astype(np.int64)
    statistics.update(
        {
            "inliers": len(inliers),
            "inlier_ratio": len(inliers) / m if m else 0.0,
            "versions": {"hmcc": __version__, "opencv": cv2.__version__, "numpy": np.__version__},
        }
    )
    return Verification(
        method,
        inliers,
        model_type,
        matrix,
        stages.reports,
        statistics,
        options,
        stages.survivors,
    )


def _hmcc(
    pair: PairData,
    px1: np.ndarray,
    px2: np.ndarray,
    options: VerifyOptions,
    stages: _Stages,
    statistics: dict[str, Any],
) -> np.ndarray:
    """Projection and the three HMCC stages; returns the surviving match indices."""
    with stages.stage("projection", len(px1)) as st:
        motions, valid, stats = _project(pair, px1, px2, options.ground)
        idx = np.flatnonzero(st.done(valid, stats))
    stages.survivors["projection"] = idx
    statistics["z0_m"] = stats["z0_m"]
    direction = motions.direction_deg

    with stages.stage("direction", len(idx)) as st:
        keep = st.done(*vote_directions(direction, options.direction))
    idx, motions, direction = idx[keep], motions.subset(keep), direction[keep]
    stages.survivors["direction"] = idx

    with stages.stage("direction_change", len(idx)) as st:
        keep = st.done(
            *vote_direction_changes(motions.start, direction, options.direction_change)
        )
    idx, motions = idx[keep], motions.subset(keep)
    stages.survivors["direction_change"] = idx

    with stages.stage("length", len(idx)) as st:
        keep = st.done(*filter_lengths(motions.length, options.length))
    stages.survivors["length"] = idx[keep]
    return idx[keep]


def _plus(
    pair: PairData,
    px1: np.ndarray,
    px2: np.ndarray,
    options: VerifyOptions,
    stages: _Stages,
    statistics: dict[str, Any],
) -> tuple[np.ndarray | None, np.ndarray]:
    """``hmcc-plus``: projection, consistency (seeds + epipolar band), model on the candidates,
    refine on all matches; ``fallback`` when HMCC is unreliable. Returns F and the inliers."""
    plus = options.plus
    u1 = pair.camera1.undistort_pixels(px1)
    u2 = pair.camera2.undistort_pixels(px2)
    reason: str | None = None
    f: np.ndarray | None = None
    seeds = np.zeros(0, dtype=np.int64)
    plausible: np.ndarray | None = None
    try:
        with stages.stage("projection", len(px1)) as st:
            motions, valid, stats = _project(pair, px1, px2, options.ground)
            idx = np.flatnonzero(st.done(valid, stats))
        statistics["z0_m"] = stats["z0_m"]
    except InputError as e:
        if pair.plane_z is not None or pair.ground_z is not None:
            raise  # the caller's plane is wrong: say so rather than hide it behind a fallback
        idx, reason = np.zeros(0, dtype=np.int64), f"projection: {e.reason}"
    stages.survivors["projection"] = idx

    if reason is None and len(idx) < plus.min_inliers:
        reason = f"{len(idx)} matches reach the plane, fewer than min_inliers"
    if reason is None:
        with stages.stage("consistency", len(idx)) as st:
            candidates, seeds, plausible, strong, stats = _consistency(
                pair, motions, stats["z0_m"], plus
            )
            keep = np.zeros(len(idx), dtype=bool)
            keep[candidates] = True
            st.done(keep, stats)
        seeds, candidates = idx[seeds], idx[candidates]
        stages.survivors["consistency"] = candidates
        with stages.stage("model", len(candidates)) as st:
            corr = Correspondences(u1, u2)
            f, keep, stats = fit_candidates(corr, candidates, strong, plus, options.seed)
            st.done(keep, {"found": f is not None} | stats)
        if f is None:
            reason = f"no model from {len(candidates)} candidates"

    inliers = np.zeros(len(px1), dtype=bool)
    if f is not None:
        with stages.stage("refine", len(px1)) as st:
            f, inliers, stats = refine_fundamental(corr, f, plus)
            if plus.gate and plausible is not None:
                implausible = np.zeros(len(px1), dtype=bool)
                implausible[idx[~plausible]] = True
                stats["gated"] = statistics["gated"] = int(np.count_nonzero(inliers & implausible))
                inliers &= ~implausible
            st.done(inliers, stats)
        stages.survivors["refine"] = np.flatnonzero(inliers)
        agreement = np.count_nonzero(inliers[seeds]) / len(seeds) if len(seeds) else 0.0
        statistics["seed_agreement"] = agreement
        if inliers.sum() < plus.min_inliers:
            reason = f"{int(inliers.sum())} inliers, fewer than min_inliers"
        elif agreement < plus.min_seed_agreement:
            reason = f"seed agreement {agreement:.2f} below min_seed_agreement"

    statistics["fallback"] = {"used": reason is not None, "reason": reason}
    if reason is not None:
        f, inliers = _plus_fallback(u1, u2, options, stages)
    return f, np.flatnonzero(inliers)


def _consistency(
    pair: PairData, motions: Motions, z0: float, plus: PlusOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, dict[str, Any]]:
    """Candidate and seed indices into ``motions``, the (N,) mask of plausible parallaxes
    (None without a baseline), the candidates' mask of strong parallax, statistics."""
    vectors = motions.vectors
    seeds, _, stats = motion_field_seeds(motions.start, vectors, plus)
    directions = plane_epipole_directions(motions.start, pair.pose1.center, pair.pose2.center, z0)
    if directions is None:
        stats["band"] = 0
        return seeds, seeds, None, np.zeros(len(seeds), dtype=bool), stats
    band, plausible, strong, band_stats = epipolar_band(
        motions.start, vectors, directions, seeds, plus
    )
    stats.update(band_stats)
    mask = np.zeros(len(vectors), dtype=bool)
    mask[seeds] = True
    mask[band] = True
    candidates = np.flatnonzero(mask)
    return candidates, seeds, plausible, strong[candidates], stats


def _plus_fallback(
    u1: np.ndarray, u2: np.ndarray, options: VerifyOptions, stages: _Stages
) -> tuple[np.ndarray | None, np.ndarray]:
    """``plus.fallback`` on all matches, then the same refine; (F or None, inlier mask)."""
    ransac = dataclasses.replace(options.ransac, estimator=options.plus.fallback)
    with stages.stage("fallback", len(u1)) as st:
        fit = estimate_model(u1, u2, ransac, options.seed)
        inliers = np.zeros(len(u1), dtype=bool)
        stats = dict(fit.stats)
        f = fit.matrix
        if f is not None:
            corr = Correspondences(u1, u2)
            f, inliers, refine_stats = refine_fundamental(corr, corr.from_pixels(f), options.plus)
            stats.update(refine_stats)
        st.done(inliers, stats)
    stages.survivors["fallback"] = np.flatnonzero(inliers)
    return f, inliers


def _project(
    pair: PairData, px1: np.ndarray, px2: np.ndarray, ground: GroundOptions
) -> tuple[Motions, np.ndarray, dict[str, Any]]:
    """Motions of the matches whose both rays reach the plane, the (M,) mask of those, stats."""
    stats: dict[str, Any] = {}
    z0 = pair.plane_z
    if z0 is None:
        z0 = _plane_below_ground(pair, px1, px2, ground, stats)
    start, ok1 = project_to_plane(pair.camera1, pair.pose1, px1, z0)
    end, ok2 = project_to_plane(pair.camera2, pair.pose2, px2, z0)
    for name, ok in (("image1", ok1), ("image2", ok2)):
        if len(ok) and not ok.any():
            raise InputError("plane.z", f"no ray of {name} reaches the plane Z0 = {z0:g} m")
    valid = ok1 & ok2
    motions = Motions(start, end) if valid.all() else Motions(start[valid], end[valid])
    stats.update(
        {
            "z0_m": z0,
            "z0_source": _z0_source(pair),
            "rays_missed_image1": int((~ok1).sum()),
            "rays_missed_image2": int((~ok2).sum()),
        }
    )
    return motions, valid, stats


def _z0_source(pair: PairData) -> str:
    if pair.plane_z is not None:
        return "given"
    return "ground_z" if pair.ground_z is not None else "auto"


def _plane_below_ground(
    pair: PairData,
    px1: np.ndarray,
    px2: np.ndarray,
    ground: GroundOptions,
    stats: dict[str, Any],
) -> float:
    """Z0 from the given or estimated ground height (see :class:`GroundOptions`)."""
    ground_z = pair.ground_z
    field = "plane.ground_z"
    if ground_z is None:
        field = "plane.z"
        ground_z, stats["ground"] = estimate_ground_height(
            pair.camera1, pair.pose1, px1, pair.camera2, pair.pose2, px2, ground
        )
        if ground_z is None:
            raise InputError(
                field, "too few matches triangulate to estimate the ground height; give it"
            )
    height = 0.5 * (pair.pose1.center[2] + pair.pose2.center[2]) - ground_z
    if height <= 0.0:
        raise InputError(field, f"the ground ({ground_z:g} m) is not below the cameras")
    stats["ground_z_m"] = ground_z
    return float(ground_z - ground.plane_depth_fraction * height)


def _gc(pair: PairData, options: VerifyOptions, stages: _Stages) -> np.ndarray:
    for name, kp in (("keypoints1", pair.keypoints1), ("keypoints2", pair.keypoints2)):
        if kp.shape[1] != 4:
            raise InputError(name, "gc-ransac needs [x, y, size, angle_deg] keypoints")
    kp1 = pair.keypoints1[pair.matches[:, 0]]
    kp2 = pair.keypoints2[pair.matches[:, 1]]
    with stages.stage("gc", len(kp1)) as st:
        keep = st.done(*gc_filter(kp1, kp2, options.gc))
    stages.survivors["gc"] = np.flatnonzero(keep)
    return stages.survivors["gc"]


def _final(pair: PairData, px1: np.ndarray, px2: np.ndarray, options: VerifyOptions) -> ModelFit:
    """The final estimator on (K, 2) candidate pixels of both images."""
    if options.ransac.model == "essential":
        focal = (pair.camera1.fx + pair.camera1.fy + pair.camera2.fx + pair.camera2.fy) / 4.0
        return estimate_model(
            px1,
            px2,
            options.ransac,
            options.seed,
            normalized1=pair.camera1.normalize(px1),
            normalized2=pair.camera2.normalize(px2),
            focal_px=focal,
        )
    return estimate_model(
        pair.camera1.undistort_pixels(px1),
        pair.camera2.undistort_pixels(px2),
        options.ransac,
        options.seed,
    )
