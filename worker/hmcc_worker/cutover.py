"""Where a compute pool pays: a one-off command (``hmcc flight``, ``hmcc colmap``) verifies at
most :data:`INPROCESS_MAX_PAIRS` pairs in its own process, because below that, starting and
warming a pool's children (a fork server that imports and warms the core, then the children)
takes longer than they save.

The number comes from the cut-over table of ``benchmarks/results/flight.md`` (``python -m
benchmarks.bench_flight --cutover ...``: the whole ``hmcc flight`` command on the first n
pairs of the benchmark flight, in its process against 2 children, on 2 cores). There the pool
started to pay at about 2 000 pairs (1 000 pairs: 1.9 s in process, 2.1 s on the pool; 3 000:
3.6 s against 3.2 s). With more children each pair costs the pool less while its start stays
about 1 s, so the pool pays sooner (about 1 000 pairs with 16, from the same figures): hence
1 000. A module of its own so that the commands read it without importing the pool (which
loads the core's compiled kernels)."""

from __future__ import annotations

__all__ = ["INPROCESS_MAX_PAIRS"]

INPROCESS_MAX_PAIRS = 1000
