"""Simulated batches whose pairs ask for matching: a simulated pair's keypoints with SIFT-like
descriptors, so that matching has a truth to find."""

from __future__ import annotations

from typing import Any

import numpy as np

from hmcc.simulate import SimulationOptions, simulate_pair


def matching_batch(
    seed: int = 0,
    n_inliers: int = 400,
    outlier_ratio: float = 0.5,
    noise: float = 0.25,
    **scene: Any,
) -> tuple[dict[str, Any], set[tuple[int, int]]]:
    """A batch body (JSON-ready but for the ndarrays of keypoints and descriptors) of one
    simulated nadir pair that asks for matching, and its true correspondences ``(i, j)``.

    The descriptors: a random non-negative 128-vector per simulated 3-D point, each view's
    a noisy copy (``noise`` times a unit normal per value), scaled and rounded to uint8 as
    SIFT's; keypoints of no true correspondence (the simulator's outliers) have descriptors
    of their own. The plane is the simulated ground's mean height. ``scene``: more
    :class:`SimulationOptions`."""
    pair = simulate_pair(
        SimulationOptions(n_inliers=n_inliers, outlier_ratio=outlier_ratio, **scene), seed=seed
    )
    rng = np.random.default_rng(seed + 1000)
    kp1, kp2 = np.asarray(pair["keypoints1"]), np.asarray(pair["keypoints2"])
    matches = np.asarray(pair["matches"])[pair["ground_truth"]["inliers"]]
    base1 = np.abs(rng.normal(size=(len(kp1), 128)))
    base2 = np.abs(rng.normal(size=(len(kp2), 128)))
    base2[matches[:, 1]] = base1[matches[:, 0]]  # one point, one descriptor

    def seen(base: np.ndarray) -> np.ndarray:
        d = base + np.abs(rng.normal(scale=noise, size=base.shape))
        unit = d / np.linalg.norm(d, axis=1, keepdims=True)
        return np.clip(np.round(512 * unit), 0, 255).astype(np.uint8)

    images = {
        "a": {**pair["image1"], "keypoints": kp1, "descriptors": seen(base1)},
        "b": {**pair["image2"], "keypoints": kp2, "descriptors": seen(base2)},
    }
    body = {
        "images": images,
        "pairs": [{"id": "ab", "image1": "a", "image2": "b", "match": True}],
        "plane": {"ground_z": pair["ground_truth"]["mean_ground_z"]},
    }
    truth = {(int(i), int(j)) for i, j in matches}
    return body, truth


def msgpack_ready(body: dict[str, Any]) -> dict[str, Any]:
    """``body`` with every ndarray a raw buffer ``{"dtype", "shape", "data"}`` (uint8 and
    float32 kept, anything else float64)."""

    def convert(value: Any) -> Any:
        if isinstance(value, np.ndarray):
            a = value if value.dtype in (np.uint8, np.float32) else value.astype("<f8")
            return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}
        if isinstance(value, dict):
            return {k: convert(v) for k, v in value.items()}
        if isinstance(value, list):
            return [convert(v) for v in value]
        return value

    return convert(body)


def json_ready(body: dict[str, Any]) -> dict[str, Any]:
    """``body`` with every ndarray as nested lists."""

    def convert(value: Any) -> Any:
        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, dict):
            return {k: convert(v) for k, v in value.items()}
        if isinstance(value, list):
            return [convert(v) for v in value]
        return value

    return convert(body)
