"""Warming the core: the first verification in a process loads numba's compiled loops from the
disk cache (or compiles them, about 40 s, once per machine) and imports OpenCV's estimators."""

from __future__ import annotations

__all__ = ["warm_up"]


def warm_up() -> None:
    """Verify one small simulated pair with the default method (with its ground given, then
    estimated), ``hmcc-ransac`` and ``gc-ransac`` (the seven-point RANSAC and the GC vote are
    compiled too); fit its essential matrix from the rough pose; vote on a relative pose and
    clip two footprints (compiled too)."""
    import numpy as np

    from hmcc.footprint import select_pairs
    from hmcc.plus import Calibration, Correspondences, posed_essential_matrix
    from hmcc.relative_pose import relative_pose
    from hmcc.simulate import SimulationOptions, simulate_pair
    from hmcc.stage_options import PlusOptions
    from hmcc_schema import parse_pair

    pair = simulate_pair(SimulationOptions(n_inliers=60, outlier_ratio=0.3), seed=0)
    flight = parse_pair(pair)
    flight.verify(0)
    # the essential matrix from the rough pose (hmcc-plus fits it on the pairs that ask: not
    # this one), some seconds to compile
    data = flight.pair_data(0)
    u1, u2 = (
        c.undistort_pixels(p)
        for c, p in zip((data.camera1, data.camera2), data.matched_pixels(), strict=True)
    )
    everything = np.ones(len(u1), dtype=bool)
    posed_essential_matrix(Correspondences(u1, u2), everything, Calibration(data), PlusOptions())
    parse_pair({k: v for k, v in pair.items() if k != "plane"}).verify(0)  # the plane: auto
    for method in ("hmcc-ransac", "gc-ransac"):
        pair["method"] = method
        parse_pair(pair).verify(0)
    # the relative pose of a verified pair (``hmcc colmap``'s children compute it)
    rays = np.column_stack((np.linspace(-0.3, 0.3, 8), np.linspace(0.2, -0.2, 8)))
    relative_pose(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]), rays, rays)
    # the overlap of two footprints (``POST /v1/pairs``, ``hmcc pairs``)
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    select_pairs([square, square + 0.5])
