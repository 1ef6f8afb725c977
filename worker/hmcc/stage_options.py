"""The options of every stage, in a module of its own: no numba, SciPy or OpenCV behind them.

Each class is re-exported by the module of its stage (:mod:`hmcc.plus` ``PlusOptions`` and so
on), where it is documented and used; it lives here so that what only reads or checks options
(the request parser, a flight being handed to child processes) does not import the kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

from annotated_types import Ge, Gt, Interval, MaxLen

from .bounds import PYDANTIC_CONFIG, check_fields

__all__ = [
    "DirectionChangeOptions",
    "DirectionOptions",
    "FootprintOptions",
    "GCOptions",
    "GroundOptions",
    "GuidedOptions",
    "LeanOptions",
    "LengthOptions",
    "PairOptions",
    "PlusOptions",
    "RansacOptions",
    "EstimatorName",
    "ModelType",
    "MIN_BIN_DEG",
]

ModelType = Literal["fundamental", "essential", "homography"]
EstimatorName = Literal[
    "ransac",
    "lo-ransac",
    "lmeds",
    "magsac++",
    "usac-default",
    "usac-accurate",
    "usac-fast",
    "usac-prosac",
]

#: Narrowest bin: keeps a histogram small (36 000 bins over 360 deg) and the division finite.
MIN_BIN_DEG = 0.01


def _check_bins(span_deg: float, bin_deg: float, name: str) -> int:
    if not MIN_BIN_DEG <= bin_deg <= span_deg:
        raise ValueError(f"{name}: must be in [{MIN_BIN_DEG:g}, {span_deg:g}] deg")
    n = span_deg / bin_deg
    if abs(n - round(n)) > 1e-9:
        raise ValueError(f"{name}: must divide {span_deg:g} deg into a whole number of bins")
    return round(n)


@dataclass(frozen=True)
class GroundOptions:
    """Where the projection plane goes when the pair gives the ground, not the plane.

    With a ground height G (given as ``plane.ground_z`` or estimated for ``plane.z = "auto"``)
    the plane is ``Z0 = G - plane_depth_fraction * (mean camera height - G)``. The rule is
    ours: the paper gives one instance, a plane at -100 m for a site near 0 m flown at 300 m
    (section 4.2) "to decrease the influence of terrain relief" (section 5: its planes were
    approximated by the sites' average altitudes), and the default 1/3 reproduces it. Below
    the ground every true motion gains a parallax component along the baseline that dominates
    pose noise and relief. 0 projects onto the ground itself.

    How ``"auto"`` estimates G from the matches:

    Every match is triangulated with the rough poses (midpoint method); the heights of the
    points in front of both cameras, below both, and seen under at least
    ``min_parallax_deg`` form a sample that mixes true ground points with outliers'
    scattered heights. The narrowest window holding ``mode_fraction`` of the sample (at least
    ``min_points``) is the densest cluster, the ground, even under a large majority of
    outliers; the estimate is the median of the heights within ``refine_window`` x the flying
    height around that window's median.
    """

    __pydantic_config__ = PYDANTIC_CONFIG

    plane_depth_fraction: Annotated[float, Interval(ge=0, le=10)] = 1.0 / 3.0
    min_parallax_deg: Annotated[float, Interval(ge=0, lt=90)] = 1.0
    mode_fraction: Annotated[float, Interval(gt=0, le=1)] = 0.15
    refine_window: Annotated[float, Interval(gt=0, le=1)] = 0.1
    min_points: Annotated[int, Ge(1)] = 5

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class DirectionOptions:
    """Global direction vote. ``bin_deg`` must divide 360."""

    __pydantic_config__ = PYDANTIC_CONFIG

    bin_deg: Annotated[float, Interval(ge=MIN_BIN_DEG, le=360)] = 10.0
    window_bins: Annotated[int, Ge(0)] = 5
    min_vote_ratio: Annotated[float, Interval(ge=0, le=1)] = 0.2

    def __post_init__(self) -> None:
        check_fields(self)
        _check_bins(360.0, self.bin_deg, "bin_deg")

    @property
    def n_bins(self) -> int:
        return _check_bins(360.0, self.bin_deg, "bin_deg")


@dataclass(frozen=True)
class DirectionChangeOptions:
    """Local direction-change vote. ``bin_deg`` must divide ``max_deg``."""

    __pydantic_config__ = PYDANTIC_CONFIG

    k_neighbors: Annotated[int, Ge(1)] = 7
    bin_deg: Annotated[float, Interval(ge=MIN_BIN_DEG, le=180)] = 3.0
    max_deg: Annotated[float, Interval(gt=0, le=180)] = 30.0
    window_bins: Annotated[int, Ge(0)] = 3
    min_vote_ratio: Annotated[float, Interval(ge=0, le=1)] = 0.4

    def __post_init__(self) -> None:
        check_fields(self)
        _check_bins(self.max_deg, self.bin_deg, "bin_deg")

    @property
    def n_bins(self) -> int:
        return _check_bins(self.max_deg, self.bin_deg, "bin_deg")


@dataclass(frozen=True)
class LengthOptions:
    """Global length consistency: motions with |z-score| > ``z_max`` are outliers."""

    __pydantic_config__ = PYDANTIC_CONFIG

    z_max: Annotated[float, Interval(gt=0)] = 3.0

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class RansacOptions:
    """Final-stage estimator. Defaults are the paper's: F, classic RANSAC, 1.0 px."""

    __pydantic_config__ = PYDANTIC_CONFIG

    model: ModelType = "fundamental"
    estimator: EstimatorName = "ransac"
    threshold_px: Annotated[float, Interval(gt=0, le=100)] = 1.0
    confidence: Annotated[float, Interval(gt=0.0, lt=1.0)] = 0.999
    max_iters: Annotated[int, Interval(ge=1, le=1_000_000)] = 10_000

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class GCOptions:
    """Parameters of the Lu et al. (2016) geometrical-consistency vote.

    Defaults are the paper's values where it gives them (see the module docstring).
    """

    __pydantic_config__ = PYDANTIC_CONFIG

    #: Rotation bin width (the paper's sampling interval), degrees; 360 / width is rounded to
    #: an integer number of bins. Paper: 10 deg -> 36 bins.
    rotation_tolerance_deg: Annotated[float, Interval(ge=0.01, le=180)] = 10.0
    #: Scale bin width on ln(scale). Paper: 17 bins over [1/5, 5] -> ln(5) / 8.
    log_scale_tolerance: Annotated[float, Interval(ge=1e-3)] = math.log(5.0) / 8.0
    #: A bin near the overall peak is "correct" if it holds >= this fraction of the peak's
    #: votes. Paper: 0.4.
    min_vote_ratio: Annotated[float, Interval(gt=0, le=1)] = 0.4
    #: Correct bins lie within +- this many bins of the overall peak in each dimension
    #: (circular in rotation). Paper: 3.
    peak_radius_bins: Annotated[int, Ge(0)] = 3
    #: Scale range [1/scale_range, scale_range]; pairs outside do not vote. Paper: 5.
    scale_range: Annotated[float, Interval(gt=1)] = 5.0
    #: d0 of the vote weight d^2 / (d^2 + d0^2), pixels; 0 = unweighted (the default). Not
    #: in the papers.
    distance_weight_px: Annotated[float, Interval(ge=0)] = 0.0
    #: Partners (other features) per candidate; None = every one (the papers', quadratic).
    #: With a number, a seeded random subset of that many. Not in the papers.
    max_partners: Annotated[int, Ge(1)] | None = None
    #: Seed of the partner subsampling (``verify`` sets it to ``params.seed``).
    seed: Annotated[int, Ge(0)] = 0

    def __post_init__(self) -> None:
        """Validate every field; raise ``ValueError("<field>: <reason>")``."""
        check_fields(self)
        if self.log_scale_tolerance > math.log(self.scale_range):
            raise ValueError("log_scale_tolerance: must not exceed ln(scale_range)")


@dataclass(frozen=True)
class PlusOptions:
    """Parameters of ``hmcc-plus`` (see :mod:`hmcc.plus`); the defaults are the measured ones."""

    __pydantic_config__ = PYDANTIC_CONFIG

    #: Cells per axis of the 2-D motion vote over the 2-98 % range.
    grid_bins: Annotated[int, Interval(ge=4, le=1024)] = 24
    #: Most seeds (smallest motion-field residuals).
    max_seeds: Annotated[int, Interval(ge=8, le=100_000)] = 60
    #: Most band matches (smallest distance across the epipolar line).
    max_band: Annotated[int, Interval(ge=0, le=100_000)] = 150
    #: Along the line: |parallax - seeds' field| <= this x the larger of the seeds' median
    #: parallax and a ground point's (+ 3 sigma).
    band_length: Annotated[float, Interval(ge=0, le=100)] = 3.0
    #: Inliers must also have a plausible parallax (within band_length, and not below the
    #: plane Z0) and rays that do not diverge by more than ``divergence_deg``.
    gate: bool = True
    #: Rays diverging by more than this (degrees: pose errors and more) meet behind a camera.
    divergence_deg: Annotated[float, Interval(ge=0, le=180)] = 5.0
    #: Sampson distance deciding inliers, pixels.
    threshold_px: Annotated[float, Interval(gt=0, le=100)] = 1.5
    #: Refit thresholds, x threshold_px.
    lo_schedule: Annotated[tuple[Annotated[float, Interval(ge=0.5, le=20)], ...], MaxLen(10)] = (
        2.0,
        1.0,
        1.0,
    )
    #: Off the seeds' field along the line by this x sigma: strong parallax.
    strong_parallax: Annotated[float, Interval(ge=0, le=100)] = 3.0
    #: 8-point samples drawn from the candidates.
    hypotheses: Annotated[int, Interval(ge=1, le=10_000)] = 32
    #: Of each sample's 8 points, drawn from the strong-parallax ones.
    parallax_points: Annotated[int, Interval(ge=0, le=8)] = 3
    #: Best-scored hypotheses refined by least squares on their inliers (at most hypotheses).
    polish: Annotated[int, Ge(1)] = 3
    #: Fewer candidates fit the model: USAC on the candidates.
    min_candidate_share: Annotated[float, Interval(ge=0, le=1)] = 0.7
    #: USAC iterations on the candidates (when sampling fails).
    model_max_iters: Annotated[int, Interval(ge=1, le=100_000)] = 500
    #: Fewer inliers: HMCC is unreliable for the pair, fall back.
    min_inliers: Annotated[int, Interval(ge=8, le=100_000)] = 15
    #: Smaller share of seeds among the inliers: the fallback runs too, and the model of lower
    #: truncated cost on all matches is the result.
    min_seed_agreement: Annotated[float, Interval(ge=0, le=1)] = 0.5
    #: The estimator on all matches when the pair cannot be trusted.
    fallback: EstimatorName = "magsac++"
    #: Check that the model explains the pair, not only the candidates (see ``check_share``).
    check: bool = True
    #: Smaller share of the wide band's expected true matches kept by the model: a second model.
    check_share: Annotated[float, Interval(ge=0, le=1)] = 0.9
    #: The wide band of the check: across the plane epipolar line, in sigmas of the seeds.
    check_sigmas: Annotated[float, Interval(gt=0, le=10_000)] = 40.0
    #: With the check, on models of at most 150 inliers: also try the models of the cameras'
    #: intrinsics (E refined from the rough poses on the inliers first; where the check fires,
    #: E of the inliers; each refined as F on all matches and kept only with a lower cost),
    #: keep the self-fitted inliers E of the others keeps and drop the outliers E and the
    #: model of the others put off (the model bent to them).
    calibrated: bool = True
    #: With the check, on a model of at most 150 inliers: an inlier farther than this x
    #: threshold_px from the model fitted on the other inliers is dropped (the model kept it
    #: only by being fitted on it) unless the calibrated model of the others keeps it; 0: off.
    self_fit: Annotated[float, Interval(ge=0, le=1000)] = 3.0

    def __post_init__(self) -> None:
        check_fields(self)
        if self.polish > self.hypotheses:
            raise ValueError("polish: must be in [1, hypotheses]")


# --------------------------------------------------------------------------- scoring
# The loops run compiled (:mod:`hmcc.plus_kernels`); here: options in, statistics out.


@dataclass(frozen=True)
class LeanOptions:
    """Parameters of ``hmcc-lean`` (see :mod:`hmcc.lean`); its threshold is
    ``ransac.threshold_px``."""

    __pydantic_config__ = PYDANTIC_CONFIG

    #: Cells per axis of the 2-D motion vote (the mode the affine field starts from).
    grid_bins: Annotated[int, Interval(ge=4, le=1024)] = 24
    #: Fewer matches on the motion field, beyond those chance puts there: no consensus.
    min_consensus: Annotated[int, Interval(ge=8, le=100_000)] = 15
    #: 8-point samples drawn from the consistent set for the F candidate.
    hypotheses: Annotated[int, Interval(ge=1, le=10_000)] = 64
    #: The footprints are grown by this share of their size before the overlap test.
    footprint_margin: Annotated[float, Interval(ge=0, le=10)] = 0.25
    #: Fewer inliers: no acceptable model, the fallback runs.
    min_inliers: Annotated[int, Interval(ge=8, le=100_000)] = 15
    #: The local optimisation: least-squares refits on the matches within each multiple of
    #: the threshold; the model with the most inliers is kept.
    lo_schedule: Annotated[tuple[Annotated[float, Interval(ge=0.5, le=20)], ...], MaxLen(10)] = (
        8.0,
        4.0,
        2.0,
        1.0,
    )
    #: The posed E is refused unless this share of the consensus is within the threshold of it
    #: (the rough poses must explain the proposal made with them).
    pose_support: Annotated[float, Interval(ge=0, le=1)] = 0.5
    #: Where the posed E is refused: fit it once more with image 2's rough yaw turned by the
    #: rotation of the consistent motions (the yaw error they show), before the fallback.
    yaw_from_field: bool = False
    #: Where the posed E is refused (the rough poses do not fit the pixels, and the proposal,
    #: made with them, may hold outliers): the fallback's model is a candidate too.
    compare_fallback: bool = False
    #: Where the posed E is refused: the plane's candidates, a homography on the consistent set
    #: decomposed with both K into relative poses (R, t), each one's E refined as the posed E
    #: is (no rough attitude needed).
    plane_candidates: bool = True
    #: The selected model is accepted when at least this share of the consensus is within
    #: the threshold of it after the local optimisation; else the fallback runs (0: off).
    min_support: Annotated[float, Interval(ge=0, le=1)] = 0.5
    #: The estimator on all matches where no candidate is acceptable.
    fallback: EstimatorName = "magsac++"

    def __post_init__(self) -> None:
        check_fields(self)


#: Squared Mahalanobis distance to the motion field under which a match is consistent:
#: chi2(2) at 99 %, as :func:`hmcc.plus_kernels.motion_field` counts them.


@dataclass(frozen=True)
class GuidedOptions:
    """The guided matcher's options (see the module docstring for how each is used).

    POS errors: ``attitude_error_deg`` (each camera), ``position_error_m`` (horizontal, each
    camera), ``ground_error_fraction`` (Z0's error as a fraction of the flying height).
    ``max_wide_fraction`` caps the wide radius (fraction of image 2's larger side).
    ``sample_size`` keypoints in the first pass (half of them first); ``tight_min_px`` the
    smallest tight radius;
    a pose fits with ``min_support`` (and ``min_support_fraction`` of the first pass's
    matches) within the tight radius; predictions of fewer than ``min_overlap`` of the
    keypoints inside image 2: the pair does not overlap. ``try_turns``: a first pass that does
    not fit is tried again with the cameras turned (``turn_sample_size`` keypoints); then,
    ``brute_force_on_mismatch``, brute force; before that, ``search_rotation``: the rotation
    from the keypoints' orientations (peak window ``rotation_window_deg``). In the second
    pass the keypoints within ``ratio_radius_factor`` x the tight radius (at least
    ``ratio_radius_min_px``) compete in the ratio rule. Rules: ``max_ratio``,
    ``max_distance_rad`` (COLMAP's ``max_ratio`` 0.8 and ``max_distance`` 0.7), mutual
    best matches only with ``cross_check``.
    """

    __pydantic_config__ = PYDANTIC_CONFIG

    attitude_error_deg: Annotated[float, Interval(ge=0, le=30)] = 3.0
    position_error_m: Annotated[float, Interval(ge=0, le=1000)] = 3.0
    ground_error_fraction: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.1
    max_wide_fraction: Annotated[float, Interval(gt=0, le=2)] = 0.25
    sample_size: Annotated[int, Ge(16)] = 1024
    tight_min_px: Annotated[float, Gt(0)] = 8.0
    min_support: Annotated[int, Ge(1)] = 12
    min_support_fraction: Annotated[float, Interval(ge=0, le=1)] = 0.25
    min_overlap: Annotated[float, Interval(ge=0, le=1)] = 0.02
    max_ratio: Annotated[float, Interval(gt=0, le=1)] = 0.8
    max_distance_rad: Annotated[float, Interval(gt=0, le=math.pi)] = 0.7
    cross_check: bool = True
    try_turns: bool = True
    turn_sample_size: Annotated[int, Ge(16)] = 256
    brute_force_on_mismatch: bool = False
    ratio_radius_factor: Annotated[float, Ge(1)] = 3.0
    ratio_radius_min_px: Annotated[float, Ge(0)] = 48.0
    search_rotation: bool = True
    rotation_window_deg: Annotated[float, Interval(gt=0, le=90)] = 10.0

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class FootprintOptions:
    """How a footprint is drawn.

    ``max_range_ratio``: the furthest ground point kept, as a multiple of the camera's height
    above the plane (5: a ray 11.3 deg below the horizon; a 45 deg oblique with a 60 deg field
    reaches 3.7). Rays above the horizon stop there too. ``border_samples``: points per image
    side (the hull keeps the corners of an undistorted camera; more follow a distorted border
    or a clipped far edge more closely).
    """

    __pydantic_config__ = PYDANTIC_CONFIG

    max_range_ratio: Annotated[float, Interval(gt=0, le=1000)] = 5.0
    border_samples: Annotated[int, Interval(ge=2, le=1000)] = 8

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class PairOptions:
    """Which pairs of a flight are chosen (:func:`flight_pairs`).

    ``min_overlap``: a pair is kept when its footprints overlap by more than this fraction of
    the smaller one (the paper's 0.5). ``max_per_image``: each image keeps at most its K
    largest overlaps (a pair stays when either image keeps it); None: no cap.
    ``min_partners``: each image keeps at least its K largest overlaps above zero, below
    ``min_overlap`` too (0: the overlap rule alone). ``footprint``: how footprints are drawn.
    """

    __pydantic_config__ = PYDANTIC_CONFIG

    min_overlap: Annotated[float, Interval(ge=0.0, le=1.0)] = 0.5
    max_per_image: Annotated[int, Ge(1)] | None = None
    min_partners: Annotated[int, Ge(0)] = 0
    footprint: FootprintOptions = field(default_factory=FootprintOptions)

    def __post_init__(self) -> None:
        check_fields(self)
