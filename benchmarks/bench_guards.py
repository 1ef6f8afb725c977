"""No valid input kills a process: every method, estimator and model on the inputs at the
edges of the request limits, each in an isolated child (issue #11).

Each case is a request that passes validation (``hmcc_schema.parse_pair``), verified by a
:class:`hmcc_worker.pool.ComputePool` child, as the service does. A native crash would come
back as ``worker_crashed``, a run past the bound as ``timeout``; the table says which case
ended how and in what time. Inputs (cameras and poses of a simulated nadir pair; keypoints
``[x, y, size, angle]``):

* ``random 100k``: 5 000 keypoints per image, 100 000 random matches (the match limit);
  gc-ransac's quadratic vote takes tens of seconds on them, within the service's timeout;
* ``200k keypoints``: 200 000 keypoints per image (the keypoint limit), 2 000 random matches;
* ``identical``: 2 000 matches of one and the same point in both images;
* ``collinear``: 2 000 matches whose points lie on one line in each image;
* ``minimal``: 8 random matches.

Configurations: every method of ``hmcc.METHODS`` with its defaults; the methods that take
``params.ransac`` also with the ``essential`` and ``homography`` models.

Run: ``python -m benchmarks.bench_guards [--timeout 60] [--quick]``. Results:
``benchmarks/results/guards.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from hmcc import METHODS
from hmcc.method_names import F_ONLY_METHODS
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_pair
from hmcc_schema.models import MAX_KEYPOINTS, MAX_MATCHES
from hmcc_worker.outcomes import unpack
from hmcc_worker.pool import ComputePool

from .common import DEFAULT_OUT, environment, with_code_hash

#: Methods whose model is fixed: those that fit F alone refuse another model when the request
#: is read (``params.ransac.model``, :data:`hmcc.method_names.F_ONLY_METHODS`); hmcc is the
#: filter alone.
_ONE_MODEL = F_ONLY_METHODS | {"hmcc"}
MODELS = ("fundamental", "essential", "homography")


def _base() -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=50, outlier_ratio=0.0), 1)
    pair.pop("ground_truth")
    return pair


def _frame(pair: dict[str, Any]) -> tuple[int, int]:
    camera = pair["image1"]["camera"]
    return int(camera["width"]), int(camera["height"])


def _keypoints(xy: np.ndarray, rng: np.random.Generator) -> list[list[float]]:
    """``[x, y, size, angle]`` rows (gc-ransac needs the SIFT size and angle)."""
    size = rng.uniform(2.0, 20.0, len(xy))
    angle = rng.uniform(0.0, 360.0, len(xy))
    return np.c_[xy, size, angle].round(2).tolist()


def _random(n_keypoints: int, n_matches: int) -> Callable[[dict[str, Any]], None]:
    def make(pair: dict[str, Any]) -> None:
        rng = np.random.default_rng(0)
        w, h = _frame(pair)
        for key in ("keypoints1", "keypoints2"):
            pair[key] = _keypoints(rng.random((n_keypoints, 2)) * [w - 1, h - 1], rng)
        pair["matches"] = rng.integers(0, n_keypoints, (n_matches, 2)).tolist()

    return make


def _identical(pair: dict[str, Any]) -> None:
    pair["keypoints1"] = [[1000.5, 700.25, 5.0, 30.0]] * 2000
    pair["keypoints2"] = [[1003.5, 690.25, 5.0, 32.0]] * 2000
    pair["matches"] = [[i, i] for i in range(2000)]


def _collinear(pair: dict[str, Any]) -> None:
    rng = np.random.default_rng(1)
    w, h = _frame(pair)
    t = rng.random(2000)
    pair["keypoints1"] = _keypoints(np.c_[t * (w - 1), t * (h - 1)], rng)
    pair["keypoints2"] = _keypoints(np.c_[t * (w - 1), (1 - t) * (h - 1)], rng)
    pair["matches"] = np.c_[np.arange(2000), rng.permutation(2000)].tolist()


CASES: dict[str, Callable[[dict[str, Any]], None]] = {
    "random 100k": _random(5000, MAX_MATCHES),
    "200k keypoints": _random(MAX_KEYPOINTS, 2000),
    "identical": _identical,
    "collinear": _collinear,
    "minimal": _random(8, 8),
}


def configurations() -> list[tuple[str, str]]:
    return [
        (method, model)
        for method in METHODS
        for model in (("fundamental",) if method in _ONE_MODEL else MODELS)
    ]


def run(timeout_s: float, cases: list[str]) -> list[dict[str, Any]]:
    base = _base()
    pool = ComputePool(1, timeout_s=timeout_s)
    pool.start()
    rows = []
    try:
        for case in cases:
            pair = json.loads(json.dumps(base))
            CASES[case](pair)
            for method, model in configurations():
                body = {**pair, "method": method}
                if method not in _ONE_MODEL:
                    body["params"] = {"ransac": {"model": model}}
                flight = parse_pair(json.dumps(body).encode())  # valid: it parses
                t0 = time.perf_counter()
                (outcome,) = pool.run(flight)
                seconds = time.perf_counter() - t0
                status, data = unpack(outcome.pack())
                doc = json.loads(data)
                row = {
                    "case": case,
                    "method": method,
                    "model": model,
                    "status": status.value,
                    "code": None if status.value == "finished" else doc.get("code"),
                    "inliers": len(doc["inliers"]) if status.value == "finished" else None,
                    "seconds": round(seconds, 3),
                }
                rows.append(row)
                print(
                    f"{case:15} {method:14} {model:11} {row['status']:8} "
                    f"{row['code'] or '':15} {seconds:7.2f} s",
                    flush=True,
                )
    finally:
        pool.close(wait=False)
    return rows


def markdown(doc: dict[str, Any]) -> str:
    rows = doc["rows"]
    crashed = [r for r in rows if r["code"] == "worker_crashed"]
    timed_out = [r for r in rows if r["code"] == "timeout"]
    env = doc["environment"]
    lines = [
        "# Every method at the edges of the limits, each in an isolated child (issue #11)",
        "",
        f"- commit {env['git_commit']}, opencv {env['opencv']}, numpy {env['numpy']}, "
        f"{env['cpu_count']} CPUs; timeout {doc['timeout_s']:g} s per case",
        f"- {len(rows)} runs: {len(crashed)} crashed the child, {len(timed_out)} timed out, "
        f"{sum(r['status'] == 'finished' for r in rows)} finished, "
        f"{sum(r['code'] == 'invalid_input' for r in rows)} refused by the core as "
        "`invalid_input` (too few usable matches, no plane)",
        "- Reproduce: `python -m benchmarks.bench_guards`",
        "",
        "| case | method | model | status | code | inliers | s |",
        "|---|---|---|---|---|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['method']} | {r['model']} | {r['status']} | "
            f"{r['code'] or ''} | {'' if r['inliers'] is None else r['inliers']} | "
            f"{r['seconds']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--timeout", type=float, default=60.0, help="seconds per case (the service's)")
    p.add_argument("--quick", action="store_true", help="the small cases only (smoke)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    cases = ["identical", "collinear", "minimal"] if args.quick else list(CASES)
    env = environment()
    rows = run(args.timeout, cases)
    doc = {"environment": env, "timeout_s": args.timeout, "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "guards_quick" if args.quick else "guards"
    (args.out / f"{stem}.json").write_text(json.dumps(with_code_hash(doc, __file__), indent=1))
    (args.out / f"{stem}.md").write_text(markdown(doc))
    crashed = sum(r["code"] == "worker_crashed" for r in rows)
    print(f"{len(rows)} runs, {crashed} crashed a child")
    return 1 if crashed else 0


if __name__ == "__main__":
    raise SystemExit(main())
