"""Matching as the service does it (a batch whose pair asks for matching, parsed and verified
in this process: ``parse_batch`` -> ``Flight.verify``) on simulated scenes with SIFT-like
descriptors (``tests/support/matching.py``), against brute force on the same features.

    .venv/bin/python -m benchmarks.service_matching [--seeds 100:110] [--inliers 1000]

Prints, per pose quality, the matches' and the inliers' precision and recall against the
scene's true correspondences (means, and the worst pair), brute force's recall, the
candidates compared per keypoint and the median times (guided matcher vs brute force, same
process and features; times from a shared machine are noisy, compare the ratio). The tests
use seeds 0 to 3; the default seeds here are others.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
from tests.support.matching import matching_batch

from hmcc.guided import GuidedOptions, match_brute_force
from hmcc_schema import parse_batch

#: The simulator's pose errors compared: a survey-grade attitude, and the simulator's default.
POSES: dict[str, dict[str, Any]] = {
    "attitude ~1 deg (imu 1/0.5/0.5, wobble 0.5)": {
        "imu_sigma_deg": (1.0, 0.5, 0.5),
        "platform_attitude_sigma_deg": 0.5,
    },
    "simulator default (imu 2/1/1, wobble 2)": {},
}


def measure(seeds: range, inliers: int, scene: dict[str, Any]) -> np.ndarray:
    rows = []
    for seed in seeds:
        body, truth = matching_batch(seed, n_inliers=inliers, **scene)
        flight = parse_batch(body, 10)
        result = flight.verify(0).to_dict()
        matches = [tuple(m) for m in result["matches"]]
        found, kept = set(matches), {matches[k] for k in result["inliers"]}
        f1, f2 = flight.images["a"].features, flight.images["b"].features
        t0 = time.perf_counter()
        brute = {tuple(m) for m in match_brute_force(f1, f2, GuidedOptions()).matches.tolist()}
        brute_ms = 1e3 * (time.perf_counter() - t0)
        rows.append(
            (
                len(found & truth) / max(len(found), 1),
                len(found & truth) / len(truth),
                len(kept & truth) / max(len(kept), 1),
                len(kept & truth) / len(truth),
                len(brute & truth) / len(truth),
                result["matching"]["candidates_per_keypoint"],
                len(f2),
                result["matching"]["time_ms"],
                brute_ms,
            )
        )
    return np.array(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="100:110", help="first:end (end excluded)")
    parser.add_argument("--inliers", type=int, default=1000, help="true matches per scene")
    args = parser.parse_args()
    first, end = (int(v) for v in args.seeds.split(":"))
    seeds = range(first, end)
    parse_batch(matching_batch(0, n_inliers=50)[0], 10).verify(0)  # warm: compiled kernels
    for name, scene in POSES.items():
        a = measure(seeds, args.inliers, scene)
        print(
            f"{name}: {len(seeds)} pairs; matches precision {a[:, 0].mean():.3f} "
            f"(worst {a[:, 0].min():.3f}), recall {a[:, 1].mean():.3f} "
            f"(worst {a[:, 1].min():.3f}); "
            f"inliers precision {a[:, 2].mean():.3f}, recall {a[:, 3].mean():.3f}; "
            f"brute force recall {a[:, 4].mean():.3f}; candidates per keypoint "
            f"{a[:, 5].mean():.1f} of {a[:, 6].mean():.0f}; "
            f"time guided {np.median(a[:, 7]):.1f} ms, "
            f"brute force {np.median(a[:, 8]):.1f} ms (ratio {np.median(a[:, 8] / a[:, 7]):.1f})"
        )


if __name__ == "__main__":
    main()
