"""numba compiles a kernel anew for each combination of its arrays' layout and flags, some
seconds a process: the callers of hmcc-plus's ray and posed kernels hand them C-contiguous,
writeable arrays whatever the pair's own (keypoints with more columns than x, y; a camera built
here, whose K is read-only, or unpickled in a pool's child, whose K is not), so that each is
compiled once."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
from numba.core import types

from hmcc import PairData, plus_kernels, verify
from hmcc.plus import Calibration, Correspondences, posed_essential_matrix
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc.stage_options import PlusOptions
from hmcc_schema import parse_pair


def _variants() -> list[PairData]:
    """One simulated pair as it comes: built here, unpickled, with (N, 4) float64 keypoints
    (their x, y a strided view) and with float32 ones on one side."""
    doc = simulate_pair(SimulationOptions(n_inliers=80, outlier_ratio=0.3), seed=3)
    pair = parse_pair(doc).pair_data(0)
    _ = pair.camera1.K, pair.camera2.K  # built (read-only) before the pickle, as in a flight

    def wide(k: np.ndarray) -> np.ndarray:
        return np.column_stack((k, np.ones(len(k)), np.zeros(len(k))))

    return [
        pair,
        pickle.loads(pickle.dumps(pair)),
        dataclasses.replace(pair, keypoints1=wide(pair.keypoints1)),
        dataclasses.replace(pair, keypoints2=pair.keypoints2.astype(np.float32)),
    ]


def _arrays(kernel: object) -> list[types.Array]:
    return [
        arg
        for signature in kernel.signatures  # type: ignore[attr-defined]
        for arg in signature
        if isinstance(arg, types.Array)
    ]


def test_the_ray_and_posed_kernels_take_c_contiguous_writeable_arrays_only() -> None:
    for pair in _variants():
        verify(pair, "hmcc-plus")  # the ray gate
        u1 = pair.camera1.undistort_pixels(pair.matched_pixels()[0])
        u2 = pair.camera2.undistort_pixels(pair.matched_pixels()[1])
        inliers = np.ones(len(u1), dtype=bool)
        posed_essential_matrix(Correspondences(u1, u2), inliers, Calibration(pair), PlusOptions())
    for kernel in (plus_kernels.ray_gate, plus_kernels.posed_model):  # (diverging: in ray_gate)
        arrays = _arrays(kernel)
        assert arrays, kernel  # they ran
        assert all(a.layout == "C" and a.mutable for a in arrays), kernel.signatures  # type: ignore[attr-defined]
