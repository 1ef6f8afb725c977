"""Match the features of a COLMAP database guided by the rough POS (``hmcc match``).

COLMAP's matching compares every keypoint of an image with every keypoint of the other; with
both cameras' rough poses a keypoint of image 1 has a predicted position in image 2 (its ray to
the ground, seen from camera 2) and is compared only with the keypoints near it
(:mod:`hmcc.guided`: the prediction, the radii, the two passes and the rules). This module is
the database side: it reads and checks everything first (database, cameras, pairs, poses, the
ground's height; a :class:`ColmapInputError` leaves the file untouched), reads each image's
keypoints and SIFT descriptors once and hands them to the children through one file per
image, matches the pairs on a process pool, and writes the matches into the database (one
transaction per batch), so ``hmcc colmap`` (verification) and COLMAP's mapper go on as after
COLMAP's own matching.

Pairs: a pairs file (``name1 name2`` a line), else every pair of the database's images (as
COLMAP's exhaustive matcher). A pair that has matches is skipped unless ``overwrite``.
Two rounds: first each image's anchor pairs (its :data:`ANCHOR_PAIRS` pairs of most
predicted footprint overlap), where the cameras' turns about their optical axes are searched
when the poses as given do not fit; then every other pair with each image's turn as its
anchors found it (searched again only for an image whose anchors found nothing). An image
whose attitude the flight track gave has its yaw corrected between the rounds (below). A pair with
an image without a usable pose is matched by brute force (the same rules over all keypoints),
counted in the report. A pair matched with an image turned about its optical axis
(:mod:`hmcc.guided`'s ``guided-turned``) counts for that image in the report's
``images[name].turned_deg`` (turn -> pairs): an image turned after capture, or a mounting
that is not the tags', shows there in most of its pairs.

The cameras are the database's, but for their focal length where the images' EXIF (read with
``--images``, as ``hmcc pairs`` reads it: :mod:`.capture`) disagrees with it by more than
:data:`~hmcc_colmap.capture.FOCAL_DISAGREEMENT` (a factor): COLMAP's prior focal length of
a downscaled image whose EXIF still describes the original (its focal-plane resolution) is
off by the downscaling factor, and predictions with it miss by hundreds of pixels. Reported
per image (``images[name].focal_px``, ``focal_source``); ``exif_focal`` off keeps the
database's.

An image with a position and no attitude (a camera with a GPS tag and nothing else) gets one
estimated from the flight track (nadir, image top along the direction of travel:
:mod:`.track`, as ``hmcc colmap`` and ``hmcc pairs`` do) unless ``track_attitude`` is off;
counted in the report (``images_attitude_estimated``, ``images[name].attitude``). Such a
heading can be tens of degrees off, by a different amount in every image (where a strip
turns, or a camera that swings), so such an image's yaw is corrected once, from its
:data:`ANCHOR_PAIRS_ESTIMATED` anchor pairs: those are matched first (the poses as given,
the rotation search: :mod:`hmcc.guided`'s ``guided-rotated``, the rotation from the
keypoints' orientations, which finds any angle; the quarter turns where the keypoints have
no orientations), each one's matches
give both cameras' yaw corrections (:func:`hmcc.yaw.fit_pair_yaws`), and one solve over the
images gives each image's (:func:`hmcc.yaw.solve_yaw_corrections`; reported as
``images[name].yaw_correction_deg`` and ``totals.images_yaw_corrected``); with those, the
same matches give the images' position corrections (a GPS fix metres off, or recorded late:
:func:`hmcc.yaw.solve_position_corrections`; ``images[name].position_correction_m``, east and
north, and ``totals.images_position_corrected``). Every other pair
with such an image, and its anchors again, is then matched with the corrected poses and
nothing searched (``guided-corrected``; ``no-overlap`` where the corrected footprints do not
meet, without a descriptor compared); an anchor keeps whichever of its two results has more
matches. A pair with an image whose anchors gave no correction (nothing matched: a wrong
position) is searched as before: the turns, then the rotation. A pair of measured attitudes
never gets the rotation search (a measured attitude is off by a quarter turn or not at all,
and the search costs a sampled brute force); a pair that fits nothing is
``pose-mismatch-unmatched``.

The ground's height Z0 (metres, on the scale of the positions' altitudes), in this order:
``ground_z``; the median camera altitude minus ``height_m``; the median of each image's
altitude minus its height above the take-off point (DJI's ``RelativeAltitude``: a flat site's
ground). With ``flying_height_m`` instead, the altitudes are not used: each pair's cameras
are taken that high above a flat ground below them (as ``hmcc pairs --flying-height``): for
GPS altitudes that drift (a GPS-only camera's altitude can climb by a hundred metres over a
flight at one height), which would otherwise scale one image's predictions against the
other's. The first pass absorbs a ground off by ``GuidedOptions.ground_error_fraction`` of
the flying height (a shift of every prediction alike).

With ``MatchOptions.verify`` (``hmcc match --verify``) each pair is verified in the child
that matched it, its matches still in memory, as ``hmcc colmap`` verifies it
(:class:`~hmcc_colmap.verify.PairVerifier`: the method, or its fallback for an image without
a usable pose, and the relative pose beside); then a :class:`~hmcc_colmap.verify.ColmapRun`
takes those results in (nothing verified again) and writes the two-view geometries exactly
as ``hmcc colmap`` does, so COLMAP's mapper goes on at once; pairs matched before and not
verified yet (a run that was interrupted) are verified there, in this process.
Verification takes the poses the pair was matched with: as given, or with the yaws corrected
for a ``guided-corrected`` pair (an anchor pair that keeps its first round's matches was
verified with the poses as given); the mounting search of ``hmcc colmap`` (images whose
attitude the track gave, ``--detect-mounting``) does not run. Each pair's row gains
its ``inliers``, ``verify_ms`` and ``verification`` (``hmcc colmap``'s status); the whole
verification report is ``report["verification"]``.
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import multiprocessing
import os
import statistics
import tempfile
import time
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pymap3d
from pydantic import ValidationError

from hmcc import Camera, InputError
from hmcc.flight import RoughPose, pair_poses
from hmcc.guided import (
    Features,
    GuidedOptions,
    MatchResult,
    match_brute_force,
    match_guided,
    normalize_descriptors,
    predicted_overlap,
    with_options,
)
from hmcc.pose import Pose, rot_z
from hmcc.yaw import PairYaws, fit_pair_yaws, solve_position_corrections, solve_yaw_corrections
from hmcc_schema import validation_issues
from hmcc_schema.convert import to_camera, to_rough_pose
from hmcc_schema.models import CameraModel, PoseModel

from .capture import exif_focal_cameras
from .database import (
    ColmapDatabase,
    ImageInfo,
    read_snapshot,
    snapshot_features,
    snapshot_orientations,
)
from .errors import ColmapInputError
from .poses import ImagePose, takeoff_ground, with_prior_positions
from .track import rough_sources
from .verify import (
    ColmapRun,
    PairVerifier,
    RunOptions,
    Verified,
    check_keypoints,
    read_pairs_file,
    sigint_held,
)

__all__ = ["GuidedMatchRun", "MatchOptions", "warm_up"]

#: Pairs whose matches are written in one transaction.
WRITE_BATCH_PAIRS = 64


@dataclass
class MatchOptions:
    """How to match: ``processes`` children (0: in this process), ``overwrite`` pairs matched
    before, the ground's height (``ground_z``, or ``height_m`` above it, or
    ``flying_height_m`` below each camera, the altitudes ignored; else the images'
    take-off heights), the matcher's options, ``pairs_per_task`` pairs a child takes at once
    (those of one image 1, whose features it then reads once); ``track_attitude``: an image
    with a position and no attitude takes one estimated from the flight track (:mod:`.track`,
    as ``hmcc colmap`` and ``hmcc pairs`` do; off: no usable pose, brute force); ``verify``:
    each pair verified where it is matched, as ``hmcc colmap`` with these options would
    (their ``overwrite``, ``processes``, ``track_attitude`` and ``exif_focal`` are this
    run's), and the two-view geometries written (None: matches only)."""

    processes: int = field(default_factory=lambda: os.cpu_count() or 1)
    overwrite: bool = False
    ground_z: float | None = None
    height_m: float | None = None
    flying_height_m: float | None = None
    exif_focal: bool = True
    guided: GuidedOptions = field(default_factory=GuidedOptions)
    pairs_per_task: int = 8
    track_attitude: bool = True
    verify: RunOptions | None = None


@dataclass(frozen=True)
class _PairTask:
    """One pair as a child matches it: the cameras, both poses in the pair's frame (None: no
    usable pose, brute force), the ground's height in that frame, the footprints' predicted
    overlap, the cameras' known turns and whether to search them, and the images' rough poses
    that verify the pair (None: no usable pose): as given, or with their yaws corrected where
    ``yaw_corrected``; ``fit_yaw``: the matches give both cameras' yaw corrections (an anchor
    pair of an image whose attitude the track gave); ``yaw_corrected``: ``pose1``, ``pose2``,
    ``rough1`` and ``rough2`` are corrected so (:meth:`GuidedMatchRun._rest_task`, which
    corrects a pair's poses as given, once)."""

    image_id1: int
    image_id2: int
    camera1: Camera
    camera2: Camera
    pose1: Pose | None
    pose2: Pose | None
    z0: float
    overlap: float = 0.0
    turns: tuple[int, int] = (0, 0)
    search_turns: bool = False
    search_rotation: bool = False
    rough1: RoughPose | None = None
    rough2: RoughPose | None = None
    fit_yaw: bool = False
    yaw_corrected: bool = False


#: What a child returns for a pair: its matches, and its verification (None: not verified).
_Matched = tuple[_PairTask, MatchResult, Verified | None]


class GuidedMatchRun:
    """One run over a database; :meth:`run` matches and writes, :attr:`report` is filled as it
    goes."""

    def __init__(
        self,
        database: Path,
        *,
        images: Path | None = None,
        poses: Path | None = None,
        pairs: Path | None = None,
        options: MatchOptions | None = None,
        progress: Callable[[int, int], None] | None = None,
    ) -> None:
        self.database = Path(database)
        self.images_dir = None if images is None else Path(images)
        self.poses_path = None if poses is None else Path(poses)
        self.pairs_path = None if pairs is None else Path(pairs)
        self.options = options or MatchOptions()
        self.progress = progress
        self.report: dict[str, Any] = {}
        self._estimated: set[str] = set()  # images whose attitude the track gave
        self._yaw_corrections: dict[int, float] = {}  # image id -> degrees (estimated ones)
        self._position_corrections: dict[int, tuple[float, float]] = {}  # -> east, north (m)

    # ------------------------------------------------------------------ reading and checks

    def run(self) -> dict[str, Any]:
        """Match and write; the report. Raises :class:`ColmapInputError` before writing."""
        t0 = time.perf_counter()
        colmap = self._verification()  # its options checked before anything is read
        self._verifier = None if colmap is None else colmap.pair_verifier()
        snapshot = read_snapshot(self.database)
        infos = {i.image_id: i for i in snapshot.images}
        cameras = _cameras(snapshot.images)
        self._focal: dict[str, tuple[float, str]] = {}
        if self.options.exif_focal and self.images_dir is not None:
            cameras, self._focal = exif_focal_cameras(snapshot.images, cameras, self.images_dir)
        matched = {(a, b) for a, b, n in snapshot.matched if n > 0}
        wanted = self._pairs(snapshot.images)
        todo = [p for p in wanted if self.options.overwrite or p not in matched]
        used = sorted({i for p in todo for i in p})
        features: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        orientations = dict(snapshot_orientations(self.database, used))
        for image_id, kps, desc in snapshot_features(self.database, used):
            check_keypoints(infos[image_id].name, cameras[image_id], kps)
            features[image_id] = (kps, desc, orientations[image_id])
        sources = self._sources(snapshot.images)
        # the ground from the sources alone first: refused before the file is opened (COLMAP's
        # pose_priors may add positions below, never the take-off heights)
        self._ground(_rough_poses(snapshot.images, sources)[0], sources, infos)
        with ColmapDatabase(self.database) as db:
            sources = with_prior_positions(sources, db.pose_prior_positions(snapshot.images))
            rough, issues = _rough_poses(snapshot.images, sources)
            z0, z0_source = self._ground(rough, sources, infos)
            flat = self.options.flying_height_m
            estimated = {i.image_id for i in snapshot.images if i.name in self._estimated}
            tasks = [
                replace(
                    _task(a, b, cameras, rough, z0, flat),
                    search_rotation=bool({a, b} & estimated),
                    rough1=rough.get(a),
                    rough2=rough.get(b),
                )
                for a, b in todo
            ]
            self._start_report(snapshot.images, rough, issues, wanted, todo, z0, z0_source)
            self.report["totals"]["read_s"] = round(time.perf_counter() - t0, 3)
            t1 = time.perf_counter()
            with tempfile.TemporaryDirectory(prefix="hmcc-match-") as tmp:
                folder = Path(tmp)
                _ship_features(folder, features)
                del features
                batch: list[tuple[int, int, np.ndarray]] = []
                verified: dict[tuple[int, int], Verified | None] = {}
                for task, result, outcome in self._match(folder, tasks, estimated):
                    self._record(infos, task, result)
                    verified[(task.image_id1, task.image_id2)] = outcome
                    batch.append((task.image_id1, task.image_id2, result.matches))
                    if len(batch) >= WRITE_BATCH_PAIRS:
                        self._write(db, batch)
                        batch = []
                self._write(db, batch)
            self.report["totals"]["match_s"] = round(time.perf_counter() - t1, 3)
        for image_id, yaw in self._yaw_corrections.items():
            self.report["images"][infos[image_id].name]["yaw_correction_deg"] = round(yaw, 1)
        for image_id, offset in self._position_corrections.items():
            self.report["images"][infos[image_id].name]["position_correction_m"] = [
                round(v, 1) for v in offset
            ]
        self.report["totals"]["images_yaw_corrected"] = len(self._yaw_corrections)
        self.report["totals"]["images_position_corrected"] = len(self._position_corrections)
        self._finish_report()
        if colmap is not None:
            t2 = time.perf_counter()
            colmap.verified = verified
            self._take_verification(colmap.run())
            self.report["totals"]["write_geometries_s"] = round(time.perf_counter() - t2, 3)
        return self.report

    def _verification(self) -> ColmapRun | None:
        """The verification run ``options.verify`` asks for (None: none); raises
        :class:`ColmapInputError` for options it refuses."""
        opts = self.options
        if opts.verify is None:
            return None
        return ColmapRun(
            self.database,
            images=self.images_dir,
            poses=self.poses_path,
            pairs=self.pairs_path,
            options=replace(
                opts.verify,
                overwrite=opts.overwrite,
                processes=opts.processes,
                url=None,
                track_attitude=opts.track_attitude,
                exif_focal=opts.exif_focal,
                detect_mounting=False,
            ),
            verified={},
        )

    def _take_verification(self, verification: dict[str, Any]) -> None:
        """The verification's report as ``report["verification"]``; each pair's row gains
        its inliers, verification time and status."""
        self.report["verification"] = verification
        rows = {(r["image1"], r["image2"]): r for r in verification["pairs"]}
        totals = self.report["totals"]
        totals["verified"] = verification["totals"]["verified"]
        totals["inlier_matches"] = verification["totals"]["inlier_matches"]
        totals["verify_ms_sum"] = verification["totals"]["verify_ms"]
        for row in self.report["pairs"]:
            done = rows.get((row["image1"], row["image2"]))
            row["inliers"] = 0 if done is None else done["inliers"]
            row["verify_ms"] = None if done is None else _rounded(done["time_ms"])
            row["verification"] = "not verified (no matches)" if done is None else done["status"]

    def _pairs(self, images: Sequence[ImageInfo]) -> list[tuple[int, int]]:
        if self.pairs_path is not None:
            return read_pairs_file(self.pairs_path, {i.name: i for i in images})
        ids = sorted(i.image_id for i in images)
        pairs = [(a, b) for k, a in enumerate(ids) for b in ids[k + 1 :]]
        if not pairs:
            raise ColmapInputError(f"{self.database}: fewer than two images; nothing to match")
        return pairs

    def _sources(self, infos: Sequence[ImageInfo]) -> dict[str, ImagePose]:
        names = [i.name for i in infos]
        if self.poses_path is None and self.images_dir is None:
            raise ColmapInputError(
                "--images DIR (POS from the images' EXIF/XMP) or --poses FILE is needed: guided "
                "matching uses the rough POS"
            )
        sources, estimated = rough_sources(
            names, self.poses_path, self.images_dir, track=self.options.track_attitude
        )
        self._estimated = set(estimated)
        return sources

    def _ground(
        self,
        rough: Mapping[int, RoughPose],
        sources: Mapping[str, ImagePose],
        infos: Mapping[int, ImageInfo],
    ) -> tuple[float, str]:
        """Z0 on the altitudes' scale and where it came from (module docstring)."""
        opts = self.options
        given = [opts.ground_z, opts.height_m, opts.flying_height_m]
        if sum(v is not None for v in given) > 1:
            raise ColmapInputError("give one of --ground-z, --height and --flying-height")
        if opts.ground_z is not None:
            return float(opts.ground_z), "given (--ground-z)"
        if opts.flying_height_m is not None:
            if not opts.flying_height_m > 0:
                raise ColmapInputError(f"--flying-height: {opts.flying_height_m:g} is not above 0")
            return 0.0, (
                f"{opts.flying_height_m:g} m below each camera, the altitudes not used "
                "(--flying-height)"
            )
        altitudes = {i: float(p.position[2]) for i, p in rough.items()}
        if opts.height_m is not None:
            if not altitudes:
                raise ColmapInputError("--height: no image has a usable pose")
            ground = statistics.median(altitudes.values()) - float(opts.height_m)
            return ground, f"median camera altitude - {opts.height_m:g} m (--height)"
        takeoff = takeoff_ground(
            {infos[i].name: altitude for i, altitude in altitudes.items()}, sources
        )
        if takeoff is not None:
            return (
                takeoff[0],
                f"median altitude - RelativeAltitude of {takeoff[1]} images (take-off point)",
            )
        if not altitudes:  # no pose at all: every pair is brute force, the plane unused
            return 0.0, "unused (no image has a usable pose)"
        raise ColmapInputError(
            "the ground's height is needed to predict matches: give --ground-z Z (metres, on "
            "the scale of the positions' altitudes) or --height H (flying height above ground)"
        )

    # ------------------------------------------------------------------ matching

    def _match(
        self, folder: Path, tasks: Sequence[_PairTask], estimated: set[int]
    ) -> Iterator[_Matched]:
        """Each task with its matches, as they finish (here, or on a process pool), in two
        rounds: first each image's anchor pairs (:data:`ANCHOR_PAIRS` of most predicted
        overlap, :data:`ANCHOR_PAIRS_ESTIMATED` for an image of ``estimated`` attitude),
        the turns about the optical axes searched where the poses do not fit (for an
        ``estimated`` one the rotation, the turns only without orientations), and the yaw
        corrections of the ``estimated`` images fitted to their matches; then the other
        pairs with each image's turn as its anchors found it (searched only for an image
        whose anchors found nothing), or with the ``estimated`` images' poses corrected by
        their yaw (no search), and the anchor pairs of those again so, the result of more
        matches kept (the anchors' own turn or rotation leaves a few degrees between the
        images that the corrected poses do not)."""
        anchors = _anchor_pairs(tasks, estimated)
        first = [
            replace(
                t,
                search_turns=True,
                fit_yaw=bool({t.image_id1, t.image_id2} & estimated),
            )
            for t in tasks
            if (t.image_id1, t.image_id2) in anchors
        ]
        votes: dict[int, dict[int, int]] = {}
        fits: list[tuple[int, int, PairYaws]] = []
        held: dict[tuple[int, int], _Matched] = {}  # matched again with corrected poses
        with self._runner(folder) as run:
            for task, result, verified in run(first):
                _vote(votes, task, result)
                fit = result.stats.get("yaw_fit")
                if fit is not None:
                    fits.append((task.image_id1, task.image_id2, PairYaws(**fit)))
                if task.fit_yaw:
                    held[(task.image_id1, task.image_id2)] = (task, result, verified)
                else:
                    yield task, result, verified
            turns = {image: _turn_of(v) for image, v in votes.items()}
            position_error = self.options.guided.position_error_m
            yaws = {
                image: yaw
                for image, yaw in solve_yaw_corrections(fits, position_error).items()
                if image in estimated
            }
            self._yaw_corrections = yaws
            offsets = self._position_corrections = solve_position_corrections(fits, yaws)
            given = {t.image_id1: t.rough1 for t in tasks} | {t.image_id2: t.rough2 for t in tasks}
            corrected = {  # each image's rough pose corrected once, not once per pair
                image: _moved_rough(_yawed_rough(rough, yaws.get(image, 0.0)), offsets.get(image))
                for image, rough in given.items()
                if rough is not None
            }
            rest = [
                self._rest_task(t, turns, yaws, corrected, estimated)
                for t in tasks
                if (t.image_id1, t.image_id2) not in anchors
            ]
            for pair, matched in list(held.items()):
                again = self._rest_task(matched[0], turns, yaws, corrected, estimated)
                if again.yaw_corrected:
                    rest.append(again)
                else:
                    del held[pair]
                    yield matched
            for matched in run(rest):
                before = held.get((matched[0].image_id1, matched[0].image_id2))
                if before is not None and len(before[1].matches) > len(matched[1].matches):
                    matched = before
                yield matched

    def _rest_task(
        self,
        task: _PairTask,
        turns: Mapping[int, int],
        yaws: Mapping[int, float],
        corrected: Mapping[int, RoughPose],
        estimated: set[int],
    ) -> _PairTask:
        """A pair of the second round: its images' rough poses as ``corrected`` (by their
        yaws and positions) where an image of estimated attitude has a yaw correction
        (``yaws``, degrees) and none lacks one (no search); else each image's turn as its
        anchors found it (searched when one has none). The corrected rough poses verify the
        pair too. ``task``'s poses are as given (a first-round task): corrected here once."""
        assert not task.yaw_corrected, "a pair's yaws are corrected once, from the poses as given"
        pair = (task.image_id1, task.image_id2)
        lacking = any(i in estimated and i not in yaws for i in pair)
        if task.pose1 is None or lacking or not any(i in yaws for i in pair):
            return replace(
                task,
                turns=(turns.get(pair[0], 0), turns.get(pair[1], 0)),
                search_turns=pair[0] not in turns or pair[1] not in turns,
            )
        rough = {i: corrected[i] for i in pair}
        cameras = {pair[0]: task.camera1, pair[1]: task.camera2}
        flat = self.options.flying_height_m
        # no overlap: only the first round's anchors are chosen by it
        moved = _task(*pair, cameras, rough, task.z0, flat, with_overlap=False)
        return replace(
            moved,
            turns=(
                0 if pair[0] in yaws else turns.get(pair[0], 0),
                0 if pair[1] in yaws else turns.get(pair[1], 0),
            ),
            search_turns=False,
            search_rotation=False,
            rough1=rough[pair[0]],
            rough2=rough[pair[1]],
            yaw_corrected=True,
        )

    @contextmanager
    def _runner(
        self, folder: Path
    ) -> Iterator[Callable[[Sequence[_PairTask]], Iterator[_Matched]]]:
        """A function matching (and verifying) tasks here or on one process pool, set up and
        torn down."""
        options = self.options.guided
        verifier = self._verifier
        if self.options.processes <= 0:
            warm_up(options, verifier)

            def here(tasks: Sequence[_PairTask]) -> Iterator[_Matched]:
                for task in tasks:
                    yield _match_and_verify(folder, task, options, verifier)

            try:
                yield here
            finally:
                _features.cache_clear()
            return
        warm_up(options, verifier)  # compiled once here, inherited by the forked children
        context = multiprocessing.get_context(
            "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        )
        with (
            _one_thread_each(),
            cf.ProcessPoolExecutor(self.options.processes, mp_context=context) as pool,
        ):

            def pooled(tasks: Sequence[_PairTask]) -> Iterator[_Matched]:
                groups = _task_groups(tasks, self.options.pairs_per_task)
                futures = [pool.submit(_match_group, folder, g, options, verifier) for g in groups]
                try:
                    for future in cf.as_completed(futures):
                        yield from future.result()
                except BaseException:
                    for f in futures:
                        f.cancel()
                    raise

            yield pooled

    def _write(self, db: ColmapDatabase, batch: list[tuple[int, int, np.ndarray]]) -> None:
        if not batch:
            return
        with sigint_held():
            written = db.write_matches(batch, self.options.overwrite)
        self.report["totals"]["written"] += written

    # ------------------------------------------------------------------ report

    def _start_report(
        self,
        images: Sequence[ImageInfo],
        rough: Mapping[int, RoughPose],
        issues: Mapping[int, str],
        wanted: Sequence[tuple[int, int]],
        todo: Sequence[tuple[int, int]],
        z0: float,
        z0_source: str,
    ) -> None:
        self.report = {
            "database": str(self.database),
            "ground_z_m": round(z0, 3),
            "ground_z_source": z0_source,
            "options": {
                "processes": self.options.processes,
                "guided": _options_dict(self.options.guided),
            },
            "totals": {
                "pairs": len(todo),
                "skipped_already_matched": len(wanted) - len(todo),
                "written": 0,
                "matches": 0,
                "modes": {},
                "images_without_pose": sum(1 for i in images if i.image_id not in rough),
                "images_attitude_estimated": len(self._estimated),
                "images_focal_from_exif": sum(1 for f in self._focal.values() if f[1] == "exif"),
            },
            "images": {
                i.name: {
                    "pose": i.image_id in rough,
                    "pose_issue": issues.get(i.image_id),
                    "attitude": "estimated from the track" if i.name in self._estimated else None,
                    "focal_px": round(self._focal[i.name][0], 1) if i.name in self._focal else None,
                    "focal_source": self._focal[i.name][1] if i.name in self._focal else None,
                    "turned_deg": {},
                    "yaw_correction_deg": None,
                    "position_correction_m": None,
                }
                for i in images
            },
            "pairs": [],
        }
        self._total = len(todo)
        self._done = 0

    def _record(self, infos: Mapping[int, ImageInfo], task: _PairTask, result: MatchResult) -> None:
        stats = result.stats
        mode = stats["mode"]
        if mode == "brute-force":
            mode = "brute-force (no pose)"
        elif mode == "guided" and task.yaw_corrected:
            mode = "guided-corrected"
        totals = self.report["totals"]
        totals["modes"][mode] = totals["modes"].get(mode, 0) + 1
        totals["matches"] += len(result.matches)
        names = (infos[task.image_id1].name, infos[task.image_id2].name)
        found = stats.get("turn_deg", (0, 0)) if stats["mode"] == "guided-turned" else (0, 0)
        for name, turn in zip(names, found, strict=True):
            if turn:  # the pairs matched with this image turned about its optical axis
                votes = self.report["images"][name]["turned_deg"]
                votes[str(turn)] = votes.get(str(turn), 0) + 1
        self.report["pairs"].append(
            {
                "image1": infos[task.image_id1].name,
                "image2": infos[task.image_id2].name,
                **stats,
                "mode": mode,
            }
        )
        self._done += 1
        if self.progress is not None:
            self.progress(self._done, self._total)

    def _finish_report(self) -> None:
        rows = self.report["pairs"]
        rows.sort(key=lambda r: (r["image1"], r["image2"]))
        totals = self.report["totals"]
        totals["candidates_per_keypoint_mean"] = (
            round(statistics.fmean(r["candidates_per_keypoint"] for r in rows), 2) if rows else 0.0
        )
        totals["pair_time_ms_sum"] = round(sum(r["time_ms"] for r in rows), 1)


# --------------------------------------------------------------------------- helpers


def _cameras(infos: Sequence[ImageInfo]) -> dict[int, Camera]:
    cameras: dict[int, Camera] = {}
    for info in infos:
        try:
            cameras[info.image_id] = to_camera(CameraModel.model_validate(info.camera))
        except (ValidationError, InputError) as e:
            issue = validation_issues(e)[0]
            raise ColmapInputError(
                f"camera {info.camera_id} of {info.name}: {issue.field}: {issue.reason}"
            ) from None
    return cameras


def _rough_poses(
    infos: Sequence[ImageInfo], sources: Mapping[str, ImagePose]
) -> tuple[dict[int, RoughPose], dict[int, str]]:
    """The images' rough poses, and why the others have none."""
    rough: dict[int, RoughPose] = {}
    issues: dict[int, str] = {}
    for info in infos:
        source = sources.get(info.name)
        pose = None if source is None else source.pose
        if source is None or pose is None:
            issues[info.image_id] = "no pose source" if source is None else str(source.why_unusable)
            continue
        try:
            rough[info.image_id] = to_rough_pose(PoseModel.model_validate(pose))
        except (ValidationError, InputError) as e:
            issue = validation_issues(e)[0]
            issues[info.image_id] = f"unusable pose ({issue.field}: {issue.reason})"
    return rough, issues


def _task(
    a: int,
    b: int,
    cameras: Mapping[int, Camera],
    rough: Mapping[int, RoughPose],
    z0: float,
    flying_height_m: float | None = None,
    *,
    with_overlap: bool = True,
) -> _PairTask:
    """The pair's task; with ``flying_height_m`` both cameras that high above the plane
    Z = 0 (``z0`` then 0), their altitudes not used; its footprints' predicted overlap unless
    not ``with_overlap`` (0 then)."""
    pose1 = pose2 = None
    if a in rough and b in rough:
        try:
            pose1, pose2 = pair_poses(rough[a], rough[b])
        except InputError:  # positions given two ways, or too far apart: no guidance
            pose1 = pose2 = None
    if pose1 is not None and pose2 is not None and flying_height_m is not None:
        pose1, pose2 = (
            Pose(p.R_world_to_cam, np.array([p.center[0], p.center[1], flying_height_m]))
            for p in (pose1, pose2)
        )
    overlap = 0.0
    if pose1 is not None and pose2 is not None and with_overlap:
        overlap = predicted_overlap(cameras[a], pose1, cameras[b], pose2, z0)
    return _PairTask(a, b, cameras[a], cameras[b], pose1, pose2, z0, overlap)


#: Each image's pairs of most predicted overlap matched first (its turn searched there).
ANCHOR_PAIRS = 2
#: The anchor pairs of an image whose attitude the track gave: its yaw is fitted to them.
ANCHOR_PAIRS_ESTIMATED = 4
#: Pairs predicted to overlap less than this are no image's anchors.
ANCHOR_MIN_OVERLAP = 0.3


def _anchor_pairs(
    tasks: Sequence[_PairTask],
    estimated: Collection[int] = (),
) -> set[tuple[int, int]]:
    best: dict[int, list[tuple[float, tuple[int, int]]]] = {}
    for t in tasks:
        if t.pose1 is None or t.overlap < ANCHOR_MIN_OVERLAP:
            continue
        for image in (t.image_id1, t.image_id2):
            best.setdefault(image, []).append((t.overlap, (t.image_id1, t.image_id2)))
    return {
        pair
        for image, ranked in best.items()
        for _, pair in sorted(ranked)[
            -(ANCHOR_PAIRS_ESTIMATED if image in estimated else ANCHOR_PAIRS) :
        ]
    }


def _yawed_rough(rough: RoughPose, degrees: float) -> RoughPose:
    """The rough pose turned by ``degrees`` (counterclockwise seen from above) about the
    vertical (:func:`hmcc.yaw.yawed`'s turn)."""
    if degrees == 0:
        return rough
    return replace(rough, R_world_to_cam=rough.R_world_to_cam @ rot_z(degrees).T)


def _moved_rough(rough: RoughPose, offset: tuple[float, float] | None) -> RoughPose:
    """The rough pose moved by ``offset`` (east, north metres; None: not moved)."""
    if offset is None:
        return rough
    east, north = offset
    if not rough.geodetic:
        return replace(rough, position=rough.position + np.array([east, north, 0.0]))
    lat, lon, alt = pymap3d.enu2geodetic(east, north, 0.0, *(float(v) for v in rough.position))
    return replace(rough, position=np.array([float(lat), float(lon), float(alt)]))


def _vote(votes: dict[int, dict[int, int]], task: _PairTask, result: MatchResult) -> None:
    """The turns a matched anchor pair found for its images (0 where the poses fit)."""
    mode = result.stats["mode"]
    if mode not in ("guided", "guided-turned"):
        return
    found = result.stats.get("turn_deg", (0, 0))
    for image, turn in zip((task.image_id1, task.image_id2), found, strict=True):
        votes.setdefault(image, {})
        votes[image][int(turn)] = votes[image].get(int(turn), 0) + 1


def _turn_of(votes: Mapping[int, int]) -> int:
    """The most voted turn (0 on a tie with it)."""
    return max(votes, key=lambda turn: (votes[turn], turn == 0))


def _task_groups(tasks: Sequence[_PairTask], size: int) -> list[list[_PairTask]]:
    """Tasks of up to ``size`` pairs sharing image 1 (in the order of the pairs)."""
    groups: list[list[_PairTask]] = []
    for task in tasks:
        if groups and groups[-1][0].image_id1 == task.image_id1 and len(groups[-1]) < size:
            groups[-1].append(task)
        else:
            groups.append([task])
    return groups


def _ship_features(
    folder: Path, features: Mapping[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> None:
    """Three ``.npy`` files an image (keypoints, unit descriptors, keypoint orientations),
    which the children load rather than receive in every task."""
    for image_id, (kps, desc, angles) in features.items():
        np.save(folder / f"{image_id}.kp.npy", np.ascontiguousarray(kps, dtype=np.float64))
        np.save(folder / f"{image_id}.desc.npy", normalize_descriptors(desc))
        np.save(folder / f"{image_id}.ori.npy", np.ascontiguousarray(angles, dtype=np.float64))


@functools.lru_cache(maxsize=64)
def _features(folder: Path, image_id: int) -> Features:
    kps = np.load(folder / f"{image_id}.kp.npy")
    desc = np.load(folder / f"{image_id}.desc.npy")
    angles = np.load(folder / f"{image_id}.ori.npy")
    return Features(kps, desc, angles if np.isfinite(angles).any() else None)


def _match_pair(folder: Path, task: _PairTask, options: GuidedOptions) -> MatchResult:
    f1 = _features(folder, task.image_id1)
    f2 = _features(folder, task.image_id2)
    if task.pose1 is None or task.pose2 is None:
        return match_brute_force(f1, f2, options)
    search_turns = task.search_turns
    if task.fit_yaw and f1.orientations is not None and f2.orientations is not None:
        search_turns = False  # the rotation search finds any angle, quarter turns included
    if options.try_turns != search_turns:
        options = with_options(options, try_turns=search_turns)
    if options.search_rotation and not task.search_rotation:
        options = with_options(options, search_rotation=False)
    result = match_guided(
        task.camera1,
        task.pose1,
        f1,
        task.camera2,
        task.pose2,
        f2,
        task.z0,
        options,
        turns=task.turns,
    )
    if task.fit_yaw and len(result.matches):
        fit = fit_pair_yaws(
            task.camera1,
            task.pose1,
            f1.keypoints,
            task.camera2,
            task.pose2,
            f2.keypoints,
            result.matches,
            task.z0,
        )
        if fit is not None:
            result.stats["yaw_fit"] = {
                "yaw1_deg": round(fit.yaw1_deg, 2),
                "yaw2_deg": round(fit.yaw2_deg, 2),
                "baseline_m": round(fit.baseline_m, 2),
                "used": fit.used,
                "mean1_m": [round(v, 2) for v in fit.mean1_m],
                "mean2_m": [round(v, 2) for v in fit.mean2_m],
                "step_m": [round(v, 2) for v in fit.step_m],
                "height_m": round(fit.height_m, 2),
            }
    return result


def _match_and_verify(
    folder: Path, task: _PairTask, options: GuidedOptions, verifier: PairVerifier | None
) -> _Matched:
    """A pair matched, then (with a ``verifier``, and enough matches) verified at once."""
    result = _match_pair(folder, task, options)
    if verifier is None or not verifier.verifiable(len(result.matches)):
        return task, result, None
    f1 = _features(folder, task.image_id1)
    f2 = _features(folder, task.image_id2)
    verified = verifier.verify(
        task.camera1,
        task.rough1,
        f1.keypoints,
        task.camera2,
        task.rough2,
        f2.keypoints,
        result.matches,
    )
    return task, result, verified


def _match_group(
    folder: Path,
    group: Iterable[_PairTask],
    options: GuidedOptions,
    verifier: PairVerifier | None = None,
) -> list[_Matched]:
    return [_match_and_verify(folder, task, options, verifier) for task in group]


@contextmanager
def _one_thread_each() -> Iterator[None]:
    """One BLAS thread and one OpenCV thread in this process meanwhile, so in the pool's
    children forked meanwhile (the children are the parallelism: a BLAS thread per core in
    each child spins on the cores the others need).

    Set here, before the fork, and inherited: a forked child must not set them itself
    (``cv2.setNumThreads`` in a child forked from a process whose OpenCV thread pool had run
    waits forever in ``pthread_cond_destroy``). Spawned children start with the defaults."""
    import cv2
    from threadpoolctl import threadpool_limits

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(1):
            yield
    finally:
        cv2.setNumThreads(threads)


def warm_up(options: GuidedOptions, verifier: PairVerifier | None = None) -> None:
    """Load (or compile) the matcher's kernels in this process, and the verification's with a
    ``verifier``."""
    if verifier is not None:
        verifier.warm_up()
    cam = Camera(64, 64, 64.0, 64.0, 31.5, 31.5)
    pose = Pose(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 10.0]))
    rng = np.random.default_rng(0)
    f = Features.from_raw(rng.uniform(0, 63, (20, 2)), rng.uniform(0, 1, (20, 128)))
    match_guided(cam, pose, f, cam, pose, f, 0.0, options)


def _rounded(ms: float | None) -> float | None:
    return None if ms is None else round(ms, 2)


def _options_dict(options: GuidedOptions) -> dict[str, Any]:
    return {k: getattr(options, k) for k in options.__dataclass_fields__}
