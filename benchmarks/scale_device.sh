#!/usr/bin/env bash
# The flight benchmark's scaling rows on a many-core machine: the core in 1 and N forked
# processes, and `hmcc flight` (JSON and binary file, the whole command) with 1, 4 and N
# children, each with its serial share and Amdahl's prediction; then a cut-over table.
#
# From a fresh checkout with a prepared venv (scripts/bootstrap test), or on a lent machine after
# benchmarks/device_setup.sh (PYTHON=python3, a redis-server on PATH for the service rows):
#
#     OUT=/path/to/results benchmarks/scale_device.sh
#
# Writes $OUT/flight.json, $OUT/flight.md (bench_flight's files, with the timeline of each
# `hmcc flight` row: `--timings`) and $OUT/log.txt.
# Environment: OUT (required), SCALE_PROCESSES (default "1,4,16"; on 2 cores "1,2"),
# SCALE_HTTP=0 to skip the service rows (embedded and RQ, as many children and workers as
# processes), SCALE_CUTOVER (pair counts; empty to skip), SCALE_QUICK=1 for the small flight (600 pairs) instead of the 18 283-pair one,
# PYTHON (default .venv/bin/python). About 4-6 minutes on 16 cores for the full flight.
set -euo pipefail
: "${OUT:?set OUT to an output folder}"
PYTHON=${PYTHON:-.venv/bin/python}
PROCESSES=${SCALE_PROCESSES:-1,4,16}
mkdir -p "$OUT"
args=(--scale-only --core-processes "$PROCESSES" --cli-processes "$PROCESSES" --out "$OUT")
CUTOVER=${SCALE_CUTOVER-100,300,1000,3000}  # set empty to skip the cut-over table
if [[ -n "$CUTOVER" ]]; then
    args+=(--cutover "$CUTOVER")
fi
if [[ "${SCALE_HTTP:-1}" == 1 ]]; then  # the service rows: a redis-server on PATH
    args+=(--http-processes "$PROCESSES")
fi
args+=(--magsac-processes "$PROCESSES")  # the baseline: OpenCV MAGSAC++ on the sampled pairs
if [[ "${SCALE_QUICK:-0}" == 1 ]]; then
    args+=(--quick --cutover 50,200)
fi
{
    echo "cores: $(nproc); processes: $PROCESSES; quick: ${SCALE_QUICK:-0}"
    "$PYTHON" -m benchmarks.bench_flight "${args[@]}" || true  # targets not met exit 1
} 2>&1 | tee "$OUT/log.txt"
# --quick writes under $OUT/quick: put its files where the full run's go
if [[ -d "$OUT/quick" ]]; then
    mv "$OUT/quick/"* "$OUT/" && rmdir "$OUT/quick"
fi
ls -l "$OUT"
