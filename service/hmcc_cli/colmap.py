"""``hmcc colmap DATABASE``: verify every matched pair of a COLMAP database and write the
verified geometries back (see :mod:`hmcc_colmap`). Totals on standard output, the full report
(per pair and per image) with ``--report``; a progress bar on a terminal.

A run where more than half of the images have no usable pose says so on standard error (one
paragraph: how many, what was looked for, how to give poses with ``--poses``) and in the
report's ``pose_warning``.

Exit codes: 0 done, 2 bad input (one line, the database untouched; a ``--report`` that cannot
be written is found out before the run), 1 a service (``--url``) failed or could not be reached,
or the report could not be written after all (the database was), 130 interrupted (the chunks
written so far stay; a rerun continues).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import orjson
from tqdm import tqdm

from hmcc.method_names import DEFAULT_METHOD
from hmcc.method_names import METHOD_NAMES as METHODS
from hmcc_worker.cutover import INPROCESS_MAX_PAIRS

from .extras import install_hint
from .outputs import checked_output, write_report
from .plural import counted
from .where import add_where_arguments, service_error, service_errors

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("database", help="COLMAP database (COLMAP >= 4), matched, not yet verified")
    p.add_argument(
        "--images",
        help="the image folder (POS from EXIF GPS + the vendors' XMP: DJI, senseFly, Parrot, "
        "Camera:Yaw/Pitch/Roll)",
    )
    p.add_argument(
        "--poses",
        help="pose file instead of the images' tags: ODM geo.txt, CSV "
        "image,lat,lon,alt,yaw,pitch,roll or image,x,y,z,omega,phi,kappa, JSON name -> pose",
    )
    p.add_argument("--method", choices=METHODS, default=DEFAULT_METHOD)
    p.add_argument("--params", help="the API's params as JSON (e.g. '{\"plus\": {...}}')")
    add_where_arguments(
        p, "child processes verifying pairs here (default: all cores; 0: in this process)"
    )
    p.add_argument("--pairs", help="only these pairs (COLMAP pairs file: 'name1 name2' a line)")
    p.add_argument("--overwrite", action="store_true", help="verify pairs verified before again")
    p.add_argument(
        "--min-inliers",
        type=int,
        default=15,
        help="fewer inliers: the pair is written unverified, as COLMAP does (default 15)",
    )
    p.add_argument("--chunk-pairs", type=int, default=1024, help="pairs per transaction")
    p.add_argument(
        "--in-process-max",
        type=int,
        default=INPROCESS_MAX_PAIRS,
        metavar="PAIRS",
        help="verify at most this many pairs in this process, without children "
        f"(default {INPROCESS_MAX_PAIRS})",
    )
    p.add_argument(
        "--no-track-attitude",
        dest="track_attitude",
        action="store_false",
        help="an image with a position and no attitude has no usable pose (default: nadir, "
        "headed along the flight track)",
    )
    p.add_argument(
        "--database-focal",
        dest="exif_focal",
        action="store_false",
        help="keep the database cameras' focal lengths (default: the images' EXIF one where "
        "they disagree by more than 20 %%; needs --images)",
    )
    p.add_argument(
        "--detect-mounting",
        action="store_true",
        help="search the camera's turn about its optical axis (0/90/180/270 deg) on a sample "
        "of pairs first, and apply the one that keeps most pairs from falling back",
    )
    p.add_argument("--report", help="write the full report (JSON) here")


def run(args: argparse.Namespace) -> int:
    try:
        from hmcc_colmap import ColmapInputError, ColmapRun, RunOptions
    except ImportError as e:
        print(
            f"error: hmcc colmap needs pycolmap ({e}): {install_hint('colmap')}",
            file=sys.stderr,
        )
        return 2
    try:
        params = orjson.loads(args.params) if args.params else None
    except orjson.JSONDecodeError as e:
        print(f"error: --params: not JSON ({e})", file=sys.stderr)
        return 2
    # Checked (and its folder made) before the database is touched: a report that cannot be
    # written must not be found out after the run wrote the geometries.
    report_path = None if args.report is None else checked_output(args.report, "--report")
    if args.report is not None and report_path is None:
        return 2
    bar = tqdm(unit="pair", disable=not sys.stderr.isatty(), file=sys.stderr)

    def progress(done: int, total: int) -> None:
        if bar.total != total:
            bar.reset(total=total)
        bar.update(done - bar.n)

    colmap = None
    try:
        colmap = ColmapRun(
            Path(args.database),
            images=args.images,
            poses=args.poses,
            pairs=args.pairs,
            options=RunOptions(
                method=args.method,
                params=params,
                min_inliers=args.min_inliers,
                overwrite=args.overwrite,
                processes=args.processes,
                in_process_max=args.in_process_max,
                url=args.url,
                api_key=args.api_key,
                chunk_pairs=max(1, args.chunk_pairs),
                track_attitude=args.track_attitude,
                exif_focal=args.exif_focal,
                detect_mounting=args.detect_mounting,
            ),
            progress=progress,
        )
        report = colmap.run()
    except ColmapInputError as e:
        bar.close()
        print(f"error: {e}", file=sys.stderr)
        return 2
    except service_errors() as e:
        bar.close()
        code = service_error(e, args.url)
        print(
            f"{counted(_written(colmap), 'pair')} written (whole chunks); run again to continue",
            file=sys.stderr,
        )
        return code
    except KeyboardInterrupt:
        bar.close()
        print(
            f"interrupted: {counted(_written(colmap), 'pair')} written (whole chunks); "
            "run again to continue",
            file=sys.stderr,
        )
        return 130
    bar.close()
    if report.get("pose_warning"):
        print(report["pose_warning"], file=sys.stderr)
    print(summary(report))
    if report.get("mounting_hint"):
        print(report["mounting_hint"], file=sys.stderr)
    return 0 if report_path is None else write_report(report_path, report)


def _written(colmap: Any) -> int:
    """Pairs a run wrote before it stopped (whole chunks; 0 if it never started)."""
    return 0 if colmap is None else int(colmap.report.get("totals", {}).get("written", 0))


def summary(report: dict[str, Any]) -> str:
    """The totals, and the images whose POS did not fit or who had none."""
    t = report["totals"]
    lines = [
        f"{report['database']}: {counted(t['pairs'], 'pair')} with {report['method']} "
        f"({report['where']}): read and checked in {t['plan_s']:.2f} s, verified and written in "
        f"{t['verify_s']:.2f} s (+{t['startup_s']:.1f} s start); "
        f"{t['skipped_already_verified']} verified before, skipped",
        f"verified {counted(t['verified'], 'pair')} "
        f"({counted(t['inlier_matches'], 'inlier match', 'inlier matches')}); "
        f"{t['under_min_inliers']} under {counted(report['min_inliers'], 'inlier')}, "
        f"{t['too_few_matches']} with too few matches, {t['failed']} failed",
        f"{counted(t['fallback_pairs'], 'pair')} fell back to {report['fallback_method']} (HMCC "
        f"could not be trusted on them); {counted(t['no_pose_pairs'], 'pair')} of images without "
        "a usable pose went to it directly",
    ]
    if t.get("images_focal_from_exif"):
        lines.append(
            f"{counted(t['images_focal_from_exif'], 'image')}: focal length from the EXIF, the "
            "database's disagreeing (--database-focal: keep the database's)"
        )
    if t.get("images_attitude_estimated"):
        lines.append(
            f"{counted(t['images_attitude_estimated'], 'image')}: attitude estimated from the "
            "track (nadir, heading along the flight; --no-track-attitude: none)"
        )
    mounting = report.get("mounting")
    if mounting:
        tried = ", ".join(
            f"{t['yaw_deg']}: {t.get('consistent', '-')}/{t['kept']}" for t in mounting["tried"]
        )
        whose = mounting.get("images", "every image")
        if whose != "every image":
            whose = "the images whose attitude was estimated"
        lines.append(
            f"mounting: {mounting['yaw_deg']} deg added to the mounting yaw of {whose} (per "
            f"flight; of {mounting['sample_pairs']} pairs sampled, by yaw: baselines consistent/"
            f"pairs kept {tried or 'none sampled'})"
        )
    if t["listed_without_matches"]:
        n = t["listed_without_matches"]
        have = "has" if n == 1 else "have"
        lines.append(f"{counted(n, 'pair')} of --pairs {have} no matches (left out)")
    for name, image in report["images"].items():
        if image["pose_issue"]:
            lines.append(f"  {name}: no usable pose ({image['pose_issue']})")
        elif image["pos_fits"] is False:
            lines.append(
                f"  {name}: its POS does not fit its pixels ({image['fallback']} of "
                f"{counted(image['pairs'], 'pair')} fell back, median rotation error "
                f"{image['pos_rotation_error_deg_median']} deg)"
            )
    return "\n".join(lines)
