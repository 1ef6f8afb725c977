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
* **Partners** (``min_partners``): an image whose footprint overlaps few others by more
  than ``min_overlap`` (at a block's edge or corner, after a turn, where the overlap was
  planned thin) is what the rule cuts off first. It keeps its ``min_partners`` largest
  overlaps whatever their fraction (above zero), so every image takes part in at least that
  many pairs where its footprint meets that many others.
* **A flight** (:func:`flight_pairs`): the images' rough poses placed in one ENU frame (as
  given, or the tangent frame at their mean latitude and longitude, height 0, as a pair's),
  their footprints on the ground (one height, or each camera's flying height below it), and
  the pairs by name.

Everything is ENU metres (x east, y north); polygons are (K, 2) float64, counter-clockwise.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

from .camera import Camera
from .errors import InputError
from .flight import RoughPose
from .jit import compiled
from .pose import Pose, geodetic_to_enu
from .projection import project_to_plane, world_rays
from .stage_options import FootprintOptions, PairOptions

__all__ = [
    "FlightPairs",
    "FootprintOptions",
    "PairOptions",
    "PairOverlap",
    "clip_convex",
    "flight_pairs",
    "footprint",
    "overlap_fraction",
    "place_poses",
    "polygon_area",
    "select_pairs",
]

_EMPTY = np.zeros((0, 2))


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
    """The (K, 2) convex hull, counter-clockwise, collinear points dropped (Qhull, through
    SciPy: a sampled edge along north or east projects to x or y values equal but for
    rounding, which a hand-written monotone chain with a collinearity tolerance got wrong).
    Points on one line have no hull: their two ends."""
    pts = np.unique(np.asarray(points, dtype=np.float64), axis=0)
    if len(pts) < 3:
        return pts
    try:
        hull = ConvexHull(pts)
    except QhullError:  # all on one line (or one point): no area
        return pts[[0, -1]]
    return pts[hull.vertices]  # counter-clockwise in 2-D


# Polygons of a few vertices are handled as lists of (x, y) floats: numpy's per-call cost
# on 4-10 vertices is most of the work (about 30x slower than these loops).
_Points = list[tuple[float, float]]


def _rows(polygon: np.ndarray) -> _Points:
    return [(x, y) for x, y in np.asarray(polygon, dtype=np.float64).reshape(-1, 2).tolist()]


def _area(pts: _Points) -> float:
    n = len(pts)
    if n < 3:
        return 0.0
    total = 0.0
    for k in range(n):
        (x0, y0), (x1, y1) = pts[k], pts[(k + 1) % n]
        total += x0 * y1 - x1 * y0
    return 0.5 * total


def _clip(subject: _Points, clip: _Points) -> _Points:
    out = subject
    n = len(clip)
    for k in range(n):
        if not out:
            return []
        (ax, ay), (bx, by) = clip[k], clip[(k + 1) % n]
        ex, ey = bx - ax, by - ay
        # > 0 inside (left of the edge a -> b)
        side = [ex * (y - ay) - ey * (x - ax) for x, y in out]
        kept: _Points = []
        m = len(out)
        for i in range(m):
            j = (i + 1) % m
            sp, sq = side[i], side[j]
            if sp >= 0.0:
                kept.append(out[i])
            if (sp >= 0.0) != (sq >= 0.0):
                (px, py), (qx, qy) = out[i], out[j]
                t = sp / (sp - sq)
                kept.append((px + (qx - px) * t, py + (qy - py) * t))
        out = kept
    return out


def _overlap(a: _Points, b: _Points, area_a: float, area_b: float) -> float:
    smaller = min(area_a, area_b)
    if not smaller > 0.0:
        return 0.0
    return min(1.0, max(0.0, _area(_clip(a, b)) / smaller))


@compiled
def _clipped_area(
    ax: np.ndarray, ay: np.ndarray, bx: np.ndarray, by: np.ndarray, work: np.ndarray
) -> float:
    """:func:`_clip` then :func:`_area`, compiled: the area of the convex polygon (``ax``,
    ``ay``) clipped by the convex, counter-clockwise (``bx``, ``by``); ``work`` (4, >= 2 +
    len(ax) + len(bx)) scratch."""
    m = len(ax)
    for k in range(m):
        work[0, k], work[1, k] = ax[k], ay[k]
    nb = len(bx)
    for e in range(nb):
        if m == 0:
            return 0.0
        x0, y0 = bx[e], by[e]
        nxt = e + 1 if e + 1 < nb else 0
        ex, ey = bx[nxt] - x0, by[nxt] - y0
        c = 0
        for i in range(m):
            j = i + 1 if i + 1 < m else 0
            px, py, qx, qy = work[0, i], work[1, i], work[0, j], work[1, j]
            sp = ex * (py - y0) - ey * (px - x0)
            sq = ex * (qy - y0) - ey * (qx - x0)
            if sp >= 0.0:
                work[2, c], work[3, c] = px, py
                c += 1
            if (sp >= 0.0) != (sq >= 0.0):
                t = sp / (sp - sq)
                work[2, c], work[3, c] = px + (qx - px) * t, py + (qy - py) * t
                c += 1
        for i in range(c):
            work[0, i], work[1, i] = work[2, i], work[3, i]
        m = c
    total = 0.0
    for k in range(m):
        j = k + 1 if k + 1 < m else 0
        total += work[0, k] * work[1, j] - work[0, j] * work[1, k]
    return 0.5 * total


@compiled
def _overlaps(
    xy: np.ndarray, starts: np.ndarray, areas: np.ndarray, first: np.ndarray, second: np.ndarray
) -> np.ndarray:
    """The overlap fraction of each candidate pair (``first[k]``, ``second[k]``): polygon p's
    vertices are ``xy[starts[p]:starts[p + 1]]``."""
    out = np.zeros(len(first))
    longest = 0
    for p in range(len(starts) - 1):
        longest = max(longest, starts[p + 1] - starts[p])
    work = np.empty((4, 2 * longest + 4))
    for k in range(len(first)):
        i, j = first[k], second[k]
        smaller = min(areas[i], areas[j])
        if not smaller > 0.0:
            continue
        a = xy[starts[i] : starts[i + 1]]
        b = xy[starts[j] : starts[j + 1]]
        area = _clipped_area(a[:, 0], a[:, 1], b[:, 0], b[:, 1], work)
        out[k] = min(1.0, max(0.0, area / smaller))
    return out


def polygon_area(polygon: np.ndarray) -> float:
    """Area (m^2) of a simple (K, 2) polygon, positive when counter-clockwise (shoelace)."""
    return _area(_rows(polygon))


def clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: the part of the (K, 2) polygon ``subject`` inside the convex,
    counter-clockwise (M, 2) polygon ``clip``; (0, 2) when they do not meet. With a convex
    subject the result is their convex intersection."""
    out = _clip(_rows(subject), _rows(clip))
    return np.array(out, dtype=np.float64) if out else _EMPTY


def overlap_fraction(a: np.ndarray, b: np.ndarray) -> float:
    """The area of the intersection of the convex footprints ``a`` and ``b`` divided by the
    area of the smaller one, in [0, 1] (see the module's note)."""
    pa, pb = _rows(a), _rows(b)
    return _overlap(pa, pb, _area(pa), _area(pb))


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
    min_partners: int = 0,
    *,
    max_candidates: int | None = None,
) -> list[PairOverlap]:
    """The pairs whose footprints overlap by more than ``min_overlap`` (fraction of the
    smaller; the paper's 0.5), sorted by ``(i, j)``.

    ``max_per_image`` keeps, of each image's pairs, those with its ``K`` largest overlaps; a
    pair stays when either image keeps it (COLMAP's spatial matcher bounds its neighbours the
    same way). ``min_partners`` then adds, for each image, its ``min_partners`` largest
    overlaps above zero, whatever ``min_overlap`` says (see the module's note). Empty
    footprints (no area) take part in no pair.

    ``max_candidates`` bounds the work (a few tens of microseconds a candidate): a
    ``ValueError`` before any is clipped when the footprints' circles meet in more pairs
    than that (counted from above: every pair within the largest radius of one).
    """
    if not 0.0 <= min_overlap <= 1.0:
        raise ValueError(f"min_overlap: {min_overlap:g} is not in [0, 1]")
    if max_per_image is not None and max_per_image < 1:
        raise ValueError(f"max_per_image: {max_per_image} is not at least 1")
    if min_partners < 0:
        raise ValueError(f"min_partners: {min_partners} is below 0")
    rows = [_rows(f) for f in footprints]
    areas = [_area(r) for r in rows]
    usable = [k for k, a in enumerate(areas) if a > 0.0]
    if len(usable) < 2:
        return []
    below: list[PairOverlap] = []
    centres = np.array([footprints[k].mean(axis=0) for k in usable])
    radii = np.array(
        [np.hypot(*(footprints[k] - c).T).max() for k, c in zip(usable, centres, strict=True)]
    )
    tree = cKDTree(centres)
    reach = radii.max()
    if max_candidates is not None:
        near_counts = tree.query_ball_point(centres, radii + reach, return_length=True)
        candidates = (int(np.sum(near_counts)) - len(usable)) // 2
        if candidates > max_candidates:
            raise ValueError(
                f"the footprints of {len(usable)} images meet in up to {candidates} pairs, "
                f"more than the {max_candidates} one call examines"
            )
    near = tree.query_ball_point(centres, radii + reach)
    lengths = np.fromiter((len(n) for n in near), dtype=np.int64, count=len(near))
    a = np.repeat(np.arange(len(near)), lengths)
    b = np.concatenate([np.asarray(n, dtype=np.int64) for n in near])
    keep = (b > a) & (np.hypot(*(centres[a] - centres[b]).T) <= radii[a] + radii[b])
    a, b = a[keep], b[keep]
    order = np.lexsort((b, a))
    a, b = a[order], b[order]
    index = np.asarray(usable, dtype=np.int64)
    vertices = [footprints[k] for k in usable]
    starts = np.concatenate(([0], np.cumsum([len(v) for v in vertices]))).astype(np.int64)
    xy = np.ascontiguousarray(np.vstack(vertices), dtype=np.float64)
    overlaps = _overlaps(xy, starts, np.asarray(areas)[index], a, b)
    above = overlaps > min_overlap
    found = [
        PairOverlap(i, j, o)
        for i, j, o in zip(
            index[a[above]].tolist(),
            index[b[above]].tolist(),
            overlaps[above].tolist(),
            strict=True,
        )
    ]
    if min_partners:
        some = ~above & (overlaps > 0.0)
        below = [
            PairOverlap(i, j, o)
            for i, j, o in zip(
                index[a[some]].tolist(),
                index[b[some]].tolist(),
                overlaps[some].tolist(),
                strict=True,
            )
        ]
    if max_per_image is not None:
        found = _best_per_image(found, max_per_image)
    if min_partners:
        found += _partners(found, below, min_partners)
    return sorted(found, key=lambda p: (p.i, p.j))


def _partners(kept: list[PairOverlap], below: list[PairOverlap], k: int) -> list[PairOverlap]:
    """Of the pairs ``below`` the overlap rule, those among the ``k`` largest overlaps of
    either of their images, all pairs (``kept`` and these) counted: an image with ``k``
    partners already gains none."""
    by_image: dict[int, list[PairOverlap]] = {}
    for p in (*kept, *below):
        by_image.setdefault(p.i, []).append(p)
        by_image.setdefault(p.j, []).append(p)
    best: set[tuple[int, int]] = set()
    for own in by_image.values():
        for p in sorted(own, key=lambda p: -p.overlap)[:k]:
            best.add((p.i, p.j))
    return [p for p in below if (p.i, p.j) in best]


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


@dataclass(frozen=True)
class FlightPairs:
    """The chosen ``pairs`` ``(name1, name2, overlap)``, names in the order the images were
    given, sorted by it; every image's ``footprints`` ((K, 2) ENU metres, in the frame of
    :func:`place_poses`)."""

    pairs: list[tuple[str, str, float]]
    footprints: dict[str, np.ndarray]


def place_poses(poses: Mapping[str, RoughPose]) -> dict[str, Pose]:
    """Every camera's pose in one ENU frame: positions as given (local metres), or WGS84
    positions in the tangent frame at their mean latitude and longitude, height 0 (ENU z is
    then the height, less the earth's curvature drop: a few metres 10 km out). Raises
    :class:`InputError` on ``images.<name>.pose.position`` for the first image that gives its
    position the other way."""
    names = list(poses)
    if not names:
        return {}
    geodetic = poses[names[0]].geodetic
    for name in names:
        if poses[name].geodetic != geodetic:
            raise InputError(
                f"images.{name}.pose.position",
                "every image must give its position the same way (x/y/z or lat/lon/alt)",
            )
    xyz = np.array([poses[n].position for n in names], dtype=np.float64)
    if geodetic:
        origin = (float(xyz[:, 0].mean()), float(xyz[:, 1].mean()), 0.0)
        xyz = geodetic_to_enu(xyz[:, 0], xyz[:, 1], xyz[:, 2], origin)
    return {n: poses[n].at(p) for n, p in zip(names, xyz, strict=True)}


def flight_pairs(
    cameras: Mapping[str, Camera],
    poses: Mapping[str, RoughPose],
    *,
    ground_z: float | None = None,
    flying_height: float | None = None,
    options: PairOptions = PairOptions(),
    max_candidates: int | None = None,
) -> FlightPairs:
    """The pairs of a flight worth matching: every image's footprint on the ground, then
    :func:`select_pairs`. The ground is ``ground_z`` (ENU metres, on the positions' height
    scale: ellipsoidal for WGS84 positions) or, for heights that drift or follow the
    terrain, ``flying_height`` metres below each camera; exactly one of the two.

    ``cameras`` and ``poses`` have the same names. Raises :class:`InputError`
    (``images.<name>.pose.position``) for positions given two ways or a camera not above
    the ground, or (on ``images``) footprints that meet in more than ``max_candidates``
    pairs (:func:`select_pairs`); ``ValueError`` for a bad combination of arguments."""
    if (ground_z is None) == (flying_height is None):
        raise ValueError("give ground_z or flying_height, exactly one")
    if flying_height is not None and not flying_height > 0.0:
        raise ValueError(f"flying_height: {flying_height:g} is not above 0")
    if set(cameras) != set(poses):
        raise ValueError("cameras and poses must name the same images")
    placed = place_poses(poses)
    names = list(placed)
    drop = 0.0 if flying_height is None else float(flying_height)
    prints = {}
    for name in names:
        pose = placed[name]
        z0 = float(pose.center[2]) - drop if ground_z is None else float(ground_z)
        try:
            prints[name] = footprint(cameras[name], pose, z0, options.footprint)
        except ValueError as e:
            raise InputError(
                f"images.{name}.pose.position", f"{e}: it must be above the ground"
            ) from None
    try:
        chosen = select_pairs(
            [prints[n] for n in names],
            options.min_overlap,
            options.max_per_image,
            options.min_partners,
            max_candidates=max_candidates,
        )
    except ValueError as e:
        raise InputError("images", str(e)) from None
    return FlightPairs([(names[p.i], names[p.j], p.overlap) for p in chosen], prints)
