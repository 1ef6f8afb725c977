"""Simulated pairs with exact truth, and precision/recall, for the core's tests."""

from __future__ import annotations

from typing import Any

import numpy as np

from hmcc import PairData
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_pair


def simulated(views=("V", "V"), ratio=0.7, seed=0, **kw) -> tuple[PairData, np.ndarray]:
    """A simulated pair and the (M,) mask of its true matches."""
    return scene_pair({"views": views, "outlier_ratio": ratio, **kw}, seed)


def scene_pair(scene: dict[str, Any], seed: int) -> tuple[PairData, np.ndarray]:
    """The pair of ``scene`` (:class:`SimulationOptions` as a dict, e.g. a benchmark's scene)
    and the (M,) mask of its true matches."""
    pair = simulate_pair(SimulationOptions(**scene), seed=seed)
    truth = np.zeros(len(pair["matches"]), dtype=bool)
    truth[pair["ground_truth"]["inliers"]] = True
    return parse_pair(pair).pair_data(0), truth


def precision_recall(found: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Precision and recall of the indices ``found`` against the truth mask."""
    hits = truth[found].sum()
    return hits / max(len(found), 1), hits / truth.sum()
