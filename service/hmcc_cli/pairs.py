"""``hmcc pairs --images DIR -o pairs.txt``: the pairs worth matching, chosen from the rough
POS by footprint overlap (see :mod:`hmcc_colmap.pairs`), written as COLMAP's pairs file for
``colmap matches_importer`` or ``pycolmap.match_image_pairs``. A summary on standard output.

Exit codes: 0 done, 2 bad input (one line naming the file or option and the reason).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .extras import install_hint

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--images", required=True, help="the image folder (EXIF GPS, DJI XMP)")
    p.add_argument(
        "--poses",
        help="pose file instead of the images' tags: ODM geo.txt, CSV "
        "image,lat,lon,alt,yaw,pitch,roll or image,x,y,z,omega,phi,kappa, JSON name -> pose",
    )
    p.add_argument(
        "--database", help="a COLMAP database: its images and cameras instead of the EXIF focal"
    )
    ground = p.add_mutually_exclusive_group()
    ground.add_argument(
        "--ground-z", type=float, help="the ground height, m, on the positions' height scale"
    )
    ground.add_argument(
        "--flying-height", type=float, help="each image's ground is this far below it, m"
    )
    p.add_argument(
        "--min-overlap",
        type=float,
        default=0.5,
        help="keep pairs overlapping by more than this fraction of the smaller footprint "
        "(default 0.5, the paper's)",
    )
    p.add_argument(
        "--max-per-image", type=int, help="keep each image's K largest overlaps (default all)"
    )
    p.add_argument(
        "--min-partners",
        type=int,
        default=0,
        help="each image also keeps its K largest overlaps above zero, below --min-overlap "
        "too (an image at the block's edge has few above half; default 0: the rule alone)",
    )
    p.add_argument(
        "--max-range",
        type=float,
        default=5.0,
        help="footprints stop at this multiple of the camera's height above the ground "
        "(rays toward the horizon; default 5)",
    )
    p.add_argument("-o", "--output", required=True, help="the pairs file to write")


def run(args: argparse.Namespace) -> int:
    try:
        from hmcc.footprint import FootprintOptions
        from hmcc_colmap.errors import ColmapInputError
        from hmcc_colmap.pairs import choose_pairs, write_pairs_file
    except ImportError as e:
        print(
            f"error: hmcc pairs needs Pillow ({e}): {install_hint('colmap')}",
            file=sys.stderr,
        )
        return 2
    try:
        options = FootprintOptions(max_range_ratio=args.max_range)
    except ValueError as e:
        print(f"error: --max-range: {str(e).partition(': ')[2]}", file=sys.stderr)
        return 2
    try:
        choice = choose_pairs(
            Path(args.images),
            poses=None if args.poses is None else Path(args.poses),
            database=None if args.database is None else Path(args.database),
            ground_z=args.ground_z,
            flying_height=args.flying_height,
            min_overlap=args.min_overlap,
            max_per_image=args.max_per_image,
            min_partners=args.min_partners,
            options=options,
        )
        write_pairs_file(Path(args.output), choice.pairs)
    except ColmapInputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: {args.output}: {e}", file=sys.stderr)
        return 2
    n = len(choice.names)
    lines = [
        f"{len(choice.pairs)} pairs of {n} images (of {n * (n - 1) // 2}) overlapping by more "
        f"than {args.min_overlap:g} of the smaller footprint"
        + (f" or among an image's {args.min_partners} largest" if args.min_partners else "")
        + f", written to {args.output}",
        f"ground: {choice.ground}",
    ]
    if choice.estimated:
        lines.append(
            f"{len(choice.estimated)} images have a position and no attitude: attitude "
            "estimated (nadir, heading from the flight track)"
        )
    for name, why in choice.without_pose.items():
        lines.append(f"  {name}: no usable pose, in no pair ({why})")
    print("\n".join(lines))
    return 0
