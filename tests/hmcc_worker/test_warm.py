"""Warming a process: the core's compiled loops are loaded (not compiled) by the first call."""

from __future__ import annotations

from hmcc import gc_filter, plus_kernels, seven_point
from hmcc_worker.warm import warm_up


def test_warm_up_loads_the_compiled_kernels() -> None:
    warm_up()
    kernels = (
        plus_kernels.fit_candidates,
        plus_kernels.refine,
        plus_kernels.motion_field,
        seven_point._ransac,
        gc_filter._vote_every_pair,
    )
    for kernel in kernels:
        assert kernel.signatures, kernel  # compiled for the types a request brings
