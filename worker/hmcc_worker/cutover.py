"""Where a compute pool pays: a one-off command (``hmcc flight``, ``hmcc colmap``) verifies at
most :data:`INPROCESS_MAX_PAIRS` pairs in its own process, because below that, starting and
warming a pool's children (a fork server that imports and warms the core, then the children)
takes longer than they save.

The number comes from the cut-over table of ``benchmarks/results/flight.md`` (``python -m
benchmarks.bench_flight --cutover ...``: the whole ``hmcc flight`` command on the first n
pairs of the benchmark flight, in its process against 2 children, on 2 cores): where the
pool's time falls below the command's own. With more children each pair costs the pool less
while its start stays about a second, so the pool pays sooner, not later.

A module of its own so that the commands read it without importing the pool (which loads the
core's compiled kernels)."""

from __future__ import annotations

__all__ = ["INPROCESS_MAX_PAIRS"]

INPROCESS_MAX_PAIRS = 1000
