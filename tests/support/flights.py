"""Small flights for tests: simulated pairs whose images carry their keypoints."""

from __future__ import annotations

from typing import Any

from hmcc.simulate import SimulationOptions, simulate_pair


def small_flight(n_pairs: int, n_inliers: int = 60, seed: int = 0) -> dict[str, Any]:
    """A flight body (``images`` with keypoints, ``pairs`` with matches only, ``plane``) of
    ``n_pairs`` simulated pairs, two images each; ``truth`` maps a pair id to its inliers."""
    doc: dict[str, Any] = {"images": {}, "pairs": [], "truth": {}}
    for k in range(n_pairs):
        pair = simulate_pair(SimulationOptions(n_inliers=n_inliers, outlier_ratio=0.4), seed + k)
        a, b = f"a{k}", f"b{k}"
        doc["images"][a] = {**pair["image1"], "keypoints": pair["keypoints1"]}
        doc["images"][b] = {**pair["image2"], "keypoints": pair["keypoints2"]}
        doc["pairs"].append({"id": f"p{k}", "image1": a, "image2": b, "matches": pair["matches"]})
        doc["truth"][f"p{k}"] = pair["ground_truth"]["inliers"]
        doc["plane"] = pair["plane"]
    return doc
