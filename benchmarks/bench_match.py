"""Matching benchmark: COLMAP's exhaustive matching and verification against ``hmcc match``
(matching guided by the rough POS) and ``hmcc colmap`` (issue #32), and what incremental
mapping makes of each.

Two flights (``--fixture``, :data:`FIXTURES`):

* **brighton**: all 18 Brighton Beach images (``shared/fixtures/brighton-beach/images``,
  2000 x 1125, DJI EXIF and XMP: GPS, gimbal attitude, height above the take-off point),
  SIFT at 1600 px; every pair (153). The matcher's rules were tuned here.
* **caliterra**: all 75 Caliterra images (``shared/fixtures/caliterra/images``, 1600 x 1200,
  EXIF GPS only), SIFT at 1000 px (as ``bench_real`` and ``bench_pairs``); every pair (2775).
  Its attitude is estimated from the flight track (``hmcc_colmap.track``, as ``hmcc colmap``
  and ``hmcc pairs`` take it); its GPS altitudes climb by over 100 m along a flight at one
  height, so ``hmcc match`` takes every camera :data:`CALITERRA_FLYING_HEIGHT_M` above the
  ground below it (``--flying-height``; the height ``bench_pairs`` estimated from COLMAP's
  exhaustive model and the GPS); COLMAP's prior focal length here is the original 4000 px
  image's (its EXIF focal-plane resolution), 2.5 times too long, and ``hmcc match`` takes the
  EXIF's for the stored size. Split: the pairs among its first 38 images were looked at
  (why pairs went unmatched: the position correction came of it), the last 37 images
  are held out; each row's verified pairs are counted by part (:func:`by_part`).

COLMAP's SIFT (pycolmap, CPU, one shared camera), extracted once and kept in ``--cache``
(default ``~/.cache/hmcc-match``). Then, on copies of that database, the same features and
the same pairs:

* **colmap**: ``pycolmap.match_exhaustive`` with its default options (SIFT ratio 0.8,
  max distance 0.7, cross check; its geometric verification included), all cores;
* **hmcc match --verify**: :class:`hmcc_colmap.guided_match.GuidedMatchRun` with
  ``MatchOptions.verify`` (what ``hmcc match --verify`` runs): one run on ``--processes``
  children, each pair verified (hmcc-plus) in the child that matched it, then the two-view
  geometries written as ``hmcc colmap`` writes them; the stage is its wall time, the pool's
  start and loading the compiled core included. The targets are this row's;
* **hmcc match + hmcc colmap**: :class:`hmcc_colmap.guided_match.GuidedMatchRun` (what
  ``hmcc match`` runs; POS and the ground from the images' EXIF/XMP) on ``--processes``
  children, then :class:`hmcc_colmap.ColmapRun` (``hmcc colmap``, hmcc-plus) in this
  process (``--processes 0``, the quicker on 18 images): the stage is both runs' wall time,
  their starts (the pool, loading the compiled core) included;
* **hmcc match + COLMAP verification**: the same matches verified by
  ``pycolmap.geometric_verification`` (its defaults), to tell the matcher's share;
* **CLI hmcc match --verify** and **CLI hmcc match; hmcc colmap**: the commands as a user runs
  them, each a fresh process (``python -m hmcc_cli``) paying the interpreter's start, the
  imports and loading the compiled core: what the rows above, in this process, do not pay.

The compiled loops of the matcher and the verification are loaded in this process before
the timed runs, so that no in-process row pays that once for the others; the hmcc rows' order
turns by one each repeat.

then ``pycolmap.incremental_mapping`` on each database: models, registered images, 3-D
points, mean reprojection error (px) of the largest model, and its tracks (:func:`tracks`:
track lengths, each observation's reprojection error, each point's mean error by its track's
length). Pairs, matches and inliers are counted the same way for every row from the
database; each pair of ``hmcc match``'s report takes its inliers from the database after
verification (the report per pair: candidates compared per keypoint, matches, inliers,
time).

Brighton: six images (strip 1, DJI_0024 to DJI_0029) were turned by 180 deg after capture (the
fixture's README): their pixels do not fit their attitude tags, as a wrong mounting would
not. The report of ``hmcc match`` says how their pairs were matched (``pose-mismatch``:
brute force after a first pass that found no consistent shift).

Targets (issue #32, row ``hmcc match --verify``): matching + verification in at most 1/5
of COLMAP's time; after mapping
at least as many registered images and 3-D points as COLMAP, the mean reprojection error
within 5 % of COLMAP's.

The machine is a shared 2-core one: times are noisy; ``--repeats`` runs of each row (median),
interleaved. Results go to ``<out>/match.json`` and ``<out>/match.md`` (Brighton),
``<out>/match-caliterra.json`` and ``.md`` (Caliterra). Usage (from the checkout's root)::

    .venv/bin/python -m benchmarks.bench_match [--fixture brighton|caliterra] [--images DIR]
                                               [--out DIR] [--cache DIR] [--repeats N]
                                               [--processes N] [--quick] [--note TEXT]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from hmcc.guided import GuidedOptions
from hmcc_colmap import ColmapRun, RunOptions
from hmcc_colmap.guided_match import GuidedMatchRun, MatchOptions, warm_up

from .bench_colmap import QUICK_IMAGES, colmap_database, counts
from .common import (
    DEFAULT_FIXTURES,
    DEFAULT_OUT,
    environment,
    fmt,
    jsonable,
    verdict,
    with_code_hash,
)

MAX_IMAGE_SIZE = 1600
#: Brighton, strip 1: pixels turned by 180 deg relative to the attitude tags (its README).
TURNED = tuple(f"DJI_00{k}.JPG" for k in range(24, 30))
#: Caliterra's flying height (m): ``bench_pairs``'s estimate from COLMAP's exhaustive model
#: and the GPS (``benchmarks/results/pairs.md``).
CALITERRA_FLYING_HEIGHT_M = 62.3
#: The reprojection error may exceed COLMAP's by this share (issue #32).
REPROJECTION_TOLERANCE = 0.05


@dataclass(frozen=True)
class Fixture:
    """A flight: its title, images, SIFT size, results file stem, ``hmcc match``'s options
    beyond the defaults, the images turned after capture, what was tuned on it, and
    ``looked_at``: the first that many images (by name, the capture order) were looked at
    while tuning and the others were not (0: no split; each row's verified pairs are then
    counted by part: :func:`by_part`)."""

    title: str
    images: Path
    max_size: int
    stem: str
    match_options: dict[str, Any]
    turned: tuple[str, ...]
    about: str
    looked_at: int = 0


FIXTURES = {
    "brighton": Fixture(
        "Brighton Beach",
        DEFAULT_FIXTURES / "images",
        MAX_IMAGE_SIZE,
        "match",
        {},
        TURNED,
        "DJI FC300S, EXIF/XMP GPS and gimbal attitude, the ground at the take-off point "
        "(RelativeAltitude). The matcher's rules were chosen here.",
    ),
    "caliterra": Fixture(
        "Caliterra",
        DEFAULT_FIXTURES.parent / "caliterra" / "images",
        1000,
        "match-caliterra",
        {"flying_height_m": CALITERRA_FLYING_HEIGHT_M},
        (),
        "Canon PowerShot SX260 HS, EXIF GPS only: the attitude estimated from the flight "
        "track, every camera 62.3 m above the ground below it (`--flying-height`, bench_pairs' "
        "estimate; the GPS altitudes drift), the focal length from the EXIF (COLMAP's prior is "
        "the 4000 px original's). **Split**: the pairs among the first 38 images (IMG_9354 to "
        "IMG_9391) were looked at to find why pairs went unmatched (which led to the position "
        "correction); the last 37 images are held out (the table by part below).",
        38,
    ),
}


def colmap_row(db: Path, images: Path, processes: int, fixture: Fixture) -> dict[str, Any]:
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    return {"stage_s": time.perf_counter() - t0}


def _guided(
    db: Path, images: Path, processes: int, fixture: Fixture
) -> tuple[float, dict[str, Any]]:
    t0 = time.perf_counter()
    options = MatchOptions(processes=processes, **fixture.match_options)
    report = GuidedMatchRun(db, images=images, options=options).run()
    return time.perf_counter() - t0, report


def _match_figures(report: dict[str, Any], fixture: Fixture) -> dict[str, Any]:
    t = report["totals"]
    turned = [
        r for r in report["pairs"] if r["image1"] in fixture.turned or r["image2"] in fixture.turned
    ]
    return {
        "turned_images": turned_images(report),
        "modes": t["modes"],
        "candidates_per_keypoint_mean": t["candidates_per_keypoint_mean"],
        "ground_z_m": report["ground_z_m"],
        "ground_z_source": report["ground_z_source"],
        "images_attitude_estimated": t.get("images_attitude_estimated", 0),
        "images_focal_from_exif": t.get("images_focal_from_exif", 0),
        "turned_image_pairs_modes": _count(r["mode"] for r in turned),
        "turned_image_pairs_matches": sum(r["matches"] for r in turned),
        "pairs": report["pairs"],
    }


def turned_images(report: dict[str, Any]) -> dict[str, str]:
    """Image -> ``"180 deg in 9 of 11 pairs"`` for the images found turned by the same angle
    in at least half of their pairs matched with the POS (``guided``, ``guided-turned``)."""
    guided = _count(
        name
        for r in report["pairs"]
        if r["mode"].startswith("guided")
        for name in (r["image1"], r["image2"])
    )
    out = {}
    for name, image in report["images"].items():
        for turn, pairs in image["turned_deg"].items():
            if pairs >= 0.5 * guided.get(name, 0):
                out[name] = f"{turn} deg in {pairs} of {guided[name]} pairs"
    return out


def _count(values: Any) -> dict[str, int]:
    out: dict[str, int] = {}
    for v in values:
        out[v] = out.get(v, 0) + 1
    return out


#: ``hmcc colmap``'s processes: 0, in the benchmark's process (starting a pool of children
#: costs 2-5 s on this machine, more than verifying 18 images' pairs; README, bench_colmap).
VERIFY_PROCESSES = 0


def hmcc_row(db: Path, images: Path, processes: int, fixture: Fixture) -> dict[str, Any]:
    match_s, report = _guided(db, images, processes, fixture)
    t0 = time.perf_counter()
    ColmapRun(db, images=images, options=RunOptions(processes=VERIFY_PROCESSES)).run()
    verify_s = time.perf_counter() - t0
    return {
        "stage_s": match_s + verify_s,
        "match_s": match_s,
        "verify_s": verify_s,
        **_match_figures(report, fixture),
    }


def hmcc_verify_row(db: Path, images: Path, processes: int, fixture: Fixture) -> dict[str, Any]:
    t0 = time.perf_counter()
    options = MatchOptions(processes=processes, verify=RunOptions(), **fixture.match_options)
    report = GuidedMatchRun(db, images=images, options=options).run()
    stage_s = time.perf_counter() - t0
    t = report["totals"]
    rows = report["pairs"]
    return {
        "stage_s": stage_s,
        "match_s": None,
        "verify_s": None,
        # where the one run's time goes (last run): reading and checking, the pool's start +
        # matching and verifying in the children + writing the matches, taking the results
        # in and writing the geometries; the children's own sums (CPU spread over processes)
        "stages_s": {
            "read": t["read_s"],
            "match_and_verify": t["match_s"],
            "geometries": t["write_geometries_s"],
            "children_match_sum": round(sum(r["time_ms"] for r in rows) / 1000, 3),
            "children_verify_sum": round(sum(r.get("verify_ms") or 0.0 for r in rows) / 1000, 3),
        },
        **_match_figures(report, fixture),
    }


def hmcc_colmap_verification_row(
    db: Path, images: Path, processes: int, fixture: Fixture
) -> dict[str, Any]:
    match_s, report = _guided(db, images, processes, fixture)
    t0 = time.perf_counter()
    pycolmap.geometric_verification(db)
    verify_s = time.perf_counter() - t0
    return {
        "stage_s": match_s + verify_s,
        "match_s": match_s,
        "verify_s": verify_s,
        **_match_figures(report, fixture),
    }


#: ``hmcc match``'s flags for a fixture's ``match_options``.
CLI_FLAGS = {"flying_height_m": "--flying-height"}


def _hmcc(*args: str | Path) -> None:
    """``hmcc ARGS`` in a fresh process (the command as a user runs it)."""
    subprocess.run(
        [sys.executable, "-m", "hmcc_cli", *map(str, args)],
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def _cli_match(db: Path, images: Path, processes: int, fixture: Fixture) -> list[str]:
    flags = [f"{CLI_FLAGS[k]}={v}" for k, v in fixture.match_options.items()]
    return ["match", str(db), "--images", str(images), "--processes", str(processes), *flags]


def cli_verify_row(db: Path, images: Path, processes: int, fixture: Fixture) -> dict[str, Any]:
    t0 = time.perf_counter()
    _hmcc(*_cli_match(db, images, processes, fixture), "--verify")
    return {"stage_s": time.perf_counter() - t0}


def cli_two_commands_row(
    db: Path, images: Path, processes: int, fixture: Fixture
) -> dict[str, Any]:
    t0 = time.perf_counter()
    _hmcc(*_cli_match(db, images, processes, fixture))
    match_s = time.perf_counter() - t0
    _hmcc("colmap", db, "--images", images, "--processes", str(VERIFY_PROCESSES))
    stage_s = time.perf_counter() - t0
    return {"stage_s": stage_s, "match_s": match_s, "verify_s": stage_s - match_s}


#: The row the targets are measured on.
OURS = "hmcc match --verify"
ROWS: dict[str, Callable[[Path, Path, int, Fixture], dict[str, Any]]] = {
    "colmap": colmap_row,
    OURS: hmcc_verify_row,
    "hmcc match + hmcc colmap": hmcc_row,
    "hmcc match + COLMAP verification": hmcc_colmap_verification_row,
    "CLI hmcc match --verify": cli_verify_row,
    "CLI hmcc match; hmcc colmap": cli_two_commands_row,
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--fixture", choices=sorted(FIXTURES), default="brighton")
    p.add_argument("--images", type=Path, help="the flight's images (default: the fixture's)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "hmcc-match")
    p.add_argument("--max-image-size", type=int, help="SIFT's (default: the fixture's)")
    p.add_argument("--processes", type=int, default=2, help="hmcc's children (default 2)")
    p.add_argument("--repeats", type=int, default=1, help="runs of each row (median)")
    p.add_argument("--quick", action="store_true", help="Brighton: 5 images at 1000 px (smoke)")
    p.add_argument("--note", help="added to the results' note (e.g. what else ran on the machine)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="hmcc-bench-match-") as tmp:
        return run(args, Path(tmp))


def run(args: argparse.Namespace, tmp: Path) -> int:
    fixture = FIXTURES[args.fixture]
    images = args.images or fixture.images
    max_size = args.max_image_size or fixture.max_size
    if args.quick:
        images = tmp / "images"
        images.mkdir()
        for name in QUICK_IMAGES:
            shutil.copy((args.images or FIXTURES["brighton"].images) / name, images / name)
        max_size = 1000
    raw, build_s = colmap_database(images, args.cache, max_size, matched=False)
    print(f"features database {raw} ({f'built in {build_s:.0f} s' if build_s else 'cached'})")
    repeats = max(1, args.repeats)
    samples: dict[str, list[float]] = {name: [] for name in ROWS}
    last: dict[str, tuple[Path, dict[str, Any]]] = {}
    warm_up(GuidedOptions(), ColmapRun(raw).pair_verifier())  # untimed, once (docstring)
    first, *ours = list(ROWS)
    for k in range(repeats):
        # interleaved (the machine's speed drifts), the hmcc rows' order turned each repeat
        turn = k % len(ours)
        for name in [first, *ours[turn:], *ours[:turn]]:
            fn = ROWS[name]
            db = tmp / f"{name.replace(' ', '_').replace('+', 'and').replace(';', '')}-{k}.db"
            shutil.copy(raw, db)
            figures = fn(db, images, args.processes, fixture)
            samples[name].append(figures["stage_s"])
            last[name] = (db, figures)
            print(f"{name}: {figures['stage_s']:.2f} s", flush=True)
    rows: list[dict[str, Any]] = []
    for name in ROWS:
        db, figures = last[name]
        if "pairs" in figures:
            with_inliers(figures["pairs"], db)
            figures["per_pair"] = per_pair(figures["pairs"])
        out: dict[str, Any] = {
            "row": name,
            **figures,
            "stage_s": statistics.median(samples[name]),
            "stage_samples_s": samples[name],
            **counts(db),
            **mapping(db, images, tmp / f"{db.stem}-sparse"),
        }
        if fixture.looked_at and not args.quick:
            out["by_part"] = by_part(db, fixture.looked_at)
        rows.append(out)
        print(json.dumps(jsonable({k: v for k, v in out.items() if k != "pairs"})))
    for other in rows[1:]:
        other["stage_vs_colmap"] = other["stage_s"] / rows[0]["stage_s"]
    doc = {
        "meta": {
            **environment(),
            "pycolmap": pycolmap.__version__,
            "fixture": "quick" if args.quick else args.fixture,
            "title": "Brighton Beach (quick)" if args.quick else fixture.title,
            "about": fixture.about,
            "images": len([p for p in images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg")]),
            "pairs": "every pair",
            "max_image_size": max_size,
            "processes": args.processes,
            "quick": args.quick,
            "match_options": fixture.match_options,
            "features_database_build_s": build_s or None,
            "repeats": repeats,
            "note": (
                f"shared, noisy 2-core machine; stage times are medians of {repeats} run(s), "
                "the rows' runs interleaved" + (f"; {args.note}" if args.note else "")
            ),
        },
        "rows": rows,
        "targets": targets(rows),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    stem = fixture.stem
    (args.out / f"{stem}.json").write_text(
        json.dumps(jsonable(with_code_hash(doc, __file__)), indent=2) + "\n"
    )
    (args.out / f"{stem}.md").write_text(markdown(doc))
    print(markdown(doc))
    return 0


def by_part(db: Path, looked_at: int) -> dict[str, list[int]]:
    """Verified pairs and their inliers by part of the flight: both images among the first
    ``looked_at`` names (looked at while tuning), neither (held out), one of each (across)."""
    con = sqlite3.connect(db)
    try:
        names = dict(con.execute("SELECT image_id, name FROM images"))
        geometries = con.execute(
            "SELECT pair_id, rows FROM two_view_geometries WHERE rows > 0"
        ).fetchall()
    finally:
        con.close()
    tuned = set(sorted(names.values())[:looked_at])
    out = {"looked at": [0, 0], "held out": [0, 0], "across": [0, 0]}
    for pair_id, rows in geometries:
        a, b = divmod(pair_id, 2147483647)  # COLMAP's pair id
        inside = (names[a] in tuned) + (names[b] in tuned)
        part = out["looked at" if inside == 2 else "held out" if inside == 0 else "across"]
        part[0] += 1
        part[1] += rows
    return out


def with_inliers(pairs: list[dict[str, Any]], db: Path) -> None:
    """Each pair of ``hmcc match``'s report gets its inliers (rows of its two-view geometry
    in ``db`` after verification; 0 when it has none)."""
    con = sqlite3.connect(db)
    try:
        ids = {name: i for i, name in con.execute("SELECT image_id, name FROM images")}
        rows = dict(con.execute("SELECT pair_id, rows FROM two_view_geometries"))
    finally:
        con.close()
    for r in pairs:
        a, b = sorted((ids[r["image1"]], ids[r["image2"]]))
        r["inliers"] = int(rows.get(a * _PAIR_ID_BASE + b, 0))


#: COLMAP's pair id: image_id1 * 2147483647 + image_id2, image_id1 < image_id2.
_PAIR_ID_BASE = 2147483647


def per_pair(pairs: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The report per pair summed up by mode: pairs, and the median (and 90th percentile) of
    candidates compared per keypoint, matches, inliers, matching time (ms) and, verified where
    matched, verification time (ms; 0 for a pair not verified)."""
    out: dict[str, dict[str, Any]] = {}
    for mode in sorted({r["mode"] for r in pairs}):
        rows = [r for r in pairs if r["mode"] == mode]
        cell: dict[str, Any] = {"pairs": len(rows)}
        keys = ["candidates_per_keypoint", "matches", "inliers", "time_ms"]
        if any("verify_ms" in r for r in rows):
            keys.append("verify_ms")
        for key in keys:
            values = np.array([float(r.get(key) or 0.0) for r in rows])
            cell[key] = [float(np.median(values)), float(np.quantile(values, 0.9))]
        out[mode] = cell
    return out


def mapping(db: Path, images: Path, out: Path) -> dict[str, Any]:
    """Incremental mapping's models; the largest one's figures and :func:`tracks`."""
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    models = pycolmap.incremental_mapping(db, images, out, pycolmap.IncrementalPipelineOptions())
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
        "tracks": tracks(best),
    }


def tracks(model: Any) -> dict[str, Any]:
    """A model's tracks: points by track length (2, 3, 4, 5, 6+), each observation's
    reprojection error (px: mean, median, 90th and 99th percentiles) and each point's mean
    error (COLMAP's ``error``) by its track's length."""
    lengths = np.array([p.track.length() for p in model.points3D.values()])
    point_error = np.array([p.error for p in model.points3D.values()])
    errors = []
    for image in model.images.values():
        if not image.has_pose:
            continue
        camera = model.cameras[image.camera_id]
        cam_from_world = image.cam_from_world()
        for p2 in image.points2D:
            if p2.has_point3D():
                xyz = model.points3D[p2.point3D_id].xyz
                errors.append(np.linalg.norm(camera.img_from_cam(cam_from_world * xyz) - p2.xy))
    obs = np.array(errors)
    groups = {"2": lengths == 2, "3": lengths == 3, "4": lengths == 4, "5": lengths == 5}
    groups["6+"] = lengths >= 6
    return {
        "points_by_length": {k: int(m.sum()) for k, m in groups.items()},
        "point_error_by_length_px": {
            k: round(float(point_error[m].mean()), 3) if m.any() else None
            for k, m in groups.items()
        },
        "observations": len(obs),
        "observation_error_px": {
            "mean": round(float(obs.mean()), 3),
            "median": round(float(np.median(obs)), 3),
            "p90": round(float(np.quantile(obs, 0.9)), 3),
            "p99": round(float(np.quantile(obs, 0.99)), 3),
        }
        if len(obs)
        else {},
    }


def targets(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    colmap, ours = rows[0], _ours(rows)
    error, error_colmap = ours.get("reprojection_error_px"), colmap.get("reprojection_error_px")
    return [
        {
            "target": f"{ours['row']} <= 1/5 of COLMAP's matching + verification",
            "value": ours["stage_s"] / colmap["stage_s"],
            "ok": ours["stage_s"] <= colmap["stage_s"] / 5,
        },
        {
            "target": "registers at least as many images",
            "value": ours.get("registered", 0),
            "ok": ours.get("registered", 0) >= colmap.get("registered", 0),
        },
        {
            "target": "at least as many 3-D points",
            "value": ours.get("points3d", 0) / max(colmap.get("points3d", 0), 1),
            "ok": ours.get("points3d", 0) >= colmap.get("points3d", 0),
        },
        {
            "target": "mean reprojection error within 5 % of COLMAP's (ratio)",
            "value": None if not (error and error_colmap) else error / error_colmap,
            "ok": None
            if not (error and error_colmap)
            else error <= (1 + REPROJECTION_TOLERANCE) * error_colmap,
        },
    ]


def _ours(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The row the targets are measured on (:data:`OURS`; results from before it: the
    second row)."""
    return next((r for r in rows if r["row"] == OURS), rows[1])


def markdown(doc: dict[str, Any]) -> str:
    meta = doc["meta"]
    title = meta.get("title", "Brighton Beach")
    lines = [
        f"# COLMAP project: matching guided by the rough POS (issue #32), {title}",
        "",
        f"{meta['images']} {title} images, COLMAP SIFT at "
        f"{meta['max_image_size']} px (pycolmap {meta['pycolmap']}), every pair; each row's "
        "matching and verification on a copy of that database, then "
        "`pycolmap.incremental_mapping`. hmcc on "
        f"{meta['processes']} processes (`hmcc match --verify` verifies in them), `hmcc colmap` "
        f"in one. {meta['note']}. Reproduce: "
        "`.venv/bin/python -m benchmarks.bench_match"
        + {"brighton": "", "quick": " --quick"}.get(
            meta.get("fixture", "brighton"), f" --fixture {meta.get('fixture')}"
        )
        + "`.",
        "",
    ]
    if meta.get("about"):
        lines += [meta["about"], ""]
    lines += [
        "| row | match + verify (s) | x COLMAP | match (s, last run) | verify (s, last run) | "
        "candidates / keypoint "
        "| matched pairs | matches | verified pairs | inliers | models | registered | "
        "3-D points | reproj. error (px) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["rows"]:
        lines.append(
            f"| {r['row']} | {r['stage_s']:.2f} | {fmt(r.get('stage_vs_colmap'), 3)} | "
            f"{fmt(r.get('match_s'), 2)} | {fmt(r.get('verify_s'), 2)} | "
            f"{fmt(r.get('candidates_per_keypoint_mean'), 1)} | {r['matched_pairs']} | "
            f"{r['raw_matches']} | {r['verified_pairs']} | {r['inlier_matches']} | "
            f"{r.get('models', '-')} | {r.get('registered', '-')} | {r.get('points3d', '-')} | "
            f"{fmt(r.get('reprojection_error_px'), 3)} |"
        )
    lines += ["", "| target | value | |", "|---|---|---|"]
    for t in doc["targets"]:
        lines.append(f"| {t['target']} | {fmt(t['value'], 3)} | {verdict(t['ok'])} |")
    if any("by_part" in r for r in doc["rows"]):
        lines += [
            "",
            "Verified pairs / inliers by part of the flight: both images looked at while "
            "tuning, both held out, one of each.",
            "",
            "| row | looked at | held out | across |",
            "|---|---|---|---|",
        ]
        for r in doc["rows"]:
            parts = r.get("by_part")
            if parts:
                cells = " | ".join(f"{v[0]} / {v[1]}" for v in parts.values())
                lines.append(f"| {r['row']} | {cells} |")
    if any("tracks" in r for r in doc["rows"]):
        lines += [
            "",
            "Tracks of each model: points by track length; each point's mean reprojection "
            "error (px) by track length; each observation's error (px).",
            "",
            "| row | points 2 / 3 / 4 / 5 / 6+ | point error 2 / 3 / 4 / 5 / 6+ | observations | "
            "observation error mean / median / p90 / p99 |",
            "|---|---|---|---|---|",
        ]
        for r in doc["rows"]:
            t = r.get("tracks")
            if not t:
                continue
            e = t["observation_error_px"]
            lines.append(
                f"| {r['row']} | {' / '.join(str(v) for v in t['points_by_length'].values())} | "
                + " / ".join(fmt(v, 3) for v in t["point_error_by_length_px"].values())
                + f" | {t['observations']} | {fmt(e.get('mean'), 3)} / {fmt(e.get('median'), 3)}"
                f" / {fmt(e.get('p90'), 3)} / {fmt(e.get('p99'), 3)} |"
            )
    ours = _ours(doc["rows"])
    stages = ours.get("stages_s")
    if stages:
        lines += [
            "",
            f"Where the time of {ours['row']} goes (last run, s): reading and checking "
            f"{stages['read']:.2f}, the pool's start + matching and verifying in the children + "
            f"writing the matches {stages['match_and_verify']:.2f}, the geometries taken in "
            f"and written {stages['geometries']:.2f}; the children's own time summed over "
            f"pairs: matching {stages['children_match_sum']:.2f}, verifying "
            f"{stages['children_verify_sum']:.2f}.",
        ]
    if ours.get("per_pair"):
        lines += [
            "",
            f"`hmcc match`'s report per pair (row {ours['row']}; inliers after verification), "
            "by mode: median and 90th percentile over the pairs.",
            "",
            "| mode | pairs | candidates / keypoint | matches | inliers | match time (ms) | "
            "verify time (ms) |",
            "|---|---|---|---|---|---|---|",
        ]
        keys = ("candidates_per_keypoint", "matches", "inliers", "time_ms", "verify_ms")
        for mode, c in ours["per_pair"].items():
            lines.append(
                f"| {mode} | {c['pairs']} | "
                + " | ".join(
                    f"{fmt(c[k][0], 1)} / {fmt(c[k][1], 1)}" if k in c else "-" for k in keys
                )
                + " |"
            )
    lines += [
        "",
        f"hmcc match: ground Z0 = {ours['ground_z_m']} m ({ours['ground_z_source']}); pairs by "
        f"mode: {_modes(ours['modes'])}"
        + (
            f"; {ours['images_attitude_estimated']} attitudes estimated from the track"
            if ours.get("images_attitude_estimated")
            else ""
        )
        + (
            f"; {ours['images_focal_from_exif']} focal lengths from the EXIF"
            if ours.get("images_focal_from_exif")
            else ""
        )
        + ".",
    ]
    if meta.get("fixture", "brighton") in ("brighton", "quick"):
        lines.append(
            f"Pairs with one of the six images turned after capture (strip 1, {TURNED[0]} to "
            f"{TURNED[-1]}): {_modes(ours['turned_image_pairs_modes'])}; "
            f"{ours['turned_image_pairs_matches']} matches. Images found turned about their "
            "optical axes (in at least half of their pairs matched with the POS): "
            + (", ".join(f"{n} ({v})" for n, v in ours["turned_images"].items()) or "none")
            + "."
        )
    return "\n".join(lines) + "\n"


def _modes(modes: dict[str, int]) -> str:
    return ", ".join(f"{n} {m}" for m, n in sorted(modes.items())) or "none"


if __name__ == "__main__":
    raise SystemExit(main())
