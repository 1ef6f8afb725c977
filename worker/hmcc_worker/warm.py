"""Warming the core: the first verification in a process loads numba's compiled loops from the
disk cache (or compiles them, about 40 s, once per machine) and imports OpenCV's estimators."""

from __future__ import annotations

__all__ = ["warm_up"]


def warm_up() -> None:
    """Verify one small simulated pair with the default method (with its ground given, then
    estimated), ``hmcc-ransac`` and ``gc-ransac`` (the seven-point RANSAC and the GC vote are
    compiled too)."""
    from hmcc.simulate import SimulationOptions, simulate_pair
    from hmcc_schema import parse_pair

    pair = simulate_pair(SimulationOptions(n_inliers=60, outlier_ratio=0.3), seed=0)
    parse_pair(pair).verify(0)
    parse_pair({k: v for k, v in pair.items() if k != "plane"}).verify(0)  # the plane: auto
    for method in ("hmcc-ransac", "gc-ransac"):
        pair["method"] = method
        parse_pair(pair).verify(0)
