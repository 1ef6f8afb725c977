"""A pair that asks for matching instead of bringing matches: its images' descriptors matched
guided by the rough poses (:mod:`hmcc.guided`), then the matches found verified by the flight's
method. The result (:class:`hmcc.verification.Verification`) holds the matches, the inliers
among them and the matcher's figures (``matching``).

**The ground.** The prediction needs the ground's height Z0 (metres, in the poses' frame):
the pair's ``ground_z`` when given, else its ``plane_z`` (the plane the caller chose; the first
pass absorbs a plane off by ``GuidedOptions.ground_error_fraction`` of the flying height).

**No usable pose.** A pair with an image without a pose, or whose cameras are not both above
the ground (Z0 at or above a camera's height: a position in another datum than the ground's,
or none known), cannot predict anything: it is matched by brute force (the same rules over all
keypoints), its ``matching`` figures saying ``mode: brute-force`` and why
(``pose_unusable``). Such a pair is verified with :data:`PLACEHOLDER_POSE` for both cameras
when an image has no pose (the methods that use the poses refuse it). Poses that are there
but do not fit the images follow :class:`hmcc.guided.GuidedOptions` (the turns searched, then no
matches or, with ``brute_force_on_mismatch``, brute force).

**Too few matches to verify** (fewer than the method's model needs: a pair that does not
overlap, say): the pair still finishes, with its matches, no inliers and no model.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from .camera import Camera
from .errors import InputError
from .guided import Features, GuidedOptions, MatchResult, match_brute_force, match_guided
from .options import VerifyOptions
from .pair import PairData
from .pose import Pose
from .verification import Verification, unverified, verify

__all__ = ["PLACEHOLDER_POSE", "MatchedView", "ground_height", "match_and_verify", "match_views"]

#: The cameras' pose in a pair with an image without one: nadir at the origin, for the methods
#: that ignore the poses (those that use them refuse such a pair).
PLACEHOLDER_POSE = Pose(np.diag([1.0, -1.0, -1.0]), np.zeros(3))


@dataclass(frozen=True)
class MatchedView:
    """One image of a pair to match: its camera, its rough pose in the pair's frame (ENU
    metres; None: the image has none), its keypoints as given ((N, 2|4) float64 pixels, for
    the verification) and its :class:`~hmcc.guided.Features` (the same keypoints,
    descriptors as unit rows)."""

    camera: Camera
    pose: Pose | None
    keypoints: np.ndarray
    features: Features


def ground_height(plane_z: float | None, ground_z: float | None) -> float | None:
    """Z0 for the prediction: ``ground_z``, else ``plane_z``, else None (not known)."""
    return ground_z if ground_z is not None else plane_z


def _pose_unusable(pose1: Pose | None, pose2: Pose | None, z0: float | None) -> str | None:
    """Why the poses cannot predict matches (None: they can)."""
    for name, pose in (("image1", pose1), ("image2", pose2)):
        if pose is None:
            return f"{name} has no pose"
    if z0 is None:
        return "no ground height (plane.ground_z or plane.z)"
    for name, pose in (("image1", pose1), ("image2", pose2)):
        assert pose is not None
        if not pose.center[2] > z0:
            return f"{name}'s camera is not above the ground (z {pose.center[2]:g} <= {z0:g})"
    return None


def match_views(
    view1: MatchedView, view2: MatchedView, z0: float | None, options: GuidedOptions
) -> MatchResult:
    """Image 1's features matched to image 2's: guided by the poses, or by brute force where
    they cannot predict (``stats["pose_unusable"]`` says why)."""
    reason = _pose_unusable(view1.pose, view2.pose, z0)
    if reason is None:
        assert z0 is not None and view1.pose is not None and view2.pose is not None
        return match_guided(
            view1.camera,
            view1.pose,
            view1.features,
            view2.camera,
            view2.pose,
            view2.features,
            z0,
            options,
        )
    found = match_brute_force(view1.features, view2.features, options)
    found.stats["pose_unusable"] = reason
    return found


def match_and_verify(
    view1: MatchedView,
    view2: MatchedView,
    method: str,
    options: VerifyOptions,
    match_options: GuidedOptions,
    *,
    plane_z: float | None = None,
    ground_z: float | None = None,
) -> Verification:
    """Match the pair (:func:`match_views`), verify the matches with ``method``; the
    verification with ``matches`` (M, 2) int64 and ``matching`` (the matcher's figures and,
    under ``params``, its options). Raises :class:`InputError` for input it cannot use
    (other than too few matches, which give a result without inliers)."""
    if view1.features.descriptors.shape[1] != view2.features.descriptors.shape[1]:
        raise InputError(
            "descriptors",
            f"the images' descriptors differ in length ({view1.features.descriptors.shape[1]} "
            f"and {view2.features.descriptors.shape[1]})",
        )
    found = match_views(view1, view2, ground_height(plane_z, ground_z), match_options)
    posed = view1.pose is not None and view2.pose is not None
    pair = PairData(
        view1.camera,
        view1.pose if posed and view1.pose is not None else PLACEHOLDER_POSE,
        view2.camera,
        view2.pose if posed and view2.pose is not None else PLACEHOLDER_POSE,
        view1.keypoints,
        view2.keypoints,
        found.matches,
        plane_z,
        ground_z,
    )
    try:
        verification = verify(pair, method, options)
    except InputError as e:
        if e.field != "matches":
            raise
        verification = unverified(method, options, len(found.matches), e.reason)
    matching: dict[str, Any] = dict(found.stats)
    matching["params"] = _echo(match_options)
    return dataclasses.replace(verification, matches=found.matches, matching=matching)


def _echo(options: GuidedOptions) -> dict[str, Any]:
    return dataclasses.asdict(options)
