"""COLMAP benchmark: the verification stage of a real flight, COLMAP's against ``hmcc colmap``,
and what incremental mapping makes of each (issue #14; the paper's Table 5 question: does the
faster verification cost reconstruction quality?).

All 18 Brighton Beach images (``shared/fixtures/brighton-beach/images``, 2000 x 1125, DJI
EXIF and XMP), COLMAP's SIFT (pycolmap, CPU, max image size 2000, one shared camera) and
exhaustive matching without verification (``skip_geometric_verification``). The raw database
is built once and kept in ``--cache`` (default ``~/.cache/hmcc-match``). Then, on copies of it,
in this process:

* **colmap**: ``pycolmap.geometric_verification`` with its defaults (all cores);
* **hmcc-plus**, **hmcc-ransac**, **magsac++**, and the paper's Table 5 baselines
  **lo-ransac** and **gc-ransac**: ``hmcc_colmap.ColmapRun`` (what ``hmcc colmap`` runs) on a
  compute pool of 2 processes, POS from the images' EXIF/XMP. The pool is started
  and warmed by a first pass over a scratch copy (as a running service's pool is), timed
  apart ("start"); the stage is the whole run as ``pycolmap.geometric_verification``'s is:
  reading and checking the database, the images' tags and the keypoints, verifying, writing,
  the report and closing the database;
* **hmcc-plus, 1 process**: the same in this process (its start: loading the compiled core);

then ``pycolmap.incremental_mapping`` on each verified database: models, registered images,
3-D points, mean reprojection error (px) and mean track length of the largest model. Verified
pairs and inlier matches are counted the same way for every row from the database
(two_view_geometries rows with inliers).

Targets (issue #14): the stage in at most 1/10 of COLMAP's time; after mapping as many images,
at least 95 % of COLMAP's 3-D points, a reprojection error within 5 % of COLMAP's.

The machine is a shared 2-core one: times are noisy (COLMAP's own stage took 0.7-1.4 s in
single runs of earlier sessions). Each row's stage therefore runs ``--repeats`` times (default
5), each on a fresh copy of the raw database, the rows' runs interleaved (every row started
first, then COLMAP, hmcc-plus, ..., COLMAP, hmcc-plus, ...: the machine's speed drifts over
minutes), and the table gives the median and the range; the last copy is the one counted and
mapped. Results go to ``<out>/colmap.json`` and
``<out>/colmap.md``.

``--fixture caliterra`` (issue #31): the same end to end on a flight with GPS only, the 75
Caliterra images (``shared/fixtures/caliterra/images``, 1600 x 1200, no attitude tag), SIFT at
1000 px as ``bench_real``'s Caliterra (the same cached database), rows **colmap**,
**hmcc-plus** (each image's attitude estimated from the flight track, the camera's turn
searched) and **magsac++**; the attitude each run reported (:func:`attitude_figures`) and the
track's attitude against COLMAP's model (:func:`track_attitude_against`). Results go to
``<out>/colmap_caliterra.json`` and ``.md``. Usage (from the checkout's root)::

    .venv/bin/python -m benchmarks.bench_colmap [--fixture brighton|caliterra] [--images DIR]
                                                [--out DIR] [--cache DIR] [--repeats N]
                                                [--quick]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import shutil
import sqlite3
import statistics
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from hmcc.methods import POS_METHODS
from hmcc.pose import geodetic_to_enu
from hmcc_colmap import ColmapRun, RunOptions
from hmcc_colmap.poses import read_image_poses
from hmcc_colmap.track import capture_order, capture_times, track_attitude
from hmcc_colmap.verify import MOUNTING_YAWS
from hmcc_schema.convert import to_rough_pose
from hmcc_schema.models import PoseModel
from hmcc_worker.pool import ComputePool

from .common import (
    DEFAULT_FIXTURES,
    DEFAULT_OUT,
    environment,
    fmt,
    jsonable,
    verdict,
    with_code_hash,
)

MAX_IMAGE_SIZE = 2000
#: --quick: five images of strips 1 and 2 at 1000 px, COLMAP and hmcc-plus in this process.
QUICK_IMAGES = ("DJI_0024.JPG", "DJI_0025.JPG", "DJI_0033.JPG", "DJI_0034.JPG", "DJI_0035.JPG")
QUICK_ROWS = ("colmap", "hmcc-plus, 1 process")


def raw_database(images: Path, cache: Path, max_size: int = MAX_IMAGE_SIZE) -> tuple[Path, float]:
    """The matched, unverified database of ``images`` (cached by the images' names and sizes,
    the pycolmap version and the options); the seconds it took to build, 0 if cached."""
    return colmap_database(images, cache, max_size, matched=True)


def colmap_database(
    images: Path, cache: Path, max_size: int, *, matched: bool
) -> tuple[Path, float]:
    """The database of ``images``' SIFT features at ``max_size`` and, if ``matched``, their
    exhaustive matches without verification (cached by the images' names and sizes, the
    pycolmap version and the size); the seconds it took to build, 0 if cached. A matched
    database is a copy of the features one (cached too, and read from the cache if there),
    then matched: one extraction serves both."""
    key = hashlib.sha1(
        json.dumps(
            [
                pycolmap.__version__,
                max_size,
                sorted((p.name, p.stat().st_size) for p in images.iterdir()),
            ]
        ).encode()
    ).hexdigest()[:12]
    kind = "raw" if matched else "features"
    path = cache / f"{fixture_label(images)}-{kind}-{key}.db"
    if path.is_file():
        return path, 0.0
    # named "brighton-" whatever the images before the name carried them: the key (images'
    # names and sizes, pycolmap, size) is the same, so is the database
    legacy = cache / f"brighton-{kind}-{key}.db"
    if legacy.is_file():
        return legacy, 0.0
    cache.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".partial")
    partial.unlink(missing_ok=True)
    if matched:
        features, features_s = colmap_database(images, cache, max_size, matched=False)
        t0 = time.perf_counter()
        shutil.copy(features, partial)
        matching = pycolmap.FeatureMatchingOptions()
        matching.skip_geometric_verification = True
        pycolmap.match_exhaustive(partial, matching_options=matching, device=pycolmap.Device.cpu)
        partial.rename(path)
        return path, features_s + time.perf_counter() - t0
    t0 = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_size
    pycolmap.extract_features(
        partial,
        images,
        camera_mode=pycolmap.CameraMode.SINGLE,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    partial.rename(path)
    return path, time.perf_counter() - t0


def fixture_label(images: Path) -> str:
    """The name a cached database of ``images`` carries: the fixture's folder (``caliterra``
    for ``.../caliterra/images``), else the images' folder; ``scratch`` for a copy in a
    temporary folder (``--quick``'s: its name changes from run to run, the key does not)."""
    resolved = images.resolve()
    if resolved.is_relative_to(Path(tempfile.gettempdir()).resolve()):
        return "scratch"
    folder = resolved.parent if resolved.name == "images" else resolved
    return folder.name or "images"


def counts(db: Path) -> dict[str, int]:
    con = sqlite3.connect(db)
    try:
        matched, raw = con.execute(
            "SELECT COUNT(*), SUM(rows) FROM matches WHERE rows > 0"
        ).fetchone()
        verified, inliers = con.execute(
            "SELECT COUNT(*), COALESCE(SUM(rows), 0) FROM two_view_geometries WHERE rows > 0"
        ).fetchone()
    finally:
        con.close()
    return {
        "matched_pairs": matched,
        "raw_matches": raw,
        "verified_pairs": verified,
        "inlier_matches": inliers,
    }


def mapping(db: Path, images: Path, out: Path) -> dict[str, Any]:
    """Incremental mapping's models; the largest one's figures."""
    out.mkdir(parents=True, exist_ok=True)
    options = pycolmap.IncrementalPipelineOptions()
    t0 = time.perf_counter()
    models = pycolmap.incremental_mapping(db, images, out, options)
    seconds = time.perf_counter() - t0
    if not models:
        return {"models": 0, "registered": 0, "mapping_s": seconds}
    best = max(models.values(), key=lambda m: m.num_reg_images())
    return {
        "models": len(models),
        "registered": best.num_reg_images(),
        "registered_all_models": sum(m.num_reg_images() for m in models.values()),
        "points3d": best.num_points3D(),
        "reprojection_error_px": best.compute_mean_reprojection_error(),
        "track_length": best.compute_mean_track_length(),
        "mapping_s": seconds,
    }


def largest_model(out: Path) -> pycolmap.Reconstruction | None:
    """The model with the most registered images that :func:`mapping` wrote under ``out``."""
    models = [pycolmap.Reconstruction(str(d)) for d in sorted(out.iterdir()) if d.is_dir()]
    return max(models, key=lambda m: m.num_reg_images(), default=None)


def track_attitude_against(model: pycolmap.Reconstruction, images: Path) -> dict[str, Any]:
    """How far the attitude ``hmcc colmap`` estimates from the flight track (nadir, image top
    along the direction of travel) is from the cameras of ``model``, for each turn of
    :data:`hmcc_colmap.verify.MOUNTING_YAWS` added to the mounting. The model is put in the
    world by its 3-D points' best plane (levelled: the vertical; GNSS heights are too rough
    to level it) and the least-squares rotation about the vertical (with a scale) from its
    camera centres to the images' GPS positions (east, north); each image's error is the
    angle (deg) between its estimated world-to-camera rotation and the model's. Also: the
    model's cameras' tilt from nadir (deg) and the horizontal residual of the fit (m)."""
    by_name = {i.name: i for i in model.images.values()}
    names = sorted(by_name)
    sources = read_image_poses(images, names)
    times = capture_times(images, names)
    sources, estimated = track_attitude(sources, names, times, images)
    order = [n for n in capture_order(names, times) if n in estimated]
    if len(order) < 3:
        return {}
    wgs84 = [sources[n].position or {} for n in order]  # EXIF GPS: every one has a position
    lat, lon = (np.array([g[k] for g in wgs84]) for k in ("lat", "lon"))
    enu = geodetic_to_enu(lat, lon, np.zeros(len(order)), (lat.mean(), lon.mean(), 0.0))
    points = np.array([p.xyz for p in model.points3D.values()])
    centres = np.array([by_name[n].projection_center() for n in order])
    normal = np.linalg.svd(points - points.mean(0))[2][2]
    if (centres - points.mean(0)).mean(0) @ normal < 0:
        normal = -normal
    level = _rotation_between(normal, np.array([0.0, 0.0, 1.0]))
    x = (centres @ level.T)[:, :2]
    x, y = x - x.mean(0), enu[:, :2] - enu[:, :2].mean(0)
    u, sv, vt = np.linalg.svd(y.T @ x)
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    turn = np.eye(3)
    turn[:2, :2] = u @ d @ vt
    scale = float(np.trace(np.diag(sv) @ d) / (x**2).sum())
    residual = np.linalg.norm(y - scale * x @ turn[:2, :2].T, axis=1)
    to_world = turn @ level  # model frame to ENU (rotation)
    true = {n: by_name[n].cam_from_world().rotation.matrix() @ to_world.T for n in order}
    out: dict[str, Any] = {
        "images": len(order),
        "fit_residual_m_median": round(float(np.median(residual)), 1),
        "tilt_deg_median": round(
            float(np.median([np.degrees(np.arccos(-true[n][2, 2])) for n in order])), 1
        ),
        "by_turn": {},
    }
    for yaw in MOUNTING_YAWS:
        errors = {}
        for n in order:
            turned = replace(sources[n], mounting={"yaw": yaw, "pitch": 0.0, "roll": 0.0})
            assert turned.pose is not None
            R = to_rough_pose(PoseModel.model_validate(turned.pose)).R_world_to_cam
            cos = (np.trace(true[n] @ R.T) - 1.0) / 2.0
            errors[n] = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        values = np.array(list(errors.values()))
        out["by_turn"][str(yaw)] = {
            "median_deg": round(float(np.median(values)), 1),
            "p90_deg": round(float(np.percentile(values, 90)), 1),
            "over_45_deg": sorted(n for n, e in errors.items() if e > 45.0),
        }
    return out


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b`` (3,)."""
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


class Row:
    """One row's verification: :meth:`start` (its start, timed apart), :meth:`once` on a
    copy of the database (the stage's seconds and the run's report), :meth:`close`."""

    def __init__(self, name: str, mapped: bool) -> None:
        self.name, self.mapped = name, mapped

    def start(self, scratch: Path, images: Path) -> float:
        return 0.0

    def once(self, db: Path, images: Path) -> tuple[float, dict[str, Any] | None]:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def figures(
        self, samples: list[float], reports: list[dict[str, Any] | None], startup: float
    ) -> dict[str, Any]:
        return {"stage_s": statistics.median(samples), "stage_samples_s": samples, "startup_s": 0.0}


class ColmapRow(Row):
    """``pycolmap.geometric_verification`` with its defaults."""

    def once(self, db: Path, images: Path) -> tuple[float, dict[str, Any] | None]:
        t0 = time.perf_counter()
        pycolmap.geometric_verification(db)
        return time.perf_counter() - t0, None


class HmccRow(Row):
    """ColmapRun in this process (``processes`` 0) or on one running pool of ``processes``
    children, warmed by a first pass over a scratch copy (as a service's pool is): the stage
    is the wall time of the run less its own start (``totals.startup_s``: loading the
    compiled core in this process), which holds reading and checking (``plan_s``), verifying
    and writing (``verify_s``), the report and closing the database; starting and warming the
    pool is the row's start."""

    def __init__(self, name: str, mapped: bool, method: str, processes: int) -> None:
        super().__init__(name, mapped)
        self.options = RunOptions(method=method, processes=processes)
        self.pool: ComputePool | None = None

    def start(self, scratch: Path, images: Path) -> float:
        if self.options.processes <= 0:
            return 0.0
        t0 = time.perf_counter()
        self.pool = ComputePool(self.options.processes)
        self.pool.start()
        ColmapRun(scratch, images=images, options=self.options, pool=self.pool).run()
        return time.perf_counter() - t0

    def once(self, db: Path, images: Path) -> tuple[float, dict[str, Any] | None]:
        t0 = time.perf_counter()
        report = ColmapRun(db, images=images, options=self.options, pool=self.pool).run()
        return time.perf_counter() - t0 - report["totals"]["startup_s"], report

    def close(self) -> None:
        if self.pool is not None:
            self.pool.close()
            self.pool = None

    def figures(
        self, samples: list[float], reports: list[dict[str, Any] | None], startup: float
    ) -> dict[str, Any]:
        done = [r for r in reports if r is not None]
        middle = done[samples.index(statistics.median_low(samples))]["totals"]
        last = done[-1]
        misfits = sorted(n for n, i in last["images"].items() if i["pos_fits"] is False)
        return {
            "stage_s": statistics.median(samples),
            "stage_samples_s": samples,
            "plan_s": middle["plan_s"],
            "verify_s": middle["verify_s"],
            "startup_s": startup + last["totals"]["startup_s"],
            "fallback_pairs": last["totals"]["fallback_pairs"],
            "pos_not_fitting": misfits,
            **attitude_figures(last),
        }


def attitude_figures(report: dict[str, Any]) -> dict[str, Any]:
    """What a run of ``hmcc colmap`` says of its images' attitude: how many the track gave,
    the mounting it searched (or None) and its hint, why pairs fell back (reason: pairs), the
    median over the images of their rough-against-verified relative rotation (deg)."""
    if report.get("method") not in POS_METHODS:
        return {}
    reasons: dict[str, int] = {}
    for pair in report["pairs"]:
        if pair.get("fallback"):
            why = re.sub(r"\d+", "N", str(pair.get("fallback_reason") or "-"))
            reasons[why] = reasons.get(why, 0) + 1
    medians = [
        i["pos_rotation_error_deg_median"]
        for i in report["images"].values()
        if i.get("pos_rotation_error_deg_median") is not None
    ]
    return {
        "images_attitude_estimated": report["totals"].get("images_attitude_estimated", 0),
        "mounting": report.get("mounting"),
        "mounting_hint": report.get("mounting_hint"),
        "fallback_reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])),
        "pos_rotation_error_deg_median": (
            round(statistics.median(medians), 2) if medians else None
        ),
    }


ROWS: list[Row] = [
    ColmapRow("colmap", True),
    HmccRow("hmcc-plus", True, "hmcc-plus", 2),
    HmccRow("hmcc-plus, 1 process", False, "hmcc-plus", 0),
    HmccRow("hmcc-ransac", True, "hmcc-ransac", 2),
    HmccRow("magsac++", True, "magsac++", 2),
    # the paper's Table 5 baselines
    HmccRow("lo-ransac", True, "lo-ransac", 2),
    HmccRow("gc-ransac", True, "gc-ransac", 2),
]


@dataclass(frozen=True)
class Fixture:
    """A flight the benchmark runs: its images, SIFT's size, the rows, the results' file
    name (``<out>/<stem>.json``) and a sentence on the images."""

    images: Path
    max_size: int
    rows: tuple[str, ...]
    stem: str
    about: str


FIXTURES = {
    "brighton": Fixture(
        DEFAULT_FIXTURES / "images",
        MAX_IMAGE_SIZE,
        tuple(r.name for r in ROWS),
        "colmap",
        "Brighton Beach images",
    ),
    # as bench_real's caliterra: SIFT at 1000 px (one cached database for both)
    "caliterra": Fixture(
        DEFAULT_FIXTURES.parent / "caliterra" / "images",
        1000,
        ("colmap", "hmcc-plus", "magsac++"),
        "colmap_caliterra",
        "Caliterra images (GPS only: no attitude tag; `hmcc colmap` estimates each image's "
        "attitude from the flight track)",
    ),
}


def timed_rows(
    rows: list[Row], dbs: dict[str, list[Path]], raw: Path, images: Path
) -> dict[str, dict[str, Any]]:
    """Every row started, then the rows' runs interleaved (COLMAP, hmcc-plus, ..., COLMAP,
    hmcc-plus, ...): the machine's speed drifts over minutes, and a row timed after another
    would be measured on another machine than the one it is compared with."""
    starts = {}
    try:
        for row in rows:
            scratch = dbs[row.name][0].with_name("warm.db")
            shutil.copy(raw, scratch)
            starts[row.name] = row.start(scratch, images)
            scratch.unlink()
        samples: dict[str, list[float]] = {row.name: [] for row in rows}
        reports: dict[str, list[dict[str, Any] | None]] = {row.name: [] for row in rows}
        for k in range(len(dbs[rows[0].name])):
            for row in rows:
                seconds, report = row.once(dbs[row.name][k], images)
                samples[row.name].append(seconds)
                reports[row.name].append(report)
    finally:
        for row in rows:
            row.close()
    return {
        row.name: row.figures(samples[row.name], reports[row.name], starts[row.name])
        for row in rows
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--fixture", choices=sorted(FIXTURES), default="brighton")
    p.add_argument("--images", type=Path, help="the fixture's images (default: its own)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "hmcc-match")
    p.add_argument("--quick", action="store_true", help="5 images at 1000 px, 2 rows (smoke)")
    p.add_argument(
        "--repeats", type=int, default=5, help="verifications of each row (median; default 5)"
    )
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="hmcc-bench-colmap-") as tmp:
        return run(args, Path(tmp))


def run(args: argparse.Namespace, tmp: Path) -> int:
    fixture = FIXTURES[args.fixture]
    images = args.images or fixture.images
    max_size, rows_to_run = fixture.max_size, [r for r in ROWS if r.name in fixture.rows]
    if args.quick:
        if args.fixture != "brighton":
            raise SystemExit("--quick: Brighton's images only")
        source, images = images, tmp / "images"
        images.mkdir()
        for name in QUICK_IMAGES:
            shutil.copy(source / name, images / name)
        max_size = 1000
        rows_to_run = [r for r in ROWS if r.name in QUICK_ROWS]
    raw, build_s = raw_database(images, args.cache, max_size)
    how = f"built in {build_s:.0f} s" if build_s else "cached"
    print(f"raw database {raw} ({how})")
    repeats = 1 if args.quick else max(1, args.repeats)
    dbs: dict[str, list[Path]] = {}
    for row in rows_to_run:
        stem = row.name.replace(" ", "_").replace(",", "")
        dbs[row.name] = [tmp / f"{stem}-{k}.db" for k in range(repeats)]
        for db in dbs[row.name]:
            shutil.copy(raw, db)
    figures = timed_rows(rows_to_run, dbs, raw, images)
    rows: list[dict[str, Any]] = []
    track_error: dict[str, Any] | None = None
    for row in rows_to_run:
        db = dbs[row.name][-1]  # counted and mapped
        out: dict[str, Any] = {"row": row.name, **figures[row.name], **counts(db)}
        if row.mapped or args.quick:
            out.update(mapping(db, images, tmp / f"{db.stem}-sparse"))
            if row.name == "colmap" and args.fixture != "brighton":
                model = largest_model(tmp / f"{db.stem}-sparse")
                if model is not None:
                    track_error = track_attitude_against(model, images)
        rows.append(out)
        print(json.dumps(jsonable(out)))
    colmap = rows[0]
    for other in rows[1:]:
        other["stage_vs_colmap"] = other["stage_s"] / colmap["stage_s"]
    summary = targets(rows)
    doc: dict[str, Any] = {
        "meta": {
            **environment(),
            "pycolmap": pycolmap.__version__,
            "images": sum(1 for p in images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg")),
            "max_image_size": max_size,
            "quick": args.quick,
            "raw_database_build_s": build_s or None,
            "repeats": repeats,
            "note": (
                f"shared, noisy 2-core machine; stage times are medians of {repeats} runs, "
                "the rows' runs interleaved"
            ),
        },
        "rows": rows,
        "targets": summary,
    }
    if args.fixture != "brighton":  # Brighton's results as they were (the paper report's)
        doc["meta"].update(fixture=args.fixture, about=fixture.about)
        doc["track_attitude_against_colmap"] = track_error
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{fixture.stem}.json").write_text(
        json.dumps(jsonable(with_code_hash(doc, __file__)), indent=2) + "\n"
    )
    (args.out / f"{fixture.stem}.md").write_text(markdown(doc))
    print(markdown(doc))
    return 0


def targets(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    colmap = rows[0]
    plus = next(r for r in rows if r["row"].startswith("hmcc-plus"))
    out = [
        {
            "target": f"{plus['row']} stage <= 1/10 of COLMAP's",
            "value": plus["stage_s"] / colmap["stage_s"],
            "ok": plus["stage_s"] <= colmap["stage_s"] / 10,
        }
    ]
    if "points3d" in colmap and "points3d" in plus:
        out += [
            {
                "target": "hmcc-plus registers as many images",
                "value": plus["registered"],
                "ok": plus["registered"] >= colmap["registered"],
            },
            {
                "target": "hmcc-plus >= 95 % of COLMAP's 3-D points",
                "value": plus["points3d"] / colmap["points3d"],
                "ok": plus["points3d"] >= 0.95 * colmap["points3d"],
            },
            {
                "target": "hmcc-plus reprojection error within 5 % of COLMAP's",
                "value": plus["reprojection_error_px"] / colmap["reprojection_error_px"],
                "ok": plus["reprojection_error_px"] <= 1.05 * colmap["reprojection_error_px"],
            },
        ]
    return out


def markdown(doc: dict[str, Any]) -> str:
    meta = doc["meta"]
    fixture = meta.get("fixture", "brighton")
    title = "COLMAP project: verification stage and reconstruction (issue #14)"
    command = ".venv/bin/python -m benchmarks.bench_colmap"
    if fixture != "brighton":
        title = f"COLMAP project end to end: {fixture.capitalize()} (issue #31)"
        command += f" --fixture {fixture}"
    lines = [
        f"# {title}",
        "",
        f"{meta['images']} {meta.get('about', 'Brighton Beach images')}, COLMAP SIFT at "
        f"{meta['max_image_size']} px, "
        f"exhaustive matching without verification (pycolmap {meta['pycolmap']}), then each "
        "row's verification on a copy of that database and `pycolmap.incremental_mapping`. "
        f"{meta['note']}. Reproduce: `{command}`.",
        "",
        "| row | stage (s) | runs (s) | x COLMAP | start (s) | verified pairs | inlier matches | "
        "models | registered | 3-D points | reproj. error (px) | track length | fallback pairs |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["rows"]:
        runs = r.get("stage_samples_s") or [r["stage_s"]]
        lines.append(
            f"| {r['row']} | {r['stage_s']:.3f} | {min(runs):.3f}-{max(runs):.3f} | "
            f"{fmt(r.get('stage_vs_colmap'), 3)} | "
            f"{r['startup_s']:.2f} | {r['verified_pairs']} of {r['matched_pairs']} | "
            f"{r['inlier_matches']} of {r['raw_matches']} | {r.get('models', '-')} | "
            f"{r.get('registered', '-')} | {r.get('points3d', '-')} | "
            f"{fmt(r.get('reprojection_error_px'), 3)} | {fmt(r.get('track_length'), 2)} | "
            f"{r.get('fallback_pairs', '-')} |"
        )
    lines += ["", "| target | value | |", "|---|---|---|"]
    for t in doc["targets"]:
        lines.append(f"| {t['target']} | {fmt(t['value'], 3)} | {verdict(t['ok'])} |")
    lines += attitude_lines(doc["rows"])
    against = doc.get("track_attitude_against_colmap")
    if against:
        lines += [
            "",
            "The attitude from the track against COLMAP's model (the `colmap` row's: levelled "
            "by its 3-D points' plane, turned about the vertical onto the images' GPS positions, "
            f"horizontal residual {against['fit_residual_m_median']} m median; its cameras "
            f"{against['tilt_deg_median']} deg from nadir, median): the angle between each of "
            f"the {against['images']} images' estimated camera rotation and the model's, by the "
            "turn added to the mounting:",
            "",
            "| turn (deg) | median (deg) | 90th percentile (deg) | over 45 deg |",
            "|---|---|---|---|",
        ]
        for yaw, t in against["by_turn"].items():
            over = t["over_45_deg"]
            said = ", ".join(over) if len(over) <= 25 else f"{len(over)} images"
            lines.append(f"| {yaw} | {t['median_deg']:.1f} | {t['p90_deg']:.1f} | {said or '-'} |")
        for r in doc["rows"]:
            mounting = r.get("mounting")
            if not mounting or str(mounting["yaw_deg"]) not in against["by_turn"]:
                continue
            off = set(against["by_turn"][str(mounting["yaw_deg"])]["over_45_deg"])
            flagged = set(r.get("pos_not_fitting", ()))
            lines += [
                "",
                f"{r['row']}, under the turn it found ({mounting['yaw_deg']} deg): of the "
                f"{len(off)} images over 45 deg off the model, its report lists "
                f"{len(off & flagged)} as not fitting their POS, and "
                f"{len(flagged - off)} more ({', '.join(sorted(flagged - off)) or 'none'}).",
            ]
    misfits = {r["row"]: r["pos_not_fitting"] for r in doc["rows"] if r.get("pos_not_fitting")}
    if misfits:
        lines += ["", "Images whose POS did not fit their pixels (report of `hmcc colmap`):", ""]
        lines += [f"- {row}: {', '.join(names)}" for row, names in misfits.items()]
    return "\n".join(lines) + "\n"


def attitude_lines(rows: list[dict[str, Any]]) -> list[str]:
    """The attitude and mounting each ``hmcc colmap`` row's run reported (rows that have it)."""
    told = [r for r in rows if "images_attitude_estimated" in r]
    if not told:
        return []
    lines = [
        "",
        "What each run of `hmcc colmap` reported of the images' attitude (its report: "
        "`images_attitude_estimated`, `mounting`, `mounting_hint`, the pairs' fallback "
        "reasons; rough against verified: the median over the images of the median angle "
        "between a pair's relative rotation from the rough poses and the verified one):",
        "",
        "| row | attitude from the track | mounting | rough against verified (deg) | "
        "fallbacks: why |",
        "|---|---|---|---|---|",
    ]
    for r in told:
        mounting = r.get("mounting")
        if mounting:
            tried = ", ".join(
                f"{t['yaw_deg']}: {t.get('consistent', '-')}/{t['kept']}" for t in mounting["tried"]
            )
            said = (
                f"{mounting['yaw_deg']} deg ({mounting.get('images', 'every image')}; of "
                f"{mounting['sample_pairs']} pairs sampled, by yaw: baselines consistent/pairs "
                f"kept {tried or 'none'})"
            )
        else:
            said = "not searched" + (f"; {r['mounting_hint']}" if r.get("mounting_hint") else "")
        why = "; ".join(f"{n} x {reason}" for reason, n in r["fallback_reasons"].items())
        lines.append(
            f"| {r['row']} | {r['images_attitude_estimated']} images | {said} | "
            f"{fmt(r.get('pos_rotation_error_deg_median'), 2)} | {why or '-'} |"
        )
    return lines


if __name__ == "__main__":
    raise SystemExit(main())
