"""A flight: images, the pairs to verify between them, one method and its options.

An image is verified in dozens of pairs, so its camera, rough pose and keypoints are prepared
once (:class:`FlightImage`); a pair names two images and brings its matches (and, when its
images carry none, its own keypoints). A single pair is a flight of two images and one pair,
so every caller (the API's routes, the workers, the command line) goes the same way:
:meth:`Flight.pair_data` assembles a :class:`PairData`, :meth:`Flight.verify` verifies it.

A pair may instead ask for matching (``FlightPair.match``): its images carry descriptors, and
:meth:`Flight.verify` matches them (:mod:`hmcc.pair_matching`, guided by the rough poses) before
it verifies the matches found; the result then holds those matches.

Positions given in WGS84 are put into a local tangent frame per pair (its mean latitude and
longitude at height 0), so a pair gives the same result alone or in a flight.
"""

from __future__ import annotations

import weakref
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from .camera import Camera
from .errors import InputError
from .method_names import DEFAULT_METHOD, POS_METHODS, model_refusal
from .options import DEFAULT_OPTIONS, VerifyOptions
from .pair import PairData
from .pose import Pose, camera_pose, ecef_to_enu, geodetic_to_ecef
from .stage_options import GuidedOptions

if TYPE_CHECKING:
    from .guided import Features
    from .pair_matching import MatchedView
    from .verification import Verification

# The matcher and the methods (numba, SciPy, OpenCV) are imported where a pair is verified:
# a process that only reads a flight and hands its pairs to others does not load them.

__all__ = [
    "FEATURES_KEPT",
    "Flight",
    "FlightImage",
    "FlightPair",
    "RoughPose",
    "pair_data",
    "pair_poses",
]

#: Cameras further apart than this cannot be a pair (and would break the tangent frame).
MAX_BASELINE_M = 1e6


@dataclass(frozen=True)
class RoughPose:
    """An image's rough pose before it is placed in a pair's frame.

    ``R_world_to_cam``: (3, 3) world(ENU)-to-camera rotation. ``position``: (3,) ENU x, y, z
    metres, or WGS84 latitude, longitude (degrees) and ellipsoidal height (metres) when
    ``geodetic``. ``lever_arm`` (3,) body-frame metres with ``R_ned_body`` (3, 3), the platform
    attitude that rotates it into the world (paper Eq. 1), or both None.
    """

    R_world_to_cam: np.ndarray
    position: np.ndarray
    geodetic: bool = False
    lever_arm: np.ndarray | None = None
    R_ned_body: np.ndarray | None = None

    def at(self, enu: np.ndarray) -> Pose:
        """The camera pose with the platform at ``enu`` (3,), ENU metres."""
        return camera_pose(enu, self.R_world_to_cam, self.lever_arm, self.R_ned_body)

    @cached_property
    def ecef(self) -> np.ndarray:
        """(3,) earth-centred position of a ``geodetic`` one, computed once: an image is in
        dozens of pairs, each with its own tangent frame."""
        lat, lon, alt = self.position
        return geodetic_to_ecef(lat, lon, alt)[0]


#: Images whose :attr:`FlightImage.features` a process keeps (16 000 SIFT keypoints: 8 MB each).
FEATURES_KEPT = 32
# id(image) -> (a weak reference to it, its features): an id is reused once its image is gone
_features: OrderedDict[int, tuple[weakref.ref[FlightImage], Features]] = OrderedDict()


@dataclass(frozen=True)
class FlightImage:
    """One image: its camera, rough pose (None: the image has none; its pairs are verified
    only by methods that ignore the poses, and matched by brute force) and, when it carries
    them, its keypoints ((N, 2|4) float64, as :class:`PairData`'s) and their descriptors
    ((N, D) uint8 or float32, one row per keypoint; for pairs that ask for matching)."""

    camera: Camera
    pose: RoughPose | None
    keypoints: np.ndarray | None = None
    descriptors: np.ndarray | None = None

    @property
    def features(self) -> Features:
        """The keypoints with their descriptors as unit rows (:class:`hmcc.guided.Features`),
        kept for the :data:`FEATURES_KEPT` images a process used last: an image is matched in
        many pairs, and its unit rows are float32 (four times SIFT's uint8)."""
        if self.keypoints is None or self.descriptors is None:
            raise InputError("descriptors", "matching needs the image's keypoints and descriptors")
        kept = _features.get(id(self))
        if kept is not None and kept[0]() is self:
            _features.move_to_end(id(self))
            return kept[1]
        from .guided import Features

        features = Features.from_raw(self.keypoints, self.descriptors)
        _features[id(self)] = (weakref.ref(self), features)
        while len(_features) > FEATURES_KEPT:
            _features.popitem(last=False)
        return features


def pair_poses(pose1: RoughPose, pose2: RoughPose) -> tuple[Pose, Pose]:
    """Both cameras in one frame: ENU as given, or the tangent frame at the pair's mean latitude
    and longitude (height 0). Raises :class:`InputError` on ``image2.pose.position`` when the
    images give positions two ways or lie more than 1000 km apart."""
    if pose1.geodetic != pose2.geodetic:
        raise InputError(
            "image2.pose.position",
            "both images must give their position the same way (x/y/z or lat/lon/alt)",
        )
    if pose1.geodetic:
        lat = 0.5 * (float(pose1.position[0]) + float(pose2.position[0]))
        lon = 0.5 * (float(pose1.position[1]) + float(pose2.position[1]))
        enu = ecef_to_enu(np.stack((pose1.ecef, pose2.ecef)), (lat, lon, 0.0))  # one call
        p1, p2 = pose1.at(enu[0]), pose2.at(enu[1])
    else:
        p1, p2 = pose1.at(pose1.position), pose2.at(pose2.position)
    if np.linalg.norm(p1.center - p2.center) > MAX_BASELINE_M:
        raise InputError("image2.pose.position", "the cameras are more than 1000 km apart")
    return p1, p2


def pair_data(
    image1: FlightImage,
    image2: FlightImage,
    matches: np.ndarray,
    *,
    keypoints1: np.ndarray | None = None,
    keypoints2: np.ndarray | None = None,
    plane_z: float | None = None,
    ground_z: float | None = None,
) -> PairData:
    """The pair of two images with its (M, 2) matches; a pair's own keypoints stand in for an
    image that carries none (the caller has checked that one of them is there). An image
    without a pose: both cameras get :data:`~hmcc.pair_matching.PLACEHOLDER_POSE` (for the
    methods that ignore the poses)."""
    kp1 = keypoints1 if keypoints1 is not None else image1.keypoints
    kp2 = keypoints2 if keypoints2 is not None else image2.keypoints
    assert kp1 is not None and kp2 is not None
    if image1.pose is None or image2.pose is None:
        from .pair_matching import PLACEHOLDER_POSE

        pose1 = pose2 = PLACEHOLDER_POSE
    else:
        pose1, pose2 = pair_poses(image1.pose, image2.pose)
    return PairData(
        image1.camera, pose1, image2.camera, pose2, kp1, kp2, matches, plane_z, ground_z
    )


def _view(image: FlightImage, pose: Pose | None) -> MatchedView:
    from .pair_matching import MatchedView

    features = image.features  # InputError without keypoints and descriptors
    assert image.keypoints is not None
    return MatchedView(image.camera, pose, image.keypoints, features)


@dataclass(frozen=True)
class FlightPair:
    """A pair of a flight: the ids of its two images, its (M, 2) integer matches, its own
    keypoints for an image that carries none, and the caller's label ``id``. ``match``: the
    pair asks for matching instead (its images' descriptors; ``matches`` is then (0, 2))."""

    image1: str
    image2: str
    matches: np.ndarray
    keypoints1: np.ndarray | None = None
    keypoints2: np.ndarray | None = None
    id: str | None = None
    match: bool = False


@dataclass(frozen=True)
class Flight:
    """Pairs of images to verify with one method and its options; ``plane_z`` / ``ground_z``
    as in :class:`PairData` (both None: estimated per pair); ``match_options`` for the pairs
    that ask for matching."""

    images: Mapping[str, FlightImage]
    pairs: Sequence[FlightPair]
    method: str = DEFAULT_METHOD
    options: VerifyOptions = field(default=DEFAULT_OPTIONS)
    plane_z: float | None = None
    ground_z: float | None = None
    match_options: GuidedOptions = field(default=GuidedOptions())

    def __post_init__(self) -> None:
        """A method that fits one model only refuses another at once, not pair by pair."""
        refused = model_refusal(self.method, self.options.ransac.model)
        if refused is not None:
            raise InputError("params.ransac.model", refused)

    def pair_data(self, index: int) -> PairData:
        """Pair ``index`` as arrays; raises :class:`InputError` when its poses do not fit (or
        an image has none and the method uses them)."""
        p = self.pairs[index]
        self._check_posed(index)
        return pair_data(
            self.images[p.image1],
            self.images[p.image2],
            p.matches,
            keypoints1=p.keypoints1,
            keypoints2=p.keypoints2,
            plane_z=self.plane_z,
            ground_z=self.ground_z,
        )

    def verify(self, index: int) -> Verification:
        """Verify pair ``index`` (match it first if it asks for matching: the result then
        holds the matches); raises :class:`InputError` for input it cannot use."""
        from .pair_matching import PLACEHOLDER_POSE, match_and_verify
        from .verification import verify

        p = self.pairs[index]
        if not p.match:
            return verify(self.pair_data(index), self.method, self.options)
        self._check_posed(index)
        image1, image2 = self.images[p.image1], self.images[p.image2]
        pose1: Pose | None
        pose2: Pose | None
        if image1.pose is not None and image2.pose is not None:
            pose1, pose2 = pair_poses(image1.pose, image2.pose)
        else:  # brute force: None says which image has no pose, the other's is not used
            pose1 = None if image1.pose is None else PLACEHOLDER_POSE
            pose2 = None if image2.pose is None else PLACEHOLDER_POSE
        return match_and_verify(
            _view(image1, pose1),
            _view(image2, pose2),
            self.method,
            self.options,
            self.match_options,
            plane_z=self.plane_z,
            ground_z=self.ground_z,
        )

    def _check_posed(self, index: int) -> None:
        if self.method not in POS_METHODS:
            return
        p = self.pairs[index]
        for side, name in ((1, p.image1), (2, p.image2)):
            if self.images[name].pose is None:
                raise InputError(
                    f"image{side}.pose",
                    f"method {self.method!r} uses the rough poses; this image has none",
                )

    def subset(self, indices: Sequence[int]) -> Flight:
        """The flight of pairs ``indices`` (in that order) and only the images they name."""
        pairs = [self.pairs[i] for i in indices]
        names = {p.image1 for p in pairs} | {p.image2 for p in pairs}
        return Flight(
            {name: self.images[name] for name in names},
            pairs,
            self.method,
            self.options,
            self.plane_z,
            self.ground_z,
            self.match_options,
        )
