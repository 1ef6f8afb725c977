"""Where hmcc-plus spends its time on an easy pair: per-stage medians in a warm loop, next to
MAGSAC++ through ``verify()`` in the same process.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m benchmarks.plus_stages [--ratio 0.1] [--repeats 200]

Prints one line per simulated geometry (200 true matches, bench_core's uniform outliers).
"rest" is the median total minus the stage medians: the rest of verify(), approximate (medians
do not add up, so it can come out slightly negative).
"""

from __future__ import annotations

import argparse
import functools
import gc
import time
from collections.abc import Callable, Sequence

import numpy as np

from hmcc import verify

from . import common as core


def median_ms(call: Callable[[], object], repeats: int) -> float:
    for _ in range(10):
        call()
    gc.disable()
    try:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            call()
            times.append(time.perf_counter() - t0)
    finally:
        gc.enable()
    return 1e3 * float(np.median(times))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args(argv)
    for views in (("V", "V"), ("V", "F"), ("B", "F")):
        pair = core.contaminate(core.simulated_clean_pair(views, 200, 0), args.ratio, 0).data
        stages: dict[str, list[float]] = {}

        def plus(pair=pair, stages=stages) -> None:
            for report in verify(pair, "hmcc-plus").stages:
                stages.setdefault(report.name, []).append(report.time_ms)

        total = median_ms(plus, args.repeats)
        magsac = median_ms(functools.partial(verify, pair, "magsac++"), args.repeats)
        parts = {name: float(np.median(ms)) for name, ms in stages.items()}
        rest = total - sum(parts.values())
        line = " ".join(f"{name} {ms:.3f}" for name, ms in parts.items())
        print(
            f"{'-'.join(views)} n={len(pair.matches)}: hmcc-plus {total:.3f} ms "
            f"(x{total / magsac:.2f} of magsac++ {magsac:.3f}) = {line} rest {rest:.3f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
