"""Verify every matched pair of a COLMAP database and write the verified geometries back.

A run reads and checks everything first (database, cameras, keypoints, pairs, poses: a
:class:`ColmapInputError` leaves the database untouched), then goes chunk by chunk: one
:class:`hmcc.flight.Flight` per chunk (its images once, its pairs naming them), verified on
this machine's compute pool or through a running service (``HmccClient.verify_flight``), and
written in one transaction. Ctrl-C stops between two writes (a signal during a write is held
until the transaction ends), so the database holds whole chunks only; a rerun skips the pairs
that have a geometry already unless ``overwrite``.

Pairs whose images both have a usable pose go to the method; the others (an image without
one) go to the method's fallback estimator (``params.plus.fallback``, MAGSAC++ by
default), counted in the report. Methods that do not use poses (``ransac``, ``magsac++``, ...)
take every pair as is.

An image with a position and no attitude gets one estimated from the flight track (nadir,
image top along the direction of travel: :mod:`.track`, as ``hmcc pairs`` does) unless
``track_attitude`` is off. With ``detect_mounting`` the camera's turn about its optical axis
(0, 90, 180 or 270 deg, one for the flight) is searched on a sample of pairs before the run:
the turn under which most pairs' rough baselines point in the image where their verified
poses' do, then the method keeps most pairs without falling back (ties: the turn as given), is
added to every image's mounting yaw. Without it, the same search runs on the images
whose attitude the track gave (the track cannot tell a camera whose image top points along
the direction of travel from one turned toward a wing), their pairs sampled and the turn added
to them alone, and a run where most pairs fall back suggests ``detect_mounting``
(``report["mounting_hint"]``). ``report["mounting"]`` says what was searched and found (None:
no search).
"""

from __future__ import annotations

import functools
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from dataclasses import replace as _replace_dc
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import orjson
from pydantic import TypeAdapter, ValidationError

from hmcc import DEFAULT_METHOD, METHODS, Camera, InputError, VerifyOptions
from hmcc.flight import Flight, FlightImage, FlightPair, RoughPose, pair_poses
from hmcc.method_names import model_refusal
from hmcc.methods import POS_METHODS
from hmcc.plus import PlusOptions
from hmcc_schema import validation_issues
from hmcc_schema.convert import to_camera, to_rough_pose
from hmcc_schema.models import CameraModel, PoseModel
from hmcc_worker.cutover import INPROCESS_MAX_PAIRS
from hmcc_worker.outcomes import unpack
from hmcc_worker.protocol import JobStatus

from .capture import exif_focal_cameras
from .database import (
    ColmapDatabase,
    Geometry,
    ImageInfo,
    PriorFill,
    Snapshot,
    chunks,
    read_snapshot,
    snapshot_keypoints,
)
from .errors import ColmapInputError

if TYPE_CHECKING:
    from hmcc_worker.pool import ComputePool
from .poses import ImagePose, looked_for, with_prior_positions
from .shipping import keypoints_in_file
from .track import rough_sources
from .twoview import (
    Pose,
    PosedOutcome,
    pair_pose,
    relative_pose,
    result_model,
    verify_and_pose,
)

__all__ = [
    "ColmapRun",
    "PairVerifier",
    "RunOptions",
    "Verified",
    "blame",
    "check_keypoints",
    "read_pairs_file",
    "sigint_held",
]

#: The pose sent for an image that has none, with an estimator that ignores poses.
PLACEHOLDER_POSE = {
    "position": {"x": 0.0, "y": 0.0, "z": 0.0},
    "attitude": {"yaw": 0.0, "pitch": 0.0, "roll": 0.0},
}
#: A pair's rough relative rotation this far (deg) from its verified one: its POS did not fit
#: (rough POS and weak geometries stay within some 20 deg; a turned image is off by 180).
POS_ROTATION_TOLERANCE_DEG = 45.0
#: Fewer matches than this: no fundamental matrix can be fitted at all.
MIN_MATCHES_FOR_F = 8
#: More than this share of the images without a usable pose: the run says so (stderr, report).
POSELESS_SHARE_WARNED = 0.5
#: A baseline's part in the image plane under this share of its length: its direction there
#: says nothing of a camera's turn (:func:`_motion_agrees`).
MIN_PLANAR_BASELINE = 0.5
#: The turns about the optical axis a mounting search tries (deg, added to the mounting yaw).
MOUNTING_YAWS = (0, 90, 180, 270)
#: More than this share of the method's pairs fell back: the run suggests --detect-mounting.
FALLBACK_SHARE_HINTED = 0.5
#: The pose files ``--poses`` reads, for the message of a run without poses.
POSE_FILE_FORMATS = (
    "OpenDroneMap's geo.txt, a CSV image,lat,lon,alt,yaw,pitch,roll or "
    "image,x,y,z,omega,phi,kappa, or a JSON object mapping image name to a pose"
)


@dataclass
class RunOptions:
    """How to verify: ``method`` and ``params`` (the API's), pairs under ``min_inliers``
        written as COLMAP writes them, ``overwrite`` pairs verified before, here on ``processes``
        children (0: in this process; so too a run of at most ``in_process_max`` pairs to verify,
    where starting the children costs more than they save) or through the service at ``url``;
    ``chunk_pairs`` pairs per
        flight and transaction; ``exif_focal``: the images' EXIF focal length where the
        database's disagrees with it (:func:`hmcc_colmap.capture.exif_focal_cameras`)."""

    method: str = DEFAULT_METHOD
    params: dict[str, Any] | None = None
    min_inliers: int = 15
    overwrite: bool = False
    processes: int = field(default_factory=lambda: os.cpu_count() or 1)
    in_process_max: int = INPROCESS_MAX_PAIRS
    url: str | None = None
    api_key: str | None = None
    binary: bool = True
    chunk_pairs: int = 1024
    track_attitude: bool = True
    exif_focal: bool = True
    detect_mounting: bool = False
    mounting_sample: int = 40


def read_pairs_file(path: Path, by_name: Mapping[str, ImageInfo]) -> list[tuple[int, int]]:
    """COLMAP's pairs list (``name1 name2`` a line) as ``(image_id1, image_id2)``, id1 < id2."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ColmapInputError(f"{path}: {e}") from None
    out = []
    for number, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != 2:
            raise ColmapInputError(f"{path}:{number}: expected 'image1 image2', got {line!r}")
        for name in fields:
            if name not in by_name:
                raise ColmapInputError(f"{path}:{number}: image {name!r} is not in the database")
        a, b = by_name[fields[0]].image_id, by_name[fields[1]].image_id
        if a != b:
            out.append((min(a, b), max(a, b)))
    if not out:
        raise ColmapInputError(f"{path}: no pairs in this file")
    return sorted(set(out))


#: A pair verified elsewhere as the run takes it in: ``(result or None, error, pose)``;
#: ``pose`` the relative pose computed beside the verification (None: computed here).
Verified = tuple[dict[str, Any] | None, str, Pose | None]

_ChunkVerifier = Callable[[ColmapDatabase, "dict[int, _Image]", "Sequence[_Pair]"], list[Geometry]]
#: A flight's pairs as they finish: ``(index, result or None, error, pose)``; ``pose`` the
#: relative pose the pool's child computed (None: computed here).
_Outcomes = Iterator[tuple[int, dict[str, Any] | None, str, Pose | None]]


@dataclass(frozen=True)
class PairVerifier:
    """How a run verifies one pair, whichever process does it: the run's ``method`` for a
    pair of two posed images (or any pair, with a method that ignores poses), its
    ``fallback`` otherwise, with the checked ``options``; a pair with fewer matches than a
    fundamental matrix and ``min_inliers`` need is not verified. Picklable: ``hmcc match
    --verify`` hands it to the children that verify each pair where they matched it
    (:meth:`verify`)."""

    method: str
    fallback: str
    options: VerifyOptions
    min_inliers: int

    def verifiable(self, matches: int) -> bool:
        return matches >= max(MIN_MATCHES_FOR_F, self.min_inliers)

    def group(self, posed: bool) -> str:
        """``"method"`` or ``"fallback"``: which verifies a pair (``posed``: both its images
        have a usable pose)."""
        return "method" if posed or self.method not in POS_METHODS else "fallback"

    def method_of(self, group: str) -> tuple[str, bool]:
        """A group's method, and whether the images' rough poses go with its pairs."""
        if group == "method":
            return self.method, self.method in POS_METHODS
        return self.fallback, False

    def verify(
        self,
        camera1: Camera,
        rough1: RoughPose | None,
        keypoints1: np.ndarray,
        camera2: Camera,
        rough2: RoughPose | None,
        keypoints2: np.ndarray,
        matches: np.ndarray,
    ) -> Verified:
        """One pair's (M, 2) ``matches`` between (N, 2) pixel keypoints, verified here as the
        run would verify it (:func:`verify_and_pose`: the relative pose computed beside)."""
        method, with_pose = self.method_of(self.group(rough1 is not None and rough2 is not None))
        images = {
            str(k): FlightImage(camera, rough if with_pose else _placeholder_pose(), kps)
            for k, camera, rough, kps in (
                (1, camera1, rough1, keypoints1),
                (2, camera2, rough2, keypoints2),
            )
        }
        flight = Flight(images, [FlightPair("1", "2", matches, id="0")], method, self.options)
        _, result, error, pose = _posed(0, verify_and_pose(flight, self.min_inliers)[0])
        return result, error, pose

    def warm_up(self) -> None:
        """Load (or compile) the core's loops this verification takes, in this process: one
        simulated pair verified with the method (its ground estimated, as a run's pairs are)
        and a relative pose; lighter than :func:`hmcc_worker.warm.warm_up`, which warms every
        method."""
        from hmcc.simulate import SimulationOptions, simulate_pair
        from hmcc_schema import parse_pair

        pair = simulate_pair(SimulationOptions(n_inliers=60, outlier_ratio=0.3), seed=0)
        pair = {k: v for k, v in pair.items() if k != "plane"} | {"method": self.method}
        parse_pair(pair).verify(0)
        rays = np.column_stack((np.linspace(-0.3, 0.3, 8), np.linspace(0.2, -0.2, 8)))
        relative_pose(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]), rays, rays)


@dataclass
class _Image:
    info: ImageInfo
    camera: Camera
    pose: dict[str, Any] | None
    pose_source: str | None
    pose_issue: str | None
    rough: RoughPose | None
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def R_world_to_cam(self) -> np.ndarray | None:
        return None if self.rough is None else self.rough.R_world_to_cam


@dataclass
class _Pair:
    image_id1: int
    image_id2: int
    matches: int


@dataclass(frozen=True)
class _Group:
    """A chunk's pairs for one method (the run's or its fallback's) as a verifier sends them:
    ``pairs`` as ``(label, image_id1, image_id2, matches)``, heaviest first; ``with_pose``:
    the images' rough poses go with them (else a placeholder, which the method ignores)."""

    method: str
    with_pose: bool
    images: Mapping[int, _Image]
    keypoints: Mapping[int, np.ndarray]
    pairs: Sequence[tuple[str, int, int, np.ndarray]]

    def image_ids(self) -> list[int]:
        return sorted({i for _, a, b, _ in self.pairs for i in (a, b)})


class ColmapRun:
    """One run over a database; :meth:`run` verifies, :attr:`report` is filled as it goes (so
    an interrupted run still says what it wrote)."""

    def __init__(
        self,
        database: Path,
        *,
        images: Path | None = None,
        poses: Path | None = None,
        pairs: Path | None = None,
        options: RunOptions | None = None,
        progress: Callable[[int, int], None] | None = None,
        pool: ComputePool | None = None,
        verified: Mapping[tuple[int, int], Verified | None] | None = None,
    ) -> None:
        self.database = Path(database)
        self.images_dir = None if images is None else Path(images)
        self.poses_path = None if poses is None else Path(poses)
        self.pairs_path = None if pairs is None else Path(pairs)
        self.options = options or RunOptions()
        self.progress = progress
        self.pool = pool  # a running pool to use (not closed here) instead of a new one
        # pairs verified where they were matched (``hmcc match --verify``), by (id1, id2), and
        # no mounting searched; a pair not among them (matched before: a run that was
        # interrupted) is verified here. None: every pair verified here
        self.verified = verified
        self.report: dict[str, Any] = {}
        self._done = self._total = 0
        self._rows: dict[tuple[int, int], dict[str, Any]] = {}
        # the first chunk's keypoints as the checks read them, so that chunk does not read them
        # again (the others are read chunk by chunk: a flight's keypoints may not fit at once)
        self._checked_keypoints: dict[int, np.ndarray] = {}
        self._estimated: set[str] = set()  # images whose attitude the track gave
        self._focal: dict[str, tuple[float, str]] = {}  # focal length (px) and its source
        if self.options.method not in METHODS:
            raise ColmapInputError(
                f"--method: unknown method {self.options.method!r} ({', '.join(METHODS)})"
            )
        if self.options.min_inliers < 1:
            raise ColmapInputError("--min-inliers: must be at least 1")
        try:
            self._verify_options = _options_adapter().validate_python(self.options.params or {})
        except ValidationError as e:
            issue = validation_issues(e)[0]
            raise ColmapInputError(f"--params: {issue.field}: {issue.reason}") from None
        refused = model_refusal(self.options.method, self._verify_options.ransac.model)
        if refused is not None:
            raise ColmapInputError(f"--params: ransac.model: {refused}")

    def pair_verifier(self) -> PairVerifier:
        """How this run verifies a pair (for children that verify where they match)."""
        opts = self.options
        return PairVerifier(
            opts.method, _fallback_method(opts.params), self._verify_options, opts.min_inliers
        )

    # ------------------------------------------------------------------ reading and checks

    def run(self) -> dict[str, Any]:
        """Verify and write; the report. Raises :class:`ColmapInputError` before writing
        anything (the file is not even opened for writing) when the input does not fit."""
        t_plan = time.perf_counter()
        snapshot = read_snapshot(self.database)
        todo, skipped, without, cameras, sources = self._plan(snapshot)
        if todo and self.options.url:
            self._reach_service()  # before the database is opened for writing
        with ColmapDatabase(self.database) as db:
            if sources is not None:
                sources = with_prior_positions(sources, db.pose_prior_positions(snapshot.images))
            images = self._images(snapshot.images, cameras, sources or {})
            mounting = None
            # the turn of every image when asked, else of the images whose attitude the track
            # gave (it cannot know the camera's turn relative to the direction of travel)
            scope = None if self.options.detect_mounting else self._estimated
            searched = self.verified is None  # verified already with the poses as given
            if searched and sources is not None and todo and (scope is None or scope):
                mounting = self._search_mounting(db, snapshot.images, cameras, sources, todo, scope)
                if mounting["yaw_deg"]:
                    sources = _turned_all(sources, mounting["yaw_deg"], scope)
                    images = self._images(snapshot.images, cameras, sources)
            self._start_report(images, todo, skipped, without)
            self.report["mounting"] = mounting
            if sources is not None:
                self._warn_without_poses(images)
                written = db.fill_pose_priors(_prior_fills(images, sources))
                self.report["totals"]["pose_priors_written"] = written
            self.report["totals"]["plan_s"] = round(time.perf_counter() - t_plan, 3)
            if not todo:  # all verified before: no pool to start
                self._finish_report(images)
                return self.report
            t0 = time.perf_counter()
            with self._verifier(len(todo)) as verify_chunk:
                self.report["totals"]["startup_s"] = round(time.perf_counter() - t0, 3)
                t1 = time.perf_counter()
                done = 0
                for chunk in chunks(todo, self.options.chunk_pairs):
                    geometries = verify_chunk(db, images, chunk)
                    with sigint_held():
                        db.write(geometries, self.options.overwrite)
                    done += len(chunk)
                    self.report["totals"]["written"] = done
                    self.report["totals"]["verify_s"] = round(time.perf_counter() - t1, 3)
        self._finish_report(images)
        return self.report

    def _plan(
        self, snapshot: Snapshot
    ) -> tuple[list[_Pair], int, int, dict[int, Camera], dict[str, ImagePose] | None]:
        """Every check on the read-only snapshot and the other inputs: the pairs to verify,
        how many were verified before, listed pairs without matches, the cameras, the poses'
        sources (None for a method without poses)."""
        by_name = {i.name: i for i in snapshot.images}
        counts = {(a, b): n for a, b, n in snapshot.matched if n > 0}
        if not counts:
            raise ColmapInputError(
                f"{self.database}: no matches in this database; match first (colmap "
                "exhaustive_matcher or pycolmap.match_exhaustive)"
            )
        without = 0
        if self.pairs_path is not None:
            wanted = read_pairs_file(self.pairs_path, by_name)
            without = sum(1 for p in wanted if p not in counts)
            keys = [p for p in wanted if p in counts]
        else:
            keys = sorted(counts)
        todo = [
            _Pair(a, b, counts[(a, b)])
            for a, b in keys
            if self.options.overwrite or (a, b) not in snapshot.verified
        ]
        cameras: dict[int, Camera] = {}
        for info in snapshot.images:
            try:
                cameras[info.image_id] = to_camera(CameraModel.model_validate(info.camera))
            except (ValidationError, InputError) as e:
                issue = validation_issues(e)[0]
                raise ColmapInputError(
                    f"camera {info.camera_id} of {info.name}: {issue.field}: {issue.reason}"
                ) from None
        if self.options.exif_focal and self.images_dir is not None:
            cameras, self._focal = exif_focal_cameras(snapshot.images, cameras, self.images_dir)
        else:
            self._focal = {
                i.name: (0.5 * (cameras[i.image_id].fx + cameras[i.image_id].fy), "database")
                for i in snapshot.images
            }
        sources = self._sources(snapshot.images)
        used = sorted({i for p in todo for i in (p.image_id1, p.image_id2)})
        names = {i.image_id: i.name for i in snapshot.images}
        first = {i for p in todo[: self.options.chunk_pairs] for i in (p.image_id1, p.image_id2)}
        if self.options.method == "gc-ransac":  # it reads the keypoints' shapes too: read again
            first = set()
        for image_id, kps in snapshot_keypoints(self.database, used):
            check_keypoints(names[image_id], cameras[image_id], kps)
            if image_id in first:
                self._checked_keypoints[image_id] = kps
        return todo, len(keys) - len(todo), without, cameras, sources

    def _reach_service(self) -> None:
        """Ask the service for its limits: an unreachable service or a refused key raises
        here (``HmccError``, ``httpx.TransportError``) with the database untouched."""
        from hmcc_client import HmccClient

        key = self.options.api_key or os.environ.get("HMCC_API_KEY")
        assert self.options.url is not None
        with HmccClient(self.options.url, api_key=key, timeout=10.0) as client:
            client.limits()

    def _sources(self, infos: Sequence[ImageInfo]) -> dict[str, ImagePose] | None:
        if self.options.method not in POS_METHODS:
            return None
        names = [i.name for i in infos]
        if self.poses_path is None and self.images_dir is None:
            raise ColmapInputError(
                "--images DIR (POS from the images' EXIF/XMP) or --poses FILE is needed with "
                f"method {self.options.method}"
            )
        sources, estimated = rough_sources(
            names, self.poses_path, self.images_dir, track=self.options.track_attitude
        )
        self._estimated = set(estimated)
        return sources

    def _images(
        self,
        infos: Sequence[ImageInfo],
        cameras: Mapping[int, Camera],
        sources: Mapping[str, ImagePose],
    ) -> dict[int, _Image]:
        images = {}
        for info in infos:
            source = sources.get(info.name)
            pose, rough, issue = self._pose(source)
            images[info.image_id] = _Image(
                info,
                cameras[info.image_id],
                pose,
                None if source is None else source.source,
                issue,
                rough,
            )
        return images

    def _pose(
        self, source: ImagePose | None
    ) -> tuple[dict[str, Any] | None, RoughPose | None, str | None]:
        if source is None:
            if self.options.method in POS_METHODS:
                return None, None, "no pose source for this image"
            return None, None, None
        pose = source.pose
        if pose is None:
            return None, None, source.why_unusable
        try:
            rough = to_rough_pose(PoseModel.model_validate(pose))
        except (ValidationError, InputError) as e:
            issue = validation_issues(e)[0]
            return None, None, f"unusable pose ({issue.field}: {issue.reason})"
        return pose, rough, None

    # ------------------------------------------------------------------ the mounting

    def _search_mounting(
        self,
        db: ColmapDatabase,
        infos: Sequence[ImageInfo],
        cameras: Mapping[int, Camera],
        sources: Mapping[str, ImagePose],
        todo: Sequence[_Pair],
        scope: set[str] | None = None,
    ) -> dict[str, Any]:
        """The flight's turn about the optical axis (:data:`MOUNTING_YAWS`) under which most
        of a sample of pairs (``mounting_sample``, spread over the pairs in image order) have
        their rough baseline where the verified pose has it (:func:`_motion_agrees`), then
        the method keeps most of them without falling back, then the turn as given, then most
        inliers; verified in this process. The
        turn is of the images named in ``scope`` (None: every image), the pairs sampled
        among theirs."""
        from hmcc_worker.warm import warm_up

        opts = self.options
        images = self._images(infos, cameras, sources)
        least = max(MIN_MATCHES_FOR_F, opts.min_inliers)
        posed = [
            p
            for p in todo
            if images[p.image_id1].rough is not None
            and images[p.image_id2].rough is not None
            and p.matches >= least
            and (
                scope is None
                or {images[p.image_id1].info.name, images[p.image_id2].info.name} <= scope
            )
        ]
        picks = sorted({round(x) for x in np.linspace(0, len(posed) - 1, opts.mounting_sample)})
        sample = [posed[k] for k in picks] if posed else []
        keypoints: dict[int, np.ndarray] = {}
        pairs: list[tuple[str, int, int, np.ndarray]] = []
        for k, pair in enumerate(sample):
            m = db.matches(pair.image_id1, pair.image_id2)
            for i in (pair.image_id1, pair.image_id2):
                if i not in keypoints:
                    keypoints[i] = db.keypoints(i)
            if not _out_of_range(m, keypoints[pair.image_id1], keypoints[pair.image_id2]):
                pairs.append((str(k), pair.image_id1, pair.image_id2, m))
        tried = []
        if pairs:
            warm_up()
        for yaw in MOUNTING_YAWS if pairs else ():
            turned = self._images(infos, cameras, _turned_all(sources, yaw, scope))
            group = _Group(opts.method, True, turned, keypoints, pairs)
            kept = consistent = inliers = 0
            for index, result, _, _ in self._inline(group):
                if result is None:
                    continue
                stats = result.get("statistics") or {}
                F, found = result_model(result)
                if not (stats.get("fallback") or {}).get("used") and len(found) >= opts.min_inliers:
                    kept += 1
                    inliers += len(found)
                if F is not None and len(found) >= opts.min_inliers:
                    _, a, b, m = pairs[index]
                    verified = pair_pose(
                        F, m[found], cameras[a], cameras[b], keypoints[a], keypoints[b]
                    )
                    agrees = _motion_agrees(_rough(turned[a]), _rough(turned[b]), verified)
                    consistent += agrees is True
            tried.append(
                {"yaw_deg": yaw, "consistent": consistent, "kept": kept, "inliers": inliers}
            )
        # most baselines consistent, then most pairs kept (a nadir camera's turns keep about
        # as many: they leave a pair's relative rotation as it was), then the turn as given,
        # then most inliers
        best = max(
            tried,
            key=lambda t: (t["consistent"], t["kept"], t["yaw_deg"] == 0, t["inliers"]),
            default=None,
        )
        return {
            "searched": True,
            "per": "flight",
            "images": "every image" if scope is None else "attitude estimated from the track",
            "sample_pairs": len(pairs),
            "yaw_deg": 0 if best is None else best["yaw_deg"],
            "tried": tried,
        }

    # ------------------------------------------------------------------ verifying

    def _in_process(self, pairs: int) -> bool:
        """Whether a run of ``pairs`` pairs is verified in this process (see :meth:`_verifier`)."""
        opts = self.options
        return opts.processes <= 0 or (self.pool is None and pairs <= opts.in_process_max)

    @contextmanager
    def _verifier(self, pairs: int) -> Iterator[_ChunkVerifier]:
        """A function verifying one chunk here or through the service, set up and torn down
        (``pairs``: how many the run verifies; few enough, they are verified in this process
        unless a running pool was given; else on children forked from a fork server that
        imported and warmed the core once)."""
        opts = self.options
        if self.verified is not None:
            yield lambda db, images, chunk: self._chunk(db, images, chunk, self._taken)
            return
        if opts.url:
            from hmcc_client import HmccClient

            key = opts.api_key or os.environ.get("HMCC_API_KEY")
            with HmccClient(opts.url, api_key=key, timeout=120.0, retries=5) as client:
                yield lambda db, images, chunk: self._chunk(
                    db, images, chunk, lambda group: self._remote(client, group)
                )
            return
        if self._in_process(pairs):
            from hmcc_worker.warm import warm_up

            warm_up()  # the core's compiled loops loaded once, timed as the start
            yield lambda db, images, chunk: self._chunk(
                db, images, chunk, lambda group: self._inline(group)
            )
            return
        if self.pool is not None:
            running = self.pool
            yield lambda db, images, chunk: self._chunk(
                db, images, chunk, lambda group: self._pooled(running, group)
            )
            return
        from hmcc_worker.pool import ComputePool

        pool = ComputePool(opts.processes, forked=True)
        try:
            pool.start()
            yield lambda db, images, chunk: self._chunk(
                db, images, chunk, lambda group: self._pooled(pool, group)
            )
        except BaseException:
            pool.close(wait=False)  # Ctrl-C or an error: drop what is running
            raise
        pool.close()

    def _chunk(
        self,
        db: ColmapDatabase,
        images: dict[int, _Image],
        chunk: Sequence[_Pair],
        run: Callable[[_Group], _Outcomes],
    ) -> list[Geometry]:
        """Verify one chunk: its groups (the method's; the fallback's), then its geometries."""
        opts = self.options
        verifier = self.pair_verifier()
        shape = opts.method == "gc-ransac"
        keypoints: dict[int, np.ndarray] = {}
        matches: list[np.ndarray] = []
        groups: dict[str, list[int]] = {"method": [], "fallback": []}
        results: list[tuple[dict[str, Any] | None, str]] = [(None, "")] * len(chunk)
        for k, pair in enumerate(chunk):
            m = db.matches(pair.image_id1, pair.image_id2)
            matches.append(m)
            if not verifier.verifiable(len(m)):
                results[k] = (None, "too few matches")
                self._advance()
                continue
            for i in (pair.image_id1, pair.image_id2):
                if i not in keypoints:
                    checked = self._checked_keypoints.pop(i, None)
                    keypoints[i] = db.keypoints(i, with_shape=shape) if checked is None else checked
            out_of_range = _out_of_range(m, keypoints[pair.image_id1], keypoints[pair.image_id2])
            if out_of_range:
                results[k] = (None, out_of_range)
                self._advance()
                continue
            posed = (
                images[pair.image_id1].pose is not None and images[pair.image_id2].pose is not None
            )
            groups[verifier.group(posed)].append(k)
        group_of = {k: name for name, indices in groups.items() for k in indices}
        geometries: list[Geometry | None] = [None] * len(chunk)
        for k, (result, error) in enumerate(results):
            if k not in group_of:  # too few matches, or unusable: nothing to verify
                geometries[k] = self._geometry(
                    images, chunk[k], matches[k], keypoints, result, error, None, None
                )
        for name, indices in groups.items():
            if not indices:
                continue
            # the pairs of most matches first: the pool deals them to its tasks in turn, so
            # that each child gets as much to do
            indices = sorted(indices, key=lambda k: -len(matches[k]))
            group = _Group(
                *verifier.method_of(name),
                images,
                keypoints,
                [(str(k), chunk[k].image_id1, chunk[k].image_id2, matches[k]) for k in indices],
            )
            # each result is taken in as it comes, while the others are still computing
            for index, result, error, pose in run(group):
                k = indices[index]
                geometries[k] = self._geometry(
                    images, chunk[k], matches[k], keypoints, result, error, name, pose
                )
                self._advance()
        done = [g for g in geometries if g is not None]
        assert len(done) == len(chunk)
        for g in done:  # the report's rows in the chunk's order, whatever order they ended in
            self.report["pairs"].append(self._rows.pop((g.image_id1, g.image_id2)))
        return done

    def _flight(self, group: _Group) -> Flight:
        """The group as the core's flight, from what the plan checked (cameras, poses,
        keypoints in their frames), the matches checked against the keypoints as they were
        read and the options checked at the start: no batch document built and parsed again
        (6 ms for the 108 Brighton pairs, before the first pair can go out)."""
        images = {
            str(i): FlightImage(
                group.images[i].camera,
                _rough(group.images[i]) if group.with_pose else _placeholder_pose(),
                group.keypoints[i],
            )
            for i in group.image_ids()
        }
        pairs = [FlightPair(str(a), str(b), m, id=label) for label, a, b, m in group.pairs]
        return Flight(images, pairs, group.method, self._verify_options)

    def _inline(self, group: _Group) -> _Outcomes:
        from hmcc_worker.outcomes import verify_flight

        for index, outcome in enumerate(verify_flight(self._flight(group))):
            yield (*_decoded(index, outcome.pack()), None)

    def _pooled(self, pool: Any, group: _Group) -> _Outcomes:
        # the pool's own tasks (one a child here: task_plan); each child computes its pairs'
        # relative poses too, in parallel, and reads its images' keypoints from one file
        # rather than from every task
        fn = functools.partial(verify_and_pose, min_inliers=self.options.min_inliers)
        with keypoints_in_file(self._flight(group)) as flight:
            for index, outcome in pool.map_flight(flight, fn=fn):
                yield _posed(index, outcome)

    def _taken(self, group: _Group) -> _Outcomes:
        """The group's pairs as they were verified where they were matched; those matched
        before (not among them) verified here."""
        assert self.verified is not None
        before = []
        for index, (_, a, b, _) in enumerate(group.pairs):
            verified = self.verified.get((a, b))
            if verified is None:
                before.append(index)
            else:
                yield index, *verified
        if before:
            rest = _replace_dc(group, pairs=[group.pairs[k] for k in before])
            for index, result, error, pose in self._inline(rest):
                yield before[index], result, error, pose

    def _remote(self, client: Any, group: _Group) -> _Outcomes:
        images = {
            str(i): {
                "camera": group.images[i].info.camera,
                "pose": group.images[i].pose if group.with_pose else PLACEHOLDER_POSE,
                "keypoints": group.keypoints[i],
            }
            for i in group.image_ids()
        }
        pairs = [
            {"id": label, "image1": str(a), "image2": str(b), "matches": m}
            for label, a, b, m in group.pairs
        ]
        items = client.verify_flight(
            images,
            pairs,
            method=group.method,
            params=self.options.params or None,
            binary=self.options.binary,
        )
        for item in items:
            if item.result is not None:
                yield item.index, item.result.to_dict(), "", None
            else:
                message = item.error.message if item.error is not None else item.status
                yield item.index, None, message, None

    def _geometry(
        self,
        images: dict[int, _Image],
        pair: _Pair,
        matches: np.ndarray,
        keypoints: Mapping[int, np.ndarray],
        result: dict[str, Any] | None,
        error: str,
        group: str | None,
        pose: Pose | None,
    ) -> Geometry:
        a, b = pair.image_id1, pair.image_id2
        img1, img2 = images[a], images[b]
        row: dict[str, Any] = {
            "image1": img1.info.name,
            "image2": img2.info.name,
            "matches": pair.matches,
            "inliers": 0,
            "method": None,
            "fallback": None,
            "fallback_reason": None,
            "time_ms": None,
            "config": "DEGENERATE",
            "pos_rotation_error_deg": None,
        }
        self._rows[(a, b)] = row
        totals = self.report["totals"]
        if group == "fallback":
            row["fallback"] = True
            row["fallback_reason"] = "no usable pose: " + "; ".join(
                f"{i.info.name}: {i.pose_issue}" for i in (img1, img2) if i.pose is None
            )
            totals["no_pose_pairs"] += 1
        if result is None:
            row["status"] = "too_few_matches" if error == "too few matches" else "failed"
            if row["status"] == "failed":
                row["error"] = error
                totals["failed"] += 1
            else:
                totals["too_few_matches"] += 1
            return Geometry(a, b, np.zeros((0, 2), np.int64))
        F, inliers = result_model(result)
        stats = result.get("statistics") or {}
        used = (stats.get("fallback") or {}).get("used")
        if group == "method":
            row["fallback"] = bool(used) if used is not None else None
            row["fallback_reason"] = (stats.get("fallback") or {}).get("reason")
        row["method"] = result.get("method")
        row["time_ms"] = (result.get("timings_ms") or {}).get("total")
        totals["verify_ms"] += row["time_ms"] or 0.0
        if row["fallback"] and group == "method":  # a pair without a pose is counted above
            totals["fallback_pairs"] += 1
        row["inliers"] = len(inliers)
        for image in (img1, img2):
            image.stats["pairs"] = image.stats.get("pairs", 0) + 1
            if row["fallback"]:
                image.stats["fallback"] = image.stats.get("fallback", 0) + 1
        if F is None or len(inliers) < self.options.min_inliers:
            row["status"] = "under_min_inliers"
            totals["under_min_inliers"] += 1
            return Geometry(a, b, np.zeros((0, 2), np.int64))
        kept = matches[inliers]
        if pose is None:  # not computed where the pair was verified
            pose = pair_pose(F, kept, img1.camera, img2.camera, keypoints[a], keypoints[b])
        R, t = pose
        if img1.R_world_to_cam is not None and img2.R_world_to_cam is not None and R is not None:
            rough = img2.R_world_to_cam @ img1.R_world_to_cam.T
            row["pos_rotation_error_deg"] = round(_angle_deg(rough.T @ R), 2)
            for image in (img1, img2):
                image.stats.setdefault("rotation_errors", []).append(row["pos_rotation_error_deg"])
        calibrated = img1.info.trusted_focal and img2.info.trusted_focal
        essential = None
        if calibrated and R is not None and t is not None:
            essential = _skew(t) @ R  # exactly essential, and the pose written beside it
        geometry = Geometry(a, b, kept, F, essential, R, t)
        row["config"] = geometry.config
        row["status"] = "verified"
        totals["verified"] += 1
        totals["inlier_matches"] += len(kept)
        for image in (img1, img2):
            image.stats["verified"] = image.stats.get("verified", 0) + 1
        return geometry

    # ------------------------------------------------------------------ the report

    def _start_report(
        self, images: dict[int, _Image], todo: Sequence[_Pair], skipped: int, without: int
    ) -> None:
        self.report = {
            "database": str(self.database),
            "method": self.options.method,
            "fallback_method": _fallback_method(self.options.params),
            "where": self.options.url
            or ("inline" if self._in_process(len(todo)) else f"{self.options.processes} processes"),
            "min_inliers": self.options.min_inliers,
            "totals": {
                "pairs": len(todo),
                "skipped_already_verified": skipped,
                "listed_without_matches": without,
                "written": 0,
                "verified": 0,
                "under_min_inliers": 0,
                "too_few_matches": 0,
                "failed": 0,
                "fallback_pairs": 0,
                "no_pose_pairs": 0,
                "inlier_matches": 0,
                "verify_ms": 0.0,
                "plan_s": 0.0,
                "startup_s": 0.0,
                "verify_s": 0.0,
                "images_without_pose": sum(
                    1 for i in images.values() if i.pose is None and i.pose_issue is not None
                ),
                "images_pos_not_fitting": 0,
                "images_attitude_estimated": len(self._estimated),
                "images_focal_from_exif": sum(1 for f in self._focal.values() if f[1] == "exif"),
                "pose_priors_written": {"positions": 0, "gravity": 0},
            },
            "pose_warning": None,
            "mounting": None,
            "mounting_hint": None,
            "images": {},
            "pairs": [],
        }
        self._done, self._total = 0, len(todo)
        if self.progress is not None:
            self.progress(0, len(todo))

    def _warn_without_poses(self, images: Mapping[int, _Image]) -> None:
        """``report["pose_warning"]``: one paragraph when more than half of the images have
        no usable pose (their pairs go to the fallback without the rough POS), saying how
        many, what was looked for and how to give poses; None otherwise."""
        lacking = [i for i in images.values() if i.pose is None]
        self.report["pose_warning"] = None
        if not images or len(lacking) <= POSELESS_SHARE_WARNED * len(images):
            return
        issues: dict[str, int] = {}
        for image in lacking:
            key = image.pose_issue or "no pose"
            issues[key] = issues.get(key, 0) + 1
        common = "; ".join(
            f"{n} x {issue}" for issue, n in sorted(issues.items(), key=lambda x: -x[1])[:3]
        )
        if self.poses_path is not None:
            where = f"the pose file {self.poses_path.name} gives no usable pose for them"
        else:
            where = f"looked for: {looked_for()}"
        self.report["pose_warning"] = (
            f"warning: {len(lacking)} of the {len(images)} images have no usable pose "
            f"({common}), so their pairs go to {_fallback_method(self.options.params)} "
            f"without the rough POS, not to {self.options.method}; {where}. Give the poses "
            f"with --poses FILE ({POSE_FILE_FORMATS})."
        )

    def _advance(self) -> None:
        self._done += 1
        if self.progress is not None:
            self.progress(self._done, self._total)

    def _finish_report(self, images: dict[int, _Image]) -> None:
        checked = [
            (r["image1"], r["image2"], r["pos_rotation_error_deg"] > POS_ROTATION_TOLERANCE_DEG)
            for r in self.report["pairs"]
            if r["pos_rotation_error_deg"] is not None
        ]
        misfits = blame(checked)
        out = {}
        for image in images.values():
            s = image.stats
            name = image.info.name
            errors = s.get("rotation_errors", [])
            out[name] = {
                "pose_source": image.pose_source,
                "pose_issue": image.pose_issue,
                "attitude": "estimated from the track" if name in self._estimated else None,
                "focal_px": round(self._focal[name][0], 1) if name in self._focal else None,
                "focal_source": self._focal[name][1] if name in self._focal else None,
                "pairs": s.get("pairs", 0),
                "verified": s.get("verified", 0),
                "fallback": s.get("fallback", 0),
                "pos_rotation_error_deg_median": (
                    round(float(np.median(errors)), 2) if errors else None
                ),
                "pos_fits": (name not in misfits) if errors else None,
            }
        self.report["images"] = out
        totals = self.report["totals"]
        totals["images_pos_not_fitting"] = len(misfits)
        totals["verify_ms"] = round(totals["verify_ms"], 2)
        self.report["mounting_hint"] = self._mounting_hint()

    def _mounting_hint(self) -> str | None:
        """One line suggesting ``--detect-mounting`` when most of the pairs the method took
        fell back, and no search ran."""
        if self.options.method not in POS_METHODS or self.options.detect_mounting:
            return None
        taken = [
            r
            for r in self.report["pairs"]
            if r["fallback"] is not None
            and not (r["fallback_reason"] or "").startswith("no usable")
        ]
        fell = sum(1 for r in taken if r["fallback"])
        if not taken or fell <= FALLBACK_SHARE_HINTED * len(taken):
            return None
        return (
            f"hint: {fell} of the {len(taken)} pairs verified with {self.options.method} fell "
            "back; if the camera is mounted (or the images were turned) otherwise than the "
            "poses say, try --detect-mounting"
        )


def blame(pairs: Sequence[tuple[str, str, bool]]) -> set[str]:
    """The images whose POS does not fit, from pairs ``(image1, image2, bad)`` (bad: the
    rough relative rotation is off the verified one). A bad pair does not say which of its
    images is wrong; the images with the largest share of bad pairs (more than half, at least
    two; all of them when several tie, as when two equal groups disagree and nothing says
    which is right) are, and their pairs are then explained; again until no image is left
    so."""
    flagged: set[str] = set()
    remaining = list(pairs)
    while True:
        tally: dict[str, list[int]] = {}
        for a, b, bad in remaining:
            for name in (a, b):
                t = tally.setdefault(name, [0, 0])
                t[0] += bad
                t[1] += 1
        scores = {name: (bad / total, bad) for name, (bad, total) in tally.items()}
        worst = max(scores.values(), default=(0.0, 0))
        if worst[0] <= 0.5 or worst[1] < 2:
            return flagged
        named = {name for name, score in scores.items() if score == worst}
        flagged |= named
        remaining = [p for p in remaining if p[0] not in named and p[1] not in named]


@functools.cache
def _options_adapter() -> TypeAdapter[VerifyOptions]:
    """Checks ``params`` (built once: 11 ms, as long as a run's planning)."""
    return TypeAdapter(VerifyOptions)


def check_keypoints(name: str, camera: Camera, kps: np.ndarray) -> None:
    """Refuse (:class:`ColmapInputError`) an image's keypoints outside its camera's frame."""
    outside = np.flatnonzero(~camera.in_frame(kps))
    if len(outside):
        x, y = kps[outside[0]]
        raise ColmapInputError(
            f"image {name}: keypoint at ({x:g}, {y:g}) lies outside its camera's "
            f"{camera.width} x {camera.height} px frame"
        )


def _fallback_method(params: Mapping[str, Any] | None) -> str:
    plus = (params or {}).get("plus") or {}
    return str(plus.get("fallback") or PlusOptions().fallback)


def _prior_fills(images: Mapping[int, _Image], sources: Mapping[str, ImagePose]) -> list[PriorFill]:
    """What the run knows for COLMAP's ``pose_priors``: each image's position (from its
    source, even without an attitude) and, with a usable pose, the gravity direction in its
    camera frame (the world's down, ``-z`` of east-north-up, rotated into the camera)."""
    fills = []
    for image in images.values():
        source = sources.get(image.info.name)
        position = None if source is None else source.position
        gravity = None
        if image.rough is not None:
            gravity = image.rough.R_world_to_cam @ np.array([0.0, 0.0, -1.0])
        if position is not None or gravity is not None:
            fills.append(PriorFill(image.info, position, gravity))
    return fills


def _turned(source: ImagePose, yaw: int) -> ImagePose:
    """``source`` with ``yaw`` deg added to its mounting's yaw: the camera turned about its
    optical axis where the mounting has no pitch or roll (unchanged: no turn, no yaw/pitch/roll
    attitude, a tilted mounting)."""
    attitude = source.attitude or {}
    mounting = dict(source.mounting or {"yaw": 0.0, "pitch": 0.0, "roll": 0.0})
    if not yaw or "yaw" not in attitude or mounting.get("pitch") or mounting.get("roll"):
        return source
    mounting["yaw"] = (float(mounting.get("yaw", 0.0)) + yaw + 180.0) % 360.0 - 180.0
    return _replace_dc(source, mounting=mounting)


def _turned_all(
    sources: Mapping[str, ImagePose], yaw: int, scope: set[str] | None
) -> dict[str, ImagePose]:
    """:func:`_turned` of the images named in ``scope`` (None: every image)."""
    return {n: _turned(p, yaw) if scope is None or n in scope else p for n, p in sources.items()}


def _motion_agrees(rough1: RoughPose, rough2: RoughPose, verified: Pose) -> bool | None:
    """Whether a pair's rough baseline, seen in the second camera (``x2 = R x1 + t``), points
    the way the verified pose's does in the image plane (within
    :data:`POS_ROTATION_TOLERANCE_DEG`); None where either direction lies too close to the
    optical axis to say (its part in the image plane under :data:`MIN_PLANAR_BASELINE` of
    its length: GNSS heights and a flat scene's near-degenerate geometry make that part
    unreliable). What tells a nadir camera from one turned about its optical axis: the turn
    leaves the pair's relative rotation as it was, and turns its baseline in the image."""
    R, t = verified
    if R is None or t is None:
        return None
    p1, p2 = pair_poses(rough1, rough2)
    b = (p2.R_world_to_cam @ (p1.center - p2.center))[:2]
    v = np.asarray(t, dtype=np.float64)[:2]
    nb = float(np.linalg.norm(p1.center - p2.center))
    if nb == 0.0 or np.linalg.norm(b) < MIN_PLANAR_BASELINE * nb:
        return None
    if np.linalg.norm(v) < MIN_PLANAR_BASELINE * float(np.linalg.norm(t)):
        return None
    cos = float(b @ v / (np.linalg.norm(b) * np.linalg.norm(v)))
    return math.degrees(math.acos(min(1.0, max(-1.0, cos)))) <= POS_ROTATION_TOLERANCE_DEG


def _rough(image: _Image) -> RoughPose:
    assert image.rough is not None
    return image.rough


@functools.cache
def _placeholder_pose() -> RoughPose:
    """:data:`PLACEHOLDER_POSE` as the core takes it."""
    return to_rough_pose(PoseModel.model_validate(PLACEHOLDER_POSE))


def _out_of_range(matches: np.ndarray, keypoints1: np.ndarray, keypoints2: np.ndarray) -> str:
    """Why a pair's (M, 2) matches do not index its images' keypoints ('' when they do)."""
    for side, keypoints in enumerate((keypoints1, keypoints2)):
        column = matches[:, side]
        if column.min() < 0 or column.max() >= len(keypoints):
            return (
                f"matches of image {side + 1} index keypoint {int(column.max())}, "
                f"beyond its {len(keypoints)} keypoints"
            )
    return ""


def _posed(index: int, outcome: Any) -> tuple[int, dict[str, Any] | None, str, Pose | None]:
    """A :func:`verify_and_pose` outcome as the run takes it in: its result with the
    inliers as an array, and the pose (None for an error, or a lost child's outcome)."""
    _, result, error = _decoded(index, outcome.pack())
    if not isinstance(outcome, PosedOutcome):
        return index, result, error, None
    assert result is not None
    result["inliers"] = outcome.inliers
    return index, result, error, outcome.pose


def _decoded(index: int, packed: bytes) -> tuple[int, dict[str, Any] | None, str]:
    status, raw = unpack(packed)
    body = orjson.loads(raw)
    if status is JobStatus.finished:
        return index, body, ""
    return index, None, str(body.get("message") or body.get("code"))


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def _angle_deg(R: np.ndarray) -> float:
    c = (float(np.trace(R)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


@contextmanager
def sigint_held() -> Iterator[None]:
    """Hold Ctrl-C until the block ends (then raise it): a transaction is never cut."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    old = signal.signal(signal.SIGINT, lambda sig, frame: got.append(sig))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
        if got:
            raise KeyboardInterrupt
