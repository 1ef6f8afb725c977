"""Benchmark of the default method ``hmcc-plus`` against OpenCV's MAGSAC++ and USAC_ACCURATE.

One run, one process, the same pairs for every method. Clean pairs (the Brighton Beach
fixtures reduced to their reference inliers, and simulated nadir ("V", "V") and oblique
("V", "F"), ("B", "F") pairs) get uniform random outliers at ratios 0.1 ... 0.9 (bench_core's
protocol). On each contaminated pair:

* ``verify(pair, m)`` for m in ``hmcc-plus``, ``hmcc-ransac``, ``lo-ransac``, ``magsac++``,
  ``usac-accurate``: precision, recall and wall time around the call;
* the raw OpenCV calls a user would make on the same pixels,
  ``cv2.findFundamentalMat(px1, px2, cv2.USAC_MAGSAC | cv2.USAC_ACCURATE, 1.0, 0.999, 10000)``;
* hmcc-plus's fallback (used, reason) and its time ratios to MAGSAC++ and USAC_ACCURATE, both
  as timed through ``verify()`` and as raw cv2 calls.

Targets for hmcc-plus in every set x ratio cell: mean precision >= 0.98; mean recall >= 0.95
(>= 0.90 at ratio 0.9); median per-pair time ratio <= 1/2 of MAGSAC++ and <= 1/3 of
USAC_ACCURATE, checked against both the ``verify()`` and the raw cv2 baselines.

Results go to ``<out>/default.json`` (every number), ``<out>/default.md`` (the tables) and
``<out>/default.png`` (precision, recall and time against the outlier ratio, per set).

Usage::

    .venv/bin/python -m benchmarks.bench_default [--quick] [--seeds N] [--sim-inliers N]
        [--out DIR] [--fixtures DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from hmcc import PairData, verify  # noqa: E402

from . import common as core  # noqa: E402

PLUS = "hmcc-plus"
METHODS: tuple[str, ...] = (PLUS, "hmcc-ransac", "lo-ransac", "magsac++", "usac-accurate")
BASELINES: tuple[str, ...] = ("magsac++", "usac-accurate")  # the time targets' references
RAW_FLAGS: dict[str, int] = {"magsac++": cv2.USAC_MAGSAC, "usac-accurate": cv2.USAC_ACCURATE}
RAW_THRESHOLD_PX = 1.0
RAW_CONFIDENCE = 0.999
RAW_MAX_ITERS = 10_000
SET_ORDER: tuple[str, ...] = ("real", "sim V-V", "sim V-F", "sim B-F", "sim L-F")
FULL_RATIOS: tuple[float, ...] = tuple(round(0.1 * k, 1) for k in range(1, 10))
QUICK_RATIOS: tuple[float, ...] = (0.1, 0.5, 0.9)

TARGET_PRECISION = 0.98
TARGET_RECALL = 0.95
TARGET_RECALL_HIGH = 0.90  # at and above HIGH_RATIO
HIGH_RATIO = 0.9
TARGET_TIME_RATIO: dict[str, float] = {"magsac++": 0.5, "usac-accurate": 1.0 / 3.0}
CLOCKS: tuple[str, ...] = ("verify", "raw")  # how the baselines of a time ratio were timed

SHORT = {
    "hmcc-plus": "plus",
    "hmcc-ransac": "hmcc-r",
    "lo-ransac": "lo-r",
    "magsac++": "magsac",
    "usac-accurate": "usac-a",
}
COLORS = {
    "hmcc-plus": "tab:red",
    "hmcc-ransac": "tab:orange",
    "lo-ransac": "tab:green",
    "magsac++": "tab:blue",
    "usac-accurate": "tab:purple",
}


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class Config:
    """Sizes, repeats and sets of one run."""

    quick: bool
    seeds: int
    sim_inliers: int
    repeats: int
    budget_s: float
    ratios: tuple[float, ...]
    fixtures_dir: Path
    max_fixtures: int | None
    out: Path


def make_config(args: argparse.Namespace) -> Config:
    """The run's configuration from the parsed command line."""
    return Config(
        quick=args.quick,
        seeds=1 if args.quick else args.seeds,
        sim_inliers=args.sim_inliers,
        repeats=2 if args.quick else 5,
        budget_s=0.05 if args.quick else 0.3,
        ratios=QUICK_RATIOS if args.quick else FULL_RATIOS,
        fixtures_dir=args.fixtures,
        max_fixtures=2 if args.quick else None,
        out=args.out,
    )


# --------------------------------------------------------------------------- timing


def pixels(data: PairData) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) contiguous float64 pixels of the matches in both images, as a user holds them."""
    px1 = np.ascontiguousarray(data.keypoints1[data.matches[:, 0], :2], dtype=np.float64)
    px2 = np.ascontiguousarray(data.keypoints2[data.matches[:, 1], :2], dtype=np.float64)
    return px1, px2


def raw_fundamental(px1: np.ndarray, px2: np.ndarray, flag: int) -> np.ndarray:
    """Inlier indices of one plain ``cv2.findFundamentalMat`` call (empty when it fails)."""
    f, mask = cv2.findFundamentalMat(
        px1, px2, flag, RAW_THRESHOLD_PX, RAW_CONFIDENCE, RAW_MAX_ITERS
    )
    if f is None or mask is None:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(mask.reshape(-1))


def time_raw(
    px1: np.ndarray, px2: np.ndarray, flag: int, repeats: int, budget_s: float
) -> tuple[np.ndarray, list[float]]:
    """``core.time_calls`` of a raw cv2 call: inliers of the warm-up, samples (ms)."""
    inliers, samples = core.time_calls(lambda: raw_fundamental(px1, px2, flag), repeats, budget_s)
    return inliers, [ms for ms, _ in samples]


def warm_up() -> None:
    """Pay first-call costs of every method and raw call on a small simulated pair."""
    clean = core.simulated_clean_pair(("V", "V"), 100, 12345)
    data = core.contaminate(clean, 0.5, 0).data
    px1, px2 = pixels(data)
    for _ in range(3):
        for method in METHODS:
            verify(data, method)
        for flag in RAW_FLAGS.values():
            raw_fundamental(px1, px2, flag)


# --------------------------------------------------------------------------- pairs


def clean_pairs_by_set(cfg: Config) -> dict[str, list[core.CleanPair]]:
    """The clean pairs of every set, real fixtures first (empty when the folder is missing)."""
    sets: dict[str, list[core.CleanPair]] = {name: [] for name in SET_ORDER}
    if cfg.fixtures_dir.is_dir():
        paths = sorted(cfg.fixtures_dir.glob("pair_*.json"))
        if cfg.max_fixtures is not None:
            paths = paths[: cfg.max_fixtures]
        sets["real"] = [core.fixture_clean_pair(p, i) for i, p in enumerate(paths)]
    for views in core.SIM_GEOMETRIES:
        for seed in range(cfg.seeds):
            clean = core.simulated_clean_pair(views, cfg.sim_inliers, seed)
            sets[clean.set_name].append(clean)
    return {name: pairs for name, pairs in sets.items() if pairs}


def run_pair(pair: core.BenchPair, cfg: Config) -> dict[str, Any]:
    """Every method and raw call on one contaminated pair: accuracy, times, time ratios."""
    record: dict[str, Any] = {
        "set": pair.set_name,
        "geometry": pair.geometry,
        "source": pair.source,
        "seed": pair.seed,
        "ratio": pair.ratio,
        "n_matches": pair.n_matches,
        "n_true": len(pair.truth),
        "methods": {},
        "raw": {},
    }
    for method in METHODS:
        result, timing = core.time_verify(pair.data, method, cfg.repeats, cfg.budget_s)
        entry = timing.summary() | core.precision_recall(result.inliers, pair.truth)
        record["methods"][method] = entry
        if method == PLUS:
            fallback = result.statistics.get("fallback", {"used": False, "reason": None})
            record["fallback"] = {"used": bool(fallback["used"]), "reason": fallback["reason"]}
    px1, px2 = pixels(pair.data)
    for name, flag in RAW_FLAGS.items():
        inliers, samples = time_raw(px1, px2, flag, cfg.repeats, cfg.budget_s)
        record["raw"][name] = {
            "samples": len(samples),
            "wall_ms": core.median(samples),
        } | core.precision_recall(inliers, pair.truth)
    plus_ms = record["methods"][PLUS]["wall_ms"]
    record["time_ratio"] = {
        "verify": {b: plus_ms / record["methods"][b]["wall_ms"] for b in BASELINES},
        "raw": {b: plus_ms / record["raw"][b]["wall_ms"] for b in BASELINES},
    }
    return record


def run_sets(cfg: Config) -> list[dict[str, Any]]:
    """Per-pair records over every set, clean pair and ratio, with progress per set."""
    records: list[dict[str, Any]] = []
    for set_name, cleans in clean_pairs_by_set(cfg).items():
        t_set = time.perf_counter()
        for clean in cleans:
            for ratio in cfg.ratios:
                records.append(run_pair(core.contaminate(clean, ratio, 0), cfg))
        done = [r for r in records if r["set"] == set_name]
        fallbacks = sum(r["fallback"]["used"] for r in done)
        print(
            f"  {set_name}: {len(cleans)} clean pairs x {len(cfg.ratios)} ratios, "
            f"{fallbacks} fallbacks, {time.perf_counter() - t_set:.1f} s",
            flush=True,
        )
    return records


# --------------------------------------------------------------------------- aggregates


def recall_target(ratio: float) -> float:
    """hmcc-plus's recall target at an outlier ratio."""
    return TARGET_RECALL_HIGH if ratio >= HIGH_RATIO - 1e-9 else TARGET_RECALL


def summarize_cell(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate one set x ratio: means of P/R, medians of times and of per-pair time ratios."""
    ratio = records[0]["ratio"]
    cell: dict[str, Any] = {
        "pairs": len(records),
        "median_matches": core.median(r["n_matches"] for r in records),
        "median_true": core.median(r["n_true"] for r in records),
        "methods": {},
        "raw": {},
    }
    for method in METHODS:
        entries = [r["methods"][method] for r in records]
        cell["methods"][method] = {
            "precision": core.mean(e["precision"] for e in entries),
            "recall": core.mean(e["recall"] for e in entries),
            "empty_outputs": sum(e["kept"] == 0 for e in entries),
            "wall_ms": core.median(e["wall_ms"] for e in entries),
            "stage_sum_ms": core.median(e["stage_sum_ms"] for e in entries),
        }
    plus = cell["methods"][PLUS]
    plus["recall_min"] = min(r["methods"][PLUS]["recall"] for r in records)
    for name in RAW_FLAGS:
        entries = [r["raw"][name] for r in records]
        cell["raw"][name] = {
            "precision": core.mean(e["precision"] for e in entries),
            "recall": core.mean(e["recall"] for e in entries),
            "wall_ms": core.median(e["wall_ms"] for e in entries),
        }
    cell["time_ratio"] = {
        clock: {b: core.median(r["time_ratio"][clock][b] for r in records) for b in BASELINES}
        for clock in CLOCKS
    }
    reasons = Counter(r["fallback"]["reason"] for r in records if r["fallback"]["used"])
    cell["fallbacks"] = sum(reasons.values())
    cell["fallback_reasons"] = dict(reasons)
    cell["targets"] = cell_targets(cell, ratio)
    return cell


def cell_targets(cell: dict[str, Any], ratio: float) -> dict[str, bool]:
    """Each target of one cell: precision, recall, time vs each baseline and clock, and the
    combined verdicts ``accuracy``, ``time_<clock>`` and ``all_<clock>``."""
    plus = cell["methods"][PLUS]
    ok = {
        "precision": bool(plus["precision"] >= TARGET_PRECISION),
        "recall": bool(plus["recall"] >= recall_target(ratio)),
    }
    for clock in CLOCKS:
        for b in BASELINES:
            ok[f"time_{clock}_{b}"] = bool(cell["time_ratio"][clock][b] <= TARGET_TIME_RATIO[b])
    ok["accuracy"] = ok["precision"] and ok["recall"]
    for clock in CLOCKS:
        ok[f"time_{clock}"] = all(ok[f"time_{clock}_{b}"] for b in BASELINES)
        ok[f"all_{clock}"] = ok["accuracy"] and ok[f"time_{clock}"]
    return ok


def summarize(records: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per set, per ratio aggregates (JSON keys are the ratio as a string)."""
    sets: dict[str, dict[str, Any]] = {}
    for (set_name, ratio), group in core.group_by(records, "set", "ratio").items():
        sets.setdefault(set_name, {})[f"{ratio:.1f}"] = summarize_cell(group)
    return sets


TARGET_LABELS: dict[str, str] = {
    "precision": f"precision >= {TARGET_PRECISION}",
    "recall": f"recall >= {TARGET_RECALL} (>= {TARGET_RECALL_HIGH} at {HIGH_RATIO})",
    "time_verify_magsac++": "time <= 1/2 of magsac++ via verify()",
    "time_verify_usac-accurate": "time <= 1/3 of usac-accurate via verify()",
    "time_raw_magsac++": "time <= 1/2 of raw cv2 USAC_MAGSAC",
    "time_raw_usac-accurate": "time <= 1/3 of raw cv2 USAC_ACCURATE",
    "accuracy": "precision and recall",
    "all_verify": "accuracy and both time targets via verify()",
    "all_raw": "accuracy and both time targets vs raw cv2",
}


def target_summary(cells: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """For every target: cells passing, cells in all, and the cells that miss it."""
    flat = [(s, r, c) for s, per_ratio in cells.items() for r, c in per_ratio.items()]
    rows = []
    for key, label in TARGET_LABELS.items():
        missed = [f"{s} @{r}" for s, r, c in flat if not c["targets"][key]]
        rows.append(
            {
                "target": key,
                "label": label,
                "passed": len(flat) - len(missed),
                "cells": len(flat),
                "missed": missed,
            }
        )
    return rows


# --------------------------------------------------------------------------- tables


def set_table(set_name: str, per_ratio: dict[str, Any]) -> core.Table:
    """One set's table: rows = ratio; P/R, times, hmcc-plus time ratios, fallbacks, verdicts."""
    rows = []
    for ratio, cell in per_ratio.items():
        ms, raw, tr, ok = cell["methods"], cell["raw"], cell["time_ratio"], cell["targets"]
        rows.append(
            [
                ratio,
                core.fmt(cell["median_matches"], 0),
                *(f"{core.fmt(ms[m]['precision'])}/{core.fmt(ms[m]['recall'])}" for m in METHODS),
                core.fmt(ms[PLUS]["recall_min"]),
                *(core.fmt_ms(ms[m]["wall_ms"]) for m in METHODS),
                *(core.fmt_ms(raw[b]["wall_ms"]) for b in BASELINES),
                *(core.fmt(tr[clock][b]) for clock in CLOCKS for b in BASELINES),
                f"{cell['fallbacks']}/{cell['pairs']}",
                core.verdict(ok["accuracy"]),
                core.verdict(ok["time_verify"]),
                core.verdict(ok["time_raw"]),
            ]
        )
    pairs = next(iter(per_ratio.values()))["pairs"]
    return core.Table(
        f"{set_name}: hmcc-plus vs baselines ({pairs} pair{'' if pairs == 1 else 's'} per ratio)",
        [
            "ratio",
            "matches",
            *(f"P/R {SHORT[m]}" for m in METHODS),
            "minR plus",
            *(f"ms {SHORT[m]}" for m in METHODS),
            *(f"ms cv2 {SHORT[b]}" for b in BASELINES),
            *(
                f"plus/{SHORT[b]}{' cv2' if clock == 'raw' else ''}"
                for clock in CLOCKS
                for b in BASELINES
            ),
            "fallbk",
            "acc",
            "t verify",
            "t cv2",
        ],
        rows,
        "P/R = mean precision/recall over pairs; minR plus = hmcc-plus's lowest recall; "
        "ms = median wall ms per pair (verify(), or the raw cv2.findFundamentalMat call); "
        "plus/X = median per-pair ratio of hmcc-plus's time to X's (targets: <= 0.50 magsac, "
        f"<= 0.33 usac-a); acc = P >= {TARGET_PRECISION} and R >= {TARGET_RECALL} "
        f"({TARGET_RECALL_HIGH} at {HIGH_RATIO}); t verify / t cv2 = both time targets "
        "against the verify() / raw cv2 baselines.",
    )


def summary_table(summary: list[dict[str, Any]]) -> core.Table:
    """Cells passing each target."""
    rows = []
    for t in summary:
        missed = ", ".join(t["missed"][:12]) + (" ..." if len(t["missed"]) > 12 else "")
        rows.append([t["label"], f"{t['passed']}/{t['cells']}", missed or "-"])
    return core.Table(
        "Targets for hmcc-plus: set x ratio cells passing",
        ["target", "cells", "missed in"],
        rows,
        left=3,
    )


def fallback_table(cells: dict[str, dict[str, Any]]) -> core.Table | None:
    """Why hmcc-plus fell back, counted per set (None when it never did)."""
    rows = []
    for set_name, per_ratio in cells.items():
        reasons: Counter[str] = Counter()
        for cell in per_ratio.values():
            reasons.update(cell["fallback_reasons"])
        for reason, count in reasons.most_common():
            rows.append([set_name, reason, str(count)])
    if not rows:
        return None
    return core.Table("hmcc-plus fallbacks", ["set", "reason", "pairs"], rows, left=2)


# --------------------------------------------------------------------------- plot


def plot(cells: dict[str, dict[str, Any]], path: Path, title: str) -> None:
    """Precision, recall and median time (log) against the outlier ratio: 3 rows x one column
    per set; the time row adds dashed lines for the raw cv2 calls."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(cells)
    fig, axes = plt.subplots(
        3, len(sets), figsize=(4.2 * len(sets), 10), sharex=True, squeeze=False
    )
    for col, set_name in enumerate(sets):
        per_ratio = cells[set_name]
        x = [float(r) for r in per_ratio]
        for row, key in enumerate(("precision", "recall", "wall_ms")):
            ax = axes[row][col]
            for method in METHODS:
                y = [c["methods"][method][key] for c in per_ratio.values()]
                ax.plot(x, y, marker="o", ms=3, color=COLORS[method], label=method)
            if key == "wall_ms":
                for b in BASELINES:
                    y = [c["raw"][b]["wall_ms"] for c in per_ratio.values()]
                    ax.plot(x, y, ls="--", color=COLORS[b], label=f"cv2 {b} (raw)")
                ax.set_yscale("log")
            else:
                targets = [TARGET_PRECISION if key == "precision" else recall_target(r) for r in x]
                ax.plot(
                    x,
                    targets,
                    ls="none",
                    marker="_",
                    ms=12,
                    mew=1.5,
                    color="grey",
                    label="hmcc-plus target",
                )
            ax.grid(True, alpha=0.3)
            if row < 2:
                ax.set_ylim(-0.02, 1.02)
        pairs = next(iter(per_ratio.values()))["pairs"]
        axes[0][col].set_title(f"{set_name} ({pairs} pair{'' if pairs == 1 else 's'} per ratio)")
        axes[2][col].set_xlabel("outlier ratio")
    axes[0][0].set_ylabel("precision (mean)")
    axes[1][0].set_ylabel("recall (mean)")
    axes[2][0].set_ylabel("wall ms (median, log)")
    handles, labels = axes[2][0].get_legend_handles_labels()
    target_handles, target_labels = axes[0][0].get_legend_handles_labels()
    handles.append(target_handles[-1])
    labels.append(target_labels[-1])
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), frameon=False)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- output


def header_lines(env: dict[str, Any], cfg: Config, command: str) -> list[str]:
    """Header printed before the tables and written to the markdown."""
    uncommitted = env["package_uncommitted"]
    return [
        "hmcc-plus default-method benchmark" + (" (QUICK)" if cfg.quick else ""),
        f"python {env['python']}  numpy {env['numpy']}  opencv {env['opencv']} "
        f"(cv2.getNumThreads() = {env['opencv_threads']})  hmcc {env['hmcc']}  commit "
        f"{env['git_commit']}"
        + (f" + uncommitted {', '.join(uncommitted)}" if uncommitted else "")
        + f"  (source sha256 {env['package_source_sha256']})",
        f"{env['platform']}, {env['cpu_count']} CPUs, load average "
        f"{' '.join(f'{x:.2f}' for x in env['load_average_at_start'])} at start",
        f"seeds {cfg.seeds}, sim inliers {cfg.sim_inliers}, ratios "
        f"{', '.join(f'{r:.1f}' for r in cfg.ratios)}, repeats {cfg.repeats}, budget "
        f"{cfg.budget_s:g} s, fixtures {cfg.fixtures_dir}"
        + (f" (first {cfg.max_fixtures})" if cfg.max_fixtures else ""),
        f"command: {command}",
    ]


PROTOCOL_NOTES = f"""\
Protocol. Pairs and outliers are bench_core's: simulated clean pairs from
`hmcc.simulate.simulate_pair` (defaults, no outliers), real pairs = the Brighton Beach fixtures
reduced to their reference inliers (an automatic MAGSAC++ reference, not manual truth); outliers
are uniform random keypoints redrawn when within 3 px of the true/reference epipolar line, the
match list is shuffled (seeded). Every method runs through `verify()` with `VerifyOptions()`
defaults (seed 0; baselines fit F at 1 px, confidence 0.999, at most 10 000 iterations on
undistorted pixels). The raw columns time
`cv2.findFundamentalMat(px1, px2, flag, {RAW_THRESHOLD_PX}, {RAW_CONFIDENCE}, {RAW_MAX_ITERS})`
(flag `cv2.USAC_MAGSAC` or `cv2.USAC_ACCURATE`) on the matches' raw pixels, which skips
`verify()`'s input handling, undistortion and result building. Timing: one untimed
warm-up call per (pair, method) gives precision and recall, then up to `repeats` timed calls
(stopping once the calls took the budget), garbage collector off, `time.perf_counter` around
the call; the median over repeats, then over pairs. Time ratios are hmcc-plus's wall time over
the baseline's on the same pair, median over the pairs of a cell. Precision leaves out pairs
with an empty output; recall = true matches kept / true matches."""


def write_outputs(result: dict[str, Any], tables: list[core.Table], out: Path) -> None:
    """``default.json`` with every number, ``default.md`` with the tables, ``default.png``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "default.json").write_text(
        json.dumps(core.jsonable(core.with_code_hash(result, __file__)), indent=1) + "\n"
    )
    meta = result["meta"]
    lines = ["# hmcc-plus (default) vs MAGSAC++ and USAC_ACCURATE", ""]
    lines += [f"- {line}" for line in meta["header"][1:-1]]
    lines += [
        f"- command: `{meta['command']}`",
        f"- wall time of the run: {meta['run_wall_s']:.1f} s (load average at the end "
        + " ".join(f"{x:.2f}" for x in meta["load_average_at_end"])
        + ")",
        "",
        PROTOCOL_NOTES,
        "",
        "![precision, recall and time per set](default.png)",
        "",
    ]
    for table in tables:
        lines += [table.markdown(), ""]
    (out / "default.md").write_text("\n".join(lines))
    try:
        import matplotlib  # noqa: F401  (the bench extra)
    except ImportError:
        print("matplotlib is not installed (scripts/bootstrap bench): no default.png")
        return
    plot(result["cells"], out / "default.png", meta["header"][0])


# --------------------------------------------------------------------------- main


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--quick", action="store_true", help="1 seed, 2 fixtures, ratios 0.1/0.5/0.9"
    )
    parser.add_argument("--seeds", type=int, default=3, help="simulated pairs per geometry")
    parser.add_argument(
        "--sim-inliers", type=int, default=200, help="true matches of a simulated pair"
    )
    parser.add_argument("--out", type=Path, default=core.DEFAULT_OUT, help="output directory")
    parser.add_argument(
        "--fixtures", type=Path, default=core.DEFAULT_FIXTURES, help="Brighton Beach fixture folder"
    )
    args = parser.parse_args(None if argv is None else [str(a) for a in argv])
    if args.seeds < 1 or args.sim_inliers < 8:
        parser.error("--seeds must be >= 1, --sim-inliers >= 8")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark, print the tables, write the json, markdown and png."""
    t_run = time.perf_counter()
    started = datetime.now(UTC).isoformat(timespec="seconds")
    args = parse_args(argv)
    cfg = make_config(args)
    command = " ".join(["benchmarks/bench_default.py", *(str(a) for a in (argv or sys.argv[1:]))])
    env = core.environment()
    header = header_lines(env, cfg, command)
    print("\n".join(header), flush=True)
    if not cfg.fixtures_dir.is_dir():
        print(f"  no fixture folder {cfg.fixtures_dir}: the real set is skipped", flush=True)
    core.section("warm-up", warm_up)
    records = core.section("pairs", lambda: run_sets(cfg))
    cells = summarize(records)
    summary = target_summary(cells)
    tables = [set_table(s, per_ratio) for s, per_ratio in cells.items()]
    fallbacks = fallback_table(cells)
    tables += [summary_table(summary), *([fallbacks] if fallbacks else [])]
    print()
    for table in tables:
        print(table.text(), end="\n\n")
    run_wall_s = time.perf_counter() - t_run
    load_end = list(os.getloadavg())
    result = {
        "meta": {
            "header": header,
            "environment": env,
            "config": dataclasses.asdict(cfg),
            "command": command,
            "run_wall_s": run_wall_s,
            "load_average_at_end": load_end,
            "started_utc": started,
            "protocol": PROTOCOL_NOTES,
            "targets": {
                "precision": TARGET_PRECISION,
                "recall": TARGET_RECALL,
                "recall_at_0.9": TARGET_RECALL_HIGH,
                "time_ratio": TARGET_TIME_RATIO,
            },
        },
        "cells": cells,
        "summary": summary,
        "pairs": records,
    }
    write_outputs(result, tables, cfg.out)
    print(
        f"wall time of the run: {run_wall_s:.1f} s; load average at the end "
        + " ".join(f"{x:.2f}" for x in load_end),
        flush=True,
    )
    written = [cfg.out / f"default.{e}" for e in ("json", "md", "png")]
    print(f"wrote {', '.join(str(p) for p in written if p.is_file())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
