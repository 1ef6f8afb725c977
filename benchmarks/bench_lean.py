"""Simulated pairs, held-out seeds: ``hmcc-lean`` against ``hmcc-plus`` and MAGSAC++ (issue 29).

Scenes of three kinds (nadir, oblique, relief: tall buildings on strong relief), each at the
outlier ratios 0.5, 0.7 and 0.9 (uniform outliers), ``--pairs`` pairs a cell with 30-300 true
matches drawn per pair. Every method at the same decision threshold (``ransac.threshold_px`` =
``plus.threshold_px``), warmed alike (``common.warm_up_opencv``, then one call a pair and
method), each call timed ``--repeats`` times (median), in one process; precision and recall
pooled over a cell's matches, time summed over its pairs. A pair's seed is
``seed_base + its index``: ``hmcc-lean`` was tuned on seed base 5000; the committed results
use 7000, never looked at before.

Usage::

    .venv/bin/python -m benchmarks.bench_lean [--seed-base 7000] [--pairs 12] [--repeats 3]
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from hmcc import VerifyOptions, verify
from hmcc.plus import PlusOptions
from hmcc.ransac import RansacOptions
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_pair

from .common import Table, environment, jsonable, time_calls, warm_up_opencv, with_code_hash

METHODS = ("hmcc-lean", "hmcc-plus", "magsac++")
RATIOS = (0.5, 0.7, 0.9)
THRESHOLDS_PX = (1.0, 1.5)
SCENES: dict[str, dict[str, Any]] = {
    "nadir": {"views": ("V", "V")},
    "oblique": {"views": ("V", "F")},
    "relief": {
        "views": ("V", "B"),
        "relief_m": 40.0,
        "building_fraction": 0.4,
        "building_height_m": (5.0, 60.0),
    },
}
OUT = Path(__file__).resolve().parent / "results"


def scene_pair(scene: str, ratio: float, seed: int) -> tuple[Any, np.ndarray]:
    """The simulated pair (PairData) and its (M,) truth mask."""
    rng = np.random.default_rng(seed)
    options = SimulationOptions(
        **SCENES[scene], outlier_ratio=ratio, n_inliers=int(rng.integers(30, 301))
    )
    doc = simulate_pair(options, seed=seed)
    truth = np.zeros(len(doc["matches"]), dtype=bool)
    truth[doc["ground_truth"]["inliers"]] = True
    return parse_pair(doc).pair_data(0), truth


def options_at(threshold_px: float) -> VerifyOptions:
    return VerifyOptions(
        ransac=RansacOptions(threshold_px=threshold_px), plus=PlusOptions(threshold_px=threshold_px)
    )


def run(args: argparse.Namespace) -> dict[str, Any]:
    warm_up_opencv()
    records = []
    for scene in SCENES:
        for ratio in RATIOS:
            for i in range(args.pairs):
                seed = args.seed_base + i
                pair, truth = scene_pair(scene, ratio, seed)
                for threshold in THRESHOLDS_PX:
                    options = options_at(threshold)
                    for method in METHODS:
                        result, samples = time_calls(
                            functools.partial(verify, pair, method, options), args.repeats, 1.0
                        )
                        found = result.inliers
                        fallback = result.statistics.get("fallback", {})
                        records.append(
                            {
                                "scene": scene,
                                "ratio": ratio,
                                "seed": seed,
                                "threshold_px": threshold,
                                "method": method,
                                "ms": statistics.median(ms for ms, _ in samples),
                                "kept": len(found),
                                "true_kept": int(truth[found].sum()),
                                "true": int(truth.sum()),
                                "fallback": bool(fallback.get("used", False)),
                            }
                        )
            print(f"{scene} {ratio}: done", flush=True)
    return {"records": records}


def summarize(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    cells: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in records:
        key = (r["scene"], r["ratio"], r["threshold_px"], r["method"])
        cells.setdefault(key, []).append(r)
    out = []
    for (scene, ratio, threshold, method), rs in cells.items():
        kept, hit = sum(r["kept"] for r in rs), sum(r["true_kept"] for r in rs)
        out.append(
            {
                "scene": scene,
                "ratio": ratio,
                "threshold_px": threshold,
                "method": method,
                "pairs": len(rs),
                "ms": sum(r["ms"] for r in rs),
                "precision": hit / kept if kept else 0.0,
                "recall": hit / max(sum(r["true"] for r in rs), 1),
                "fallback": sum(r["fallback"] for r in rs),
            }
        )
    return out


def tables(summary: list[dict[str, Any]]) -> list[Table]:
    out = []
    for threshold in THRESHOLDS_PX:
        rows = []
        for ratio in RATIOS:
            for method in METHODS:
                cell = [
                    s
                    for s in summary
                    if s["ratio"] == ratio
                    and s["threshold_px"] == threshold
                    and s["method"] == method
                ]
                kept = {s["scene"]: s for s in cell}
                ms = sum(s["ms"] for s in cell)
                row = [f"{ratio:g}", method, f"{ms:.1f}"]
                for scene in SCENES:
                    s = kept[scene]
                    row.append(f"{s['precision']:.3f} / {s['recall']:.3f}")
                fallback = sum(s["fallback"] for s in cell) if method != "magsac++" else None
                pairs = sum(s["pairs"] for s in cell)
                row.append("-" if fallback is None else f"{fallback}/{pairs}")
                rows.append(row)
        out.append(
            Table(
                f"Simulated held-out seeds, every method at {threshold:g} px: time (ms, summed "
                "over the pairs of every scene), precision / recall per scene",
                ["outliers", "method", "time (ms)", *[f"P / R {s}" for s in SCENES], "fallback"],
                rows,
                left=2,
            )
        )
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed-base", type=int, default=7000)
    p.add_argument("--pairs", type=int, default=12, help="pairs a scene and ratio")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--name", default="lean")
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    doc = run(args)
    summary = summarize(doc["records"])
    meta = environment() | {
        "seed_base": args.seed_base,
        "pairs": args.pairs,
        "repeats": args.repeats,
        "scenes": SCENES,
        "run_s": round(time.perf_counter() - t0, 1),
    }
    result = {"meta": meta, "summary": summary, "records": doc["records"]}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(
        json.dumps(jsonable(with_code_hash(result, __file__)), indent=1) + "\n"
    )
    lines = [
        f"# hmcc-lean on simulated pairs (seed base {args.seed_base}, held out)",
        "",
        f"{args.pairs} pairs a scene and outlier ratio, 30-300 true matches each, uniform "
        "outliers; tuned on seed base 5000. Reproduce: `.venv/bin/python -m "
        f"benchmarks.bench_lean --seed-base {args.seed_base} --pairs {args.pairs}`. "
        f"Run took {meta['run_s']} s on a shared 2-core machine.",
        "",
    ]
    for table in tables(summary):
        lines += [table.markdown(), ""]
    text = "\n".join(lines)
    (args.out / f"{args.name}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
