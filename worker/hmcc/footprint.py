"""Image footprints on the ground plane from the rough POS, and the pairs worth matching.

The paper's experiments choose the pairs to match from the rough POS: "one image pair would be
preserved only if the dimension of overlap exceeds half of the footprint size" (section 4.5, after
Jiang and Jiang, 2017a). Unlike a distance between camera centres (COLMAP's spatial matcher),
a footprint follows the view: an oblique camera sees the ground far ahead of its centre, and a
camera flown higher sees more of it.

* **Footprint**: the image's border, sampled, back-projected onto the plane Z = Z0 with the
  core's own ray-plane intersection (:func:`hmcc.projection.project_to_plane`, distortion
  included). A border ray that misses the plane (above the horizon) or meets it further than
  ``max_range_ratio`` x the camera's height above the plane is clipped at that range, along
  its own horizontal direction; the footprint is the convex hull of those points. For a
  pinhole camera whose rays all reach the plane this is exactly the image of the frame, a
  convex quadrilateral (a trapezoid for an oblique); clipped, the far edge follows the range
  circle.
* **Overlap**: the area of the two footprints' intersection divided by the area of the
  *smaller* one. The paper speaks of "half of the footprint size", one footprint; the smaller
  is the reading that keeps a nadir image whose footprint lies inside an oblique's (what
  oblique flights need), and it is the definition the shared fixtures' ``footprint_overlap``
  uses.
* **Intersection**: Sutherland-Hodgman clipping of one convex polygon by another. Footprints
  are convex by construction (a hull), so the clip is exact; it needs no library (shapely's
  general polygons would be an optional dependency for what a dozen lines do on 4-10
  vertices, about 20 us a pair).
* **Candidates**: a k-d tree (SciPy's ``cKDTree``) of the footprints' centroids; two
  footprints can only meet when their centroids are closer than the sum of their radii (the
  furthest vertex from the centroid), so only those pairs are clipped, not all n^2.

Everything is ENU metres (x east, y north); polygons are (K, 2) float64, counter-clockwise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from annotated_types import Ge, Gt
from scipy.spatial import cKDTree

from .bounds import PYDANTIC_CONFIG, check_fields
from .camera import Camera
from .pose import Pose
from .projection import project_to_plane, world_rays

__all__ = [
    "FootprintOptions",
    "PairOverlap",
    "clip_convex",
    "footprint",
    "overlap_fraction",
    "polygon_area",
    "select_pairs",
]

_EMPTY = np.zeros((0, 2))


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

    max_range_ratio: Annotated[float, Gt(0)] = 5.0
    border_samples: Annotated[int, Ge(2)] = 8

    def __post_init__(self) -> None:
        check_fields(self)


def _border_pixels(camera: Camera, samples: int) -> np.ndarray:
    """(4 * (samples - 1), 2) pixels around the frame's outer edge (pixel centres at
    integers, so the frame spans -0.5 .. width - 0.5), clockwise from the top-left corner."""
    x0, y0, x1, y1 = -0.5, -0.5, camera.width - 0.5, camera.height - 0.5
    t = np.linspace(0.0, 1.0, samples)[:-1]
    top = np.column_stack((x0 + t * (x1 - x0), np.full_like(t, y0)))
    right = np.column_stack((np.full_like(t, x1), y0 + t * (y1 - y0)))
    bottom = np.column_stack((x1 - t * (x1 - x0), np.full_like(t, y1)))
    left = np.column_stack((np.full_like(t, x0), y1 - t * (y1 - y0)))
    return np.vstack((top, right, bottom, left))


def footprint(
    camera: Camera, pose: Pose, z0: float, options: FootprintOptions = FootprintOptions()
) -> np.ndarray:
    """The image's footprint on the plane Z = ``z0`` (ENU metres): a (K, 2) convex polygon,
    counter-clockwise. Raises ``ValueError`` when the camera is not above the plane."""
    height = float(pose.center[2]) - float(z0)
    if not height > 0.0:
        raise ValueError(f"the camera ({pose.center[2]:g} m) is not above the plane ({z0:g} m)")
    pixels = _border_pixels(camera, options.border_samples)
    points, valid = project_to_plane(camera, pose, pixels, z0)
    centre = np.asarray(pose.center[:2], dtype=np.float64)
    max_range = options.max_range_ratio * height
    far = ~valid | (np.hypot(*(points - centre).T) > max_range)
    if far.any():
        horizontal = world_rays(camera, pose, pixels[far])[:, :2]
        norm = np.hypot(*horizontal.T)
        keep = norm > 1e-12  # a ray straight up has no direction to clip along
        clipped = centre + max_range * horizontal[keep] / norm[keep, None]
        points = np.vstack((points[~far], clipped))
    return _convex_hull(points)


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Andrew's monotone chain: the (K, 2) hull, counter-clockwise, collinear points dropped."""
    pts = np.unique(np.asarray(points, dtype=np.float64), axis=0)  # sorted by x, then y
    if len(pts) < 3:
        return pts

    def half(seq: np.ndarray) -> list[np.ndarray]:
        chain: list[np.ndarray] = []
        for p in seq:
            while len(chain) >= 2 and _turns_right_or_straight(chain[-2], chain[-1], p):
                chain.pop()
            chain.append(p)
        return chain

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _turns_right_or_straight(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """o -> a -> b is no left turn: clockwise, or collinear to rounding (sampled points of a
    straight edge projected through a rotation are collinear to ~1e-14 of their spread)."""
    oa, ob = a - o, b - o
    cross = oa[0] * ob[1] - oa[1] * ob[0]
    return bool(cross <= 1e-9 * np.hypot(*oa) * np.hypot(*ob))


def polygon_area(polygon: np.ndarray) -> float:
    """Area (m^2) of a simple (K, 2) polygon, positive when counter-clockwise (shoelace)."""
    if len(polygon) < 3:
        return 0.0
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: the part of the (K, 2) polygon ``subject`` inside the convex,
    counter-clockwise (M, 2) polygon ``clip``; (0, 2) when they do not meet. With a convex
    subject the result is their convex intersection."""
    out = np.asarray(subject, dtype=np.float64)
    for k in range(len(clip)):
        if len(out) == 0:
            return _EMPTY
        a, b = clip[k], clip[(k + 1) % len(clip)]
        edge = b - a
        # > 0 inside (left of the edge a -> b), for every vertex at once
        side = edge[0] * (out[:, 1] - a[1]) - edge[1] * (out[:, 0] - a[0])
        kept: list[np.ndarray] = []
        for i in range(len(out)):
            p, q = out[i], out[(i + 1) % len(out)]
            sp, sq = side[i], side[(i + 1) % len(out)]
            if sp >= 0.0:
                kept.append(p)
            if (sp >= 0.0) != (sq >= 0.0):
                kept.append(p + (q - p) * (sp / (sp - sq)))
        out = np.array(kept) if kept else _EMPTY
    return out


def overlap_fraction(a: np.ndarray, b: np.ndarray) -> float:
    """The area of the intersection of the convex footprints ``a`` and ``b`` divided by the
    area of the smaller one, in [0, 1] (see the module's note)."""
    smaller = min(polygon_area(a), polygon_area(b))
    if not smaller > 0.0:
        return 0.0
    return min(1.0, max(0.0, polygon_area(clip_convex(a, b)) / smaller))


@dataclass(frozen=True)
class PairOverlap:
    """A chosen pair: indices ``i < j`` into the footprints and their overlap fraction."""

    i: int
    j: int
    overlap: float


def select_pairs(
    footprints: Sequence[np.ndarray],
    min_overlap: float = 0.5,
    max_per_image: int | None = None,
) -> list[PairOverlap]:
    """The pairs whose footprints overlap by more than ``min_overlap`` (fraction of the
    smaller; the paper's 0.5), sorted by ``(i, j)``.

    ``max_per_image`` keeps, of each image's pairs, those with its ``K`` largest overlaps; a
    pair stays when either image keeps it (COLMAP's spatial matcher bounds its neighbours the
    same way). Empty footprints (no area) take part in no pair.
    """
    if not 0.0 <= min_overlap <= 1.0:
        raise ValueError(f"min_overlap: {min_overlap:g} is not in [0, 1]")
    if max_per_image is not None and max_per_image < 1:
        raise ValueError(f"max_per_image: {max_per_image} is not at least 1")
    usable = [k for k, f in enumerate(footprints) if polygon_area(f) > 0.0]
    if len(usable) < 2:
        return []
    centres = np.array([footprints[k].mean(axis=0) for k in usable])
    radii = np.array(
        [np.hypot(*(footprints[k] - c).T).max() for k, c in zip(usable, centres, strict=True)]
    )
    tree = cKDTree(centres)
    reach = radii.max()
    found: list[PairOverlap] = []
    for a, near in enumerate(tree.query_ball_point(centres, radii + reach)):
        for b in near:
            if b <= a or np.hypot(*(centres[a] - centres[b])) > radii[a] + radii[b]:
                continue
            i, j = usable[a], usable[b]
            overlap = overlap_fraction(footprints[i], footprints[j])
            if overlap > min_overlap:
                found.append(PairOverlap(i, j, overlap))
    if max_per_image is not None:
        found = _best_per_image(found, max_per_image)
    return sorted(found, key=lambda p: (p.i, p.j))


def _best_per_image(pairs: list[PairOverlap], k: int) -> list[PairOverlap]:
    """The pairs among the ``k`` largest overlaps of either of their images."""
    by_image: dict[int, list[PairOverlap]] = {}
    for p in pairs:
        by_image.setdefault(p.i, []).append(p)
        by_image.setdefault(p.j, []).append(p)
    kept: set[tuple[int, int]] = set()
    for own in by_image.values():
        for p in sorted(own, key=lambda p: -p.overlap)[:k]:
            kept.add((p.i, p.j))
    return [p for p in pairs if (p.i, p.j) in kept]
