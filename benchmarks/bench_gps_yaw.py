"""GPS-only flights whose cameras' yaws are off the flight track by large, per-image amounts
(``tests/support/gps_flight.py``): ``hmcc match`` against brute force on the same features,
the simulator's truth the judge.

For each seed and yaw error (the largest per-image error, degrees): the simulated database
(36 images, every pair), brute force on every pair (the true matches it finds: the recall's
denominator), then :class:`hmcc_colmap.guided_match.GuidedMatchRun` in this process
(``processes=0``, the attitude from the track), each pair's CPU time taken around its
matching (``time.process_time``; BLAS on one thread). Printed per run: pairs, CPU and
median CPU per pair by mode, pairs with matches, true matches found, and the recall: true
matches found by both / true matches brute force finds. Brute force's results can be kept
between runs (``--brute-cache DIR``: the flights are deterministic). ``--gps-lag M``: every
position M metres behind its camera along the track (a fix recorded late).

With ``--verify`` the run is ``hmcc match --verify`` (the default method and options,
:class:`hmcc_colmap.verify.RunOptions`), each pair's verification CPU taken around
:meth:`hmcc_colmap.verify.PairVerifier.verify`; printed besides: the pairs verified (and
those whose inliers are less than half true: a wrong geometry), the pairs verified with the
method's fallback, the verification's CPU, and the inliers written against the truth:
precision (true inliers / inliers) and recall (true inliers / true matches among the pairs'
matches, those the verification was given), overall and by matching mode. Usage::

    .venv/bin/python -m benchmarks.bench_gps_yaw [--seeds 1 2] [--yaw 10 60 180]
                                                 [--brute-cache DIR] [--verify]
                                                 [--gps-lag M]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import pickle  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from tests.support.gps_flight import gps_flight_db, stored_matches  # noqa: E402

from hmcc.guided import Features, GuidedOptions, match_brute_force  # noqa: E402
from hmcc_colmap import guided_match  # noqa: E402
from hmcc_colmap.database import snapshot_features  # noqa: E402
from hmcc_colmap.guided_match import GuidedMatchRun, MatchOptions  # noqa: E402
from hmcc_colmap.verify import PairVerifier, RunOptions  # noqa: E402


def _set(m: np.ndarray) -> set[tuple[int, int]]:
    return {(int(i), int(j)) for i, j in m}


def run_one(
    seed: int,
    yaw: float,
    folder: Path,
    cache: Path | None = None,
    verify: bool = False,
    gps_lag: float = 0.0,
) -> dict[str, Any]:
    name = f"s{seed}-y{yaw:g}" + (f"-lag{gps_lag:g}" if gps_lag else "")
    flight = gps_flight_db(folder / name, seed, yaw, strips=3, per_strip=12, gps_lag_m=gps_lag)
    kept = None if cache is None else cache / f"brute-{name}.pkl"
    if kept is not None and kept.exists():
        brute, brute_cpu = pickle.loads(kept.read_bytes())
    else:
        feats = {
            i: Features.from_raw(k, d)
            for i, k, d in snapshot_features(flight.database, flight.image_ids)
        }
        options = GuidedOptions()
        brute = {}
        t0 = time.process_time()
        for (a, b), true in flight.truth.items():
            found = match_brute_force(feats[a], feats[b], options).matches
            brute[(a, b)] = _set(found) & _set(true)
        brute_cpu = time.process_time() - t0
        if kept is not None:
            kept.write_bytes(pickle.dumps((brute, brute_cpu)))

    cpu: dict[tuple[int, int], float] = {}
    inner = guided_match._match_pair

    def timed(folder_: Path, task: Any, opts: GuidedOptions) -> Any:
        c0 = time.process_time()
        result = inner(folder_, task, opts)
        pair = (task.image_id1, task.image_id2)  # an anchor may be matched twice
        cpu[pair] = cpu.get(pair, 0.0) + time.process_time() - c0
        return result

    verify_cpu: list[float] = []
    inner_verify = PairVerifier.verify

    def timed_verify(self: PairVerifier, *args: Any) -> Any:
        c0 = time.process_time()
        result = inner_verify(self, *args)
        verify_cpu.append(time.process_time() - c0)
        return result

    guided_match._match_pair = timed  # type: ignore[assignment]
    PairVerifier.verify = timed_verify  # type: ignore[method-assign,assignment]
    try:
        c0 = time.process_time()
        report = GuidedMatchRun(
            flight.database,
            poses=flight.geo,
            options=MatchOptions(
                processes=0, ground_z=0.0, verify=RunOptions() if verify else None
            ),
        ).run()
        run_cpu = time.process_time() - c0
    finally:
        guided_match._match_pair = inner  # type: ignore[assignment]
        PairVerifier.verify = inner_verify  # type: ignore[method-assign]
    stored = stored_matches(flight.database)
    ids = {n: i for n, i in zip(flight.names, flight.image_ids, strict=True)}
    modes: dict[str, list[float]] = {}
    mode_recall: dict[str, list[int]] = {}
    found_true = both = wanted = matched_pairs = brute_pairs = lost_pairs = 0
    for row in report["pairs"]:
        a, b = ids[row["image1"]], ids[row["image2"]]
        key = (min(a, b), max(a, b))
        modes.setdefault(row["mode"], []).append(cpu.get((a, b), 0.0))
        got = _set(stored.get(key, np.zeros((0, 2))))
        true_set = _set(flight.truth[key])
        found_true += len(got & true_set)
        both += len(got & brute[key])
        wanted += len(brute[key])
        counts = mode_recall.setdefault(row["mode"], [0, 0])
        counts[0] += len(got & brute[key])
        counts[1] += len(brute[key])
        matched_pairs += len(got) >= 15
        brute_pairs += len(brute[key]) >= 15
        lost_pairs += len(brute[key]) >= 15 and len(got & brute[key]) < 15
    out = {
        "seed": seed,
        "yaw": yaw,
        "pairs": len(report["pairs"]),
        "modes": {
            m: (
                len(v),
                round(1e3 * sum(v) / len(v), 1),
                round(1e3 * statistics.median(v), 1),
                round(mode_recall[m][0] / max(mode_recall[m][1], 1), 3),
                mode_recall[m][1],
            )
            for m, v in sorted(modes.items())
        },
        "cpu_s": round(run_cpu, 2),
        "brute_cpu_s": round(brute_cpu, 2),
        "matched_pairs": matched_pairs,
        "brute_pairs": brute_pairs,
        "lost_pairs": lost_pairs,
        "true_found": found_true,
        "recall": round(both / max(wanted, 1), 4),
        "yaw_rms_after": report["totals"].get("yaw_error_rms_deg"),
    }
    if verify:
        out["verify"] = _verification(flight, report, stored, ids, verify_cpu)
    return out


def _verification(
    flight: Any,
    report: dict[str, Any],
    stored: dict[tuple[int, int], np.ndarray],
    ids: dict[str, int],
    cpu: list[float],
) -> dict[str, Any]:
    """The inliers ``--verify`` wrote against the truth (module docstring)."""
    inliers = stored_matches(flight.database, verified=True)
    by_mode: dict[str, list[int]] = {}  # mode -> [verified, inliers, true inliers, true given]
    wrong = 0
    for row in report["pairs"]:
        a, b = ids[row["image1"]], ids[row["image2"]]
        key = (min(a, b), max(a, b))
        true_set = _set(flight.truth[key])
        kept = _set(inliers.get(key, np.zeros((0, 2))))
        given = _set(stored.get(key, np.zeros((0, 2)))) & true_set
        counts = by_mode.setdefault(row["mode"], [0, 0, 0, 0])
        counts[0] += bool(kept)
        counts[1] += len(kept)
        counts[2] += len(kept & true_set)
        counts[3] += len(given)
        wrong += bool(kept) and 2 * len(kept & true_set) < len(kept)
    totals = [sum(c[k] for c in by_mode.values()) for k in range(4)]

    def scores(c: list[int]) -> tuple[int, float, float]:
        return c[0], round(c[2] / max(c[1], 1), 4), round(c[2] / max(c[3], 1), 4)

    verification = report["verification"]["totals"]
    return {
        "verified": report["totals"]["verified"],
        "wrong": wrong,
        "fallback_pairs": verification["fallback_pairs"],
        "inliers": totals[1],
        "precision": scores(totals)[1],
        "recall": scores(totals)[2],
        "cpu_s": round(sum(cpu), 3),
        "cpu_median_ms": round(1e3 * statistics.median(cpu), 2) if cpu else None,
        "pairs_timed": len(cpu),
        "modes": {m: scores(c) for m, c in sorted(by_mode.items()) if c[3]},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--yaw", type=float, nargs="+", default=[10.0, 60.0, 180.0])
    parser.add_argument("--brute-cache", type=Path, help="keep brute force's matches here")
    parser.add_argument("--verify", action="store_true", help="hmcc match --verify")
    parser.add_argument(
        "--gps-lag", type=float, default=0.0, help="each position this far behind (m)"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="hmcc-gps-yaw-") as tmp:
        for seed in args.seeds:
            for yaw in args.yaw:
                r = run_one(seed, yaw, Path(tmp), args.brute_cache, args.verify, args.gps_lag)
                print(
                    f"seed {r['seed']} yaw +-{r['yaw']:g}: {r['pairs']} pairs, match CPU "
                    f"{r['cpu_s']} s (brute force {r['brute_cpu_s']} s), pairs with >= 15 "
                    f"matches {r['matched_pairs']} (brute force {r['brute_pairs']}, lost "
                    f"{r['lost_pairs']}), recall {r['recall']}, true matches {r['true_found']}"
                )
                for mode, (count, mean, median, recall, wanted) in r["modes"].items():
                    print(
                        f"    {mode:26s} {count:4d} pairs  CPU mean {mean:6.1f} ms  "
                        f"median {median:6.1f} ms  recall {recall:.3f} of {wanted}"
                    )
                if "verify" in r:
                    v = r["verify"]
                    print(
                        f"  verify: {v['verified']} pairs verified ({v['wrong']} under half "
                        f"true, {v['fallback_pairs']} by the fallback), CPU {v['cpu_s']} s "
                        f"over {v['pairs_timed']} pairs (median {v['cpu_median_ms']} ms), "
                        f"{v['inliers']} inliers, precision "
                        f"{v['precision']}, recall {v['recall']}"
                    )
                    for mode, (count, precision, recall) in v["modes"].items():
                        print(
                            f"    {mode:26s} {count:4d} verified  precision {precision:.4f}  "
                            f"recall {recall:.4f}"
                        )
                print(flush=True)


if __name__ == "__main__":
    main()
