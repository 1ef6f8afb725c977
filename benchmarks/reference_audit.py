"""The Brighton Beach reference inliers that cannot be true: their rays meet behind a camera or
above the drone under the pair's rough POS (:func:`benchmarks.common.impossible_matches`).

The fixtures' reference is one MAGSAC++ draw at 1 px, without the POS. bench_hard scores real
pairs against the reference without these matches; this script shows them: one row per match
(pair, index, where the rays meet) in ``<out>/reference_audit.md`` and the two image patches
around each (image 1 left, image 2 right, 80 x 80 px of the 2000 px frame, the keypoint circled)
in ``<out>/reference_audit.jpg``, four matches per row in the table's order.

    .venv/bin/python -m benchmarks.reference_audit [--fixtures DIR] [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from hmcc import PairData
from hmcc_schema import parse_pair, reference_to_pair

from . import common as core

PATCH_PX, SHOWN_PX, PER_ROW = 80, 120, 4


def meeting_points(data: PairData, rows: np.ndarray) -> np.ndarray:
    """(R, 3) midpoints of the rays' closest approach (ENU metres) of the matches ``rows``,
    behind a camera too (:func:`hmcc.projection.triangulate_midpoints` zeroes those, and they
    are the ones shown here)."""
    px1, px2 = data.matched_pixels()
    w1 = data.camera1.rays(px1[rows]) @ data.pose1.R_world_to_cam
    w2 = data.camera2.rays(px2[rows]) @ data.pose2.R_world_to_cam
    c1, c2 = data.pose1.center, data.pose2.center
    points = []
    for a, b in zip(w1, w2, strict=True):
        t = np.linalg.lstsq(np.column_stack((a, -b)), c2 - c1, rcond=None)[0]
        points.append(0.5 * (c1 + t[0] * a + c2 + t[1] * b))
    return np.asarray(points).reshape(-1, 3)


def patch(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    half = PATCH_PX // 2
    padded = cv2.copyMakeBorder(image, half, half, half, half, cv2.BORDER_CONSTANT)
    x, y = (int(round(v)) for v in xy)
    shown = cv2.resize(padded[y : y + PATCH_PX, x : x + PATCH_PX], (SHOWN_PX, SHOWN_PX))
    cv2.circle(shown, (SHOWN_PX // 2, SHOWN_PX // 2), 4, (0, 0, 255), 1)
    return shown


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fixtures", type=Path, default=core.DEFAULT_FIXTURES)
    parser.add_argument("--out", type=Path, default=core.DEFAULT_OUT)
    args = parser.parse_args(argv)
    lines = [
        "# Reference inliers that cannot be true (Brighton Beach fixtures)",
        "",
        "Rays meeting behind a camera or above both cameras under the pair's rough POS "
        "(`benchmarks/common.py::impossible_matches`). Reproduce: "
        "`.venv/bin/python -m benchmarks.reference_audit`. The ground is at about 160 m "
        "(the fixtures' Z0, 160.15), the drone about 40 m above it. Patches, image 1 left and "
        "image 2 right, four matches per row in this table's order: `reference_audit.jpg`.",
        "",
        "| pair | reference inliers | match | meets at z (m) | cameras at z (m) |",
        "|---|---|---|---|---|",
    ]
    tiles, total, dropped_total = [], 0, 0
    for path in sorted(args.fixtures.glob("pair_*.json")):
        doc = reference_to_pair(json.loads(path.read_text()))
        data = parse_pair(doc).pair_data(0)
        reference = np.asarray(sorted(doc["ground_truth"]["inliers"]), dtype=np.int64)
        total += len(reference)
        dropped = core.impossible_matches(data, reference)
        if not len(dropped):
            continue
        dropped_total += len(dropped)
        name = path.stem.removeprefix("pair_")
        first, second = (args.fixtures / "images" / f"{n}.JPG" for n in name.split("_DJI_", 1))
        second = second.with_name("DJI_" + second.name)
        image1, image2 = (np.asarray(cv2.imread(str(f))) for f in (first, second))
        px1, px2 = data.matched_pixels()
        cameras = f"{data.pose1.center[2]:.1f}, {data.pose2.center[2]:.1f}"
        for row, point in zip(dropped, meeting_points(data, dropped), strict=True):
            lines.append(f"| {name} | {len(reference)} | {row} | {point[2]:.1f} | {cameras} |")
            gap = np.zeros((SHOWN_PX, 4, 3), np.uint8)
            white = np.full((SHOWN_PX, 8, 3), 255, np.uint8)  # between matches
            tiles.append(np.hstack((patch(image1, px1[row]), gap, patch(image2, px2[row]), white)))
    lines += ["", f"{dropped_total} of {total} reference inliers."]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "reference_audit.md").write_text("\n".join(lines) + "\n")
    if tiles:
        blank = np.zeros_like(tiles[0])
        rows = [
            np.hstack(tiles[k : k + PER_ROW] + [blank] * (PER_ROW - len(tiles[k : k + PER_ROW])))
            for k in range(0, len(tiles), PER_ROW)
        ]
        jpeg = [cv2.IMWRITE_JPEG_QUALITY, 85]
        cv2.imwrite(str(args.out / "reference_audit.jpg"), np.vstack(rows), jpeg)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
