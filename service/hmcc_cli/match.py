"""``hmcc match DATABASE``: match the features of a COLMAP database guided by the images'
rough POS and write the matches into it (see :mod:`hmcc_colmap.guided_match`); then
``hmcc colmap DATABASE`` verifies them and COLMAP's mapper goes on. With ``--verify`` each
pair is verified where it was matched (``--method``, ``--verify-params``, ``--min-inliers``
as ``hmcc colmap``'s ``--method``, ``--params``, ``--min-inliers``) and the two-view
geometries are written too: one command instead of two, the mapper goes on at once. Totals
on standard output, the full report (per pair and per image) with ``--report``; a progress
bar on a terminal.

Exit codes: 0 done, 2 bad input (one line, the database untouched), 130 interrupted (the
batches written so far stay; a rerun continues with the pairs not matched yet).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
from pathlib import Path
from typing import Any

import orjson
from tqdm import tqdm

from hmcc.method_names import DEFAULT_METHOD
from hmcc.method_names import METHOD_NAMES as METHODS

from . import colmap
from .extras import install_hint
from .outputs import checked_output, write_report

__all__ = ["add_arguments", "run", "summary"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("database", help="COLMAP database (COLMAP >= 4) with SIFT features")
    p.add_argument(
        "--images", help="the image folder (POS from EXIF GPS + the vendors' XMP attitude)"
    )
    p.add_argument(
        "--poses",
        help="pose file instead of the images' tags: ODM geo.txt, CSV "
        "image,lat,lon,alt,yaw,pitch,roll or image,x,y,z,omega,phi,kappa, JSON name -> pose",
    )
    p.add_argument(
        "--pairs-file",
        "--pairs",
        dest="pairs_file",
        help="only these pairs ('name1 name2' a line; default: every pair of images)",
    )
    p.add_argument(
        "--processes",
        type=int,
        default=os.cpu_count() or 1,
        help="child processes matching pairs (default: all cores; 0: in this process)",
    )
    ground = p.add_mutually_exclusive_group()
    ground.add_argument(
        "--ground-z", type=float, help="the ground's height, metres, on the altitudes' scale"
    )
    ground.add_argument(
        "--height",
        type=float,
        help="the flying height above the ground, metres (the ground: the median altitude less it)",
    )
    ground.add_argument(
        "--flying-height",
        type=float,
        help="each camera this high above the ground below it, metres; the altitudes are not "
        "used (GPS altitudes that drift)",
    )
    p.add_argument("--overwrite", action="store_true", help="match pairs matched before again")
    p.add_argument(
        "--database-focal",
        dest="exif_focal",
        action="store_false",
        help="keep the database cameras' focal lengths (default: the images' EXIF one where "
        "they disagree by more than 20 %%)",
    )
    p.add_argument(
        "--no-track-attitude",
        dest="track_attitude",
        action="store_false",
        help="an image with a position and no attitude has no usable pose, brute force "
        "(default: nadir, headed along the flight track)",
    )
    p.add_argument("--params", help="GuidedOptions as JSON (e.g. '{\"attitude_error_deg\": 5}')")
    verify = p.add_argument_group("verification (hmcc colmap's, where each pair is matched)")
    verify.add_argument(
        "--verify",
        action="store_true",
        help="verify each pair as it is matched and write the two-view geometries too, as "
        "hmcc colmap does (no mounting search: the poses as given)",
    )
    verify.add_argument(
        "--method", choices=METHODS, help=f"with --verify (default {DEFAULT_METHOD})"
    )
    verify.add_argument(
        "--verify-params", help="with --verify: the API's params as JSON (hmcc colmap --params)"
    )
    verify.add_argument(
        "--min-inliers",
        type=int,
        help="with --verify: fewer inliers, the pair is written unverified (default 15)",
    )
    p.add_argument("--report", help="write the full report (JSON) here")


def run(args: argparse.Namespace) -> int:
    try:
        from hmcc.guided import GuidedOptions
        from hmcc_colmap import ColmapInputError
        from hmcc_colmap.guided_match import GuidedMatchRun, MatchOptions
    except ImportError as e:
        print(
            f"error: hmcc match needs pycolmap ({e}): {install_hint('colmap')}",
            file=sys.stderr,
        )
        return 2
    try:
        guided = GuidedOptions(**(orjson.loads(args.params) if args.params else {}))
    except (orjson.JSONDecodeError, TypeError, ValueError) as e:
        print(f"error: --params: {e}", file=sys.stderr)
        return 2
    verify = _verify_options(args)
    if verify is False:
        return 2
    # checked (and its folder made) before the database is touched
    report_path = None if args.report is None else checked_output(args.report, "--report")
    if args.report is not None and report_path is None:
        return 2
    bar = tqdm(unit="pair", disable=not sys.stderr.isatty(), file=sys.stderr)

    def progress(done: int, total: int) -> None:
        if bar.total != total:
            bar.reset(total=total)
        bar.update(done - bar.n)

    matcher = None
    try:
        matcher = GuidedMatchRun(
            Path(args.database),
            images=args.images,
            poses=args.poses,
            pairs=args.pairs_file,
            options=MatchOptions(
                processes=args.processes,
                overwrite=args.overwrite,
                ground_z=args.ground_z,
                height_m=args.height,
                flying_height_m=args.flying_height,
                guided=guided,
                track_attitude=args.track_attitude,
                exif_focal=args.exif_focal,
                verify=verify,
            ),
            progress=progress,
        )
        report = matcher.run()
    except ColmapInputError as e:
        bar.close()
        message = str(e)
        if message.startswith("--params:") and verify is not None:  # hmcc colmap's flag
            message = "--verify-params:" + message.removeprefix("--params:")
        print(f"error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        bar.close()
        written = 0 if matcher is None else matcher.report.get("totals", {}).get("written", 0)
        print(f"interrupted: {written} pairs written; run again to continue", file=sys.stderr)
        return 130
    bar.close()
    print(summary(report))
    return 0 if report_path is None else write_report(report_path, report)


def _verify_options(args: argparse.Namespace) -> Any:
    """``hmcc colmap``'s options for ``--verify`` (None without it; False, the error printed,
    for a verification flag without it or params that are not JSON)."""
    from hmcc_colmap import RunOptions

    given = [
        flag
        for flag, value in (
            ("--method", args.method),
            ("--verify-params", args.verify_params),
            ("--min-inliers", args.min_inliers),
        )
        if value is not None
    ]
    if not args.verify:
        if given:
            print(f"error: {given[0]}: only with --verify", file=sys.stderr)
            return False
        return None
    try:
        params = orjson.loads(args.verify_params) if args.verify_params else None
    except orjson.JSONDecodeError as e:
        print(f"error: --verify-params: not JSON ({e})", file=sys.stderr)
        return False
    options = RunOptions(method=args.method or DEFAULT_METHOD, params=params)
    if args.min_inliers is not None:
        options.min_inliers = args.min_inliers
    return options


def summary(report: dict[str, Any]) -> str:
    """The totals, and the images without a usable pose."""
    t = report["totals"]
    modes = ", ".join(f"{n} {mode}" for mode, n in sorted(t["modes"].items()))
    lines = [
        f"{report['database']}: {t['pairs']} pairs matched in {t['match_s']:.2f} s (read in "
        f"{t['read_s']:.2f} s), {t['written']} written, {t['skipped_already_matched']} "
        "matched before, skipped",
        f"{t['matches']} matches; {t['candidates_per_keypoint_mean']:g} candidates per keypoint "
        f"(mean over pairs); {modes or 'no pairs'}",
        f"ground Z0 = {report['ground_z_m']:g} m ({report['ground_z_source']})",
    ]
    if t.get("images_focal_from_exif"):
        lines.append(
            f"{t['images_focal_from_exif']} images: focal length from the EXIF, the database's "
            "disagreeing (--database-focal: keep the database's)"
        )
    if t.get("images_attitude_estimated"):
        lines.append(
            f"{t['images_attitude_estimated']} images: attitude estimated from the track (nadir, "
            "heading along the flight; --no-track-attitude: none)"
        )
    if t.get("images_yaw_corrected"):
        moved = [
            math.hypot(*i["position_correction_m"])
            for i in report["images"].values()
            if i.get("position_correction_m")
        ]
        lines.append(
            f"{t['images_yaw_corrected']} images: yaw corrected from their anchor pairs' "
            f"matches; {len(moved)} positions corrected"
            + (f" (median {statistics.median(moved):.1f} m)" if moved else "")
        )
    verification = report.get("verification")
    if verification is not None:
        lines.append(
            f"verified where matched, geometries written in {t['write_geometries_s']:.2f} s:"
        )
        lines += [
            f"  {line}"
            for line in colmap.summary(verification).splitlines()[1:]
            if ": no usable pose (" not in line  # said below
        ]
    for name, image in report["images"].items():
        if not image["pose"]:
            lines.append(f"  {name}: no usable pose ({image['pose_issue']}): brute force")
        for turn, pairs in image["turned_deg"].items():
            lines.append(
                f"  {name}: turned by {turn} deg about its optical axis in {pairs} pairs "
                "(turned after capture, or not mounted as its tags say?)"
            )
    return "\n".join(lines)
